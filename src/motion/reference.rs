//! Reference motions given as poses, turned back into model features: the inverse of reading
//! `smpl24_6d` features out as a root translation plus local joint rotations in a convention.
//! An editing session needs features; callers (engines, BVH files) have poses.
//!
//! Reading does `pelvis = trans + rest pelvis`, `p' = s·W·p`, `root' = W·R·Cᵀ` and
//! `local' = C·R·Cᵀ` (see `convention`); this module undoes each step exactly. `humanml263`
//! features cannot be rebuilt from rotations (its rotations come from an IK without twist and its
//! features hold velocities and contacts), so references for it are given as features.

use super::convention::{Change, Convention};
use super::format::Format;
use super::layout::Layout;
use super::rotation::{self, Mat3, Vec3};
use super::skeleton::Skeleton;
use crate::error::{invalid_arg, Result};

/// How far `RᵀR` may be from the identity before a "rotation matrix" is rejected: loose enough
/// for `f32` matrices that went through an engine, tight enough to catch a scale or shear.
const ORTHONORMAL_TOLERANCE: f64 = 1e-3;
/// Quaternions shorter than this are rejected instead of normalised: they carry no direction.
const MIN_QUAT_NORM: f64 = 1e-3;

/// `smpl24_6d` features `[frames, 147]` from root (pelvis) positions `[frames, 3]` and local
/// joint rotations `[frames, 24, …]` given in `layout` (`LocalMatrix`, `Local6d`,
/// `LocalQuatXyzw` or `LocalQuatWxyz`), both in `convention` and its unit: decoding the result
/// with [`Poses::decode`](super::Poses::decode) and reading the same layouts in the same
/// convention gives the inputs back. Non-unit quaternions are normalised; 6D rows are
/// orthonormalised as decoding does; matrices must already be proper rotations.
pub fn smpl24_features(
    root: &[f32],
    rotations: &[f32],
    layout: Layout,
    convention: Convention,
    frames: usize,
) -> Result<Vec<f32>> {
    let joints = Skeleton::smpl24().joint_count();
    let per_joint = match layout {
        Layout::LocalMatrix => 9,
        Layout::Local6d => 6,
        Layout::LocalQuatXyzw | Layout::LocalQuatWxyz => 4,
        other => {
            return Err(invalid_arg!(
                "reference rotations must be a local layout (local_matrix, local_6d, local_quat_xyzw or local_quat_wxyz), got {other}"
            ))
        }
    };
    if frames == 0 {
        return Err(invalid_arg!("a reference motion needs at least one frame"));
    }
    check_len("reference root", root.len(), frames, 3)?;
    check_len(
        "reference rotations",
        rotations.len(),
        frames,
        joints * per_joint,
    )?;
    check_finite("reference root", root, 3, 1)?;
    check_finite(
        "reference rotations",
        rotations,
        joints * per_joint,
        per_joint,
    )?;

    let roots: Vec<Vec3> = root
        .chunks_exact(3)
        .map(|p| [p[0] as f64, p[1] as f64, p[2] as f64])
        .collect();
    let mats = rotations
        .chunks_exact(per_joint)
        .enumerate()
        .map(|(i, v)| {
            let v: Vec<f64> = v.iter().map(|&x| x as f64).collect();
            to_matrix(&v, layout).map_err(|why| {
                invalid_arg!(
                    "reference rotation at frame {}, joint {} ({}): {why}",
                    i / joints,
                    i % joints,
                    Skeleton::smpl24().joint_names()[i % joints]
                )
            })
        })
        .collect::<Result<Vec<Mat3>>>()?;
    Ok(features_from_poses(&roots, &mats, convention))
}

/// The native-frame features of poses already checked: `roots` `[frames]` pelvis positions and
/// `local` `[frames × 24]` proper rotations, both in `convention`.
pub(crate) fn features_from_poses(
    roots: &[Vec3],
    local: &[Mat3],
    convention: Convention,
) -> Vec<f32> {
    let skel = Skeleton::smpl24();
    let joints = skel.joint_count();
    let ch = Change::new(Format::Smpl24Rot6d, convention);
    let rest_pelvis = skel.rest_offsets()[0];
    let mut out = Vec::with_capacity(roots.len() * Format::Smpl24Rot6d.feature_dim());
    for (p, frame) in roots.iter().zip(local.chunks_exact(joints)) {
        let pelvis = ch.inverse_position(p);
        out.extend((0..3).map(|k| (pelvis[k] - rest_pelvis[k]) as f32));
        for (j, r) in frame.iter().enumerate() {
            let native = if j == 0 {
                ch.inverse_global(r)
            } else {
                ch.inverse_local(r)
            };
            out.extend(rotation::to_6d_rows(&native).map(|x| x as f32));
        }
    }
    out
}

/// `len == frames × per_frame`, with the expected shape in the error.
fn check_len(what: &str, len: usize, frames: usize, per_frame: usize) -> Result<()> {
    match frames.checked_mul(per_frame) {
        Some(want) if want == len => Ok(()),
        Some(want) => Err(invalid_arg!(
            "{what} holds {len} values; {frames} frames need {want} ({frames} x {per_frame})"
        )),
        None => Err(invalid_arg!("{frames} frames of {what} overflow")),
    }
}

/// Every value finite; the error names the frame and the item (`per_item` values each).
fn check_finite(what: &str, v: &[f32], per_frame: usize, per_item: usize) -> Result<()> {
    match v.iter().position(|x| !x.is_finite()) {
        None => Ok(()),
        Some(i) => Err(invalid_arg!(
            "{what} are not finite at frame {}, item {}",
            i / per_frame,
            (i % per_frame) / per_item
        )),
    }
}

/// One rotation in `layout` as a matrix, or why it is not a rotation.
fn to_matrix(v: &[f64], layout: Layout) -> std::result::Result<Mat3, String> {
    match layout {
        Layout::LocalMatrix => {
            let m = [[v[0], v[1], v[2]], [v[3], v[4], v[5]], [v[6], v[7], v[8]]];
            check_rotation(&m)?;
            Ok(m)
        }
        Layout::Local6d => {
            let a = [v[0], v[1], v[2]];
            let b = [v[3], v[4], v[5]];
            let (na, nb) = (rotation::dot(&a, &a).sqrt(), rotation::dot(&b, &b).sqrt());
            let c = rotation::cross(&a, &b);
            if na < 1e-12 || rotation::dot(&c, &c).sqrt() <= 1e-6 * na * nb {
                return Err("its two 6D rows are zero or parallel".into());
            }
            Ok(rotation::from_6d_rows(&[
                v[0], v[1], v[2], v[3], v[4], v[5],
            ]))
        }
        _ => {
            let q = if layout == Layout::LocalQuatXyzw {
                [v[3], v[0], v[1], v[2]]
            } else {
                [v[0], v[1], v[2], v[3]]
            };
            let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
            if n < MIN_QUAT_NORM {
                return Err(format!("quaternion of length {n:.3e} has no direction"));
            }
            // quat_to_matrix scales by 2/|q|², so a non-unit quaternion gives its rotation.
            Ok(rotation::quat_to_matrix(&q))
        }
    }
}

/// A proper rotation: `|RᵀR − I| ≤` tolerance entrywise and `det > 0`.
fn check_rotation(m: &Mat3) -> std::result::Result<(), String> {
    let mtm = rotation::mul(&rotation::transpose(m), m);
    let err = (0..3)
        .flat_map(|r| (0..3).map(move |c| (r, c)))
        .map(|(r, c)| (mtm[r][c] - if r == c { 1.0 } else { 0.0 }).abs())
        .fold(0.0f64, f64::max);
    if err > ORTHONORMAL_TOLERANCE {
        return Err(format!(
            "matrix is not orthonormal (|RᵀR − I| = {err:.3e} > {ORTHONORMAL_TOLERANCE:e})"
        ));
    }
    if rotation::det(m) < 0.0 {
        return Err("matrix is a reflection (determinant −1), not a rotation".into());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn identity_rotations() -> Vec<f32> {
        (0..24)
            .flat_map(|_| [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
            .collect()
    }

    #[test]
    fn rest_pose_in_native_is_zero_translation_and_identity_rows() {
        // Pelvis at the rest pelvis, identity everywhere → translation 0 (up to the f32 input's
        // rounding), 6D [1,0,0,0,1,0].
        let rest = Skeleton::smpl24().rest_offsets()[0].map(|x| x as f32);
        let f = smpl24_features(
            &rest,
            &identity_rotations(),
            Layout::LocalMatrix,
            Convention::Native,
            1,
        )
        .unwrap();
        assert!(f[..3].iter().all(|x| x.abs() < 1e-8), "{:?}", &f[..3]);
        for j in 0..24 {
            assert_eq!(&f[3 + 6 * j..9 + 6 * j], &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
        }
    }

    #[test]
    fn an_upright_unreal_character_gets_smpls_tilt_back() {
        // Unreal (Z up, X forward, Y right, cm) from the native Z-up world (−Y forward, +X
        // left): native (x, y, z) = (−Y', −X', Z') / 100. An unturned Unreal root (identity)
        // is the tilt Rx(+90°) = rows [1,0,0], [0,0,−1], [0,1,0] in SMPL's data; other joints
        // stay identity.
        let rest = Skeleton::smpl24().rest_offsets()[0];
        let root = [-50.0f32, 120.0, 95.0];
        let f = smpl24_features(
            &root,
            &identity_rotations(),
            Layout::LocalMatrix,
            Convention::Unreal,
            1,
        )
        .unwrap();
        let want = [-1.2 - rest[0], 0.5 - rest[1], 0.95 - rest[2]];
        for k in 0..3 {
            assert!(
                (f[k] as f64 - want[k]).abs() < 1e-6,
                "{:?} vs {want:?}",
                &f[..3]
            );
        }
        assert_eq!(&f[3..9], &[1.0, 0.0, 0.0, 0.0, 0.0, -1.0]);
        assert_eq!(&f[9..15], &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    }

    #[test]
    fn bad_rotations_are_named() {
        let root = [0.0f32; 3];
        let mut q: Vec<f32> = (0..24).flat_map(|_| [0.0, 0.0, 0.0, 1.0]).collect();
        q[5 * 4 + 3] = 0.0;
        let e = smpl24_features(&root, &q, Layout::LocalQuatXyzw, Convention::Unity, 1)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("frame 0, joint 5 (R_Knee)") && e.contains("no direction"),
            "{e}"
        );
        let mut m = identity_rotations();
        m[2 * 9 + 8] = -1.0;
        let e = smpl24_features(&root, &m, Layout::LocalMatrix, Convention::Ros, 1)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("joint 2 (R_Hip)") && e.contains("reflection"),
            "{e}"
        );
        m[2 * 9 + 8] = 1.1;
        let e = smpl24_features(&root, &m, Layout::LocalMatrix, Convention::Ros, 1)
            .unwrap_err()
            .to_string();
        assert!(e.contains("not orthonormal"), "{e}");
    }
}
