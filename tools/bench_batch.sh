#!/usr/bin/env bash
# Bulk generation throughput on the demo model: N jobs (default 200, the demo model's defaults:
# 120 frames, 10 DDIM steps, a BVH each) three ways, interleaved round by round:
#   loop   a shell loop of `flame generate`, one process (and one model load) per job;
#   batch  `flame batch` on the same jobs as JSONL (one load, sessions overlapped);
#   ray    bindings/python/examples/ray_batch.py with 2 actors on a local Ray instance (2 CPUs),
#          the whole script timed (Ray's start included) and, from its own clock, the jobs alone.
# Prints each round's seconds and jobs/s and the medians, the batch / loop ratio and Ray's
# overhead against `flame batch`, and the peak RSS of `flame batch` and of one `flame generate`
# (GNU time's maximum resident set size). Checks that every output of the three is the same
# bytes. Ray needs a Python with `ray` and numpy (RAY_PYTHON, default target/ray-venv/bin/python,
# made here with pip when missing); the package runs from bindings/python over
# target/release/libflame.so.
#
#   bash tools/bench_batch.sh [JOBS=200] [ROUNDS=3]
#
# Needs the demo model (`bash tools/try.sh` assembles it). ~4 min per round on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT="$PWD"
JOBS=${1:-200}
ROUNDS=${2:-3}
MODEL=${FLAME_MODEL:-$ROOT/models/demo/flame_demo.safetensors}
[ -f "$MODEL" ] || { echo "bench_batch.sh: no $MODEL (run bash tools/try.sh)" >&2; exit 1; }
cargo build --release --quiet
FLAME="$ROOT/target/release/flame"
RAY_PYTHON=${RAY_PYTHON:-$ROOT/target/ray-venv/bin/python}
if [ ! -x "$RAY_PYTHON" ]; then
    python3 -m venv "$ROOT/target/ray-venv"
    "$ROOT/target/ray-venv/bin/pip" install --quiet --disable-pip-version-check numpy ray==2.60.0
fi
work="$ROOT/target/bench_batch"
rm -rf "$work"
mkdir -p "$work"

# The demo corpus's actions, one prompt each, cycled; seeds 0..N-1.
prompts=("a person walks forward" "a person runs" "a person jumps twice" "a person hops on one leg"
    "a person waves" "a person claps" "a person punches" "a person kicks" "a person squats"
    "a person crouches" "a person turns around" "a person raises both arms" "a person bows"
    "a person side steps to the left" "a person stands still")
: >"$work/jobs.jsonl"
for ((i = 0; i < JOBS; i++)); do
    p=${prompts[$((i % ${#prompts[@]}))]}
    printf '{"prompt": "%s", "seed": %d, "out": "out/%d.bvh"}\n' "$p" "$i" "$i" >>"$work/jobs.jsonl"
done

fresh() { rm -rf "$work/$1"; mkdir -p "$work/$1/out"; }
now() { date +%s.%N; }

run_loop() {
    fresh loop
    local t0 t1 i p
    t0=$(now)
    for ((i = 0; i < JOBS; i++)); do
        p=${prompts[$((i % ${#prompts[@]}))]}
        "$FLAME" generate --model "$MODEL" --prompt "$p" --seed "$i" \
            --out "$work/loop/out/$i.bvh" >/dev/null 2>&1
    done
    t1=$(now)
    echo "$t0 $t1" | awk '{ printf "%.2f", $2 - $1 }'
}

run_batch() {
    fresh batch
    local t0 t1
    t0=$(now)
    (cd "$work/batch" && /usr/bin/time -f "%M" -o "$work/batch.rss" \
        "$FLAME" batch --model "$MODEL" --jobs "$work/jobs.jsonl" >/dev/null 2>"$work/batch.log")
    t1=$(now)
    echo "$t0 $t1" | awk '{ printf "%.2f", $2 - $1 }'
}

run_ray() {
    fresh ray
    local t0 t1
    t0=$(now)
    FLAME_LIBRARY="$ROOT/target/release/libflame.so" PYTHONPATH="$ROOT/bindings/python:$ROOT/bindings/python/examples" \
        "$RAY_PYTHON" - "$work" "$MODEL" <<'EOF' >"$work/ray.jobs_seconds" 2>"$work/ray.log"
import sys, time
sys.path.insert(0, "bindings/python/examples")
import ray, ray_batch
work, model = sys.argv[1], sys.argv[2]
ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
t = time.perf_counter()
merged = ray_batch.run(f"{work}/jobs.jsonl", model, f"{work}/ray", actors=2, shard_size=10)
print(f"{time.perf_counter() - t:.2f}")
assert all(r["status"] == "ok" for r in merged), [r for r in merged if r["status"] != "ok"][:3]
EOF
    t1=$(now)
    echo "$t0 $t1" | awk '{ printf "%.2f", $2 - $1 }'
}

same_outputs() {
    local i
    for ((i = 0; i < JOBS; i++)); do
        cmp -s "$work/loop/out/$i.bvh" "$work/batch/out/$i.bvh" &&
            cmp -s "$work/loop/out/$i.bvh" "$work/ray/out/$i.bvh" ||
            { echo "bench_batch.sh: job $i differs between the three runs" >&2; return 1; }
    done
}

declare -a L B R RJ
for ((r = 1; r <= ROUNDS; r++)); do
    L+=("$(run_loop)")
    B+=("$(run_batch)")
    R+=("$(run_ray)")
    RJ+=("$(cat "$work/ray.jobs_seconds")")
    same_outputs
    echo "round $r: loop ${L[-1]} s, batch ${B[-1]} s, ray ${R[-1]} s (jobs alone ${RJ[-1]} s)," \
        "batch peak RSS $(cat "$work/batch.rss") KB; outputs identical"
done
/usr/bin/time -f "%M" -o "$work/generate.rss" "$FLAME" generate --model "$MODEL" \
    --prompt "a person jumps twice" --out "$work/one.bvh" >/dev/null 2>&1

median() { printf '%s\n' "$@" | sort -g | awk '{ v[NR] = $1 } END { print (NR % 2) ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2 }'; }
ml=$(median "${L[@]}") mb=$(median "${B[@]}") mr=$(median "${R[@]}") mj=$(median "${RJ[@]}")
cores=$(nproc)
cpu=$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ *//')
echo
echo "$JOBS demo-model jobs (120 frames, 10 DDIM steps, BVH), $cores cores ($cpu), median of $ROUNDS rounds:"
echo "| run | seconds | jobs/s |"
echo "| --- | ---: | ---: |"
for row in "shell loop of flame generate:$ml" "flame batch:$mb" "Ray, 2 actors (script):$mr" "Ray, 2 actors (jobs alone):$mj"; do
    name=${row%%:*} s=${row##*:}
    echo "| $name | $s | $(awk -v s="$s" -v n="$JOBS" 'BEGIN { printf "%.2f", n / s }') |"
done
awk -v l="$ml" -v b="$mb" -v r="$mr" -v j="$mj" 'BEGIN {
    printf "flame batch / shell loop: %.2fx the jobs/s\n", l / b
    printf "Ray over flame batch: %+.0f%% time for the script, %+.0f%% for the jobs alone\n", 100 * (r / b - 1), 100 * (j / b - 1)
}'
echo "peak RSS: flame batch $(cat "$work/batch.rss") KB, one flame generate $(cat "$work/generate.rss") KB"
