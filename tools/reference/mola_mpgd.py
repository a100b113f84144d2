"""PyTorch reference of MoLA's MPGD motion editing (sony/MoLA 3313148;
docs/official/mola-mld.md#mola-mpgd-editing),
built on tools/reference/mola.py (its denoiser, decoder and diffusers DDIMScheduler).

Official flow (models/t2m_latent_diffusion.py `_diffusion_reverse` with `control`, and
models/mola_module.py `_step_with_mpgd`), for each of the 50 trailing timesteps t (999..19):
  ε      = ε_u + g·(ε_c − ε_u)                       (CFG, batch [cond, uncond = zeros])
  x̂0     = (x_t − √(1 − ᾱ_t)·ε) / √ᾱ_t
  L(x̂0)  = Σ_{b,frame,joint} ‖(J(x̂0) − c)⊙m‖₂ over xyz,   m = (c ≠ 0) per coordinate
  J(z)   = recover_from_ric(D(z)ᵀ[:, :length, :263]·std + mean, 22)  (D = VAE decoder, raw: no
           flag sigmoid; the flag channel dropped; length = the control's frame count)
  ρ(t)   = −t·(t − 1000)/1000/1000·4·s            (s = edit scale; raw integer t)
  x̂0'    = x̂0 − ρ(t)·∇_{x̂0} L                     (gradient only; no clamp, no normalisation)
  x_prev = √ᾱ_prev·x̂0' + √(1 − ᾱ_prev)·ε          (the ORIGINAL ε; η = 0; ᾱ_prev = ᾱ_0 at t = 19)
The latent has (length + 4)//4 frames; the final motion is cut by the flag as without editing
(visualize_test.py and utils/eval_mola.py call `forward_decoder_clip(z)` without a length).

Control builders: `path` as utils/eval_mola.py `evaluation_stage2_editing_test` (the reference's
pelvis, all xyz, every frame; joints 1..21 zero). The official code has no builder for
`inbetweening` and `upper_edit` (that function raises NotImplementedError for them); they
follow the demo controls: demo/control_example_start_end*.npy (all 22 joints on the first 4
and last 4 frames) and demo/control_example_lowerbody_circle.npy (joints 0, 1, 2, 4, 5, 7, 8,
10, 11 — pelvis, hips, knees, ankles, feet — on every frame).
"""
import torch

from . import mola, ric

MAX_STEP = 1000
DEFAULT_EDIT_SCALE = 0.6  # options/option_diffusion.py --edit-scale
KEYFRAMES = 4
LOWER_BODY = (0, 1, 2, 4, 5, 7, 8, 10, 11)


# -- controls --------------------------------------------------------------------------------------

def path_control(ref_joints):
    """ref joints `[L, 22, 3]` -> control with the pelvis trajectory (joint 0, xyz) only."""
    c = torch.zeros_like(ref_joints)
    c[:, 0] = ref_joints[:, 0]
    return c


def inbetweening_control(ref_joints, keyframes=KEYFRAMES):
    """All joints on the first and last `keyframes` frames."""
    c = torch.zeros_like(ref_joints)
    c[:keyframes] = ref_joints[:keyframes]
    c[-keyframes:] = ref_joints[-keyframes:]
    return c


def upper_edit_control(ref_joints):
    """The lower body (pelvis, hips, knees, ankles, feet) on every frame; the upper body free."""
    c = torch.zeros_like(ref_joints)
    idx = list(LOWER_BODY)
    c[:, idx] = ref_joints[:, idx]
    return c


CONTROLS = {"path": path_control, "inbetweening": inbetweening_control,
            "upper_edit": upper_edit_control}


# -- MPGD pieces -----------------------------------------------------------------------------------

def edit_rho(t, scale, max_step=MAX_STEP):
    """ρ(t) = −t·(t − max)/max/max·4·s with the official operation order: the integer product
    is exact (int64), then float32 divisions, then ·4·s."""
    t = torch.as_tensor(t, dtype=torch.int64)
    return -t * (t - max_step) / max_step / max_step * 4 * scale


def control_joints(dec, z, length, mean, std):
    """z `[B, C, T']` -> joints `[B, length, 22, 3]` of the raw decoded features (flag dropped)."""
    x = dec(z).transpose(1, 2)  # [B, 4T', 264]
    return ric.feats2joints(x[:, :length, :-1], mean, std)


def control_loss(dec, z, control, mean, std):
    """Σ over batch, frames, joints of ‖(J(z) − c)⊙m‖₂ (norm over xyz), m = c ≠ 0."""
    mask = control != 0
    joints = control_joints(dec, z, control.shape[1], mean, std)
    return torch.norm((joints - control * mask) * mask, dim=-1, p=2).sum()


def mpgd_gradient(dec, x0, control, mean, std):
    """(∇_{x̂0} L, L) with x̂0 taken as a leaf (the official z.requires_grad_ on a no-grad x̂0).
    At a zero residual (unconstrained joints) torch's norm backward gives 0."""
    with torch.enable_grad():
        z = x0.detach().requires_grad_(True)
        loss = control_loss(dec, z, control, mean, std)
        (g,) = torch.autograd.grad([loss], [z])
    return g, loss.detach()


def guided_eps(den, x, t, cond, guidance):
    """CFG as mola.sample: batch [cond, uncond = zeros] unless guidance is 0 or exactly 1."""
    tt = t.reshape(1)
    if guidance == 0 or guidance == 1.0:
        return den(x, tt, cond)
    e = den(torch.cat([x, x]), torch.cat([tt, tt]), torch.cat([cond, torch.zeros_like(cond)]))
    return e[1:] + guidance * (e[:1] - e[1:])


@torch.no_grad()
def sample_mpgd(den, dec, x_T, cond, control, mean, std, edit_scale=DEFAULT_EDIT_SCALE,
                guidance=11.0, steps=50):
    """x_T `[1, C, (L+4)//4]`, control `[1, L, 22, 3]` -> per-step dicts {t, rho, x0, x0_edit,
    grad, loss, eps, x}: x = the latent after the step."""
    assert x_T.shape[2] == mola.latent_frames(control.shape[1]), (x_T.shape, control.shape)
    sch = mola.make_scheduler()
    sch.set_timesteps(steps)
    x = x_T
    trace = []
    for t in sch.timesteps:
        eps = guided_eps(den, x, t, cond, guidance)
        prev = t - sch.config.num_train_timesteps // sch.num_inference_steps
        a_t = sch.alphas_cumprod[t]
        a_prev = sch.alphas_cumprod[prev] if prev >= 0 else sch.final_alpha_cumprod
        x0 = (x - (1 - a_t) ** 0.5 * eps) / a_t ** 0.5
        g, loss = mpgd_gradient(dec, x0, control, mean, std)
        rho = edit_rho(t, edit_scale)
        x0_edit = x0 - rho * g
        x = a_prev ** 0.5 * x0_edit + (1 - a_prev) ** 0.5 * eps
        trace.append({"t": int(t), "rho": rho, "x0": x0, "x0_edit": x0_edit, "grad": g,
                      "loss": loss, "eps": eps, "x": x})
    return trace
