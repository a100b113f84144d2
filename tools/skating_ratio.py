#!/usr/bin/env python3
"""The foot skating ratio of GMD and OmniControl, in NumPy only.

    python tools/skating_ratio.py FILE.npy [...] [--fps 20] [--json]

Each FILE.npy holds world joint positions [frames, J, 3] (float32 or float64), Y up, metres:
what `flame generate --positions FILE.npy --convention gltf` writes. J is 22 (HumanML3D) or 24
(SMPL-24); the toes are joints 10 (L_Foot) and 11 (R_Foot) in both. Prints each file's ratio,
skating steps and lowest toe height, then the mean ratio; --json prints one JSON object instead.
Importable: `skating_ratio(positions, fps=20)`, `skating_mask(positions, fps=20)`.

The definition is `calculate_skating_ratio` in data_loaders/humanml/utils/metrics.py, the same
function in korrawe/guided-motion-diffusion (commit 7bc73c013340d1c438d7202df7d8900986d9d85b)
and neu-vi/OmniControl (commit 6cf22c3e3aa9b6c25d357adf568b15be8f0954a9), written again here
without SciPy or PyTorch:

- speed[t] = |xz[t+1] - xz[t]| * fps for the T-1 steps t = 0..T-2 (horizontal only, m/s);
- avg[t] = SciPy's uniform_filter1d(speed, size=5, mode='constant', origin=0): the sum of
  speed[t-2..t+2] with steps outside 0..T-2 taken as 0, divided by 5 at every step;
- contact: y[t] < 0.05 and y[t+1] < 0.05 (raw height, no floor estimated);
- a toe skates in step t when in contact, speed[t] > 0.5 and avg[t] > 0.5;
- a step skates when either toe does; ratio = skating steps / (T-1).

The official function takes a padded batch and divides by the padded length - 1; here each
motion is measured at its own length (the same for a batch of one). It computes in the float32
of its tensors; this casts to float64, as src/motion/skating.rs does, so the two agree exactly.
"""

import argparse
import json
import sys

import numpy as np

LEFT_TOE, RIGHT_TOE = 10, 11
CONTACT_HEIGHT = 0.05
SKATE_SPEED = 0.5
WINDOW = 5


def _check(positions, fps):
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[2] != 3:
        raise ValueError(f"positions must be [frames, joints, 3], got {list(p.shape)}")
    if p.shape[0] < 2:
        raise ValueError(f"{p.shape[0]} frames; the ratio measures steps between frames, needs 2")
    if p.shape[1] <= RIGHT_TOE:
        raise ValueError(f"{p.shape[1]} joints; the toes are joints {LEFT_TOE} and {RIGHT_TOE}")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps {fps} must be positive and finite")
    if not np.isfinite(p).all():
        t, j, _ = np.argwhere(~np.isfinite(p))[0]
        raise ValueError(f"frame {t}, joint {j} is not finite")
    return p


def _box_mean(speed):
    """Centred 5-step mean with zero padding: uniform_filter1d(mode='constant', cval=0)."""
    half = WINDOW // 2
    padded = np.concatenate([np.zeros(half), speed, np.zeros(half)])
    # Window sums by explicit shifted adds (no cumulative sum, whose rounding drifts).
    sums = sum(padded[k : k + len(speed)] for k in range(WINDOW))
    return sums / WINDOW


def skating_mask(positions, fps=20.0):
    """[frames-1] booleans: whether either toe skates in the step from frame t to t+1."""
    p = _check(positions, fps)
    toes = p[:, [LEFT_TOE, RIGHT_TOE], :]  # [T, 2, 3]
    step = toes[1:] - toes[:-1]  # [T-1, 2, 3]
    speed = np.sqrt(step[..., 0] ** 2 + step[..., 2] ** 2) * fps  # [T-1, 2], X and Z only
    avg = np.stack([_box_mean(speed[:, k]) for k in range(2)], axis=1)
    height = toes[..., 1]
    contact = (height[:-1] < CONTACT_HEIGHT) & (height[1:] < CONTACT_HEIGHT)
    skating = contact & (speed > SKATE_SPEED) & (avg > SKATE_SPEED)
    return skating.any(axis=1)


def skating_ratio(positions, fps=20.0):
    """Skating steps over frames-1, in [0, 1]."""
    mask = skating_mask(positions, fps)
    return float(mask.sum()) / len(mask)


def min_toe_height(positions):
    """The lowest height either toe reaches (metres; negative = below the ground y = 0)."""
    p = np.asarray(positions, dtype=np.float64)
    return float(p[:, [LEFT_TOE, RIGHT_TOE], 1].min())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", metavar="FILE.npy")
    ap.add_argument("--fps", type=float, default=20.0, help="frame rate (default 20)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)

    rows = []
    for path in args.files:
        p = np.load(path)
        try:
            mask = skating_mask(p, args.fps)
        except ValueError as e:
            sys.exit(f"skating_ratio.py: {path}: {e}")
        rows.append(
            {
                "file": path,
                "frames": int(p.shape[0]),
                "joints": int(p.shape[1]),
                "skating_steps": int(mask.sum()),
                "ratio": float(mask.sum()) / len(mask),
                "min_toe_height": min_toe_height(p),
            }
        )
    mean = float(np.mean([r["ratio"] for r in rows]))
    lowest = min(r["min_toe_height"] for r in rows)
    if args.json:
        out = {"fps": args.fps, "files": rows, "mean_ratio": mean, "min_toe_height": lowest}
        print(json.dumps(out, indent=1))
    else:
        for r in rows:
            print(
                f"{r['file']}: ratio {r['ratio']:.4f} ({r['skating_steps']}/{r['frames'] - 1} "
                f"steps), min toe height {r['min_toe_height'] * 100:+.2f} cm"
            )
        print(f"mean ratio {mean:.4f} over {len(rows)} files, lowest toe {lowest * 100:+.2f} cm")


if __name__ == "__main__":
    main()
