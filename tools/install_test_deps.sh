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
    echo "install_test_deps: apt-get install $pkgs"
    # `apt-get update` only when something is missing, and once per run.
    if [ -z "${APT_UPDATED:-}" ]; then
        $SUDO apt-get update -qq >/dev/null
        APT_UPDATED=1
    fi
    # shellcheck disable=SC2086  # the list is word-split on purpose
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends $pkgs >/dev/null
}

# --- C/C++ ABI tests and packaging (tests/c/run.sh) -------------------------------------------
# gcc/g++ compile the tests; valgrind checks the shared-library builds for leaks and invalid
# accesses; cmake and pkg-config build the two consumers of an installed libflame.
apt_install gcc:gcc g++:g++ make:make valgrind:valgrind cmake:cmake pkg-config:pkg-config

# --- Other test suites (C#/Mono, Python bindings): add their lines below -----------------------
# (reserved for the engineer who owns those bindings; keep the apt_install / pip pattern)

# --- end of other test suites -------------------------------------------------------------------
