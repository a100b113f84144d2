#!/usr/bin/env bash
# glTF export checked by real consumers. `flame generate --out x.glb` (and .gltf, and one
# `flame edit`) on every family's fixture model and, when it is assembled, the trained demo
# model; then:
#   - the Khronos glTF-Validator (npm package gltf-validator, run under Node.js) must report
#     0 errors and 0 warnings on every file (tools/gltf_validate.mjs);
#   - Blender's bundled glTF importer, headless, must import every file and its armature's
#     joint world positions on every frame must equal `--positions` (libflame's forward
#     kinematics, gltf convention) within 1 mm (tools/blender_gltf_check.py).
# Root bone and frame rate: libflame's own test code (the ignored test
# motion::gltf::tests::write_root_bone_check_files) writes a smpl24_6d and a humanml263 clip
# resampled to 30 fps with the root motion on a `root` bone, and the world positions the same clip
# with its root motion kept has; once the CLI has --root-motion, `flame generate --fps 30
# --root-motion separate` files of flame_tiny and mdm_tiny are checked the same way against a
# `--root-motion keep` run. Each must pass the validator, and Blender must put the root bone on
# the ground under the pelvis, the joints where the kept clip has them (1 mm), and import one
# keyframe per frame at 30 fps (blender_gltf_check.py --root-bone --fps 30).
# The pygltflib read-back against flame_session_read runs with the Python binding's tests.
#
#   bash tools/gltf_check.sh            # files in a temporary folder
#   FLAME_GLTF_OUT=dir bash tools/gltf_check.sh
#
# Needs node and npm (the validator is installed into target/node, pinned), Blender and
# Debian's python3-numpy (tools/install_test_deps.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD

validator_version=2.0.0-dev.3.10
node_dir=$root/target/node
if [[ ! -f $node_dir/node_modules/gltf-validator/package.json ]] ||
    ! grep -q "\"version\": \"$validator_version\"" "$node_dir/node_modules/gltf-validator/package.json"; then
    echo "gltf_check: npm install gltf-validator@$validator_version into target/node"
    mkdir -p "$node_dir"
    npm install --silent --no-audit --no-fund --prefix "$node_dir" "gltf-validator@$validator_version" >/dev/null
fi

out="${FLAME_GLTF_OUT:-$(mktemp -d)}"
mkdir -p "$out"
cargo build --quiet --bin flame
flame=$root/target/debug/flame

prompt="a person walks forward and waves."
models=(flame_tiny mdm_tiny motionfm_tiny mld_tiny mola_tiny finemogen_tiny omg_tiny)
paths=()
for m in "${models[@]}"; do paths+=("tests/fixtures/$m.safetensors"); done
if [[ -f models/demo/flame_demo.safetensors ]]; then
    models+=(flame_demo)
    paths+=(models/demo/flame_demo.safetensors)
else
    echo "gltf_check: the demo model is not assembled (bash tools/try.sh): fixtures only" >&2
fi

glbs=() all=()
for i in "${!models[@]}"; do
    m=${models[i]}
    "$flame" generate --model "${paths[i]}" --prompt "$prompt" --frames 40 --steps 4 --seed 7 \
        --out "$out/$m.glb" --positions "$out/$m.npy" >/dev/null 2>"$out/$m.log"
    "$flame" generate --model "${paths[i]}" --prompt "$prompt" --frames 40 --steps 4 --seed 7 \
        --out "$out/$m.gltf" >/dev/null 2>>"$out/$m.log"
    glbs+=("$out/$m.glb")
    all+=("$out/$m.glb" "$out/$m.gltf")
done
# An edit's output goes through the same writer.
"$flame" generate --model tests/fixtures/flame_tiny.safetensors --prompt "$prompt" --frames 40 \
    --steps 4 --out "$out/ref.npy" >/dev/null 2>&1
"$flame" edit --model tests/fixtures/flame_tiny.safetensors --prompt "a person jumps." \
    --reference "$out/ref.npy" --task inbetween --steps 4 --out "$out/edit.glb" \
    --positions "$out/edit.npy" >/dev/null 2>"$out/edit.log"
glbs+=("$out/edit.glb")
all+=("$out/edit.glb")

# Root bone and 30 fps (see the header): Rust test code, then the CLI if it has the flags.
FLAME_GLTF_OUT="$out" cargo test --quiet --lib motion::gltf::tests::write_root_bone_check_files \
    -- --ignored >/dev/null
rooted=("$out/root_separate_smpl.glb" "$out/root_separate_hml.glb")
if "$flame" generate --help 2>&1 | grep -q -- --root-motion; then
    for m in flame_tiny mdm_tiny; do
        common=(--model "tests/fixtures/$m.safetensors" --prompt "$prompt" --frames 40 --steps 4
            --seed 7 --fps 30)
        "$flame" generate "${common[@]}" --root-motion separate --out "$out/${m}_root_separate.glb" \
            >/dev/null 2>>"$out/$m.log"
        "$flame" generate "${common[@]}" --root-motion keep --out "$out/${m}_root_keep.glb" \
            --positions "$out/${m}_root_separate.npy" >/dev/null 2>>"$out/$m.log"
        rooted+=("$out/${m}_root_separate.glb")
    done
else
    echo "gltf_check: flame generate has no --root-motion yet: root-bone files from the CLI not checked" >&2
fi
all+=("${rooted[@]}")

GLTF_VALIDATOR_DIR=$node_dir node tools/gltf_validate.mjs "${all[@]}"

for f in "${glbs[@]}" "$out/flame_tiny.gltf" "$out/mdm_tiny.gltf"; do
    base=${f%.*}
    # Keep only the script's verdict from Blender's chatter; pipefail keeps its exit code.
    blender -b --factory-startup --python-exit-code 2 --python tools/blender_gltf_check.py \
        -- "$f" "$base.npy" 2>&1 | grep -E '^(blender [0-9]|import failed|the |Traceback|.*Error)'
done
for f in "${rooted[@]}"; do
    blender -b --factory-startup --python-exit-code 2 --python tools/blender_gltf_check.py \
        -- "$f" "${f%.*}.npy" --root-bone --fps 30 2>&1 |
        grep -E '^(blender [0-9]|import failed|the |Traceback|.*Error)'
done
echo "gltf_check: ok (${#all[@]} files validated, ${#glbs[@]} + 2 + ${#rooted[@]} imported by Blender; files in $out)"
