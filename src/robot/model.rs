//! [`Robot`]: the kinematic tree of a URDF, immutable and shareable (`Send + Sync`; one robot
//! serves any number of [`super::RobotData`] and threads).
//!
//! - **Links** are held parents first, in a depth-first walk from the root that visits a link's
//!   children in the document order of their joints: the order MuJoCo gives the bodies of a
//!   URDF it compiles (its `mjXURDF::AddToTree`). Link 0 is the root.
//! - **The floating base** is implicit at the root link: its world pose is an input of
//!   [`super::forward`], never a joint of the file. A root link named `world` with a single
//!   `fixed` or `floating` joint (a URDF bolted to, or floating in, a world frame) is dropped with
//!   that joint: its child is the root and the base pose places it; the joint's origin is kept
//!   as [`Robot::world_mount`] and not applied. Any other `world` root is an ordinary link (a
//!   fixed-base arm: give it the identity as base pose).
//! - **Degrees of freedom** are the revolute, continuous and prismatic joints that mimic no other
//!   joint, in URDF document order ([`Robot::dof_names`]): the joint vector `q` of every call,
//!   and the order users see. The full configuration is `nq = 7 + n` numbers, base position then
//!   base quaternion **x, y, z, w** then `q` (Pinocchio's free-flyer layout, BeyondMimic's CSV
//!   columns), and a velocity is `nv = 6 + n`: base linear velocity, base angular velocity (both
//!   in world axes, see [`super::kinematics`]) then `q̇`.
//! - **MuJoCo's order** ([`Robot::mujoco_joint_order`]): MuJoCo compiling a URDF makes one hinge
//!   or slide per revolute, continuous or prismatic joint, in the order of its bodies (above), so
//!   its `qpos` after the free joint holds the joints in that depth-first order, mimic joints
//!   included (MuJoCo ignores `<mimic>`: they become independent joints). On GR1T2 and JVRC-1 the
//!   two orders coincide; a file whose joints are not listed depth-first differs.
//!   (Pinocchio also walks depth first, but visits children in the order urdfdom keeps them,
//!   sorted by joint name: compare with it by name.)
//! - **Mimic joints** are handled, not refused: a joint with `<mimic joint="s" multiplier="m"
//!   offset="o">` is at `m · q_s + o` and is not a degree of freedom; chains of mimics are
//!   followed to their independent joint. The mimic joint's own limits are kept on the
//!   [`Joint`] but do not enter [`Robot::joint_limits`].
//! - **Refused** (each an error naming the joint or link): a joint whose parent or child link does
//!   not exist, a link with two parents, a cycle, several roots (or none), a `floating` joint
//!   inside the tree, a `planar` joint, a mimic naming a missing or fixed joint, or mimics that
//!   form a cycle.

use std::collections::HashMap;

use super::pose::Pose;
use super::urdf::{self, Collision, JointType, Limit, Urdf};
use crate::error::{invalid_arg, Result};
use crate::motion::rotation::{Vec3, IDENTITY};

/// What a joint does with its position.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JointKind {
    /// A rotation about the axis, between limits.
    Revolute,
    /// A rotation about the axis, unbounded.
    Continuous,
    /// A translation along the axis.
    Prismatic,
    /// No motion.
    Fixed,
}

/// Where a joint's position comes from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum JointMotion {
    /// A fixed joint.
    None,
    /// Degree of freedom `q[dof]`.
    Dof(usize),
    /// `multiplier · q[dof] + offset` (a `<mimic>`, followed to its independent joint).
    Mimic {
        /// Index into `q` of the independent joint at the end of the mimic chain.
        dof: usize,
        /// Product of the chain's multipliers.
        multiplier: f64,
        /// The chain's offsets composed (radians or metres).
        offset: f64,
    },
}

/// A joint between two links.
#[derive(Clone, Debug, PartialEq)]
pub struct Joint {
    /// `<joint name>`, unique in the robot.
    pub name: String,
    /// The joint's type (a `floating` joint is only ever the dropped `world` joint, and `planar`
    /// is refused, so four kinds remain).
    pub kind: JointKind,
    /// Link index (into [`Robot::links`]).
    pub parent: usize,
    /// Link index (into [`Robot::links`]).
    pub child: usize,
    /// The joint frame in the parent link's frame; the child link's frame at position 0.
    pub origin: Pose,
    /// Unit axis in the joint frame (`[1, 0, 0]` for a fixed joint that gives none).
    pub axis: Vec3,
    /// As the file gives it (a continuous joint's lower/upper are not limits).
    pub limit: Option<Limit>,
    /// Where its position comes from: a degree of freedom, a mimic of one, or none (fixed).
    pub motion: JointMotion,
}

/// A rigid body of the tree.
#[derive(Clone, Debug, PartialEq)]
pub struct Link {
    /// `<link name>`, unique in the robot ([`Robot::link_index`] finds it).
    pub name: String,
    /// `None` for the root (link 0); always a smaller index otherwise.
    pub parent: Option<usize>,
    /// The joint (index into [`Robot::joints`]) between the parent and this link.
    pub joint: Option<usize>,
    /// Collision shapes in this link's frame, as the file lists them.
    pub collisions: Vec<Collision>,
}

/// Per degree of freedom (the order of [`Robot::dof_names`]): position limits (±∞ for a
/// continuous joint), velocity and effort limits (+∞ when the file gives none).
#[derive(Clone, Debug, PartialEq)]
pub struct JointLimits {
    /// Lowest position, radians (revolute) or metres (prismatic); -∞ for a continuous joint.
    pub lower: Vec<f64>,
    /// Highest position, same units; +∞ for a continuous joint.
    pub upper: Vec<f64>,
    /// Largest speed, rad/s or m/s, ≥ 0.
    pub velocity: Vec<f64>,
    /// Largest torque (N·m) or force (N), ≥ 0, as the file states it.
    pub effort: Vec<f64>,
}

/// How link `i + 1` is placed from its parent, precomputed for [`super::forward`] and the
/// Jacobians (one flat array, no lookups through joints).
#[derive(Clone, Copy, Debug)]
pub(super) struct Step {
    pub parent: usize,
    pub origin: Pose,
    /// Whether `origin.rotation` differs from the identity (most URDF joints have no `rpy`:
    /// their product is skipped).
    pub origin_turns: bool,
    pub axis: Vec3,
    /// `(k, ±1)` when the axis is `±e_k`: the joint's rotation then mixes two columns of the
    /// frame instead of a whole matrix product (humanoid joints turn about x, y or z).
    pub coordinate_axis: Option<(usize, f64)>,
    pub moves: Moves,
    /// Column of `q` (meaningless when `moves` is `Moves::No`).
    pub dof: usize,
    /// Position = `scale · q[dof] + offset` (1 and 0 unless a mimic).
    pub scale: f64,
    pub offset: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Moves {
    No,
    Rotates,
    Slides,
}

/// A robot's kinematic tree (module doc).
#[derive(Clone, Debug)]
pub struct Robot {
    name: String,
    links: Vec<Link>,
    joints: Vec<Joint>,
    /// Joint index of each degree of freedom.
    dofs: Vec<usize>,
    dof_names: Vec<String>,
    limits: JointLimits,
    mujoco: Vec<usize>,
    link_by_name: HashMap<String, usize>,
    world_mount: Option<Pose>,
    pub(super) steps: Vec<Step>,
}

impl Robot {
    /// Reads a URDF ([`urdf::parse`]) and builds its tree (module doc). Never panics.
    pub fn from_urdf(text: &str) -> Result<Robot> {
        Robot::from_description(urdf::parse(text)?)
    }

    /// Builds the tree of a parsed description.
    pub fn from_description(urdf: Urdf) -> Result<Robot> {
        build(urdf)
    }

    /// `<robot name>`.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Joint degrees of freedom (`n`).
    pub fn dof_count(&self) -> usize {
        self.dofs.len()
    }

    /// Configuration size: 3 + 4 (base position, quaternion x, y, z, w) + `n`.
    pub fn nq(&self) -> usize {
        7 + self.dofs.len()
    }

    /// Velocity size: 3 + 3 (base linear, angular; world axes) + `n`.
    pub fn nv(&self) -> usize {
        6 + self.dofs.len()
    }

    /// The degrees of freedom's joint names, in URDF document order: the order of `q`.
    pub fn dof_names(&self) -> &[String] {
        &self.dof_names
    }

    /// The degree of freedom of the joint named `name` (`None` for fixed, mimic or unknown).
    pub fn dof_index(&self, name: &str) -> Option<usize> {
        self.dof_names.iter().position(|n| n == name)
    }

    /// The joint (index into [`Robot::joints`]) of each degree of freedom.
    pub fn dof_joints(&self) -> &[usize] {
        &self.dofs
    }

    /// Links, parents first (module doc); link 0 is the root.
    pub fn links(&self) -> &[Link] {
        &self.links
    }

    /// The index of the link named `name`.
    pub fn link_index(&self, name: &str) -> Option<usize> {
        self.link_by_name.get(name).copied()
    }

    /// Every joint (fixed ones too) in URDF document order, less a dropped `world` joint.
    pub fn joints(&self) -> &[Joint] {
        &self.joints
    }

    /// Limits per degree of freedom.
    pub fn joint_limits(&self) -> &JointLimits {
        &self.limits
    }

    /// The revolute, continuous and prismatic joints (mimic ones included), as indices into
    /// [`Robot::joints`], in the order of MuJoCo's `qpos` after its free joint (module doc).
    pub fn mujoco_joint_order(&self) -> &[usize] {
        &self.mujoco
    }

    /// The position of joint `joint` (radians or metres) in the joint vector `q` (0 for a fixed
    /// joint).
    pub fn joint_position(&self, joint: usize, q: &[f64]) -> f64 {
        match self.joints[joint].motion {
            JointMotion::None => 0.0,
            JointMotion::Dof(d) => q[d],
            JointMotion::Mimic {
                dof,
                multiplier,
                offset,
            } => multiplier * q[dof] + offset,
        }
    }

    /// The origin of a dropped `world` joint: where the file mounted the root in its world
    /// (module doc). Not applied by [`super::forward`].
    pub fn world_mount(&self) -> Option<&Pose> {
        self.world_mount.as_ref()
    }
}

/// `(k, sign)` when `axis` is exactly `sign · e_k`.
fn coordinate_axis(axis: &Vec3) -> Option<(usize, f64)> {
    let k = axis.iter().position(|v| v.abs() == 1.0)?;
    let others_zero = (0..3).all(|i| i == k || axis[i] == 0.0);
    others_zero.then_some((k, axis[k]))
}

/// Up to five names joined for a message, with the count of the rest.
fn list(names: &[&str]) -> String {
    let mut s = names
        .iter()
        .take(5)
        .map(|n| format!("`{n}`"))
        .collect::<Vec<_>>()
        .join(", ");
    if names.len() > 5 {
        s.push_str(&format!(" and {} more", names.len() - 5));
    }
    s
}

fn build(urdf: Urdf) -> Result<Robot> {
    let n_links = urdf.links.len();
    if n_links == 0 {
        return Err(invalid_arg!("URDF: the robot has no link"));
    }
    let index: HashMap<&str, usize> = urdf
        .links
        .iter()
        .enumerate()
        .map(|(i, l)| (l.name.as_str(), i))
        .collect();

    // Parent joint of each link and child joints of each link, in document order.
    let mut parent_joint: Vec<Option<usize>> = vec![None; n_links];
    let mut child_joints: Vec<Vec<usize>> = vec![Vec::new(); n_links];
    let mut ends: Vec<(usize, usize)> = Vec::with_capacity(urdf.joints.len());
    for (j, joint) in urdf.joints.iter().enumerate() {
        let find = |role: &str, name: &str| {
            index.get(name).copied().ok_or_else(|| {
                invalid_arg!(
                    "URDF: joint `{}` (line {}): its {role} link `{name}` does not exist",
                    joint.name,
                    joint.line
                )
            })
        };
        let (p, c) = (find("parent", &joint.parent)?, find("child", &joint.child)?);
        if p == c {
            return Err(invalid_arg!(
                "URDF: joint `{}` (line {}) joins link `{}` to itself (a cycle)",
                joint.name,
                joint.line,
                joint.child
            ));
        }
        if let Some(first) = parent_joint[c] {
            let first = &urdf.joints[first];
            return Err(invalid_arg!(
                "URDF: link `{}` has two parents: `{}` through joint `{}` (line {}) and `{}` \
                 through joint `{}` (line {})",
                joint.child,
                first.parent,
                first.name,
                first.line,
                joint.parent,
                joint.name,
                joint.line
            ));
        }
        parent_joint[c] = Some(j);
        child_joints[p].push(j);
        ends.push((p, c));
    }

    let roots: Vec<usize> = (0..n_links)
        .filter(|&l| parent_joint[l].is_none())
        .collect();
    if roots.len() > 1 {
        let names: Vec<&str> = roots.iter().map(|&l| urdf.links[l].name.as_str()).collect();
        return Err(invalid_arg!(
            "URDF: {} links are roots (no joint has them as child): {}; a robot is one tree",
            roots.len(),
            list(&names)
        ));
    }
    let Some(&root) = roots.first() else {
        return Err(cycle_error(&urdf, &parent_joint, &ends, 0));
    };

    // Depth-first, children in joint document order (an explicit stack: a 10,000-link chain
    // must not overflow the call stack).
    let mut order: Vec<usize> = Vec::with_capacity(n_links);
    let mut stack = vec![root];
    while let Some(l) = stack.pop() {
        order.push(l);
        stack.extend(child_joints[l].iter().rev().map(|&j| ends[j].1));
    }
    if order.len() < n_links {
        let mut reached = vec![false; n_links];
        order.iter().for_each(|&l| reached[l] = true);
        let stray = (0..n_links).find(|&l| !reached[l]).unwrap_or(0);
        return Err(cycle_error(&urdf, &parent_joint, &ends, stray));
    }

    // A `world` root with one fixed or floating joint: dropped (module doc).
    let mut dropped_joint = None;
    let mut world_mount = None;
    if urdf.links[root].name == "world" && child_joints[root].len() == 1 {
        let j = child_joints[root][0];
        if matches!(urdf.joints[j].kind, JointType::Fixed | JointType::Floating) {
            dropped_joint = Some(j);
            world_mount = Some(urdf.joints[j].origin);
            order.remove(0);
        }
    }

    for (j, joint) in urdf.joints.iter().enumerate() {
        if Some(j) == dropped_joint {
            continue;
        }
        match joint.kind {
            JointType::Floating => {
                return Err(invalid_arg!(
                    "URDF: joint `{}` (line {}) is floating inside the tree; only the base \
                     floats (a `world` link's single floating joint is the base)",
                    joint.name,
                    joint.line
                ))
            }
            JointType::Planar => {
                return Err(invalid_arg!(
                    "URDF: joint `{}` (line {}) is planar, which is not supported",
                    joint.name,
                    joint.line
                ))
            }
            _ => {}
        }
    }

    // Degrees of freedom: independent movable joints in document order.
    let movable = |t: JointType| {
        matches!(
            t,
            JointType::Revolute | JointType::Continuous | JointType::Prismatic
        )
    };
    let mut dof_of_joint: Vec<Option<usize>> = vec![None; urdf.joints.len()];
    let mut dofs = Vec::new();
    for (j, joint) in urdf.joints.iter().enumerate() {
        if movable(joint.kind) && joint.mimic.is_none() && Some(j) != dropped_joint {
            dof_of_joint[j] = Some(dofs.len());
            dofs.push(j);
        }
    }
    let joint_by_name: HashMap<&str, usize> = urdf
        .joints
        .iter()
        .enumerate()
        .map(|(j, joint)| (joint.name.as_str(), j))
        .collect();
    let motion_of = |j: usize| -> Result<JointMotion> {
        let joint = &urdf.joints[j];
        if !movable(joint.kind) {
            // A mimic on a fixed joint moves nothing (urdfdom ignores it too).
            return Ok(JointMotion::None);
        }
        let (mut at, mut multiplier, mut offset) = (j, 1.0, 0.0);
        for _ in 0..=urdf.joints.len() {
            let Some(m) = &urdf.joints[at].mimic else {
                return Ok(match (dof_of_joint[at], j == at) {
                    (Some(d), true) => JointMotion::Dof(d),
                    (Some(dof), false) => JointMotion::Mimic {
                        dof,
                        multiplier,
                        offset,
                    },
                    // Unreachable for a movable joint; reported rather than assumed.
                    (None, _) => {
                        return Err(invalid_arg!(
                            "URDF: joint `{}` mimics a joint with no degree of freedom",
                            joint.name
                        ))
                    }
                });
            };
            let src = joint_by_name
                .get(m.joint.as_str())
                .copied()
                .ok_or_else(|| {
                    invalid_arg!(
                        "URDF: joint `{}` (line {}) mimics joint `{}`, which does not exist",
                        urdf.joints[at].name,
                        urdf.joints[at].line,
                        m.joint
                    )
                })?;
            if !movable(urdf.joints[src].kind) || Some(src) == dropped_joint {
                return Err(invalid_arg!(
                    "URDF: joint `{}` (line {}) mimics joint `{}`, which is {} and has no \
                     position",
                    urdf.joints[at].name,
                    urdf.joints[at].line,
                    m.joint,
                    urdf.joints[src].kind.name()
                ));
            }
            // q_at = m·q_src + o, and q_j = multiplier·q_at + offset.
            offset += multiplier * m.offset;
            multiplier *= m.multiplier;
            at = src;
        }
        Err(invalid_arg!(
            "URDF: the mimic joints through `{}` (line {}) form a cycle",
            joint.name,
            joint.line
        ))
    };

    // Links renumbered parents first.
    let mut new_index = vec![usize::MAX; n_links];
    for (i, &l) in order.iter().enumerate() {
        new_index[l] = i;
    }
    let mut joints = Vec::with_capacity(urdf.joints.len());
    let mut joint_index = vec![usize::MAX; urdf.joints.len()];
    for (j, joint) in urdf.joints.iter().enumerate() {
        if Some(j) == dropped_joint {
            continue;
        }
        let kind = match joint.kind {
            JointType::Revolute => JointKind::Revolute,
            JointType::Continuous => JointKind::Continuous,
            JointType::Prismatic => JointKind::Prismatic,
            _ => JointKind::Fixed,
        };
        joint_index[j] = joints.len();
        joints.push(Joint {
            name: joint.name.clone(),
            kind,
            parent: new_index[ends[j].0],
            child: new_index[ends[j].1],
            origin: joint.origin,
            axis: if kind == JointKind::Fixed && joint.axis == [0.0; 3] {
                [1.0, 0.0, 0.0]
            } else {
                joint.axis
            },
            limit: joint.limit,
            motion: motion_of(j)?,
        });
    }

    let mut links = Vec::with_capacity(order.len());
    let mut steps = Vec::with_capacity(order.len().saturating_sub(1));
    for &l in &order {
        let joint = parent_joint[l]
            .filter(|&j| Some(j) != dropped_joint)
            .map(|j| joint_index[j]);
        let parent = joint.map(|j| joints[j].parent);
        if let Some(j) = joint {
            let jt = &joints[j];
            let (dof, scale, offset) = match jt.motion {
                JointMotion::None => (0, 0.0, 0.0),
                JointMotion::Dof(d) => (d, 1.0, 0.0),
                JointMotion::Mimic {
                    dof,
                    multiplier,
                    offset,
                } => (dof, multiplier, offset),
            };
            steps.push(Step {
                parent: jt.parent,
                origin: jt.origin,
                origin_turns: jt.origin.rotation != IDENTITY,
                axis: jt.axis,
                coordinate_axis: coordinate_axis(&jt.axis),
                moves: match jt.kind {
                    JointKind::Fixed => Moves::No,
                    JointKind::Prismatic => Moves::Slides,
                    _ => Moves::Rotates,
                },
                dof,
                scale,
                offset,
            });
        }
        links.push(Link {
            name: urdf.links[l].name.clone(),
            parent,
            joint,
            collisions: urdf.links[l].collisions.clone(),
        });
    }

    let mujoco = links
        .iter()
        .filter_map(|l| l.joint)
        .filter(|&j| joints[j].kind != JointKind::Fixed)
        .collect();
    let mut limits = JointLimits {
        lower: Vec::with_capacity(dofs.len()),
        upper: Vec::with_capacity(dofs.len()),
        velocity: Vec::with_capacity(dofs.len()),
        effort: Vec::with_capacity(dofs.len()),
    };
    for &j in &dofs {
        let joint = &urdf.joints[j];
        let limit = joint.limit.unwrap_or(Limit {
            lower: 0.0,
            upper: 0.0,
            velocity: f64::INFINITY,
            effort: f64::INFINITY,
        });
        let (lower, upper) = if joint.kind == JointType::Continuous {
            (f64::NEG_INFINITY, f64::INFINITY)
        } else {
            (limit.lower, limit.upper)
        };
        limits.lower.push(lower);
        limits.upper.push(upper);
        limits.velocity.push(limit.velocity);
        limits.effort.push(limit.effort);
    }
    let dofs: Vec<usize> = dofs.iter().map(|&j| joint_index[j]).collect();
    let dof_names = dofs.iter().map(|&j| joints[j].name.clone()).collect();
    let link_by_name = links
        .iter()
        .enumerate()
        .map(|(i, l)| (l.name.clone(), i))
        .collect();
    Ok(Robot {
        name: urdf.name,
        links,
        joints,
        dofs,
        dof_names,
        limits,
        mujoco,
        link_by_name,
        world_mount,
        steps,
    })
}

/// The error for a cycle that `start` is on or below: parents followed from `start` until a
/// link repeats, the repeating loop named by its joints.
fn cycle_error(
    urdf: &Urdf,
    parent_joint: &[Option<usize>],
    ends: &[(usize, usize)],
    start: usize,
) -> crate::Error {
    let mut seen = vec![false; urdf.links.len()];
    let mut l = start;
    while !seen[l] {
        seen[l] = true;
        match parent_joint[l] {
            Some(j) => l = ends[j].0,
            None => break,
        }
    }
    // `l` is on the loop: walk it once more, naming its joints.
    let mut names = Vec::new();
    let first = l;
    while let Some(j) = parent_joint[l] {
        names.push(urdf.joints[j].name.as_str());
        l = ends[j].0;
        if l == first || names.len() > urdf.links.len() {
            break;
        }
    }
    names.reverse();
    invalid_arg!(
        "URDF: the joints {} form a cycle through link `{}` (a robot is a tree)",
        list(&names),
        urdf.links[first].name
    )
}
