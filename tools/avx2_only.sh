#!/usr/bin/env bash
# Run a command as if the CPU had AVX2 + FMA + F16C and nothing wider (AVX-512, VNNI, BF16 and
# AMX hidden from `cpuid` for that process and its children; tools/avx2_only/avx2_only.c says
# how). Every library in the process sees the same CPU: libflame's dispatch, ONNX Runtime's MLAS,
# PyTorch's oneDNN and MKL all pick their AVX2 code. The hardware does not change, so this is an
# AVX2-only CPU's instruction set at this CPU's speed per instruction, not an AVX2-only CPU.
# AVX2_ONLY_KEEP_AVX_VNNI=1 leaves AVX-VNNI visible where the CPU has it (an AVX2 CPU with
# AVX-VNNI, like Intel's client cores since Alder Lake).
# Needs Linux's CPUID faulting (the `cpuid_fault` flag in /proc/cpuinfo); exits 3 without it.
#
#   tools/avx2_only.sh target/release/flame info
#   PYTHON=target/bench-venv/bin/python tools/avx2_only.sh tools/bench.sh MODEL 196 2 1 3
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
if ! grep -qw cpuid_fault /proc/cpuinfo; then
    echo "avx2_only.sh: this CPU (or its hypervisor) does not offer CPUID faulting; cannot hide AVX-512" >&2
    exit 3
fi
lib="${CARGO_TARGET_DIR:-$root/target}/avx2_only.so"
src="$root/tools/avx2_only/avx2_only.c"
if [ ! -f "$lib" ] || [ "$src" -nt "$lib" ]; then
    mkdir -p "$(dirname "$lib")"
    gcc -O2 -Wall -Wextra -Werror -shared -fPIC -o "$lib" "$src" -ldl
fi
export LD_PRELOAD="$lib${LD_PRELOAD:+:$LD_PRELOAD}"
exec "$@"
