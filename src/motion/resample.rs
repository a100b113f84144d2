//! Frame-rate resampling of decoded poses: any rate from 1 to 240 frames per second to any other.
//!
//! - **Times.** Output frame `k` is at `k / to_fps` seconds, input frame `j` at `j / from_fps`.
//!   The output keeps every time up to and including the last input frame's, `(T − 1) / from_fps`,
//!   and never extrapolates past it: `T` frames give `⌊(T − 1)·to/from⌋ + 1` (120 frames at 20
//!   fps span 5.95 s and give 179 frames at 30 fps, the last at 5.9333 s; 0 frames give 0). The
//!   clip may therefore end up to one output frame short of the input's end, but no pose is
//!   invented beyond what the model made.
//! - **Exact frames.** A rate is an `f64`, an exact binary fraction `m·2^e` (`m` < 2⁵³), so
//!   where output frame `k` falls among the input frames, `k·from/to = j + rem/den`, is computed
//!   in `u128` integers without rounding for any two rates, integral or not (29.97 included):
//!   for `k` < 2²⁰ and rates within a factor 2⁵⁰ of each other nothing overflows. An output
//!   frame whose time is an input frame's (`rem = 0`) is that frame, copied bit for bit
//!   (rotations, positions, contacts and all); the others interpolate at `rem/den`.
//! - **Rotations.** Each joint's local rotation by slerp of unit quaternions along the shorter
//!   arc (the second quaternion negated when the dot product is negative), Shoemake, "Animating
//!   rotation with quaternion curves", SIGGRAPH 1985, §3.3; the quaternions come from
//!   [`rotation::to_quat`] and are normalised first (a degenerate model output is not unit).
//! - **Translations.** The root (and the `root` bone when there is one) linearly. A monotone
//!   cubic (Fritsch–Carlson) would be smoother through the samples, but any cubic can leave the
//!   segment between two samples where a linear one cannot overshoot, and linear is what a glTF
//!   `LINEAR` sampler does between keyframes (glTF 2.0 §3.11, "Animations", Appendix C
//!   "Interpolation"): an engine replaying the resampled file at the original keys sees the same
//!   path.
//! - **Consistency.** For formats whose positions are the forward kinematics of their rotations
//!   ([`Format::positions_are_kinematic`], smpl24_6d) the interpolated frames' world rotations
//!   and positions are recomputed by forward kinematics of the resampled local rotations and
//!   root. humanml263's positions are its own output, which its rotations only approximate:
//!   they are interpolated linearly per joint, and its world rotations are the products of the
//!   resampled local ones (`global(j) = global(parent) · local(j)`, as its decoder defines them).
//! - **Contacts.** Each output frame takes the nearest input frame's contacts; at exactly half
//!   way (an exact integer test) the earlier frame's, so a contact span never grows at both ends.
//!
//! [`Format::positions_are_kinematic`]: super::format::Format::positions_are_kinematic

use super::poses::Poses;
use super::rotation::{self, Mat3, QuatWxyz, Vec3};
use super::skeleton::forward_kinematics;
use crate::error::{invalid_arg, Result};

/// The most frames a resampled clip may have: 2²⁰ (over an hour at 240 fps, several GiB of
/// poses). More is an error before anything is allocated.
pub const MAX_FRAMES: usize = 1 << 20;

/// `poses` (at `from_fps`) resampled to `to_fps`: see the module doc. Rates must be positive
/// and finite ([`super::Finish`] keeps its target in [`FPS_RANGE`], 1 to 240); the poses'
/// optional tracks (contacts, root bone) must be empty or one entry a frame.
///
/// [`FPS_RANGE`]: super::finish::FPS_RANGE
pub fn resample(poses: &Poses, from_fps: f64, to_fps: f64) -> Result<Poses> {
    let from = exact_rate("source", from_fps)?;
    let to = exact_rate("target", to_fps)?;
    let out_frames = output_frames(poses.frames, from, to)?;
    resample_range(poses, from_fps, to_fps, 0, 0..out_frames)
}

/// Where output frame `k` (at `to_fps`) falls among the input frames (at `from_fps`): the input
/// frame at or before it, and whether it is exactly that frame (then it is copied bit for bit).
pub(crate) fn source_of(k: usize, from_fps: f64, to_fps: f64) -> Result<(usize, bool)> {
    let from = exact_rate("source", from_fps)?;
    let to = exact_rate("target", to_fps)?;
    let at = position(k, from, to).ok_or_else(|| {
        invalid_arg!("resample: the rates {from_fps} and {to_fps} are too far apart")
    })?;
    Ok((at.frame, at.rem == 0))
}

/// Output frames `wanted` of [`resample`] of a longer clip whose input frames
/// `source_first..source_first + poses.frames` are `poses` (a stream's, `crate::stream`): the
/// same bits as those frames of the whole clip's [`resample`]. Every output frame's input frames
/// ([`source_of`]: that one, and the next unless exact) must be in `poses`.
pub(crate) fn resample_range(
    poses: &Poses,
    from_fps: f64,
    to_fps: f64,
    source_first: usize,
    wanted: std::ops::Range<usize>,
) -> Result<Poses> {
    let from = exact_rate("source", from_fps)?;
    let to = exact_rate("target", to_fps)?;
    let frames = poses.frames;
    let joints = poses.joint_count();
    for (name, len) in [
        ("contacts", poses.contacts.len()),
        ("root bone", poses.root_bone.len()),
    ] {
        if len != 0 && len != frames {
            return Err(invalid_arg!(
                "resample: the {name} track has {len} entries for {frames} frames"
            ));
        }
    }
    let out_frames = wanted.len();
    let n = out_frames
        .checked_mul(joints)
        .ok_or_else(|| invalid_arg!("resample: {out_frames} frames of {joints} joints overflow"))?;
    let mut out = Poses::empty(poses.format, out_frames);
    out.continuous = poses.continuous;
    if !poses.contacts.is_empty() {
        out.contacts = Vec::with_capacity(out_frames);
    }
    if !poses.root_bone.is_empty() {
        out.root_bone = Vec::with_capacity(out_frames);
    }
    debug_assert_eq!(out.local.len(), n);

    let skel = poses.format.skeleton();
    let kinematic = poses.format.positions_are_kinematic();
    for (k, global) in wanted.enumerate() {
        let at = position(global, from, to).ok_or_else(|| {
            invalid_arg!("resample: the rates {from_fps} and {to_fps} are too far apart")
        })?;
        let dst = k * joints..(k + 1) * joints;
        let a = at
            .frame
            .checked_sub(source_first)
            .filter(|&a| a + usize::from(at.rem != 0) < frames)
            .ok_or_else(|| {
                invalid_arg!(
                    "resample: output frame {global} needs input frames {source_first}+ not given"
                )
            })?;
        let src_a = a * joints..(a + 1) * joints;
        if at.rem == 0 {
            out.root[k] = poses.root[a];
            out.local[dst.clone()].copy_from_slice(&poses.local[src_a.clone()]);
            out.global[dst.clone()].copy_from_slice(&poses.global[src_a.clone()]);
            out.positions[dst].copy_from_slice(&poses.positions[src_a]);
            if !poses.contacts.is_empty() {
                out.contacts.push(poses.contacts[a]);
            }
            if !poses.root_bone.is_empty() {
                out.root_bone.push(poses.root_bone[a]);
            }
            continue;
        }
        // rem > 0 only when k·from < (T − 1)·to, so frame a + 1 exists.
        let b = a + 1;
        let src_b = b * joints..(b + 1) * joints;
        let alpha = at.rem as f64 / at.den as f64;
        out.root[k] = lerp(&poses.root[a], &poses.root[b], alpha);
        if !poses.root_bone.is_empty() {
            out.root_bone
                .push(lerp(&poses.root_bone[a], &poses.root_bone[b], alpha));
        }
        if !poses.contacts.is_empty() {
            // Nearest frame; exactly half way (2·rem = den) goes to the earlier one.
            let nearest = if 2 * at.rem <= at.den { a } else { b };
            out.contacts.push(poses.contacts[nearest]);
        }
        for (o, (ra, rb)) in out.local[dst.clone()].iter_mut().zip(
            poses.local[src_a.clone()]
                .iter()
                .zip(&poses.local[src_b.clone()]),
        ) {
            *o = slerp_matrices(ra, rb, alpha);
        }
        if kinematic {
            forward_kinematics(
                skel.parents(),
                skel.rest_offsets(),
                &out.root[k],
                &out.local[dst.clone()],
                &mut out.positions[dst.clone()],
                &mut out.global[dst],
            )?;
        } else {
            for (o, (pa, pb)) in out.positions[dst.clone()]
                .iter_mut()
                .zip(poses.positions[src_a].iter().zip(&poses.positions[src_b]))
            {
                *o = lerp(pa, pb, alpha);
            }
            let (local, global) = (&out.local[dst.clone()], &mut out.global[dst]);
            for j in 0..joints {
                global[j] = match skel.parent(j) {
                    Some(p) => rotation::mul(&global[p], &local[j]),
                    None => local[j],
                };
            }
        }
    }
    Ok(out)
}

/// A positive, finite rate as the exact binary fraction `m · 2^e` (`m` < 2⁵³).
#[derive(Clone, Copy)]
struct Rate {
    m: u128,
    e: i32,
}

fn exact_rate(which: &str, fps: f64) -> Result<Rate> {
    if !(fps.is_finite() && fps > 0.0) {
        return Err(invalid_arg!(
            "resample: the {which} frame rate must be a positive number of frames per second, got {fps}"
        ));
    }
    // IEEE 754 binary64: 11 exponent bits biased by 1023, 52 fraction bits, the leading 1
    // implicit except for subnormals.
    let bits = fps.to_bits();
    let exp = ((bits >> 52) & 0x7ff) as i32;
    let frac = (bits & ((1 << 52) - 1)) as u128;
    Ok(if exp == 0 {
        Rate { m: frac, e: -1074 }
    } else {
        Rate {
            m: frac | 1 << 52,
            e: exp - 1075,
        }
    })
}

/// `n · a / b` as the exact fraction `num / den` of integers, or `None` when the rates are so
/// far apart (or `n` so large) that it does not fit in `u128`.
fn ratio(n: u128, a: Rate, b: Rate) -> Option<(u128, u128)> {
    let shift = a.e - b.e;
    let shl = |x: u128, s: i32| -> Option<u128> {
        (s < 128 && x.leading_zeros() as i32 > s).then(|| x << s)
    };
    let num = n.checked_mul(a.m)?;
    if shift >= 0 {
        Some((shl(num, shift)?, b.m))
    } else {
        Some((num, shl(b.m, -shift)?))
    }
}

/// `⌊(T − 1)·to/from⌋ + 1` output frames for `T` input frames (0 for 0), checked against
/// [`MAX_FRAMES`].
fn output_frames(frames: usize, from: Rate, to: Rate) -> Result<usize> {
    if frames == 0 {
        return Ok(0);
    }
    let too_many = || {
        invalid_arg!(
            "resample: {frames} frames would become more than the {MAX_FRAMES} frames allowed"
        )
    };
    let (num, den) = ratio(frames as u128 - 1, to, from).ok_or_else(too_many)?;
    let last = num / den;
    if last >= MAX_FRAMES as u128 {
        return Err(invalid_arg!(
            "resample: {frames} frames would become {} frames, more than the {MAX_FRAMES} allowed",
            last + 1
        ));
    }
    Ok(last as usize + 1)
}

/// Where output frame `k` falls among the input frames: `k·from/to = frame + rem/den`.
struct At {
    frame: usize,
    rem: u128,
    den: u128,
}

/// `None` only if the fraction overflows, which [`output_frames`]' bound rules out for every
/// `k` it allows (`k·from/to ≤ T − 1`; the module doc's argument).
fn position(k: usize, from: Rate, to: Rate) -> Option<At> {
    let (num, den) = ratio(k as u128, from, to)?;
    Some(At {
        frame: usize::try_from(num / den).ok()?,
        rem: num % den,
        den,
    })
}

fn lerp(a: &Vec3, b: &Vec3, t: f64) -> Vec3 {
    [0, 1, 2].map(|i| a[i] + (b[i] - a[i]) * t)
}

/// `q / |q|`, the identity for a zero quaternion.
fn unit(q: QuatWxyz) -> QuatWxyz {
    let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
    if n > 1e-12 {
        q.map(|x| x / n)
    } else {
        [1.0, 0.0, 0.0, 0.0]
    }
}

/// Slerp of unit quaternions along the shorter arc: `a` at `t = 0`, `b` at `t = 1` (Shoemake
/// 1985). Nearly equal quaternions (`cos θ > 1 − 1e-10`, where `sin θ` loses its digits) are
/// interpolated linearly and normalised, which agrees with slerp to O(θ³).
pub(crate) fn slerp(a: &QuatWxyz, b: &QuatWxyz, t: f64) -> QuatWxyz {
    let mut d: f64 = (0..4).map(|i| a[i] * b[i]).sum();
    let b = if d < 0.0 {
        d = -d;
        b.map(|x| -x)
    } else {
        *b
    };
    let (wa, wb) = if d > 1.0 - 1e-10 {
        (1.0 - t, t)
    } else {
        let theta = d.min(1.0).acos();
        let s = theta.sin();
        (((1.0 - t) * theta).sin() / s, (t * theta).sin() / s)
    };
    unit([0, 1, 2, 3].map(|i| wa * a[i] + wb * b[i]))
}

fn slerp_matrices(a: &Mat3, b: &Mat3, t: f64) -> Mat3 {
    let qa = unit(rotation::to_quat(a));
    let qb = unit(rotation::to_quat(b));
    rotation::quat_to_matrix(&slerp(&qa, &qb, t))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::Format;
    use std::f64::consts::{FRAC_PI_2, PI};

    /// The gltf tests' smooth synthetic motion: every feature a sinusoid of time.
    fn motion(format: Format, frames: usize) -> Poses {
        crate::motion::testutil::sinusoid_motion(format, frames)
    }

    fn bits(m: &[Mat3]) -> Vec<u64> {
        m.iter().flatten().flatten().map(|x| x.to_bits()).collect()
    }

    fn vbits(v: &[Vec3]) -> Vec<u64> {
        v.iter().flatten().map(|x| x.to_bits()).collect()
    }

    fn near(a: &Vec3, b: &Vec3, tol: f64) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < tol)
    }

    fn close(a: &Mat3, b: &Mat3, tol: f64) -> bool {
        (0..3).all(|r| (0..3).all(|c| (a[r][c] - b[r][c]).abs() < tol))
    }

    #[test]
    fn twenty_to_thirty_keeps_the_last_time_and_copies_common_frames() {
        for format in Format::ALL {
            let mut poses = motion(format, 120);
            poses.contacts = (0..120).map(|t| [(t % 2) as f64, 0.0, 1.0, 0.5]).collect();
            poses.root_bone = (0..120).map(|t| [t as f64 * 0.01, 0.0, -0.5]).collect();
            let out = resample(&poses, 20.0, 30.0).unwrap();
            // 119 intervals of 1/20 s = 5.95 s; 5.95·30 = 178.5 → frames 0..=178.
            assert_eq!(out.frames, 179);
            assert_eq!(out.local.len(), 179 * poses.joint_count());
            assert_eq!(out.contacts.len(), 179);
            assert_eq!(out.root_bone.len(), 179);
            let j = poses.joint_count();
            // Output 3m is at 3m/30 = 2m/20 s: input frame 2m, bit for bit.
            for m in 0..60 {
                let (k, i) = (3 * m, 2 * m);
                let (o, s) = (k * j..(k + 1) * j, i * j..(i + 1) * j);
                assert_eq!(bits(&out.local[o.clone()]), bits(&poses.local[s.clone()]));
                assert_eq!(bits(&out.global[o.clone()]), bits(&poses.global[s.clone()]));
                assert_eq!(vbits(&out.positions[o]), vbits(&poses.positions[s]));
                assert_eq!(
                    out.root[k].map(f64::to_bits),
                    poses.root[i].map(f64::to_bits)
                );
                assert_eq!(out.contacts[k], poses.contacts[i]);
                assert_eq!(out.root_bone[k], poses.root_bone[i]);
            }
            // Output 1 is at 1/30 s = input 2/3: root and root bone two thirds of the way from
            // frame 0 to frame 1, contacts frame 1's (nearer), output 2 (input 4/3) frame 1's.
            let want = lerp(&poses.root[0], &poses.root[1], 2.0 / 3.0);
            assert!(near(&out.root[1], &want, 1e-15));
            assert!((out.root_bone[1][0] - 0.02 / 3.0).abs() < 1e-15);
            assert_eq!(out.contacts[1], [1.0, 0.0, 1.0, 0.5]);
            assert_eq!(out.contacts[2], [1.0, 0.0, 1.0, 0.5]);
            // Consistency of an interpolated frame: globals = products of the locals; for
            // smpl24_6d positions = their forward kinematics, for humanml263 the lerp.
            let skel = format.skeleton();
            let (l, g) = (&out.local[j..2 * j], &out.global[j..2 * j]);
            for c in 1..j {
                let p = skel.parent(c).unwrap();
                assert!(close(&g[c], &rotation::mul(&g[p], &l[c]), 1e-12));
            }
            if format == Format::HumanMl263 {
                let want = lerp(&poses.positions[5], &poses.positions[j + 5], 2.0 / 3.0);
                assert!(near(&out.positions[j + 5], &want, 1e-15));
            } else {
                let (c, p) = (4, 1); // left knee hangs from the left hip
                let bone = rotation::apply(&g[p], &skel.rest_offsets()[c]);
                let want = rotation::add(&out.positions[j + p], &bone);
                assert!(near(&out.positions[j + c], &want, 1e-15));
            }
        }
    }

    /// Two frames, joint 1 turning from `a` to `b` radians about `axis`.
    fn two_frames(axis: Vec3, a: f64, b: f64) -> Poses {
        let mut p = Poses::empty(Format::Smpl24Rot6d, 2);
        let j = p.joint_count();
        p.local[1] = rotation::axis_angle(&axis, a);
        p.local[j + 1] = rotation::axis_angle(&axis, b);
        p.root = vec![[0.0, 0.0, 1.0], [0.1, 0.0, 1.0]];
        p
    }

    #[test]
    fn midpoints_are_the_slerp_half_way() {
        // 20 → 40 fps: output 1 is at 1/40 s, half way between the two frames.
        let poses = two_frames([0.0, 0.0, 1.0], 0.2, 1.0);
        let out = resample(&poses, 20.0, 40.0).unwrap();
        assert_eq!(out.frames, 3);
        let j = poses.joint_count();
        // About one axis slerp is the mean angle: Rz(0.6).
        assert!(close(
            &out.local[j + 1],
            &rotation::axis_angle(&[0.0, 0.0, 1.0], 0.6),
            1e-14
        ));
        assert_eq!(out.root[1], [0.05, 0.0, 1.0]);
        // Identity → 90° about X: the half step is 45° about X, (cos 22.5°, sin 22.5°, 0, 0).
        let q = slerp(
            &[1.0, 0.0, 0.0, 0.0],
            &rotation::to_quat(&rotation::axis_angle(&[1.0, 0.0, 0.0], FRAC_PI_2)),
            0.5,
        );
        let (c, s) = ((PI / 8.0).cos(), (PI / 8.0).sin());
        assert!((q[0] - c).abs() < 1e-15 && (q[1] - s).abs() < 1e-15);
        assert!(q[2].abs() < 1e-15 && q[3].abs() < 1e-15);
        // The shorter arc: from +170° to −170° about Z passes through 180°, not 0°.
        let poses = two_frames([0.0, 0.0, 1.0], 170f64.to_radians(), -170f64.to_radians());
        let out = resample(&poses, 20.0, 40.0).unwrap();
        assert!(close(
            &out.local[j + 1],
            &rotation::axis_angle(&[0.0, 0.0, 1.0], PI),
            1e-14
        ));
        // A quarter step of a 90° turn is 22.5°.
        let poses = two_frames([0.0, 1.0, 0.0], 0.0, FRAC_PI_2);
        let out = resample(&poses, 30.0, 120.0).unwrap();
        assert_eq!(out.frames, 5);
        assert!(close(
            &out.local[j + 1],
            &rotation::axis_angle(&[0.0, 1.0, 0.0], PI / 8.0),
            1e-14
        ));
    }

    #[test]
    fn contacts_take_the_nearest_frame_and_the_earlier_on_a_tie() {
        let mut poses = two_frames([0.0, 0.0, 1.0], 0.0, 1.0);
        poses.contacts = vec![[1.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0]];
        // 20 → 80 fps: outputs at input 0, 1/4, 1/2, 3/4, 1.
        let out = resample(&poses, 20.0, 80.0).unwrap();
        let (a, b) = (poses.contacts[0], poses.contacts[1]);
        assert_eq!(out.contacts, vec![a, a, a, b, b]);
    }

    #[test]
    fn the_extreme_rates_and_a_non_integral_one() {
        let poses = motion(Format::Smpl24Rot6d, 120);
        let j = poses.joint_count();
        // 1 fps keeps the seconds 0..=5: input frames 0, 20, …, 100, all copies.
        let one = resample(&poses, 20.0, 1.0).unwrap();
        assert_eq!(one.frames, 6);
        for s in 0..6 {
            assert_eq!(
                bits(&one.local[s * j..(s + 1) * j]),
                bits(&poses.local[20 * s * j..(20 * s + 1) * j])
            );
        }
        // 240 fps: 119·12 + 1 frames; every 12th is an input frame.
        let fast = resample(&poses, 20.0, 240.0).unwrap();
        assert_eq!(fast.frames, 1429);
        assert_eq!(
            vbits(&fast.positions[1428 * j..]),
            vbits(&poses.positions[119 * j..])
        );
        // NTSC's 29.97: 119·29.97/20 = 178.32 → 179 frames; none but frame 0 is an input frame
        // (k·20 = j·29.97 needs k a multiple of 2997).
        let ntsc = resample(&poses, 20.0, 29.97).unwrap();
        assert_eq!(ntsc.frames, 179);
        // 240 → 20 and back to a lower, non-dividing rate.
        assert_eq!(resample(&fast, 240.0, 20.0).unwrap().frames, 120);
        assert_eq!(resample(&poses, 20.0, 7.0).unwrap().frames, 42); // ⌊119·7/20⌋ + 1
    }

    #[test]
    fn empty_and_single_frame_clips() {
        let empty = Poses::empty(Format::HumanMl263, 0);
        assert_eq!(resample(&empty, 20.0, 60.0).unwrap().frames, 0);
        let one = motion(Format::HumanMl263, 1);
        let out = resample(&one, 20.0, 60.0).unwrap();
        assert_eq!(out.frames, 1);
        assert_eq!(vbits(&out.positions), vbits(&one.positions));
        assert_eq!(out.contacts, one.contacts);
    }

    #[test]
    fn bad_rates_and_tracks_are_errors() {
        let poses = motion(Format::Smpl24Rot6d, 3);
        for (from, to) in [
            (0.0, 30.0),
            (20.0, f64::INFINITY),
            (20.0, f64::NAN),
            (-20.0, 30.0),
        ] {
            let e = resample(&poses, from, to).unwrap_err().to_string();
            assert!(e.contains("frame rate must be a positive number"), "{e}");
        }
        // 3 frames at 1e-300 fps span 2e300 s: far more frames than allowed, caught before
        // any arithmetic overflows.
        let e = resample(&poses, 1e-300, 240.0).unwrap_err().to_string();
        assert!(e.contains("more than the 1048576 frames allowed"), "{e}");
        let mut bad = poses.clone();
        bad.root_bone = vec![[0.0; 3]; 2];
        let e = resample(&bad, 20.0, 30.0).unwrap_err().to_string();
        assert!(
            e.contains("root bone track has 2 entries for 3 frames"),
            "{e}"
        );
        // 5000 frames at 1 fps → 240 fps: 4999·240 + 1 = 1 199 761 frames > 2²⁰.
        let long = Poses::empty(Format::Smpl24Rot6d, 5000);
        let e = resample(&long, 1.0, 240.0).unwrap_err().to_string();
        assert!(e.contains("would become 1199761 frames"), "{e}");
    }
}
