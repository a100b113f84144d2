#!/usr/bin/env bash
# The C# bindings' tests under Mono: builds libflame and the CLI (unless FLAME_LIBRARY and
# FLAME_CLI are given), writes the CLI's reference features, compiles bindings/csharp/Flame.cs
# with tests/bindings/csharp/FlameTest.cs using mcs and runs the result with mono.
#
# Needs mcs and mono (Debian: mono-mcs, mono-runtime; tools/install_test_deps.sh installs them).
# Environment:
#   FLAME_LIBRARY, FLAME_CLI   use these instead of building (both or neither)
#   CARGO_PROFILE              debug (default) or release
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT="$PWD"

for tool in mcs mono; do
    command -v "$tool" >/dev/null || {
        echo "run_csharp.sh: $tool is needed: bash tools/install_test_deps.sh" >&2
        exit 1
    }
done

profile="${CARGO_PROFILE:-debug}"
if [ -z "${FLAME_LIBRARY:-}" ]; then
    if [ "$profile" = release ]; then cargo build --release --quiet; else cargo build --quiet; fi
    FLAME_LIBRARY="$ROOT/target/$profile/libflame.so"
    FLAME_CLI="$ROOT/target/$profile/flame"
fi
model="$ROOT/tests/fixtures/flame_tiny.safetensors"

work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

"$FLAME_CLI" generate --model "$model" --prompt "a person walks forward and waves." \
    --frames 24 --steps 10 --sampler ddim --seed 3 --threads 1 --out "$work/reference.npy" >/dev/null 2>&1

mcs -debug -warnaserror -nologo -out:"$work/FlameTest.exe" \
    bindings/csharp/Flame.cs tests/bindings/csharp/FlameTest.cs
# The Unity example, against stand-ins for UnityEngine (UNITY_5_3_OR_NEWER as in the Editor).
mcs -debug -warnaserror -nologo -define:UNITY_5_3_OR_NEWER -out:"$work/FlameExampleTest.exe" \
    bindings/csharp/Flame.cs bindings/csharp/FlameExample.cs \
    tests/bindings/csharp/UnityStubs.cs tests/bindings/csharp/FlameExampleTest.cs

# DllImport("flame") resolves to libflame.so through the library search path: a copy under that
# name in the scratch directory, first on the path, so no other libflame is picked up.
cp "$FLAME_LIBRARY" "$work/libflame.so"
export LD_LIBRARY_PATH="$work${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"

status=0
mono --debug "$work/FlameTest.exe" "$model" "$work/reference.npy" "$FLAME_CLI" "$work" "$ROOT/include/flame.h" \
    | tee "$work/api.log" || status=1
mono --debug "$work/FlameExampleTest.exe" "$model" "$work/reference.npy" \
    | tee "$work/example.log" || status=1

# One closing line for both programs.
count() { grep -hoE '^[0-9]+ passed, [0-9]+ failed$' "$work"/*.log | awk -v f="$1" '{ s += $f } END { print s + 0 }'; }
passed="$(count 1)"
failed="$(count 3)"
[ "$passed" -gt 0 ] || status=1
echo "csharp: $passed passed, $failed failed"
exit "$status"
