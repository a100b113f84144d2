//! A retargeted clip ([`RigMotion`]) as a BVH on the rig's own hierarchy, bone names and units
//! ([`to_string`]), for tools that take motion as BVH (Blender, MotionBuilder, game engines'
//! importers). It holds no rig data a BVH cannot say: no rest rotations, no scale, no skin.
//!
//! - **Hierarchy.** The rig's bones, depth first from each root, children in stored order. BVH
//!   has no rest rotations: its rest pose is every joint at identity, so each `OFFSET` is the
//!   bone's rest world position minus its parent's (a root's: its rest world position), in the
//!   rig's world axes and units; read back as a rig, the file gives the rig's rest positions.
//!   A rig with several roots (a deform-only export whose bones hang from non-deform ones) is
//!   written under one extra `ROOT` at the origin that never moves, named `root` (or `root_1`,
//!   … when a bone has that name). Whitespace in a name becomes `_` (BVH names are one token).
//!   Each leaf gets an `End Site` half its own offset long, along it (readers such as Blender
//!   need a non-zero tail).
//! - **Channels.** Roots and the bones whose translation is animated ([`RigMotion::moving`]:
//!   the hips, and bones beside the body that follow it): `Xposition
//!   Yposition Zposition Zrotation Xrotation Yrotation`; every other bone `Zrotation Xrotation
//!   Yrotation`, the rotation being `Rz · Rx · Ry` in degrees as in `crate::motion::bvh`.
//!   Position channels hold the bone's whole position relative to its parent (in the parent's
//!   posed BVH frame), so they replace the `OFFSET`, as Blender's importer reads them; a root's
//!   are its posed world position.
//! - **Rotations.** The BVH rotation that puts every joint where the rig's pose does: a bone's
//!   BVH world rotation is its posed world rotation times the inverse of its rest world one
//!   (`B = G · W⁻¹`, turning the rest world offsets of its children into posed ones), and the
//!   channels hold `B(parent)ᵀ · B`.
//!
//! Lengths are printed with enough decimals for a millionth of the rig's size (six for a
//! rig in centimetres, eight in metres), so the file reproduces the pose to that.

use std::fmt::Write;

use super::pose::RigMotion;
use super::rig::Rig;
use crate::error::{invalid_arg, Result};
use crate::motion::rotation::{self, Vec3};

/// `motion` on `rig` as BVH text (module doc). Errors: a motion not made for this rig (bone
/// count, hips bone or buffer sizes differ), no frames, a frame rate that is not positive, a
/// non-finite rotation or position (named by frame and bone), names that collide once
/// whitespace is replaced.
pub fn to_string(rig: &Rig, motion: &RigMotion) -> Result<String> {
    check(rig, motion)?;
    let n = rig.bone_count();
    let rest_pos = rig.rest_world_positions();
    let names = bvh_names(rig)?;
    let roots: Vec<usize> = (0..n).filter(|&b| rig.parent(b).is_none()).collect();
    let extra_root = (roots.len() > 1).then(|| free_name(&names));
    let mut positioned = vec![false; n];
    for &b in &roots {
        positioned[b] = true;
    }
    for &b in &motion.moving {
        positioned[b] = true;
    }
    let decimals = length_decimals(rest_pos);

    let offset = |b: usize| match rig.parent(b) {
        Some(p) => sub(&rest_pos[b], &rest_pos[p]),
        None => rest_pos[b],
    };
    let mut out = String::from("HIERARCHY\n");
    let mut order = Vec::with_capacity(n);
    let depth = match &extra_root {
        Some(name) => {
            let _ = writeln!(
                out,
                "ROOT {name}\n{{\n\tOFFSET {}",
                triple(&[0.0; 3], decimals)
            );
            let _ = writeln!(out, "\tCHANNELS 6 {POSITIONS} {ROTATIONS}");
            1
        }
        None => 0,
    };
    // Depth first with an explicit stack: a rig may chain up to `MAX_BONES` bones.
    enum Step {
        Open(usize, usize),
        Close(usize),
    }
    let mut stack: Vec<Step> = roots.iter().rev().map(|&b| Step::Open(b, depth)).collect();
    while let Some(step) = stack.pop() {
        match step {
            Step::Open(b, d) => {
                let pad = "\t".repeat(d);
                let keyword = if d == 0 { "ROOT" } else { "JOINT" };
                let o = offset(b);
                let _ = writeln!(out, "{pad}{keyword} {}\n{pad}{{", names[b]);
                let _ = writeln!(out, "{pad}\tOFFSET {}", triple(&o, decimals));
                if positioned[b] {
                    let _ = writeln!(out, "{pad}\tCHANNELS 6 {POSITIONS} {ROTATIONS}");
                } else {
                    let _ = writeln!(out, "{pad}\tCHANNELS 3 {ROTATIONS}");
                }
                order.push(b);
                stack.push(Step::Close(d));
                let first_child = stack.len();
                stack.extend(rig.children(b).map(|c| Step::Open(c, d + 1)));
                stack[first_child..].reverse();
                if stack.len() == first_child {
                    let tail = end_site(&o, rig.metres_per_unit());
                    let _ = writeln!(
                        out,
                        "{pad}\tEnd Site\n{pad}\t{{\n{pad}\t\tOFFSET {}\n{pad}\t}}",
                        triple(&tail, decimals)
                    );
                }
            }
            Step::Close(d) => {
                let _ = writeln!(out, "{}}}", "\t".repeat(d));
            }
        }
    }
    if extra_root.is_some() {
        out.push_str("}\n");
    }

    let _ = write!(
        out,
        "MOTION\nFrames: {}\nFrame Time: {:.6}\n",
        motion.frames,
        1.0 / motion.fps
    );
    let rest_rot = rig.rest_world_rotations();
    let mut bvh_world = vec![rotation::IDENTITY; n];
    for t in 0..motion.frames {
        let world = motion.world_frame(t);
        let pos = motion.positions_frame(t);
        for b in 0..n {
            bvh_world[b] = rotation::mul(&world[b], &rotation::transpose(&rest_rot[b]));
        }
        if extra_root.is_some() {
            out.push_str("0 0 0 0 0 0");
        }
        let mut first = extra_root.is_none();
        for &b in &order {
            let (local, at) = match rig.parent(b) {
                Some(p) => {
                    let to_parent = rotation::transpose(&bvh_world[p]);
                    (
                        rotation::mul(&to_parent, &bvh_world[b]),
                        rotation::apply(&to_parent, &sub(&pos[b], &pos[p])),
                    )
                }
                None => (bvh_world[b], pos[b]),
            };
            if !first {
                out.push(' ');
            }
            first = false;
            if positioned[b] {
                let _ = write!(out, "{} ", triple(&at, decimals));
            }
            let e = rotation::to_euler_zxy_degrees(&local);
            let _ = write!(out, "{:.6} {:.6} {:.6}", e[0], e[1], e[2]);
        }
        out.push('\n');
    }
    Ok(out)
}

const POSITIONS: &str = "Xposition Yposition Zposition";
const ROTATIONS: &str = "Zrotation Xrotation Yrotation";

/// Refuses a motion that does not fit `rig` or holds non-finite values.
fn check(rig: &Rig, m: &RigMotion) -> Result<()> {
    let n = rig.bone_count();
    if m.bones != n {
        return Err(invalid_arg!(
            "the motion is for a rig of {} bones; this rig has {n}",
            m.bones
        ));
    }
    if m.frames == 0 {
        return Err(invalid_arg!("a BVH needs at least one frame"));
    }
    if !(m.fps.is_finite() && m.fps > 0.0) {
        return Err(invalid_arg!(
            "BVH frame rate must be positive, got {}",
            m.fps
        ));
    }
    if m.hips_bone >= n {
        return Err(invalid_arg!(
            "the motion's hips bone {} is not one of the rig's {n} bones",
            m.hips_bone
        ));
    }
    if let Some(&b) = m.moving.iter().find(|&&b| b >= n) {
        return Err(invalid_arg!(
            "the motion moves bone {b}; the rig has {n} bones"
        ));
    }
    let total = m.frames.checked_mul(n);
    for (what, len) in [
        ("world rotations", m.world.len()),
        ("local rotations", m.local.len()),
        ("positions", m.positions.len()),
        ("translations", m.translation.len()),
    ] {
        if Some(len) != total {
            return Err(invalid_arg!(
                "the motion has {len} {what} for {} frames of {n} bones",
                m.frames
            ));
        }
    }
    for (i, (w, p)) in m.world.iter().zip(&m.positions).enumerate() {
        if !(w.iter().flatten().all(|v| v.is_finite()) && p.iter().all(|v| v.is_finite())) {
            return Err(invalid_arg!(
                "frame {}, bone `{}`: the pose is not finite",
                i / n,
                rig.name(i % n)
            ));
        }
    }
    Ok(())
}

/// The rig's names as BVH tokens, refused when two become equal.
fn bvh_names(rig: &Rig) -> Result<Vec<String>> {
    let names: Vec<String> = rig
        .names()
        .iter()
        .map(|s| {
            s.chars()
                .map(|c| {
                    if c.is_whitespace() || c == '{' || c == '}' {
                        '_'
                    } else {
                        c
                    }
                })
                .collect()
        })
        .collect();
    let mut seen = std::collections::HashMap::with_capacity(names.len());
    for (b, name) in names.iter().enumerate() {
        if let Some(a) = seen.insert(name.as_str(), b) {
            return Err(invalid_arg!(
                "bones `{}` and `{}` are both `{name}` in a BVH (whitespace becomes `_`)",
                rig.name(a),
                rig.name(b)
            ));
        }
    }
    Ok(names)
}

/// `root`, or `root_1`, `root_2`, … if a bone has that name.
fn free_name(names: &[String]) -> String {
    let taken = |s: &str| names.iter().any(|n| n == s);
    std::iter::once("root".to_string())
        .chain((1..).map(|k| format!("root_{k}")))
        .find(|s| !taken(s))
        .expect("some name is free")
}

/// Decimals for lengths: a millionth of the rig's rest extent, at least six.
fn length_decimals(rest: &[Vec3]) -> usize {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in rest {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let extent = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max);
    if extent > 0.0 {
        // Half a unit in the last place at most 1e-8 of the extent: FK over a chain of
        // offsets then stays within 1e-6 of it.
        ((-(extent * 1e-8).log10()).ceil() as usize).clamp(6, 12)
    } else {
        6
    }
}

/// A leaf's `End Site`: half its offset, along it; a leaf at its parent's place gets a tail
/// of 5 cm up (Y, BVH's usual up) so readers still make a bone of it.
fn end_site(offset: &Vec3, metres_per_unit: f64) -> Vec3 {
    if rotation::dot(offset, offset) > 0.0 {
        offset.map(|v| 0.5 * v)
    } else {
        [0.0, 0.05 / metres_per_unit, 0.0]
    }
}

fn triple(v: &Vec3, decimals: usize) -> String {
    format!(
        "{:.*} {:.*} {:.*}",
        decimals, v[0], decimals, v[1], decimals, v[2]
    )
}

fn sub(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::bvh::{self, Channel};
    use crate::motion::rotation::Mat3;
    use crate::motion::{Format, Skeleton};
    use crate::retarget::pose::Options;
    use crate::retarget::rig::{BoneSpec, RestTransform, RigSource};
    use crate::retarget::transfer::tests::test_rig;
    use crate::retarget::{gltf_rig, Target};

    /// World positions of every joint of a parsed BVH in every frame, by forward kinematics:
    /// a joint's rotation is its rotation channels' product in the listed order, its position
    /// relative to its parent its position channels when it has them (they replace the
    /// OFFSET, as Blender's importer reads them), else its OFFSET.
    fn bvh_positions(file: &bvh::BvhMotion) -> Vec<Vec<Vec3>> {
        let joints = file.joints();
        (0..file.frames())
            .map(|t| {
                let row = file.frame(t).unwrap();
                let mut k = 0;
                let mut world = vec![rotation::IDENTITY; joints.len()];
                let mut pos = vec![[0.0; 3]; joints.len()];
                for (j, joint) in joints.iter().enumerate() {
                    let mut r = rotation::IDENTITY;
                    let mut at = joint.offset();
                    for c in joint.channels() {
                        let v = row[k];
                        k += 1;
                        if c.is_rotation() {
                            let mut axis = [0.0; 3];
                            axis[c.axis()] = 1.0;
                            r = rotation::mul(&r, &rotation::axis_angle(&axis, v.to_radians()));
                        } else {
                            at[c.axis()] = v;
                        }
                    }
                    match joint.parent() {
                        Some(p) => {
                            world[j] = rotation::mul(&world[p], &r);
                            pos[j] = rotation::add(&pos[p], &rotation::apply(&world[p], &at));
                        }
                        None => {
                            world[j] = r;
                            pos[j] = at;
                        }
                    }
                }
                pos
            })
            .collect()
    }

    /// The largest distance between the BVH's joints and the motion's bone positions over
    /// all frames, over the rig's rest extent; and the file.
    fn reproduction_error(rig: &Rig, motion: &RigMotion) -> (f64, bvh::BvhMotion) {
        let text = to_string(rig, motion).unwrap();
        let file = bvh::parse(&text).unwrap();
        assert_eq!(file.frames(), motion.frames);
        let fk = bvh_positions(&file);
        let index: Vec<usize> = (0..rig.bone_count())
            .map(|b| {
                let name = rig.name(b).replace(char::is_whitespace, "_");
                file.joints()
                    .iter()
                    .position(|j| j.name() == name)
                    .unwrap_or_else(|| panic!("no joint `{name}`"))
            })
            .collect();
        let rest = rig.rest_world_positions();
        let extent = rest
            .iter()
            .flat_map(|a| rest.iter().map(move |b| dist(a, b)))
            .fold(0.0, f64::max);
        let mut worst = 0.0f64;
        for (t, frame) in fk.iter().enumerate() {
            for (b, &j) in index.iter().enumerate() {
                worst = worst.max(dist(&frame[j], &motion.positions_frame(t)[b]));
            }
        }
        (worst / extent, file)
    }

    fn dist(a: &Vec3, b: &Vec3) -> f64 {
        let d = sub(a, b);
        rotation::dot(&d, &d).sqrt()
    }

    fn clip(target: &Target, frames: usize) -> RigMotion {
        let poses = crate::motion::testutil::sinusoid_motion(Format::Smpl24Rot6d, frames);
        target.motion(&poses, 30.0, &Options::default()).unwrap()
    }

    #[test]
    fn forward_kinematics_of_the_file_gives_the_rigs_posed_positions() {
        // The unlike rig: centimetres, Z up, a `root` bone above the pelvis (so the hips are
        // not the BVH root and carry position channels of their own), a roll on every bone.
        let (rig, _, _) = test_rig(5);
        let target = Target::auto(Skeleton::smpl24(), rig).unwrap();
        let motion = clip(&target, 30);
        let rig = target.rig();
        let (err, file) = reproduction_error(rig, &motion);
        assert!(err < 1e-6, "joints off by {err} of the rig's size");
        // The hierarchy is the rig's: same names, same parents, OFFSETs the rest offsets.
        assert_eq!(file.joints().len(), rig.bone_count());
        for j in file.joints() {
            let b = rig.find(j.name()).unwrap();
            let parent = j
                .parent()
                .map(|p| rig.find(file.joints()[p].name()).unwrap());
            assert_eq!(parent, rig.parent(b), "{}", j.name());
            let rest = rig.rest_world_positions();
            let want = match parent {
                Some(p) => sub(&rest[b], &rest[p]),
                None => rest[b],
            };
            assert!(dist(&j.offset(), &want) < 1e-5, "{}", j.name());
            let positions = j.channels().iter().filter(|c| !c.is_rotation()).count();
            let moves = motion.moving.contains(&b) || parent.is_none();
            assert_eq!(positions, if moves { 3 } else { 0 }, "{}", j.name());
        }
        // The pose really moves: the pelvis travels and the limbs turn.
        let hips = motion.hips_bone;
        let travel = dist(
            &motion.positions_frame(0)[hips],
            &motion.positions_frame(29)[hips],
        );
        assert!(travel > 1.0, "{travel} cm");
        assert_eq!(file.frame_time(), 0.033333);
        let first = file.frame(0).unwrap();
        assert_eq!(first.len(), file.channel_count());
        assert_eq!(
            file.joints()[0].channels(),
            &[
                Channel::Xposition,
                Channel::Yposition,
                Channel::Zposition,
                Channel::Zrotation,
                Channel::Xrotation,
                Channel::Yrotation
            ]
        );
    }

    /// The committed test rig `name` (made by tools/make_test_rigs.py) read, mapped, driven
    /// and written: every bone of the BVH where the retarget puts it.
    fn fixture_rig_written(name: &str) {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/rigs");
        let bytes = std::fs::read(dir.join(name)).unwrap();
        let rig = gltf_rig::read(&bytes, None).unwrap_or_else(|e| panic!("{name}: {e}"));
        let target =
            Target::auto(Skeleton::smpl24(), rig).unwrap_or_else(|e| panic!("{name}: {e}"));
        let motion = clip(&target, 20);
        let (err, _) = reproduction_error(target.rig(), &motion);
        assert!(err < 1e-6, "{name}: joints off by {err} of the rig's size");
    }

    #[test]
    fn the_fixture_rigs_are_driven_and_written() {
        // Centimetres under a turned and scaled `Armature` node; a Z-up bind pose with a
        // `root` bone above the pelvis (the pelvis gets position channels of its own); a
        // child with no neck and no shoulders, facing -Z.
        for name in ["mixamo.glb", "apose.glb", "child.glb"] {
            fixture_rig_written(name);
        }
    }

    /// A rig of three bones in metres with two roots (as a deform-only export leaves a thigh
    /// whose parent was not a deform bone).
    fn two_root_rig() -> Rig {
        let bone = |name: &str, parent, t: Vec3| BoneSpec {
            name: name.to_string(),
            parent,
            rest: RestTransform {
                translation: t,
                rotation: rotation::axis_angle(&[0.3, 1.0, 0.2], 0.7),
                scale: [1.0; 3],
            },
        };
        Rig::new(
            vec![
                bone("hips", None, [0.0, 1.0, 0.0]),
                bone("spine bone", Some(0), [0.0, 0.3, 0.0]),
                bone("thigh", None, [0.1, 0.95, 0.0]),
            ],
            1.0,
            RigSource::Code,
        )
        .unwrap()
    }

    /// A hand-made motion for [`two_root_rig`]: every bone turning, the roots travelling.
    fn two_root_motion(rig: &Rig, frames: usize) -> RigMotion {
        let n = rig.bone_count();
        let rest = rig.rest_world_rotations();
        let (mut world, mut local, mut positions, mut hips) = (vec![], vec![], vec![], vec![]);
        let mut translation = vec![];
        for t in 0..frames {
            let turn =
                |b: usize| rotation::axis_angle(&[1.0, b as f64, 0.5], 0.1 * t as f64 + b as f64);
            let g: Vec<Mat3> = (0..n).map(|b| rotation::mul(&turn(b), &rest[b])).collect();
            let root = [0.01 * t as f64, 1.0, 0.02 * t as f64];
            let spine = rotation::apply(&g[0], &rig.rest()[1].translation);
            let p = vec![
                root,
                rotation::add(&root, &spine),
                rotation::add(&root, &[0.1, -0.05, 0.0]),
            ];
            local.extend([
                g[0],
                rotation::mul(&rotation::transpose(&g[0]), &g[1]),
                g[2],
            ]);
            translation.extend([
                root,
                rig.rest()[1].translation,
                rotation::apply(&rotation::transpose(&g[0]), &sub(&p[2], &root)),
            ]);
            world.extend(g);
            positions.extend(p);
            hips.push(root);
        }
        RigMotion {
            fps: 20.0,
            frames,
            bones: n,
            hips_bone: 0,
            local,
            world,
            positions,
            translation,
            moving: vec![0],
            hips,
        }
    }

    #[test]
    fn several_roots_hang_from_one_still_root() {
        let rig = two_root_rig();
        let motion = two_root_motion(&rig, 12);
        let (err, file) = reproduction_error(&rig, &motion);
        assert!(err < 1e-6, "joints off by {err} of the rig's size");
        let names: Vec<&str> = file.joints().iter().map(|j| j.name()).collect();
        assert_eq!(names, ["root", "hips", "spine_bone", "thigh"]);
        assert!((0..12).all(|t| file.frame(t).unwrap()[..6] == [0.0; 6]));
        // A rig 35 cm tall in metres: nine decimals (a millionth of its size is 0.35 µm).
        let text = to_string(&rig, &motion).unwrap();
        assert!(
            text.contains("\tOFFSET 0.000000000 1.000000000 0.000000000\n"),
            "{text}"
        );
    }

    #[test]
    fn motions_that_do_not_fit_are_refused() {
        let rig = two_root_rig();
        let good = two_root_motion(&rig, 4);
        let refused = |m: &RigMotion, want: &str| {
            let e = to_string(&rig, m).unwrap_err().to_string();
            assert!(e.contains(want), "{e}");
        };
        let mut m = good.clone();
        m.bones = 4;
        refused(&m, "rig of 4 bones");
        let mut m = good.clone();
        m.positions.pop();
        refused(&m, "11 positions");
        let mut m = good.clone();
        m.world.truncate(3);
        refused(&m, "3 world rotations");
        let mut m = good.clone();
        m.world[7][1][2] = f64::NAN;
        refused(&m, "frame 2, bone `spine bone`");
        let mut m = good.clone();
        m.positions[11][0] = f64::INFINITY;
        refused(&m, "frame 3, bone `thigh`");
        let mut m = good.clone();
        m.fps = 0.0;
        refused(&m, "frame rate");
        let mut m = good.clone();
        m.hips_bone = 3;
        refused(&m, "hips bone 3");
        let mut m = good.clone();
        m.moving.push(3);
        refused(&m, "moves bone 3");
        let mut m = good.clone();
        m.translation.pop();
        refused(&m, "11 translations");
        let mut m = good.clone();
        (m.frames, m.world, m.local, m.positions, m.translation) =
            (0, vec![], vec![], vec![], vec![]);
        refused(&m, "at least one frame");
        // Names equal once whitespace is replaced.
        let bones = ["a b", "a_b"]
            .iter()
            .enumerate()
            .map(|(i, name)| BoneSpec {
                name: name.to_string(),
                parent: i.checked_sub(1),
                rest: RestTransform::offset([0.0, 1.0, 0.0]),
            })
            .collect();
        let rig2 = Rig::new(bones, 1.0, RigSource::Code).unwrap();
        let mut m = good.clone();
        m.bones = 2;
        (m.world, m.local, m.positions, m.translation) = (
            m.world[..8].to_vec(),
            m.local[..8].to_vec(),
            m.positions[..8].to_vec(),
            m.translation[..8].to_vec(),
        );
        let e = to_string(&rig2, &m).unwrap_err().to_string();
        assert!(e.contains("`a b` and `a_b`"), "{e}");
    }
}
