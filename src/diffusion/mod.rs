//! Diffusion: noise schedules, respacing, the DDPM/DDIM samplers, and the fixed-step ODE
//! samplers of flow matching ([`flow`]). Samplers drive any denoiser through plain slices: they
//! never know which network produced a prediction.
//!
//! Semantics follow OpenAI guided-diffusion (`gaussian_diffusion.py`, `respace.py`) as used by
//! FLAME and MDM: f64 tables, f32 per-step arithmetic (see [`DiffusionSampler::step`]).

pub mod flow;
mod respace;
mod sampler;
mod schedule;

pub use respace::{
    parse_timestep_respacing, respaced_betas, space_timesteps, space_timesteps_ddim_stride,
};
pub use sampler::{
    guide, DiffusionSampler, Parameterization, SamplerKind, Variance, X0Replacement,
};
pub use schedule::{betas, BetaSchedule, Schedule};
