#!/usr/bin/env bash
# libflame vs PyTorch eager and ONNX Runtime on the same model file, frames, steps, guidance batch
# and threads, in one run, with their ratios. Medians; compare only ratios measured in the same run.
#
#   tools/bench.sh [MODEL] [FRAMES=49,98,196,392] [THREADS=2] [STEPS=10] [RUNS=3]
#   WEIGHTS="f32 bf16" tools/bench.sh models/flame_base_random.safetensors 196
#   WEIGHTS=f32 GUIDANCE=11 tools/bench.sh models/mola_base_random.safetensors 200 2 50 3
#
# GUIDANCE (default: each tool's 2.5) is passed to all; any value other than 0 and 1 runs the
# guided batch of 2 in all. ROUNDS (default 1) repeats libflame, torch (and ORT) per frame count,
# round-robin, and the table shows the median over the rounds of each run's medians.
# Prints a markdown table: frames, weights, libflame text/step/generation ms, GFLOP/s, peak RSS,
# torch step/generation ms and torch_gen / libflame_gen. For a latent model (MoLA, MLD) the
# generation includes the VAE decode, which is also shown on its own for both. For a model with
# mixtures of experts (FineMoGen) the MoE time per step is shown for both.
# RESULTS=FILE keeps every run's RESULT line (each round's load average before it as a comment).
# TORCH_ARGS (default empty) is passed to tools/bench_torch.py only, e.g.
#   WEIGHTS=f32 TORCH_ARGS=--text-moe-once tools/bench.sh models/finemogen_base_random.safetensors 196 2 50 3
# ONNX Runtime (tools/bench_onnx.py: the same step exported by torch.onnx, checked against PyTorch,
# timed by an InferenceSession with the same threads) runs third in every round when the Python
# has onnxruntime (ORT=auto, the default; ORT=1 requires it, ORT=0 skips it); its exported files
# are kept in $CARGO_TARGET_DIR/onnx and reused. ORT_ARGS (default empty) is passed to
# tools/bench_onnx.py only, e.g. ORT_ARGS="--spin 0".
# The table's ratios are the other's generation time over libflame's (above 1: libflame faster);
# a second table lists each round's generation times and ratios.
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
read -ra ORT_EXTRA <<< "${ORT_ARGS:-}"
ORT=${ORT:-auto}
if [ "$ORT" = auto ]; then
    if "$PY" -c 'import onnxruntime, onnx, onnxscript' 2> /dev/null; then ORT=1; else
        echo "ONNX Runtime: not run ($PY lacks onnxruntime, onnx or onnxscript; pip install -r tools/requirements.txt)"
        ORT=0
    fi
fi
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}
cargo build --release --quiet --bin flame-bench
BENCH=$CARGO_TARGET_DIR/release/flame-bench
OUT=$(mktemp)
ORT_LOG=$(mktemp)
trap 'rm -f "$OUT" "$ORT_LOG"' EXIT
ORT_CACHE=$CARGO_TARGET_DIR/onnx

echo "machine: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(nproc) cpus, load: $(cut -d' ' -f1-3 /proc/loadavg)"
echo "model: $MODEL, frames $FRAMES, $STEPS steps, guidance ${GUIDANCE:-2.5}, $THREADS threads, $RUNS runs, $ROUNDS rounds"
IFS=',' read -ra FR <<< "$FRAMES"
for f in "${FR[@]}"; do
    # Interleave the implementations per frame count so load changes hit all alike.
    for ((r = 0; r < ROUNDS; r++)); do
        echo "# frames $f round $((r + 1)) $(date -u +%H:%M:%S) load $(cut -d' ' -f1-3 /proc/loadavg)" >> "$OUT"
        for w in $WEIGHTS; do
            "$BENCH" --model "$MODEL" --frames "$f" --steps "$STEPS" --threads "$THREADS" \
                --runs "$RUNS" --weights "$w" "${GUIDE[@]}" | grep '^RESULT' >> "$OUT"
        done
        "$PY" tools/bench_torch.py --model "$MODEL" --frames "$f" --steps "$STEPS" \
            --threads "$THREADS" --runs "$RUNS" "${GUIDE[@]}" "${TORCH_EXTRA[@]}" \
            | grep '^RESULT' >> "$OUT"
        if [ "$ORT" = 1 ]; then
            rc=0
            "$PY" tools/bench_onnx.py --model "$MODEL" --frames "$f" --steps "$STEPS" \
                --threads "$THREADS" --runs "$RUNS" --cache "$ORT_CACHE" "${GUIDE[@]}" \
                "${ORT_EXTRA[@]}" > "$ORT_LOG" 2>&1 || rc=$?
            if [ "$rc" = 0 ]; then
                grep '^onnxruntime' "$ORT_LOG" | head -1 | sed 's/^/# /' >> "$OUT"
                grep '^  check' "$ORT_LOG" | sed 's/^ */# /' >> "$OUT"
                grep '^RESULT' "$ORT_LOG" >> "$OUT"
            else
                cat "$ORT_LOG" >&2
                exit "$rc"
            fi
        fi
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
function ratio(a, b) { return (a == "nan" || b == "nan" || b + 0 == 0) ? "nan" : a / b }
# "# frames F round R HH:MM:SS load L1 L5 L15" starts a round.
/^# frames / { rnd = $5; if (!(($3, rnd) in rseen)) { rseen[$3, rnd] = 1; nr++; rf[nr] = $3; rr[nr] = rnd; rload[nr] = $8 } next }
/^#/ { next }
{
    f = val("frames"); impl = val("impl")
    if (impl == "torch" || impl == "ort") { id = impl " " f; RG[impl, f, rnd] = val("gen_ms"); if (impl == "ort") ort = 1 }
    else { id = f " " val("weights"); RG["flame " val("weights"), f, rnd] = val("gen_ms"); if (!(id in seen)) { seen[id] = 1; n++; row[n] = id; fr[n] = f; w[n] = val("weights") } }
    add(id SUBSEP "text", val("text_ms")); add(id SUBSEP "step", val("step_ms")); add(id SUBSEP "gen", val("gen_ms"))
    add(id SUBSEP "gf", val("gflops")); add(id SUBSEP "lgf", val("linear_gflops")); add(id SUBSEP "hwm", val("hwm_mib"))
    if (val("decode_ms") != "") { latent = 1; add(id SUBSEP "dec", val("decode_ms")) }
    if (val("moe_ms") + 0 > 0) moe = 1
    add(id SUBSEP "moe", val("moe_ms"))
}
END {
    if (latent) {
        h = "| frames | weights | text ms | step ms | " steps "-step gen ms (incl. decode) | decode ms | GFLOP/s (step) | GFLOP/s (linear layers) | peak RSS MiB | torch step ms | torch gen ms (incl. decode) | torch decode ms | speed-up (gen) |"
        sep = "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    } else if (moe) {
        h = "| frames | weights | text ms | step ms | " steps "-step gen ms | MoE ms/step | GFLOP/s (step) | GFLOP/s (linear layers) | peak RSS MiB | torch text ms | torch step ms | torch gen ms | torch MoE ms/step | speed-up (gen) |"
        sep = "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    } else {
        h = "| frames | weights | text ms | step ms | " steps "-step gen ms | GFLOP/s (step) | GFLOP/s (linear layers) | peak RSS MiB | torch text ms | torch step ms | torch gen ms | speed-up (gen) |"
        sep = "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    }
    if (ort) {
        h = h (latent ? " ORT step ms | ORT gen ms (incl. decode) | ORT decode ms | speed-up vs ORT (gen) |" : " ORT step ms | ORT gen ms | speed-up vs ORT (gen) |")
        sep = sep (latent ? "---:|---:|---:|---:|" : "---:|---:|---:|")
    }
    print h; print sep
    for (i = 1; i <= n; i++) {
        id = row[i]; t = "torch " fr[i]; o = "ort " fr[i]
        if (latent)
            line = sprintf("| %s | %s | %.1f | %.1f | %.1f | %.1f | %.1f | %.1f | %.0f | %.1f | %.1f | %.1f | %.2fx |", fr[i], w[i], med(id SUBSEP "text"), med(id SUBSEP "step"), med(id SUBSEP "gen"), med(id SUBSEP "dec"), med(id SUBSEP "gf"), med(id SUBSEP "lgf"), med(id SUBSEP "hwm"), med(t SUBSEP "step"), med(t SUBSEP "gen"), med(t SUBSEP "dec"), ratio(med(t SUBSEP "gen"), med(id SUBSEP "gen")))
        else if (moe)
            line = sprintf("| %s | %s | %.1f | %.1f | %.1f | %.1f | %.1f | %.1f | %.0f | %.1f | %.1f | %.1f | %.1f | %.2fx |", fr[i], w[i], med(id SUBSEP "text"), med(id SUBSEP "step"), med(id SUBSEP "gen"), med(id SUBSEP "moe"), med(id SUBSEP "gf"), med(id SUBSEP "lgf"), med(id SUBSEP "hwm"), med(t SUBSEP "text"), med(t SUBSEP "step"), med(t SUBSEP "gen"), med(t SUBSEP "moe"), ratio(med(t SUBSEP "gen"), med(id SUBSEP "gen")))
        else
            line = sprintf("| %s | %s | %.1f | %.1f | %.1f | %.1f | %.1f | %.0f | %.1f | %.1f | %.1f | %.2fx |", fr[i], w[i], med(id SUBSEP "text"), med(id SUBSEP "step"), med(id SUBSEP "gen"), med(id SUBSEP "gf"), med(id SUBSEP "lgf"), med(id SUBSEP "hwm"), med(t SUBSEP "text"), med(t SUBSEP "step"), med(t SUBSEP "gen"), ratio(med(t SUBSEP "gen"), med(id SUBSEP "gen")))
        if (ort && latent)
            line = line sprintf(" %.1f | %.1f | %.1f | %.2fx |", med(o SUBSEP "step"), med(o SUBSEP "gen"), med(o SUBSEP "dec"), ratio(med(o SUBSEP "gen"), med(id SUBSEP "gen")))
        else if (ort)
            line = line sprintf(" %.1f | %.1f | %.2fx |", med(o SUBSEP "step"), med(o SUBSEP "gen"), ratio(med(o SUBSEP "gen"), med(id SUBSEP "gen")))
        print line
    }
    # Each round: generation ms of every implementation and the ratios within the round.
    if (nr > 1 || ort) {
        print ""
        print "| frames | round | load before | weights | libflame gen ms | torch gen ms | " (ort ? "ORT gen ms | " : "") "torch / libflame |" (ort ? " ORT / libflame |" : "")
        print "|---:|---:|---|---|---:|---:|" (ort ? "---:|" : "") "---:|" (ort ? "---:|" : "")
        for (k = 1; k <= nr; k++)
            for (i = 1; i <= n; i++) {
                if (fr[i] != rf[k]) continue
                lg = RG["flame " w[i], rf[k], rr[k]]; tg = RG["torch", rf[k], rr[k]]; og = RG["ort", rf[k], rr[k]]
                if (lg == "") lg = "nan"; if (tg == "") tg = "nan"; if (og == "") og = "nan"
                line = sprintf("| %s | %s | %s | %s | %.1f | %.1f | ", rf[k], rr[k], rload[k], w[i], lg, tg)
                if (ort) line = line sprintf("%.1f | ", og)
                line = line sprintf("%.2fx |", ratio(tg, lg))
                if (ort) line = line sprintf(" %.2fx |", ratio(og, lg))
                print line
            }
    }
}' "$OUT"
