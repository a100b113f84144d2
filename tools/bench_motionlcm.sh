#!/usr/bin/env bash
# libflame vs PyTorch eager on the full-size random MotionLCM v1 and v2 models
# (tools/make_motionlcm_base_models.sh), same machine, same run, interleaved:
#   tools/bench_motionlcm.sh [ROUNDS (default 5)]
# Per round, for v1 and v2 and for 1 and 4 steps: `flame-bench` and `tools/bench_torch.py`
# (the order alternates round by round), plus `flame-bench --weights W` at 1 step for each W in
# EXTRA_WEIGHTS (default "bf16-compute int8 int8-file"; "" for none; `int8-file` runs the file
# `flame quantize --steps 1` writes, models/motionlcm_{v1,v2}_int8.safetensors, made first if
# missing) and, when TORCH_INT8=1 (the default), PyTorch's own int8 route at 1 step
# (`bench_torch.py --int8`: dynamic quantisation of every nn.Linear); each invocation reports
# the medians of its RUNS runs (bench_torch.py after one warm-up generation). Then a table of the
# medians over the rounds: prompt encoding (sentence-t5-large), one step, the VAE decode, the
# whole motion (steps + decode, prompt already encoded: the binaries' `gen_ms`), libflame /
# PyTorch time ratios, and whether the 1-step target (<= 16 ms and >= 2x PyTorch) is met.
# Environment: PYTHON (default target/bench-venv/bin/python if present, else python3),
# FLAME_BENCH (default target/release/flame-bench, built if missing), THREADS (2), FRAMES (196),
# RUNS (5), STEPS ("1 4"), MODELS ("v1 v2"), EXTRA_WEIGHTS, TORCH_INT8 (1), OUT (results file,
# default target/bench_motionlcm.tsv).
set -euo pipefail
cd "$(dirname "$0")/.."
ROUNDS=${1:-5}
if [ -z "${PYTHON:-}" ]; then
    if [ -x target/bench-venv/bin/python ]; then PYTHON=target/bench-venv/bin/python; else PYTHON=python3; fi
fi
FLAME_BENCH=${FLAME_BENCH:-target/release/flame-bench}
THREADS=${THREADS:-2}
FRAMES=${FRAMES:-196}
RUNS=${RUNS:-5}
STEPS=${STEPS:-"1 4"}
MODELS=${MODELS:-"v1 v2"}
EXTRA_WEIGHTS=${EXTRA_WEIGHTS-"bf16-compute int8 int8-file"}
TORCH_INT8=${TORCH_INT8:-1}
OUT=${OUT:-target/bench_motionlcm.tsv}

for m in $MODELS; do
    f=models/motionlcm_${m}_base_random.safetensors
    if [ ! -f "$f" ]; then
        echo "$f missing: run tools/make_motionlcm_base_models.sh first" >&2
        exit 1
    fi
done
if [ ! -x "$FLAME_BENCH" ]; then cargo build --release --bin flame-bench; fi
FLAME=${FLAME:-target/release/flame}
case " $EXTRA_WEIGHTS " in
*" int8-file "*)
    for m in $MODELS; do
        q=models/motionlcm_${m}_int8.safetensors
        if [ ! -f "$q" ]; then
            if [ ! -x "$FLAME" ]; then cargo build --release --bin flame; fi
            echo "making $q (flame quantize, 16 calibration prompts at 1 step)"
            "$FLAME" quantize --model "models/motionlcm_${m}_base_random.safetensors" --out "$q" \
                --steps 1 --threads "$THREADS"
        fi
    done
    ;;
esac

mkdir -p "$(dirname "$OUT")"
printf 'round\tmodel\timpl\tsteps\ttext_ms\tstep_ms\tgen_ms\tdecode_ms\n' > "$OUT"
log=$(mktemp)
trap 'rm -f "$log"' EXIT

# field NAME LINE: the value of NAME=... on a RESULT line.
field() { tr ' ' '\n' <<<"$2" | sed -n "s/^$1=//p"; }
record() { # round model impl steps command...
    local round=$1 model=$2 impl=$3 steps=$4
    shift 4
    if ! "$@" >"$log" 2>&1; then
        cat "$log" >&2
        echo "failed: $*" >&2
        exit 1
    fi
    local line
    line=$(grep '^RESULT' "$log" | tail -1)
    printf '%s\t%s\t%s\t%s\t%s\t%s\t%s\t%s\n' "$round" "$model" "$impl" "$steps" \
        "$(field text_ms "$line")" "$(field step_ms "$line")" "$(field gen_ms "$line")" \
        "$(field decode_ms "$line")" >>"$OUT"
    printf '  %-3s %-12s %s steps: %s\n' "$model" "$impl" "$steps" "${line#RESULT }"
}
flame() { # round model steps weights
    local file=models/motionlcm_$2_base_random.safetensors weights=$4
    if [ "$4" = int8-file ]; then file=models/motionlcm_$2_int8.safetensors weights=int8; fi
    record "$1" "$2" "libflame-$4" "$3" "$FLAME_BENCH" --model "$file" \
        --frames "$FRAMES" --steps "$3" --threads "$THREADS" --runs "$RUNS" --weights "$weights"
}
torch() { # round model steps [--int8]
    record "$1" "$2" "pytorch${4:+-int8}" "$3" "$PYTHON" tools/bench_torch.py \
        --model "models/motionlcm_$2_base_random.safetensors" \
        --frames "$FRAMES" --steps "$3" --threads "$THREADS" --runs "$RUNS" ${4:+"$4"}
}

echo "bench_motionlcm: $ROUNDS rounds, $FRAMES frames, $THREADS threads, $RUNS runs per invocation, steps $STEPS"
echo "  $(grep -m1 'model name' /proc/cpuinfo 2>/dev/null | cut -d: -f2- | sed 's/^ //'), $(nproc) CPUs; load average at start: $(cut -d' ' -f1-3 /proc/loadavg)"
"$PYTHON" -c 'import torch; print("  torch", torch.__version__, "| threads by default:",
    torch.get_num_threads(), "| MKL:", torch.backends.mkl.is_available(), "| oneDNN:",
    torch.backends.mkldnn.is_available())' || true
start=$(date +%s)
for round in $(seq 1 "$ROUNDS"); do
    echo "round $round of $ROUNDS"
    for m in $MODELS; do
        for s in $STEPS; do
            if [ $((round % 2)) = 1 ]; then
                flame "$round" "$m" "$s" f32
                torch "$round" "$m" "$s"
            else
                torch "$round" "$m" "$s"
                flame "$round" "$m" "$s" f32
            fi
        done
        for w in $EXTRA_WEIGHTS; do flame "$round" "$m" 1 "$w"; done
        if [ "$TORCH_INT8" = 1 ]; then torch "$round" "$m" 1 --int8; fi
    done
done
echo "done in $(( $(date +%s) - start )) s; load average at the end: $(cut -d' ' -f1-3 /proc/loadavg); raw values in $OUT"

"$PYTHON" - "$OUT" "$ROUNDS" "$FRAMES" "$THREADS" <<'EOF'
import csv
import math
import statistics
import sys

path, rounds, frames, threads = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4]
rows = list(csv.DictReader(open(path), delimiter="\t"))


def med(model, impl, steps, key):
    v = [float(r[key]) for r in rows if (r["model"], r["impl"], r["steps"]) == (model, impl, steps)
         and r[key] not in ("", "nan")]
    return statistics.median(v) if v else math.nan


models = sorted({r["model"] for r in rows})
steps = sorted({r["steps"] for r in rows}, key=int)
seen = list(dict.fromkeys(r["impl"] for r in rows))
impls = [i for i in seen if i.startswith("libflame")] + [i for i in seen if i == "pytorch-int8"] \
    + [i for i in seen if i == "pytorch"]
impls.sort(key=lambda i: (i != "libflame-f32", i.startswith("pytorch"), i == "pytorch"))
ours = [i for i in impls if i.startswith("libflame")]
print(f"\nMotionLCM, {frames} frames, {threads} threads: medians over {rounds} rounds "
      "(each the median of its runs), ms")
print("(whole = steps + decode with the prompt already encoded; ratio = libflame time / PyTorch "
      "time, < 0.5 is 2x faster)")
head = f"{'model':<5} {'impl':<22} {'prompt (T5-L)':>13} {'one step':>9} {'decode':>8}"
for s in steps:
    head += f" {'whole ' + s + '-step':>13}"
print(head)
for m in models:
    for impl in impls:
        line = f"{m:<5} {impl:<22} {med(m, impl, '1', 'text_ms'):13.2f} " \
               f"{med(m, impl, '1', 'step_ms'):9.2f} {med(m, impl, '1', 'decode_ms'):8.2f}"
        for s in steps:
            line += f" {med(m, impl, s, 'gen_ms'):13.2f}"
        print(line)
    for impl in ours if "pytorch" in impls else []:
        line = f"{m:<5} {'ratio ' + impl[9:] + '/pytorch':<22}"
        for key in ("text_ms", "step_ms", "decode_ms"):
            width = {"text_ms": 13, "step_ms": 9, "decode_ms": 8}[key]
            line += f" {med(m, impl, '1', key) / med(m, 'pytorch', '1', key):{width}.2f}"
        for s in steps:
            line += f" {med(m, impl, s, 'gen_ms') / med(m, 'pytorch', s, 'gen_ms'):13.2f}"
        print(line)
    if "pytorch" in impls and "1" in steps:
        for impl in ours:
            whole = med(m, impl, "1", "gen_ms")
            speed = med(m, "pytorch", "1", "gen_ms") / whole
            ok = whole <= 16.0 and speed >= 2.0
            also = ""
            if impl.startswith("libflame-int8") and "pytorch-int8" in impls:
                also = f" ({med(m, 'pytorch-int8', '1', 'gen_ms') / whole:.2f}x PyTorch's int8)"
            print(f"{m:<5} target (whole 1-step <= 16 ms and >= 2x PyTorch f32), {impl[9:]}: "
                  f"{whole:.2f} ms, {speed:.2f}x{also} -> {'met' if ok else 'NOT met'}")
more = [f"{m} {impl} {s} steps {med(m, impl, s, 'step_ms'):.2f} ms/step"
        for m in models for impl in impls for s in steps
        if s != "1" and not math.isnan(med(m, impl, s, "step_ms"))]
if more:
    print("per-step medians at more steps: " + "; ".join(more))
EOF
