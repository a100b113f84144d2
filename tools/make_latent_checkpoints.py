#!/usr/bin/env python3
"""Write full-size random MoLA / MLD checkpoints shaped like the released ones, for the converter
check and the benchmark (the released weights are not needed).

  python tools/make_latent_checkpoints.py mola --out DIR [--seed 0] [--clip]
      -> DIR/stage1.pth {'net': vae.decoder.model.* + stand-in encoder tensors},
         DIR/stage2.pth {'trans': denoiser.* (buffers included) + the wrapper's unused copies}
  python tools/make_latent_checkpoints.py mld --out DIR [--seed 0] [--clip]
      -> DIR/mld.ckpt {'state_dict': denoiser.* (with mem_pos.pe), vae.* (decoder + stand-in
         encoder tensors), text_encoder.* stand-in}
Both also write DIR/mean.npy, DIR/std.npy (263 values). --clip adds DIR/clip/, a random
full-size CLIP text tower (MoLA: ViT-B/32, projection 512; MLD: ViT-L/14, projection 768) with
the CLIP tokenizer of tests/fixtures/clip_tokenizer, so `convert.py mola|mld` can run on DIR.

Sizes: MoLA docs/official/mola-mld.md#mola-denoiser-tensor-names and
docs/official/mola-mld.md#mola-vae-decoder (latent 16, embed 512, depth 9, 4 heads, rotary 64, ff 2048,
cond 512, time features 128; VAE width 512, 2 up stages, 3 blocks); MLD
docs/official/mola-mld.md#mld-denoiser (latent 256, 9-layer
skip stacks, 4 heads, ff 1024, text 768, position tables 500). The encoder-side tensors are
stand-ins with invented names under the prefixes the converter skips; their real names do not
matter to it.
"""
import argparse
import os
import shutil
import sys
import time

import numpy as np
import torch

TOOLS = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, TOOLS)
from make_latent_fixtures import randomize  # noqa: E402
from reference import mld, mola  # noqa: E402

CLIP_TOKENIZER = os.path.join(os.path.dirname(TOOLS), "tests", "fixtures", "clip_tokenizer",
                              "tokenizer.json")
CLIP_SIZES = {"mola": dict(hidden_size=512, intermediate_size=2048, num_hidden_layers=12,
                           num_attention_heads=8, projection_dim=512),
              "mld": dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12,
                          num_attention_heads=12, projection_dim=768)}


def write_clip(folder, arch, seed):
    from transformers import CLIPTextConfig, CLIPTextModelWithProjection
    cfg = CLIPTextConfig(vocab_size=49408, max_position_embeddings=77, hidden_act="quick_gelu",
                         **CLIP_SIZES[arch])
    torch.manual_seed(seed)
    CLIPTextModelWithProjection(cfg).save_pretrained(folder, safe_serialization=True)
    shutil.copyfile(CLIP_TOKENIZER, os.path.join(folder, "tokenizer.json"))


def write_mola(out, gen):
    st2 = mola.Stage2()
    randomize(st2, gen)
    torch.save({"trans": st2.state_dict(), "epoch": 0}, os.path.join(out, "stage2.pth"))
    st1 = mola.Stage1Decoder()
    randomize(st1, gen)
    net = dict(st1.state_dict())
    # Stand-ins for the encoder side (skipped by the converter).
    net["vae.encoder.model.0.weight"] = torch.randn(512, 263, 3, generator=gen)
    net["vae.encoder.model.0.bias"] = torch.randn(512, generator=gen)
    torch.save({"net": net, "epoch": 0}, os.path.join(out, "stage1.pth"))
    return sum(v.numel() for v in st2.denoiser.state_dict().values()), \
        sum(v.numel() for v in st1.state_dict().values())


def write_mld(out, gen):
    den, vae = mld.Denoiser(), mld.VaeDecoder()
    randomize(den, gen)
    randomize(vae, gen)
    state = {"denoiser." + k: v for k, v in den.state_dict().items()}
    state.update({"vae." + k: v for k, v in vae.state_dict().items()})
    state["vae.skel_embedding.weight"] = torch.randn(256, 263, generator=gen)
    state["vae.global_motion_token"] = torch.randn(2, 256, generator=gen)
    state["vae.query_pos_encoder.pe"] = torch.randn(500, 1, 256, generator=gen)
    state["text_encoder.text_model.final_layer_norm.weight"] = torch.ones(768)
    torch.save({"state_dict": state, "epoch": 0, "pytorch-lightning_version": "1.7.7"},
               os.path.join(out, "mld.ckpt"))
    return sum(v.numel() for v in den.state_dict().values()), \
        sum(v.numel() for v in vae.state_dict().values())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("arch", choices=["mola", "mld"])
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--clip", action="store_true", help="also write a random CLIP folder")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    os.makedirs(args.out, exist_ok=True)
    torch.manual_seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    n_den, n_vae = (write_mola if args.arch == "mola" else write_mld)(args.out, gen)
    rng = np.random.default_rng(args.seed)
    np.save(os.path.join(args.out, "mean.npy"), rng.normal(0, 0.5, 263).astype(np.float32))
    np.save(os.path.join(args.out, "std.npy"), rng.uniform(0.05, 1.0, 263).astype(np.float32))
    if args.clip:
        write_clip(os.path.join(args.out, "clip"), args.arch, args.seed + 1)
    print(f"{args.arch}: denoiser {n_den / 1e6:.1f} M values, VAE decoder {n_vae / 1e6:.1f} M; "
          f"wrote {args.out} in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
