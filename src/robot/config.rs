//! [`RetargetConfig`]: how a human motion is mapped onto one robot, read from JSON in the shape of
//! GMR's IK configurations (YanjieZe/GMR, `general_motion_retargeting/ik_configs/*.json`, keys
//! explained in YanjieZe/GMR `docs/IK_CONFIG.md`), so a GMR user can port a table, plus the keys libflame
//! adds for the feet and the solver. Every name is resolved when the file is read, against the
//! robot and the human skeleton; nothing is looked up by name per frame.
//!
//! # Keys (GMR's)
//! - `robot_root_name`: the robot body that stands for the human root (usually the pelvis).
//! - `human_root_name`: the human joint positions are scaled about (GMR: `pelvis`).
//! - `ground_height`: metres, as GMR's `motion_retarget.py` applies it: subtracted from the z of
//!   every entry's position offset *before* that offset is turned by the target rotation (so with
//!   a rotation offset it is not a plain vertical shift; every shipped GMR table has 0).
//! - `human_height_assumption`: metres; every `human_scale_table` value is multiplied by
//!   `human_height / human_height_assumption` (GMR's `ratio`).
//! - `use_ik_match_table1`, `use_ik_match_table2`: which of the two IK stages run.
//! - `human_scale_table`: `{human joint: scale}`. The root's position is multiplied by the root's
//!   scale; every other listed joint's offset from the root by its own scale, then added to the
//!   scaled root (GMR's `scale_human_data`). A joint used by a table must be listed (GMR drops an
//!   unlisted joint from the targets, which then fails there; here it is an error at load).
//! - `ik_match_table1`, `ik_match_table2`: `{robot body: [human joint, position weight, rotation
//!   weight, [x, y, z], [w, x, y, z]]}`. The target rotation is the human joint's world rotation
//!   times the rotation offset (quaternion **w first**, applied on the right: in the human
//!   joint's frame); the target position is the scaled human position plus the position offset
//!   turned by that target rotation (GMR's `offset_human_data`). An entry whose two weights are
//!   both 0 is kept out of the solve, as in GMR. GMR computes the targets of both stages with
//!   table 1's offsets (`update_targets`); here each table uses its own, which is the same
//!   whenever the tables agree (they do in GMR's shipped files, except the G1 toes' rotation).
//! - `robot_initial_qpos`: `{joint: value}`, the configuration a run starts from (default 0,
//!   clamped into the limits).
//!
//! # Human joint names
//! Either libflame's (the SMPL-24 names of [`crate::motion::Skeleton::smpl24`]: `Pelvis`,
//! `L_Hip`, `L_Knee`, `L_Ankle`, `L_Foot`, `Spine3`, `L_Shoulder`, `L_Elbow`, `L_Wrist`,
//! `L_Hand`, …) or SMPL-X's as GMR reads them (`smplx.joint_names.JOINT_NAMES`, used by GMR's
//! `utils/smpl.py`: `pelvis`, `left_hip`, `left_knee`, `left_ankle`, `left_foot`, `spine3`,
//! `left_shoulder`, `left_elbow`, `left_wrist`, …). The first 22 SMPL-X joints are SMPL's in the
//! same order, so the names map index for index: SMPL-X's `left_foot` is joint 10, the foot's
//! ball (libflame's `L_Foot`), and `left_ankle` is joint 7 (`L_Ankle`). SMPL's hands
//! (`L_Hand`/`R_Hand`, joints 22 and 23) are also accepted as `left_hand`/`right_hand`; they
//! exist in 24-joint (smpl24_6d) motions only.
//!
//! # Keys (libflame's)
//! - `feet`: `{"left": foot, "right": foot}`, each `{"body": robot body, "human": [joints],
//!   "sole": {"centre": [x, y], "half_length": l, "half_width": w, "height": h}}`. `human` names
//!   the joints whose contacts make the foot's contact (among the ankle and the foot joint of
//!   that side: the contact slots of [`crate::motion::contacts`]). The sole is a rectangle in the
//!   body's x-y plane, its normal the body's z axis, `h` metres below the body origin, `l` along
//!   x and `w` along y from the centre. The foot body must be the body of an entry of a table in
//!   use (that entry gives the foot's target outside contacts).
//! - `human_height`: metres, the height of the motion's person (default 1.66, GMR's
//!   `1.66 + 0.1 · betas[0]` with libflame's neutral shape, betas 0).
//! - `velocity_limit`: rad/s (or m/s) per joint, default 3π as GMR's; each joint's is the
//!   smaller of it and the URDF's `velocity`.
//! - `iterations`: solver iterations per stage and frame (default 4; the first frame of a run,
//!   which starts from rest, gets [`FIRST_FRAME_FACTOR`] times more).
//! - `damping`: the solver's Tikhonov damping (default 0.5, GMR's `damping`).
//!
//! Keys starting with `_` are comments. Any other key is an error (a misspelt key would
//! otherwise be silently ignored), as are negative, non-finite or too large (above
//! [`MAX_WEIGHT`]) weights, negative or non-finite scales and sizes, an
//! unknown body or human joint (named in the message), and a zero rotation offset.

use std::path::{Path, PathBuf};

use serde_json::{Map, Value};

use super::model::Robot;
use crate::error::{invalid_arg, Result};
use crate::motion::rotation::{self, Mat3, Vec3};
use crate::motion::Skeleton;

/// The first frame of a run starts from the rest configuration, far from the pose: it gets this
/// many times the configured iterations.
pub const FIRST_FRAME_FACTOR: usize = 10;

/// The default human height, metres (module doc).
pub const DEFAULT_HUMAN_HEIGHT: f64 = 1.66;

/// Indices of the human joints whose contacts exist: left ankle, left foot, right ankle, right
/// foot (the slots of [`crate::motion::contacts::SLOT_JOINTS`]).
const CONTACT_JOINTS: [usize; 4] = crate::motion::contacts::SLOT_JOINTS;

/// One row of an IK match table, names resolved.
#[derive(Clone, Debug, PartialEq)]
pub struct MatchEntry {
    /// Robot link index ([`Robot::links`]) whose pose is driven.
    pub body: usize,
    /// That link's name, as the table's key gives it (for messages).
    pub body_name: String,
    /// Human joint index in SMPL-24 order (a 22-joint motion holds the first 22).
    pub human: usize,
    /// Weight of the position error (metres) in the solve, ≥ 0; 0 leaves the position free.
    pub position_weight: f64,
    /// Weight of the rotation error (radians) in the solve, ≥ 0; 0 leaves the rotation free.
    pub rotation_weight: f64,
    /// In the target frame, `ground_height` already taken off its z (module doc).
    pub position_offset: Vec3,
    /// Applied on the right of the human joint's world rotation.
    pub rotation_offset: Mat3,
}

/// A foot's sole rectangle in its body's frame (module doc, `feet`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sole {
    /// The rectangle's centre (x, y) in the body's frame, metres.
    pub centre: [f64; 2],
    /// Half the sole's extent along the body's x axis, metres, > 0.
    pub half_length: f64,
    /// Half the sole's extent along the body's y axis, metres, > 0.
    pub half_width: f64,
    /// How far below the body origin (along the body's -z) the sole lies, metres, ≥ 0.
    pub height: f64,
}

impl Sole {
    /// The rectangle's four corners in the body's frame.
    pub fn corners(&self) -> [Vec3; 4] {
        let [cx, cy] = self.centre;
        let (l, w, h) = (self.half_length, self.half_width, self.height);
        [
            [cx + l, cy + w, -h],
            [cx + l, cy - w, -h],
            [cx - l, cy + w, -h],
            [cx - l, cy - w, -h],
        ]
    }
}

/// A robot foot and the human contacts that plant it.
#[derive(Clone, Debug, PartialEq)]
pub struct Foot {
    /// Robot link index ([`Robot::links`]) of the foot; an entry of a table in use drives it.
    pub body: usize,
    /// That link's name (`feet.<side>.body`).
    pub body_name: String,
    /// Contact slots (0..4: left ankle, left foot, right ankle, right foot) whose contact makes
    /// this foot's.
    pub slots: Vec<usize>,
    /// The sole, for floor contact and anchoring.
    pub sole: Sole,
}

/// A retarget configuration, resolved against one robot (module doc).
#[derive(Clone, Debug, PartialEq)]
pub struct RetargetConfig {
    /// `robot_root_name` as a link index ([`Robot::links`]).
    pub robot_root: usize,
    /// `human_root_name` as an SMPL-24 joint index: the point positions are scaled about.
    pub human_root: usize,
    /// `ground_height`, metres (already taken off every entry's position offset).
    pub ground_height: f64,
    /// `human_height_assumption`, metres: the height the scale table was tuned for.
    pub human_height_assumption: f64,
    /// `human_height`, metres ([`DEFAULT_HUMAN_HEIGHT`] when absent); the scales are multiplied
    /// by `human_height / human_height_assumption`.
    pub human_height: f64,
    /// `use_ik_match_table1`: whether stage 1 runs.
    pub use_table1: bool,
    /// `use_ik_match_table2`: whether stage 2 runs (at least one of the two does).
    pub use_table2: bool,
    /// Per human joint (SMPL-24 order), the scale with the height ratio applied; `None` when the
    /// joint is not in `human_scale_table`.
    pub scales: [Option<f64>; 24],
    /// `ik_match_table1`, in the file's key order (entries with both weights 0 included;
    /// [`MatchEntry::active`] tells them apart).
    pub table1: Vec<MatchEntry>,
    /// `ik_match_table2`, likewise.
    pub table2: Vec<MatchEntry>,
    /// Left, right; empty when the file has no `feet`.
    pub feet: Vec<Foot>,
    /// Per degree of freedom: the smaller of `velocity_limit` and the URDF's.
    pub velocity_limits: Vec<f64>,
    /// Per degree of freedom, the start of a run (within limits).
    pub initial_q: Vec<f64>,
    /// Solver iterations per stage and frame, 1 to 1000 (default 4; the first frame of a run
    /// gets [`FIRST_FRAME_FACTOR`] times more).
    pub iterations: usize,
    /// Tikhonov damping added to the normal equations' diagonal, ≥ 0 (default 0.5): larger is
    /// smoother and slower to reach the targets.
    pub damping: f64,
}

/// The human joint named `name` (libflame's SMPL-24 names or SMPL-X's, module doc), as an
/// SMPL-24 index.
pub fn human_joint(name: &str) -> Option<usize> {
    let smpl = Skeleton::smpl24().joint_names();
    let smplx = Skeleton::humanml22().joint_names();
    smpl.iter()
        .position(|n| *n == name)
        .or_else(|| smplx.iter().position(|n| *n == name))
        .or(match name {
            "left_hand" => Some(22),
            "right_hand" => Some(23),
            _ => None,
        })
}

fn number(v: &Value, what: &str) -> Result<f64> {
    match v.as_f64() {
        Some(x) if x.is_finite() => Ok(x),
        _ => Err(invalid_arg!(
            "retarget config: {what} must be a finite number, got {v}"
        )),
    }
}

fn non_negative(v: &Value, what: &str) -> Result<f64> {
    let x = number(v, what)?;
    if x < 0.0 {
        return Err(invalid_arg!(
            "retarget config: {what} must not be negative, got {x}"
        ));
    }
    Ok(x)
}

/// The largest IK weight a configuration may give (GMR's tables use up to 100): a weight near
/// f64's range would square into infinities inside the solve.
pub const MAX_WEIGHT: f64 = 1e6;

/// A task weight: 0..=[`MAX_WEIGHT`].
fn weight(v: &Value, what: &str) -> Result<f64> {
    let x = non_negative(v, what)?;
    if x > MAX_WEIGHT {
        return Err(invalid_arg!(
            "retarget config: {what} is {x}; it must be at most {MAX_WEIGHT}"
        ));
    }
    Ok(x)
}

fn positive(v: &Value, what: &str) -> Result<f64> {
    let x = number(v, what)?;
    if x <= 0.0 {
        return Err(invalid_arg!(
            "retarget config: {what} must be positive, got {x}"
        ));
    }
    Ok(x)
}

fn numbers<const N: usize>(v: &Value, what: &str) -> Result<[f64; N]> {
    let a = v.as_array().filter(|a| a.len() == N).ok_or_else(|| {
        invalid_arg!("retarget config: {what} must be an array of {N} numbers, got {v}")
    })?;
    let mut out = [0.0; N];
    for (o, x) in out.iter_mut().zip(a) {
        *o = number(x, what)?;
    }
    Ok(out)
}

fn object<'a>(v: &'a Value, what: &str) -> Result<&'a Map<String, Value>> {
    v.as_object()
        .ok_or_else(|| invalid_arg!("retarget config: {what} must be an object"))
}

fn boolean(v: &Value, what: &str) -> Result<bool> {
    v.as_bool()
        .ok_or_else(|| invalid_arg!("retarget config: {what} must be true or false, got {v}"))
}

fn string<'a>(v: &'a Value, what: &str) -> Result<&'a str> {
    v.as_str()
        .ok_or_else(|| invalid_arg!("retarget config: {what} must be a string, got {v}"))
}

fn body(robot: &Robot, name: &str, what: &str) -> Result<usize> {
    robot.link_index(name).ok_or_else(|| {
        invalid_arg!(
            "retarget config: {what}: robot `{}` has no body (link) `{name}`",
            robot.name()
        )
    })
}

fn human(name: &str, what: &str) -> Result<usize> {
    human_joint(name).ok_or_else(|| {
        invalid_arg!(
            "retarget config: {what}: no human joint `{name}` (libflame's SMPL-24 names such as \
             `L_Ankle`, or SMPL-X's such as `left_ankle`)"
        )
    })
}

/// Refuses keys other than `allowed` and `_`-comments.
fn known_keys(map: &Map<String, Value>, allowed: &[&str], what: &str) -> Result<()> {
    for key in map.keys() {
        if !key.starts_with('_') && !allowed.contains(&key.as_str()) {
            return Err(invalid_arg!(
                "retarget config: unknown key `{key}` in {what} (known: {})",
                allowed.join(", ")
            ));
        }
    }
    Ok(())
}

const TOP_KEYS: [&str; 15] = [
    "robot_root_name",
    "human_root_name",
    "ground_height",
    "human_height_assumption",
    "use_ik_match_table1",
    "use_ik_match_table2",
    "human_scale_table",
    "ik_match_table1",
    "ik_match_table2",
    "robot_initial_qpos",
    "feet",
    "human_height",
    "velocity_limit",
    "iterations",
    "damping",
];

impl RetargetConfig {
    /// Reads a configuration (module doc) and resolves it against `robot`. Errors name the key,
    /// body or joint at fault.
    pub fn from_json(text: &str, robot: &Robot) -> Result<RetargetConfig> {
        let doc: Value = serde_json::from_str(text)
            .map_err(|e| invalid_arg!("retarget config: not valid JSON: {e}"))?;
        let top = object(&doc, "the document")?;
        known_keys(top, &TOP_KEYS, "the document")?;
        let get = |key: &str| {
            top.get(key)
                .ok_or_else(|| invalid_arg!("retarget config: missing key `{key}`"))
        };
        let robot_root = body(
            robot,
            string(get("robot_root_name")?, "robot_root_name")?,
            "robot_root_name",
        )?;
        let human_root = human(
            string(get("human_root_name")?, "human_root_name")?,
            "human_root_name",
        )?;
        let ground_height = number(get("ground_height")?, "ground_height")?;
        let human_height_assumption =
            positive(get("human_height_assumption")?, "human_height_assumption")?;
        let human_height = match top.get("human_height") {
            Some(v) => positive(v, "human_height")?,
            None => DEFAULT_HUMAN_HEIGHT,
        };
        let ratio = human_height / human_height_assumption;
        let use_table1 = boolean(get("use_ik_match_table1")?, "use_ik_match_table1")?;
        let use_table2 = boolean(get("use_ik_match_table2")?, "use_ik_match_table2")?;

        let mut scales = [None; 24];
        for (name, v) in object(get("human_scale_table")?, "human_scale_table")? {
            if name.starts_with('_') {
                continue;
            }
            let what = format!("human_scale_table.{name}");
            let j = human(name, &what)?;
            scales[j] = Some(positive(v, &what)? * ratio);
        }
        if scales[human_root].is_none() {
            return Err(invalid_arg!(
                "retarget config: human_scale_table has no scale for the human root `{}`",
                string(get("human_root_name")?, "")?
            ));
        }

        let table = |key: &str| -> Result<Vec<MatchEntry>> {
            let mut out = Vec::new();
            for (name, v) in object(get(key)?, key)? {
                if name.starts_with('_') {
                    continue;
                }
                let what = format!("{key}.{name}");
                out.push(entry(robot, name, v, &what, ground_height, &scales)?);
            }
            Ok(out)
        };
        let table1 = table("ik_match_table1")?;
        let table2 = table("ik_match_table2")?;
        if !use_table1 && !use_table2 {
            return Err(invalid_arg!(
                "retarget config: use_ik_match_table1 and use_ik_match_table2 are both false"
            ));
        }

        let feet = match top.get("feet") {
            None => Vec::new(),
            Some(v) => feet(robot, v)?,
        };
        for foot in &feet {
            let tracked = [(use_table1, &table1), (use_table2, &table2)]
                .iter()
                .any(|(used, t)| *used && t.iter().any(|e| e.body == foot.body && e.active()));
            if !tracked {
                return Err(invalid_arg!(
                    "retarget config: foot body `{}` has no weighted entry in a table in use",
                    foot.body_name
                ));
            }
        }

        let velocity_limit = match top.get("velocity_limit") {
            Some(v) => positive(v, "velocity_limit")?,
            None => 3.0 * std::f64::consts::PI,
        };
        let limits = robot.joint_limits();
        let velocity_limits = limits
            .velocity
            .iter()
            .map(|&v| {
                if v > 0.0 {
                    v.min(velocity_limit)
                } else {
                    velocity_limit
                }
            })
            .collect();
        let mut initial_q = vec![0.0; robot.dof_count()];
        if let Some(v) = top.get("robot_initial_qpos") {
            for (name, x) in object(v, "robot_initial_qpos")? {
                if name.starts_with('_') {
                    continue;
                }
                let what = format!("robot_initial_qpos.{name}");
                let d = robot.dof_index(name).ok_or_else(|| {
                    invalid_arg!(
                        "retarget config: {what}: robot `{}` has no joint `{name}` that is a \
                         degree of freedom",
                        robot.name()
                    )
                })?;
                initial_q[d] = number(x, &what)?;
            }
        }
        for (d, q) in initial_q.iter_mut().enumerate() {
            *q = q.clamp(limits.lower[d], limits.upper[d]);
        }
        let iterations = match top.get("iterations") {
            Some(v) => match v.as_u64() {
                Some(n @ 1..=1000) => n as usize,
                _ => {
                    return Err(invalid_arg!(
                        "retarget config: iterations must be an integer from 1 to 1000, got {v}"
                    ))
                }
            },
            None => 4,
        };
        let damping = match top.get("damping") {
            Some(v) => non_negative(v, "damping")?,
            None => 0.5,
        };
        Ok(RetargetConfig {
            robot_root,
            human_root,
            ground_height,
            human_height_assumption,
            human_height,
            use_table1,
            use_table2,
            scales,
            table1,
            table2,
            feet,
            velocity_limits,
            initial_q,
            iterations,
            damping,
        })
    }

    /// The stages that run, in order (table 1 then table 2).
    pub fn stages(&self) -> impl Iterator<Item = &[MatchEntry]> {
        [
            (self.use_table1, &self.table1),
            (self.use_table2, &self.table2),
        ]
        .into_iter()
        .filter(|(used, _)| *used)
        .map(|(_, t)| t.as_slice())
    }

    /// The human joints every used entry reads, the largest index + 1: a motion needs at least
    /// this many joints.
    pub fn joints_needed(&self) -> usize {
        self.stages()
            .flatten()
            .map(|e| e.human + 1)
            .chain([self.human_root + 1])
            .max()
            .unwrap_or(1)
    }
}

impl MatchEntry {
    /// Whether the entry takes part in the solve (a weight is nonzero).
    pub fn active(&self) -> bool {
        self.position_weight > 0.0 || self.rotation_weight > 0.0
    }
}

fn entry(
    robot: &Robot,
    name: &str,
    v: &Value,
    what: &str,
    ground_height: f64,
    scales: &[Option<f64>; 24],
) -> Result<MatchEntry> {
    let a = v.as_array().filter(|a| a.len() == 5).ok_or_else(|| {
        invalid_arg!(
            "retarget config: {what} must be [human joint, position weight, rotation weight, \
             [x, y, z], [w, x, y, z]]"
        )
    })?;
    let body = body(robot, name, what)?;
    let human_name = string(&a[0], what)?;
    let human = human(human_name, what)?;
    let position_weight = weight(&a[1], &format!("{what} position weight"))?;
    let rotation_weight = weight(&a[2], &format!("{what} rotation weight"))?;
    let [x, y, z] = numbers::<3>(&a[3], &format!("{what} position offset"))?;
    let quat = numbers::<4>(&a[4], &format!("{what} rotation offset (w, x, y, z)"))?;
    let norm = quat.iter().map(|c| c * c).sum::<f64>().sqrt();
    if norm < 1e-9 {
        return Err(invalid_arg!(
            "retarget config: {what} rotation offset is the zero quaternion"
        ));
    }
    let e = MatchEntry {
        body,
        body_name: name.to_string(),
        human,
        position_weight,
        rotation_weight,
        position_offset: [x, y, z - ground_height],
        rotation_offset: rotation::quat_to_matrix(&quat.map(|c| c / norm)),
    };
    if e.active() && scales[human].is_none() {
        return Err(invalid_arg!(
            "retarget config: {what} follows human joint `{human_name}`, which \
             human_scale_table does not list"
        ));
    }
    Ok(e)
}

fn feet(robot: &Robot, v: &Value) -> Result<Vec<Foot>> {
    let map = object(v, "feet")?;
    known_keys(map, &["left", "right"], "feet")?;
    let mut out = Vec::with_capacity(2);
    for (side, slots) in [("left", [0, 1]), ("right", [2, 3])] {
        let what = format!("feet.{side}");
        let f = object(
            map.get(side)
                .ok_or_else(|| invalid_arg!("retarget config: feet has no `{side}`"))?,
            &what,
        )?;
        known_keys(f, &["body", "human", "sole"], &what)?;
        let field = |key: &str| {
            f.get(key)
                .ok_or_else(|| invalid_arg!("retarget config: {what} has no `{key}`"))
        };
        let body_name = string(field("body")?, &format!("{what}.body"))?;
        let body = body(robot, body_name, &format!("{what}.body"))?;
        let humans = field("human")?
            .as_array()
            .filter(|a| !a.is_empty())
            .ok_or_else(|| {
                invalid_arg!("retarget config: {what}.human must be a non-empty array of joints")
            })?;
        let mut foot_slots = Vec::new();
        for h in humans {
            let name = string(h, &format!("{what}.human"))?;
            let j = human(name, &format!("{what}.human"))?;
            let slot = slots
                .iter()
                .copied()
                .find(|&s| CONTACT_JOINTS[s] == j)
                .ok_or_else(|| {
                    invalid_arg!(
                        "retarget config: {what}.human: `{name}` has no contact on this side \
                         (the {side} ankle and foot joints have)"
                    )
                })?;
            if !foot_slots.contains(&slot) {
                foot_slots.push(slot);
            }
        }
        let s = object(field("sole")?, &format!("{what}.sole"))?;
        known_keys(
            s,
            &["centre", "half_length", "half_width", "height"],
            &format!("{what}.sole"),
        )?;
        let sole_field = |key: &str| {
            s.get(key)
                .ok_or_else(|| invalid_arg!("retarget config: {what}.sole has no `{key}`"))
        };
        let sole = Sole {
            centre: numbers::<2>(sole_field("centre")?, &format!("{what}.sole.centre"))?,
            half_length: positive(
                sole_field("half_length")?,
                &format!("{what}.sole.half_length"),
            )?,
            half_width: positive(
                sole_field("half_width")?,
                &format!("{what}.sole.half_width"),
            )?,
            height: non_negative(sole_field("height")?, &format!("{what}.sole.height"))?,
        };
        out.push(Foot {
            body,
            body_name: body_name.to_string(),
            slots: foot_slots,
            sole,
        });
    }
    if out[0].body == out[1].body {
        return Err(invalid_arg!(
            "retarget config: feet.left and feet.right are the same body `{}`",
            out[0].body_name
        ));
    }
    Ok(out)
}

/// The configuration shipped for `robot` in `dir`: `dir/<robot name, lowercased>.json` when that
/// file exists (`Ok(None)` otherwise), read and resolved. libflame ships `robots/gr1t2.json`,
/// `robots/jvrc1.json`, `robots/g1.json` and `robots/h1.json`.
pub fn load_default_config(robot: &Robot, dir: &Path) -> Result<Option<RetargetConfig>> {
    let path = default_config_path(robot, dir);
    if !path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&path)
        .map_err(|e| invalid_arg!("retarget config {}: {e}", path.display()))?;
    RetargetConfig::from_json(&text, robot)
        .map(Some)
        .map_err(|e| invalid_arg!("{}: {e}", path.display()))
}

/// `dir/<robot name, lowercased>.json` (whether or not it exists).
pub fn default_config_path(robot: &Robot, dir: &Path) -> PathBuf {
    dir.join(format!("{}.json", robot.name().to_lowercase()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn smplx_and_libflame_names_meet_on_smpl_indices() {
        for (a, b, j) in [
            ("Pelvis", "pelvis", 0),
            ("L_Ankle", "left_ankle", 7),
            ("L_Foot", "left_foot", 10),
            ("Spine3", "spine3", 9),
            ("R_Wrist", "right_wrist", 21),
            ("L_Hand", "left_hand", 22),
        ] {
            assert_eq!(human_joint(a), Some(j));
            assert_eq!(human_joint(b), Some(j));
        }
        assert_eq!(human_joint("left_toe"), None);
        let s = Sole {
            centre: [0.05, -0.01],
            half_length: 0.1,
            half_width: 0.04,
            height: 0.03,
        };
        let c = s.corners();
        assert_eq!(c[0], [0.15000000000000002, 0.03, -0.03]);
        assert_eq!(c[3], [-0.05, -0.05, -0.03]);
    }

    #[test]
    fn task_weights_are_bounded() {
        // A weight of 2.2e14 (a fuzz finding) squared into infinities inside the solve.
        let w = |v: f64| weight(&serde_json::json!(v), "w").map_err(|e| e.to_string());
        assert_eq!(w(0.0), Ok(0.0));
        assert_eq!(w(MAX_WEIGHT), Ok(MAX_WEIGHT));
        let e = w(2.2e14).unwrap_err();
        assert!(
            e.contains("w is 220000000000000; it must be at most 1000000"),
            "{e}"
        );
        assert!(w(-1.0).is_err());
    }
}
