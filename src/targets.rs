//! Joint-position targets: pin joints at chosen frames and steer the sampler toward them with
//! the gradient of `L = Σ_{frame, joint} ‖(P(x̂) − c) ⊙ m‖₂` (MoLA's MPGD: sony/MoLA
//! `models/mola_module.py`; docs/official/mola-mld.md#mola-mpgd-editing), where
//! `P` decodes the clean-motion estimate x̂ (a latent family's decoder first), de-normalises it
//! and runs the motion format's forward kinematics; the products are in [`crate::grad`].
//!
//! The rule per sampler (the session applies it, see [`TargetParams`]):
//! - diffusion: after the step's x̂0 (guided, clamped, masked values kept), x̂0 moves down the
//!   gradient and the step continues from it; DDIM keeps the step's ORIGINAL ε (MPGD), DDPM
//!   takes the posterior mean at the moved x̂0 and at the x_t that it and ε make. The mask's
//!   kept values are imposed again afterwards.
//! - flow matching: the velocity's implied end point `x̂1 = x + (1 − t)·v` is moved the same
//!   way, i.e. `v ← v + δ/(1 − t)` for the move δ of x̂1.
//!
//! How far it moves (`pull`): latent families take MoLA's one plain step `−ρ·∇L`;
//! motion-space families up to 100 backtracking gradient steps of at most ρ each. Values an
//! editing mask keeps never move.
//!
//! `ρ = s·w(τ)` with τ the noise level (diffusion: `timestep / num_timesteps`; flow: `1 − t`):
//! [`TargetSchedule::Mpgd`] `w = 4·τ·(1 − τ)` (MoLA's `4·s·t·(1000 − t)/1000²`), or
//! [`TargetSchedule::Constant`] `w = 1`.
//!
//! [`TargetParams`]: crate::targets::TargetParams
//! [`TargetSchedule::Mpgd`]: crate::targets::TargetSchedule::Mpgd
//! [`TargetSchedule::Constant`]: crate::targets::TargetSchedule::Constant

use std::str::FromStr;

use crate::error::{invalid_arg, Error, Result};
use crate::grad;
use crate::models::{Model, Workspace};
use crate::motion::convention::{Change, Convention};
use crate::motion::format::Format;
use crate::motion::mask::Task;
use crate::motion::rotation::Vec3;

/// The largest target scale a session accepts.
pub const MAX_TARGET_SCALE: f32 = 100.0;

/// How the guidance weight changes with the noise level τ ∈ [0, 1].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TargetSchedule {
    /// `4·τ·(1 − τ)`: nothing at either end, full strength half way (MoLA's MPGD).
    #[default]
    Mpgd,
    /// The same weight at every step.
    Constant,
}

impl TargetSchedule {
    /// Every schedule; the index of each is its value in the C ABI (`FlameTargetSchedule`).
    pub const ALL: [TargetSchedule; 2] = [TargetSchedule::Mpgd, TargetSchedule::Constant];

    /// The name `FromStr` and the CLI's `--target-schedule` take (`mpgd`, `constant`).
    pub fn name(self) -> &'static str {
        match self {
            TargetSchedule::Mpgd => "mpgd",
            TargetSchedule::Constant => "constant",
        }
    }

    /// The schedule of C ABI value `v` (its index in [`TargetSchedule::ALL`]); an error for any
    /// other value.
    pub fn from_u32(v: u32) -> Result<TargetSchedule> {
        TargetSchedule::ALL.get(v as usize).copied().ok_or_else(|| {
            invalid_arg!("unknown target schedule {v} (expected 0 mpgd or 1 constant)")
        })
    }

    /// The weight at noise level `tau`.
    pub fn weight(self, tau: f64) -> f64 {
        match self {
            TargetSchedule::Mpgd => 4.0 * tau * (1.0 - tau),
            TargetSchedule::Constant => 1.0,
        }
    }
}

impl FromStr for TargetSchedule {
    type Err = Error;
    fn from_str(s: &str) -> Result<TargetSchedule> {
        TargetSchedule::ALL
            .into_iter()
            .find(|k| k.name() == s)
            .ok_or_else(|| {
                invalid_arg!("unknown target schedule `{s}` (expected mpgd or constant)")
            })
    }
}

/// How strongly targets steer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TargetParams {
    /// `s` in `ρ = s·w(τ)`, in [0, [`MAX_TARGET_SCALE`]]; 0 turns the guidance off.
    pub scale: f32,
    /// How the weight `w(τ)` follows the noise level.
    pub schedule: TargetSchedule,
}

impl Default for TargetParams {
    /// MoLA's default edit scale 0.6 with its schedule.
    fn default() -> TargetParams {
        TargetParams {
            scale: 0.6,
            schedule: TargetSchedule::Mpgd,
        }
    }
}

impl TargetParams {
    /// What a session of `model` starts with: scale 0.6 and, for latent families, MoLA's MPGD
    /// schedule; motion-space families (FLAME, MDM, Motion Flow Matching) take the constant
    /// schedule, since their network re-predicts the estimate at every step and a pull that
    /// fades out by the last steps is mostly undone (demo numbers in docs/targets.md).
    pub fn for_model(model: &Model) -> TargetParams {
        TargetParams {
            scale: 0.6,
            schedule: if model.is_latent() {
                TargetSchedule::Mpgd
            } else {
                TargetSchedule::Constant
            },
        }
    }

    /// An error unless `scale` is finite and within [0, [`MAX_TARGET_SCALE`]].
    pub fn validate(&self) -> Result<()> {
        if !(self.scale.is_finite() && (0.0..=MAX_TARGET_SCALE).contains(&self.scale)) {
            return Err(invalid_arg!(
                "target scale must be a finite number from 0 to {MAX_TARGET_SCALE}, got {}",
                self.scale
            ));
        }
        Ok(())
    }

    /// ρ at noise level `tau`.
    pub fn rho(&self, tau: f64) -> f64 {
        self.scale as f64 * self.schedule.weight(tau.clamp(0.0, 1.0))
    }
}

/// Joint positions to steer toward, in the motion format's native frame (metres), with one
/// weight (0 or 1) per coordinate.
#[derive(Clone, Debug, PartialEq)]
pub struct PositionTargets {
    format: Format,
    frames: usize,
    target: Vec<Vec3>,
    weight: Vec<Vec3>,
}

impl PositionTargets {
    /// `targets`: `[frames × joints × 3]` positions in `convention` (its axes and unit), the
    /// joints of `format`'s skeleton. `mask`: one flag per value (nonzero = constrained), or
    /// `None`: every finite value is constrained and NaN leaves it free. A constrained value must
    /// be finite, and something must be constrained.
    pub fn new(
        format: Format,
        targets: &[f32],
        mask: Option<&[u8]>,
        convention: Convention,
    ) -> Result<PositionTargets> {
        let joints = format.skeleton().joint_count();
        let per_frame = joints * 3;
        if targets.is_empty() || !targets.len().is_multiple_of(per_frame) {
            return Err(invalid_arg!(
                "position targets hold {} values; expected frames x {joints} joints x 3 (a multiple of {per_frame}, at least one frame)",
                targets.len()
            ));
        }
        if let Some(m) = mask {
            if m.len() != targets.len() {
                return Err(invalid_arg!(
                    "the target mask has {} flags; the targets have {} values (one flag per value)",
                    m.len(),
                    targets.len()
                ));
            }
        }
        let constrained = |i: usize| match mask {
            Some(m) => m[i] != 0,
            None => !targets[i].is_nan(),
        };
        if let Some(i) = (0..targets.len()).find(|&i| constrained(i) && !targets[i].is_finite()) {
            return Err(invalid_arg!(
                "position target at frame {}, joint {}, axis {} is {} but constrained",
                i / per_frame,
                i % per_frame / 3,
                i % 3,
                targets[i]
            ));
        }
        if !(0..targets.len()).any(constrained) {
            return Err(invalid_arg!(
                "the position targets constrain nothing (every value is masked out or NaN)"
            ));
        }
        let change = Change::new(format, convention);
        let (mut target, mut weight) = (Vec::new(), Vec::new());
        for (j, p) in targets.chunks_exact(3).enumerate() {
            let w: Vec3 = std::array::from_fn(|a| constrained(3 * j + a) as u8 as f64);
            // A free coordinate's value does not matter; zero keeps the conversion finite.
            let v: Vec3 = std::array::from_fn(|a| if w[a] > 0.0 { p[a] as f64 } else { 0.0 });
            let native = change.inverse_position(&v);
            // A convention may permute axes: the weights follow the same permutation.
            let wn = change.inverse_position(&w).map(|x| (x != 0.0) as u8 as f64);
            target.push(native);
            weight.push(wn);
        }
        Ok(PositionTargets {
            format,
            frames: targets.len() / per_frame,
            target,
            weight,
        })
    }

    /// Targets taken from a reference motion's joint positions (`[frames × joints]`, native
    /// frame): joint j on frame f is constrained (all three coordinates) where
    /// `keep[f × joints + j]`.
    pub fn from_positions(
        format: Format,
        positions: &[Vec3],
        frames: usize,
        keep: &[bool],
    ) -> Result<PositionTargets> {
        let joints = format.skeleton().joint_count();
        if frames == 0 || positions.len() != frames * joints || keep.len() != positions.len() {
            return Err(invalid_arg!(
                "reference positions hold {} joints and {} keep flags; {frames} frames of {joints} joints expected",
                positions.len(),
                keep.len()
            ));
        }
        if let Some(i) =
            (0..positions.len()).find(|&i| keep[i] && !positions[i].iter().all(|v| v.is_finite()))
        {
            return Err(invalid_arg!(
                "reference position of joint {} at frame {} is not finite",
                i % joints,
                i / joints
            ));
        }
        if !keep.iter().any(|&k| k) {
            return Err(invalid_arg!("the position targets constrain nothing"));
        }
        Ok(PositionTargets {
            format,
            frames,
            target: positions.to_vec(),
            weight: keep.iter().map(|&k| [k as u8 as f64; 3]).collect(),
        })
    }

    /// [`PositionTargets::from_positions`] for an editing task, as MoLA's MPGD tasks: `path`
    /// the pelvis on every frame, `upper-body` the pelvis and legs on every frame, `inbetween`
    /// and `predict` every joint on the frames the task's keep-mask keeps.
    pub fn from_task(
        format: Format,
        positions: &[Vec3],
        frames: usize,
        task: Task,
    ) -> Result<PositionTargets> {
        let joints = format.skeleton().joint_count();
        let dim = format.feature_dim();
        let mask = crate::motion::mask::Mask::for_task(format, frames, task)?;
        let lower = crate::motion::mask::lower_body_joints(format);
        let mut keep = Vec::with_capacity(frames * joints);
        for flags in mask.flags().chunks_exact(dim) {
            let frame_kept = flags.iter().any(|&k| k);
            keep.extend((0..joints).map(|j| match task {
                Task::Path => j == 0,
                Task::UpperBody => lower.contains(&j),
                Task::Inbetween | Task::Predict => frame_kept,
            }));
        }
        PositionTargets::from_positions(format, positions, frames, &keep)
    }

    /// The target positions, `[frames × joints]`, in the format's native frame (metres).
    pub fn positions(&self) -> &[Vec3] {
        &self.target
    }

    /// One weight (0 or 1) per coordinate of [`PositionTargets::positions`].
    pub fn weights(&self) -> &[Vec3] {
        &self.weight
    }

    /// The motion format whose joints the targets are given for.
    pub fn format(&self) -> Format {
        self.format
    }

    /// Frames the targets cover (from the first frame of the motion).
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Number of constrained coordinates.
    pub fn constrained(&self) -> usize {
        self.weight.iter().flatten().filter(|&&w| w > 0.0).count()
    }

    /// The loss `L` on native joint positions `[frames × joints]`.
    pub fn loss(&self, positions: &[Vec3]) -> f64 {
        let mut g = vec![[0.0; 3]; self.target.len()];
        grad::l2_norm_sum_grad(
            &positions[..self.target.len()],
            &self.target,
            &self.weight,
            &mut g,
        )
    }
}

/// Scratch of [`gradient`], reused from step to step.
#[derive(Default)]
pub(crate) struct TargetScratch {
    x: Vec<f64>,
    pos: Vec<Vec3>,
    d_pos: Vec<Vec3>,
    d_x: Vec<f64>,
    ws: Workspace,
    /// `∇L` with respect to the sample, written by [`gradient`].
    grad: Vec<f32>,
    trial: Vec<f32>,
    moved: Vec<f32>,
}

/// `∇L` at `sample` (`[rows, sample_dim]`, the model's space) into `scratch.grad`; returns L.
fn gradient(
    model: &Model,
    targets: &PositionTargets,
    sample: &[f32],
    rows: usize,
    scratch: &mut TargetScratch,
) -> Result<f64> {
    let format = model.motion_format();
    let dim = format.feature_dim();
    let opts = model.read_options(0.0, true);
    let TargetScratch {
        x,
        pos,
        d_pos,
        d_x,
        ws,
        grad,
        ..
    } = scratch;
    let mut loss = 0.0;
    let mut of_features = |features: &[f32], frames: usize, d_features: &mut [f32]| -> Result<()> {
        let n = targets.frames;
        if n > frames {
            return Err(invalid_arg!(
                "position targets cover {n} frames; the motion has {frames}"
            ));
        }
        denormalized(&features[..n * dim], dim, &opts, x);
        grad::positions(format, x, n, pos)?;
        d_pos.clear();
        d_pos.resize(pos.len(), [0.0; 3]);
        loss = grad::l2_norm_sum_grad(pos, &targets.target, &targets.weight, d_pos);
        d_x.clear();
        d_x.resize(n * dim, 0.0);
        grad::positions_vjp(format, x, n, d_pos, d_x)?;
        if let Some(norm) = &opts.normalization {
            grad::denormalize_backward(d_x, norm.std)?;
        }
        d_features.fill(0.0);
        for (o, &g) in d_features.iter_mut().zip(d_x.iter()) {
            *o = g as f32;
        }
        Ok(())
    };
    match model.denoiser().decoder() {
        None => {
            grad.clear();
            grad.resize(sample.len(), 0.0);
            of_features(sample, rows, grad)?;
        }
        Some(decoder) => decoder.vjp(sample, rows, &mut of_features, grad, ws)?,
    }
    Ok(loss)
}

/// One guidance update at the estimate `x_hat` with step size `rho`: `x̂ ← x̂ − r·∇L(x̂)`, or
/// for a flow velocity `(v, 1 − t)`, `v ← v − r/(1 − t)·∇L(x̂)`. Latent families take MoLA's
/// plain step `r = ρ`; motion-space families halve `r` from ρ until the loss at the moved
/// estimate is no larger than at `x_hat` (their positions cost no network evaluation, and
/// humanml263's integrated root makes a plain step's size grow with the number of frames).
/// Values `kept` (an editing mask's) do not move: the mask keeps them, targets steer the rest.
/// Returns the loss at `x_hat`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn pull(
    model: &Model,
    targets: &PositionTargets,
    x_hat: &mut [f32],
    rows: usize,
    rho: f64,
    velocity: Option<(&mut [f32], f32)>,
    kept: Option<&[bool]>,
    scratch: &mut TargetScratch,
) -> Result<f64> {
    let freeze = |grad: &mut [f32]| {
        if let Some(kept) = kept {
            for (g, _) in grad.iter_mut().zip(kept).filter(|(_, &k)| k) {
                *g = 0.0;
            }
        }
    };
    let loss = gradient(model, targets, x_hat, rows, scratch)?;
    freeze(&mut scratch.grad);
    if model.denoiser().decoder().is_some() {
        // MoLA's MPGD: one plain step of size ρ.
        apply(x_hat, velocity, rho as f32, &scratch.grad);
        return Ok(loss);
    }
    // Motion-space families: up to MAX_ITERATIONS backtracking gradient steps on a copy of
    // the estimate (each step at most ρ, halved until the loss does not grow), then the
    // estimate (or the velocity) moved by the total.
    let mut moved = std::mem::take(&mut scratch.moved);
    let mut trial = std::mem::take(&mut scratch.trial);
    moved.clear();
    moved.extend_from_slice(x_hat);
    let mut current = loss;
    // The step size adapts: halved until the loss does not grow, doubled (up to 16·ρ) after a
    // step taken at once.
    let mut step = rho as f32;
    for iteration in 0..MAX_ITERATIONS {
        if iteration > 0 {
            current = gradient(model, targets, &moved, rows, scratch)?;
            freeze(&mut scratch.grad);
        }
        let mut r = step;
        let mut accepted = None;
        for halving in 0..=MAX_HALVINGS {
            trial.clear();
            trial.extend(moved.iter().zip(&scratch.grad).map(|(&x, &g)| x - r * g));
            let l = motion_loss(model, targets, &trial, scratch)?;
            if l <= current {
                accepted = Some(l);
                step = if halving == 0 {
                    (2.0 * r).min(16.0 * rho as f32)
                } else {
                    r
                };
                break;
            }
            r *= 0.5;
        }
        let Some(l) = accepted else { break };
        std::mem::swap(&mut moved, &mut trial);
        // Stop once an iteration gains less than 0.1% of the loss.
        if current - l <= 1e-3 * current {
            break;
        }
    }
    // The total move as a gradient-like direction of unit step: grad = x̂ − moved.
    for ((g, &x), &m) in scratch.grad.iter_mut().zip(x_hat.iter()).zip(&moved) {
        *g = x - m;
    }
    apply(x_hat, velocity, 1.0, &scratch.grad);
    scratch.moved = moved;
    scratch.trial = trial;
    Ok(loss)
}

/// `out ← out − r·g` on the estimate, or `v ← v − r/(1 − t)·g` on a flow velocity.
fn apply(x_hat: &mut [f32], velocity: Option<(&mut [f32], f32)>, r: f32, g: &[f32]) {
    let (out, r) = match velocity {
        Some((v, left)) => (v, r / left),
        None => (x_hat, r),
    };
    for (v, &g) in out.iter_mut().zip(g) {
        *v -= r * g;
    }
}

/// Gradient steps per guidance update of a motion-space family.
const MAX_ITERATIONS: usize = 100;

/// Halvings of the step size before a motion-space update gives up.
const MAX_HALVINGS: usize = 12;

/// `L` at motion features `x` (`[frames, feature_dim]`, model space).
fn motion_loss(
    model: &Model,
    targets: &PositionTargets,
    x: &[f32],
    scratch: &mut TargetScratch,
) -> Result<f64> {
    let format = model.motion_format();
    let dim = format.feature_dim();
    let n = targets.frames;
    let opts = model.read_options(0.0, true);
    let TargetScratch {
        x: xd, pos, d_pos, ..
    } = scratch;
    denormalized(&x[..n * dim], dim, &opts, xd);
    grad::positions(format, xd, n, pos)?;
    d_pos.clear();
    d_pos.resize(pos.len(), [0.0; 3]);
    Ok(grad::l2_norm_sum_grad(
        pos,
        &targets.target,
        &targets.weight,
        d_pos,
    ))
}

/// `x · std + mean` in f64 (or `x` for formats that are not normalised).
fn denormalized(x: &[f32], dim: usize, opts: &crate::motion::ReadOptions, out: &mut Vec<f64>) {
    out.clear();
    out.extend(x.iter().map(|&v| v as f64));
    if let Some(norm) = &opts.normalization {
        for row in out.chunks_exact_mut(dim) {
            for ((v, &m), &s) in row.iter_mut().zip(norm.mean).zip(norm.std) {
                *v = *v * s as f64 + m as f64;
            }
        }
    }
}

/// Whether `model` can be steered by position targets (motion-space families always; latent
/// ones when their decoder has a backward).
pub fn supported(model: &Model) -> Result<()> {
    match model.denoiser().decoder() {
        Some(d) if !d.has_vjp() => Err(invalid_arg!(
            "position targets need the gradient of this model's decoder ({}), which libflame does not implement{}",
            d.summary(),
            if model.denoiser().takes_control() {
                "; this file follows joint positions through its trajectory ControlNet instead \
                 (set_control, `flame generate --control`, `flame edit` with --method auto)"
            } else {
                ""
            }
        )),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::{GaussianRng, NoiseSource};

    fn model(name: &str) -> Model {
        Model::load(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("tests/fixtures")
                .join(name),
        )
        .unwrap()
    }

    /// The gradient's directional derivative equals central differences of the loss (f64
    /// loss on f32 samples: steps of 1e-3 along a random unit direction).
    #[test]
    fn gradient_matches_central_differences() {
        for (file, frames) in [
            ("mdm_tiny.safetensors", 12),
            ("flame_tiny.safetensors", 12),
            ("mola_tiny.safetensors", 12),
        ] {
            let m = model(file);
            let rows = m.sample_rows(frames);
            let n = rows * m.sample_dim();
            let mut rng = GaussianRng::new(3);
            let mut x = vec![0.0f32; n];
            rng.fill(&mut x);
            let mut dir = vec![0.0f32; n];
            rng.fill(&mut dir);
            let norm = dir.iter().map(|v| v * v).sum::<f32>().sqrt();
            dir.iter_mut().for_each(|v| *v /= norm);
            let joints = m.motion_format().skeleton().joint_count();
            let mut values = vec![0.0f32; frames * joints * 3];
            rng.fill(&mut values);
            let t =
                PositionTargets::new(m.motion_format(), &values, None, Convention::Native).unwrap();
            let mut s = TargetScratch::default();
            gradient(&m, &t, &x, rows, &mut s).unwrap();
            let analytic: f64 = s
                .grad
                .iter()
                .zip(&dir)
                .map(|(&g, &d)| g as f64 * d as f64)
                .sum();
            let h = 1e-3f32;
            let at = |sign: f32, s: &mut TargetScratch| {
                let y: Vec<f32> = x
                    .iter()
                    .zip(&dir)
                    .map(|(&a, &d)| a + sign * h * d)
                    .collect();
                gradient(&m, &t, &y, rows, s).unwrap()
            };
            let numeric = (at(1.0, &mut s) - at(-1.0, &mut s)) / (2.0 * h as f64);
            let rel = (analytic - numeric).abs() / numeric.abs().max(1e-3);
            assert!(
                rel < 2e-2,
                "{file}: analytic {analytic} vs numeric {numeric}"
            );
        }
    }
}
