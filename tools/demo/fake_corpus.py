#!/usr/bin/env python3
"""A small stand-in for the demo corpus, in exactly the format `flame-corpus generate` writes, so
the training pipeline (tools/demo/train.py) can be developed and smoke-tested before the real
procedural generator exists. The motions are smooth random curves, not plausible human motion.

  python3 tools/demo/fake_corpus.py --out DIR [--count 64] [--seed 0]

Writes (the corpus contract):
  DIR/motions/<id>.npy  float32 [frames, 147] smpl24_6d features, 20 fps, 40..200 frames,
                        unnormalised: root translation (m), then 24 x 6D rotations (first two rows
                        of each local rotation matrix, row-major, FLAME's convention)
  DIR/corpus.jsonl      {"id","file","frames","family","actions","variant","split_frame","texts"}
  DIR/summary.json      counts per family, frame range, seed

Each family moves its own joints at its own tempo, so a text-conditioned model has something to
learn; the sentences are templated per family.
"""
import argparse
import json
import os

import numpy as np

JOINTS = 24
FPS = 20
MIN_FRAMES, MAX_FRAMES = 40, 200

# family -> (joints it moves, tempo in Hz, forward speed m/s, sentences)
FAMILIES = {
    "walk": ([1, 2, 4, 5], 1.0, 1.0, [
        "a person walks forward.", "someone walks straight ahead.",
        "a man takes a few steps forward.", "the person is walking forwards.",
        "a figure walks ahead at a steady pace.", "walking forward slowly."]),
    "wave": ([17, 19, 21], 1.5, 0.0, [
        "a person waves with the right hand.", "someone waves hello.",
        "the person raises an arm and waves.", "a man is waving his hand.",
        "waving the right arm in greeting.", "a person stands and waves."]),
    "jump": ([1, 2, 4, 5, 16, 17], 0.8, 0.0, [
        "a person jumps in place.", "someone jumps up and down.",
        "the person hops on the spot.", "a man jumps several times.",
        "jumping up repeatedly.", "a person bends the knees and jumps."]),
    "turn": ([0, 3, 6, 9], 0.4, 0.2, [
        "a person turns around.", "someone turns to the left.",
        "the person rotates in place.", "a man turns his body around.",
        "turning slowly on the spot.", "a person spins around once."]),
    "squat": ([1, 2, 4, 5, 3], 0.5, 0.0, [
        "a person squats down and stands up.", "someone does a squat.",
        "the person crouches and rises again.", "a man squats several times.",
        "squatting down slowly.", "a person bends down into a squat."]),
}


def axis_angle_to_matrix(aa):
    """Rodrigues: [..., 3] axis-angle -> [..., 3, 3]."""
    theta = np.linalg.norm(aa, axis=-1, keepdims=True)
    axis = aa / np.maximum(theta, 1e-12)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = np.zeros_like(x)
    k = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(aa.shape[:-1] + (3, 3))
    s, c = np.sin(theta)[..., None], np.cos(theta)[..., None]
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + s * k + (1 - c) * (k @ k)


def smooth_curve(rng, frames, tempo, amplitude):
    """Sum of a family-tempo sine and a couple of slow random harmonics."""
    t = np.arange(frames) / FPS
    phase = rng.uniform(0, 2 * np.pi)
    out = amplitude * np.sin(2 * np.pi * tempo * t + phase)
    for _ in range(2):
        f = rng.uniform(0.05, 0.3)
        out += 0.1 * amplitude * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    return out


def make_motion(rng, family, frames):
    joints, tempo, speed, _ = FAMILIES[family]
    aa = np.zeros((frames, JOINTS, 3))
    for j in range(JOINTS):  # small idle sway everywhere
        for k in range(3):
            aa[:, j, k] = smooth_curve(rng, frames, 0.2, 0.03)
    for j in joints:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        curve = smooth_curve(rng, frames, tempo * rng.uniform(0.8, 1.2), rng.uniform(0.4, 0.9))
        aa[:, j] += curve[:, None] * axis[None]
    rot6d = axis_angle_to_matrix(aa)[..., :2, :].reshape(frames, JOINTS * 6)
    t = np.arange(frames) / FPS
    trans = np.zeros((frames, 3))
    trans[:, 1] = speed * t * rng.uniform(0.8, 1.2)
    trans[:, 2] = 0.9 + 0.05 * np.sin(2 * np.pi * tempo * t)
    return np.concatenate([trans, rot6d], axis=1).astype(np.float32)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--count", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    os.makedirs(os.path.join(args.out, "motions"), exist_ok=True)
    families = sorted(FAMILIES)
    counts = {f: 0 for f in families}
    lengths = []
    with open(os.path.join(args.out, "corpus.jsonl"), "w") as f:
        for i in range(args.count):
            family = families[i % len(families)]
            frames = int(rng.integers(MIN_FRAMES, MAX_FRAMES + 1))
            motion = make_motion(rng, family, frames)
            mid = f"{i:06d}"
            rel = f"motions/{mid}.npy"
            np.save(os.path.join(args.out, rel), motion)
            texts = list(rng.permutation(FAMILIES[family][3])[:5])
            rec = {"id": mid, "file": rel, "frames": frames, "family": family,
                   "actions": [family], "variant": int(rng.integers(0, 3)), "split_frame": None,
                   "texts": [str(t) for t in texts]}
            f.write(json.dumps(rec) + "\n")
            counts[family] += 1
            lengths.append(frames)
    summary = {"count": args.count, "seed": args.seed, "fps": FPS, "families": counts,
               "frames": {"min": min(lengths), "max": max(lengths)},
               "generator": "tools/demo/fake_corpus.py (stand-in)"}
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    print(f"wrote {args.count} motions to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
