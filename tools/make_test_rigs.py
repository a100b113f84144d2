#!/usr/bin/env python3
"""Writes the skinned test rigs of tests/fixtures/rigs/ (deterministic: same bytes every run).

    target/test-venv/bin/python tools/make_test_rigs.py [OUT_DIR]

Three characters unlike libflame's SMPL skeleton and unlike each other, each a GLB with one
armature, one skin (inverse bind matrices) and a box mesh per bone (JOINTS_0 / WEIGHTS_0, each
box weighted fully to its bone), so Blender and engines import them as characters:

- mixamo.glb: Mixamo's bone names (`mixamorig:Hips` ... `mixamorig:HeadTop_End`, shoulders,
  thumb and index fingers, toes and `Toe_End` leaves), 1.78 m, T-pose, the way a Mixamo FBX
  comes out of Blender's glTF exporter: bones in centimetres under a non-joint `Armature` node
  with a 90 degree rotation about X and a 0.01 scale (inside it the character is -Z up, +Y
  forward).
- apose.glb: Unreal mannequin names (`root`, `pelvis`, `spine_01`..`spine_05`, `neck_01`,
  `head`, `clavicle_l`, `upperarm_l`, `upperarm_twist_01_l`, `lowerarm_l`, `hand_l`, `thigh_l`,
  `thigh_twist_01_l`, `calf_l`, `foot_l`, `ball_l`, right side `_r`), 1.85 m, A-pose (arms 45
  degrees down), metres; Unreal's Z-up, -Y-forward frame baked into the bind pose: the `root`
  joint's node rotation is -90 degrees about X.
- child.glb: a child 1.10 m tall, head a fifth of the height, short legs, no neck and no
  shoulder bones, Rigify-style `.L`/`.R` names (`hips`, `spine`, `chest`, `head`,
  `upper_arm.L`, `forearm.L`, `hand.L`, `thigh.L`, `shin.L`, `foot.L`, `toe.L`), facing -Z (as
  VRM 0.x models do).

Every bone has its own rest rotation, as exporters make them: its +Y axis along the bone (to its
first child, a leaf along its parent's bone) and a roll about that axis that differs per bone.
All three stand on y = 0 (soles) in glTF's Y-up world.

    target/test-venv/bin/python tools/make_test_rigs.py --control OUT_DIR

writes instead smpl.glb (not committed): SMPL-24's own rest skeleton (the offsets of
tools/motion_reference.py; SMPL-X joint names, `pelvis` ... `right_hand`), lowest foot joint on
y = 0, every bone rolled like the others: the control of tools/retarget_check.sh, a rig on which
a retarget has nothing to change but the rest rotations, so its checks must pass.
"""

import os
import struct
import sys

import numpy as np
import pygltflib as g

# glTF component types and targets.
FLOAT, UBYTE, USHORT = 5126, 5121, 5123
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


def rot_x(deg):
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(deg):
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def axis_angle(axis, angle):
    x, y, z = axis / np.linalg.norm(axis)
    c, s, t = np.cos(angle), np.sin(angle), 1 - np.cos(angle)
    return np.array([
        [c + t * x * x, t * x * y - s * z, t * x * z + s * y],
        [t * x * y + s * z, c + t * y * y, t * y * z - s * x],
        [t * x * z - s * y, t * y * z + s * x, c + t * z * z],
    ])


def quat_xyzw(m):
    """A rotation matrix as a glTF quaternion (x, y, z, w), w >= 0."""
    w = np.sqrt(max(0.0, 1 + m[0, 0] + m[1, 1] + m[2, 2])) / 2
    x = np.sqrt(max(0.0, 1 + m[0, 0] - m[1, 1] - m[2, 2])) / 2
    y = np.sqrt(max(0.0, 1 - m[0, 0] + m[1, 1] - m[2, 2])) / 2
    z = np.sqrt(max(0.0, 1 - m[0, 0] - m[1, 1] + m[2, 2])) / 2
    x = np.copysign(x, m[2, 1] - m[1, 2])
    y = np.copysign(y, m[0, 2] - m[2, 0])
    z = np.copysign(z, m[1, 0] - m[0, 1])
    q = np.array([x, y, z, w])
    return q / np.linalg.norm(q)


def aim_y(direction, roll):
    """A rotation whose +Y points along `direction`, turned by `roll` radians about it."""
    d = direction / np.linalg.norm(direction)
    y = np.array([0.0, 1.0, 0.0])
    axis = np.cross(y, d)
    s, c = np.linalg.norm(axis), np.dot(y, d)
    if s < 1e-9:
        base = np.eye(3) if c > 0 else rot_x(180)
    else:
        base = axis_angle(axis, np.arctan2(s, c))
    return base @ axis_angle(y, roll)


def mirror(joints):
    """Left-side joints (name containing `{s}`, `{S}` or `{Side}`) and their right twins (x
    negated). Left is +X in glTF's frame for a character facing +Z."""
    out = []
    for name, parent, pos in joints:
        if "{" not in name:
            out.append((name, parent, pos))
            continue
        for side, s, S, sgn in (("Left", "l", "L", 1.0), ("Right", "r", "R", -1.0)):
            fill = dict(Side=side, s=s, S=S)
            p = None if parent is None else parent.format(**fill)
            out.append((name.format(**fill), p, np.array([sgn * pos[0], pos[1], pos[2]])))
    return out


def mixamo_joints():
    m = "mixamorig:"
    j = [
        (m + "Hips", None, (0, 1.00, 0.0)),
        (m + "Spine", m + "Hips", (0, 1.10, 0.01)),
        (m + "Spine1", m + "Spine", (0, 1.22, 0.015)),
        (m + "Spine2", m + "Spine1", (0, 1.35, 0.0)),
        (m + "Neck", m + "Spine2", (0, 1.51, -0.01)),
        (m + "Head", m + "Neck", (0, 1.60, 0.01)),
        (m + "HeadTop_End", m + "Head", (0, 1.78, 0.02)),
        (m + "{Side}Shoulder", m + "Spine2", (0.06, 1.46, -0.01)),
        (m + "{Side}Arm", m + "{Side}Shoulder", (0.18, 1.45, -0.02)),
        (m + "{Side}ForeArm", m + "{Side}Arm", (0.46, 1.45, -0.03)),
        (m + "{Side}Hand", m + "{Side}ForeArm", (0.71, 1.45, -0.02)),
        (m + "{Side}HandThumb1", m + "{Side}Hand", (0.74, 1.43, 0.02)),
        (m + "{Side}HandThumb2", m + "{Side}HandThumb1", (0.77, 1.42, 0.05)),
        (m + "{Side}HandThumb3", m + "{Side}HandThumb2", (0.80, 1.41, 0.07)),
        (m + "{Side}HandIndex1", m + "{Side}Hand", (0.80, 1.45, 0.01)),
        (m + "{Side}HandIndex2", m + "{Side}HandIndex1", (0.845, 1.45, 0.01)),
        (m + "{Side}HandIndex3", m + "{Side}HandIndex2", (0.875, 1.45, 0.01)),
        (m + "{Side}UpLeg", m + "Hips", (0.09, 0.95, 0.0)),
        (m + "{Side}Leg", m + "{Side}UpLeg", (0.095, 0.52, 0.015)),
        (m + "{Side}Foot", m + "{Side}Leg", (0.10, 0.085, -0.025)),
        (m + "{Side}ToeBase", m + "{Side}Foot", (0.105, 0.02, 0.11)),
        (m + "{Side}Toe_End", m + "{Side}ToeBase", (0.11, 0.02, 0.19)),
    ]
    return mirror([(a, b, np.array(c, dtype=float)) for a, b, c in j])


def apose_joints():
    j = [
        ("root", None, (0, 0.0, 0.0)),
        ("pelvis", "root", (0, 1.04, 0.0)),
        ("spine_01", "pelvis", (0, 1.12, 0.005)),
        ("spine_02", "spine_01", (0, 1.20, 0.01)),
        ("spine_03", "spine_02", (0, 1.28, 0.01)),
        ("spine_04", "spine_03", (0, 1.37, 0.0)),
        ("spine_05", "spine_04", (0, 1.46, -0.01)),
        ("neck_01", "spine_05", (0, 1.57, -0.015)),
        ("head", "neck_01", (0, 1.66, 0.0)),
        ("clavicle_{s}", "spine_05", (0.05, 1.50, 0.0)),
        ("upperarm_{s}", "clavicle_{s}", (0.19, 1.50, -0.02)),
        ("upperarm_twist_01_{s}", "upperarm_{s}", None),
        ("lowerarm_{s}", "upperarm_{s}", None),
        ("hand_{s}", "lowerarm_{s}", None),
        ("thigh_{s}", "pelvis", (0.10, 0.98, 0.0)),
        ("thigh_twist_01_{s}", "thigh_{s}", (0.10, 0.76, 0.005)),
        ("calf_{s}", "thigh_{s}", (0.105, 0.55, 0.01)),
        ("foot_{s}", "calf_{s}", (0.11, 0.09, -0.03)),
        ("ball_{s}", "foot_{s}", (0.115, 0.025, 0.12)),
    ]
    # A-pose: from the shoulder, the arm 45 degrees below horizontal (outward and down).
    shoulder = np.array([0.19, 1.50, -0.02])
    down = np.array([np.cos(np.radians(45)), -np.sin(np.radians(45)), 0.0])
    arm = {
        "upperarm_twist_01_{s}": shoulder + 0.15 * down,
        "lowerarm_{s}": shoulder + 0.30 * down,
        "hand_{s}": shoulder + 0.57 * down,
    }
    return mirror([(a, b, arm[a] if c is None else np.array(c, dtype=float)) for a, b, c in j])


def child_joints():
    # 1.10 m: the head from 0.88 m to the top (0.22 m, a fifth), legs 0.50 m to the hip joint.
    j = [
        ("hips", None, (0, 0.52, 0.0)),
        ("spine", "hips", (0, 0.60, 0.005)),
        ("chest", "spine", (0, 0.72, 0.01)),
        ("head", "chest", (0, 0.88, 0.0)),
        ("upper_arm.{S}", "chest", (0.12, 0.83, -0.01)),
        ("forearm.{S}", "upper_arm.{S}", (0.29, 0.83, -0.015)),
        ("hand.{S}", "forearm.{S}", (0.44, 0.83, -0.01)),
        ("thigh.{S}", "hips", (0.07, 0.49, 0.0)),
        ("shin.{S}", "thigh.{S}", (0.072, 0.28, 0.01)),
        ("foot.{S}", "shin.{S}", (0.075, 0.06, -0.015)),
        ("toe.{S}", "foot.{S}", (0.078, 0.015, 0.075)),
    ]
    return mirror([(a, b, np.array(c, dtype=float)) for a, b, c in j])


SMPL_NAMES = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hand", "right_hand",
]


def smpl_joints():
    """SMPL-24's rest joints from tools/motion_reference.py's offsets (read as literals: that
    module needs SciPy)."""
    import ast
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "motion_reference.py")
    values = {}
    for node in ast.parse(open(path).read()).body:
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", None) in (
                "SMPL_PARENTS", "SMPL_OFFSETS"):
            v = node.value.args[0] if isinstance(node.value, ast.Call) else node.value
            values[node.targets[0].id] = ast.literal_eval(v)
    parents, offsets = values["SMPL_PARENTS"], np.array(values["SMPL_OFFSETS"])
    pos = np.zeros((24, 3))
    for j in range(1, 24):
        pos[j] = pos[parents[j]] + offsets[j]
    pos[:, 1] -= pos[[7, 8, 10, 11], 1].min()
    return [(SMPL_NAMES[j], None if parents[j] < 0 else SMPL_NAMES[parents[j]], pos[j])
            for j in range(24)]


def bone_frames(joints):
    """Per joint a world rotation: +Y along the bone, a roll of its own."""
    index = {name: i for i, (name, _, _) in enumerate(joints)}
    rots = []
    for i, (name, parent, pos) in enumerate(joints):
        kids = [k for k, (_, p, _) in enumerate(joints) if p == name]
        if kids:
            d = joints[kids[0]][2] - pos
        elif parent is not None:
            d = pos - joints[index[parent]][2]
        else:
            d = np.array([0.0, 1.0, 0.0])
        if np.linalg.norm(d) < 1e-9:
            d = np.array([0.0, 1.0, 0.0])
        rots.append(aim_y(d, 0.4 + 0.83 * i))
    return rots


def box(a, b, half):
    """Eight corners and twelve triangles of a box around the segment a -> b."""
    d = b - a
    n = np.linalg.norm(d)
    if n < 1e-9:
        d, n = np.array([0.0, 1.0, 0.0]), 0.0
        a = a - 0.5 * half * d
        b = a + half * d
    d = (b - a) / np.linalg.norm(b - a)
    u = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    corners = [end + su * half * u + sv * half * v
               for end in (a, b) for su in (-1, 1) for sv in (-1, 1)]
    # Corner k = 4*end + 2*(su>0) + (sv>0); faces wound outward.
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = []
    for q in quads:
        tris += [(q[0], q[1], q[2]), (q[0], q[2], q[3])]
    return np.array(corners), tris


def mesh_of(joints):
    """Boxes around each bone (head to first child's head; a leaf a small box of its own),
    every vertex weighted to its bone alone."""
    positions, joint_ids, tris = [], [], []
    for i, (name, parent, pos) in enumerate(joints):
        kids = [k for k, (_, p, _) in enumerate(joints) if p == name]
        end = joints[kids[0]][2] if kids else pos + np.array([0.0, 0.03, 0.0])
        length = np.linalg.norm(end - pos)
        corners, t = box(pos, end, max(0.01, min(0.05, 0.2 * length)))
        base = len(positions)
        positions += list(corners)
        joint_ids += [i] * len(corners)
        tris += [(base + x, base + y, base + z) for x, y, z in t]
    return (np.array(positions, dtype=np.float32), np.array(joint_ids),
            np.array(tris, dtype=np.uint16))


class Blob:
    """One binary buffer, each view 4-byte aligned."""

    def __init__(self):
        self.data = bytearray()
        self.views = []
        self.accessors = []

    def add(self, array, component, kind, target=None, minmax=False):
        raw = array.tobytes()
        self.views.append(g.BufferView(buffer=0, byteOffset=len(self.data), byteLength=len(raw),
                                       target=target))
        self.data += raw
        self.data += b"\0" * (-len(self.data) % 4)
        acc = g.Accessor(bufferView=len(self.views) - 1, componentType=component,
                         count=len(array), type=kind)
        if minmax:
            acc.min = [float(x) for x in array.min(axis=0)]
            acc.max = [float(x) for x in array.max(axis=0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1


def floats(v):
    return [float(x) for x in np.asarray(v, dtype=np.float32)]


def write_rig(path, joints, top):
    """`joints` (name, parent, world position in metres, glTF axes) as a skinned GLB.

    `top` is the frame the bones live in: (`node` name or None, its rotation, its scale).
    With a node name, a non-joint node of that name holds the transform above the top joint
    (Mixamo's `Armature`); without, the top joint's own rest rotation is `top`'s rotation
    (the frame baked into the bind pose).
    """
    node_name, top_rot, top_scale = top
    world_rot = bone_frames(joints)
    if node_name is None:
        world_rot[0] = top_rot
    index = {name: i for i, (name, _, _) in enumerate(joints)}
    # Joint world matrices: rotation (times the armature's scale for bones inside it) and
    # position.
    world = []
    for (name, parent, pos), r in zip(joints, world_rot):
        m = np.eye(4)
        m[:3, :3] = r * (top_scale if node_name else 1.0)
        m[:3, 3] = pos
        world.append(m)
    a = np.eye(4)
    if node_name:
        a[:3, :3] = top_rot * top_scale
    nodes = []
    for i, (name, parent, pos) in enumerate(joints):
        above = a if parent is None else world[index[parent]]
        local = np.linalg.inv(above) @ world[i]
        lin = local[:3, :3]
        scale = np.linalg.norm(lin, axis=0)
        assert np.allclose(scale, 1.0, atol=1e-9), (name, scale)
        nodes.append(g.Node(name=name, translation=floats(local[:3, 3]),
                            rotation=floats(quat_xyzw(lin))))
    for i, (name, parent, _) in enumerate(joints):
        nodes[i].children = [k for k, (_, p, _) in enumerate(joints) if p == name] or None
    top_joint = [i for i, (_, p, _) in enumerate(joints) if p is None]
    assert len(top_joint) == 1
    # Nodes: the joints, then the skinned mesh (a scene root without a transform, as glTF
    # wants skinned meshes), then the armature node if any.
    mesh_node = len(nodes)
    nodes.append(g.Node(name="body", mesh=0, skin=0))
    if node_name:
        nodes.append(g.Node(name=node_name, rotation=floats(quat_xyzw(top_rot)),
                            scale=[float(top_scale)] * 3, children=top_joint))
        skeleton = len(nodes) - 1
    else:
        skeleton = top_joint[0]
    scene_nodes = [mesh_node, skeleton]

    blob = Blob()
    positions, joint_ids, tris = mesh_of(joints)
    pos_acc = blob.add(positions, FLOAT, "VEC3", ARRAY_BUFFER, minmax=True)
    js = np.zeros((len(joint_ids), 4), dtype=np.uint8)
    js[:, 0] = joint_ids
    ws = np.zeros((len(joint_ids), 4), dtype=np.float32)
    ws[:, 0] = 1.0
    j_acc = blob.add(js, UBYTE, "VEC4", ARRAY_BUFFER)
    w_acc = blob.add(ws, FLOAT, "VEC4", ARRAY_BUFFER)
    i_acc = blob.add(tris.reshape(-1), USHORT, "SCALAR", ELEMENT_ARRAY_BUFFER)
    # Inverse bind matrices, column-major as glTF stores matrices.
    ibm = np.array([np.linalg.inv(w).T for w in world], dtype=np.float32)
    ibm_acc = blob.add(ibm.reshape(len(world), 16), FLOAT, "MAT4")

    doc = g.GLTF2(
        asset=g.Asset(version="2.0", generator="libflame tools/make_test_rigs.py"),
        scene=0,
        scenes=[g.Scene(name=os.path.splitext(os.path.basename(path))[0], nodes=scene_nodes)],
        nodes=nodes,
        meshes=[g.Mesh(name="body", primitives=[g.Primitive(
            attributes=g.Attributes(POSITION=pos_acc, JOINTS_0=j_acc, WEIGHTS_0=w_acc),
            indices=i_acc)])],
        skins=[g.Skin(name="skin", joints=list(range(len(joints))), skeleton=skeleton,
                      inverseBindMatrices=ibm_acc)],
        accessors=blob.accessors,
        bufferViews=blob.views,
        buffers=[g.Buffer(byteLength=len(blob.data))],
    )
    doc.set_binary_blob(bytes(blob.data))
    data = b"".join(doc.save_to_bytes())
    with open(path, "wb") as f:
        f.write(data)
    return data


RIGS = {
    # Mixamo via Blender: the Armature node turns the -Z-up, +Y-forward inside into glTF's
    # frame (+90 degrees about X) and scales centimetres to metres.
    "mixamo.glb": (mixamo_joints, ("Armature", rot_x(90), 0.01)),
    # Unreal: Z up and -Y forward inside, on the root joint itself.
    "apose.glb": (apose_joints, (None, rot_x(-90), 1.0)),
    # Facing -Z: the whole child turned half a turn about Y; the root joint keeps a roll of
    # its own on top.
    "child.glb": (child_joints, (None, rot_y(180) @ axis_angle(np.array([0.2, 1.0, 0.1]), 0.6),
                                 1.0)),
}


def main():
    if sys.argv[1:2] == ["--control"] and len(sys.argv) == 3:
        os.makedirs(sys.argv[2], exist_ok=True)
        path = os.path.join(sys.argv[2], "smpl.glb")
        data = write_rig(path, smpl_joints(), (None, np.eye(3), 1.0))
        print(f"smpl.glb: 24 bones, {len(data)} bytes")
        return
    out = sys.argv[1] if len(sys.argv) > 1 else os.path.join(
        os.path.dirname(os.path.abspath(__file__)), "..", "tests", "fixtures", "rigs")
    os.makedirs(out, exist_ok=True)
    for name, (make, top) in RIGS.items():
        joints = make()
        if name == "child.glb":
            # Facing -Z: x and z negated (a half turn about Y), so left stays the body's left.
            joints = [(n, p, np.array([-v[0], v[1], -v[2]])) for n, p, v in joints]
        data = write_rig(os.path.join(out, name), joints, top)
        print(f"{name}: {len(joints)} bones, {len(data)} bytes")


if __name__ == "__main__":
    main()
