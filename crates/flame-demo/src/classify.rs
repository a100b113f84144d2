//! A rule-based action classifier over SMPL-24 joint positions (native `smpl24_6d` world: +Z
//! up, metres, any heading). It measures a few robust statistics and walks a fixed decision
//! list; the first rule that fires names the family, `stand` is what is left.
//!
//! Measurements (all relative to a floor estimated from the data, and to the body's own facing
//! taken from the hip line, so a floating, shifted or rotated motion reads the same):
//! - feet: height of L_Foot/R_Foot above the floor; *airborne* frames have both feet above
//!   [`AIRBORNE`]; *held* is the largest fraction of frames one given foot is
//!   [`HELD_GAP`] higher than the other.
//! - root: the pelvis path (5-frame moving average against jitter) split into forward and
//!   leftward travel in the body's frame; the 75th percentile of the speed over 0.5 s windows;
//!   the heading change from the first to the last quarter second.
//! - pelvis dips: standing height = 95th percentile of pelvis height; a dip starts below
//!   standing − [`DIP_ENTER`] and ends above standing − [`DIP_EXIT`] (hysteresis).
//! - trunk: angle of the pelvis→neck line from vertical, 90th percentile minus 10th.
//! - arms, per side, in the body frame relative to the shoulder: wrist height, forward reach,
//!   and the jitter-free side-to-side oscillation of a raised wrist (RMS of the lateral position
//!   minus its 0.65 s moving average); the wrist-to-wrist distance's open–shut cycles.
//!
//! Decision list (thresholds sit well inside the gap between what families produce):
//! 1. run: windowed speed p75 ≥ [`RUN_SPEED`] m/s.
//! 2. hop: held ≥ [`HOP_HELD`] and ≥ 2 airborne bouts.
//! 3. jump: an airborne bout reaching [`JUMP_CLEAR`] m under both feet.
//! 4. side_step: sideways travel ≥ [`SIDE_TRAVEL`] m and ≥ 1.5 × the forward travel.
//! 5. walk: forward or backward travel ≥ [`WALK_TRAVEL`] m.
//! 6. turn: heading change ≥ [`TURN_ANGLE`].
//! 7. kick: a foot ≥ [`KICK_HEIGHT`] m up and ≥ [`KICK_REACH`] m in front of the pelvis.
//! 8. squat (≥ 2 pelvis dips) or crouch (1 dip).
//! 9. bow: trunk pitch range ≥ [`BOW_PITCH`] rad.
//! 10. wave: a raised wrist (≥ [`RAISED`] m above its shoulder) oscillating sideways with RMS
//!     ≥ [`WAVE_RMS`] m, or only one wrist raised; raise_arms: both raised, not oscillating.
//! 11. clap: ≥ 2 shut–open cycles of the hands in front of the chest.
//! 12. punch: a wrist reaching ≥ [`PUNCH_REACH`] m in front of its shoulder at about shoulder
//!     height.
//! 13. stand.

use super::family::Family;
use super::rig::joint::*;
use flame::motion::rotation::Vec3;

/// Both feet this high (m) = off the ground.
pub const AIRBORNE: f64 = 0.05;
/// One foot this much higher than the other (m) = held up.
pub const HELD_GAP: f64 = 0.12;
pub const HOP_HELD: f64 = 0.3;
pub const JUMP_CLEAR: f64 = 0.09;
pub const RUN_SPEED: f64 = 1.7;
pub const SIDE_TRAVEL: f64 = 0.18;
pub const WALK_TRAVEL: f64 = 0.5;
pub const TURN_ANGLE: f64 = 1.05;
pub const KICK_HEIGHT: f64 = 0.25;
pub const KICK_REACH: f64 = 0.2;
pub const DIP_ENTER: f64 = 0.15;
pub const DIP_EXIT: f64 = 0.08;
pub const BOW_PITCH: f64 = 0.3;
pub const RAISED: f64 = 0.12;
pub const WAVE_RMS: f64 = 0.02;
pub const CLAP_SHUT: f64 = 0.15;
pub const CLAP_OPEN: f64 = 0.22;
pub const PUNCH_REACH: f64 = 0.33;

/// The statistics the rules look at (printed by `flame-corpus classify`).
#[derive(Clone, Debug, Default)]
pub struct Features {
    pub run_speed: f64,
    pub held: f64,
    pub airborne_bouts: usize,
    pub airborne_clear: f64,
    pub forward_travel: f64,
    pub side_travel: f64,
    pub turn: f64,
    pub kick: f64,
    pub dips: usize,
    pub dip_depth: f64,
    pub trunk_pitch: f64,
    pub raised: [f64; 2],
    pub wave_rms: [f64; 2],
    pub clap_cycles: usize,
    pub punch_reach: f64,
}

fn percentile(v: &[f64], q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mut s = v.to_vec();
    s.sort_by(|a, b| a.total_cmp(b));
    s[((s.len() - 1) as f64 * q).round() as usize]
}

fn moving_average(v: &[f64], radius: usize) -> Vec<f64> {
    let n = v.len();
    (0..n)
        .map(|i| {
            let (a, b) = (i.saturating_sub(radius), (i + radius + 1).min(n));
            v[a..b].iter().sum::<f64>() / (b - a) as f64
        })
        .collect()
}

/// Number of separate runs of `true` that last at least `min_len`.
fn bouts(flags: &[bool], min_len: usize) -> usize {
    let mut count = 0;
    let mut len = 0;
    for &f in flags.iter().chain(std::iter::once(&false)) {
        if f {
            len += 1;
        } else {
            if len >= min_len {
                count += 1;
            }
            len = 0;
        }
    }
    count
}

/// Cycles of a signal going below `enter` then back above `exit` (`enter < exit`).
fn cycles_below(v: &[f64], enter: f64, exit: f64) -> usize {
    let mut inside = false;
    let mut count = 0;
    for &x in v {
        if !inside && x < enter {
            inside = true;
            count += 1;
        } else if inside && x > exit {
            inside = false;
        }
    }
    count
}

/// Measures the [`Features`] of `frames` frames of SMPL-24 positions (`[frames × 24]`, native
/// Z-up world) at `fps`.
pub fn features(positions: &[Vec3], frames: usize, fps: f64) -> Features {
    let n = frames;
    let at = |t: usize, j: usize| positions[t * JOINTS + j];
    let mut f = Features::default();
    if n < 2 || positions.len() < n * JOINTS {
        return f;
    }
    // Floor: feet are on the ground for most frames of every family.
    let lowest: Vec<f64> = (0..n)
        .map(|t| at(t, L_FOOT)[2].min(at(t, R_FOOT)[2]))
        .collect();
    let floor = percentile(&lowest, 0.1);
    let foot_h: Vec<[f64; 2]> = (0..n)
        .map(|t| [at(t, L_FOOT)[2] - floor, at(t, R_FOOT)[2] - floor])
        .collect();

    // Facing from the hip line (left = L_Hip − R_Hip; forward = left × up).
    let heading: Vec<f64> = {
        let mut h: Vec<f64> = (0..n)
            .map(|t| {
                let (l, r) = (at(t, L_HIP), at(t, R_HIP));
                let (lx, ly) = (l[0] - r[0], l[1] - r[1]);
                (-lx).atan2(ly) // angle of the forward vector (ly, −lx)
            })
            .collect();
        for t in 1..n {
            let mut d = h[t] - h[t - 1];
            while d > std::f64::consts::PI {
                d -= std::f64::consts::TAU;
            }
            while d < -std::f64::consts::PI {
                d += std::f64::consts::TAU;
            }
            h[t] = h[t - 1] + d;
        }
        moving_average(&h, 2)
    };
    let fwd = |t: usize| [heading[t].cos(), heading[t].sin()];

    // Root travel.
    let px = moving_average(&(0..n).map(|t| at(t, PELVIS)[0]).collect::<Vec<_>>(), 2);
    let py = moving_average(&(0..n).map(|t| at(t, PELVIS)[1]).collect::<Vec<_>>(), 2);
    for t in 1..n {
        let (dx, dy) = (px[t] - px[t - 1], py[t] - py[t - 1]);
        let [fx, fy] = fwd(t);
        f.forward_travel += dx * fx + dy * fy;
        // Left of forward (fx, fy) in a right-handed Z-up frame is (−fy, fx).
        f.side_travel += -dx * fy + dy * fx;
    }
    let w = ((0.5 * fps).round() as usize).max(1);
    let speeds: Vec<f64> = (0..n.saturating_sub(w))
        .map(|t| (px[t + w] - px[t]).hypot(py[t + w] - py[t]) * fps / w as f64)
        .collect();
    f.run_speed = percentile(&speeds, 0.75);
    let q = ((0.25 * fps).round() as usize).clamp(1, n / 2);
    let mean = |s: &[f64]| s.iter().sum::<f64>() / s.len() as f64;
    f.turn = mean(&heading[n - q..]) - mean(&heading[..q]);

    // Feet.
    let airborne: Vec<bool> = foot_h.iter().map(|h| h[0].min(h[1]) > AIRBORNE).collect();
    f.airborne_bouts = bouts(&airborne, 1);
    f.airborne_clear = foot_h.iter().map(|h| h[0].min(h[1])).fold(0.0, f64::max);
    let held =
        |s: usize| foot_h.iter().filter(|h| h[s] - h[1 - s] > HELD_GAP).count() as f64 / n as f64;
    f.held = held(0).max(held(1));
    for t in 0..n {
        let [fx, fy] = fwd(t);
        for (s, j) in [(0, L_FOOT), (1, R_FOOT)] {
            let p = at(t, j);
            let ahead = (p[0] - px[t]) * fx + (p[1] - py[t]) * fy;
            if foot_h[t][s] >= KICK_HEIGHT {
                f.kick = f.kick.max(ahead);
            }
        }
    }

    // Pelvis dips and trunk pitch.
    let pelvis_h: Vec<f64> = (0..n).map(|t| at(t, PELVIS)[2] - floor).collect();
    let stand = percentile(&pelvis_h, 0.95);
    f.dips = cycles_below(&pelvis_h, stand - DIP_ENTER, stand - DIP_EXIT);
    f.dip_depth = stand - pelvis_h.iter().cloned().fold(f64::MAX, f64::min);
    // Signed: forward lean positive, so the rest pose's slight backward tilt does not fold in.
    let pitch: Vec<f64> = (0..n)
        .map(|t| {
            let (p, k) = (at(t, PELVIS), at(t, NECK));
            let [fx, fy] = fwd(t);
            let ahead = (k[0] - p[0]) * fx + (k[1] - p[1]) * fy;
            ahead.atan2(k[2] - p[2])
        })
        .collect();
    f.trunk_pitch = percentile(&pitch, 0.9) - percentile(&pitch, 0.1);

    // Arms in the body frame.
    for s in 0..2 {
        let (sh, wr) = (L_SHOULDER + s, L_WRIST + s);
        let out_sign = if s == 0 { 1.0 } else { -1.0 };
        let mut up = Vec::with_capacity(n);
        let mut out = Vec::with_capacity(n);
        for t in 0..n {
            let (a, b) = (at(t, sh), at(t, wr));
            let [fx, fy] = fwd(t);
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let reach = dx * fx + dy * fy;
            let lateral = out_sign * (-dx * fy + dy * fx);
            let height = b[2] - a[2];
            up.push(height);
            out.push(lateral);
            if height > -0.25 && height < 0.2 {
                f.punch_reach = f.punch_reach.max(reach);
            }
        }
        let raised: Vec<bool> = up.iter().map(|&h| h > RAISED).collect();
        f.raised[s] = raised.iter().filter(|&&r| r).count() as f64 / n as f64;
        let trend = moving_average(&out, ((0.3 * fps).round() as usize).max(1));
        let resid: Vec<f64> = (0..n)
            .filter(|&t| raised[t])
            .map(|t| (out[t] - trend[t]).powi(2))
            .collect();
        if !resid.is_empty() {
            f.wave_rms[s] = (resid.iter().sum::<f64>() / resid.len() as f64).sqrt();
        }
    }
    let gap: Vec<f64> = (0..n)
        .map(|t| {
            let (a, b) = (at(t, L_WRIST), at(t, R_WRIST));
            let (sa, sb) = (at(t, L_SHOULDER), at(t, R_SHOULDER));
            let [fx, fy] = fwd(t);
            let front =
                ((a[0] + b[0] - sa[0] - sb[0]) * fx + (a[1] + b[1] - sa[1] - sb[1]) * fy) / 2.0;
            let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
            // Hands meeting beside the body are not a clap.
            if front > 0.12 {
                d
            } else {
                f64::MAX
            }
        })
        .collect();
    f.clap_cycles = cycles_below(&gap, CLAP_SHUT, CLAP_OPEN);
    f
}

/// The decision list of the module documentation applied to measured features.
pub fn decide(f: &Features) -> Family {
    let raised = |s: usize| f.raised[s] >= 0.1;
    if f.run_speed >= RUN_SPEED {
        Family::Run
    } else if f.held >= HOP_HELD && f.airborne_bouts >= 2 {
        Family::Hop
    } else if f.airborne_clear >= JUMP_CLEAR {
        Family::Jump
    } else if f.side_travel.abs() >= SIDE_TRAVEL
        && f.side_travel.abs() >= 1.5 * f.forward_travel.abs()
    {
        Family::SideStep
    } else if f.forward_travel.abs() >= WALK_TRAVEL {
        Family::Walk
    } else if f.turn.abs() >= TURN_ANGLE {
        Family::Turn
    } else if f.kick >= KICK_REACH {
        Family::Kick
    } else if f.dips >= 2 {
        Family::Squat
    } else if f.dips == 1 {
        Family::Crouch
    } else if f.trunk_pitch >= BOW_PITCH {
        Family::Bow
    } else if (raised(0) && f.wave_rms[0] >= WAVE_RMS)
        || (raised(1) && f.wave_rms[1] >= WAVE_RMS)
        || (raised(0) != raised(1))
    {
        Family::Wave
    } else if raised(0) && raised(1) {
        Family::RaiseArms
    } else if f.clap_cycles >= 2 {
        Family::Clap
    } else if f.punch_reach >= PUNCH_REACH {
        Family::Punch
    } else {
        Family::Stand
    }
}

/// The family of `frames` frames of SMPL-24 positions (`[frames × 24]`, as
/// `Poses::positions(Convention::Native)` returns for `smpl24_6d`) at `fps`.
pub fn classify(positions: &[Vec3], frames: usize, fps: f64) -> Family {
    decide(&features(positions, frames, fps))
}

/// Decodes `[frames × 147]` `smpl24_6d` features and classifies them.
pub fn classify_features(features: &[f32], frames: usize, fps: f64) -> flame::Result<Family> {
    let positions = positions_of(features, frames)?;
    Ok(classify(&positions, frames, fps))
}

/// SMPL-24 joint positions (native world) of `smpl24_6d` features, via the library's decoder.
pub fn positions_of(features: &[f32], frames: usize) -> flame::Result<Vec<Vec3>> {
    use flame::motion::{Convention, Format, Poses, ReadOptions};
    Ok(Poses::decode(
        Format::Smpl24Rot6d,
        features,
        frames,
        &ReadOptions::default(),
    )?
    .positions(Convention::Native))
}
