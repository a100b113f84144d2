#!/usr/bin/env python3
"""Generate tests/fixtures/ddim_diffusers.{safetensors,json}: diffusers' own DDIMScheduler
(tools/reference/diffusers_ddim.py) as MoLA and MLD use it, for tests/diffusers_ddim.rs.

- `alphas_cumprod`: the scheduler's float32 table (scaled_linear 0.00085-0.012, T = 1000).
- Timesteps of `set_timesteps(n)` for leading (steps_offset 1 and 0) and trailing spacing at
  several n, including n where diffusers' trailing rule yields n + 1 timesteps ending at -1 (which
  libflame refuses).
- Trajectories from a fixed x_T (seeded torch.Generator, stored) with the fake network of the
  reference module: every sample and every pred_original_sample. Cases: MLD (leading, offset 1,
  set_alpha_to_one False, 50 steps), MoLA (trailing, offset 1, False, 50 steps), trailing at 7
  steps (prev = t - 1000 // 7 is not the next timestep), leading offset 0 without
  set_alpha_to_one at 10 steps (the last step goes from ᾱ_0 to ᾱ_0), v-prediction with eta 0.5
  (stored noise, added at the last step too), and sample prediction with clip_sample.

Run from anywhere: python tools/make_ddim_fixtures.py
"""
import json
import os
import sys

import diffusers
import torch
from safetensors.torch import save_file

TOOLS = os.path.dirname(os.path.abspath(__file__))
FIX = os.path.join(os.path.dirname(TOOLS), "tests", "fixtures")
sys.path.insert(0, TOOLS)

from reference.diffusers_ddim import run, scheduler  # noqa: E402

N = 64  # values per sample (e.g. a [16, 4] latent)
SEED = 404
TIMESTEP_COUNTS = [1, 3, 7, 10, 16, 50, 61, 333, 999, 1000]
CASES = [
    # name, spacing, steps_offset, set_alpha_to_one, prediction, clip, steps, eta
    ("mld", "leading", 1, False, "epsilon", False, 50, 0.0),
    ("mola", "trailing", 1, False, "epsilon", False, 50, 0.0),
    ("trailing7", "trailing", 0, False, "epsilon", False, 7, 0.0),
    ("leading0", "leading", 0, False, "epsilon", False, 10, 0.0),
    ("v_eta", "trailing", 0, False, "v_prediction", False, 10, 0.5),
    ("sample_clip", "leading", 1, True, "sample", True, 10, 0.0),
]


def main():
    g = torch.Generator().manual_seed(SEED)
    x_t = torch.randn(N, generator=g, dtype=torch.float32)
    bias = (torch.arange(N, dtype=torch.float32) / N - 0.5) * 0.2
    tensors = {"x_T": x_t, "bias": bias}
    meta = {"diffusers": diffusers.__version__, "torch": torch.__version__, "n": N,
            "timesteps": {}, "cases": []}

    tensors["alphas_cumprod"] = scheduler("leading").alphas_cumprod.clone()
    for spacing, offset in [("leading", 1), ("leading", 0), ("trailing", 1)]:
        s = scheduler(spacing, steps_offset=offset)
        for n in TIMESTEP_COUNTS:
            s.set_timesteps(n)
            key = f"{spacing}_offset{offset}_{n}"
            meta["timesteps"][key] = [int(t) for t in s.timesteps]

    for name, spacing, offset, to_one, pred, clip, steps, eta in CASES:
        s = scheduler(spacing, offset, to_one, pred, clip)
        noise = None
        if eta > 0:
            noise = torch.randn(steps, N, generator=g, dtype=torch.float32)
            tensors[f"{name}.noise"] = noise
        timesteps, samples, estimates = run(s, steps, x_t, bias, eta, noise)
        tensors[f"{name}.samples"] = samples
        tensors[f"{name}.estimates"] = estimates
        meta["cases"].append({"name": name, "spacing": spacing, "steps_offset": offset,
                              "set_alpha_to_one": to_one, "prediction": pred,
                              "clip_sample": clip, "steps": steps, "eta": eta,
                              "timesteps": timesteps})

    save_file({k: v.contiguous() for k, v in tensors.items()},
              os.path.join(FIX, "ddim_diffusers.safetensors"))
    with open(os.path.join(FIX, "ddim_diffusers.json"), "w") as f:
        json.dump(meta, f, separators=(",", ":"))
        f.write("\n")


if __name__ == "__main__":
    main()
