//! Timestep spacing: which of the T training steps a shorter sampling run keeps. Two families:
//! guided-diffusion's `respace.py` (kakaobrain/flame `src/models/components/respace.py`;
//! docs/official/flame.md#respacing; the respaced schedule itself is built by
//! [`super::DiffusionSampler::new`] via [`respaced_betas`]) and diffusers' `"leading"` and
//! `"trailing"` spacings of `DDIMScheduler.set_timesteps` (huggingface/diffusers
//! `scheduling_ddim.py`; docs/official/mola-mld.md#mola-scheduler,
//! docs/official/mola-mld.md#mld-scheduler), whose steps keep the training table's ᾱ
//! ([`super::DiffusionSampler::new_diffusers`]).

use std::fmt;
use std::str::FromStr;

use crate::error::{invalid_arg, Error, Result};

/// How a model's sampling steps are chosen from its training steps (`diffusion.spacing`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Spacing {
    /// guided-diffusion's section rule ([`space_timesteps`]) and respaced process (FLAME, MDM).
    #[default]
    Respace,
    /// diffusers' default: t = k·(T div N) + `steps_offset`, k = N−1..0 (MLD: 981, 961, …, 1).
    Leading,
    /// diffusers' `round(arange(T, 0, −T/N)) − 1` (MoLA: 999, 979, …, 19).
    Trailing,
    /// The latent consistency sampler's own timesteps ([`crate::diffusion::lcm`]: MotionLCM's
    /// grid or table, from `diffusion.lcm_timesteps`).
    Lcm,
}

impl Spacing {
    /// The config name.
    pub fn name(self) -> &'static str {
        match self {
            Spacing::Respace => "respace",
            Spacing::Leading => "leading",
            Spacing::Trailing => "trailing",
            Spacing::Lcm => "lcm",
        }
    }

    /// Whether steps follow diffusers' `DDIMScheduler` (leading or trailing).
    pub fn is_diffusers(self) -> bool {
        matches!(self, Spacing::Leading | Spacing::Trailing)
    }
}

impl fmt::Display for Spacing {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Spacing {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s.trim().to_ascii_lowercase().as_str() {
            "respace" => Ok(Spacing::Respace),
            "leading" => Ok(Spacing::Leading),
            "trailing" => Ok(Spacing::Trailing),
            "lcm" => Ok(Spacing::Lcm),
            _ => Err(invalid_arg!(
                "timestep spacing {s:?}: expected respace, leading, trailing or lcm"
            )),
        }
    }
}

/// The `steps` timesteps of diffusers' spacing, in sampling order (descending), or an error
/// where diffusers would index outside the training table. `Respace` is not a diffusers
/// spacing and is refused.
pub fn diffusers_timesteps(
    spacing: Spacing,
    num_timesteps: usize,
    steps: usize,
    steps_offset: usize,
) -> Result<Vec<usize>> {
    let t = num_timesteps;
    if steps == 0 || steps > t {
        return Err(invalid_arg!(
            "steps must be between 1 and {t} for this model, got {steps}"
        ));
    }
    match spacing {
        Spacing::Leading => {
            let ratio = t / steps;
            let last = (steps - 1) * ratio + steps_offset;
            if last >= t {
                return Err(invalid_arg!(
                    "leading spacing with {steps} steps and steps_offset {steps_offset} \
                     reaches timestep {last}, past the last training step {}",
                    t - 1
                ));
            }
            Ok((0..steps).rev().map(|k| k * ratio + steps_offset).collect())
        }
        Spacing::Trailing => trailing_timesteps(t, steps),
        Spacing::Respace | Spacing::Lcm => {
            Err(invalid_arg!("{spacing} is not a diffusers DDIM spacing"))
        }
    }
}

/// numpy's `round(arange(T, 0, −T/N)) − 1` exactly: arange fills `T + i·δ` with
/// δ = (T − T/N) − T and has ⌈T/(T/N)⌉ elements; round is half-to-even.
fn trailing_timesteps(t: usize, steps: usize) -> Result<Vec<usize>> {
    let tf = t as f64;
    let ratio = tf / steps as f64;
    let delta = (tf - ratio) - tf;
    let len = (-tf / -ratio).ceil() as usize;
    if len != steps {
        // diffusers then appends a step at −1, which indexes ᾱ from the end of the table.
        return Err(invalid_arg!(
            "trailing spacing cannot take {steps} steps over {t}: diffusers' rule gives {len} \
             timesteps (the last at −1) for this count; choose another step count"
        ));
    }
    // With N ≤ T the smallest value is about T/N ≥ 1, so no step falls below 0.
    (0..len)
        .map(|i| {
            let v = (tf + i as f64 * delta).round_ties_even() - 1.0;
            (v >= 0.0).then_some(v as usize).ok_or_else(|| {
                invalid_arg!("trailing spacing with {steps} steps over {t} reaches timestep {v}")
            })
        })
        .collect()
}

/// The section rule: split `0..num_timesteps` into `sections.len()` nearly equal parts (the first
/// `T % n` parts one step longer) and take `sections[i]` evenly spread steps from part `i`,
/// rounding the running float position half-to-even as Python's `round` does. Sorted ascending.
///
/// Errors on T = 0, no sections, a zero count, or a section asked for more steps than it has.
pub fn space_timesteps(num_timesteps: usize, sections: &[usize]) -> Result<Vec<usize>> {
    if num_timesteps == 0 {
        return Err(invalid_arg!("space_timesteps: num_timesteps is 0"));
    }
    if sections.is_empty() {
        return Err(invalid_arg!("space_timesteps: no section counts"));
    }
    let size_per = num_timesteps / sections.len();
    let extra = num_timesteps % sections.len();
    let mut start = 0usize;
    // Capacity from T, not from the counts: a count may be absurd (it is refused below).
    let mut steps = Vec::with_capacity(num_timesteps.min(1 << 20));
    for (i, &count) in sections.iter().enumerate() {
        let size = size_per + usize::from(i < extra);
        if count == 0 {
            return Err(invalid_arg!(
                "space_timesteps: section {i} asks for 0 steps"
            ));
        }
        if size < count {
            return Err(invalid_arg!(
                "space_timesteps: cannot take {count} steps from section {i} of {size} steps"
            ));
        }
        let stride = if count <= 1 {
            1.0
        } else {
            (size - 1) as f64 / (count - 1) as f64
        };
        // Accumulate as a Python float does; the rounding of the running sum is part of the rule.
        let mut cur = 0.0f64;
        for _ in 0..count {
            steps.push(start + cur.round_ties_even() as usize);
            cur += stride;
        }
        start += size;
    }
    steps.sort_unstable();
    steps.dedup();
    Ok(steps)
}

/// The "ddimN" rule: `{0, k, 2k, …}` for the smallest stride k in 1..T whose `range(0, T, k)` has
/// exactly `n` elements (T = 1000: ddim50 → k = 20). Errors when no such stride exists.
pub fn space_timesteps_ddim_stride(num_timesteps: usize, n: usize) -> Result<Vec<usize>> {
    (1..num_timesteps)
        .find(|&k| num_timesteps.div_ceil(k) == n)
        .map(|k| (0..num_timesteps).step_by(k).collect())
        .ok_or_else(|| {
            invalid_arg!(
                "cannot create exactly {n} steps with an integer stride over {num_timesteps}"
            )
        })
}

/// Parses a guided-diffusion `timestep_respacing` string: `""` keeps all steps, `"ddimN"` uses
/// the stride rule, otherwise a comma list of section counts (`"250"`, `"10,15,20"`).
pub fn parse_timestep_respacing(num_timesteps: usize, spec: &str) -> Result<Vec<usize>> {
    let spec = spec.trim();
    if spec.is_empty() {
        return space_timesteps(num_timesteps, &[num_timesteps]);
    }
    if let Some(n) = spec.strip_prefix("ddim") {
        let n: usize = n
            .parse()
            .map_err(|_| invalid_arg!("timestep respacing {spec:?}: bad ddim count"))?;
        return space_timesteps_ddim_stride(num_timesteps, n);
    }
    let sections = spec
        .split(',')
        .map(|p| p.trim().parse::<usize>())
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(|_| {
            invalid_arg!(
                "timestep respacing {spec:?}: expected \"ddimN\" or comma-separated counts"
            )
        })?;
    space_timesteps(num_timesteps, &sections)
}

/// Betas of the respaced process: walking the original ᾱ in increasing t, each kept step gets
/// β = 1 − ᾱ_t/ᾱ_last (ᾱ_last starting at 1), so the respaced ᾱ equal the original ones at the
/// kept steps. Returns `(betas, timestep_map)`; `use_timesteps` may be unsorted or repeat values
/// (it is a set in the reference), but every entry must be < T.
pub fn respaced_betas(
    base_alphas_cumprod: &[f64],
    use_timesteps: &[usize],
) -> Result<(Vec<f64>, Vec<usize>)> {
    let t = base_alphas_cumprod.len();
    if use_timesteps.is_empty() {
        return Err(invalid_arg!("use_timesteps: no timesteps kept"));
    }
    if let Some(bad) = use_timesteps.iter().find(|&&s| s >= t) {
        return Err(invalid_arg!(
            "use_timesteps: step {bad} is out of range for T = {t}"
        ));
    }
    let mut keep = vec![false; t];
    for &s in use_timesteps {
        keep[s] = true;
    }
    let mut last = 1.0f64;
    let mut betas = Vec::new();
    let mut map = Vec::new();
    for (i, &ac) in base_alphas_cumprod.iter().enumerate() {
        if keep[i] {
            betas.push(1.0 - ac / last);
            last = ac;
            map.push(i);
        }
    }
    Ok((betas, map))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn single_section_of_ten_over_1000() {
        // stride 999/9 = 111 exactly.
        let s = space_timesteps(1000, &[10]).unwrap();
        assert_eq!(s, [0, 111, 222, 333, 444, 555, 666, 777, 888, 999]);
    }

    #[test]
    fn all_steps_and_single_step() {
        assert_eq!(
            space_timesteps(1000, &[1000]).unwrap(),
            (0..1000).collect::<Vec<_>>()
        );
        assert_eq!(space_timesteps(1000, &[1]).unwrap(), [0]);
    }

    #[test]
    fn three_sections_worked_by_hand() {
        // T = 300, sections [10, 15, 20]: three sections of 100 steps starting at 0, 100, 200.
        // Section 0: stride 99/9 = 11 → 0, 11, …, 99.
        // Section 1: stride 99/14 = 7.0714…; running sums round to 0 7 14 21 28 35 42, then
        //   7·stride = 49.5 exactly in real arithmetic, but the accumulated float is
        //   49.49999999999999 → 49 (this is why the sum must be accumulated, not multiplied),
        //   then 57 64 71 78 85 92 99.
        // Section 2: stride 99/19 = 5.2105…; sums 0 5.21 10.42 15.63 20.84 26.05 31.26 36.47
        //   41.68 46.89 52.11 57.32 62.53 67.74 72.95 78.16 83.37 88.58 93.79 99.0 round to
        //   0 5 10 16 21 26 31 36 42 47 52 57 63 68 73 78 83 89 94 99.
        let s = space_timesteps(300, &[10, 15, 20]).unwrap();
        let mut want: Vec<usize> = (0..10).map(|k| 11 * k).collect();
        want.extend(
            [0, 7, 14, 21, 28, 35, 42, 49, 57, 64, 71, 78, 85, 92, 99]
                .iter()
                .map(|x| 100 + x),
        );
        want.extend(
            [
                0, 5, 10, 16, 21, 26, 31, 36, 42, 47, 52, 57, 63, 68, 73, 78, 83, 89, 94, 99,
            ]
            .iter()
            .map(|x| 200 + x),
        );
        assert_eq!(s, want);
    }

    #[test]
    fn uneven_sections_give_first_sections_the_extra_steps() {
        // T = 10, [3, 2, 1]: sizes 4, 3, 3 at 0, 4, 7. Strides 3/2 = 1.5 → 0, 1.5→2, 3;
        // 2/1 = 2 → 4, 6; single step → 7.
        assert_eq!(space_timesteps(10, &[3, 2, 1]).unwrap(), [0, 2, 3, 4, 6, 7]);
    }

    #[test]
    fn half_rounds_to_even() {
        // T = 5, [3]: stride 4/2 = 2 → 0, 2, 4 (no tie); T = 4, [3]: stride 1.5 → 0, 1.5 → 2, 3.
        assert_eq!(space_timesteps(4, &[3]).unwrap(), [0, 2, 3]);
        // T = 6, [3]: stride 2.5 → 0, 2.5 → 2 (even), 5.
        assert_eq!(space_timesteps(6, &[3]).unwrap(), [0, 2, 5]);
    }

    #[test]
    fn section_errors() {
        assert!(space_timesteps(10, &[11]).is_err());
        assert!(space_timesteps(10, &[3, 6]).is_err()); // second section has 5 steps
        assert!(space_timesteps(10, &[0]).is_err());
        assert!(space_timesteps(10, &[]).is_err());
        assert!(space_timesteps(0, &[1]).is_err());
    }

    #[test]
    fn ddim_stride_rule() {
        let s50 = space_timesteps_ddim_stride(1000, 50).unwrap();
        assert_eq!(s50, (0..1000).step_by(20).collect::<Vec<_>>());
        let s100 = space_timesteps_ddim_stride(1000, 100).unwrap();
        assert_eq!(s100, (0..1000).step_by(10).collect::<Vec<_>>());
        // ddim1000 → stride 1 (all steps).
        assert_eq!(space_timesteps_ddim_stride(1000, 1000).unwrap().len(), 1000);
        // 1000/k never rounds up to exactly 999 for any integer k.
        assert!(space_timesteps_ddim_stride(1000, 999).is_err());
        assert!(space_timesteps_ddim_stride(1000, 1).is_err());
    }

    #[test]
    fn parse_spec_strings() {
        assert_eq!(parse_timestep_respacing(50, "").unwrap().len(), 50);
        assert_eq!(
            parse_timestep_respacing(1000, "ddim50").unwrap(),
            space_timesteps_ddim_stride(1000, 50).unwrap()
        );
        assert_eq!(
            parse_timestep_respacing(300, "10, 15,20").unwrap(),
            space_timesteps(300, &[10, 15, 20]).unwrap()
        );
        assert!(parse_timestep_respacing(1000, "ddimx").is_err());
        assert!(parse_timestep_respacing(1000, "fast").is_err());
    }

    #[test]
    fn absurd_section_counts_are_errors_not_overflows() {
        let huge = format!("{},1", usize::MAX);
        assert!(parse_timestep_respacing(1000, &huge).is_err());
        assert!(parse_timestep_respacing(1000, &format!("ddim{}", usize::MAX)).is_err());
        assert!(parse_timestep_respacing(10, &"1,".repeat(20)[..39]).is_err());
    }

    #[test]
    fn spacing_names() {
        for s in [Spacing::Respace, Spacing::Leading, Spacing::Trailing] {
            assert_eq!(s.name().parse::<Spacing>().unwrap(), s);
        }
        assert_eq!(" Trailing ".parse::<Spacing>().unwrap(), Spacing::Trailing);
        assert!("linspace".parse::<Spacing>().is_err());
        assert_eq!(Spacing::default(), Spacing::Respace);
        assert!(!Spacing::Respace.is_diffusers() && Spacing::Leading.is_diffusers());
    }

    #[test]
    fn leading_by_hand() {
        // T div N = 20: k·20 + offset for k = 49..0 (MLD: offset 1 → 981 … 1).
        let mld = diffusers_timesteps(Spacing::Leading, 1000, 50, 1).unwrap();
        assert_eq!(mld, (0..50).rev().map(|k| 20 * k + 1).collect::<Vec<_>>());
        // 7 steps: ratio 142, 852 … 0 (the top 148 steps are never visited).
        let l7 = diffusers_timesteps(Spacing::Leading, 1000, 7, 0).unwrap();
        assert_eq!(l7, [852, 710, 568, 426, 284, 142, 0]);
        // The largest offset that keeps 980 + offset < 1000, and one past it.
        assert_eq!(
            diffusers_timesteps(Spacing::Leading, 1000, 50, 19).unwrap()[0],
            999
        );
        let e = diffusers_timesteps(Spacing::Leading, 1000, 50, 20).unwrap_err();
        assert!(e.to_string().contains("reaches timestep 1000"), "{e}");
    }

    #[test]
    fn trailing_by_hand() {
        // MoLA: 1000/50 = 20 → 1000, 980, …, 20, minus one.
        let mola = diffusers_timesteps(Spacing::Trailing, 1000, 50, 1).unwrap();
        assert_eq!(mola, (1..=50).rev().map(|k| 20 * k - 1).collect::<Vec<_>>());
        // 1000/16 = 62.5: 937.5 and 812.5 round half to even (938, 812), then minus one.
        let t16 = diffusers_timesteps(Spacing::Trailing, 1000, 16, 0).unwrap();
        assert_eq!(&t16[..4], [999, 937, 874, 811]);
        assert_eq!(t16.len(), 16);
        // The offset has no effect.
        assert_eq!(
            diffusers_timesteps(Spacing::Trailing, 1000, 16, 7).unwrap(),
            t16
        );
        // ⌈1000/(1000/61)⌉ = 62 in floating point: diffusers would append a step at −1.
        let e = diffusers_timesteps(Spacing::Trailing, 1000, 61, 0).unwrap_err();
        assert!(e.to_string().contains("gives 62 timesteps"), "{e}");
        assert_eq!(
            diffusers_timesteps(Spacing::Trailing, 4, 4, 0).unwrap(),
            [3, 2, 1, 0]
        );
    }

    #[test]
    fn diffusers_spacing_errors() {
        for sp in [Spacing::Leading, Spacing::Trailing] {
            assert!(diffusers_timesteps(sp, 1000, 0, 0).is_err());
            assert!(diffusers_timesteps(sp, 1000, 1001, 0).is_err());
        }
        assert!(diffusers_timesteps(Spacing::Respace, 1000, 10, 0).is_err());
    }

    #[test]
    fn respaced_betas_reproduce_kept_alpha_bars() {
        let ac = [0.9, 0.72, 0.504, 0.3];
        let (b, map) = respaced_betas(&ac, &[3, 0, 2, 2]).unwrap();
        assert_eq!(map, [0, 2, 3]);
        // β = 1 − 0.9/1, 1 − 0.504/0.9, 1 − 0.3/0.504.
        let want = [0.1, 1.0 - 0.504 / 0.9, 1.0 - 0.3 / 0.504];
        for (g, w) in b.iter().zip(want) {
            assert!((g - w).abs() < 1e-15);
        }
        assert!(respaced_betas(&ac, &[4]).is_err());
        assert!(respaced_betas(&ac, &[]).is_err());
    }
}
