#!/usr/bin/env bash
# Builds libflame (release) and installs it under PREFIX for C and C++ consumers:
#
#   PREFIX/include/flame.h, flame.hpp
#   PREFIX/lib/libflame.so (macOS: libflame.dylib), PREFIX/lib/libflame.a, both without debug info
#   PREFIX/lib/libflame.so.debug (macOS: libflame.dylib.dSYM), the shared library's debug info
#   PREFIX/lib/pkgconfig/flame.pc, flame-static.pc
#   PREFIX/lib/cmake/flame/flameConfig.cmake, flameConfigVersion.cmake
#
# usage: packaging/install.sh PREFIX
# Environment: DESTDIR (staged install: files go to $DESTDIR$PREFIX, paths inside them name
# PREFIX), FLAME_LIBDIR (default lib), CARGO_TARGET_DIR (as cargo), CARGO (default cargo),
# FLAME_STRIP=0 (install the libraries as cargo built them, debug info inside), OBJCOPY.
#
# The release profile builds with line tables (debug = 1: backtraces, profilers); the installed
# libraries leave them out (packaging/strip.sh): the shared library's go to libflame.so.debug,
# which gdb finds through the library's .gnu_debuglink (delete it if unwanted).
# Linux and macOS; on Windows build with cargo and copy the files by hand (see docs/linking.md).
set -euo pipefail

if [ $# -ne 1 ]; then
    echo "usage: $0 PREFIX" >&2
    exit 2
fi
case "$1" in
    /*) PREFIX="${1%/}" ;;
    *) PREFIX="$(pwd)/${1%/}" ;;
esac
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
cd "$ROOT"
CARGO="${CARGO:-cargo}"
LIBDIR="${FLAME_LIBDIR:-lib}"
TARGET_DIR="${CARGO_TARGET_DIR:-$ROOT/target}"
DEST="${DESTDIR:-}$PREFIX"

VERSION="$(sed -n 's/^version *= *"\([^"]*\)".*/\1/p' Cargo.toml | head -n 1)"
VERSION_MAJOR="${VERSION%%.*}"
VERSION_MINOR="$(echo "$VERSION" | cut -d. -f2)"

# One build that also reports the native libraries a static link needs (cargo replays the note
# when the build is already fresh).
LOG="$(mktemp)"
trap 'rm -f "$LOG"' EXIT
if ! "$CARGO" rustc --release --lib -p flame --quiet -- --print native-static-libs 2>"$LOG"; then
    cat "$LOG" >&2
    exit 1
fi
NATIVE_LIBS="$(sed -n 's/^note: native-static-libs: //p' "$LOG" | tail -n 1)"
if [ -z "$NATIVE_LIBS" ]; then
    echo "install.sh: rustc printed no native-static-libs line" >&2
    exit 1
fi

# The same list for CMake: one element per library, "-framework X" kept together.
CMAKE_LIBS=""
# shellcheck disable=SC2086  # split into words on purpose
set -- $NATIVE_LIBS
while [ $# -gt 0 ]; do
    item="$1"
    if [ "$1" = "-framework" ] && [ $# -gt 1 ]; then
        item="$1 $2"
        shift
    fi
    CMAKE_LIBS="${CMAKE_LIBS:+$CMAKE_LIBS;}$item"
    shift
done

case "$(uname -s)" in
    Darwin) SHARED=libflame.dylib ;;
    *) SHARED=libflame.so ;;
esac
POINTER_BYTES=$(($(getconf LONG_BIT) / 8))

install -d "$DEST/include" "$DEST/$LIBDIR/pkgconfig" "$DEST/$LIBDIR/cmake/flame"
install -m 644 include/flame.h bindings/cpp/flame.hpp "$DEST/include/"
if [ "${FLAME_STRIP:-1}" = 0 ]; then
    install -m 755 "$TARGET_DIR/release/$SHARED" "$DEST/$LIBDIR/"
    install -m 644 "$TARGET_DIR/release/libflame.a" "$DEST/$LIBDIR/"
else
    bash packaging/strip.sh shared "$TARGET_DIR/release/$SHARED" "$DEST/$LIBDIR/$SHARED"
    bash packaging/strip.sh static "$TARGET_DIR/release/libflame.a" "$DEST/$LIBDIR/libflame.a"
    chmod 755 "$DEST/$LIBDIR/$SHARED"
    chmod 644 "$DEST/$LIBDIR/libflame.a"
fi

fill() {
    sed -e "s|@PREFIX@|$PREFIX|g" -e "s|@LIBDIR@|$LIBDIR|g" -e "s|@VERSION@|$VERSION|g" \
        -e "s|@VERSION_MAJOR@|$VERSION_MAJOR|g" -e "s|@VERSION_MINOR@|$VERSION_MINOR|g" \
        -e "s|@NATIVE_STATIC_LIBS@|$NATIVE_LIBS|g" \
        -e "s|@CMAKE_NATIVE_STATIC_LIBS@|\"$CMAKE_LIBS\"|g" \
        -e "s|@SIZEOF_VOID_P@|$POINTER_BYTES|g" "packaging/$1" >"$2"
    chmod 644 "$2"
}
fill flame.pc.in "$DEST/$LIBDIR/pkgconfig/flame.pc"
fill flame-static.pc.in "$DEST/$LIBDIR/pkgconfig/flame-static.pc"
fill flameConfig.cmake.in "$DEST/$LIBDIR/cmake/flame/flameConfig.cmake"
fill flameConfigVersion.cmake.in "$DEST/$LIBDIR/cmake/flame/flameConfigVersion.cmake"

echo "installed libflame $VERSION into $DEST"
