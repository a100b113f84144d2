//! Diffusion: noise schedules, timestep spacing (guided-diffusion's respacing and diffusers'
//! leading/trailing), the DDPM/DDIM samplers, the fixed-step ODE samplers of flow matching
//! ([`flow`]), the latent consistency sampler ([`lcm`]), and [`build_sampler`], which picks and builds one from a model's configuration.
//! Samplers drive any denoiser through plain slices: they never know which network produced a
//! prediction.
//!
//! Semantics follow OpenAI guided-diffusion (`gaussian_diffusion.py`, `respace.py`) as used by
//! FLAME and MDM: f64 tables, f32 per-step arithmetic (see [`DiffusionSampler::step`]); models
//! with diffusers spacing (MoLA, MLD) follow diffusers' `DDIMScheduler` instead
//! ([`DiffusionSampler::new_diffusers`]).
//!
//! [`flow`]: crate::diffusion::flow
//! [`lcm`]: crate::diffusion::lcm
//! [`build_sampler`]: crate::diffusion::build_sampler
//! [`DiffusionSampler::step`]: crate::diffusion::DiffusionSampler::step
//! [`DiffusionSampler::new_diffusers`]: crate::diffusion::DiffusionSampler::new_diffusers

pub mod flow;
mod from_config;
pub mod lcm;
mod respace;
mod sampler;
mod schedule;

pub use from_config::{build_sampler, BuiltSampler, Method, SamplerChoice};
pub use respace::{
    diffusers_timesteps, parse_timestep_respacing, respaced_betas, space_timesteps,
    space_timesteps_ddim_stride, Spacing,
};
pub use sampler::{
    guide, Convention, DiffusionSampler, Parameterization, SamplerKind, Variance, X0Guide,
    X0Replacement,
};
pub use schedule::{betas, diffusers_alphas_cumprod, BetaSchedule, Schedule};
