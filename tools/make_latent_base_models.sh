#!/usr/bin/env bash
# Full-size random-weight MoLA and MLD model files for benchmarks (f32, git-ignored):
#   models/mola_base_random.safetensors  MoLA denoiser (9 x 512) + VAE-SAN decoder + CLIP ViT-B/32 text
#   models/mld_base_random.safetensors   MLD denoiser and VAE decoder (9-layer skip stacks, 256)
#                                        + CLIP ViT-L/14 text
# Each goes official-layout random checkpoints (tools/make_latent_checkpoints.py --clip) ->
# tools/convert.py mola|mld, as a released checkpoint would. The intermediate folder is deleted
# unless KEEP_CKPT=1.
# Usage: tools/make_latent_base_models.sh [mola|mld|both] [extra convert.py args, e.g. --dtype f16]
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
WHICH=${1:-both}
shift || true
case "$WHICH" in
    mola | mld) ARCHS=$WHICH ;;
    both) ARCHS="mola mld" ;;
    *) echo "usage: $0 [mola|mld|both] [convert.py args]" >&2; exit 2 ;;
esac
mkdir -p models

now() { date +%s.%N; }
for arch in $ARCHS; do
    out=models/${arch}_base_random.safetensors
    work=models/.${arch}_base_random.work
    t0=$(now)
    "$PY" tools/make_latent_checkpoints.py "$arch" --out "$work" --clip
    t1=$(now)
    if [ "$arch" = mola ]; then
        src=(--vae "$work/stage1.pth" --denoiser "$work/stage2.pth")
    else
        src=(--ckpt "$work/mld.ckpt")
    fi
    "$PY" tools/convert.py "$arch" "${src[@]}" --clip "$work/clip" --mean "$work/mean.npy" \
        --std "$work/std.npy" --out "$out" "$@"
    t2=$(now)
    if [ "${KEEP_CKPT:-0}" != 1 ]; then rm -rf "$work"; fi
    awk -v a="$t0" -v b="$t1" -v c="$t2" -v out="$out" 'BEGIN {
        printf "timings: checkpoints %.1f s, convert %.1f s, total %.1f s -> %s\n", b - a, c - b, c - a, out }'
    ls -l "$out"
done
