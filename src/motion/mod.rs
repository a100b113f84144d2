//! Motion formats, skeletons, forward kinematics, coordinate conventions, post-processing and
//! exporters: everything between a model's raw features and the poses an engine or robot uses.
//! Nothing here runs a network or knows about sessions; it takes features (`&[f32]`, frame-major)
//! and gives poses.
//!
//! # Formats ([`Format`], declared by the model file's `config.motion.format`)
//!
//! | value | name | features | skeleton | native frame |
//! |---|---|---|---|---|
//! | 0 | `smpl24_6d` (FLAME) | 147 = translation + 24 × 6D (ROW convention) | SMPL-24 | Z up, −Y forward, +X left, m |
//! | 1 | `humanml263` (HumanML3D) | 263, normalised by the model's mean/std | HumanML3D-22 | Y up, +Z forward, +X left, m |
//!
//! Both run at 20 fps. `smpl24_6d` poses come from SMPL forward kinematics (the pelvis sits at
//! the translation plus the rest pelvis); `humanml263` positions from `recover_from_ric`,
//! rotations from the cont6d features hung on the hierarchy as `humanml263`'s module doc
//! explains. The HumanML3D skeleton's bone lengths are not published; each bone takes the length
//! of the same SMPL-24 joint's rest offset (see [`Skeleton::humanml22`]).
//!
//! # Layouts ([`Layout`], per frame, `f32`, frame-major; J = 24 or 22)
//!
//! | value | name | shape |
//! |---|---|---|
//! | 0 | `root_translation` | `[frames, 3]` pelvis world position |
//! | 1 | `local_quat_xyzw` | `[frames, J, 4]` |
//! | 2 | `local_quat_wxyz` | `[frames, J, 4]` |
//! | 3 | `local_matrix` | `[frames, J, 3, 3]` row-major, acting on column vectors |
//! | 4 | `local_6d` | `[frames, J, 6]` first two rows of the matrix |
//! | 5 | `global_positions` | `[frames, J, 3]` |
//! | 6 | `global_quat_xyzw` | `[frames, J, 4]` |
//! | 7 | `global_quat_wxyz` | `[frames, J, 4]` |
//! | 8 | `foot_contacts` | `[frames, 4]` L ankle, L foot, R ankle, R foot (humanml263's own, smpl24_6d's detected) |
//! | 9 | `root_bone` | `[frames, 3]` the `root` bone of [`RootMotion::Separate`] (on the ground under the pelvis) |
//!
//! Local rotations are parent-relative (the root's is its world rotation):
//! `global(j) = global(parent)·local(j)`, `p(j) = p(parent) + global(parent)·offset(j)` with the
//! rest offsets of [`rest_offsets`] in the same convention. Quaternions come from pytorch3d's
//! matrix→quaternion with w ≥ 0; with [`ReadOptions::continuous`] (the default) each joint's
//! track is then made sign-continuous (`q[t]` flipped when `dot(q[t], q[t−1]) < 0`).
//!
//! # Conventions ([`Convention`])
//!
//! | value | name | handedness | up | forward | left | unit |
//! |---|---|---|---|---|---|---|
//! | 0 | `native` | right | format's | format's | +X | m |
//! | 1 | `unity` | left | +Y | +Z | −X (right = +X) | m |
//! | 2 | `unreal` | left | +Z | +X | −Y (right = +Y) | cm |
//! | 3 | `ros` | right | +Z | +X | +Y | m |
//! | 4 | `blender` | right | +Z | −Y | +X | m |
//! | 5 | `gltf` | right | +Y | +Z | +X | m |
//!
//! "Forward" is where an unturned character faces, "left" its left hand. A conversion keeps up,
//! forward and left; positions `p' = s·M p`, rotations `R' = M R M⁻¹` (proper even when `M` is
//! a reflection). `native` is the data untouched: for `smpl24_6d` that means the Z-up AMASS world
//! for positions, but SMPL's Y-up body frame for the rest offsets and joint rotations, the root
//! rotation carrying the +90° X tilt that stands the body up (so the native forward is −Y).
//! Presets put the rest pose upright, facing forward, and remove the tilt. Details in
//! `convention`'s module doc.
//!
//! # Post-processing and exports
//!
//! [`ReadOptions::smooth_sigma`] applies FLAME's temporal Gaussian smoothing (σ = 1, scipy's
//! `gaussian_filter1d` defaults) to the features before decoding. [`bvh::to_string`] and
//! [`json::to_string`] and [`gltf::to_glb`] / [`gltf::to_gltf`] write files; [`read_layout`] and [`layout_len`] are the C-shaped entry
//! points.
//!
//! [`Format`]: crate::motion::Format
//! [`Skeleton::humanml22`]: crate::motion::Skeleton::humanml22
//! [`Layout`]: crate::motion::Layout
//! [`RootMotion::Separate`]: crate::motion::RootMotion::Separate
//! [`rest_offsets`]: crate::motion::rest_offsets
//! [`ReadOptions::continuous`]: crate::motion::ReadOptions::continuous
//! [`Convention`]: crate::motion::Convention
//! [`ReadOptions::smooth_sigma`]: crate::motion::ReadOptions::smooth_sigma
//! [`bvh::to_string`]: crate::motion::bvh::to_string
//! [`json::to_string`]: crate::motion::json::to_string
//! [`gltf::to_glb`]: crate::motion::gltf::to_glb
//! [`gltf::to_gltf`]: crate::motion::gltf::to_gltf
//! [`read_layout`]: crate::motion::read_layout
//! [`layout_len`]: crate::motion::layout_len

pub mod amass;
pub mod bvh;
pub mod contacts;
pub mod convention;
pub mod feet;
pub mod finish;
pub mod format;
pub mod gltf;
pub(crate) mod humanml263;
pub mod ik;
pub mod json;
pub mod layout;
pub mod looping;
pub mod mask;
pub mod poses;
pub mod postprocess;
#[cfg(feature = "preview")]
pub mod preview;
pub mod reference;
pub mod resample;
pub mod root_motion;
pub mod rotation;
pub mod skating;
pub mod skeleton;
mod smpl24_6d;
#[cfg(test)]
pub(crate) mod testutil;

pub use contacts::ContactParams;
pub use convention::{Axis, Convention, Frame, Handedness, Unit};
pub use finish::{Feet, Finish, RootMotion};
pub use format::{Format, Normalization};
pub use layout::{Layout, QuatOrder};
pub use mask::{BodyPart, Mask, Task};
pub use poses::{Poses, ReadOptions};
pub use skeleton::Skeleton;

use crate::error::{invalid_arg, Result};

/// Decodes `frames` rows of `format` features and returns one layout in one convention,
/// frame-major `f32` of [`layout_len`] values. Decoding runs in `f64`; callers that want several
/// layouts of one motion should decode once with [`Poses::decode`] and call [`Poses::layout`].
pub fn read_layout(
    format: Format,
    features: &[f32],
    frames: usize,
    layout: Layout,
    convention: Convention,
    opts: &ReadOptions,
) -> Result<Vec<f32>> {
    layout.frame_shape(format)?;
    Poses::decode(format, features, frames, opts)?.layout(layout, convention)
}

/// The number of `f32` values [`read_layout`] returns, so a caller can size its buffer.
pub fn layout_len(format: Format, frames: usize, layout: Layout) -> Result<usize> {
    let per_frame: usize = layout.frame_shape(format)?.iter().product();
    frames
        .checked_mul(per_frame)
        .ok_or_else(|| invalid_arg!("{frames} frames of {layout} overflow"))
}

/// `[J, 3]` rest offsets of `format`'s skeleton in `convention` (joint − parent; row 0 the root's
/// rest position), flattened.
pub fn rest_offsets(format: Format, convention: Convention) -> Vec<f32> {
    let ch = convention::Change::new(format, convention);
    format
        .skeleton()
        .rest_offsets()
        .iter()
        .flat_map(|o| ch.offset(o))
        .map(|v| v as f32)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_len_matches_read_layout() {
        let frames = 3;
        for format in Format::ALL {
            let features = vec![0.5f32; frames * format.feature_dim()];
            for layout in Layout::ALL {
                let n = layout_len(format, frames, layout).unwrap();
                if layout == Layout::RootBone {
                    continue;
                }
                let v = read_layout(
                    format,
                    &features,
                    frames,
                    layout,
                    Convention::Unity,
                    &ReadOptions::default(),
                )
                .unwrap();
                assert_eq!(v.len(), n, "{format} {layout}");
            }
        }
        assert!(layout_len(Format::Smpl24Rot6d, usize::MAX, Layout::LocalMatrix).is_err());
        assert_eq!(
            layout_len(Format::HumanMl263, 0, Layout::GlobalPositions).unwrap(),
            0
        );
    }

    #[test]
    fn bad_input_is_an_error_not_a_panic() {
        let opts = ReadOptions::default();
        let f = Format::Smpl24Rot6d;
        let e = read_layout(
            f,
            &[0.0; 10],
            1,
            Layout::RootTranslation,
            Convention::Native,
            &opts,
        )
        .unwrap_err();
        assert!(
            e.to_string()
                .contains("features hold 10 values; 1 frames of smpl24_6d need 147"),
            "{e}"
        );
        let mut x = vec![0.0f32; 294];
        x[150] = f32::NAN;
        let e =
            read_layout(f, &x, 2, Layout::RootTranslation, Convention::Native, &opts).unwrap_err();
        assert!(e.to_string().contains("frame 1, channel 3"), "{e}");
        let bad_sigma = ReadOptions {
            smooth_sigma: -1.0,
            ..opts
        };
        assert!(read_layout(
            f,
            &[0.0; 147],
            1,
            Layout::RootTranslation,
            Convention::Native,
            &bad_sigma
        )
        .is_err());
        let mean = [0.0f32; 3];
        let norm = ReadOptions {
            normalization: Some(Normalization {
                mean: &mean,
                std: &mean,
            }),
            ..opts
        };
        let e = read_layout(
            Format::HumanMl263,
            &[0.0; 263],
            1,
            Layout::RootTranslation,
            Convention::Native,
            &norm,
        )
        .unwrap_err();
        assert!(
            e.to_string().contains("normalisation mean has 3 values"),
            "{e}"
        );
        // Zero 6D vectors (a degenerate model output) still decode without NaN or panic.
        let v = read_layout(
            f,
            &[0.0; 147],
            1,
            Layout::GlobalPositions,
            Convention::Unreal,
            &opts,
        )
        .unwrap();
        assert!(v.iter().all(|x| x.is_finite()));
    }

    #[test]
    fn rest_offsets_are_scaled_and_rotated() {
        let native = rest_offsets(Format::HumanMl263, Convention::Native);
        let unreal = rest_offsets(Format::HumanMl263, Convention::Unreal);
        // Left knee (joint 4) points down: native −Y; Unreal −Z in centimetres.
        assert!(native[13] < -0.3);
        assert!(
            (unreal[14] - 100.0 * native[13]).abs() < 1e-4
                && unreal[12] == 0.0
                && unreal[13] == 0.0
        );
    }
}
