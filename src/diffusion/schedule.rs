//! Beta schedules and the float64 tables derived from them.
//!
//! Everything here is computed in f64 with the same operation order as guided-diffusion's
//! `gaussian_diffusion.py` (numpy semantics), so the tables agree with the reference to the last
//! bit or two; the sampler casts them to f32 only when it gathers a step's coefficients.

use std::fmt;
use std::str::FromStr;

use crate::error::{invalid_arg, Error, Result};

/// Which β_t schedule a model was trained with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum BetaSchedule {
    /// Nichol & Dhariwal's squared-cosine ᾱ(s), β capped at 0.999 (FLAME, MDM).
    Cosine,
    /// guided-diffusion's linear schedule, rescaled so any T spans the T=1000 range.
    Linear,
    /// diffusers' "scaled_linear": a linspace of √β squared, computed in float32 (MLD, MoLA).
    ScaledLinear,
}

impl BetaSchedule {
    /// The canonical config name.
    pub fn name(self) -> &'static str {
        match self {
            BetaSchedule::Cosine => "cosine",
            BetaSchedule::Linear => "linear",
            BetaSchedule::ScaledLinear => "scaled_linear",
        }
    }
}

impl fmt::Display for BetaSchedule {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for BetaSchedule {
    type Err = Error;
    /// Accepts the guided-diffusion and diffusers spellings.
    fn from_str(s: &str) -> Result<Self> {
        match s.trim().to_ascii_lowercase().as_str() {
            "cosine" | "squaredcos_cap_v2" => Ok(BetaSchedule::Cosine),
            "linear" => Ok(BetaSchedule::Linear),
            "scaled_linear" => Ok(BetaSchedule::ScaledLinear),
            _ => Err(invalid_arg!(
                "beta schedule {s:?}: expected cosine, squaredcos_cap_v2, linear or scaled_linear"
            )),
        }
    }
}

/// The T betas of `schedule` (empty when `num_timesteps` is 0).
pub fn betas(schedule: BetaSchedule, num_timesteps: usize) -> Vec<f64> {
    match schedule {
        BetaSchedule::Cosine => cosine_betas(num_timesteps),
        BetaSchedule::Linear => linear_betas(num_timesteps),
        BetaSchedule::ScaledLinear => scaled_linear_betas(num_timesteps),
    }
}

/// ᾱ(s) = cos²(((s + 0.008)/1.008)·π/2), evaluated left to right as Python does.
fn cosine_alpha_bar(s: f64) -> f64 {
    let c = ((s + 0.008) / 1.008 * std::f64::consts::PI / 2.0).cos();
    c * c
}

/// β_i = min(1 − ᾱ((i+1)/T)/ᾱ(i/T), 0.999), i = 0..T−1 (kakaobrain/flame
/// `src/models/components/gaussian_diffusion.py`; docs/official/flame.md#noise-schedule).
fn cosine_betas(t: usize) -> Vec<f64> {
    let tf = t as f64;
    (0..t)
        .map(|i| {
            let t1 = i as f64 / tf;
            let t2 = (i + 1) as f64 / tf;
            (1.0 - cosine_alpha_bar(t2) / cosine_alpha_bar(t1)).min(0.999)
        })
        .collect()
}

/// numpy's `linspace(start, stop, n)` for float64: `i·step + start`, last element = `stop`.
fn linspace_f64(start: f64, stop: f64, n: usize) -> Vec<f64> {
    if n == 1 {
        return vec![start];
    }
    let step = (stop - start) / (n - 1) as f64;
    let mut v: Vec<f64> = (0..n).map(|i| i as f64 * step + start).collect();
    if let Some(last) = v.last_mut() {
        *last = stop;
    }
    v
}

/// guided-diffusion "linear": scale = 1000/T; linspace(scale·1e-4, scale·0.02, T) in f64.
fn linear_betas(t: usize) -> Vec<f64> {
    if t == 0 {
        return Vec::new();
    }
    let scale = 1000.0 / t as f64;
    linspace_f64(scale * 0.0001, scale * 0.02, t)
}

/// `torch.linspace(start, end, n, dtype=float32)` as the CPU kernel computes it: the f32 step
/// `(end − start)/(n − 1)`, the first half counted up from `start` and the second half counted
/// down from `end`, each element a single fused multiply-add (the compiled kernel is contracted to
/// FMA; verified bit-exact against torch 2.x for several n).
fn linspace_f32_torch(start: f64, end: f64, n: usize) -> Vec<f32> {
    let (start, end) = (start as f32, end as f32);
    if n == 1 {
        return vec![start];
    }
    let step = (end - start) / (n - 1) as f32;
    let half = n / 2;
    (0..n)
        .map(|i| {
            if i < half {
                step.mul_add(i as f32, start)
            } else {
                (-step).mul_add((n - i - 1) as f32, end)
            }
        })
        .collect()
}

/// diffusers "scaled_linear": `linspace(√0.00085, √0.012, T, dtype=float32) ** 2`. diffusers
/// keeps these betas in float32, so they are computed (and squared) in f32 and only then widened
/// to f64; the derived tables are then built in f64 like every other schedule.
fn scaled_linear_betas(t: usize) -> Vec<f64> {
    if t == 0 {
        return Vec::new();
    }
    linspace_f32_torch(0.00085f64.sqrt(), 0.012f64.sqrt(), t)
        .into_iter()
        .map(|b| (b * b) as f64)
        .collect()
}

/// diffusers' `alphas_cumprod` for `betas`: each β rounded to f32 (diffusers keeps its betas in
/// float32; the scaled_linear betas are f32 already), α = 1 − β in f32, and `torch.cumprod` as its
/// CPU kernel computes it — the running product in f64, each entry stored as f32
/// (huggingface/diffusers `scheduling_ddim.py` run on CPU;
/// docs/official/mola-mld.md#scheduler-tables-in-float32; a plain f32 running product differs in
/// 944 of the 1000 scaled_linear entries). The f32 values are returned widened to f64.
pub fn diffusers_alphas_cumprod(betas: &[f64]) -> Vec<f64> {
    let mut acc = 1.0f64;
    betas
        .iter()
        .map(|&b| {
            acc *= f64::from(1.0f32 - b as f32);
            f64::from(acc as f32)
        })
        .collect()
}

/// The float64 tables guided-diffusion derives from a beta sequence (kakaobrain/flame
/// `gaussian_diffusion.py`; docs/official/flame.md#noise-schedule), plus the two
/// log-variance tables the sampler's variance modes read.
#[derive(Debug, Clone, PartialEq)]
pub struct Schedule {
    /// β_t, one per step, t = 0 (least noise) first; each in (0, 1) (a diffusers step with
    /// ᾱ_prev = ᾱ has β = 0).
    pub betas: Vec<f64>,
    /// ᾱ_t = ∏_{s≤t}(1 − β_s): the signal's share of x_t's variance, falling towards 0.
    pub alphas_cumprod: Vec<f64>,
    /// `[1, ᾱ_0, …, ᾱ_{T−2}]`.
    pub alphas_cumprod_prev: Vec<f64>,
    /// √ᾱ_t, the clean motion's scale in x_t = √ᾱ_t·x0 + √(1 − ᾱ_t)·ε.
    pub sqrt_alphas_cumprod: Vec<f64>,
    /// √(1 − ᾱ_t), the noise's scale in x_t.
    pub sqrt_one_minus_alphas_cumprod: Vec<f64>,
    /// √(1/ᾱ_t), x_t's weight in x̂0 = √(1/ᾱ_t)·x_t − √(1/ᾱ_t − 1)·ε.
    pub sqrt_recip_alphas_cumprod: Vec<f64>,
    /// √(1/ᾱ_t − 1), ε's weight in that x̂0.
    pub sqrt_recipm1_alphas_cumprod: Vec<f64>,
    /// σ̃²_t = β_t(1 − ᾱ_prev,t)/(1 − ᾱ_t); σ̃²_0 = 0.
    pub posterior_variance: Vec<f64>,
    /// log σ̃²_t with entry 0 replaced by log σ̃²_1 (log 0 would be −∞).
    pub posterior_log_variance_clipped: Vec<f64>,
    /// c1_t = β_t·√ᾱ_prev,t/(1 − ᾱ_t): x̂0's weight in the posterior mean c1·x̂0 + c2·x_t.
    pub posterior_mean_coef1: Vec<f64>,
    /// c2_t = (1 − ᾱ_prev,t)·√(1 − β_t)/(1 − ᾱ_t): x_t's weight in the posterior mean.
    pub posterior_mean_coef2: Vec<f64>,
    /// log β_t: the upper end of the learned-range interpolation.
    pub log_betas: Vec<f64>,
    /// log of `[σ̃²_1, β_1, …, β_{T−1}]`: guided-diffusion's FIXED_LARGE variance.
    pub fixed_large_log_variance: Vec<f64>,
}

impl Schedule {
    /// Derives every table from `betas`; each β must lie in (0, 1).
    pub fn new(betas: &[f64]) -> Result<Self> {
        if betas.is_empty() {
            return Err(invalid_arg!("betas: empty schedule"));
        }
        if let Some((i, b)) = betas
            .iter()
            .enumerate()
            .find(|(_, b)| !(**b > 0.0 && **b < 1.0))
        {
            return Err(invalid_arg!(
                "beta {i} of the noise schedule is {b}; it must be between 0 and 1, both excluded"
            ));
        }
        let n = betas.len();
        // numpy cumprod is a sequential running product.
        let mut alphas_cumprod = Vec::with_capacity(n);
        let mut acc = 1.0f64;
        for (i, b) in betas.iter().enumerate() {
            let a = 1.0 - b;
            acc = if i == 0 { a } else { acc * a };
            alphas_cumprod.push(acc);
        }
        let mut alphas_cumprod_prev = Vec::with_capacity(n);
        alphas_cumprod_prev.push(1.0);
        alphas_cumprod_prev.extend_from_slice(&alphas_cumprod[..n - 1]);
        Ok(Self::from_tables(
            betas.to_vec(),
            alphas_cumprod,
            alphas_cumprod_prev,
        ))
    }

    /// The tables of a process whose step `i` goes from ᾱ_i = `alphas_cumprod[i]` to
    /// `alphas_cumprod_prev[i]` (diffusers' per-step pairs, where ᾱ_prev need not be the
    /// previous entry): β_i = 1 − ᾱ_i/ᾱ_prev,i. Needs 0 < ᾱ_i ≤ ᾱ_prev,i ≤ 1 and ᾱ_i < 1; a
    /// step with ᾱ_prev = ᾱ (β = 0, diffusers' last leading step at t = 0 without
    /// `set_alpha_to_one`) leaves the sample unchanged.
    pub fn from_alpha_bars(alphas_cumprod: &[f64], alphas_cumprod_prev: &[f64]) -> Result<Self> {
        if alphas_cumprod.is_empty() || alphas_cumprod.len() != alphas_cumprod_prev.len() {
            return Err(invalid_arg!(
                "alpha bars: {} values and {} previous values",
                alphas_cumprod.len(),
                alphas_cumprod_prev.len()
            ));
        }
        let pairs = alphas_cumprod.iter().zip(alphas_cumprod_prev);
        if let Some((i, (a, p))) = pairs
            .enumerate()
            .find(|(_, (a, p))| !(**a > 0.0 && **a < 1.0 && **a <= **p && **p <= 1.0))
        {
            return Err(invalid_arg!(
                "alpha bar {i}: {a} after {p} is not a step of 0 < ᾱ ≤ ᾱ_prev ≤ 1, ᾱ < 1"
            ));
        }
        let betas = alphas_cumprod
            .iter()
            .zip(alphas_cumprod_prev)
            .map(|(a, p)| 1.0 - a / p)
            .collect();
        Ok(Self::from_tables(
            betas,
            alphas_cumprod.to_vec(),
            alphas_cumprod_prev.to_vec(),
        ))
    }

    /// Every derived table, from checked betas, ᾱ and ᾱ_prev
    /// (docs/official/flame.md#noise-schedule).
    fn from_tables(
        betas: Vec<f64>,
        alphas_cumprod: Vec<f64>,
        alphas_cumprod_prev: Vec<f64>,
    ) -> Self {
        let n = betas.len();
        let map = |f: &dyn Fn(usize) -> f64| (0..n).map(f).collect::<Vec<f64>>();
        let (b, ac, acp) = (&betas, &alphas_cumprod, &alphas_cumprod_prev);
        let sqrt_alphas_cumprod = map(&|i| ac[i].sqrt());
        let sqrt_one_minus_alphas_cumprod = map(&|i| (1.0 - ac[i]).sqrt());
        let sqrt_recip_alphas_cumprod = map(&|i| (1.0 / ac[i]).sqrt());
        let sqrt_recipm1_alphas_cumprod = map(&|i| (1.0 / ac[i] - 1.0).sqrt());
        let posterior_variance = map(&|i| b[i] * (1.0 - acp[i]) / (1.0 - ac[i]));
        // With a single step there is no σ̃²_1; entry 0 is then log 0 = −∞, which is harmless
        // because the sampler never adds noise at t = 0.
        let first = if n > 1 {
            posterior_variance[1]
        } else {
            posterior_variance[0]
        };
        let posterior_log_variance_clipped = map(&|i| {
            if i == 0 {
                first.ln()
            } else {
                posterior_variance[i].ln()
            }
        });
        let posterior_mean_coef1 = map(&|i| b[i] * acp[i].sqrt() / (1.0 - ac[i]));
        let posterior_mean_coef2 = map(&|i| (1.0 - acp[i]) * (1.0 - b[i]).sqrt() / (1.0 - ac[i]));
        let log_betas = map(&|i| b[i].ln());
        let fixed_large_log_variance = map(&|i| if i == 0 { first.ln() } else { b[i].ln() });

        Schedule {
            betas,
            alphas_cumprod,
            alphas_cumprod_prev,
            sqrt_alphas_cumprod,
            sqrt_one_minus_alphas_cumprod,
            sqrt_recip_alphas_cumprod,
            sqrt_recipm1_alphas_cumprod,
            posterior_variance,
            posterior_log_variance_clipped,
            posterior_mean_coef1,
            posterior_mean_coef2,
            log_betas,
            fixed_large_log_variance,
        }
    }

    /// Number of timesteps T.
    pub fn len(&self) -> usize {
        self.betas.len()
    }

    /// Always false: [`Schedule::new`] rejects empty schedules.
    pub fn is_empty(&self) -> bool {
        self.betas.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, rel: f64) -> bool {
        (a - b).abs() <= rel * b.abs().max(1e-300)
    }

    #[test]
    fn parse_names() {
        assert_eq!(
            "cosine".parse::<BetaSchedule>().unwrap(),
            BetaSchedule::Cosine
        );
        assert_eq!(
            "squaredcos_cap_v2".parse::<BetaSchedule>().unwrap(),
            BetaSchedule::Cosine
        );
        assert_eq!(
            "linear".parse::<BetaSchedule>().unwrap(),
            BetaSchedule::Linear
        );
        assert_eq!(
            "scaled_linear".parse::<BetaSchedule>().unwrap(),
            BetaSchedule::ScaledLinear
        );
        assert!(matches!(
            "sigmoid".parse::<BetaSchedule>(),
            Err(Error::InvalidArgument(_))
        ));
        for s in [
            BetaSchedule::Cosine,
            BetaSchedule::Linear,
            BetaSchedule::ScaledLinear,
        ] {
            assert_eq!(s.name().parse::<BetaSchedule>().unwrap(), s);
        }
    }

    #[test]
    fn cosine_1000_matches_reference_numbers() {
        // docs/official/flame.md#noise-schedule (derived): β_0 = 4.1284e−5, β_999 = 0.999 is the
        // only capped value, ᾱ_0 = 0.9999587, ᾱ_499 = 0.4938436, ᾱ_999 = 2.4288e−9.
        let b = betas(BetaSchedule::Cosine, 1000);
        assert_eq!(b.len(), 1000);
        assert!(close(b[0], 4.1284e-5, 1e-4));
        assert_eq!(b[999], 0.999);
        assert_eq!(b.iter().filter(|&&x| x >= 0.999).count(), 1);
        let s = Schedule::new(&b).unwrap();
        assert!(close(s.alphas_cumprod[0], 0.9999587, 1e-7));
        assert!(close(s.alphas_cumprod[499], 0.4938436, 1e-6));
        assert!(close(s.alphas_cumprod[999], 2.4288e-9, 1e-4));
        // Bit-exact against numpy/math (guided-diffusion's get_named_beta_schedule, run once).
        assert_eq!(b[0], 4.128422482196914e-05);
        assert_eq!(s.alphas_cumprod[499], 0.4938435904406382);
    }

    #[test]
    fn cosine_50_matches_reference_numbers() {
        // docs/official/mdm.md#sampling-and-guidance (derived): β_0 = 1.7475e−3, ᾱ_49 = 9.712e−7,
        // β_49 = 0.999.
        let b = betas(BetaSchedule::Cosine, 50);
        assert!(close(b[0], 1.7475e-3, 1e-4));
        assert_eq!(b[49], 0.999);
        let s = Schedule::new(&b).unwrap();
        assert!(close(s.alphas_cumprod[49], 9.712e-7, 1e-4));
    }

    #[test]
    fn linear_schedule_is_numpy_linspace() {
        let b = betas(BetaSchedule::Linear, 1000);
        assert_eq!(b[0], 0.0001);
        assert_eq!(b[999], 0.02);
        // numpy.linspace(1e-4, 0.02, 1000)[1] and [500], printed with repr.
        assert_eq!(b[1], 0.00011991991991991993);
        assert_eq!(b[500], 0.010059959959959959);
        // T = 100 rescales to 1000/100 = 10× the endpoints.
        let b = betas(BetaSchedule::Linear, 100);
        assert!(close(b[0], 0.001, 1e-12));
        assert!(close(b[99], 0.2, 1e-12));
    }

    #[test]
    fn scaled_linear_matches_torch_float32() {
        // (torch.linspace(0.00085**0.5, 0.012**0.5, 1000, dtype=torch.float32)**2), torch 2.x,
        // as float32 bit patterns at indices 0, 1, 499, 500, 998, 999.
        let b = betas(BetaSchedule::ScaledLinear, 1000);
        let bits: Vec<u32> = [0, 1, 499, 500, 998, 999]
            .iter()
            .map(|&i| (b[i] as f32).to_bits())
            .collect();
        assert_eq!(bits, SCALED_LINEAR_BITS);
        assert!(
            b.iter().all(|&x| (x as f32) as f64 == x),
            "values are widened f32"
        );
        assert!(close(b[0], 0.00085, 1e-6));
        assert!(close(b[999], 0.012, 1e-6));
    }

    const SCALED_LINEAR_BITS: [u32; 6] = [
        0x3a5ed288, 0x3a600dda, 0x3b9d6922, 0x3b9dc6c2, 0x3c4451b9, 0x3c449ba5,
    ];

    #[test]
    fn derived_tables_by_hand() {
        // β = [0.1, 0.2, 0.3]: ᾱ = [0.9, 0.72, 0.504].
        let s = Schedule::new(&[0.1, 0.2, 0.3]).unwrap();
        let want_ac = [0.9, 0.72, 0.504];
        for (got, want) in s.alphas_cumprod.iter().zip(want_ac) {
            assert!(close(*got, want, 1e-14));
        }
        assert_eq!(s.alphas_cumprod_prev[0], 1.0);
        assert_eq!(s.posterior_variance[0], 0.0);
        // σ̃²_2 = 0.3·(1 − 0.72)/(1 − 0.504); c1_2 = 0.3·√0.72/0.496; c2_2 = 0.28·√0.7/0.496.
        assert!(close(s.posterior_variance[2], 0.3 * 0.28 / 0.496, 1e-14));
        assert!(close(
            s.posterior_mean_coef1[2],
            0.3 * 0.72f64.sqrt() / 0.496,
            1e-14
        ));
        assert!(close(
            s.posterior_mean_coef2[2],
            0.28 * 0.7f64.sqrt() / 0.496,
            1e-14
        ));
        // σ̃²_1 = 0.2·0.1/0.28; entry 0 of the clipped log table copies it.
        let pv1: f64 = 0.2 * 0.1 / 0.28;
        assert!(close(s.posterior_log_variance_clipped[0], pv1.ln(), 1e-14));
        assert!(close(s.posterior_log_variance_clipped[1], pv1.ln(), 1e-14));
        assert!(close(s.fixed_large_log_variance[0], pv1.ln(), 1e-14));
        assert!(close(s.fixed_large_log_variance[2], 0.3f64.ln(), 1e-14));
        // t = 0: c1 = β_0/(1 − ᾱ_0) = 1, c2 = 0.
        assert!(close(s.posterior_mean_coef1[0], 1.0, 1e-14));
        assert_eq!(s.posterior_mean_coef2[0], 0.0);
        assert!(close(
            s.sqrt_recipm1_alphas_cumprod[1],
            (1.0 / 0.72 - 1.0f64).sqrt(),
            1e-14
        ));
    }

    #[test]
    fn diffusers_table_by_hand() {
        // β = [0.1, 0.2, 0.3] in f32; α in f32; running product in f64, stored as f32.
        let got = diffusers_alphas_cumprod(&[0.1, 0.2, 0.3]);
        let a: Vec<f64> = [0.1f32, 0.2, 0.3]
            .iter()
            .map(|&b| f64::from(1.0f32 - b))
            .collect();
        let want = [a[0], a[0] * a[1], a[0] * a[1] * a[2]].map(|v| f64::from(v as f32));
        assert_eq!(got, want);
        assert!(close(got[2], 0.504, 1e-7));
    }

    #[test]
    fn tables_from_alpha_bar_pairs() {
        // Steps 0.72 → 0.9 and 0.504 → 0.72 of the β = [0.1, 0.2, 0.3] process, and a last
        // step that stays at ᾱ (β = 0: the sample is kept).
        let s = Schedule::from_alpha_bars(&[0.72, 0.504, 0.9], &[0.9, 0.72, 0.9]).unwrap();
        assert!(close(s.betas[0], 0.2, 1e-14));
        assert!(close(s.betas[1], 0.3, 1e-14));
        assert_eq!(s.betas[2], 0.0);
        assert!(close(s.posterior_variance[1], 0.3 * 0.28 / 0.496, 1e-14));
        assert_eq!(s.posterior_mean_coef1[2], 0.0);
        assert_eq!(s.posterior_mean_coef2[2], 1.0);
        // The guided-diffusion tables agree with `new` on the same process.
        let n = Schedule::new(&[0.1, 0.2, 0.3]).unwrap();
        let p = Schedule::from_alpha_bars(&n.alphas_cumprod, &n.alphas_cumprod_prev).unwrap();
        for i in 0..3 {
            assert!(close(
                p.posterior_mean_coef2[i].max(1e-300),
                n.posterior_mean_coef2[i].max(1e-300),
                1e-12
            ));
            assert!(close(p.betas[i], n.betas[i], 1e-12));
        }
        for (ac, acp) in [
            (&[0.5][..], &[0.4][..]),
            (&[1.0], &[1.0]),
            (&[0.0], &[0.5]),
            (&[0.5], &[1.5]),
            (&[f64::NAN], &[1.0]),
            (&[0.5, 0.4], &[1.0]),
            (&[], &[]),
        ] {
            assert!(
                Schedule::from_alpha_bars(ac, acp).is_err(),
                "{ac:?} {acp:?}"
            );
        }
    }

    #[test]
    fn rejects_bad_betas() {
        assert!(Schedule::new(&[]).is_err());
        assert!(Schedule::new(&[0.1, 1.0]).is_err());
        assert!(Schedule::new(&[0.0, 0.1]).is_err());
        assert!(Schedule::new(&[0.1, f64::NAN]).is_err());
        // Linear with T = 10 would need β up to 2.0.
        assert!(Schedule::new(&betas(BetaSchedule::Linear, 10)).is_err());
    }
}
