#!/usr/bin/env bash
# Runs the libFuzzer targets of fuzz/ (see docs/fuzzing.md).
#
#   bash tools/fuzz.sh [SECONDS] [TARGET...]
#
# Runs every target (or the given ones) for SECONDS each (default 20, the smoke run of the test
# command), one process on one core, memory capped so an allocation bomb is a finding. Prints
# executions, coverage (edges) and findings per target; exits non-zero if any target found a
# crash, panic, timeout, leak or out-of-memory (the input is kept under fuzz/artifacts/TARGET/).
#
# Environment:
#   FUZZ_RUNS=N          stop a target after N executions (as well as after SECONDS)
#   FUZZ_SANITIZER=S     address (default) or none
#   FUZZ_RSS_MB=N        memory cap per run in MB (default 2048)
#   FUZZ_LOG_DIR=DIR     where each target's libFuzzer output goes (default fuzz/logs)
#
# cargo-fuzz needs nightly-only compiler flags; on a stable toolchain RUSTC_BOOTSTRAP=1 makes
# rustc accept them. cargo-fuzz is installed (pinned) if missing.
set -euo pipefail

CARGO_FUZZ_VERSION=0.13.2
ALL_TARGETS=(npy batch_jobs bvh pose_reference prompt ffi_params ffi_controls model_config model_header model_load model_file rig_gltf rig_bvh bone_map urdf robot_config t5_file)

cd "$(dirname "$0")/.."
root=$(pwd)

secs=20
if [[ $# -gt 0 && $1 =~ ^[0-9]+$ ]]; then
    secs=$1
    shift
fi
targets=("$@")
[[ ${#targets[@]} -eq 0 ]] && targets=("${ALL_TARGETS[@]}")
for t in "${targets[@]}"; do
    [[ -f fuzz/fuzz_targets/$t.rs ]] || { echo "fuzz.sh: no target '$t' (have: ${ALL_TARGETS[*]})" >&2; exit 2; }
done

sanitizer=${FUZZ_SANITIZER:-address}
rss=${FUZZ_RSS_MB:-2048}
logs=${FUZZ_LOG_DIR:-$root/fuzz/logs}
mkdir -p "$logs"
export RUSTC_BOOTSTRAP=1

if [[ $(cargo fuzz --version 2>/dev/null) != "cargo-fuzz $CARGO_FUZZ_VERSION" ]]; then
    echo "fuzz.sh: installing cargo-fuzz $CARGO_FUZZ_VERSION" >&2
    cargo install cargo-fuzz --version "$CARGO_FUZZ_VERSION" --locked
fi

cd fuzz
# -a: debug assertions (and so overflow checks) on, as in the test builds.
cargo fuzz build -a --sanitizer "$sanitizer"

# Longest input per target: model files are ~0.6 to 1.1 MB, their headers up to ~72 KB (~20 KB
# without the tokenizer text). Prompts: the library takes any length (it tokenizes the whole
# text, then truncates to the encoder's window); 512 bytes is several times any window here
# (at most 93 tokens), and tokenizing costs ~5 to 10 us a byte instrumented, so longer inputs
# would only slow the target (see docs/fuzzing.md).
max_len() {
    case $1 in
        model_file) echo 1200000 ;;
        t5_file) echo 200000 ;;
        model_load) echo 80000 ;;
        model_header) echo 32768 ;;
        bvh) echo 16384 ;;
        prompt) echo 512 ;;
        *) echo 4096 ;;
    esac
}

# Fixture model files: the families (MotionLCM v1 and v2, without and with a ControlNet), then
# the f16 FLAME.
fixtures=(flame_tiny mdm_tiny motionfm_tiny mld_tiny mola_tiny finemogen_tiny omg_tiny
    motionlcm_v1_tiny motionlcm_v2_tiny motionlcm_v1_control_tiny motionlcm_v2_control_tiny
    flame_tiny_f16)

# Fixture `$1`'s safetensors header (its first 8 bytes give the length).
fixture_header() {
    local f=$root/tests/fixtures/$1.safetensors n
    n=$(od -An -t u8 -N 8 "$f" | tr -d ' ')
    tail -c +9 "$f" | head -c "$n"
}

# Seeds that are too big to commit are made from the test fixtures: whole files for model_file;
# for model_load each family's header after its pick byte (0 to 10, the order of
# MODEL_FIXTURES), for model_header the same without the `flame.tokenizer` entry (padded with
# spaces to a multiple of 8, as safetensors writers pad, so f32 data stays aligned).
extra_seeds() {
    local d i
    case $1 in
        model_file)
            d=target/seeds/model_file
            mkdir -p "$d"
            for i in "${fixtures[@]}"; do cp "$root/tests/fixtures/$i.safetensors" "$d/"; done
            # An int8 file as `flame quantize` writes it (I8 weights, their scales, the
            # quantisation metadata), from the tiny FLAME fixture.
            if [ ! -f "$d/flame_tiny_int8.safetensors" ]; then
                cargo run --quiet --manifest-path "$root/Cargo.toml" --bin flame -- \
                    quantize --threads 1 --frames 40 \
                    --model "$root/tests/fixtures/flame_tiny.safetensors" \
                    --out "$d/flame_tiny_int8.safetensors" >/dev/null 2>&1 ||
                    echo "fuzz.sh: could not write the int8 seed (model_file runs without it)" >&2
            fi
            # The same with one scale per group of 8 inputs (`--group`: 2-D scales, the group
            # size in the metadata).
            if [ ! -f "$d/flame_tiny_int8_g8.safetensors" ]; then
                cargo run --quiet --manifest-path "$root/Cargo.toml" --bin flame -- \
                    quantize --threads 1 --frames 40 --group 8 \
                    --model "$root/tests/fixtures/flame_tiny.safetensors" \
                    --out "$d/flame_tiny_int8_g8.safetensors" >/dev/null 2>&1 ||
                    echo "fuzz.sh: could not write the grouped int8 seed (model_file runs without it)" >&2
            fi
            echo "$d"
            ;;
        t5_file)
            d=target/seeds/t5_file
            mkdir -p "$d"
            cp "$root/tests/fixtures/t5_tiny.safetensors" "$d/"
            echo "$d"
            ;;
        model_load)
            d=target/seeds/model_load
            mkdir -p "$d"
            for i in 0 1 2 3 4 5 6 7 8 9 10; do
                { printf "\\x$(printf %02x "$i")"; fixture_header "${fixtures[i]}"; } >"$d/${fixtures[i]}"
            done
            echo "$d"
            ;;
        model_header)
            d=target/seeds/model_header
            mkdir -p "$d"
            for i in 0 1 2 3 4 5 6 7 8 9 10; do
                { printf "\\x$(printf %02x "$i")"; fixture_header "${fixtures[i]}" | perl -0777 -pe '
                    s/,"flame\.tokenizer":"(?:[^"\\]|\\.)*"|"flame\.tokenizer":"(?:[^"\\]|\\.)*",?//;
                    s/ +$//; $_ .= " " x (-length() % 8)'; } >"$d/${fixtures[i]}"
            done
            echo "$d"
            ;;
    esac
}

# Findings only: libFuzzer also writes `slow-unit-*` files (any input over 10 s, such as a
# target's first, which builds its fixtures, on a busy machine); those are not findings.
findings() { find "artifacts/$1" -type f ! -name 'slow-unit-*' | wc -l; }

failed=0
printf '%-15s %12s %9s %8s %7s  %s\n' target executions exec/s edges seconds findings
for t in "${targets[@]}"; do
    # New inputs go to a scratch corpus; the committed one (fuzz/corpus/T) is only read.
    scratch=target/corpus/$t
    mkdir -p "$scratch" "corpus/$t" "artifacts/$t"
    before=$(findings "$t")
    log=$logs/$t.log
    args=(-rss_limit_mb="$rss" -malloc_limit_mb="$rss" -max_total_time="$secs" -timeout=30
        -max_len="$(max_len "$t")" -print_final_stats=1)
    [[ -n ${FUZZ_RUNS:-} ]] && args+=(-runs="$FUZZ_RUNS")
    start=$(date +%s)
    status=0
    # shellcheck disable=SC2046
    cargo fuzz run -a --sanitizer "$sanitizer" "$t" "$scratch" "corpus/$t" $(extra_seeds "$t") \
        -- "${args[@]}" >"$log" 2>&1 || status=$?
    took=$(($(date +%s) - start))
    execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -1)
    rate=$(sed -n 's/^stat::average_exec_per_sec: *//p' "$log" | tail -1)
    edges=$(grep -o 'cov: [0-9]*' "$log" | tail -1 | cut -d' ' -f2)
    if [[ -z $execs ]]; then # no final stats after a crash: the last status line's count
        execs=$(grep -o '^#[0-9]*' "$log" | tail -1 | tr -d '#')
    fi
    found=$(($(findings "$t") - before))
    if [[ $status -ne 0 || $found -gt 0 ]]; then
        failed=1
        what="FOUND (exit $status): $(ls -t "artifacts/$t" | grep -v '^slow-unit-' | head -1), see $log"
    else
        what=none
    fi
    printf '%-15s %12s %9s %8s %7s  %s\n' "$t" "${execs:-?}" "${rate:-?}" "${edges:-?}" "$took" "$what"
done
exit $failed
