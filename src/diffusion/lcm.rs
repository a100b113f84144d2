//! The latent consistency sampler (Luo et al. 2023, "Latent Consistency Models", arXiv:2310.04378,
//! Algorithm 1) as MotionLCM runs it (Dai et al., ECCV 2024; Dai-Wenxun/MotionLCM, tags v1.0
//! f534a7f and v2.0 086f8db): diffusers' `LCMScheduler` (`schedulers/scheduling_lcm.py`, pinned
//! at 0.24.0 by both tags) with 1000 training steps, scaled_linear betas 0.00085–0.012,
//! epsilon prediction, no clipping and `timestep_scaling` 10.
//!
//! Each step turns the network's ε̂ at `t` into a consistency estimate
//! `d = c_out(t)·x̂0 + c_skip(t)·z` with `x̂0 = (z − √(1 − ᾱ_t)·ε̂)/√ᾱ_t`; every step but the last
//! then re-noises `d` to the next listed timestep `t′` with fresh Gaussian noise:
//! `z ← √ᾱ_t′·d + √(1 − ᾱ_t′)·ξ`. The last step returns `d`. The boundary-condition scalings
//! (`get_scalings_for_boundary_condition_discrete`, σ_data 0.5) make `d` equal `z` at `t = 0`.
//!
//! Timesteps: MotionLCM v1 takes diffusers' grid (`set_timesteps` with `original_inference_steps`
//! 50: the 50 timesteps `20j − 1` from the top, taken at `⌊linspace(0, 50, n, endpoint=False)⌋`);
//! v2 reads a table of its own (`mld/models/schedulers/scheduling_lcm.py` at v2.0) for 1, 2 and
//! 4 steps only, where the 4-step list repeats 299: the step there re-noises to 299 and denoises
//! again.
//!
//! Arithmetic follows diffusers': the ᾱ table in float32
//! ([`diffusers_alphas_cumprod`]), every per-element
//! operation in f32 in diffusers' order.

use crate::config::DiffusionConfig;
use crate::diffusion::{betas, diffusers_alphas_cumprod, BetaSchedule};
use crate::error::{bad_file, invalid_arg, Result};

/// diffusers' `timestep_scaling` default, which both MotionLCM releases keep.
pub const TIMESTEP_SCALING: f32 = 10.0;

/// MotionLCM v1's `original_inference_steps` (configs/modules/scheduler_lcm.yaml at v1.0).
pub const V1_ORIGINAL_STEPS: usize = 50;

/// MotionLCM v2's timestep table: step count → timesteps, the only counts it samples.
pub const V2_TIMESTEPS: [(usize, &[usize]); 3] =
    [(1, &[799]), (2, &[699, 299]), (4, &[699, 399, 299, 299])];

/// Which release's timestep rule a model follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LcmTimesteps {
    /// diffusers' grid from `original_inference_steps` (v1: 50).
    Grid {
        /// The distillation's step count the grid is taken from.
        original_steps: usize,
    },
    /// MotionLCM v2's table ([`V2_TIMESTEPS`]).
    V2Table,
}

impl LcmTimesteps {
    /// The rule a model file's `diffusion` section names (`lcm_timesteps`, with
    /// `original_inference_steps` for the grid); `BadModelFile` naming the field otherwise.
    pub fn from_config(dc: &DiffusionConfig) -> Result<LcmTimesteps> {
        match dc.lcm_timesteps.as_deref().map(str::trim) {
            Some("grid") => match dc.original_inference_steps {
                Some(n) if (1..=dc.num_timesteps).contains(&n) => {
                    Ok(LcmTimesteps::Grid { original_steps: n })
                }
                Some(n) => Err(bad_file!(
                    "config diffusion.original_inference_steps is {n}; it must be between 1 \
                     and num_timesteps ({})",
                    dc.num_timesteps
                )),
                None => Err(bad_file!(
                    "config diffusion.lcm_timesteps `grid` needs diffusion.original_inference_steps"
                )),
            },
            Some("motionlcm_v2") => {
                if dc.num_timesteps != 1000 {
                    return Err(bad_file!(
                        "config diffusion.lcm_timesteps `motionlcm_v2` is a table over 1000 \
                         training steps, not {}",
                        dc.num_timesteps
                    ));
                }
                Ok(LcmTimesteps::V2Table)
            }
            Some(other) => Err(bad_file!(
                "unknown config diffusion.lcm_timesteps `{other}` (accepted: grid, motionlcm_v2)"
            )),
            None => Err(bad_file!(
                "config diffusion.spacing `lcm` needs diffusion.lcm_timesteps (grid or \
                 motionlcm_v2)"
            )),
        }
    }

    /// The step counts this rule samples, for error messages and `flame info`.
    pub fn allowed(self) -> String {
        match self {
            LcmTimesteps::Grid { original_steps } => format!("1 to {original_steps}"),
            LcmTimesteps::V2Table => V2_TIMESTEPS
                .iter()
                .map(|(n, _)| n.to_string())
                .collect::<Vec<_>>()
                .join(", "),
        }
    }

    /// The timesteps of an `steps`-step run over `train_steps` training steps, or an error
    /// naming the counts this rule allows.
    pub fn timesteps(self, steps: usize, train_steps: usize) -> Result<Vec<usize>> {
        let refuse = || {
            invalid_arg!(
                "the latent consistency sampler has no {steps}-step schedule here; it samples {} \
                 steps",
                self.allowed()
            )
        };
        match self {
            LcmTimesteps::V2Table => V2_TIMESTEPS
                .iter()
                .find(|(n, _)| *n == steps)
                .map(|(_, t)| t.to_vec())
                .ok_or_else(refuse),
            LcmTimesteps::Grid { original_steps } => {
                if original_steps == 0 || original_steps > train_steps {
                    return Err(invalid_arg!(
                        "original_inference_steps {original_steps} must be 1 to the {train_steps} \
                         training steps"
                    ));
                }
                if steps == 0 || steps > original_steps {
                    return Err(refuse());
                }
                // diffusers: origin = (1..=N)·k − 1 with k = T div N, reversed, then taken at
                // floor(linspace(0, N, n, endpoint=False)) (numpy evaluates i·N/n in f64).
                let k = train_steps / original_steps;
                Ok((0..steps)
                    .map(|i| {
                        let idx = (i as f64 * (original_steps as f64 / steps as f64)).floor();
                        let j = original_steps - idx as usize; // 1-based origin index, from the top
                        j * k - 1
                    })
                    .collect())
            }
        }
    }
}

/// The sampler for one run: its timesteps and the ᾱ table.
#[derive(Clone, Debug)]
pub struct LcmSampler {
    alphas_cumprod: Vec<f32>,
    timesteps: Vec<usize>,
    timestep_scaling: f32,
}

impl LcmSampler {
    /// MotionLCM's sampler: 1000 steps of scaled_linear betas, `steps` timesteps by `rule`.
    pub fn motionlcm(rule: LcmTimesteps, steps: usize) -> Result<Self> {
        let base = betas(BetaSchedule::ScaledLinear, 1000);
        let timesteps = rule.timesteps(steps, base.len())?;
        Self::new(&base, timesteps, TIMESTEP_SCALING)
    }

    /// A sampler over `base_betas` (the training schedule) visiting `timesteps` in order.
    pub fn new(base_betas: &[f64], timesteps: Vec<usize>, timestep_scaling: f32) -> Result<Self> {
        let table: Vec<f32> = diffusers_alphas_cumprod(base_betas)
            .into_iter()
            .map(|a| a as f32)
            .collect();
        if timesteps.is_empty() {
            return Err(invalid_arg!(
                "the latent consistency sampler needs a timestep"
            ));
        }
        if let Some(t) = timesteps.iter().find(|&&t| t >= table.len()) {
            return Err(invalid_arg!(
                "timestep {t} is out of range for {} training steps",
                table.len()
            ));
        }
        if !(timestep_scaling.is_finite() && timestep_scaling > 0.0) {
            return Err(invalid_arg!(
                "timestep_scaling must be finite and positive, got {timestep_scaling}"
            ));
        }
        Ok(LcmSampler {
            alphas_cumprod: table,
            timesteps,
            timestep_scaling,
        })
    }

    /// The timesteps the network sees, in order.
    pub fn timesteps(&self) -> &[usize] {
        &self.timesteps
    }

    /// Number of steps (network calls).
    pub fn len(&self) -> usize {
        self.timesteps.len()
    }

    /// Always false: a sampler has at least one step.
    pub fn is_empty(&self) -> bool {
        self.timesteps.is_empty()
    }

    /// `(c_skip, c_out)` at timestep `t`, in f32 as diffusers computes them from the timestep
    /// tensor: `s = 10t`, `c_skip = 0.25/(s² + 0.25)`, `c_out = s/√(s² + 0.25)`.
    pub fn boundary_scalings(&self, t: usize) -> (f32, f32) {
        let s = t as f32 * self.timestep_scaling;
        let d = s * s + 0.25;
        (0.25 / d, s / d.sqrt())
    }

    /// Step `i`: from the network's ε̂ (`eps`) at the sample `z`, writes the consistency estimate
    /// into `denoised` (the run's result after the last step).
    pub fn denoise(&self, i: usize, eps: &[f32], z: &[f32], denoised: &mut [f32]) {
        assert!(eps.len() == z.len() && z.len() == denoised.len());
        let t = self.timesteps[i];
        let a = self.alphas_cumprod[t];
        let (sqrt_a, sqrt_b) = (a.sqrt(), (1.0 - a).sqrt());
        let (c_skip, c_out) = self.boundary_scalings(t);
        for ((d, &e), &x) in denoised.iter_mut().zip(eps).zip(z) {
            let x0 = (x - sqrt_b * e) / sqrt_a;
            *d = c_out * x0 + c_skip * x;
        }
    }

    /// `(a_z, a_ε)` with [`LcmSampler::denoise`]'s result `= a_z·z + a_ε·ε̂` at step `i`
    /// (`c_skip + c_out/√ᾱ` and `−c_out·√(1 − ᾱ)/√ᾱ`): the step's derivatives, for a backward
    /// through it.
    pub fn denoise_coefficients(&self, i: usize) -> (f32, f32) {
        let t = self.timesteps[i];
        let a = self.alphas_cumprod[t];
        let (sqrt_a, sqrt_b) = (a.sqrt(), (1.0 - a).sqrt());
        let (c_skip, c_out) = self.boundary_scalings(t);
        (c_skip + c_out / sqrt_a, -c_out * sqrt_b / sqrt_a)
    }

    /// After step `i` (not the last): the next sample, `denoised` re-noised to the next
    /// timestep with the Gaussian `noise`.
    pub fn renoise(&self, i: usize, denoised: &[f32], noise: &[f32], z: &mut [f32]) {
        assert!(
            i + 1 < self.timesteps.len(),
            "the last step is not re-noised"
        );
        assert!(denoised.len() == noise.len() && noise.len() == z.len());
        let a = self.alphas_cumprod[self.timesteps[i + 1]];
        let (sqrt_a, sqrt_b) = (a.sqrt(), (1.0 - a).sqrt());
        for ((x, &d), &n) in z.iter_mut().zip(denoised).zip(noise) {
            *x = sqrt_a * d + sqrt_b * n;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn v1_grid_and_v2_table_match_the_published_lists() {
        // Hand-derived from diffusers' rule (50 origin steps of 20): 1 → [999], 2 → [999, 499],
        // 4 → [999, 759, 499, 259].
        let v1 = LcmTimesteps::Grid { original_steps: 50 };
        assert_eq!(v1.timesteps(1, 1000).unwrap(), [999]);
        assert_eq!(v1.timesteps(2, 1000).unwrap(), [999, 499]);
        assert_eq!(v1.timesteps(4, 1000).unwrap(), [999, 759, 499, 259]);
        assert_eq!(v1.timesteps(50, 1000).unwrap().last(), Some(&19));
        let msg = v1.timesteps(51, 1000).unwrap_err().to_string();
        assert!(msg.contains("1 to 50"), "{msg}");
        assert!(v1.timesteps(0, 1000).is_err());
        let v2 = LcmTimesteps::V2Table;
        assert_eq!(v2.timesteps(4, 1000).unwrap(), [699, 399, 299, 299]);
        let msg = v2.timesteps(3, 1000).unwrap_err().to_string();
        assert!(msg.contains("1, 2, 4"), "{msg}");
    }

    #[test]
    fn the_boundary_condition_holds_at_zero_and_fades_at_the_top() {
        let s = LcmSampler::motionlcm(LcmTimesteps::V2Table, 1).unwrap();
        assert_eq!(s.boundary_scalings(0), (1.0, 0.0));
        // At t = 999: s = 9990, c_skip = 0.25/(9990² + 0.25) ≈ 2.505e-9, c_out ≈ 1 − 1.25e-9.
        let (skip, out) = s.boundary_scalings(999);
        assert!((skip - 2.505e-9).abs() < 1e-12, "{skip}");
        assert_eq!(out, 1.0);
    }
}
