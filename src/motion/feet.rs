//! The floor and foot locking: [`put_on_ground`] moves the clip so its lowest contact point is
//! at height 0; [`lock`] pins each planted foot where it stands and solves the leg by two-bone IK
//! ([`super::ik`]), so a model's sliding feet stay put. Both work in the format's native world
//! frame ([`Format::up_axis`](super::Format::up_axis)), on joint positions (the floor is where
//! the lowest foot *joint* stands, as in HumanML3D's own "put on floor", `process_file` in
//! EricGuo5513/HumanML3D `motion_representation.ipynb`; the skin's sole is a few centimetres
//! lower).
//!
//! # Locking
//!
//! Per leg (left: hip 1, knee 4, ankle 7, toe 10; right: 2, 5, 8, 11), with contact slots in
//! [`super::contacts`]' order:
//!
//! - **Spans**: a foot is planted in a frame when its ankle or its toe is in contact; a span is a
//!   maximal run of planted frames.
//! - **Pins**: in each span the toe has one pin, the mean of its positions over the span's
//!   frames where the toe is in contact, and the ankle one pin, the mean over the ankle's contact
//!   frames — moved, when some frame has both in contact, to the mean foot length from the toe's
//!   pin (the foot is rigid: both pins must be reachable at once). Neither goes below the clip's
//!   floor (the lowest contact point, which [`put_on_ground`] puts at 0; without it, the clip's
//!   own heights).
//! - **Targets** in a span: a joint in contact goes to its pin. A joint not in contact follows
//!   the other one with the raw foot's shape: in heel-off (toe only) the ankle goes to the toe's
//!   pin plus the raw toe→ankle vector, so the heel rises while the ball of the foot stays put
//!   as in real gait (terminal stance begins with heel rise, Perry & Burnfield, *Gait Analysis*,
//!   2nd ed., ch. 2); in heel strike (ankle only) the toe keeps the raw foot's direction.
//! - **Fades**: outside a span the correction at its first / last frame (target − raw) is carried
//!   on for [`FADE_SECONDS`] and faded out by a smoothstep, added to the raw positions (offset
//!   blending: the foot keeps its own swing path, shifted by a fading amount). Inside the span
//!   the pin holds fully, so a planted foot does not move at all; at the span's ends nothing pops.
//! - **Solve**: per frame with a target, the hip is fixed, the ankle goes to its target by
//!   [`super::ik::solve`] (knee pole kept), then the ankle's world rotation turns the foot so the
//!   toe points at its target. The deltas change the LOCAL rotations of hip, knee and ankle
//!   (their globals follow; the toe's local is kept), and the leg's positions are recomputed by
//!   forward kinematics on the rest offsets, so bone lengths never change. Frames without a
//!   correction are not touched. Joints other than knees, ankles and toes never move (the hips'
//!   rotations change, their positions do not).
//! - **Swings**: between two planted spans the foot's path is redrawn from pin to pin, rising
//!   before it travels and travelling before it lands, at least [`SWING_CLEARANCE`] above the
//!   floor at mid-swing (`shape_swings` says why); a leg never planted is left as it is.
//! - **Floor**: every target is kept at or above the floor, and a toe whose target is nearer
//!   than the foot's length is turned no lower than the floor, so the lock never pushes a foot
//!   under it.
//!
//! **humanml263**: its positions come from `recover_from_ric` and are not the forward
//! kinematics of its rotations. The same solve runs on the positions themselves (the frame's own
//! thigh, shin and foot vectors rotated as rigid vectors, so each frame keeps its own bone
//! lengths), and the same world deltas are applied to the rotations (its hung rotation at hip,
//! knee and ankle is the world rotation of the thigh, shin and foot bone, `humanml263`'s module
//! doc), so the two stay as close as they were.

use super::contacts::SLOT_JOINTS;
use super::ik;
use super::poses::Poses;
use super::rotation::{self, Vec3};
use crate::error::{invalid_arg, Result};

/// Seconds over which a pin's correction fades in before and out after its span: 4 frames at
/// 20 fps. Walking swing lasts ≈ 0.4 s (≈ 40 % of a ≈ 1 s gait cycle, Perry & Burnfield ch. 2),
/// so the fade out of one contact and the fade into the next meet at mid-swing at most and the
/// swing keeps its own shape; and a correction of a few centimetres spread over 0.2 s adds well
/// under 0.5 m/s to the foot, far less visible than the one-frame pop it replaces.
pub const FADE_SECONDS: f64 = 0.2;

/// Metres a swinging toe clears the floor by wherever it moves faster than [`SWING_SPEED`].
/// A toe joint lower than the contact height (5 cm, the skating metric's) that moves at walking
/// speed reads as a foot dragged along the floor; in captured motion that never happens
/// (HumanML3D's real motions score 0.000 on GMD's skating ratio), while the demo model's swinging
/// toes pass at a median of about 1 cm. 6 cm is that height with a centimetre's margin.
pub const SWING_CLEARANCE: f64 = 0.06;

/// Metres per second of horizontal toe speed above which a swinging foot must clear the floor:
/// the skating metric's 0.5 m/s (GMD, OmniControl `calculate_skating_ratio`). Slower feet may
/// shuffle near the floor.
pub const SWING_SPEED: f64 = 0.5;

/// Seconds over which a swing lift rises to its height and settles again: a raised cosine this
/// wide on each side of a frame that needs it, and the same span at both ends of the swing so
/// that a foot leaving or reaching a pin is not lifted (0.15 s is 3 frames at 20 fps, about a
/// third of a walking swing).
pub const SWING_EASE_SECONDS: f64 = 0.15;

/// A leg's joints and its contact slots.
#[derive(Clone, Copy)]
struct Leg {
    hip: usize,
    knee: usize,
    ankle: usize,
    toe: usize,
    ankle_slot: usize,
    toe_slot: usize,
}

const LEGS: [Leg; 2] = [
    Leg {
        hip: 1,
        knee: 4,
        ankle: SLOT_JOINTS[0],
        toe: SLOT_JOINTS[1],
        ankle_slot: 0,
        toe_slot: 1,
    },
    Leg {
        hip: 2,
        knee: 5,
        ankle: SLOT_JOINTS[2],
        toe: SLOT_JOINTS[3],
        ankle_slot: 2,
        toe_slot: 3,
    },
];

/// Shifts the whole clip vertically (root, joint positions and the root bone when present) so
/// its lowest contact point sits at height 0. The lowest contact point is the lowest height of a
/// planted foot's joints (ankle or toe, in a frame where that foot's ankle or toe is in contact:
/// a heel-only contact must not sink the toes by the ankle's height); with no contact at all,
/// the lowest foot joint of the clip. Frames past the end of `contacts` count as without
/// contact; an empty clip is left as it is.
pub fn put_on_ground(poses: &mut Poses, contacts: &[[bool; 4]]) {
    let Some(floor) = floor_height(poses, contacts) else {
        return;
    };
    let up = poses.format.up_axis();
    for p in poses
        .root
        .iter_mut()
        .chain(poses.positions.iter_mut())
        .chain(poses.root_bone.iter_mut())
    {
        p[up] -= floor;
    }
}

/// The clip's floor: [`put_on_ground`]'s lowest contact point; `None` for an empty clip.
pub(crate) fn floor_height(poses: &Poses, contacts: &[[bool; 4]]) -> Option<f64> {
    let joints = poses.joint_count();
    let up = poses.format.up_axis();
    let h = |t: usize, j: usize| poses.positions[t * joints + j][up];
    let mut floor = f64::INFINITY;
    for t in 0..poses.frames {
        let c = contacts.get(t).copied().unwrap_or([false; 4]);
        for leg in LEGS {
            if c[leg.ankle_slot] || c[leg.toe_slot] {
                floor = floor.min(h(t, leg.ankle)).min(h(t, leg.toe));
            }
        }
    }
    if floor.is_finite() {
        return Some(floor);
    }
    let lowest = (0..poses.frames)
        .flat_map(|t| SLOT_JOINTS.iter().map(move |&j| (t, j)))
        .map(|(t, j)| h(t, j))
        .fold(f64::INFINITY, f64::min);
    lowest.is_finite().then_some(lowest)
}

/// Locks the feet during their contact spans (module doc), `contacts` one entry per frame and
/// `fps` the clip's frame rate (for the fade length). Also stores `contacts` as the clip's
/// finished contacts (0/1).
pub fn lock(poses: &mut Poses, contacts: &[[bool; 4]], fps: f64) -> Result<()> {
    lock_on(poses, contacts, fps, None)
}

/// [`lock`] on a given floor (a stream fixes it once, `crate::stream`); `None` = the clip's.
pub(crate) fn lock_on(
    poses: &mut Poses,
    contacts: &[[bool; 4]],
    fps: f64,
    floor: Option<f64>,
) -> Result<()> {
    if !(fps.is_finite() && fps > 0.0) {
        return Err(invalid_arg!(
            "foot locking needs a positive frame rate, got {fps}"
        ));
    }
    if contacts.len() != poses.frames {
        return Err(invalid_arg!(
            "foot locking got {} frames of contacts for a clip of {} frames",
            contacts.len(),
            poses.frames
        ));
    }
    poses.contacts = contacts
        .iter()
        .map(|c| c.map(|on| if on { 1.0 } else { 0.0 }))
        .collect();
    let Some(floor) = floor.or_else(|| floor_height(poses, contacts)) else {
        return Ok(());
    };
    let fade = ((FADE_SECONDS * fps).round() as usize).max(1);
    for leg in LEGS {
        lock_leg(poses, contacts, leg, floor, fade, fps);
    }
    Ok(())
}

/// One leg: pins, fades and the per-frame solve.
fn lock_leg(
    poses: &mut Poses,
    contacts: &[[bool; 4]],
    leg: Leg,
    floor: f64,
    fade: usize,
    fps: f64,
) {
    let n = poses.frames;
    let joints = poses.joint_count();
    let up = poses.format.up_axis();
    let planted: Vec<bool> = contacts
        .iter()
        .map(|c| c[leg.ankle_slot] || c[leg.toe_slot])
        .collect();
    // Corrections (target − raw) of the ankle and the toe per frame.
    let mut corr_a = vec![[0.0; 3]; n];
    let mut corr_f = vec![[0.0; 3]; n];
    let pos = |t: usize, j: usize| poses.positions[t * joints + j];
    let spans = super::contacts::runs(&planted, true);
    for &(s, e) in &spans {
        let pin = |slot: usize, j: usize| {
            let (mut sum, mut count) = ([0.0; 3], 0usize);
            for t in (s..=e).filter(|&t| contacts[t][slot]) {
                sum = rotation::add(&sum, &pos(t, j));
                count += 1;
            }
            let mut m = sum.map(|v| v / count.max(1) as f64);
            m[up] = m[up].max(floor);
            m
        };
        let pin_f = pin(leg.toe_slot, leg.toe);
        let mut pin_a = pin(leg.ankle_slot, leg.ankle);
        if (s..=e).any(|t| contacts[t][leg.ankle_slot] && contacts[t][leg.toe_slot]) {
            // Both pinned: the foot is rigid, so the ankle's pin is put at the mean foot length
            // from the toe's (towards the ankle's mean), else frames with both joints in contact
            // could not hold the toe on its pin and it would jump where heel-off begins.
            let (mut len, mut count) = (0.0, 0usize);
            for t in (s..=e).filter(|&t| contacts[t][leg.ankle_slot]) {
                let d = sub(&pos(t, leg.toe), &pos(t, leg.ankle));
                len += rotation::dot(&d, &d).sqrt();
                count += 1;
            }
            let dir = sub(&pin_a, &pin_f);
            let dl = rotation::dot(&dir, &dir).sqrt();
            if dl > 0.0 {
                pin_a = add_scaled(&pin_f, &dir, len / count.max(1) as f64 / dl);
                pin_a[up] = pin_a[up].max(floor);
            }
        }
        for t in s..=e {
            let (raw_a, raw_f) = (pos(t, leg.ankle), pos(t, leg.toe));
            let foot = sub(&raw_f, &raw_a);
            let ta = if contacts[t][leg.ankle_slot] {
                pin_a
            } else {
                sub(&pin_f, &foot)
            };
            let tf = if contacts[t][leg.toe_slot] {
                pin_f
            } else {
                rotation::add(&pin_a, &foot)
            };
            corr_a[t] = sub(&ta, &raw_a);
            corr_f[t] = sub(&tf, &raw_f);
        }
    }
    // Fades: only into frames where this foot is not planted (in-span corrections are final).
    for &(s, e) in &spans {
        let (start_a, start_f, end_a, end_f) = (corr_a[s], corr_f[s], corr_a[e], corr_f[e]);
        for d in 1..=fade {
            let w = smoothstep(1.0 - d as f64 / (fade + 1) as f64);
            if let Some(t) = s.checked_sub(d).filter(|&t| !planted[t]) {
                corr_a[t] = add_scaled(&corr_a[t], &start_a, w);
                corr_f[t] = add_scaled(&corr_f[t], &start_f, w);
            }
            if let Some(t) = Some(e + d).filter(|&t| t < n && !planted[t]) {
                corr_a[t] = add_scaled(&corr_a[t], &end_a, w);
                corr_f[t] = add_scaled(&corr_f[t], &end_f, w);
            }
        }
    }
    shape_swings(poses, &planted, leg, floor, fps, &mut corr_a, &mut corr_f);
    for t in 0..n {
        let (raw_a, raw_f) = (
            poses.positions[t * joints + leg.ankle],
            poses.positions[t * joints + leg.toe],
        );
        let mut ta = rotation::add(&raw_a, &corr_a[t]);
        let mut tf = rotation::add(&raw_f, &corr_f[t]);
        ta[up] = ta[up].max(floor);
        tf[up] = tf[up].max(floor);
        if ta != raw_a || tf != raw_f {
            solve_frame(poses, t, leg, &ta, &tf, floor);
        }
    }
}

/// Shapes a leg's swings (runs of frames where the foot is not planted), as corrections added
/// to `corr_a` / `corr_f`:
///
/// - A swing between two planted frames is redrawn from the toe's last pinned place to its next
///   one: horizontally along the straight line with a smootherstep in time (`6x⁵ − 15x⁴ + 10x³`:
///   the foot leaves and lands with zero speed and acceleration, and moves mostly in the middle),
///   vertically at least [`SWING_CLEARANCE`] above the floor times a rise that reaches full
///   height a fifth of the way in and comes back as late (`S(min(1, 5x, 5(1−x)))`), or higher
///   where the model lifts it higher. The ankle moves with the toe, so the foot keeps its shape.
///   Why redraw rather than offset: the model's swing toes drag at a median of about 1 cm and
///   catch up with a pin's fade at 1–3 m/s near the floor — on the floor, that is a foot
///   sliding. A redrawn swing is the usual procedural gait step (the foot rises before it
///   travels and travels before it lands).
/// - A swing that runs into the clip's start or end keeps its path and is only lifted to the
///   clearance wherever its toe moves faster than [`SWING_SPEED`] (raised cosine over
///   [`SWING_EASE_SECONDS`] around each such frame).
fn shape_swings(
    poses: &Poses,
    planted: &[bool],
    leg: Leg,
    floor: f64,
    fps: f64,
    corr_a: &mut [Vec3],
    corr_f: &mut [Vec3],
) {
    let n = poses.frames;
    let joints = poses.joint_count();
    let up = poses.format.up_axis();
    let ease = (SWING_EASE_SECONDS * fps).round().max(1.0);
    let raw_f = |t: usize| poses.positions[t * joints + leg.toe];
    let toes: Vec<Vec3> = (0..n)
        .map(|t| rotation::add(&raw_f(t), &corr_f[t]))
        .collect();
    let horizontal_speed = |a: &Vec3, b: &Vec3| {
        let mut d = sub(b, a);
        d[up] = 0.0;
        rotation::dot(&d, &d).sqrt() * fps
    };
    // A leg never planted tells nothing of where its feet should be: left as it is.
    if !planted.contains(&true) {
        return;
    }
    for (s, e) in super::contacts::runs(planted, false) {
        if s > 0 && e + 1 < n {
            let (from, to) = (toes[s - 1], toes[e + 1]);
            let span = (e + 2 - s) as f64;
            for t in s..=e {
                let x = (t + 1 - s) as f64 / span;
                let travel = x * x * x * (x * (6.0 * x - 15.0) + 10.0);
                let mut target = add_scaled(&from, &sub(&to, &from), travel);
                let rise = smoothstep((5.0 * x).min(5.0 * (1.0 - x)).min(1.0));
                let chord = from[up] + (to[up] - from[up]) * travel;
                target[up] = toes[t][up].max(chord).max(floor + SWING_CLEARANCE * rise);
                let shift = sub(&target, &toes[t]);
                corr_f[t] = rotation::add(&corr_f[t], &shift);
                corr_a[t] = rotation::add(&corr_a[t], &shift);
            }
            continue;
        }
        let need: Vec<f64> = (s..=e)
            .map(|t| {
                let p = toes[t];
                let before = (t > 0).then(|| horizontal_speed(&toes[t - 1], &p));
                let after = (t + 1 < n).then(|| horizontal_speed(&p, &toes[t + 1]));
                if before.unwrap_or(0.0).max(after.unwrap_or(0.0)) > SWING_SPEED {
                    (floor + SWING_CLEARANCE - p[up]).max(0.0)
                } else {
                    0.0
                }
            })
            .collect();
        for t in s..=e {
            let mut lift = 0.0f64;
            for (k, &h) in need.iter().enumerate() {
                let d = (t as f64 - (s + k) as f64).abs() / ease;
                if h > 0.0 && d < 1.0 {
                    lift = lift.max(h * 0.5 * (1.0 + (std::f64::consts::PI * d).cos()));
                }
            }
            // Eased to zero where the swing meets a planted frame (not at the clip's end).
            let from_start = if s > 0 {
                (t - s + 1) as f64
            } else {
                f64::INFINITY
            };
            let to_end = if e + 1 < n {
                (e + 1 - t) as f64
            } else {
                f64::INFINITY
            };
            lift *= smoothstep(from_start.min(to_end) / (ease + 1.0));
            corr_a[t][up] += lift;
            corr_f[t][up] += lift;
        }
    }
}

/// Moves frame `t`'s leg so the ankle reaches `ankle_target` (as far as the leg reaches) and the
/// toe points at `toe_target`: local rotations of hip, knee and ankle changed, globals and leg
/// positions recomputed (module doc).
fn solve_frame(
    poses: &mut Poses,
    t: usize,
    leg: Leg,
    ankle_target: &Vec3,
    toe_target: &Vec3,
    floor: f64,
) {
    let joints = poses.joint_count();
    let skel = poses.format.skeleton();
    let kinematic = poses.format.positions_are_kinematic();
    let up = poses.format.up_axis();
    let base = t * joints;
    let p = |j: usize| poses.positions[base + j];
    let (hip, knee, ankle, toe) = (p(leg.hip), p(leg.knee), p(leg.ankle), p(leg.toe));
    let sol = ik::solve(&hip, &knee, &ankle, ankle_target);
    // The foot after the leg's turn, then turned so the toe points at its target.
    let foot = rotation::apply(&sol.lower, &sub(&toe, &ankle));
    let aim = ik::rotate_onto(
        &foot,
        &toe_direction(&sol.end, &foot, toe_target, floor, up),
        None,
    );
    let foot_delta = rotation::mul(&aim, &sol.lower);

    let g = |j: usize| poses.global[base + j];
    let parent = skel.parent(leg.hip).unwrap_or(0);
    let g_parent = g(parent);
    let g_hip = rotation::mul(&sol.upper, &g(leg.hip));
    let g_knee = rotation::mul(&sol.lower, &g(leg.knee));
    let g_ankle = rotation::mul(&foot_delta, &g(leg.ankle));
    let l_toe = poses.local[base + leg.toe];
    let l = &mut poses.local;
    l[base + leg.hip] = rotation::mul(&rotation::transpose(&g_parent), &g_hip);
    l[base + leg.knee] = rotation::mul(&rotation::transpose(&g_hip), &g_knee);
    l[base + leg.ankle] = rotation::mul(&rotation::transpose(&g_knee), &g_ankle);
    let gl = &mut poses.global;
    gl[base + leg.hip] = g_hip;
    gl[base + leg.knee] = g_knee;
    gl[base + leg.ankle] = g_ankle;
    gl[base + leg.toe] = rotation::mul(&g_ankle, &l_toe);

    let ps = &mut poses.positions;
    if kinematic {
        // Forward kinematics on the rest offsets: bone lengths are the skeleton's exactly.
        let off = skel.rest_offsets();
        let k = rotation::add(&hip, &rotation::apply(&g_hip, &off[leg.knee]));
        let a = rotation::add(&k, &rotation::apply(&g_knee, &off[leg.ankle]));
        let f = rotation::add(&a, &rotation::apply(&g_ankle, &off[leg.toe]));
        ps[base + leg.knee] = k;
        ps[base + leg.ankle] = a;
        ps[base + leg.toe] = f;
    } else {
        // The frame's own bones, rotated.
        ps[base + leg.knee] = sol.mid;
        ps[base + leg.ankle] = sol.end;
        ps[base + leg.toe] =
            rotation::add(&sol.end, &rotation::apply(&foot_delta, &sub(&toe, &ankle)));
    }
}

/// The direction the foot (ankle at `ankle`, ankle→toe vector `foot`) points so its toe is as
/// near `target` as the rigid foot allows without going under `floor`: towards the target, its
/// slope raised when the toe would end below the floor (a target nearer than the foot's length
/// would otherwise put the toe past it, under the floor).
fn toe_direction(ankle: &Vec3, foot: &Vec3, target: &Vec3, floor: f64, up: usize) -> Vec3 {
    let length = rotation::dot(foot, foot).sqrt();
    let mut d = sub(target, ankle);
    let dl = rotation::dot(&d, &d).sqrt();
    if length == 0.0 || dl == 0.0 {
        return if dl == 0.0 { *foot } else { d };
    }
    d = d.map(|v| v / dl);
    let lowest = (floor - ankle[up]) / length;
    if d[up] >= lowest || lowest > 1.0 {
        return d;
    }
    // Keep the horizontal heading, lift the slope to reach the floor exactly.
    let rise = lowest.max(-1.0);
    let mut h = d;
    h[up] = 0.0;
    let hl = rotation::dot(&h, &h).sqrt();
    if hl == 0.0 {
        let mut v = [0.0; 3];
        v[up] = rise.signum();
        return v;
    }
    let scale = (1.0 - rise * rise).max(0.0).sqrt() / hl;
    let mut out = h.map(|v| v * scale);
    out[up] = rise;
    out
}

/// `3x² − 2x³` on [0, 1]: zero slope at both ends, so a fade starts and ends without a kink.
fn smoothstep(x: f64) -> f64 {
    let x = x.clamp(0.0, 1.0);
    x * x * (3.0 - 2.0 * x)
}

fn sub(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn add_scaled(a: &Vec3, b: &Vec3, k: f64) -> Vec3 {
    [a[0] + k * b[0], a[1] + k * b[1], a[2] + k * b[2]]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::format::Format;
    use crate::motion::poses::ReadOptions;
    use crate::motion::rotation::Mat3;
    use crate::motion::skeleton::{forward_kinematics, Skeleton};

    const LEG_JOINTS: [usize; 6] = [4, 5, 7, 8, 10, 11];

    fn rx(deg: f64) -> [f64; 6] {
        rotation::to_6d_rows(&rotation::axis_angle(&[1.0, 0.0, 0.0], deg.to_radians()))
    }

    /// A smpl24_6d "walk" of 30 frames: knees bent (hip −30°, knee +50°, ankle −20° about the
    /// body X axis, foot flat), the pelvis gliding forward (world −Y) 10 cm over frames 5..=24
    /// while the left leg keeps its pose, so a left foot planted over 5..=24 slides
    /// 10 cm; the right hip swings ±15° (a swinging leg).
    fn walk() -> Poses {
        let frames = 30;
        let mut x = Vec::new();
        for t in 0..frames {
            let glide = -0.1 * (t.clamp(5, 24) - 5) as f64 / 19.0;
            x.extend([0.0, glide, 0.9]);
            let mut rot = [[1.0, 0.0, 0.0, 0.0, 1.0, 0.0]; 24];
            rot[0] = rx(90.0);
            rot[1] = rx(-30.0);
            rot[4] = rx(50.0);
            rot[7] = rx(-20.0);
            rot[2] = rx(-30.0 + 15.0 * (t as f64 * 0.4).sin());
            rot[5] = rx(50.0);
            rot[8] = rx(-20.0);
            x.extend(rot.iter().flatten());
        }
        let x: Vec<f32> = x.iter().map(|&v| v as f32).collect();
        Poses::decode(Format::Smpl24Rot6d, &x, frames, &ReadOptions::default()).unwrap()
    }

    /// Left ankle and toe in contact over 5..=24; right toe over 0..=2 and 27..=29.
    fn walk_contacts(frames: usize) -> Vec<[bool; 4]> {
        (0..frames)
            .map(|t| {
                let left = (5..25).contains(&t);
                let right = !(3..27).contains(&t);
                [left, left, false, right]
            })
            .collect()
    }

    fn horizontal(p: &Vec3, q: &Vec3, up: usize) -> f64 {
        (0..3)
            .filter(|&k| k != up)
            .map(|k| (p[k] - q[k]).powi(2))
            .sum::<f64>()
            .sqrt()
    }

    fn at(p: &Poses, t: usize, j: usize) -> Vec3 {
        p.positions[t * p.joint_count() + j]
    }

    /// The largest horizontal distance of joint `j` from its frame-`s` position over `s..=e`.
    fn drift(p: &Poses, j: usize, s: usize, e: usize) -> f64 {
        let up = p.format.up_axis();
        (s..=e)
            .map(|t| horizontal(&at(p, t, j), &at(p, s, j), up))
            .fold(0.0, f64::max)
    }

    fn max_diff(a: &[Vec3], b: &[Vec3]) -> f64 {
        a.iter()
            .zip(b)
            .flat_map(|(x, y)| (0..3).map(move |k| (x[k] - y[k]).abs()))
            .fold(0.0, f64::max)
    }

    fn mat_diff(a: &Mat3, b: &Mat3) -> f64 {
        (0..3)
            .flat_map(|r| (0..3).map(move |c| (a[r][c] - b[r][c]).abs()))
            .fold(0.0, f64::max)
    }

    #[test]
    fn smpl24_lock_pins_the_sliding_foot_and_keeps_the_skeleton() {
        let raw = walk();
        let contacts = walk_contacts(raw.frames);
        let mut grounded = raw.clone();
        put_on_ground(&mut grounded, &contacts);
        // The test clip does slide: the left toe travels 10 cm during its span.
        assert!((drift(&grounded, 10, 5, 24) - 0.1).abs() < 1e-6);
        let mut locked = grounded.clone();
        lock(&mut locked, &contacts, 20.0).unwrap();
        let (skel, j, up) = (Skeleton::smpl24(), locked.joint_count(), 2);

        // Pinned: the left toe and ankle move < 1 mm horizontally over the span (in fact 0).
        assert!(
            drift(&locked, 10, 5, 24) < 1e-3,
            "{}",
            drift(&locked, 10, 5, 24)
        );
        assert!(drift(&locked, 7, 5, 24) < 1e-3);
        for t in 5..=24 {
            assert!((at(&locked, t, 10)[up] - at(&locked, 5, 10)[up]).abs() < 1e-3);
        }
        // Nothing pops: the left toe's largest step per frame stays under 2.5 cm (the 5 cm
        // correction at the span's end spread over the 4-frame fade; without the fade it would
        // jump 5 cm in one frame).
        let step = (1..locked.frames)
            .map(|t| {
                let d = sub(&at(&locked, t, 10), &at(&locked, t - 1, 10));
                rotation::dot(&d, &d).sqrt()
            })
            .fold(0.0, f64::max);
        assert!(step < 0.025, "step {step}");

        for t in 0..locked.frames {
            let span = t * j..(t + 1) * j;
            // Bone lengths are the rest offsets' exactly, on every frame.
            for b in 1..j {
                let pa = skel.parent(b).unwrap();
                let len = rotation::dot(&skel.rest_offsets()[b], &skel.rest_offsets()[b]).sqrt();
                let d = sub(&locked.positions[t * j + b], &locked.positions[t * j + pa]);
                assert!(
                    (rotation::dot(&d, &d).sqrt() - len).abs() < 1e-9,
                    "frame {t} joint {b}"
                );
            }
            // Positions and globals are the forward kinematics of root and locals.
            let (mut p, mut g) = (vec![[0.0; 3]; j], vec![rotation::IDENTITY; j]);
            forward_kinematics(
                skel.parents(),
                skel.rest_offsets(),
                &locked.root[t],
                &locked.local[span.clone()],
                &mut p,
                &mut g,
            )
            .unwrap();
            assert!(max_diff(&p, &locked.positions[span.clone()]) < 1e-9);
            for (a, b) in g.iter().zip(&locked.global[span.clone()]) {
                assert!(mat_diff(a, b) < 1e-9);
            }
            // Joints other than knees, ankles and toes do not move; rotations other than the
            // legs' are untouched; the toes' locals are kept.
            for b in (0..j).filter(|b| !LEG_JOINTS.contains(b)) {
                assert!(max_diff(&[at(&locked, t, b)], &[at(&grounded, t, b)]) < 1e-9);
                if ![1, 2].contains(&b) {
                    assert_eq!(locked.global[t * j + b], grounded.global[t * j + b]);
                    assert_eq!(locked.local[t * j + b], grounded.local[t * j + b]);
                }
            }
            for b in [10, 11] {
                assert_eq!(locked.local[t * j + b], grounded.local[t * j + b]);
            }
            // No foot joint under the floor (0 after put_on_ground) by more than 5 mm.
            for b in SLOT_JOINTS {
                assert!(at(&locked, t, b)[up] > -0.005, "frame {t} joint {b}");
            }
        }
        assert_eq!(locked.root, grounded.root);
        // Frames far from any span of a leg are untouched (left leg: 0 is 5 frames before 5).
        assert_eq!(at(&locked, 0, 10), at(&grounded, 0, 10));
        // The finished contacts are stored.
        assert_eq!(locked.contacts[5], [1.0, 1.0, 0.0, 0.0]);
        assert_eq!(locked.contacts.len(), locked.frames);
    }

    #[test]
    fn ground_puts_the_lowest_contact_point_at_zero() {
        let raw = walk();
        let contacts = walk_contacts(raw.frames);
        let lowest = |p: &Poses, only_contacts: bool| {
            let mut m = f64::INFINITY;
            for (t, c) in contacts.iter().enumerate().take(p.frames) {
                for (slot, &b) in SLOT_JOINTS.iter().enumerate() {
                    if !only_contacts || c[slot] {
                        m = m.min(at(p, t, b)[2]);
                    }
                }
            }
            m
        };
        let mut g = raw.clone();
        g.root_bone = vec![[0.0, 0.0, 0.0]; g.frames];
        put_on_ground(&mut g, &contacts);
        assert!(lowest(&g, true).abs() < 1e-12, "{}", lowest(&g, true));
        let shift = raw.root[0][2] - g.root[0][2];
        assert!((shift - lowest(&raw, true)).abs() < 1e-12, "{shift}");
        assert!((g.root_bone[3][2] + shift).abs() < 1e-12);
        assert!(
            max_diff(
                &[sub(&at(&g, 7, 15), &at(&raw, 7, 15))],
                &[[0.0, 0.0, -shift]]
            ) < 1e-12
        );
        // No contacts: the lowest foot joint.
        let mut g = raw.clone();
        put_on_ground(&mut g, &vec![[false; 4]; raw.frames]);
        assert!(lowest(&g, false).abs() < 1e-12);
        // Empty clips.
        let mut e = Poses::empty(Format::HumanMl263, 0);
        put_on_ground(&mut e, &[]);
        lock(&mut e, &[], 20.0).unwrap();
    }

    #[test]
    fn no_contact_and_all_contact_clips() {
        let raw = walk();
        let mut g = raw.clone();
        put_on_ground(&mut g, &vec![[false; 4]; raw.frames]);
        let mut locked = g.clone();
        lock(&mut locked, &vec![[false; 4]; g.frames], 20.0).unwrap();
        assert_eq!(locked.positions, g.positions);
        assert_eq!(locked.local, g.local);
        // Every joint in contact in every frame: each foot pinned at its mean for the whole clip.
        let all = vec![[true; 4]; g.frames];
        let mut locked = g.clone();
        lock(&mut locked, &all, 20.0).unwrap();
        assert!(drift(&locked, 10, 0, 29) < 1e-3 && drift(&locked, 11, 0, 29) < 1e-3);
        assert!(locked.positions.iter().flatten().all(|v| v.is_finite()));
        // Bad arguments are errors.
        let e = lock(&mut g.clone(), &all[1..], 20.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("29 frames of contacts for a clip of 30"), "{e}");
        let e = lock(&mut g, &all, 0.0).unwrap_err().to_string();
        assert!(e.contains("positive frame rate, got 0"), "{e}");
    }

    #[test]
    fn heel_off_keeps_the_toe_and_lets_the_heel_rise() {
        // Left foot planted 5..=24: ankle and toe in contact up to 14, then toe only (heel off).
        let mut g = walk();
        let contacts: Vec<[bool; 4]> = (0..g.frames)
            .map(|t| {
                let left = (5..25).contains(&t);
                [left && t < 15, left, false, false]
            })
            .collect();
        put_on_ground(&mut g, &contacts);
        // Raise the raw heel over 15..=24 by turning the left ankle (toe down) progressively.
        let j = g.joint_count();
        let skel = Skeleton::smpl24();
        for t in 15..25 {
            let span = t * j..(t + 1) * j;
            let mut local = g.local[span.clone()].to_vec();
            local[7] = rotation::mul(
                &local[7],
                &rotation::axis_angle(&[1.0, 0.0, 0.0], (3.0 * (t - 14) as f64).to_radians()),
            );
            let root = g.root[t];
            forward_kinematics(
                skel.parents(),
                skel.rest_offsets(),
                &root,
                &local,
                &mut g.positions[span.clone()],
                &mut g.global[span.clone()],
            )
            .unwrap();
            g.local[span].copy_from_slice(&local);
        }
        let mut locked = g.clone();
        lock(&mut locked, &contacts, 20.0).unwrap();
        assert!(
            drift(&locked, 10, 5, 24) < 1e-3,
            "{}",
            drift(&locked, 10, 5, 24)
        );
        assert!(drift(&locked, 7, 5, 14) < 1e-3);
        // The heel rises by the raw foot's turn (30° at frame 24 lifts it several cm).
        let rise = at(&locked, 24, 7)[2] - at(&locked, 14, 7)[2];
        assert!(rise > 0.02, "{rise}");
    }

    /// A humanml263-like clip built in the crate: the walk's pose on the HumanML3D skeleton
    /// (Y up), then each frame's left thigh and shin stretched by up to ±2 % (positions that
    /// are not the forward kinematics of the rotations, as `recover_from_ric`'s are not), the
    /// left foot planted over 5..=24 while the pelvis glides 10 cm along +Z.
    fn humanml_walk() -> Poses {
        let frames = 30;
        let skel = Skeleton::humanml22();
        let j = skel.joint_count();
        let mut p = Poses::empty(Format::HumanMl263, frames);
        for t in 0..frames {
            let mut local = vec![rotation::IDENTITY; j];
            let r = |deg: f64| rotation::axis_angle(&[1.0, 0.0, 0.0], deg.to_radians());
            local[1] = r(-30.0);
            local[4] = r(50.0);
            local[7] = r(-20.0);
            local[2] = r(-30.0 + 15.0 * (t as f64 * 0.4).sin());
            local[5] = r(50.0);
            local[8] = r(-20.0);
            let root = [0.0, 0.85, 0.005 * (t.clamp(5, 25) - 5) as f64];
            let span = t * j..(t + 1) * j;
            forward_kinematics(
                skel.parents(),
                skel.rest_offsets(),
                &root,
                &local,
                &mut p.positions[span.clone()],
                &mut p.global[span.clone()],
            )
            .unwrap();
            p.local[span].copy_from_slice(&local);
            p.root[t] = root;
            // Stretch the left thigh and shin (the foot moves with them).
            let pos = &mut p.positions[t * j..(t + 1) * j];
            let (s1, s2) = (0.02 * (t as f64).sin(), -0.02 * (t as f64 * 0.7).cos());
            let thigh = sub(&pos[4], &pos[1]);
            let shift1 = thigh.map(|v| v * s1);
            for b in [4, 7, 10] {
                pos[b] = rotation::add(&pos[b], &shift1);
            }
            let shin = sub(&pos[7], &pos[4]);
            let shift2 = shin.map(|v| v * s2);
            for b in [7, 10] {
                pos[b] = rotation::add(&pos[b], &shift2);
            }
            let left = if (5..25).contains(&t) { 1.0 } else { 0.0 };
            p.contacts.push([left, left, 0.0, 0.0]);
        }
        p
    }

    #[test]
    fn humanml263_locks_positions_and_rotations_keeping_each_frames_bones() {
        let raw = humanml_walk();
        let contacts = super::super::contacts::of(&raw, 20.0, &Default::default());
        let mut g = raw.clone();
        put_on_ground(&mut g, &contacts);
        assert!(drift(&g, 10, 5, 24) > 0.09);
        let mut locked = g.clone();
        lock(&mut locked, &contacts, 20.0).unwrap();
        let skel = Skeleton::humanml22();
        let j = locked.joint_count();
        assert!(
            drift(&locked, 10, 5, 24) < 1e-3,
            "{}",
            drift(&locked, 10, 5, 24)
        );
        for t in 0..locked.frames {
            let b = t * j;
            // Each frame keeps its own leg bone lengths.
            for (c, pa) in [(4, 1), (7, 4), (10, 7), (5, 2), (8, 5), (11, 8)] {
                let len = |p: &Poses| {
                    let d = sub(&p.positions[b + c], &p.positions[b + pa]);
                    rotation::dot(&d, &d).sqrt()
                };
                assert!((len(&locked) - len(&g)).abs() < 1e-9, "frame {t} bone {c}");
            }
            // Rotations: hierarchy consistent, turned by the same deltas as the position bones.
            for c in 1..j {
                let pa = skel.parent(c).unwrap();
                let want = rotation::mul(&locked.global[b + pa], &locked.local[b + c]);
                assert!(mat_diff(&want, &locked.global[b + c]) < 1e-9);
            }
            for (joint, child) in [(1, 4), (4, 7), (7, 10)] {
                let delta = rotation::mul(
                    &locked.global[b + joint],
                    &rotation::transpose(&g.global[b + joint]),
                );
                let before = sub(&g.positions[b + child], &g.positions[b + joint]);
                let after = sub(&locked.positions[b + child], &locked.positions[b + joint]);
                assert!(max_diff(&[rotation::apply(&delta, &before)], &[after]) < 1e-9);
            }
            for c in (0..j).filter(|c| !LEG_JOINTS.contains(c)) {
                assert_eq!(locked.positions[b + c], g.positions[b + c]);
            }
            for c in [0, 3, 6, 9, 12, 15, 20, 21] {
                assert_eq!(locked.global[b + c], g.global[b + c]);
            }
        }
    }

    #[test]
    fn a_swing_dragged_along_the_floor_is_redrawn_above_it() {
        // Both legs bent and still, the pelvis gliding 0.6 m forward (world −Y) over frames
        // 10..=19 (1.2 m/s) and still before and after; both feet planted on 0..=9 and 20..=29:
        // raw, the swinging toes drag along the floor at 1.2 m/s, which the skating ratio counts.
        let frames = 30;
        let mut x = Vec::new();
        for t in 0..frames {
            let glide = -0.6 * (t.clamp(9, 19) - 9) as f64 / 10.0;
            x.extend([0.0, glide, 0.9]);
            let mut rot = [[1.0, 0.0, 0.0, 0.0, 1.0, 0.0]; 24];
            rot[0] = rx(90.0);
            for (hip, knee, ankle) in [(1, 4, 7), (2, 5, 8)] {
                rot[hip] = rx(-30.0);
                rot[knee] = rx(50.0);
                rot[ankle] = rx(-20.0);
            }
            x.extend(rot.iter().flatten());
        }
        let x: Vec<f32> = x.iter().map(|&v| v as f32).collect();
        let mut raw =
            Poses::decode(Format::Smpl24Rot6d, &x, frames, &ReadOptions::default()).unwrap();
        let contacts: Vec<[bool; 4]> = (0..frames).map(|t| [!(10..=19).contains(&t); 4]).collect();
        put_on_ground(&mut raw, &contacts);
        let ratio = |p: &Poses| {
            let y_up = p.positions(crate::motion::Convention::Gltf);
            crate::motion::skating::skating_ratio(&y_up, frames, 24, 20.0).unwrap()
        };
        assert!(ratio(&raw) > 0.3, "raw {}", ratio(&raw));
        let mut locked = raw.clone();
        lock(&mut locked, &contacts, 20.0).unwrap();
        assert_eq!(ratio(&locked), 0.0);
        let up = 2;
        for leg in LEGS {
            let toe = |t: usize| locked.positions[t * 24 + leg.toe];
            // Never under the floor; the clearance at mid-swing; planted frames do not move.
            assert!((0..frames).all(|t| toe(t)[up] > -1e-9));
            assert!(toe(14)[up] >= SWING_CLEARANCE - 1e-9, "{}", toe(14)[up]);
            assert!(drift(&locked, leg.toe, 0, 9) < 1e-9 && drift(&locked, leg.toe, 20, 29) < 1e-9);
            // The foot leaves slowly: under 1 cm in the first swing frame.
            let first = sub(&toe(10), &toe(9));
            assert!(first[0].hypot(first[1]) < 0.01, "{first:?}");
        }
        // Hips and everything above never move.
        for t in 0..frames {
            for j in [0, 1, 2, 3, 6, 9, 12, 15] {
                assert_eq!(locked.positions[t * 24 + j], raw.positions[t * 24 + j]);
            }
        }
    }
}
