#!/usr/bin/env bash
# Full-size random-weight FineMoGen model file for benchmarks (f32, git-ignored):
#   models/finemogen_base_random.safetensors  the released HumanML3D denoiser (4 SAMI + SFFN layers,
#                                             8 x 64 parts, mixtures of 16 experts; 65.46 M values)
#                                             + the CLIP ViT-B/32 text tower
# An official-layout random checkpoint (tools/make_finemogen_checkpoint.py --size full, CLIP under
# model.clip.*) -> tools/convert.py finemogen, as a released checkpoint would. The intermediate
# folder is deleted unless KEEP_CKPT=1.
# Usage: tools/make_finemogen_base_model.sh [extra convert.py args, e.g. --dtype f16]
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
mkdir -p models
out=models/finemogen_base_random.safetensors
work=models/.finemogen_base_random.work

now() { date +%s.%N; }
t0=$(now)
"$PY" tools/make_finemogen_checkpoint.py --size full --out "$work" --clip-in-ckpt
t1=$(now)
"$PY" tools/convert.py finemogen --ckpt "$work/latest.pth" --tokenizer "$work/tokenizer.json" \
    --mean "$work/mean.npy" --std "$work/std.npy" --out "$out" "$@"
t2=$(now)
if [ "${KEEP_CKPT:-0}" != 1 ]; then rm -rf "$work"; fi
awk -v a="$t0" -v b="$t1" -v c="$t2" -v out="$out" 'BEGIN {
    printf "timings: checkpoint %.1f s, convert %.1f s, total %.1f s -> %s\n",
        b - a, c - b, c - a, out }'
ls -l "$out"
