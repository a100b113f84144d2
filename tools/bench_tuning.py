#!/usr/bin/env python3
"""PyTorch eager timing of MotionLCM's consistency latent tuning (the release's `--optimize` loop,
tools/reference/motionlcm_tuning.py: autograd through the 1-step sampler with the ControlNet, the
VAE decoder and recover_from_ric; torch.optim.Adam with diffusers' cosine schedule) on a converted
trajectory-control file, for tools/bench_tuning.sh.

The hint is a pelvis path on every frame (the control checkpoints' test setting); the text vector
is a random unit vector (the prompt does not change the cost, and sentence-t5-large need not be
loaded). Prints `torch_ms_per_iteration <median over runs>` and the runs.

  python tools/bench_tuning.py --model models/motionlcm_v2_control_base_random.safetensors \
      --frames 196 --iterations 20 --threads 2 --runs 3
"""
import argparse
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from reference import motionlcm  # noqa: E402
from reference import motionlcm_control as mc  # noqa: E402
from reference import motionlcm_tuning as tuning  # noqa: E402


def pelvis_path(frames):
    h = torch.full((frames, 22, 3), float("nan"))
    f = torch.arange(frames, dtype=torch.float32)
    h[:, 0] = torch.stack([0.02 * f, torch.full((frames,), 0.9), 0.01 * f], dim=1)
    return h


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--frames", type=int, default=196)
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs", type=int, default=3)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    den, cn, traj, dec, _, _, cfg, mean_raw, std_raw = mc.load_libflame(a.model)
    for m in (den, cn, traj, dec):
        m.requires_grad_(False)
    from safetensors import safe_open
    with safe_open(a.model, "pt") as f:
        mean, std = f.get_tensor("motion.mean").float(), f.get_tensor("motion.std").float()
    joints = pelvis_path(a.frames)
    _, _, cond = mc.control_condition(traj, cfg, joints, mean_raw, std_raw)
    g = torch.Generator().manual_seed(0)
    text = torch.nn.functional.normalize(torch.randn(cfg["denoiser"]["text_dim"], generator=g),
                                         dim=0)
    chain = tuning.Chain(den, cn, dec, cfg, text, cond, a.frames, mean, std,
                         motionlcm.guidance_for(cfg, 1))
    tokens, channels = cfg["denoiser"]["latent_tokens"], cfg["denoiser"]["latent_channels"]
    z = torch.randn((1, tokens, channels), generator=g)
    tuning.tune(chain, z, joints, 2, 0)  # warm-up
    runs = []
    for _ in range(a.runs):
        t0 = time.perf_counter()
        tuning.tune(chain, z, joints, a.iterations, a.iterations // 8)
        runs.append((time.perf_counter() - t0) * 1e3 / a.iterations)
    print(f"torch {torch.__version__}, threads {a.threads}, frames {a.frames}, "
          f"{a.iterations} iterations, runs (ms/iteration): "
          + " ".join(f"{r:.1f}" for r in runs))
    print(f"torch_ms_per_iteration {statistics.median(runs):.2f}")


if __name__ == "__main__":
    main()
