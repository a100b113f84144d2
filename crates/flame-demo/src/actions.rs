//! Action generators: each turns a few sampled parameters into a clip of [`Pose`]s that starts
//! and ends in the neutral stance (zero velocity at both ends, so clips chain C1), together with
//! a [`Detail`] record the sentence templates describe.
//!
//! Time profiles are built only from C1 pieces: quintic smoothstep ramps, `sin²` humps and
//! keyframes eased with the quintic smoothstep. Locomotion (walk, run, side steps, turning on
//! the spot) comes from a footstep plan: every foot lands on a footprint placed where the pelvis
//! will be at mid-stance, stays there exactly until it lifts, and swings to its next footprint
//! (vertical lift first, then the horizontal move), so planted feet never slide. The pelvis height
//! is fitted afterwards ([`fit_pelvis_height`]) so both legs can reach their ankle targets.

use std::f64::consts::{FRAC_PI_2, PI, TAU};

use super::family::Family;
use super::rig::{
    forward, left, sub, Foot, Pose, Rig, FPS, HANG, SIDE, STANCE_HALF_WIDTH, TOE_OUT,
};
use flame::motion::rotation::Vec3;
use flame::rng::GaussianRng;

/// How fast an action is performed, as the sentences say it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pace {
    Slow,
    Normal,
    Fast,
}

/// Which limb, or which way.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Side {
    Left,
    Right,
    Both,
    Alternate,
}

/// How big an action is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Size {
    Small,
    Normal,
    Large,
}

/// What was generated, in the terms the sentences use.
#[derive(Clone, Debug, PartialEq)]
pub struct Detail {
    pub family: Family,
    /// Stable variant name (`forward`, `curve_left`, `left`, `both`, `in_place`, …).
    pub variant: String,
    pub pace: Option<Pace>,
    /// The limb used (wave, punch, kick, hop).
    pub limb: Option<Side>,
    /// The way travelled or turned (walk curves, side steps, turns).
    pub direction: Option<Side>,
    pub count: Option<usize>,
    pub size: Option<Size>,
    /// Turning angle in degrees (turns, curved walks).
    pub degrees: Option<u32>,
    /// Punch order for combinations, e.g. `[Left, Right, Left]`.
    pub sequence: Vec<Side>,
}

impl Detail {
    fn new(family: Family, variant: &str) -> Detail {
        Detail {
            family,
            variant: variant.to_string(),
            pace: None,
            limb: None,
            direction: None,
            count: None,
            size: None,
            degrees: None,
            sequence: Vec::new(),
        }
    }
}

/// A generated clip: poses at [`FPS`], where it ends (ground x, z and heading), what it is.
pub struct Clip {
    pub poses: Vec<Pose>,
    pub end: Place,
    pub detail: Detail,
}

/// A ground position and heading.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Place {
    pub x: f64,
    pub z: f64,
    pub yaw: f64,
}

/// Uniform draws on top of the crate's seeded generator.
pub struct Dice(GaussianRng);

impl Dice {
    pub fn new(seed: u64) -> Dice {
        Dice(GaussianRng::new(seed))
    }
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.0.next_uniform()
    }
    /// An integer in `lo..=hi`.
    pub fn int(&mut self, lo: usize, hi: usize) -> usize {
        lo + (self.0.next_u64() % (hi - lo + 1) as u64) as usize
    }
    pub fn chance(&mut self, p: f64) -> bool {
        self.0.next_uniform() < p
    }
    pub fn pick<T: Copy>(&mut self, items: &[T]) -> T {
        items[self.int(0, items.len() - 1)]
    }
}

/// Quintic smoothstep of `x` clamped to [0, 1] (zero slope and curvature at both ends).
pub(crate) fn ease(x: f64) -> f64 {
    let x = x.clamp(0.0, 1.0);
    x * x * x * (x * (6.0 * x - 15.0) + 10.0)
}

/// `sin²(π x)` on [0, 1], zero outside: a C1 hump.
pub(crate) fn hump(x: f64) -> f64 {
    if (0.0..=1.0).contains(&x) {
        (PI * x).sin().powi(2)
    } else {
        0.0
    }
}

/// Horizontal progress of a foot swing at fraction `x`: nothing while the foot leaves and
/// meets the ground (first and last 12 %), so a foot near the ground never scuffs.
pub(crate) fn carry(x: f64) -> f64 {
    ease((x - 0.12) / 0.76)
}

/// A hump over the time window `[a, b]`.
fn hump_in(t: f64, a: f64, b: f64) -> f64 {
    hump((t - a) / (b - a))
}

/// Eased keyframe interpolation: holds the first/last value outside the keys.
pub(crate) fn keys(t: f64, k: &[(f64, f64)]) -> f64 {
    if t <= k[0].0 {
        return k[0].1;
    }
    for w in k.windows(2) {
        let ((t0, v0), (t1, v1)) = (w[0], w[1]);
        if t <= t1 {
            return v0 + (v1 - v0) * ease((t - t0) / (t1 - t0).max(1e-9));
        }
    }
    k[k.len() - 1].1
}

fn lerp3(a: &Vec3, b: &Vec3, e: f64) -> Vec3 {
    [0, 1, 2].map(|i| a[i] + (b[i] - a[i]) * e)
}

/// A wrist path from `a` to `b` by way of `via` (a quadratic Bézier for the direction, the
/// length interpolated linearly), so a raised arm swings out and up instead of folding through
/// the shoulder.
fn arc(a: &Vec3, via: &Vec3, b: &Vec3, e: f64) -> Vec3 {
    let len = |v: &Vec3| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let (w0, w1, w2) = ((1.0 - e) * (1.0 - e), 2.0 * (1.0 - e) * e, e * e);
    let dir = [0, 1, 2].map(|i| w0 * a[i] + w1 * via[i] + w2 * b[i]);
    let l = len(a) + (len(b) - len(a)) * e;
    let n = len(&dir).max(1e-9);
    dir.map(|x| x * l / n)
}

/// Number of frames covering `seconds`.
fn frames_for(seconds: f64) -> usize {
    (seconds * FPS).round() as usize + 1
}

/// Samples `f(t)` at [`FPS`] for `n` frames.
fn sample(n: usize, f: impl Fn(f64) -> Pose) -> Vec<Pose> {
    (0..n).map(|i| f(i as f64 / FPS)).collect()
}

/// A point `fwd` ahead of and `side` to the left of a place, at height `up`.
fn offset(p: &Place, fwd: f64, side: f64, up: f64) -> Vec3 {
    let (f, l) = (forward(p.yaw), left(p.yaw));
    [
        p.x + fwd * f[0] + side * l[0],
        up,
        p.z + fwd * f[2] + side * l[2],
    ]
}

/// A stationary clip: the neutral stance at `at`, changed by `f(t, pose)`.
fn stationary(at: Place, seconds: f64, detail: Detail, f: impl Fn(f64, &mut Pose)) -> Clip {
    let rig = Rig::get();
    let poses = sample(frames_for(seconds), |t| {
        let mut p = rig.stand(at.x, at.z, at.yaw);
        f(t, &mut p);
        p
    });
    Clip {
        poses,
        end: at,
        detail,
    }
}

/// Pelvis displacement in the heading frame (forward, left, up).
fn shift_pelvis(p: &mut Pose, at: &Place, fwd: f64, side: f64, up: f64) {
    let (f, l) = (forward(at.yaw), left(at.yaw));
    p.pelvis[0] += fwd * f[0] + side * l[0];
    p.pelvis[1] += up;
    p.pelvis[2] += fwd * f[2] + side * l[2];
}

// ---------------------------------------------------------------------------------------------
// Locomotion: a path, a progress profile and a footstep plan.

/// Where a locomotion clip goes as its progress `u` runs from 0 to 1.
#[derive(Clone, Copy, Debug)]
enum Path {
    /// Travel `dist` metres in the direction `heading + rel` while the heading turns by `turn`.
    Travel { dist: f64, rel: f64, turn: f64 },
    /// Turn by `turn` radians on the spot.
    Spin { turn: f64 },
}

impl Path {
    /// Amount of progress (metres or radians) at the rate the clip is driven.
    fn amount(&self) -> f64 {
        match *self {
            Path::Travel { dist, .. } => dist,
            Path::Spin { turn } => turn.abs(),
        }
    }

    fn at(&self, start: &Place, u: f64) -> Place {
        match *self {
            Path::Spin { turn } => Place {
                yaw: start.yaw + turn * u,
                ..*start
            },
            Path::Travel { dist, rel, turn } => {
                let (a0, s) = (start.yaw + rel, dist * u);
                let (dx, dz) = if turn.abs() < 1e-6 {
                    (s * a0.sin(), s * a0.cos())
                } else {
                    let r = dist / turn;
                    let a = a0 + s / r;
                    (r * (a0.cos() - a.cos()), r * (a.sin() - a0.sin()))
                };
                Place {
                    x: start.x + dx,
                    z: start.z + dz,
                    yaw: start.yaw + turn * u,
                }
            }
        }
    }
}

/// Progress in [0, 1] of a move of `amount` at peak `rate` with eased ramps of `ramp` seconds
/// (velocity is a cubic smoothstep up, a plateau and a cubic smoothstep down).
fn progress(t: f64, amount: f64, rate: f64, ramp: f64) -> f64 {
    fn integral(x: f64) -> f64 {
        if x <= 0.0 {
            0.0
        } else if x < 1.0 {
            x * x * x - x * x * x * x / 2.0
        } else {
            x - 0.5
        }
    }
    let end = amount / rate + ramp;
    let s = rate * ramp * (integral(t / ramp) - integral((t - end + ramp) / ramp));
    (s / amount).clamp(0.0, 1.0)
}

/// The stepping of a gait.
#[derive(Clone, Copy, Debug)]
struct Gait {
    /// Steps per second.
    cadence: f64,
    /// Fraction of a cycle each foot is planted.
    duty: f64,
    /// Peak ankle lift in swing (m).
    lift: f64,
    /// Ankle distance from the path while travelling.
    half_width: f64,
    /// Foot that lifts first.
    lead: usize,
    /// Lift peaks early in the swing (running).
    early: bool,
}

/// One swing of a foot from one footprint to the next.
#[derive(Clone, Copy, Debug)]
struct Step {
    lift: f64,
    land: f64,
    from: Foot,
    to: Foot,
}

/// Where foot `side` is planted when the body is at `place`.
fn footprint(place: &Place, side: usize, half_width: f64) -> Foot {
    let a = offset(
        place,
        -0.03,
        SIDE[side] * half_width,
        Rig::get().ankle_heights[side],
    );
    Foot {
        ankle: a,
        yaw: place.yaw + SIDE[side] * TOE_OUT,
        pitch: 0.0,
    }
}

/// The foot at time `t` given its swings (planted before, between and after them). `body(t)`
/// is the pelvis's ground position: mid-swing the foot follows the body (passing under the
/// hips, as people's feet do) and only near lift-off and touch-down the straight line between
/// footprints. `early` makes the lift peak early (running's heel kick).
fn foot_at(
    steps: &[Step],
    start: Foot,
    t: f64,
    lift: f64,
    early: bool,
    body: &dyn Fn(f64) -> Vec3,
) -> Foot {
    let mut planted = start;
    for s in steps {
        if t < s.lift {
            return planted;
        }
        if t < s.land {
            let x = (t - s.lift) / (s.land - s.lift);
            // Lift first, move while clear of the ground, set down last.
            let e = carry(x);
            let line = lerp3(&s.from.ankle, &s.to.ankle, e);
            let (b0, b1, bt) = (body(s.lift), body(s.land), body(t));
            let rel = lerp3(&sub(&s.from.ankle, &b0), &sub(&s.to.ankle, &b1), e);
            let carried = [bt[0] + rel[0], 0.0, bt[2] + rel[2]];
            let w = hump(x).powi(2);
            let mut a = lerp3(&line, &carried, w);
            let rise = if early { hump(x.powf(0.75)) } else { hump(x) };
            a[1] = s.from.ankle[1] + lift * rise;
            return Foot {
                ankle: a,
                yaw: s.from.yaw + (s.to.yaw - s.from.yaw) * e,
                pitch: -0.25 * hump(x).powi(2) * (lift / 0.1).min(1.0),
            };
        }
        planted = s.to;
    }
    planted
}

/// Locomotion clip: progress along `path` at `rate` with `gait` steps. `style` adjusts the pose
/// each frame given the activity (0 standing … 1 full speed) and the time.
fn locomote(
    start: Place,
    path: Path,
    rate: f64,
    gait: Gait,
    detail: Detail,
    style: impl Fn(&mut Pose, f64, f64),
) -> Clip {
    let ramp = (1.0 / gait.cadence * 2.0).clamp(0.6, 1.2);
    let amount = path.amount().max(1e-6);
    let moving = amount / rate + ramp;
    let cycle = 2.0 / gait.cadence;
    let swing = (1.0 - gait.duty) * cycle;
    let stance = gait.duty * cycle;
    let u_at = |t: f64| progress(t, amount, rate, ramp);
    let end = path.at(&start, 1.0);

    let mut steps: [Vec<Step>; 2] = [Vec::new(), Vec::new()];
    let starts = [0, 1].map(|s| footprint(&start, s, STANCE_HALF_WIDTH));
    let mut last_land: f64 = 0.0;
    for side in 0..2 {
        let first = if side == gait.lead { 0.0 } else { cycle / 2.0 };
        let mut from = starts[side];
        for k in 0.. {
            let lift = first + k as f64 * cycle;
            let land = lift + swing;
            let u = u_at(land + stance / 2.0);
            let to = if u >= 1.0 - 1e-9 {
                footprint(&end, side, STANCE_HALF_WIDTH)
            } else {
                footprint(&path.at(&start, u), side, gait.half_width)
            };
            steps[side].push(Step {
                lift,
                land,
                from,
                to,
            });
            from = to;
            last_land = last_land.max(land);
            if u >= 1.0 - 1e-9 || k > 400 {
                break;
            }
        }
    }
    let seconds = last_land.max(moving) + 0.35;
    let rig = Rig::get();
    let body = |t: f64| {
        let p = path.at(&start, u_at(t));
        [p.x, 0.0, p.z]
    };
    let poses = sample(frames_for(seconds), |t| {
        let u = u_at(t);
        let here = path.at(&start, u);
        let mut p = rig.stand(here.x, here.z, here.yaw);
        for s in 0..2 {
            p.feet[s] = foot_at(&steps[s], starts[s], t, gait.lift, gait.early, &body);
        }
        // Activity: how far into the moving phase (eased up at the start, down at the end).
        let act = ease(t / ramp) * (1.0 - ease((t - moving + ramp) / ramp).min(1.0));
        // Arms swing against the legs: the left arm forward when the right foot is ahead.
        let f = forward(p.yaw);
        let ahead = |s: usize| {
            let d = [
                p.feet[s].ankle[0] - p.pelvis[0],
                0.0,
                p.feet[s].ankle[2] - p.pelvis[2],
            ];
            d[0] * f[0] + d[2] * f[2]
        };
        let diff = ahead(1) - ahead(0);
        p.hands[0][2] += 0.45 * diff;
        p.hands[1][2] -= 0.45 * diff;
        style(&mut p, act, t);
        p
    });
    Clip { poses, end, detail }
}

/// Walk forward, backward, or along a curve.
pub fn walk(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let variant = d.pick(&[
        "forward",
        "forward",
        "backward",
        "curve_left",
        "curve_right",
    ]);
    let backward = variant == "backward";
    let pace = d.pick(&[Pace::Slow, Pace::Normal, Pace::Normal, Pace::Fast]);
    let (speed, cadence) = match (backward, pace) {
        (true, Pace::Slow) => (d.range(0.35, 0.45), d.range(1.5, 1.7)),
        (true, _) => (d.range(0.5, 0.7), d.range(1.7, 2.0)),
        (false, Pace::Slow) => (d.range(0.5, 0.7), d.range(1.5, 1.7)),
        (false, Pace::Normal) => (d.range(0.8, 1.0), d.range(1.75, 1.95)),
        (false, Pace::Fast) => (d.range(1.1, 1.25), d.range(2.0, 2.2)),
    };
    let mut seconds = d.range(2.5, 8.5).min(budget - 3.0).max(1.2);
    let mut turn = 0.0;
    let mut dir = None;
    if variant.starts_with("curve") {
        let sign = if variant == "curve_left" { 1.0 } else { -1.0 };
        turn = sign * d.range(60.0, 180.0).to_radians();
        seconds = seconds.max((turn.abs() / 0.7).min(budget - 3.0));
        dir = Some(if sign > 0.0 { Side::Left } else { Side::Right });
    }
    let dist = speed * seconds;
    let mut detail = Detail::new(Family::Walk, variant);
    detail.pace = Some(pace);
    detail.direction = dir;
    detail.degrees = (turn != 0.0).then(|| (turn.abs().to_degrees() / 15.0).round() as u32 * 15);
    let gait = Gait {
        cadence,
        duty: 0.58,
        lift: d.range(0.07, 0.1),
        half_width: d.range(0.08, 0.1),
        lead: d.int(0, 1),
        early: false,
    };
    let rel = if backward { PI } else { 0.0 };
    let lean = if backward { -0.04 } else { 0.03 + 0.03 * speed };
    let path = Path::Travel { dist, rel, turn };
    locomote(at, path, speed, gait, detail, move |p, act, _| {
        p.pitch += lean * act;
        p.pelvis[1] -= 0.015 * act;
    })
}

/// Run (or jog) forward, sometimes along a gentle curve.
pub fn run(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let pace = d.pick(&[Pace::Slow, Pace::Normal, Pace::Fast]);
    let (speed, cadence) = match pace {
        Pace::Slow => (d.range(2.0, 2.3), d.range(2.7, 2.9)),
        Pace::Normal => (d.range(2.4, 2.7), d.range(2.9, 3.1)),
        Pace::Fast => (d.range(2.8, 3.0), d.range(3.1, 3.3)),
    };
    let seconds = d.range(2.0, 5.5).min(budget - 2.0).max(1.0);
    let curve = d.chance(0.25);
    let turn = if curve {
        d.pick(&[-1.0, 1.0]) * d.range(45.0, 90.0).to_radians()
    } else {
        0.0
    };
    let mut detail = Detail::new(Family::Run, if curve { "curve" } else { "forward" });
    detail.pace = Some(pace);
    if curve {
        detail.direction = Some(if turn > 0.0 { Side::Left } else { Side::Right });
    }
    let gait = Gait {
        cadence,
        // Short contacts keep the planted foot within the leg's reach at running speed.
        duty: 0.3,
        lift: d.range(0.3, 0.4),
        half_width: 0.07,
        lead: d.int(0, 1),
        early: true,
    };
    let dist = speed * seconds;
    let path = Path::Travel {
        dist,
        rel: 0.0,
        turn,
    };
    let phase = 1.0 / cadence;
    locomote(at, path, speed, gait, detail, move |p, act, t| {
        p.pitch += 0.12 * act;
        p.spine[0] += 0.06 * act;
        p.pelvis[1] -= act * (0.05 + 0.02 * (TAU * t / phase).cos());
        // Bent elbows, hands carried near the waist.
        for s in 0..2 {
            let h = p.hands[s];
            let swing = h[2] - HANG[2];
            p.hands[s] = lerp3(&h, &[0.06, -0.27, 0.2 + 0.5 * swing], act);
        }
    })
}

/// Step sideways (step, close, step…) to the left or right.
pub fn side_step(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let go_left = d.chance(0.5);
    let steps = d.int(2, 7);
    let step_len = d.range(0.2, 0.32);
    let cadence = d.range(1.6, 2.0);
    let max_steps = ((budget - 2.9) * cadence / 2.0).floor().max(1.0) as usize;
    let steps = steps.min(max_steps).max(1);
    let dist = steps as f64 * step_len;
    let pace = if cadence < 1.75 {
        Pace::Slow
    } else {
        Pace::Normal
    };
    let mut detail = Detail::new(Family::SideStep, if go_left { "left" } else { "right" });
    detail.direction = Some(if go_left { Side::Left } else { Side::Right });
    detail.count = Some(steps);
    detail.pace = Some(pace);
    let gait = Gait {
        cadence,
        duty: 0.6,
        lift: d.range(0.05, 0.08),
        half_width: d.range(0.14, 0.17),
        lead: if go_left { 0 } else { 1 },
        early: false,
    };
    let rate = step_len * cadence / 2.0;
    let rel = if go_left { FRAC_PI_2 } else { -FRAC_PI_2 };
    let path = Path::Travel {
        dist,
        rel,
        turn: 0.0,
    };
    locomote(at, path, rate, gait, detail, |p, act, _| {
        p.pelvis[1] -= 0.03 * act;
    })
}

/// Turn around on the spot, stepping.
pub fn turn(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let go_left = d.chance(0.5);
    let mut degrees = d.pick(&[90u32, 90, 180, 180, 180, 270, 360]);
    let rate = d.range(70.0, 130.0).to_radians();
    while degrees > 90 && (degrees as f64).to_radians() / rate + 2.9 > budget {
        degrees -= 90;
    }
    let sign = if go_left { 1.0 } else { -1.0 };
    let mut detail = Detail::new(Family::Turn, if go_left { "left" } else { "right" });
    detail.direction = Some(if go_left { Side::Left } else { Side::Right });
    detail.degrees = Some(degrees);
    detail.pace = Some(if rate < 85f64.to_radians() {
        Pace::Slow
    } else if rate > 115f64.to_radians() {
        Pace::Fast
    } else {
        Pace::Normal
    });
    let gait = Gait {
        cadence: d.range(1.7, 2.2),
        duty: 0.6,
        lift: d.range(0.05, 0.08),
        half_width: STANCE_HALF_WIDTH,
        lead: if go_left { 0 } else { 1 },
        early: false,
    };
    let path = Path::Spin {
        turn: sign * (degrees as f64).to_radians(),
    };
    locomote(at, path, rate, gait, detail, |p, act, _| {
        p.pelvis[1] -= 0.02 * act;
    })
}

// ---------------------------------------------------------------------------------------------
// Jumps and hops.

/// Jump in place, forward, or several times.
pub fn jump(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let forward_jump = d.chance(0.45);
    let mut count = d.pick(&[1usize, 1, 2, 3, 4]);
    let size = d.pick(&[Size::Small, Size::Normal, Size::Large]);
    let rise = match size {
        Size::Small => d.range(0.16, 0.22),
        Size::Normal => d.range(0.24, 0.32),
        Size::Large => d.range(0.34, 0.42),
    };
    let flight = 2.0 * (2.0 * rise / 9.81).sqrt() * 0.9;
    let gap = d.range(0.5, 0.8);
    let per = flight + gap;
    while count > 1 && 1.4 + count as f64 * per > budget {
        count -= 1;
    }
    let dist = if forward_jump {
        d.range(0.35, 0.8)
    } else {
        0.0
    };
    let crouch = d.range(0.12, 0.2);
    let variant = match (forward_jump, count) {
        (true, _) => "forward",
        (false, 1) => "in_place",
        (false, _) => "repeated",
    };
    let mut detail = Detail::new(Family::Jump, variant);
    detail.count = Some(count);
    detail.size = Some(size);
    let takeoffs: Vec<f64> = (0..count).map(|k| 0.6 + k as f64 * per).collect();
    let last_land = takeoffs[count - 1] + flight;
    let seconds = last_land + 0.8;
    let rig = Rig::get();
    let lift = 0.8 * rise;
    let poses = sample(frames_for(seconds), |t| {
        let mut crouching = hump_in(t, takeoffs[0] - 0.6, takeoffs[0] + 0.02)
            + hump_in(t, last_land - 0.02, last_land + 0.6);
        let mut up = 0.0;
        let mut travelled = 0.0;
        let mut feet_up = 0.0;
        let mut feet_moved = 0.0;
        for (k, &a) in takeoffs.iter().enumerate() {
            let b = a + flight;
            up += rise * hump_in(t, a - 0.08, b + 0.08);
            feet_up += lift * hump_in(t, a, b);
            travelled += dist * ease((t - a + 0.15) / (flight + 0.3));
            feet_moved += dist * carry((t - a) / flight);
            if k + 1 < count {
                crouching += hump_in(t, b - 0.02, takeoffs[k + 1] + 0.02);
            }
        }
        let mut p = rig.stand(at.x, at.z, at.yaw);
        shift_pelvis(
            &mut p,
            &at,
            travelled - 0.04 * crouching,
            0.0,
            up - crouch * crouching,
        );
        p.pitch = 0.2 * crouching;
        p.spine[0] = 0.25 * crouching;
        for s in 0..2 {
            let foot = footprint(&at, s, STANCE_HALF_WIDTH);
            let mut a = foot.ankle;
            let f = forward(at.yaw);
            a[0] += feet_moved * f[0];
            a[2] += feet_moved * f[2];
            a[1] += feet_up;
            p.feet[s] = Foot { ankle: a, ..foot };
            let air = up / rise;
            p.hands[s] = [
                HANG[0] + 0.05 * air,
                HANG[1] + 0.12 * crouching + 0.3 * air,
                HANG[2] - 0.2 * crouching + 0.25 * air,
            ];
        }
        p
    });
    Clip {
        poses,
        end: Place {
            x: at.x + dist * count as f64 * forward(at.yaw)[0],
            z: at.z + dist * count as f64 * forward(at.yaw)[2],
            yaw: at.yaw,
        },
        detail,
    }
}

/// Hop on one foot, in place or forward.
pub fn hop(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let support = d.int(0, 1);
    let raised = 1 - support;
    let forward_hop = d.chance(0.35);
    let period = d.range(0.5, 0.65);
    let mut count = d.int(2, 6);
    while count > 2 && 2.4 + count as f64 * period > budget {
        count -= 1;
    }
    let dist = if forward_hop {
        d.range(0.12, 0.25)
    } else {
        0.0
    };
    let flight = 0.45 * period;
    let lift = d.range(0.09, 0.14);
    let held_up = d.range(0.2, 0.28);
    let held_back = d.range(0.1, 0.2);
    let mut detail = Detail::new(
        Family::Hop,
        if forward_hop { "forward" } else { "in_place" },
    );
    detail.limb = Some(if support == 0 {
        Side::Left
    } else {
        Side::Right
    });
    detail.count = Some(count);
    let t_raise = 0.6;
    let first = t_raise + 0.5;
    let takeoffs: Vec<f64> = (0..count).map(|k| first + k as f64 * period).collect();
    let last_land = takeoffs[count - 1] + flight;
    let t_lower = last_land + 0.35;
    let seconds = t_lower + 0.6 + 0.3;
    let rig = Rig::get();
    let f = forward(at.yaw);
    let poses = sample(frames_for(seconds), |t| {
        let on_one = keys(
            t,
            &[
                (0.0, 0.0),
                (t_raise, 1.0),
                (t_lower, 1.0),
                (t_lower + 0.6, 0.0),
            ],
        );
        let mut up = 0.0;
        let mut foot_up = 0.0;
        let mut moved = 0.0;
        let mut foot_moved = 0.0;
        let mut crouching = hump_in(t, takeoffs[0] - 0.4, takeoffs[0] + 0.02)
            + hump_in(t, last_land - 0.02, last_land + 0.4);
        for (k, &a) in takeoffs.iter().enumerate() {
            let b = a + flight;
            up += lift * 1.1 * hump_in(t, a - 0.05, b + 0.05);
            foot_up += lift * hump_in(t, a, b);
            moved += dist * ease((t - a + 0.1) / (flight + 0.2));
            foot_moved += dist * carry((t - a) / flight);
            if k + 1 < count {
                crouching += hump_in(t, b - 0.02, takeoffs[k + 1] + 0.02);
            }
        }
        let mut p = rig.stand(at.x, at.z, at.yaw);
        // Weight over the support foot before the other one leaves the ground.
        let over = SIDE[support] * 0.07 * on_one;
        shift_pelvis(
            &mut p,
            &at,
            moved,
            over,
            up - 0.07 * crouching - 0.02 * on_one,
        );
        p.roll = -SIDE[support] * 0.04 * on_one;
        p.spine[0] = 0.1 * crouching;
        let home = footprint(&at, support, STANCE_HALF_WIDTH);
        let mut a = home.ankle;
        a[0] += foot_moved * f[0];
        a[2] += foot_moved * f[2];
        a[1] += foot_up;
        p.feet[support] = Foot { ankle: a, ..home };
        let rest = footprint(&at, raised, STANCE_HALF_WIDTH);
        let mut r = rest.ankle;
        // The raised foot rides with the body, behind the hip, knee bent; it leaves and meets
        // the ground vertically so it never scuffs.
        let back = held_back * ease((on_one - 0.25) / 0.75);
        r[0] += (moved - back) * f[0];
        r[2] += (moved - back) * f[2];
        r[1] += held_up * on_one + (up - 0.07 * crouching) * on_one;
        p.feet[raised] = Foot {
            ankle: r,
            pitch: 0.3 * on_one,
            ..rest
        };
        for s in 0..2 {
            p.hands[s] = [
                HANG[0] + 0.12 * on_one,
                HANG[1] + 0.1 * on_one,
                HANG[2] + 0.05,
            ];
        }
        p
    });
    let total = dist * count as f64;
    Clip {
        poses,
        end: Place {
            x: at.x + total * f[0],
            z: at.z + total * f[2],
            yaw: at.yaw,
        },
        detail,
    }
}

// ---------------------------------------------------------------------------------------------
// Arms.

/// Which arms a one-or-both-arms action uses: `[left, right]`.
fn arms_of(side: Side) -> [bool; 2] {
    match side {
        Side::Left => [true, false],
        Side::Right => [false, true],
        _ => [true, true],
    }
}

/// Wave one hand or both.
pub fn wave(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let limb = d.pick(&[Side::Left, Side::Right, Side::Both]);
    let freq = d.range(1.4, 2.4);
    let mut count = d.int(2, 6);
    while count > 2 && 2.6 + count as f64 / freq > budget {
        count -= 1;
    }
    let size = d.pick(&[Size::Small, Size::Normal, Size::Large]);
    let amp = match size {
        Size::Small => d.range(0.07, 0.085),
        Size::Normal => d.range(0.095, 0.11),
        Size::Large => d.range(0.12, 0.13),
    };
    let raised = [d.range(0.15, 0.2), d.range(0.28, 0.32), d.range(0.05, 0.12)];
    let t_up = d.range(0.5, 0.8);
    let waving = count as f64 / freq;
    let t_down = t_up + 0.15 + waving + 0.15;
    let seconds = t_down + t_up + d.range(0.2, 0.6);
    let mut detail = Detail::new(Family::Wave, variant_of(limb));
    detail.limb = Some(limb);
    detail.count = Some(count);
    detail.size = Some(size);
    detail.pace = Some(if freq > 2.0 { Pace::Fast } else { Pace::Normal });
    let used = arms_of(limb);
    let head_turn = d.range(-0.2, 0.2);
    stationary(at, seconds, detail, move |t, p| {
        let up = keys(
            t,
            &[(0.0, 0.0), (t_up, 1.0), (t_down, 1.0), (t_down + t_up, 0.0)],
        );
        let tau = t - t_up - 0.15;
        let osc = if (0.0..=waving).contains(&tau) {
            (TAU * freq * tau).sin() * (1.0 - (TAU * tau / waving).cos()).clamp(0.0, 1.0)
        } else {
            0.0
        };
        for (hand, _) in p.hands.iter_mut().zip(used).filter(|(_, u)| *u) {
            *hand = arc(&HANG, &[0.3, -0.1, 0.2], &raised, up);
            hand[0] += amp * osc;
        }
        p.head[2] = head_turn * up;
    })
}

fn variant_of(side: Side) -> &'static str {
    match side {
        Side::Left => "left",
        Side::Right => "right",
        Side::Both => "both",
        Side::Alternate => "alternate",
    }
}

/// Clap the hands in front of the chest.
pub fn clap(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let freq = d.range(1.6, 2.8);
    let mut count = d.int(2, 8);
    while count > 2 && 1.8 + count as f64 / freq > budget {
        count -= 1;
    }
    let open = d.range(0.13, 0.2);
    let height = d.range(-0.12, 0.02);
    let reach = d.range(0.28, 0.34);
    // Shoulders sit 0.17 m from the midline; wrists 3 cm either side of it when palms meet.
    let closed = -0.14;
    let t_in = d.range(0.5, 0.7);
    let clapping = count as f64 / freq;
    let seconds = t_in + clapping + t_in + d.range(0.2, 0.5);
    let mut detail = Detail::new(Family::Clap, if freq > 2.3 { "fast" } else { "steady" });
    detail.count = Some(count);
    detail.pace = Some(if freq > 2.3 {
        Pace::Fast
    } else if freq < 1.9 {
        Pace::Slow
    } else {
        Pace::Normal
    });
    stationary(at, seconds, detail, move |t, p| {
        let ready = keys(
            t,
            &[
                (0.0, 0.0),
                (t_in, 1.0),
                (t_in + clapping, 1.0),
                (2.0 * t_in + clapping, 0.0),
            ],
        );
        let tau = t - t_in;
        let shut = if (0.0..=clapping).contains(&tau) {
            (1.0 - (TAU * freq * tau).cos()) / 2.0
        } else {
            0.0
        };
        let hands = [closed + open * (1.0 - shut), height, reach];
        for s in 0..2 {
            p.hands[s] = lerp3(&HANG, &hands, ready);
        }
        p.head[0] = 0.15 * ready;
    })
}

/// Punch with the left hand, the right hand, or a combination.
pub fn punch(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let limb = d.pick(&[Side::Left, Side::Right, Side::Alternate, Side::Alternate]);
    let mut count = d.int(1, 6);
    let gap = d.range(0.4, 0.65);
    while count > 1 && 2.3 + count as f64 * gap > budget {
        count -= 1;
    }
    let first = d.int(0, 1);
    let sequence: Vec<usize> = (0..count)
        .map(|k| match limb {
            Side::Left => 0,
            Side::Right => 1,
            _ => (first + k) % 2,
        })
        .collect();
    let guard = [
        d.range(-0.05, 0.0),
        d.range(-0.08, -0.02),
        d.range(0.16, 0.22),
    ];
    let strike = [d.range(-0.08, -0.04), d.range(-0.03, 0.03), 0.46];
    let out_time = d.range(0.13, 0.18);
    let back_time = d.range(0.2, 0.28);
    let t_guard = 0.5;
    let starts: Vec<f64> = (0..count).map(|k| t_guard + 0.1 + k as f64 * gap).collect();
    let t_end = starts[count - 1] + out_time + back_time + 0.15;
    let seconds = t_end + 0.5 + d.range(0.2, 0.5);
    let variant = match (limb, count) {
        (Side::Alternate, _) => "combination",
        (Side::Left, _) => "left",
        _ => "right",
    };
    let mut detail = Detail::new(Family::Punch, variant);
    detail.limb = Some(limb);
    detail.count = Some(count);
    detail.pace = Some(if gap < 0.5 { Pace::Fast } else { Pace::Normal });
    detail.sequence = sequence
        .iter()
        .map(|&s| if s == 0 { Side::Left } else { Side::Right })
        .collect();
    stationary(at, seconds, detail, move |t, p| {
        let up = keys(
            t,
            &[(0.0, 0.0), (t_guard, 1.0), (t_end, 1.0), (t_end + 0.5, 0.0)],
        );
        let mut ext = [0.0; 2];
        for (k, &a) in starts.iter().enumerate() {
            let e = keys(
                t,
                &[
                    (a, 0.0),
                    (a + out_time, 1.0),
                    (a + out_time + back_time, 0.0),
                ],
            );
            ext[sequence[k]] += e;
        }
        let base = lerp3(&HANG, &guard, up);
        for (hand, e) in p.hands.iter_mut().zip(ext) {
            *hand = lerp3(&base, &strike, e);
        }
        // The torso turns into each punch.
        p.spine[2] = 0.35 * (ext[1] - ext[0]);
    })
}

/// Raise both arms overhead (once or a few times).
pub fn raise_arms(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let mut count = d.pick(&[1usize, 1, 2, 3]);
    let rise = d.range(0.6, 1.0);
    let hold = d.range(0.5, 1.8);
    while count > 1 && count as f64 * (2.0 * rise + hold + 0.3) + 0.7 > budget {
        count -= 1;
    }
    let high = [d.range(0.06, 0.15), d.range(0.42, 0.45), d.range(0.0, 0.08)];
    let mut detail = Detail::new(
        Family::RaiseArms,
        if count > 1 { "repeated" } else { "once" },
    );
    detail.count = Some(count);
    detail.pace = Some(if rise < 0.75 { Pace::Fast } else { Pace::Slow });
    let mut k = vec![(0.0, 0.0)];
    let mut t = d.range(0.1, 0.4);
    for _ in 0..count {
        k.push((t, 0.0));
        k.push((t + rise, 1.0));
        k.push((t + rise + hold, 1.0));
        k.push((t + 2.0 * rise + hold, 0.0));
        t += 2.0 * rise + hold + 0.3;
    }
    let seconds = t + d.range(0.0, 0.3);
    stationary(at, seconds, detail, move |t, p| {
        let up = keys(t, &k);
        for s in 0..2 {
            // Up through the front, so the wrists do not sweep sideways (that reads as a wave); the
            // far control point keeps the wrist's distance from shrinking on the way.
            p.hands[s] = arc(&HANG, &[high[0], -0.05, 0.9], &high, up);
        }
        p.head[0] = -0.2 * up;
    })
}

// ---------------------------------------------------------------------------------------------
// Legs and trunk.

/// A front kick with the left or right leg, once or a few times.
pub fn kick(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let s = d.int(0, 1);
    let support = 1 - s;
    let size = d.pick(&[Size::Normal, Size::Large]);
    let height = match size {
        Size::Large => d.range(0.55, 0.7),
        _ => d.range(0.38, 0.5),
    };
    let reach = d.range(0.42, 0.55);
    let per = d.range(1.0, 1.3);
    let mut count = d.pick(&[1usize, 1, 2, 3]);
    while count > 1 && 1.3 + count as f64 * per > budget {
        count -= 1;
    }
    let mut detail = Detail::new(Family::Kick, if s == 0 { "left" } else { "right" });
    detail.limb = Some(if s == 0 { Side::Left } else { Side::Right });
    detail.count = Some(count);
    detail.size = Some(size);
    let t0 = 0.5;
    let seconds = t0 + count as f64 * per + 0.5;
    let home = footprint(&at, s, STANCE_HALF_WIDTH);
    let f = forward(at.yaw);
    stationary(at, seconds, detail, move |t, p| {
        let weight = keys(
            t,
            &[
                (0.0, 0.0),
                (t0, 1.0),
                (seconds - 0.5, 1.0),
                (seconds - 0.05, 0.0),
            ],
        );
        let mut fwd = 0.0;
        let mut up = 0.0;
        let mut point = 0.0;
        for k in 0..count {
            let a = t0 + k as f64 * per;
            let (c, e, r, l) = (a + 0.3, a + 0.5, a + 0.72, per - 0.05);
            fwd += keys(
                t,
                &[(a, 0.0), (c, 0.12), (e, reach), (r, 0.12), (a + l, 0.0)],
            );
            up += keys(
                t,
                &[(a, 0.0), (c, 0.3), (e, height), (r, 0.3), (a + l, 0.0)],
            );
            point += keys(t, &[(c, 0.0), (e, 0.5), (r, 0.0)]);
        }
        shift_pelvis(
            p,
            &at,
            -0.03 * weight,
            SIDE[support] * 0.06 * weight,
            -0.015 * weight,
        );
        p.pitch = -0.12 * (up / height).min(1.0);
        // Forward travel only once the foot is clear of the ground.
        let fwd = fwd * ease(up / 0.1);
        let mut a = home.ankle;
        a[0] += fwd * f[0];
        a[2] += fwd * f[2];
        a[1] += up;
        p.feet[s] = Foot {
            ankle: a,
            pitch: point,
            ..home
        };
        p.hands[s][2] -= 0.1 * (up / height).min(1.0);
        p.hands[1 - s][2] += 0.12 * (up / height).min(1.0);
        for h in p.hands.iter_mut() {
            h[0] += 0.08 * weight;
        }
    })
}

/// Knee bends, repeated.
pub fn squat(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let period = d.range(1.5, 2.4);
    let mut count = d.int(2, 5);
    while count > 2 && count as f64 * period + 1.1 > budget {
        count -= 1;
    }
    let size = d.pick(&[Size::Normal, Size::Large]);
    let depth = match size {
        Size::Large => d.range(0.34, 0.4),
        _ => d.range(0.24, 0.32),
    };
    let arms = d.pick(&["forward", "forward", "hips", "down"]);
    let mut detail = Detail::new(Family::Squat, arms);
    detail.count = Some(count);
    detail.size = Some(size);
    detail.pace = Some(if period < 1.8 { Pace::Fast } else { Pace::Slow });
    let t0 = d.range(0.3, 0.5);
    let span = count as f64 * period;
    let seconds = t0 + span + d.range(0.3, 0.6);
    stationary(at, seconds, detail, move |t, p| {
        let tau = t - t0;
        let b = if (0.0..=span).contains(&tau) {
            (1.0 - (TAU * tau / period).cos()) / 2.0
        } else {
            0.0
        };
        let arms_on = keys(
            t,
            &[(0.0, 0.0), (t0, 1.0), (t0 + span, 1.0), (seconds, 0.0)],
        );
        shift_pelvis(p, &at, -0.35 * depth * b, 0.0, -depth * b);
        p.pitch = 0.35 * b;
        p.spine[0] = 0.25 * b;
        p.head[0] = -0.15 * b;
        for h in p.hands.iter_mut() {
            *h = match arms {
                "forward" => lerp3(&HANG, &[0.0, 0.0, 0.45], b),
                "hips" => lerp3(&HANG, &[0.03, -0.3, -0.02], arms_on),
                _ => lerp3(&HANG, &[0.06, -0.42, 0.18], b),
            };
        }
    })
}

/// Crouch down low, stay a moment, stand back up.
pub fn crouch(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let down = d.range(0.8, 1.3);
    let depth = d.range(0.4, 0.5);
    let hold = d.range(0.8, 2.5).min(budget - 2.0 * down - 1.1).max(0.5);
    let t0 = d.range(0.2, 0.5);
    let seconds = t0 + 2.0 * down + hold + d.range(0.2, 0.5);
    let mut detail = Detail::new(Family::Crouch, "down_up");
    detail.pace = Some(if down < 1.0 { Pace::Fast } else { Pace::Slow });
    detail.size = Some(Size::Large);
    let hands_low = [
        d.range(0.0, 0.06),
        d.range(-0.42, -0.36),
        d.range(0.2, 0.25),
    ];
    stationary(at, seconds, detail, move |t, p| {
        let b = keys(
            t,
            &[
                (t0, 0.0),
                (t0 + down, 1.0),
                (t0 + down + hold, 1.0),
                (t0 + 2.0 * down + hold, 0.0),
            ],
        );
        shift_pelvis(p, &at, -0.3 * depth * b, 0.0, -depth * b);
        p.pitch = 0.4 * b;
        p.spine[0] = 0.45 * b;
        p.head[0] = -0.3 * b;
        for h in p.hands.iter_mut() {
            *h = lerp3(&HANG, &hands_low, b);
        }
    })
}

/// Bow from the waist, once or twice.
pub fn bow(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let size = d.pick(&[Size::Small, Size::Normal, Size::Large]);
    let angle = match size {
        Size::Small => d.range(0.6, 0.75),
        Size::Normal => d.range(0.8, 1.0),
        Size::Large => d.range(1.05, 1.25),
    };
    let down = d.range(0.6, 1.0);
    let hold = d.range(0.4, 1.4);
    let mut count = d.pick(&[1usize, 1, 1, 2]);
    if count == 2 && 2.0 * (2.0 * down + hold + 0.3) + 0.6 > budget {
        count = 1;
    }
    let mut detail = Detail::new(Family::Bow, if count > 1 { "twice" } else { "once" });
    detail.count = Some(count);
    detail.size = Some(size);
    detail.pace = Some(if down < 0.75 { Pace::Fast } else { Pace::Slow });
    let mut k = vec![(0.0, 0.0)];
    let mut t = d.range(0.2, 0.5);
    for _ in 0..count {
        k.extend([
            (t, 0.0),
            (t + down, 1.0),
            (t + down + hold, 1.0),
            (t + 2.0 * down + hold, 0.0),
        ]);
        t += 2.0 * down + hold + 0.3;
    }
    let seconds = t + d.range(0.0, 0.3);
    stationary(at, seconds, detail, move |t, p| {
        let b = keys(t, &k);
        shift_pelvis(p, &at, -0.08 * angle * b, 0.0, -0.01 * b);
        p.pitch = 0.3 * angle * b;
        p.spine[0] = 0.7 * angle * b;
        p.head[0] = 0.2 * angle * b;
    })
}

/// Stand still, or stand and look around.
pub fn stand(d: &mut Dice, at: Place, budget: f64) -> Clip {
    let look = d.chance(0.6);
    let seconds = d.range(2.5, 6.0).min(budget);
    let mut detail = Detail::new(Family::Stand, if look { "look_around" } else { "still" });
    let mut k = vec![(0.0, 0.0)];
    if look {
        let mut t = d.range(0.2, 0.6);
        let mut sign = d.pick(&[-1.0, 1.0]);
        let mut looks = 0;
        while t + 1.6 < seconds {
            let turn = d.range(0.7, 1.2) * sign;
            let move_t = d.range(0.5, 0.8);
            k.push((t, k[k.len() - 1].1));
            k.push((t + move_t, turn));
            t += move_t + d.range(0.3, 0.8);
            sign = -sign;
            looks += 1;
        }
        k.push((t, k[k.len() - 1].1));
        k.push((t + 0.6, 0.0));
        detail.count = Some(looks);
    }
    let sway = d.range(0.005, 0.012);
    let sway_period = d.range(2.5, 4.0);
    let seconds = seconds.max(k[k.len() - 1].0 + 0.2);
    stationary(at, seconds, detail, move |t, p| {
        let yaw = keys(t, &k);
        p.head[2] = 0.8 * yaw;
        p.spine[2] = 0.2 * yaw;
        let s =
            (TAU * t / sway_period).sin() * ease(t / 0.8) * (1.0 - ease((t - seconds + 0.8) / 0.8));
        shift_pelvis(p, &at, 0.0, sway * s, 0.0);
    })
}

/// Generates one clip of `family` starting at `at`, using at most about `budget` seconds.
pub fn generate(family: Family, d: &mut Dice, at: Place, budget: f64) -> Clip {
    match family {
        Family::Walk => walk(d, at, budget),
        Family::Run => run(d, at, budget),
        Family::Jump => jump(d, at, budget),
        Family::Hop => hop(d, at, budget),
        Family::Wave => wave(d, at, budget),
        Family::Clap => clap(d, at, budget),
        Family::Punch => punch(d, at, budget),
        Family::Kick => kick(d, at, budget),
        Family::Squat => squat(d, at, budget),
        Family::Crouch => crouch(d, at, budget),
        Family::Turn => turn(d, at, budget),
        Family::RaiseArms => raise_arms(d, at, budget),
        Family::Bow => bow(d, at, budget),
        Family::SideStep => side_step(d, at, budget),
        Family::Stand => stand(d, at, budget),
    }
}

/// Lowers the pelvis where a leg could not reach its ankle target, then smooths the height so
/// the result stays C1; ankles are never moved, so planted feet stay planted.
pub fn fit_pelvis_height(poses: &mut [Pose]) {
    let rig = Rig::get();
    let limit = |p: &Pose, ratio: f64| {
        let g = Rig::pelvis_rotation(p);
        let reach = ratio * rig.leg_reach();
        (0..2)
            .map(|s| {
                let hip = rig.hip_offset(&g, s);
                let a = p.feet[s].ankle;
                let dx = a[0] - (p.pelvis[0] + hip[0]);
                let dz = a[2] - (p.pelvis[2] + hip[2]);
                let h2 = (reach * reach - dx * dx - dz * dz).max(0.0);
                a[1] - hip[1] + h2.sqrt()
            })
            .fold(f64::MAX, f64::min)
    };
    let soft: Vec<f64> = poses
        .iter()
        .map(|p| p.pelvis[1].min(limit(p, super::rig::STAND_REACH)))
        .collect();
    let mut h = gaussian(&soft, 2.0);
    // Where the smoothed curve still overreaches, subtract a smooth bump covering the excess
    // (a widened, blurred copy of it) rather than clipping, which would leave kinks.
    let hard: Vec<f64> = poses.iter().map(|p| limit(p, 0.998)).collect();
    for _ in 0..6 {
        let excess: Vec<f64> = h.iter().zip(&hard).map(|(a, b)| (a - b).max(0.0)).collect();
        if excess.iter().all(|&e| e < 1e-5) {
            break;
        }
        let n = excess.len();
        let widened: Vec<f64> = (0..n)
            .map(|i| {
                excess[i.saturating_sub(3)..(i + 4).min(n)]
                    .iter()
                    .cloned()
                    .fold(0.0, f64::max)
            })
            .collect();
        for (x, c) in h.iter_mut().zip(gaussian(&widened, 2.0)) {
            *x -= 1.2 * c;
        }
    }
    for (p, (x, lim)) in poses.iter_mut().zip(h.into_iter().zip(hard)) {
        p.pelvis[1] = x.min(lim);
    }
}

/// Gaussian smoothing with edge samples repeated (radius 4σ).
fn gaussian(x: &[f64], sigma: f64) -> Vec<f64> {
    let r = (4.0 * sigma).ceil() as isize;
    let w: Vec<f64> = (-r..=r)
        .map(|k| (-(k * k) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f64 = w.iter().sum();
    let n = x.len() as isize;
    (0..n)
        .map(|i| {
            (-r..=r)
                .zip(&w)
                .map(|(k, wk)| wk * x[(i + k).clamp(0, n - 1) as usize])
                .sum::<f64>()
                / total
        })
        .collect()
}
