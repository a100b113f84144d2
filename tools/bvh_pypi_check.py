#!/usr/bin/env python3
"""Fallback of tools/blender_bvh_check.py for machines where Blender will not run: reads a
libflame BVH with the `bvh` PyPI package (pure Python, `pip install bvh==0.3`), poses it by the
usual BVH reading (rotation channels composed in the listed order, root position channels plus
the root OFFSET), applies Blender's default import axis conversion (Y up -> Z up:
(x, y, z) -> (x, -z, y)) and compares with the expected positions.

    python3 tools/bvh_pypi_check.py FILE.bvh EXPECTED.npy [TOL_M] [--upright]

Same inputs (--upright included), output and exit codes as blender_bvh_check.py (FILE.bvh in convention gltf,
EXPECTED.npy float32 [frames, joints, 3] in convention blender, libflame's joint order).
"""
import math
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from blender_bvh_check import UPRIGHT_M, bfs_order, load_npy_f32  # noqa: E402  (no bpy needed)


def matmul(a, b):
    return [[sum(a[r][k] * b[k][c] for k in range(3)) for c in range(3)] for r in range(3)]


def apply(m, v):
    return [sum(m[r][k] * v[k] for k in range(3)) for r in range(3)]


def axis_rotation(axis, degrees):
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    if axis == "X":
        return [[1, 0, 0], [0, c, -s], [0, s, c]]
    if axis == "Y":
        return [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    return [[c, -s, 0], [s, c, 0], [0, 0, 1]]


def main():
    upright = "--upright" in sys.argv
    argv = [a for a in sys.argv[1:] if a != "--upright"]
    if len(argv) not in (2, 3):
        print(__doc__)
        sys.exit(2)
    from bvh import Bvh

    bvh_path, expected_path = argv[0], argv[1]
    tol = float(argv[2]) if len(argv) == 3 else 1e-3
    t0 = time.time()
    with open(bvh_path) as f:
        mocap = Bvh(f.read())
    (frames, joints, _), flat = load_npy_f32(expected_path)
    names = mocap.get_joints_names()  # file (depth-first) order: parents before children
    order = bfs_order(bvh_path)
    if len(names) != joints or mocap.nframes != frames:
        print(f"{bvh_path}: {len(names)} joints x {mocap.nframes} frames, expected "
              f"{joints} x {frames}")
        sys.exit(2)
    parent = {n: (mocap.joint_parent(n).name if mocap.joint_parent(n) else None) for n in names}
    offsets = {n: [float(x) for x in mocap.joint_offset(n)] for n in names}
    channels = {n: mocap.joint_channels(n) for n in names}
    worst, where, lowest = 0.0, None, float("inf")
    for t in range(frames):
        world, pos = {}, {}
        for n in names:
            values = [float(v) for v in mocap.frame_joint_channels(t, n, channels[n])]
            rot = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
            local = list(offsets[n])
            for c, v in zip(channels[n], values):
                if c.endswith("rotation"):
                    rot = matmul(rot, axis_rotation(c[0], v))
                else:
                    local["XYZ".index(c[0])] += v
            p = parent[n]
            if p is None:
                pos[n], world[n] = local, rot
            else:
                d = apply(world[p], local)
                pos[n] = [pos[p][k] + d[k] for k in range(3)]
                world[n] = matmul(world[p], rot)
        for j, n in enumerate(order):
            x, y, z = pos[n]
            got = (x, -z, y)  # Blender's default BVH import: forward -Z, up Y
            err = max(abs(got[k] - flat[(t * joints + j) * 3 + k]) for k in range(3))
            if err > worst:
                worst, where = err, (t, n)
        y = {n.lower(): pos[n][1] for n in names}  # Blender's Z is the file's Y
        lowest = min(lowest, y["head"] - y["pelvis"])
    print(f"bvh (PyPI) fallback: {frames} frames x {joints} joints, max error "
          f"{worst * 1000:.4f} mm (frame {where[0]}, {where[1]}), head at least {lowest:.3f} m "
          f"above the pelvis along Z [{time.time() - t0:.2f} s]")
    sys.exit(0 if worst <= tol and (not upright or lowest >= UPRIGHT_M) else 1)


if __name__ == "__main__":
    main()
