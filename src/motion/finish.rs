//! Game-ready clips from decoded poses: foot contacts, the floor, foot locking, loops, root
//! motion and the frame rate, applied in that order to a [`Poses`] and giving a [`Poses`]. This is
//! geometry on poses, after the model: the raw features and the sampler never see it, and
//! [`Finish::default`] (every step off) leaves the decode exactly as it was.
//!
//! | step | option | what it does | module |
//! |---|---|---|---|
//! | contacts | [`Finish::contacts`] | per foot joint and frame; humanml263 from its features, smpl24_6d detected | [`super::contacts`] |
//! | floor | [`Finish::ground`] | the lowest contact point over the clip put at height 0 | [`super::feet`] |
//! | feet | [`Finish::feet`] | each contact span's foot joint pinned, the leg solved by two-bone IK | [`super::feet`] |
//! | loop | [`Finish::wrap`] | the last frames cross-faded into the first, root motion kept | [`super::looping`] |
//! | root motion | [`Finish::root_motion`] | keep, remove the horizontal root path, or put it on a root bone | [`super::root_motion`] |
//! | frame rate | [`Finish::fps`] | resampled by slerp (rotations) and linear interpolation (translations) | [`super::resample`] |
//!
//! Everything runs in the format's native world frame (Y up for humanml263, Z up for
//! smpl24_6d: [`Format::up_axis`]) and in metres, before any convention is applied.

use std::fmt;
use std::str::FromStr;

use super::contacts::{self, ContactParams};
use super::format::Format;
use super::poses::Poses;
use super::{feet, looping, resample, root_motion};
use crate::error::{invalid_arg, Error, Result};

/// What happens to the feet during their contact spans.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum Feet {
    /// The raw poses: feet may slide.
    #[default]
    Off = 0,
    /// Each contact span's foot joint is pinned where it stands, the leg solved by two-bone IK.
    Lock = 1,
}

/// Where the horizontal travel of the clip goes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum RootMotion {
    /// The pelvis carries it (the model's own motion).
    #[default]
    Keep = 0,
    /// Removed: the pelvis stays over the origin (an in-place clip).
    InPlace = 1,
    /// Moved to a `root` bone on the ground under the pelvis, parent of the pelvis (the Unreal
    /// Mannequin's `root`, Unity's root transform): exporters write that bone.
    Separate = 2,
}

/// The post-processing applied when poses are read. `Default` = nothing (raw poses).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Finish {
    /// How smpl24_6d contacts are detected (humanml263 reads its own).
    pub contacts: ContactParams,
    /// Put the lowest contact point of the clip at height 0.
    pub ground: bool,
    /// Foot locking.
    pub feet: Feet,
    /// Make the clip's end flow into its start (a cross-fade of the last frames; the generated
    /// loop itself comes from editing, see `session`).
    pub wrap: bool,
    /// Where the horizontal root travel goes.
    pub root_motion: RootMotion,
    /// With [`RootMotion::InPlace`] or [`RootMotion::Separate`]: also remove the heading's drift
    /// (the yaw of the root) from the pelvis.
    pub remove_yaw: bool,
    /// Output frame rate; `None` = the model's.
    pub fps: Option<f64>,
}

impl Finish {
    /// The game-ready defaults of `flame generate` for pose outputs: contacts, floor and feet
    /// locked; root motion kept; the model's frame rate.
    pub fn game_ready() -> Finish {
        Finish {
            ground: true,
            feet: Feet::Lock,
            ..Finish::default()
        }
    }

    /// Whether this leaves the decoded poses untouched.
    pub fn is_identity(&self) -> bool {
        !self.ground
            && self.feet == Feet::Off
            && !self.wrap
            && self.root_motion == RootMotion::Keep
            && self.fps.is_none()
    }

    /// Checks every value; errors name the offending one.
    pub fn validate(&self) -> Result<()> {
        self.contacts.validate()?;
        if let Some(fps) = self.fps {
            check_fps(fps)?;
        }
        Ok(())
    }

    /// The frame rate of the output given the model's.
    pub fn output_fps(&self, source_fps: f64) -> f64 {
        self.fps.unwrap_or(source_fps)
    }

    /// `poses` (decoded at `source_fps`) with every step applied.
    pub fn apply(&self, poses: &Poses, source_fps: f64) -> Result<Poses> {
        self.validate()?;
        if !(source_fps.is_finite() && source_fps > 0.0) {
            return Err(invalid_arg!(
                "source frame rate must be positive, got {source_fps}"
            ));
        }
        let mut out = poses.clone();
        if self.is_identity() {
            return Ok(out);
        }
        let on_floor = contacts::of(&out, source_fps, &self.contacts);
        out.contacts = on_floor
            .iter()
            .map(|c| c.map(|on| if on { 1.0 } else { 0.0 }))
            .collect();
        if self.ground {
            feet::put_on_ground(&mut out, &on_floor);
        }
        if self.feet == Feet::Lock {
            feet::lock(&mut out, &on_floor, source_fps)?;
        }
        if self.wrap {
            looping::wrap(&mut out, source_fps)?;
        }
        root_motion::apply(&mut out, self.root_motion, self.remove_yaw);
        match self.fps {
            Some(fps) if fps != source_fps => resample::resample(&out, source_fps, fps),
            _ => Ok(out),
        }
    }
}

/// The range `--fps` and the read parameters accept.
pub const FPS_RANGE: std::ops::RangeInclusive<f64> = 1.0..=240.0;

fn check_fps(fps: f64) -> Result<()> {
    if !FPS_RANGE.contains(&fps) {
        return Err(invalid_arg!(
            "frame rate must be between {} and {} frames per second, got {fps}",
            FPS_RANGE.start(),
            FPS_RANGE.end()
        ));
    }
    Ok(())
}

impl Feet {
    pub const ALL: [Feet; 2] = [Feet::Off, Feet::Lock];

    pub fn name(self) -> &'static str {
        match self {
            Feet::Off => "off",
            Feet::Lock => "lock",
        }
    }

    /// The value with integer `v` (the C ABI's enum).
    pub fn from_u32(v: u32) -> Result<Feet> {
        Feet::ALL
            .get(v as usize)
            .copied()
            .ok_or_else(|| invalid_arg!("unknown feet mode {v} (0 off, 1 lock)"))
    }
}

impl RootMotion {
    pub const ALL: [RootMotion; 3] = [RootMotion::Keep, RootMotion::InPlace, RootMotion::Separate];

    pub fn name(self) -> &'static str {
        match self {
            RootMotion::Keep => "keep",
            RootMotion::InPlace => "in-place",
            RootMotion::Separate => "separate",
        }
    }

    /// The value with integer `v` (the C ABI's enum).
    pub fn from_u32(v: u32) -> Result<RootMotion> {
        RootMotion::ALL
            .get(v as usize)
            .copied()
            .ok_or_else(|| invalid_arg!("unknown root motion {v} (0 keep, 1 in-place, 2 separate)"))
    }
}

macro_rules! named_enum {
    ($t:ty, $what:literal) => {
        impl FromStr for $t {
            type Err = Error;
            fn from_str(s: &str) -> Result<$t> {
                <$t>::ALL
                    .iter()
                    .copied()
                    .find(|v| v.name() == s)
                    .ok_or_else(|| {
                        let names: Vec<&str> = <$t>::ALL.iter().map(|v| v.name()).collect();
                        invalid_arg!("unknown {} {s:?} (one of {})", $what, names.join(", "))
                    })
            }
        }

        impl fmt::Display for $t {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str(self.name())
            }
        }
    };
}
named_enum!(Feet, "feet mode");
named_enum!(RootMotion, "root motion");

impl Format {
    /// The index (0 x, 1 y, 2 z) of the native world frame's up axis, which points up (+):
    /// humanml263 is Y up, smpl24_6d's AMASS world Z up.
    pub fn up_axis(self) -> usize {
        match self {
            Format::Smpl24Rot6d => 2,
            Format::HumanMl263 => 1,
        }
    }
}
