#!/usr/bin/env python3
"""Generate the MotionLCM parity fixtures in tests/fixtures/ (seeded, deterministic):
motionlcm_v1_tiny.safetensors, motionlcm_v2_tiny.safetensors, motionlcm_expected.safetensors.

Steps:
 1. A tiny sentence-t5 folder in a temporary directory, laid out as
    sentence-transformers/sentence-t5-large is published (modules.json: Transformer at "",
    1_Pooling (mean), 2_Dense (no bias, Identity), 3_Normalize; config.json, tokenizer.json,
    sentence_bert_config.json): a random T5 v1.0 encoder (ReLU feed-forward, d_model 32, 2 blocks,
    4 heads of 8, d_ff 64, 32 buckets, max distance 128) with tools/make_t5_fixtures.py's Unigram
    tokenizer and a Dense 32 -> 48. Written twice with the same weights: once with
    model.safetensors files (v1's), once with pytorch_model.bin files that also hold the tied
    `encoder.embed_tokens.weight` (v2's), so both ways of publishing are read.
 2. Tiny random MotionLCM checkpoints in the official layout ({'state_dict': ...}, see
    tools/convert_motionlcm.py): v1 (latent [1, 32]) and v2 (latent [4, 8], latent_pre /
    latent_post, vae.latent_post), width 32, text/time dim 48, cond_dim 16, 3-layer skip stacks,
    ff 64, denoiser position rows 20, VAE rows 64; every weight nonzero (cond_proj too, which the
    official code zero-initialises), norms around 1. They carry what the converter must skip:
    VAE encoder-side tensors (v2's vae.latent_pre too), an evaluator tensor, v1 the unused
    `denoiser.mem_pos.pe`.
 3. `tools/convert.py motionlcm` (f32, --frames 24) -> the two tiny files; the converter's
    refusals are exercised (a ControlNet checkpoint, and the same converted with --skip-prefix;
    an MLD checkpoint without cond_proj; an unknown denoiser tensor; a gated T5 by config and by
    tensor names; a Dense of the wrong width, with a bias, and a non-mean pooling), and a v2
    checkpoint without vae.global_motion_token converts with --latent-tokens to the same tensors.
 4. tools/reference/motionlcm.py on the CONVERTED files (float32) -> motionlcm_expected:
    text vectors of two prompts (transformers' T5EncoderModel loaded from the folder, mean
    pooling, Dense, L2; checked against the converted files' T5 and against plain torch ops),
    one denoiser forward per release, the guidance embedding, and 1-, 2- and 4-step latent
    consistency sampling per release (diffusers' LCMScheduler with the given re-noising draws)
    with every step's estimate and the VAE decoding of the final latent (24 frames, model space).

Expected tensors (r in v1, v2; n in 1, 2, 4; L x C the release's latent):
  text.{i} [48], text.{i}.ids [S_i] (float32 ids)           i < 2, metadata "prompts"
  {r}.forward.z [1, L, C], {r}.forward.t [1] (699), {r}.forward.w [1] (6.5: the embedded value),
  {r}.forward.eps [1, L, C] = denoiser(z, t, e(w), text.0)
  {r}.embedding [16] = e(6.5)
  {r}.s{n}.noise [1, L, C] (z_T), {r}.s{n}.renoise [max(n-1, 1), L, C] (the draws after each step
  but the last, in order; for n = 1 one unused row), {r}.s{n}.guidance [1] (v1 7.5; v2 8.0,
  12.5, 13.5; the embedded w is guidance - 1), {r}.s{n}.timesteps [n], {r}.s{n}.latent [1, L, C]
  (the last step's denoised), {r}.s{n}.denoised [n, L, C], {r}.s{n}.features [24, 263]
All conditioned on text.0.

Run from anywhere: python tools/make_motionlcm_fixtures.py   (~20 s)
"""
import hashlib
import json
import math
import os
import shutil
import sys
import tempfile

import numpy as np
import torch
import torch.nn.functional as F
from safetensors import safe_open
from safetensors.torch import load_file, save_file

TOOLS = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(TOOLS)
FIX = os.path.join(REPO, "tests", "fixtures")
sys.path.insert(0, TOOLS)

from make_latent_fixtures import log, randomize, run_convert  # noqa: E402
from make_t5_fixtures import tokenizer as t5_tokenizer  # noqa: E402
from reference import motionlcm  # noqa: E402

T5 = dict(d_model=32, d_kv=8, d_ff=64, num_layers=2, num_heads=4,
          relative_attention_num_buckets=32, relative_attention_max_distance=128)
TEXT_DIM, COND_DIM, WIDTH = 48, 16, 32
DEN = dict(latent_dim=WIDTH, text_dim=TEXT_DIM, cond_dim=COND_DIM, layers=3, heads=4, ff_size=64,
           max_len=20)
VAE = dict(latent_dim=WIDTH, layers=3, heads=4, ff_size=64, nfeats=263, max_len=64,
           final_norm=True)
LATENT = {"v1": (1, WIDTH), "v2": (4, 8)}
FRAMES = 24
PROMPTS = ["a person walks forward and waves.",
           "someone jumps twice in place, then turns around slowly"]
SEEDS = {"t5": 40, "v1": 41, "v2": 42, "stats": 43, "inputs": 44, "extra": 45}
OUT = {"v1": "motionlcm_v1_tiny.safetensors", "v2": "motionlcm_v2_tiny.safetensors"}
EXPECTED = "motionlcm_expected.safetensors"
TOKENIZER_SHA256 = "9575c627cd9d655e4e3e657b302f84059d9e554c0d55083987a8e5319653394c"
MODULES = [{"idx": 0, "name": "0", "path": "", "type": "sentence_transformers.models.Transformer"},
           {"idx": 1, "name": "1", "path": "1_Pooling",
            "type": "sentence_transformers.models.Pooling"},
           {"idx": 2, "name": "2", "path": "2_Dense", "type": "sentence_transformers.models.Dense"},
           {"idx": 3, "name": "3", "path": "3_Normalize",
            "type": "sentence_transformers.models.Normalize"}]
POOLING = {"word_embedding_dimension": 32, "pooling_mode_cls_token": False,
           "pooling_mode_mean_tokens": True, "pooling_mode_max_tokens": False,
           "pooling_mode_mean_sqrt_len_tokens": False}
DENSE = {"in_features": 32, "out_features": TEXT_DIM, "bias": False,
         "activation_function": "torch.nn.modules.linear.Identity"}


def dump(path, obj):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump(obj, f, indent=2)


# -- 1. the tiny sentence-t5 folder -------------------------------------------------------------

def canonical_tokenizer(tok=None, digest=TOKENIZER_SHA256):
    """make_t5_fixtures.tokenizer()'s Unigram model (or `tok`'s) made reproducible: the
    `tokenizers` trainer returns the same pieces on every run, but orders pieces of equal score
    differently and jitters some single characters' scores by 1e-4 from run to run. The pieces are
    kept, the scores rounded to 3 decimals and the ids assigned by (score descending, piece) after
    the three specials (`<pad>` 0, `</s>` 1, `<unk>` 2); `digest` (TOKENIZER_SHA256 for the
    fixtures' tokenizer, None: not checked) pins the result."""
    from tokenizers import Tokenizer
    j = json.loads((tok or t5_tokenizer()).to_str())
    vocab = j["model"]["vocab"]
    assert [p for p, _ in vocab[:3]] == ["<pad>", "</s>", "<unk>"], vocab[:3]
    rest = sorted(((p, round(s, 3)) for p, s in vocab[3:]), key=lambda x: (-x[1], x[0]))
    j["model"]["vocab"] = [[p, 0.0] for p, _ in vocab[:3]] + [[p, s] for p, s in rest]
    tok = Tokenizer.from_str(json.dumps(j))
    got = hashlib.sha256(tok.to_str().encode()).hexdigest()
    assert digest is None or got == digest, got
    return tok


def tiny_init(name, p, gen):
    """The fixtures' T5 weights: RMSNorm scales 1 + 0.3·N, everything else 0.3·N."""
    base = 1.0 if "layer_norm" in name else 0.0
    p.copy_(base + 0.3 * torch.randn(p.shape, generator=gen))


def t5_encoder(tok, sizes=None, text_dim=TEXT_DIM, seed=SEEDS["t5"], init=tiny_init):
    """(T5EncoderModel of `sizes` (T5's keyword arguments; default the tiny T5), dense weight
    [text_dim, d_model]), every weight drawn by `init(name, tensor, generator)` in parameter
    order, then the Dense weight (named "dense.weight")."""
    from transformers import T5Config, T5EncoderModel
    sizes = sizes or T5
    cfg = T5Config(vocab_size=tok.get_vocab_size(), feed_forward_proj="relu",
                   layer_norm_epsilon=1e-6, dropout_rate=0.0, is_encoder_decoder=False,
                   use_cache=False, **sizes)
    torch.manual_seed(seed)
    model = T5EncoderModel(cfg).eval()
    gen = torch.Generator().manual_seed(seed)
    dense = torch.empty(text_dim, sizes["d_model"])
    with torch.no_grad():
        for name, p in model.named_parameters():
            init(name, p, gen)
        init("dense.weight", dense, gen)
    return model, dense


def tiny_t5():
    """(T5EncoderModel, dense weight [48, 32], tokenizer) with seeded nonzero weights."""
    tok = canonical_tokenizer()
    assert tok.token_to_id("<pad>") == 0 and tok.token_to_id("</s>") == 1
    model, dense = t5_encoder(tok)
    return model, dense, tok


def write_folder(folder, model, dense, tok, binary, dense_cfg=DENSE, pooling=POOLING,
                 config_patch=None, state_patch=None):
    """A sentence-transformers folder; `binary`: pytorch_model.bin files (with the tied
    encoder.embed_tokens.weight) instead of model.safetensors."""
    os.makedirs(folder)
    model.config.to_json_file(os.path.join(folder, "config.json"))
    if config_patch:
        with open(os.path.join(folder, "config.json")) as f:
            c = json.load(f)
        c.update(config_patch)
        dump(os.path.join(folder, "config.json"), c)
    state = {k: v.clone().contiguous() for k, v in model.state_dict().items()}
    if not binary:
        state.pop("encoder.embed_tokens.weight")
    if state_patch:
        state = state_patch(state)
    if binary:
        torch.save(state, os.path.join(folder, "pytorch_model.bin"))
    else:
        save_file(state, os.path.join(folder, "model.safetensors"))
    tok.save(os.path.join(folder, "tokenizer.json"))
    dump(os.path.join(folder, "sentence_bert_config.json"),
         {"max_seq_length": 256, "do_lower_case": False})
    dump(os.path.join(folder, "modules.json"), MODULES)
    dump(os.path.join(folder, "1_Pooling", "config.json"), pooling)
    dump(os.path.join(folder, "2_Dense", "config.json"), dense_cfg)
    dstate = {"linear.weight": dense.clone().contiguous()}
    if binary:
        torch.save(dstate, os.path.join(folder, "2_Dense", "pytorch_model.bin"))
    else:
        save_file(dstate, os.path.join(folder, "2_Dense", "model.safetensors"))
    os.makedirs(os.path.join(folder, "3_Normalize"))


# -- 2. the tiny checkpoints --------------------------------------------------------------------

def checkpoint(release, den=None, vae=None, latent=None, seed=None):
    """{'state_dict'} of a MotionLCM in the official layout: `den` / `vae` the sizes (DEN, VAE
    keys; default the tiny ones), `latent` (tokens, channels) (default LATENT[release]), `seed`
    (default SEEDS[release])."""
    den, vae = den or DEN, vae or VAE
    tokens, channels = latent or LATENT[release]
    seed = SEEDS[release] if seed is None else seed
    v2 = release == "v2"
    torch.manual_seed(seed)
    dnet = motionlcm.Denoiser(den["latent_dim"], tokens, channels, den["text_dim"],
                              den["cond_dim"], den["layers"], den["heads"], den["ff_size"],
                              den["max_len"], "none" if v2 else "relu", v2)
    dec = motionlcm.Decoder(vae["latent_dim"], channels, vae["layers"], vae["heads"],
                            vae["ff_size"], vae["nfeats"], vae["max_len"], vae["final_norm"], v2)
    gen = torch.Generator().manual_seed(seed)
    randomize(dnet, gen)
    randomize(dec, gen)
    state = {"denoiser." + k: v.clone() for k, v in dnet.state_dict().items()}
    state.update({"vae." + k: v.clone() for k, v in dec.state_dict().items()})
    assert state["denoiser.time_embedding.cond_proj.weight"].abs().min() > 0
    # What the converter must recognise and skip.
    vw, dw = vae["latent_dim"], den["latent_dim"]
    extra = {"vae.skel_embedding.weight": (vw, 263), "vae.skel_embedding.bias": (vw,),
             "vae.global_motion_token": (2 * tokens, vw),
             "vae.query_pos_encoder.pe": (vae["max_len"], 1, vw),
             "vae.encoder.middle_block.linear1.weight": (vae["ff_size"], vw),
             "vae.encoder.norm.weight": (vw,),
             "t2m_textencoder.input_emb.weight": (16, 8)}
    if v2:
        extra.update({"vae.latent_pre.weight": (channels, vw),
                      "vae.latent_pre.bias": (channels,)})
    else:
        extra["denoiser.mem_pos.pe"] = (den["max_len"], 1, dw)
    for k, shape in extra.items():
        state[k] = torch.randn(shape, generator=gen)
    return {"state_dict": state}


def tiny_checkpoint(release):
    """{'state_dict'} of a tiny MotionLCM in the official layout."""
    return checkpoint(release)


# -- 3. convert --------------------------------------------------------------------------------

def canonical_header(path):
    """Rewrite a safetensors file with its `__metadata__` keys sorted: safetensors writes the
    metadata map in an order that changes from run to run (the tensors and values are the same),
    which would make the fixtures differ byte-wise between runs."""
    with open(path, "rb") as f:
        blob = f.read()
    n = int.from_bytes(blob[:8], "little")
    header = json.loads(blob[8:8 + n])
    meta = header.pop("__metadata__", None)
    ordered = {"__metadata__": dict(sorted(meta.items()))} if meta else {}
    ordered.update(header)
    text = json.dumps(ordered, separators=(",", ":"), ensure_ascii=False).encode()
    text += b" " * (-len(text) % 8)
    with open(path, "wb") as f:
        f.write(len(text).to_bytes(8, "little") + text + blob[8 + n:])


def convert_args(ckpt, t5_dir, tmp, out, *more):
    return ["motionlcm", "--ckpt", ckpt, "--t5", t5_dir, "--mean", os.path.join(tmp, "mean.npy"),
            "--std", os.path.join(tmp, "std.npy"), "--out", out, "--heads", "4",
            "--dtype", "f32", "--frames", str(FRAMES), *more]


def refuse(tmp, ckpt, t5_dir, needle, *more):
    err = run_convert(convert_args(ckpt, t5_dir, tmp, os.path.join(tmp, "refused.st"), *more),
                      expect_ok=False)
    assert needle in err, (needle, err)


def same_tensors(a, b):
    ta, tb = load_file(a), load_file(b)
    assert sorted(ta) == sorted(tb), sorted(set(ta) ^ set(tb))
    for k in ta:
        assert torch.equal(ta[k], tb[k]), k
    with safe_open(a, "pt") as fa, safe_open(b, "pt") as fb:
        assert fa.metadata() == fb.metadata()


def make_files(tmp):
    model, dense, tok = tiny_t5()
    folders = {"v1": os.path.join(tmp, "st5_safetensors"), "v2": os.path.join(tmp, "st5_bin")}
    write_folder(folders["v1"], model, dense, tok, binary=False)
    write_folder(folders["v2"], model, dense, tok, binary=True)
    ckpts = {}
    for r in ("v1", "v2"):
        ckpts[r] = tiny_checkpoint(r)
        path = os.path.join(tmp, f"motionlcm_{r}.ckpt")
        torch.save(ckpts[r], path)
        out = os.path.join(FIX, OUT[r])
        run_convert(convert_args(path, folders[r], tmp, out))
        canonical_header(out)
        with safe_open(out, "pt") as f:
            cfg = json.loads(f.metadata()["flame.config"])
            names = set(f.keys())
        assert cfg["denoiser"]["latent_tokens"] == LATENT[r][0], cfg["denoiser"]
        assert cfg["denoiser"]["latent_channels"] == LATENT[r][1], cfg["denoiser"]
        assert "denoiser.mem_pos.pe" not in names
        assert "text.encoder.embed_tokens.weight" not in names
        assert not any(n.startswith(("vae.encoder.", "vae.skel", "vae.latent_pre", "t2m_"))
                       for n in names)
    v1_ckpt = os.path.join(tmp, "motionlcm_v1.ckpt")
    fa = folders["v1"]

    # Refusals.
    state = dict(ckpts["v1"]["state_dict"])
    gen = torch.Generator().manual_seed(SEEDS["extra"])
    state["controlnet.controlnet_cond_embedding.0.weight"] = torch.randn(WIDTH, WIDTH,
                                                                         generator=gen)
    state["traj_encoder.skel_embedding.weight"] = torch.randn(WIDTH, 66, generator=gen)
    control = os.path.join(tmp, "control.ckpt")
    torch.save({"state_dict": state}, control)
    refuse(tmp, control, fa, "trajectory control")
    skipped = os.path.join(tmp, "control_t2m.safetensors")
    run_convert(convert_args(control, fa, tmp, skipped, "--skip-prefix", "controlnet.",
                             "--skip-prefix", "traj_encoder."))
    same_tensors(skipped, os.path.join(FIX, OUT["v1"]))

    state = {k: v for k, v in ckpts["v1"]["state_dict"].items()
             if k != "denoiser.time_embedding.cond_proj.weight"}
    torch.save({"state_dict": state}, os.path.join(tmp, "mld.ckpt"))
    refuse(tmp, os.path.join(tmp, "mld.ckpt"), fa, "convert.py mld")

    state = dict(ckpts["v2"]["state_dict"])
    state["denoiser.encoder.extra.weight"] = torch.ones(2)
    torch.save({"state_dict": state}, os.path.join(tmp, "unknown.ckpt"))
    refuse(tmp, os.path.join(tmp, "unknown.ckpt"), fa,
           "unknown tensor 'denoiser.encoder.extra.weight'")

    bad = os.path.join(tmp, "st5_gated_config")
    write_folder(bad, model, dense, tok, False, config_patch={"feed_forward_proj": "gated-gelu"})
    refuse(tmp, v1_ckpt, bad, "feed_forward_proj 'gated-gelu'")

    def gate(s):
        for k in [k for k in s if k.endswith("DenseReluDense.wi.weight")]:
            w = s.pop(k)
            s[k.replace(".wi.", ".wi_0.")], s[k.replace(".wi.", ".wi_1.")] = w, w.clone()
        return s
    bad = os.path.join(tmp, "st5_gated_names")
    write_folder(bad, model, dense, tok, False, state_patch=gate)
    refuse(tmp, v1_ckpt, bad, "gated feed-forward (T5 v1.1)")

    bad = os.path.join(tmp, "st5_dense40")
    write_folder(bad, model, torch.randn(40, 32, generator=gen), tok, False,
                 dense_cfg=dict(DENSE, out_features=40))
    refuse(tmp, v1_ckpt, bad, "out_features 40 != the denoiser's text_dim 48")
    bad = os.path.join(tmp, "st5_dense_bias")
    write_folder(bad, model, dense, tok, False, dense_cfg=dict(DENSE, bias=True))
    refuse(tmp, v1_ckpt, bad, "sentence-t5's Dense has none")
    bad = os.path.join(tmp, "st5_cls")
    write_folder(bad, model, dense, tok, False,
                 pooling=dict(POOLING, pooling_mode_cls_token=True))
    refuse(tmp, v1_ckpt, bad, "only mean pooling")

    # v2 without the VAE's global_motion_token: --latent-tokens says L.
    state = {k: v for k, v in ckpts["v2"]["state_dict"].items() if k != "vae.global_motion_token"}
    torch.save({"state_dict": state}, os.path.join(tmp, "v2_nogmt.ckpt"))
    refuse(tmp, os.path.join(tmp, "v2_nogmt.ckpt"), folders["v2"], "the sequence needs 22",
           "--latent-tokens", "20")
    out = os.path.join(tmp, "v2_nogmt.safetensors")
    err = run_convert(convert_args(os.path.join(tmp, "v2_nogmt.ckpt"), folders["v2"], tmp, out,
                                   "--latent-tokens", str(LATENT["v2"][0])))
    assert "no vae.global_motion_token" in err, err
    same_tensors(out, os.path.join(FIX, OUT["v2"]))
    refuse(tmp, os.path.join(tmp, "motionlcm_v2.ckpt"), folders["v2"], "global_motion_token says 4",
           "--latent-tokens", "16")
    return folders, dense


# -- 4. expected values ------------------------------------------------------------------------

def plain_t5(w, ids, max_distance):
    """The sentence vector of one unpadded sentence from the converted `text.*` tensors, with
    plain torch ops (RMSNorm, unscaled attention plus the bucketed bias, ReLU feed-forward)."""
    x = w["shared.weight"][ids]
    n = ids.shape[0]
    table = w["encoder.block.0.layer.0.SelfAttention.relative_attention_bias.weight"]
    buckets, heads = table.shape
    rel = torch.arange(n)[None, :] - torch.arange(n)[:, None]  # key - query
    half = buckets // 2
    exact = half // 2
    dist = rel.abs()
    far = exact + (torch.log(dist.float().clamp(min=1) / exact) / math.log(max_distance / exact)
                   * (half - exact)).long()
    idx = torch.where(dist < exact, dist, far.clamp(max=half - 1)) + (rel > 0).long() * half
    bias = table[idx].permute(2, 0, 1)  # [heads, n, n]

    def rms(v, g):
        return v * torch.rsqrt(v.pow(2).mean(-1, keepdim=True) + 1e-6) * g

    layers = len({k.split(".")[2] for k in w if k.startswith("encoder.block.")})
    for i in range(layers):
        p = f"encoder.block.{i}.layer."
        h = rms(x, w[p + "0.layer_norm.weight"])
        q, k, v = (h @ w[f"{p}0.SelfAttention.{m}.weight"].T for m in "qkv")
        q, k, v = (t.reshape(n, heads, -1).transpose(0, 1) for t in (q, k, v))
        att = torch.softmax(q @ k.transpose(1, 2) + bias, dim=-1) @ v
        x = x + att.transpose(0, 1).reshape(n, -1) @ w[p + "0.SelfAttention.o.weight"].T
        h = rms(x, w[p + "1.layer_norm.weight"])
        x = x + torch.relu(h @ w[p + "1.DenseReluDense.wi.weight"].T) @ \
            w[p + "1.DenseReluDense.wo.weight"].T
    x = rms(x, w["encoder.final_layer_norm.weight"])
    return F.normalize(x.mean(0) @ w["dense.weight"].T, dim=0)


def text_vectors(folder, dense):
    """text.{i} by transformers' T5EncoderModel loaded from the folder, checked against the
    converted files' T5 and plain ops."""
    from transformers import T5EncoderModel
    hf = motionlcm.SentenceT5(T5EncoderModel.from_pretrained(folder).eval(), dense).eval()
    with open(os.path.join(folder, "tokenizer.json")) as f:
        tok = motionlcm.tokenizer_from(f.read(), 256)
    out = {}
    files = {r: motionlcm.load_libflame(os.path.join(FIX, OUT[r])) for r in OUT}
    for i, prompt in enumerate(PROMPTS):
        ids, vec = motionlcm.encode_text(hf, tok, prompt)
        assert int(ids[-1]) == 1 and len(ids) > 8, ids
        for r, (_, _, text, ftok, cfg) in files.items():
            fids, fvec = motionlcm.encode_text(text, ftok, prompt)
            assert torch.equal(fids, ids), (r, fids, ids)
            err = float((fvec - vec).abs().max())
            assert err < 1e-6, (r, err)
            w = {k[len("text."):]: v for k, v in
                 load_file(os.path.join(FIX, OUT[r])).items() if k.startswith("text.")}
            err2 = float((plain_t5(w, ids, cfg["text_encoder"]["relative_attention_max_distance"])
                          - vec).abs().max())
            log(f"text {i} ({r} file): T5EncoderModel from the folder vs the file's: {err:.1e}; "
                f"vs plain torch ops: {err2:.1e}")
            assert err2 < 1e-5, (r, err2)
        assert abs(float(vec.norm()) - 1) < 1e-5
        out[f"text.{i}"] = vec
        out[f"text.{i}.ids"] = ids.to(torch.float32)
    return out


def release_expected(r, text):
    den, dec, _, _, cfg = motionlcm.load_libflame(os.path.join(FIX, OUT[r]))
    tokens, channels = LATENT[r]
    shape = (1, tokens, channels)
    gen = torch.Generator().manual_seed(SEEDS["inputs"] + (0 if r == "v1" else 100))
    t = {}
    emb = motionlcm.guidance_embedding(torch.tensor([6.5]), COND_DIM)
    half = COND_DIM // 2
    a = 6500.0 * np.exp(-math.log(10000) / (half - 1) * np.arange(half))
    ref = np.concatenate([np.sin(a), np.cos(a)])
    err = float(np.abs(emb[0].double().numpy() - ref).max())
    log(f"{r}: guidance embedding vs float64: {err:.1e}")
    assert err < 2e-3, err  # the float32 argument reaches 6500
    t[f"{r}.embedding"] = emb[0]
    z = torch.randn(shape, generator=gen)
    with torch.no_grad():
        eps = den(z, torch.tensor([699.0]), emb, text[None])
        # Without cond_proj's contribution the output differs: the embedding is live.
        den_off = den(z, torch.tensor([699.0]), torch.zeros_like(emb), text[None])
        assert float((eps - den_off).abs().max()) > 1e-3
    t[f"{r}.forward.z"], t[f"{r}.forward.t"], t[f"{r}.forward.w"] = z, torch.tensor([699.0]), \
        torch.tensor([6.5])
    t[f"{r}.forward.eps"] = eps
    abar = motionlcm.check_scheduler().alphas_cumprod
    want_t = {"v1": {1: [999], 2: [999, 499], 4: [999, 759, 499, 259]},
              "v2": {1: [799], 2: [699, 299], 4: [699, 399, 299, 299]}}[r]
    maxes = {"eps": float(eps.abs().max())}
    for n in (1, 2, 4):
        noise = torch.randn(shape, generator=gen)
        renoise = torch.randn((max(n - 1, 1),) + shape[1:], generator=gen)
        g = motionlcm.guidance_for(cfg, n)
        assert g == ({"v1": 7.5}.get(r) or motionlcm.V2_GUIDANCE[n]), g
        steps, samples, denoised = motionlcm.sample(den, cfg, noise, text[None], g, n,
                                                    renoise[: n - 1])
        assert steps == want_t[n], (r, n, steps)
        assert torch.equal(samples[-1], denoised[-1])
        for k in range(n - 1):  # the re-noising z = sqrt(abar')·denoised + sqrt(1 - abar')·xi
            a_next = abar[steps[k + 1]]
            want = a_next.sqrt() * denoised[k] + (1 - a_next).sqrt() * renoise[k]
            assert torch.allclose(samples[k], want, atol=1e-6), (r, n, k)
        with torch.no_grad():
            feats = dec(denoised[-1], FRAMES)[0]
        t[f"{r}.s{n}.noise"], t[f"{r}.s{n}.renoise"] = noise, renoise
        t[f"{r}.s{n}.guidance"] = torch.tensor([g])
        t[f"{r}.s{n}.timesteps"] = torch.tensor(steps, dtype=torch.float32)
        t[f"{r}.s{n}.latent"] = denoised[-1].clone()
        t[f"{r}.s{n}.denoised"] = denoised[:, 0]
        t[f"{r}.s{n}.features"] = feats
        maxes[f"s{n} latent"] = float(denoised[-1].abs().max())
        maxes[f"s{n} features"] = float(feats.abs().max())
        assert feats.shape == (FRAMES, 263)
    log(f"{r}: max |x| " + ", ".join(f"{k} {v:.3g}" for k, v in maxes.items()))
    for k, v in maxes.items():
        assert 0.05 < v < 1e3, (k, v)
    return t


def main():
    torch.set_num_threads(1)
    gen = np.random.default_rng(SEEDS["stats"])
    mean = gen.normal(0, 0.5, 263).astype(np.float32)
    std = gen.uniform(0.05, 1.0, 263).astype(np.float32)
    tmp = tempfile.mkdtemp(prefix="motionlcm_fixtures_")
    try:
        np.save(os.path.join(tmp, "mean.npy"), mean)
        np.save(os.path.join(tmp, "std.npy"), std)
        folders, dense = make_files(tmp)
        expected = text_vectors(folders["v1"], dense)
        for r in ("v1", "v2"):
            expected.update(release_expected(r, expected["text.0"]))
    finally:
        shutil.rmtree(tmp)
    expected = {k: v.float().contiguous() for k, v in sorted(expected.items())}
    for k, v in expected.items():
        assert torch.isfinite(v).all(), k
        log(f"  {k:22s} {str(list(v.shape)):14s} max|x| {v.abs().max():.4g}")
    save_file(expected, os.path.join(FIX, EXPECTED),
              metadata={"prompts": json.dumps(PROMPTS), "frames": str(FRAMES),
                        "generator": "tools/make_motionlcm_fixtures.py"})
    canonical_header(os.path.join(FIX, EXPECTED))
    total = sum(os.path.getsize(os.path.join(FIX, n)) for n in list(OUT.values()) + [EXPECTED])
    log(f"motionlcm fixtures total {total / 1e6:.2f} MB")
    assert total < 1.5e6, "motionlcm fixtures must stay small"
    return 0


if __name__ == "__main__":
    sys.exit(main())
