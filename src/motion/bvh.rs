//! BVH export and import: the format's skeleton as the hierarchy, one frame of channels per
//! motion frame; and a reader ([`parse`], [`to_features`]) that turns a BVH written by libflame
//! (in any convention) back into `smpl24_6d` features, so it can serve as an editing reference.
//!
//! - Hierarchy: joints in depth-first order from the root, children in index order, OFFSETs
//!   = the rest offsets in the chosen convention and unit; the root's OFFSET is zero so that
//!   readers that add it to the root's position channels and readers that do not agree. Each
//!   leaf gets an `End Site` half its own bone long, along that bone (readers such as Blender
//!   need a non-zero tail).
//! - Channels: root `Xposition Yposition Zposition Zrotation Xrotation Yrotation`, every other
//!   joint `Zrotation Xrotation Yrotation`; the rotation is `Rz · Rx · Ry` (degrees), i.e. the
//!   listed order from parent side to child side; the root position is the pelvis's world
//!   position in the convention.
//! - `Frame Time` = 1 / fps.
//! - Root bone: when the poses carry one ([`super::RootMotion::Separate`]), the hierarchy starts
//!   with an extra `ROOT root` (OFFSET zero, the same 6 channels as a root: its position the
//!   ground point under the pelvis, its rotation zero) whose one child is the pelvis, now a
//!   `JOINT` with 6 channels too: its position relative to `root` (OFFSET zero as well, so
//!   readers that replace the OFFSET with the position channels, as Blender's importer does,
//!   and readers that add them agree). Blender gives the zero-length `root` bone a tail of its
//!   own (its importer lengthens zero-length bones), and poses the pelvis at root + channels.
//!
//! BVH has no handedness field; most readers (Blender among them) take Y up and right-handed,
//! so `gltf` (or `native` for humanml263) is the convention to write for them; Blender's
//! importer then turns Y-up into its Z-up world, which gives exactly libflame's `blender`
//! convention (see tools/blender_bvh_check.py).

use std::fmt::Write;

use super::convention::{Change, Convention};
use super::format::Format;
use super::poses::Poses;
use super::reference;
use super::rotation::{self, Mat3, Vec3};
use super::skeleton::Skeleton;
use crate::error::{invalid_arg, Result};

/// The BVH text of `poses` in `convention`, `fps` frames per second.
pub fn to_string(poses: &Poses, convention: Convention, fps: f32) -> Result<String> {
    if !(fps.is_finite() && fps > 0.0) {
        return Err(invalid_arg!("BVH frame rate must be positive, got {fps}"));
    }
    if poses.frames() == 0 {
        return Err(invalid_arg!("a BVH needs at least one frame"));
    }
    let bone = !poses.root_bone.is_empty();
    if bone && poses.root_bone.len() != poses.frames() {
        return Err(invalid_arg!(
            "the root bone track has {} entries for {} frames",
            poses.root_bone.len(),
            poses.frames()
        ));
    }
    let skel = poses.format().skeleton();
    let ch = Change::new(poses.format(), convention);
    let offsets: Vec<Vec3> = skel.rest_offsets().iter().map(|o| ch.offset(o)).collect();
    let mut order = Vec::with_capacity(skel.joint_count());
    let mut out = String::from("HIERARCHY\n");
    if bone {
        let _ = writeln!(
            out,
            "ROOT {ROOT_BONE}\n{{\n\tOFFSET 0.000000 0.000000 0.000000\n\t{ROOT_CHANNELS}"
        );
    }
    write_joint(&mut out, skel, &offsets, 0, usize::from(bone), &mut order);
    if bone {
        out.push_str("}\n");
    }

    let joints = skel.joint_count();
    let root = poses.root_translation(convention);
    let local = poses.local_rotations(convention);
    let _ = write!(
        out,
        "MOTION\nFrames: {}\nFrame Time: {:.6}\n",
        poses.frames(),
        1.0 / fps as f64
    );
    for (t, p) in root.iter().enumerate() {
        if let Some(b) = poses.root_bone.get(t) {
            let b = ch.position(b);
            let _ = write!(
                out,
                "{:.6} {:.6} {:.6} 0.000000 0.000000 0.000000 ",
                b[0], b[1], b[2]
            );
        }
        let _ = write!(out, "{:.6} {:.6} {:.6}", p[0], p[1], p[2]);
        for &j in &order {
            let e = rotation::to_euler_zxy_degrees(&local[t * joints + j]);
            let _ = write!(out, " {:.6} {:.6} {:.6}", e[0], e[1], e[2]);
        }
        out.push('\n');
    }
    Ok(out)
}

/// The name of the extra root joint written for a root bone.
pub const ROOT_BONE: &str = "root";

const ROOT_CHANNELS: &str =
    "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation";

/// Writes joint `j` and its subtree (at `depth`; the skeleton's root is the file's `ROOT` at
/// depth 0, a `JOINT` under the root bone at depth 1), recording the depth-first order of the
/// channels.
fn write_joint(
    out: &mut String,
    skel: &Skeleton,
    offsets: &[Vec3],
    j: usize,
    depth: usize,
    order: &mut Vec<usize>,
) {
    let pad = "\t".repeat(depth);
    let name = skel.joint_names()[j];
    let o = if j == 0 { [0.0; 3] } else { offsets[j] };
    order.push(j);
    if j == 0 {
        let keyword = if depth == 0 { "ROOT" } else { "JOINT" };
        let _ = writeln!(out, "{pad}{keyword} {name}\n{pad}{{");
        let _ = writeln!(out, "{pad}\tOFFSET {:.6} {:.6} {:.6}", o[0], o[1], o[2]);
        let _ = writeln!(out, "{pad}\t{ROOT_CHANNELS}");
    } else {
        let _ = writeln!(out, "{pad}JOINT {name}\n{pad}{{");
        let _ = writeln!(out, "{pad}\tOFFSET {:.6} {:.6} {:.6}", o[0], o[1], o[2]);
        let _ = writeln!(out, "{pad}\tCHANNELS 3 Zrotation Xrotation Yrotation");
    }
    let mut leaf = true;
    for c in skel.children(j) {
        leaf = false;
        write_joint(out, skel, offsets, c, depth + 1, order);
    }
    if leaf {
        let e = o.map(|x| 0.5 * x);
        let _ = writeln!(
            out,
            "{pad}\tEnd Site\n{pad}\t{{\n{pad}\t\tOFFSET {:.6} {:.6} {:.6}\n{pad}\t}}",
            e[0], e[1], e[2]
        );
    }
    let _ = writeln!(out, "{pad}}}");
}

// ---------------------------------------------------------------------------------------------
// Reading

/// One BVH channel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Channel {
    /// Translation along X, in the file's length unit.
    Xposition,
    /// Translation along Y, in the file's length unit.
    Yposition,
    /// Translation along Z, in the file's length unit.
    Zposition,
    /// Rotation about X, degrees.
    Xrotation,
    /// Rotation about Y, degrees.
    Yrotation,
    /// Rotation about Z, degrees.
    Zrotation,
}

impl Channel {
    const ALL: [Channel; 6] = [
        Channel::Xposition,
        Channel::Yposition,
        Channel::Zposition,
        Channel::Xrotation,
        Channel::Yrotation,
        Channel::Zrotation,
    ];

    /// The name as written in a `CHANNELS` line.
    pub fn name(self) -> &'static str {
        match self {
            Channel::Xposition => "Xposition",
            Channel::Yposition => "Yposition",
            Channel::Zposition => "Zposition",
            Channel::Xrotation => "Xrotation",
            Channel::Yrotation => "Yrotation",
            Channel::Zrotation => "Zrotation",
        }
    }

    /// The channel named `name` (case-insensitive), if any.
    pub fn from_name(name: &str) -> Option<Channel> {
        Channel::ALL
            .into_iter()
            .find(|c| c.name().eq_ignore_ascii_case(name))
    }

    /// The axis (0 = X, 1 = Y, 2 = Z).
    pub fn axis(self) -> usize {
        match self {
            Channel::Xposition | Channel::Xrotation => 0,
            Channel::Yposition | Channel::Yrotation => 1,
            Channel::Zposition | Channel::Zrotation => 2,
        }
    }

    /// Whether this is a rotation channel (degrees) rather than a position one.
    pub fn is_rotation(self) -> bool {
        matches!(
            self,
            Channel::Xrotation | Channel::Yrotation | Channel::Zrotation
        )
    }
}

/// One joint of a parsed hierarchy.
#[derive(Clone, Debug)]
pub struct BvhJoint {
    name: String,
    parent: Option<usize>,
    offset: Option<Vec3>,
    channels: Vec<Channel>,
    /// Index of the joint's first channel within a frame.
    first_channel: usize,
    /// 1-based line of the `ROOT`/`JOINT` keyword, for error messages.
    line: usize,
}

impl BvhJoint {
    /// The name after `ROOT` or `JOINT` (unique in the hierarchy).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The parent's index in [`BvhMotion::joints`], `None` for the root.
    pub fn parent(&self) -> Option<usize> {
        self.parent
    }

    /// `OFFSET`: the joint's rest position relative to its parent, in the file's axes and unit
    /// (every joint has one; the parser refuses a joint without).
    pub fn offset(&self) -> Vec3 {
        self.offset.unwrap_or_default()
    }

    /// The joint's `CHANNELS`, in file order (0 to 6): its rotation is the product of its
    /// rotation channels in this order (`Zrotation Xrotation Yrotation` is `Rz · Rx · Ry`).
    pub fn channels(&self) -> &[Channel] {
        &self.channels
    }
}

/// A parsed BVH file: the hierarchy in file order (parents before children) and the motion,
/// `frames × channel_count` values (degrees and the file's unit), frame-major.
#[derive(Clone, Debug)]
pub struct BvhMotion {
    joints: Vec<BvhJoint>,
    channel_count: usize,
    frame_time: f64,
    data: Vec<f64>,
}

impl BvhMotion {
    /// The hierarchy's joints in file order, parents before children (index 0 is the `ROOT`);
    /// `End Site`s are not joints.
    pub fn joints(&self) -> &[BvhJoint] {
        &self.joints
    }

    /// Channels per frame, over all joints.
    pub fn channel_count(&self) -> usize {
        self.channel_count
    }

    /// Number of frames (equal to the file's `Frames:`).
    pub fn frames(&self) -> usize {
        self.data.len().checked_div(self.channel_count).unwrap_or(0)
    }

    /// Seconds per frame (`Frame Time`).
    pub fn frame_time(&self) -> f64 {
        self.frame_time
    }

    /// `1 / Frame Time`, snapped to the integer rate when the 6 printed decimals explain the
    /// difference (libflame writes `1/fps` with `{:.6}`: 30 fps reads back as 0.033333).
    pub fn fps(&self) -> f32 {
        let rate = 1.0 / self.frame_time;
        let whole = rate.round();
        if whole >= 1.0 && (1.0 / whole - self.frame_time).abs() <= 5.0001e-7 {
            whole as f32
        } else {
            rate as f32
        }
    }

    /// The channel values of frame `t`, in file order.
    pub fn frame(&self, t: usize) -> Option<&[f64]> {
        let n = self.channel_count;
        (t < self.frames()).then(|| &self.data[t * n..(t + 1) * n])
    }
}

/// A parse error at a 1-based line.
fn at(line: usize, msg: impl std::fmt::Display) -> crate::error::Error {
    invalid_arg!("BVH line {line}: {msg}")
}

/// Parses BVH text: `HIERARCHY` with one `ROOT`, nested `JOINT`s and `End Site`s, `OFFSET` and
/// `CHANNELS`; then `MOTION`, `Frames:`, `Frame Time:` and one line of numbers per frame.
/// Errors carry the line number. Storage grows with the data actually present, never with the
/// declared `Frames:` count, which must match the number of frame lines.
pub fn parse(text: &str) -> Result<BvhMotion> {
    let lines: Vec<&str> = text.lines().collect();
    let motion_at = lines
        .iter()
        .position(|l| l.split_whitespace().next() == Some("MOTION"))
        .ok_or_else(|| invalid_arg!("BVH has no MOTION section"))?;
    let tokens: Vec<(usize, &str)> = lines[..motion_at]
        .iter()
        .enumerate()
        .flat_map(|(i, l)| l.split_whitespace().map(move |t| (i + 1, t)))
        .collect();
    let (joints, channel_count) = parse_hierarchy(&tokens, motion_at + 1)?;
    let (frame_time, data) = parse_motion(&lines, motion_at, channel_count)?;
    Ok(BvhMotion {
        joints,
        channel_count,
        frame_time,
        data,
    })
}

/// The hierarchy's joints and the total channel count. An explicit stack (no recursion) keeps
/// deeply nested input from overflowing the call stack.
fn parse_hierarchy(tokens: &[(usize, &str)], motion_line: usize) -> Result<(Vec<BvhJoint>, usize)> {
    let mut it = Tokens(tokens.iter());
    match it.0.next().copied() {
        Some((_, "HIERARCHY")) => {}
        Some((line, t)) => return Err(at(line, format!("expected HIERARCHY, found `{t}`"))),
        None => return Err(at(motion_line, "MOTION before any HIERARCHY")),
    }
    let mut joints: Vec<BvhJoint> = Vec::new();
    // Open blocks: Some(joint) or None for an End Site.
    let mut stack: Vec<Option<usize>> = Vec::new();
    let mut channel_count = 0usize;
    let mut names = std::collections::HashSet::new();
    while let Some(&(line, tok)) = it.0.next() {
        match tok {
            "ROOT" | "JOINT" => {
                let parent = match (tok, stack.last()) {
                    ("ROOT", None) if joints.is_empty() => None,
                    ("ROOT", _) => return Err(at(line, "only one ROOT is supported")),
                    ("JOINT", Some(Some(p))) => Some(*p),
                    ("JOINT", Some(None)) => return Err(at(line, "JOINT inside an End Site")),
                    _ => return Err(at(line, "JOINT outside any ROOT")),
                };
                let (name_line, name) = it.need(line, "a joint name")?;
                if name_line != line || name == "{" || name == "}" {
                    return Err(at(line, format!("{tok} has no name")));
                }
                expect(it.need(line, "`{`")?, "{")?;
                if !names.insert(name) {
                    return Err(at(line, format!("joint `{name}` appears twice")));
                }
                stack.push(Some(joints.len()));
                joints.push(BvhJoint {
                    name: name.to_string(),
                    parent,
                    offset: None,
                    channels: Vec::new(),
                    first_channel: channel_count,
                    line,
                });
            }
            "End" => {
                expect(it.need(line, "`Site`")?, "Site")?;
                if !matches!(stack.last(), Some(Some(_))) {
                    return Err(at(line, "End Site outside a joint"));
                }
                expect(it.need(line, "`{`")?, "{")?;
                stack.push(None);
            }
            "OFFSET" => {
                let mut v = [0.0; 3];
                for x in &mut v {
                    *x = number(it.need(line, "an OFFSET value")?)?;
                }
                match stack.last() {
                    Some(Some(j)) if joints[*j].offset.is_none() => joints[*j].offset = Some(v),
                    Some(Some(j)) => {
                        return Err(at(line, format!("second OFFSET for `{}`", joints[*j].name)))
                    }
                    Some(None) => {} // End Site tails carry no motion.
                    None => return Err(at(line, "OFFSET outside a joint")),
                }
            }
            "CHANNELS" => {
                let Some(Some(j)) = stack.last().copied() else {
                    return Err(at(line, "CHANNELS outside a joint"));
                };
                let (_, n) = it.need(line, "a channel count")?;
                let n: usize = n
                    .parse()
                    .ok()
                    .filter(|&n| n <= 6)
                    .ok_or_else(|| at(line, format!("channel count `{n}` is not 0 to 6")))?;
                if !joints[j].channels.is_empty() {
                    return Err(at(
                        line,
                        format!("second CHANNELS for `{}`", joints[j].name),
                    ));
                }
                for _ in 0..n {
                    let (l, name) = it.need(line, "a channel name")?;
                    let c = Channel::from_name(name).ok_or_else(|| {
                        at(
                            l,
                            format!("unknown channel `{name}` (CHANNELS of line {line})"),
                        )
                    })?;
                    if joints[j].channels.contains(&c) {
                        return Err(at(l, format!("channel {} listed twice", c.name())));
                    }
                    joints[j].channels.push(c);
                }
                channel_count += n;
            }
            "}" => {
                if stack.pop().is_none() {
                    return Err(at(line, "`}` without an open block"));
                }
            }
            other => return Err(at(line, format!("unexpected `{other}` in the hierarchy"))),
        }
    }
    if let Some(open) = stack.iter().rev().find_map(|x| *x) {
        return Err(at(
            motion_line,
            format!(
                "MOTION before joint `{}` (line {}) is closed",
                joints[open].name, joints[open].line
            ),
        ));
    }
    if let Some(j) = joints.iter().find(|j| j.offset.is_none()) {
        return Err(at(j.line, format!("joint `{}` has no OFFSET", j.name)));
    }
    if joints.is_empty() {
        return Err(at(motion_line, "the hierarchy has no ROOT"));
    }
    Ok((joints, channel_count))
}

/// `Frames:`, `Frame Time:` and the frame lines after the `MOTION` line at index `motion_at`.
fn parse_motion(lines: &[&str], motion_at: usize, channels: usize) -> Result<(f64, Vec<f64>)> {
    let mut rest = lines
        .iter()
        .enumerate()
        .skip(motion_at + 1)
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty());
    let mut header = |key: &str| -> Result<(usize, &str)> {
        let (line, l) = rest
            .next()
            .ok_or_else(|| invalid_arg!("BVH ends before `{key}:`"))?;
        l.strip_prefix(key)
            .map(|v| v.trim_start())
            .and_then(|v| v.strip_prefix(':'))
            .map(|v| (line, v.trim()))
            .ok_or_else(|| at(line, format!("expected `{key}:`, found `{l}`")))
    };
    let (frames_line, n) = header("Frames")?;
    let declared: usize = n.parse().map_err(|_| {
        at(
            frames_line,
            format!("frame count `{n}` is not a whole number"),
        )
    })?;
    let (time_line, t) = header("Frame Time")?;
    let frame_time = number((time_line, t))?;
    if frame_time <= 0.0 {
        return Err(at(
            time_line,
            format!("Frame Time must be positive, got {t}"),
        ));
    }
    let mut data = Vec::new();
    let mut seen = 0usize;
    for (line, l) in rest {
        if seen == declared {
            return Err(at(
                line,
                format!("more frame lines than the {declared} declared by `Frames:`"),
            ));
        }
        let before = data.len();
        for tok in l.split_whitespace() {
            data.push(number((line, tok))?);
        }
        let got = data.len() - before;
        if got != channels {
            return Err(at(
                line,
                format!(
                    "frame {seen} has {got} values; the hierarchy declares {channels} channels"
                ),
            ));
        }
        seen += 1;
    }
    if seen != declared {
        return Err(at(
            lines.len(),
            format!("file ends after {seen} of the {declared} frames declared at line {frames_line} (truncated?)"),
        ));
    }
    Ok((frame_time, data))
}

/// The hierarchy's tokens with their lines.
struct Tokens<'a>(std::slice::Iter<'a, (usize, &'a str)>);

impl<'a> Tokens<'a> {
    /// The next token, or an error saying what was missing after `line`.
    fn need(&mut self, line: usize, what: &str) -> Result<(usize, &'a str)> {
        self.0.next().copied().ok_or_else(|| {
            at(
                line,
                format!("MOTION or the end comes where {what} was expected"),
            )
        })
    }
}

fn expect((line, tok): (usize, &str), want: &str) -> Result<()> {
    if tok == want {
        Ok(())
    } else {
        Err(at(line, format!("expected `{want}`, found `{tok}`")))
    }
}

/// A finite number.
fn number((line, tok): (usize, &str)) -> Result<f64> {
    tok.parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| at(line, format!("`{tok}` is not a finite number")))
}

/// How far (metres) a file's OFFSETs may be from a convention's rest offsets and still be taken
/// as written in it: far above the 6 printed decimals, far below any difference between
/// conventions (they differ by axis swaps and signs of offsets ≥ 5 cm).
const OFFSET_TOLERANCE_M: f64 = 1e-4;

/// The `smpl24_6d` features `[frames, 147]` of a BVH written by libflame, with the frame count,
/// the convention the file was written in and its frame rate.
///
/// Joints are matched to SMPL-24 by name (any order; the parents must match SMPL's). The
/// convention is the one whose rest offsets (unit included) the file's OFFSETs reproduce;
/// `native` and `gltf` share their offsets for SMPL (both put the body Y-up), and are told apart
/// by which of them stands the character upright in the format's own world. Rotation channels
/// may come in any order (the listed order is the order of the product, parent side first);
/// only the root may carry position channels, all three; a non-zero root OFFSET is added to the
/// root position. A file whose `ROOT` is a joint named `root` with the pelvis as its child (what
/// [`to_string`] writes for a clip with a root bone) is read too: the pelvis's world position is
/// the root's plus the root's rotation times the pelvis's own (OFFSET plus channels), its world
/// rotation the product of the two. `humanml263` references must be given as features.
pub fn to_features(bvh: &BvhMotion, format: Format) -> Result<(Vec<f32>, usize, Convention, f32)> {
    let poses = FilePoses::read(bvh, format)?;
    let candidates = poses.conventions(format)?;
    let convention = if candidates.len() == 1 {
        candidates[0]
    } else {
        let score = |c: &Convention| poses.uprightness(format, *c);
        candidates
            .into_iter()
            .max_by(|a, b| score(a).total_cmp(&score(b)))
            .unwrap_or(Convention::Native)
    };
    let features = reference::features_from_poses(&poses.root, &poses.local, convention);
    Ok((features, bvh.frames(), convention, bvh.fps()))
}

/// [`to_features`] for a file known to be in `convention` (its OFFSETs must still match it):
/// for when a motion lies down for its whole length and uprightness cannot decide between
/// `native` and `gltf`.
pub fn to_features_in(bvh: &BvhMotion, format: Format, convention: Convention) -> Result<Vec<f32>> {
    let poses = FilePoses::read(bvh, format)?;
    let dev = poses.offset_deviation(format, convention);
    if dev > OFFSET_TOLERANCE_M {
        return Err(invalid_arg!(
            "BVH offsets are not SMPL-24's in the {convention} convention (off by up to {dev:.4} m)"
        ));
    }
    Ok(reference::features_from_poses(
        &poses.root,
        &poses.local,
        convention,
    ))
}

/// A BVH's SMPL-24 poses in the file's own coordinates.
struct FilePoses {
    /// `[24]` OFFSETs in SMPL joint order.
    offsets: Vec<Vec3>,
    /// `[frames]` root positions.
    root: Vec<Vec3>,
    /// `[frames × 24]` local rotations, SMPL joint order.
    local: Vec<Mat3>,
}

impl FilePoses {
    fn read(bvh: &BvhMotion, format: Format) -> Result<FilePoses> {
        if format != Format::Smpl24Rot6d {
            return Err(invalid_arg!(
                "BVH references need a smpl24_6d model; for {format} give .npy features"
            ));
        }
        if bvh.frames() == 0 {
            return Err(invalid_arg!("the BVH has no frames"));
        }
        let skel = format.skeleton();
        let (order, bone) = match_joints(bvh, skel)?;
        let mut root = Vec::with_capacity(bvh.frames());
        let mut local = Vec::with_capacity(bvh.frames() * order.len());
        for row in bvh.data.chunks_exact(bvh.channel_count.max(1)) {
            let mut p = [0.0; 3];
            for (j, &b) in order.iter().enumerate() {
                let (r, q) = joint_transform(&bvh.joints[b], row);
                if j == 0 {
                    p = q;
                }
                local.push(r);
            }
            if let Some(b) = bone {
                // The pelvis hangs from the root bone: world = root ∘ pelvis.
                let (rb, pb) = joint_transform(&bvh.joints[b], row);
                let pelvis = local.len() - order.len();
                p = rotation::add(&pb, &rotation::apply(&rb, &p));
                local[pelvis] = rotation::mul(&rb, &local[pelvis]);
            }
            root.push(p);
        }
        Ok(FilePoses {
            offsets: order.iter().map(|&b| bvh.joints[b].offset()).collect(),
            root,
            local,
        })
    }

    /// The largest difference (metres) between the file's non-root OFFSETs and the rest offsets
    /// in `convention`.
    fn offset_deviation(&self, format: Format, convention: Convention) -> f64 {
        let ch = Change::new(format, convention);
        let scale = convention.frame(format).unit.scale();
        format.skeleton().rest_offsets()[1..]
            .iter()
            .zip(&self.offsets[1..])
            .flat_map(|(rest, file)| {
                let want = ch.offset(rest);
                (0..3).map(move |k| (file[k] - want[k]).abs() / scale)
            })
            .fold(0.0, f64::max)
    }

    /// Every convention whose rest offsets the file reproduces, or an error naming the closest.
    fn conventions(&self, format: Format) -> Result<Vec<Convention>> {
        let devs: Vec<(Convention, f64)> = Convention::ALL
            .iter()
            .map(|&c| (c, self.offset_deviation(format, c)))
            .collect();
        let matching: Vec<Convention> = devs
            .iter()
            .filter(|(_, d)| *d <= OFFSET_TOLERANCE_M)
            .map(|(c, _)| *c)
            .collect();
        if !matching.is_empty() {
            return Ok(matching);
        }
        let mut sorted = devs;
        sorted.sort_by(|a, b| a.1.total_cmp(&b.1));
        let closest: Vec<String> = sorted
            .iter()
            .take(3)
            .map(|(c, d)| format!("{c} (off by {d:.4} m)"))
            .collect();
        Err(invalid_arg!(
            "BVH offsets match SMPL-24's rest skeleton in no convention (tolerance {OFFSET_TOLERANCE_M} m); closest: {}",
            closest.join(", ")
        ))
    }

    /// How upright the character stands if the file is in `convention`: the mean over frames of
    /// the native world's up · (root rotation · the body's up).
    fn uprightness(&self, format: Format, convention: Convention) -> f64 {
        let ch = Change::new(format, convention);
        let up = Convention::Native.frame(format).up.vector();
        let joints = format.skeleton().joint_count();
        let sum: f64 = self
            .local
            .chunks_exact(joints)
            .map(|frame| {
                let r = ch.inverse_global(&frame[0]);
                rotation::dot(&up, &rotation::apply(&r, &[0.0, 1.0, 0.0]))
            })
            .sum();
        sum / self.root.len().max(1) as f64
    }
}

/// A joint's rotation (its rotation channels' product in the listed order) and position (its
/// OFFSET plus its position channels) in one frame's `row`.
fn joint_transform(joint: &BvhJoint, row: &[f64]) -> (Mat3, Vec3) {
    let mut r = rotation::IDENTITY;
    let mut p = joint.offset();
    for (k, c) in joint.channels.iter().enumerate() {
        let v = row[joint.first_channel + k];
        if c.is_rotation() {
            let mut axis = [0.0; 3];
            axis[c.axis()] = 1.0;
            r = rotation::mul(&r, &rotation::axis_angle(&axis, v.to_radians()));
        } else {
            p[c.axis()] += v;
        }
    }
    (r, p)
}

/// For each skeleton joint, its index in the BVH, and the index of a root bone above the
/// skeleton's root if there is one: names matched case-insensitively, the hierarchy and
/// channels checked against what the skeleton and [`FilePoses::read`] need.
fn match_joints(bvh: &BvhMotion, skel: &Skeleton) -> Result<(Vec<usize>, Option<usize>)> {
    let names = skel.joint_names();
    let mut order: Vec<Option<usize>> = vec![None; names.len()];
    let mut bone = None;
    for (b, joint) in bvh.joints.iter().enumerate() {
        if joint.parent.is_none() && joint.name.eq_ignore_ascii_case(ROOT_BONE) {
            check_channels(joint, true)?;
            bone = Some(b);
            continue;
        }
        let j = names
            .iter()
            .position(|n| n.eq_ignore_ascii_case(&joint.name))
            .ok_or_else(|| {
                at(
                    joint.line,
                    format!(
                        "joint `{}` is not an SMPL-24 joint (expected {}, …)",
                        joint.name,
                        names[..4].join(", ")
                    ),
                )
            })?;
        if order[j].replace(b).is_some() {
            return Err(at(
                joint.line,
                format!("joint `{}` appears twice", joint.name),
            ));
        }
    }
    let missing: Vec<&str> = (0..names.len())
        .filter(|&j| order[j].is_none())
        .map(|j| names[j])
        .collect();
    if !missing.is_empty() {
        return Err(invalid_arg!(
            "BVH lacks SMPL-24 joints: {}",
            missing.join(", ")
        ));
    }
    let order: Vec<usize> = order.into_iter().flatten().collect();
    for (j, &b) in order.iter().enumerate() {
        let joint = &bvh.joints[b];
        let want = skel.parent(j).map(|p| order[p]).or(bone);
        if joint.parent != want {
            let parent =
                |p: Option<usize>| p.map_or("none (root)", |p| bvh.joints[p].name.as_str());
            return Err(at(
                joint.line,
                format!(
                    "joint `{}` hangs from {}; SMPL-24 hangs it from {}",
                    joint.name,
                    parent(joint.parent),
                    match (skel.parent(j), bone) {
                        (Some(p), _) => names[p],
                        (None, Some(_)) => ROOT_BONE,
                        (None, None) => "none (root)",
                    }
                ),
            ));
        }
        check_channels(joint, j == 0)?;
    }
    Ok((order, bone))
}

/// Three rotation channels, one per axis, plus (root only) three position channels.
fn check_channels(joint: &BvhJoint, is_root: bool) -> Result<()> {
    let rotations = joint.channels.iter().filter(|c| c.is_rotation()).count();
    let positions = joint.channels.len() - rotations;
    let want_positions = if is_root { 3 } else { 0 };
    if rotations != 3 || positions != want_positions {
        let listed: Vec<&str> = joint.channels.iter().map(|c| c.name()).collect();
        return Err(at(
            joint.line,
            format!(
                "joint `{}` has channels [{}]; libflame reads {} X/Y/Z rotations in any order",
                joint.name,
                listed.join(" "),
                if is_root {
                    "3 positions and 3"
                } else {
                    "exactly 3"
                }
            ),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::{resample, root_motion, Format, ReadOptions, RootMotion};

    /// A drifting, turning synthetic motion (every feature a sinusoid of time).
    fn motion(format: Format, frames: usize) -> Poses {
        crate::motion::testutil::sinusoid_motion(format, frames)
    }

    /// The same clip with its root motion kept and moved to a root bone.
    fn keep_and_separate(format: Format, frames: usize) -> (Poses, Poses) {
        let keep = motion(format, frames);
        let mut sep = keep.clone();
        root_motion::apply(&mut sep, RootMotion::Separate, false);
        (keep, sep)
    }

    #[test]
    fn a_root_bone_is_an_extra_root_above_the_pelvis() {
        let (keep, sep) = keep_and_separate(Format::Smpl24Rot6d, 6);
        let text = to_string(&sep, Convention::Gltf, 30.0).unwrap();
        let head: Vec<&str> = text.lines().take(8).collect();
        assert_eq!(
            head,
            [
                "HIERARCHY",
                "ROOT root",
                "{",
                "\tOFFSET 0.000000 0.000000 0.000000",
                "\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation",
                "\tJOINT Pelvis",
                "\t{",
                "\t\tOFFSET 0.000000 0.000000 0.000000",
            ]
        );
        let bvh = parse(&text).unwrap();
        assert_eq!(bvh.joints().len(), 25);
        assert_eq!(bvh.joints()[1].parent(), Some(0));
        // root 6 + pelvis 6 + 23 joints × 3.
        assert_eq!(bvh.channel_count(), 81);
        assert_eq!(bvh.fps(), 30.0);
        let ch = Change::new(Format::Smpl24Rot6d, Convention::Gltf);
        for t in 0..6 {
            let row = bvh.frame(t).unwrap();
            // The root bone: the pelvis's ground point, glTF's Y (up) 0, no rotation.
            let b = ch.position(&sep.root_bone[t]);
            let k = ch.position(&keep.root[t]);
            assert_eq!(row[1], 0.0);
            assert_eq!(&row[3..6], &[0.0; 3]);
            for i in [0, 2] {
                assert!((row[i] - b[i]).abs() <= 5e-7 && (row[i] - k[i]).abs() <= 5e-7);
                assert_eq!(row[6 + i], 0.0, "the pelvis has no horizontal offset left");
            }
            assert!((row[7] - k[1]).abs() <= 5e-7, "the pelvis keeps its height");
        }
    }

    #[test]
    fn a_root_bone_file_reads_back_as_the_original_motion() {
        let (keep, sep) = keep_and_separate(Format::Smpl24Rot6d, 8);
        for (poses, bone) in [(&sep, true), (&keep, false)] {
            let text = to_string(poses, Convention::Gltf, 20.0).unwrap();
            assert_eq!(text.contains("ROOT root"), bone);
            let bvh = parse(&text).unwrap();
            let x = to_features_in(&bvh, Format::Smpl24Rot6d, Convention::Gltf).unwrap();
            let back = Poses::decode(Format::Smpl24Rot6d, &x, 8, &ReadOptions::default()).unwrap();
            let worst = back
                .positions
                .iter()
                .zip(&keep.positions)
                .flat_map(|(a, b)| (0..3).map(move |i| (a[i] - b[i]).abs()))
                .fold(0.0, f64::max);
            // 6 printed decimals of metres and degrees.
            assert!(worst < 2e-5, "bone {bone}: {worst} m");
        }
        // A root bone with a rotation (libflame writes none) turns the body about it: 90° about
        // X on every frame, `Zrotation Xrotation Yrotation` = 0 90 0, which lays the pelvis
        // (straight above the bone) down along +Z.
        let text = to_string(&sep, Convention::Gltf, 20.0).unwrap();
        let (head, motion) = text.split_at(text.find("MOTION").unwrap());
        let mut turned = head.to_string();
        for (i, line) in motion.lines().enumerate() {
            let mut w: Vec<&str> = line.split_whitespace().collect();
            if i >= 3 {
                w[3..6].copy_from_slice(&["0", "90", "0"]);
            }
            turned.push_str(&w.join(" "));
            turned.push('\n');
        }
        let x = to_features_in(
            &parse(&turned).unwrap(),
            Format::Smpl24Rot6d,
            Convention::Gltf,
        )
        .unwrap();
        let back = Poses::decode(Format::Smpl24Rot6d, &x, 8, &ReadOptions::default()).unwrap();
        let (got, kept) = (
            back.positions(Convention::Gltf),
            keep.positions(Convention::Gltf),
        );
        let ch = Change::new(Format::Smpl24Rot6d, Convention::Gltf);
        let rx = rotation::axis_angle(&[1.0, 0.0, 0.0], std::f64::consts::FRAC_PI_2);
        let mut worst = 0.0f64;
        for t in 0..8 {
            let b = ch.position(&sep.root_bone[t]);
            for j in 0..24 {
                let p = kept[t * 24 + j];
                let rel = rotation::apply(&rx, &[p[0] - b[0], p[1] - b[1], p[2] - b[2]]);
                let want = rotation::add(&b, &rel);
                for i in 0..3 {
                    worst = worst.max((got[t * 24 + j][i] - want[i]).abs());
                }
            }
        }
        assert!(worst < 2e-5, "turned root bone: {worst} m");
        // A `root` anywhere but at the top is not SMPL's.
        let text =
            to_string(&sep, Convention::Gltf, 20.0)
                .unwrap()
                .replacen("ROOT root", "ROOT base", 1);
        let e = to_features_in(
            &parse(&text).unwrap(),
            Format::Smpl24Rot6d,
            Convention::Gltf,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("joint `base` is not an SMPL-24 joint"), "{e}");
        let mut bad = sep.clone();
        bad.root_bone.pop();
        let e = to_string(&bad, Convention::Gltf, 20.0)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("root bone track has 7 entries for 8 frames"),
            "{e}"
        );
    }

    /// For tools/bvh_roundtrip.sh: with FLAME_BVH_OUT=DIR, writes `root_separate.bvh` (a
    /// smpl24_6d clip, 40 frames at 20 fps resampled to 30 fps = 59 frames, its root motion on a
    /// root bone, gltf convention) and `root_separate_blender.npy`, the world joint positions
    /// Blender must give ([frames, 24, 3], blender convention: the clip with its root motion
    /// kept, resampled alike).
    #[test]
    #[ignore]
    fn write_blender_check_files() {
        let dir = std::env::var("FLAME_BVH_OUT").expect("set FLAME_BVH_OUT to a directory");
        let dir = std::path::Path::new(&dir);
        let (keep, sep) = keep_and_separate(Format::Smpl24Rot6d, 40);
        let keep = resample::resample(&keep, 20.0, 30.0).unwrap();
        let sep = resample::resample(&sep, 20.0, 30.0).unwrap();
        assert_eq!(sep.frames(), 59);
        let text = to_string(&sep, Convention::Gltf, 30.0).unwrap();
        std::fs::write(dir.join("root_separate.bvh"), text).unwrap();
        let p = keep
            .layout(crate::motion::Layout::GlobalPositions, Convention::Blender)
            .unwrap();
        crate::npy::write_f32(
            &dir.join("root_separate_blender.npy"),
            &[keep.frames(), keep.joint_count(), 3],
            &p,
        )
        .unwrap();
    }
}
