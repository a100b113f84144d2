"""Imports a libflame BVH into Blender and compares every frame's bone head world positions with
the joint positions libflame expects.

    blender -b --factory-startup --python tools/blender_bvh_check.py -- FILE.bvh EXPECTED.npy [TOL_M] [--upright] [--root-bone] [--fps F]

- FILE.bvh must be written with `--convention gltf` (Y up, right-handed, metres): Blender's BVH
  importer, with its default axis settings (forward -Z, up Y), turns Y-up into its Z-up world by
  (x, y, z) -> (x, -z, y), which is exactly libflame's `blender` convention (Z up, -Y forward).
- EXPECTED.npy holds float32 [frames, joints, 3] positions in convention `blender`, joints in
  libflame's order (for both skeletons that is the breadth-first order of the BVH hierarchy,
  children in file order; tests/motion_bvh.rs checks it).
- Prints the largest error over all frames and joints (metres) and exits 1 if it exceeds TOL_M
  (default 0.001), 2 on a usage or import problem.
- With --upright, also exits 1 unless on every frame the imported Head is at least 0.35 m above
  the Pelvis along Blender's Z (up): a standing character stands, whatever EXPECTED.npy says.
- With --root-bone the file's ROOT must be libflame's `root` bone (the root motion moved to a
  bone on the ground, `--root-motion separate`), above the skeleton: EXPECTED.npy holds the
  joints only (the world positions of the clip with its root motion kept, which the joints must
  still reach through the root bone), and on every frame the root bone's head must be on the
  ground (Blender Z = 0) under the pelvis, within TOL_M.
- With --fps F the import also sets the scene's rate from the file (the importer's
  update_scene_fps), which must come out as F frames per second, and the armature's action must
  hold one keyframe per frame of EXPECTED.npy, one scene frame apart.

Debian's Blender 3.4 importer opens files with mode 'rU', which its Python 3.11 rejects; the mode
is mapped to 'r' around the import (tools/blender_import_bvh.py, also usable on its own).
"""
import os
import struct
import sys
import time
import traceback

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from blender_import_bvh import import_bvh  # noqa: E402


# A standing SMPL body's head is about 0.55 m above its pelvis; lying down it is about 0.
UPRIGHT_M = 0.35


def load_npy_f32(path):
    """A float32 C-order .npy as (shape, flat list): Debian's Blender Python has no NumPy."""
    with open(path, "rb") as f:
        data = f.read()
    if data[:6] != b"\x93NUMPY":
        raise ValueError(f"{path} is not a .npy file")
    if data[6] == 1:
        hlen, start = struct.unpack("<H", data[8:10])[0], 10
    else:
        hlen, start = struct.unpack("<I", data[8:12])[0], 12
    header = eval(data[start:start + hlen].decode("latin1"), {}, {})  # a dict literal
    if header["descr"] != "<f4" or header["fortran_order"]:
        raise ValueError(f"{path}: expected little-endian float32 in C order")
    shape = tuple(header["shape"])
    count = 1
    for d in shape:
        count *= d
    values = struct.unpack(f"<{count}f", data[start + hlen:start + hlen + 4 * count])
    return shape, values


def bfs_order(bvh_path):
    """Joint names of the BVH in breadth-first order of its hierarchy (children in file order)."""
    children, names, stack, in_end = {}, [], [], False
    with open(bvh_path) as f:
        for line in f:
            w = line.split()
            if not w:
                continue
            if w[0] in ("ROOT", "JOINT"):
                parent = next((s for s in reversed(stack) if s is not None), None)
                names.append(w[1])
                children.setdefault(parent, []).append(w[1])
                pending = w[1]
            elif w[0] == "End":
                in_end = True
            elif w[0] == "{":
                stack.append(None if in_end else pending)
            elif w[0] == "}":
                if stack.pop() is None:
                    in_end = False
            elif w[0] == "MOTION":
                break
    order, i = list(children[None]), 0
    while i < len(order):
        order.extend(children.get(order[i], []))
        i += 1
    return order


def main():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    upright = "--upright" in argv
    root_bone = "--root-bone" in argv
    argv = [a for a in argv if a not in ("--upright", "--root-bone")]
    want_fps = None
    if "--fps" in argv:
        i = argv.index("--fps")
        if i + 1 >= len(argv):
            print(__doc__)
            sys.exit(2)
        want_fps = float(argv[i + 1])
        del argv[i:i + 2]
    if len(argv) not in (2, 3):
        print(__doc__)
        sys.exit(2)
    bvh_path, expected_path = argv[0], argv[1]
    tol = float(argv[2]) if len(argv) == 3 else 1e-3

    import bpy

    (frames, joints, _), flat = load_npy_f32(expected_path)
    t0 = time.time()
    # Defaults spelled out: axis_forward '-Z', axis_up 'Y', scale 1, native Euler order,
    # first BVH frame on scene frame 1.
    result = import_bvh(bvh_path, axis_forward="-Z", axis_up="Y", global_scale=1.0,
                        rotate_mode="NATIVE", frame_start=1, use_fps_scale=False,
                        update_scene_fps=want_fps is not None)
    if "FINISHED" not in result:
        print(f"import failed: {result}")
        sys.exit(2)
    arm = next(o for o in bpy.context.scene.objects if o.type == "ARMATURE")
    order = bfs_order(bvh_path)
    if root_bone:
        if order[0] != "root":
            print(f"the file's ROOT is {order[0]}, not the root bone")
            sys.exit(1)
        order = order[1:]
    if want_fps is not None:
        render = bpy.context.scene.render
        rate = render.fps / render.fps_base
        action = arm.animation_data.action
        keys = sorted({round(k.co.x, 3) for fc in action.fcurves for k in fc.keyframe_points})
        gaps = {round(b - a, 3) for a, b in zip(keys, keys[1:])}
        if abs(rate - want_fps) > 1e-3 or len(keys) != frames or (gaps and gaps != {1.0}):
            print(f"the import runs at {rate:g} fps with {len(keys)} keyframes {sorted(gaps)} apart; "
                  f"expected {want_fps:g} fps and {frames} keyframes 1 apart")
            sys.exit(1)
    if len(order) != joints:
        print(f"{bvh_path} has {len(order)} joints, {expected_path} {joints}")
        sys.exit(2)
    scene = bpy.context.scene
    worst, where, lowest, ground = 0.0, None, float("inf"), 0.0
    for t in range(frames):
        scene.frame_set(1 + t)
        mw = arm.matrix_world
        if root_bone:
            r = mw @ arm.pose.bones["root"].head
            p = mw @ arm.pose.bones[order[0]].head
            ground = max(ground, abs(r[2]), abs(r[0] - p[0]), abs(r[1] - p[1]))
        z = {}
        for j, name in enumerate(order):
            head = mw @ arm.pose.bones[name].head
            z[name.lower()] = head[2]
            err = max(abs(head[k] - flat[(t * joints + j) * 3 + k]) for k in range(3))
            if err > worst:
                worst, where = err, (t, name)
        lowest = min(lowest, z["head"] - z["pelvis"])  # SMPL names in either case
    root_note = f", root bone at most {ground * 1000:.4f} mm off the ground under the pelvis" if root_bone else ""
    fps_note = f" at {want_fps:g} fps" if want_fps is not None else ""
    print(f"blender {bpy.app.version_string}: {os.path.basename(bvh_path)}, {frames} frames{fps_note} "
          f"x {joints} joints, max error {worst * 1000:.4f} mm (frame {where[0]}, {where[1]}), "
          f"head at least {lowest:.3f} m above the pelvis along Z{root_note} "
          f"[import + evaluation {time.time() - t0:.2f} s]")
    ok = worst <= tol and ground <= tol and (not upright or lowest >= UPRIGHT_M)
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    # Blender exits 0 after an uncaught exception in a --python script: make failures visible.
    try:
        main()
    except SystemExit:
        raise
    except Exception:
        traceback.print_exc()
        sys.exit(2)
