#!/usr/bin/env bash
# libflame vs PyTorch eager on the same model file, frames, steps, guidance batch and threads, in
# one run, with their ratio. Medians; compare only ratios measured in the same run.
#
#   tools/bench.sh [MODEL] [FRAMES=49,98,196,392] [THREADS=2] [STEPS=10] [RUNS=3]
#   WEIGHTS="f32 bf16" tools/bench.sh models/flame_base_random.safetensors 196
#
# Prints a markdown table: frames, weights, libflame text/step/generation ms, GFLOP/s, peak RSS,
# torch step/generation ms and torch_gen / libflame_gen.
set -euo pipefail
cd "$(dirname "$0")/.."
MODEL=${1:-models/flame_base_random.safetensors}
FRAMES=${2:-49,98,196,392}
THREADS=${3:-2}
STEPS=${4:-10}
RUNS=${5:-3}
WEIGHTS=${WEIGHTS:-f32 f16 bf16}
PY=${PYTHON:-python3}
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}
cargo build --release --quiet --bin flame-bench
BENCH=$CARGO_TARGET_DIR/release/flame-bench
OUT=$(mktemp)
trap 'rm -f "$OUT"' EXIT

echo "machine: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(nproc) cpus, load: $(cut -d' ' -f1-3 /proc/loadavg)"
echo "model: $MODEL, frames $FRAMES, $STEPS steps, $THREADS threads, $RUNS runs"
IFS=',' read -ra FR <<< "$FRAMES"
for f in "${FR[@]}"; do
    # Interleave the implementations per frame count so load changes hit both alike.
    for w in $WEIGHTS; do
        "$BENCH" --model "$MODEL" --frames "$f" --steps "$STEPS" --threads "$THREADS" \
            --runs "$RUNS" --weights "$w" | grep '^RESULT' >> "$OUT"
    done
    "$PY" tools/bench_torch.py --model "$MODEL" --frames "$f" --steps "$STEPS" \
        --threads "$THREADS" --runs "$RUNS" | grep '^RESULT' >> "$OUT"
done
echo "load after: $(cut -d' ' -f1-3 /proc/loadavg)"

awk '
function val(key,   i, kv) { for (i = 2; i <= NF; i++) { split($i, kv, "="); if (kv[1] == key) return kv[2] } return "" }
val("impl") == "torch" { tstep[val("frames")] = val("step_ms"); tgen[val("frames")] = val("gen_ms"); ttext[val("frames")] = val("text_ms"); next }
{ n++; fr[n] = val("frames"); w[n] = val("weights"); text[n] = val("text_ms"); step[n] = val("step_ms"); gen[n] = val("gen_ms"); gf[n] = val("gflops"); lgf[n] = val("linear_gflops"); hwm[n] = val("hwm_mib") }
END {
    print "| frames | weights | text ms | step ms | 10-step gen ms | GFLOP/s (step) | GFLOP/s (linear layers) | peak RSS MiB | torch text ms | torch step ms | torch gen ms | speed-up (gen) |"
    print "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    for (i = 1; i <= n; i++) {
        f = fr[i]
        printf "| %s | %s | %.1f | %.1f | %.1f | %.1f | %.1f | %.0f | %.1f | %.1f | %.1f | %.2fx |\n", f, w[i], text[i], step[i], gen[i], gf[i], lgf[i], hwm[i], ttext[f], tstep[f], tgen[f], tgen[f] / gen[i]
    }
}' "$OUT"
