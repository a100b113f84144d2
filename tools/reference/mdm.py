"""PyTorch reference of MDM's `trans_enc` denoiser (GuyTevet/motion-diffusion-model) and of Motion
Flow Matching's `MDM_Flow` (dongzhuoyao/motionfm), which is the same network predicting a velocity.

Written from GuyTevet/motion-diffusion-model `model/mdm.py` (docs/official/mdm.md) and
dongzhuoyao/motionfm `model/mdm_flow.py` (docs/official/motionfm.md); it is the oracle the
Rust parity tests are generated from (tools/make_mdm_fixtures.py). Submodule names are the official
ones, so `state_dict()` has exactly an official checkpoint's keys (docs/official/mdm.md#state-dict-names) minus
`clip_model.*`: `input_process.poseEmbedding`, `sequence_pos_encoder.pe`, `seqTransEncoder`,
`embed_timestep.{sequence_pos_encoder.pe, time_embed.0, time_embed.2}`, `embed_text`,
`output_process.poseFinal`.

Also here: the MotionFM time mapping (`flow_time_index`), the MDM DDIM sampler with x0
parameterisation and CFG on x0 (`ddim_x0_loop`, over tools/reference/diffusion.py's
SpacedDiffusion tables), and the flow-matching Euler loop with guidance on the velocity
(`euler_loop`). Tensors use the official layout `[B, njoints, 1, frames]`.
"""
import json

import numpy as np
import torch
from torch import nn


class PositionalEncoding(nn.Module):
    """pe `[max_len, 1, d]`, sin on even channels, cos on odd (interleaved)
    (docs/official/mdm.md#positional-encoding)."""

    def __init__(self, d_model, max_len=5000):
        super().__init__()
        position = torch.arange(0, max_len, dtype=torch.float32)[:, None]
        # The quotient is a float64 scalar rounded once to float32 by the multiply.
        div_term = torch.exp(torch.arange(0, d_model, 2).float() * (-np.log(10000.0) / d_model))
        pe = torch.zeros(max_len, d_model)
        pe[:, 0::2] = torch.sin(position * div_term)
        pe[:, 1::2] = torch.cos(position * div_term)
        self.register_buffer("pe", pe[:, None, :])

    def forward(self, x):
        """x `[S, B, d]` + pe[0..S]."""
        return x + self.pe[: x.shape[0]]


class TimestepEmbedder(nn.Module):
    """Linear -> SiLU -> Linear on pe[t]; returns `[1, B, d]` (docs/official/mdm.md#timestep-embedding)."""

    def __init__(self, latent_dim, sequence_pos_encoder):
        super().__init__()
        self.sequence_pos_encoder = sequence_pos_encoder
        self.time_embed = nn.Sequential(nn.Linear(latent_dim, latent_dim), nn.SiLU(),
                                        nn.Linear(latent_dim, latent_dim))

    def forward(self, timesteps):
        return self.time_embed(self.sequence_pos_encoder.pe[timesteps]).permute(1, 0, 2)


class InputProcess(nn.Module):
    def __init__(self, input_feats, latent_dim):
        super().__init__()
        self.poseEmbedding = nn.Linear(input_feats, latent_dim)

    def forward(self, x):
        """`[B, njoints, 1, T]` -> `[T, B, d]`."""
        b, j, f, t = x.shape
        x = x.permute(3, 0, 1, 2).reshape(t, b, j * f)
        return self.poseEmbedding(x)


class OutputProcess(nn.Module):
    def __init__(self, input_feats, latent_dim, njoints):
        super().__init__()
        self.njoints = njoints
        self.poseFinal = nn.Linear(latent_dim, input_feats)

    def forward(self, x):
        """`[T, B, d]` -> `[B, njoints, 1, T]`."""
        t, b, _ = x.shape
        x = self.poseFinal(x).reshape(t, b, self.njoints, 1)
        return x.permute(1, 2, 3, 0)


class MDM(nn.Module):
    """MDM trans_enc, text-conditioned, "add" policy for time + text
    (docs/official/mdm.md#denoiser-forward-pass)."""

    def __init__(self, njoints=263, latent_dim=512, layers=8, heads=4, ff_size=1024,
                 activation="gelu", clip_dim=512, max_len=5000, dropout=0.1):
        super().__init__()
        self.njoints = njoints
        self.latent_dim = latent_dim
        self.clip_dim = clip_dim
        self.input_process = InputProcess(njoints, latent_dim)
        self.sequence_pos_encoder = PositionalEncoding(latent_dim, max_len)
        layer = nn.TransformerEncoderLayer(d_model=latent_dim, nhead=heads,
                                           dim_feedforward=ff_size, dropout=dropout,
                                           activation=activation)
        self.seqTransEncoder = nn.TransformerEncoder(layer, num_layers=layers,
                                                     enable_nested_tensor=False)
        self.embed_timestep = TimestepEmbedder(latent_dim, self.sequence_pos_encoder)
        self.embed_text = nn.Linear(clip_dim, latent_dim)
        self.output_process = OutputProcess(njoints, latent_dim, njoints)

    def forward(self, x, timesteps, text_features):
        """x `[B, njoints, 1, T]`, timesteps `[B]` long (pe rows), text_features `[B, clip_dim]`
        (zeros for the unconditional pass) -> `[B, njoints, 1, T]`."""
        emb = self.embed_timestep(timesteps)  # [1, B, d]
        emb = emb + self.embed_text(text_features)[None]
        xseq = torch.cat([emb, self.input_process(x)], dim=0)  # [T+1, B, d]
        xseq = self.sequence_pos_encoder(xseq)
        out = self.seqTransEncoder(xseq)[1:]
        return self.output_process(out)


def flow_time_index(t):
    """t in [0, 1] (float32 tensor) -> pe row trunc(float32(t * 1000)) (docs/official/motionfm.md#time-index)."""
    t = torch.as_tensor(t, dtype=torch.float32)
    return (t * 1000).long()


def frame_major(x):
    """`[njoints, 1, T]` -> `[T, njoints]` (libflame's layout)."""
    return x[:, 0, :].permute(1, 0).contiguous()


def guided(net, x, timesteps, cond, guidance):
    """CFG (docs/official/mdm.md#sampling-and-guidance):
    out_u + s*(out_c - out_u), cond = text vectors `[B, clip]`, uncond =
    zeros; both passes see the same x and t (run as one 2B batch)."""
    b = x.shape[0]
    out = net(torch.cat([x, x]), torch.cat([timesteps, timesteps]),
              torch.cat([cond, torch.zeros_like(cond)]))
    out_c, out_u = out[:b], out[b:]
    return out_u + guidance * (out_c - out_u)


def ddim_x0_loop(net, diffusion, x_T, cond, guidance):
    """MDM DDIM, eta 0, x0 parameterisation (START_X), no clamp, CFG on x0.

    `diffusion` is a reference.diffusion.SpacedDiffusion (the network sees timestep_map[t]).
    Per step: x0 = guided net output; eps = (sqrt(1/abar)·x_t - x0)/sqrt(1/abar - 1);
    x_{t-1} = sqrt(abar_prev)·x0 + sqrt(1 - abar_prev)·eps (coefficients float64 -> float32).
    Returns a list of per-step dicts {t, model_t, x, pred_xstart}."""
    from reference.diffusion import _gather
    x = x_T
    trace = []
    for i in reversed(range(diffusion.num_timesteps)):
        t = torch.full((x.shape[0],), i, dtype=torch.long)
        model_t = diffusion.model_timesteps(t)
        x0 = guided(net, x, model_t, cond, guidance)
        eps = diffusion.predict_eps_from_xstart(x, t, x0)
        abar_prev = _gather(diffusion.alphas_cumprod_prev, t, x.shape)
        x = x0 * torch.sqrt(abar_prev) + torch.sqrt(1 - abar_prev) * eps
        trace.append({"t": i, "model_t": int(model_t[0]), "x": x, "pred_xstart": x0})
    return trace


def euler_loop(net, x0_noise, cond, guidance, steps):
    """MotionFM Euler ODE from t = 0 (noise) to 1 (data), custom-loop semantics
    (docs/official/motionfm.md#euler-sampler):
    t_k = float32(k) / float32(N), v = guided velocity at t_k, x <- x + float32(1/N)·v.
    Returns a list of per-step dicts {t, index, x, v}."""
    x = x0_noise
    dt = torch.tensor(1.0 / steps, dtype=torch.float32)
    trace = []
    for k in range(steps):
        t = torch.tensor(k, dtype=torch.float32) / torch.tensor(steps, dtype=torch.float32)
        idx = flow_time_index(t).expand(x.shape[0])
        v = guided(net, x, idx, cond, guidance)
        x = x + dt * v
        trace.append({"t": float(t), "index": int(idx[0]), "x": x, "v": v})
    return trace


def load_libflame(path):
    """A converted libflame mdm/motionfm file back into this module; returns (net, config)."""
    from safetensors import safe_open
    with safe_open(path, "pt") as f:
        config = json.loads(f.metadata()["flame.config"])
        tensors = {k: f.get_tensor(k).float() for k in f.keys()}
    d = config["denoiser"]
    net = MDM(njoints=d["njoints"], latent_dim=d["latent_dim"], layers=d["layers"],
              heads=d["heads"], ff_size=d["ff_size"], activation=d["activation"],
              clip_dim=d["clip_dim"], max_len=d["max_len"])
    state = {k: v for k, v in tensors.items() if not k.startswith(("text.", "motion."))}
    missing, unexpected = net.load_state_dict(state, strict=False)
    assert not unexpected, unexpected
    assert all(k.endswith(".pe") for k in missing), missing
    net.eval()
    return net, config
