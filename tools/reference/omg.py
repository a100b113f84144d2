"""PyTorch definition of the OMG-style model (Liang et al., "Towards Open-vocabulary Motion
Generation via Mixture of Controllers", CVPR 2024, sections 3.1 and 3.2; docs/official/omg.md).

No official code or weights were released, so this module DEFINES the model libflame runs: the
paper's statements plus libflame's documented choice for every detail it does not give
(docs/omg.md). Module names are the model file's tensor names (file = `denoiser.` + these):

  x_embed                       Linear(F -> d): one token per frame, no absolute position
  t_embed.mlp.{0,2}             sinusoid(t) -> Linear -> SiLU -> Linear = c
  blocks.{i}                    adaLN-Zero DiT block with RoPE self-attention:
      adaLN_modulation.1, attn.qkv, attn.proj, mlp.fc1, mlp.fc2
  final_layer.adaLN_modulation.1, final_layer.linear
  control.blocks.{i}            trainable copy of block i (the motion ControlNet)
  control.down.{i}              Conv1d(d -> d_m, k)
  control.moc.{i}               Mixture-of-Controllers: q, k, v, adain.{gamma,beta},
                                experts.{w0,b0,w1,b1}, gate.{0,2,4}
  control.up.{i}                Conv1d(d_m -> d, k)

`cfg["control"] is None` gives the backbone alone (D_u, a "backbone-only" model).
Tensors are frame-major: x [B, T, F]. `forward(x, t, text)` returns x-hat-0; t is the ORIGINAL
diffusion step (0..999, also under respacing); text None = D_u, else a dict from
`encode_text` / `batch_texts` = D_c.

Rounding conventions the runtime follows: the timestep sinusoid and the RoPE cos/sin tables
are computed in float64 and rounded once to the working dtype; everything else runs in the
weights' dtype (float32 normally). Sampling: DDIM eta 0 over the cosine schedule with x0
prediction (guided-diffusion tables, float64 gathered to float32), guidance
x0 = D_u + s * (D_c - D_u).
"""
import copy
import json
import math

import torch
import torch.nn.functional as F
from torch import nn

from .diffusion import SpacedDiffusion, cosine_betas, space_timesteps

SOT, EOT, CONTEXT = 49406, 49407, 77

CONTROL_DEFAULTS = dict(control_dim=256, text_dim=768, conv_kernel=1, attn_heads=1, experts=12,
                        expert_hidden=512, expert_activation="gelu", gate_hidden=512,
                        gate_activation="gelu", mask_gamma=24.0, mask_beta=0.25, adain_eps=1e-5,
                        text_padding=False)
BACKBONE_DEFAULTS = dict(input_feats=263, d_model=1024, layers=8, heads=8, ff_size=2048,
                         time_freq_dim=256, rope_base=10000.0, rope_dims=128, norm_eps=1e-6,
                         mlp_activation="gelu_tanh", max_frames=300)
# Table 1 of the paper: layers, d_model, heads (head dim 128, ff 2·d).
PRESETS = {"base": (8, 1024, 8), "large": (12, 1280, 10), "huge": (16, 1664, 13),
           "giant": (24, 2048, 16)}
MLP_ACTIVATIONS = ("gelu_tanh", "gelu")
MOC_ACTIVATIONS = ("gelu", "gelu_tanh", "silu")


def preset(name, input_feats=263, control=True, **overrides):
    """The denoiser configuration of a paper size (Table 1); `control=False`: backbone only."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r} (expected one of {', '.join(PRESETS)})")
    layers, d, heads = PRESETS[name]
    cfg = dict(BACKBONE_DEFAULTS, input_feats=input_feats, d_model=d, layers=layers, heads=heads,
               ff_size=2 * d, rope_dims=d // heads)
    cfg["control"] = dict(CONTROL_DEFAULTS) if control else None
    cfg.update(overrides)
    return cfg


def full_config(cfg):
    """cfg with every default filled in (a preset name is accepted); validated."""
    if isinstance(cfg, str):
        cfg = preset(cfg)
    out = dict(BACKBONE_DEFAULTS)
    out.update({k: v for k, v in cfg.items() if k != "control"})
    if "rope_dims" not in cfg:
        out["rope_dims"] = out["d_model"] // out["heads"]
    ctrl = cfg.get("control")
    out["control"] = None if ctrl is None else dict(CONTROL_DEFAULTS, **ctrl)
    validate(out)
    return out


def validate(c):
    d, h = c["d_model"], c["heads"]
    if d % h:
        raise ValueError(f"d_model {d} is not divisible by heads {h}")
    r = c["rope_dims"]
    if r % 2 or not 0 <= r <= d // h:
        raise ValueError(f"rope_dims {r}: must be even and at most the head dim {d // h}")
    if c["time_freq_dim"] % 2 or c["time_freq_dim"] < 2:
        raise ValueError(f"time_freq_dim {c['time_freq_dim']} must be even")
    if c["mlp_activation"] not in MLP_ACTIVATIONS:
        raise ValueError(f"mlp_activation {c['mlp_activation']!r} (accepted: "
                         f"{', '.join(MLP_ACTIVATIONS)})")
    m = c["control"]
    if m is None:
        return
    if m["conv_kernel"] % 2 == 0:
        raise ValueError(f"conv_kernel {m['conv_kernel']} must be odd (length-preserving)")
    if m["control_dim"] % m["attn_heads"]:
        raise ValueError(f"control_dim {m['control_dim']} not divisible by attn_heads "
                         f"{m['attn_heads']}")
    for k in ("expert_activation", "gate_activation"):
        if m[k] not in MOC_ACTIVATIONS:
            raise ValueError(f"{k} {m[k]!r} (accepted: {', '.join(MOC_ACTIVATIONS)})")


def activation(name):
    return {"gelu": nn.GELU(), "gelu_tanh": nn.GELU(approximate="tanh"),
            "silu": nn.SiLU()}[name]


# -- positions and time ----------------------------------------------------------------------------

def timestep_sinusoid(t, dim, dtype):
    """DiT's timestep features: [cos(t f_i), sin(t f_i)], f_i = exp(-ln(10000) i / (dim/2)),
    i < dim/2 (cos first). Computed in float64 and rounded once. t [B] -> [B, dim]."""
    half = dim // 2
    f = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float64) / half)
    arg = torch.as_tensor(t, dtype=torch.float64).reshape(-1, 1) * f[None]
    return torch.cat([torch.cos(arg), torch.sin(arg)], dim=-1).to(dtype)


def rope_tables(frames, rope_dims, base, dtype):
    """cos, sin [T, r/2] of angle p · base^(-2i/r) (p = frame index), float64 rounded once."""
    half = rope_dims // 2
    inv = float(base) ** (-2.0 * torch.arange(half, dtype=torch.float64) / rope_dims)
    ang = torch.arange(frames, dtype=torch.float64)[:, None] * inv[None]
    return torch.cos(ang).to(dtype), torch.sin(ang).to(dtype)


def apply_rope(x, cos, sin):
    """Rotate-half RoPE on the first r dims of x [B, T, H, hd]: the pair (j, j + r/2), j < r/2,
    turns by the angle of row j: (a, b) -> (a cos - b sin, b cos + a sin); dims >= r untouched."""
    half = cos.shape[1]
    if half == 0:
        return x
    c, s = cos[None, :, None, :], sin[None, :, None, :]
    a, b = x[..., :half], x[..., half:2 * half]
    return torch.cat([a * c - b * s, b * c + a * s, x[..., 2 * half:]], dim=-1)


def modulate(x, shift, scale):
    return x * (1 + scale[:, None]) + shift[:, None]


# -- the DiT backbone (10.2) -----------------------------------------------------------------------

class TimestepEmbedder(nn.Module):
    def __init__(self, d, freq_dim):
        super().__init__()
        self.freq_dim = freq_dim
        self.mlp = nn.Sequential(nn.Linear(freq_dim, d), nn.SiLU(), nn.Linear(d, d))

    def forward(self, t):
        dtype = self.mlp[0].weight.dtype
        return self.mlp(timestep_sinusoid(t, self.freq_dim, dtype))


class Attention(nn.Module):
    """Multi-head self-attention over the frames with RoPE on q and k; no mask."""

    def __init__(self, d, heads):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(d, 3 * d)
        self.proj = nn.Linear(d, d)

    def forward(self, x, rope):
        b, t, d = x.shape
        hd = d // self.heads
        q, k, v = self.qkv(x).reshape(b, t, 3, self.heads, hd).unbind(2)  # [B, T, H, hd]
        q, k = apply_rope(q, *rope), apply_rope(k, *rope)
        q, k, v = (z.transpose(1, 2) for z in (q, k, v))  # [B, H, T, hd]
        a = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(hd), dim=-1)
        return self.proj((a @ v).transpose(1, 2).reshape(b, t, d))


class Mlp(nn.Module):
    def __init__(self, d, ff, act):
        super().__init__()
        self.fc1 = nn.Linear(d, ff)
        self.act = activation(act)
        self.fc2 = nn.Linear(ff, d)

    def forward(self, x):
        return self.fc2(self.act(self.fc1(x)))


class DiTBlock(nn.Module):
    """adaLN-Zero: x += g_msa · Attn(mod(LN(x))), x += g_mlp · MLP(mod(LN(x))); LN without
    affine; the six modulations from SiLU(c) in the order shift, scale, gate (msa then mlp)."""

    def __init__(self, c):
        super().__init__()
        d = c["d_model"]
        self.eps = c["norm_eps"]
        self.attn = Attention(d, c["heads"])
        self.mlp = Mlp(d, c["ff_size"], c["mlp_activation"])
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(d, 6 * d))

    def forward(self, x, c, rope):
        d = x.shape[-1]
        sh_a, sc_a, g_a, sh_m, sc_m, g_m = self.adaLN_modulation(c).chunk(6, dim=-1)
        x = x + g_a[:, None] * self.attn(modulate(F.layer_norm(x, (d,), eps=self.eps), sh_a,
                                                  sc_a), rope)
        return x + g_m[:, None] * self.mlp(modulate(F.layer_norm(x, (d,), eps=self.eps), sh_m,
                                                    sc_m))


class FinalLayer(nn.Module):
    def __init__(self, c):
        super().__init__()
        d = c["d_model"]
        self.eps = c["norm_eps"]
        self.adaLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(d, 2 * d))
        self.linear = nn.Linear(d, c["input_feats"])

    def forward(self, x, c):
        shift, scale = self.adaLN_modulation(c).chunk(2, dim=-1)
        return self.linear(modulate(F.layer_norm(x, (x.shape[-1],), eps=self.eps), shift, scale))


# -- the Mixture-of-Controllers block (10.4) -------------------------------------------------------

class AdaIN(nn.Module):
    """gamma(e) · (f - mu) / sqrt(var + eps) + beta(e); mu, biased var per channel over frames."""

    def __init__(self, text_dim, dim, eps):
        super().__init__()
        self.eps = eps
        self.gamma = nn.Linear(text_dim, dim)
        self.beta = nn.Linear(text_dim, dim)

    def forward(self, f, eos):
        mu = f.mean(dim=1, keepdim=True)
        var = ((f - mu) ** 2).mean(dim=1, keepdim=True)
        return self.gamma(eos)[:, None] * (f - mu) / torch.sqrt(var + self.eps) \
            + self.beta(eos)[:, None]


class Experts(nn.Module):
    """K two-layer FFNs y = act(x W0 + b0) W1 + b1 (W0 stored [in, out])."""

    def __init__(self, k, dim, hidden, act):
        super().__init__()
        self.w0 = nn.Parameter(torch.empty(k, dim, hidden))
        self.b0 = nn.Parameter(torch.empty(k, hidden))
        self.w1 = nn.Parameter(torch.empty(k, hidden, dim))
        self.b1 = nn.Parameter(torch.empty(k, dim))
        self.act = activation(act)
        for p in (self.w0, self.w1):
            nn.init.uniform_(p, -1 / math.sqrt(p.shape[1]), 1 / math.sqrt(p.shape[1]))
        nn.init.zeros_(self.b0)
        nn.init.zeros_(self.b1)

    def blended_params(self, x, omega):
        """Token i's own expert, parameters mixed (the paper's e(i) = sum_j w_ij e_j):
        x [B, T, dm], omega [B, n, K] -> y [B, n, T, dm]."""
        w0 = torch.einsum("bnk,kde->bnde", omega, self.w0)
        b0 = omega @ self.b0
        w1 = torch.einsum("bnk,ked->bned", omega, self.w1)
        b1 = omega @ self.b1
        h = self.act(torch.einsum("btd,bnde->bnte", x, w0) + b0[:, :, None])
        return torch.einsum("bnte,bned->bntd", h, w1) + b1[:, :, None]

    def blended_outputs(self, x, omega):
        """The contrast case: every expert run on x, their OUTPUTS mixed by omega."""
        h = self.act(torch.einsum("btd,kde->bkte", x, self.w0) + self.b0[None, :, None])
        y = torch.einsum("bkte,ked->bktd", h, self.w1) + self.b1[None, :, None]
        return torch.einsum("bnk,bktd->bntd", omega, y)


class MoC(nn.Module):
    """Cross-attention of the motion features on the text tokens, Ada-IN on the end-of-text
    feature, per-token blended experts, masked residuals summed over the tokens."""

    def __init__(self, m):
        super().__init__()
        dm, dt = m["control_dim"], m["text_dim"]
        self.heads = m["attn_heads"]
        self.gamma, self.beta = float(m["mask_gamma"]), float(m["mask_beta"])
        self.q = nn.Linear(dm, dm)
        self.k = nn.Linear(dt, dm)
        self.v = nn.Linear(dt, dm)
        self.adain = AdaIN(dt, dm, m["adain_eps"])
        self.experts = Experts(m["experts"], dm, m["expert_hidden"], m["expert_activation"])
        gh, act = m["gate_hidden"], m["gate_activation"]
        self.gate = nn.Sequential(nn.Linear(dt, gh), activation(act), nn.Linear(gh, gh),
                                  activation(act), nn.Linear(gh, m["experts"]))
        self.last = None  # A, M, omega of the latest call (inspection)

    def forward(self, f, text, blend="params"):
        tokens, eos, keep = text["tokens"], text["eos"], text.get("mask")
        b, t, dm = f.shape
        n, h = tokens.shape[1], self.heads
        dh = dm // h
        q = self.q(f).reshape(b, t, h, dh).transpose(1, 2)          # [B, h, T, dh]
        k = self.k(tokens).reshape(b, n, h, dh).transpose(1, 2)     # [B, h, n, dh]
        v = self.v(tokens).reshape(b, n, h, dh).transpose(1, 2)
        s = q @ k.transpose(-1, -2) / math.sqrt(dh)                 # [B, h, T, n]
        if keep is not None:
            s = s.masked_fill(~keep[:, None, None, :], float("-inf"))
        a_h = torch.softmax(s, dim=-1)
        f1 = f + (a_h @ v).transpose(1, 2).reshape(b, t, dm)
        a = a_h.mean(dim=1)                                         # [B, T, n]
        f2 = self.adain(f1, eos)
        omega = torch.softmax(self.gate(tokens), dim=-1)            # [B, n, K]
        if blend == "params":
            y = self.experts.blended_params(f2, omega)
        elif blend == "outputs":
            y = self.experts.blended_outputs(f2, omega)
        else:
            raise ValueError(f"blend {blend!r} (expected 'params' or 'outputs')")
        mask = torch.sigmoid(self.gamma * (a - self.beta * a.amax(dim=1, keepdim=True)))
        if keep is not None:
            mask = mask * keep[:, None, :].to(mask.dtype)
        self.last = {"A": a, "M": mask, "omega": omega}
        return (mask.transpose(1, 2)[..., None] * y).sum(dim=1)     # [B, T, dm]


class ControlNet(nn.Module):
    def __init__(self, c):
        super().__init__()
        m, d, k = c["control"], c["d_model"], c["control"]["conv_kernel"]
        self.blocks = nn.ModuleList(DiTBlock(c) for _ in range(c["layers"]))
        self.down = nn.ModuleList(nn.Conv1d(d, m["control_dim"], k, padding=k // 2)
                                  for _ in range(c["layers"]))
        self.moc = nn.ModuleList(MoC(m) for _ in range(c["layers"]))
        self.up = nn.ModuleList(nn.Conv1d(m["control_dim"], d, k, padding=k // 2)
                                for _ in range(c["layers"]))

    def residual(self, i, h, c, rope, text, blend):
        """Up_i(MoC_i(Down_i(Copy_i(h, c)))) [B, T, d]; the convs run along the frames."""
        g = self.blocks[i](h, c, rope)
        f = self.down[i](g.transpose(1, 2)).transpose(1, 2)
        r = self.moc[i](f, text, blend)
        return self.up[i](r.transpose(1, 2)).transpose(1, 2)


class OMG(nn.Module):
    """The OMG-style denoiser: D_u (text None) or D_c (text given). cfg: the file's `denoiser`
    section (defaults filled in) or a preset name."""

    def __init__(self, cfg):
        super().__init__()
        self.cfg = full_config(cfg)
        c = self.cfg
        self.x_embed = nn.Linear(c["input_feats"], c["d_model"])
        self.t_embed = TimestepEmbedder(c["d_model"], c["time_freq_dim"])
        self.blocks = nn.ModuleList(DiTBlock(c) for _ in range(c["layers"]))
        self.final_layer = FinalLayer(c)
        if c["control"] is not None:
            self.control = ControlNet(c)

    @property
    def backbone_only(self):
        return self.cfg["control"] is None

    def forward(self, x, t, text=None, blend="params"):
        """x [B, T, F] (noisy features), t [B] or a number (original diffusion step), text None
        (D_u) or {"tokens" [B, n, D_t], "eos" [B, D_t], optional "mask" [B, n] bool} (D_c).
        Returns x-hat-0 [B, T, F]."""
        b, frames, _ = x.shape
        c = self.cfg
        if frames > c["max_frames"]:
            raise ValueError(f"{frames} frames exceed max_frames {c['max_frames']}")
        if text is not None and self.backbone_only:
            raise ValueError("a backbone-only model generates unconditionally (text must be None)")
        dtype = self.x_embed.weight.dtype
        t = torch.as_tensor(t, dtype=torch.float64).reshape(-1).expand(b)
        rope = rope_tables(frames, c["rope_dims"], c["rope_base"], dtype)
        emb = self.t_embed(t)
        h = self.x_embed(x)
        for i, blk in enumerate(self.blocks):
            out = blk(h, emb, rope)
            if text is not None:
                out = out + self.control.residual(i, h, emb, rope, text, blend)
            h = out
        return self.final_layer(h, emb)

    def mocs(self):
        return [] if self.backbone_only else list(self.control.moc)


# -- text (10.4) -----------------------------------------------------------------------------------

def clip_ids(tokenizer, prompt, context=CONTEXT):
    """clip.tokenize(prompt, truncate=True): [SOT] + ids + [EOT], zero-padded to `context`."""
    content = tokenizer.encode(prompt, add_special_tokens=False).ids[: context - 2]
    ids = [SOT] + content + [EOT]
    return ids + [0] * (context - len(ids))


def is_blank(prompt):
    return prompt is None or not prompt.strip()


@torch.no_grad()
def encode_text(clip, tokenizer, prompt, text_padding=False):
    """CLIP per-token features at the final layer norm (HF last_hidden_state) of SOT..EOT
    (text_padding: all 77 positions) and e = the EOT token's feature.
    -> {"ids" [n], "tokens" [n, D_t], "eos" [D_t]} (float32)."""
    ids = clip_ids(tokenizer, prompt)
    eot = ids.index(EOT)
    feats = clip.text_model(input_ids=torch.tensor([ids])).last_hidden_state[0]
    keep = len(ids) if text_padding else eot + 1
    return {"ids": ids[:keep], "tokens": feats[:keep].float(), "eos": feats[eot].float()}


def batch_texts(texts, dtype=torch.float32):
    """Encoded texts -> the `text` argument of OMG.forward (padded, with a token mask)."""
    n = max(len(t["ids"]) for t in texts)
    dt = texts[0]["tokens"].shape[1]
    tokens = torch.zeros(len(texts), n, dt, dtype=dtype)
    mask = torch.zeros(len(texts), n, dtype=torch.bool)
    for i, t in enumerate(texts):
        tokens[i, :len(t["ids"])] = t["tokens"].to(dtype)
        mask[i, :len(t["ids"])] = True
    eos = torch.stack([t["eos"] for t in texts]).to(dtype)
    out = {"tokens": tokens, "eos": eos}
    if not bool(mask.all()):
        out["mask"] = mask
    return out


# -- guidance and sampling (10.3, 10.2) ------------------------------------------------------------

def guided_x0(net, x, t, text, guidance, blend="params"):
    """x0 = D_u + s (D_c - D_u) = (1 - s) D_u + s D_c; no text: D_u alone."""
    u = net(x, t)
    if text is None:
        return u
    return u + guidance * (net(x, t, text, blend) - u)


def make_diffusion(steps, num_timesteps=1000):
    """Cosine schedule, `steps` evenly spaced kept steps (space_timesteps(T, [steps]))."""
    return SpacedDiffusion(cosine_betas(num_timesteps), space_timesteps(num_timesteps, [steps]))


@torch.no_grad()
def ddim_sample(net, noise, text, guidance=4.5, steps=200, blend="params"):
    """DDIM eta 0 with x0 prediction, no clamp: eps = (x_t / sqrt(abar) - x0) / sqrt(1/abar - 1),
    x_prev = sqrt(abar_prev) x0 + sqrt(1 - abar_prev) eps (coefficients float64 -> dtype).
    noise [B, T, F]. Returns per-step dicts {t (original), x (after the step), x0}."""
    diff = make_diffusion(steps)
    dt = noise.dtype

    def tab(table, i):
        return torch.tensor(float(table[i]), dtype=torch.float64).to(dt)

    x = noise
    trace = []
    for i in reversed(range(diff.num_timesteps)):
        t = int(diff.timestep_map[i])
        x0 = guided_x0(net, x, float(t), text, guidance, blend)
        eps = (tab(diff.sqrt_recip_alphas_cumprod, i) * x - x0) \
            / tab(diff.sqrt_recipm1_alphas_cumprod, i)
        abp = tab(diff.alphas_cumprod_prev, i)
        x = x0 * torch.sqrt(abp) + torch.sqrt(1 - abp) * eps
        trace.append({"t": t, "x": x, "x0": x0})
    return trace


# -- files -----------------------------------------------------------------------------------------

def zero_up(net):
    """A copy of `net` whose every control.up.* weight and bias is zero (then D_c == D_u)."""
    out = copy.deepcopy(net)
    with torch.no_grad():
        for up in out.control.up:
            up.weight.zero_()
            up.bias.zero_()
    return out


def with_config(net, **changes):
    """The same weights under a changed configuration (fields not in any shape: heads of the
    MoC attention, rope_dims, text_padding, ...); control fields go under control=dict(...)."""
    cfg = copy.deepcopy(net.cfg)
    ctrl = changes.pop("control", None)
    cfg.update(changes)
    if ctrl:
        cfg["control"].update(ctrl)
    out = OMG(cfg).to(net.x_embed.weight.dtype)
    out.load_state_dict(net.state_dict())
    return out.eval()


def save_state_dict(net, path, wrap=False):
    """torch.save of the state dict (wrap: as {'state_dict': ...}), the converter's input."""
    sd = {k: v.detach().clone() for k, v in net.state_dict().items()}
    torch.save({"state_dict": sd} if wrap else sd, path)


def load_libflame(path):
    """(net, clip, tokenizer, config, mean, std) from a converted libflame omg file (float32;
    mean/std None when the file has none)."""
    from safetensors import safe_open
    from tokenizers import Tokenizer
    from transformers import CLIPTextConfig, CLIPTextModelWithProjection
    with safe_open(path, "pt") as f:
        meta = f.metadata()
        tensors = {k: f.get_tensor(k).float() for k in f.keys()}
    cfg = json.loads(meta["flame.config"])
    if cfg["architecture"] != "omg":
        raise ValueError(f"{path}: architecture {cfg['architecture']!r}, not omg")
    net = OMG(cfg["denoiser"])
    den = {k[len("denoiser."):]: v for k, v in tensors.items() if k.startswith("denoiser.")}
    net.load_state_dict(den, strict=True)
    te = cfg["text_encoder"]
    ccfg = CLIPTextConfig(vocab_size=te["vocab_size"], hidden_size=te["width"],
                          intermediate_size=te["intermediate_size"],
                          num_hidden_layers=te["layers"], num_attention_heads=te["heads"],
                          max_position_embeddings=te["context_length"],
                          projection_dim=te["projection_dim"], hidden_act="quick_gelu",
                          layer_norm_eps=te["layer_norm_eps"], attn_implementation="eager")
    clip = CLIPTextModelWithProjection(ccfg)
    clip_sd = {k[len("text."):]: v for k, v in tensors.items() if k.startswith("text.")}
    missing, unexpected = clip.load_state_dict(clip_sd, strict=False)
    assert not unexpected and all(k.endswith("position_ids") for k in missing), (missing,
                                                                                 unexpected)
    tok = Tokenizer.from_str(meta["flame.tokenizer"])
    return (net.eval(), clip.eval(), tok, cfg, tensors.get("motion.mean"),
            tensors.get("motion.std"))


def count_params(cfg):
    """Parameter count of a configuration (no allocation)."""
    c = full_config(cfg)
    d, f, ff, tf = c["d_model"], c["input_feats"], c["ff_size"], c["time_freq_dim"]
    block = (d * 6 * d + 6 * d) + (d * 3 * d + 3 * d) + (d * d + d) + (d * ff + ff) + (ff * d + d)
    n = (f * d + d) + (tf * d + d) + (d * d + d) + c["layers"] * block + (d * 2 * d + 2 * d) \
        + (d * f + f)
    m = c["control"]
    if m is not None:
        dm, dt, k, e, eh, gh = (m["control_dim"], m["text_dim"], m["conv_kernel"], m["experts"],
                                m["expert_hidden"], m["gate_hidden"])
        moc = (dm * dm + dm) + 2 * (dt * dm + dm) + 2 * (dt * dm + dm) \
            + e * (dm * eh + eh + eh * dm + dm) + (dt * gh + gh) + (gh * gh + gh) + (gh * e + e)
        n += c["layers"] * (block + (d * dm * k + dm) + moc + (dm * d * k + d))
    return n


__all__ = ["OMG", "preset", "full_config", "encode_text", "batch_texts", "guided_x0",
           "ddim_sample", "make_diffusion", "zero_up", "with_config", "save_state_dict",
           "load_libflame", "count_params", "timestep_sinusoid", "rope_tables"]
