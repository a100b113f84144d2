//! A robot joint trajectory: what retargeting a human motion onto a robot hands back, and what the
//! exporters write (BeyondMimic's CSV, GMR's fields, MuJoCo's qpos).
//!
//! Quaternion order is part of every name that holds one: `root_rot_xyzw` is x, y, z, w (GMR's
//! `root_rot`, BeyondMimic's CSV columns); MuJoCo's qpos is w first and is produced on export,
//! never stored.

use crate::error::{invalid_arg, Result};

/// Per-frame floating-base pose and joint positions of a robot, in the robot's world (URDF: +Z up,
/// metres, radians). Frames are rows; `dof_pos` is row-major `frames × dof_names.len()`, columns in
/// the order of `dof_names` (the robot's degrees of freedom in URDF document order,
/// [`super::Robot::dof_names`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Trajectory {
    /// Frames per second of the rows.
    pub fps: f64,
    /// The robot's name (the URDF `<robot name>`).
    pub robot: String,
    /// Degree-of-freedom names, the columns of `dof_pos`.
    pub dof_names: Vec<String>,
    /// World position of the floating base (the root link's origin), metres.
    pub root_pos: Vec<[f64; 3]>,
    /// World orientation of the floating base, unit quaternion x, y, z, w.
    pub root_rot_xyzw: Vec<[f64; 4]>,
    /// Joint positions, radians (metres for prismatic joints), `frames × dofs`, row-major.
    pub dof_pos: Vec<f64>,
    /// Per frame, the weighted task residual the solver ended the frame with (the square root of
    /// the weighted sum of squared position errors in metres and orientation errors in radians):
    /// a robot that cannot reach a target shows it here instead of failing.
    pub residual: Vec<f64>,
}

impl Trajectory {
    /// Number of frames.
    pub fn frames(&self) -> usize {
        self.root_pos.len()
    }

    /// Number of degrees of freedom (columns of `dof_pos`).
    pub fn dofs(&self) -> usize {
        self.dof_names.len()
    }

    /// Joint positions of frame `t`.
    pub fn dof_row(&self, t: usize) -> &[f64] {
        let n = self.dofs();
        &self.dof_pos[t * n..(t + 1) * n]
    }

    /// Checks that every per-frame array has one entry per frame, that `dof_pos` is
    /// `frames × dofs`, that every value is finite and the fps positive.
    pub fn validate(&self) -> Result<()> {
        let t = self.frames();
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return Err(invalid_arg!(
                "trajectory fps {} is not a positive number",
                self.fps
            ));
        }
        if self.root_rot_xyzw.len() != t || self.residual.len() != t {
            return Err(invalid_arg!(
                "trajectory has {} root positions, {} root rotations and {} residuals",
                t,
                self.root_rot_xyzw.len(),
                self.residual.len()
            ));
        }
        if self.dof_pos.len() != t * self.dofs() {
            return Err(invalid_arg!(
                "trajectory dof_pos has {} values, expected {} frames × {} dofs",
                self.dof_pos.len(),
                t,
                self.dofs()
            ));
        }
        let finite = self.root_pos.iter().flatten().all(|v| v.is_finite())
            && self.root_rot_xyzw.iter().flatten().all(|v| v.is_finite())
            && self.dof_pos.iter().all(|v| v.is_finite());
        if !finite {
            return Err(invalid_arg!("trajectory holds a non-finite value"));
        }
        Ok(())
    }
}
