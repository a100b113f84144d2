#!/usr/bin/env bash
# Installs what the tests outside `cargo test` need on a fresh Debian/Ubuntu machine: the C/C++
# ABI tests (tests/c/run.sh) and the packaging check (packaging/install.sh + a CMake and a
# pkg-config consumer). Idempotent and quiet: installs only what is missing, prints one line per
# group of packages it installs. Run as root (CI) or with sudo available.
set -euo pipefail

SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    SUDO="sudo"
fi

# Debian packages whose command is missing: "command:package" pairs.
apt_missing() {
    local pair missing=()
    for pair in "$@"; do
        command -v "${pair%%:*}" >/dev/null 2>&1 || missing+=("${pair#*:}")
    done
    echo "${missing[@]+"${missing[@]}"}"
}

apt_install() {
    local pkgs
    pkgs="$(apt_missing "$@")"
    [ -z "$pkgs" ] && return 0
    # shellcheck disable=SC2086  # the list is word-split on purpose
    apt_install_packages $pkgs
}

# Installs these Debian packages (apt-get update first, once per run).
apt_install_packages() {
    local pkgs="$*"
    echo "install_test_deps: apt-get install $pkgs"
    local log
    log="$(mktemp)"
    # `apt-get update` only when something is missing, and once per run. Output is shown only
    # when a command fails.
    if [ -z "${APT_UPDATED:-}" ]; then
        if ! $SUDO apt-get update -qq >"$log" 2>&1; then
            cat "$log" >&2
            rm -f "$log"
            return 1
        fi
        APT_UPDATED=1
    fi
    # shellcheck disable=SC2086  # the list is word-split on purpose
    if ! DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends \
        $pkgs >"$log" 2>&1; then
        cat "$log" >&2
        rm -f "$log"
        return 1
    fi
    rm -f "$log"
}

# --- C/C++ ABI tests and packaging (tests/c/run.sh) -------------------------------------------
# gcc/g++ compile the tests; valgrind checks the shared-library builds for leaks and invalid
# accesses; cmake and pkg-config build the two consumers of an installed libflame.
apt_install gcc:gcc g++:g++ make:make valgrind:valgrind cmake:cmake pkg-config:pkg-config

# --- Language bindings (tests/bindings/run_all.sh) ---------------------------------------------
# C#: Mono's compiler and runtime. The Unreal plugin's staging script sets libflame.so's SONAME
# with patchelf; its C++ test uses g++ (above).
apt_install mcs:mono-mcs mono:mono-runtime patchelf:patchelf
# Python: tests/bindings/run_python.sh makes its own virtual environment and takes numpy, pytest
# and setuptools from PyPI into it, so nothing is installed into the machine's Python. It needs
# python3's venv module (with ensurepip), which Debian ships apart as python3-venv.
if ! python3 -c 'import venv, ensurepip' >/dev/null 2>&1; then
    if [ "$(command -v python3)" = /usr/bin/python3 ]; then
        apt_install_packages python3-venv
    else
        echo "install_test_deps: $(command -v python3) has no venv module; install one that has" >&2
        exit 1
    fi
fi

# --- BVH import by a real consumer (tools/bvh_roundtrip.sh) ---------------------------------------
# Debian's Blender 3.4, run headless. Installed with its recommends, as measured (about 90 s).
if ! command -v blender >/dev/null 2>&1; then
    echo "install_test_deps: apt-get install blender"
    [ -n "${APT_UPDATED:-}" ] || $SUDO apt-get update -qq >/dev/null
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq blender >/dev/null
fi

# --- glTF export checked by real consumers (tools/gltf_check.sh) -------------------------------
# The Khronos glTF-Validator runs under Node.js (npm installs it into target/node); Blender's
# glTF importer needs NumPy, which Debian's Blender takes from python3-numpy.
apt_install node:nodejs npm:npm
if ! /usr/bin/python3 -c 'import numpy' >/dev/null 2>&1; then
    apt_install_packages python3-numpy
fi
