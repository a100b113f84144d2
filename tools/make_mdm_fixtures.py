#!/usr/bin/env python3
"""Generate the MDM / Motion Flow Matching parity fixtures in tests/fixtures/ (seeded).

Steps:
 1. Build two tiny random MDM trans_enc nets (tools/reference/mdm.py: njoints 263, latent 64,
    2 layers, 4 heads, ff 128, clip_dim 512) and save them in the official layouts: MDM as
    {'model', 'model_avg'} with args.json use_ema (plus a `clip_model.*` tensor and both `pe`
    buffers, which the converter must drop), MotionFM as a plain state dict.
 2. Build a tiny random CLIPTextModelWithProjection (projection 512, vocabulary sized to
    tiny_roberta's tokenizer.json, which is embedded only as an opaque placeholder: the text
    tower of these files is NOT a usable CLIP; the tests feed the text vector directly), random HumanML3D-like Mean/Std, and convert with tools/convert.py mdm / motionfm.
 3. Load the converted files back into the reference, cross-check one forward against an
    independent float64 numpy implementation, and write the expected outputs (frame-major
    `[frames, 263]`) to mdm_expected.safetensors + .json: one guided-pair forward at a diffusion t
    (MDM) and at a flow t (MotionFM), a 10-step DDIM trajectory (MDM, x0, guidance 2.5) and a
    10-step Euler trajectory (MotionFM, guidance 2.5), all with the same given text vector.

Run from anywhere: python tools/make_mdm_fixtures.py
"""
import json
import os
import subprocess
import sys
import tempfile

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import save_file
from scipy.special import erf

TOOLS = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(TOOLS)
FIX = os.path.join(REPO, "tests", "fixtures")
sys.path.insert(0, TOOLS)

from reference.diffusion import SpacedDiffusion, cosine_betas, space_timesteps  # noqa: E402
from reference.mdm import (MDM, ddim_x0_loop, euler_loop, flow_time_index,  # noqa: E402
                           frame_major, load_libflame)

NET = dict(njoints=263, latent_dim=64, layers=2, heads=4, ff_size=128, clip_dim=512)
FRAMES = 12
GUIDANCE = 2.5
RESPACING = [10]
EULER_STEPS = 10
FORWARD_T_DIFFUSION = 500
# 0.01f * 5 in float32 is 0.049999997: the pe row is 49, not 50 (truncation,
# docs/official/motionfm.md#time-index).
FORWARD_T_FLOW = float(np.float32(0.01) * np.float32(5))
SEEDS = {"mdm": 10, "motionfm": 11, "clip": 12, "stats": 13, "text": 14, "forward_x": 15,
         "ddim": 16, "euler": 17}
OWNED = ["mdm_tiny.safetensors", "motionfm_tiny.safetensors", "mdm_expected.safetensors",
         "mdm_expected.json"]


def log(msg):
    print(msg, file=sys.stderr)


def random_net(seed):
    torch.manual_seed(seed)
    net = MDM(**NET)
    with torch.no_grad():
        for name, p in net.named_parameters():
            if "norm" in name:  # non-trivial LayerNorm affine
                p.copy_((1.0 if name.endswith("weight") else 0.0) + 0.1 * torch.randn_like(p))
    return net.eval()


def tiny_clip(folder, tokenizer_json):
    from transformers import CLIPTextConfig, CLIPTextModelWithProjection
    with open(tokenizer_json) as f:
        tok = json.load(f)
    # Every id the tokenizer can produce, added tokens included, must have an embedding row.
    ids = list(tok["model"]["vocab"].values()) + [t["id"] for t in tok.get("added_tokens", [])]
    cfg = CLIPTextConfig(vocab_size=max(ids) + 1, hidden_size=32, intermediate_size=128,
                         num_hidden_layers=2, num_attention_heads=2, max_position_embeddings=77,
                         projection_dim=NET["clip_dim"], hidden_act="quick_gelu")
    torch.manual_seed(SEEDS["clip"])
    model = CLIPTextModelWithProjection(cfg)
    model.save_pretrained(folder, safe_serialization=True)
    with open(tokenizer_json) as src, open(os.path.join(folder, "tokenizer.json"), "w") as dst:
        dst.write(src.read())


def run_convert(argv):
    cmd = [sys.executable, os.path.join(TOOLS, "convert.py")] + argv
    r = subprocess.run(cmd, capture_output=True, text=True)
    log(r.stdout + r.stderr)
    assert r.returncode == 0, r.returncode


# -- independent float64 numpy forward ------------------------------------------------------------

def np_forward(w, cfg, x, row, text):
    """x `[T, J]`, pe row index, text `[clip]` -> `[T, J]`, float64."""
    f64 = {k: v.double().numpy() for k, v in w.items()}
    c, heads = cfg["latent_dim"], cfg["heads"]
    pos = np.arange(cfg["max_len"], dtype=np.float64)[:, None]
    div = np.exp(np.arange(0, c, 2) * (-np.log(10000.0) / c))
    pe = np.zeros((cfg["max_len"], c))
    pe[:, 0::2], pe[:, 1::2] = np.sin(pos * div), np.cos(pos * div)

    def lin(v, name):
        return v @ f64[name + ".weight"].T + f64[name + ".bias"]

    def ln(v, name):
        mu = v.mean(-1, keepdims=True)
        var = ((v - mu) ** 2).mean(-1, keepdims=True)
        return (v - mu) / np.sqrt(var + 1e-5) * f64[name + ".weight"] + f64[name + ".bias"]

    h = lin(pe[row], "embed_timestep.time_embed.0")
    h = h / (1 + np.exp(-h))
    emb = lin(h, "embed_timestep.time_embed.2") + lin(text, "embed_text")
    seq = np.concatenate([emb[None], lin(x, "input_process.poseEmbedding")]) + pe[: x.shape[0] + 1]
    hd = c // heads
    for n in range(cfg["layers"]):
        p = f"seqTransEncoder.layers.{n}."
        qkv = seq @ f64[p + "self_attn.in_proj_weight"].T + f64[p + "self_attn.in_proj_bias"]
        q, k, v = np.split(qkv, 3, axis=-1)
        att = np.zeros_like(q)
        for i in range(heads):
            s = slice(i * hd, (i + 1) * hd)
            sc = q[:, s] @ k[:, s].T / np.sqrt(hd)
            sc = np.exp(sc - sc.max(-1, keepdims=True))
            att[:, s] = (sc / sc.sum(-1, keepdims=True)) @ v[:, s]
        seq = ln(seq + lin(att, p + "self_attn.out_proj"), p + "norm1")
        f = lin(seq, p + "linear1")
        f = 0.5 * f * (1 + erf(f / np.sqrt(2)))
        seq = ln(seq + lin(f, p + "linear2"), p + "norm2")
    return lin(seq[1:], "output_process.poseFinal")


def main():
    torch.set_num_threads(1)
    assert sorted(space_timesteps(1000, RESPACING)) == [0, 111, 222, 333, 444, 555, 666, 777,
                                                        888, 999]
    assert int(flow_time_index(torch.tensor(FORWARD_T_FLOW))) == 49
    mdm_net, fm_net = random_net(SEEDS["mdm"]), random_net(SEEDS["motionfm"])
    mdm_raw = {k: v + 0.01 * torch.randn_like(v) for k, v in mdm_net.state_dict().items()}
    # The real CLIP tokenizer.json (tests/fixtures/clip_tokenizer, 1.7 MB, 49408 tokens) would
    # make each model file > 3 MB on its own; these files only test the denoiser, so the text
    # tower is a small-vocabulary placeholder and tiny_roberta's tokenizer.json rides along as an
    # opaque file. Do not encode prompts with these files.
    tok = os.path.join(FIX, "tiny_roberta", "tokenizer.json")
    gen = np.random.default_rng(SEEDS["stats"])
    mean = gen.normal(0, 0.5, 263).astype(np.float32)
    std = gen.uniform(0.05, 1.0, 263).astype(np.float32)

    with tempfile.TemporaryDirectory() as tmp:
        clip_dir = os.path.join(tmp, "clip")
        tiny_clip(clip_dir, tok)
        np.save(os.path.join(tmp, "Mean.npy"), mean)
        np.save(os.path.join(tmp, "Std.npy"), std)
        ema = dict(mdm_net.state_dict())
        ema["clip_model.token_embedding.weight"] = torch.zeros(4, 4)
        torch.save({"model": mdm_raw, "model_avg": ema}, os.path.join(tmp, "mdm.pt"))
        with open(os.path.join(tmp, "args.json"), "w") as f:
            json.dump({"arch": "trans_enc", "latent_dim": 64, "layers": 2, "use_ema": True,
                       "diffusion_steps": 1000, "noise_schedule": "cosine",
                       "guidance_param": GUIDANCE, "dataset": "humanml"}, f)
        torch.save(fm_net.state_dict(), os.path.join(tmp, "motionfm.pt"))
        common = ["--clip", clip_dir, "--mean", os.path.join(tmp, "Mean.npy"), "--std",
                  os.path.join(tmp, "Std.npy")]
        run_convert(["mdm", "--ckpt", os.path.join(tmp, "mdm.pt"), "--args",
                     os.path.join(tmp, "args.json"), "--out",
                     os.path.join(FIX, "mdm_tiny.safetensors")] + common)
        run_convert(["motionfm", "--ckpt", os.path.join(tmp, "motionfm.pt"), "--out",
                     os.path.join(FIX, "motionfm_tiny.safetensors")] + common)

    ref_mdm, cfg_mdm = load_libflame(os.path.join(FIX, "mdm_tiny.safetensors"))
    ref_fm, cfg_fm = load_libflame(os.path.join(FIX, "motionfm_tiny.safetensors"))
    for ref, src in ((ref_mdm, mdm_net), (ref_fm, fm_net)):
        for k, v in src.state_dict().items():
            assert torch.equal(ref.state_dict()[k], v), k
    with safe_open(os.path.join(FIX, "mdm_tiny.safetensors"), "pt") as f:
        assert torch.equal(f.get_tensor("motion.std"), torch.from_numpy(std))
        assert not any(k.startswith("clip_model.") or k.endswith(".pe") for k in f.keys())
    assert cfg_mdm["diffusion"]["parameterization"] == "x0"
    assert cfg_fm["diffusion"]["parameterization"] == "velocity"
    log("converter: EMA copy taken, clip_model/pe dropped, stats stored, configs as expected")

    gen = torch.Generator().manual_seed(SEEDS["text"])
    text = torch.randn(1, NET["clip_dim"], generator=gen)
    gen = torch.Generator().manual_seed(SEEDS["forward_x"])
    x = torch.randn(1, 263, 1, FRAMES, generator=gen)
    t = {}
    with torch.no_grad():
        pair_x = torch.cat([x, x])
        pair_c = torch.cat([text, torch.zeros_like(text)])
        td = torch.full((2,), FORWARD_T_DIFFUSION, dtype=torch.long)
        out_d = ref_mdm(pair_x, td, pair_c)
        tf = flow_time_index(torch.tensor(FORWARD_T_FLOW, dtype=torch.float32)).expand(2)
        out_f = ref_fm(pair_x, tf, pair_c)

        # Independent float64 check of both forwards (cond and uncond rows).
        for ref, cfg, out, row in ((ref_mdm, cfg_mdm, out_d, FORWARD_T_DIFFUSION),
                                   (ref_fm, cfg_fm, out_f, int(tf[0]))):
            for b in range(2):
                want = np_forward(ref.state_dict(), cfg["denoiser"],
                                  frame_major(x[0]).double().numpy(), row,
                                  pair_c[b].double().numpy())
                err = np.abs(frame_major(out[b]).double().numpy() - want).max()
                log(f"torch vs float64 numpy forward (row {row}, b {b}): max err {err:.2e}")
                assert err < 2e-5, err

        diffusion = SpacedDiffusion(cosine_betas(1000), space_timesteps(1000, RESPACING))
        gen = torch.Generator().manual_seed(SEEDS["ddim"])
        x_T = torch.randn(1, 263, 1, FRAMES, generator=gen)
        ddim = ddim_x0_loop(ref_mdm, diffusion, x_T, text, GUIDANCE)
        gen = torch.Generator().manual_seed(SEEDS["euler"])
        z0 = torch.randn(1, 263, 1, FRAMES, generator=gen)
        euler = euler_loop(ref_fm, z0, text, GUIDANCE, EULER_STEPS)

    t["text"] = text[0]
    t["forward_x"] = frame_major(x[0])
    t["forward_t_diffusion"] = torch.tensor(float(FORWARD_T_DIFFUSION))
    t["forward_t_flow"] = torch.tensor(FORWARD_T_FLOW, dtype=torch.float32)
    t["mdm_out_cond"], t["mdm_out_uncond"] = frame_major(out_d[0]), frame_major(out_d[1])
    t["motionfm_out_cond"], t["motionfm_out_uncond"] = frame_major(out_f[0]), frame_major(out_f[1])
    t["ddim_x_T"] = frame_major(x_T[0])
    t["ddim_xs"] = torch.stack([frame_major(s["x"][0]) for s in ddim])
    t["ddim_x0s"] = torch.stack([frame_major(s["pred_xstart"][0]) for s in ddim])
    t["ddim_model_t"] = torch.tensor([float(s["model_t"]) for s in ddim])
    t["euler_x_0"] = frame_major(z0[0])
    t["euler_xs"] = torch.stack([frame_major(s["x"][0]) for s in euler])
    t["euler_vs"] = torch.stack([frame_major(s["v"][0]) for s in euler])
    t["euler_t"] = torch.tensor([s["t"] for s in euler], dtype=torch.float32)
    t["euler_index"] = torch.tensor([float(s["index"]) for s in euler])
    t = {k: v.float().contiguous() for k, v in t.items()}
    for k, v in t.items():
        assert torch.isfinite(v).all(), k
        log(f"  {k:22s} {str(list(v.shape)):14s} std {v.std() if v.numel() > 1 else 0:.4f} "
            f"max|x| {v.abs().max():.4f}")
    assert t["euler_index"].tolist() == [100.0 * k for k in range(EULER_STEPS)]

    info = {
        "description": "MDM / Motion Flow Matching tiny parity fixture; generated by "
                       "tools/make_mdm_fixtures.py from tools/reference/mdm.py. Tensors are "
                       "frame-major [frames, 263] (official layout [B, 263, 1, frames]).",
        "model_mdm": "mdm_tiny.safetensors",
        "model_motionfm": "motionfm_tiny.safetensors",
        "frames": FRAMES,
        "guidance": GUIDANCE,
        "text": "the given conditioning vector [512] (a stand-in for CLIP's encode_text); the "
                "unconditional input is zeros",
        "forward": "mdm_out_* = MDM x0 prediction at diffusion step forward_t_diffusion; "
                   "motionfm_out_* = velocity at flow time forward_t_flow (float32 "
                   "0.049999997 -> pe row 49); *_cond with `text`, *_uncond with zeros",
        "ddim": "MDM, respacing [10] over T=1000 cosine (timestep_map = ddim_model_t), eta 0, "
                "x0 parameterisation, no clamp, CFG on x0: x0 = u + s(c - u). Step k: x0s[k] = "
                "guided x0 at spaced t = 9-k (network step ddim_model_t[k]); eps = "
                "(sqrt(1/abar)x - x0)/sqrt(1/abar - 1); xs[k] = sqrt(abar_prev)x0 + "
                "sqrt(1-abar_prev)eps. Start ddim_x_T; final = xs[-1]",
        "euler": "MotionFM, N = 10 steps, t_k = float32(k)/float32(N) (euler_t), pe row "
                 "trunc(float32(t_k*1000)) (euler_index), v = u + s(c - u) (euler_vs[k]), "
                 "x_{k+1} = x_k + float32(1/N)*v (euler_xs[k]); start euler_x_0 (t = 0 = noise)",
        "respacing": RESPACING,
        "seeds": SEEDS,
        "config_mdm": cfg_mdm,
        "config_motionfm": cfg_fm,
    }
    save_file(t, os.path.join(FIX, "mdm_expected.safetensors"),
              metadata={"generator": "tools/make_mdm_fixtures.py"})
    with open(os.path.join(FIX, "mdm_expected.json"), "w") as f:
        json.dump(info, f, indent=1)
        f.write("\n")
    total = sum(os.path.getsize(os.path.join(FIX, n)) for n in OWNED)
    log(f"MDM fixtures total {total / 1e6:.2f} MB")
    assert total < 3e6, "MDM fixtures must stay under 3 MB"
    return 0


if __name__ == "__main__":
    sys.exit(main())
