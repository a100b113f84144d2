#!/usr/bin/env bash
# Retargeting checked by real consumers: the demo model's clips carried onto characters unlike
# libflame's skeleton and unlike each other, then read back by Blender and the Khronos
# glTF-Validator.
#
# Rigs: a control first, SMPL-24's own rest skeleton as a glTF rig (tools/make_test_rigs.py
# --control; a retarget has nothing to change on it, so every check must pass: a failure there
# is the checker's); the committed fixtures (tests/fixtures/rigs/: mixamo.glb, apose.glb,
# child.glb, made by tools/make_test_rigs.py; avatar.vrm when present); and a Rigify character
# generated now by Blender (tools/blender_rigify_rig.py: deform bones only, as game pipelines
# export it).
# For each rig and two prompts (walking; walking and waving), 120 frames, seed 7:
#   flame generate --rig RIG --out anim.glb --positions src.npy --rig-positions rig.npy
#   flame generate --rig RIG --out anim.bvh --rig-positions rig2.npy   (must equal rig.npy)
# (a .vrm rig gets anim.vrm, its own container), then
#   - the glTF-Validator (npm gltf-validator, pinned, in target/node; tools/gltf_validate.mjs)
#     must report 0 errors and 0 warnings on every written .glb/.gltf/.vrm;
#   - Blender imports anim.glb and anim.bvh and tools/blender_retarget_check.py checks, every
#     frame: (i) bone heads = --rig-positions within 1 mm; (ii) mapped bone directions against
#     the source's (arms and spine/head <= 2 deg median, <= 5 max; legs <= 2 median, <= 10
#     max); (iii) the rig's foot-skating ratio no higher than the source's; (iv) planted feet
#     within 5 mm of the source's. It prints its numbers per rig; every check fails the run.
# Then tools/vrma_check.sh, if it exists.
#
#   bash tools/retarget_check.sh            # files in a temporary folder
#   FLAME_RETARGET_OUT=dir bash tools/retarget_check.sh
#
# Needs the demo model (bash tools/try.sh), node and npm, Blender 3.4+ and Debian's
# python3-numpy (tools/install_test_deps.sh), and for the control a Python with NumPy and
# pygltflib (PYTHON; default target/test-venv/bin/python). Exits non-zero when any check fails; every rig is
# still checked and reported first.
set -uo pipefail
cd "$(dirname "$0")/.."
root=$PWD
die() { echo "retarget_check: $*" >&2; exit 2; }

model=models/demo/flame_demo.safetensors
[[ -f $model ]] || die "no demo model: run 'bash tools/try.sh' once (it assembles $model)"
command -v blender >/dev/null || die "no blender on PATH (tools/install_test_deps.sh)"

validator_version=2.0.0-dev.3.10
node_dir=$root/target/node
if [[ ! -f $node_dir/node_modules/gltf-validator/package.json ]] ||
    ! grep -q "\"version\": \"$validator_version\"" "$node_dir/node_modules/gltf-validator/package.json"; then
    echo "retarget_check: npm install gltf-validator@$validator_version into target/node"
    mkdir -p "$node_dir"
    npm install --silent --no-audit --no-fund --prefix "$node_dir" "gltf-validator@$validator_version" >/dev/null ||
        die "npm install gltf-validator failed"
fi

out="${FLAME_RETARGET_OUT:-$(mktemp -d)}"
mkdir -p "$out"
cargo build --quiet --bin flame || die "cargo build failed"
flame=$root/target/debug/flame

failed=()
blender_run() {
    # Keep the scripts' own lines from Blender's chatter; the exit code is the script's.
    local log=$1
    shift
    blender -b --factory-startup --python-exit-code 2 --python "$@" >"$log" 2>&1
    local rc=$?
    grep -E "^(rigify|[a-z_]+ \(|[a-z_]+: |Traceback|  File|[A-Za-z]*Error)" "$log"
    return $rc
}

rigs=()
python="${PYTHON:-$root/target/test-venv/bin/python}"
if "$python" tools/make_test_rigs.py --control "$out" >"$out/control.log" 2>&1; then
    rigs+=("$out/smpl.glb")
else
    echo "retarget_check: no control rig ($python: $(tail -1 "$out/control.log"))"
    failed+=("control rig")
fi
rigs+=(tests/fixtures/rigs/mixamo.glb tests/fixtures/rigs/apose.glb tests/fixtures/rigs/child.glb)
if blender_run "$out/rigify.log" tools/blender_rigify_rig.py -- "$out/rigify.glb"; then
    rigs+=("$out/rigify.glb")
else
    failed+=("rigify export")
fi
if [[ -f tests/fixtures/rigs/avatar.vrm ]]; then
    rigs+=(tests/fixtures/rigs/avatar.vrm)
else
    echo "retarget_check: no tests/fixtures/rigs/avatar.vrm: VRM not checked" >&2
fi

prompts=("a person walks forward" "a person walks forward and waves")
tags=(walk wave)
written=()
[[ -f $out/smpl.glb ]] && written+=("$out/smpl.glb")
[[ -f $out/rigify.glb ]] && written+=("$out/rigify.glb")
cases=()
for rig in "${rigs[@]}"; do
    base=$(basename "${rig%.*}")
    ext=glb
    [[ $rig == *.vrm ]] && ext=vrm
    for i in "${!prompts[@]}"; do
        o="$out/${base}_${tags[i]}"
        common=(--model "$model" --prompt "${prompts[i]}" --frames 120 --seed 7 --rig "$rig")
        if ! "$flame" generate "${common[@]}" --out "$o.$ext" --positions "$o.src.npy" \
            --rig-positions "$o.rig.npy" >"$o.log" 2>&1; then
            echo "${base} (${tags[i]}): flame generate failed: $(grep -v '^step' "$o.log" | tail -1)"
            failed+=("${base}_${tags[i]} generate")
            continue
        fi
        if ! "$flame" generate "${common[@]}" --out "$o.bvh" --rig-positions "$o.rig2.npy" \
            >>"$o.log" 2>&1; then
            echo "${base} (${tags[i]}): flame generate --out .bvh failed: $(tail -1 "$o.log")"
            failed+=("${base}_${tags[i]} bvh")
            continue
        fi
        # The BVH is checked against the first run's positions: the runs must agree.
        if ! cmp -s "$o.rig.npy" "$o.rig2.npy"; then
            echo "${base} (${tags[i]}): the .bvh run's --rig-positions differ from the .$ext run's"
            failed+=("${base}_${tags[i]} determinism")
            continue
        fi
        written+=("$o.$ext")
        cases+=("$rig|$o|$ext|${base}_${tags[i]}")
    done
done

GLTF_VALIDATOR_DIR=$node_dir node tools/gltf_validate.mjs "${written[@]}" >"$out/validator.log" 2>&1 ||
    failed+=("glTF-Validator")
# One line per file, then any issue lines.
grep -E "errors|^\s+\[" "$out/validator.log" | sed "s|$out/||"

for c in "${cases[@]}"; do
    IFS='|' read -r rig o ext name <<<"$c"
    blender_run "$o.check.log" tools/blender_retarget_check.py -- "$name" "$rig" "$o.$ext" \
        "$o.rig.npy" "$o.src.npy" "$o.bvh" || failed+=("$name")
done

if [[ -f tools/vrma_check.sh ]]; then
    bash tools/vrma_check.sh || failed+=("vrma_check.sh")
else
    echo "retarget_check: no tools/vrma_check.sh yet: VRMA not checked" >&2
fi

if ((${#failed[@]})); then
    echo "retarget_check: FAILED: ${failed[*]} (files in $out)"
    exit 1
fi
echo "retarget_check: ok (${#cases[@]} clips on ${#rigs[@]} rigs; files in $out)"
