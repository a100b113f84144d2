//! The sampler a model's configuration and a session's choices ask for: one place that turns
//! `diffusion.*` and `defaults.*` of the model file, a step count, an optional guided-diffusion
//! respacing string and the sampler kind into a ready [`DiffusionSampler`] or [`FlowSampler`].

use super::flow::{FlowSampler, OdeMethod};
use super::respace::{diffusers_timesteps, parse_timestep_respacing, space_timesteps, Spacing};
use super::sampler::{DiffusionSampler, SamplerKind};
use super::schedule::betas;
use crate::config::{Defaults, DiffusionConfig, MAX_FLOW_STEPS};
use crate::error::{bad_file, invalid_arg, Error, Result};

/// Which reverse process to run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Method {
    Ddpm,
    /// DDIM with the chosen (or the file's default) η.
    Ddim,
    /// An ODE solver of flow matching.
    Ode(OdeMethod),
}

/// A session's sampling choices; `None` means the model file's default.
#[derive(Debug, Clone, Copy)]
pub struct SamplerChoice<'a> {
    pub method: Method,
    pub steps: Option<usize>,
    /// A guided-diffusion `timestep_respacing` string (`"ddim50"`, `"10"`, `"15,15,8,6,6"`) for a
    /// model with `diffusion.spacing` `respace`; it sets the step count.
    pub respacing: Option<&'a str>,
    pub eta: Option<f32>,
    pub clip_denoised: Option<bool>,
}

/// The sampler [`build_sampler`] made.
#[derive(Debug, Clone)]
pub enum BuiltSampler {
    Diffusion(DiffusionSampler),
    Flow(FlowSampler),
}

/// Builds the sampler for a model's `diffusion` configuration and sampling `defaults`:
/// flow models get an ODE sampler; diffusion models a guided-diffusion respaced process
/// (`spacing` `respace`: `steps` by the section rule, or the kept steps of a respacing string)
/// or diffusers' DDIM/DDPM schedule (`leading`, `trailing`: `steps` only).
///
/// Errors (`InvalidArgument`): a step count out of range, a sampler of the other family, a
/// respacing string that does not parse, disagrees with an explicit `steps`, or is given to a
/// diffusers-spaced or flow model, a negative or non-finite η.
pub fn build_sampler(
    dc: &DiffusionConfig,
    defaults: &Defaults,
    choice: &SamplerChoice,
) -> Result<BuiltSampler> {
    let flow_model = matches!(dc.parameterization.as_str(), "velocity" | "flow");
    let name = method_name(choice.method);
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
                return Err(invalid_arg!("steps {steps} outside 1..={MAX_FLOW_STEPS}"));
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
                return Err(invalid_arg!("eta must be a finite value >= 0"));
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
    let spacing: Spacing = dc.spacing.parse().map_err(|_| bad("spacing", &dc.spacing))?;
    let t = dc.num_timesteps;
    let base = betas(schedule, t);
    let clip = choice.clip_denoised.unwrap_or(dc.clip_denoised);
    let sampler = match (spacing, choice.respacing) {
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
    Ok(BuiltSampler::Diffusion(sampler))
}

fn method_name(m: Method) -> &'static str {
    match m {
        Method::Ddpm => "ddpm",
        Method::Ddim => "ddim",
        Method::Ode(OdeMethod::Euler) => "euler",
        Method::Ode(OdeMethod::Heun) => "heun",
        Method::Ode(OdeMethod::Midpoint) => "midpoint",
    }
}

fn steps_within(steps: usize, num_timesteps: usize) -> Result<usize> {
    if steps == 0 || steps > num_timesteps {
        return Err(invalid_arg!("steps {steps} outside 1..={num_timesteps}"));
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
