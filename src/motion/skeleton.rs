//! The two skeletons libflame poses — SMPL's 24 joints and HumanML3D's 22 — with joint names,
//! parents and rest offsets, and forward kinematics over any such hierarchy. Rest offsets are in
//! each skeleton's own body frame (Y up, facing +Z, +X the character's left, metres); putting
//! them into an engine's frame is `convention`'s job.

use std::sync::OnceLock;

use super::rotation::{self, Mat3, Vec3};
use crate::error::{invalid_arg, Result};

/// A joint hierarchy: names, parents (every parent listed before its children) and rest offsets.
#[derive(Clone, Debug)]
pub struct Skeleton {
    name: &'static str,
    joint_names: &'static [&'static str],
    parents: &'static [i32],
    offsets: Vec<Vec3>,
}

/// SMPL's joint order (docs/official/smpl.md#joint-order).
const SMPL24_NAMES: [&str; 24] = [
    "Pelvis",
    "L_Hip",
    "R_Hip",
    "Spine1",
    "L_Knee",
    "R_Knee",
    "Spine2",
    "L_Ankle",
    "R_Ankle",
    "Spine3",
    "L_Foot",
    "R_Foot",
    "Neck",
    "L_Collar",
    "R_Collar",
    "Head",
    "L_Shoulder",
    "R_Shoulder",
    "L_Elbow",
    "R_Elbow",
    "L_Wrist",
    "R_Wrist",
    "L_Hand",
    "R_Hand",
];

const SMPL24_PARENTS: [i32; 24] = [
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
];

/// The neutral SMPL template's rest (T-pose) offsets, Stanford-TML/EDGE `vis.py` `smpl_offsets`
/// (docs/official/smpl.md#rest-offsets): row 0 is the pelvis's
/// absolute rest position, the others joint − parent, in metres.
const SMPL24_OFFSETS: [Vec3; 24] = [
    [-0.00179506, -0.22333345, 0.02821913],
    [0.06951974, -0.09140623, -0.00681534],
    [-0.06767048, -0.09052168, -0.00431982],
    [-0.00253286, 0.10896323, -0.02669631],
    [0.03427655, -0.37519860, -0.00449580],
    [-0.03829005, -0.38256901, -0.00885003],
    [0.00548703, 0.13518043, 0.00109247],
    [-0.01359570, -0.39796036, -0.04369333],
    [0.01577377, -0.39841465, -0.04231180],
    [0.00145700, 0.05292223, 0.02542457],
    [0.02635814, -0.05579088, 0.11928840],
    [-0.02537175, -0.04814396, 0.12334795],
    [-0.00277839, 0.21387036, -0.04285703],
    [0.07884474, 0.12174930, -0.03408961],
    [-0.08175919, 0.11883283, -0.03861529],
    [0.00515184, 0.06496961, 0.05134897],
    [0.09097693, 0.03046890, -0.00886815],
    [-0.09601238, 0.03255117, -0.00914307],
    [0.25961225, -0.01277206, -0.02745644],
    [-0.25374196, -0.01332922, -0.02140098],
    [0.24923363, 0.00898603, -0.00117092],
    [-0.25529808, 0.00777229, -0.00555919],
    [0.08404218, -0.00816154, -0.01494537],
    [-0.08462193, -0.00611726, -0.01031508],
];

/// HumanML3D's joint names (`data_loaders/humanml/utils/paramUtil.py`;
/// docs/official/humanml3d.md#joint-names).
const HUMANML22_NAMES: [&str; 22] = [
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
];

/// `t2m_raw_offsets`: unit rest directions (arms hanging down, feet and head pointing forward).
const HUMANML22_DIRECTIONS: [Vec3; 22] = [
    [0.0, 0.0, 0.0],
    [1.0, 0.0, 0.0],
    [-1.0, 0.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, 0.0, 1.0],
    [0.0, 1.0, 0.0],
    [1.0, 0.0, 0.0],
    [-1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
];

/// HumanML3D's kinematic chains (`paramUtil.py`; docs/official/humanml3d.md#kinematic-chains); the
/// order of joints inside a chain is the order
/// in which the official forward kinematics accumulates rotations.
pub(crate) const HUMANML22_CHAINS: [&[usize]; 5] = [
    &[0, 2, 5, 8, 11],
    &[0, 1, 4, 7, 10],
    &[0, 3, 6, 9, 12, 15],
    &[9, 14, 17, 19, 21],
    &[9, 13, 16, 18, 20],
];

impl Skeleton {
    /// SMPL's 24 joints with the neutral template's rest offsets
    /// (docs/official/smpl.md#rest-offsets).
    pub fn smpl24() -> &'static Skeleton {
        static S: OnceLock<Skeleton> = OnceLock::new();
        S.get_or_init(|| Skeleton {
            name: "smpl24",
            joint_names: &SMPL24_NAMES,
            parents: &SMPL24_PARENTS,
            offsets: SMPL24_OFFSETS.to_vec(),
        })
    }

    /// HumanML3D's 22 joints: `t2m_raw_offsets` directions times bone lengths. The dataset's target
    /// skeleton lengths are in no repository (docs/official/humanml3d.md#rotation-features), so
    /// each bone takes the length of the same joint's SMPL-24 rest offset (HumanML3D's joints are
    /// SMPL's first 22, same order). The root's offset is zero, as in `t2m_raw_offsets`.
    pub fn humanml22() -> &'static Skeleton {
        static S: OnceLock<Skeleton> = OnceLock::new();
        S.get_or_init(|| {
            let offsets = HUMANML22_DIRECTIONS
                .iter()
                .zip(&SMPL24_OFFSETS)
                .enumerate()
                .map(|(j, (d, o))| {
                    let len = if j == 0 {
                        0.0
                    } else {
                        rotation::dot(o, o).sqrt()
                    };
                    d.map(|x| x * len)
                })
                .collect();
            Skeleton {
                name: "humanml22",
                joint_names: &HUMANML22_NAMES,
                parents: &SMPL24_PARENTS[..22],
                offsets,
            }
        })
    }

    /// `smpl24` or `humanml22`.
    pub fn name(&self) -> &'static str {
        self.name
    }

    /// Number of joints: 24 for `smpl24`, 22 for `humanml22`.
    pub fn joint_count(&self) -> usize {
        self.joint_names.len()
    }

    /// One name per joint, in index order: SMPL's (`Pelvis`, `L_Hip`, …;
    /// docs/official/smpl.md#joint-order) or HumanML3D's (`pelvis`, `left_hip`, …;
    /// docs/official/humanml3d.md#joint-names). The two orders coincide on the first 22 joints.
    pub fn joint_names(&self) -> &'static [&'static str] {
        self.joint_names
    }

    /// Parent index of every joint, −1 for the root.
    pub fn parents(&self) -> &'static [i32] {
        self.parents
    }

    /// The parent of joint `j`, `None` for the root (and for a joint that does not exist).
    pub fn parent(&self, j: usize) -> Option<usize> {
        self.parents.get(j).and_then(|&p| usize::try_from(p).ok())
    }

    /// Rest offsets in the body frame, metres: joint − parent; row 0 is the root's rest position
    /// (SMPL's rest pelvis, HumanML3D's zero).
    pub fn rest_offsets(&self) -> &[Vec3] {
        &self.offsets
    }

    /// The children of joint `j`, in index order.
    pub fn children(&self, j: usize) -> impl Iterator<Item = usize> + '_ {
        (0..self.joint_count()).filter(move |&c| self.parent(c) == Some(j))
    }
}

/// Forward kinematics of one frame: `world(j) = world(parent) · local(j)` and
/// `p(j) = p(parent) + world(parent) · offset(j)`, with `p(0) = root`. `offsets[0]` is not used:
/// the root's position is given. Fills `positions` and `world` (one entry per joint); every
/// slice must have one entry per joint and every parent must come before its children.
pub fn forward_kinematics(
    parents: &[i32],
    offsets: &[Vec3],
    root: &Vec3,
    local: &[Mat3],
    positions: &mut [Vec3],
    world: &mut [Mat3],
) -> Result<()> {
    let n = parents.len();
    if [offsets.len(), local.len(), positions.len(), world.len()]
        .iter()
        .any(|&l| l != n)
    {
        return Err(invalid_arg!(
            "forward kinematics of {n} joints got {} offsets, {} rotations, {} positions, {} world slots",
            offsets.len(),
            local.len(),
            positions.len(),
            world.len()
        ));
    }
    for j in 0..n {
        match usize::try_from(parents[j]) {
            Ok(p) if p < j => {
                world[j] = rotation::mul(&world[p], &local[j]);
                positions[j] =
                    rotation::add(&positions[p], &rotation::apply(&world[p], &offsets[j]));
            }
            Ok(p) => {
                return Err(invalid_arg!(
                    "joint {j}'s parent {p} does not come before it"
                ))
            }
            Err(_) if j == 0 => {
                world[j] = local[j];
                positions[j] = *root;
            }
            Err(_) => {
                return Err(invalid_arg!(
                    "joint {j} has no parent; only joint 0 may be the root"
                ))
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parents_come_before_children() {
        for s in [Skeleton::smpl24(), Skeleton::humanml22()] {
            assert_eq!(s.parents().len(), s.joint_count());
            assert_eq!(s.rest_offsets().len(), s.joint_count());
            assert_eq!(s.parents()[0], -1);
            for j in 1..s.joint_count() {
                assert!(s.parent(j).unwrap() < j, "{} joint {j}", s.name());
            }
        }
    }

    #[test]
    fn rest_positions_match_reference_5() {
        // docs/official/smpl.md#rest-offsets (derived): L_Ankle (0.0884, −1.0879, −0.0268),
        // L_Wrist (0.6813, 0.2222, −0.0436).
        let s = Skeleton::smpl24();
        let n = s.joint_count();
        let (mut p, mut w) = (vec![[0.0; 3]; n], vec![rotation::IDENTITY; n]);
        forward_kinematics(
            s.parents(),
            s.rest_offsets(),
            &s.rest_offsets()[0],
            &vec![rotation::IDENTITY; n],
            &mut p,
            &mut w,
        )
        .unwrap();
        for (j, want) in [
            (7, [0.0884, -1.0879, -0.0268]),
            (20, [0.6813, 0.2222, -0.0436]),
        ] {
            for k in 0..3 {
                assert!((p[j][k] - want[k]).abs() < 1e-4, "joint {j}: {:?}", p[j]);
            }
        }
    }

    #[test]
    fn forward_kinematics_rejects_bad_hierarchies() {
        let (o, r) = ([[0.0; 3]; 2], [rotation::IDENTITY; 2]);
        let (mut p, mut w) = ([[0.0; 3]; 2], [rotation::IDENTITY; 2]);
        let e = forward_kinematics(&[-1, 1], &o, &[0.0; 3], &r, &mut p, &mut w).unwrap_err();
        assert!(
            e.to_string()
                .contains("joint 1's parent 1 does not come before it"),
            "{e}"
        );
        let e = forward_kinematics(&[-1, -1], &o, &[0.0; 3], &r, &mut p, &mut w).unwrap_err();
        assert!(
            e.to_string().contains("only joint 0 may be the root"),
            "{e}"
        );
        let e = forward_kinematics(&[-1, 0], &o[..1], &[0.0; 3], &r, &mut p, &mut w).unwrap_err();
        assert!(e.to_string().contains("got 1 offsets"), "{e}");
    }

    #[test]
    fn humanml_bones_take_smpl_lengths_and_t2m_directions() {
        let h = Skeleton::humanml22();
        let s = Skeleton::smpl24();
        assert_eq!(h.joint_names()[21], "right_wrist");
        assert_eq!(h.rest_offsets()[0], [0.0; 3]);
        // Left knee (4): straight down, length |SMPL offset 4| = √(0.03428² + 0.37520² + 0.00450²) = 0.376788
        let len4 = rotation::dot(&s.rest_offsets()[4], &s.rest_offsets()[4]).sqrt();
        assert_eq!(h.rest_offsets()[4], [0.0, -len4, 0.0]);
        assert!((len4 - 0.376788).abs() < 1e-6);
        // Left foot (10) points forward (+Z).
        assert!(h.rest_offsets()[10][2] > 0.1 && h.rest_offsets()[10][0] == 0.0);
        assert_eq!(h.children(9).collect::<Vec<_>>(), vec![12, 13, 14]);
    }
}
