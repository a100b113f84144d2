//! Forward kinematics and Jacobians of a [`Robot`] into a per-run [`RobotData`]: no allocation
//! after [`RobotData::new`], every output in a caller's buffer.
//!
//! **Velocity convention** (what an IK solver integrates with, [`integrate`]): a velocity is
//! `nv = 6 + n` numbers `[v_b, ω_b, q̇]`, where
//! - `v_b` is the time derivative of the base position (the root link's origin), world axes;
//! - `ω_b` is the base angular velocity in **world** axes: `Ṙ_b = [ω_b]× R_b`;
//! - `q̇` the joint velocities in the order of [`Robot::dof_names`].
//!
//! A point `p` fixed on a link then moves at `ṗ = v_b + ω_b × (p − p_b) + Σ_j J_j q̇_j` and the
//! link turns at `ω = ω_b + Σ_j a_j q̇_j` (`a_j` the world axis of a revolute joint between the
//! root and the link). [`jacobian_point`] writes the 6 × nv matrix of that map, rows
//! `[ṗ; ω]`, both in world axes ("world-aligned", Pinocchio's `LOCAL_WORLD_ALIGNED` at the
//! point — but with the base columns in world axes, where Pinocchio's free-flyer velocity is in
//! the base's local frame).

use super::model::{Moves, Robot};
use super::pose::{unit_axis_rotation, Pose};
use crate::error::{invalid_arg, Result};
use crate::motion::rotation::{self, Mat3, Vec3};

/// Per-run state of a [`Robot`]: the world pose of every link after [`forward`].
#[derive(Clone, Debug)]
pub struct RobotData {
    poses: Vec<Pose>,
}

impl RobotData {
    /// Buffers for `robot` (every link at the identity until [`forward`] runs).
    pub fn new(robot: &Robot) -> RobotData {
        RobotData {
            poses: vec![Pose::IDENTITY; robot.links().len()],
        }
    }

    /// Link `link`'s world pose (index as in [`Robot::links`]).
    pub fn link_pose(&self, link: usize) -> &Pose {
        &self.poses[link]
    }

    /// Every link's world pose, in the order of [`Robot::links`].
    pub fn link_poses(&self) -> &[Pose] {
        &self.poses
    }
}

fn check(robot: &Robot, data: &RobotData) -> Result<()> {
    if data.poses.len() != robot.links().len() {
        return Err(invalid_arg!(
            "robot data for {} links used with a robot of {}",
            data.poses.len(),
            robot.links().len()
        ));
    }
    Ok(())
}

/// Places every link: the root at `base`, each other link at its parent's pose · joint origin ·
/// the joint's motion at `q` (`q.len() == robot.dof_count()`, radians and metres). Non-finite
/// `q` gives non-finite poses; nothing is clamped to limits.
pub fn forward(robot: &Robot, base: &Pose, q: &[f64], data: &mut RobotData) -> Result<()> {
    check(robot, data)?;
    if q.len() != robot.dof_count() {
        return Err(invalid_arg!(
            "q has {} values, the robot {} degrees of freedom",
            q.len(),
            robot.dof_count()
        ));
    }
    data.poses[0] = *base;
    for (i, step) in robot.steps.iter().enumerate() {
        let parent = &data.poses[step.parent];
        let mut pose = Pose {
            rotation: if step.origin_turns {
                rotation::mul(&parent.rotation, &step.origin.rotation)
            } else {
                parent.rotation
            },
            translation: parent.point(&step.origin.translation),
        };
        let value = || step.scale * q[step.dof] + step.offset;
        match step.moves {
            Moves::No => {}
            Moves::Rotates => match step.coordinate_axis {
                Some((k, sign)) => turn_about_column(&mut pose.rotation, k, sign * value()),
                None => {
                    let turn = unit_axis_rotation(&step.axis, value());
                    pose.rotation = rotation::mul(&pose.rotation, &turn);
                }
            },
            Moves::Slides => {
                let along = rotation::apply(&pose.rotation, &step.axis);
                let v = value();
                for (t, a) in pose.translation.iter_mut().zip(along) {
                    *t += a * v;
                }
            }
        }
        data.poses[i + 1] = pose;
    }
    Ok(())
}

/// `r ← r · R_k(angle)` for the rotation about coordinate axis `k`: column `k` stays, the two
/// others (in cyclic order `a = k+1`, `b = k+2`) become `c·a + s·b` and `c·b − s·a`.
fn turn_about_column(r: &mut Mat3, k: usize, angle: f64) {
    let (s, c) = angle.sin_cos();
    let (a, b) = ((k + 1) % 3, (k + 2) % 3);
    for row in r.iter_mut() {
        let (x, y) = (row[a], row[b]);
        row[a] = c * x + s * y;
        row[b] = c * y - s * x;
    }
}

/// The 6 × nv Jacobian of the point `point` (given in link `link`'s frame) at the poses of the
/// last [`forward`], row-major into `out` (`out.len() == 6 · nv`): rows 0–2 the point's linear
/// velocity, rows 3–5 the link's angular velocity, world axes; columns as the module doc's
/// velocity. Joints that do not move the link give zero columns; a mimic joint adds its
/// multiplier times its column to its source's.
pub fn jacobian_point(
    robot: &Robot,
    data: &RobotData,
    link: usize,
    point: Vec3,
    out: &mut [f64],
) -> Result<()> {
    check(robot, data)?;
    let nv = robot.nv();
    if link >= robot.links().len() {
        return Err(invalid_arg!(
            "link {link} of a robot with {} links",
            robot.links().len()
        ));
    }
    if out.len() != 6 * nv {
        return Err(invalid_arg!(
            "the Jacobian buffer has {} values, 6 × nv = {}",
            out.len(),
            6 * nv
        ));
    }
    out.fill(0.0);
    let p = data.poses[link].point(&point);
    let base = data.poses[0].translation;
    let r = [p[0] - base[0], p[1] - base[1], p[2] - base[2]];
    // Base linear: identity on the linear rows. Base angular: e_k × r (linear), e_k (angular).
    for k in 0..3 {
        out[k * nv + k] = 1.0;
        out[(3 + k) * nv + 3 + k] = 1.0;
    }
    let columns = [[0.0, r[2], -r[1]], [-r[2], 0.0, r[0]], [r[1], -r[0], 0.0]];
    for (row, values) in columns.iter().enumerate() {
        out[row * nv + 3..row * nv + 6].copy_from_slice(values);
    }
    let mut l = link;
    while l > 0 {
        let step = &robot.steps[l - 1];
        let pose = &data.poses[l];
        let col = 6 + step.dof;
        match step.moves {
            Moves::No => {}
            Moves::Rotates => {
                // The child's frame turns about the axis through its own origin.
                let a = rotation::apply(&pose.rotation, &step.axis);
                let d = [
                    p[0] - pose.translation[0],
                    p[1] - pose.translation[1],
                    p[2] - pose.translation[2],
                ];
                let lin = rotation::cross(&a, &d);
                for k in 0..3 {
                    out[k * nv + col] += step.scale * lin[k];
                    out[(3 + k) * nv + col] += step.scale * a[k];
                }
            }
            Moves::Slides => {
                let a = rotation::apply(&pose.rotation, &step.axis);
                for k in 0..3 {
                    out[k * nv + col] += step.scale * a[k];
                }
            }
        }
        l = step.parent;
    }
    Ok(())
}

/// One explicit Euler step of the module doc's velocity `v` (`nv` values) over `dt` seconds:
/// the base position moves by `v_b·dt`, the base rotation turns by `exp([ω_b·dt]×)` on the left
/// (world axes), `q` by `q̇·dt` (not clamped to limits). The rotation stays orthonormal to
/// rounding.
pub fn integrate(robot: &Robot, base: &mut Pose, q: &mut [f64], v: &[f64], dt: f64) -> Result<()> {
    if q.len() != robot.dof_count() || v.len() != robot.nv() {
        return Err(invalid_arg!(
            "integrate: q has {} values and v {}, the robot needs {} and {}",
            q.len(),
            v.len(),
            robot.dof_count(),
            robot.nv()
        ));
    }
    for (x, dx) in base.translation.iter_mut().zip(&v[..3]) {
        *x += dx * dt;
    }
    let w = [v[3] * dt, v[4] * dt, v[5] * dt];
    let angle = rotation::dot(&w, &w).sqrt();
    if angle > 0.0 {
        let turn = unit_axis_rotation(&w.map(|x| x / angle), angle);
        base.rotation = rotation::mul(&turn, &base.rotation);
    }
    for (x, dx) in q.iter_mut().zip(&v[6..]) {
        *x += dx * dt;
    }
    Ok(())
}
