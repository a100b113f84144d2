"""PyTorch reference of MotionLCM's consistency latent tuning (`--optimize`; Dai et al., ECCV 2024;
github.com/Dai-Wenxun/MotionLCM v2.0 086f8db) on a converted trajectory-control file, written from
the release and differentiated by torch.autograd: nothing here is derived by hand.

Facts, with the official file they come from:
- mld/models/modeltype/mld.py `_optimize_latents`: the initial latent is the only parameter;
  each iteration runs `_diffusion_reverse` (here one step: diffusers' LCMScheduler.step, whose
  last step returns `denoised` without re-noising) with the ControlNet, `vae.decode`,
  `feats2joints` (de-normalisation with the dataset's Mean/Std, then recover_from_ric); the loss
  is `F.mse_loss(joints, hint_3d, reduction='none') * hint_mask` summed over frames, joints and
  axes and divided by `hint_mask.sum()`, plus `loss_correlate_penalty` x
  `noise_regularize_1d(latents, dim=1)` (+ `loss_diff_penalty` x the distance to the first
  latent, penalty 0); `loss.mean().backward()`; with `clip_grad` the gradient is divided by its L2
  norm over the latent; `optimizer.step()` then `lr_scheduler.step()`.
- The optimiser and schedule: `torch.optim.Adam([latents], lr=learning_rate)` and diffusers'
  `get_scheduler(lr_scheduler, optimizer, num_warmup_steps, num_training_steps)`
  (configs/modules/noise_optimizer.yaml: 400 steps, lr 0.1, "cosine", 50 warm-up, clip_grad true,
  loss_hint_type l2, loss_diff_penalty 0, loss_correlate_penalty 100).
- mld/models/architectures/dno.py `noise_regularize_1d(noise, stop_at=2, dim=1)`: while the size
  along `dim` is > stop_at, add (mean over every dim but the batch of noise * roll(noise, 1,
  dim))^2, then average pairs along `dim`; a size that is not a power of two is first padded with
  fresh random noise (not reproduced: asserted away).
"""
import torch
import torch.nn.functional as F
from diffusers.optimization import get_scheduler

from reference import diffusers_lcm, motionlcm
from reference import motionlcm_control as mc
from reference.grad import recover_from_ric


def noise_regularize_1d(noise, stop_at=2, dim=1):
    size = noise.shape[dim]
    assert size & (size - 1) == 0, "padding with random noise is not reproduced"
    loss = torch.zeros(noise.shape[0], dtype=noise.dtype)
    while size > stop_at:
        rolled = torch.roll(noise, shifts=1, dims=dim)
        loss = loss + (noise * rolled).mean(dim=tuple(range(1, noise.ndim))).pow(2)
        noise = noise.view(*noise.shape[:dim], size // 2, 2, *noise.shape[dim + 1:]).mean(dim=dim + 1)
        size //= 2
    return loss


class Chain:
    """The differentiated generation of one controlled sample: latent -> 1-step LCM -> decode ->
    joints. `text` [text_dim], `control_cond` [L, C] (the trajectory encoder's output),
    `mean`/`std` the motion statistics."""

    def __init__(self, den, cn, dec, cfg, text, control_cond, frames, mean, std, guidance):
        self.den, self.cn, self.dec, self.cfg = den, cn, dec, cfg
        self.text, self.control_cond, self.frames = text[None], control_cond[None], frames
        self.mean, self.std = mean.double(), std.double()
        self.w = motionlcm.guidance_embedding(torch.tensor([guidance - 1.0]),
                                              cfg["denoiser"]["cond_dim"])
        self.scale = float(cfg["control"]["scale"])
        self.sched = diffusers_lcm.scheduler()
        steps = motionlcm.timesteps_for(cfg, 1)
        if isinstance(steps, int):
            self.sched.set_timesteps(steps)
        else:
            self.sched.set_timesteps(timesteps=steps)
        self.t = self.sched.timesteps[0]

    def eps(self, z):
        return mc.controlled_eps(self.den, self.cn, z, torch.tensor([float(self.t)]), self.w,
                                 self.text, self.control_cond, self.scale)[0]

    def latent(self, z):
        self.sched._step_index = None  # each iteration is a new one-step run
        return self.sched.step(self.eps(z), self.t, z).prev_sample

    def features(self, z0):
        return self.dec(z0, self.frames)[0]

    def joints(self, z):
        feats = self.features(self.latent(z)).double()
        return recover_from_ric(feats * self.std + self.mean)


def hint_loss(joints, targets):
    """targets [F, 22, 3] with NaN = free over the first F frames."""
    mask = (~torch.isnan(targets)).double()
    h = torch.nan_to_num(targets.double(), nan=0.0) * mask
    j = joints[: targets.shape[0]]
    return (F.mse_loss(j, h, reduction="none") * mask).sum() / mask.sum()


def loss(chain, z, targets, penalty=100.0):
    """(total, hint loss, regulariser) at z [1, L, C]."""
    h = hint_loss(chain.joints(z), targets)
    r = noise_regularize_1d(z)[0]
    return h + penalty * r, h, r


def gradient(chain, z, targets):
    z = z.detach().clone().requires_grad_(True)
    total, h, r = loss(chain, z, targets)
    (g,) = torch.autograd.grad(total, z)
    return total.detach(), h.detach(), r.detach(), g


def tune(chain, z, targets, iterations, warmup, lr=0.1):
    """The release's loop: returns (the tuned latent, the loss at every iteration)."""
    current = z.detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([current], lr=lr)
    sched = get_scheduler("cosine", optimizer=opt, num_warmup_steps=warmup,
                          num_training_steps=iterations)
    losses = []
    for _ in range(iterations):
        total, _, _ = loss(chain, current, targets)
        opt.zero_grad()
        total.backward()
        current.grad.data /= current.grad.norm(p=2, dim=[1, 2], keepdim=True)
        opt.step()
        sched.step()
        losses.append(float(total.detach()))
    return current.detach(), torch.tensor(losses, dtype=torch.float64)
