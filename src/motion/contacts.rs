//! PLACEHOLDER (being written): foot contacts per foot joint and frame.
use super::poses::Poses;
use crate::error::Result;

/// How smpl24_6d contacts are detected.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ContactParams {
    pub height: f64,
    pub speed: f64,
    pub min_frames: usize,
}

impl Default for ContactParams {
    fn default() -> Self {
        ContactParams {
            height: 0.05,
            speed: 0.5,
            min_frames: 2,
        }
    }
}

impl ContactParams {
    pub fn validate(&self) -> Result<()> {
        todo!()
    }
}

/// `[frames]` contacts `[L ankle, L foot, R ankle, R foot]`.
pub fn of(_poses: &Poses, _fps: f64, _params: &ContactParams) -> Vec<[bool; 4]> {
    todo!()
}
