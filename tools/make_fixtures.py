#!/usr/bin/env python3
"""Generate the FLAME parity fixtures in tests/fixtures/ (deterministic, seeded).

Steps:
 1. Build a tiny random FLAME (tools/make_random_checkpoint.py preset "tiny": C=64, 2 decoder
    layers, 4 heads, ff 128, motion 147, 471 lengths, max_text_length 20) on the tiny RoBERTa of
    tests/fixtures/tiny_roberta, and save it as an official-layout Lightning checkpoint in a temp dir
    (net.* = ema + noise, ema_model.model.* = ema, lm.embeddings.position_ids present).
 2. Convert it with tools/convert.py (--heads 4) to flame_tiny.safetensors (f32) and
    flame_tiny_f16.safetensors, and exercise the converter's fallbacks and errors.
 3. Load the converted file back into the reference (tools/reference/flame.py), cross-check the
    reference forward against an independent float64 numpy implementation, and write the expected
    outputs (frame-major `[frames, 147]` layout) to flame_tiny_expected.safetensors + .json, plus
    tokenizer cases to tiny_roberta_tokens.json.

Run from anywhere: python tools/make_fixtures.py
"""
import json
import math
import os
import struct
import subprocess
import sys
import tempfile
import types

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import save_file
from scipy.special import erf

TOOLS = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(TOOLS)
FIX = os.path.join(REPO, "tests", "fixtures")
TOK_DIR = os.path.join(FIX, "tiny_roberta")
sys.path.insert(0, TOOLS)

from make_random_checkpoint import build_model, lightning_checkpoint  # noqa: E402
from reference.diffusion import (ClassifierFreeGuidance, SpacedDiffusion,  # noqa: E402
                                 cosine_betas, GaussianDiffusion, space_timesteps)
from reference.flame import load_libflame  # noqa: E402

PROMPT = "a person walks forward and waves."
FRAMES = 24
GUIDANCE = 8.0
RESPACING = [10]
FORWARD_T = 500
SEEDS = {"weights": 0, "forward_x": 1234, "ddim": 2024, "ddpm": 7}
OWNED_FILES = ["flame_tiny.safetensors", "flame_tiny_f16.safetensors",
               "flame_tiny_expected.safetensors", "flame_tiny_expected.json",
               "tiny_roberta_tokens.json"]
TOKENIZER_CASES = [
    "", PROMPT, "A person walks forward and waves.", "a person walks forward  and waves.",
    "someone doesn't stop, they're jumping 3 times!!",
    "a man is walking in a straight line and then turns 90 degrees to the right before stopping "
    "and waving with both hands",
    "zebra quux \u00e9t\u00e9 \u2014 ok", "  leading spaces", "trailing space ",
    "a person walks <mask> and waves.",
]


def dumps_compact(obj, indent=""):
    """JSON with one key per line but lists of scalars kept on one line."""
    if isinstance(obj, dict):
        inner = indent + " "
        items = [f"{inner}{json.dumps(k)}: {dumps_compact(v, inner)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    if isinstance(obj, list) and any(isinstance(v, (dict, list)) for v in obj):
        inner = indent + " "
        return "[\n" + ",\n".join(inner + dumps_compact(v, inner) for v in obj) + "\n" + indent + "]"
    return json.dumps(obj, ensure_ascii=False)


def log(msg):
    print(msg, flush=True)


def run_convert(args, expect_rc=0):
    cmd = [sys.executable, os.path.join(TOOLS, "convert.py"), "flame"] + args
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != expect_rc:
        raise SystemExit(f"convert.py {args} exited {res.returncode} (want {expect_rc}):\n"
                         f"{res.stdout}\n{res.stderr}")
    return res


def read_file(path):
    with safe_open(path, framework="pt") as f:
        return f.metadata(), {k: f.get_tensor(k) for k in f.keys()}


def canonicalize_header(path):
    """safetensors writes `__metadata__` in hash-map order; sort it so that regenerating the
    fixtures gives byte-identical files. Header length is kept (padding with spaces is allowed)."""
    with open(path, "r+b") as f:
        n = struct.unpack("<Q", f.read(8))[0]
        header = json.loads(f.read(n))
        meta = header.pop("__metadata__", None)
        if meta is not None:
            header = {"__metadata__": dict(sorted(meta.items())), **header}
        text = json.dumps(header, separators=(",", ":"), ensure_ascii=False).encode()
        if len(text) > n:
            raise SystemExit(f"{path}: canonical header longer than the original")
        f.seek(8)
        f.write(text + b" " * (n - len(text)))


def expected_names(state):
    """libflame names for a net state dict (lm.* -> text.*, position_ids dropped)."""
    out = {}
    for k, v in state.items():
        if k.endswith("position_ids"):
            continue
        out[("text." + k[3:]) if k.startswith("lm.") else k] = v
    return out


# -- step 2: converter checks ---------------------------------------------------------------------

def check_converter(tmp, ckpt, ema_state, net_state):
    ckpt_path = os.path.join(tmp, "flame_tiny.ckpt")
    torch.save(ckpt, ckpt_path)
    out32 = os.path.join(FIX, "flame_tiny.safetensors")
    out16 = os.path.join(FIX, "flame_tiny_f16.safetensors")
    common = ["--text-model", TOK_DIR, "--heads", "4", "--max-text-length", "20"]
    log(run_convert(["--ckpt", ckpt_path, "--out", out32] + common).stdout.strip())
    log(run_convert(["--ckpt", ckpt_path, "--out", out16, "--dtype", "f16"] + common)
        .stdout.strip())
    canonicalize_header(out32)
    canonicalize_header(out16)

    meta, tensors = read_file(out32)
    want = expected_names(ema_state)
    assert set(tensors) == set(want), set(tensors) ^ set(want)
    for k, v in want.items():
        assert tensors[k].dtype == torch.float32 and torch.equal(tensors[k], v), k
    raw = expected_names(net_state)
    differing = sum(not torch.equal(tensors[k], raw[k]) for k in want)
    assert differing == len(want), "net.* and ema_model.model.* must differ everywhere"
    with open(os.path.join(TOK_DIR, "tokenizer.json")) as f:
        assert meta["flame.tokenizer"] == f.read()
    assert meta["format"] == "libflame"
    _, t16 = read_file(out16)
    for k, v in want.items():
        assert t16[k].dtype == torch.float16 and torch.equal(t16[k], v.half()), k
    log(f"converter: {len(want)} tensors equal the EMA weights (f32 exact, f16 = ema.half())")

    # Raw-net fallback: warning, and the raw weights are taken.
    sd = {k: v for k, v in ckpt["state_dict"].items() if k.startswith("net.")}
    p = os.path.join(tmp, "raw_only.ckpt")
    torch.save({"state_dict": sd}, p)
    res = run_convert(["--ckpt", p, "--out", os.path.join(tmp, "raw.safetensors")] + common)
    assert "falling back" in res.stderr, res.stderr
    _, t = read_file(os.path.join(tmp, "raw.safetensors"))
    assert all(torch.equal(t[k], raw[k]) for k in raw)

    # LM from DIR/model.safetensors (hub layout: roberta. prefix, lm_head, no EMA lm.* in ckpt).
    sd = {k: v for k, v in ckpt["state_dict"].items() if not k.startswith(("net.lm.",
                                                                              "ema_model.model.lm."))}
    p = os.path.join(tmp, "no_lm.ckpt")
    torch.save({"state_dict": sd}, p)
    text_dir = os.path.join(tmp, "text_with_weights")
    os.makedirs(text_dir)
    for name in ("config.json", "tokenizer.json"):
        with open(os.path.join(TOK_DIR, name)) as src, open(os.path.join(text_dir, name), "w") as d:
            d.write(src.read())
    hub = {"roberta." + k[3:]: v.clone() for k, v in ema_state.items() if k.startswith("lm.")}
    hub["roberta.embeddings.position_ids"] = torch.arange(64)[None]
    hub["lm_head.bias"] = torch.zeros(4)
    save_file(hub, os.path.join(text_dir, "model.safetensors"))
    res = run_convert(["--ckpt", p, "--out", os.path.join(tmp, "hub.safetensors"),
                       "--text-model", text_dir, "--heads", "4"])
    assert "model.safetensors" in res.stderr
    _, t = read_file(os.path.join(tmp, "hub.safetensors"))
    assert set(t) == set(want) and all(torch.equal(t[k], want[k]) for k in want)

    # Official files pickle FLAME's own classes in hyper_parameters; the converter must cope
    # without FLAME's source (the class below does not exist in the converter's process).
    fake_names = ["src", "src.models", "src.models.components",
                  "src.models.components.text2motion_model"]
    assert not any(n in sys.modules for n in fake_names)
    for n in fake_names:
        sys.modules[n] = types.ModuleType(n)
    fake = sys.modules[fake_names[-1]]
    fake.Text2MotionTransformer = type("Text2MotionTransformer", (torch.nn.Module,),
                                       {"__module__": fake.__name__})
    try:
        p = os.path.join(tmp, "pickled_net.ckpt")
        obj = fake.Text2MotionTransformer()
        obj.max_text_length = 20
        torch.save(dict(ckpt, hyper_parameters={"net": obj}), p)
    finally:
        for n in fake_names:
            del sys.modules[n]
    res = run_convert(["--ckpt", p, "--out", os.path.join(tmp, "pickled.safetensors")] + common)
    assert "stubbed" in res.stderr, res.stderr
    _, t = read_file(os.path.join(tmp, "pickled.safetensors"))
    assert set(t) == set(want) and all(torch.equal(t[k], want[k]) for k in want)

    # Clear errors: a missing tensor, a wrong shape, indivisible heads, no net at all.
    sd = dict(ckpt["state_dict"])
    del sd["ema_model.model.tf_decoder.layers.1.norm2.bias"]
    p = os.path.join(tmp, "missing.ckpt")
    torch.save({"state_dict": sd}, p)
    res = run_convert(["--ckpt", p, "--out", os.path.join(tmp, "x.safetensors")] + common, 2)
    assert "tf_decoder.layers.1.norm2.bias" in res.stderr, res.stderr
    sd = dict(ckpt["state_dict"])
    sd["ema_model.model.text_h_proj.weight"] = torch.zeros(64, 47)
    torch.save({"state_dict": sd}, p)
    res = run_convert(["--ckpt", p, "--out", os.path.join(tmp, "x.safetensors")] + common, 2)
    assert "text_h_proj.weight" in res.stderr, res.stderr
    res = run_convert(["--ckpt", ckpt_path, "--out", os.path.join(tmp, "x.safetensors"),
                       "--text-model", TOK_DIR, "--heads", "5"], 2)
    assert "--heads" in res.stderr
    torch.save({"state_dict": {"model.foo": torch.zeros(1)}}, p)
    res = run_convert(["--ckpt", p, "--out", os.path.join(tmp, "x.safetensors")] + common, 2)
    assert "ema_model.model." in res.stderr
    log("converter: fallbacks (raw net, LM from model.safetensors, unimportable pickled classes) "
        "and errors behave")
    return json.loads(meta["flame.config"])


# -- step 3a: independent numpy forward (float64) -------------------------------------------------

def np_layer_norm(x, g, b, eps):
    mu = x.mean(-1, keepdims=True)
    var = ((x - mu) ** 2).mean(-1, keepdims=True)
    return (x - mu) / np.sqrt(var + eps) * g + b


def np_attention(q, k, v, heads, key_bias=None):
    """q [Lq,E], k/v [Lk,E]; per-head softmax(q k^T / sqrt(d) + key_bias) v, heads concatenated."""
    d = q.shape[1] // heads
    out = []
    for h in range(heads):
        s = slice(h * d, (h + 1) * d)
        scores = q[:, s] @ k[:, s].T / math.sqrt(d)
        if key_bias is not None:
            scores = scores + key_bias[None, :]
        scores = scores - scores.max(-1, keepdims=True)
        w = np.exp(scores)
        w /= w.sum(-1, keepdims=True)
        out.append(w @ v[:, s])
    return np.concatenate(out, axis=1)


def np_roberta(w, cfg, ids, mask):
    """RoBERTa (docs/official/text-encoders.md#roberta-base) for one sequence; w = libflame tensors as float64
    numpy."""
    g = lambda n: w["text." + n]  # noqa: E731
    eps = cfg["layer_norm_eps"]
    pad = cfg["pad_token_id"]
    m = (ids != pad).astype(np.int64)
    pos = np.cumsum(m) * m + pad
    x = (g("embeddings.word_embeddings.weight")[ids] + g("embeddings.position_embeddings.weight")[pos]
         + g("embeddings.token_type_embeddings.weight")[0])
    x = np_layer_norm(x, g("embeddings.LayerNorm.weight"), g("embeddings.LayerNorm.bias"), eps)
    key_bias = np.where(mask > 0, 0.0, -1e30)
    lin = lambda a, n: a @ g(n + ".weight").T + g(n + ".bias")  # noqa: E731
    for i in range(cfg["num_layers"]):
        p = f"encoder.layer.{i}."
        ctx = np_attention(lin(x, p + "attention.self.query"), lin(x, p + "attention.self.key"),
                           lin(x, p + "attention.self.value"), cfg["num_heads"], key_bias)
        a = np_layer_norm(lin(ctx, p + "attention.output.dense") + x,
                          g(p + "attention.output.LayerNorm.weight"),
                          g(p + "attention.output.LayerNorm.bias"), eps)
        hmid = lin(a, p + "intermediate.dense")
        hmid = 0.5 * hmid * (1 + erf(hmid / math.sqrt(2)))
        x = np_layer_norm(lin(hmid, p + "output.dense") + a, g(p + "output.LayerNorm.weight"),
                          g(p + "output.LayerNorm.bias"), eps)
    pooled = np.tanh(lin(x[0], "pooler.dense"))
    return pooled, x


def np_sinusoid(s, dim):
    half = dim // 2
    freqs = np.exp(-math.log(10000.0) * np.arange(half) / half)
    args = np.asarray(s, dtype=np.float64)[:, None] * freqs[None]
    return np.concatenate([np.cos(args), np.sin(args)], axis=1)


def np_flame(w, cfg, x, t, motion_length, pooled, hidden):
    """FLAME's denoiser (docs/official/flame.md#denoiser-forward-pass) for one sample: x [147, L] ->
    [294, L]."""
    d = cfg["denoiser"]
    c, heads, eps = d["model_channels"], d["num_heads"], d["layer_norm_eps"]
    lin = lambda a, n: a @ w[n + ".weight"].T + w[n + ".bias"]  # noqa: E731
    frames = x.shape[1]
    ml = w["motion_length_emb.weight"][motion_length]
    ts = np_sinusoid([t], c)[0]
    pool = lin(pooled, "text_pooler_proj")
    memory = np.concatenate([ml[None], ts[None], pool[None], lin(hidden, "text_h_proj")])
    h = np.concatenate([ml[None], ts[None], pool[None], lin(x.T, "input_projection")])
    h = h + np_sinusoid(np.arange(frames + 3), c)
    for i in range(d["num_layers"]):
        p = f"tf_decoder.layers.{i}."

        def mha(q_in, kv_in, name):
            wi, bi = w[p + name + ".in_proj_weight"], w[p + name + ".in_proj_bias"]
            q = q_in @ wi[:c].T + bi[:c]
            k = kv_in @ wi[c:2 * c].T + bi[c:2 * c]
            v = kv_in @ wi[2 * c:].T + bi[2 * c:]
            return lin(np_attention(q, k, v, heads), p + name + ".out_proj")

        h = np_layer_norm(h + mha(h, h, "self_attn"), w[p + "norm1.weight"], w[p + "norm1.bias"], eps)
        h = np_layer_norm(h + mha(h, memory, "multihead_attn"), w[p + "norm2.weight"],
                          w[p + "norm2.bias"], eps)
        ff = lin(np.maximum(lin(h, p + "linear1"), 0), p + "linear2")
        h = np_layer_norm(h + ff, w[p + "norm3.weight"], w[p + "norm3.bias"], eps)
    return lin(h[3:], "last_projection").T


def check_against_numpy(model, path, config, texts, x, t, frames):
    _, tensors = read_file(path)
    w = {k: v.double().numpy() for k, v in tensors.items()}
    ids, mask = model.tokenize(texts)
    with torch.no_grad():
        pooled, hidden = model.encode_text(texts)
        out = model(x, t, torch.full((x.shape[0],), frames), texts)
    worst = 0.0
    for b in range(len(texts)):
        p_np, h_np = np_roberta(w, config["text_encoder"], ids[b].numpy(), mask[b].numpy())
        o_np = np_flame(w, config, x[b].double().numpy(), int(t[b]), frames, p_np, h_np)
        for a, ref in ((pooled[b], p_np), (hidden[b], h_np), (out[b], o_np)):
            err = np.abs(a.double().numpy() - ref).max() / max(1.0, np.abs(ref).max())
            worst = max(worst, err)
    assert worst < 2e-5, f"torch reference vs numpy: max scaled error {worst:.3g}"
    log(f"reference forward == independent float64 numpy forward (max scaled error {worst:.2g})")


# -- step 3b: expected outputs --------------------------------------------------------------------

def frame_major(x):
    """Official channel-first [C, L] -> our [L, C]."""
    return x.transpose(-1, -2).contiguous()


def run_reference(model, seeds):
    """All expected outputs (official layouts) from one model; deterministic."""
    texts = [PROMPT, ""]
    res = {}
    with torch.no_grad():
        pooled, hidden = model.encode_text(texts)
        res["text"] = (pooled, hidden)
        gen = torch.Generator().manual_seed(seeds["forward_x"])
        x = torch.randn(1, 147, FRAMES, generator=gen)
        xb = torch.cat([x, x])
        tb = torch.full((2,), FORWARD_T, dtype=torch.long)
        out = model(xb, tb, torch.full((2,), FRAMES), mask=torch.ones(2, FRAMES, dtype=torch.bool),
                    text_features=(pooled, hidden))
        res["forward_x"] = x[0]
        res["forward_out"] = out
        res["eps_guided"] = out[1, :147] + GUIDANCE * (out[0, :147] - out[1, :147])

        diffusion = SpacedDiffusion(cosine_betas(1000), space_timesteps(1000, RESPACING))
        res["timestep_map"] = diffusion.timestep_map
        cfg = ClassifierFreeGuidance(model, [PROMPT], FRAMES, GUIDANCE,
                                     text_features=(pooled, hidden))
        # The wrapper must reproduce the hand-guided eps (second half of x is ignored).
        wrapped = cfg(torch.cat([x, torch.randn(1, 147, FRAMES, generator=gen)]), tb)
        assert torch.equal(wrapped[0, :147], res["eps_guided"])
        assert torch.equal(wrapped[1, :147], res["eps_guided"])
        assert torch.equal(wrapped[0, 147:], out[0, 147:])

        gen = torch.Generator().manual_seed(seeds["ddim"])
        x_T = torch.randn(2, 147, FRAMES, generator=gen)
        _, trace = diffusion.sample_loop(cfg, x_T, "ddim", eta=0.0)
        res["ddim"] = (x_T[0], trace)

        gen = torch.Generator().manual_seed(seeds["ddpm"])
        x_T = torch.randn(2, 147, FRAMES, generator=gen)
        noises = torch.randn(diffusion.num_timesteps, 2, 147, FRAMES, generator=gen)
        _, trace = diffusion.sample_loop(cfg, x_T, "ddpm", noise_fn=lambda k, shape: noises[k])
        res["ddpm"] = (x_T[0], trace)
    return res


def to_fixture_tensors(res):
    pooled, hidden = res["text"]
    out = {
        "text_cond_hidden": hidden[0], "text_cond_pooled": pooled[0],
        "text_uncond_hidden": hidden[1], "text_uncond_pooled": pooled[1],
        "forward_x": frame_major(res["forward_x"]),
        "forward_t": torch.tensor(float(FORWARD_T)),
        "forward_out_cond": frame_major(res["forward_out"][0]),
        "forward_out_uncond": frame_major(res["forward_out"][1]),
        "forward_eps_guided": frame_major(res["eps_guided"]),
        "timestep_map": torch.tensor(res["timestep_map"], dtype=torch.float32),
    }
    for name in ("ddim", "ddpm"):
        x_T, trace = res[name]
        out[f"{name}_x_T"] = frame_major(x_T)
        out[f"{name}_xs"] = torch.stack([frame_major(s["x"][0]) for s in trace])
        out[f"{name}_x0s"] = torch.stack([frame_major(s["pred_xstart"][0]) for s in trace])
        if name == "ddpm":
            out["ddpm_noise"] = torch.stack([frame_major(s["noise"][0]) for s in trace])
    return {k: v.float().contiguous() for k, v in out.items()}


def sanity(tensors):
    for k, v in tensors.items():
        assert torch.isfinite(v).all(), f"{k} has NaN/Inf"
    for name in ("ddim", "ddpm"):
        x0s = tensors[f"{name}_x0s"]
        assert x0s.abs().max() <= 1.0, f"{name} x0 not clamped"
        # t = 0: c1 = 1, c2 = 0 and no noise -> the final sample is the clamped x0.
        assert torch.allclose(tensors[f"{name}_xs"][-1], x0s[-1], atol=1e-6), name
    eps = tensors["forward_out_cond"][:, :147]
    assert 0.1 <= eps.std() <= 1.0, f"eps std {eps.std():.3f} outside [0.1, 1]"
    lines = []
    for k, v in tensors.items():
        lines.append(f"  {k:22s} {str(list(v.shape)):16s} mean {v.mean():+.4f} std "
                     f"{v.std() if v.numel() > 1 else 0:.4f} max|x| {v.abs().max():.4f}")
    for name in ("ddim", "ddpm"):
        frac = (tensors[f"{name}_x0s"].abs() >= 1.0).float().mean(dim=(1, 2))
        lines.append(f"  {name} fraction of x0 clamped per step: "
                     + " ".join(f"{f:.2f}" for f in frac.tolist()))
    log("fixture tensors:\n" + "\n".join(lines))


def check_schedule():
    base = GaussianDiffusion(cosine_betas(1000))
    assert abs(base.betas[0] - 4.1284e-5) < 1e-9 and base.betas[999] == 0.999
    assert abs(base.alphas_cumprod[499] - 0.4938436) < 1e-7
    assert abs(base.alphas_cumprod[999] / 2.4288e-9 - 1) < 1e-4
    assert sorted(space_timesteps(1000, [10])) == [0, 111, 222, 333, 444, 555, 666, 777, 888, 999]
    assert sorted(space_timesteps(1000, "ddim50")) == list(range(0, 1000, 20))
    assert len(space_timesteps(1000, [1000])) == 1000
    log("schedule: the cosine schedule's derived values and the respacing reproduced")


def tokenizer_cases(model):
    cases = []
    for text in TOKENIZER_CASES:
        ids, mask = model.tokenize([text])
        cases.append({"text": text, "input_ids": ids[0].tolist(),
                      "attention_mask": mask[0].tolist()})
    empty = cases[0]
    assert empty["input_ids"] == [0, 2] + [1] * 18, empty
    assert empty["attention_mask"] == [1, 1] + [0] * 18, empty
    # Independent check through the stock HF fast tokenizer loaded from the file.
    from transformers import RobertaTokenizerFast
    hf = RobertaTokenizerFast(tokenizer_file=os.path.join(TOK_DIR, "tokenizer.json"))
    for c in cases:
        enc = hf([c["text"]], padding="max_length", truncation=True, max_length=20)
        assert enc["input_ids"][0] == c["input_ids"], c
    return cases


def main():
    torch.set_num_threads(1)  # reproducible float reductions
    check_schedule()
    model, text_config = build_model("tiny", TOK_DIR, seed=SEEDS["weights"])
    ema_state = {k: v.clone() for k, v in model.state_dict().items()}
    ckpt = lightning_checkpoint(ema_state, text_config, seed=SEEDS["weights"])
    net_state = {k[len("net."):]: v for k, v in ckpt["state_dict"].items() if k.startswith("net.")}

    with tempfile.TemporaryDirectory() as tmp:
        config = check_converter(tmp, ckpt, ema_state, net_state)

    path = os.path.join(FIX, "flame_tiny.safetensors")
    ref, config2 = load_libflame(path)
    assert config == config2
    for k, v in ref.state_dict().items():
        if not k.endswith("position_ids"):
            assert torch.equal(v, ema_state[k]), k

    gen = torch.Generator().manual_seed(99)
    check_against_numpy(ref, path, config, [PROMPT, "", "someone jumps twice"],
                        torch.randn(3, 147, FRAMES, generator=gen), torch.tensor([500, 0, 999]),
                        FRAMES)

    res = run_reference(ref, SEEDS)
    tensors = to_fixture_tensors(res)
    again = to_fixture_tensors(run_reference(ref, SEEDS))
    assert all(torch.equal(tensors[k], again[k]) for k in tensors), "reference not deterministic"
    # The in-memory model (never written to disk) must agree with the converted file.
    direct = to_fixture_tensors(run_reference(model, SEEDS))
    assert all(torch.equal(tensors[k], direct[k]) for k in tensors), "converted file != in-memory"
    log("reference reproduces itself (twice from the file, once from the in-memory model)")
    sanity(tensors)

    # Same forward with the f16 file's weights (rounded to f16, math in f32): the target for a
    # runtime that widens f16 weights to f32.
    ref16, _ = load_libflame(os.path.join(FIX, "flame_tiny_f16.safetensors"))
    with torch.no_grad():
        x = res["forward_x"][None].expand(2, -1, -1)
        out16 = ref16(x, torch.full((2,), FORWARD_T), torch.full((2,), FRAMES), [PROMPT, ""])
    tensors["f16w_forward_out_cond"] = frame_major(out16[0]).contiguous()
    tensors["f16w_forward_out_uncond"] = frame_major(out16[1]).contiguous()
    err = (tensors["f16w_forward_out_cond"] - tensors["forward_out_cond"]).abs().max()
    log(f"f16-weight forward differs from f32 by max {err:.2e}")

    ids_c, mask_c = ref.tokenize([PROMPT])
    ids_u, mask_u = ref.tokenize([""])
    info = {
        "description": "FLAME tiny parity fixture; generated by tools/make_fixtures.py. Tensors "
                       "are frame-major [frames, 147|294] (official layout is channel-first).",
        "model": "flame_tiny.safetensors",
        "model_f16": "flame_tiny_f16.safetensors",
        "prompt": PROMPT,
        "uncond_prompt": "",
        "input_ids_cond": ids_c[0].tolist(), "attention_mask_cond": mask_c[0].tolist(),
        "input_ids_uncond": ids_u[0].tolist(), "attention_mask_uncond": mask_u[0].tolist(),
        "frames": FRAMES,
        "motion_length": FRAMES,
        "guidance": GUIDANCE,
        "forward_t": FORWARD_T,
        "num_timesteps": 1000,
        "schedule": "cosine",
        "respacing": RESPACING,
        "steps": len(res["timestep_map"]),
        "timestep_map": res["timestep_map"],
        "eta": 0.0,
        "clip_denoised": True,
        "seeds": SEEDS,
        "rng": "torch.Generator (CPU) randn; x_T and noise are stored, so no RNG parity is needed",
        "loop_order": "index k of ddim_*/ddpm_* is loop step k, spaced t = steps-1-k, network "
                      "timestep timestep_map[t]; *_xs[k] is x_{t-1} after the step, *_x0s[k] the "
                      "clamped x0 estimate at that step; final sample = *_xs[-1]",
        "ddpm_noise": "z added at loop step k (the one drawn at t = 0 is multiplied by 0)",
        "cfg": "batch [cond; uncond]; first half of x duplicated; eps = eps_u + s*(eps_c - eps_u); "
               "variance channels (147..293) from the conditional row",
        "forward_eps_guided": "forward_out_uncond[:, :147] + guidance * (forward_out_cond[:, :147]"
                              " - forward_out_uncond[:, :147])",
        "f16w_forward_out": "forward_out_* recomputed with the weights of model_f16 (widened to "
                            "f32, math in f32)",
        "text_encoder_outputs": "text_*_hidden = last_hidden_state [max_length, H] (all positions, "
                                "pads included); text_*_pooled = pooler_output [H]",
        "config": config,
    }
    save_file(tensors, os.path.join(FIX, "flame_tiny_expected.safetensors"),
              metadata={"generator": "tools/make_fixtures.py"})
    with open(os.path.join(FIX, "flame_tiny_expected.json"), "w") as f:
        f.write(dumps_compact(info) + "\n")
    with open(os.path.join(FIX, "tiny_roberta_tokens.json"), "w") as f:
        # One case per line keeps the file readable and diffs small.
        cases = ",\n  ".join(json.dumps(c, ensure_ascii=False) for c in tokenizer_cases(ref))
        f.write('{"tokenizer": "tiny_roberta/tokenizer.json", "max_length": 20, '
                '"padding": "max_length", "truncation": true,\n "cases": [\n  '
                + cases + "\n ]}\n")

    # Size budget for the files this script and make_tiny_tokenizer.py own (others share the dir).
    owned = [os.path.join(FIX, n) for n in OWNED_FILES]
    owned += [os.path.join(TOK_DIR, n) for n in os.listdir(TOK_DIR)]
    total = sum(os.path.getsize(p) for p in owned)
    log(f"FLAME fixtures total {total / 1e6:.2f} MB")
    assert total < 3e6, "FLAME fixtures must stay under 3 MB"
    return 0


if __name__ == "__main__":
    sys.exit(main())
