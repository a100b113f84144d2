"""Reference of the three editing loops (motion in-painting with a reference and a keep-mask), written
from the official loops: FLAME (`edit_motion.py`; docs/official/flame.md#editing), MDM
(`sample/edit.py`; docs/official/mdm.md#editing) and Motion Flow Matching ("euler_replacement_edit_till",
`flow/flow_matching_class.py`; docs/official/motionfm.md#editing).
It is the oracle of tools/make_edit_fixtures.py.

Masks are per value (the official FLAME code keeps whole joints and the translation, MDM/MotionFM
keep frame ranges or feature dims; a per-value boolean mask covers all of them), True = keep the
reference. Mixing is written as a select (`torch.where`), which is exactly x·(¬M) + r·M for a 0/1
mask and finite values, and exactly the official in-place index write.

All noise is passed in (no generator inside), so a caller can store it and replay it elsewhere.

- `flame_edit_loop`: before EVERY reverse step at spaced index t (t = 0 included) the reference is
  diffused to t with fresh noise, q_sample(ref, t) = sqrt(abar_t)·ref + sqrt(1 - abar_t)·q_noise
  (coefficients float64 -> float32, abar of the SPACED table), the kept values of x_t are replaced
  by it, and the usual guided FLAME p_sample runs on that x_t (eps, learned-range variance,
  clip_denoised, z added when t != 0).
- `mdm_edit_loop`: MDM's DDPM with x0 prediction, CFG on x0, then x0 <- x0·(¬M) + ref·M (no
  clamp), fixed-small variance; x_t itself is never replaced.
- `flow_edit_loop`: x_ref,i = ((N - i)·z0 + i·ref)/N in float32; while i/N <= edit_till the kept
  values of x are replaced by x_ref,i; then one Euler step with the guided velocity.
"""
import numpy as np
import torch

from reference.diffusion import _gather
from reference.mdm import flow_time_index, guided


def _bool(mask):
    return mask.bool() if mask.dtype != torch.bool else mask


def q_sample(diffusion, x_start, t, noise):
    """guided-diffusion q_sample on the (spaced) tables: float64 sqrt tables gathered to float32."""
    sqrt_abar = np.sqrt(diffusion.alphas_cumprod)
    sqrt_one_minus = np.sqrt(1.0 - diffusion.alphas_cumprod)
    return (_gather(sqrt_abar, t, x_start.shape) * x_start
            + _gather(sqrt_one_minus, t, x_start.shape) * noise)


def flame_edit_loop(diffusion, model, x_T, reference, keep, q_noises, z_noises,
                    clip_denoised=True, record=False):
    """FLAME editing (docs/official/flame.md#editing) over a respaced `SpacedDiffusion`.

    model: a guided callable model(x, timesteps) on the CFG batch (reference.diffusion
    .ClassifierFreeGuidance); x_T, reference, keep: `[B, 147, L]` (B = the CFG batch, 2N);
    q_noises[k], z_noises[k]: the q_sample noise and the p_sample noise of loop step k (spaced
    t = steps-1-k), each `[B, 147, L]`; z_noises[k] is ignored when t = 0.

    Returns a list of per-step dicts: t, x_in (x_t after replacement), x (sample after the step),
    pred_xstart (clamped x0 at the step); with record=True also `out` (the guided model output).
    """
    keep = _bool(keep)
    x = x_T
    trace = []
    steps = diffusion.num_timesteps
    for k, i in enumerate(reversed(range(steps))):
        t = torch.full((x.shape[0],), i, dtype=torch.long)
        x_ref = q_sample(diffusion, reference, t, q_noises[k])
        x_in = torch.where(keep, x_ref, x)
        z = z_noises[k] if i != 0 else torch.zeros_like(x)
        if record:
            out = model(x_in, diffusion.model_timesteps(t))
            seen = {"out": out}
            fixed = lambda xx, tt, o=out: o  # noqa: E731  same output, no second forward
            step = diffusion.p_sample(fixed, x_in, t, z, clip_denoised)
        else:
            seen = {}
            step = diffusion.p_sample(model, x_in, t, z, clip_denoised)
        x = step["sample"]
        trace.append({"t": i, "x_in": x_in, "x_ref": x_ref, "x": x,
                      "pred_xstart": step["pred_xstart"], **seen})
    return trace


def mdm_p_sample_replace(diffusion, net, x, t, cond, guidance, reference, keep, noise):
    """One MDM DDPM step with x0 replacement (docs/official/mdm.md#editing): x0 = guided net output (CFG on
    x0, uncond = zero text vector), x0 <- where(keep, ref, x0), mean = c1·x0 + c2·x_t,
    sample = mean + [t != 0]·exp(0.5·clipped log posterior variance)·z. Returns (sample, x0, raw)
    where raw is the guided x0 before replacement."""
    model_t = diffusion.model_timesteps(t)
    raw = guided(net, x, model_t, cond, guidance)
    x0 = torch.where(_bool(keep), reference, raw)
    mean = diffusion.q_posterior_mean(x0, x, t)
    log_var = _gather(diffusion.posterior_log_variance_clipped, t, x.shape)
    nonzero = (t != 0).float().view(-1, *([1] * (x.dim() - 1)))
    return mean + nonzero * torch.exp(0.5 * log_var) * noise, x0, raw


def mdm_edit_loop(diffusion, net, x_T, cond, guidance, reference, keep, z_noises):
    """MDM editing (docs/official/mdm.md#editing) over a respaced `SpacedDiffusion`; tensors
    `[B, 263, 1, T]`.

    z_noises[k] is the p_sample noise of loop step k (spaced t = steps-1-k), ignored at t = 0.
    Returns per-step dicts: t, model_t, x (sample after the step), pred_xstart (replaced x0),
    raw_x0 (guided x0 before replacement)."""
    x = x_T
    trace = []
    for k, i in enumerate(reversed(range(diffusion.num_timesteps))):
        t = torch.full((x.shape[0],), i, dtype=torch.long)
        z = z_noises[k] if i != 0 else torch.zeros_like(x)
        x_next, x0, raw = mdm_p_sample_replace(diffusion, net, x, t, cond, guidance, reference,
                                               keep, z)
        trace.append({"t": i, "model_t": int(diffusion.model_timesteps(t)[0]), "x_in": x,
                      "x": x_next, "pred_xstart": x0, "raw_x0": raw})
        x = x_next
    return trace


def flow_reference_point(z0, reference, i, steps):
    """x_ref,i = ((N - i)·z0 + i·ref)/N, float32 tensors times/over python ints, in that order."""
    return ((steps - i) * z0 + i * reference) / steps


def flow_edit_loop(net, z0, cond, guidance, reference, keep, steps, edit_till):
    """Motion Flow Matching "euler_replacement_edit_till" (docs/official/motionfm.md#editing); tensors
    `[B, 263, 1, T]`.

    For i = 0..N-1: t = float32(i)/float32(N); if i/N <= edit_till (python floats) the kept values
    of x become x_ref,i; v = guided velocity at pe row trunc(float32(t·1000)); x <- x +
    float32(1/N)·v. Returns per-step dicts: i, t, index, edited, x_in, x (after the step), v."""
    keep = _bool(keep)
    x = z0
    dt = torch.tensor(1.0 / steps, dtype=torch.float32)
    trace = []
    for i in range(steps):
        t = torch.tensor(i, dtype=torch.float32) / torch.tensor(steps, dtype=torch.float32)
        edited = i / steps <= edit_till
        if edited:
            x = torch.where(keep, flow_reference_point(z0, reference, i, steps), x)
        idx = flow_time_index(t).expand(x.shape[0])
        v = guided(net, x, idx, cond, guidance)
        x_in = x
        x = x + dt * v
        trace.append({"i": i, "t": float(t), "index": int(idx[0]), "edited": edited,
                      "x_in": x_in, "x": x, "v": v})
    return trace
