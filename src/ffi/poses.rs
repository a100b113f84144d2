//! What the C ABI needs from the motion formats: skeleton tables, which feature channels a
//! joint owns (for keep-masks), and pose layouts for `flame_session_read`.

use std::ops::Range;

use crate::error::{invalid_arg, Result};

/// Joint names and parents of a motion format's skeleton (empty when the format has none).
pub(crate) fn skeleton(format: &str) -> (Vec<String>, Vec<i32>) {
    let _ = format;
    (Vec::new(), Vec::new())
}

/// The feature channels joint `joint` owns in `format`; -1 is the root translation.
pub(crate) fn joint_channels(format: &str, joint: i32) -> Result<Range<usize>> {
    match format {
        // REFERENCE 1.14: channels 0..3 root translation, then 6D rotations of 24 joints.
        "smpl24_6d" => match joint {
            -1 => Ok(0..3),
            0..=23 => {
                let j = joint as usize;
                Ok(3 + 6 * j..3 + 6 * j + 6)
            }
            _ => Err(invalid_arg!(
                "joint {joint} is not a smpl24_6d joint (0..=23, or -1 for the root translation)"
            )),
        },
        other => Err(invalid_arg!(
            "keeping joints is not supported for the `{other}` motion format"
        )),
    }
}

/// Features in the requested layout. Layout 0 is the raw features (frames × feature_dim).
pub(crate) fn read(
    format: &str,
    features: &[f32],
    frames: usize,
    layout: i32,
    convention: i32,
    flags: u32,
) -> Result<Vec<f32>> {
    let _ = (format, frames, convention, flags);
    match layout {
        0 => Ok(features.to_vec()),
        other => Err(invalid_arg!("unknown layout {other}")),
    }
}
