//! Foot contacts per foot joint and frame, in the order left ankle (7), left foot (10), right
//! ankle (8), right foot (11) — HumanML3D's feature order (`feet_l`, then `feet_r`, each ankle
//! then toe: `fid_l = [7, 10]`, `fid_r = [8, 11]` in EricGuo5513/HumanML3D
//! `motion_representation.ipynb`, `process_file`).
//!
//! - `humanml263` carries them in its last 4 features; they are read and thresholded at 0.5.
//! - `smpl24_6d` carries none; they are detected from each foot joint's height above the clip's
//!   floor and its speed, with hysteresis and a minimum span ([`ContactParams`]).
//!
//! Whatever the format, contacts already stored in [`Poses`] (a humanml263 decode's, or the
//! finished 0/1 ones a [`super::Finish`] left) are used as they are, so finishing a finished clip
//! sees the same contacts.
//!
//! # Detection (smpl24_6d)
//!
//! - **Floor**: the lowest height any of the four foot joints reaches over the clip (HumanML3D's
//!   own "put on floor" likewise takes the lowest joint of the clip, `process_file`).
//! - **Height** of a joint: its height above the floor minus its *standing level*: 0 for a toe,
//!   and for an ankle the rest height of the ankle above its own toe joint (the body-up component
//!   of the toe's rest offset: 5.6 cm left, 4.8 cm right on SMPL's template), so an ankle of a
//!   foot standing flat has height ≈ 0 like its toe and one margin serves both joints.
//! - **Speed**: the 3D speed of the joint by central differences (one-sided at the clip's ends),
//!   in m/s. HumanML3D's labels also use the 3D displacement.
//! - A joint **enters** contact when height < [`ContactParams::height`] and speed <
//!   [`ContactParams::speed`], and **stays** in contact until its height exceeds the threshold
//!   times [`ContactParams::release`] (hysteresis: heights hovering at the threshold do not
//!   chatter) or its speed exceeds [`ContactParams::speed`].
//! - **Minimum span**: first every gap shorter than [`ContactParams::min_span`] between two
//!   contact spans is closed (a one-frame lift inside a stance is noise), then every span shorter
//!   than it is dropped (a one-frame touch-down is noise).

use super::format::Format;
use super::poses::Poses;
use super::rotation::Vec3;
use crate::error::{invalid_arg, Result};

/// The joint of each contact slot: left ankle, left foot (toe), right ankle, right foot.
pub const SLOT_JOINTS: [usize; 4] = [7, 10, 8, 11];

/// How smpl24_6d contacts are detected (module doc). Every field is checked by
/// [`ContactParams::validate`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ContactParams {
    /// Metres: a foot joint can enter contact only while its height above its standing level
    /// (module doc) is below this. Default 0.05 m: the contact height of the foot-skating metric
    /// of GMD and OmniControl (`thresh_height = 0.05` in `calculate_skating_ratio`,
    /// korrawe/guided-motion-diffusion and neu-vi/OmniControl,
    /// `data_loaders/humanml/utils/metrics.py`), the usual yardstick of generated motion.
    pub height: f64,
    /// Metres per second: a foot joint can enter contact only while its 3D speed is below this.
    /// Default √0.002 · 20 ≈ 0.894 m/s: HumanML3D's own labels (`foot_detect` in `process_file`,
    /// EricGuo5513/HumanML3D `motion_representation.ipynb`) call a joint in contact when its
    /// squared per-frame displacement is under `velfactor = 0.002` m² at 20 fps. Using the labels'
    /// threshold gives smpl24_6d contacts with the meaning humanml263 models are trained on. It
    /// is above the skating metric's 0.5 m/s on purpose: a planted foot that a model lets slide
    /// at 0.5–0.9 m/s must still count as planted so locking can fix it.
    pub speed: f64,
    /// Ratio ≥ 1: a joint in contact leaves it when its height exceeds `height · release`, or
    /// its speed exceeds `speed` (the band is on height only). Default 1.5: decoded model output
    /// jitters by a few centimetres from frame to frame, and a band of half the height (2.5 cm)
    /// absorbs that. Speed has no band: a foot moving at walking speed has left the floor
    /// whatever its height — the demo model's small steps lift the toe only ~6 cm at ~1 m/s, and
    /// a band of 1.5 on speed as well kept such a step planted, so locking erased it, while a
    /// planted foot's jitter stays far below 0.894 m/s. 1 = no hysteresis.
    pub release: f64,
    /// Seconds: contact spans shorter than this are dropped, and gaps shorter than this between
    /// two contact spans are closed. Default 0.1 s (2 frames at 20 fps): a one-frame (50 ms)
    /// flicker is removed, while every real contact is longer (walking stance ≈ 0.6 s, Perry &
    /// Burnfield, *Gait Analysis*, 2nd ed., ch. 2; sprinting contacts ≈ 0.1 s, Weyand et al.
    /// 2000, J. Appl. Physiol. 89(5)). 0 keeps everything.
    pub min_span: f64,
}

impl Default for ContactParams {
    /// Height 0.05 m, speed √0.002·20 m/s, release 1.5, minimum span 0.1 s (field docs say why).
    fn default() -> Self {
        ContactParams {
            height: 0.05,
            speed: 0.002f64.sqrt() * 20.0,
            release: 1.5,
            min_span: 0.1,
        }
    }
}

impl ContactParams {
    /// Checks every value: height in [0, 1] m, speed in [0, 20] m/s, release in [1, 10],
    /// minimum span in [0, 10] s. Larger values would call a person in the air or running in
    /// contact, so they are mistakes, not settings.
    pub fn validate(&self) -> Result<()> {
        let checks = [
            ("contact height (m)", self.height, 0.0, 1.0),
            ("contact speed (m/s)", self.speed, 0.0, 20.0),
            ("contact release ratio", self.release, 1.0, 10.0),
            ("contact minimum span (s)", self.min_span, 0.0, 10.0),
        ];
        for (name, v, lo, hi) in checks {
            if !(lo..=hi).contains(&v) {
                return Err(invalid_arg!(
                    "{name} must be between {lo} and {hi}, got {v}"
                ));
            }
        }
        Ok(())
    }

    /// The minimum span in frames at `fps` (at least 1).
    pub(crate) fn min_frames(&self, fps: f64) -> usize {
        ((self.min_span * fps).round() as usize).max(1)
    }
}

/// `[frames]` contacts `[L ankle, L foot, R ankle, R foot]`: the stored ones thresholded at 0.5
/// when `poses` has them (humanml263's features, or a finish's), else detected from heights and
/// speeds at `fps` with `params` (module doc). `params` are assumed valid.
pub fn of(poses: &Poses, fps: f64, params: &ContactParams) -> Vec<[bool; 4]> {
    if poses.contacts.len() == poses.frames && poses.frames > 0 {
        return poses.contacts.iter().map(|c| c.map(|v| v > 0.5)).collect();
    }
    detect(poses, fps, params)
}

/// Detection from heights and speeds (module doc).
fn detect(poses: &Poses, fps: f64, params: &ContactParams) -> Vec<[bool; 4]> {
    detect_on(poses, fps, params, None)
}

/// [`detect`] with the floor given (a stream fixes it once, `crate::stream`) instead of the
/// clip's lowest foot joint.
pub(crate) fn detect_on(
    poses: &Poses,
    fps: f64,
    params: &ContactParams,
    floor: Option<f64>,
) -> Vec<[bool; 4]> {
    let frames = poses.frames;
    let joints = poses.joint_count();
    let up = poses.format.up_axis();
    let mut out = vec![[false; 4]; frames];
    if frames == 0 || joints <= SLOT_JOINTS[3] {
        return out;
    }
    let at = |t: usize, j: usize| -> &Vec3 { &poses.positions[t * joints + j] };
    let floor = floor.unwrap_or_else(|| {
        (0..frames)
            .flat_map(|t| SLOT_JOINTS.iter().map(move |&j| at(t, j)[up]))
            .fold(f64::INFINITY, f64::min)
    });
    let levels = standing_levels(poses.format);
    let fps = if fps.is_finite() && fps > 0.0 {
        fps
    } else {
        poses.format.fps() as f64
    };
    let min_frames = params.min_frames(fps);
    let mut track = vec![false; frames];
    for (slot, &j) in SLOT_JOINTS.iter().enumerate() {
        let mut on = false;
        for (t, c) in track.iter_mut().enumerate() {
            let height = at(t, j)[up] - floor - levels[slot];
            let speed = speed_at(t, frames, fps, |i| at(i, j));
            on = next_state(on, height, speed, params);
            *c = on;
        }
        clean_spans(&mut track, min_frames);
        for (o, &c) in out.iter_mut().zip(&track) {
            o[slot] = c;
        }
    }
    out
}

/// One frame of the hysteresis rule (module doc): whether a joint is in contact, given its
/// height above its standing level, its speed and whether it was in contact the frame before.
pub(crate) fn next_state(was_on: bool, height: f64, speed: f64, params: &ContactParams) -> bool {
    let k = if was_on { params.release } else { 1.0 };
    height < params.height * k && speed < params.speed
}

/// Per slot, how high the joint stands above the floor when its foot is flat: 0 for a toe; for
/// an ankle the body-up (Y) component of its toe's rest offset, negated (SMPL's rest body frame
/// is Y up; a skeleton whose toes point straight forward, like HumanML3D's, gives 0).
pub(crate) fn standing_levels(format: Format) -> [f64; 4] {
    let offsets = format.skeleton().rest_offsets();
    let ankle = |toe: usize| (-offsets[toe][1]).max(0.0);
    [ankle(SLOT_JOINTS[1]), 0.0, ankle(SLOT_JOINTS[3]), 0.0]
}

/// The speed (m/s) of a track at frame `t` by central differences, one-sided at the ends, 0 for a
/// one-frame clip.
pub(crate) fn speed_at<'a>(
    t: usize,
    frames: usize,
    fps: f64,
    p: impl Fn(usize) -> &'a Vec3,
) -> f64 {
    if frames < 2 {
        return 0.0;
    }
    let (a, b) = (t.saturating_sub(1), (t + 1).min(frames - 1));
    let (pa, pb) = (p(a), p(b));
    let d = [pb[0] - pa[0], pb[1] - pa[1], pb[2] - pa[2]];
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() * fps / (b - a) as f64
}

/// Closes gaps shorter than `min` frames between two spans, then drops spans shorter than `min`
/// (unless one span is the whole clip).
pub(crate) fn clean_spans(track: &mut [bool], min: usize) {
    for (s, e) in runs(track, false) {
        if s > 0 && e + 1 < track.len() && e + 1 - s < min {
            track[s..=e].fill(true);
        }
    }
    let last = track.len().saturating_sub(1);
    for (s, e) in runs(track, true) {
        // A span covering the whole clip is all the clip knows, not a flicker.
        if e + 1 - s < min && (s, e) != (0, last) {
            track[s..=e].fill(false);
        }
    }
}

/// The maximal runs `(first, last)` (inclusive) of `value` in `track`.
pub(crate) fn runs(track: &[bool], value: bool) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut start = None;
    for (t, &v) in track.iter().enumerate() {
        match (v == value, start) {
            (true, None) => start = Some(t),
            (false, Some(s)) => {
                out.push((s, t - 1));
                start = None;
            }
            _ => {}
        }
    }
    if let Some(s) = start {
        out.push((s, track.len() - 1));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smpl24_6d clip whose four foot joints follow `track` (height, forward position) per
    /// frame, each ankle at its standing level above its toe. Other joints stay at the origin;
    /// detection reads only the foot joints.
    fn clip(track: &[(f64, f64)]) -> Poses {
        let mut p = Poses::empty(Format::Smpl24Rot6d, track.len());
        let levels = standing_levels(Format::Smpl24Rot6d);
        let j = p.joint_count();
        for (t, &(h, y)) in track.iter().enumerate() {
            for (slot, &joint) in SLOT_JOINTS.iter().enumerate() {
                // Z up; the floor sits at 0 because some frame of every track has height 0.
                p.positions[t * j + joint] = [0.1 * slot as f64, y, h + levels[slot]];
            }
        }
        p
    }

    fn left_toe(c: &[[bool; 4]]) -> Vec<bool> {
        c.iter().map(|c| c[1]).collect()
    }

    #[test]
    fn defaults_are_the_cited_values_and_valid() {
        let d = ContactParams::default();
        assert_eq!(d.height, 0.05);
        // velfactor 0.002 m² per frame at 20 fps.
        assert!((d.speed - 0.894427).abs() < 1e-6);
        assert_eq!(d.min_frames(20.0), 2);
        d.validate().unwrap();
    }

    #[test]
    fn validate_names_the_bad_value() {
        let bad = [
            (
                ContactParams {
                    height: -0.1,
                    ..Default::default()
                },
                "contact height (m) must be between 0 and 1, got -0.1",
            ),
            (
                ContactParams {
                    speed: f64::NAN,
                    ..Default::default()
                },
                "contact speed (m/s) must be between 0 and 20, got NaN",
            ),
            (
                ContactParams {
                    release: 0.5,
                    ..Default::default()
                },
                "contact release ratio must be between 1 and 10, got 0.5",
            ),
            (
                ContactParams {
                    min_span: 1e6,
                    ..Default::default()
                },
                "contact minimum span (s) must be between 0 and 10, got 1000000",
            ),
        ];
        for (p, want) in bad {
            let e = p.validate().unwrap_err().to_string();
            assert!(e.contains(want), "{e}");
        }
    }

    #[test]
    fn one_frame_flicker_is_ignored_and_a_one_frame_lift_is_closed() {
        // Heights (m), no horizontal motion, so speeds are vertical central differences:
        // 0-5 on the floor; 6, 7, 9 in the air at 0.3; frame 8 dips to the floor between two
        // equally high frames (speed 0: a one-frame touch-down); 10-17 on the floor except frame
        // 13 lifted to 0.08 (over the release height 0.075; its neighbours' speeds 0.8 m/s stay
        // under the entry speed, so frame 14 re-enters); 18, 19 in the air. Frames 5, 10 and 17
        // border the air (speed 0.3 / 2 · 20 = 3 m/s) and are out.
        let mut h = [0.0; 20];
        for t in [6, 7, 9, 18, 19] {
            h[t] = 0.3;
        }
        h[13] = 0.08;
        let track: Vec<(f64, f64)> = h.iter().map(|&h| (h, 0.0)).collect();
        let p = clip(&track);
        let c = left_toe(&of(&p, 20.0, &ContactParams::default()));
        let want: Vec<bool> = (0..20).map(|t| t < 5 || (11..17).contains(&t)).collect();
        assert_eq!(c, want);
        // Without the minimum span both flickers show: the method is what removes them.
        let raw = ContactParams {
            min_span: 0.0,
            ..Default::default()
        };
        let c = left_toe(&of(&p, 20.0, &raw));
        assert!(c[8] && !c[13] && c[12] && c[14], "{c:?}");
    }

    #[test]
    fn hysteresis_enters_low_and_leaves_high() {
        // Height in cm: air 30, hover 6 (between the entry 5 and release 7.5 heights), floor 0,
        // hover 6 again, air. Entry at 6 cm is refused; once in contact, 6 cm keeps it.
        let h = [30.0, 6.0, 6.0, 6.0, 0.0, 0.0, 6.0, 6.0, 6.0, 30.0, 30.0];
        let track: Vec<(f64, f64)> = h.iter().map(|&c| (c / 100.0, 0.0)).collect();
        let p = clip(&track);
        let c = left_toe(&of(&p, 20.0, &ContactParams::default()));
        // Frame 8 is still in contact by height, but its central speed (0.24 m over 2 frames at
        // 20 fps = 2.4 m/s) is past the speed threshold.
        let want = [
            false, false, false, false, true, true, true, true, false, false, false,
        ];
        assert_eq!(c, want);
        let no_hysteresis = ContactParams {
            release: 1.0,
            min_span: 0.0,
            ..Default::default()
        };
        let c = left_toe(&of(&p, 20.0, &no_hysteresis));
        assert_eq!(
            c,
            [false, false, false, false, true, true, false, false, false, false, false]
        );
    }

    #[test]
    fn a_sliding_foot_on_the_floor_is_not_in_contact_above_the_speed() {
        // On the floor, moving forward 0.03 m per frame (0.6 m/s: under the speed 0.894), then
        // 0.05 (1.0 m/s: over it, so the contact ends although the foot is on the floor; frame
        // 6 straddles 0.03 and 0.05: 0.8 m/s, still in).
        let mut y = 0.0;
        let mut track = Vec::new();
        for step in [0.03; 6].iter().chain(&[0.05; 8]) {
            track.push((0.0, y));
            y += step;
        }
        let p = clip(&track);
        let c = left_toe(&of(&p, 20.0, &ContactParams::default()));
        assert!(c[..7].iter().all(|&c| c), "{c:?}");
        assert!(c[7..].iter().all(|&c| !c), "{c:?}");
        // Entering at 1.2 m/s is refused.
        let fast: Vec<(f64, f64)> = (0..6).map(|t| (0.0, 0.06 * t as f64)).collect();
        let c = left_toe(&of(&clip(&fast), 20.0, &ContactParams::default()));
        assert!(c.iter().all(|&c| !c), "{c:?}");
    }

    #[test]
    fn ankles_are_measured_from_their_standing_level() {
        let levels = standing_levels(Format::Smpl24Rot6d);
        assert!((levels[0] - 0.05579088).abs() < 1e-12 && (levels[2] - 0.04814396).abs() < 1e-12);
        assert_eq!(standing_levels(Format::HumanMl263), [0.0; 4]);
        let p = clip(&[(0.0, 0.0); 4]);
        let c = of(&p, 20.0, &ContactParams::default());
        assert!(c.iter().all(|c| *c == [true; 4]), "{c:?}");
    }

    #[test]
    fn stored_contacts_are_thresholded_and_empty_clips_work() {
        let mut p = Poses::empty(Format::HumanMl263, 3);
        p.contacts = vec![[0.9, 0.1, 0.5, 0.51], [0.0; 4], [1.0; 4]];
        let c = of(&p, 20.0, &ContactParams::default());
        assert_eq!(c, vec![[true, false, false, true], [false; 4], [true; 4]]);
        // From the decoded features (the last 4 of 263).
        let mut x = vec![0.0f32; 2 * 263];
        x[259..263].copy_from_slice(&[1.0, 0.0, 0.0, 1.0]);
        x[263 + 261] = 0.8;
        let p = Poses::decode(Format::HumanMl263, &x, 2, &Default::default()).unwrap();
        let c = of(&p, 20.0, &ContactParams::default());
        assert_eq!(
            c,
            vec![[true, false, false, true], [false, false, true, false]]
        );
        for f in Format::ALL {
            assert!(of(&Poses::empty(f, 0), 20.0, &ContactParams::default()).is_empty());
        }
        let one = of(&clip(&[(0.0, 0.0)]), 20.0, &ContactParams::default());
        assert_eq!(one, vec![[true; 4]]);
    }

    #[test]
    fn runs_are_inclusive() {
        assert_eq!(runs(&[true, true, false, true], true), vec![(0, 1), (3, 3)]);
        assert_eq!(runs(&[true, true, false, true], false), vec![(2, 2)]);
        assert!(runs(&[], true).is_empty());
    }
}
