//! PLACEHOLDER (being written): loops.
use super::poses::Poses;
use crate::error::Result;

pub fn wrap(_poses: &mut Poses) -> Result<()> {
    todo!()
}
