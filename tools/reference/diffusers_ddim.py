"""Reference of diffusers' DDIM sampling as MoLA and MLD configure it
(docs/official/mola-mld.md#mola-scheduler, docs/official/mola-mld.md#mld-scheduler, docs/official/mola-mld.md#scheduler-tables-in-float32):
the loop runs diffusers' own `DDIMScheduler` (diffusers 0.42.1), so the oracle of the Rust parity
test (tests/diffusers_ddim.rs) is the independent implementation itself, not a re-derivation.

- `scheduler(spacing, steps_offset, set_alpha_to_one, ...)`: a `DDIMScheduler` with 1000 training
  steps and scaled_linear betas 0.00085-0.012 (both models), clip_sample False unless asked.
- `fake_eps(x, t, bias)`: the deterministic stand-in network shared with the Rust test,
  eps = (0.5·x + bias) + s(t) with s(t) = float32(t·0.0003 − 0.2) (t the integer timestep the
  network sees), all in float32.
- `run(sched, steps, x_T, bias, eta, noise)`: `set_timesteps(steps)` then one `step` per timestep,
  returning the timesteps, the sample after every step and every `pred_original_sample`. With
  eta > 0 the per-step noise is passed as `variance_noise` (stored, so the Rust test replays it).
"""
import torch
from diffusers import DDIMScheduler

NUM_TRAIN_TIMESTEPS = 1000
BETA_START, BETA_END = 0.00085, 0.012


def scheduler(spacing, steps_offset=0, set_alpha_to_one=False, prediction_type="epsilon",
              clip_sample=False):
    return DDIMScheduler(
        num_train_timesteps=NUM_TRAIN_TIMESTEPS,
        beta_start=BETA_START,
        beta_end=BETA_END,
        beta_schedule="scaled_linear",
        clip_sample=clip_sample,
        set_alpha_to_one=set_alpha_to_one,
        steps_offset=steps_offset,
        prediction_type=prediction_type,
        timestep_spacing=spacing,
    )


def fake_eps(x, t, bias):
    shift = torch.tensor(t * 0.0003 - 0.2, dtype=torch.float32)
    return (x * 0.5 + bias) + shift


def run(sched, steps, x_t, bias, eta=0.0, noise=None):
    sched.set_timesteps(steps)
    timesteps = [int(t) for t in sched.timesteps]
    x = x_t.clone()
    samples, estimates = [], []
    for k, t in enumerate(timesteps):
        out = sched.step(fake_eps(x, t, bias), t, x, eta=eta,
                         variance_noise=None if noise is None else noise[k])
        x = out.prev_sample
        samples.append(x.clone())
        estimates.append(out.pred_original_sample.clone())
    return timesteps, torch.stack(samples), torch.stack(estimates)
