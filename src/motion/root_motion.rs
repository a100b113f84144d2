//! PLACEHOLDER (being written): root motion.
use super::finish::RootMotion;
use super::poses::Poses;

pub fn apply(_poses: &mut Poses, _mode: RootMotion, _remove_yaw: bool) {
    todo!()
}
