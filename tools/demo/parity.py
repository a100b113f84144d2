#!/usr/bin/env python3
"""Expected denoiser outputs of the trained demo model, for the Rust parity test
(tests/assemble.rs `demo_model_matches_pytorch`): proves that the converted, assembled model file
computes what the PyTorch net computes.

  python3 tools/demo/parity.py --ckpt RUN/flame_demo.ckpt --out PARITY.safetensors \
      [--text-model MINILM_DIR] [--dtype f16] [--prompt TEXT] [--frames 40]

The EMA net of the checkpoint runs with its weights rounded through --dtype (the dtype the model
file stores, so only arithmetic differs), on a seeded x [frames, 147] at several timesteps, for the
prompt and for "" (one row each). Text states come from the same BertModel the training used.
Written frame-major (`[frames, C]`, the Rust layout): x, text_cond_hidden [20, 384],
text_cond_pooled [384], out_cond_K / out_uncond_K [frames, 294] for timestep K of the
`flame.parity` metadata JSON (prompt, frames, timesteps, dtype).
"""
import argparse
import json
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402

DTYPES = {"f32": None, "f16": torch.float16, "bf16": torch.bfloat16}
TIMESTEPS = [999, 500, 111, 0]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ckpt", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--text-model", default=None)
    ap.add_argument("--dtype", choices=sorted(DTYPES), default="f16")
    ap.add_argument("--prompt", default="a person walks forward and waves.")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    torch.set_num_threads(2)
    net, _ = common.load_ema_net(args.ckpt, DTYPES[args.dtype])
    tokenizer, lm = common.load_text_encoder(common.minilm_dir(args.text_model))
    pooled, hidden = common.encode_texts(tokenizer, lm, [args.prompt, ""])
    x = torch.randn(args.frames, common.MOTION_DIM, generator=torch.Generator().manual_seed(
        args.seed))
    xb = x.T[None].expand(2, -1, -1).contiguous()  # [2, 147, frames], channel-first
    lengths = torch.full((2,), args.frames, dtype=torch.long)
    tensors = {"x": x.contiguous(), "text_cond_hidden": hidden[0].contiguous(),
               "text_cond_pooled": pooled[0].contiguous()}
    with torch.no_grad():
        for k, t in enumerate(TIMESTEPS):
            out = net(xb, torch.full((2,), t), lengths, text_features=(pooled, hidden))
            tensors[f"out_cond_{k}"] = out[0].T.contiguous()
            tensors[f"out_uncond_{k}"] = out[1].T.contiguous()
    meta = {"prompt": args.prompt, "frames": args.frames, "timesteps": TIMESTEPS,
            "dtype": args.dtype, "ckpt": os.path.basename(args.ckpt)}
    from safetensors.torch import save_file
    save_file(tensors, args.out, metadata={"flame.parity": json.dumps(meta)})
    print(f"wrote {args.out}: {len(TIMESTEPS)} timesteps x (prompt, \"\"), {args.frames} frames, "
          f"weights through {args.dtype}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
