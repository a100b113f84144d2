#!/usr/bin/env bash
# Full-size random-weight MotionLCM model files for benchmarks (f32, git-ignored):
#   models/motionlcm_v1_base_random.safetensors  v1.0 layout: latent [1, 256]
#   models/motionlcm_v2_base_random.safetensors  v2.0 layout: latent [16, 32], hidden 256
# Both: MLD's denoiser (9 layers x 256, 4 heads, ff 1024, text/time 768, cond_dim 256,
# query_pos 500) and VAE decoder (9 layers x 256, 500 rows, 263 features), and one random
# full-size sentence-t5-large (24 x 1024, vocab 32128, Dense 1024 -> 768) shared by both.
# Official-layout random checkpoints and a sentence-transformers folder
# (tools/make_motionlcm_checkpoints.py) -> tools/convert.py motionlcm, as a released checkpoint
# would go. The intermediate folder is deleted unless KEEP_CKPT=1. Nothing is downloaded.
# With CONTROL=1, also models/motionlcm_{v1,v2}_control_base_random.safetensors: the same plus a
# full-size random ControlNet and trajectory encoder (make_motionlcm_checkpoints.py --control).
# Usage: tools/make_motionlcm_base_models.sh [v1|v2|both] [extra convert.py args, e.g. --dtype f16]
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
WHICH=${1:-both}
shift || true
case "$WHICH" in
    v1 | v2) RELEASES=$WHICH ;;
    both) RELEASES="v1 v2" ;;
    *) echo "usage: $0 [v1|v2|both] [convert.py args]" >&2; exit 2 ;;
esac
mkdir -p models

now() { date +%s.%N; }
work=models/.motionlcm_base_random.work
t0=$(now)
CONTROL=${CONTROL:-0}
control_arg=()
if [ "$CONTROL" = 1 ]; then control_arg=(--control); fi
"$PY" tools/make_motionlcm_checkpoints.py --out "$work" --release "$WHICH" "${control_arg[@]}"
t1=$(now)
awk -v a="$t0" -v b="$t1" 'BEGIN { printf "timings: checkpoints and sentence-t5-large %.1f s\n", b - a }'
for r in $RELEASES; do
    out=models/motionlcm_${r}_base_random.safetensors
    tc=$(now)
    "$PY" tools/convert.py motionlcm --ckpt "$work/motionlcm_$r.ckpt" --t5 "$work/sentence-t5-large" \
        --mean "$work/mean.npy" --std "$work/std.npy" --out "$out" --heads 4 --frames 196 "$@"
    td=$(now)
    awk -v c="$tc" -v d="$td" -v out="$out" 'BEGIN { printf "timings: convert %.1f s -> %s\n", d - c, out }'
    ls -l "$out"
    if [ "$CONTROL" = 1 ]; then
        out=models/motionlcm_${r}_control_base_random.safetensors
        "$PY" tools/convert.py motionlcm --ckpt "$work/motionlcm_${r}_control.ckpt" \
            --t5 "$work/sentence-t5-large" --mean "$work/mean.npy" --std "$work/std.npy" \
            --control-mean "$work/mean_raw.npy" --control-std "$work/std_raw.npy" --out "$out" \
            --heads 4 --frames 196 "$@"
        ls -l "$out"
    fi
done
if [ "${KEEP_CKPT:-0}" != 1 ]; then rm -rf "$work"; fi
t2=$(now)
awk -v a="$t0" -v b="$t2" 'BEGIN { printf "timings: total %.1f s\n", b - a }'
