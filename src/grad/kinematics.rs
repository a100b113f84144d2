//! Joint positions of a motion format from de-normalised features (`f64`, the format's native
//! frame), exactly as [`crate::motion::Poses::decode`] computes them, and their vector-Jacobian
//! product: the last link of a guidance loss on positions.
//!
//! - `humanml263`: the official `recover_from_ric`. θ is the exclusive cumulative sum of channel
//!   0 and the root rotation `R(θ)` (world → facing frame) is a yaw by 2θ; the planar velocity
//!   (channels 1, 2) of frame t−1, turned into the world by `R(θ_t)ᵀ`, is accumulated; the height
//!   is channel 3; joints 1..21 are channels 4..67 in the facing frame, turned by `R(θ_t)ᵀ` and
//!   offset by the root's x and z. Channels 67.. do not move the joints (their gradient is 0).
//!   The backward runs the two cumulative sums in reverse as suffix sums, O(frames).
//! - `smpl24_6d`: root translation (channels 0..3) plus 24 local rotations in pytorch3d's 6D ROW
//!   convention (Gram–Schmidt), SMPL forward kinematics on the neutral rest skeleton. The
//!   backward walks the hierarchy from the leaves (children before parents) and then through the
//!   Gram–Schmidt of every joint.

use crate::error::{invalid_arg, Result};
use crate::motion::humanml263::{ric_positions, root_track};
use crate::motion::rotation::{self, Mat3, Vec3};
use crate::motion::skeleton::forward_kinematics;
use crate::motion::Format;

/// First channel of humanml263's root-relative joint positions.
const RIC: usize = 4;

/// `[frames × joints]` joint positions (frame-major) of `frames` rows of de-normalised `format`
/// features, into `out` (resized). Equal to what `Poses::decode` gives without smoothing.
pub fn positions(format: Format, x: &[f64], frames: usize, out: &mut Vec<Vec3>) -> Result<()> {
    let dim = check_features(format, x, frames)?;
    let joints = format.skeleton().joint_count();
    out.clear();
    out.resize(frames * joints, [0.0; 3]);
    match format {
        Format::HumanMl263 => {
            let (r_root, root) = root_track(x, dim);
            for (t, (row, p)) in x
                .chunks_exact(dim)
                .zip(out.chunks_exact_mut(joints))
                .enumerate()
            {
                ric_positions(row, &r_root[t], &root[t], p);
            }
        }
        Format::Smpl24Rot6d => {
            let mut world = vec![rotation::IDENTITY; joints];
            for (row, p) in x.chunks_exact(dim).zip(out.chunks_exact_mut(joints)) {
                smpl_frame(row, p, &mut world)?;
            }
        }
    }
    Ok(())
}

/// `d_x = (∂positions/∂x)ᵀ · d_pos`: the gradient with respect to the features of a loss whose
/// gradient with respect to [`positions`] is `d_pos` (`[frames × joints]`). `d_x` (`frames ×
/// feature_dim`) is overwritten.
pub fn positions_vjp(
    format: Format,
    x: &[f64],
    frames: usize,
    d_pos: &[Vec3],
    d_x: &mut [f64],
) -> Result<()> {
    let dim = check_features(format, x, frames)?;
    let joints = format.skeleton().joint_count();
    if d_pos.len() != frames * joints {
        return Err(invalid_arg!(
            "position gradient holds {} joints; {frames} frames of {format} have {}",
            d_pos.len(),
            frames * joints
        ));
    }
    if let Some(i) = d_pos.iter().position(|p| p.iter().any(|v| !v.is_finite())) {
        return Err(invalid_arg!(
            "position gradient is not finite at frame {}, joint {}",
            i / joints,
            i % joints
        ));
    }
    if d_x.len() != x.len() {
        return Err(invalid_arg!(
            "feature gradient holds {} values; the features hold {}",
            d_x.len(),
            x.len()
        ));
    }
    d_x.fill(0.0);
    match format {
        Format::HumanMl263 => humanml_vjp(x, frames, dim, joints, d_pos, d_x),
        Format::Smpl24Rot6d => {
            for ((row, dp), dx) in x
                .chunks_exact(dim)
                .zip(d_pos.chunks_exact(joints))
                .zip(d_x.chunks_exact_mut(dim))
            {
                smpl_frame_vjp(row, dp, dx)?;
            }
        }
    }
    Ok(())
}

/// The feature width after checking `x` holds `frames ≥ 1` finite rows of `format`.
fn check_features(format: Format, x: &[f64], frames: usize) -> Result<usize> {
    let dim = format.feature_dim();
    if frames == 0 {
        return Err(invalid_arg!(
            "positions of {format} need at least one frame"
        ));
    }
    let want = frames
        .checked_mul(dim)
        .ok_or_else(|| invalid_arg!("{frames} frames of {format} features overflow"))?;
    if x.len() != want {
        return Err(invalid_arg!(
            "features hold {} values; {frames} frames of {format} need {want} ({frames} x {dim})",
            x.len()
        ));
    }
    if let Some(i) = x.iter().position(|v| !v.is_finite()) {
        return Err(invalid_arg!(
            "features are not finite at frame {}, channel {}",
            i / dim,
            i % dim
        ));
    }
    Ok(dim)
}

/// The backward of `recover_from_ric`. With φ_t = 2θ_t and `W_t = R(θ_t)ᵀ` (a yaw by −φ_t),
/// `∂(W_t p)/∂φ_t = (−(W_t p)_z, 0, (W_t p)_x)`; the root's x, z at frame t sum the rotated
/// velocities of frames 1..=t, so each velocity's gradient is a suffix sum of the root
/// gradients, and channel 0 of frame s reaches every θ_t with t > s: another suffix sum.
fn humanml_vjp(
    x: &[f64],
    frames: usize,
    dim: usize,
    joints: usize,
    d_pos: &[Vec3],
    d_x: &mut [f64],
) {
    let (r_root, _) = root_track(x, dim);
    let mut d_phi = vec![0.0f64; frames];
    // ∂L/∂(root x, root z) of every frame: the root joint's and every joint's (they add it).
    let mut d_root = vec![[0.0f64; 2]; frames];
    for t in 0..frames {
        let to_world = rotation::transpose(&r_root[t]);
        let (row, dp) = (
            &x[t * dim..(t + 1) * dim],
            &d_pos[t * joints..(t + 1) * joints],
        );
        let drow = &mut d_x[t * dim..(t + 1) * dim];
        let mut g = [dp[0][0], dp[0][2]];
        drow[3] = dp[0][1];
        for (j, d) in dp.iter().enumerate().skip(1) {
            let c = RIC + 3 * (j - 1);
            g[0] += d[0];
            g[1] += d[2];
            let w = rotation::apply(&to_world, &[row[c], row[c + 1], row[c + 2]]);
            d_phi[t] += d[2] * w[0] - d[0] * w[2];
            drow[c..c + 3].copy_from_slice(&rotation::apply(&r_root[t], d));
        }
        d_root[t] = g;
    }
    let mut suffix = [0.0f64; 2];
    for s in (1..frames).rev() {
        suffix[0] += d_root[s][0];
        suffix[1] += d_root[s][1];
        let prev = (s - 1) * dim;
        let to_world = rotation::transpose(&r_root[s]);
        let v = rotation::apply(&to_world, &[x[prev + 1], 0.0, x[prev + 2]]);
        d_phi[s] += suffix[1] * v[0] - suffix[0] * v[2];
        let du = rotation::apply(&r_root[s], &[suffix[0], 0.0, suffix[1]]);
        d_x[prev + 1] = du[0];
        d_x[prev + 2] = du[2];
    }
    let mut later = 0.0;
    for s in (0..frames).rev() {
        d_x[s * dim] = later;
        later += 2.0 * d_phi[s];
    }
}

/// One smpl24_6d frame's local rotations.
fn smpl_locals(row: &[f64]) -> Vec<Mat3> {
    row[3..]
        .chunks_exact(6)
        .map(|d| rotation::from_6d_rows(&[d[0], d[1], d[2], d[3], d[4], d[5]]))
        .collect()
}

/// One smpl24_6d frame's positions (as `smpl24_6d::decode`: pelvis = translation + rest pelvis).
fn smpl_frame(row: &[f64], positions: &mut [Vec3], world: &mut [Mat3]) -> Result<()> {
    let skel = Format::Smpl24Rot6d.skeleton();
    let pelvis = rotation::add(&[row[0], row[1], row[2]], &skel.rest_offsets()[0]);
    forward_kinematics(
        skel.parents(),
        skel.rest_offsets(),
        &pelvis,
        &smpl_locals(row),
        positions,
        world,
    )
}

/// The backward of one frame's forward kinematics, `world(j) = world(p) · local(j)` and
/// `pos(j) = pos(p) + world(p) · offset(j)`, into `d_row` (the frame's 147 gradients).
fn smpl_frame_vjp(row: &[f64], d_pos: &[Vec3], d_row: &mut [f64]) -> Result<()> {
    let skel = Format::Smpl24Rot6d.skeleton();
    let n = skel.joint_count();
    let local = smpl_locals(row);
    let (mut pos, mut world) = (vec![[0.0; 3]; n], vec![rotation::IDENTITY; n]);
    smpl_frame(row, &mut pos, &mut world)?;
    let mut g_pos = d_pos.to_vec();
    let mut g_world = vec![[[0.0f64; 3]; 3]; n];
    let mut g_local = vec![[[0.0f64; 3]; 3]; n];
    // Children come after parents, so in reverse every joint's gradients are complete before
    // they are passed to its parent.
    for j in (1..n).rev() {
        let p = skel
            .parent(j)
            .expect("SMPL joints past the root have parents");
        let o = &skel.rest_offsets()[j];
        let gp = g_pos[j];
        let gw = g_world[j];
        let from_rotation = rotation::mul(&gw, &rotation::transpose(&local[j]));
        for r in 0..3 {
            g_pos[p][r] += gp[r];
            for c in 0..3 {
                g_world[p][r][c] += gp[r] * o[c] + from_rotation[r][c];
            }
        }
        g_local[j] = rotation::mul(&rotation::transpose(&world[p]), &gw);
    }
    g_local[0] = g_world[0];
    d_row[..3].copy_from_slice(&g_pos[0]);
    for ((d, g), out) in row[3..]
        .chunks_exact(6)
        .zip(&g_local)
        .zip(d_row[3..].chunks_exact_mut(6))
    {
        out.copy_from_slice(&from_6d_rows_vjp(&[d[0], d[1], d[2], d[3], d[4], d[5]], g));
    }
    Ok(())
}

/// The guard of `rotation::from_6d_rows`'s normalisation (torch's `F.normalize` eps).
const NORM_EPS: f64 = 1e-12;

/// The backward of `v / max(|v|, ε)` at `v` for an upstream gradient `g`: `(g − y (y·g)) / |v|`,
/// or `g / ε` where the guard is active (its clamp passes no gradient to the norm).
fn normalize_vjp(v: &Vec3, g: &Vec3) -> Vec3 {
    let norm = rotation::dot(v, v).sqrt();
    if norm <= NORM_EPS {
        return g.map(|x| x / NORM_EPS);
    }
    let y = v.map(|x| x / norm);
    let k = rotation::dot(&y, g);
    std::array::from_fn(|i| (g[i] - y[i] * k) / norm)
}

/// The backward of [`rotation::from_6d_rows`] (pytorch3d's Gram–Schmidt: `b1 = n(a1)`,
/// `b2 = n(a2 − (b1·a2) b1)`, `b3 = b1 × b2`, the rows of the matrix) for the gradient `g` of
/// the matrix.
fn from_6d_rows_vjp(d: &[f64; 6], g: &Mat3) -> [f64; 6] {
    let (a1, a2) = ([d[0], d[1], d[2]], [d[3], d[4], d[5]]);
    let b1 = a1.map(|x| x / rotation::dot(&a1, &a1).sqrt().max(NORM_EPS));
    let k = rotation::dot(&b1, &a2);
    let u: Vec3 = std::array::from_fn(|i| a2[i] - k * b1[i]);
    let b2 = u.map(|x| x / rotation::dot(&u, &u).sqrt().max(NORM_EPS));
    // b3 = b1 × b2: g3·(b1 × b2) = b1·(b2 × g3) = b2·(g3 × b1).
    let mut g_b1 = rotation::add(&g[0], &rotation::cross(&b2, &g[2]));
    let g_b2 = rotation::add(&g[1], &rotation::cross(&g[2], &b1));
    let g_u = normalize_vjp(&u, &g_b2);
    // u = a2 − k b1 with k = b1·a2.
    let g_k = -rotation::dot(&b1, &g_u);
    let g_a2: Vec3 = std::array::from_fn(|i| g_u[i] + g_k * b1[i]);
    for i in 0..3 {
        g_b1[i] += -k * g_u[i] + g_k * a2[i];
    }
    let g_a1 = normalize_vjp(&a1, &g_b1);
    [g_a1[0], g_a1[1], g_a1[2], g_a2[0], g_a2[1], g_a2[2]]
}
