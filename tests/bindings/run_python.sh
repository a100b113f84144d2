#!/usr/bin/env bash
# The Python bindings' tests: builds libflame and the CLI (unless FLAME_LIBRARY and FLAME_CLI are
# given), pip-installs bindings/python into a scratch directory (so the packaging is tested too)
# and runs tests/bindings/python with pytest against that installed copy.
#
# Needs python3 with numpy and pytest (tools/install_test_deps.sh installs them). Environment:
#   FLAME_LIBRARY, FLAME_CLI   use these instead of building (both or neither)
#   CARGO_PROFILE              debug (default) or release
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT="$PWD"

profile="${CARGO_PROFILE:-debug}"
if [ -z "${FLAME_LIBRARY:-}" ]; then
    if [ "$profile" = release ]; then cargo build --release --quiet; else cargo build --quiet; fi
    export FLAME_LIBRARY="$ROOT/target/$profile/libflame.so"
    export FLAME_CLI="$ROOT/target/$profile/flame"
fi

python3 -c 'import numpy, pytest' 2>/dev/null || {
    echo "run_python.sh: numpy and pytest are needed: bash tools/install_test_deps.sh" >&2
    exit 1
}

scratch="$(mktemp -d)"
trap 'rm -rf "$scratch"' EXIT
# pip builds in the source tree: build from a copy so the checkout stays clean.
cp -r bindings/python "$scratch/src"
# With setuptools at hand, build without fetching it from PyPI into an isolated environment.
isolation=()
python3 -c 'import setuptools' 2>/dev/null && isolation=(--no-build-isolation)
python3 -m pip install --quiet --disable-pip-version-check --no-deps "${isolation[@]}" \
    --target "$scratch/site" "$scratch/src" 2>&1 | grep -v "as the 'root' user" || true
[ -f "$scratch/site/flame/__init__.py" ] || { echo "run_python.sh: pip install failed" >&2; exit 1; }

cd "$scratch"  # so `import flame` can only mean the installed copy
PYTHONPATH="$scratch/site" python3 -m pytest -q -p no:cacheprovider "$ROOT/tests/bindings/python" "$@"
