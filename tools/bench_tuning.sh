#!/usr/bin/env bash
# What MotionLCM's consistency latent tuning costs (`flame generate --control --optimize N`),
# libflame against PyTorch eager on the same full-size random control files
# (CONTROL=1 tools/make_motionlcm_base_models.sh), same machine, interleaved rounds:
#   tools/bench_tuning.sh [ROUNDS (default 3)]
# Per round, for v1 and v2 (the order alternating): `flame generate` with a pelvis path on every
# frame and `--optimize ITERATIONS` (its own report of the tuning's seconds), and
# tools/bench_tuning.py (the release's loop under autograd, median of RUNS runs). Prints the
# median milliseconds per iteration of each, their ratio, and what the release's 400 iterations
# cost. Environment: PYTHON (default target/bench-venv/bin/python if present), FLAME (default
# target/release/flame, built if missing), THREADS (2), FRAMES (196), ITERATIONS (20), RUNS (3),
# MODELS ("v1 v2"), WEIGHTS (f32; e.g. int8 for libflame's int8 weights).
set -euo pipefail
cd "$(dirname "$0")/.."
ROUNDS=${1:-3}
if [ -z "${PYTHON:-}" ]; then
    if [ -x target/bench-venv/bin/python ]; then PYTHON=target/bench-venv/bin/python; else PYTHON=python3; fi
fi
FLAME=${FLAME:-target/release/flame}
THREADS=${THREADS:-2}
FRAMES=${FRAMES:-196}
ITERATIONS=${ITERATIONS:-20}
RUNS=${RUNS:-3}
MODELS=${MODELS:-"v1 v2"}
WEIGHTS=${WEIGHTS:-f32}
for m in $MODELS; do
    f=models/motionlcm_${m}_control_base_random.safetensors
    [ -f "$f" ] || { echo "$f missing: run CONTROL=1 tools/make_motionlcm_base_models.sh" >&2; exit 1; }
done
[ -x "$FLAME" ] || cargo build --release --bin flame
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
# The same pelvis path as bench_tuning.py: x = 0.02 f, y = 0.9, z = 0.01 f; the rest free.
"$PYTHON" - "$work/hint.npy" "$FRAMES" <<'PY'
import sys
import numpy as np
frames = int(sys.argv[2])
h = np.full((frames, 22, 3), np.nan, dtype=np.float32)
f = np.arange(frames, dtype=np.float32)
h[:, 0] = np.stack([0.02 * f, np.full(frames, 0.9, np.float32), 0.01 * f], axis=1)
np.save(sys.argv[1], h)
PY

flame_run() {  # model -> ms per iteration
    "$FLAME" generate --model "models/motionlcm_$1_control_base_random.safetensors" \
        --prompt "a person walks forward along a curve." --frames "$FRAMES" --steps 1 \
        --threads "$THREADS" --weights "$WEIGHTS" --convention native --control "$work/hint.npy" \
        --optimize "$ITERATIONS" --out "$work/out.npy" 2>&1 >/dev/null |
        sed -n 's/^latent tuning: .* (\([0-9.]*\) ms each).*/\1/p'
}
torch_run() {
    "$PYTHON" tools/bench_tuning.py --model "models/motionlcm_$1_control_base_random.safetensors" \
        --frames "$FRAMES" --iterations "$ITERATIONS" --threads "$THREADS" --runs "$RUNS" |
        sed -n 's/^torch_ms_per_iteration //p'
}
declare -A F T
for r in $(seq "$ROUNDS"); do
    for m in $MODELS; do
        if [ $((r % 2)) = 1 ]; then
            f=$(flame_run "$m"); t=$(torch_run "$m")
        else
            t=$(torch_run "$m"); f=$(flame_run "$m")
        fi
        echo "round $r $m: libflame $f ms/iteration, PyTorch $t ms/iteration"
        F[$m]+="$f "
        T[$m]+="$t "
    done
done
median() { tr ' ' '\n' | grep . | sort -g | awk '{ a[NR] = $1 } END { print (NR % 2) ? a[(NR + 1) / 2] : (a[NR / 2] + a[NR / 2 + 1]) / 2 }'; }
echo "model  libflame ms/it  PyTorch ms/it  PyTorch/libflame  400 iterations (libflame, PyTorch)"
for m in $MODELS; do
    f=$(echo "${F[$m]}" | median)
    t=$(echo "${T[$m]}" | median)
    awk -v m="$m" -v f="$f" -v t="$t" 'BEGIN { printf "%-6s %14.1f %14.1f %17.2fx  %.1f s, %.1f s\n", m, f, t, t / f, f * 0.4, t * 0.4 }'
done
echo "($WEIGHTS weights, $FRAMES frames, $THREADS threads, $ITERATIONS iterations per run, medians of $ROUNDS rounds)"
