#!/usr/bin/env bash
# The project's test command (README "Build and test"): formatting, lints, the Rust tests, the
# C ABI tests (shared and static library, C++ wrapper, packaging; valgrind when CI=true or
# FLAME_VALGRIND=1), the language bindings' tests, and the BVH round trip through Blender.
# Needs what tools/install_test_deps.sh installs.
set -euo pipefail
cd "$(dirname "$0")/.."

echo "== cargo fmt / clippy"
cargo fmt --check
cargo clippy --all-targets -- -D warnings

echo "== cargo test"
cargo test

echo "== C ABI, C++ wrapper, packaging"
bash tests/c/run.sh

echo "== language bindings"
bash tests/bindings/run_all.sh

echo "== BVH import by a real consumer"
bash tools/bvh_roundtrip.sh
