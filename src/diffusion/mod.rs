//! Diffusion: noise schedules, respacing, and the DDPM/DDIM samplers. The sampler drives any
//! denoiser through plain slices: it never knows which network produced a prediction.
