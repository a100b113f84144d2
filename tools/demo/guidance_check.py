#!/usr/bin/env python3
"""Quick check for the demo model's default guidance: sample corpus prompts with the shipped
sampler (DDIM, eta 0, 10 respaced steps, x0 prediction guided as libflame guides it) at several
guidance values and score each by nearest-neighbour retrieval against the corpus.

  python3 tools/demo/guidance_check.py --ckpt RUN/flame_demo.ckpt --corpus DIR \
      [--stats RUN] [--guidance 1,1.5,2,2.5,3,4] [--per-family 4] [--frames 100] [--dtype f16]

Each sample and each corpus motion is described by the per-channel mean and std over time of its
normalised features. "family acc" is how often the nearest corpus motion belongs to the prompt's
family (text adherence); "nn dist" is the mean distance to that nearest motion (how far samples
drift from the data; guidance too high makes it grow). The suggested value: among the guidances whose
nn dist is at most 25 % above the lowest, the smallest within 2 points of the best accuracy.
A crude check, not an evaluation: the corpus' own classifier (flame-corpus) is the real one.
"""
import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402
from reference.diffusion import space_timesteps  # noqa: E402

DTYPES = {"f32": None, "f16": torch.float16}


def describe(x):
    """[N, frames, 147] -> [N, 294]: per-channel mean and std over time."""
    return torch.cat([x.mean(1), x.std(1)], dim=1)


@torch.no_grad()
def ddim_x0(net, feats, frames, guidance, steps, gen):
    """libflame's DDIM (eta 0) for an x0-predicting model, guidance on x0, no clamping."""
    n = feats[0].shape[0] // 2
    ab_all = common.diffusion_tables()
    kept = sorted(space_timesteps(common.NUM_TIMESTEPS, [steps]))
    ab = ab_all[kept]
    ab_prev = np.append(1.0, ab[:-1])
    x = torch.randn(n, common.MOTION_DIM, frames, generator=gen)
    lengths = torch.full((2 * n,), frames, dtype=torch.long)
    for k in reversed(range(len(kept))):
        t = torch.full((2 * n,), kept[k])
        out = net(torch.cat([x, x]), t, lengths, text_features=feats)[:, :common.MOTION_DIM]
        x0 = out[n:] + guidance * (out[:n] - out[n:])
        a, ap = float(ab[k]), float(ab_prev[k])
        eps = (x / a ** 0.5 - x0) / (1 / a - 1) ** 0.5
        x = ap ** 0.5 * x0 + (1 - ap) ** 0.5 * eps
    return x.permute(0, 2, 1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ckpt", required=True)
    ap.add_argument("--corpus", required=True)
    ap.add_argument("--stats", default=None, help="dir with mean.npy/std.npy (default: ckpt dir)")
    ap.add_argument("--text-model", default=None)
    ap.add_argument("--guidance", default="1,1.5,2,2.5,3,4")
    ap.add_argument("--per-family", type=int, default=4)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--dtype", choices=sorted(DTYPES), default="f16")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    torch.set_num_threads(args.threads)
    stats = args.stats or os.path.dirname(os.path.abspath(args.ckpt))
    mean = np.load(os.path.join(stats, "mean.npy"))
    std = np.load(os.path.join(stats, "std.npy"))
    records = common.load_corpus(args.corpus)
    families = sorted({r["family"] for r in records})
    corpus_desc = describe_all([(r["motion"] - mean) / std for r in records])
    corpus_fam = np.array([families.index(r["family"]) for r in records])

    rng = np.random.default_rng(args.seed)
    prompts, fam = [], []
    for f, name in enumerate(families):
        members = [r for r in records if r["family"] == name]
        for i in rng.choice(len(members), args.per_family, replace=len(members) < args.per_family):
            prompts.append(str(rng.choice(members[i]["texts"])))
            fam.append(f)
    fam = np.array(fam)

    net, _ = common.load_ema_net(args.ckpt, DTYPES[args.dtype])
    tokenizer, lm = common.load_text_encoder(common.minilm_dir(args.text_model))
    pooled, hidden = common.encode_texts(tokenizer, lm, prompts + [""] * len(prompts))

    rows = []
    print(f"{len(prompts)} prompts over {len(families)} families, {args.frames} frames, "
          f"DDIM {args.steps} steps")
    print("guidance  family acc  nn dist")
    for g in [float(v) for v in args.guidance.split(",")]:
        gen = torch.Generator().manual_seed(args.seed)
        x = ddim_x0(net, (pooled, hidden), args.frames, g, args.steps, gen)
        d = torch.cdist(describe(x), corpus_desc)
        nn_dist, nn_idx = d.min(1)
        acc = float((corpus_fam[nn_idx.numpy()] == fam).mean())
        rows.append((g, acc, float(nn_dist.mean())))
        print(f"{g:8.2f}  {acc:10.3f}  {rows[-1][2]:7.3f}", flush=True)
    # Guidances that keep samples near the data; among them the best accuracy, the smaller
    # guidance on ties (within 2 points).
    best_dist = min(r[2] for r in rows)
    near = [r for r in rows if r[2] <= 1.25 * best_dist]
    best_acc = max(r[1] for r in near)
    ok = [r for r in near if r[1] >= best_acc - 0.02]
    print(f"suggested guidance: {min(ok, key=lambda r: r[0])[0]}")
    return 0


def describe_all(motions):
    return torch.stack([describe(torch.from_numpy(m)[None])[0] for m in motions])


if __name__ == "__main__":
    sys.exit(main())
