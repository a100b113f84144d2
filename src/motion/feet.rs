//! PLACEHOLDER (being written): the floor and foot locking.
use super::poses::Poses;
use crate::error::Result;

pub fn put_on_ground(_poses: &mut Poses, _contacts: &[[bool; 4]]) {
    todo!()
}

pub fn lock(_poses: &mut Poses, _contacts: &[[bool; 4]], _fps: f64) -> Result<()> {
    todo!()
}
