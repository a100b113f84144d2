//! Robots from their URDF: the kinematic tree, forward kinematics and Jacobians that humanoid
//! retargeting (IK onto a robot) is built on. Poses in, poses out: nothing here knows about
//! sessions, models or the C ABI.
//!
//! As in Pinocchio and MuJoCo, the model and the per-run data are apart:
//! - [`Robot`] ([`model`]): immutable, shareable, read once by [`Robot::from_urdf`]
//!   ([`urdf`] is the reader). Links parents first (`links()`, `link_index(name)`), joints,
//!   degrees of freedom in URDF document order (`dof_names()`, the order of `q`), limits per
//!   degree of freedom (`joint_limits()`: lower, upper, velocity, effort; ±∞ for continuous
//!   joints), `nq() = 7 + n` (base position, quaternion x, y, z, w, joints) and `nv() = 6 + n`,
//!   and MuJoCo's joint order (`mujoco_joint_order()`).
//! - [`RobotData`] ([`kinematics`]): per-run buffers, made once with [`RobotData::new`].
//!   [`forward`]`(&robot, &base, &q, &mut data)` places every link (`data.link_pose(i)`: a
//!   [`Pose`], rotation matrix + translation, world frame); [`jacobian_point`]`(&robot, &data,
//!   link, point_in_link, &mut out)` writes the 6 × nv world-aligned Jacobian of a point fixed on
//!   a link, row-major; [`integrate`] steps a configuration by a velocity in the same
//!   convention. None of the three allocates.
//!
//! - Retargeting a human motion onto the robot ([`retarget`]): a [`RetargetConfig`] ([`config`],
//!   GMR's IK-table JSON plus feet and solver keys; `robots/<name>.json` ships for GR1T2,
//!   JVRC-1, G1 and H1, found by [`load_default_config`]), an immutable [`Retargeter`] and a
//!   per-run [`RetargetState`]: `step` solves one [`HumanFrame`], `motion` a whole clip into a
//!   [`Trajectory`].
//!
//! Units: metres and radians, `f64` throughout. A floating base is always there (module doc of
//! [`model`]): for a fixed-base robot, give the identity as base and ignore the first six
//! Jacobian columns.
//!
//! ```
//! use flame::robot::{forward, jacobian_point, Pose, Robot, RobotData};
//! let robot = Robot::from_urdf(r#"<robot name="arm">
//!   <link name="base"/><link name="tip"/>
//!   <joint name="shoulder" type="revolute">
//!     <parent link="base"/><child link="tip"/><origin xyz="0 0 1"/><axis xyz="0 1 0"/>
//!     <limit lower="-1" upper="1" velocity="2" effort="10"/>
//!   </joint></robot>"#)?;
//! let mut data = RobotData::new(&robot);
//! forward(&robot, &Pose::IDENTITY, &[0.5], &mut data)?;
//! let tip = robot.link_index("tip").unwrap();
//! let mut jac = vec![0.0; 6 * robot.nv()];
//! jacobian_point(&robot, &data, tip, [1.0, 0.0, 0.0], &mut jac)?;
//! assert_eq!((robot.nq(), robot.nv()), (8, 7));
//! # Ok::<(), flame::Error>(())
//! ```
//!
//! [`Robot`]: crate::robot::Robot
//! [`model`]: crate::robot::model
//! [`Robot::from_urdf`]: crate::robot::Robot::from_urdf
//! [`urdf`]: crate::robot::urdf
//! [`RobotData`]: crate::robot::RobotData
//! [`kinematics`]: crate::robot::kinematics
//! [`RobotData::new`]: crate::robot::RobotData::new
//! [`forward`]: crate::robot::forward
//! [`Pose`]: crate::robot::Pose
//! [`jacobian_point`]: crate::robot::jacobian_point
//! [`integrate`]: crate::robot::integrate
//! [`retarget`]: crate::robot::retarget
//! [`RetargetConfig`]: crate::robot::RetargetConfig
//! [`config`]: crate::robot::config
//! [`load_default_config`]: crate::robot::load_default_config
//! [`Retargeter`]: crate::robot::Retargeter
//! [`RetargetState`]: crate::robot::RetargetState
//! [`HumanFrame`]: crate::robot::HumanFrame
//! [`Trajectory`]: crate::robot::Trajectory

pub mod config;
pub mod export;
pub mod kinematics;
pub mod model;
pub mod pose;
pub mod retarget;
pub mod trajectory;
pub mod urdf;

pub use config::{
    default_config_path, load_default_config, Foot, MatchEntry, RetargetConfig, Sole,
};
pub use kinematics::{forward, integrate, jacobian_point, RobotData};
pub use model::{Joint, JointKind, JointLimits, JointMotion, Link, Robot};
pub use pose::Pose;
pub use retarget::{HumanFrame, RetargetState, Retargeter};
pub use trajectory::Trajectory;
pub use urdf::{Collision, Geometry};
