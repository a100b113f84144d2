//! Analytic two-bone inverse kinematics (hip–knee–ankle, shoulder–elbow–wrist): the closed-form
//! solution of the triangle root–mid–end by the law of cosines, with the bend plane kept.
//!
//! Given the current chain `root → mid → end` (bone lengths `a = |mid − root|`,
//! `b = |end − mid|`) and a target for `end`, with the root fixed:
//!
//! - the reach `r = |target − root|` is clamped to `[|a − b|, REACH_LIMIT · (a + b)]`: just
//!   under full extension, where the knee's direction is ill-conditioned, and never shorter than
//!   the fully folded chain;
//! - the angle at the root between the root→target line `u` and the upper bone is
//!   `acos((a² + r² − b²) / (2 a r))` (the law of cosines), the cosine clamped to `[−1, 1]`;
//! - the **pole** (which side of `u` the mid joint goes) is the current mid joint's offset
//!   perpendicular to `u`, so the mid joint stays in the plane of root, target and its current
//!   position (the knee keeps pointing where it pointed). If the current mid joint lies on that
//!   line, the side it bends to relative to the current root→end line is used, and for a
//!   straight chain on the line, any perpendicular (there is no bend to keep);
//! - the upper bone's rotation maps the old (bone, bend normal) frame onto the new one, so the
//!   bend axis is carried along; the lower bone then turns about that bend axis only: relative to
//!   the upper bone the mid joint stays a hinge, with no twist added.
//!
//! The result is the world-space rotation delta of each bone, so a caller applies the same
//! deltas to world rotations (`global' = delta · global`) and to the bone vectors of a position
//! chain, and bone lengths are kept exactly (they are rotated, never rebuilt). Nothing here
//! knows about poses or skeletons; `feet` uses it for the legs, and rig retargeting can for arms.
//!
//! No input gives NaN: zero-length bones, a target on the root, a target out of reach and a
//! straight chain all have defined answers (documented on [`solve`]).

use super::rotation::{self, Mat3, Vec3};

/// The longest reach as a fraction of the chain's length `a + b`: 0.9999 leaves the mid joint
/// bent by ~1.6° at most, so its direction is still well defined (at 1 the pole has no effect
/// and rounding decides the bend), while a 0.8 m leg falls short of full stretch by 0.08 mm.
pub const REACH_LIMIT: f64 = 0.9999;

/// A two-bone solution.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TwoBone {
    /// World-space rotation of the upper bone (root → mid): `mid' − root = upper · (mid − root)`.
    pub upper: Mat3,
    /// World-space rotation of the lower bone (mid → end), absolute (it contains the upper
    /// bone's): `end' − mid' = lower · (end − mid)`. Whatever hangs below `end` and should keep its
    /// world orientation relative to the lower bone turns by `lower` too.
    pub lower: Mat3,
    /// The new mid joint position.
    pub mid: Vec3,
    /// The new end position (the target when it was reachable).
    pub end: Vec3,
    /// Whether `end` reaches the target (to 1e-9 of the chain's length).
    pub reached: bool,
}

/// Solves the chain `root → mid → end` for `end` to reach `target`, the root fixed and the bend
/// plane kept (module doc). Degenerate chains: if either bone has (relatively) zero length, the
/// chain turns rigidly about the root towards the target (`upper == lower`); if both have, the
/// identity. A target on the root keeps the current root→end direction and folds the chain as
/// far as it folds.
pub fn solve(root: &Vec3, mid: &Vec3, end: &Vec3, target: &Vec3) -> TwoBone {
    let t = sub(mid, root);
    let s = sub(end, mid);
    let (a, b) = (norm(&t), norm(&s));
    let scale = a + b;
    let tiny = 1e-12 * scale;
    let finish = |upper: Mat3, lower: Mat3| {
        let mid = rotation::add(root, &rotation::apply(&upper, &t));
        let end = rotation::add(&mid, &rotation::apply(&lower, &s));
        let reached = norm(&sub(&end, target)) <= 1e-9 * scale.max(f64::MIN_POSITIVE);
        TwoBone {
            upper,
            lower,
            mid,
            end,
            reached,
        }
    };
    if !(scale > 0.0 && scale.is_finite()) {
        return finish(rotation::IDENTITY, rotation::IDENTITY);
    }
    if a <= tiny || b <= tiny {
        // One bone: turn the whole chain about the root.
        let r = rotate_onto(&sub(end, root), &sub(target, root), None);
        return finish(r, r);
    }
    let d = sub(target, root);
    let dl = norm(&d);
    let u = if dl > tiny {
        scaled(&d, 1.0 / dl)
    } else {
        let e = sub(end, root);
        let el = norm(&e);
        if el > tiny {
            scaled(&e, 1.0 / el)
        } else {
            scaled(&t, 1.0 / a)
        }
    };
    let r = dl.min(REACH_LIMIT * scale).max((a - b).abs()).max(tiny);
    let cos = ((a * a + r * r - b * b) / (2.0 * a * r)).clamp(-1.0, 1.0);
    let sin = (1.0 - cos * cos).sqrt();
    let pole = perpendicular(&t, &u)
        .or_else(|| {
            let e = sub(end, root);
            perpendicular(&t, &e).and_then(|side| perpendicular(&side, &u))
        })
        .unwrap_or_else(|| any_perpendicular(&u));
    // The new upper bone, in the plane of u and the pole, on the pole's side.
    let t_new = [
        a * (cos * u[0] + sin * pole[0]),
        a * (cos * u[1] + sin * pole[1]),
        a * (cos * u[2] + sin * pole[2]),
    ];
    let s_new = sub(&scaled(&u, r), &t_new);
    // The new bend plane's normal: t_new × s_new = r·a·sin·(pole × u).
    let n_new = rotation::cross(&pole, &u);
    let n_old = rotation::cross(&t, &s);
    let upper = if norm(&n_old) > 1e-9 * a * b {
        frame_onto(&t, &n_old, &t_new, &n_new)
    } else {
        // A straight chain has no bend plane to carry.
        rotate_onto(&t, &t_new, Some(&n_new))
    };
    let turned = rotation::apply(&upper, &s);
    // Both `turned` and `s_new` are perpendicular to n_new: a hinge turn about it.
    let angle = rotation::dot(&rotation::cross(&turned, &s_new), &n_new)
        .atan2(rotation::dot(&turned, &s_new));
    let lower = rotation::mul(&rotation::axis_angle(&n_new, angle), &upper);
    finish(upper, lower)
}

/// The smallest rotation turning the direction of `from` onto that of `to`; the identity if
/// either is (nearly) zero. Opposite directions turn by π about `axis` made perpendicular to
/// `from` (or any perpendicular when `axis` is `None` or parallel).
pub fn rotate_onto(from: &Vec3, to: &Vec3, axis: Option<&Vec3>) -> Mat3 {
    let (fl, tl) = (norm(from), norm(to));
    if !(fl > 1e-300 && tl > 1e-300) {
        return rotation::IDENTITY;
    }
    let (f, t) = (scaled(from, 1.0 / fl), scaled(to, 1.0 / tl));
    let c = rotation::cross(&f, &t);
    let (sin, cos) = (norm(&c), rotation::dot(&f, &t));
    if sin > 1e-12 {
        return rotation::axis_angle(&c, sin.atan2(cos));
    }
    if cos > 0.0 {
        return rotation::IDENTITY;
    }
    let ax = axis
        .and_then(|a| perpendicular(a, &f))
        .unwrap_or_else(|| any_perpendicular(&f));
    rotation::axis_angle(&ax, std::f64::consts::PI)
}

/// The rotation taking the orthonormal frame built on (`a`, `n` made perpendicular to `a`) onto
/// the one built on (`a2`, `n2` likewise); `a`, `a2` non-zero and `n`, `n2` not parallel to them.
fn frame_onto(a: &Vec3, n: &Vec3, a2: &Vec3, n2: &Vec3) -> Mat3 {
    let basis = |x: &Vec3, y: &Vec3| -> Mat3 {
        let x = scaled(x, 1.0 / norm(x));
        let y = perpendicular(y, &x).unwrap_or_else(|| any_perpendicular(&x));
        let z = rotation::cross(&x, &y);
        // Columns x, y, z.
        [[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]]
    };
    let old = basis(a, n);
    let new = basis(a2, n2);
    rotation::mul(&new, &rotation::transpose(&old))
}

/// The unit component of `v` perpendicular to the unit-or-not direction `u`, `None` when `v` is
/// (relatively) parallel to `u` or zero.
fn perpendicular(v: &Vec3, u: &Vec3) -> Option<Vec3> {
    let ul = norm(u);
    let vl = norm(v);
    if !(ul > 0.0 && vl > 0.0) {
        return None;
    }
    let k = rotation::dot(v, u) / (ul * ul);
    let p = [v[0] - k * u[0], v[1] - k * u[1], v[2] - k * u[2]];
    let pl = norm(&p);
    (pl > 1e-9 * vl).then(|| scaled(&p, 1.0 / pl))
}

/// A unit vector perpendicular to the non-zero `u`: `u` crossed with the axis it is least
/// aligned with.
fn any_perpendicular(u: &Vec3) -> Vec3 {
    let k = (0..3)
        .min_by(|&i, &j| u[i].abs().total_cmp(&u[j].abs()))
        .unwrap_or(0);
    let mut e = [0.0; 3];
    e[k] = 1.0;
    let c = rotation::cross(u, &e);
    let cl = norm(&c);
    if cl > 0.0 {
        scaled(&c, 1.0 / cl)
    } else {
        [1.0, 0.0, 0.0]
    }
}

fn sub(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn scaled(v: &Vec3, k: f64) -> Vec3 {
    [v[0] * k, v[1] * k, v[2] * k]
}

fn norm(v: &Vec3) -> f64 {
    rotation::dot(v, v).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    const H: f64 = std::f64::consts::FRAC_1_SQRT_2;

    fn close(a: &Vec3, b: &Vec3, tol: f64) -> bool {
        (0..3).all(|k| (a[k] - b[k]).abs() <= tol)
    }

    fn dist(a: &Vec3, b: &Vec3) -> f64 {
        norm(&sub(a, b))
    }

    /// Every solution's invariants: finite, proper rotations, bones rotated to the returned
    /// joints, bone lengths kept to 1e-12, and the mid joint a hinge (upperᵀ·lower turns about
    /// the bend normal the upper bone carries).
    fn check(root: &Vec3, mid: &Vec3, end: &Vec3, sol: &TwoBone) {
        for m in [sol.upper, sol.lower] {
            assert!(m.iter().flatten().all(|x| x.is_finite()), "{sol:?}");
            assert!((rotation::det(&m) - 1.0).abs() < 1e-12);
            let mmt = rotation::mul(&m, &rotation::transpose(&m));
            for (r, row) in mmt.iter().enumerate() {
                for (c, x) in row.iter().enumerate() {
                    let want = if r == c { 1.0 } else { 0.0 };
                    assert!((x - want).abs() < 1e-12);
                }
            }
        }
        let (a, b) = (dist(mid, root), dist(end, mid));
        assert!((dist(&sol.mid, root) - a).abs() < 1e-12, "{sol:?}");
        assert!((dist(&sol.end, &sol.mid) - b).abs() < 1e-12, "{sol:?}");
        let t2 = rotation::apply(&sol.upper, &sub(mid, root));
        assert!(close(&rotation::add(root, &t2), &sol.mid, 1e-12));
        let s2 = rotation::apply(&sol.lower, &sub(end, mid));
        assert!(close(&rotation::add(&sol.mid, &s2), &sol.end, 1e-12));
        let n = rotation::cross(&sub(mid, root), &sub(end, mid));
        if norm(&n) > 1e-6 {
            let rel = rotation::mul(&rotation::transpose(&sol.upper), &sol.lower);
            assert!(close(&rotation::apply(&rel, &n), &n, 1e-12), "knee twisted");
        }
    }

    #[test]
    fn right_angle_leg_turned_rigidly() {
        // Hip at 0, knee (1, 0, 0), ankle (1, 1, 0): a right angle at the knee, reach √2. The
        // target (0, √2, 0) is the ankle turned +45° about Z, at the same reach, and the knee's
        // side (+X of the Y line) is kept: the solution is the whole leg turned +45° about Z,
        // knee at (√½, √½, 0).
        let (root, mid, end) = ([0.0; 3], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]);
        let target = [0.0, 2f64.sqrt(), 0.0];
        let sol = solve(&root, &mid, &end, &target);
        check(&root, &mid, &end, &sol);
        assert!(sol.reached);
        assert!(close(&sol.mid, &[H, H, 0.0], 1e-12), "{:?}", sol.mid);
        assert!(close(&sol.end, &target, 1e-12));
        let rz = rotation::axis_angle(&[0.0, 0.0, 1.0], std::f64::consts::FRAC_PI_4);
        for m in [sol.upper, sol.lower] {
            for r in 0..3 {
                assert!(close(&m[r], &rz[r], 1e-12), "{m:?}");
            }
        }
    }

    #[test]
    fn reachable_target_bends_by_the_law_of_cosines() {
        // Same leg, target (0, 1, 0) at reach 1 = a = b: an equilateral triangle, so the thigh
        // leaves the root→target line at 60° on the knee's side: knee (sin 60°, cos 60°, 0).
        let (root, mid, end) = ([0.0; 3], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]);
        let target = [0.0, 1.0, 0.0];
        let sol = solve(&root, &mid, &end, &target);
        check(&root, &mid, &end, &sol);
        assert!(sol.reached);
        assert!(
            close(&sol.mid, &[3f64.sqrt() / 2.0, 0.5, 0.0], 1e-12),
            "{:?}",
            sol.mid
        );
        assert!(close(&sol.end, &target, 1e-12));
    }

    #[test]
    fn unreachable_target_stops_just_short_along_the_line() {
        let (root, mid, end) = ([0.0; 3], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]);
        let target = [0.0, 3.0, 0.0];
        let sol = solve(&root, &mid, &end, &target);
        check(&root, &mid, &end, &sol);
        assert!(!sol.reached);
        // End at REACH_LIMIT · 2 along +Y, knee still on the +X side.
        assert!(
            close(&sol.end, &[0.0, 2.0 * REACH_LIMIT, 0.0], 1e-12),
            "{:?}",
            sol.end
        );
        assert!(sol.mid[0] > 0.0 && sol.mid[0] < 0.03);
        // Too close: folded as far as a ≠ b allow, end at |a − b| from the root.
        let (mid2, end2) = ([0.0, -0.5, 0.0], [0.3, -0.5, 0.0]);
        let sol = solve(&root, &mid2, &end2, &[0.0, -0.01, 0.0]);
        check(&root, &mid2, &end2, &sol);
        assert!(!sol.reached);
        assert!((dist(&sol.end, &root) - 0.2).abs() < 1e-12);
    }

    #[test]
    fn full_stretch_zero_target_and_colinear_pole_give_no_nan() {
        // A straight leg down, target at its end (full stretch, knee on the line: no pole).
        let (root, mid, end) = ([0.0; 3], [0.0, -1.0, 0.0], [0.0, -2.0, 0.0]);
        for target in [
            end,
            [0.0, -3.0, 0.0],
            root,
            [0.0, 1.0, 0.0],
            [0.5, -1.0, 0.2],
        ] {
            let sol = solve(&root, &mid, &end, &target);
            check(&root, &mid, &end, &sol);
        }
        let sol = solve(&root, &mid, &end, &end);
        assert!(dist(&sol.end, &end) < 2.0 * 2.0 * (1.0 - REACH_LIMIT));
        // A bent leg whose knee lies on the root→target line: the side it bends to relative to
        // the current root→end line is used. The knee (0, −1) lies on the −X side of the line
        // to the ankle (1, −1), so with the ankle brought under the hip the knee goes to −X
        // (the bend normal +Z is kept).
        let (mid, end) = ([0.0, -1.0, 0.0], [1.0, -1.0, 0.0]);
        let sol = solve(&root, &mid, &end, &[0.0, -1.2, 0.0]);
        check(&root, &mid, &end, &sol);
        assert!(sol.reached && sol.mid[0] < -0.1, "{sol:?}");
        // Target on the root with equal bones: folded completely, no NaN.
        let sol = solve(&root, &[0.0, -1.0, 0.0], &[1.0, -1.0, 0.0], &root);
        check(&root, &[0.0, -1.0, 0.0], &[1.0, -1.0, 0.0], &sol);
        assert!(dist(&sol.end, &root) < 1e-9);
    }

    #[test]
    fn degenerate_chains_turn_rigidly_or_not_at_all() {
        let root = [0.0; 3];
        // Zero-length lower bone: the upper bone points at the target.
        let sol = solve(
            &root,
            &[0.0, -1.0, 0.0],
            &[0.0, -1.0, 0.0],
            &[1.0, 0.0, 0.0],
        );
        assert!(close(&sol.mid, &[1.0, 0.0, 0.0], 1e-12) && sol.upper == sol.lower);
        // Everything at one point.
        let sol = solve(&root, &root, &root, &[1.0, 0.0, 0.0]);
        assert_eq!(sol.upper, rotation::IDENTITY);
        assert!(!sol.reached);
        assert_eq!(
            rotate_onto(&[1.0, 0.0, 0.0], &[0.0; 3], None),
            rotation::IDENTITY
        );
        let flip = rotate_onto(&[1.0, 0.0, 0.0], &[-2.0, 0.0, 0.0], Some(&[1.0, 0.0, 1.0]));
        assert!(close(
            &rotation::apply(&flip, &[1.0, 0.0, 0.0]),
            &[-1.0, 0.0, 0.0],
            1e-12
        ));
        // The π turn is about the axis hint made perpendicular (Z), so Y goes to −Y.
        assert!(close(
            &rotation::apply(&flip, &[0.0, 1.0, 0.0]),
            &[0.0, -1.0, 0.0],
            1e-12
        ));
    }

    #[test]
    fn pole_side_and_bend_sense_are_kept_in_3d() {
        // A leg in general position (thigh 0.4, shin 0.42), targets around the ankle.
        let root = [0.1, 0.9, -0.05];
        let mid = [0.15, 0.52, 0.08];
        let end = [0.12, 0.13, -0.02];
        let n_old = rotation::cross(&sub(&mid, &root), &sub(&end, &mid));
        for target in [
            [0.12, 0.13, -0.02],
            [0.2, 0.2, 0.1],
            [0.0, 0.25, -0.2],
            [0.3, 0.2, 0.05],
            [0.1, 0.5, 0.0],
        ] {
            let sol = solve(&root, &mid, &end, &target);
            check(&root, &mid, &end, &sol);
            assert!(sol.reached, "{target:?}");
            assert!(close(&sol.end, &target, 1e-12));
            // The knee stays on the side of the root→target line where it was.
            let u = sub(&target, &root);
            let side = perpendicular(&sub(&mid, &root), &u).unwrap();
            let new_side = perpendicular(&sub(&sol.mid, &root), &u).unwrap();
            assert!(rotation::dot(&side, &new_side) > 1.0 - 1e-9, "{target:?}");
            // The knee bends the same way: the new bend normal is the old one carried by the
            // thigh's rotation.
            let n_new = rotation::cross(&sub(&sol.mid, &root), &sub(&sol.end, &sol.mid));
            assert!(rotation::dot(&rotation::apply(&sol.upper, &n_old), &n_new) > 0.0);
        }
        // Target at the current ankle: nothing moves.
        let sol = solve(&root, &mid, &end, &end);
        assert!(close(&sol.mid, &mid, 1e-12), "{sol:?}");
    }
}
