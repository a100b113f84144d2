//! JSON export in the spirit of FLAME's official output for Unity (kakaobrain/flame
//! `t2m_sample.py`; docs/official/flame.md#json-export: translation
//! `[L,3]` and rotation_quat `[L,24,4]`), made self-describing: the convention, the quaternion
//! order, the skeleton (names, parents, rest offsets) travel with the poses.
//!
//! ```json
//! {"format": "smpl24_6d", "convention": "unity", "handedness": "left", "up": "+y",
//!  "forward": "+z", "left": "-x", "unit": "m", "fps": 20.0, "frames": L,
//!  "joint_names": [...J], "parents": [-1, 0, ...], "offsets": [[x,y,z], ...J],
//!  "translation": [[x,y,z], ...L], "rotation_quat_order": "wxyz",
//!  "rotation_quat": [[[w,x,y,z], ...J], ...L],
//!  "foot_contacts": [[la,lf,ra,rf], ...L], "foot_contact_joints": [...4],
//!  "root_bone": "root", "root_bone_translation": [[x,y,z], ...L]}
//! ```
//!
//! `translation` is the root joint's (pelvis's) world position; `rotation_quat` the local
//! (parent-relative) rotations; `offsets` the rest offsets (joint − parent, row 0 the root's rest
//! position), so `global(j) = global(parent)·local(j)`, `p(j) = p(parent) + global(parent)·offset(j)`
//! reproduces the poses. The foot-contact fields appear when the poses carry contacts
//! (humanml263's own, or the finished ones of either format), `foot_contact_joints` naming the
//! four joints in the skeleton's names. The root-bone fields appear when the root motion was
//! moved to a root bone ([`super::RootMotion::Separate`]): `root_bone_translation` is the
//! bone's position (on the ground under the pelvis), and `translation` is then relative to it
//! (the bone has no rotation: the pelvis's world position is the sum of the two).

use serde::Serialize;

use super::convention::{Change, Convention};
use super::layout::QuatOrder;
use super::poses::Poses;
use crate::error::{invalid_arg, Result};

#[derive(Serialize)]
struct Document<'a> {
    format: &'a str,
    convention: &'a str,
    handedness: &'a str,
    up: &'a str,
    forward: &'a str,
    left: &'a str,
    unit: &'a str,
    fps: f32,
    frames: usize,
    joint_names: &'a [&'a str],
    parents: &'a [i32],
    offsets: Vec<[f32; 3]>,
    translation: Vec<[f32; 3]>,
    rotation_quat_order: &'a str,
    rotation_quat: Vec<Vec<[f32; 4]>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    foot_contacts: Option<Vec<[f32; 4]>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    foot_contact_joints: Option<[&'a str; 4]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    root_bone: Option<&'a str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    root_bone_translation: Option<Vec<[f32; 3]>>,
}

fn narrow<const N: usize>(v: &[f64; N]) -> [f32; N] {
    v.map(|x| x as f32)
}

/// The JSON text of `poses` in `convention`, quaternions in `order`.
pub fn to_string(
    poses: &Poses,
    convention: Convention,
    fps: f32,
    order: QuatOrder,
) -> Result<String> {
    if !(fps.is_finite() && fps > 0.0) {
        return Err(invalid_arg!("JSON frame rate must be positive, got {fps}"));
    }
    let format = poses.format();
    let skel = format.skeleton();
    let frame = convention.frame(format);
    let ch = Change::new(format, convention);
    let joints = skel.joint_count();
    let quats = poses.quaternions(&poses.local_rotations(convention));
    let frames = poses.frames();
    let contacts = (poses.contacts.len() == frames && frames > 0).then_some(&poses.contacts);
    let bone = (!poses.root_bone.is_empty()).then_some(&poses.root_bone);
    if let Some(b) = bone {
        if b.len() != frames {
            return Err(invalid_arg!(
                "the root bone track has {} entries for {frames} frames",
                b.len()
            ));
        }
    }
    let names = skel.joint_names();
    let doc = Document {
        format: format.name(),
        convention: convention.name(),
        handedness: frame.handedness().name(),
        up: frame.up.name(),
        forward: frame.forward.name(),
        left: frame.left.name(),
        unit: frame.unit.symbol(),
        fps,
        frames: poses.frames(),
        joint_names: skel.joint_names(),
        parents: skel.parents(),
        offsets: skel
            .rest_offsets()
            .iter()
            .map(|o| narrow(&ch.offset(o)))
            .collect(),
        translation: poses
            .root_translation(convention)
            .iter()
            .map(narrow)
            .collect(),
        rotation_quat_order: order.name(),
        rotation_quat: quats
            .chunks(joints)
            .map(|f| f.iter().map(|q| narrow(&order.arrange(q))).collect())
            .collect(),
        foot_contacts: contacts.map(|c| c.iter().map(narrow).collect()),
        // Left ankle, left foot, right ankle, right foot: joints 7, 10, 8, 11 of both skeletons.
        foot_contact_joints: contacts.map(|_| [7, 10, 8, 11].map(|j| names[j])),
        root_bone: bone.map(|_| super::bvh::ROOT_BONE),
        root_bone_translation: bone.map(|b| b.iter().map(|p| narrow(&ch.position(p))).collect()),
    };
    serde_json::to_string(&doc)
        .map_err(|e| invalid_arg!("cannot serialise the motion as JSON: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::{root_motion, Format, ReadOptions, RootMotion};
    use serde_json::Value;

    #[test]
    fn root_bone_and_contacts_are_fields_when_present() {
        let x: Vec<f32> = (0..2 * 147).map(|i| (i as f32 * 0.37).sin()).collect();
        let keep = Poses::decode(Format::Smpl24Rot6d, &x, 2, &ReadOptions::default()).unwrap();
        let doc = |p: &Poses| -> Value {
            serde_json::from_str(&to_string(p, Convention::Unreal, 30.0, QuatOrder::Wxyz).unwrap())
                .unwrap()
        };
        let plain = doc(&keep);
        for field in [
            "foot_contacts",
            "foot_contact_joints",
            "root_bone",
            "root_bone_translation",
        ] {
            assert!(plain.get(field).is_none(), "{field}");
        }
        let mut sep = keep.clone();
        root_motion::apply(&mut sep, RootMotion::Separate, false);
        sep.contacts = vec![[1.0, 0.0, 0.0, 1.0], [0.0; 4]];
        let d = doc(&sep);
        assert_eq!(d["root_bone"], "root");
        assert_eq!(
            d["foot_contact_joints"],
            serde_json::json!(["L_Ankle", "L_Foot", "R_Ankle", "R_Foot"])
        );
        assert_eq!(
            d["foot_contacts"][0],
            serde_json::json!([1.0, 0.0, 0.0, 1.0])
        );
        // Unreal: Z up, centimetres. The bone is on the ground and bone + translation is the
        // pelvis's world position of the clip with its root motion kept.
        for t in 0..2 {
            let (b, tr, k) = (
                &d["root_bone_translation"][t],
                &d["translation"][t],
                &plain["translation"][t],
            );
            assert_eq!(b[2], 0.0);
            for i in 0..3 {
                let sum = b[i].as_f64().unwrap() + tr[i].as_f64().unwrap();
                assert!((sum - k[i].as_f64().unwrap()).abs() < 1e-4, "{t} {i}");
            }
        }
    }
}
