//! Root motion: where the clip's horizontal travel goes ([`RootMotion`]).
//!
//! - [`RootMotion::Keep`]: nothing changes (and `remove_yaw` is ignored: the heading is part of
//!   the motion the pelvis carries).
//! - [`RootMotion::InPlace`]: on every frame the pelvis's horizontal position (its coordinates
//!   on the two axes other than [`Format::up_axis`]) becomes exactly 0, and every joint moves
//!   with it: the root translation and all positions lose the pelvis's horizontal offset, the
//!   height is kept, rotations are untouched. Zero rather than the first frame's position: an
//!   in-place clip then sits over the origin whatever the model's start, which is what an
//!   engine's in-place animation expects (the character's own transform places it).
//! - [`RootMotion::Separate`]: the pelvis as in-place, and the removed track stored in
//!   `Poses::root_bone` as the point on the ground (height 0) under the pelvis, so that
//!   `root_bone + (in-place position)` is the original position of every joint. Exporters write
//!   it as a `root` bone, parent of the pelvis, without rotation.
//! - `remove_yaw` (with in-place or separate): the heading's drift is removed as well. The
//!   heading ψ of a frame is the twist of the root's world rotation about the up axis (the
//!   swing–twist decomposition: for a unit quaternion `(w, v)` and up axis `u`,
//!   `ψ = 2·atan2(v·u, w)`): it is exactly the yaw of humanml263's root (a pure rotation about Y)
//!   and of smpl24_6d's `Rz(ψ)·Rx(+90°)·…` (the tilt has no Z twist), and unlike the projection
//!   of a forward vector it stays defined for a body lying on its back. Each frame is turned by
//!   `Rot(up, −(ψ_t − ψ_0))` about the vertical line through its pelvis: the root's local
//!   rotation (its world rotation, world-from-body with smpl24_6d's tilt inside) and every
//!   global rotation are left-multiplied by it, every position `p` becomes
//!   `pelvis + Rot·(p − pelvis)`; the other local rotations are parent-relative and do not
//!   change. Every frame then faces the way frame 0 faced. The removed yaw is not kept anywhere
//!   (the root bone carries no rotation), so with `Separate` the original positions are
//!   recovered from the root bone only without `remove_yaw`.
//!
//! A root bone already present (from an earlier call) is folded in first: the pelvis's
//! horizontal travel is then the bone's plus its own.
//!
//! [`Format::up_axis`]: super::format::Format::up_axis

use super::finish::RootMotion;
use super::poses::Poses;
use super::rotation::{self, Vec3};

/// Applies `mode` (and, for in-place and separate, `remove_yaw`) to `poses`: see the module doc.
pub fn apply(poses: &mut Poses, mode: RootMotion, remove_yaw: bool) {
    apply_after(poses, mode, remove_yaw, None)
}

/// [`apply`] on frames that continue earlier ones (a stream's, `crate::stream`): `before` is
/// the heading every frame is turned to (the first frame's of the whole motion) and the heading
/// of the frame before `poses`' first ([`headings_after`]); `None` = `poses` is the whole motion.
pub(crate) fn apply_after(
    poses: &mut Poses,
    mode: RootMotion,
    remove_yaw: bool,
    before: Option<(f64, f64)>,
) {
    if mode == RootMotion::Keep {
        return;
    }
    let up = poses.format.up_axis();
    let frames = poses.frames;
    let joints = poses.joint_count();
    if remove_yaw {
        remove_heading_drift(poses, up, before);
    }
    let old_bone = std::mem::take(&mut poses.root_bone);
    let old_bone = (old_bone.len() == frames).then_some(old_bone);
    let mut bone: Vec<Vec3> = Vec::new();
    if mode == RootMotion::Separate {
        bone.reserve_exact(frames);
    }
    for t in 0..frames {
        // The pelvis's horizontal offset: its position with the height set to 0.
        let mut d = poses.root[t];
        d[up] = 0.0;
        for p in poses.positions[t * joints..(t + 1) * joints]
            .iter_mut()
            .chain(std::iter::once(&mut poses.root[t]))
        {
            for i in (0..3).filter(|&i| i != up) {
                p[i] -= d[i];
            }
        }
        if mode == RootMotion::Separate {
            if let Some(old) = &old_bone {
                for i in (0..3).filter(|&i| i != up) {
                    d[i] += old[t][i];
                }
            }
            bone.push(d);
        }
    }
    poses.root_bone = bone;
}

/// The heading (radians) of each frame's root rotation about axis `up` (module doc); a frame
/// whose twist is undefined (its swing is a half turn: `w` and `v·u` both ≈ 0) keeps the
/// previous frame's heading.
fn headings(poses: &Poses, up: usize) -> Vec<f64> {
    headings_after(poses, up, 0.0)
}

/// [`headings`] with `last` the heading of the frame before the first.
pub(crate) fn headings_after(poses: &Poses, up: usize, mut last: f64) -> Vec<f64> {
    let joints = poses.joint_count();
    let mut out = Vec::with_capacity(poses.frames);
    for t in 0..poses.frames {
        let q = rotation::to_quat(&poses.global[t * joints]);
        let (w, s) = (q[0], q[1 + up]);
        if w * w + s * s > 1e-12 {
            last = 2.0 * s.atan2(w);
        }
        out.push(last);
    }
    out
}

/// Turns every frame about the vertical line through its pelvis so that its heading is frame
/// 0's (module doc).
fn remove_heading_drift(poses: &mut Poses, up: usize, before: Option<(f64, f64)>) {
    let joints = poses.joint_count();
    let (psi, psi0) = match before {
        Some((psi0, last)) => (headings_after(poses, up, last), psi0),
        None => {
            let psi = headings(poses, up);
            let psi0 = psi.first().copied().unwrap_or(0.0);
            (psi, psi0)
        }
    };
    let mut axis = [0.0; 3];
    axis[up] = 1.0;
    for (t, psi_t) in psi.iter().enumerate() {
        let turn = rotation::axis_angle(&axis, -(psi_t - psi0));
        let pelvis = poses.root[t];
        let span = t * joints..(t + 1) * joints;
        poses.local[t * joints] = rotation::mul(&turn, &poses.local[t * joints]);
        for g in &mut poses.global[span.clone()] {
            *g = rotation::mul(&turn, g);
        }
        for p in &mut poses.positions[span] {
            let rel = [0, 1, 2].map(|i| p[i] - pelvis[i]);
            *p = rotation::add(&pelvis, &rotation::apply(&turn, &rel));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::skeleton::forward_kinematics;
    use crate::motion::{Format, Skeleton};
    use std::f64::consts::FRAC_PI_2;

    /// A drifting, turning synthetic motion (every feature a sinusoid of time).
    fn motion(format: Format, frames: usize) -> Poses {
        crate::motion::testutil::sinusoid_motion(format, frames)
    }

    #[test]
    fn in_place_zeroes_the_horizontal_pelvis_and_keeps_the_body() {
        for format in Format::ALL {
            let up = format.up_axis();
            let before = motion(format, 30);
            let mut p = before.clone();
            apply(&mut p, RootMotion::InPlace, false);
            let j = p.joint_count();
            assert!(p.root_bone.is_empty());
            for t in 0..30 {
                for i in 0..3 {
                    if i == up {
                        assert_eq!(p.root[t][i], before.root[t][i], "height kept");
                    } else {
                        assert_eq!(p.root[t][i], 0.0, "{format} frame {t}");
                        assert_eq!(p.positions[t * j][i], 0.0);
                    }
                }
                for c in 0..j {
                    let (a, b) = (p.positions[t * j + c], before.positions[t * j + c]);
                    assert_eq!(a[up], b[up]);
                    for i in 0..3 {
                        let rel = a[i] - p.root[t][i];
                        let rel0 = b[i] - before.root[t][i];
                        assert!((rel - rel0).abs() < 1e-15, "{format} {t} {c}");
                    }
                }
            }
            assert_eq!(p.local, before.local);
            assert_eq!(p.global, before.global);
            // Keep changes nothing, and ignores remove_yaw.
            let mut k = before.clone();
            apply(&mut k, RootMotion::Keep, true);
            assert_eq!(
                (k.root, k.positions, k.global),
                (before.root, before.positions, before.global)
            );
        }
    }

    #[test]
    fn separate_moves_the_travel_to_a_ground_bone() {
        // A hand example in smpl24_6d's Z-up world: pelvis (0.5, −0.25, 0.9), a joint at
        // (0.75, 0, 0.3) → pelvis (0, 0, 0.9), joint (0.25, 0.25, 0.3), bone (0.5, −0.25, 0).
        let mut p = Poses::empty(Format::Smpl24Rot6d, 1);
        p.root[0] = [0.5, -0.25, 0.9];
        p.positions[0] = p.root[0];
        p.positions[7] = [0.75, 0.0, 0.3];
        apply(&mut p, RootMotion::Separate, false);
        assert_eq!(p.root[0], [0.0, 0.0, 0.9]);
        assert_eq!(p.positions[7], [0.25, 0.25, 0.3]);
        assert_eq!(p.root_bone, vec![[0.5, -0.25, 0.0]]);
        // Applied again, the bone keeps the whole travel (nothing left on the pelvis to add).
        apply(&mut p, RootMotion::Separate, false);
        assert_eq!(p.root_bone, vec![[0.5, -0.25, 0.0]]);

        for format in Format::ALL {
            let up = format.up_axis();
            let before = motion(format, 25);
            let mut p = before.clone();
            apply(&mut p, RootMotion::Separate, false);
            let j = p.joint_count();
            assert_eq!(p.root_bone.len(), 25);
            for t in 0..25 {
                let bone = p.root_bone[t];
                assert_eq!(bone[up], 0.0, "on the ground");
                // The pelvis exactly: bone + in-place pelvis = the original root.
                assert_eq!(rotation::add(&bone, &p.root[t]), before.root[t]);
                for c in 0..j {
                    let back = rotation::add(&bone, &p.positions[t * j + c]);
                    let orig = before.positions[t * j + c];
                    for i in 0..3 {
                        // (p − d) + d: at most one rounding of each, ≤ 2 ulp of a few metres.
                        assert!(
                            (back[i] - orig[i]).abs()
                                <= 2.0 * f64::EPSILON * orig[i].abs().max(bone[i].abs()).max(1.0)
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn removing_yaw_faces_every_frame_like_the_first() {
        // smpl24_6d: the root's world rotation Rz(0.4·t)·Rx(+90°) (the tilt that stands SMPL up
        // in the Z-up world), travelling along +X; joints posed by forward kinematics.
        let skel = Skeleton::smpl24();
        let frames = 5;
        let mut p = Poses::empty(Format::Smpl24Rot6d, frames);
        let j = p.joint_count();
        let tilt = rotation::axis_angle(&[1.0, 0.0, 0.0], FRAC_PI_2);
        for t in 0..frames {
            let yaw = rotation::axis_angle(&[0.0, 0.0, 1.0], 0.4 * t as f64);
            p.local[t * j] = rotation::mul(&yaw, &tilt);
            p.local[t * j + 1] = rotation::axis_angle(&[0.2, 1.0, 0.0], 0.3);
            p.root[t] = [0.25 * t as f64, 0.0, 0.9];
            let s = t * j..(t + 1) * j;
            forward_kinematics(
                skel.parents(),
                skel.rest_offsets(),
                &p.root[t],
                &p.local[s.clone()],
                &mut p.positions[s.clone()],
                &mut p.global[s],
            )
            .unwrap();
        }
        apply(&mut p, RootMotion::InPlace, true);
        // Every frame's root is the tilt alone (ψ_0 = 0), and the left hip sits at
        // pelvis + Rx(90°)·offset(1) = (0.0695, 0.0068, −0.0914) + (0, 0, 0.9).
        let off = rotation::apply(&tilt, &skel.rest_offsets()[1]);
        let mut world = vec![rotation::IDENTITY; j];
        let mut pos = vec![[0.0; 3]; j];
        for t in 0..frames {
            let g = p.global[t * j];
            assert!(
                (0..3).all(|r| (0..3).all(|c| (g[r][c] - tilt[r][c]).abs() < 1e-12)),
                "{t}"
            );
            let hip = p.positions[t * j + 1];
            let want = [off[0], off[1], 0.9 + off[2]];
            assert!(
                (0..3).all(|i| (hip[i] - want[i]).abs() < 1e-12),
                "{t}: {hip:?}"
            );
            assert!((off[1] - 0.00681534).abs() < 1e-8 && (off[2] + 0.09140623).abs() < 1e-8);
            // Still the forward kinematics of the (turned) local rotations.
            forward_kinematics(
                skel.parents(),
                skel.rest_offsets(),
                &p.root[t],
                &p.local[t * j..(t + 1) * j],
                &mut pos,
                &mut world,
            )
            .unwrap();
            for (a, b) in pos.iter().zip(&p.positions[t * j..(t + 1) * j]) {
                assert!((0..3).all(|i| (a[i] - b[i]).abs() < 1e-12));
            }
        }
        // humanml263: its root rotation is a pure yaw about Y, made constant; heights kept.
        let before = motion(Format::HumanMl263, 20);
        let mut h = before.clone();
        apply(&mut h, RootMotion::Separate, true);
        let j = h.joint_count();
        assert!(headings(&before, 1)
            .iter()
            .any(|y| (y - headings(&before, 1)[0]).abs() > 0.1));
        for t in 0..20 {
            let (g, g0) = (h.global[t * j], h.global[0]);
            assert!(
                (0..3).all(|r| (0..3).all(|c| (g[r][c] - g0[r][c]).abs() < 1e-12)),
                "{t}"
            );
            for c in 0..j {
                let d = (h.positions[t * j + c][1] - before.positions[t * j + c][1]).abs();
                assert!(d < 1e-12);
            }
        }
    }
}
