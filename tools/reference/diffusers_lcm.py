"""Reference of MotionLCM's latent consistency sampling (Dai-Wenxun/MotionLCM v1.0 f534a7f and
v2.0 086f8db): the loop runs diffusers' own `LCMScheduler` (diffusers 0.42.1 here; both MotionLCM
tags pin 0.24.0, whose `step` and grid rule are the same), so the oracle of the Rust parity test
(tests/diffusers_lcm.rs) is the independent implementation itself.

- `scheduler()`: an `LCMScheduler` as MotionLCM configures it: 1000 training steps, scaled_linear
  betas 0.00085-0.012, epsilon prediction, clip_sample False, set_alpha_to_one False,
  original_inference_steps 50, timestep_scaling 10.
- `run(sched, timesteps_or_n, x_T, bias, noise)`: v1 calls `set_timesteps(n)`; a list sets
  MotionLCM v2's table the way its own scheduler does (the list as given, the step index set once
  from the first timestep, so a repeated 299 re-noises to 299 and denoises again: diffusers'
  `set_timesteps` refuses a list that is not strictly descending, so the list is written into
  `timesteps` directly). The network is `fake_eps` of tools/reference/diffusers_ddim.py; the
  re-noising noise is the stored `noise[k]` (diffusers draws it through `randn_tensor`, replaced
  here). Returns the timesteps, each step's sample after the step (`prev_sample`) and each
  `denoised`.
"""
import torch
from diffusers import LCMScheduler
from diffusers.schedulers import scheduling_lcm

from reference.diffusers_ddim import fake_eps


def scheduler():
    return LCMScheduler(
        num_train_timesteps=1000,
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="scaled_linear",
        clip_sample=False,
        set_alpha_to_one=False,
        original_inference_steps=50,
        prediction_type="epsilon",
        timestep_scaling=10.0,
    )


def run(sched, steps, x_t, bias, noise):
    if isinstance(steps, int):
        sched.set_timesteps(steps)
    else:
        sched.set_timesteps(timesteps=[steps[0]])
        sched.timesteps = torch.tensor(steps, dtype=torch.int64)
        sched.num_inference_steps = len(steps)
    timesteps = [int(t) for t in sched.timesteps]
    draws = iter(noise)
    original = scheduling_lcm.randn_tensor
    scheduling_lcm.randn_tensor = lambda shape, **kw: next(draws).reshape(shape).clone()
    try:
        x = x_t.clone()
        samples, denoised = [], []
        for t in sched.timesteps:
            out = sched.step(fake_eps(x, int(t), bias), t, x)
            x = out.prev_sample
            samples.append(x.clone())
            denoised.append(out.denoised.clone())
    finally:
        scheduling_lcm.randn_tensor = original
    return timesteps, torch.stack(samples), torch.stack(denoised)
