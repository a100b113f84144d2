"""PyTorch reference of MLD's text-to-motion inference (ChenFengYe/motion-latent-diffusion,
humanml3d config), from the files docs/official/mola-mld.md names (docs/official/mola-mld.md#mld-denoiser,
docs/official/mola-mld.md#mld-vae-decoder) plus standard PyTorch modules where they are silent.

Module names follow the official Lightning `state_dict` (under `denoiser.` and `vae.`):
- denoiser: `time_embedding.linear_{1,2}`, `emb_proj.1` (ReLU at index 0), `query_pos.pe`
  `[max_len, 1, D]` (learned), `mem_pos.pe` (present, unused), `encoder.{input_blocks.i,
  middle_block, output_blocks.i, linear_blocks.i, norm}`;
- VAE decoder: `query_pos_decoder.pe`, `decoder.{input_blocks.i, middle_block, output_blocks.i,
  linear_blocks.i, norm}`, `final_layer`.
Encoder and decoder layers are post-LN (normalize_before False), GELU, dropout off, with
nn.MultiheadAttention names (`self_attn.in_proj_weight`, ...), as nn.TransformerEncoderLayer /
nn.TransformerDecoderLayer name them.

Sampling: the `diffusers` DDIMScheduler ("leading" spacing, steps_offset 1, set_alpha_to_one
False), eta 0, CFG with batch [uncond; cond], uncond = the text encoder's embedding of "".
Latents `[B, 1, D]`.
"""
import json
import math

import torch
import torch.nn.functional as F
from torch import nn


def time_sinusoid(t, dim):
    """`[B]` -> `[B, dim]`: cos first; exponent = (-ln(10000)·i in float32) / (dim/2)."""
    half = dim // 2
    exponent = -math.log(10000) * torch.arange(half, dtype=torch.float32) / half
    a = t.to(torch.float32)[:, None] * torch.exp(exponent)[None, :]
    return torch.cat([a.cos(), a.sin()], dim=-1)


class LearnedPE(nn.Module):
    def __init__(self, max_len, dim):
        super().__init__()
        self.pe = nn.Parameter(torch.rand(max_len, 1, dim))

    def forward(self, x):
        """x `[S, B, D]` + pe[:S]."""
        return x + self.pe[: x.shape[0]]


class EncoderLayer(nn.Module):
    def __init__(self, d, heads, ff):
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d, heads, dropout=0.0)
        self.linear1, self.linear2 = nn.Linear(d, ff), nn.Linear(ff, d)
        self.norm1, self.norm2 = nn.LayerNorm(d), nn.LayerNorm(d)

    def forward(self, x, memory=None):
        x = self.norm1(x + self.self_attn(x, x, x, need_weights=False)[0])
        return self.norm2(x + self.linear2(F.gelu(self.linear1(x))))


class DecoderLayer(nn.Module):
    def __init__(self, d, heads, ff):
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d, heads, dropout=0.0)
        self.multihead_attn = nn.MultiheadAttention(d, heads, dropout=0.0)
        self.linear1, self.linear2 = nn.Linear(d, ff), nn.Linear(ff, d)
        self.norm1, self.norm2, self.norm3 = nn.LayerNorm(d), nn.LayerNorm(d), nn.LayerNorm(d)

    def forward(self, x, memory):
        x = self.norm1(x + self.self_attn(x, x, x, need_weights=False)[0])
        x = self.norm2(x + self.multihead_attn(x, memory, memory, need_weights=False)[0])
        return self.norm3(x + self.linear2(F.gelu(self.linear1(x))))


class SkipStack(nn.Module):
    """U-shaped stack of an odd number of layers: (n-1)/2 input blocks whose outputs are kept,
    a middle block, (n-1)/2 output blocks each preceded by Linear(2D -> D) over
    cat([x, skip], -1), the skips taken last-in first-out; then the final LayerNorm (if any).
    (choice) The concatenation order [x, skip] and the LIFO pairing are the U-Net reading of
    "concatenates its skip" (7.2 does not spell out either)."""

    def __init__(self, layer_cls, n_layers, d, heads, ff, final_norm=True):
        super().__init__()
        assert n_layers % 2 == 1, "a skip stack has an odd number of layers"
        nb = (n_layers - 1) // 2
        self.input_blocks = nn.ModuleList([layer_cls(d, heads, ff) for _ in range(nb)])
        self.middle_block = layer_cls(d, heads, ff)
        self.output_blocks = nn.ModuleList([layer_cls(d, heads, ff) for _ in range(nb)])
        self.linear_blocks = nn.ModuleList([nn.Linear(2 * d, d) for _ in range(nb)])
        self.norm = nn.LayerNorm(d) if final_norm else None

    def forward(self, x, memory=None):
        skips = []
        for m in self.input_blocks:
            x = m(x, memory)
            skips.append(x)
        x = self.middle_block(x, memory)
        for m, lin in zip(self.output_blocks, self.linear_blocks):
            x = m(lin(torch.cat([x, skips.pop()], dim=-1)), memory)
        return self.norm(x) if self.norm is not None else x


class Denoiser(nn.Module):
    def __init__(self, latent_dim=256, layers=9, heads=4, ff_size=1024, text_dim=768,
                 max_len=500):
        super().__init__()
        self.text_dim = text_dim
        self.time_embedding = nn.Module()
        self.time_embedding.linear_1 = nn.Linear(text_dim, latent_dim)
        self.time_embedding.linear_2 = nn.Linear(latent_dim, latent_dim)
        self.emb_proj = nn.Sequential(nn.ReLU(), nn.Linear(text_dim, latent_dim))
        self.query_pos = LearnedPE(max_len, latent_dim)
        self.mem_pos = LearnedPE(max_len, latent_dim)  # in the state dict, unused (choice: skipped)
        self.encoder = SkipStack(EncoderLayer, layers, latent_dim, heads, ff_size)

    def forward(self, z, t, text):
        """z `[B, 1, D]`, t `[B]`, text `[B, text_dim]` -> eps `[B, 1, D]`."""
        te = self.time_embedding
        time = te.linear_2(F.silu(te.linear_1(time_sinusoid(t, self.text_dim))))
        seq = torch.cat([z.transpose(0, 1), time[None], self.emb_proj(text)[None]], dim=0)
        out = self.encoder(self.query_pos(seq))
        return out[: z.shape[1]].transpose(0, 1)


class VaeDecoder(nn.Module):
    """Under `vae.`: query_pos_decoder, decoder (skip stack of DecoderLayer), final_layer."""

    def __init__(self, latent_dim=256, layers=9, heads=4, ff_size=1024, nfeats=263, max_len=500,
                 final_norm=True):
        super().__init__()
        self.query_pos_decoder = LearnedPE(max_len, latent_dim)
        self.decoder = SkipStack(DecoderLayer, layers, latent_dim, heads, ff_size, final_norm)
        self.final_layer = nn.Linear(latent_dim, nfeats)

    def forward(self, z, frames):
        """z `[B, 1, D]` -> features `[B, frames, nfeats]` (every frame valid)."""
        b, _, d = z.shape
        q = self.query_pos_decoder(torch.zeros(frames, b, d))
        return self.final_layer(self.decoder(q, z.transpose(0, 1))).transpose(0, 1)


def make_scheduler():
    from diffusers import DDIMScheduler
    return DDIMScheduler(num_train_timesteps=1000, beta_schedule="scaled_linear",
                         beta_start=0.00085, beta_end=0.012, clip_sample=False,
                         set_alpha_to_one=False, steps_offset=1, timestep_spacing="leading",
                         prediction_type="epsilon")


def sample(den, z_T, cond, uncond, guidance, steps=50):
    """DDIM eta 0. guidance > 1: batch [uncond; cond], eps = u + s(c - u); otherwise one
    conditional pass (MLD enables CFG only for a scale above 1)."""
    sch = make_scheduler()
    sch.set_timesteps(steps)
    z = z_T
    trace = []
    for t in sch.timesteps:
        tt = t.reshape(1)
        if guidance > 1.0:
            e = den(torch.cat([z, z]), torch.cat([tt, tt]), torch.cat([uncond, cond]))
            eps = e[:1] + guidance * (e[1:] - e[:1])
        else:
            eps = den(z, tt, cond)
        out = sch.step(eps, t, z, eta=0.0)
        z = out.prev_sample
        trace.append({"t": int(t), "x": z, "x0": out.pred_original_sample, "eps": eps})
    return trace


def load_libflame(path):
    """A converted libflame MLD file -> (Denoiser, VaeDecoder, config)."""
    from safetensors import safe_open
    with safe_open(path, "pt") as f:
        config = json.loads(f.metadata()["flame.config"])
        tensors = {k: f.get_tensor(k).float() for k in f.keys()}
    d, v = config["denoiser"], config["vae"]
    den = Denoiser(d["latent_dim"], d["layers"], d["heads"], d["ff_size"], d["text_dim"],
                   d["max_len"])
    state = {k[len("denoiser."):]: t for k, t in tensors.items() if k.startswith("denoiser.")}
    missing, unexpected = den.load_state_dict(state, strict=False)
    assert not unexpected and missing == ["mem_pos.pe"], (missing, unexpected)
    dec = VaeDecoder(v["latent_dim"], v["layers"], v["heads"], v["ff_size"], v["nfeats"],
                     v["max_len"], v["final_norm"])
    dec.load_state_dict({k[len("vae."):]: t for k, t in tensors.items() if k.startswith("vae.")})
    return den.eval(), dec.eval(), config
