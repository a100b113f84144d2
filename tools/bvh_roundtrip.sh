#!/usr/bin/env bash
# BVH round trip through a real consumer: libflame writes BVH files and the joint positions they
# must produce (tests/motion_bvh.rs, ignored test write_blender_check_files: a walk with root
# travel and turning, smpl24_6d and humanml263), Blender imports them with its default settings
# and every frame's bone heads must match within 1 mm (tools/blender_bvh_check.py); the smpl24_6d
# walk must also stand upright (Head above Pelvis along Blender's Z). A third file,
# cli_walk.bvh, is what `flame generate --out x.bvh` writes without --convention: it must give the
# same 1 mm match (so the default is the Y-up convention the importer expects) and, from a trained
# model, stand upright (Head above Pelvis along Blender's Z on every frame). The trained model is
# $FLAME_BVH_MODEL, else the assembled demo model (models/demo/flame_demo.safetensors, which
# tools/try.sh makes); without either, the tiny random-weight fixture checks the 1 mm match only.
# Root bone and frame rate (Blender only; the PyPI fallback skips them): root_separate.bvh, a
# smpl24_6d clip resampled to 30 fps with its root motion on a `root` bone, written by libflame's
# test code (the ignored test motion::bvh::tests::write_blender_check_files), and, once the CLI
# has --root-motion, cli_root.bvh from `flame generate --fps 30 --root-motion separate`: Blender
# must put the root bone on the ground under the pelvis, every joint where the same clip with
# its root motion kept has it (1 mm), and import one keyframe per frame at 30 fps
# (blender_bvh_check.py --root-bone --fps 30).
#
#   bash tools/bvh_roundtrip.sh            # Blender if it runs, else the `bvh` PyPI fallback
#   FLAME_BVH_CHECKER=blender bash tools/bvh_roundtrip.sh   # require Blender (CI)
#   FLAME_BVH_CHECKER=pypi bash tools/bvh_roundtrip.sh      # force the fallback
#
# Blender comes from Debian: apt-get update && apt-get install -y blender (3.4.1 on bookworm).
set -euo pipefail
cd "$(dirname "$0")/.."

out="${FLAME_BVH_OUT:-$(mktemp -d)}"
mkdir -p "$out"
model="${FLAME_BVH_MODEL:-}"
[[ -z "$model" && -f models/demo/flame_demo.safetensors ]] && model=models/demo/flame_demo.safetensors
cli_upright=--upright
if [[ -z "$model" ]]; then
    echo "bvh_roundtrip: no trained model (demo model not assembled): cli_walk is not checked for standing upright" >&2
    cli_upright=
elif [[ "$model" != /* ]]; then
    model="$PWD/$model"
fi
FLAME_BVH_OUT="$out" FLAME_BVH_MODEL="$model" \
    cargo test --quiet --test motion_bvh -- --ignored write_blender_check_files >/dev/null
FLAME_BVH_OUT="$out" cargo test --quiet --lib motion::bvh::tests::write_blender_check_files \
    -- --ignored >/dev/null
rooted=(root_separate)
cargo build --quiet --bin flame
flame=target/debug/flame
if "$flame" generate --help 2>&1 | grep -q -- --root-motion; then
    cli_model="${model:-tests/fixtures/flame_tiny.safetensors}"
    common=(--model "$cli_model" --prompt "a person walks forward." --frames 60 --seed 1 --fps 30)
    "$flame" generate "${common[@]}" --root-motion separate --out "$out/cli_root.bvh" >/dev/null
    "$flame" generate "${common[@]}" --root-motion keep --convention blender \
        --out "$out/cli_root_keep.json" --positions "$out/cli_root_blender.npy" >/dev/null
    rooted+=(cli_root)
else
    echo "bvh_roundtrip: flame generate has no --root-motion yet: cli_root.bvh not checked" >&2
fi

checker="${FLAME_BVH_CHECKER:-auto}"
if [[ "$checker" == auto ]]; then
    if command -v blender >/dev/null && blender -b --factory-startup --version >/dev/null 2>&1; then
        checker=blender
    else
        echo "bvh_roundtrip: Blender does not run here; using the bvh PyPI fallback" >&2
        checker=pypi
    fi
fi

for motion in smpl_walk hml_walk cli_walk; do
    bvh="$out/$motion.bvh"
    expected="$out/${motion}_blender.npy"
    # hml_walk is synthetic features posed by HumanML3D's twist-free IK: not a standing body.
    case "$motion" in
        smpl_walk) upright=--upright ;;
        hml_walk) upright= ;;
        cli_walk) upright="$cli_upright" ;;
    esac
    case "$checker" in
        blender)
            # Keep only the script's verdict from Blender's chatter; pipefail keeps its exit code.
            blender -b --factory-startup --python-exit-code 2 --python tools/blender_bvh_check.py \
                -- "$bvh" "$expected" $upright 2>&1 | grep -E '^(blender [0-9]|import failed|Traceback|.*Error)'
            ;;
        pypi)
            python3 -c 'import bvh' 2>/dev/null ||
                python3 -m pip install --quiet --disable-pip-version-check bvh==0.3
            python3 tools/bvh_pypi_check.py "$bvh" "$expected" $upright
            ;;
        *)
            echo "bvh_roundtrip: FLAME_BVH_CHECKER must be auto, blender or pypi" >&2
            exit 2
            ;;
    esac
done
if [[ "$checker" == blender ]]; then
    for motion in "${rooted[@]}"; do
        blender -b --factory-startup --python-exit-code 2 --python tools/blender_bvh_check.py \
            -- "$out/$motion.bvh" "$out/${motion}_blender.npy" --root-bone --fps 30 2>&1 |
            grep -E '^(blender [0-9]|import failed|the |Traceback|.*Error)'
    done
else
    echo "bvh_roundtrip: the root-bone files (${rooted[*]}) need Blender: not checked" >&2
fi
echo "bvh_roundtrip: ok ($checker, files in $out)"
