#!/usr/bin/env bash
# The project's checks, as the README gives them: formatting, lints, every test.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo fmt --check
cargo clippy --all-targets -- -D warnings
cargo test
