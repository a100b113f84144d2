#!/usr/bin/env bash
# libflame's VRM Animation (.vrma) and glTF hand-back checked by real consumers:
#   1. libflame's own test code (the ignored test write_vrma_check_files in
#      tests/retarget_files.rs) writes a synthetic smpl24_6d clip as motion.vrma
#      (retarget::vrma::to_glb), the normalized humanoid rotations libflame's retarget of the
#      same clip onto tests/fixtures/rigs/avatar.vrm gives (expected.json), and avatar.vrm
#      handed back with the clip (retarget::gltf_out::write, avatar_animated.vrm);
#   2. three-vrm (npm packages three, @pixiv/three-vrm, @pixiv/three-vrm-animation, pinned)
#      loads the avatar and the .vrma, plays the clip and its normalized bone rotations must
#      equal expected.json within 1e-4 (tools/vrma_three_check.mjs);
#   3. the Khronos glTF-Validator must report 0 errors and 0 warnings on motion.vrma and
#      avatar_animated.vrm (tools/gltf_validate.mjs).
# Exits nonzero on any failure.
#
#   bash tools/vrma_check.sh              # files in a temporary folder
#   FLAME_RETARGET_OUT=dir bash tools/vrma_check.sh
#
# Needs node and npm (the packages are installed into target/node, beside the validator
# tools/gltf_check.sh installs). avatar.vrm is made by tools/make_vrm_avatar.py (committed).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD

node_dir=$root/target/node
packages=(gltf-validator@2.0.0-dev.3.10 three@0.187.0 @pixiv/three-vrm@3.5.5
    @pixiv/three-vrm-animation@3.5.5)
have() { # package@version installed in target/node?
    local name=${1%@*} version=${1##*@}
    grep -q "\"version\": \"$version\"" "$node_dir/node_modules/$name/package.json" 2>/dev/null
}
missing=()
for p in "${packages[@]}"; do have "$p" || missing+=("$p"); done
if [[ ${#missing[@]} -gt 0 ]]; then
    echo "vrma_check: npm install ${missing[*]} into target/node"
    mkdir -p "$node_dir"
    npm install --silent --no-audit --no-fund --prefix "$node_dir" "${packages[@]}" >/dev/null
fi

out="${FLAME_RETARGET_OUT:-$(mktemp -d)}"
mkdir -p "$out"
out=$(cd "$out" && pwd)
FLAME_RETARGET_OUT="$out" cargo test --quiet --test retarget_files write_vrma_check_files \
    -- --ignored >/dev/null

THREE_VRM_DIR=$node_dir node tools/vrma_three_check.mjs tests/fixtures/rigs/avatar.vrm \
    "$out/motion.vrma" "$out/expected.json"
GLTF_VALIDATOR_DIR=$node_dir node tools/gltf_validate.mjs "$out/motion.vrma" \
    "$out/avatar_animated.vrm"
echo "vrma_check: ok (three-vrm plays motion.vrma as libflame retargets onto avatar.vrm; 2 files validated; files in $out)"
