//! Decoding HumanML3D's 263 features (GuyTevet/motion-diffusion-model
//! `data_loaders/humanml/scripts/motion_process.py`; docs/official/humanml3d.md#feature-layout),
//! de-normalised already: joint positions by
//! the official `recover_from_ric`, rotations from the cont6d (COLUMN convention) features by the
//! official `recover_from_rot` chain product, hung on the 22-joint hierarchy, and foot contacts.
//!
//! Why rotations need "hanging": HumanML3D stores, at each joint j, a rotation that turns the
//! bone ENDING at j, accumulated per kinematic chain from the root's rotation (even the arm
//! chains that leave the spine at joint 9 restart from the root), and its root rotation
//! `q_root = (cos θ, 0, sin θ, 0)` maps world to facing frame (positions use `qinv(q_root)`). A
//! parent-relative hierarchy needs one world rotation per joint, so libflame defines:
//!
//! - `B(j)`: the official chain product at j, `R(q_root) · R(c₁) ⋯ R(j)` — the world rotation of
//!   the bone ending at j;
//! - `global(0) = R(q_root)ᵀ`: the body's facing yaw, the same one positions use;
//! - `global(j) = B(next)`, where `next` follows j in its kinematic chain (9 → 12, the neck);
//!   the leaves (feet 10/11, head 15, wrists 20/21) have no bone of their own and take their
//!   parent's rotation;
//! - `local(0) = global(0)`, `local(j) = global(parent)ᵀ · global(j)`.
//!
//! The rotations come from an IK without twist and are not SMPL rotations
//! (docs/official/humanml3d.md#rotation-features): the
//! positions from `recover_from_ric` are the format's reliable output, and posing the rest
//! skeleton with these rotations only approximates them.

use super::format::Format;
use super::poses::Poses;
use super::rotation::{self, Mat3, Vec3};
use super::skeleton::{Skeleton, HUMANML22_CHAINS};

const RIC: usize = 4;
const ROT: usize = 67;
const CONTACTS: usize = 259;

/// Where a decode's root path starts: the half-yaw θ and the planar (x, z) position of its
/// first frame. [`RootStart::ORIGIN`] is the official start; a later one continues a motion
/// whose earlier frames are not decoded (a stream's window).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct RootStart {
    pub theta: f64,
    pub planar: [f64; 2],
}

impl RootStart {
    pub const ORIGIN: RootStart = RootStart {
        theta: 0.0,
        planar: [0.0; 2],
    };

    /// The start that frame `t` of `poses` (a humanml263 decode) had: θ from the root's world
    /// rotation `R(q_root)ᵀ = Ry(−2θ)` (θ is only needed modulo π), the planar position from
    /// the root.
    pub fn at(poses: &Poses, t: usize) -> RootStart {
        let g = &poses.global[t * poses.joint_count()];
        // R(q_root) = gᵀ = Ry(2θ): R[0][2] = g[2][0] = sin 2θ, R[0][0] = cos 2θ.
        let theta = 0.5 * g[2][0].atan2(g[0][0]);
        RootStart {
            theta,
            planar: [poses.root[t][0], poses.root[t][2]],
        }
    }
}

/// Decodes de-normalised `[frames, 263]` features in the native (Y-up) frame, the root path
/// starting at `start`.
pub(crate) fn decode(x: &[f64], frames: usize, start: RootStart) -> Poses {
    let joints = Skeleton::humanml22().joint_count();
    let dim = Format::HumanMl263.feature_dim();
    let next = next_in_chain(joints);
    let mut poses = Poses::empty(Format::HumanMl263, frames);
    let (r_root, root) = root_track_from(x, dim, start);
    for (t, row) in x.chunks_exact(dim).enumerate() {
        let span = t * joints..(t + 1) * joints;
        poses.root[t] = root[t];
        ric_positions(
            row,
            &r_root[t],
            &root[t],
            &mut poses.positions[span.clone()],
        );
        hung_rotations(
            row,
            &r_root[t],
            &next,
            &mut poses.global[span.clone()],
            &mut poses.local[span],
        );
        let c = &row[CONTACTS..CONTACTS + 4];
        poses.contacts.push([c[0], c[1], c[2], c[3]]);
    }
    poses
}

/// `recover_root_rot_pos`: per frame, `R(q_root)` (world → facing frame) and the root position.
/// θ is the exclusive cumulative sum of dim 0 (half the yaw change); the planar velocity of frame
/// t−1 is rotated into the world by `qinv(q_root[t])` and accumulated; the height is dim 3.
pub(crate) fn root_track(x: &[f64], dim: usize) -> (Vec<Mat3>, Vec<Vec3>) {
    root_track_from(x, dim, RootStart::ORIGIN)
}

/// [`root_track`] from another start.
fn root_track_from(x: &[f64], dim: usize, start: RootStart) -> (Vec<Mat3>, Vec<Vec3>) {
    let (mut theta, mut planar) = (start.theta, start.planar);
    let (mut rots, mut positions) = (Vec::new(), Vec::new());
    let mut prev: Option<&[f64]> = None;
    for row in x.chunks_exact(dim) {
        if let Some(p) = prev {
            theta += p[0];
        }
        let r = rotation::quat_to_matrix(&[theta.cos(), 0.0, theta.sin(), 0.0]);
        if let Some(p) = prev {
            let v = rotation::apply(&rotation::transpose(&r), &[p[1], 0.0, p[2]]);
            planar[0] += v[0];
            planar[1] += v[2];
        }
        rots.push(r);
        positions.push([planar[0], row[3], planar[1]]);
        prev = Some(row);
    }
    (rots, positions)
}

/// `recover_from_ric` for one frame: joints 1..21 are stored in the facing frame relative to the
/// root's x and z (y absolute); joint 0 is the root.
pub(crate) fn ric_positions(row: &[f64], r_root: &Mat3, root: &Vec3, out: &mut [Vec3]) {
    let to_world = rotation::transpose(r_root);
    out[0] = *root;
    for (j, p) in row[RIC..RIC + 63].chunks_exact(3).enumerate() {
        let w = rotation::apply(&to_world, &[p[0], p[1], p[2]]);
        out[j + 1] = [w[0] + root[0], w[1], w[2] + root[2]];
    }
}

/// One frame's cont6d rotations hung on the hierarchy (module doc): the official chain products
/// give each bone's world rotation, each joint takes the rotation of the bone leaving it.
fn hung_rotations(
    row: &[f64],
    r_root: &Mat3,
    next: &[Option<usize>],
    global: &mut [Mat3],
    local: &mut [Mat3],
) {
    let skel = Skeleton::humanml22();
    let stored: Vec<Mat3> = row[ROT..ROT + 126]
        .chunks_exact(6)
        .map(|d| rotation::from_6d_columns(&[d[0], d[1], d[2], d[3], d[4], d[5]]))
        .collect();
    let mut bone = [rotation::IDENTITY; 22];
    for chain in HUMANML22_CHAINS {
        let mut m = *r_root;
        for &j in &chain[1..] {
            m = rotation::mul(&m, &stored[j - 1]);
            bone[j] = m;
        }
    }
    global[0] = rotation::transpose(r_root);
    local[0] = global[0];
    for j in 1..global.len() {
        let parent = global[skel.parent(j).unwrap_or(0)];
        global[j] = next[j].map_or(parent, |n| bone[n]);
        local[j] = rotation::mul(&rotation::transpose(&parent), &global[j]);
    }
}

/// For each joint, the joint after it in its kinematic chain (`None` for the root, whose bones
/// all start chains, and for the leaves).
fn next_in_chain(joints: usize) -> Vec<Option<usize>> {
    let mut next = vec![None; joints];
    for chain in HUMANML22_CHAINS {
        for pair in chain[1..].windows(2) {
            next[pair[0]] = Some(pair[1]);
        }
    }
    next
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_inner_joint_has_a_next_bone() {
        let next = next_in_chain(22);
        assert_eq!(next[0], None);
        assert_eq!(next[9], Some(12));
        assert_eq!(next[14], Some(17));
        for leaf in [10, 11, 15, 20, 21] {
            assert_eq!(next[leaf], None);
        }
        let skel = Skeleton::humanml22();
        for (j, n) in next.iter().enumerate() {
            if let Some(n) = n {
                assert_eq!(skel.parent(*n), Some(j));
            }
        }
    }
}
