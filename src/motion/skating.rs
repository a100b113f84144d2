//! The foot skating ratio of GMD and OmniControl: the share of frame steps in which a toe that
//! touches the ground slides horizontally faster than 0.5 m/s.
//!
//! The definition follows `calculate_skating_ratio` in `data_loaders/humanml/utils/metrics.py`,
//! which is the same function in both official repositories:
//! korrawe/guided-motion-diffusion (commit 7bc73c013340d1c438d7202df7d8900986d9d85b) and
//! neu-vi/OmniControl (commit 6cf22c3e3aa9b6c25d357adf568b15be8f0954a9). In their terms, for a
//! motion of `T` frames at 20 fps and the toes (joints 10 = L_Foot, 11 = R_Foot of the 22-joint
//! HumanML3D skeleton; SMPL-24 numbers the same two joints alike), Y up, metres:
//!
//! - `speed[t] = |xz[t+1] − xz[t]| · fps` for the `T − 1` steps `t = 0 … T−2` (`np.linalg.norm`
//!   over the X and Z columns of the difference, times `fps`: per-frame displacement scaled to
//!   m/s; the height plays no part in the speed);
//! - `avg[t]` = scipy's `uniform_filter1d(speed, size=5, mode='constant', origin=0)`: the mean of
//!   `speed[t−2 … t+2]` with the steps outside `0 … T−2` counted as 0 (`cval` 0) and the sum
//!   always divided by 5, so the first and last two steps average over fewer real values;
//! - contact: `y[t] < 0.05 && y[t+1] < 0.05` (the raw height, no floor estimated; both strict);
//! - a foot skates in step `t` when in contact, `speed[t] > 0.5` and `avg[t] > 0.5` (strict);
//! - a step skates when either toe does; ratio = skating steps / (T − 1).
//!
//! Two differences of scope, not of definition: the official function takes a batch padded to the
//! longest motion and divides by that padded length − 1, here one motion of its own length is
//! measured (the same number when the batch is one motion); and it computes in the float32 of its
//! tensors where this computes in `f64`, which can only matter for a speed within float32
//! rounding of a threshold. `tools/skating_ratio.py` is an independent NumPy implementation of
//! the same definition, and `tests/skating_numpy.rs` checks the two agree.

use crate::error::{invalid_arg, Result};

/// The left toe (L_Foot), joint 10 of both HumanML3D-22 and SMPL-24.
pub const LEFT_TOE: usize = 10;
/// The right toe (R_Foot), joint 11 of both skeletons.
pub const RIGHT_TOE: usize = 11;
/// A toe touches the ground below this height (metres; `thresh_height` of the official code).
pub const CONTACT_HEIGHT: f64 = 0.05;
/// A touching toe skates above this horizontal speed (m/s; `thresh_vel`).
pub const SKATE_SPEED: f64 = 0.5;
/// The box filter's width in steps (`avg_window`), centred on the step it averages for.
pub const WINDOW: usize = 5;

/// Per frame step `t` (frame `t` to `t + 1`, so `frames − 1` values): whether either toe skates,
/// as the module doc defines it. `positions_y_up` is `[frames, joints, 3]` world positions,
/// frame-major, Y up, metres.
pub fn skating_mask(
    positions_y_up: &[[f64; 3]],
    frames: usize,
    joints: usize,
    fps: f64,
) -> Result<Vec<bool>> {
    check(positions_y_up, frames, joints, fps)?;
    let steps = frames - 1;
    let mut mask = vec![false; steps];
    for toe in [LEFT_TOE, RIGHT_TOE] {
        let at = |t: usize| positions_y_up[t * joints + toe];
        let speed: Vec<f64> = (0..steps)
            .map(|t| {
                let (a, b) = (at(t), at(t + 1));
                let (dx, dz) = (b[0] - a[0], b[2] - a[2]);
                // sqrt(dx² + dz²) as np.linalg.norm computes it (hypot may differ in the last bit).
                (dx * dx + dz * dz).sqrt() * fps
            })
            .collect();
        let half = WINDOW / 2;
        for (t, skates) in mask.iter_mut().enumerate() {
            // Zero padding: only the steps inside 0..steps add to the sum, the divisor stays 5.
            let window = &speed[t.saturating_sub(half)..(t + half + 1).min(steps)];
            let avg = window.iter().sum::<f64>() / WINDOW as f64;
            let contact = at(t)[1] < CONTACT_HEIGHT && at(t + 1)[1] < CONTACT_HEIGHT;
            if contact && speed[t] > SKATE_SPEED && avg > SKATE_SPEED {
                *skates = true;
            }
        }
    }
    Ok(mask)
}

/// The skating ratio: skating steps of [`skating_mask`] over `frames − 1`, in `[0, 1]`.
/// Errors when there are fewer than 2 frames or 12 joints, the slice is not
/// `frames × joints` long, `fps` is not positive and finite, or a position is not finite.
pub fn skating_ratio(
    positions_y_up: &[[f64; 3]],
    frames: usize,
    joints: usize,
    fps: f64,
) -> Result<f64> {
    let mask = skating_mask(positions_y_up, frames, joints, fps)?;
    Ok(mask.iter().filter(|&&s| s).count() as f64 / mask.len() as f64)
}

fn check(positions: &[[f64; 3]], frames: usize, joints: usize, fps: f64) -> Result<()> {
    if frames < 2 {
        return Err(invalid_arg!(
            "skating ratio: {frames} frames; it measures steps between frames and needs at least 2"
        ));
    }
    if joints <= RIGHT_TOE {
        return Err(invalid_arg!(
            "skating ratio: {joints} joints; the toes are joints {LEFT_TOE} and {RIGHT_TOE} \
             (HumanML3D-22 or SMPL-24)"
        ));
    }
    if frames.checked_mul(joints) != Some(positions.len()) {
        return Err(invalid_arg!(
            "skating ratio: {} positions, but {frames} frames of {joints} joints need {}",
            positions.len(),
            frames.saturating_mul(joints)
        ));
    }
    if !(fps.is_finite() && fps > 0.0) {
        return Err(invalid_arg!(
            "skating ratio: fps {fps} must be positive and finite"
        ));
    }
    if let Some(i) = positions
        .iter()
        .position(|p| p.iter().any(|v| !v.is_finite()))
    {
        return Err(invalid_arg!(
            "skating ratio: frame {}, joint {} is not finite",
            i / joints,
            i % joints
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const FPS: f64 = 20.0;

    /// `frames` frames of `joints` joints, all at the origin except the two toes, whose
    /// positions come from `left(t)` and `right(t)`.
    fn motion(
        frames: usize,
        joints: usize,
        left: impl Fn(usize) -> [f64; 3],
        right: impl Fn(usize) -> [f64; 3],
    ) -> Vec<[f64; 3]> {
        let mut p = vec![[0.0, 0.9, 0.0]; frames * joints];
        for t in 0..frames {
            p[t * joints + LEFT_TOE] = left(t);
            p[t * joints + RIGHT_TOE] = right(t);
        }
        p
    }

    /// A toe at height `y` moving along +X at `speed` m/s.
    fn sliding(y: f64, speed: f64) -> impl Fn(usize) -> [f64; 3] {
        move |t| [speed * t as f64 / FPS, y, 0.0]
    }

    fn still(t: usize) -> [f64; 3] {
        let _ = t;
        [0.2, 0.0, 0.0]
    }

    fn ratio(p: &[[f64; 3]], frames: usize, joints: usize) -> f64 {
        skating_ratio(p, frames, joints, FPS).unwrap()
    }

    #[test]
    fn a_grounded_toe_at_1_m_per_s_skates_every_step() {
        // speed 1 in every step; even the edge steps average 3/5 = 0.6 > 0.5.
        let p = motion(11, 22, sliding(0.0, 1.0), still);
        assert_eq!(ratio(&p, 11, 22), 1.0);
        // The right toe alone, too (either foot counts).
        let p = motion(11, 22, still, sliding(0.01, 1.0));
        assert_eq!(ratio(&p, 11, 22), 1.0);
    }

    #[test]
    fn a_grounded_toe_at_0_4_m_per_s_does_not_skate() {
        let p = motion(11, 22, sliding(0.0, 0.4), sliding(0.0, 0.4));
        assert_eq!(ratio(&p, 11, 22), 0.0);
    }

    #[test]
    fn a_toe_6_cm_up_does_not_touch_and_the_height_bound_is_strict() {
        let p = motion(11, 22, sliding(0.06, 1.0), still);
        assert_eq!(ratio(&p, 11, 22), 0.0);
        let p = motion(11, 22, sliding(CONTACT_HEIGHT, 1.0), still);
        assert_eq!(ratio(&p, 11, 22), 0.0, "exactly 5 cm is not a contact");
        let p = motion(11, 22, sliding(0.0499, 1.0), still);
        assert_eq!(ratio(&p, 11, 22), 1.0);
    }

    #[test]
    fn contact_needs_this_frame_and_the_one_before() {
        // Up (10 cm) in frames 0..=4, down from frame 5, sliding at 1 m/s throughout: the steps
        // 5→6 … 9→10 touch (5 of 10); the landing step 4→5 does not, since frame 4 is up.
        let land = |t: usize| [t as f64 / FPS, if t < 5 { 0.1 } else { 0.0 }, 0.0];
        let p = motion(11, 22, land, still);
        let mask = skating_mask(&p, 11, 22, FPS).unwrap();
        let want: Vec<bool> = (0..10).map(|t| t >= 5).collect();
        assert_eq!(mask, want);
        assert_eq!(ratio(&p, 11, 22), 0.5);
        // Taking off: down in frames 0..=5, up from 6: steps 0→1 … 4→5 touch, 5→6 does not.
        let lift = |t: usize| [t as f64 / FPS, if t <= 5 { 0.0 } else { 0.1 }, 0.0];
        let p = motion(11, 22, lift, still);
        let mask = skating_mask(&p, 11, 22, FPS).unwrap();
        let want: Vec<bool> = (0..10).map(|t| t < 5).collect();
        assert_eq!(mask, want);
    }

    #[test]
    fn the_box_filter_pads_with_zeros_and_always_divides_by_5() {
        // 0.7 m/s everywhere: the edge steps average 3 × 0.7 / 5 = 0.42 (no), the next ones
        // 4 × 0.7 / 5 = 0.56 (yes). Edge replication or a shrinking window would give 1.0.
        let p = motion(11, 22, sliding(0.0, 0.7), still);
        let mask = skating_mask(&p, 11, 22, FPS).unwrap();
        let want: Vec<bool> = (0..10).map(|t| (1..=8).contains(&t)).collect();
        assert_eq!(mask, want);
        assert_eq!(ratio(&p, 11, 22), 0.8);
    }

    #[test]
    fn a_single_fast_step_skates_only_when_its_window_mean_does() {
        // One step of d metres in an otherwise still motion: speed d·20 in that step only, its
        // window mean d·20/5, the neighbours' instantaneous speed 0.
        let jump = |d: f64| move |t: usize| [if t > 5 { d } else { 0.0 }, 0.0, 0.0];
        // 2 m/s: mean 0.4 → no skate.
        let p = motion(11, 22, jump(0.1), still);
        assert_eq!(ratio(&p, 11, 22), 0.0);
        // 3 m/s: mean 0.6 → exactly the step 5→6 skates; its neighbours (mean 0.6 too) do not,
        // their own speed being 0.
        let p = motion(11, 22, jump(0.15), still);
        let mask = skating_mask(&p, 11, 22, FPS).unwrap();
        assert_eq!(mask.iter().position(|&s| s), Some(5));
        assert_eq!(ratio(&p, 11, 22), 0.1);
    }

    #[test]
    fn either_toe_counts_once_per_step() {
        // Left slides while on the ground in frames 0..=6, right from frame 4 on: the union of
        // steps 0..=5 and 4..=9 is every step, counted once.
        let left = |t: usize| [t as f64 / FPS, if t <= 6 { 0.0 } else { 0.2 }, 0.0];
        let right = |t: usize| [0.0, if t >= 4 { 0.0 } else { 0.2 }, t as f64 / FPS];
        let p = motion(11, 22, left, right);
        assert_eq!(ratio(&p, 11, 22), 1.0);
    }

    #[test]
    fn speed_is_horizontal_per_frame_times_fps() {
        // 0.018 m in X and 0.024 m in Z per frame: 0.03 m/frame = 0.6 m/s at 20 fps, though
        // each component alone (0.36, 0.48 m/s) is below 0.5. The window means are 0.36, 0.48,
        // then 0.6: steps 2..=7 skate.
        let diag = |t: usize| [0.018 * t as f64, 0.0, 0.024 * t as f64];
        let p = motion(11, 22, diag, still);
        assert_eq!(ratio(&p, 11, 22), 0.6);
        let z_only = |t: usize| [0.0, 0.0, 0.024 * t as f64];
        let p_z = motion(11, 22, z_only, still);
        assert_eq!(ratio(&p_z, 11, 22), 0.0);
        // The same displacement at 10 fps is 0.3 m/s.
        assert_eq!(skating_ratio(&p, 11, 22, 10.0).unwrap(), 0.0);
        // Fast vertical motion under 5 cm is no skate.
        let bounce = |t: usize| [0.0, [0.0, 0.049][t % 2], 0.0];
        let p = motion(11, 22, bounce, still);
        assert_eq!(ratio(&p, 11, 22), 0.0);
    }

    #[test]
    fn only_joints_10_and_11_matter_on_either_skeleton() {
        let mut p = motion(11, 24, still, still);
        // Pelvis (0), ankles (7, 8) and the SMPL-24-only hands (22, 23) slide on the ground.
        for t in 0..11 {
            for j in [0, 7, 8, 22, 23] {
                p[t * 24 + j] = [t as f64 / FPS * 2.0, 0.0, 0.0];
            }
        }
        assert_eq!(ratio(&p, 11, 24), 0.0);
        for t in 0..11 {
            p[t * 24 + RIGHT_TOE] = [t as f64 / FPS * 2.0, 0.0, 0.0];
        }
        assert_eq!(ratio(&p, 11, 24), 1.0);
    }

    #[test]
    fn two_frames_are_one_step() {
        // One step: speed 1, window mean 1/5 → no skate; the minimum size is accepted.
        let p = motion(2, 22, sliding(0.0, 1.0), still);
        assert_eq!(skating_mask(&p, 2, 22, FPS).unwrap(), vec![false]);
        // 3 m/s: mean 0.6 → the one step skates, ratio 1/1.
        let p = motion(2, 22, sliding(0.0, 3.0), still);
        assert_eq!(ratio(&p, 2, 22), 1.0);
    }

    #[test]
    fn bad_input_is_an_error() {
        let p = motion(11, 22, still, still);
        let msg = |r: Result<f64>| r.unwrap_err().to_string();
        assert!(msg(skating_ratio(&p[..22], 1, 22, FPS)).contains("1 frames"));
        assert!(msg(skating_ratio(&p[..121], 11, 11, FPS)).contains("11 joints"));
        assert!(msg(skating_ratio(&p, 10, 22, FPS)).contains("242 positions"));
        assert!(msg(skating_ratio(&p, 11, 22, 0.0)).contains("fps"));
        assert!(msg(skating_ratio(&p, 11, 22, f64::NAN)).contains("fps"));
        let mut q = p.clone();
        q[3 * 22 + 11][2] = f64::INFINITY;
        assert!(msg(skating_ratio(&q, 11, 22, FPS)).contains("frame 3, joint 11"));
        assert!(skating_ratio(&p, usize::MAX, 22, FPS).is_err());
    }
}
