"""Random-weight MDM-sized Motion Flow Matching model for benchmarks (not committed).

MDM's published size (8 layers, 512 wide, 4 heads, feed-forward 1024, 263 HumanML3D features)
in the official state-dict layout, with a small random CLIP text tower (projection 512) and
random HumanML3D statistics, converted by tools/convert.py motionfm:

    python3 tools/make_mdm_base_model.py [--out models/motionfm_base_random.safetensors]
"""
import argparse
import os
import sys
import tempfile

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import make_mdm_fixtures as fx  # noqa: E402
from reference.mdm import MDM  # noqa: E402

BASE = dict(njoints=263, latent_dim=512, layers=8, heads=4, ff_size=1024, clip_dim=512)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="models/motionfm_base_random.safetensors")
    args = ap.parse_args()
    torch.manual_seed(0)
    net = MDM(**BASE).eval()
    gen = np.random.default_rng(0)
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        clip_dir = os.path.join(tmp, "clip")
        fx.tiny_clip(clip_dir, os.path.join(fx.FIX, "tiny_roberta", "tokenizer.json"))
        np.save(os.path.join(tmp, "Mean.npy"), gen.normal(0, 0.5, 263).astype(np.float32))
        np.save(os.path.join(tmp, "Std.npy"), gen.uniform(0.05, 1.0, 263).astype(np.float32))
        torch.save(net.state_dict(), os.path.join(tmp, "motionfm.pt"))
        fx.run_convert(["motionfm", "--ckpt", os.path.join(tmp, "motionfm.pt"), "--out", args.out,
                        "--clip", clip_dir, "--mean", os.path.join(tmp, "Mean.npy"),
                        "--std", os.path.join(tmp, "Std.npy"), "--heads", "4"])
    print(args.out)


if __name__ == "__main__":
    main()
