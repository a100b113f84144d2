#!/usr/bin/env bash
# Checks what tools/try.sh wrote into DIR: out.bvh is a complete BVH (hierarchy of the 24 SMPL
# joints, as many motion lines as its frame count says, 6 channels on the root and 3 on every
# other joint), out.png is a PNG whose IHDR and IEND chunks are in place, and out.gif a GIF89a
# (signature, trailer) under 1 MB.
set -euo pipefail
dir="${1:?usage: check_try_output.sh DIR}"
bvh="$dir/out.bvh"
png="$dir/out.png"
gif="$dir/out.gif"
fail() { echo "check_try_output: $*" >&2; exit 1; }
[[ -s "$bvh" ]] || fail "no $bvh"
[[ -s "$png" ]] || fail "no $png"
[[ -s "$gif" ]] || fail "no $gif"
[[ "$(head -c 6 "$gif")" == "GIF89a" ]] || fail "$gif has no GIF89a signature"
[[ "$(tail -c 1 "$gif" | od -An -tx1 | tr -d ' ')" == "3b" ]] || fail "$gif does not end with the GIF trailer"
[[ "$(stat -c %s "$gif")" -lt 1000000 ]] || fail "$gif is $(stat -c %s "$gif") bytes (over 1 MB)"
[[ "$(head -n1 "$bvh")" == "HIERARCHY" ]] || fail "$bvh does not start with HIERARCHY"
joints=$(grep -cE '^\s*(ROOT|JOINT) ' "$bvh")
[[ "$joints" == 24 ]] || fail "$bvh has $joints joints, expected 24"
frames=$(sed -n 's/^Frames:\s*//p' "$bvh")
[[ "$frames" =~ ^[0-9]+$ && "$frames" -gt 0 ]] || fail "$bvh: bad frame count '$frames'"
lines=$(sed -n '/^Frame Time:/,$p' "$bvh" | tail -n +2 | grep -c .)
[[ "$lines" == "$frames" ]] || fail "$bvh: $lines motion lines for $frames frames"
values=$(sed -n '/^Frame Time:/{n;p;q}' "$bvh" | wc -w)
[[ "$values" == $((6 + 23 * 3)) ]] || fail "$bvh: $values values per frame, expected 75"
[[ "$(head -c 8 "$png" | od -An -tx1 | tr -d ' \n')" == "89504e470d0a1a0a" ]] \
    || fail "$png has no PNG signature"
[[ "$(head -c 16 "$png" | tail -c 4)" == "IHDR" ]] || fail "$png: first chunk is not IHDR"
[[ "$(tail -c 8 "$png" | head -c 4)" == "IEND" ]] || fail "$png does not end with IEND"
size=$(od -An -tu1 -j16 -N8 "$png" | xargs printf '%d ' | awk '{print $1*16777216+$2*65536+$3*256+$4 "x" $5*16777216+$6*65536+$7*256+$8}')
echo "ok: $bvh ($frames frames), $png ($size, $(stat -c %s "$png") bytes), $gif ($(stat -c %s "$gif") bytes)"
