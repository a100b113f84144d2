//! The hand-over to the user's character: poses in, poses out. A [`Rig`] is the user's
//! skeleton, read from their file; a bone map pairs libflame's joints with its bones; the
//! retarget carries rotations across with the rest-relative transform of the VRM Animation
//! specification (vrm-c/vrm-specification, `VRMC_vrm_animation-1.0/how_to_transform_human_pose.md`)
//! that three-vrm, Unity, Unreal's IK Retargeter and Rokoko share.
//!
//! Nothing here knows about sessions, models or the C ABI: it takes poses (local rotations and
//! a root translation in a convention) and gives poses.
//!
//! [`Rig`]: crate::retarget::Rig

pub mod bonemap;
pub mod bvh_out;
pub mod bvh_rig;
pub mod engine;
pub mod gltf_motion;
pub mod gltf_out;
pub mod gltf_rig;
pub mod pose;
pub mod rig;
pub mod target;
pub mod transfer;
pub mod vrma;

pub use pose::{Options, RigMotion, RigPose};
pub use rig::{BoneSpec, RestTransform, Rig, RigSource, VrmVersion};
pub use target::Target;
pub use transfer::Transfer;
