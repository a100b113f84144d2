"""Makes a Rigify character the way a game pipeline does and exports it as GLB, headless:

    blender -b --factory-startup --python tools/blender_rigify_rig.py -- OUT.glb

- Enables Blender's bundled Rigify add-on, adds its human metarig
  (`bpy.ops.object.armature_human_metarig_add()`) and generates the rig
  (`bpy.ops.pose.rigify_generate()`): the control, mechanism (`MCH-`), original (`ORG-`) and
  deform (`DEF-`) bones of a real Rigify character.
- Adds a mesh of one box per deform bone, each box weighted fully to its bone (a vertex group
  per bone, an Armature modifier on the generated rig).
- Exports glTF binary with deform bones only (`export_def_bones=True`), no animation, as game
  pipelines export Rigify characters (the control and mechanism bones mean nothing to an
  engine). Blender's exporter then keeps a deform bone's nearest deform ancestor as its parent
  and hangs a deform bone with none (DEF-thigh.L, whose armature parent is ORG-spine, a
  non-deform bone) directly under the armature node: the file's skin has several top joints.
- Prints `rigify: <bone> <- <parent or (armature)>` for the bones the retarget check maps
  (spine, thighs, upper arms, shoulders) as the exported file has them, read back from its JSON.

Exit code 0 when the file is written, 2 on a failure (Blender's `--python-exit-code 2`).
"""
import json
import struct
import sys

import addon_utils
import bpy
import bmesh
from mathutils import Vector


def main():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    if len(argv) != 1:
        raise SystemExit("usage: blender -b --factory-startup --python "
                         "tools/blender_rigify_rig.py -- OUT.glb")
    out = argv[0]
    addon_utils.enable("rigify", default_set=True, persistent=False)
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob)
    bpy.ops.object.armature_human_metarig_add()
    metarig = bpy.context.active_object
    bpy.ops.object.mode_set(mode="POSE")
    bpy.ops.pose.rigify_generate()
    bpy.ops.object.mode_set(mode="OBJECT")
    rig = next(o for o in bpy.data.objects if o.type == "ARMATURE" and o is not metarig)
    # The metarig is a template, not part of the character.
    bpy.data.objects.remove(metarig)
    # Rigify's widget shapes live in their own collection; they are not meshes of the character.
    for coll in list(bpy.data.collections):
        if coll.name.startswith("WGTS"):
            for ob in list(coll.objects):
                bpy.data.objects.remove(ob)
            bpy.data.collections.remove(coll)

    deform = [b for b in rig.data.bones if b.use_deform]
    mesh = bpy.data.meshes.new("body")
    bm = bmesh.new()
    groups = []
    for b in deform:
        head = rig.matrix_world @ b.head_local
        tail = rig.matrix_world @ b.tail_local
        axis = tail - head
        half = max(0.005, min(0.04, 0.2 * axis.length))
        u = axis.orthogonal().normalized() * half
        v = axis.cross(u).normalized() * half
        verts = [bm.verts.new(end + su * u + sv * v)
                 for end in (head, tail) for su in (-1, 1) for sv in (-1, 1)]
        for q in ((0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4),
                  (1, 5, 7, 3)):
            bm.faces.new([verts[k] for k in q])
        groups.append((b.name, len(bm.verts) - 8))
    bm.to_mesh(mesh)
    bm.free()
    body = bpy.data.objects.new("body", mesh)
    bpy.context.scene.collection.objects.link(body)
    for name, first in groups:
        vg = body.vertex_groups.new(name=name)
        vg.add(list(range(first, first + 8)), 1.0, "REPLACE")
    # Not parented to the rig: glTF wants a skinned mesh's node at the scene root (the
    # validator warns otherwise); the Armature modifier alone makes the skin.
    mod = body.modifiers.new("Armature", "ARMATURE")
    mod.object = rig

    bpy.ops.object.select_all(action="DESELECT")
    bpy.ops.export_scene.gltf(
        filepath=out,
        export_format="GLB",
        export_def_bones=True,
        export_animations=False,
        export_skins=True,
        export_yup=True,
    )
    report(out, rig)


def report(path, rig):
    """The exported hierarchy of the bones the check maps, read back from the file."""
    with open(path, "rb") as f:
        data = f.read()
    length = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + length])
    nodes = doc["nodes"]
    parent = {}
    for i, n in enumerate(nodes):
        for c in n.get("children", []):
            parent[c] = i
    joints = set(doc["skins"][0]["joints"])
    print(f"rigify: {len(joints)} joints in the skin, "
          f"{sum(1 for j in joints if parent.get(j) not in joints)} top joints")
    for i, n in enumerate(nodes):
        name = n.get("name", "")
        if i in joints and (name in ("DEF-spine", "DEF-spine.003", "DEF-spine.004")
                            or name.startswith(("DEF-thigh", "DEF-upper_arm", "DEF-shoulder"))):
            p = parent.get(i)
            above = nodes[p].get("name", "") if p is not None else "(scene)"
            kind = "joint" if p in joints else "not a joint"
            print(f"rigify: {name} <- {above} ({kind}); in Blender's armature: "
                  f"{rig.data.bones[name].parent.name if rig.data.bones[name].parent else '-'}")


try:
    main()
except SystemExit:
    raise
except Exception:
    import traceback
    traceback.print_exc()
    sys.exit(2)
