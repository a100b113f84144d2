//! Decoding FLAME's `smpl24_6d` features (docs/official/flame.md#motion-representation,
//! docs/official/flame.md#6d-to-rotation-matrix, docs/official/smpl.md#forward-kinematics): per
//! frame, the root translation (AMASS's Z-up world, metres) and 24 SMPL local rotations in
//! pytorch3d's 6D ROW convention, posed on the neutral SMPL skeleton by SMPL's forward kinematics.

use super::format::Format;
use super::poses::Poses;
use super::rotation::{self, Mat3};
use super::skeleton::{forward_kinematics, Skeleton};
use crate::error::Result;

/// Decodes `[frames, 147]` features (already smoothed if asked) in the native frame.
pub(crate) fn decode(x: &[f64], frames: usize) -> Result<Poses> {
    let skel = Skeleton::smpl24();
    let joints = skel.joint_count();
    let dim = Format::Smpl24Rot6d.feature_dim();
    let mut poses = Poses::empty(Format::Smpl24Rot6d, frames);
    for (t, row) in x.chunks_exact(dim).enumerate() {
        let local: Vec<Mat3> = row[3..]
            .chunks_exact(6)
            .map(|d| rotation::from_6d_rows(&[d[0], d[1], d[2], d[3], d[4], d[5]]))
            .collect();
        // SMPL's root rotation turns the body about its rest pelvis, so the pelvis lands at trans +
        // J_pelvis whatever the root rotation is (docs/official/smpl.md#forward-kinematics).
        let pelvis = rotation::add(&[row[0], row[1], row[2]], &skel.rest_offsets()[0]);
        let span = t * joints..(t + 1) * joints;
        forward_kinematics(
            skel.parents(),
            skel.rest_offsets(),
            &pelvis,
            &local,
            &mut poses.positions[span.clone()],
            &mut poses.global[span.clone()],
        )?;
        poses.local[span].copy_from_slice(&local);
        poses.root[t] = pelvis;
    }
    Ok(poses)
}
