//! Keep-masks for motion editing: which feature values of a reference motion a session keeps
//! (`true`) and which it regenerates, built from frame ranges, joints, named body parts and the
//! standard editing tasks (in-betweening, prediction, upper-body editing, path following).
//!
//! Masks are frame-major `[frames, feature_dim]`, one flag per feature value, in the model's own
//! feature space: a joint is the set of channels that describe it (see [`joint_channels`]). The
//! sets follow the official editing code: `humanml263`'s lower body is MDM's `HML_LOWER_BODY_MASK`
//! and `smpl24_6d`'s is FLAME's kept set (docs/official/mdm.md#upper-body-mask,
//! docs/official/flame.md#editing). Nothing here runs a sampler; the session applies the mask.

use std::fmt;
use std::str::FromStr;

use super::format::Format;
use super::skeleton::Skeleton;
use crate::error::{invalid_arg, Error, Result};

/// A named group of channels that editing tools keep or regenerate together.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum BodyPart {
    /// The root's trajectory: `smpl24_6d`'s translation, `humanml263`'s root yaw velocity,
    /// planar velocity and height.
    RootPath,
    /// Root path, pelvis and legs (with all foot contacts): what an upper-body edit keeps.
    LowerBody,
    /// Every joint not in the lower body: spine, neck, head, collars, arms (and SMPL's hands).
    UpperBody,
    /// Collars, shoulders, elbows, wrists (and SMPL's hands).
    Arms,
    /// Hips, knees, ankles and feet (with `humanml263`'s foot contacts).
    Legs,
}

/// The joints (SMPL ids; HumanML3D uses the first 22) of the legs: FLAME's kept set without the
/// pelvis (`configs/edit_motion.yaml`; docs/official/flame.md#editing).
const LEG_JOINTS: [usize; 8] = [1, 2, 4, 5, 7, 8, 10, 11];
/// Collars 13/14, shoulders 16/17, elbows 18/19, wrists 20/21, hands 22/23.
const ARM_JOINTS: [usize; 10] = [13, 14, 16, 17, 18, 19, 20, 21, 22, 23];

impl BodyPart {
    /// Every part, indexed by the C ABI's integer value.
    pub const ALL: [BodyPart; 5] = [
        BodyPart::RootPath,
        BodyPart::LowerBody,
        BodyPart::UpperBody,
        BodyPart::Arms,
        BodyPart::Legs,
    ];

    /// The name used on the command line.
    pub fn name(self) -> &'static str {
        match self {
            BodyPart::RootPath => "root-path",
            BodyPart::LowerBody => "lower-body",
            BodyPart::UpperBody => "upper-body",
            BodyPart::Arms => "arms",
            BodyPart::Legs => "legs",
        }
    }
}

impl FromStr for BodyPart {
    type Err = Error;
    fn from_str(s: &str) -> Result<BodyPart> {
        BodyPart::ALL
            .into_iter()
            .find(|p| p.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| {
                invalid_arg!(
                    "unknown body part `{s}` (expected root-path, lower-body, upper-body, arms or legs)"
                )
            })
    }
}

impl fmt::Display for BodyPart {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// The standard editing tasks of the official code, as masks over a reference of `L` frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Task {
    /// Keep everything except frames `[⌊L/4⌋, ⌊3L/4⌋)` (MDM's `in_between`,
    /// docs/official/mdm.md#in-between-mask).
    Inbetween,
    /// Keep frames `[0, ⌊L/4⌋)` and generate the rest (Motion Flow Matching's "prediction").
    Predict,
    /// Keep the lower body on every frame, regenerate the upper body (FLAME's and MDM's edit).
    UpperBody,
    /// Keep the root path on every frame, regenerate the body.
    Path,
}

impl Task {
    /// Every task, indexed by the C ABI's integer value.
    pub const ALL: [Task; 4] = [Task::Inbetween, Task::Predict, Task::UpperBody, Task::Path];

    /// The name used by `flame edit --task`.
    pub fn name(self) -> &'static str {
        match self {
            Task::Inbetween => "inbetween",
            Task::Predict => "predict",
            Task::UpperBody => "upper-body",
            Task::Path => "path",
        }
    }
}

impl FromStr for Task {
    type Err = Error;
    fn from_str(s: &str) -> Result<Task> {
        Task::ALL
            .into_iter()
            .find(|t| t.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| {
                invalid_arg!(
                    "unknown editing task `{s}` (expected inbetween, predict, upper-body or path)"
                )
            })
    }
}

impl fmt::Display for Task {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// `humanml263` offsets (docs/official/humanml3d.md#feature-layout).
const HML_RIC: usize = 4;
const HML_ROT: usize = 67;
const HML_VEL: usize = 193;
const HML_CONTACTS: usize = 259;
/// The joint each foot-contact channel describes: left ankle, left foot, right ankle, right foot.
const HML_CONTACT_JOINTS: [usize; 4] = [7, 10, 8, 11];

/// The feature channels that describe `joint` (ascending). `smpl24_6d`: its 6D rotation (joint 0
/// is the pelvis's rotation; the translation is the root path, not a joint). `humanml263`: joint
/// 0 is the root's channels 0..4 and its velocity; other joints their ric position, cont6d
/// rotation and velocity; the ankles and feet also own their foot-contact channel.
pub fn joint_channels(format: Format, joint: usize) -> Result<Vec<usize>> {
    let joints = format.skeleton().joint_count();
    if joint >= joints {
        return Err(invalid_arg!(
            "joint {joint} does not exist: {format} has {joints} joints (0 to {})",
            joints - 1
        ));
    }
    Ok(match format {
        Format::Smpl24Rot6d => (3 + 6 * joint..3 + 6 * joint + 6).collect(),
        Format::HumanMl263 => {
            let vel = HML_VEL + 3 * joint..HML_VEL + 3 * joint + 3;
            let mut c: Vec<usize> = if joint == 0 {
                (0..HML_RIC).chain(vel).collect()
            } else {
                let ric = HML_RIC + 3 * (joint - 1);
                let rot = HML_ROT + 6 * (joint - 1);
                (ric..ric + 3).chain(rot..rot + 6).chain(vel).collect()
            };
            if let Some(k) = HML_CONTACT_JOINTS.iter().position(|&j| j == joint) {
                c.push(HML_CONTACTS + k);
            }
            c
        }
    })
}

/// The root trajectory's channels: `smpl24_6d` 0..3 (translation), `humanml263` 0..4 (yaw
/// velocity, planar velocity, height).
pub fn root_path_channels(format: Format) -> Vec<usize> {
    match format {
        Format::Smpl24Rot6d => (0..3).collect(),
        Format::HumanMl263 => (0..HML_RIC).collect(),
    }
}

/// The joints of the lower body (pelvis and legs) that exist in `format`, ascending.
pub(crate) fn lower_body_joints(format: Format) -> Vec<usize> {
    let joints = format.skeleton().joint_count();
    std::iter::once(0)
        .chain(LEG_JOINTS)
        .filter(|&j| j < joints)
        .collect()
}

/// The channels of a body part (ascending, no repeats). Lower and upper body partition the
/// features.
pub fn part_channels(format: Format, part: BodyPart) -> Vec<usize> {
    let joints = format.skeleton().joint_count();
    let exists = |j: &usize| *j < joints;
    let lower = |j: &usize| *j == 0 || LEG_JOINTS.contains(j);
    let (set, with_root): (Vec<usize>, bool) = match part {
        BodyPart::RootPath => (Vec::new(), true),
        BodyPart::LowerBody => ((0..joints).filter(lower).collect(), true),
        BodyPart::UpperBody => ((0..joints).filter(|j| !lower(j)).collect(), false),
        BodyPart::Arms => (ARM_JOINTS.into_iter().filter(exists).collect(), false),
        BodyPart::Legs => (LEG_JOINTS.to_vec(), false),
    };
    let mut channels: Vec<usize> = if with_root {
        root_path_channels(format)
    } else {
        Vec::new()
    };
    for j in set {
        // Every joint here exists by construction.
        channels.extend(joint_channels(format, j).unwrap_or_default());
    }
    channels.sort_unstable();
    channels.dedup();
    channels
}

/// What one item of a joint list names: a joint, or the root path (`root`, `root-path`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Selected {
    Joint(usize),
    RootPath,
}

/// Looks a joint up by index or by name (case-insensitive, SMPL's `L_Knee` or HumanML3D's
/// `left_knee` spelling for either format, since HumanML3D's joints are SMPL's first 22).
fn select(item: &str, format: Format) -> Result<Selected> {
    let item = item.trim();
    if item.eq_ignore_ascii_case("root") || item.eq_ignore_ascii_case("root-path") {
        return Ok(Selected::RootPath);
    }
    let joints = format.skeleton().joint_count();
    let index = match item.parse::<usize>() {
        Ok(j) => j,
        Err(_) => [Skeleton::smpl24(), Skeleton::humanml22()]
            .iter()
            .find_map(|s| {
                s.joint_names()
                    .iter()
                    .position(|n| n.eq_ignore_ascii_case(item))
            })
            .ok_or_else(|| {
                invalid_arg!(
                    "unknown joint `{item}` (give an index from 0 to {}, a joint name such as {} or root-path)",
                    joints - 1,
                    format.skeleton().joint_names()[4]
                )
            })?,
    };
    if index >= joints {
        return Err(invalid_arg!(
            "joint `{item}` ({index}) does not exist in {format} ({joints} joints)"
        ));
    }
    Ok(Selected::Joint(index))
}

/// Parses a comma-separated joint list (`"0,L_Knee,left_wrist"`) into joint indices, in the
/// given order. `root`/`root-path` is not a joint: [`Mask::keep_joint_list`] accepts it.
pub fn parse_joints(spec: &str, format: Format) -> Result<Vec<usize>> {
    split_list(spec, "joint")?
        .into_iter()
        .map(|item| match select(item, format)? {
            Selected::Joint(j) => Ok(j),
            Selected::RootPath => Err(invalid_arg!(
                "`{item}` is the root path, not a joint; use Mask::keep_joint_list or the root-path body part"
            )),
        })
        .collect()
}

/// Parses comma-separated half-open frame ranges `"A:B,C:D"` over `frames` frames: `:B` starts at
/// 0, `A:` runs to the end, a lone `A` is the one frame `A:A+1`, and a negative number counts
/// from the end (`-10:` = the last ten frames). Every range must be non-empty and inside the
/// motion.
pub fn parse_frame_ranges(spec: &str, frames: usize) -> Result<Vec<(usize, usize)>> {
    split_list(spec, "frame range")?
        .into_iter()
        .map(|item| {
            let bound = |s: &str, default: usize| -> Result<usize> {
                let s = s.trim();
                if s.is_empty() {
                    return Ok(default);
                }
                let v: i64 = s
                    .parse()
                    .map_err(|_| invalid_arg!("frame range `{item}`: `{s}` is not an integer"))?;
                let resolved = if v < 0 {
                    (frames as i64).checked_add(v)
                } else {
                    Some(v)
                };
                match resolved {
                    Some(r) if (0..=frames as i64).contains(&r) => Ok(r as usize),
                    _ => Err(invalid_arg!(
                        "frame range `{item}`: {v} is outside a motion of {frames} frames"
                    )),
                }
            };
            let (start, end) = match item.split_once(':') {
                Some((a, b)) => (bound(a, 0)?, bound(b, frames)?),
                None => {
                    let a = bound(item, 0)?;
                    (a, a + 1)
                }
            };
            check_range(start, end, frames).map_err(|e| match e {
                Error::InvalidArgument(m) => invalid_arg!("frame range `{item}`: {m}"),
                other => other,
            })?;
            Ok((start, end))
        })
        .collect()
}

/// The non-empty, trimmed items of a comma-separated list.
fn split_list<'a>(spec: &'a str, what: &str) -> Result<Vec<&'a str>> {
    let items: Vec<&str> = spec.split(',').map(str::trim).collect();
    if items.iter().any(|s| s.is_empty()) {
        return Err(invalid_arg!(
            "empty {what} in `{spec}` (expected a comma-separated list)"
        ));
    }
    Ok(items)
}

/// `[start, end)` must be non-empty and end at or before `frames`.
fn check_range(start: usize, end: usize, frames: usize) -> Result<()> {
    if start >= end {
        return Err(invalid_arg!(
            "frames from {start} to {end} (end excluded) are an empty range (start must be below end)"
        ));
    }
    if end > frames {
        return Err(invalid_arg!(
            "frames from {start} to {end} (end excluded) run past the motion's {frames} frames"
        ));
    }
    Ok(())
}

/// A keep-mask: `true` = keep the reference's value, `false` = generate it. Frame-major
/// `[frames, feature_dim]`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Mask {
    format: Format,
    frames: usize,
    keep: Vec<bool>,
}

impl Mask {
    /// A mask over `frames` frames that keeps nothing.
    pub fn new(format: Format, frames: usize) -> Result<Mask> {
        let n = frames
            .checked_mul(format.feature_dim())
            .ok_or_else(|| invalid_arg!("a mask of {frames} frames of {format} overflows"))?;
        Ok(Mask {
            format,
            frames,
            keep: vec![false; n],
        })
    }

    /// A mask from C-style flags (0 = generate, 1 = keep), `[frames, feature_dim]`. Other values
    /// are rejected: they usually mean a float or a wrong-typed buffer was passed.
    pub fn from_flags(format: Format, frames: usize, flags: &[u8]) -> Result<Mask> {
        let mut m = Mask::new(format, frames)?;
        if flags.len() != m.keep.len() {
            return Err(invalid_arg!(
                "mask holds {} flags; {frames} frames of {format} need {} ({frames} x {})",
                flags.len(),
                m.keep.len(),
                format.feature_dim()
            ));
        }
        let dim = format.feature_dim();
        for (i, (&f, k)) in flags.iter().zip(&mut m.keep).enumerate() {
            *k = match f {
                0 => false,
                1 => true,
                v => {
                    return Err(invalid_arg!(
                        "mask flag at frame {}, channel {} is {v}; expected 0 or 1",
                        i / dim,
                        i % dim
                    ))
                }
            };
        }
        Ok(m)
    }

    /// The mask of a standard task over a reference of `frames` frames. Errors when the task
    /// would keep nothing or regenerate nothing at this length (prediction needs 4 frames,
    /// in-betweening 2).
    pub fn for_task(format: Format, frames: usize, task: Task) -> Result<Mask> {
        if frames == 0 {
            return Err(invalid_arg!(
                "task {task} needs a reference of at least one frame"
            ));
        }
        let mut m = Mask::new(format, frames)?;
        // ⌊L/4⌋ and ⌊3L/4⌋ as the official int(0.25·L), int(0.75·L), without overflow.
        let quarter = frames / 4;
        let three_quarters = quarter * 3 + (frames % 4) * 3 / 4;
        match task {
            Task::Inbetween => {
                if quarter == three_quarters {
                    return Err(invalid_arg!(
                        "in-betweening {frames} frame(s) regenerates nothing; give at least 2"
                    ));
                }
                m.keep_all();
                m.set_frames(quarter, three_quarters, false);
            }
            Task::Predict => {
                if quarter == 0 {
                    return Err(invalid_arg!(
                        "prediction keeps the first quarter of the frames; {frames} frame(s) keep none, give at least 4"
                    ));
                }
                m.keep_frames(0, quarter)?;
            }
            Task::UpperBody => m.keep_part(BodyPart::LowerBody, 0, frames)?,
            Task::Path => m.keep_part(BodyPart::RootPath, 0, frames)?,
        }
        Ok(m)
    }

    /// The feature format the mask is laid over (its `feature_dim` flags per frame).
    pub fn format(&self) -> Format {
        self.format
    }

    /// Number of frames the mask covers.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// The flags, frame-major `[frames, feature_dim]`.
    pub fn flags(&self) -> &[bool] {
        &self.keep
    }

    /// Keeps every value of every frame.
    pub fn keep_all(&mut self) {
        self.keep.fill(true);
    }

    /// Keeps all channels of frames `[start, end)`; `end` = `frames` means to the end.
    pub fn keep_frames(&mut self, start: usize, end: usize) -> Result<()> {
        check_range(start, end, self.frames)?;
        self.set_frames(start, end, true);
        Ok(())
    }

    /// Keeps `channels` on frames `[start, end)`. Every channel is checked before any is set.
    pub fn keep_channels(&mut self, channels: &[usize], start: usize, end: usize) -> Result<()> {
        check_range(start, end, self.frames)?;
        let dim = self.format.feature_dim();
        if let Some(c) = channels.iter().find(|&&c| c >= dim) {
            return Err(invalid_arg!(
                "channel {c} does not exist: {} has {dim} features",
                self.format
            ));
        }
        for row in self.keep[start * dim..end * dim].chunks_exact_mut(dim) {
            for &c in channels {
                row[c] = true;
            }
        }
        Ok(())
    }

    /// Keeps joint `joint`'s channels ([`joint_channels`]) on frames `[start, end)`.
    pub fn keep_joint(&mut self, joint: usize, start: usize, end: usize) -> Result<()> {
        let channels = joint_channels(self.format, joint)?;
        self.keep_channels(&channels, start, end)
    }

    /// Keeps a joint given by name (case-insensitive; `root`/`root-path` = the root path) or
    /// index on frames `[start, end)`.
    pub fn keep_joint_named(&mut self, name: &str, start: usize, end: usize) -> Result<()> {
        match select(name, self.format)? {
            Selected::Joint(j) => self.keep_joint(j, start, end),
            Selected::RootPath => self.keep_part(BodyPart::RootPath, start, end),
        }
    }

    /// Keeps every item of a comma-separated list of joints (indices, names, `root-path`) on
    /// frames `[start, end)`; the whole list is checked before anything is set.
    pub fn keep_joint_list(&mut self, spec: &str, start: usize, end: usize) -> Result<()> {
        let mut channels = Vec::new();
        for item in split_list(spec, "joint")? {
            match select(item, self.format)? {
                Selected::Joint(j) => channels.extend(joint_channels(self.format, j)?),
                Selected::RootPath => channels.extend(root_path_channels(self.format)),
            }
        }
        self.keep_channels(&channels, start, end)
    }

    /// Keeps a body part's channels ([`part_channels`]) on frames `[start, end)`.
    pub fn keep_part(&mut self, part: BodyPart, start: usize, end: usize) -> Result<()> {
        self.keep_channels(&part_channels(self.format, part), start, end)
    }

    /// How many values are kept.
    pub fn kept_count(&self) -> usize {
        self.keep.iter().filter(|&&k| k).count()
    }

    /// Nothing kept: editing with this mask is plain generation.
    pub fn is_empty(&self) -> bool {
        !self.keep.contains(&true)
    }

    /// Everything kept: editing with this mask returns the reference.
    pub fn is_full(&self) -> bool {
        !self.keep.contains(&false)
    }

    /// The last frame with at least one kept value, `None` when nothing is kept (a session can
    /// check that a reference covers it).
    pub fn last_kept_frame(&self) -> Option<usize> {
        let dim = self.format.feature_dim();
        self.keep.iter().rposition(|&k| k).map(|i| i / dim)
    }

    fn set_frames(&mut self, start: usize, end: usize, keep: bool) {
        let dim = self.format.feature_dim();
        self.keep[start * dim..end * dim].fill(keep);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn smpl_joints_are_their_six_d_blocks() {
        let f = Format::Smpl24Rot6d;
        assert_eq!(joint_channels(f, 0).unwrap(), vec![3, 4, 5, 6, 7, 8]);
        assert_eq!(
            joint_channels(f, 23).unwrap(),
            (141..147).collect::<Vec<_>>()
        );
        let e = joint_channels(f, 24).unwrap_err().to_string();
        assert!(
            e.contains("joint 24 does not exist: smpl24_6d has 24 joints"),
            "{e}"
        );
    }

    #[test]
    fn humanml_joints_own_ric_rot_velocity_and_contacts() {
        let f = Format::HumanMl263;
        // Root: dims 0..4 and its velocity 193..196.
        assert_eq!(
            joint_channels(f, 0).unwrap(),
            vec![0, 1, 2, 3, 193, 194, 195]
        );
        // Right wrist (21): ric 4+60.., rot 67+120.., velocity 193+63..; no contact.
        assert_eq!(
            joint_channels(f, 21).unwrap(),
            vec![64, 65, 66, 187, 188, 189, 190, 191, 192, 256, 257, 258]
        );
        // Right foot (11) owns contact 262 (order: L ankle, L foot, R ankle, R foot).
        assert_eq!(*joint_channels(f, 11).unwrap().last().unwrap(), 262);
        assert_eq!(*joint_channels(f, 7).unwrap().last().unwrap(), 259);
        assert!(joint_channels(f, 22).is_err());
    }

    #[test]
    fn names_parse_both_ways() {
        for p in BodyPart::ALL {
            assert_eq!(p.name().parse::<BodyPart>().unwrap(), p);
        }
        for t in Task::ALL {
            assert_eq!(t.name().parse::<Task>().unwrap(), t);
        }
        assert!("torso".parse::<BodyPart>().is_err());
        assert!("in-between".parse::<Task>().is_err());
    }
}
