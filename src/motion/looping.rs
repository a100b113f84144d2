//! Loops: a clip whose last frame flows into its first. [`wrap`] is the post-processing half:
//! it removes what is left of the jump at the wrap, in position and in velocity, by adding a
//! smooth correction to the frames on both sides of it. A clip that was generated to loop (the
//! end edited to continue into the start, see `session`) needs only a small correction; any
//! other clip still gets a continuous wrap.
//!
//! # What "continues" means
//!
//! A loop plays frames `0..N` and then again, moved by the loop's root motion `T`: frame `N` is
//! `T(frame 0)`. `T` turns about the up axis through the pelvis and shifts horizontally; it
//! keeps the clip's travel (a walking loop walks on, as game locomotion clips do): the heading
//! and the horizontal pelvis position advance over the wrap by one frame of their average
//! rate, `(x[N−1] − x[0]) / (N − 1)`.
//!
//! # The correction
//!
//! Every channel — the root position, each joint's local rotation (as a rotation vector of its
//! change), and for humanml263, whose positions are not the kinematics of its rotations, each
//! joint position — is treated as a signal that runs from the clip's end into `T` of its start.
//! At the wrap it jumps by `J` in value (the start against the end extrapolated one frame) and
//! by `V` in velocity. Half of each is corrected on either side over `F` frames: the end side
//! adds `J/2 · S((u + F)/F) + V/2 · u(1 + u/F)²` (`u = t − N ∈ [−F, 0)`), the start side subtracts
//! `J/2 · S((F − u)/F) + V/2 · u(1 − u/F)²` (`u = t ∈ [0, F)`), `S` the smoothstep. Both terms
//! and their slopes vanish at `|u| = F`, so nothing changes where the correction starts; at the
//! wrap the two sides meet with the same value and slope. This is the cubic blend of a seam
//! (as `edit`'s seam blending) applied to the circular clip.

use super::poses::Poses;
use super::rotation::{self, Mat3, Vec3};
use crate::error::{invalid_arg, Result};

/// The shortest clip [`wrap`] accepts: each side of the wrap needs three frames for a velocity
/// and its change.
pub const MIN_FRAMES: usize = 6;

/// Seconds over which each side of the wrap is corrected: long enough that a correction of a
/// few centimetres stays below the motion's own accelerations, short enough to leave most of a
/// 2–10 s clip as generated.
const BLEND_SECONDS: f64 = 0.5;

/// Makes `poses` (at `fps`) loop: see the module doc. The correction spans at least
/// `BLEND_SECONDS` on each side; a larger jump gets a longer span (up to half the clip
/// on each side), the shortest whose wrap changes every joint's velocity by no more than the
/// clip's own largest frame-to-frame change ([`velocity_jumps`]).
pub fn wrap(poses: &mut Poses, fps: f64) -> Result<()> {
    check_length(poses.frames)?;
    let t = LoopMotion::of(poses);
    wrap_with(poses, fps, &t);
    Ok(())
}

/// [`wrap`] of a clip whose last frame is the first frame of the next cycle (a loop generated
/// by `crate::cycle`): `T` is the move from frame 0 to that frame, exactly, and the frame is
/// dropped after the correction.
pub fn wrap_to_last(poses: &mut Poses, fps: f64) -> Result<()> {
    check_length(poses.frames.saturating_sub(1))?;
    let last = poses.frames - 1;
    let t = LoopMotion::between(poses, 0, last);
    *poses = poses.frames_range(0, last);
    wrap_with(poses, fps, &t);
    Ok(())
}

fn check_length(n: usize) -> Result<()> {
    if n < MIN_FRAMES {
        return Err(invalid_arg!(
            "a loop needs at least {MIN_FRAMES} frames, the clip has {n}"
        ));
    }
    Ok(())
}

fn wrap_with(poses: &mut Poses, fps: f64, t: &LoopMotion) {
    let n = poses.frames;
    let longest = n / 2;
    let shortest = ((BLEND_SECONDS * fps).round() as usize).clamp(3, longest);
    let mut best = None;
    for blend in shortest..=longest {
        let mut tried = poses.clone();
        correct(&mut tried, t, blend);
        let (inside, at_wrap) = velocity_jumps(&tried, t);
        let done = at_wrap <= inside;
        if done || blend == longest {
            best = Some(tried);
            if done {
                break;
            }
        }
    }
    if let Some(p) = best {
        *poses = p;
    }
}

/// Applies the correction of the module doc over `blend` frames on each side of the wrap.
fn correct(poses: &mut Poses, t: &LoopMotion, blend: usize) {
    let n = poses.frames;
    let joints = poses.joint_count();
    let root: Vec<Vec3> = poses.root.clone();
    for (k, c) in correction(&root, blend, |p| t.position(p), sub) {
        poses.root[k] = add(&poses.root[k], &c);
    }
    // Rotations: the root's world rotation is moved by T's turn, the others are T-invariant.
    for j in 0..joints {
        let track: Vec<Mat3> = (0..n).map(|k| poses.local[k * joints + j]).collect();
        let turn = if j == 0 { t.turn } else { rotation::IDENTITY };
        let fix = correction(
            &track,
            blend,
            |r| rotation::mul(&turn, r),
            |a, b| log(&rotation::mul(&rotation::transpose(b), a)),
        );
        for (k, c) in fix {
            let r = &mut poses.local[k * joints + j];
            *r = rotation::mul(r, &exp(&c));
        }
    }
    if !poses.format.positions_are_kinematic() {
        for j in 0..joints {
            let track: Vec<Vec3> = (0..n).map(|k| poses.positions[k * joints + j]).collect();
            for (k, c) in correction(&track, blend, |p| t.position(p), sub) {
                let p = &mut poses.positions[k * joints + j];
                *p = add(p, &c);
            }
        }
    }
    for k in (0..blend).chain(n - blend..n) {
        poses.refresh_frame(k);
    }
}

/// Over every joint's world position: the largest change of velocity between consecutive
/// frames inside the clip, and the largest at the wrap (frame N−1 → `T`(frame 0) against
/// N−2 → N−1, and `T`(0) → `T`(1) against N−1 → `T`(0)), in the poses' units per frame.
pub fn velocity_jumps(p: &Poses, t: &LoopMotion) -> (f64, f64) {
    let n = p.frames;
    let j = p.joint_count();
    let at = |k: usize, i: usize| p.positions[k * j + i];
    let norm = |v: Vec3| rotation::dot(&v, &v).sqrt();
    let (mut inside, mut wrap) = (0.0f64, 0.0f64);
    for i in 0..j {
        for k in 1..n - 1 {
            let a = sub(&at(k, i), &at(k - 1, i));
            let b = sub(&at(k + 1, i), &at(k, i));
            inside = inside.max(norm(sub(&b, &a)));
        }
        let (s0, s1) = (t.position(&at(0, i)), t.position(&at(1, i)));
        let before = sub(&at(n - 1, i), &at(n - 2, i));
        let across = sub(&s0, &at(n - 1, i));
        let after = sub(&s1, &s0);
        wrap = wrap
            .max(norm(sub(&across, &before)))
            .max(norm(sub(&after, &across)));
    }
    (inside, wrap)
}

/// The move `T` from a loop's start to its next cycle: a turn about the up axis through
/// `pivot` (frame 0's pelvis), then the pivot carried to `target`.
#[derive(Clone, Copy, Debug)]
pub struct LoopMotion {
    /// The heading change: a rotation about the format's native up axis (Y for humanml263, Z for
    /// smpl24_6d; [`crate::motion::Format::up_axis`]).
    pub turn: Mat3,
    /// The point turned about: the start frame's pelvis, native world frame, metres.
    pub pivot: Vec3,
    /// Where `pivot` lands, same frame and unit; its height is the pivot's (the move is
    /// horizontal).
    pub target: Vec3,
}

impl LoopMotion {
    /// The loop motion of `poses`: heading and horizontal pelvis position advanced past the last
    /// frame by one frame of their average rate over the clip.
    pub fn of(poses: &Poses) -> LoopMotion {
        let n = poses.frames;
        let up_axis = poses.format.up_axis();
        let angle = heading_change(poses, 0, n - 1);
        let (p0, p1) = (poses.root[0], poses.root[n - 1]);
        let step = sub(&p1, &p0).map(|d| d / (n - 1) as f64);
        let mut target = add(&p1, &step);
        target[up_axis] = p0[up_axis];
        LoopMotion {
            turn: rotation::axis_angle(&up(up_axis), angle * n as f64 / (n - 1) as f64),
            pivot: p0,
            target,
        }
    }

    /// The move taking frame `a`'s pelvis (position and heading about the up axis) onto frame
    /// `b`'s, height kept.
    pub fn between(poses: &Poses, a: usize, b: usize) -> LoopMotion {
        let up_axis = poses.format.up_axis();
        let mut target = poses.root[b];
        target[up_axis] = poses.root[a][up_axis];
        LoopMotion {
            turn: rotation::axis_angle(&up(up_axis), heading_change(poses, a, b)),
            pivot: poses.root[a],
            target,
        }
    }

    /// Where `T` takes a point.
    pub fn position(&self, p: &Vec3) -> Vec3 {
        add(
            &rotation::apply(&self.turn, &sub(p, &self.pivot)),
            &self.target,
        )
    }
}

/// The correction of a circular signal `x` (N frames) whose continuation after frame N−1 is
/// `next(x[0]), next(x[1]), …`: per corrected frame, the tangent-space offset to add.
/// `diff(a, b)` is the tangent vector from `b` to `a` (in `b`'s tangent space for rotations).
fn correction<X>(
    x: &[X],
    blend: usize,
    next: impl Fn(&X) -> X,
    diff: impl Fn(&X, &X) -> Vec3,
) -> Vec<(usize, Vec3)> {
    let n = x.len();
    let start = [next(&x[0]), next(&x[1]), next(&x[2])];
    // Both sides predict the signal and its slope half a frame past their last frame, at the
    // wrap point m = N − ½ (second-order accurate, so a smooth signal gives no jump).
    let end_slope = diff(&x[n - 1], &x[n - 2]);
    let end_bend = sub(&end_slope, &diff(&x[n - 2], &x[n - 3]));
    let start_slope = diff(&start[1], &start[0]);
    let start_bend = sub(&diff(&start[2], &start[1]), &start_slope);
    let jump = sub(
        &diff(&start[0], &x[n - 1]),
        &lin(&start_slope, 0.5, &end_slope, 0.5),
    );
    let kink = sub(
        &sub(&start_slope, &end_slope),
        &lin(&start_bend, 0.5, &end_bend, 0.5),
    );
    let f = blend as f64;
    let mut out = Vec::with_capacity(2 * blend);
    for k in n - blend..n {
        let u = k as f64 + 0.5 - n as f64;
        let w = smoothstep((u + f) / f);
        let s = u * (1.0 + u / f).powi(2);
        out.push((k, lin(&jump, 0.5 * w, &kink, 0.5 * s)));
    }
    for k in 0..blend {
        let u = k as f64 + 0.5;
        let w = smoothstep((f - u) / f);
        let s = u * (1.0 - u / f).powi(2);
        out.push((k, lin(&jump, -0.5 * w, &kink, -0.5 * s)));
    }
    out
}

/// The unit vector of the up axis.
fn up(axis: usize) -> Vec3 {
    let mut v = [0.0; 3];
    v[axis] = 1.0;
    v
}

/// The signed angle about the up axis from frame `a`'s heading to frame `b`'s: each heading is
/// the body's forward (+Z in the body frames, skeleton's module doc) turned by the root's world
/// rotation and laid flat.
fn heading_change(poses: &Poses, a: usize, b: usize) -> f64 {
    let joints = poses.joint_count();
    let up_axis = poses.format.up_axis();
    let heading = |k: usize| {
        let mut h = rotation::apply(&poses.global[k * joints], &[0.0, 0.0, 1.0]);
        h[up_axis] = 0.0;
        h
    };
    let (h0, h1) = (heading(a), heading(b));
    rotation::dot(&up(up_axis), &rotation::cross(&h0, &h1)).atan2(rotation::dot(&h0, &h1))
}

fn smoothstep(x: f64) -> f64 {
    let x = x.clamp(0.0, 1.0);
    x * x * (3.0 - 2.0 * x)
}

fn lin(a: &Vec3, ka: f64, b: &Vec3, kb: f64) -> Vec3 {
    [0, 1, 2].map(|i| a[i] * ka + b[i] * kb)
}

fn add(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn sub(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// The rotation vector of `m` (axis × angle, angle in [0, π]).
fn log(m: &Mat3) -> Vec3 {
    let [w, x, y, z] = rotation::to_quat(m);
    let s = (x * x + y * y + z * z).sqrt();
    if s < 1e-12 {
        return [2.0 * x, 2.0 * y, 2.0 * z];
    }
    let angle = 2.0 * s.atan2(w);
    [x, y, z].map(|v| v / s * angle)
}

/// The rotation of rotation vector `v`.
fn exp(v: &Vec3) -> Mat3 {
    let angle = rotation::dot(v, v).sqrt();
    if angle < 1e-12 {
        return rotation::IDENTITY;
    }
    rotation::axis_angle(v, angle)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::format::Format;

    /// A smpl24_6d clip standing upright (root tilted +90° about X, as the data stands), the
    /// pelvis moving on `root(t)`, the root turning by `yaw(t)` about Z, the left knee and right
    /// elbow bending by `bend(t)`.
    fn clip(
        n: usize,
        root: impl Fn(f64) -> Vec3,
        yaw: impl Fn(f64) -> f64,
        bend: impl Fn(f64) -> f64,
    ) -> Poses {
        let mut p = Poses::empty(Format::Smpl24Rot6d, n);
        let joints = p.joint_count();
        let tilt = rotation::axis_angle(&[1.0, 0.0, 0.0], std::f64::consts::FRAC_PI_2);
        for k in 0..n {
            let t = k as f64;
            p.root[k] = root(t);
            p.local[k * joints] =
                rotation::mul(&rotation::axis_angle(&[0.0, 0.0, 1.0], yaw(t)), &tilt);
            p.local[k * joints + 4] = rotation::axis_angle(&[1.0, 0.0, 0.0], bend(t));
            p.local[k * joints + 19] = rotation::axis_angle(&[0.0, 1.0, 0.0], 0.5 * bend(t));
            p.refresh_frame(k);
        }
        p
    }

    #[test]
    fn a_clip_that_already_loops_is_unchanged() {
        // Constant travel, a heading that keeps still, a knee swinging with the clip's period:
        // the clip continues into T(frame 0) exactly, so both jumps are zero and nothing moves.
        let n = 40;
        let period = n as f64;
        let mut p = clip(
            n,
            |t| [0.02 * t, -0.01 * t, 0.9],
            |_| 0.3,
            |t| 0.6 * (2.0 * std::f64::consts::PI * t / period).sin(),
        );
        // The predictions at the wrap are second-order: what is left is the third-order term
        // of a 0.6 rad swing over 40 frames, well under a millimetre; a wrong jump would move
        // the knee's children by centimetres.
        let before = p.clone();
        wrap(&mut p, 20.0).unwrap();
        for (a, b) in p.positions.iter().zip(&before.positions) {
            assert!(sub(a, b).iter().all(|d| d.abs() < 1e-3), "{a:?} {b:?}");
        }
    }

    #[test]
    fn the_wrap_jump_falls_below_the_clip_own_accelerations() {
        // A near-loop, as editing leaves it: a walk whose knee swing ends 0.15 rad and whose
        // pelvis bob ends 2 cm away from where the next cycle starts. Raw, the wrap jumps by
        // more than any frame-to-frame change inside; wrapped, by no more.
        let n = 60;
        let cycle = 2.0 * std::f64::consts::PI / n as f64;
        let mut p = clip(
            n,
            |t| {
                [
                    0.03 * t,
                    0.0,
                    0.9 + 0.02 * (cycle * 2.0 * t).sin() + 0.02 * t / 59.0,
                ]
            },
            |_| 0.2,
            |t| 0.4 + 0.5 * (cycle * 2.0 * t).sin() + 0.15 * t / 59.0,
        );
        let (inside_raw, wrap_raw) = velocity_jumps(&p, &LoopMotion::of(&p));
        assert!(wrap_raw > 2.0 * inside_raw, "{wrap_raw} vs {inside_raw}");
        wrap(&mut p, 20.0).unwrap();
        let (inside, at_wrap) = velocity_jumps(&p, &LoopMotion::of(&p));
        assert!(
            at_wrap <= inside,
            "wrap {at_wrap} > inside {inside} (raw {wrap_raw} vs {inside_raw})"
        );
        // Bone lengths stay the skeleton's: the correction acts on rotations.
        let skel = Format::Smpl24Rot6d.skeleton();
        for k in 0..n {
            for i in 1..24 {
                let par = skel.parent(i).unwrap();
                let d = sub(&p.positions[k * 24 + i], &p.positions[k * 24 + par]);
                let o = skel.rest_offsets()[i];
                assert!((rotation::dot(&d, &d).sqrt() - rotation::dot(&o, &o).sqrt()).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn a_clip_far_from_looping_still_wraps_continuously() {
        // The knee ends 1.6 rad away from its start: no blend within the clip keeps the wrap's
        // acceleration under the clip's own, but the jump in position (what pops on screen)
        // is gone and the change of velocity at the wrap shrinks twentyfold.
        let n = 60;
        let mut p = clip(
            n,
            |t| [0.03 * t, 0.0, 0.9 + 0.03 * (t / 5.0).sin()],
            |t| 0.3 * (t / 25.0).sin(),
            |t| 0.2 + 0.9 * (t / 13.0).sin(),
        );
        let (_, wrap_raw) = velocity_jumps(&p, &LoopMotion::of(&p));
        wrap(&mut p, 20.0).unwrap();
        let (_, at_wrap) = velocity_jumps(&p, &LoopMotion::of(&p));
        assert!(at_wrap < wrap_raw / 20.0, "{at_wrap} vs raw {wrap_raw}");
    }

    #[test]
    fn too_short_a_clip_is_refused_by_name() {
        let mut p = clip(5, |_| [0.0, 0.0, 0.9], |_| 0.0, |_| 0.0);
        let e = wrap(&mut p, 20.0).unwrap_err().to_string();
        assert!(e.contains("at least 6 frames, the clip has 5"), "{e}");
    }
}
