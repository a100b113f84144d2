#!/usr/bin/env bash
# Copies a built libflame library to DEST in its shipped form, without debug info:
#
#   shared  DEST keeps its exported C symbols (the dynamic symbol table) and loses the debug
#           sections and the full symbol table, which go to DEST.debug (Linux: objcopy
#           --only-keep-debug, and DEST names it in a .gnu_debuglink section, so gdb finds it
#           beside DEST, in .debug/ there, or under /usr/lib/debug/; macOS: dsymutil writes
#           DEST.dSYM, which lldb finds beside DEST).
#   static  each object of the archive loses its debug sections (objcopy --strip-debug; macOS:
#           strip -S) and, on Linux, the LLVM bitcode Rust's standard library embeds for its own
#           link-time optimisation (.llvmbc, .llvmcmd: no C or C++ linker reads it); symbols
#           stay, as linking needs them. No separate debug file: link the unstripped
#           target/release/libflame.a when debugging a static build.
#
# usage: packaging/strip.sh shared|static SRC DEST
# Environment: OBJCOPY (default objcopy, Linux).
set -euo pipefail

if [ $# -ne 3 ] || { [ "$1" != shared ] && [ "$1" != static ]; }; then
    echo "usage: $0 shared|static SRC DEST" >&2
    exit 2
fi
kind="$1" src="$2" dest="$3"
[ -f "$src" ] || { echo "strip.sh: $src is missing" >&2; exit 1; }
[ -d "$(dirname "$dest")" ] || { echo "strip.sh: no folder $(dirname "$dest")" >&2; exit 1; }
# Writing DEST over SRC would lose the debug info this script means to keep.
if [ -e "$dest" ] && [ "$src" -ef "$dest" ]; then
    echo "strip.sh: DEST must differ from SRC" >&2
    exit 2
fi

need() {
    command -v "$1" >/dev/null || {
        echo "strip.sh: \`$1\` not found ($2); packaging/install.sh installs unstripped libraries with FLAME_STRIP=0" >&2
        exit 1
    }
}

case "$(uname -s)" in
    Darwin)
        need strip "Xcode command line tools"
        if [ "$kind" = shared ]; then
            need dsymutil "Xcode command line tools"
            rm -rf "$dest.dSYM"
            dsymutil "$src" -o "$dest.dSYM"
            strip -S -x -o "$dest" "$src"
        else
            strip -S -o "$dest" "$src"
        fi
        ;;
    *)
        OBJCOPY="${OBJCOPY:-objcopy}"
        need "$OBJCOPY" "GNU binutils"
        if [ "$kind" = shared ]; then
            "$OBJCOPY" --only-keep-debug "$src" "$dest.debug"
            chmod 644 "$dest.debug"
            # The link records the debug file's name (not its folder) and CRC, so it comes second.
            "$OBJCOPY" --strip-unneeded --add-gnu-debuglink="$dest.debug" "$src" "$dest"
        else
            "$OBJCOPY" --strip-debug --remove-section=.llvmbc --remove-section=.llvmcmd \
                "$src" "$dest"
        fi
        ;;
esac
