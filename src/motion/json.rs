//! JSON export in the spirit of FLAME's official output for Unity (REFERENCE 1.13: translation
//! `[L,3]` and rotation_quat `[L,24,4]`), made self-describing: the convention, the quaternion
//! order, the skeleton (names, parents, rest offsets) travel with the poses.
//!
//! ```json
//! {"format": "smpl24_6d", "convention": "unity", "handedness": "left", "up": "+y",
//!  "forward": "+z", "left": "-x", "unit": "m", "fps": 20.0, "frames": L,
//!  "joint_names": [...J], "parents": [-1, 0, ...], "offsets": [[x,y,z], ...J],
//!  "translation": [[x,y,z], ...L], "rotation_quat_order": "wxyz",
//!  "rotation_quat": [[[w,x,y,z], ...J], ...L],
//!  "foot_contacts": [[la,lf,ra,rf], ...L], "foot_contact_joints": [...4]}
//! ```
//!
//! `translation` is the root joint's (pelvis's) world position; `rotation_quat` the local
//! (parent-relative) rotations; `offsets` the rest offsets (joint − parent, row 0 the root's rest
//! position), so `global(j) = global(parent)·local(j)`, `p(j) = p(parent) + global(parent)·offset(j)`
//! reproduces the poses. The foot-contact fields appear only for formats that have them.

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
        foot_contacts: poses
            .foot_contacts()
            .map(|c| c.iter().map(narrow).collect()),
        foot_contact_joints: poses
            .foot_contacts()
            .map(|_| ["left_ankle", "left_foot", "right_ankle", "right_foot"]),
    };
    serde_json::to_string(&doc)
        .map_err(|e| invalid_arg!("cannot serialise the motion as JSON: {e}"))
}
