"""PyTorch reference of MoLA's text-to-motion inference (sony/MoLA 3313148), from the files
docs/official/mola-mld.md names (docs/official/mola-mld.md#mola-denoiser,
docs/official/mola-mld.md#mola-vae-decoder).

Module names follow the official state dicts, so `state_dict()` has an official checkpoint's keys:
- `Stage2` = the 'trans' dict: `denoiser.*` (the stable-audio style DiffusionTransformer, 7.3.1)
  plus the wrapper's unused top-level copies (`timestep_features`, `to_timestep_embed`,
  `to_global_embed`, `preprocess_conv`, `postprocess_conv`) and the buffers (`inv_freq`, the
  LayerNorm `beta`s).
- `Stage1Decoder` = the decoder part of the 'net' dict, under `vae.decoder.model.*` (7.3.2), with
  ReLU inside the residual blocks, as the released stage-2 scripts build it.

Also here: the DDIM sampler (the `diffusers` DDIMScheduler, i.e. an implementation independent of
libflame's, configured as 7.3.3), CFG as 7.3.1.6, and the valid-length cut of the decoded flag.
Tensors use the official layouts: latents `[B, C, T']`, decoded motion `[B, 264, T]`.
"""
import json
import math

import torch
import torch.nn.functional as F
from torch import nn

FLAG_THRESHOLD = 0.999
MIN_FRAMES = 10


# -- denoiser --------------------------------------------------------------------------------------

class FourierFeatures(nn.Module):
    """f = fl32(fl32(fl32(2pi)·t)·W) (7.3.3 rounding order), then [cos f, sin f]."""

    def __init__(self, n):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(n, 1))

    def forward(self, t):
        two_pi = torch.tensor(2 * math.pi, dtype=torch.float32)
        tw = two_pi * t.to(torch.float32)  # [B]
        f = tw[:, None] * self.weight[:, 0][None, :]  # in_features 1: one product per entry
        return torch.cat([f.cos(), f.sin()], dim=-1)


class LayerNormZeroBeta(nn.Module):
    """Learned scale `gamma`, bias a persistent zero buffer `beta` (7.1.4, 7.3.1)."""

    def __init__(self, dim, eps=1e-5):
        super().__init__()
        self.eps = eps
        self.gamma = nn.Parameter(torch.ones(dim))
        self.register_buffer("beta", torch.zeros(dim))

    def forward(self, x):
        return F.layer_norm(x, x.shape[-1:], self.gamma, self.beta, self.eps)


class Rotary(nn.Module):
    """inv_freq = 10000^(-2i/rotary_dim), a persistent buffer `[rotary_dim/2]`."""

    def __init__(self, rotary_dim):
        super().__init__()
        inv = 1.0 / (10000 ** (torch.arange(0, rotary_dim, 2).float() / rotary_dim))
        self.register_buffer("inv_freq", inv)

    def angles(self, n):
        pos = torch.arange(n, dtype=self.inv_freq.dtype)
        a = pos[:, None] * self.inv_freq[None, :]
        return torch.cat([a, a], dim=-1)  # [n, rotary_dim]


def rotate_half(x):
    a, b = x.chunk(2, dim=-1)
    return torch.cat([-b, a], dim=-1)


def apply_rotary(x, ang):
    """x `[B, H, N, D]`: the first rotary_dim dims of each head rotated, pairing dim i with
    i + rotary_dim/2 (rotate-half); the rest passes through."""
    r = ang.shape[-1]
    xr, rest = x[..., :r], x[..., r:]
    xr = xr * ang.cos() + rotate_half(xr) * ang.sin()
    return torch.cat([xr, rest], dim=-1)


class Attention(nn.Module):
    def __init__(self, dim, heads):
        super().__init__()
        self.heads = heads
        self.to_qkv = nn.Linear(dim, 3 * dim, bias=False)
        self.to_out = nn.Linear(dim, dim, bias=False)

    def forward(self, x, ang):
        b, n, d = x.shape
        q, k, v = self.to_qkv(x).chunk(3, dim=-1)  # three [B, N, dim] blocks, each head-major
        q, k, v = (t.reshape(b, n, self.heads, d // self.heads).transpose(1, 2) for t in (q, k, v))
        q, k = apply_rotary(q, ang), apply_rotary(k, ang)
        att = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(d // self.heads), dim=-1)
        out = (att @ v).transpose(1, 2).reshape(b, n, d)
        return self.to_out(out)


class GLU(nn.Module):
    def __init__(self, dim, inner):
        super().__init__()
        self.proj = nn.Linear(dim, 2 * inner)

    def forward(self, x):
        value, gate = self.proj(x).chunk(2, dim=-1)
        return value * F.silu(gate)


class FeedForward(nn.Module):
    def __init__(self, dim, inner):
        super().__init__()
        # Indices as the official Sequential: 0 = GLU, 1 = (no-param identity), 2 = out linear.
        self.ff = nn.Sequential(GLU(dim, inner), nn.Identity(), nn.Linear(inner, dim))

    def forward(self, x):
        return self.ff(x)


class Block(nn.Module):
    def __init__(self, dim, heads, ff_dim, eps):
        super().__init__()
        self.pre_norm = LayerNormZeroBeta(dim, eps)
        self.self_attn = Attention(dim, heads)
        self.ff_norm = LayerNormZeroBeta(dim, eps)
        self.ff = FeedForward(dim, ff_dim)

    def forward(self, x, ang):
        x = x + self.self_attn(self.pre_norm(x), ang)
        return x + self.ff(self.ff_norm(x))


class ContinuousTransformer(nn.Module):
    def __init__(self, io, dim, depth, heads, rotary_dim, ff_dim, eps):
        super().__init__()
        self.project_in = nn.Linear(io, dim, bias=False)
        self.project_out = nn.Linear(dim, io, bias=False)
        self.rotary_pos_emb = Rotary(rotary_dim)
        self.layers = nn.ModuleList([Block(dim, heads, ff_dim, eps) for _ in range(depth)])

    def forward(self, x, prepend):
        """x `[B, T', io]`, prepend `[B, 1, dim]` -> `[B, 1 + T', io]`."""
        x = torch.cat([prepend, self.project_in(x)], dim=1)
        ang = self.rotary_pos_emb.angles(x.shape[1])  # positions include the prepended token
        for layer in self.layers:
            x = layer(x, ang)
        return self.project_out(x)


def _embedders(io, dim, cond_dim, time_features):
    return dict(
        timestep_features=FourierFeatures(time_features),
        to_timestep_embed=nn.Sequential(nn.Linear(2 * time_features, dim), nn.SiLU(),
                                        nn.Linear(dim, dim)),
        to_global_embed=nn.Sequential(nn.Linear(cond_dim, dim, bias=False), nn.SiLU(),
                                      nn.Linear(dim, dim, bias=False)),
        preprocess_conv=nn.Conv1d(io, io, 1, bias=False),
        postprocess_conv=nn.Conv1d(io, io, 1, bias=False),
    )


class DiffusionTransformer(nn.Module):
    def __init__(self, latent_channels=16, embed_dim=512, depth=9, num_heads=4, rotary_dim=64,
                 ff_dim=2048, cond_dim=512, time_features=128, layer_norm_eps=1e-5):
        super().__init__()
        for name, m in _embedders(latent_channels, embed_dim, cond_dim, time_features).items():
            setattr(self, name, m)
        self.transformer = ContinuousTransformer(latent_channels, embed_dim, depth, num_heads,
                                                 rotary_dim, ff_dim, layer_norm_eps)

    def forward(self, x, t, cond):
        """x `[B, io, T']`, t `[B]` (integer steps), cond `[B, cond_dim]` -> eps `[B, io, T']`."""
        g = self.to_global_embed(cond) + self.to_timestep_embed(self.timestep_features(t))
        x = self.preprocess_conv(x) + x
        out = self.transformer(x.transpose(1, 2), g[:, None, :])
        out = out.transpose(1, 2)[:, :, 1:]  # drop the prepended token
        return self.postprocess_conv(out) + out


class Stage2(nn.Module):
    """The 'trans' state dict: the denoiser plus the wrapper's unused top-level copies."""

    def __init__(self, **cfg):
        super().__init__()
        self.denoiser = DiffusionTransformer(**cfg)
        sizes = (cfg.get("latent_channels", 16), cfg.get("embed_dim", 512),
                 cfg.get("cond_dim", 512), cfg.get("time_features", 128))
        for name, m in _embedders(*sizes).items():
            setattr(self, name, m)


# -- VAE decoder -----------------------------------------------------------------------------------

class ResConv1D(nn.Module):
    """ReLU -> Conv(k3, dilation d, pad d) -> ReLU -> Conv(k1) + residual."""

    def __init__(self, width, dilation):
        super().__init__()
        self.conv1 = nn.Conv1d(width, width, 3, padding=dilation, dilation=dilation)
        self.conv2 = nn.Conv1d(width, width, 1)

    def forward(self, x):
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class Resnet1D(nn.Module):
    def __init__(self, width, blocks, growth):
        super().__init__()
        # Dilations growth^(blocks-1-i): 9, 3, 1 for 3 blocks of growth 3.
        self.model = nn.Sequential(*[ResConv1D(width, growth ** (blocks - 1 - i))
                                     for i in range(blocks)])

    def forward(self, x):
        return self.model(x)


class Upsample(nn.Module):
    def forward(self, x):
        return F.interpolate(x, scale_factor=2, mode="nearest")


class Decoder(nn.Module):
    """`model` Sequential with the official indices (7.3.2): 0 conv, 1 ReLU, 2..(1+U) up stages
    [Resnet1D, Upsample, conv], then conv, ReLU, conv to output_dim."""

    def __init__(self, latent_channels=16, width=512, output_dim=264, upsample_layers=2,
                 res_blocks=3, dilation_growth=3):
        super().__init__()
        mods = [nn.Conv1d(latent_channels, width, 3, padding=1), nn.ReLU()]
        for _ in range(upsample_layers):
            mods.append(nn.Sequential(Resnet1D(width, res_blocks, dilation_growth), Upsample(),
                                      nn.Conv1d(width, width, 3, padding=1)))
        mods += [nn.Conv1d(width, width, 3, padding=1), nn.ReLU(),
                 nn.Conv1d(width, output_dim, 3, padding=1)]
        self.model = nn.Sequential(*mods)

    def forward(self, z):
        return self.model(z)


class Stage1Decoder(nn.Module):
    """Holds the decoder at the official path `vae.decoder.model.*`."""

    def __init__(self, **cfg):
        super().__init__()
        self.vae = nn.Module()
        self.vae.decoder = Decoder(**cfg)

    def forward(self, z):
        return self.vae.decoder(z)


def valid_length(flag_logits, threshold=FLAG_THRESHOLD, min_frames=MIN_FRAMES):
    """flag logits `[T]` -> number of frames kept: the first frame with sigmoid(flag) <= threshold
    (all above: T - 1; docs/official/mola-mld.md#length-flag), at least min_frames.
    (choice) The result is also capped
    at T, which only matters for T < min_frames (not reachable by the official lengths)."""
    below = (torch.sigmoid(flag_logits) <= threshold).nonzero()
    n = int(below[0, 0]) if below.numel() else flag_logits.shape[0] - 1
    return min(max(n, min_frames), flag_logits.shape[0])


def decode(dec, z):
    """z `[1, C, T']` -> (features `[T_valid, output_dim - 1]` frame-major, valid length,
    raw output `[output_dim, T]`)."""
    out = dec(z)[0]
    n = valid_length(out[-1])
    return out[:-1, :n].transpose(0, 1).contiguous(), n, out


# -- sampling --------------------------------------------------------------------------------------

def latent_frames(frames):
    return (frames + 4) // 4


def make_scheduler():
    from diffusers import DDIMScheduler
    return DDIMScheduler(num_train_timesteps=1000, beta_schedule="scaled_linear",
                         beta_start=0.00085, beta_end=0.012, clip_sample=False,
                         set_alpha_to_one=False, steps_offset=1, timestep_spacing="trailing",
                         prediction_type="epsilon")


def sample(den, x_T, cond, guidance, steps=50):
    """DDIM, eta 0. CFG with batch [cond, uncond = zeros] unless guidance is 0 or exactly 1
    (one conditional pass, 7.3.1.6). Returns the list of per-step dicts {t, x, x0, eps}."""
    sch = make_scheduler()
    sch.set_timesteps(steps)
    x = x_T
    trace = []
    cfg = not (guidance == 0 or guidance == 1.0)
    for t in sch.timesteps:
        tt = t.reshape(1)
        if cfg:
            e = den(torch.cat([x, x]), torch.cat([tt, tt]),
                    torch.cat([cond, torch.zeros_like(cond)]))
            e_c, e_u = e[:1], e[1:]
            eps = e_u + guidance * (e_c - e_u)
        else:
            eps = den(x, tt, cond)
        out = sch.step(eps, t, x, eta=0.0)
        x = out.prev_sample
        trace.append({"t": int(t), "x": x, "x0": out.pred_original_sample, "eps": eps})
    return trace


# -- libflame file ---------------------------------------------------------------------------------

def load_libflame(path):
    """A converted libflame MoLA file -> (DiffusionTransformer, Decoder, config)."""
    from safetensors import safe_open
    with safe_open(path, "pt") as f:
        config = json.loads(f.metadata()["flame.config"])
        tensors = {k: f.get_tensor(k).float() for k in f.keys()}
    d, v = dict(config["denoiser"]), config["vae"]
    d.pop("max_latent_frames")
    den = DiffusionTransformer(**d)
    state = {k[len("denoiser."):]: t for k, t in tensors.items() if k.startswith("denoiser.")}
    missing, unexpected = den.load_state_dict(state, strict=False)
    assert not unexpected, unexpected
    assert all(k.endswith(("inv_freq", ".beta")) for k in missing), missing
    dec = Decoder(latent_channels=d["latent_channels"], width=v["width"],
                  output_dim=v["output_dim"], upsample_layers=v["upsample_layers"],
                  res_blocks=v["res_blocks"], dilation_growth=v["dilation_growth"])
    pre = "vae.decoder."
    dec.load_state_dict({k[len(pre):]: t for k, t in tensors.items() if k.startswith(pre)})
    return den.eval(), dec.eval(), config
