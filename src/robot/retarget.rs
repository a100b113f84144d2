//! Humanoid retargeting: a human motion (libflame's joints, [`Convention::Ros`]: +Z up, +X
//! forward, metres) onto a robot's joint trajectory, by differential inverse kinematics frame by
//! frame, in the manner of GMR (YanjieZe/GMR, `general_motion_retargeting/motion_retarget.py`):
//! body-to-joint pairs from a [`RetargetConfig`], two stages (table 1 then table 2), warm-started
//! from the previous frame.
//!
//! # Targets
//! Per table entry, the human joint's position scaled about the root (the root's own position
//! scaled by its scale, every other joint's offset from the root by its scale) plus the entry's
//! position offset turned by the target rotation, and the joint's world rotation times the
//! entry's rotation offset (GMR's `scale_human_data` and `offset_human_data`; config module doc).
//!
//! # One frame ([`Retargeter::step`])
//! Per stage, a fixed number of Gauss-Newton iterations on the weighted task errors, each a small
//! box-constrained quadratic program in the velocity `Δ = [Δbase, Δq]` (nv = 6 + n):
//!
//! `min ½ Σ_k ‖W_k (J_k Δ − e_k)‖² + ½ λ ‖Δ‖²` with `lo ≤ Δq ≤ hi`,
//!
//! as mink builds it for GMR (kevinzakka/mink: `FrameTask` errors and Jacobians, `solve_ik`): `e_k`
//! the position error (metres, world axes) and the rotation error `log(R_target R_bodyᵀ)`
//! (radians, world axes), `W_k` the entry's position and rotation weights, `λ` the configured
//! damping plus mink's Levenberg-Marquardt term `Σ_k ‖W_k e_k‖²` (its `lm_damping` 1, as GMR sets
//! it). The bounds are the joint position limits and, after the first frame, the velocity limits
//! between frames (`|q − q_prev| ≤ v_max · dt`), intersected; the base is free. The program is
//! solved by an active set on the bounds (starting from the bounds the previous solve ended on,
//! solve the free variables by Cholesky, clamp the ones that leave their box, release clamped
//! ones whose gradient points inside, a bounded number of passes), then projected on the box: limits hold exactly whatever happens, and the number of
//! operations per frame is fixed (deterministic, bit-identical between runs). Nothing allocates
//! per frame: [`RetargetState`] holds every buffer.
//!
//! # Feet and floor
//! The floor is z = 0 of the human motion's world ([`Retargeter::motion`] puts the motion's
//! lowest foot joint there). While a foot is in contact (any of its configured human contact
//! slots), its body's target becomes an **anchor**: the foot body's own target at one frame of the
//! span, flattened (rotation reduced to its yaw, so the sole is level) and set down (the body
//! origin at the sole's height above the floor). Anchored, the foot neither slides nor turns. Its
//! weights are raised to at least [`CONTACT_POSITION_WEIGHT`] and [`CONTACT_ROTATION_WEIGHT`].
//! - [`Retargeter::motion`] (whole clip): one anchor per span, the span's middle frame, and the
//!   change blended into [`BLEND_SECONDS`] of frames on either side (smoothstep weights), as
//!   Kovar, Schreiner and Gleicher plant a foot and blend the change into the neighbouring frames
//!   ("Footskate Cleanup for Motion Capture Editing", SCA 2002, section 4).
//! - [`Retargeter::step`] (a stream): the future is unknown, so the anchor is the span's first
//!   frame, held until the contact ends (no blending).
//!
//! No part of the robot goes below the floor: every iteration adds a one-sided row for each sole
//! corner under the floor (its height error, weight [`FLOOR_WEIGHT`]); after the last iteration the
//! lowest point of the sole rectangles and of every primitive collision shape (sphere, box,
//! cylinder, capsule; meshes are not read) is found analytically and the base is lifted by what
//! is missing, if anything.
//!
//! # Residual
//! Each frame reports `sqrt(Σ_k (w_p,k ‖e_p,k‖² + w_r,k ‖e_r,k‖²) / Σ_k (w_p,k + w_r,k))` over the
//! last stage's entries, at the frame's final configuration: a weighted root-mean-square in metres
//! and radians. A target out of reach gives a large residual, never an error.

use super::config::{RetargetConfig, FIRST_FRAME_FACTOR};
use super::kinematics::{forward, integrate, jacobian_point, RobotData};
use super::model::{JointMotion, Robot};
use super::pose::Pose;
use super::trajectory::Trajectory;
use super::urdf::Geometry;
use crate::error::{invalid_arg, Result};
use crate::motion::contacts::{self, ContactParams};
use crate::motion::rotation::{self, Mat3, Vec3};
use crate::motion::{Convention, Poses};

/// Minimum position weight of an anchored foot's entries: ten times the pelvis's (100 in GMR's
/// tables), so that where a planted foot and the human's pelvis cannot both be met (a foot coming
/// down a few centimetres from where the span holds it), the pelvis gives way and the foot does
/// not slide. At 100, GR1T2's sole slid 5 cm in one contact frame of a demo walk in a circle
/// (tests/robot_retarget_check.rs); at 1000 it moves at most 1.1 cm.
pub const CONTACT_POSITION_WEIGHT: f64 = 1000.0;
/// Minimum rotation weight of an anchored foot's entries: a level sole matters as much as its
/// place (GMR's G1 table 2 gives its toes 50).
pub const CONTACT_ROTATION_WEIGHT: f64 = 50.0;
/// Weight of a sole corner's height error while it is under the floor.
pub const FLOOR_WEIGHT: f64 = 100.0;
/// Seconds of frames on each side of a contact span into which [`Retargeter::motion`] blends the
/// anchor's change.
pub const BLEND_SECONDS: f64 = 0.2;
/// mink's `lm_damping` as GMR sets it for every task.
const LM_DAMPING: f64 = 1.0;
/// Added to the diagonal whatever the damping, so the system is always positive definite.
const MIN_DAMPING: f64 = 1e-9;
/// Active-set passes of the box-constrained solve.
const MAX_PASSES: usize = 8;

/// One frame of human motion in [`Convention::Ros`]: a world position and world rotation per
/// skeleton joint (22 for HumanML3D, 24 for SMPL, in libflame's order), and the foot contacts
/// (left ankle, left foot, right ankle, right foot; [`crate::motion::contacts`]).
#[derive(Clone, Copy, Debug)]
pub struct HumanFrame<'a> {
    /// World position of each joint, metres; 22 or 24 entries, as many as `rotations`.
    pub positions: &'a [Vec3],
    /// World rotation of each joint (row-major, acting on column vectors), same count.
    pub rotations: &'a [Mat3],
    /// Whether each contact slot touches the floor this frame: left ankle, left foot, right
    /// ankle, right foot. A foot's contact anchors it (module doc, "Feet and floor").
    pub contacts: [bool; 4],
}

/// A table entry ready to solve: its body's Jacobian columns and its foot, if any.
#[derive(Clone, Debug)]
struct Task {
    body: usize,
    human: usize,
    position_weight: f64,
    rotation_weight: f64,
    position_offset: Vec3,
    rotation_offset: Mat3,
    /// Jacobian columns that can be nonzero for the body (the base's six, then the degrees of
    /// freedom on its chain), ascending.
    columns: Vec<usize>,
    /// Index into the config's feet when the body is a foot.
    foot: Option<usize>,
}

/// A primitive collision shape whose lowest point the floor check finds.
#[derive(Clone, Copy, Debug)]
struct Shape {
    link: usize,
    origin: Pose,
    kind: ShapeKind,
}

#[derive(Clone, Copy, Debug)]
enum ShapeKind {
    Sphere(f64),
    Box(Vec3),
    /// Radius, half length along the shape's z; a capsule adds its radius at both ends.
    Cylinder(f64, f64),
    Capsule(f64, f64),
}

/// The immutable part of retargeting onto one robot: the robot, its configuration, the tasks
/// with their Jacobian columns, the limits. `Send + Sync`: one serves any number of
/// [`RetargetState`]s and threads.
#[derive(Clone, Debug)]
pub struct Retargeter {
    robot: Robot,
    config: RetargetConfig,
    /// Per stage in use, its active tasks; `slots[s]` is where stage `s`'s targets start in a
    /// state's target buffer.
    stages: Vec<Vec<Task>>,
    slots: Vec<usize>,
    task_count: usize,
    /// Per foot, the Jacobian columns of its body.
    foot_columns: Vec<Vec<usize>>,
    shapes: Vec<Shape>,
    /// The sparsity of the normal equations' Cholesky factor (see [`Pattern`]).
    pattern: Pattern,
}

/// The elimination order and the nonzeros of the Cholesky factor of the normal equations.
///
/// A task row touches only the base and the joints on its body's chain, so the normal matrix
/// couples two joints only when one lies on the other's path to the root. Eliminating the
/// deepest joints first (the base last) then creates no fill beyond those pairs (a tree's
/// branch-induced sparsity): the factor of GR1T2's 38 × 38 system has about a fifth of a dense
/// one's products. The fill is found once, symbolically, so any structure (mimic joints
/// included) stays exact.
#[derive(Clone, Debug)]
struct Pattern {
    /// `order[p]`: the variable eliminated at position `p`.
    order: Vec<usize>,
    /// Per position `p`, the later positions `q > p` where column `p` of the factor can be
    /// nonzero, ascending: `later[starts[p]..starts[p + 1]]`.
    starts: Vec<usize>,
    later: Vec<usize>,
}

impl Pattern {
    /// Every entry nonzero, variables in their own order.
    #[cfg(test)]
    fn dense(n: usize) -> Pattern {
        Pattern::new(&[(0..n).collect()], &vec![0; n])
    }

    /// The pattern of a matrix whose nonzeros are the diagonal and the products of every pair
    /// in each of `cliques`, eliminated deepest first (ties: the later variable first).
    fn new(cliques: &[Vec<usize>], depth: &[usize]) -> Pattern {
        let n = depth.len();
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by_key(|&v| (std::cmp::Reverse(depth[v]), std::cmp::Reverse(v)));
        let mut position = vec![0; n];
        for (p, &v) in order.iter().enumerate() {
            position[v] = p;
        }
        let mut nz = vec![false; n * n];
        for c in cliques {
            for &a in c {
                for &b in c {
                    nz[position[a] * n + position[b]] = true;
                }
            }
        }
        let mut starts = vec![0];
        let mut later = Vec::new();
        for p in 0..n {
            let first = later.len();
            later.extend((p + 1..n).filter(|&q| nz[p * n + q]));
            // Eliminating p couples every pair of its later neighbours (the fill).
            for i in first..later.len() {
                for j in first..later.len() {
                    nz[later[i] * n + later[j]] = true;
                }
            }
            starts.push(later.len());
        }
        Pattern {
            order,
            starts,
            later,
        }
    }

    fn later(&self, p: usize) -> &[usize] {
        &self.later[self.starts[p]..self.starts[p + 1]]
    }
}

/// Per-run state: the configuration, the previous frame's joints, the stream's foot anchors and
/// every buffer the solver needs. Cheap to make ([`Retargeter::state`]); one per run or thread.
#[derive(Clone, Debug)]
pub struct RetargetState {
    q: Vec<f64>,
    base: Pose,
    q_prev: Vec<f64>,
    initial_q: Vec<f64>,
    /// No frame solved since the start or [`RetargetState::reset`].
    fresh: bool,
    anchors: [Option<Pose>; 2],
    data: RobotData,
    targets: Vec<Pose>,
    jac: Vec<f64>,
    /// A task's weighted Jacobian rows on its columns (6 × the longest chain).
    rows: Vec<f64>,
    h: Vec<f64>,
    g: Vec<f64>,
    dx: Vec<f64>,
    lo: Vec<f64>,
    hi: Vec<f64>,
    clamped: Vec<bool>,
    /// The clamped variables' indices, for the right-hand side of the free solve.
    held: Vec<usize>,
    /// Per variable, the bound it ended on in the last solve (−1 lower, 1 upper, 0 free): the
    /// next solve starts from that active set, usually already the right one, so it needs one
    /// or two passes instead of rediscovering every bound.
    side: Vec<i8>,
    chol: Vec<f64>,
    rhs: Vec<f64>,
}

impl RetargetState {
    /// Joint positions after the last frame (radians, metres), in [`Robot::dof_names`] order.
    pub fn q(&self) -> &[f64] {
        &self.q
    }

    /// The floating base's world pose after the last frame.
    pub fn base(&self) -> &Pose {
        &self.base
    }

    /// The base's rotation as a unit quaternion **x, y, z, w**.
    pub fn root_rot_xyzw(&self) -> [f64; 4] {
        self.base.quat_xyzw()
    }

    /// Back to the rest configuration: the next frame is solved as a first frame (no velocity
    /// limit, more iterations, the base placed on the root's target).
    pub fn reset(&mut self) {
        self.q.copy_from_slice(&self.initial_q);
        self.q_prev.copy_from_slice(&self.initial_q);
        self.base = Pose::IDENTITY;
        self.fresh = true;
        self.anchors = [None, None];
        self.side.fill(0);
    }
}

/// The rotation vector (axis × angle, radians) of `m`, through its quaternion (stable at every
/// angle, the angle in [0, π]).
fn log_rotation(m: &Mat3) -> Vec3 {
    let [w, x, y, z] = rotation::to_quat(m);
    let s = (x * x + y * y + z * z).sqrt();
    if s < 1e-12 {
        // sin(θ/2) ≈ θ/2: the vector part doubled.
        return [2.0 * x, 2.0 * y, 2.0 * z];
    }
    let k = 2.0 * s.atan2(w) / s;
    [x * k, y * k, z * k]
}

/// The rotation by the rotation vector `v`.
fn exp_rotation(v: &Vec3) -> Mat3 {
    let angle = rotation::dot(v, v).sqrt();
    if angle < 1e-15 {
        return rotation::IDENTITY;
    }
    super::pose::unit_axis_rotation(&v.map(|x| x / angle), angle)
}

/// The rotation about +Z keeping `m`'s heading (where its x axis points, seen from above).
fn yaw_only(m: &Mat3) -> Mat3 {
    let yaw = m[1][0].atan2(m[0][0]);
    super::pose::unit_axis_rotation(&[0.0, 0.0, 1.0], yaw)
}

fn sub(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// Jacobian columns of link `link`: the base's six, then the degrees of freedom of the joints
/// between the root and the link (mimic joints through their source), ascending.
fn chain_columns(robot: &Robot, link: usize) -> Vec<usize> {
    let mut cols: Vec<usize> = (0..6).collect();
    let mut l = link;
    while let (Some(parent), Some(j)) = (robot.links()[l].parent, robot.links()[l].joint) {
        match robot.joints()[j].motion {
            JointMotion::Dof(d) | JointMotion::Mimic { dof: d, .. } => cols.push(6 + d),
            JointMotion::None => {}
        }
        l = parent;
    }
    cols.sort_unstable();
    cols.dedup();
    cols
}

impl Retargeter {
    /// Prepares retargeting onto `robot` with `config` (which must have been read against the
    /// same robot: its body indices are checked again here).
    pub fn new(robot: Robot, config: RetargetConfig) -> Result<Retargeter> {
        let links = robot.links().len();
        let bodies = config
            .stages()
            .flatten()
            .map(|e| e.body)
            .chain(config.feet.iter().map(|f| f.body))
            .chain([config.robot_root]);
        if let Some(b) = bodies.into_iter().find(|&b| b >= links) {
            return Err(invalid_arg!(
                "retarget: the configuration names body {b}, robot `{}` has {links} links (read \
                 it against this robot)",
                robot.name()
            ));
        }
        if config.initial_q.len() != robot.dof_count()
            || config.velocity_limits.len() != robot.dof_count()
        {
            return Err(invalid_arg!(
                "retarget: the configuration is for {} degrees of freedom, robot `{}` has {}",
                config.initial_q.len(),
                robot.name(),
                robot.dof_count()
            ));
        }
        let mut stages = Vec::new();
        let mut slots = Vec::new();
        let mut task_count = 0;
        for table in config.stages() {
            let tasks: Vec<Task> = table
                .iter()
                .filter(|e| e.active())
                .map(|e| Task {
                    body: e.body,
                    human: e.human,
                    position_weight: e.position_weight,
                    rotation_weight: e.rotation_weight,
                    position_offset: e.position_offset,
                    rotation_offset: e.rotation_offset,
                    columns: chain_columns(&robot, e.body),
                    foot: config.feet.iter().position(|f| f.body == e.body),
                })
                .collect();
            slots.push(task_count);
            task_count += tasks.len();
            stages.push(tasks);
        }
        let foot_columns: Vec<Vec<usize>> = config
            .feet
            .iter()
            .map(|f| chain_columns(&robot, f.body))
            .collect();
        let mut shapes = Vec::new();
        for (link, l) in robot.links().iter().enumerate() {
            for c in &l.collisions {
                let kind = match c.geometry {
                    Geometry::Sphere { radius } => ShapeKind::Sphere(radius),
                    Geometry::Box { size } => ShapeKind::Box(size.map(|s| s / 2.0)),
                    Geometry::Cylinder { radius, length } => {
                        ShapeKind::Cylinder(radius, length / 2.0)
                    }
                    Geometry::Capsule { radius, length } => {
                        ShapeKind::Capsule(radius, length / 2.0)
                    }
                    Geometry::Mesh { .. } => continue,
                };
                shapes.push(Shape {
                    link,
                    origin: c.origin,
                    kind,
                });
            }
        }
        let nv = robot.nv();
        let mut depth = vec![0; nv];
        for (l, link) in robot.links().iter().enumerate() {
            if let Some(JointMotion::Dof(d)) = link.joint.map(|j| robot.joints()[j].motion) {
                depth[6 + d] = chain_columns(&robot, l).len();
            }
        }
        let cliques: Vec<Vec<usize>> = stages
            .iter()
            .flatten()
            .map(|t: &Task| t.columns.clone())
            .chain(foot_columns.iter().cloned())
            .collect();
        let pattern = Pattern::new(&cliques, &depth);
        Ok(Retargeter {
            robot,
            config,
            stages,
            slots,
            task_count,
            foot_columns,
            shapes,
            pattern,
        })
    }

    /// The robot retargeted onto.
    pub fn robot(&self) -> &Robot {
        &self.robot
    }

    /// The configuration it was built with.
    pub fn config(&self) -> &RetargetConfig {
        &self.config
    }

    /// A run's state at the rest configuration (the config's `robot_initial_qpos`), ready for
    /// its first frame.
    pub fn state(&self) -> RetargetState {
        let nv = self.robot.nv();
        let n = self.robot.dof_count();
        RetargetState {
            q: self.config.initial_q.clone(),
            base: Pose::IDENTITY,
            q_prev: self.config.initial_q.clone(),
            initial_q: self.config.initial_q.clone(),
            fresh: true,
            anchors: [None, None],
            data: RobotData::new(&self.robot),
            targets: vec![Pose::IDENTITY; self.task_count],
            jac: vec![0.0; 6 * nv],
            rows: vec![0.0; 6 * nv],
            h: vec![0.0; nv * nv],
            g: vec![0.0; nv],
            dx: vec![0.0; nv],
            lo: vec![0.0; nv],
            hi: vec![0.0; nv],
            clamped: vec![false; nv],
            held: Vec::with_capacity(nv),
            side: vec![0; nv],
            chol: vec![0.0; nv * nv],
            rhs: vec![0.0; nv.max(n)],
        }
    }

    /// Solves one frame (module doc) from the state's configuration, `dt` seconds after the
    /// previous frame (the velocity limits' time), and returns its residual. Streamed contacts
    /// anchor a foot at the span's first frame. Allocation-free.
    pub fn step(&self, state: &mut RetargetState, frame: &HumanFrame, dt: f64) -> Result<f64> {
        self.check_frame(frame, dt)?;
        let mut anchors = [None, None];
        for (f, foot) in self.config.feet.iter().enumerate() {
            if foot.slots.iter().any(|&s| frame.contacts[s]) {
                if state.anchors[f].is_none() {
                    state.anchors[f] = self.foot_target(frame, f).map(|p| self.plant(f, &p));
                }
                anchors[f] = state.anchors[f];
            } else {
                state.anchors[f] = None;
            }
        }
        self.solve(state, frame, dt, &anchors)
    }

    /// Retargets a whole motion at `fps` frames per second (module doc): the motion is put on
    /// the floor (its lowest foot joint at z = 0), contacts detected
    /// ([`contacts::of`] with the default parameters), one anchor per contact span blended into
    /// its neighbours, then every frame solved in order from a fresh state.
    pub fn motion(&self, poses: &Poses, fps: f64) -> Result<Trajectory> {
        if !(fps.is_finite() && fps > 0.0) {
            return Err(invalid_arg!("retarget: fps must be positive, got {fps}"));
        }
        let joints = poses.joint_count();
        let frames = poses.frames();
        let mut positions = poses.positions(Convention::Ros);
        let rotations = poses.global_rotations(Convention::Ros);
        let floor = (0..frames)
            .flat_map(|t| contacts::SLOT_JOINTS.map(|j| positions[t * joints + j][2]))
            .fold(f64::INFINITY, f64::min);
        if floor.is_finite() {
            positions.iter_mut().for_each(|p| p[2] -= floor);
        }
        let contact = contacts::of(poses, fps, &ContactParams::default());
        let frame = |t: usize| HumanFrame {
            positions: &positions[t * joints..(t + 1) * joints],
            rotations: &rotations[t * joints..(t + 1) * joints],
            contacts: contact[t],
        };
        if frames > 0 {
            self.check_frame(&frame(0), 1.0 / fps)?;
        }
        let anchors = self.clip_anchors(frames, fps, &frame)?;

        let n = self.robot.dof_count();
        let mut state = self.state();
        let mut out = Trajectory {
            fps,
            robot: self.robot.name().to_string(),
            dof_names: self.robot.dof_names().to_vec(),
            root_pos: Vec::with_capacity(frames),
            root_rot_xyzw: Vec::with_capacity(frames),
            dof_pos: Vec::with_capacity(frames * n),
            residual: Vec::with_capacity(frames),
        };
        for (t, a) in anchors.iter().enumerate() {
            let residual = self.solve(&mut state, &frame(t), 1.0 / fps, a)?;
            out.root_pos.push(state.base.translation);
            out.root_rot_xyzw.push(state.root_rot_xyzw());
            out.dof_pos.extend_from_slice(&state.q);
            out.residual.push(residual);
        }
        Ok(out)
    }

    fn check_frame(&self, frame: &HumanFrame, dt: f64) -> Result<()> {
        let n = frame.positions.len();
        if n != frame.rotations.len() || !(n == 22 || n == 24) {
            return Err(invalid_arg!(
                "retarget: a frame has {n} positions and {} rotations; 22 or 24 joints each",
                frame.rotations.len()
            ));
        }
        if n < self.config.joints_needed() {
            return Err(invalid_arg!(
                "retarget: the configuration follows SMPL's hands (joints 22, 23), the motion \
                 has {n} joints"
            ));
        }
        let finite = frame.positions.iter().flatten().all(|v| v.is_finite())
            && frame
                .rotations
                .iter()
                .flatten()
                .flatten()
                .all(|v| v.is_finite());
        if !finite {
            return Err(invalid_arg!("retarget: the frame holds a non-finite value"));
        }
        if !(dt.is_finite() && dt > 0.0) {
            return Err(invalid_arg!(
                "retarget: dt must be a positive number of seconds, got {dt}"
            ));
        }
        Ok(())
    }

    /// The target of `task` for `frame` (module doc, Targets).
    fn target(&self, task: &Task, frame: &HumanFrame) -> Pose {
        let root = self.config.human_root;
        let root_pos = frame.positions[root];
        let s_root = self.config.scales[root].unwrap_or(1.0);
        let scaled_root = root_pos.map(|x| x * s_root);
        let position = if task.human == root {
            scaled_root
        } else {
            let s = self.config.scales[task.human].unwrap_or(1.0);
            let d = sub(&frame.positions[task.human], &root_pos);
            [0, 1, 2].map(|k| scaled_root[k] + s * d[k])
        };
        let r = rotation::mul(&frame.rotations[task.human], &task.rotation_offset);
        let off = rotation::apply(&r, &task.position_offset);
        Pose {
            rotation: r,
            translation: rotation::add(&position, &off),
        }
    }

    /// The foot `f`'s free target: its body's entry in the last stage that has one.
    fn foot_target(&self, frame: &HumanFrame, f: usize) -> Option<Pose> {
        self.stages
            .iter()
            .rev()
            .find_map(|s| s.iter().find(|t| t.foot == Some(f)))
            .map(|t| self.target(t, frame))
    }

    /// `target` flattened and set on the floor: yaw only, the body origin the sole's height up.
    fn plant(&self, f: usize, target: &Pose) -> Pose {
        let h = self.config.feet[f].sole.height;
        Pose {
            rotation: yaw_only(&target.rotation),
            translation: [target.translation[0], target.translation[1], h],
        }
    }

    /// Per frame, the override of each foot's target (module doc: mid-span anchors, blended).
    fn clip_anchors<'a>(
        &self,
        frames: usize,
        fps: f64,
        frame: &dyn Fn(usize) -> HumanFrame<'a>,
    ) -> Result<Vec<[Option<Pose>; 2]>> {
        let mut out = vec![[None, None]; frames];
        let blend = (BLEND_SECONDS * fps).round() as usize;
        for (f, foot) in self.config.feet.iter().enumerate() {
            let in_contact = |t: usize| foot.slots.iter().any(|&s| frame(t).contacts[s]);
            let free: Vec<Option<Pose>> = (0..frames)
                .map(|t| self.foot_target(&frame(t), f))
                .collect();
            // Best (smallest distance) blend weight so far per frame outside spans.
            let mut best = vec![usize::MAX; frames];
            let mut t = 0;
            while t < frames {
                if !in_contact(t) {
                    t += 1;
                    continue;
                }
                let start = t;
                while t < frames && in_contact(t) {
                    t += 1;
                }
                let end = t; // exclusive
                let Some(mid) = free[(start + end - 1) / 2] else {
                    continue;
                };
                let anchor = self.plant(f, &mid);
                for slot in &mut out[start..end] {
                    slot[f] = Some(anchor);
                }
                // The change at each boundary, faded out over `blend` frames.
                let sides = [
                    (start.checked_sub(1), -1isize),
                    ((end < frames).then_some(end), 1isize),
                ];
                for (first, dir) in sides {
                    let (Some(first), Some(edge)) =
                        (first, free[if dir < 0 { start } else { end - 1 }])
                    else {
                        continue;
                    };
                    let dp = sub(&anchor.translation, &edge.translation);
                    let dr = log_rotation(&rotation::mul(
                        &anchor.rotation,
                        &rotation::transpose(&edge.rotation),
                    ));
                    for d in 0..blend {
                        let u = first as isize + dir * d as isize;
                        if u < 0 || u as usize >= frames || in_contact(u as usize) {
                            break;
                        }
                        let u = u as usize;
                        if d >= best[u] {
                            continue;
                        }
                        let Some(own) = free[u] else { continue };
                        best[u] = d;
                        let x = 1.0 - (d + 1) as f64 / (blend + 1) as f64;
                        let w = x * x * (3.0 - 2.0 * x);
                        out[u][f] = Some(Pose {
                            rotation: rotation::mul(
                                &exp_rotation(&dr.map(|v| v * w)),
                                &own.rotation,
                            ),
                            translation: [0, 1, 2].map(|k| own.translation[k] + w * dp[k]),
                        });
                    }
                }
            }
        }
        Ok(out)
    }

    /// One frame with the feet's targets overridden by `anchors` (module doc).
    fn solve(
        &self,
        st: &mut RetargetState,
        frame: &HumanFrame,
        dt: f64,
        anchors: &[Option<Pose>; 2],
    ) -> Result<f64> {
        for (s, tasks) in self.stages.iter().enumerate() {
            for (i, task) in tasks.iter().enumerate() {
                st.targets[self.slots[s] + i] = match task.foot.and_then(|f| anchors[f]) {
                    Some(anchor) => anchor,
                    None => self.target(task, frame),
                };
            }
        }
        let mut iterations = self.config.iterations;
        if st.fresh {
            self.place_base(st)?;
            iterations *= FIRST_FRAME_FACTOR;
        }
        let limit_dt = (!st.fresh).then_some(dt);
        for s in 0..self.stages.len() {
            for _ in 0..iterations {
                self.iterate(st, s, anchors, limit_dt)?;
            }
        }
        forward(&self.robot, &st.base, &st.q, &mut st.data)?;
        let lowest = self.lowest_point(&st.data);
        if lowest < 0.0 {
            st.base.translation[2] -= lowest;
            forward(&self.robot, &st.base, &st.q, &mut st.data)?;
        }
        st.q_prev.copy_from_slice(&st.q);
        st.fresh = false;
        Ok(self.residual(st, anchors))
    }

    /// The first frame: the base put where the robot root's target is, the joints at rest.
    fn place_base(&self, st: &mut RetargetState) -> Result<()> {
        let root = self.config.robot_root;
        let found = self.stages.iter().enumerate().rev().find_map(|(s, tasks)| {
            tasks
                .iter()
                .position(|t| t.body == root)
                .map(|i| st.targets[self.slots[s] + i])
        });
        let Some(target) = found else {
            return Ok(());
        };
        forward(&self.robot, &Pose::IDENTITY, &st.q, &mut st.data)?;
        st.base = target.then(&st.data.link_pose(root).inverse());
        Ok(())
    }

    /// The weights of `task`, raised while its foot is anchored.
    fn weights(task: &Task, anchors: &[Option<Pose>; 2]) -> (f64, f64) {
        match task.foot.and_then(|f| anchors[f]) {
            Some(_) => (
                task.position_weight.max(CONTACT_POSITION_WEIGHT),
                task.rotation_weight.max(CONTACT_ROTATION_WEIGHT),
            ),
            None => (task.position_weight, task.rotation_weight),
        }
    }

    /// One Gauss-Newton step of stage `s` (module doc).
    fn iterate(
        &self,
        st: &mut RetargetState,
        s: usize,
        anchors: &[Option<Pose>; 2],
        limit_dt: Option<f64>,
    ) -> Result<()> {
        let robot = &self.robot;
        let nv = robot.nv();
        forward(robot, &st.base, &st.q, &mut st.data)?;
        st.h.fill(0.0);
        st.g.fill(0.0);
        let mut lm = 0.0;
        for (i, task) in self.stages[s].iter().enumerate() {
            let target = st.targets[self.slots[s] + i];
            let pose = *st.data.link_pose(task.body);
            let ep = sub(&target.translation, &pose.translation);
            let er = log_rotation(&rotation::mul(
                &target.rotation,
                &rotation::transpose(&pose.rotation),
            ));
            let (wp, wr) = Self::weights(task, anchors);
            jacobian_point(robot, &st.data, task.body, [0.0; 3], &mut st.jac)?;
            let e = [ep[0], ep[1], ep[2], er[0], er[1], er[2]];
            let w = [wp, wp, wp, wr, wr, wr];
            accumulate_task(st, nv, &task.columns, &w, &e);
            lm += wp * wp * rotation::dot(&ep, &ep) + wr * wr * rotation::dot(&er, &er);
        }
        for (f, foot) in self.config.feet.iter().enumerate() {
            let pose = *st.data.link_pose(foot.body);
            for corner in foot.sole.corners() {
                let z = pose.point(&corner)[2];
                if z >= 0.0 {
                    continue;
                }
                jacobian_point(robot, &st.data, foot.body, corner, &mut st.jac)?;
                accumulate_row(
                    st,
                    nv,
                    &self.foot_columns[f],
                    2,
                    FLOOR_WEIGHT * FLOOR_WEIGHT,
                    -z,
                );
            }
        }
        let lambda = self.config.damping + LM_DAMPING * lm + MIN_DAMPING;
        for k in 0..nv {
            st.h[k * nv + k] += lambda;
        }
        // Bounds on Δ: the base is free; joints keep their limits and, after the first frame,
        // their velocity limits from the previous frame.
        let limits = robot.joint_limits();
        for k in 0..6 {
            st.lo[k] = f64::NEG_INFINITY;
            st.hi[k] = f64::INFINITY;
        }
        for d in 0..robot.dof_count() {
            let q = st.q[d];
            let (mut lo, mut hi) = (limits.lower[d] - q, limits.upper[d] - q);
            if let Some(dt) = limit_dt {
                let v = self.config.velocity_limits[d] * dt;
                lo = lo.max(st.q_prev[d] - v - q);
                hi = hi.min(st.q_prev[d] + v - q);
            }
            // q is inside both boxes, so 0 is in [lo, hi] up to rounding.
            st.lo[6 + d] = lo.min(0.0);
            st.hi[6 + d] = hi.max(0.0);
        }
        solve_box(st, &self.pattern, nv);
        let RetargetState {
            base,
            q,
            dx,
            q_prev,
            ..
        } = st;
        integrate(robot, base, q, dx, 1.0)?;
        for d in 0..q.len() {
            let mut lo = limits.lower[d];
            let mut hi = limits.upper[d];
            if let Some(dt) = limit_dt {
                let v = self.config.velocity_limits[d] * dt;
                lo = lo.max(q_prev[d] - v);
                hi = hi.min(q_prev[d] + v);
            }
            q[d] = q[d].clamp(lo.min(hi), hi);
        }
        Ok(())
    }

    /// The lowest height of the sole rectangles and of the primitive collision shapes.
    fn lowest_point(&self, data: &RobotData) -> f64 {
        let mut lowest = f64::INFINITY;
        for foot in &self.config.feet {
            let pose = data.link_pose(foot.body);
            for c in foot.sole.corners() {
                lowest = lowest.min(pose.point(&c)[2]);
            }
        }
        for shape in &self.shapes {
            let pose = data.link_pose(shape.link).then(&shape.origin);
            let r = &pose.rotation;
            let cz = pose.translation[2];
            let az = r[2][2].abs();
            let side = (1.0 - az * az).max(0.0).sqrt();
            let z = match shape.kind {
                ShapeKind::Sphere(radius) => cz - radius,
                ShapeKind::Box(half) => cz - (0..3).map(|k| r[2][k].abs() * half[k]).sum::<f64>(),
                ShapeKind::Cylinder(radius, half) => cz - half * az - radius * side,
                ShapeKind::Capsule(radius, half) => cz - half * az - radius,
            };
            lowest = lowest.min(z);
        }
        lowest
    }

    /// The residual of the last stage at the state's poses (module doc).
    fn residual(&self, st: &RetargetState, anchors: &[Option<Pose>; 2]) -> f64 {
        let Some(s) = self.stages.len().checked_sub(1) else {
            return 0.0;
        };
        let (mut sum, mut weight) = (0.0, 0.0);
        for (i, task) in self.stages[s].iter().enumerate() {
            let target = &st.targets[self.slots[s] + i];
            let pose = st.data.link_pose(task.body);
            let ep = sub(&target.translation, &pose.translation);
            let er = log_rotation(&rotation::mul(
                &target.rotation,
                &rotation::transpose(&pose.rotation),
            ));
            let (wp, wr) = Self::weights(task, anchors);
            sum += wp * rotation::dot(&ep, &ep) + wr * rotation::dot(&er, &er);
            weight += wp + wr;
        }
        if weight > 0.0 {
            (sum / weight).sqrt()
        } else {
            0.0
        }
    }
}

/// Adds row `row` of the Jacobian in `st.jac`, weighted by `w2`, with error `e`, to the normal
/// equations `h Δ = g` over the columns `cols` (the only ones the row can touch).
fn accumulate_row(st: &mut RetargetState, nv: usize, cols: &[usize], row: usize, w2: f64, e: f64) {
    let j = &st.jac[row * nv..(row + 1) * nv];
    for &a in cols {
        let ja = j[a];
        if ja == 0.0 {
            continue;
        }
        st.g[a] += w2 * ja * e;
        let h = &mut st.h[a * nv..(a + 1) * nv];
        for &b in cols {
            h[b] += w2 * ja * j[b];
        }
    }
}

/// Adds a task's six rows of `st.jac` (weights `w`, errors `e`) to `h Δ = g` over `cols`: the
/// rows gathered on the chain's columns once, each pair of columns summed over the six rows
/// once, and written to both triangles.
fn accumulate_task(st: &mut RetargetState, nv: usize, cols: &[usize], w: &[f64; 6], e: &[f64; 6]) {
    let m = cols.len();
    // Column-major: the six weighted entries of column a at rows[6a..6a + 6].
    for (a, &c) in cols.iter().enumerate() {
        let mut grad = 0.0;
        for r in 0..6 {
            let v = w[r] * st.jac[r * nv + c];
            st.rows[6 * a + r] = v;
            grad += v * w[r] * e[r];
        }
        st.g[c] += grad;
    }
    for a in 0..m {
        let ca = &st.rows[6 * a..6 * a + 6];
        let row = cols[a] * nv;
        for b in 0..=a {
            let cb = &st.rows[6 * b..6 * b + 6];
            let mut sum = 0.0;
            for r in 0..6 {
                sum += ca[r] * cb[r];
            }
            st.h[row + cols[b]] += sum;
            if b != a {
                st.h[cols[b] * nv + cols[a]] += sum;
            }
        }
    }
}

/// `min ½ Δᵀ H Δ − gᵀ Δ` with `lo ≤ Δ ≤ hi` into `st.dx` (module doc: an active set on the
/// bounds, a bounded number of passes, then projected on the box).
fn solve_box(st: &mut RetargetState, pattern: &Pattern, n: usize) {
    for k in 0..n {
        let (lo, hi) = (st.lo[k], st.hi[k]);
        let (clamped, dx) = match st.side.get(k) {
            Some(-1) if lo.is_finite() => (true, lo),
            Some(1) if hi.is_finite() => (true, hi),
            _ => (false, 0.0),
        };
        st.clamped[k] = clamped;
        st.dx[k] = dx;
    }
    for _ in 0..MAX_PASSES {
        solve_free(st, pattern, n);
        let mut changed = false;
        for k in 0..n {
            if st.clamped[k] {
                continue;
            }
            if st.dx[k] < st.lo[k] {
                st.dx[k] = st.lo[k];
                st.clamped[k] = true;
                changed = true;
            } else if st.dx[k] > st.hi[k] {
                st.dx[k] = st.hi[k];
                st.clamped[k] = true;
                changed = true;
            }
        }
        if changed {
            continue;
        }
        // Release the clamped variable whose gradient points most into its box.
        let mut release = None;
        let mut most = 0.0;
        for k in 0..n {
            if !st.clamped[k] {
                continue;
            }
            let row = &st.h[k * n..(k + 1) * n];
            let grad = st.g[k] - row.iter().zip(&st.dx).map(|(a, b)| a * b).sum::<f64>();
            // Descent direction is +grad: inward at the lower bound when grad > 0, at the upper
            // when grad < 0.
            let inward = if st.dx[k] <= st.lo[k] { grad } else { -grad };
            if inward > most {
                most = inward;
                release = Some(k);
            }
        }
        match release {
            Some(k) => st.clamped[k] = false,
            None => break,
        }
    }
    for k in 0..n {
        st.dx[k] = st.dx[k].clamp(st.lo[k], st.hi[k]);
        if let Some(side) = st.side.get_mut(k) {
            *side = match (st.clamped[k], st.dx[k] <= st.lo[k]) {
                (false, _) => 0,
                (true, true) => -1,
                (true, false) => 1,
            };
        }
    }
}

/// Solves the free variables of `h Δ = g` with the clamped ones held at their values: a
/// Cholesky factor over `pattern` (clamped variables as identity rows, their values in the
/// right-hand side) in `st.chol` (positions of `pattern.order`, lower triangle), `st.rhs`.
fn solve_free(st: &mut RetargetState, pattern: &Pattern, n: usize) {
    let order = &pattern.order;
    st.held.clear();
    st.held.extend((0..n).filter(|&k| st.clamped[k]));
    let (h, chol, rhs) = (&st.h, &mut st.chol, &mut st.rhs);
    for p in 0..n {
        let i = order[p];
        if st.clamped[i] {
            chol[p * n + p] = 1.0;
            for &q in pattern.later(p) {
                chol[q * n + p] = 0.0;
            }
            rhs[p] = st.dx[i];
            continue;
        }
        let mut r = st.g[i];
        for &k in &st.held {
            r -= h[i * n + k] * st.dx[k];
        }
        rhs[p] = r;
        chol[p * n + p] = h[i * n + i];
        for &q in pattern.later(p) {
            let j = order[q];
            chol[q * n + p] = if st.clamped[j] { 0.0 } else { h[j * n + i] };
        }
    }
    // Right-looking, in place: column p of L, then its outer product off the later columns.
    for p in 0..n {
        let d = chol[p * n + p].max(MIN_DAMPING).sqrt();
        chol[p * n + p] = d;
        let later = pattern.later(p);
        for &q in later {
            chol[q * n + p] /= d;
        }
        for (x, &q) in later.iter().enumerate() {
            let lq = chol[q * n + p];
            if lq == 0.0 {
                continue;
            }
            for &r in &later[..=x] {
                chol[q * n + r] -= lq * chol[r * n + p];
            }
        }
    }
    for p in 0..n {
        let y = rhs[p] / chol[p * n + p];
        rhs[p] = y;
        for &q in pattern.later(p) {
            rhs[q] -= chol[q * n + p] * y;
        }
    }
    for p in (0..n).rev() {
        let mut sum = rhs[p];
        for &q in pattern.later(p) {
            sum -= chol[q * n + p] * rhs[q];
        }
        rhs[p] = sum / chol[p * n + p];
    }
    for (p, &i) in order.iter().enumerate() {
        st.dx[i] = rhs[p];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_and_exp_invert_each_other_at_every_angle() {
        for (axis, angle) in [
            ([1.0, 2.0, -0.5], 0.3),
            ([0.0, 0.0, 1.0], 3.0),
            ([-1.0, 0.2, 0.1], 1e-9),
            ([0.3, -0.4, 0.5], std::f64::consts::PI - 1e-7),
        ] {
            let n = rotation::dot(&axis, &axis).sqrt();
            let v: Vec3 = axis.map(|x| x / n * angle);
            let back = log_rotation(&exp_rotation(&v));
            for k in 0..3 {
                assert!((back[k] - v[k]).abs() < 1e-9, "{v:?} → {back:?}");
            }
        }
        let yaw = yaw_only(&rotation::mul(
            &exp_rotation(&[0.0, 0.0, 0.7]),
            &exp_rotation(&[0.2, -0.3, 0.0]),
        ));
        assert!((yaw[2][2] - 1.0).abs() < 1e-15);
    }

    /// The box-constrained solve against the best of every active set, on 3 variables (one
    /// free, two boxed), for problems where the optimum is inside, on one bound, on both.
    #[test]
    fn the_box_solve_finds_the_constrained_minimum() {
        let robot = Robot::from_urdf(r#"<robot name="r"><link name="a"/></robot>"#).unwrap();
        let config = RetargetConfig::from_json(
            r#"{"robot_root_name": "a", "human_root_name": "Pelvis", "ground_height": 0,
                "human_height_assumption": 1.66, "use_ik_match_table1": true,
                "use_ik_match_table2": false, "human_scale_table": {"Pelvis": 1},
                "ik_match_table1": {"a": ["Pelvis", 1, 1, [0, 0, 0], [1, 0, 0, 0]]},
                "ik_match_table2": {}}"#,
            &robot,
        )
        .unwrap();
        let r = Retargeter::new(robot, config).unwrap();
        let mut st = r.state();
        let n = 3;
        let h = [4.0, 1.0, 0.5, 1.0, 3.0, -0.8, 0.5, -0.8, 2.0];
        let objective = |x: &[f64], g: &[f64]| {
            let mut v = 0.0;
            for a in 0..n {
                v -= g[a] * x[a];
                for b in 0..n {
                    v += 0.5 * x[a] * h[a * n + b] * x[b];
                }
            }
            v
        };
        for g in [[0.1, 0.2, -0.1], [5.0, -4.0, 3.0], [-6.0, 0.5, -7.0]] {
            st.lo[..3].copy_from_slice(&[f64::NEG_INFINITY, -0.5, -1.0]);
            st.hi[..3].copy_from_slice(&[f64::INFINITY, 0.5, 0.2]);
            // `solve_box` reads `n` as the row stride: a 3 × 3 problem in the state's buffers.
            st.h = h.to_vec();
            st.g = g.to_vec();
            solve_box(&mut st, &Pattern::dense(n), n);
            let got = st.dx[..3].to_vec();
            // Exhaustive: every variable free, at its lower or at its upper bound.
            let mut best = f64::INFINITY;
            for code in 0..9 {
                let fix = [code % 3, code / 3];
                let mut probe = r.state();
                probe.h = h.to_vec();
                probe.g = g.to_vec();
                probe.clamped = vec![false, fix[0] != 0, fix[1] != 0];
                probe.dx = vec![0.0, [0.0, -0.5, 0.5][fix[0]], [0.0, -1.0, 0.2][fix[1]]];
                solve_free(&mut probe, &Pattern::dense(n), n);
                let x = &probe.dx[..3];
                if x[1] >= -0.5 - 1e-12
                    && x[1] <= 0.5 + 1e-12
                    && x[2] >= -1.0 - 1e-12
                    && x[2] <= 0.2 + 1e-12
                {
                    best = best.min(objective(x, &g));
                }
            }
            assert!(got[1].abs() <= 0.5 && (-1.0..=0.2).contains(&got[2]));
            assert!((objective(&got, &g) - best).abs() < 1e-12, "{got:?}");
        }
    }
}
