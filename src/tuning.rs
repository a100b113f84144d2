//! Consistency latent tuning: MotionLCM v2's `--optimize` (Dai et al., ECCV 2024;
//! Dai-Wenxun/MotionLCM v2.0, `mld/models/modeltype/mld.py` `_optimize_latents`,
//! `mld/models/architectures/dno.py`, `configs/modules/noise_optimizer.yaml`).
//!
//! Before sampling, the initial latent z_T itself is optimised so that the motion the 1-step
//! sampler makes from it follows the control hint more closely. Each iteration runs the whole
//! generation forward — one consistency step (with the ControlNet), the VAE decoder, the joint
//! positions (`recover_from_ric`) — and back with libflame's own reverse-mode products
//! (`models::backward`, [`crate::grad`]). As the release does:
//! - loss = Σ m (J − H)² / Σ m over the hinted coordinates (`F.mse_loss`, `loss_hint_type
//!   l2`), plus 100 × the noise regulariser R(z) (`loss_correlate_penalty`; the distance to
//!   the first latent has penalty 0 and is left out);
//! - R(z) = Σ over token scales L, L/2, …, 4 of (mean(z ⊙ roll₁(z)))², the tokens averaged in
//!   pairs between scales (`DNO.noise_regularize_1d`, `dim=1`, `stop_at=2`);
//! - the gradient divided by its L2 norm (`clip_grad`), then one `torch.optim.Adam` step (β
//!   0.9, 0.999, ε 1e-8) at learning rate 0.1 × diffusers' cosine schedule with warm-up
//!   (`get_scheduler("cosine")`: linear from 0 over the warm-up, then half a cosine to 0). The
//!   release runs 400 iterations with 50 of warm-up; a shorter run keeps that proportion (one
//!   eighth).

use crate::diffusion::lcm::LcmSampler;
use crate::error::{invalid_arg, Error, Result};
use crate::grad;
use crate::models::{Cancel, Condition, Model, Workspace};
use crate::motion::rotation::Vec3;
use crate::targets::PositionTargets;

/// Adam's moment decays and ε (PyTorch's defaults, which the release uses).
const BETAS: (f64, f64) = (0.9, 0.999);
const ADAM_EPS: f64 = 1e-8;

/// How a tuning run optimises (the release's values by default).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TuningParams {
    /// Adam iterations (the release: 400).
    pub iterations: usize,
    /// Peak learning rate (0.1).
    pub learning_rate: f64,
    /// Warm-up iterations; `None` = one eighth of `iterations` (the release's 50 of 400).
    pub warmup: Option<usize>,
    /// Weight of the noise regulariser (100).
    pub correlate_penalty: f64,
}

impl TuningParams {
    /// The release's settings with `iterations` iterations.
    pub fn new(iterations: usize) -> TuningParams {
        TuningParams {
            iterations,
            learning_rate: 0.1,
            warmup: None,
            correlate_penalty: 100.0,
        }
    }

    fn warmup_iterations(&self) -> usize {
        self.warmup.unwrap_or(self.iterations / 8)
    }

    /// The learning rate of iteration `k` (0-based): diffusers' `get_cosine_schedule_with_warmup`
    /// (`num_cycles` 0.5) as `LambdaLR` applies it, the first step at factor λ(0) = 0 when
    /// there is a warm-up.
    pub fn learning_rate_at(&self, k: usize) -> f64 {
        let (n, w) = (self.iterations, self.warmup_iterations());
        let factor = if k < w {
            k as f64 / w.max(1) as f64
        } else {
            let progress = (k - w) as f64 / (n.saturating_sub(w)).max(1) as f64;
            (0.5 * (1.0 + (std::f64::consts::PI * progress).cos())).max(0.0)
        };
        self.learning_rate * factor
    }

    fn validate(&self) -> Result<()> {
        if self.iterations == 0 || self.iterations > MAX_ITERATIONS {
            return Err(invalid_arg!(
                "latent tuning runs 1 to {MAX_ITERATIONS} iterations, got {}",
                self.iterations
            ));
        }
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0) {
            return Err(invalid_arg!(
                "the tuning's learning rate must be finite and positive, got {}",
                self.learning_rate
            ));
        }
        if self.warmup.is_some_and(|w| w > self.iterations) {
            return Err(invalid_arg!(
                "the tuning's warm-up ({:?}) is longer than its {} iterations",
                self.warmup,
                self.iterations
            ));
        }
        if !(self.correlate_penalty.is_finite() && self.correlate_penalty >= 0.0) {
            return Err(invalid_arg!(
                "the noise regulariser's weight must be finite and non-negative, got {}",
                self.correlate_penalty
            ));
        }
        Ok(())
    }
}

/// More iterations than anyone runs (the release: 400), so a typo does not run for hours.
pub const MAX_ITERATIONS: usize = 100_000;

/// What a tuning run did.
#[derive(Clone, Debug, PartialEq)]
pub struct TuningReport {
    /// Iterations run.
    pub iterations: usize,
    /// The hint loss Σ m (J − H)²/Σ m (m²) at the first latent and at the tuned one.
    pub hint_loss: [f64; 2],
    /// The mean distance (m) of a hinted joint from its target at the first latent and at the
    /// tuned one (the release's `control_error`, over the hinted joints).
    pub control_error: [f64; 2],
    /// The whole loss (hint + the weighted regulariser) at every iteration's latent, before its
    /// update.
    pub losses: Vec<f64>,
}

/// What one evaluation of the chain gives.
struct Evaluation {
    hint_loss: f64,
    control_error: f64,
    loss: f64,
}

/// The inputs of a tuning run that stay fixed.
pub(crate) struct Problem<'a> {
    pub model: &'a Model,
    pub sampler: &'a LcmSampler,
    /// Rows of the sample (the latent's tokens).
    pub rows: usize,
    pub frames: usize,
    /// The embedded guidance `w`.
    pub w: f32,
    pub cond: &'a Condition,
    /// The encoded control (the trajectory encoder's output), when the network takes one.
    pub control: Option<&'a [f32]>,
    pub targets: &'a PositionTargets,
}

/// Buffers of one evaluation.
#[derive(Default)]
struct Scratch {
    eps: Vec<f32>,
    denoised: Vec<f32>,
    features: Vec<f32>,
    x: Vec<f64>,
    pos: Vec<Vec3>,
    d_pos: Vec<Vec3>,
    d_x: Vec<f64>,
    d_features: Vec<f32>,
    d_denoised: Vec<f32>,
    d_eps: Vec<f32>,
    d_net: Vec<f32>,
    net_tape: Workspace,
    vae_tape: Workspace,
}

impl Problem<'_> {
    /// Loss and its gradient at `z` (into `grad`, f64).
    fn evaluate(
        &self,
        z: &[f32],
        p: &TuningParams,
        s: &mut Scratch,
        grad_out: Option<&mut [f64]>,
    ) -> Result<Evaluation> {
        let model = self.model;
        let den = model.denoiser();
        let decoder = den.decoder().ok_or_else(|| {
            invalid_arg!("latent tuning needs a latent model (one with a decoder)")
        })?;
        let t = self.sampler.timesteps()[0];
        let n = z.len();
        s.eps.resize(n, 0.0);
        den.eps_recorded(
            z,
            self.rows,
            t as f32,
            self.w,
            self.cond,
            self.control,
            &mut s.eps,
            &mut s.net_tape,
        )?;
        s.denoised.resize(n, 0.0);
        self.sampler.denoise(0, &s.eps, z, &mut s.denoised);
        decoder.decode_recorded(
            &s.denoised,
            self.rows,
            self.frames,
            &mut s.features,
            &mut s.vae_tape,
        )?;
        let format = model.motion_format();
        let dim = format.feature_dim();
        let frames = self.targets.frames();
        let opts = model.read_options(0.0, true);
        s.x.clear();
        s.x.extend(s.features[..frames * dim].iter().map(|&v| v as f64));
        if let Some(norm) = &opts.normalization {
            for row in s.x.chunks_exact_mut(dim) {
                for ((v, &m), &sd) in row.iter_mut().zip(norm.mean).zip(norm.std) {
                    *v = *v * sd as f64 + m as f64;
                }
            }
        }
        grad::positions(format, &s.x, frames, &mut s.pos)?;
        let (target, weight) = (self.targets.positions(), self.targets.weights());
        let mask: f64 = weight.iter().flatten().sum();
        let (mut sq, mut dist, mut hinted) = (0.0, 0.0, 0.0);
        s.d_pos.clear();
        s.d_pos.resize(s.pos.len(), [0.0; 3]);
        for (((p, h), m), d) in s.pos.iter().zip(target).zip(weight).zip(s.d_pos.iter_mut()) {
            let r: [f64; 3] = std::array::from_fn(|k| (p[k] - h[k]) * m[k]);
            sq += r.iter().map(|v| v * v).sum::<f64>();
            *d = std::array::from_fn(|k| 2.0 * r[k] * m[k] / mask);
            if m.iter().any(|&v| v > 0.0) {
                dist += (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
                hinted += m.iter().sum::<f64>() / 3.0;
            }
        }
        let hint_loss = sq / mask;
        let control_error = dist / hinted.max(f64::MIN_POSITIVE);
        let c = den.sample_dim();
        let (reg, d_reg) = regulariser(z, self.rows, c)?;
        let loss = hint_loss + p.correlate_penalty * reg;
        let Some(g) = grad_out else {
            return Ok(Evaluation {
                hint_loss,
                control_error,
                loss,
            });
        };
        s.d_x.clear();
        s.d_x.resize(frames * dim, 0.0);
        grad::positions_vjp(format, &s.x, frames, &s.d_pos, &mut s.d_x)?;
        if let Some(norm) = &opts.normalization {
            grad::denormalize_backward(&mut s.d_x, norm.std)?;
        }
        s.d_features.clear();
        s.d_features.resize(s.features.len(), 0.0);
        for (o, &v) in s.d_features.iter_mut().zip(&s.d_x) {
            *o = v as f32;
        }
        s.d_denoised.resize(n, 0.0);
        decoder.decode_vjp(&s.d_features, &mut s.d_denoised, &mut s.vae_tape)?;
        // The consistency step is linear in (z, ε̂): denoised = a_z·z + a_ε·ε̂.
        let (a_z, a_eps) = self.sampler.denoise_coefficients(0);
        s.d_eps.clear();
        s.d_eps.extend(s.d_denoised.iter().map(|&v| a_eps * v));
        s.d_net.resize(n, 0.0);
        den.eps_vjp(&s.d_eps, &mut s.d_net, &mut s.net_tape)?;
        for (((o, &dd), &dn), &dr) in g.iter_mut().zip(&s.d_denoised).zip(&s.d_net).zip(&d_reg) {
            *o = a_z as f64 * dd as f64 + dn as f64 + p.correlate_penalty * dr;
        }
        Ok(Evaluation {
            hint_loss,
            control_error,
            loss,
        })
    }
}

/// The gradient at `z` of the loss (hint loss + the weighted regulariser), for tests that
/// compare it with PyTorch autograd: `(loss, gradient)`.
pub(crate) fn loss_gradient(
    problem: &Problem<'_>,
    z: &[f32],
    p: &TuningParams,
) -> Result<(f64, Vec<f64>)> {
    let mut s = Scratch::default();
    let mut g = vec![0.0; z.len()];
    let e = problem.evaluate(z, p, &mut s, Some(&mut g))?;
    Ok((e.loss, g))
}

/// Runs the tuning from `z` (replaced by the tuned latent), checking `cancel` before every
/// iteration.
pub(crate) fn tune(
    problem: &Problem<'_>,
    z: &mut [f32],
    p: &TuningParams,
    cancel: &Cancel,
) -> Result<TuningReport> {
    p.validate()?;
    if problem.sampler.len() != 1 {
        return Err(invalid_arg!(
            "latent tuning differentiates the 1-step sampler (the release's setting); this \
             session runs {} steps",
            problem.sampler.len()
        ));
    }
    let mut s = Scratch::default();
    let n = z.len();
    let mut current = z.to_vec();
    let (mut m, mut v) = (vec![0.0f64; n], vec![0.0f64; n]);
    let mut g = vec![0.0f64; n];
    let mut losses = Vec::with_capacity(p.iterations);
    let mut first = None;
    for k in 0..p.iterations {
        cancel.check()?;
        let e = problem.evaluate(&current, p, &mut s, Some(&mut g))?;
        if !e.loss.is_finite() || g.iter().any(|v| !v.is_finite()) {
            return Err(Error::NotFinite(format!(
                "latent tuning: the loss or its gradient is not finite at iteration {}",
                k + 1
            )));
        }
        first.get_or_insert((e.hint_loss, e.control_error));
        losses.push(e.loss);
        let norm = g.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm > 0.0 {
            g.iter_mut().for_each(|v| *v /= norm);
        }
        let step = (k + 1) as i32;
        let (bc1, bc2) = (1.0 - BETAS.0.powi(step), 1.0 - BETAS.1.powi(step));
        let lr = p.learning_rate_at(k);
        for (((x, &gi), mi), vi) in current.iter_mut().zip(&g).zip(&mut m).zip(&mut v) {
            *mi = BETAS.0 * *mi + (1.0 - BETAS.0) * gi;
            *vi = BETAS.1 * *vi + (1.0 - BETAS.1) * gi * gi;
            let denom = vi.sqrt() / bc2.sqrt() + ADAM_EPS;
            *x = (*x as f64 - lr / bc1 * *mi / denom) as f32;
        }
    }
    cancel.check()?;
    let last = problem.evaluate(&current, p, &mut s, None)?;
    let (h0, c0) = first.expect("at least one iteration");
    z.copy_from_slice(&current);
    Ok(TuningReport {
        iterations: p.iterations,
        hint_loss: [h0, last.hint_loss],
        control_error: [c0, last.control_error],
        losses,
    })
}

/// The release's noise regulariser over `z` (`[tokens, channels]`) and its gradient:
/// R = Σ_scales (mean(z ⊙ roll₁(z)))², rolled along the tokens, the tokens averaged in pairs
/// between scales while more than 2 remain. The release pads a token count that is not a
/// power of two with fresh noise at every call; the released latents (1 and 16 tokens) never
/// need it, and it is refused here.
pub(crate) fn regulariser(z: &[f32], tokens: usize, channels: usize) -> Result<(f64, Vec<f64>)> {
    if tokens == 0 || !tokens.is_power_of_two() || z.len() != tokens * channels {
        return Err(invalid_arg!(
            "the noise regulariser takes a power-of-two token count (the release pads others \
             with random noise); got {tokens} tokens × {channels}"
        ));
    }
    let mut levels = vec![z.iter().map(|&v| v as f64).collect::<Vec<f64>>()];
    let mut sizes = vec![tokens];
    let mut loss = 0.0;
    let mut direct: Vec<Vec<f64>> = Vec::new();
    loop {
        let (x, l) = (
            levels.last().expect("one level"),
            *sizes.last().expect("one size"),
        );
        if l <= 2 {
            direct.push(vec![0.0; x.len()]);
            break;
        }
        let count = (l * channels) as f64;
        let at = |i: usize, c: usize| x[(i % l) * channels + c];
        let mean: f64 = (0..l)
            .flat_map(|i| (0..channels).map(move |c| (i, c)))
            .map(|(i, c)| at(i, c) * at(i + l - 1, c))
            .sum::<f64>()
            / count;
        loss += mean * mean;
        // d(mean)/dx[i] = (x[i − 1] + x[i + 1]) / count.
        let d: Vec<f64> = (0..l)
            .flat_map(|i| (0..channels).map(move |c| (i, c)))
            .map(|(i, c)| 2.0 * mean * (at(i + l - 1, c) + at(i + 1, c)) / count)
            .collect();
        direct.push(d);
        let pooled: Vec<f64> = (0..l / 2)
            .flat_map(|i| (0..channels).map(move |c| (i, c)))
            .map(|(i, c)| 0.5 * (at(2 * i, c) + at(2 * i + 1, c)))
            .collect();
        levels.push(pooled);
        sizes.push(l / 2);
    }
    // Back through the pooling, coarsest scale first.
    let mut g = direct.pop().expect("one level");
    while let Some(mut d) = direct.pop() {
        for (i, row) in g.chunks_exact(channels).enumerate() {
            for (c, &v) in row.iter().enumerate() {
                d[2 * i * channels + c] += 0.5 * v;
                d[(2 * i + 1) * channels + c] += 0.5 * v;
            }
        }
        g = d;
    }
    Ok((loss, g))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The schedule of the release's 400 iterations: 0 at the first step, the peak at the end of
    /// the warm-up, half at the middle of the cosine, and (nearly) 0 at the end.
    #[test]
    fn the_cosine_schedule_warms_up_then_falls() {
        let p = TuningParams::new(400);
        assert_eq!(p.learning_rate_at(0), 0.0);
        assert!((p.learning_rate_at(25) - 0.05).abs() < 1e-12);
        assert!((p.learning_rate_at(50) - 0.1).abs() < 1e-12);
        assert!((p.learning_rate_at(225) - 0.05).abs() < 1e-12);
        assert!(p.learning_rate_at(399) < 1e-5);
    }

    /// The regulariser's gradient against central differences, at 16 tokens (three scales).
    #[test]
    fn the_regulariser_gradient_matches_differences() {
        let (l, c) = (16, 3);
        let z: Vec<f32> = (0..l * c)
            .map(|i| ((i * 37 % 11) as f32 - 5.0) / 4.0)
            .collect();
        let (_, g) = regulariser(&z, l, c).unwrap();
        for i in [0, 5, 17, 47] {
            let h = 1e-3f32;
            let mut a = z.clone();
            a[i] += h;
            let mut b = z.clone();
            b[i] -= h;
            let fd = (regulariser(&a, l, c).unwrap().0 - regulariser(&b, l, c).unwrap().0)
                / (a[i] as f64 - b[i] as f64);
            assert!(
                (fd - g[i]).abs() < 1e-6 * (1.0 + g[i].abs()),
                "{i}: {fd} vs {}",
                g[i]
            );
        }
        assert_eq!(regulariser(&z[..3], 1, 3).unwrap().0, 0.0);
        assert!(regulariser(&z[..9], 3, 3).is_err());
    }
}
