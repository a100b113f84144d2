"""Checks a clip retargeted onto a character with Blender's own importers, headless:

    blender -b --factory-startup --python tools/blender_retarget_check.py -- \\
        NAME RIG ANIM.glb RIG_POSITIONS.npy POSITIONS.npy [ANIM.bvh]

RIG is the character file given to `flame generate --rig`; ANIM.glb (or .gltf/.vrm) what
`--out` wrote; RIG_POSITIONS.npy what `--rig-positions` wrote (float32 [frames, bones, 3]: bone
world positions in the rig file's axes and units, bones in the rig's stored order); POSITIONS.npy
what `--positions` wrote (float32 [frames, 24, 3]: libflame's SMPL-24 joints, glTF axes,
metres, floor at y = 0); ANIM.bvh what `--out x.bvh` wrote for the same clip. Prints one line
per check, prefixed with NAME, and exits 1 if any fails, 2 on a usage or import problem.

Blender's glTF importer turns glTF's Y-up into its Z-up by (x, y, z) -> (x, -z, y), and its BVH
importer (defaults: forward -Z, up Y) does the same to a BVH in the rig's glTF axes; every
Blender position below is turned back, (bx, by, bz) -> (bx, bz, -by), and compared in glTF axes
(metres: glTF is in metres, armature-node scales included).

Checks, on every frame:
  (i)   file: the armature's posed bone heads (world) equal RIG_POSITIONS within 1 mm, for
        ANIM.glb and for ANIM.bvh (the files hold what libflame computed). The rig's stored
        order is rebuilt from RIG here: the skin's joints, each one's parent its nearest joint
        ancestor, ordered parents first, otherwise by skin index (lowest ready first).
  (ii)  directions: each mapped bone's world direction (upper arm, forearm, hips -> neck,
        neck -> head, thigh, shin; both sides), from Blender's heads, against the source bone's
        from POSITIONS turned into the rig's axes by C = F_rig · F_srcᵀ, where each F is
        (left, up, forward) from that skeleton's rest pose (left: right thigh -> left thigh;
        up: hips -> neck, or -> head for a rig without a neck, made perpendicular to left;
        forward = left x up). The source's rest is SMPL's (the offsets of
        tools/motion_reference.py), the rig's its bind pose (inverse bind matrices). Median and
        max angle per group: arms and spine/head at most 2 deg median and 5 deg max; legs at
        most 2 deg median and 10 deg max (the feet's IK bends them).
  (iii) skating: the foot-skating ratio of tools/skating_ratio.py on the rig's toe joints,
        heights above the rig's floor (its lowest foot joint at rest; heights along glTF's
        +Y, the world's up for rig and source alike), the
        metric's heights and speeds scaled by the rig's size (its legs' length, thigh plus
        shin at rest, over the source's), is at most the source's.
  (iv)  contacts: where a source toe is planted (the metric's contact, toe below 5 cm at t
        and t+1, and not sliding: slower than 0.5 m/s), the rig's foot is within 5 mm of
        where the source's is: the lowest of its foot joints' (foot, toes) heights above their
        own rest heights (a flat foot at rest stands on the floor, whatever its ankle height)
        against the same of the source's (ankle, toe), scaled by the rig's size. (libflame's
        own planted feet are not all flat: a toe-down or heel-down contact lifts the other
        joint; a rig foot sinking or floating relative to the source's is the error.)

Bone roles (which bone is the upper arm, ...) come from the file: a VRM's humanoid map, else
the naming of the rig's family (Mixamo, SMPL-X joint names, Unreal, Rigify DEF- bones, plain
`.L`/`.R`), looked up
here, not by libflame's bone map.

Debian's Blender 3.4 importers need NumPy's `numpy.bool` alias (glTF) and a BVH opened without
mode 'rU' (tools/blender_import_bvh.py).
"""
import ast
import heapq
import json
import os
import struct
import sys
import time
import traceback

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

TOL_FILE_M = 1e-3
LIMITS = {"arms": (2.0, 5.0), "spine/head": (2.0, 5.0), "legs": (2.0, 10.0)}
CONTACT_TOL_M = 5e-3
# SMPL-24 joints.
PELVIS, L_HIP, R_HIP, L_KNEE, R_KNEE, L_ANKLE, R_ANKLE, L_TOE, R_TOE = 0, 1, 2, 4, 5, 7, 8, 10, 11
NECK, HEAD, L_SHOULDER, R_SHOULDER, L_ELBOW, R_ELBOW, L_WRIST, R_WRIST = 12, 15, 16, 17, 18, 19, 20, 21


def smpl_rest():
    """SMPL-24's rest joint positions (glTF axes), from tools/motion_reference.py's offsets
    (read as a literal: that module needs SciPy, Blender's Python has none)."""
    import numpy as np
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "motion_reference.py")
    tree = ast.parse(open(path).read())
    values = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1:
            name = getattr(node.targets[0], "id", None)
            if name == "SMPL_PARENTS":
                values[name] = ast.literal_eval(node.value)
            elif name == "SMPL_OFFSETS":
                values[name] = np.array(ast.literal_eval(node.value.args[0]))
    parents, offsets = values["SMPL_PARENTS"], values["SMPL_OFFSETS"]
    pos = np.zeros((24, 3))
    for j in range(1, 24):
        pos[j] = pos[parents[j]] + offsets[j]
    return pos


def gltf_json(path):
    return gltf_parts(path)[0]


def gltf_parts(path):
    """A .glb's or .gltf's JSON document and its GLB binary chunk (None for .gltf)."""
    with open(path, "rb") as f:
        data = f.read()
    if data[:4] == b"glTF":
        length = struct.unpack("<I", data[12:16])[0]
        doc = json.loads(data[20:20 + length])
        rest = data[20 + length:]
        binary = rest[8:8 + struct.unpack("<I", rest[:4])[0]] if len(rest) >= 8 else None
        return doc, binary
    return json.loads(data), None


def buffer_bytes(doc, binary, index):
    """Buffer `index`: the GLB chunk, or a base64 data URI."""
    import base64
    uri = doc["buffers"][index].get("uri")
    if uri is None:
        return binary
    return base64.b64decode(uri.split(",", 1)[1])


def skin_of(doc):
    """The skin libflame reads without a name: the only one, or a VRM's holding its humanoid
    bones."""
    skins = doc["skins"]
    if len(skins) == 1:
        return skins[0]
    human = set(humanoid_nodes(doc).values())
    return next(s for s in skins if human <= set(s["joints"]))


def rest_positions(path):
    """name -> bind-pose world position (glTF axes) of every joint of the rig's skin: the
    translation of the inverse of its inverse bind matrix."""
    import numpy as np
    doc, binary = gltf_parts(path)
    skin = skin_of(doc)
    acc = doc["accessors"][skin["inverseBindMatrices"]]
    view = doc["bufferViews"][acc["bufferView"]]
    data = buffer_bytes(doc, binary, view["buffer"])
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    ibm = np.frombuffer(data, dtype="<f4", count=16 * acc["count"], offset=start)
    # Column-major 4x4: reshaped row-major it is the transpose.
    mats = ibm.reshape(-1, 4, 4).transpose(0, 2, 1).astype(np.float64)
    names = [doc["nodes"][n].get("name", f"node{n}") for n in skin["joints"]]
    return {n: np.linalg.inv(m)[:3, 3] for n, m in zip(names, mats)}


def stored_order(doc):
    """The rig's bone names in libflame's stored order (module doc, check i)."""
    joints = skin_of(doc)["joints"]
    node_parent = {}
    for i, n in enumerate(doc["nodes"]):
        for c in n.get("children", []):
            node_parent[c] = i
    slot = {node: k for k, node in enumerate(joints)}
    parent = []
    for node in joints:
        p = node_parent.get(node)
        while p is not None and p not in slot:
            p = node_parent.get(p)
        parent.append(None if p is None else slot[p])
    children = [[] for _ in joints]
    ready = []
    for k, p in enumerate(parent):
        if p is None:
            heapq.heappush(ready, k)
        else:
            children[p].append(k)
    order = []
    while ready:
        k = heapq.heappop(ready)
        order.append(k)
        for c in children[k]:
            heapq.heappush(ready, c)
    names = [doc["nodes"][node].get("name", f"node{node}") for node in joints]
    return [names[k] for k in order]


def humanoid_nodes(doc):
    """A VRM file's humanoid map: VRM bone name -> node index (empty for plain glTF)."""
    ext = doc.get("extensions", {})
    if "VRMC_vrm" in ext:
        bones = ext["VRMC_vrm"]["humanoid"]["humanBones"]
        return {k: v["node"] for k, v in bones.items()}
    if "VRM" in ext:
        return {b["bone"]: b["node"] for b in ext["VRM"]["humanoid"]["humanBones"]}
    return {}


def roles(doc, names):
    """role -> bone name: hips, neck (or None), head, and per side s in l, r: s_arm, s_fore,
    s_hand, s_thigh, s_shin, s_foot, s_toe."""
    human = humanoid_nodes(doc)
    if human:
        node = lambda b: doc["nodes"][human[b]].get("name", f"node{human[b]}") if b in human else None
        r = {"hips": node("hips"), "neck": node("neck"), "head": node("head")}
        for s, side in (("l", "left"), ("r", "right")):
            for role, bone in (("arm", "UpperArm"), ("fore", "LowerArm"), ("hand", "Hand"),
                               ("thigh", "UpperLeg"), ("shin", "LowerLeg"), ("foot", "Foot"),
                               ("toe", "Toes")):
                r[f"{s}_{role}"] = node(side + bone)
        return r
    have = set(names)
    tables = [
        ("mixamorig:Hips", lambda s: {
            "hips": "mixamorig:Hips", "neck": "mixamorig:Neck", "head": "mixamorig:Head",
            **{f"{s[0]}_{k}": f"mixamorig:{s[1]}{v}" for k, v in (
                ("arm", "Arm"), ("fore", "ForeArm"), ("hand", "Hand"), ("thigh", "UpLeg"),
                ("shin", "Leg"), ("foot", "Foot"), ("toe", "ToeBase"))}}),
        ("left_hip", lambda s: {
            "hips": "pelvis", "neck": "neck", "head": "head",
            **{f"{s[0]}_{k}": f"{s[1].lower()}_{v}" for k, v in (
                ("arm", "shoulder"), ("fore", "elbow"), ("hand", "wrist"), ("thigh", "hip"),
                ("shin", "knee"), ("foot", "ankle"), ("toe", "foot"))}}),
        ("spine_01", lambda s: {
            "hips": "pelvis", "neck": "neck_01", "head": "head",
            **{f"{s[0]}_{k}": f"{v}_{s[0]}" for k, v in (
                ("arm", "upperarm"), ("fore", "lowerarm"), ("hand", "hand"), ("thigh", "thigh"),
                ("shin", "calf"), ("foot", "foot"), ("toe", "ball"))}}),
        # Blender's human metarig: spine (hips), .001-.003 (torso), .004-.005 (neck),
        # .006 (head).
        ("DEF-spine", lambda s: {
            "hips": "DEF-spine", "neck": "DEF-spine.004", "head": "DEF-spine.006",
            **{f"{s[0]}_{k}": f"DEF-{v}.{s[0].upper()}" for k, v in (
                ("arm", "upper_arm"), ("fore", "forearm"), ("hand", "hand"), ("thigh", "thigh"),
                ("shin", "shin"), ("foot", "foot"), ("toe", "toe"))}}),
        ("hips", lambda s: {
            "hips": "hips", "neck": "neck", "head": "head",
            **{f"{s[0]}_{k}": f"{v}.{s[0].upper()}" for k, v in (
                ("arm", "upper_arm"), ("fore", "forearm"), ("hand", "hand"), ("thigh", "thigh"),
                ("shin", "shin"), ("foot", "foot"), ("toe", "toe"))}}),
    ]
    for hips, make in tables:
        if hips in have:
            r = {}
            for side in (("l", "Left"), ("r", "Right")):
                r.update(make(side))
            return {k: (v if v in have else None) for k, v in r.items()}
    raise SystemExit(f"no bone roles known for a rig with bones {names[:6]}...")


def frame_of(left, up):
    """(left, up, forward) columns of a character standing in its world: up is the world axis
    nearest to its hips-to-neck line and left the horizontal world axis nearest to its right
    thigh-to-left thigh line. A character stands along its world's up and faces along one of
    its axes, while its spine leans at rest by its own amount (SMPL's about 5 degrees forward),
    so directions are compared in the two worlds, not along the two leans."""
    import numpy as np

    def axis(v):
        a = np.zeros(3)
        i = int(np.argmax(np.abs(v)))
        a[i] = np.sign(v[i])
        return a

    u = axis(up)
    l = axis(left - u * np.dot(left, u))
    return np.stack([l, u, np.cross(l, u)], axis=1)


def angles(a, b):
    import numpy as np
    cos = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def to_gltf(v):
    return (v[0], v[2], -v[1])


def clear_scene():
    import bpy
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob)
    for a in list(bpy.data.actions):
        bpy.data.actions.remove(a)
    for arm in list(bpy.data.armatures):
        bpy.data.armatures.remove(arm)


def posed_heads(arm, names, frames):
    """[frames, len(names), 3] world bone heads in glTF axes at scene frames `frames`."""
    import bpy
    import numpy as np
    out = np.zeros((len(frames), len(names), 3))
    bones = [arm.pose.bones[n] for n in names]
    for t, f in enumerate(frames):
        bpy.context.scene.frame_set(int(f), subframe=f - int(f))
        mw = arm.matrix_world
        for k, b in enumerate(bones):
            out[t, k] = to_gltf(mw @ b.head)
    return out


class Report:
    def __init__(self, name):
        self.name, self.failed = name, []

    def line(self, check, ok, text):
        print(f"{self.name}: {check}: {'ok' if ok else 'FAIL'}: {text}")
        if not ok:
            self.failed.append(check)


def measure(rep, heads, rest, idx, role, src, fps):
    """Checks (ii) to (iv) on `heads` [frames, bones, 3] (glTF axes), the rig's bones in
    stored order (`idx`: name -> index), `rest` their bind-pose positions."""
    import numpy as np
    from skating_ratio import skating_mask
    frames = len(heads)
    # (ii) directions.
    s_rest = smpl_rest()
    top = NECK if role["neck"] else HEAD
    f_src = frame_of(s_rest[L_HIP] - s_rest[R_HIP], s_rest[top] - s_rest[PELVIS])
    up_bone = role["neck"] or role["head"]
    f_rig = frame_of(rest[idx[role["l_thigh"]]] - rest[idx[role["r_thigh"]]],
                     rest[idx[up_bone]] - rest[idx[role["hips"]]])
    c = f_rig @ f_src.T
    segments = {"arms": [], "spine/head": [], "legs": []}
    for s, (sh, el, wr, hp, kn, an) in (("l", (L_SHOULDER, L_ELBOW, L_WRIST, L_HIP, L_KNEE, L_ANKLE)),
                                        ("r", (R_SHOULDER, R_ELBOW, R_WRIST, R_HIP, R_KNEE, R_ANKLE))):
        segments["arms"] += [(f"{s}_arm", f"{s}_fore", sh, el), (f"{s}_fore", f"{s}_hand", el, wr)]
        segments["legs"] += [(f"{s}_thigh", f"{s}_shin", hp, kn), (f"{s}_shin", f"{s}_foot", kn, an)]
    if role["neck"]:
        segments["spine/head"] += [("hips", "neck", PELVIS, NECK), ("neck", "head", NECK, HEAD)]
    else:
        segments["spine/head"] += [("hips", "head", PELVIS, HEAD)]
    for group, segs in segments.items():
        worst = []
        per = []
        for a, b, ja, jb in segs:
            got = heads[:, idx[role[a]]] - heads[:, idx[role[b]]]
            want = (src[:, ja] - src[:, jb]) @ c.T
            ang = angles(got, want)
            worst.append(ang)
            per.append(f"{role[a]}->{role[b]} {np.median(ang):.2f}/{ang.max():.2f}")
        ang = np.concatenate(worst)
        med_lim, max_lim = LIMITS[group]
        ok = np.median(ang) <= med_lim and ang.max() <= max_lim
        rep.line(f"directions {group}", ok,
                 f"median {np.median(ang):.3f} deg, max {ang.max():.3f} deg "
                 f"(limits {med_lim:g}/{max_lim:g}; per bone median/max: {'; '.join(per)})")

    # (iii) skating and (iv) contacts. Heights are along the world's up, glTF's +Y (the glTF
    # specification's, and the source's): not along the bodies' up of (ii), which leans with
    # each skeleton's rest spine.
    up = np.array([0.0, 1.0, 0.0])
    feet = {s: [role[f"{s}_foot"], role[f"{s}_toe"]] for s in "lr"}
    floor = min(rest[idx[n]] @ up for s in "lr" for n in feet[s] if n)
    src_floor = min(s_rest[j] @ up for j in (L_ANKLE, R_ANKLE, L_TOE, R_TOE))
    # The rig's size: its legs' length (thigh plus shin, both sides' mean) over the source's.
    # Not the hips bone's height: a rig may hang its hips bone below its thighs (Rigify) or
    # above them.
    def leg(p, h, k, a):
        return np.linalg.norm(p(k) - p(h)) + np.linalg.norm(p(a) - p(k))
    rig_p = lambda r: rest[idx[role[r]]]
    rig_legs = np.mean([leg(rig_p, f"{s}_thigh", f"{s}_shin", f"{s}_foot") for s in "lr"])
    src_legs = np.mean([leg(lambda j: s_rest[j], h, k, a)
                        for h, k, a in ((L_HIP, L_KNEE, L_ANKLE), (R_HIP, R_KNEE, R_ANKLE))])
    scale = rig_legs / src_legs
    # The rig's toes, heights above its floor, divided by its size: the metric's 5 cm and
    # 0.5 m/s become the rig's.
    toes = np.zeros((frames, 12, 3))
    for k, s in ((L_TOE, "l"), (R_TOE, "r")):
        p = heads[:, idx[role[f"{s}_toe"]]] - up * floor
        toes[:, k] = p / scale
    rig_mask = skating_mask(toes, fps)
    src_mask = skating_mask(src, fps)
    rig_ratio, src_ratio = rig_mask.mean(), src_mask.mean()
    rep.line("skating", rig_ratio <= src_ratio,
             f"rig {rig_ratio:.4f} ({rig_mask.sum()} of {len(rig_mask)} steps), source "
             f"{src_ratio:.4f} ({src_mask.sum()}); rig size {scale:.3f} x the source's")
    counts, heights, expected = [], [], []
    for j, ankle, s in ((L_TOE, L_ANKLE, "l"), (R_TOE, R_ANKLE, "r")):
        y = src[:, j, 1]
        step = np.linalg.norm((src[1:, j] - src[:-1, j])[:, [0, 2]], axis=1) * fps
        planted = np.nonzero((y[:-1] < 0.05) & (y[1:] < 0.05) & (step <= 0.5))[0]
        # Each foot joint's height above where it stands at rest (a flat foot at rest is on
        # the floor; the joints' own heights differ with each rig's foot), the lowest of them.
        rig_low = np.min([heads[:, idx[n]] @ up - rest[idx[n]] @ up for n in feet[s] if n],
                         axis=0)
        src_low = np.minimum(src[:, j, 1] - (s_rest[j] @ up - src_floor),
                             src[:, ankle, 1] - (s_rest[ankle] @ up - src_floor))
        heights.append(rig_low[planted])
        expected.append(scale * src_low[planted])
        counts.append(len(planted))
    h, e = np.concatenate(heights), np.concatenate(expected)
    off = np.abs(h - e).max() if len(h) else 0.0
    rep.line("contacts", off <= CONTACT_TOL_M,
             f"{sum(counts)} planted foot-frames: the rig's lowest foot joint "
             f"{h.min() * 1000:.2f}..{h.max() * 1000:.2f} mm above its rest height, at most "
             f"{off * 1000:.2f} mm from the source's scaled ({e.min() * 1000:.2f}.."
             f"{e.max() * 1000:.2f} mm; limit {CONTACT_TOL_M * 1000:g} mm)")



def main():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    if len(argv) not in (5, 6):
        print(__doc__)
        sys.exit(2)
    name, rig_path, anim_path, rig_npy, src_npy = argv[:5]
    bvh_path = argv[5] if len(argv) == 6 else None

    import bpy
    import numpy as np
    if not hasattr(np, "bool"):
        np.bool = bool
    from blender_import_bvh import import_bvh

    t0 = time.time()
    rep = Report(name)
    rig_pos = np.load(rig_npy).astype(np.float64)
    src = np.load(src_npy).astype(np.float64)
    frames, bones, _ = rig_pos.shape
    if src.shape != (frames, 24, 3):
        print(f"{src_npy} is {src.shape}, expected [{frames}, 24, 3]")
        sys.exit(2)
    doc = gltf_json(rig_path)
    order = stored_order(doc)
    if len(order) != bones:
        print(f"{rig_path} has {len(order)} bones, {rig_npy} {bones}")
        sys.exit(2)
    role = roles(doc, order)
    anim_doc = gltf_json(anim_path)
    times = anim_doc["accessors"][anim_doc["animations"][0]["samplers"][0]["input"]]
    fps = (times["count"] - 1) / times["max"][0]

    # (i) the glTF file.
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = int(round(fps)), 1.0
    clear_scene()
    result = bpy.ops.import_scene.gltf(filepath=os.path.abspath(anim_path))
    if "FINISHED" not in result:
        print(f"import failed: {result}")
        sys.exit(2)
    arm = next(o for o in scene.objects if o.type == "ARMATURE")
    missing = [n for n in order if n not in arm.pose.bones]
    if missing:
        print(f"the imported armature has no bones {missing[:5]}")
        sys.exit(2)
    action = arm.animation_data.action if arm.animation_data else None
    keys = sorted({round(k.co.x, 3) for fc in action.fcurves for k in fc.keyframe_points}) \
        if action else []
    if len(keys) != frames:
        rep.line("file", False, f"{os.path.basename(anim_path)}: {len(keys)} keyframes for "
                 f"{frames} frames")
        keys = keys[:frames] if len(keys) >= frames else [k for k in range(frames)]
    heads = posed_heads(arm, order, keys)
    err = np.abs(heads - rig_pos).max(axis=2)
    t, b = np.unravel_index(err.argmax(), err.shape)
    rep.line("file", err.max() <= TOL_FILE_M,
             f"{os.path.basename(anim_path)}: {frames} frames x {bones} bones at {fps:g} fps, "
             f"max {err.max() * 1000:.4f} mm from --rig-positions (frame {t}, {order[b]})")
    # The rig's rest from its file's bind pose (Blender's imported rest is not it: the
    # importer moves bones).
    rest_by_name = rest_positions(rig_path)
    rest = np.array([rest_by_name[n] for n in order])
    idx = {n: k for k, n in enumerate(order)}

    measure(rep, heads, rest, idx, role, src, fps)

    # (i) the BVH.
    if bvh_path:
        clear_scene()
        result = import_bvh(os.path.abspath(bvh_path), axis_forward="-Z", axis_up="Y",
                            global_scale=1.0, rotate_mode="NATIVE", frame_start=1,
                            use_fps_scale=False, update_scene_fps=False)
        if "FINISHED" not in result:
            print(f"BVH import failed: {result}")
            sys.exit(2)
        arm = next(o for o in scene.objects if o.type == "ARMATURE")
        # BVH names are one token: whitespace became `_`, as Blender's importer does too.
        bvh_names = ["_".join(n.split()) for n in order]
        heads_bvh = posed_heads(arm, bvh_names, [1 + t for t in range(frames)])
        err = np.abs(heads_bvh - rig_pos).max(axis=2)
        t, b = np.unravel_index(err.argmax(), err.shape)
        rep.line("file", err.max() <= TOL_FILE_M,
                 f"{os.path.basename(bvh_path)}: max {err.max() * 1000:.4f} mm from "
                 f"--rig-positions (frame {t}, {order[b]})")
    verdict = "FAIL " + ", ".join(rep.failed) if rep.failed else "all checks ok"
    print(f"{name}: {verdict} [blender {bpy.app.version_string}, {time.time() - t0:.1f} s]")
    sys.exit(1 if rep.failed else 0)


if __name__ == "__main__":
    # Blender exits 0 after an uncaught exception in a --python script: make failures visible.
    try:
        main()
    except SystemExit:
        raise
    except Exception:
        traceback.print_exc()
        sys.exit(2)
