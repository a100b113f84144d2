//! glTF 2.0 export: a motion as a skinned character with one animation, in the binary container
//! (`.glb`, [`to_glb`]) or as JSON with the buffer embedded as a base64 data URI (`.gltf`,
//! [`to_gltf`]). What engines import (Unity through glTFast or UnityGLTF, Unreal 5's glTF
//! importer, Godot, Blender, three.js).
//!
//! # What the file holds
//!
//! - **Skeleton.** One node per joint of the format's skeleton (SMPL-24 or HumanML3D-22), named
//!   as the skeleton names them, under one root node named after the skeleton (`smpl24`,
//!   `humanml22`; no transform). A joint's rest translation is its rest offset, its rest
//!   rotation the identity: the rest pose is the skeleton's T-pose (HumanML3D: arms down), the
//!   pelvis lifted so the lowest joint touches the ground (y = 0).
//! - **Skin.** `joints` = the joint nodes in skeleton order (so animation channel `j` and skin
//!   joint `j` are libflame's joint `j`), `skeleton` = the root node, inverse bind matrices of
//!   that rest pose.
//! - **Mesh.** A figure made of one box per bone (parent joint → joint, rigidly weighted to the
//!   parent) and one per leaf joint (half its bone long, weighted to the joint), with flat
//!   normals, in three primitives coloured as the preview draws them: left limbs blue, right
//!   orange, pelvis–spine–head grey. A few hundred vertices; the mesh node is a root node without
//!   a transform, as skinned meshes must be.
//! - **Animation.** One, named after the prompt (letters, digits, `-` and `_` kept, every other
//!   run of characters one `_`, at most 64 characters; `motion` when there is none), with
//!   LINEAR samplers at `fps`, times `t / fps` from 0: the root joint's translation (the pelvis's
//!   world position) and every joint's rotation, parent-relative, as unit quaternions
//!   `x, y, z, w`, sign-continuous along each track when the poses were decoded so
//!   ([`super::ReadOptions::continuous`], the default). A degenerate rotation (a 6D output
//!   whose two vectors are parallel or zero, which clamped untrained models give) decodes to
//!   a non-unit quaternion; the file holds it normalised.
//! - **Joint translations** (`humanml263` only). HumanML3D's joint positions come from its own
//!   position features, and its rotations (an IK without twist) only approximate them on the
//!   rest skeleton (`humanml263`'s module doc). So that the file shows the motion the model
//!   made, every other joint's translation is animated as well: the parent-relative offset
//!   that puts the joint at its decoded position. `smpl24_6d` positions are the rotations'
//!   forward kinematics, and its joints keep their rest offsets.
//! - **Conventions.** glTF's own: right-handed, +Y up, +Z forward, +X left, metres — libflame's
//!   `gltf` convention, so the translations and quaternions are exactly what
//!   [`Poses::layout`] gives for [`Layout::RootTranslation`] and [`Layout::LocalQuatXyzw`] in
//!   [`Convention::Gltf`], and the joint world positions the file animates are those of
//!   [`Layout::GlobalPositions`] (rounding of `f32` aside). Smoothing is the decoder's
//!   ([`super::ReadOptions::smooth_sigma`]).
//! - **Root bone.** When the poses carry one ([`super::RootMotion::Separate`]), one more node,
//!   `root`, is the last node of the file: the child of the skeleton's root node, the parent of
//!   the pelvis, and the last joint of the skin (so skin joint `j` stays libflame's joint `j`;
//!   its inverse bind matrix is the identity: it rests at the origin, on the ground). Its
//!   translation is animated with the ground point under the pelvis, the pelvis's with its
//!   position relative to it (the clip's in-place pelvis); it has no rotation. The figure is
//!   bound to the joints only, so it poses exactly as without the bone.
//! - **Metadata.** `asset.generator` = `libflame <version>`; `asset.extras` holds `libflame`
//!   (the version), `format`, `fps`, `frames` and, when given, `prompt`, `model` and `seed`.
//!   When the poses carry foot contacts (humanml263's own, or the finished ones), the
//!   animation's `extras` hold them as `foot_contacts`, one `[left ankle, left foot, right
//!   ankle, right foot]` array a frame (0 and 1 written as integers), with the four joints'
//!   names in `foot_contact_joints`.
//!
//! Every value written is checked finite first: a motion that overflows `f32` (a root path
//! integrated from absurd velocities, say) is an error, not a file with NaN in it.

use base64::Engine as _;
use serde_json::{json, Map, Value};

use super::convention::{Change, Convention};
use super::layout::Layout;
use super::poses::Poses;
use super::rotation::{self, Vec3};
use super::skeleton::Skeleton;
use crate::error::{invalid_arg, Result};

/// What a glTF file says about its motion besides the poses.
#[derive(Clone, Copy, Debug, Default)]
pub struct GltfOptions<'a> {
    /// Frames per second of the animation; 0 = the format's own rate.
    pub fps: f32,
    /// The prompt, kept in `asset.extras.prompt`; it also names the animation.
    pub prompt: Option<&'a str>,
    /// The model (a file name or an architecture), kept in `asset.extras.model`.
    pub model: Option<&'a str>,
    /// The generation's seed, kept in `asset.extras.seed`.
    pub seed: Option<u64>,
    /// The animation's name; `None` = the sanitised prompt.
    pub name: Option<&'a str>,
}

/// The root bone's node name (module doc).
pub const ROOT_BONE: &str = "root";

/// The joints foot contacts are given for, in their order: left ankle, left foot, right ankle,
/// right foot (both skeletons number them alike).
const FOOT_JOINTS: [usize; 4] = [7, 10, 8, 11];

/// The two containers glTF 2.0 defines.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Container {
    /// Binary glTF (`.glb`): a JSON chunk and a binary chunk.
    Glb,
    /// JSON glTF (`.gltf`) with its one buffer embedded as a base64 data URI.
    Gltf,
}

impl Container {
    /// The container a file name's extension asks for (`glb` or `gltf`, any case).
    pub fn from_extension(ext: &str) -> Option<Container> {
        match ext.to_ascii_lowercase().as_str() {
            "glb" => Some(Container::Glb),
            "gltf" => Some(Container::Gltf),
            _ => None,
        }
    }
}

/// The file in `container`.
pub fn to_bytes(poses: &Poses, opts: &GltfOptions, container: Container) -> Result<Vec<u8>> {
    match container {
        Container::Glb => to_glb(poses, opts),
        Container::Gltf => to_gltf(poses, opts).map(String::into_bytes),
    }
}

/// The motion as binary glTF (`.glb`).
pub fn to_glb(poses: &Poses, opts: &GltfOptions) -> Result<Vec<u8>> {
    let (mut doc, bin) = build(poses, opts)?;
    doc["buffers"] = json!([{ "byteLength": bin.len() }]);
    let mut text = serde_json::to_vec(&doc).map_err(|e| invalid_arg!("glTF JSON: {e}"))?;
    // Chunks are 4-byte aligned: JSON padded with spaces, the binary chunk with zeros (it is
    // already a multiple of 4).
    while !text.len().is_multiple_of(4) {
        text.push(b' ');
    }
    let total = 12 + 8 + text.len() + 8 + bin.len();
    let total32 =
        u32::try_from(total).map_err(|_| invalid_arg!("a {total}-byte glb exceeds 4 GiB"))?;
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&total32.to_le_bytes());
    out.extend_from_slice(&(text.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&text);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    Ok(out)
}

/// The motion as JSON glTF (`.gltf`), the buffer embedded as a base64 data URI.
pub fn to_gltf(poses: &Poses, opts: &GltfOptions) -> Result<String> {
    let (mut doc, bin) = build(poses, opts)?;
    let uri = format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&bin)
    );
    doc["buffers"] = json!([{ "byteLength": bin.len(), "uri": uri }]);
    serde_json::to_string(&doc).map_err(|e| invalid_arg!("glTF JSON: {e}"))
}

/// The animation's name for `prompt`: see the module doc.
pub fn animation_name(prompt: &str) -> String {
    let mut name = String::new();
    for c in prompt.chars() {
        if c.is_alphanumeric() || c == '-' || c == '_' {
            name.push(c);
        } else if !name.is_empty() && !name.ends_with('_') {
            name.push('_');
        }
        if name.chars().count() >= 64 {
            break;
        }
    }
    let name = name.trim_end_matches('_');
    if name.is_empty() {
        "motion".to_string()
    } else {
        name.to_string()
    }
}

/// glTF rotations must be unit quaternions. Decoded rotations are, except where a model's 6D
/// output is degenerate (two parallel or zero vectors, as a clamped untrained model can give):
/// those are normalised, and a zero quaternion becomes the identity.
fn normalize_quaternions(q: &mut [f32]) {
    for q in q.chunks_exact_mut(4) {
        let n = q.iter().map(|&v| v as f64 * v as f64).sum::<f64>().sqrt();
        if (n - 1.0).abs() > 1e-6 {
            if n > 1e-12 {
                q.iter_mut().for_each(|v| *v = (*v as f64 / n) as f32);
            } else {
                q.copy_from_slice(&[0.0, 0.0, 0.0, 1.0]);
            }
        }
    }
}

/// The binary buffer being assembled, with its buffer views and accessors.
#[derive(Default)]
struct Buffer {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

/// An accessor's element type.
#[derive(Clone, Copy)]
enum Kind {
    Scalar,
    Vec3,
    Vec4,
    Mat4,
}

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::Scalar => "SCALAR",
            Kind::Vec3 => "VEC3",
            Kind::Vec4 => "VEC4",
            Kind::Mat4 => "MAT4",
        }
    }

    fn width(self) -> usize {
        match self {
            Kind::Scalar => 1,
            Kind::Vec3 => 3,
            Kind::Vec4 => 4,
            Kind::Mat4 => 16,
        }
    }
}

const FLOAT: u32 = 5126;
const UNSIGNED_SHORT: u32 = 5123;
const UNSIGNED_BYTE: u32 = 5121;
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;

impl Buffer {
    /// Appends `bytes` as a buffer view (4-byte aligned) and returns its index.
    fn view(&mut self, bytes: &[u8], target: Option<u32>) -> usize {
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let mut v = json!({ "buffer": 0, "byteOffset": offset, "byteLength": bytes.len() });
        if let Some(t) = target {
            v["target"] = json!(t);
        }
        self.views.push(v);
        self.views.len() - 1
    }

    /// A float accessor over `values` (`kind.width()` per element); `bounds` adds min and max
    /// (required for positions and animation inputs).
    fn floats(
        &mut self,
        values: &[f32],
        kind: Kind,
        target: Option<u32>,
        bounds: bool,
    ) -> Result<usize> {
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(invalid_arg!(
                "glTF: value {i} of a {} accessor is not finite in f32 (the motion overflows)",
                kind.name()
            ));
        }
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes, target);
        let w = kind.width();
        let mut a = json!({
            "bufferView": view,
            "componentType": FLOAT,
            "count": values.len() / w,
            "type": kind.name(),
        });
        if bounds {
            let mut lo = vec![f32::INFINITY; w];
            let mut hi = vec![f32::NEG_INFINITY; w];
            for e in values.chunks_exact(w) {
                for k in 0..w {
                    lo[k] = lo[k].min(e[k]);
                    hi[k] = hi[k].max(e[k]);
                }
            }
            a["min"] = json!(lo);
            a["max"] = json!(hi);
        }
        self.accessors.push(a);
        Ok(self.accessors.len() - 1)
    }

    /// An integer accessor (`UNSIGNED_BYTE` or `UNSIGNED_SHORT` components).
    fn integers(
        &mut self,
        bytes: &[u8],
        component: u32,
        count: usize,
        kind: Kind,
        target: u32,
    ) -> usize {
        let view = self.view(bytes, Some(target));
        self.accessors.push(json!({
            "bufferView": view,
            "componentType": component,
            "count": count,
            "type": kind.name(),
        }));
        self.accessors.len() - 1
    }
}

/// The three colours of the figure, as the preview's inks.
const SIDES: [(&str, [f32; 4]); 3] = [
    ("spine", [0.196, 0.196, 0.196, 1.0]),
    ("left", [0.122, 0.467, 0.706, 1.0]),
    ("right", [0.941, 0.471, 0.078, 1.0]),
];

/// 0 spine, 1 left, 2 right, from a joint's name.
fn side(name: &str) -> usize {
    let n = name.to_ascii_lowercase();
    if n.starts_with("l_") || n.starts_with("left_") {
        1
    } else if n.starts_with("r_") || n.starts_with("right_") {
        2
    } else {
        0
    }
}

/// The figure's mesh in the rest pose: flat-shaded boxes, four vertices a face.
#[derive(Default)]
struct Figure {
    positions: Vec<f32>,
    normals: Vec<f32>,
    joints: Vec<u8>,
    /// Triangle indices per side (spine, left, right).
    indices: [Vec<u16>; 3],
}

impl Figure {
    /// A box around the segment `a`–`b`, `half` wide each way, rigidly bound to `joint`.
    fn bone(&mut self, a: Vec3, b: Vec3, half: f64, joint: usize, side: usize) {
        let d = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let len = rotation::dot(&d, &d).sqrt();
        if len < 1e-6 {
            return;
        }
        let d = d.map(|x| x / len);
        // The world axis least aligned with the bone gives the box's other two axes.
        let helper = if d[0].abs() < 0.6 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let u = unit(rotation::cross(&d, &helper));
        let v = rotation::cross(&d, &u);
        let mid = [
            0.5 * (a[0] + b[0]),
            0.5 * (a[1] + b[1]),
            0.5 * (a[2] + b[2]),
        ];
        let along = 0.5 * len;
        // (normal, half extent along it, s, t) with s × t = normal: corners go counter-clockwise
        // seen from outside. (d, u, v) is right-handed: d × u = v, u × v = d, v × d = u.
        let neg = |x: Vec3| x.map(|c| -c);
        let faces = [
            (u, half, (v, half), (d, along)),
            (neg(u), half, (d, along), (v, half)),
            (v, half, (d, along), (u, half)),
            (neg(v), half, (u, half), (d, along)),
            (d, along, (u, half), (v, half)),
            (neg(d), along, (v, half), (u, half)),
        ];
        for (n, h, (s, hs), (t, ht)) in faces {
            let base = (self.positions.len() / 3) as u16;
            let centre = [mid[0] + n[0] * h, mid[1] + n[1] * h, mid[2] + n[2] * h];
            for (cs, ct) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
                for k in 0..3 {
                    self.positions
                        .push((centre[k] + cs * hs * s[k] + ct * ht * t[k]) as f32);
                    self.normals.push(n[k] as f32);
                }
                self.joints.extend_from_slice(&[joint as u8, 0, 0, 0]);
            }
            self.indices[side].extend_from_slice(&[
                base,
                base + 1,
                base + 2,
                base,
                base + 2,
                base + 3,
            ]);
        }
    }
}

fn unit(v: Vec3) -> Vec3 {
    let n = rotation::dot(&v, &v).sqrt();
    v.map(|x| x / n)
}

/// The rest pose's joint positions (identity rotations, the lowest joint at y = 0) and its
/// per-joint translations (root: its rest position; others: their offsets), glTF convention.
fn rest_pose(skel: &Skeleton, offsets: &[Vec3]) -> (Vec<Vec3>, Vec<Vec3>) {
    let n = skel.joint_count();
    let mut pos = vec![[0.0; 3]; n];
    for j in 1..n {
        let p = skel.parent(j).unwrap_or(0);
        pos[j] = rotation::add(&pos[p], &offsets[j]);
    }
    let lift = -pos.iter().map(|p| p[1]).fold(f64::INFINITY, f64::min);
    for p in &mut pos {
        p[1] += lift;
    }
    let mut trs = offsets.to_vec();
    trs[0] = pos[0];
    (pos, trs)
}

/// The glTF document (without `buffers`) and its binary buffer.
fn build(poses: &Poses, opts: &GltfOptions) -> Result<(Value, Vec<u8>)> {
    let frames = poses.frames();
    if frames == 0 {
        return Err(invalid_arg!("a glTF animation needs at least one frame"));
    }
    let format = poses.format();
    let fps = if opts.fps == 0.0 {
        format.fps()
    } else {
        opts.fps
    };
    if !(fps.is_finite() && fps > 0.0) {
        return Err(invalid_arg!("glTF frame rate must be positive, got {fps}"));
    }
    let skel = format.skeleton();
    let joints = skel.joint_count();
    let bone = !poses.root_bone.is_empty();
    if bone && poses.root_bone.len() != frames {
        return Err(invalid_arg!(
            "glTF: the root bone track has {} entries for {frames} frames",
            poses.root_bone.len()
        ));
    }
    // Node 0 the skeleton's root, 1 + j joint j, joints + 1 the figure, joints + 2 the root bone.
    let root_node = joints + 2;
    let conv = Convention::Gltf;
    let ch = Change::new(format, conv);
    let offsets: Vec<Vec3> = skel.rest_offsets().iter().map(|o| ch.offset(o)).collect();
    let (rest, trs) = rest_pose(skel, &offsets);

    let mut buf = Buffer::default();

    // The figure, in the rest pose.
    let mut fig = Figure::default();
    for j in 1..joints {
        let p = skel.parent(j).unwrap_or(0);
        let half = (0.12 * rotation::dot(&offsets[j], &offsets[j]).sqrt()).clamp(0.015, 0.04);
        let s = side(skel.joint_names()[j]);
        fig.bone(rest[p], rest[j], half, p, s);
        if skel.children(j).next().is_none() {
            let tip = rotation::add(&rest[j], &offsets[j].map(|x| 0.5 * x));
            let head = skel.joint_names()[j].eq_ignore_ascii_case("head");
            let half = if head { 0.08 } else { half };
            let tip = if head {
                rotation::add(&rest[j], &[0.0, 0.2, 0.0])
            } else {
                tip
            };
            fig.bone(rest[j], tip, half, j, s);
        }
    }
    let vertices = fig.positions.len() / 3;
    if vertices > u16::MAX as usize {
        return Err(invalid_arg!("glTF: the figure has {vertices} vertices"));
    }
    let position = buf.floats(&fig.positions, Kind::Vec3, Some(ARRAY_BUFFER), true)?;
    let normal = buf.floats(&fig.normals, Kind::Vec3, Some(ARRAY_BUFFER), false)?;
    let joint_ids = buf.integers(
        &fig.joints,
        UNSIGNED_BYTE,
        vertices,
        Kind::Vec4,
        ARRAY_BUFFER,
    );
    let weights: Vec<f32> = (0..vertices).flat_map(|_| [1.0, 0.0, 0.0, 0.0]).collect();
    let weight = buf.floats(&weights, Kind::Vec4, Some(ARRAY_BUFFER), false)?;
    let mut primitives = Vec::new();
    for (s, idx) in fig.indices.iter().enumerate() {
        if idx.is_empty() {
            continue;
        }
        let bytes: Vec<u8> = idx.iter().flat_map(|i| i.to_le_bytes()).collect();
        let indices = buf.integers(
            &bytes,
            UNSIGNED_SHORT,
            idx.len(),
            Kind::Scalar,
            ELEMENT_ARRAY_BUFFER,
        );
        primitives.push(json!({
            "attributes": {
                "POSITION": position,
                "NORMAL": normal,
                "JOINTS_0": joint_ids,
                "WEIGHTS_0": weight,
            },
            "indices": indices,
            "material": s,
        }));
    }

    // Inverse bind matrices: the rest pose has identity rotations, so each is a translation by
    // minus the joint's rest position (column-major).
    let ibm: Vec<f32> = rest
        .iter()
        .chain(bone.then_some(&[0.0; 3]))
        .flat_map(|p| {
            let mut m = [0.0f32; 16];
            m[0] = 1.0;
            m[5] = 1.0;
            m[10] = 1.0;
            m[15] = 1.0;
            m[12] = -p[0] as f32;
            m[13] = -p[1] as f32;
            m[14] = -p[2] as f32;
            m
        })
        .collect();
    let ibm = buf.floats(&ibm, Kind::Mat4, None, false)?;

    // The animation.
    let times: Vec<f32> = (0..frames)
        .map(|t| (t as f64 / fps as f64) as f32)
        .collect();
    let input = buf.floats(&times, Kind::Scalar, None, true)?;
    // With a root bone the poses' root translation is already the pelvis's position relative
    // to it (root_motion's `Separate`), which is what the pelvis node's translation must be
    // under a parent without rotation.
    let root = poses.layout(Layout::RootTranslation, conv)?;
    let bone_track: Vec<f32> = poses
        .root_bone
        .iter()
        .flat_map(|b| ch.position(b))
        .map(|x| x as f32)
        .collect();
    let mut quats = poses.layout(Layout::LocalQuatXyzw, conv)?;
    normalize_quaternions(&mut quats);
    let translation = buf.floats(&root, Kind::Vec3, None, false)?;
    let mut samplers =
        vec![json!({ "input": input, "output": translation, "interpolation": "LINEAR" })];
    let mut channels =
        vec![json!({ "sampler": 0, "target": { "node": 1, "path": "translation" } })];
    let mut track = vec![0.0f32; frames * 4];
    for j in 0..joints {
        for t in 0..frames {
            track[t * 4..t * 4 + 4].copy_from_slice(&quats[(t * joints + j) * 4..][..4]);
        }
        let output = buf.floats(&track, Kind::Vec4, None, false)?;
        samplers.push(json!({ "input": input, "output": output, "interpolation": "LINEAR" }));
        channels.push(json!({
            "sampler": samplers.len() - 1,
            "target": { "node": 1 + j, "path": "rotation" },
        }));
    }
    if bone {
        let output = buf.floats(&bone_track, Kind::Vec3, None, false)?;
        samplers.push(json!({ "input": input, "output": output, "interpolation": "LINEAR" }));
        channels.push(json!({
            "sampler": samplers.len() - 1,
            "target": { "node": root_node, "path": "translation" },
        }));
    }
    if !format.positions_are_kinematic() {
        // The positions are the format's own output, not the rotations' forward kinematics:
        // each joint's translation is animated too, `global(parent)ᵀ · (p(j) − p(parent))`, so
        // the hierarchy lands every joint where the format puts it.
        let pos = poses.positions(conv);
        let global = poses.global_rotations(conv);
        let mut track = vec![0.0f32; frames * 3];
        for j in 1..joints {
            let p = skel.parent(j).unwrap_or(0);
            for t in 0..frames {
                let (a, b) = (pos[t * joints + p], pos[t * joints + j]);
                let d = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
                let local = rotation::apply(&rotation::transpose(&global[t * joints + p]), &d);
                for k in 0..3 {
                    track[t * 3 + k] = local[k] as f32;
                }
            }
            let output = buf.floats(&track, Kind::Vec3, None, false)?;
            samplers.push(json!({ "input": input, "output": output, "interpolation": "LINEAR" }));
            channels.push(json!({
                "sampler": samplers.len() - 1,
                "target": { "node": 1 + j, "path": "translation" },
            }));
        }
    }

    // Nodes: 0 the skeleton's root, 1..=J the joints (node 1 + j is joint j), J + 1 the figure.
    let top = if bone { root_node } else { 1 };
    let mut nodes = vec![json!({ "name": skel.name(), "children": [top] })];
    for (j, rest) in trs.iter().enumerate() {
        let t = rest.map(|x| x as f32);
        let mut node = json!({ "name": skel.joint_names()[j], "translation": t });
        let children: Vec<usize> = skel.children(j).map(|c| 1 + c).collect();
        if !children.is_empty() {
            node["children"] = json!(children);
        }
        nodes.push(node);
    }
    nodes.push(json!({ "name": "figure", "mesh": 0, "skin": 0 }));
    let mut skin_joints: Vec<usize> = (1..=joints).collect();
    if bone {
        nodes.push(json!({ "name": ROOT_BONE, "children": [1] }));
        skin_joints.push(root_node);
    }

    let materials: Vec<Value> = SIDES
        .iter()
        .map(|(name, colour)| {
            json!({
                "name": name,
                "pbrMetallicRoughness": {
                    "baseColorFactor": colour,
                    "metallicFactor": 0.0,
                    "roughnessFactor": 0.8,
                },
            })
        })
        .collect();

    let version = env!("CARGO_PKG_VERSION");
    let mut extras = Map::new();
    extras.insert("libflame".into(), json!(version));
    extras.insert("format".into(), json!(format.name()));
    extras.insert("fps".into(), json!(fps));
    extras.insert("frames".into(), json!(frames));
    if let Some(p) = opts.prompt {
        extras.insert("prompt".into(), json!(p));
    }
    if let Some(m) = opts.model {
        extras.insert("model".into(), json!(m));
    }
    if let Some(s) = opts.seed {
        extras.insert("seed".into(), json!(s));
    }
    let name = match opts.name {
        Some(n) => animation_name(n),
        None => animation_name(opts.prompt.unwrap_or("")),
    };
    let mut animation = json!({ "name": name, "samplers": samplers, "channels": channels });
    if poses.contacts.len() == frames {
        let names = skel.joint_names();
        let value = |c: f64| {
            if c == 0.0 || c == 1.0 {
                json!(c as u8)
            } else {
                json!(c as f32)
            }
        };
        let contacts: Vec<Value> = poses
            .contacts
            .iter()
            .map(|f| Value::Array(f.iter().map(|&c| value(c)).collect()))
            .collect();
        animation["extras"] = json!({
            "foot_contacts": contacts,
            "foot_contact_joints": FOOT_JOINTS.map(|j| names[j]),
        });
    }

    let doc = json!({
        "asset": {
            "version": "2.0",
            "generator": format!("libflame {version}"),
            "extras": extras,
        },
        "scene": 0,
        "scenes": [{ "name": name, "nodes": [0, joints + 1] }],
        "nodes": nodes,
        "meshes": [{ "name": "figure", "primitives": primitives }],
        "materials": materials,
        "skins": [{
            "name": skel.name(),
            "inverseBindMatrices": ibm,
            "skeleton": 0,
            "joints": skin_joints,
        }],
        "animations": [animation],
        "bufferViews": buf.views,
        "accessors": buf.accessors,
    });
    Ok((doc, buf.bin))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::{Format, ReadOptions};

    /// A smooth synthetic motion: every feature a different sinusoid of time (rotations from
    /// arbitrary 6D vectors, a drifting root).
    fn motion(format: Format, frames: usize) -> Poses {
        crate::motion::testutil::sinusoid_motion(format, frames)
    }

    /// The JSON and binary chunks of a glb, after checking its header and chunk lengths.
    fn split(glb: &[u8]) -> (Value, &[u8]) {
        assert_eq!(&glb[..4], b"glTF");
        let word = |o: usize| u32::from_le_bytes(glb[o..o + 4].try_into().unwrap()) as usize;
        assert_eq!(word(4), 2);
        assert_eq!(word(8), glb.len());
        let jlen = word(12);
        assert_eq!(&glb[16..20], b"JSON");
        assert_eq!(jlen % 4, 0);
        let doc: Value = serde_json::from_slice(&glb[20..20 + jlen]).unwrap();
        let b = 20 + jlen;
        let blen = word(b);
        assert_eq!(&glb[b + 4..b + 8], b"BIN\0");
        assert_eq!(b + 8 + blen, glb.len());
        (doc, &glb[b + 8..])
    }

    /// Accessor `i`'s floats.
    fn floats(doc: &Value, bin: &[u8], i: usize) -> Vec<f32> {
        let a = &doc["accessors"][i];
        assert_eq!(a["componentType"], FLOAT);
        let v = &doc["bufferViews"][a["bufferView"].as_u64().unwrap() as usize];
        let off = v["byteOffset"].as_u64().unwrap() as usize;
        let len = v["byteLength"].as_u64().unwrap() as usize;
        bin[off..off + len]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect()
    }

    fn quat_matrix(q: &[f32]) -> [[f64; 3]; 3] {
        let (x, y, z, w) = (q[0] as f64, q[1] as f64, q[2] as f64, q[3] as f64);
        [
            [
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y - w * z),
                2.0 * (x * z + w * y),
            ],
            [
                2.0 * (x * y + w * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z - w * x),
            ],
            [
                2.0 * (x * z - w * y),
                2.0 * (y * z + w * x),
                1.0 - 2.0 * (x * x + y * y),
            ],
        ]
    }

    #[test]
    fn node_transforms_animate_the_joint_positions_of_the_gltf_convention() {
        for format in Format::ALL {
            let frames = 7;
            let poses = motion(format, frames);
            let glb = to_glb(&poses, &GltfOptions::default()).unwrap();
            let (doc, bin) = split(&glb);
            let joints = format.skeleton().joint_count();
            let anim = &doc["animations"][0];
            // Sampler outputs per node and path.
            let mut rot = vec![Vec::new(); joints];
            let mut trans: Vec<Vec<f32>> = vec![Vec::new(); joints];
            let mut root_t = Vec::new();
            for c in anim["channels"].as_array().unwrap() {
                let s = &anim["samplers"][c["sampler"].as_u64().unwrap() as usize];
                assert_eq!(s["interpolation"], "LINEAR");
                let times = floats(&doc, bin, s["input"].as_u64().unwrap() as usize);
                assert_eq!(times.len(), frames);
                assert!((times[1] - 0.05).abs() < 1e-7, "20 fps");
                let out = floats(&doc, bin, s["output"].as_u64().unwrap() as usize);
                let node = c["target"]["node"].as_u64().unwrap() as usize;
                match c["target"]["path"].as_str().unwrap() {
                    "translation" if node == 1 => root_t = out,
                    "translation" => {
                        assert_eq!(format, Format::HumanMl263);
                        trans[node - 1] = out;
                    }
                    "rotation" => rot[node - 1] = out,
                    p => panic!("unexpected path {p}"),
                }
            }
            // What flame_session_read gives for the gltf layouts, bit for bit.
            assert_eq!(
                root_t,
                poses
                    .layout(Layout::RootTranslation, Convention::Gltf)
                    .unwrap()
            );
            let q = poses
                .layout(Layout::LocalQuatXyzw, Convention::Gltf)
                .unwrap();
            for t in 0..frames {
                for j in 0..joints {
                    assert_eq!(rot[j][t * 4..t * 4 + 4], q[(t * joints + j) * 4..][..4]);
                }
            }
            // Compose the node hierarchy (the file's rest translations, the animated rotations
            // and root translation) and compare with libflame's forward kinematics.
            let nodes = doc["nodes"].as_array().unwrap();
            let rest: Vec<Vec3> = (0..joints)
                .map(|j| {
                    let t = &nodes[1 + j]["translation"];
                    [0, 1, 2].map(|k| t[k].as_f64().unwrap())
                })
                .collect();
            let mut parent = vec![usize::MAX; joints];
            for (j, n) in nodes[1..=joints].iter().enumerate() {
                for c in n["children"].as_array().into_iter().flatten() {
                    parent[c.as_u64().unwrap() as usize - 1] = j;
                }
            }
            let want = poses
                .layout(Layout::GlobalPositions, Convention::Gltf)
                .unwrap();
            let mut worst = 0.0f64;
            for t in 0..frames {
                let mut world = vec![rotation::IDENTITY; joints];
                let mut pos = vec![[0.0; 3]; joints];
                for j in 0..joints {
                    let r = quat_matrix(&rot[j][t * 4..t * 4 + 4]);
                    if j == 0 {
                        world[0] = r;
                        pos[0] = [0, 1, 2].map(|k| root_t[t * 3 + k] as f64);
                    } else {
                        let p = parent[j];
                        let offset = match &trans[j][..] {
                            [] => rest[j],
                            tr => [0, 1, 2].map(|k| tr[t * 3 + k] as f64),
                        };
                        world[j] = rotation::mul(&world[p], &r);
                        pos[j] = rotation::add(&pos[p], &rotation::apply(&world[p], &offset));
                    }
                    for k in 0..3 {
                        worst =
                            worst.max((pos[j][k] - want[(t * joints + j) * 3 + k] as f64).abs());
                    }
                }
            }
            assert!(worst < 1e-5, "{format}: {worst} m");
        }
    }

    #[test]
    fn the_skin_binds_the_figure_in_the_rest_pose() {
        let poses = motion(Format::Smpl24Rot6d, 2);
        let glb = to_glb(&poses, &GltfOptions::default()).unwrap();
        let (doc, bin) = split(&glb);
        let skin = &doc["skins"][0];
        let joints = 24;
        assert_eq!(skin["joints"].as_array().unwrap().len(), joints);
        let ibm = floats(
            &doc,
            bin,
            skin["inverseBindMatrices"].as_u64().unwrap() as usize,
        );
        // Rest world position of every joint from the nodes' translations (identity rotations).
        let nodes = doc["nodes"].as_array().unwrap();
        let mut pos = vec![[0.0f64; 3]; joints];
        let mut lowest = f64::MAX;
        for j in 0..joints {
            let t = &nodes[1 + j]["translation"];
            let t = [0, 1, 2].map(|k| t[k].as_f64().unwrap());
            pos[j] = match Skeleton::smpl24().parent(j) {
                Some(p) => rotation::add(&pos[p], &t),
                None => t,
            };
            lowest = lowest.min(pos[j][1]);
            // IBM · bind world = identity: a translation by minus the rest position.
            for k in 0..3 {
                assert!((ibm[j * 16 + 12 + k] as f64 + pos[j][k]).abs() < 1e-6);
            }
        }
        assert!(
            lowest.abs() < 1e-6,
            "the rest pose stands on y = 0: {lowest}"
        );
        // Every vertex is bound to one joint with weight 1, and lies near that joint's bones.
        let prim = &doc["meshes"][0]["primitives"][0]["attributes"];
        let verts = floats(&doc, bin, prim["POSITION"].as_u64().unwrap() as usize);
        let normals = floats(&doc, bin, prim["NORMAL"].as_u64().unwrap() as usize);
        for n in normals.chunks_exact(3) {
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            assert!((len - 1.0).abs() < 1e-6);
        }
        let acc = &doc["accessors"][prim["JOINTS_0"].as_u64().unwrap() as usize];
        let v = &doc["bufferViews"][acc["bufferView"].as_u64().unwrap() as usize];
        let off = v["byteOffset"].as_u64().unwrap() as usize;
        let ids = &bin[off..off + verts.len() / 3 * 4];
        for (i, p) in verts.chunks_exact(3).enumerate() {
            let j = ids[i * 4] as usize;
            assert_eq!(&ids[i * 4 + 1..i * 4 + 4], &[0, 0, 0]);
            let d = (0..3)
                .map(|k| (p[k] as f64 - pos[j][k]).powi(2))
                .sum::<f64>()
                .sqrt();
            assert!(d < 0.65, "vertex {i} is {d} m from its joint {j}");
        }
        assert_eq!(doc["meshes"][0]["primitives"].as_array().unwrap().len(), 3);
    }

    #[test]
    fn the_json_container_embeds_the_same_buffer_and_metadata() {
        let poses = motion(Format::HumanMl263, 5);
        let opts = GltfOptions {
            fps: 30.0,
            prompt: Some("a person waves, then sits down."),
            model: Some("demo.safetensors"),
            seed: Some(42),
            name: None,
        };
        let (doc_b, bin) = {
            let glb = to_glb(&poses, &opts).unwrap();
            let (d, b) = split(&glb);
            (d, b.to_vec())
        };
        let text = to_gltf(&poses, &opts).unwrap();
        let doc: Value = serde_json::from_str(&text).unwrap();
        let uri = doc["buffers"][0]["uri"].as_str().unwrap();
        let data = base64::engine::general_purpose::STANDARD
            .decode(
                uri.strip_prefix("data:application/octet-stream;base64,")
                    .unwrap(),
            )
            .unwrap();
        assert_eq!(data, bin);
        assert_eq!(doc["buffers"][0]["byteLength"], bin.len());
        assert_eq!(doc["accessors"], doc_b["accessors"]);
        let extras = &doc["asset"]["extras"];
        assert_eq!(extras["prompt"], "a person waves, then sits down.");
        assert_eq!(extras["model"], "demo.safetensors");
        assert_eq!(extras["seed"], 42);
        assert_eq!(extras["libflame"], env!("CARGO_PKG_VERSION"));
        assert_eq!(extras["fps"], 30.0);
        assert_eq!(
            doc["animations"][0]["name"],
            "a_person_waves_then_sits_down"
        );
        assert_eq!(doc["asset"]["version"], "2.0");
    }

    #[test]
    fn degenerate_rotations_are_written_as_unit_quaternions() {
        // Joint 5's 6D rows parallel (a clamped output), joint 6's zero.
        let dim = Format::Smpl24Rot6d.feature_dim();
        let mut x = vec![0.0f32; 2 * dim];
        for t in 0..2 {
            let row = &mut x[t * dim..(t + 1) * dim];
            for j in 0..24 {
                row[3 + 6 * j..9 + 6 * j].copy_from_slice(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
            }
            row[3 + 30..9 + 30].copy_from_slice(&[1.0, 1.0, 1.0, 1.0, 1.0, 1.0]);
            row[3 + 36..9 + 36].fill(0.0);
        }
        let poses = Poses::decode(Format::Smpl24Rot6d, &x, 2, &ReadOptions::default()).unwrap();
        let raw = poses
            .layout(Layout::LocalQuatXyzw, Convention::Gltf)
            .unwrap();
        let norm = |q: &[f32]| q.iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!(
            (norm(&raw[20..24]) - 1.0).abs() > 0.1,
            "joint 5 is degenerate"
        );
        let glb = to_glb(&poses, &GltfOptions::default()).unwrap();
        let (doc, bin) = split(&glb);
        let anim = &doc["animations"][0];
        for c in anim["channels"].as_array().unwrap() {
            if c["target"]["path"] == "rotation" {
                let s = &anim["samplers"][c["sampler"].as_u64().unwrap() as usize];
                let q = floats(&doc, bin, s["output"].as_u64().unwrap() as usize);
                for q in q.chunks_exact(4) {
                    assert!((norm(q) - 1.0).abs() < 1e-6, "{q:?}");
                }
            }
        }
    }

    /// World positions of every node on every frame, composed from the file's node tree (rest
    /// translations, animated translations and rotations): `[frames][node]`.
    fn node_world_positions(doc: &Value, bin: &[u8], frames: usize) -> Vec<Vec<Vec3>> {
        let nodes = doc["nodes"].as_array().unwrap();
        let n = nodes.len();
        let anim = &doc["animations"][0];
        let mut trans: Vec<Option<Vec<f32>>> = vec![None; n];
        let mut rot: Vec<Option<Vec<f32>>> = vec![None; n];
        for c in anim["channels"].as_array().unwrap() {
            let s = &anim["samplers"][c["sampler"].as_u64().unwrap() as usize];
            let out = floats(doc, bin, s["output"].as_u64().unwrap() as usize);
            let node = c["target"]["node"].as_u64().unwrap() as usize;
            match c["target"]["path"].as_str().unwrap() {
                "translation" => trans[node] = Some(out),
                "rotation" => rot[node] = Some(out),
                p => panic!("unexpected path {p}"),
            }
        }
        let rest = |i: usize| -> Vec3 {
            match nodes[i].get("translation") {
                Some(t) => [0, 1, 2].map(|k| t[k].as_f64().unwrap()),
                None => [0.0; 3],
            }
        };
        (0..frames)
            .map(|t| {
                let mut pos = vec![[0.0; 3]; n];
                let mut world = vec![rotation::IDENTITY; n];
                // Depth first from node 0 (parents before children).
                let mut stack = vec![0usize];
                while let Some(i) = stack.pop() {
                    let tr = trans[i]
                        .as_ref()
                        .map_or(rest(i), |v| [0, 1, 2].map(|k| v[t * 3 + k] as f64));
                    let r = rot[i]
                        .as_ref()
                        .map_or(rotation::IDENTITY, |v| quat_matrix(&v[t * 4..t * 4 + 4]));
                    // Children were given their parent's world transform when pushed.
                    let (pp, pw) = (pos[i], world[i]);
                    pos[i] = rotation::add(&pp, &rotation::apply(&pw, &tr));
                    world[i] = rotation::mul(&pw, &r);
                    for c in nodes[i]["children"].as_array().into_iter().flatten() {
                        let c = c.as_u64().unwrap() as usize;
                        pos[c] = pos[i];
                        world[c] = world[i];
                        stack.push(c);
                    }
                }
                pos
            })
            .collect()
    }

    fn keep_and_separate(format: Format, frames: usize) -> (Poses, Poses) {
        let keep = motion(format, frames);
        let mut sep = keep.clone();
        crate::motion::root_motion::apply(&mut sep, crate::motion::RootMotion::Separate, false);
        (keep, sep)
    }

    #[test]
    fn a_root_bone_parents_the_pelvis_and_the_figure_moves_as_before() {
        for format in Format::ALL {
            let frames = 6;
            let (keep, sep) = keep_and_separate(format, frames);
            let joints = format.skeleton().joint_count();
            let glb = to_glb(&sep, &GltfOptions::default()).unwrap();
            let (doc, bin) = split(&glb);
            let nodes = doc["nodes"].as_array().unwrap();
            assert_eq!(nodes.len(), joints + 3);
            let root = joints + 2;
            assert_eq!(nodes[root]["name"], "root");
            assert_eq!(nodes[root]["children"], json!([1]));
            assert_eq!(nodes[0]["children"], json!([root]));
            assert_eq!(nodes[joints + 1]["name"], "figure");
            let skin = &doc["skins"][0];
            let sj = skin["joints"].as_array().unwrap();
            assert_eq!(sj.len(), joints + 1);
            assert_eq!(sj[joints], root);
            let ibm = floats(
                &doc,
                bin,
                skin["inverseBindMatrices"].as_u64().unwrap() as usize,
            );
            let identity = [
                1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1.,
            ];
            assert_eq!(ibm[joints * 16..], identity);
            // Composed through the root bone, every joint lands where the clip with its root
            // motion kept puts it.
            let world = node_world_positions(&doc, bin, frames);
            let want = keep
                .layout(Layout::GlobalPositions, Convention::Gltf)
                .unwrap();
            let mut worst = 0.0f64;
            for t in 0..frames {
                // The root bone stands on the ground (glTF's y = 0) under the pelvis.
                assert_eq!(world[t][root][1], 0.0);
                for k in [0, 2] {
                    assert!((world[t][root][k] - world[t][1][k]).abs() < 1e-6);
                }
                for j in 0..joints {
                    for k in 0..3 {
                        let d = world[t][1 + j][k] - want[(t * joints + j) * 3 + k] as f64;
                        worst = worst.max(d.abs());
                    }
                }
            }
            assert!(worst < 1e-5, "{format}: {worst} m");
            // Without the bone the file is as before: the same composition, no `root` node.
            let glb = to_glb(&keep, &GltfOptions::default()).unwrap();
            let (doc, bin) = split(&glb);
            assert_eq!(doc["nodes"].as_array().unwrap().len(), joints + 2);
            let plain = node_world_positions(&doc, bin, frames);
            for t in 0..frames {
                for j in 0..joints {
                    for k in 0..3 {
                        assert!((plain[t][1 + j][k] - world[t][1 + j][k]).abs() < 1e-5);
                    }
                }
            }
        }
    }

    #[test]
    fn foot_contacts_travel_in_the_animation_extras() {
        let mut poses = motion(Format::Smpl24Rot6d, 3);
        let glb = to_glb(&poses, &GltfOptions::default()).unwrap();
        assert!(split(&glb).0["animations"][0].get("extras").is_none());
        poses.contacts = vec![[1.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 1.0], [0.0; 4]];
        let glb = to_glb(&poses, &GltfOptions::default()).unwrap();
        let extras = split(&glb).0["animations"][0]["extras"].clone();
        assert_eq!(
            extras["foot_contacts"],
            json!([[1, 1, 0, 0], [1, 0, 0, 1], [0, 0, 0, 0]])
        );
        assert_eq!(
            extras["foot_contact_joints"],
            json!(["L_Ankle", "L_Foot", "R_Ankle", "R_Foot"])
        );
        // humanml263's own contacts are the features' values (here not 0 or 1).
        let poses = motion(Format::HumanMl263, 2);
        let glb = to_glb(&poses, &GltfOptions::default()).unwrap();
        let extras = split(&glb).0["animations"][0]["extras"].clone();
        assert_eq!(
            extras["foot_contacts"][1][2].as_f64().unwrap() as f32,
            poses.contacts[1][2] as f32
        );
        assert_eq!(extras["foot_contact_joints"][3], "right_foot");
    }

    /// For tools/gltf_check.sh: with FLAME_GLTF_OUT=DIR, writes `root_separate_{smpl,hml}.glb`
    /// (40 frames at 20 fps resampled to 30 fps = 59 frames, the root motion on a root bone)
    /// and `root_separate_{smpl,hml}.npy`, the world joint positions Blender must give
    /// (`[59, joints, 3]`, gltf convention: the clip with its root motion kept, resampled
    /// alike).
    #[test]
    #[ignore]
    fn write_root_bone_check_files() {
        let dir = std::env::var("FLAME_GLTF_OUT").expect("set FLAME_GLTF_OUT to a directory");
        let dir = std::path::Path::new(&dir);
        for (format, name) in [(Format::Smpl24Rot6d, "smpl"), (Format::HumanMl263, "hml")] {
            let (keep, sep) = keep_and_separate(format, 40);
            let keep = crate::motion::resample::resample(&keep, 20.0, 30.0).unwrap();
            let sep = crate::motion::resample::resample(&sep, 20.0, 30.0).unwrap();
            assert_eq!(sep.frames(), 59);
            let opts = GltfOptions {
                fps: 30.0,
                ..Default::default()
            };
            std::fs::write(
                dir.join(format!("root_separate_{name}.glb")),
                to_glb(&sep, &opts).unwrap(),
            )
            .unwrap();
            let p = keep
                .layout(Layout::GlobalPositions, Convention::Gltf)
                .unwrap();
            crate::npy::write_f32(
                &dir.join(format!("root_separate_{name}.npy")),
                &[keep.frames(), keep.joint_count(), 3],
                &p,
            )
            .unwrap();
        }
    }

    #[test]
    fn animation_names_are_sanitised() {
        assert_eq!(
            animation_name("a person jumps twice."),
            "a_person_jumps_twice"
        );
        assert_eq!(animation_name("  walk -> run!! "), "walk_-_run");
        assert_eq!(animation_name(""), "motion");
        assert_eq!(animation_name("?!"), "motion");
        assert_eq!(animation_name("läuft_schnell"), "läuft_schnell");
        assert_eq!(animation_name(&"x".repeat(100)).len(), 64);
    }

    #[test]
    fn bad_motions_and_options_are_errors() {
        let poses = motion(Format::Smpl24Rot6d, 3);
        for fps in [-1.0, f32::NAN, f32::INFINITY] {
            let e = to_glb(
                &poses,
                &GltfOptions {
                    fps,
                    ..Default::default()
                },
            )
            .unwrap_err();
            assert!(e.to_string().contains("frame rate must be positive"), "{e}");
        }
        let empty = Poses::decode(Format::Smpl24Rot6d, &[], 0, &ReadOptions::default()).unwrap();
        let e = to_glb(&empty, &GltfOptions::default()).unwrap_err();
        assert!(e.to_string().contains("at least one frame"), "{e}");
        // HumanML3D's root path integrates velocities: 3e38 a frame overflows f32 by frame 2.
        let dim = Format::HumanMl263.feature_dim();
        let mut x = vec![0.0f32; 3 * dim];
        for t in 0..3 {
            x[t * dim + 1] = 3.0e38;
            x[t * dim + 2] = 3.0e38;
        }
        let poses = Poses::decode(Format::HumanMl263, &x, 3, &ReadOptions::default()).unwrap();
        let e = to_glb(&poses, &GltfOptions::default()).unwrap_err();
        assert!(e.to_string().contains("not finite"), "{e}");
        assert!(to_gltf(&poses, &GltfOptions::default()).is_err());
    }
}
