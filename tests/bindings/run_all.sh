#!/usr/bin/env bash
# Every language binding's tests (Python, C#/Mono, the Unreal plugin's C++) against one build of
# libflame, ending with one line that adds up their counts. Exits non-zero when any suite
# failed or could not run.
#
# Needs what tools/install_test_deps.sh installs. Environment as for the run_*.sh scripts.
set -uo pipefail
cd "$(dirname "$0")/../.."
ROOT="$PWD"

profile="${CARGO_PROFILE:-debug}"
if [ -z "${FLAME_LIBRARY:-}" ]; then
    if [ "$profile" = release ]; then cargo build --release --quiet; else cargo build --quiet; fi || exit 1
    export FLAME_LIBRARY="$ROOT/target/$profile/libflame.so"
    export FLAME_CLI="$ROOT/target/$profile/flame"
fi

logs="$(mktemp -d)"
trap 'rm -rf "$logs"' EXIT
status=0 passed=0 failed=0
for suite in python csharp unreal; do
    echo "== bindings: $suite"
    start=$SECONDS
    bash "tests/bindings/run_$suite.sh" 2>&1 | tee "$logs/$suite.log"
    rc=${PIPESTATUS[0]}
    # The suite's own closing line: "N passed, N failed" (pytest: "N passed, N failed, ...").
    line="$(grep -E '[0-9]+ (passed|failed)' "$logs/$suite.log" | tail -1)"
    p="$(grep -oE '[0-9]+ passed' <<<"$line" | awk '{ s += $1 } END { print s + 0 }')"
    f="$(grep -oE '[0-9]+ (failed|errors?)' <<<"$line" | awk '{ s += $1 } END { print s + 0 }')"
    if [ "$rc" -ne 0 ]; then
        status=1
        [ "$f" -eq 0 ] && f=1   # crashed or could not run
    fi
    passed=$((passed + p))
    failed=$((failed + f))
    echo "== bindings: $suite: exit $rc, $p passed, $f failed, $((SECONDS - start)) s"
done
echo "bindings: $passed passed, $failed failed"
exit "$status"
