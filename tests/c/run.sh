#!/usr/bin/env bash
# The C ABI tests, the C++ wrapper test and the packaging check, as one command:
#
#   bash tests/c/run.sh
#
# 1. cargo build (debug: target/debug/libflame.{so,a} and the flame CLI);
# 2. the CLI writes the reference features the tests must match bit for bit;
# 3. test_api, test_threads, test_hardening, test_targets and test_stages (C11), each linked
#    against the shared and the static library, test_cancel, test_stream, test_batch and
#    test_cleanup (C11, shared), test_robot (C11, shared; the GR1T2 URDF from tools/fetch_robots.sh),
#    test_cpp, test_cpp_gltf, test_cpp_stream and test_cpp_robot (C++17, shared; test_cpp_robot
#    with the GR1T2 URDF), all with -Wall -Wextra
#    -Werror, are built and run;
# 4. with valgrind (FLAME_VALGRIND=1, or CI=true and valgrind installed; FLAME_VALGRIND=0
#    skips) the shared builds run again under memcheck, on a smaller reference (8 frames,
#    2 steps) and with FLAME_TEST_QUICK=1;
# 5. packaging/install.sh installs a release build into a temporary prefix (libraries stripped
#    of debug info, which stays in libflame.so.debug), and CMake (find_package(flame)) and
#    pkg-config consumers are built against it and run (FLAME_PACKAGING=0 skips; needs cmake and
#    pkg-config: tools/install_test_deps.sh).
#
# Each test program ends with "N passed, N failed"; this script adds them up (a build error, a
# crash or a valgrind error counts as one failure), prints each step's time, and ends with the
# total "N passed, N failed" line. Exit status 0 only when nothing failed.
# Builds go to target/c-tests/. FLAME_STRICT=1 turns known ABI bugs into failures.
set -uo pipefail

ROOT="$(cd "$(dirname "$0")/../.." && pwd)"
cd "$ROOT" || exit 1
MODEL="$ROOT/tests/fixtures/flame_tiny.safetensors"
PROMPT="a person walks forward and waves."
LIB="$ROOT/target/debug"
OUT="$ROOT/target/c-tests"
WORK="$(mktemp -d)"
trap 'rm -rf "$WORK"' EXIT
mkdir -p "$OUT"

CFLAGS=(-std=c11 -Wall -Wextra -Werror -g -pthread -I"$ROOT/include")
CXXFLAGS=(-std=c++17 -Wall -Wextra -Werror -g -pthread -I"$ROOT/include" -I"$ROOT/bindings/cpp")
# shellcheck disable=SC2054  # the commas belong to the linker flag
SHARED_LIBS=(-L"$LIB" -lflame -Wl,-rpath,"$LIB" -lm)
# What the static library needs besides libc, from
#   cargo rustc --lib --crate-type staticlib -- --print native-static-libs
# which prints "-lgcc_s -lutil -lrt -lpthread -lm -ldl -lc" on Linux/glibc: gcc adds libgcc_s
# and libc itself, and glibc >= 2.34 keeps util and rt inside libc. (Asking rustc here would
# rebuild the library with different flags on every run; packaging/install.sh does ask it.)
STATIC_LIBS=("$LIB/libflame.a" -lpthread -ldl -lm)
# shellcheck disable=SC2054  # the comma belongs to the option
VALGRIND=(valgrind --error-exitcode=1 --leak-check=full --errors-for-leak-kinds=definite,indirect)

# Which reduced-precision weight types this CPU runs (test_api expects a load or a clear
# refusal): bf16-compute needs AVX512_BF16 on the AVX-512 kernel; int8 runs on AVX512_VNNI or
# AVX2 (with FMA and F16C, the AVX2 kernel's needs), on any kernel but the portable one.
cpu_has() { grep -qw "$1" /proc/cpuinfo 2>/dev/null; }
if cpu_has avx512_bf16 && cpu_has avx512f && [ "${FLAME_KERNEL:-avx512}" = avx512 ]; then
    export FLAME_TEST_CPU_BF16=1
else
    export FLAME_TEST_CPU_BF16=0
fi
if cpu_has avx2 && cpu_has fma && cpu_has f16c && [ "${FLAME_KERNEL:-avx512}" != portable ]; then
    export FLAME_TEST_CPU_INT8=1
else
    export FLAME_TEST_CPU_INT8=0
fi

PASSED=0
FAILED=0
START="$(date +%s.%N)"

now() { date +%s.%N; }
since() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }'; }

# report LABEL PASSED FAILED SECONDS [NOTE]: adds to the totals and prints one line.
report() {
    local label="$1" p="$2" f="$3" secs="$4" note="${5:-}"
    PASSED=$((PASSED + p))
    FAILED=$((FAILED + f))
    local mark="ok  "
    [ "$f" -gt 0 ] && mark="FAIL"
    printf '%s %-42s %5s s  %4d passed, %d failed%s\n' "$mark" "$label" "$secs" "$p" "$f" "$note"
}

# step LABEL LOG CMD...: one check that passes when CMD exits 0 (its output goes to LOG and
# is shown on failure).
step() {
    local label="$1" log="$2"
    shift 2
    local t0
    t0="$(now)"
    if "$@" >"$log" 2>&1; then
        report "$label" 1 0 "$(since "$t0")"
        return 0
    fi
    report "$label" 0 1 "$(since "$t0")"
    sed 's/^/    | /' "$log" | tail -n 40
    return 1
}

# run_test LABEL LOG CMD...: a test program; adds its "N passed, N failed" line. No such line,
# or a non-zero exit with no failure counted (a crash, a valgrind error), is one failure.
run_test() {
    local label="$1" log="$2"
    shift 2
    local t0 status p=0 f=0 line note=""
    t0="$(now)"
    "$@" >"$log" 2>&1
    status=$?
    line="$(grep -E '^[0-9]+ passed, [0-9]+ failed$' "$log" | tail -n 1)"
    if [ -n "$line" ]; then
        p="${line%% passed*}"
        f="${line#*passed, }"
        f="${f%% failed*}"
    fi
    if [ -z "$line" ] || { [ "$status" -ne 0 ] && [ "$f" -eq 0 ]; }; then
        f=$((f + 1))
        note="  (exit status $status)"
    fi
    local known
    known="$(grep -E '^known bugs: ' "$log" | head -n 1 | cut -d' ' -f3)"
    [ -n "$known" ] && note="$note  [$known known bugs]"
    report "$label" "$p" "$f" "$(since "$t0")" "$note"
    if [ "$f" -gt 0 ]; then
        local show='^(FAIL|     )|ERROR SUMMARY|definitely lost|indirectly lost|Invalid|uninit'
        grep -E "$show|panicked" "$log" | head -n 60 | sed 's/^/    | /'
        echo "    (full output: $log)"
    fi
}

finish() {
    echo "tests/c/run.sh: $(since "$START") s"
    echo "$PASSED passed, $FAILED failed"
    [ "$FAILED" -eq 0 ]
    exit $?
}

# ---- 1. build ------------------------------------------------------------------------------
if ! step "cargo build" "$OUT/cargo-build.log" cargo build; then
    finish
fi

# ---- 2. reference features from the CLI ----------------------------------------------------
# shellcheck disable=SC2317  # called through step
reference() { # NAME FRAMES STEPS
    "$LIB/flame" generate --model "$MODEL" --prompt "$PROMPT" --frames "$2" --steps "$3" \
        --sampler ddim --seed 3 --threads 1 --out "$OUT/$1.npy"
}
step "reference (CLI, 24 frames, 10 steps)" "$OUT/ref.log" reference ref 24 10 || finish
step "reference (CLI, 8 frames, 2 steps)" "$OUT/ref_quick.log" reference ref_quick 8 2 || finish
# The poses of a loop (test_cleanup's and test_cpp's loop sessions read the same).
loop_positions() {
    "$LIB/flame" generate --model "$MODEL" --prompt "$PROMPT" --frames 40 --steps 4 \
        --sampler ddim --seed 5 --threads 1 --loop --feet off --ground off \
        --positions "$OUT/loop_positions.npy" --out "$OUT/loop.json"
}
step "loop positions (CLI, 40 frames, --loop)" "$OUT/loop.log" loop_positions || finish
# Prompts per time stage on FineMoGen (test_stages), when its fixture is there.
FMG_MODEL="$ROOT/tests/fixtures/finemogen_tiny.safetensors"
STAGES_ARGS=("$ROOT/tests/fixtures")
# shellcheck disable=SC2317  # called through step
stages_reference() {
    "$LIB/flame" generate --model "$FMG_MODEL" --stage "a person walks forward@24" \
        --stage "a person jumps@31" --frames 55 --steps 4 --sampler ddim --seed 1 --threads 1 \
        --out "$OUT/stages_ref.npy"
}
if [ -f "$FMG_MODEL" ]; then
    step "reference (CLI, FineMoGen stages 24 + 31)" "$OUT/stages_ref.log" stages_reference &&
        STAGES_ARGS+=("$OUT/stages_ref.npy")
fi

# ---- 3. compile and run --------------------------------------------------------------------
BUILT=()
compile() { # NAME COMPILER FLAGS... -- SOURCE LIBS...
    local name="$1"
    shift
    if step "compile $name" "$OUT/$name.build.log" "$@" -o "$OUT/$name"; then
        BUILT+=("$name")
    fi
}
built() { [[ " ${BUILT[*]} " == *" $1 "* ]]; }

compile test_api_shared gcc "${CFLAGS[@]}" tests/c/test_api.c "${SHARED_LIBS[@]}"
compile test_api_static gcc "${CFLAGS[@]}" tests/c/test_api.c "${STATIC_LIBS[@]}"
compile test_threads_shared gcc "${CFLAGS[@]}" tests/c/test_threads.c "${SHARED_LIBS[@]}"
compile test_threads_static gcc "${CFLAGS[@]}" tests/c/test_threads.c "${STATIC_LIBS[@]}"
compile test_hardening_shared gcc "${CFLAGS[@]}" tests/c/test_hardening.c "${SHARED_LIBS[@]}"
compile test_hardening_static gcc "${CFLAGS[@]}" tests/c/test_hardening.c "${STATIC_LIBS[@]}"
compile test_targets_shared gcc "${CFLAGS[@]}" tests/c/test_targets.c "${SHARED_LIBS[@]}"
compile test_targets_static gcc "${CFLAGS[@]}" tests/c/test_targets.c "${STATIC_LIBS[@]}"
compile test_stages_shared gcc "${CFLAGS[@]}" tests/c/test_stages.c "${SHARED_LIBS[@]}"
compile test_stages_static gcc "${CFLAGS[@]}" tests/c/test_stages.c "${STATIC_LIBS[@]}"
compile test_cancel_shared gcc "${CFLAGS[@]}" tests/c/test_cancel.c "${SHARED_LIBS[@]}"
compile test_stream_shared gcc "${CFLAGS[@]}" tests/c/test_stream.c "${SHARED_LIBS[@]}"
compile test_batch_shared gcc "${CFLAGS[@]}" tests/c/test_batch.c "${SHARED_LIBS[@]}"
compile test_cleanup_shared gcc "${CFLAGS[@]}" tests/c/test_cleanup.c "${SHARED_LIBS[@]}"
compile test_retarget_shared gcc "${CFLAGS[@]}" tests/c/test_retarget.c "${SHARED_LIBS[@]}"
compile test_amass_shared gcc "${CFLAGS[@]}" tests/c/test_amass.c "${SHARED_LIBS[@]}"
compile test_robot_shared gcc "${CFLAGS[@]}" tests/c/test_robot.c "${SHARED_LIBS[@]}"
compile test_cpp_retarget_shared g++ "${CXXFLAGS[@]}" tests/c/test_cpp_retarget.cpp "${SHARED_LIBS[@]}"
compile test_cpp_shared g++ "${CXXFLAGS[@]}" tests/c/test_cpp.cpp "${SHARED_LIBS[@]}"
compile test_cpp_gltf_shared g++ "${CXXFLAGS[@]}" tests/c/test_cpp_gltf.cpp "${SHARED_LIBS[@]}"
compile test_cpp_stream_shared g++ "${CXXFLAGS[@]}" tests/c/test_cpp_stream.cpp "${SHARED_LIBS[@]}"
compile test_cpp_robot_shared g++ "${CXXFLAGS[@]}" tests/c/test_cpp_robot.cpp "${SHARED_LIBS[@]}"

API_ARGS=("$MODEL" "$OUT/ref.npy" "$WORK")
for kind in shared static; do
    built "test_api_$kind" && run_test "test_api ($kind)" "$OUT/test_api_$kind.log" \
        "$OUT/test_api_$kind" "${API_ARGS[@]}"
    built "test_threads_$kind" && run_test "test_threads ($kind)" "$OUT/test_threads_$kind.log" \
        "$OUT/test_threads_$kind" "$MODEL"
    built "test_hardening_$kind" && run_test "test_hardening ($kind)" \
        "$OUT/test_hardening_$kind.log" "$OUT/test_hardening_$kind" "$ROOT/tests/fixtures"
    built "test_targets_$kind" && run_test "test_targets ($kind)" \
        "$OUT/test_targets_$kind.log" "$OUT/test_targets_$kind" "$ROOT/tests/fixtures"
    built "test_stages_$kind" && run_test "test_stages ($kind)" \
        "$OUT/test_stages_$kind.log" "$OUT/test_stages_$kind" "${STAGES_ARGS[@]}"
done
built test_cancel_shared && run_test "test_cancel (shared)" "$OUT/test_cancel_shared.log" \
    "$OUT/test_cancel_shared" "$MODEL"
built test_stream_shared && run_test "test_stream (shared)" "$OUT/test_stream_shared.log" \
    "$OUT/test_stream_shared" "$ROOT/tests/fixtures"
mkdir -p "$WORK/batch"
built test_batch_shared && run_test "test_batch (shared)" "$OUT/test_batch_shared.log" \
    "$OUT/test_batch_shared" "$MODEL" "$WORK/batch"
built test_cleanup_shared && run_test "test_cleanup (shared)" "$OUT/test_cleanup_shared.log" \
    "$OUT/test_cleanup_shared" "$ROOT/tests/fixtures" "$OUT/loop_positions.npy"
built test_retarget_shared && run_test "test_retarget (shared)" \
    "$OUT/test_retarget_shared.log" "$OUT/test_retarget_shared" "$ROOT/tests/fixtures"
built test_amass_shared && run_test "test_amass (shared)" "$OUT/test_amass_shared.log" \
    "$OUT/test_amass_shared" "$ROOT/tests/fixtures"
# The real GR1T2 URDF (PyPI fourier-robot-descriptions), fetched once into target/robots.
[ -f "$ROOT/target/robots/gr1t2.urdf" ] || bash "$ROOT/tools/fetch_robots.sh" >/dev/null 2>&1
if [ -f "$ROOT/target/robots/gr1t2.urdf" ]; then
    built test_robot_shared && run_test "test_robot (shared)" "$OUT/test_robot_shared.log" \
        "$OUT/test_robot_shared" "$ROOT/tests/fixtures" "$ROOT/target/robots/gr1t2.urdf" \
        "$ROOT/robots/gr1t2.json"
    built test_cpp_robot_shared && run_test "test_cpp_robot (shared)" \
        "$OUT/test_cpp_robot_shared.log" "$OUT/test_cpp_robot_shared" "$ROOT/tests/fixtures" \
        "$ROOT/target/robots/gr1t2.urdf" "$ROOT/robots/gr1t2.json"
else
    echo "skip test_robot, test_cpp_robot: target/robots/gr1t2.urdf is missing and tools/fetch_robots.sh could not fetch it"
fi
built test_cpp_retarget_shared && run_test "test_cpp_retarget (shared)" \
    "$OUT/test_cpp_retarget_shared.log" "$OUT/test_cpp_retarget_shared" "$ROOT/tests/fixtures"
built test_cpp_shared && run_test "test_cpp (shared)" "$OUT/test_cpp_shared.log" \
    "$OUT/test_cpp_shared" "$MODEL" "$OUT/ref.npy" 10 "$OUT/loop_positions.npy"
built test_cpp_gltf_shared && run_test "test_cpp_gltf (shared)" "$OUT/test_cpp_gltf_shared.log" \
    "$OUT/test_cpp_gltf_shared" "$ROOT/tests/fixtures"
built test_cpp_stream_shared && run_test "test_cpp_stream (shared)" \
    "$OUT/test_cpp_stream_shared.log" "$OUT/test_cpp_stream_shared" "$ROOT/tests/fixtures"

# ---- 4. valgrind ---------------------------------------------------------------------------
# No suppressions: memcheck reports no error and no definite or indirect leak from libflame,
# Rust's runtime or glibc. What it lists as "possibly lost" (hashbrown tables whose pointer
# points past the allocation's start, crossbeam-epoch's global collector, thread stacks of
# worker threads still exiting) is not among the kinds that fail the run.
use_valgrind=0
case "${FLAME_VALGRIND:-}" in
    1) use_valgrind=1 ;;
    0) use_valgrind=0 ;;
    *) [ "${CI:-}" = "true" ] && command -v valgrind >/dev/null && use_valgrind=1 ;;
esac
if [ "$use_valgrind" = 1 ]; then
    if ! command -v valgrind >/dev/null; then
        report "valgrind" 0 1 0.0 "  (FLAME_VALGRIND=1 but valgrind is not installed)"
    else
        QUICK=("$OUT/ref_quick.npy")
        export FLAME_TEST_QUICK=1
        # valgrind's virtual CPU has no AVX-512 (but AVX2): the library refuses bf16-compute
        # there, naming the instruction, and runs int8 on AVX2.
        cpu_bf16=$FLAME_TEST_CPU_BF16
        export FLAME_TEST_CPU_BF16=0
        built test_api_shared && run_test "test_api (shared, valgrind)" \
            "$OUT/test_api_valgrind.log" \
            "${VALGRIND[@]}" "$OUT/test_api_shared" "$MODEL" "${QUICK[@]}" "$WORK" 2
        built test_threads_shared && run_test "test_threads (shared, valgrind)" \
            "$OUT/test_threads_valgrind.log" "${VALGRIND[@]}" "$OUT/test_threads_shared" "$MODEL"
        built test_hardening_shared && run_test "test_hardening (shared, valgrind)" \
            "$OUT/test_hardening_valgrind.log" "${VALGRIND[@]}" "$OUT/test_hardening_shared" \
            "$ROOT/tests/fixtures"
        built test_targets_shared && run_test "test_targets (shared, valgrind)" \
            "$OUT/test_targets_valgrind.log" "${VALGRIND[@]}" "$OUT/test_targets_shared" \
            "$ROOT/tests/fixtures"
        built test_stages_shared && run_test "test_stages (shared, valgrind)" \
            "$OUT/test_stages_valgrind.log" "${VALGRIND[@]}" "$OUT/test_stages_shared" \
            "${STAGES_ARGS[@]}"
        built test_cancel_shared && run_test "test_cancel (shared, valgrind)" \
            "$OUT/test_cancel_valgrind.log" "${VALGRIND[@]}" "$OUT/test_cancel_shared" "$MODEL"
        built test_stream_shared && run_test "test_stream (shared, valgrind)" \
            "$OUT/test_stream_valgrind.log" "${VALGRIND[@]}" "$OUT/test_stream_shared" \
            "$ROOT/tests/fixtures"
        mkdir -p "$WORK/batch_valgrind"
        built test_batch_shared && run_test "test_batch (shared, valgrind)" \
            "$OUT/test_batch_valgrind.log" "${VALGRIND[@]}" "$OUT/test_batch_shared" "$MODEL" \
            "$WORK/batch_valgrind"
        built test_cleanup_shared && run_test "test_cleanup (shared, valgrind)" \
            "$OUT/test_cleanup_valgrind.log" "${VALGRIND[@]}" "$OUT/test_cleanup_shared" \
            "$ROOT/tests/fixtures"
        built test_retarget_shared && run_test "test_retarget (shared, valgrind)" \
            "$OUT/test_retarget_valgrind.log" "${VALGRIND[@]}" "$OUT/test_retarget_shared" \
            "$ROOT/tests/fixtures"
        built test_cpp_retarget_shared && run_test "test_cpp_retarget (shared, valgrind)" \
            "$OUT/test_cpp_retarget_valgrind.log" "${VALGRIND[@]}" \
            "$OUT/test_cpp_retarget_shared" "$ROOT/tests/fixtures"
        built test_cpp_shared && run_test "test_cpp (shared, valgrind)" \
            "$OUT/test_cpp_valgrind.log" \
            "${VALGRIND[@]}" "$OUT/test_cpp_shared" "$MODEL" "${QUICK[@]}" 2 \
            "$OUT/loop_positions.npy"
        built test_cpp_gltf_shared && run_test "test_cpp_gltf (shared, valgrind)" \
            "$OUT/test_cpp_gltf_valgrind.log" \
            "${VALGRIND[@]}" "$OUT/test_cpp_gltf_shared" "$ROOT/tests/fixtures"
        built test_cpp_stream_shared && run_test "test_cpp_stream (shared, valgrind)" \
            "$OUT/test_cpp_stream_valgrind.log" \
            "${VALGRIND[@]}" "$OUT/test_cpp_stream_shared" "$ROOT/tests/fixtures"
        unset FLAME_TEST_QUICK
        export FLAME_TEST_CPU_BF16=$cpu_bf16
    fi
else
    echo "skip valgrind (set FLAME_VALGRIND=1 to run it)"
fi

# ---- 5. packaging --------------------------------------------------------------------------
# stripped LIBDIR: the installed libraries have no debug sections (nor embedded bitcode), the
# shared one exports what cargo's build exports and names its debug file, which has them
# (packaging/strip.sh).
# shellcheck disable=SC2317  # called through step
stripped() {
    local so="$1/libflame.so" built="$ROOT/target/release/libflame.so"
    local left
    left="$(readelf -SW "$so" "$1/libflame.a" | grep -cE '\.debug_|\.llvmbc')"
    if [ "$left" -gt 0 ]; then
        echo "$left debug or bitcode sections left in the installed libraries"
        return 1
    fi
    readelf -SW "$1/libflame.so.debug" | grep -qF .debug_line || {
        echo "libflame.so.debug has no .debug_line"
        return 1
    }
    readelf -p .gnu_debuglink "$so" | grep -qF libflame.so.debug || {
        echo "libflame.so names no libflame.so.debug"
        return 1
    }
    diff <(nm -D --defined-only "$built" | awk '{print $3}' | sort) \
        <(nm -D --defined-only "$so" | awk '{print $3}' | sort) || {
        echo "the installed libflame.so exports other symbols than $built"
        return 1
    }
    ls -l "$built" "$ROOT/target/release/libflame.a" "$so" "$1/libflame.a" "$1/libflame.so.debug"
}

packaging() {
    local prefix="$WORK/prefix" pc="$WORK/prefix/lib/pkgconfig"
    step "packaging/install.sh (release build)" "$OUT/install.log" \
        bash packaging/install.sh "$prefix" || return
    step "installed files" "$OUT/install-files.log" ls \
        "$prefix/include/flame.h" "$prefix/include/flame.hpp" "$prefix/lib/libflame.so" \
        "$prefix/lib/libflame.a" "$pc/flame.pc" "$pc/flame-static.pc" \
        "$prefix/lib/cmake/flame/flameConfig.cmake" \
        "$prefix/lib/cmake/flame/flameConfigVersion.cmake" "$prefix/lib/libflame.so.debug"
    step "installed libraries stripped" "$OUT/install-stripped.log" \
        stripped "$prefix/lib"

    local cb="$WORK/cmake-build"
    if step "cmake consumer: configure + build" "$OUT/cmake-consumer.log" \
        bash -c "cmake -S tests/c/cmake_consumer -B '$cb' -DCMAKE_PREFIX_PATH='$prefix' \
                 -DCMAKE_BUILD_TYPE=Release && cmake --build '$cb'"; then
        step "cmake consumer: flame::flame" "$OUT/consumer-shared.log" "$cb/consumer_shared"
        step "cmake consumer: flame::flame_static" "$OUT/consumer-static.log" "$cb/consumer_static"
        step "cmake consumer: flame.hpp" "$OUT/consumer-cpp.log" "$cb/consumer_cpp"
        # The shared consumer needs plain libflame.so (no build path baked in) ...
        step "cmake consumer: NEEDED libflame.so" "$OUT/consumer-needed.log" \
            bash -c "readelf -d '$cb/consumer_shared' | grep -F '[libflame.so]'"
        # ... and the static one does not need it at all.
        step "cmake consumer: static has no libflame.so" "$OUT/consumer-static-needed.log" \
            bash -c "! readelf -d '$cb/consumer_static' | grep -F libflame"
    fi

    export PKG_CONFIG_PATH="$pc"
    step "pkg-config consumer (flame)" "$OUT/pkgconfig-shared.log" bash -c \
        "gcc ${CFLAGS[*]} tests/c/cmake_consumer/main.c \$(pkg-config --cflags --libs flame) \
         -Wl,-rpath,'$prefix/lib' -o '$WORK/pc_shared' && '$WORK/pc_shared'"
    step "pkg-config consumer (flame-static)" "$OUT/pkgconfig-static.log" bash -c \
        "gcc ${CFLAGS[*]} tests/c/cmake_consumer/main.c \
         \$(pkg-config --cflags --libs flame-static) -o '$WORK/pc_static' && '$WORK/pc_static'"
    unset PKG_CONFIG_PATH
}

if [ "${FLAME_PACKAGING:-1}" = 0 ]; then
    echo "skip packaging (FLAME_PACKAGING=0)"
elif ! command -v cmake >/dev/null || ! command -v pkg-config >/dev/null; then
    if [ "${CI:-}" = "true" ]; then
        report "packaging" 0 1 0.0 \
            "  (cmake or pkg-config missing: bash tools/install_test_deps.sh)"
    else
        echo "skip packaging: cmake or pkg-config missing (bash tools/install_test_deps.sh)"
    fi
else
    packaging
fi

finish
