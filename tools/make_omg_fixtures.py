#!/usr/bin/env python3
"""Generate the OMG-style parity fixtures in tests/fixtures/ (seeded, deterministic, ~20 s).

Steps:
 1. The tiny OMG-style model of docs/omg.md ("Fixtures") from tools/reference/omg.py with every
    weight random and nonzero, rounded to f16 (the files are f16): the up-projections are
    nonzero, the MoC's q/k weights have a larger gain so the attention over the tokens is peaked
    (the masks M then spread over (0, 1) instead of sitting near one value; checked), the
    gates' last layers too (the gates' weights omega are not uniform), and the ControlNet copies
    are their backbone blocks plus an independent perturbation (a copy "initialised from the
    block and trained"). A tiny CLIP text tower (16 wide, 2 layers, 2 heads) with the real CLIP
    tokenizer (tests/fixtures/clip_tokenizer).
 2. The state dict is saved as {'state_dict': ...} and converted with `convert.py omg --dtype
    f16`; the backbone alone (no control.*) is saved as a plain dict and converted to the
    backbone-only file (30 fps). The converter's errors are checked (unknown, missing and
    misshaped tensors, a ControlNet missing a layer, a CLIP of the wrong width, humanml263
    without statistics, a format of the wrong width, a preset that does not match).
 3. The CONVERTED files are loaded back into the reference (the weights must equal the
    in-memory ones); one forward of D_u, D_c, D_c with the experts' outputs blended, and the
    variants (2 MoC heads, rope_dims 8, text padding) is cross-checked against an independent
    float64 numpy implementation written from the contract; the 20-step guided and unguided
    DDIM runs are repeated in float64 for the tolerances; the expected values are written.

Run from anywhere: python tools/make_omg_fixtures.py
"""
import contextlib
import io
import json
import math
import os
import sys
import tempfile

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from scipy.special import erf

TOOLS = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(TOOLS)
FIX = os.path.join(REPO, "tests", "fixtures")
sys.path.insert(0, TOOLS)

from make_fixtures import canonicalize_header  # noqa: E402
from reference import omg  # noqa: E402

TOKENIZER = os.path.join(FIX, "clip_tokenizer", "tokenizer.json")
TINY = dict(input_feats=263, d_model=32, layers=2, heads=2, ff_size=64, time_freq_dim=16,
            rope_base=10000.0, rope_dims=16, norm_eps=1e-6, mlp_activation="gelu_tanh",
            max_frames=300,
            control=dict(control_dim=16, text_dim=16, conv_kernel=3, attn_heads=1, experts=4,
                         expert_hidden=32, expert_activation="gelu", gate_hidden=24,
                         gate_activation="gelu", mask_gamma=24.0, mask_beta=0.25,
                         adain_eps=1e-5, text_padding=False))
CLIP = dict(hidden_size=16, intermediate_size=32, num_hidden_layers=2, num_attention_heads=2,
            projection_dim=16)
BACKBONE_CLIP = dict(hidden_size=8, intermediate_size=16, num_hidden_layers=1,
                     num_attention_heads=2, projection_dim=8)
PROMPTS = {"A": "a person walks forward, then turns around and jumps"}
FRAMES = 48
FORWARD_T = 600
GUIDANCE = 4.5
STEPS = 20
STEPS_KEPT = [1, 5, 10, 20]
LONG_FRAMES = 300
LONG_ROWS = [0, 1, 150, 298, 299]
# Gains of the uniform ±gain/sqrt(fan_in) draws (1 elsewhere): peaked MoC attention, non-uniform
# gates.
GAIN_QK, GAIN_GATE_OUT = 8.0, 4.0
SEEDS = {"net": 60, "copies": 61, "clip": 62, "stats": 63, "forward": 64, "noise": 65}
OWNED = ["omg_tiny.safetensors", "omg_tiny_backbone.safetensors", "omg_expected.safetensors",
         "omg_expected.json"]
VARIANTS = {"cond_heads2": dict(control=dict(attn_heads=2)),
            "uncond_rope8": dict(rope_dims=8),
            "cond_rope8": dict(rope_dims=8),
            "cond_padding": dict(control=dict(text_padding=True))}


def log(msg):
    print(msg, file=sys.stderr)


# -- the tiny model --------------------------------------------------------------------------------

def f16(t):
    t = t.half().float()
    return t.masked_fill(t == 0, 2.0 ** -10)  # an exact zero draw (or f16 underflow)


@torch.no_grad()
def randomize(net, gen):
    """Biases 0.1·N; matrices and convs uniform ±gain/sqrt(fan_in) (the experts' [K, in, out]
    by their own fan-in); all rounded to f16 and nonzero."""
    for name, p in net.named_parameters():
        if name.startswith("control.blocks."):
            continue
        if p.dim() == 1 or name.endswith(("experts.b0", "experts.b1")):
            v = 0.1 * torch.randn(p.shape, generator=gen)
        else:
            fan_in = p.shape[1] if name.endswith(("experts.w0", "experts.w1")) else p[0].numel()
            gain = GAIN_QK if name.endswith((".q.weight", ".k.weight")) and ".moc." in name \
                else GAIN_GATE_OUT if name.endswith("gate.4.weight") else 1.0
            v = gain * (torch.rand(p.shape, generator=gen) * 2 - 1) / math.sqrt(fan_in)
        p.copy_(f16(v))
    copies = torch.Generator().manual_seed(SEEDS["copies"])
    for name, p in net.named_parameters():
        if name.startswith("control.blocks."):
            src = net.get_parameter(name[len("control."):])
            p.copy_(f16(src + 0.3 * src.abs().mean() * torch.randn(p.shape, generator=copies)))
    for name, p in net.named_parameters():
        assert (p != 0).all(), name


def tiny_clip(seed, sizes=None):
    from transformers import CLIPTextConfig, CLIPTextModelWithProjection
    cfg = CLIPTextConfig(vocab_size=49408, max_position_embeddings=77, hidden_act="quick_gelu",
                         layer_norm_eps=1e-5, bos_token_id=omg.SOT, eos_token_id=omg.EOT,
                         pad_token_id=0, attn_implementation="eager", **(sizes or CLIP))
    torch.manual_seed(seed)
    clip = CLIPTextModelWithProjection(cfg).eval()
    # Larger random weights and LayerNorms than HF's init, so the features differ per token.
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in clip.named_parameters():
            if "layer_norm" in name and name.endswith("weight"):
                v = 1 + 0.3 * torch.randn(p.shape, generator=gen)
            else:
                v = 0.5 * torch.randn(p.shape, generator=gen)
            p.copy_(f16(v))
    return clip


def write_clip_dir(folder, clip):
    clip.save_pretrained(folder, safe_serialization=True)
    with open(TOKENIZER) as f:
        tok = json.load(f)
    with open(os.path.join(folder, "tokenizer.json"), "w") as dst:
        json.dump(tok, dst, separators=(",", ":"), ensure_ascii=False)


def run_convert(argv, expect_ok=True):
    """`python tools/convert.py omg ARGV`, run in this process (saves the start-up time)."""
    import convert
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = convert.main(["omg"] + argv)
    log((out.getvalue() + err.getvalue()).strip())
    assert (rc == 0) == expect_ok, (rc, argv)
    return err.getvalue()


def convert_all(tmp, net, clip):
    clip_dir = os.path.join(tmp, "clip")
    write_clip_dir(clip_dir, clip)
    gen = np.random.default_rng(SEEDS["stats"])
    np.save(os.path.join(tmp, "mean.npy"), gen.normal(0, 0.5, 263).astype(np.float32))
    np.save(os.path.join(tmp, "std.npy"), gen.uniform(0.05, 1.0, 263).astype(np.float32))
    stats = ["--mean", os.path.join(tmp, "mean.npy"), "--std", os.path.join(tmp, "std.npy")]
    full = os.path.join(tmp, "model.pt")
    omg.save_state_dict(net, full, wrap=True)
    out = os.path.join(FIX, "omg_tiny.safetensors")
    run_convert(["--ckpt", full, "--clip", clip_dir, "--heads", "2", "--dtype", "f16",
                 "--frames", str(FRAMES), "--out", out] + stats)
    backbone = {k: v for k, v in net.state_dict().items() if not k.startswith("control.")}
    bpath = os.path.join(tmp, "backbone.pt")
    torch.save(backbone, bpath)
    # Its text tower only tokenizes (a prompt is refused): a narrower stand-in keeps it small.
    small = os.path.join(tmp, "clip_small")
    write_clip_dir(small, tiny_clip(SEEDS["clip"] + 1, BACKBONE_CLIP))
    run_convert(["--ckpt", bpath, "--clip", small, "--heads", "2", "--dtype", "f16",
                 "--fps", "30", "--frames", str(LONG_FRAMES),
                 "--out", os.path.join(FIX, "omg_tiny_backbone.safetensors")] + stats)

    # Strictness and option checks: each case must fail with its message.
    sd = net.state_dict()
    x = os.path.join(tmp, "x.safetensors")
    cases = [
        ("unknown", dict(sd, **{"control.moc.0.extra.weight": torch.ones(2)}), [],
         "unknown tensor 'control.moc.0.extra.weight'"),
        ("missing", {k: v for k, v in sd.items() if k != "control.moc.1.gate.2.bias"}, [],
         "missing tensor 'control.moc.1.gate.2.bias'"),
        ("shape", dict(sd, **{"control.moc.1.experts.b1": torch.ones(4, 15)}), [],
         "tensor 'control.moc.1.experts.b1' has shape (4, 15), expected (4, 16)"),
        ("layer", {k: v for k, v in sd.items() if not k.startswith("control.up.1.")}, [],
         "1 'control.up.N' entries, the backbone has 2 blocks"),
        ("even", dict(sd, **{f"control.{w}.{i}.weight": sd[f"control.{w}.{i}.weight"][..., :2]
                             for w in ("down", "up") for i in range(2)}), [],
         "conv kernel 2 is even"),
        ("stats", sd, ["--no-stats"], "--mean and --std are required"),
        ("format", sd, ["--format", "smpl24_6d"], "--format smpl24_6d has 147 features"),
        ("preset", sd, ["--preset", "base"], "is not the base preset"),
        ("heads", sd, ["--heads", "3"], "not divisible by 3 heads"),
        ("rope", sd, ["--rope-dims", "18"], "--rope-dims 18: must be even and at most"),
        ("frames", sd, ["--frames", "301"], "--frames 301: must lie in 1..--max-frames"),
    ]
    for name, state, extra, msg in cases:
        path = os.path.join(tmp, f"bad_{name}.pt")
        torch.save(state, path)
        heads = [] if "--heads" in extra or "--preset" in extra else ["--heads", "2"]
        args = [a for a in extra if a != "--no-stats"]
        err = run_convert(["--ckpt", path, "--clip", clip_dir, "--out", x] + heads + args
                          + ([] if "--no-stats" in extra else stats), expect_ok=False)
        assert msg in err, (name, err)
    # A CLIP of another width than the MoC's text_dim.
    wide = tiny_clip_width(tmp, 24)
    err = run_convert(["--ckpt", full, "--clip", wide, "--heads", "2", "--out", x] + stats,
                      expect_ok=False)
    assert "CLIP width 24 != the MoC's text_dim 16" in err, err
    return out


def tiny_clip_width(tmp, width):
    from transformers import CLIPTextConfig, CLIPTextModelWithProjection
    cfg = CLIPTextConfig(vocab_size=49408, max_position_embeddings=77, hidden_size=width,
                         intermediate_size=2 * width, num_hidden_layers=1, num_attention_heads=2,
                         projection_dim=8)
    folder = os.path.join(tmp, f"clip{width}")
    write_clip_dir(folder, CLIPTextModelWithProjection(cfg))
    return folder


# -- independent float64 numpy implementation (from docs/omg.md, not from the torch code) ----------

def np_ln(x, eps):
    mu = x.mean(-1, keepdims=True)
    return (x - mu) / np.sqrt(((x - mu) ** 2).mean(-1, keepdims=True) + eps)


def np_act(name, x):
    if name == "gelu":
        return 0.5 * x * (1 + erf(x / math.sqrt(2)))
    if name == "gelu_tanh":
        return 0.5 * x * (1 + np.tanh(math.sqrt(2 / math.pi) * (x + 0.044715 * x ** 3)))
    return x / (1 + np.exp(-x))


def np_softmax(s):
    s = np.exp(s - s.max(-1, keepdims=True))
    return s / s.sum(-1, keepdims=True)


def np_silu(x):
    return x / (1 + np.exp(-x))


def np_lin(w, p, x):
    return x @ w[p + ".weight"].T + w[p + ".bias"]


def np_conv(w, p, x):
    """Conv1d along the frames with 'same' zero padding; x [T, Cin] -> [T, Cout]."""
    wt, b = w[p + ".weight"], w[p + ".bias"]
    k = wt.shape[2]
    xp = np.pad(x, ((k // 2, k // 2), (0, 0)))
    t = x.shape[0]
    return b + sum(xp[j:j + t] @ wt[:, :, j].T for j in range(k))


def np_block(w, p, c, h, cemb):
    d, nh, r = c["d_model"], c["heads"], c["rope_dims"]
    hd = d // nh
    mod = np_lin(w, p + "adaLN_modulation.1", np_silu(cemb))
    sh_a, sc_a, g_a, sh_m, sc_m, g_m = (mod[j * d:(j + 1) * d] for j in range(6))
    t = h.shape[0]
    inv = c["rope_base"] ** (-2.0 * np.arange(r // 2) / r)
    ang = np.arange(t)[:, None] * inv[None]

    def rope(z):
        z = z.copy()
        for j in range(r // 2):
            a, b = z[:, j].copy(), z[:, j + r // 2].copy()
            z[:, j] = a * np.cos(ang[:, j]) - b * np.sin(ang[:, j])
            z[:, j + r // 2] = b * np.cos(ang[:, j]) + a * np.sin(ang[:, j])
        return z

    y = np_ln(h, c["norm_eps"]) * (1 + sc_a) + sh_a
    qkv = np_lin(w, p + "attn.qkv", y)
    att = np.zeros((t, d))
    for j in range(nh):
        q = rope(qkv[:, j * hd:(j + 1) * hd])
        k = rope(qkv[:, d + j * hd:d + (j + 1) * hd])
        v = qkv[:, 2 * d + j * hd:2 * d + (j + 1) * hd]
        att[:, j * hd:(j + 1) * hd] = np_softmax(q @ k.T / math.sqrt(hd)) @ v
    h = h + g_a * np_lin(w, p + "attn.proj", att)
    y = np_ln(h, c["norm_eps"]) * (1 + sc_m) + sh_m
    ff = np_lin(w, p + "mlp.fc2", np_act(c["mlp_activation"], np_lin(w, p + "mlp.fc1", y)))
    return h + g_m * ff


def np_moc(w, p, m, f, tokens, eos, blend):
    t, dm = f.shape
    n, nh = tokens.shape[0], m["attn_heads"]
    dh = dm // nh
    q, k, v = np_lin(w, p + "q", f), np_lin(w, p + "k", tokens), np_lin(w, p + "v", tokens)
    a_sum = np.zeros((t, n))
    f1 = f.copy()
    for j in range(nh):
        s = slice(j * dh, (j + 1) * dh)
        a = np_softmax(q[:, s] @ k[:, s].T / math.sqrt(dh))
        f1[:, s] += a @ v[:, s]
        a_sum += a
    a = a_sum / nh
    mu = f1.mean(0)
    var = ((f1 - mu) ** 2).mean(0)
    f2 = np_lin(w, p + "adain.gamma", eos) * (f1 - mu) / np.sqrt(var + m["adain_eps"]) \
        + np_lin(w, p + "adain.beta", eos)
    g = m["gate_activation"]
    om = np_softmax(np_lin(w, p + "gate.4", np_act(g, np_lin(w, p + "gate.2", np_act(
        g, np_lin(w, p + "gate.0", tokens))))))
    w0, b0, w1, b1 = (w[p + "experts." + s] for s in ("w0", "b0", "w1", "b1"))
    act = m["expert_activation"]
    out = np.zeros((t, dm))
    for i in range(n):
        if blend == "params":
            W0, B0 = np.tensordot(om[i], w0, 1), om[i] @ b0
            W1, B1 = np.tensordot(om[i], w1, 1), om[i] @ b1
            y = np_act(act, f2 @ W0 + B0) @ W1 + B1
        else:
            y = sum(om[i, j] * (np_act(act, f2 @ w0[j] + b0[j]) @ w1[j] + b1[j])
                    for j in range(len(om[i])))
        mask = 1 / (1 + np.exp(-m["mask_gamma"] * (a[:, i] - m["mask_beta"] * a[:, i].max())))
        out += mask[:, None] * y
    return out


def np_forward(w, c, x, t, text=None, blend="params"):
    """x [T, F], original step t, text (tokens [n, D], eos [D]) or None -> x-hat-0 [T, F]."""
    half = c["time_freq_dim"] // 2
    arg = t * np.exp(-math.log(10000) * np.arange(half) / half)
    cemb = np_lin(w, "t_embed.mlp.2", np_silu(np_lin(w, "t_embed.mlp.0",
                                                     np.concatenate([np.cos(arg), np.sin(arg)]))))
    h = np_lin(w, "x_embed", x)
    for i in range(c["layers"]):
        out = np_block(w, f"blocks.{i}.", c, h, cemb)
        if text is not None:
            g = np_block(w, f"control.blocks.{i}.", c, h, cemb)
            r = np_moc(w, f"control.moc.{i}.", c["control"], np_conv(w, f"control.down.{i}", g),
                       *text, blend)
            out = out + np_conv(w, f"control.up.{i}", r)
        h = out
    mod = np_lin(w, "final_layer.adaLN_modulation.1", np_silu(cemb))
    d = c["d_model"]
    return np_lin(w, "final_layer.linear", np_ln(h, c["norm_eps"]) * (1 + mod[d:]) + mod[:d])


def check(name, got, want, tol):
    got = np.asarray(got, dtype=np.float64)
    err = float(np.abs(got - want).max())
    scale = float(np.abs(want).max())
    log(f"float32 torch vs float64 numpy {name}: max err {err:.2e} (max |x| {scale:.3g})")
    assert err <= tol * max(1.0, scale), (name, err)
    return err


# -- expected values -------------------------------------------------------------------------------

def long_input():
    """The 300-frame input of the backbone check: x[t, j] = sin(0.05 t + 0.3 j) (float64 ->
    float32), so the runtime test can rebuild it."""
    t, j = np.meshgrid(np.arange(LONG_FRAMES), np.arange(263), indexing="ij")
    return torch.from_numpy(np.sin(0.05 * t + 0.3 * j).astype(np.float32))


@torch.no_grad()
def expected(net_mem, clip_mem):
    net, clip, tok, cfg, mean, std = omg.load_libflame(os.path.join(FIX, "omg_tiny.safetensors"))
    assert cfg["denoiser"] == TINY, cfg["denoiser"]
    assert cfg["motion"] == {"format": "humanml263", "fps": 20.0}
    assert cfg["defaults"] == {"sampler": "ddim", "steps": 200, "guidance": 4.5, "eta": 0.0,
                               "frames": FRAMES}
    for k, v in net_mem.state_dict().items():
        assert torch.equal(net.state_dict()[k], v), k
    for k, v in clip_mem.state_dict().items():
        assert torch.equal(clip.state_dict()[k], v), k
    assert mean is not None and std is not None

    te = omg.encode_text(clip, tok, PROMPTS["A"])
    te_pad = omg.encode_text(clip, tok, PROMPTS["A"], text_padding=True)
    assert te["ids"][0] == omg.SOT and te["ids"][-1] == omg.EOT and len(te_pad["ids"]) == 77
    assert torch.equal(te_pad["tokens"][:len(te["ids"])], te["tokens"])
    text = omg.batch_texts([te])
    text_pad = omg.batch_texts([te_pad])
    gen = torch.Generator().manual_seed(SEEDS["forward"])
    x = torch.randn(1, FRAMES, 263, generator=gen)
    w = {k: v.double().numpy() for k, v in net.state_dict().items()}
    npx = x[0].double().numpy()
    np_text = (te["tokens"].double().numpy(), te["eos"].double().numpy())
    o = {"text.tokens": te["tokens"], "text.ids": torch.tensor(te["ids"], dtype=torch.int64),
         "forward.x": x[0]}
    errs = {}
    o["forward.uncond"] = net(x, FORWARD_T)[0]
    errs["uncond"] = check("D_u", o["forward.uncond"], np_forward(w, TINY, npx, FORWARD_T), 2e-5)
    o["forward.cond"] = net(x, FORWARD_T, text)[0]
    mocs = {k: torch.stack([m.last[k][0] for m in net.mocs()]) for k in ("A", "M", "omega")}
    errs["cond"] = check("D_c", o["forward.cond"],
                         np_forward(w, TINY, npx, FORWARD_T, np_text), 2e-5)
    o["forward.blend_outputs"] = net(x, FORWARD_T, text, blend="outputs")[0]
    errs["blend_outputs"] = check("D_c, outputs blended", o["forward.blend_outputs"],
                                  np_forward(w, TINY, npx, FORWARD_T, np_text, "outputs"), 2e-5)
    zu = omg.zero_up(net)
    o["forward.zero_up"] = zu(x, FORWARD_T, text)[0]
    assert torch.equal(o["forward.zero_up"], o["forward.uncond"]), "zero up-projection != D_u"
    for name, change in VARIANTS.items():
        v = omg.with_config(net, **json.loads(json.dumps(change)))
        vt = text_pad if name == "cond_padding" else text
        o[f"forward.{name}"] = v(x, FORWARD_T, None if name.startswith("uncond") else vt)[0]
        vc = json.loads(json.dumps(TINY))
        for key, val in change.items():
            if key == "control":
                vc["control"].update(val)
            else:
                vc[key] = val
        vtext = None if name.startswith("uncond") else (
            (te_pad["tokens"].double().numpy(), te_pad["eos"].double().numpy())
            if name == "cond_padding" else np_text)
        errs[name] = check(name, o[f"forward.{name}"], np_forward(w, vc, npx, FORWARD_T, vtext),
                           2e-5)
        base = o["forward.uncond" if name.startswith("uncond") else "forward.cond"]
        assert (o[f"forward.{name}"] - base).abs().max() > 1e-2, name
    o["moc.attn"], o["moc.mask"], o["moc.omega"] = mocs["A"], mocs["M"], mocs["omega"]

    # The masks: neither all 0 nor all 1.
    mask = mocs["M"]
    spread = {}
    for i in range(mask.shape[0]):
        m = mask[i]
        inside = ((m > 0.05) & (m < 0.95))
        full = ((m.min(0).values < 0.05) & (m.max(0).values > 0.95))
        spread[f"layer{i}"] = {"fraction_in_(0.05,0.95)": round(float(inside.float().mean()), 4),
                               "min": float(m.min()), "max": float(m.max()),
                               "tokens_spanning_(0.05,0.95)": int(full.sum()),
                               "tokens_with_values_inside": int(inside.any(0).sum())}
        assert 0.2 < float(inside.float().mean()) < 0.95 and int(full.sum()) >= 1, spread
    om = mocs["omega"]
    spread["omega"] = {"min": float(om.min()), "max": float(om.max())}
    diff_blend = float((o["forward.blend_outputs"] - o["forward.cond"]).abs().max())
    diff_cu = float((o["forward.cond"] - o["forward.uncond"]).abs().max())
    log(f"masks: {spread}")
    log(f"max |D_c - D_u| {diff_cu:.4f}; max |params blend - outputs blend| {diff_blend:.4f}")
    assert diff_blend > 0.05 and diff_cu > 0.1

    gen = torch.Generator().manual_seed(SEEDS["noise"])
    noise = torch.randn(1, FRAMES, 263, generator=gen)
    o["guided.noise"] = noise[0]
    runs = {"guided": omg.ddim_sample(net, noise, text, GUIDANCE, STEPS),
            "uncond": omg.ddim_sample(net, noise, None, GUIDANCE, STEPS)}
    net64 = omg.with_config(net).double()
    text64 = {k: v.double() for k, v in text.items()}
    runs64 = {"guided": omg.ddim_sample(net64, noise.double(), text64, GUIDANCE, STEPS),
              "uncond": omg.ddim_sample(net64, noise.double(), None, GUIDANCE, STEPS)}
    steps_t = [s["t"] for s in runs["guided"]]
    tol = {}
    for name in ("guided", "uncond"):
        keep = [runs[name][k - 1] for k in STEPS_KEPT]
        o[f"{name}.x"] = torch.stack([s["x"][0] for s in keep])
        if name == "guided":
            o["guided.x0"] = torch.stack([s["x0"][0] for s in keep])
        for key in ("x", "x0"):
            e = max(float((a[key] - b[key]).abs().max()) for a, b in zip(runs[name], runs64[name]))
            tol[f"{name}.{key}"] = e
        log(f"{name}: float32 vs float64 over {STEPS} steps: x {tol[name + '.x']:.2e}, x0 "
            f"{tol[name + '.x0']:.2e}; final max |x| {runs[name][-1]['x'].abs().max():.3g}")
    tol["forward_vs_numpy_f64"] = errs

    # The backbone-only file: same D_u; 300 frames at 30 fps.
    bnet, _, _, bcfg, _, _ = omg.load_libflame(os.path.join(FIX, "omg_tiny_backbone.safetensors"))
    assert bcfg["denoiser"]["control"] is None and bcfg["motion"]["fps"] == 30.0
    assert bnet.backbone_only and torch.equal(bnet(x, FORWARD_T)[0], o["forward.uncond"])
    try:
        bnet(x, FORWARD_T, text)
        raise AssertionError("a backbone-only model accepted a text")
    except ValueError:
        pass
    xl = long_input()
    long = bnet(xl[None], FORWARD_T)[0]
    bw = {k: v.double().numpy() for k, v in bnet.state_dict().items()}
    errs["long300"] = check("D_u over 300 frames", long,
                            np_forward(bw, dict(TINY, control=None), xl.double().numpy(),
                                       FORWARD_T), 2e-5)
    o["long.x_head"] = xl[:2]
    o["long.uncond_rows"] = long[LONG_ROWS]

    info = {
        "description": "OMG-style tiny parity fixture; generated by tools/make_omg_fixtures.py "
                       "from tools/reference/omg.py (the definition of the model, docs/omg.md). "
                       "Frame-major [frames, 263]; features in the model's normalised space.",
        "model": "omg_tiny.safetensors", "backbone_model": "omg_tiny_backbone.safetensors",
        "prompts": PROMPTS, "ids": {"A": te["ids"]}, "frames": FRAMES,
        "text": "text.tokens = CLIP final-LN features of SOT..EOT of prompt A (the MoC's "
                "tokens; e = the last row); text.ids its ids (clip.tokenize, truncate)",
        "forward": {"t": FORWARD_T, "x": "forward.x",
                    "uncond": "D_u(x, t) (backbone alone)",
                    "cond": "D_c(x, t, prompt A), experts' PARAMETERS blended",
                    "blend_outputs": "D_c with the experts' OUTPUTS blended (contrast case)",
                    "zero_up": "D_c with every control.up.* weight and bias zero (== uncond, "
                               "bit for bit)",
                    "variants": {k: v for k, v in VARIANTS.items()},
                    "variant_note": "same weights, configuration changed as given: "
                                    "cond_heads2 = D_c with control.attn_heads 2; "
                                    "uncond_rope8 / cond_rope8 = rope_dims 8 (half of each head "
                                    "rotated); cond_padding = text_padding true (all 77 CLIP "
                                    "positions, e still the EOT feature)"},
        "moc": "moc.attn [layers, T, n] = A (softmax over tokens), moc.mask [layers, T, n] = M, "
               "moc.omega [layers, n, K]: of the forward.cond call",
        "mask_spread": spread,
        "max_abs_cond_minus_uncond": diff_cu, "max_abs_params_minus_outputs_blend": diff_blend,
        "guidance": GUIDANCE, "sampler": "DDIM eta 0, cosine schedule (1000), x0 prediction, "
                                         "space_timesteps(1000, [20]), no clamp; "
                                         "x0 = D_u + s (D_c - D_u); uncond run: x0 = D_u",
        "steps": steps_t, "steps_kept": STEPS_KEPT,
        "trajectories": "guided.x[k] / guided.x0[k]: the sample after / the guided x0 of loop "
                        "step steps_kept[k] (1-based; step j runs at original t = steps[j-1]), "
                        "start guided.noise; uncond.x[k]: the same run with no prompt",
        "long": {"frames": LONG_FRAMES, "rows": LONG_ROWS, "t": FORWARD_T,
                 "x": "x[t, j] = float32(sin(0.05 t + 0.3 j)) computed in float64; long.x_head "
                      "= its first 2 rows",
                 "uncond_rows": "D_u of the backbone-only file (30 fps) at these rows"},
        "tolerance_f64": tol,
        "tolerance_note": "max abs differences of the float32 reference from the float64 one "
                          "(trajectories: over all 20 steps) and from the independent float64 "
                          "numpy forward",
        "seeds": SEEDS, "gains": {"moc_qk": GAIN_QK, "gate_out": GAIN_GATE_OUT},
        "config": cfg,
    }
    return o, info


def save(tensors, info, stem):
    out = {}
    for k, v in tensors.items():
        v = v.contiguous() if v.dtype == torch.int64 else v.float().contiguous()
        assert v.dtype == torch.int64 or torch.isfinite(v).all(), k
        log(f"  {k:24s} {str(list(v.shape)):16s}")
        out[k] = v
    save_file(out, os.path.join(FIX, stem + ".safetensors"),
              metadata={"generator": "tools/make_omg_fixtures.py"})
    info["tensors"] = {k: list(v.shape) for k, v in out.items()}
    with open(os.path.join(FIX, stem + ".json"), "w") as f:
        json.dump(info, f, indent=1)
        f.write("\n")


def main():
    torch.set_num_threads(1)
    torch.manual_seed(SEEDS["net"])
    net = omg.OMG(TINY).eval()
    randomize(net, torch.Generator().manual_seed(SEEDS["net"]))
    clip = tiny_clip(SEEDS["clip"])
    with tempfile.TemporaryDirectory() as tmp:
        convert_all(tmp, net, clip)
    for name in OWNED[:2]:
        canonicalize_header(os.path.join(FIX, name))  # byte-identical regeneration
    o, info = expected(net, clip)
    save(o, info, "omg_expected")
    sizes = {n: os.path.getsize(os.path.join(FIX, n)) for n in OWNED}
    log(f"sizes: {sizes}")
    assert sizes["omg_expected.safetensors"] < 1.5e6
    assert sizes["omg_tiny.safetensors"] < 4e6 and sizes["omg_tiny_backbone.safetensors"] < 4e6
    # The written expected file round-trips.
    back = load_file(os.path.join(FIX, "omg_expected.safetensors"))
    assert set(back) == set(o)
    return 0


if __name__ == "__main__":
    sys.exit(main())
