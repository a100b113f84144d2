//! The C ABI's view of motion: its own layout and convention enums (raw features are layout 0,
//! so the motion module's Rust enums stay out of the header), read flags, skeleton tables and
//! the feature channels a joint owns (for keep-masks).

use crate::error::{invalid_arg, Result};
use crate::models::Model;
use crate::motion::{self, Convention, Format, Layout};

/// What [`crate::ffi::flame_session_read`] writes per frame. `J` is the skeleton's joint count
/// (`FlameModelInfo.joint_count`).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameLayout {
    /// `[frames, feature_dim]` the model's raw features (convention and flags ignored).
    Features = 0,
    /// `[frames, 3]` the root joint's world position.
    RootTranslation = 1,
    /// `[frames, J, 4]` parent-relative rotations as quaternions x, y, z, w.
    LocalQuatXyzw = 2,
    /// `[frames, J, 4]` parent-relative rotations as quaternions w, x, y, z.
    LocalQuatWxyz = 3,
    /// `[frames, J, 3, 3]` parent-relative rotation matrices, row-major.
    LocalMatrix = 4,
    /// `[frames, J, 6]` parent-relative rotations as the first two matrix rows.
    Local6d = 5,
    /// `[frames, J, 3]` world joint positions.
    GlobalPositions = 6,
    /// `[frames, J, 4]` world rotations as quaternions x, y, z, w.
    GlobalQuatXyzw = 7,
    /// `[frames, J, 4]` world rotations as quaternions w, x, y, z.
    GlobalQuatWxyz = 8,
    /// `[frames, 4]` foot contacts (left ankle, left foot, right ankle, right foot), 0 or 1
    /// (humanml263 models' own values, ≈0 or 1, when read raw).
    FootContacts = 9,
    /// `[frames, 3]` the `root` bone's world position (on the ground under the pelvis); only
    /// with a cleanup's `FLAME_ROOT_MOTION_SEPARATE`.
    RootBone = 10,
}

/// The coordinate frame poses are expressed in (docs/conventions.md).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameConvention {
    /// The motion format's own frame, untouched.
    Native = 0,
    /// Left-handed, Y up, Z forward, metres.
    Unity = 1,
    /// Left-handed, Z up, X forward, centimetres.
    Unreal = 2,
    /// Right-handed, Z up, X forward, metres.
    Ros = 3,
    /// Right-handed, Z up, -Y forward, metres.
    Blender = 4,
    /// Right-handed, Y up, Z forward, metres.
    Gltf = 5,
}

/// Read flag: temporal Gaussian smoothing (σ = 1 frame) of the features before posing, as
/// FLAME's official output does.
pub const FLAME_READ_SMOOTH: u32 = 1;
/// Read flag: keep each quaternion's sign as computed (w ≥ 0) instead of making every joint's
/// track sign-continuous between frames.
pub const FLAME_READ_RAW_SIGNS: u32 = 2;

const LAYOUTS: [Layout; 10] = [
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

const CONVENTIONS: [Convention; 6] = [
    Convention::Native,
    Convention::Unity,
    Convention::Unreal,
    Convention::Ros,
    Convention::Blender,
    Convention::Gltf,
];

/// Joint names and parents of the model's skeleton.
pub(crate) fn skeleton(format: Format) -> (Vec<String>, Vec<i32>) {
    let s = format.skeleton();
    (
        s.joint_names().iter().map(|n| n.to_string()).collect(),
        s.parents().to_vec(),
    )
}

/// The feature channels joint `joint` owns in `format`; -1 is the root path (smpl24_6d's
/// translation, humanml263's root velocity and height channels).
pub(crate) fn joint_channels(format: Format, joint: i32) -> Result<Vec<usize>> {
    match joint {
        -1 => Ok(motion::mask::root_path_channels(format)),
        j if j >= 0 => motion::mask::joint_channels(format, j as usize),
        j => Err(invalid_arg!(
            "joint {j} is not a joint index (0..J-1, or -1 for the root path)"
        )),
    }
}

/// A C layout value that describes joint rotations (for pose references).
pub(crate) fn rotation_layout(layout: i32) -> Result<Layout> {
    match layout {
        l if l == FlameLayout::LocalQuatXyzw as i32 => Ok(Layout::LocalQuatXyzw),
        l if l == FlameLayout::LocalQuatWxyz as i32 => Ok(Layout::LocalQuatWxyz),
        l if l == FlameLayout::LocalMatrix as i32 => Ok(Layout::LocalMatrix),
        l if l == FlameLayout::Local6d as i32 => Ok(Layout::Local6d),
        l => Err(invalid_arg!(
            "layout {l} does not hold local rotations (2 quat xyzw, 3 quat wxyz, 4 matrix, 5 6D)"
        )),
    }
}

/// A C convention value.
pub(crate) fn convention(convention: i32) -> Result<Convention> {
    usize::try_from(convention)
        .ok()
        .and_then(|c| CONVENTIONS.get(c).copied())
        .ok_or_else(|| invalid_arg!("unknown convention {convention} (a FlameConvention, 0 to 5)"))
}

/// The features decoded with read `flags` (smoothing, quaternion signs).
pub(crate) fn decode(
    model: &Model,
    features: &[f32],
    frames: usize,
    flags: u32,
    finish: &motion::Finish,
) -> Result<motion::Poses> {
    let opts = motion::ReadOptions {
        finish: *finish,
        ..model.read_options(smooth_sigma(flags)?, flags & FLAME_READ_RAW_SIGNS == 0)
    };
    motion::Poses::decode(model.motion_format(), features, frames, &opts)
}

/// The smoothing σ read `flags` ask for, after checking them.
fn smooth_sigma(flags: u32) -> Result<f32> {
    if flags & !(FLAME_READ_SMOOTH | FLAME_READ_RAW_SIGNS) != 0 {
        return Err(invalid_arg!("unknown read flags {flags:#x}"));
    }
    Ok(if flags & FLAME_READ_SMOOTH != 0 {
        1.0
    } else {
        0.0
    })
}

/// The features in the requested layout, convention and flags.
pub(crate) fn read(
    model: &Model,
    features: &[f32],
    frames: usize,
    layout: i32,
    convention: i32,
    flags: u32,
    finish: &motion::Finish,
) -> Result<Vec<f32>> {
    let smooth = smooth_sigma(flags)?;
    let convention = self::convention(convention)?;
    if layout == FlameLayout::Features as i32 {
        return Ok(features.to_vec());
    }
    // Layout 0 (features) was handled above; `checked_sub` because the caller's value may be
    // i32::MIN.
    let layout = usize::try_from(layout)
        .ok()
        .and_then(|l| l.checked_sub(1))
        .and_then(|l| LAYOUTS.get(l).copied())
        .ok_or_else(|| invalid_arg!("unknown layout {layout} (a FlameLayout, 0 to 10)"))?;
    let opts = motion::ReadOptions {
        finish: *finish,
        ..model.read_options(smooth, flags & FLAME_READ_RAW_SIGNS == 0)
    };
    motion::read_layout(
        model.motion_format(),
        features,
        frames,
        layout,
        convention,
        &opts,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_layout_of_i32_min_is_an_unknown_layout() {
        // Found by the ffi_params fuzzer: `layout - 1` overflowed (a panic in debug builds).
        let model = Model::from_file(
            crate::checkpoint::ModelFile::open(std::path::Path::new(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/tests/fixtures/flame_tiny.safetensors"
            )))
            .unwrap(),
        )
        .unwrap();
        for layout in [i32::MIN, i32::MIN + 1, -1, 99, i32::MAX] {
            let err = read(&model, &[], 0, layout, 0, 0, &Default::default()).unwrap_err();
            assert!(
                err.to_string().contains("unknown layout"),
                "{layout}: {err}"
            );
        }
    }
}
