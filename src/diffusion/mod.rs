//! Diffusion: noise schedules, respacing, and the DDPM/DDIM samplers. The sampler drives any
//! denoiser through plain slices: it never knows which network produced a prediction.
//!
//! Semantics follow OpenAI guided-diffusion (`gaussian_diffusion.py`, `respace.py`) as used by
//! FLAME and MDM: f64 tables, f32 per-step arithmetic (see [`DiffusionSampler::step`]).

mod respace;
mod sampler;
mod schedule;

pub use respace::{
    parse_timestep_respacing, respaced_betas, space_timesteps, space_timesteps_ddim_stride,
};
pub use sampler::{guide, DiffusionSampler, Parameterization, SamplerKind, Variance};
pub use schedule::{betas, BetaSchedule, Schedule};
