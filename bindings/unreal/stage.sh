#!/usr/bin/env bash
# Copies what the Flame plugin links against into its ThirdParty folder: include/flame.h and the
# shared library of this machine's platform from target/<profile>/ (Linux or macOS; on Windows,
# copy the two files by hand, see README.md).
#
# usage: bash bindings/unreal/stage.sh [--profile release|debug] [--plugin DIR]
#   --plugin DIR   the plugin to stage into (default: bindings/unreal/Flame, or a copy of it
#                  already in a project's Plugins/ folder)
set -euo pipefail
root="$(cd "$(dirname "$0")/../.." && pwd)"
profile=release
plugin="$root/bindings/unreal/Flame"
while [ $# -gt 0 ]; do
    case "$1" in
        --profile) profile="$2"; shift 2 ;;
        --plugin) plugin="$2"; shift 2 ;;
        *) echo "usage: $0 [--profile release|debug] [--plugin DIR]" >&2; exit 2 ;;
    esac
done

case "$(uname -s)" in
    Linux) platform=Linux; lib=libflame.so ;;
    Darwin) platform=Mac; lib=libflame.dylib ;;
    *) echo "stage.sh: on Windows copy target/release/flame.dll and flame.dll.lib by hand" >&2; exit 1 ;;
esac
src="$root/target/$profile/$lib"
[ -f "$src" ] || { echo "stage.sh: $src is missing: cargo build --$profile" >&2; exit 1; }

third="$plugin/ThirdParty/flame"
mkdir -p "$third/include" "$third/lib/$platform"
cp "$root/include/flame.h" "$third/include/"
cp "$src" "$third/lib/$platform/"

if [ "$platform" = Linux ]; then
    # cargo builds libflame.so without an SONAME, so a binary linked against it by path records
    # that absolute path and a packaged game would look for it on the build machine's disk.
    if command -v patchelf >/dev/null; then
        patchelf --set-soname libflame.so "$third/lib/$platform/$lib"
    else
        echo "stage.sh: warning: patchelf not found; $lib has no SONAME (apt-get install patchelf)" >&2
    fi
fi
echo "staged flame.h and $lib into $third"
