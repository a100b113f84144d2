//! The sampler a model's configuration and a session's choices ask for: one place that turns
//! `diffusion.*` and `defaults.*` of the model file, a step count, an optional guided-diffusion
//! respacing string and the sampler kind into a ready [`DiffusionSampler`] or [`FlowSampler`].

use super::flow::{FlowSampler, OdeMethod};
use super::lcm::{LcmSampler, LcmTimesteps, TIMESTEP_SCALING};
use super::respace::{diffusers_timesteps, parse_timestep_respacing, space_timesteps, Spacing};
use super::sampler::{DiffusionSampler, SamplerKind};
use super::schedule::betas;
use crate::config::{Defaults, DiffusionConfig, MAX_FLOW_STEPS};
use crate::error::{bad_file, invalid_arg, Error, Result};

/// Which reverse process to run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Method {
    /// Ancestral DDPM (guided-diffusion `p_sample`): fresh noise at every step but the last.
    Ddpm,
    /// DDIM with the chosen (or the file's default) η.
    Ddim,
    /// An ODE solver of flow matching.
    Ode(OdeMethod),
    /// The latent consistency sampler ([`super::lcm`]) of a model with `diffusion.spacing`
    /// `lcm`.
    Lcm,
}

/// A session's sampling choices; `None` means the model file's default.
#[derive(Debug, Clone, Copy)]
pub struct SamplerChoice<'a> {
    /// The reverse process; it must suit the model (DDPM/DDIM for diffusion, an ODE method for
    /// flow matching).
    pub method: Method,
    /// Sampling steps: 1..=`num_timesteps` (diffusion) or 1..=[`MAX_FLOW_STEPS`] (flow).
    pub steps: Option<usize>,
    /// A guided-diffusion `timestep_respacing` string (`"ddim50"`, `"10"`, `"15,15,8,6,6"`) for a
    /// model with `diffusion.spacing` `respace`; it sets the step count.
    pub respacing: Option<&'a str>,
    /// DDIM's η, finite and ≥ 0 (0 = deterministic); only [`Method::Ddim`] reads it.
    pub eta: Option<f32>,
    /// Clamp every x̂0 estimate to [−1, 1] (diffusion models only).
    pub clip_denoised: Option<bool>,
}

/// The sampler [`build_sampler`] made.
#[derive(Debug, Clone)]
pub enum BuiltSampler {
    /// A DDPM or DDIM sampler over the kept timesteps of a diffusion model.
    Diffusion(Box<DiffusionSampler>),
    /// An ODE sampler of a flow-matching model (`parameterization` `velocity` or `flow`).
    Flow(FlowSampler),
    /// The latent consistency sampler of a model with `diffusion.spacing` `lcm`.
    Lcm(LcmSampler),
}

/// Builds the sampler for a model's `diffusion` configuration and sampling `defaults`:
/// flow models get an ODE sampler; diffusion models a guided-diffusion respaced process
/// (`spacing` `respace`: `steps` by the section rule, or the kept steps of a respacing string)
/// or diffusers' DDIM/DDPM schedule (`leading`, `trailing`: `steps` only).
///
/// Models with `spacing` `lcm` get the latent consistency sampler over their timestep rule.
///
/// Errors (`InvalidArgument`): a step count out of range (for `lcm`, one the rule has no
/// timesteps for, naming the counts it has), a sampler of the other family, a
/// respacing string that does not parse, disagrees with an explicit `steps`, or is given to a
/// diffusers-spaced or flow model, a negative or non-finite η.
pub fn build_sampler(
    dc: &DiffusionConfig,
    defaults: &Defaults,
    choice: &SamplerChoice,
) -> Result<BuiltSampler> {
    let flow_model = matches!(dc.parameterization.as_str(), "velocity" | "flow");
    let name = method_name(choice.method);
    let lcm_model = dc.spacing.parse::<Spacing>().ok() == Some(Spacing::Lcm);
    match (lcm_model, choice.method) {
        (true, Method::Lcm) => {
            if let Some(spec) = choice.respacing {
                return Err(invalid_arg!(
                    "respacing {spec:?} picks steps of a diffusion schedule; this latent \
                     consistency model takes only a step count"
                ));
            }
            let rule = LcmTimesteps::from_config(dc)?;
            let steps = choice.steps.unwrap_or(defaults.steps);
            let timesteps = rule.timesteps(steps, dc.num_timesteps)?;
            let schedule = dc.schedule.parse().map_err(|_| {
                bad_file!(
                    "config diffusion.schedule `{}` is not supported",
                    dc.schedule
                )
            })?;
            let base = betas(schedule, dc.num_timesteps);
            let scaling = dc.timestep_scaling.unwrap_or(TIMESTEP_SCALING);
            return Ok(BuiltSampler::Lcm(LcmSampler::new(
                &base, timesteps, scaling,
            )?));
        }
        (true, _) => {
            return Err(invalid_arg!(
                "sampler {name} does not fit this latent consistency model, which samples with lcm"
            ))
        }
        (false, Method::Lcm) => {
            return Err(invalid_arg!(
                "sampler lcm needs a latent consistency model (diffusion.spacing `lcm`); this \
                 model takes {}",
                if flow_model {
                    "euler, heun or midpoint"
                } else {
                    "ddpm or ddim"
                }
            ))
        }
        (false, _) => {}
    }
    match (flow_model, choice.method) {
        (true, Method::Ode(m)) => {
            if let Some(spec) = choice.respacing {
                return Err(invalid_arg!(
                    "respacing {spec:?} picks steps of a diffusion schedule; this flow-matching \
                     model integrates an ODE and takes only a step count"
                ));
            }
            let steps = choice.steps.unwrap_or(defaults.steps);
            if steps == 0 || steps > MAX_FLOW_STEPS {
                return Err(invalid_arg!("steps must be between 1 and {MAX_FLOW_STEPS}, got {steps}"));
            }
            return Ok(BuiltSampler::Flow(FlowSampler::new(m, steps)?));
        }
        (true, _) => {
            return Err(invalid_arg!(
                "sampler {name} needs a diffusion model; this flow-matching model takes euler, heun or midpoint"
            ))
        }
        (false, Method::Ode(_)) => {
            return Err(invalid_arg!(
                "sampler {name} needs a flow-matching model; this diffusion model takes ddpm or ddim"
            ))
        }
        (false, _) => {}
    }
    let kind = match choice.method {
        Method::Ddim => {
            let eta = choice.eta.unwrap_or(defaults.eta);
            if !(eta.is_finite() && eta >= 0.0) {
                return Err(invalid_arg!("eta must be a finite number, 0 or more"));
            }
            SamplerKind::Ddim { eta }
        }
        _ => SamplerKind::Ddpm,
    };
    let bad = |what: &str, v: &str| bad_file!("config diffusion.{what} `{v}` is not supported");
    let schedule = dc
        .schedule
        .parse()
        .map_err(|_| bad("schedule", &dc.schedule))?;
    let param = dc
        .parameterization
        .parse()
        .map_err(|_| bad("parameterization", &dc.parameterization))?;
    let variance = dc
        .variance
        .parse()
        .map_err(|_| bad("variance", &dc.variance))?;
    let spacing: Spacing = dc
        .spacing
        .parse()
        .map_err(|_| bad("spacing", &dc.spacing))?;
    let t = dc.num_timesteps;
    let base = betas(schedule, t);
    let clip = choice.clip_denoised.unwrap_or(dc.clip_denoised);
    // The file's default respacing applies when the session asks for neither.
    let respacing = choice.respacing.or(match choice.steps {
        None => defaults.respacing.as_deref(),
        Some(_) => None,
    });
    let sampler = match (spacing, respacing) {
        (Spacing::Respace, Some(spec)) => {
            let kept = respaced_steps(t, spec, choice.steps)?;
            DiffusionSampler::new(&base, &kept, kind, param, variance, clip)?
        }
        (Spacing::Respace, None) => {
            let steps = steps_within(choice.steps.unwrap_or(defaults.steps), t)?;
            let kept = space_timesteps(t, &[steps])?;
            DiffusionSampler::new(&base, &kept, kind, param, variance, clip)?
        }
        (_, Some(spec)) => {
            return Err(invalid_arg!(
                "respacing {spec:?} is guided-diffusion's (models with diffusion.spacing \
                 `respace`); this model samples diffusers' `{spacing}` timesteps, which take \
                 only a step count"
            ))
        }
        (_, None) => {
            let steps = steps_within(choice.steps.unwrap_or(defaults.steps), t)?;
            let ts = diffusers_timesteps(spacing, t, steps, dc.steps_offset)?;
            DiffusionSampler::new_diffusers(
                &base,
                &ts,
                dc.set_alpha_to_one,
                kind,
                param,
                variance,
                clip,
            )?
        }
    };
    Ok(BuiltSampler::Diffusion(Box::new(sampler)))
}

fn method_name(m: Method) -> &'static str {
    match m {
        Method::Ddpm => "ddpm",
        Method::Ddim => "ddim",
        Method::Ode(OdeMethod::Euler) => "euler",
        Method::Ode(OdeMethod::Heun) => "heun",
        Method::Ode(OdeMethod::Midpoint) => "midpoint",
        Method::Lcm => "lcm",
    }
}

fn steps_within(steps: usize, num_timesteps: usize) -> Result<usize> {
    if steps == 0 || steps > num_timesteps {
        return Err(invalid_arg!(
            "steps must be between 1 and {num_timesteps} for this model, got {steps}"
        ));
    }
    Ok(steps)
}

/// The kept steps of a respacing string, checked against an explicit step count.
fn respaced_steps(num_timesteps: usize, spec: &str, steps: Option<usize>) -> Result<Vec<usize>> {
    if spec.trim().is_empty() {
        return Err(invalid_arg!(
            "respacing is empty: give none for the model's spacing, or e.g. \"ddim50\", \"50\" \
             or \"{num_timesteps}\" (every step)"
        ));
    }
    let kept = parse_timestep_respacing(num_timesteps, spec).map_err(|e| {
        let why = match e {
            Error::InvalidArgument(m) => m,
            other => other.to_string(),
        };
        invalid_arg!("respacing {spec:?} over {num_timesteps} training steps: {why}")
    })?;
    match steps {
        Some(n) if n != kept.len() => Err(invalid_arg!(
            "steps {n} disagrees with respacing {spec:?}, which keeps {} steps (give one of \
             the two, or both agreeing)",
            kept.len()
        )),
        _ => Ok(kept),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diffusion::{space_timesteps_ddim_stride, Convention};

    fn dc(spacing: &str, parameterization: &str) -> DiffusionConfig {
        DiffusionConfig {
            num_timesteps: 1000,
            schedule: "scaled_linear".into(),
            parameterization: parameterization.into(),
            variance: "fixed_small".into(),
            clip_denoised: false,
            uncond: "zeros".into(),
            spacing: spacing.into(),
            steps_offset: 1,
            set_alpha_to_one: false,
            lcm_timesteps: None,
            original_inference_steps: None,
            timestep_scaling: None,
        }
    }

    fn defaults() -> Defaults {
        Defaults {
            sampler: "ddim".into(),
            steps: 50,
            guidance: 1.0,
            eta: 0.0,
            frames: 1,
            respacing: None,
            guidance_by_steps: None,
        }
    }

    fn choice(method: Method, steps: Option<usize>, respacing: Option<&str>) -> SamplerChoice<'_> {
        SamplerChoice {
            method,
            steps,
            respacing,
            eta: None,
            clip_denoised: None,
        }
    }

    fn diffusion(c: &DiffusionConfig, ch: &SamplerChoice) -> Result<DiffusionSampler> {
        match build_sampler(c, &defaults(), ch)? {
            BuiltSampler::Diffusion(d) => Ok(*d),
            BuiltSampler::Flow(_) | BuiltSampler::Lcm(_) => panic!("a diffusion sampler"),
        }
    }

    fn err(c: &DiffusionConfig, ch: &SamplerChoice) -> String {
        match build_sampler(c, &defaults(), ch) {
            Err(e @ Error::InvalidArgument(_)) => e.to_string(),
            other => panic!("{ch:?} gave {other:?}"),
        }
    }

    #[test]
    fn latent_consistency_models_take_lcm_and_their_step_counts() {
        let mut c = dc("lcm", "epsilon");
        c.steps_offset = 0;
        c.lcm_timesteps = Some("motionlcm_v2".into());
        let mut d = defaults();
        d.steps = 1;
        let lcm_of = |c: &DiffusionConfig, ch: &SamplerChoice| match build_sampler(c, &d, ch) {
            Ok(BuiltSampler::Lcm(s)) => Ok(s),
            Ok(_) => panic!("an lcm sampler"),
            Err(e) => Err(e.to_string()),
        };
        let lcm = |ch: &SamplerChoice| lcm_of(&c, ch);
        assert_eq!(
            lcm(&choice(Method::Lcm, None, None)).unwrap().timesteps(),
            [799]
        );
        let four = lcm(&choice(Method::Lcm, Some(4), None)).unwrap();
        assert_eq!(four.timesteps(), [699, 399, 299, 299]);
        let e = lcm(&choice(Method::Lcm, Some(3), None)).unwrap_err();
        assert!(
            e.contains("no 3-step schedule") && e.contains("1, 2, 4"),
            "{e}"
        );
        let e = lcm(&choice(Method::Ddim, None, None)).unwrap_err();
        assert!(e.contains("samples with lcm"), "{e}");
        let e = lcm(&choice(Method::Lcm, None, Some("10"))).unwrap_err();
        assert!(e.contains("takes only a step count"), "{e}");
        let mut v1 = c.clone();
        v1.lcm_timesteps = Some("grid".into());
        v1.original_inference_steps = Some(50);
        let two = lcm_of(&v1, &choice(Method::Lcm, Some(2), None)).unwrap();
        assert_eq!(two.timesteps(), [999, 499]);
        // A diffusion model refuses lcm.
        let e = err(&dc("leading", "epsilon"), &choice(Method::Lcm, None, None));
        assert!(e.contains("needs a latent consistency model"), "{e}");
    }

    #[test]
    fn a_default_respacing_applies_when_neither_steps_nor_respacing_are_asked() {
        let c = dc("respace", "x0");
        let mut d = defaults();
        d.respacing = Some("15,15,8,6,6".into());
        let built = |ch: &SamplerChoice| match build_sampler(&c, &d, ch).unwrap() {
            BuiltSampler::Diffusion(s) => s,
            BuiltSampler::Flow(_) | BuiltSampler::Lcm(_) => panic!("a diffusion model"),
        };
        // The kept steps of FineMoGen's "15,15,8,6,6", ascending (mingyuan-zhang/FineMoGen
        // `configs/finemogen/finemogen_t2m.py`; docs/official/finemogen.md#respacing).
        let s = built(&choice(Method::Ddim, None, None));
        let map = s.timestep_map();
        assert_eq!(map.len(), 50);
        assert_eq!(&map[..5], &[0, 14, 28, 43, 57]);
        assert_eq!(&map[14..16], &[199, 200]);
        assert_eq!(&map[44..], &[800, 840, 880, 919, 959, 999]);
        // An explicit step count or respacing wins.
        assert_eq!(
            built(&choice(Method::Ddim, Some(10), None)).timestep_map(),
            space_timesteps(1000, &[10]).unwrap()
        );
        assert_eq!(
            built(&choice(Method::Ddim, None, Some("ddim50"))).timestep_map(),
            space_timesteps_ddim_stride(1000, 50).unwrap()
        );
    }

    #[test]
    fn respace_takes_steps_or_a_respacing_string() {
        let mut c = dc("respace", "epsilon");
        c.steps_offset = 0;
        c.set_alpha_to_one = true;
        let s = diffusion(&c, &choice(Method::Ddpm, Some(10), None)).unwrap();
        assert_eq!(s.timestep_map(), space_timesteps(1000, &[10]).unwrap());
        assert_eq!(s.convention(), Convention::GuidedDiffusion);
        let s = diffusion(&c, &choice(Method::Ddim, None, None)).unwrap();
        assert_eq!(s.num_steps(), 50, "the file's default");
        // "ddim50" keeps every 20th step, unlike the section rule's 50 steps.
        let ddim50 = choice(Method::Ddim, None, Some("ddim50"));
        let s = diffusion(&c, &ddim50).unwrap();
        assert_eq!(
            s.timestep_map(),
            space_timesteps_ddim_stride(1000, 50).unwrap()
        );
        let s = diffusion(&c, &choice(Method::Ddim, Some(50), Some("ddim50"))).unwrap();
        assert_eq!(s.num_steps(), 50);
        // Five sections of 200 steps: 15 + 15 + 8 + 6 + 6 = 50 kept steps.
        let sections = choice(Method::Ddpm, Some(50), Some("15,15,8,6,6"));
        let s = diffusion(&c, &sections).unwrap();
        assert_eq!(
            s.timestep_map(),
            space_timesteps(1000, &[15, 15, 8, 6, 6]).unwrap()
        );
        let e = err(&c, &choice(Method::Ddpm, Some(49), Some("15,15,8,6,6")));
        assert!(
            e.contains("steps 49 disagrees with respacing \"15,15,8,6,6\", which keeps 50"),
            "{e}"
        );
        let e = err(&c, &choice(Method::Ddpm, None, Some(" ")));
        assert!(e.contains("respacing is empty"), "{e}");
        let e = err(&c, &choice(Method::Ddpm, None, Some("ddimx")));
        assert!(
            e.contains("respacing \"ddimx\" over 1000 training steps"),
            "{e}"
        );
        let e = err(&c, &choice(Method::Ddpm, None, Some("ddim999")));
        assert!(e.contains("cannot create exactly 999 steps"), "{e}");
        let e = err(&c, &choice(Method::Ddpm, Some(1001), None));
        assert!(
            e.contains("steps must be between 1 and 1000 for this model, got 1001"),
            "{e}"
        );
    }

    #[test]
    fn diffusers_spacing_takes_steps_only() {
        let mld = dc("leading", "epsilon");
        let s = diffusion(&mld, &choice(Method::Ddim, None, None)).unwrap();
        assert_eq!(s.convention(), Convention::Diffusers);
        assert_eq!((s.model_timestep(49), s.model_timestep(0)), (981.0, 1.0));
        let mola = dc("trailing", "epsilon");
        let s = diffusion(&mola, &choice(Method::Ddim, Some(10), None)).unwrap();
        assert_eq!((s.model_timestep(9), s.model_timestep(0)), (999.0, 99.0));
        let e = err(&mola, &choice(Method::Ddim, None, Some("ddim50")));
        assert!(
            e.contains("respacing \"ddim50\" is guided-diffusion's")
                && e.contains("diffusers' `trailing` timesteps"),
            "{e}"
        );
        let e = err(&mola, &choice(Method::Ddim, Some(61), None));
        assert!(e.contains("cannot take 61 steps"), "{e}");
        let mut far = dc("leading", "epsilon");
        far.steps_offset = 30;
        let e = err(&far, &choice(Method::Ddim, None, None));
        assert!(e.contains("reaches timestep 1010"), "{e}");
    }

    #[test]
    fn families_and_eta() {
        let flow = dc("respace", "velocity");
        let euler = choice(Method::Ode(OdeMethod::Euler), Some(7), None);
        match build_sampler(&flow, &defaults(), &euler).unwrap() {
            BuiltSampler::Flow(f) => assert_eq!(f.num_steps(), 7),
            other => panic!("{other:?}"),
        }
        let e = err(
            &flow,
            &choice(Method::Ode(OdeMethod::Heun), None, Some("ddim10")),
        );
        assert!(
            e.contains("this flow-matching model integrates an ODE"),
            "{e}"
        );
        let e = err(&flow, &choice(Method::Ddim, None, None));
        assert!(e.contains("sampler ddim needs a diffusion model"), "{e}");
        let c = dc("leading", "epsilon");
        let e = err(&c, &choice(Method::Ode(OdeMethod::Midpoint), None, None));
        assert!(
            e.contains("sampler midpoint needs a flow-matching model"),
            "{e}"
        );
        let mut bad_eta = choice(Method::Ddim, None, None);
        bad_eta.eta = Some(f32::NAN);
        assert!(err(&c, &bad_eta).contains("eta must be a finite number, 0 or more"));
    }
}
