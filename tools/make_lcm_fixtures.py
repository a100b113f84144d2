#!/usr/bin/env python3
"""Generate tests/fixtures/lcm_diffusers.{safetensors,json}: diffusers' own LCMScheduler
(tools/reference/diffusers_lcm.py) as MotionLCM v1 and v2 use it, for tests/diffusers_lcm.rs.

- Timesteps of `set_timesteps(n)` (original_inference_steps 50) for n = 1 to 50.
- Trajectories from a fixed x_T (seeded torch.Generator, stored) with the fake network of
  tools/reference/diffusers_ddim.py and stored re-noising noise: v1 at 1, 2, 4 and 7 steps, and
  v2's table at 1, 2 and 4 steps (the 4-step list repeats 299). Every step's sample and
  consistency estimate (`denoised`).

Run from anywhere: python tools/make_lcm_fixtures.py
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

from reference.diffusers_lcm import run, scheduler  # noqa: E402

N = 512  # values per sample (a v2 latent, [16, 32])
SEED = 2024
CASES = [
    ("v1_1", 1), ("v1_2", 2), ("v1_4", 4), ("v1_7", 7),
    ("v2_1", [799]), ("v2_2", [699, 299]), ("v2_4", [699, 399, 299, 299]),
]


def main():
    g = torch.Generator().manual_seed(SEED)
    x_t = torch.randn(N, generator=g, dtype=torch.float32)
    bias = (torch.arange(N, dtype=torch.float32) / N - 0.5) * 0.2
    tensors = {"x_T": x_t, "bias": bias}
    meta = {"diffusers": diffusers.__version__, "torch": torch.__version__, "n": N,
            "timesteps": {}, "cases": []}
    s = scheduler()
    tensors["alphas_cumprod"] = s.alphas_cumprod.clone()
    for n in range(1, 51):
        s.set_timesteps(n)
        meta["timesteps"][str(n)] = [int(t) for t in s.timesteps]
    for name, steps in CASES:
        count = steps if isinstance(steps, int) else len(steps)
        noise = torch.randn(count, N, generator=g, dtype=torch.float32)
        timesteps, samples, denoised = run(scheduler(), steps, x_t, bias, noise)
        # diffusers draws noise for every step but the last.
        tensors[f"{name}.noise"] = noise
        tensors[f"{name}.samples"] = samples
        tensors[f"{name}.denoised"] = denoised
        meta["cases"].append({"name": name, "timesteps": timesteps})
    save_file({k: v.contiguous() for k, v in tensors.items()},
              os.path.join(FIX, "lcm_diffusers.safetensors"))
    with open(os.path.join(FIX, "lcm_diffusers.json"), "w") as f:
        json.dump(meta, f, separators=(",", ":"))
        f.write("\n")


if __name__ == "__main__":
    main()
