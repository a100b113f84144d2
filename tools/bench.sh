#!/usr/bin/env bash
# libflame vs PyTorch eager on the same model file, frames, steps, guidance batch and threads, in
# one run, with their ratio. Medians; compare only ratios measured in the same run.
#
#   tools/bench.sh [MODEL] [FRAMES=49,98,196,392] [THREADS=2] [STEPS=10] [RUNS=3]
#   WEIGHTS="f32 bf16" tools/bench.sh models/flame_base_random.safetensors 196
#   WEIGHTS=f32 GUIDANCE=11 tools/bench.sh models/mola_base_random.safetensors 200 2 50 3
#
# GUIDANCE (default: each tool's 2.5) is passed to both; any value other than 0 and 1 runs the
# guided batch of 2 in both. ROUNDS (default 1) repeats the libflame/torch pair per frame count,
# alternating, and the table shows the median over the rounds of each run's medians.
# Prints a markdown table: frames, weights, libflame text/step/generation ms, GFLOP/s, peak RSS,
# torch step/generation ms and torch_gen / libflame_gen. For a latent model (MoLA, MLD) the
# generation includes the VAE decode, which is also shown on its own for both. For a model with
# mixtures of experts (FineMoGen) the MoE time per step is shown for both.
# RESULTS=FILE keeps every run's RESULT line (each round's load average before it as a comment).
# TORCH_ARGS (default empty) is passed to tools/bench_torch.py only, e.g.
#   WEIGHTS=f32 TORCH_ARGS=--text-moe-once tools/bench.sh models/finemogen_base_random.safetensors 196 2 50 3
set -euo pipefail
cd "$(dirname "$0")/.."
MODEL=${1:-models/flame_base_random.safetensors}
FRAMES=${2:-49,98,196,392}
THREADS=${3:-2}
STEPS=${4:-10}
RUNS=${5:-3}
WEIGHTS=${WEIGHTS:-f32 f16 bf16}
ROUNDS=${ROUNDS:-1}
GUIDE=()
if [ -n "${GUIDANCE:-}" ]; then GUIDE=(--guidance "$GUIDANCE"); fi
PY=${PYTHON:-python3}
read -ra TORCH_EXTRA <<< "${TORCH_ARGS:-}"
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}
cargo build --release --quiet --bin flame-bench
BENCH=$CARGO_TARGET_DIR/release/flame-bench
OUT=$(mktemp)
trap 'rm -f "$OUT"' EXIT

echo "machine: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(nproc) cpus, load: $(cut -d' ' -f1-3 /proc/loadavg)"
echo "model: $MODEL, frames $FRAMES, $STEPS steps, guidance ${GUIDANCE:-2.5}, $THREADS threads, $RUNS runs, $ROUNDS rounds"
IFS=',' read -ra FR <<< "$FRAMES"
for f in "${FR[@]}"; do
    # Interleave the implementations per frame count so load changes hit both alike.
    for ((r = 0; r < ROUNDS; r++)); do
        echo "# frames $f round $((r + 1)) $(date -u +%H:%M:%S) load $(cut -d' ' -f1-3 /proc/loadavg)" >> "$OUT"
        for w in $WEIGHTS; do
            "$BENCH" --model "$MODEL" --frames "$f" --steps "$STEPS" --threads "$THREADS" \
                --runs "$RUNS" --weights "$w" "${GUIDE[@]}" | grep '^RESULT' >> "$OUT"
        done
        "$PY" tools/bench_torch.py --model "$MODEL" --frames "$f" --steps "$STEPS" \
            --threads "$THREADS" --runs "$RUNS" "${GUIDE[@]}" "${TORCH_EXTRA[@]}" \
            | grep '^RESULT' >> "$OUT"
    done
done
echo "load after: $(cut -d' ' -f1-3 /proc/loadavg)"
if [ -n "${RESULTS:-}" ]; then cp "$OUT" "$RESULTS"; fi

awk -v steps="$STEPS" '
function val(key,   i, kv) { for (i = 2; i <= NF; i++) { split($i, kv, "="); if (kv[1] == key) return kv[2] } return "" }
# Appends v to list k (values joined by spaces); med(k) is the median of the list.
function add(k, v) { if (v == "") return; L[k] = (k in L) ? L[k] " " v : v }
function med(k,   n, a, i, j, t) {
    if (!(k in L)) return "nan"
    n = split(L[k], a, " ")
    for (i = 2; i <= n; i++) { t = a[i] + 0; for (j = i - 1; j >= 1 && a[j] + 0 > t; j--) a[j + 1] = a[j]; a[j + 1] = t }
    return n % 2 ? a[(n + 1) / 2] : (a[n / 2] + a[n / 2 + 1]) / 2
}
/^#/ { next }
{
    f = val("frames")
    if (val("impl") == "torch") { id = "torch " f } else { id = f " " val("weights"); if (!(id in seen)) { seen[id] = 1; n++; row[n] = id; fr[n] = f; w[n] = val("weights") } }
    add(id SUBSEP "text", val("text_ms")); add(id SUBSEP "step", val("step_ms")); add(id SUBSEP "gen", val("gen_ms"))
    add(id SUBSEP "gf", val("gflops")); add(id SUBSEP "lgf", val("linear_gflops")); add(id SUBSEP "hwm", val("hwm_mib"))
    if (val("decode_ms") != "") { latent = 1; add(id SUBSEP "dec", val("decode_ms")) }
    if (val("moe_ms") + 0 > 0) moe = 1
    add(id SUBSEP "moe", val("moe_ms"))
}
END {
    if (latent) {
        print "| frames | weights | text ms | step ms | " steps "-step gen ms (incl. decode) | decode ms | GFLOP/s (step) | GFLOP/s (linear layers) | peak RSS MiB | torch step ms | torch gen ms (incl. decode) | torch decode ms | speed-up (gen) |"
        print "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    } else if (moe) {
        print "| frames | weights | text ms | step ms | " steps "-step gen ms | MoE ms/step | GFLOP/s (step) | GFLOP/s (linear layers) | peak RSS MiB | torch text ms | torch step ms | torch gen ms | torch MoE ms/step | speed-up (gen) |"
        print "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    } else {
        print "| frames | weights | text ms | step ms | " steps "-step gen ms | GFLOP/s (step) | GFLOP/s (linear layers) | peak RSS MiB | torch text ms | torch step ms | torch gen ms | speed-up (gen) |"
        print "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    }
    for (i = 1; i <= n; i++) {
        id = row[i]; t = "torch " fr[i]
        if (latent)
            printf "| %s | %s | %.1f | %.1f | %.1f | %.1f | %.1f | %.1f | %.0f | %.1f | %.1f | %.1f | %.2fx |\n", fr[i], w[i], med(id SUBSEP "text"), med(id SUBSEP "step"), med(id SUBSEP "gen"), med(id SUBSEP "dec"), med(id SUBSEP "gf"), med(id SUBSEP "lgf"), med(id SUBSEP "hwm"), med(t SUBSEP "step"), med(t SUBSEP "gen"), med(t SUBSEP "dec"), med(t SUBSEP "gen") / med(id SUBSEP "gen")
        else if (moe)
            printf "| %s | %s | %.1f | %.1f | %.1f | %.1f | %.1f | %.1f | %.0f | %.1f | %.1f | %.1f | %.1f | %.2fx |\n", fr[i], w[i], med(id SUBSEP "text"), med(id SUBSEP "step"), med(id SUBSEP "gen"), med(id SUBSEP "moe"), med(id SUBSEP "gf"), med(id SUBSEP "lgf"), med(id SUBSEP "hwm"), med(t SUBSEP "text"), med(t SUBSEP "step"), med(t SUBSEP "gen"), med(t SUBSEP "moe"), med(t SUBSEP "gen") / med(id SUBSEP "gen")
        else
            printf "| %s | %s | %.1f | %.1f | %.1f | %.1f | %.1f | %.0f | %.1f | %.1f | %.1f | %.2fx |\n", fr[i], w[i], med(id SUBSEP "text"), med(id SUBSEP "step"), med(id SUBSEP "gen"), med(id SUBSEP "gf"), med(id SUBSEP "lgf"), med(id SUBSEP "hwm"), med(t SUBSEP "text"), med(t SUBSEP "step"), med(t SUBSEP "gen"), med(t SUBSEP "gen") / med(id SUBSEP "gen")
    }
}' "$OUT"
