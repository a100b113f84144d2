//! A libflame clip as a VRM Animation (`.vrma`, VRMC_vrm_animation 1.0) (TO BE WRITTEN).

use crate::error::{invalid_arg, Result};
use crate::motion::Poses;

/// `poses` at `fps` as a `.vrma` GLB named `name`.
pub fn to_glb(poses: &Poses, fps: f64, name: &str) -> Result<Vec<u8>> {
    let _ = (poses, fps, name);
    Err(invalid_arg!("writing a VRM Animation is not built yet"))
}
