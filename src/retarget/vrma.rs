//! A libflame clip as a VRM Animation (`.vrma`: a GLB with the root extension
//! `VRMC_vrm_animation`, specVersion `1.0`; vrm-c/vrm-specification,
//! `specification/VRMC_vrm_animation-1.0/README.md`) ([`to_glb`]), which three-vrm
//! (`@pixiv/three-vrm-animation`), UniVRM and other VRM players put on any VRM avatar.
//!
//! - **Skeleton.** The 22 humanoid bones libflame drives ([`HumanBone`]: no eyes, jaw or
//!   fingers), one node each, named and mapped (`humanoid.humanBones`, name → `{node}`) by
//!   their VRM names, in the VRM T-pose (`specification/VRMC_vrm-1.0/tpose.md`): facing +Z,
//!   Y up, metres, arms horizontal along ±X (left +X), legs and spine vertical, symmetric about
//!   X = 0, the lowest joint (the toes) on y = 0; every rest rotation the identity. Bone
//!   lengths are SMPL's (`Skeleton::smpl24` rest offsets, left and right averaged): spine,
//!   neck, head, legs and arms keep their lengths and are turned straight; the hips' and
//!   collars' offsets keep their sideways and vertical parts (front-back dropped); the feet keep
//!   SMPL's pitch (toes below the ankles), in the sagittal plane.
//! - **Rotations.** `poses` retargeted onto that T-pose rig by libflame's own [`Target`] with
//!   no IK ([`Options`] `feet: false, hands: false`): SMPL's rest is first turned onto the
//!   T-pose (the retarget pose of [`super::Transfer`]), so a player applying the file
//!   rest-relatively to any avatar gets plain rest-relative rotations (three-vrm:
//!   `q' = P · q · W⁻¹` with the file's rest world rotations, identities here). Rotation
//!   channels on all 22 bones, translation on the hips only (the hips' world position, metres:
//!   players scale it by their avatar's hips height over this file's, the rest hips' `y`).
//! - **Time.** LINEAR samplers with times `frame / fps` at the poses' own rate (the
//!   specification suggests 30 fps; resample first for that).

use serde_json::{json, Map, Value};

use super::bonemap::HumanBone;
use super::gltf_out::{quaternion_track, Clip, File};
use super::pose::Options;
use super::rig::{BoneSpec, RestTransform, Rig, RigSource};
use super::target::Target;
use crate::error::{invalid_arg, Result};
use crate::motion::rotation::{Vec3, IDENTITY};
use crate::motion::{Poses, Skeleton};

/// `poses` at `fps` as a `.vrma` GLB whose animation is named `name` (module doc).
pub fn to_glb(poses: &Poses, fps: f64, name: &str) -> Result<Vec<u8>> {
    if !(fps.is_finite() && fps > 0.0) {
        return Err(invalid_arg!(
            "a VRM Animation's frame rate must be positive, got {fps}"
        ));
    }
    if poses.frames() == 0 {
        return Err(invalid_arg!("a VRM Animation needs at least one frame"));
    }
    let rig = t_pose_rig()?;
    let target = Target::auto(poses.format().skeleton(), rig)?;
    let motion = target.motion(
        poses,
        fps,
        &Options {
            feet: false,
            hands: false,
        },
    )?;
    let rig = target.rig();
    let n = rig.bone_count();
    let frames = motion.frames;
    let finite = motion
        .local
        .iter()
        .flatten()
        .flatten()
        .all(|v| v.is_finite())
        && motion.hips.iter().flatten().all(|v| v.is_finite());
    if !finite {
        return Err(invalid_arg!(
            "the poses have a NaN or infinite rotation or root"
        ));
    }

    // Node b is bone b (stored parents first: the hips, node 0, is the one root).
    let mut nodes = Vec::with_capacity(n);
    let mut human = Map::new();
    for b in 0..n {
        let mut node = json!({
            "name": rig.name(b),
            "translation": rig.rest()[b].translation.map(|v| v as f32),
        });
        let children: Vec<usize> = rig.children(b).collect();
        if !children.is_empty() {
            node["children"] = json!(children);
        }
        nodes.push(node);
        human.insert(rig.name(b).to_string(), json!({ "node": b }));
    }
    let version = env!("CARGO_PKG_VERSION");
    let doc = json!({
        "asset": { "version": "2.0", "generator": format!("libflame {version}") },
        "extensionsUsed": ["VRMC_vrm_animation"],
        "extensions": {
            "VRMC_vrm_animation": {
                "specVersion": "1.0",
                "humanoid": { "humanBones": human },
            }
        },
        "scene": 0,
        "scenes": [{ "nodes": [0] }],
        "nodes": nodes,
    });
    let Value::Object(doc) = doc else {
        unreachable!("json! of an object literal")
    };
    let times: Vec<f32> = (0..frames).map(|t| (t as f64 / fps) as f32).collect();
    let mut clip = Clip::new(name, &times)?;
    for b in 0..n {
        let track = (0..frames).map(|t| motion.local_frame(t)[b]);
        clip.channel(b, "rotation", &quaternion_track(track))?;
    }
    let hips: Vec<f32> = motion.hips.iter().flatten().map(|&v| v as f32).collect();
    clip.channel(motion.hips_bone, "translation", &hips)?;
    let mut file = File::new_glb(doc);
    file.append(clip)?;
    file.into_bytes()
}

/// The VRM T-pose rig of SMPL's bone lengths (module doc), bones named and declared by their
/// VRM humanBone names.
pub fn t_pose_rig() -> Result<Rig> {
    let skel = Skeleton::smpl24();
    let joint = |h: HumanBone| -> Result<usize> {
        skel.joint_names()
            .iter()
            .position(|&j| j == h.smpl_joint())
            .ok_or_else(|| invalid_arg!("SMPL-24 has no joint `{}`", h.smpl_joint()))
    };
    let offset = |h: HumanBone| -> Result<Vec3> { Ok(skel.rest_offsets()[joint(h)?]) };
    let length = |v: Vec3| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let mut bones = Vec::with_capacity(HumanBone::ALL.len());
    let mut declared = Vec::with_capacity(HumanBone::ALL.len());
    for h in HumanBone::ALL {
        use HumanBone::*;
        // Left and right averaged (the left side's offset, x mirrored from the right's): the
        // T-pose is symmetric about X = 0.
        let o = match mirror(h) {
            Some(other) => {
                let (a, b) = (offset(h)?, offset(other)?);
                let sign = if a[0] >= 0.0 { 1.0 } else { -1.0 };
                [
                    sign * (a[0].abs() + b[0].abs()) / 2.0,
                    (a[1] + b[1]) / 2.0,
                    (a[2] + b[2]) / 2.0,
                ]
            }
            None => offset(h)?,
        };
        let side = if o[0] >= 0.0 { 1.0 } else { -1.0 };
        let t = match h {
            Hips => [0.0; 3],
            Spine | Chest | UpperChest | Neck | Head => [0.0, length(o), 0.0],
            LeftUpperLeg | RightUpperLeg | LeftShoulder | RightShoulder => [o[0], o[1], 0.0],
            LeftLowerLeg | RightLowerLeg | LeftFoot | RightFoot => [0.0, -length(o), 0.0],
            LeftToes | RightToes => [0.0, o[1], o[2]],
            LeftUpperArm | RightUpperArm | LeftLowerArm | RightLowerArm | LeftHand | RightHand => {
                [side * length(o), 0.0, 0.0]
            }
        };
        declared.push((h.name().to_string(), h.index()));
        bones.push(BoneSpec {
            name: h.name().to_string(),
            parent: h.parent().map(HumanBone::index),
            rest: RestTransform {
                translation: t,
                rotation: IDENTITY,
                scale: [1.0; 3],
            },
        });
    }
    // The hips lifted so that the lowest joint is on the floor.
    let mut y = vec![0.0; bones.len()];
    for b in 0..bones.len() {
        y[b] = bones[b].parent.map_or(0.0, |p| y[p]) + bones[b].rest.translation[1];
    }
    let lowest = y.iter().copied().fold(f64::INFINITY, f64::min);
    bones[HumanBone::Hips.index()].rest.translation[1] = -lowest;
    Rig::new(bones, 1.0, RigSource::Code)?.with_declared(declared)
}

/// The other side's bone (`None` for the spine).
fn mirror(h: HumanBone) -> Option<HumanBone> {
    let name = h.name();
    let other = if let Some(rest) = name.strip_prefix("left") {
        format!("right{rest}")
    } else if let Some(rest) = name.strip_prefix("right") {
        format!("left{rest}")
    } else {
        return None;
    };
    HumanBone::from_name(&other)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::rotation;

    #[test]
    fn the_t_pose_rig_is_symmetric_upright_and_on_the_floor() {
        let rig = t_pose_rig().unwrap();
        let pos = rig.rest_world_positions();
        let at = |h: HumanBone| pos[rig.find(h.name()).unwrap()];
        let lowest = pos.iter().map(|p| p[1]).fold(f64::INFINITY, f64::min);
        assert!(lowest.abs() < 1e-12, "{lowest}");
        for h in HumanBone::ALL {
            let (a, b) = (at(h), at(mirror(h).unwrap_or(h)));
            let same = (a[0] + b[0]).abs() + (a[1] - b[1]).abs() + (a[2] - b[2]).abs();
            assert!(same < 1e-12, "{h:?}: {a:?} and {b:?}");
        }
        // Arms along ±X at one height, legs straight down under the hips' sockets.
        let (s, w) = (at(HumanBone::LeftUpperArm), at(HumanBone::LeftHand));
        assert!(w[0] > s[0] + 0.4 && (w[1] - s[1]).abs() + (w[2] - s[2]).abs() < 1e-12);
        let (hip, ankle) = (at(HumanBone::RightUpperLeg), at(HumanBone::RightFoot));
        assert!((hip[0] - ankle[0]).abs() + (hip[2] - ankle[2]).abs() < 1e-12 && hip[0] < 0.0);
        // The SMPL upper arm's length is kept.
        let smpl = Skeleton::smpl24().rest_offsets()[18];
        let len = rotation::dot(&smpl, &smpl).sqrt();
        let got = at(HumanBone::LeftLowerArm)[0] - s[0];
        assert!((got - len).abs() < 0.01, "{got} vs {len}");
    }
}
