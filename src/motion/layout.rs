//! Pose layouts: what a caller can read per frame, each with a stable integer value (the C ABI's
//! enum), a name, and a documented shape. Quaternion layouts name their component order.

use std::fmt;
use std::str::FromStr;

use super::format::Format;
use crate::error::{invalid_arg, Error, Result};

/// One per-frame quantity, laid out frame-major as `f32`. `J` is the format's joint count
/// (smpl24_6d 24, humanml263 22). Rotations are parent-relative ("local") or world ("global");
/// both follow the skeleton's hierarchy, so `global(j) = global(parent) · local(j)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum Layout {
    /// `[frames, 3]` the root joint's (pelvis's) world position.
    RootTranslation = 0,
    /// `[frames, J, 4]` local rotations as quaternions, x y z w.
    LocalQuatXyzw = 1,
    /// `[frames, J, 4]` local rotations as quaternions, w x y z.
    LocalQuatWxyz = 2,
    /// `[frames, J, 3, 3]` local rotation matrices, row-major, acting on column vectors.
    LocalMatrix = 3,
    /// `[frames, J, 6]` local rotations as the first two ROWS of the matrix,
    /// `[R00,R01,R02,R10,R11,R12]` (pytorch3d's `matrix_to_rotation_6d`, FLAME's own 6D).
    Local6d = 4,
    /// `[frames, J, 3]` world joint positions.
    GlobalPositions = 5,
    /// `[frames, J, 4]` world rotations as quaternions, x y z w.
    GlobalQuatXyzw = 6,
    /// `[frames, J, 4]` world rotations as quaternions, w x y z.
    GlobalQuatWxyz = 7,
    /// `[frames, 4]` foot contacts in the order left ankle, left foot, right ankle, right foot:
    /// humanml263's as the model gives them (≈0 or 1; threshold at 0.5), smpl24_6d's detected
    /// from height and speed (0 or 1, [`super::ContactParams`]); after a finish, the contacts it
    /// used (0 or 1).
    FootContacts = 8,
    /// `[frames, 3]` the world position of the `root` bone on the ground under the pelvis that
    /// [`super::RootMotion::Separate`] adds; an error for poses without one.
    RootBone = 9,
}

/// The component order of a quaternion written out.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum QuatOrder {
    /// x y z w: Unity, Unreal, ROS, glTF.
    Xyzw,
    /// w x y z: FLAME's official output, USD, Isaac Sim.
    Wxyz,
}

impl Layout {
    /// Every layout, in integer order.
    pub const ALL: [Layout; 10] = [
        Layout::RootTranslation,
        Layout::LocalQuatXyzw,
        Layout::LocalQuatWxyz,
        Layout::LocalMatrix,
        Layout::Local6d,
        Layout::GlobalPositions,
        Layout::GlobalQuatXyzw,
        Layout::GlobalQuatWxyz,
        Layout::FootContacts,
        Layout::RootBone,
    ];

    /// The snake-case name (`root_translation`, `local_quat_xyzw`, …), as `FromStr` takes it.
    pub fn name(self) -> &'static str {
        match self {
            Layout::RootTranslation => "root_translation",
            Layout::LocalQuatXyzw => "local_quat_xyzw",
            Layout::LocalQuatWxyz => "local_quat_wxyz",
            Layout::LocalMatrix => "local_matrix",
            Layout::Local6d => "local_6d",
            Layout::GlobalPositions => "global_positions",
            Layout::GlobalQuatXyzw => "global_quat_xyzw",
            Layout::GlobalQuatWxyz => "global_quat_wxyz",
            Layout::FootContacts => "foot_contacts",
            Layout::RootBone => "root_bone",
        }
    }

    /// The layout with integer value `v` (the C ABI's enum).
    pub fn from_u32(v: u32) -> Result<Layout> {
        Layout::ALL
            .get(v as usize)
            .copied()
            .ok_or_else(|| invalid_arg!("unknown pose layout {v}"))
    }

    /// The shape of one frame (`[J, 4]`, `[3]`, …) for `format`, or an error when the format
    /// does not have this layout.
    pub fn frame_shape(self, format: Format) -> Result<Vec<usize>> {
        let j = format.skeleton().joint_count();
        Ok(match self {
            Layout::RootTranslation => vec![3],
            Layout::LocalQuatXyzw
            | Layout::LocalQuatWxyz
            | Layout::GlobalQuatXyzw
            | Layout::GlobalQuatWxyz => {
                vec![j, 4]
            }
            Layout::LocalMatrix => vec![j, 3, 3],
            Layout::Local6d => vec![j, 6],
            Layout::GlobalPositions => vec![j, 3],
            Layout::FootContacts => vec![4],
            Layout::RootBone => vec![3],
        })
    }

    /// The order of a quaternion layout, `None` for the others.
    pub fn quat_order(self) -> Option<QuatOrder> {
        match self {
            Layout::LocalQuatXyzw | Layout::GlobalQuatXyzw => Some(QuatOrder::Xyzw),
            Layout::LocalQuatWxyz | Layout::GlobalQuatWxyz => Some(QuatOrder::Wxyz),
            _ => None,
        }
    }
}

impl QuatOrder {
    /// `xyzw` or `wxyz`, as the JSON export's `rotation_quat_order` field writes it.
    pub fn name(self) -> &'static str {
        match self {
            QuatOrder::Xyzw => "xyzw",
            QuatOrder::Wxyz => "wxyz",
        }
    }

    /// Reorders a w-first quaternion.
    pub(crate) fn arrange(self, q: &[f64; 4]) -> [f64; 4] {
        match self {
            QuatOrder::Xyzw => [q[1], q[2], q[3], q[0]],
            QuatOrder::Wxyz => *q,
        }
    }
}

impl FromStr for Layout {
    type Err = Error;
    fn from_str(s: &str) -> Result<Layout> {
        Layout::ALL
            .into_iter()
            .find(|l| l.name() == s)
            .ok_or_else(|| {
                let names: Vec<&str> = Layout::ALL.iter().map(|l| l.name()).collect();
                invalid_arg!(
                    "unknown pose layout `{s}` (expected one of {})",
                    names.join(", ")
                )
            })
    }
}

impl FromStr for QuatOrder {
    type Err = Error;
    fn from_str(s: &str) -> Result<QuatOrder> {
        match s {
            "xyzw" => Ok(QuatOrder::Xyzw),
            "wxyz" => Ok(QuatOrder::Wxyz),
            _ => Err(invalid_arg!(
                "unknown quaternion order `{s}` (expected xyzw or wxyz)"
            )),
        }
    }
}

impl fmt::Display for Layout {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn integers_names_and_shapes_are_stable() {
        for (i, l) in Layout::ALL.into_iter().enumerate() {
            assert_eq!(l as u32, i as u32);
            assert_eq!(Layout::from_u32(i as u32).unwrap(), l);
            assert_eq!(l.name().parse::<Layout>().unwrap(), l);
        }
        assert!(Layout::from_u32(10).is_err());
        assert_eq!(
            Layout::LocalQuatXyzw
                .frame_shape(Format::Smpl24Rot6d)
                .unwrap(),
            vec![24, 4]
        );
        assert_eq!(
            Layout::LocalMatrix.frame_shape(Format::HumanMl263).unwrap(),
            vec![22, 3, 3]
        );
        assert_eq!(
            Layout::FootContacts
                .frame_shape(Format::HumanMl263)
                .unwrap(),
            vec![4]
        );
        assert_eq!(
            Layout::FootContacts
                .frame_shape(Format::Smpl24Rot6d)
                .unwrap(),
            vec![4]
        );
        assert_eq!(
            QuatOrder::Xyzw.arrange(&[1.0, 2.0, 3.0, 4.0]),
            [2.0, 3.0, 4.0, 1.0]
        );
        assert!("zyxw".parse::<QuatOrder>().is_err());
    }
}
