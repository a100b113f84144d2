#!/usr/bin/env bash
# Random-weight FLAME-base model for benchmarks: models/flame_base_random.safetensors (f32).
# FLAME-base denoiser (8 x 768, 8 heads, ff 2048) + a RoBERTa-base-sized random LM, with the tiny
# tokenizer of tests/fixtures/tiny_roberta (ids < 1000, so any prompt works with the 50265 vocab).
# The intermediate .ckpt (~1.5 GB, two copies of the net) is deleted unless KEEP_CKPT=1.
# Usage: tools/make_base_model.sh [OUT.safetensors] [extra convert.py args, e.g. --dtype f16]
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
OUT=${1:-models/flame_base_random.safetensors}
shift || true
WORK=models/.flame_base_random.work
mkdir -p "$(dirname "$OUT")" "$WORK"

now() { date +%s.%N; }
t0=$(now)
"$PY" tools/make_random_checkpoint.py --preset base --out "$WORK/flame_base_random.ckpt" \
    --text-model tests/fixtures/tiny_roberta --text-model-out "$WORK/text"
t1=$(now)
"$PY" tools/convert.py flame --ckpt "$WORK/flame_base_random.ckpt" --text-model "$WORK/text" \
    --out "$OUT" --heads 8 "$@"
t2=$(now)
if [ "${KEEP_CKPT:-0}" != 1 ]; then rm -rf "$WORK"; fi
awk -v a="$t0" -v b="$t1" -v c="$t2" -v out="$OUT" 'BEGIN {
    printf "timings: checkpoint %.1f s, convert %.1f s, total %.1f s -> %s\n", b - a, c - b, c - a, out }'
ls -l "$OUT"
