#!/usr/bin/env python3
"""Write a random FineMoGen checkpoint in the released layout (mmcv: {'state_dict': {'model.…'},
'meta': …}), for the converter check, the parity fixtures and the benchmark.

  python tools/make_finemogen_checkpoint.py --size full|tiny --out DIR [--seed 0] \
      [--clip-in-ckpt] [--hf-clip]
  -> DIR/latest.pth, DIR/mean.npy, DIR/std.npy (263 values), DIR/tokenizer.json;
     --clip-in-ckpt: the CLIP (text tower random, OpenAI names, plus stand-in vision tensors and
                     logit_scale) under model.clip.*, as FineMoGen's MotionDiffusion holds it;
     --hf-clip:      the same text tower as a Hugging Face folder DIR/clip/ (config.json,
                     model.safetensors, tokenizer.json) for `convert.py finemogen --clip`.
  Then: python tools/convert.py finemogen --ckpt DIR/latest.pth [--clip DIR/clip] \
            --tokenizer DIR/tokenizer.json --mean DIR/mean.npy --std DIR/std.npy --out M.safetensors

Sizes: full = docs/official/finemogen.md#released-configuration and
docs/official/finemogen.md#tensor-names (part_dim 64, 4 layers, time_embed 2048, text 256 x 2 layers,
ff 2048, ffn 256, 16 experts, gate 256, expert hidden 1024 / 256; CLIP ViT-B/32 text tower 512
x 12, 8 heads); tiny = the parity-fixture sizes of docs/model-files-finemogen.md (CLIP tower 8
wide, 2 layers, 2 heads: convert with --clip-heads 2). Every weight is random and nonzero; the
learned scalars are away from their initial values (sigma 100, t_sigma 1, temperature ln 2),
layer 0's gate temperatures above ln 100 (so exp is clamped at 100), the others below. The
buffers `_num_global_experts` and the unused `key_motion` are included, as in a saved model.
The tokenizer is the real CLIP tokenizer of tests/fixtures/clip_tokenizer.
"""
import argparse
import math
import os
import shutil
import sys
import time

import numpy as np
import torch

TOOLS = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, TOOLS)
from convert_finemogen import hf_to_openai_clip  # noqa: E402
from reference import finemogen as fm  # noqa: E402

CLIP_TOKENIZER = os.path.join(os.path.dirname(TOOLS), "tests", "fixtures", "clip_tokenizer",
                              "tokenizer.json")
TINY = dict(fm.RELEASED, part_dim=16, num_layers=2, time_embed_dim=64, clip_width=8,
            text_latent_dim=32, text_layers=2, text_heads=4, text_ff_size=64, ffn_dim=32,
            num_experts=4, gate_dim=16, text_expert_hidden=64, motion_expert_hidden=32)
CLIP_SIZES = {"full": dict(hidden_size=512, intermediate_size=2048, num_hidden_layers=12,
                           num_attention_heads=8, projection_dim=512),
              "tiny": dict(hidden_size=8, intermediate_size=32, num_hidden_layers=2,
                           num_attention_heads=2, projection_dim=8)}
CONFIGS = {"full": fm.RELEASED, "tiny": TINY}


def uniform(shape, bound, gen):
    t = (torch.rand(shape, generator=gen, dtype=torch.float64) * 2 - 1) * bound
    return t.float()


@torch.no_grad()
def randomize(net, gen):
    """Every parameter random and nonzero: LayerNorm weights 1 + 0.1 N, biases 0.1 N, Linear
    weights U(±1/sqrt(fan_in)), expert weights U(±1/sqrt(their fan-in)), position/part
    embeddings and body_weight N(0, 1), sigma 100·U(0.5, 1.5) (frame² units), t_sigma U(0.6, 1.6),
    gate temperature U(4.7, 5.2) in layer 0 (clamped at ln 100) and U(3.2, 3.7) elsewhere."""
    for name, p in net.named_parameters():
        leaf = name.rsplit(".", 1)[-1]
        if leaf == "sigma":
            p.copy_(100 * (0.5 + torch.rand(1, generator=gen)))
        elif leaf == "t_sigma":
            p.copy_(0.6 + torch.rand(1, generator=gen))
        elif leaf == "temperature":
            layer0 = name.startswith("temporal_decoder_blocks.0.")
            p.copy_((4.7 if layer0 else 3.2) + 0.5 * torch.rand(1, generator=gen))
        elif leaf in ("embedding", "body_weight", "key_motion", "sim_matrix"):
            p.copy_(torch.randn(p.shape, generator=gen))
        elif leaf in ("batched_fc1_w", "batched_fc2_w"):
            fan_in = p.shape[2] if leaf == "batched_fc1_w" else p.shape[1]
            p.copy_(uniform(p.shape, 1 / math.sqrt(fan_in), gen))
        elif leaf in ("batched_fc1_bias", "batched_fc2_bias"):
            p.copy_(0.1 * torch.randn(p.shape, generator=gen))
        elif p.dim() == 1:
            is_norm = ("norm" in name or name.startswith("text_ln")) and leaf == "weight"
            p.copy_((1.0 if is_norm else 0.0) + 0.1 * torch.randn(p.shape, generator=gen))
        else:
            p.copy_(uniform(p.shape, 1 / math.sqrt(p[0].numel()), gen))
        p.masked_fill_(p == 0, 1e-3)


def clip_model(size, seed, tiny_scale=0.5):
    from transformers import CLIPTextConfig, CLIPTextModelWithProjection
    cfg = CLIPTextConfig(vocab_size=49408, max_position_embeddings=77, hidden_act="quick_gelu",
                         layer_norm_eps=1e-5, bos_token_id=fm.SOT, eos_token_id=fm.EOT,
                         pad_token_id=0, attn_implementation="eager", **CLIP_SIZES[size])
    torch.manual_seed(seed)
    model = CLIPTextModelWithProjection(cfg).eval()
    if size == "tiny":
        # A tiny tower at HF's init (std 0.02) is nearly constant; larger random weights and
        # random LayerNorms make its 77 outputs differ per token and position.
        gen = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            for name, p in model.named_parameters():
                if "layer_norm" in name and name.endswith("weight"):
                    p.copy_(1 + 0.3 * torch.randn(p.shape, generator=gen))
                else:
                    p.copy_(tiny_scale * torch.randn(p.shape, generator=gen))
    return model


def official_state(net, clip=None, gen=None):
    """{'model.' + name: tensor} as MotionDiffusion.state_dict() holds it (clip: OpenAI names,
    plus stand-ins for the vision tower and logit_scale)."""
    state = {"model." + k: v.detach().clone() for k, v in net.state_dict().items()}
    if clip is not None:
        hf = {k: v.detach().clone() for k, v in clip.state_dict().items()
              if not k.endswith("position_ids")}
        for k, v in hf_to_openai_clip(hf).items():
            state["model.clip." + k] = v
        state["model.clip.visual.conv1.weight"] = torch.randn(16, 3, 4, 4, generator=gen)
        state["model.clip.visual.ln_post.weight"] = torch.ones(16)
        state["model.clip.logit_scale"] = torch.tensor(math.log(1 / 0.07))
    return state


def save_checkpoint(path, state):
    meta = {"mmcv_version": "1.7.1", "time": "random weights", "epoch": 12, "iter": 0,
            "config": "configs/finemogen/finemogen_t2m.py (random stand-in)"}
    torch.save({"meta": meta, "state_dict": state}, path)


def write_stats(out, seed):
    rng = np.random.default_rng(seed)
    np.save(os.path.join(out, "mean.npy"), rng.normal(0, 0.5, 263).astype(np.float32))
    np.save(os.path.join(out, "std.npy"), rng.uniform(0.05, 1.0, 263).astype(np.float32))


def write_hf_clip(folder, clip):
    clip.save_pretrained(folder, safe_serialization=True)
    shutil.copyfile(CLIP_TOKENIZER, os.path.join(folder, "tokenizer.json"))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", choices=sorted(CONFIGS), default="full")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--clip-in-ckpt", action="store_true",
                    help="store the CLIP under model.clip.* (OpenAI names)")
    ap.add_argument("--hf-clip", action="store_true", help="also write DIR/clip/ (HF folder)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    os.makedirs(args.out, exist_ok=True)
    torch.manual_seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    net = fm.FineMoGenNet(CONFIGS[args.size])
    randomize(net, gen)
    clip = clip_model(args.size, args.seed + 1) if args.clip_in_ckpt or args.hf_clip else None
    state = official_state(net, clip if args.clip_in_ckpt else None, gen)
    save_checkpoint(os.path.join(args.out, "latest.pth"), state)
    write_stats(args.out, args.seed)
    shutil.copyfile(CLIP_TOKENIZER, os.path.join(args.out, "tokenizer.json"))
    if args.hf_clip:
        write_hf_clip(os.path.join(args.out, "clip"), clip)
    n = sum(v.numel() for k, v in state.items() if not k.startswith("model.clip."))
    print(f"finemogen {args.size}: {n / 1e6:.2f} M denoiser values"
          f"{', CLIP in the checkpoint' if args.clip_in_ckpt else ''}; wrote {args.out} in "
          f"{time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
