"""PyTorch reference of MotionLCM's trajectory control (ControlNet; Dai et al., ECCV 2024;
github.com/Dai-Wenxun/MotionLCM, v1.0 f534a7f and v2.0 086f8db) on a converted libflame file
(tools/convert_motionlcm.py documents its `controlnet.*`, `traj_encoder.*`, `control.*` tensors and
the `control` configuration). The text-to-motion parts are reference/motionlcm.py's.

Facts, with the official file they come from:
- Hint (mld/data/humanml/dataset.py random_mask, both tags): the global joint positions
  [frames, 22, 3] (recover_from_ric, HumanML3D's Y-up metres), (joints - Mean_raw) / Std_raw per
  joint and axis (datasets/humanml_spatial_norm/), times the 0/1 mask (a chosen joint has all
  three axes), flattened to [frames, 66] (v1.0 dataset.py reshapes; v2.0 mld/models/modeltype/
  mld.py forward: `hint.view(bs, frames, -1)`).
- Frame mask (which frame tokens the trajectory encoder attends to): v1.0 mld.py
  _diffusion_reverse `hint.sum(-1) != 0` over the 66 normalised values ("row_sum"); v2.0 mld.py
  forward `hint_mask.view(bs, frames, -1).sum(-1) != 0`, i.e. any value hinted ("mask").
- Trajectory encoder (mld/models/architectures/mld_traj_encoder.py, both tags): skel_embedding
  Linear(66 -> D) per frame, the `global_motion_token` rows [L, D] in front, the learned
  `query_pos_encoder.pe` added over the whole sequence, MLD's post-LN skip stack with
  src_key_padding_mask = not [L tokens always valid, frame mask], its final LayerNorm, the first
  L tokens; v2.0 then `latent_proj` Linear(D -> C) (configs/modules/traj_encoder.yaml:
  hidden_dim 256, force_post_proj true). Output: the ControlNet's condition [L, C].
- ControlNet (mld/models/architectures/mld_denoiser.py with is_controlnet=True, both tags): a
  copy of the denoiser without the final encoder norm; first sample += controlnet_cond_embedding(
  cond) (v1.0: three Linear(D -> D) without activation; v2.0: Linear(C -> E), SiLU, Linear(E -> E),
  SiLU, Linear(E -> C), E = controlnet_embed_dim, configs/modules/denoiser.yaml); then the
  denoiser's forward, keeping the output of each of the stack's blocks (input blocks, middle,
  output blocks, in that order; v1.0 mld/models/operator/cross_attention.py SkipTransformerEncoder
  return_intermediate, v2.0 mld/models/operator/attention.py maybe_controlnet_moe) over the whole
  sequence, each through its own Linear(D -> D) `controlnet_down_mid_blocks.{i}`.
- Injection: the main denoiser adds residual i right after block i (before the skip is stored,
  before the final norm; same two files). v1.0 multiplies the residuals by control_scale
  (mld.py _diffusion_reverse; configs/motionlcm_control.yaml 1.0); v2.0 does not scale.
- The ControlNet sees the same sample, timestep, guidance embedding (timestep_cond) and text as
  the denoiser (mld.py _diffusion_reverse, both tags; LCM's scale_model_input is the identity).
"""
import json

import torch
import torch.nn.functional as F
from torch import nn

from reference import diffusers_lcm, motionlcm
from reference.mld import EncoderLayer, LearnedPE, SkipStack, time_sinusoid

JOINTS = 22


# -- the hint ------------------------------------------------------------------------------------

def normalise_hint(joints, mean_raw, std_raw):
    """joints `[F, 22, 3]` target positions with NaN for free values -> (hint `[F, 66]`, mask
    `[F, 22, 3]` float 0/1). A value is hinted when it is not NaN."""
    mask = (~torch.isnan(joints)).to(torch.float32)
    x = torch.nan_to_num(joints, nan=0.0)
    hint = (x - mean_raw) / std_raw * mask
    return hint.reshape(joints.shape[0], -1), mask


def frame_mask(hint, mask, kind):
    """`[F]` bool: the frames the trajectory encoder attends to. "row_sum" (v1.0): the 66
    normalised masked values do not sum to 0; "mask" (v2.0): any value is hinted."""
    if kind == "row_sum":
        return hint.sum(-1) != 0
    if kind == "mask":
        return mask.reshape(mask.shape[0], -1).sum(-1) != 0
    raise ValueError(kind)


# -- the skip stack with key padding, residual injection and intermediates ----------------------

def layer_forward(layer, x, key_padding_mask=None):
    """reference/mld.py's EncoderLayer (post-LN, GELU) with a key padding mask (True = ignored)."""
    a = layer.self_attn(x, x, x, key_padding_mask=key_padding_mask, need_weights=False)[0]
    x = layer.norm1(x + a)
    return layer.norm2(x + layer.linear2(F.gelu(layer.linear1(x))))


def stack_forward(stack, x, key_padding_mask=None, residuals=None, collect=False):
    """SkipStack.forward with residual i added right after block i (input blocks, middle, output
    blocks), before the skip is kept and before the final norm; `collect`: also return every
    block's output (after its residual, if any). Returns (x, [block outputs])."""
    res = list(residuals) if residuals is not None else None
    outs, skips = [], []

    def after(x):
        if res is not None:
            x = x + res.pop(0)
        if collect:
            outs.append(x)
        return x

    for m in stack.input_blocks:
        x = after(layer_forward(m, x, key_padding_mask))
        skips.append(x)
    x = after(layer_forward(stack.middle_block, x, key_padding_mask))
    for m, lin in zip(stack.output_blocks, stack.linear_blocks):
        x = after(layer_forward(m, lin(torch.cat([x, skips.pop()], dim=-1)), key_padding_mask))
    assert res is None or not res, "one residual per block"
    if stack.norm is not None:
        x = stack.norm(x)
    return x, outs


# -- the trajectory encoder --------------------------------------------------------------------

class TrajEncoder(nn.Module):
    """Module names = the file's `traj_encoder.*` names. `projected`: v2's latent_proj."""

    def __init__(self, width, tokens, channels, layers, heads, ff_size, max_len, projected):
        super().__init__()
        self.skel_embedding = nn.Linear(3 * JOINTS, width)
        self.global_motion_token = nn.Parameter(torch.randn(tokens, width))
        self.query_pos_encoder = LearnedPE(max_len, width)
        self.encoder = SkipStack(EncoderLayer, layers, width, heads, ff_size, final_norm=True)
        self.latent_proj = nn.Linear(width, channels) if projected else None

    def forward(self, hint, frames_valid):
        """hint `[B, F, 66]`, frames_valid `[B, F]` bool -> the ControlNet's condition
        `[B, L, C]`."""
        b = hint.shape[0]
        x = self.skel_embedding(hint).transpose(0, 1)
        tokens = self.global_motion_token[:, None, :].expand(-1, b, -1)
        valid = torch.cat([torch.ones(b, tokens.shape[0], dtype=torch.bool), frames_valid], 1)
        seq = self.query_pos_encoder(torch.cat([tokens, x], 0))
        out, _ = stack_forward(self.encoder, seq, key_padding_mask=~valid)
        out = out[: tokens.shape[0]]
        if self.latent_proj is not None:
            out = self.latent_proj(out)
        return out.transpose(0, 1)


# -- the ControlNet and the controlled denoiser ------------------------------------------------

def embed(den, z, t, cond, text):
    """The denoiser's input sequence `[L + 2, B, D]` (latent tokens, time, text) with the learned
    positions, as reference/motionlcm.py's Denoiser.forward builds it."""
    x = z.transpose(0, 1)
    if den.projected:
        x = den.latent_pre(x)
    te = den.time_embedding
    h = time_sinusoid(t, den.text_dim) + te.cond_proj(cond)
    time = te.linear_2(F.silu(te.linear_1(h)))
    return den.query_pos(torch.cat([x, time[None], den.emb_proj(text)[None]], dim=0))


class ControlNet(motionlcm.Denoiser):
    """Module names = the file's `controlnet.*` names: the denoiser's without `encoder.norm` and
    `latent_post`, plus `controlnet_cond_embedding` and `controlnet_down_mid_blocks`."""

    def __init__(self, latent_dim, latent_tokens, latent_channels, text_dim, cond_dim, layers,
                 heads, ff_size, max_len, text_activation, projected, embed_dim, embed_activation):
        super().__init__(latent_dim, latent_tokens, latent_channels, text_dim, cond_dim, layers,
                         heads, ff_size, max_len, text_activation, projected)
        self.encoder.norm = None
        if projected:
            del self.latent_post
        c, e = latent_channels, embed_dim
        if embed_activation == "silu":  # v2: keys 0, 2, 4
            mods = [nn.Linear(c, e), nn.SiLU(), nn.Linear(e, e), nn.SiLU(), nn.Linear(e, c)]
        elif embed_activation == "none":  # v1: keys 0, 1, 2 (C = D = E)
            mods = [nn.Linear(c, e), nn.Linear(e, e), nn.Linear(e, c)]
        else:
            raise ValueError(embed_activation)
        self.controlnet_cond_embedding = nn.Sequential(*mods)
        self.controlnet_down_mid_blocks = nn.ModuleList(
            [nn.Linear(latent_dim, latent_dim) for _ in range(layers)])

    def forward(self, z, t, cond, text, control_cond):
        """z `[B, L, C]`, control_cond `[B, L, C]` -> the residuals, one `[L + 2, B, D]` per
        block (not yet scaled)."""
        z = z + self.controlnet_cond_embedding(control_cond)
        _, outs = stack_forward(self.encoder, embed(self, z, t, cond, text), collect=True)
        return [blk(o) for o, blk in zip(outs, self.controlnet_down_mid_blocks)]


def denoise(den, z, t, cond, text, residuals=None):
    """reference/motionlcm.py's Denoiser.forward with the ControlNet's residuals injected."""
    seq = embed(den, z, t, cond, text)
    out, _ = stack_forward(den.encoder, seq, residuals=residuals)
    out = out[: z.shape[1]]
    if den.projected:
        out = den.latent_post(out)
    return out.transpose(0, 1)


def controlled_eps(den, cn, z, t, cond, text, control_cond, scale):
    """(eps `[B, L, C]`, the scaled residuals)."""
    res = [scale * r for r in cn(z, t, cond, text, control_cond)]
    return denoise(den, z, t, cond, text, res), res


# -- loading and sampling ----------------------------------------------------------------------

def load_libflame(path):
    """A converted trajectory-control motionlcm file -> (Denoiser, ControlNet, TrajEncoder,
    Decoder, SentenceT5, tokenizer, config, mean_raw `[22, 3]`, std_raw `[22, 3]`)."""
    from safetensors import safe_open
    den, dec, text, tok, config = motionlcm.load_libflame(path)
    with safe_open(path, "pt") as f:
        tensors = {k: f.get_tensor(k).float() for k in f.keys()
                   if k.startswith(("controlnet.", "traj_encoder.", "control."))}
        assert json.loads(f.metadata()["flame.config"]) == config
    d, c = config["denoiser"], config["control"]
    cn = ControlNet(d["latent_dim"], d["latent_tokens"], d["latent_channels"], d["text_dim"],
                    d["cond_dim"], d["layers"], d["heads"], d["ff_size"], d["max_len"],
                    d["text_activation"], den.projected, c["embed_dim"], c["embed_activation"])
    cn.load_state_dict({k[len("controlnet."):]: x for k, x in tensors.items()
                        if k.startswith("controlnet.")}, strict=True)
    traj = TrajEncoder(d["latent_dim"], d["latent_tokens"], d["latent_channels"], c["layers"],
                       c["heads"], c["ff_size"], c["max_len"], den.projected)
    traj.load_state_dict({k[len("traj_encoder."):]: x for k, x in tensors.items()
                          if k.startswith("traj_encoder.")}, strict=True)
    return (den, cn.eval(), traj.eval(), dec, text, tok, config, tensors["control.mean_raw"],
            tensors["control.std_raw"])


def control_condition(traj, config, joints, mean_raw, std_raw):
    """joints `[F, 22, 3]` (NaN = free) -> (hint `[F, 66]`, frame mask `[F]` bool, condition
    `[L, C]`)."""
    hint, mask = normalise_hint(joints, mean_raw, std_raw)
    valid = frame_mask(hint, mask, config["control"]["frame_mask"])
    with torch.no_grad():
        cond = traj(hint[None], valid[None])[0]
    return hint, valid, cond


def sample(den, cn, config, z_T, text, guidance, steps, renoise, control_cond):
    """reference/motionlcm.py's sample() with the ControlNet's (scaled) residuals in every
    denoiser call; control_cond `[L, C]`."""
    cond = motionlcm.guidance_embedding(torch.tensor([guidance - 1.0]),
                                        config["denoiser"]["cond_dim"])
    scale = float(config["control"]["scale"])

    def net(x, t):
        tt = torch.tensor([t])
        return controlled_eps(den, cn, x, tt, cond, text, control_cond[None], scale)[0]

    with torch.no_grad(), motionlcm._network(net):
        return diffusers_lcm.run(diffusers_lcm.scheduler(), motionlcm.timesteps_for(config, steps),
                                 z_T, None, [r[None] for r in renoise])
