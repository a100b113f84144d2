#!/usr/bin/env bash
# The Unreal plugin's C++ (bindings/unreal/Flame), compiled with g++ against stand-ins for the
# engine's headers (tests/bindings/unreal/ue_stubs) and run against the real libflame, with
# AddressSanitizer and UndefinedBehaviorSanitizer: test_component (UFlameMotionComponent) and
# test_stream_component (UFlameStreamComponent), then one line adding up their counts. This
# checks the plugin's logic and its use of flame.h; it is no substitute for building it in
# Unreal (Build.cs and the UCLASS macros are not exercised).
#
# Needs g++ (tools/install_test_deps.sh installs it). Environment:
#   FLAME_LIBRARY, FLAME_CLI   use these instead of building (both or neither)
#   CARGO_PROFILE              debug (default) or release
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT="$PWD"

command -v g++ >/dev/null || { echo "run_unreal.sh: g++ is needed: bash tools/install_test_deps.sh" >&2; exit 1; }

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
# A latent model (MoLA): the decoder decides the frames of what the component publishes.
latent_model="$ROOT/tests/fixtures/mola_tiny.safetensors"
"$FLAME_CLI" generate --model "$latent_model" --prompt "a person walks forward and waves." \
    --frames 60 --steps 4 --sampler ddim --seed 3 --threads 1 --out "$work/latent_reference.npy" >/dev/null 2>&1

# The engine headers the plugin includes, each standing for ue_stub.h.
stubs="$work/include"
for h in CoreMinimal.h Components/ActorComponent.h FlameMotionComponent.generated.h \
         FlameStreamComponent.generated.h HAL/ThreadSafeCounter.h HAL/PlatformProcess.h \
         HAL/CriticalSection.h \
         Modules/ModuleInterface.h Modules/ModuleManager.h Interfaces/IPluginManager.h \
         Misc/Paths.h Misc/ScopeLock.h Async/Async.h \
         Components/PoseableMeshComponent.h Engine/SkinnedAsset.h ReferenceSkeleton.h; do
    mkdir -p "$stubs/$(dirname "$h")"
    echo "#include \"$ROOT/tests/bindings/unreal/ue_stubs/ue_stub.h\"" >"$stubs/$h"
done

cp "$FLAME_LIBRARY" "$work/libflame.so"
plugin=bindings/unreal/Flame/Source/Flame
sources=("$plugin/Private/FlameModule.cpp" "$plugin/Private/FlameMotionComponent.cpp"
         "$plugin/Private/FlameStreamComponent.cpp")
for test in test_component test_stream_component; do
    g++ -std=c++17 -g -O1 -Wall -Wextra -Werror -fsanitize=address,undefined -fno-sanitize-recover=undefined \
        -I"$stubs" -I"$plugin/Public" -I"$plugin/Private" -Iinclude \
        "${sources[@]}" "tests/bindings/unreal/$test.cpp" \
        -L"$work" -lflame -lpthread -o "$work/$test"
done

# Both run even when the first fails; the last line adds up their "N passed, N failed".
status=0
LD_LIBRARY_PATH="$work" "$work/test_component" "$model" "$work/reference.npy" "$latent_model" \
    "$work/latent_reference.npy" 2>&1 | tee "$work/component.log" || status=1
LD_LIBRARY_PATH="$work" "$work/test_stream_component" "$ROOT/tests/fixtures" 2>&1 |
    tee "$work/stream_component.log" || status=1
passed=0 failed=0
for log in component stream_component; do
    line="$(grep -E '^[0-9]+ passed, [0-9]+ failed$' "$work/$log.log" | tail -n 1 || true)"
    if [ -z "$line" ]; then
        failed=$((failed + 1)) # crashed before its summary
        continue
    fi
    passed=$((passed + ${line%% passed*}))
    f="${line#*passed, }"
    failed=$((failed + ${f%% failed*}))
done
[ "$failed" -gt 0 ] && status=1
echo "$passed passed, $failed failed"
exit "$status"
