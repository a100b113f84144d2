#!/usr/bin/env python3
"""Generate the consistency latent tuning parity fixtures (MotionLCM `--optimize`):
tests/fixtures/motionlcm_tuning_expected.safetensors, from the trajectory-control tiny files
tools/make_motionlcm_control_fixtures.py wrote (motionlcm_{v1,v2}_control_tiny.safetensors) and
its expected values (prompt 0's text vector, the main hint's joints), through
tools/reference/motionlcm_tuning.py (PyTorch autograd, torch.optim.Adam, diffusers'
get_scheduler and LCMScheduler).

Expected tensors (r in v1, v2; L x C the latent: v1 [1, 32], v2 [4, 8]; 24 frames):
  {r}.z [1, L, C]              the initial latent (seeded normal draws)
  {r}.guidance [1]             the 1-step default guidance (v1 7.5, v2 8.0)
  {r}.t [1]                    the 1-step sampler's timestep
  {r}.loss, {r}.hint_loss, {r}.reg [1]   at z: hint loss + 100 x regulariser (float64 rounded to
                               float32, as every tensor here)
  {r}.grad [1, L, C]           d loss / d z
  {r}.eps_up [1, L, C], {r}.eps_vjp [1, L, C]      a random upstream gradient at the controlled
                               eps and its product back to z (the denoiser and its ControlNet)
  {r}.feat_up [24, 263], {r}.dec_vjp [1, L, C]     the same for the VAE decoder at z
  {r}.tuned [1, L, C], {r}.losses [12]   12 iterations of the release's loop (warm-up
                               1 = 12/8, cosine to 0), from z
Metadata: prompts, frames, iterations, warmup, generator.

Run from anywhere (~10 s): target/bench-venv/bin/python tools/make_motionlcm_tuning_fixtures.py
"""
import json
import os
import sys

import torch
from safetensors.torch import load_file, save_file

TOOLS = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, TOOLS)

import make_motionlcm_control_fixtures as ctl  # noqa: E402
import make_motionlcm_fixtures as base  # noqa: E402
from make_latent_fixtures import log  # noqa: E402
from reference import motionlcm  # noqa: E402
from reference import motionlcm_control as mc  # noqa: E402
from reference import motionlcm_tuning as tuning  # noqa: E402

FIX = base.FIX
EXPECTED = "motionlcm_tuning_expected.safetensors"
ITERATIONS, WARMUP = 12, 1
SEEDS = {"v1": 61, "v2": 62}


def stats(path):
    from safetensors import safe_open
    with safe_open(path, "pt") as f:
        names = [k for k in f.keys() if k.startswith("motion.")]
        t = {k: f.get_tensor(k).float() for k in names}
    return t


def release(r, control):
    den, cn, traj, dec, _, _, cfg, mean_raw, std_raw = mc.load_libflame(
        os.path.join(FIX, ctl.OUT[r]))
    for m in (den, cn, traj, dec):
        m.requires_grad_(False)
    s = stats(os.path.join(FIX, ctl.OUT[r]))
    mean, std = s["motion.mean"], s["motion.std"]
    joints = control[f"{r}.joints"]
    _, _, cond = mc.control_condition(traj, cfg, joints, mean_raw, std_raw)
    assert torch.allclose(cond, control[f"{r}.control_cond"], atol=1e-6)
    guidance = motionlcm.guidance_for(cfg, 1)
    chain = tuning.Chain(den, cn, dec, cfg, control["text.0"], cond, ctl.FRAMES, mean, std,
                         guidance)
    tokens, channels = base.LATENT[r]
    g = torch.Generator().manual_seed(SEEDS[r])
    z = torch.randn((1, tokens, channels), generator=g)
    t = {f"{r}.z": z, f"{r}.guidance": torch.tensor([guidance]),
         f"{r}.t": torch.tensor([float(chain.t)])}
    total, h, reg, grad = tuning.gradient(chain, z, joints)
    t[f"{r}.loss"], t[f"{r}.hint_loss"], t[f"{r}.reg"] = (total.reshape(1), h.reshape(1),
                                                          reg.double().reshape(1))
    t[f"{r}.grad"] = grad
    # The network and the decoder apart, for random upstream gradients.
    up = torch.randn((1, tokens, channels), generator=g)
    zz = z.clone().requires_grad_(True)
    (d,) = torch.autograd.grad(chain.eps(zz), zz, up)
    t[f"{r}.eps_up"], t[f"{r}.eps_vjp"] = up, d
    fup = torch.randn((ctl.FRAMES, 263), generator=g)
    zz = z.clone().requires_grad_(True)
    (d,) = torch.autograd.grad(chain.features(zz), zz, fup)
    t[f"{r}.feat_up"], t[f"{r}.dec_vjp"] = fup, d
    tuned, losses = tuning.tune(chain, z, joints, ITERATIONS, WARMUP)
    t[f"{r}.tuned"], t[f"{r}.losses"] = tuned, losses
    log(f"{r}: loss {float(total):.5g} (hint {float(h):.5g}, reg {float(reg):.3g}), "
        f"|grad| {float(grad.norm()):.4g}; after {ITERATIONS}: {float(losses[-1]):.5g}, "
        f"|tuned - z| max {float((tuned - z).abs().max()):.3g}")
    assert losses[-1] < losses[0], "the loop must lower the loss"
    return t


def main():
    torch.set_num_threads(1)
    control = load_file(os.path.join(FIX, ctl.EXPECTED))
    out = {}
    for r in ("v1", "v2"):
        out.update(release(r, control))
    out = {k: v.float().contiguous() for k, v in sorted(out.items())}
    for k, v in out.items():
        assert torch.isfinite(v).all(), k
    save_file(out, os.path.join(FIX, EXPECTED),
              metadata={"prompts": json.dumps(base.PROMPTS[:1]), "frames": str(ctl.FRAMES),
                        "iterations": str(ITERATIONS), "warmup": str(WARMUP),
                        "generator": "tools/make_motionlcm_tuning_fixtures.py"})
    base.canonical_header(os.path.join(FIX, EXPECTED))
    log(f"{EXPECTED}: {os.path.getsize(os.path.join(FIX, EXPECTED)) / 1e3:.1f} kB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
