//! A retargeted clip as a BVH on the rig's own hierarchy and names (TO BE WRITTEN).

use super::pose::RigMotion;
use super::rig::Rig;
use crate::error::{invalid_arg, Result};

/// `motion` on `rig` as BVH text.
pub fn to_string(rig: &Rig, motion: &RigMotion) -> Result<String> {
    let _ = (rig, motion);
    Err(invalid_arg!("writing a rig's BVH is not built yet"))
}
