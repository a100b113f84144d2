//! The user's glTF/GLB/VRM file handed back with a retargeted animation added (TO BE WRITTEN).

use super::pose::RigMotion;
use super::rig::Rig;
use crate::error::{invalid_arg, Result};

/// `original` (the bytes the rig was read from, `.glb`/`.vrm` or `.gltf`) with `motion` added as
/// the animation `name`, in the same container; an animation of that name written by libflame
/// before is replaced.
pub fn write(original: &[u8], rig: &Rig, motion: &RigMotion, name: &str) -> Result<Vec<u8>> {
    let _ = (original, rig, motion, name);
    Err(invalid_arg!("writing a rig's glTF is not built yet"))
}
