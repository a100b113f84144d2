"""Imports a libflame glTF (.glb or .gltf) with Blender's bundled glTF importer, headless, and
compares every frame's joint world positions with the positions libflame's forward kinematics
gives.

    blender -b --factory-startup --python tools/blender_gltf_check.py -- FILE.glb POSITIONS.npy [TOL_M]

- POSITIONS.npy holds float32 [frames, joints, 3] joint positions in libflame's `gltf`
  convention (what `flame generate --out x.glb --positions p.npy` writes), joints in libflame's
  order; the armature's bones carry the joint names.
- The importer turns glTF's Y-up into Blender's Z-up, (x, y, z) -> (x, -z, y); a bone head's
  world position (bx, by, bz) is therefore (bx, bz, -by) in glTF's frame.
- The scene's frame rate is set to the file's (asset.extras.fps) before the import, so each
  glTF keyframe lands on a whole scene frame; the keyframes are read from the imported action.
- Prints the largest error over all frames and joints (metres) and exits 1 if it exceeds TOL_M
  (default 0.001), or if the imported animation does not have one keyframe per frame; 2 on a
  usage or import problem.

Debian's Blender 3.4 importer needs NumPy (Debian's python3-numpy, which tools/install_test_deps.sh
installs) and still uses `numpy.bool`, an alias NumPy 1.24 removed; the alias is restored for
the import.
"""
import json
import os
import struct
import sys
import time
import traceback

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from blender_bvh_check import load_npy_f32  # noqa: E402


def gltf_json(path):
    """The JSON document of a .glb or .gltf."""
    with open(path, "rb") as f:
        data = f.read()
    if data[:4] == b"glTF":
        length = struct.unpack("<I", data[12:16])[0]
        return json.loads(data[20:20 + length])
    return json.loads(data)


def main():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    if len(argv) not in (2, 3):
        print(__doc__)
        sys.exit(2)
    path, expected_path = argv[0], argv[1]
    tol = float(argv[2]) if len(argv) == 3 else 1e-3

    import bpy
    import numpy

    if not hasattr(numpy, "bool"):
        numpy.bool = bool

    (frames, joints, _), flat = load_npy_f32(expected_path)
    doc = gltf_json(path)
    fps = doc["asset"]["extras"]["fps"]
    names = [n["name"] for n in doc["nodes"][1:1 + joints]]
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = int(round(fps)), 1.0
    t0 = time.time()
    result = bpy.ops.import_scene.gltf(filepath=os.path.abspath(path))
    if "FINISHED" not in result:
        print(f"import failed: {result}")
        sys.exit(2)
    arm = next(o for o in scene.objects if o.type == "ARMATURE")
    missing = [n for n in names if n not in arm.pose.bones]
    if missing:
        print(f"the armature has no bones {missing}")
        sys.exit(2)
    action = arm.animation_data.action if arm.animation_data else None
    if action is None:
        print("the armature has no animation")
        sys.exit(1)
    keys = sorted({round(k.co.x, 3) for fc in action.fcurves for k in fc.keyframe_points})
    if len(keys) != frames:
        print(f"the imported action has {len(keys)} keyframes, the motion {frames} frames")
        sys.exit(1)
    worst, where = 0.0, None
    for t, key in enumerate(keys):
        scene.frame_set(int(key), subframe=key - int(key))
        mw = arm.matrix_world
        for j, name in enumerate(names):
            b = mw @ arm.pose.bones[name].head
            g = (b[0], b[2], -b[1])
            err = max(abs(g[k] - flat[(t * joints + j) * 3 + k]) for k in range(3))
            if err > worst:
                worst, where = err, (t, name)
    print(f"blender {bpy.app.version_string} glTF importer: {os.path.basename(path)}, "
          f"{frames} frames x {joints} joints at {fps:g} fps (keyframes {keys[0]:g}..{keys[-1]:g}), "
          f"max error {worst * 1000:.4f} mm (frame {where[0]}, {where[1]}) "
          f"[import + evaluation {time.time() - t0:.2f} s]")
    sys.exit(0 if worst <= tol else 1)


if __name__ == "__main__":
    # Blender exits 0 after an uncaught exception in a --python script: make failures visible.
    try:
        main()
    except SystemExit:
        raise
    except Exception:
        traceback.print_exc()
        sys.exit(2)
