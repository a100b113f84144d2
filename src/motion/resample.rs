//! PLACEHOLDER (being written): frame-rate resampling.
use super::poses::Poses;
use crate::error::Result;

pub fn resample(_poses: &Poses, _from_fps: f64, _to_fps: f64) -> Result<Poses> {
    todo!()
}
