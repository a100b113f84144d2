"""Imports a libflame glTF (.glb or .gltf) with Blender's bundled glTF importer, headless, and
compares every frame's joint world positions with the positions libflame's forward kinematics
gives.

    blender -b --factory-startup --python tools/blender_gltf_check.py -- FILE.glb POSITIONS.npy [TOL_M] [--root-bone] [--fps F]

- POSITIONS.npy holds float32 [frames, joints, 3] joint positions in libflame's `gltf`
  convention (what `flame generate --out x.glb --positions p.npy` writes), joints in libflame's
  order; the armature's bones carry the joint names.
- The importer turns glTF's Y-up into Blender's Z-up, (x, y, z) -> (x, -z, y); a bone head's
  world position (bx, by, bz) is therefore (bx, bz, -by) in glTF's frame.
- The scene's frame rate is set to the file's (asset.extras.fps) before the import, so each
  glTF keyframe lands on a whole scene frame; the keyframes are read from the imported action.
- Prints the largest error over all frames and joints (metres) and exits 1 if it exceeds TOL_M
  (default 0.001), or if the imported animation does not have one keyframe per frame, one scene
  frame apart; 2 on a usage or import problem.
- With --root-bone the file must have libflame's `root` bone (the root motion moved to a bone on
  the ground, `--root-motion separate`): POSITIONS.npy then holds the world positions of the clip
  with its root motion kept, which the joints must still reach through the root bone, and on
  every frame the root bone's head must be on the ground (glTF y = 0) under the pelvis, within
  TOL_M.
- With --fps F the file must say it runs at F frames per second (asset.extras.fps) and its
  animation's last key must be at (frames - 1) / F seconds.

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
    root_bone = "--root-bone" in argv
    argv = [a for a in argv if a != "--root-bone"]
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
    if want_fps is not None:
        # The animation's time input: its max is the last key's time.
        times = doc["accessors"][doc["animations"][0]["samplers"][0]["input"]]
        last = times["max"][0]
        if fps != want_fps or abs(last - (frames - 1) / want_fps) > 1e-4:
            print(f"the file runs at {fps} fps with its last key at {last} s; expected {want_fps} fps "
                  f"and {(frames - 1) / want_fps} s for {frames} frames")
            sys.exit(1)
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
    gaps = {round(b - a, 3) for a, b in zip(keys, keys[1:])}
    if gaps and gaps != {1.0}:
        print(f"the imported keyframes are {sorted(gaps)} scene frames apart, not 1 (a wrong rate?)")
        sys.exit(1)
    if root_bone and "root" not in arm.pose.bones:
        print("the armature has no root bone")
        sys.exit(1)
    ground = 0.0  # the root bone's largest distance from the ground point under the pelvis
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
        if root_bone:
            r = mw @ arm.pose.bones["root"].head
            p = mw @ arm.pose.bones[names[0]].head
            # Blender's Z is glTF's y (up); X and Y the ground plane.
            ground = max(ground, abs(r[2]), abs(r[0] - p[0]), abs(r[1] - p[1]))
    root_note = f", root bone at most {ground * 1000:.4f} mm off the ground under the pelvis" if root_bone else ""
    print(f"blender {bpy.app.version_string} glTF importer: {os.path.basename(path)}, "
          f"{frames} frames x {joints} joints at {fps:g} fps (keyframes {keys[0]:g}..{keys[-1]:g}), "
          f"max error {worst * 1000:.4f} mm (frame {where[0]}, {where[1]}){root_note} "
          f"[import + evaluation {time.time() - t0:.2f} s]")
    sys.exit(0 if worst <= tol and ground <= tol else 1)


if __name__ == "__main__":
    # Blender exits 0 after an uncaught exception in a --python script: make failures visible.
    try:
        main()
    except SystemExit:
        raise
    except Exception:
        traceback.print_exc()
        sys.exit(2)
