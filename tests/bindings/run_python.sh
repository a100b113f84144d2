#!/usr/bin/env bash
# The Python bindings' tests, run against the package as a user installs it: a fresh virtual
# environment (python3 -m venv) gets pytest and pygltflib (the glTF reader test_gltf.py checks
# Session.write_gltf with) from PyPI and the libflame wheel built from
# bindings/python by pip (an isolated build: setuptools from PyPI, the library from cargo; numpy
# from PyPI as the wheel's dependency). Then, from a folder outside the checkout and with
# FLAME_LIBRARY unset, `import flame` must find the library inside the installed wheel, and
# pytest runs tests/bindings/python against it. Nothing is taken from the machine's Python but
# the interpreter and its venv module.
#
# Needs python3 with the venv module (Debian: python3-venv; tools/install_test_deps.sh installs
# it), cargo and access to PyPI. Environment:
#   FLAME_LIBRARY, FLAME_CLI   use these instead of building (both or neither). A library
#                              other than this checkout's target/<profile>/libflame.so is packed
#                              into the wheel as it is; this checkout's own is built by cargo
#                              inside the wheel build (fresh: no rebuild) and must equal it.
#   CARGO_PROFILE              debug (default) or release: what is built and packed
#   FLAME_PYTHON               the interpreter that makes the venv (default python3)
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT="$PWD"

profile="${CARGO_PROFILE:-debug}"
if [ -z "${FLAME_LIBRARY:-}" ]; then
    if [ "$profile" = release ]; then cargo build --release --quiet; else cargo build --quiet; fi
    FLAME_LIBRARY="$ROOT/target/$profile/libflame.so"
    FLAME_CLI="$ROOT/target/$profile/flame"
fi
export FLAME_CLI
own="$ROOT/target/$profile/libflame.so"
wheel_env=(FLAME_CARGO_PROFILE="$profile")
if [ ! "$FLAME_LIBRARY" -ef "$own" ]; then
    wheel_env=(FLAME_WHEEL_LIBRARY="$FLAME_LIBRARY")
fi

python="${FLAME_PYTHON:-python3}"
"$python" -c 'import venv, ensurepip' 2>/dev/null || {
    echo "run_python.sh: $python has no venv module (Debian: apt-get install python3-venv;" \
        "or bash tools/install_test_deps.sh)" >&2
    exit 1
}

scratch="$(mktemp -d)"
trap 'rm -rf "$scratch"' EXIT
fail() { echo "run_python.sh: $*" >&2; exit 1; }
quiet_pip() { "$venv/bin/python" -m pip --disable-pip-version-check "$@" 2>&1 | grep -v "as the 'root' user" || true; }

venv="$scratch/venv"
"$python" -m venv "$venv" || fail "python3 -m venv failed"
py="$venv/bin/python"

# The wheel, as `pip install bindings/python` builds it (the same build, kept as a file so its
# tag and contents can be checked).
echo "run_python.sh: building the wheel (pip wheel bindings/python)"
env "${wheel_env[@]}" "$py" -m pip wheel --quiet --disable-pip-version-check --no-deps \
    --wheel-dir "$scratch/dist" "$ROOT/bindings/python" >"$scratch/wheel.log" 2>&1 ||
    { cat "$scratch/wheel.log" >&2; fail "building the wheel failed"; }
wheels=("$scratch"/dist/libflame-*.whl)
[ -f "${wheels[0]}" ] || fail "pip wheel wrote no libflame wheel"
whl="${wheels[0]}"
case "$(basename "$whl")" in
    *-py3-none-any.whl) fail "$(basename "$whl") is not a platform wheel" ;;
esac
echo "run_python.sh: $(basename "$whl")"

# Test-only requirements, pinned where a test depends on a reader's behaviour; Ray for
# test_batch.py's run of bindings/python/examples/ray_batch.py on a local instance (about 25 s
# to install on a fresh venv from PyPI, less from pip's cache).
quiet_pip install --quiet "$whl" pytest pygltflib==1.16.5 ray==2.60.0
[ -x "$venv/bin/pytest" ] || fail "pip install of the wheel and pytest failed"
"$py" -c 'import pygltflib' 2>/dev/null || fail "pip install of pygltflib failed"
"$py" -c 'import ray' 2>/dev/null || fail "pip install of ray failed"

# Outside the checkout, with no FLAME_LIBRARY: the installed package and its own library.
site="$(cd /tmp && env -u FLAME_LIBRARY -u PYTHONPATH "$py" -c \
    'import flame; print(flame.__file__); print(flame.library_path()); print(flame.version())')" ||
    fail "import flame from /tmp failed"
echo "$site" | sed 's/^/run_python.sh: /'
init="$(sed -n 1p <<<"$site")"
lib="$(sed -n 2p <<<"$site")"
case "$init" in "$venv"/*) ;; *) fail "flame was imported from $init, not the venv" ;; esac
[ "$lib" = "$(dirname "$init")/libflame.so" ] || fail "flame loads $lib, not its bundled library"
# The wheel ships the library without debug info (setup.py strips it when objcopy exists).
want="$FLAME_LIBRARY"
if command -v objcopy >/dev/null && [ "${FLAME_STRIP:-1}" != 0 ]; then
    want="$scratch/libflame.stripped.so"
    objcopy --strip-debug "$FLAME_LIBRARY" "$want"
fi
cmp -s "$lib" "$want" || fail "the wheel's library differs from $FLAME_LIBRARY (stripped of debug info)"
echo "run_python.sh: packed library $(wc -c <"$lib") bytes (built: $(wc -c <"$FLAME_LIBRARY"))"

cd "$scratch"  # so `import flame` can only mean the installed copy
env -u FLAME_LIBRARY -u PYTHONPATH FLAME_TEST_WHEEL=1 \
    "$py" -m pytest -q -p no:cacheprovider "$ROOT/tests/bindings/python" "$@"
