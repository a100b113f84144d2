"""Writes tests/fixtures/rigs/avatar.vrm: a small VRM 1.0 avatar unlike SMPL, for the retarget
file tests (tests/retarget_files.rs) and the three-vrm check (tools/vrma_check.sh).

    target/test-venv/bin/python tools/make_vrm_avatar.py [OUT.vrm]

Needs numpy and pygltflib (tools/test-requirements.txt). The file:

- 22 humanoid bones (VRM 1.0's 15 required ones plus chest, upperChest, neck, shoulders and
  toes; vrm-c/vrm-specification, specification/VRMC_vrm-1.0/humanoid.md) under a non-joint
  `Root` node, in the VRM T-pose (specification/VRMC_vrm-1.0/tpose.md: facing +Z, Y up, arms
  along +-X, the lowest joint on y = 0).
- Child-like proportions: legs 0.62, spine 0.75, arms 0.7 of SMPL's, a big head box.
- A different rest rotation on every bone (VRM 1.0 allows them; the node translations are
  turned to match, so the joints sit at the T-pose positions).
- A skinned mesh: one box per bone, rigidly weighted to it; inverse bind matrices of the rest.
- The VRMC_vrm extension: specVersion 1.0, meta (name, version, authors, licenseUrl and the
  permissions of specification/VRMC_vrm-1.0/schema/VRMC_vrm.meta.schema.json) and
  humanoid.humanBones.

What must agree with libflame's canonical VRMA T-pose (src/retarget/vrma.rs) for the three-vrm
check to compare like with like: the bones' rest *directions* (legs and spine vertical, arms
horizontal, the feet pitched as SMPL's are) and the split of the spine (hips-spine-chest-
upperChest-neck in SMPL's ratios); lengths may differ. The rest-relative retarget aims each bone
along the source's rest direction, so a rig whose foot is pitched differently, say, gets another
(equally valid) foot rotation than a VRMA player derives from the T-pose.
"""

import sys
from pathlib import Path

import numpy as np
import pygltflib as g

# SMPL's rest offsets (src/motion/skeleton.rs, SMPL24_OFFSETS; glTF axes, metres) that fix the
# directions and spine split shared with the VRMA T-pose: pelvis->spine1, spine1->spine2,
# spine2->spine3, spine3->neck, neck->head, and the two ankle->foot offsets.
SMPL = {
    "spine": [-0.00253286, 0.10896323, -0.02669631],
    "chest": [0.00548703, 0.13518043, 0.00109247],
    "upperChest": [0.00145700, 0.05292223, 0.02542457],
    "neck": [-0.00277839, 0.21387036, -0.04285703],
    "head": [0.00515184, 0.06496961, 0.05134897],
    "leftToes": [0.02635814, -0.05579088, 0.11928840],
    "rightToes": [-0.02537175, -0.04814396, 0.12334795],
}

LEGS, SPINE, ARMS = 0.62, 0.75, 0.70

# (VRM humanBone, node name, parent humanBone, offset from the parent in the T-pose, metres).
length = lambda key: float(np.linalg.norm(SMPL[key]))
foot = np.array(SMPL["leftToes"]) + np.array(SMPL["rightToes"]) * [-1, 1, 1]
foot = 0.5 * foot
foot_dir = np.array([0.0, foot[1], foot[2]]) / np.linalg.norm([foot[1], foot[2]])
BONES = [
    ("hips", "J_Hips", None, [0, 0, 0]),
    ("spine", "J_Spine", "hips", [0, SPINE * length("spine"), 0]),
    ("chest", "J_Chest", "spine", [0, SPINE * length("chest"), 0]),
    ("upperChest", "J_UpperChest", "chest", [0, SPINE * length("upperChest"), 0]),
    ("neck", "J_Neck", "upperChest", [0, SPINE * length("neck"), 0]),
    ("head", "J_Head", "neck", [0, 0.09, 0]),
]
for side, sx, s in (("left", 1, "L"), ("right", -1, "R")):
    cap = side.capitalize()
    BONES += [
        (f"{side}Shoulder", f"J_{s}_Shoulder", "upperChest", [sx * 0.06, 0.05, 0]),
        (f"{side}UpperArm", f"J_{s}_UpperArm", f"{side}Shoulder", [sx * ARMS * 0.1, 0, 0]),
        (f"{side}LowerArm", f"J_{s}_LowerArm", f"{side}UpperArm", [sx * ARMS * 0.26, 0, 0]),
        (f"{side}Hand", f"J_{s}_Hand", f"{side}LowerArm", [sx * ARMS * 0.25, 0, 0]),
        (f"{side}UpperLeg", f"J_{s}_UpperLeg", "hips", [sx * 0.06, -0.07, 0]),
        (f"{side}LowerLeg", f"J_{s}_LowerLeg", f"{side}UpperLeg", [0, -LEGS * 0.38, 0]),
        (f"{side}Foot", f"J_{s}_Foot", f"{side}LowerLeg", [0, -LEGS * 0.40, 0]),
        (f"{side}Toes", f"J_{s}_Toes", f"{side}Foot", list(0.09 * foot_dir)),
    ]
del cap
INDEX = {b[0]: i for i, b in enumerate(BONES)}


def quat_matrix(q):
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rest_quat(i):
    """Bone i's rest rotation (x, y, z, w): a different axis and angle for every bone."""
    axis = np.array([np.sin(1.3 * i + 0.2), np.cos(0.7 * i), 0.5])
    axis /= np.linalg.norm(axis)
    angle = 0.25 + 0.2 * (i % 5)
    return np.append(axis * np.sin(angle / 2), np.cos(angle / 2))


def main():
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "tests/fixtures/rigs/avatar.vrm")
    n = len(BONES)
    pos = np.zeros((n, 3))
    for i, (_, _, parent, off) in enumerate(BONES):
        pos[i] = (pos[INDEX[parent]] if parent else 0) + np.array(off, dtype=float)
    pos[:, 1] -= pos[:, 1].min()  # the lowest joint (the toes) on the floor
    quats = [rest_quat(i) for i in range(n)]
    world = [None] * n
    nodes = []
    for i, (human, name, parent, _) in enumerate(BONES):
        p = INDEX[parent] if parent else None
        r = quat_matrix(quats[i])
        world[i] = (world[p] if p is not None else np.eye(3)) @ r
        # The translation that puts the joint at its T-pose position under the turned parent.
        t = world[p].T @ (pos[i] - pos[p]) if p is not None else pos[i]
        children = [j for j, b in enumerate(BONES) if b[2] == human]
        nodes.append(g.Node(name=name, translation=[float(v) for v in t],
                            rotation=[float(v) for v in quats[i]], children=children or None))
    root = n
    nodes.append(g.Node(name="Root", children=[INDEX["hips"]]))
    mesh_node = n + 1
    nodes.append(g.Node(name="Body", mesh=0, skin=0))

    # One box per bone, from the joint to its first child (leaves: a short box onward; the head a
    # big one), rigidly bound to the bone.
    positions, joints, indices = [], [], []
    box_faces = [(0, 1, 2), (0, 2, 3), (4, 6, 5), (4, 7, 6), (0, 4, 5), (0, 5, 1),
                 (1, 5, 6), (1, 6, 2), (2, 6, 7), (2, 7, 3), (3, 7, 4), (3, 4, 0)]
    for i, (human, _, parent, _) in enumerate(BONES):
        kids = [j for j, b in enumerate(BONES) if b[2] == human]
        a = pos[i]
        if human == "head":
            lo, hi = a + [-0.11, 0.0, -0.11], a + [0.11, 0.24, 0.11]
        else:
            b = pos[kids[0]] if kids else a + 0.5 * (a - pos[INDEX[parent]])
            half = 0.03
            lo, hi = np.minimum(a, b) - half, np.maximum(a, b) + half
        base = len(positions)
        for k in range(8):
            x = hi[0] if k in (1, 2, 5, 6) else lo[0]
            y = hi[1] if k in (2, 3, 6, 7) else lo[1]
            z = hi[2] if k >= 4 else lo[2]
            positions.append([x, y, z])
            joints.append([i, 0, 0, 0])
        indices += [base + v for f in box_faces for v in f]
    positions = np.array(positions, dtype=np.float32)
    joints = np.array(joints, dtype=np.uint8)
    weights = np.tile(np.array([1, 0, 0, 0], dtype=np.float32), (len(positions), 1))
    indices = np.array(indices, dtype=np.uint16)
    ibm = []
    for i in range(n):
        m = np.eye(4)
        m[:3, :3] = world[i]
        m[:3, 3] = pos[i]
        ibm.append(np.linalg.inv(m).T.reshape(-1))  # column-major
    ibm = np.array(ibm, dtype=np.float32)

    blob = b""
    views, accessors = [], []

    def add(data, kind, component, target=None, bounds=False):
        nonlocal blob
        while len(blob) % 4:
            blob += b"\0"
        raw = data.tobytes()
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(raw),
                                  target=target))
        blob += raw
        acc = g.Accessor(bufferView=len(views) - 1, componentType=component,
                         count=len(data), type=kind)
        if bounds:
            acc.min = [float(v) for v in data.min(axis=0)]
            acc.max = [float(v) for v in data.max(axis=0)]
        accessors.append(acc)
        return len(accessors) - 1

    a_pos = add(positions, g.VEC3, g.FLOAT, g.ARRAY_BUFFER, bounds=True)
    a_joints = add(joints, g.VEC4, g.UNSIGNED_BYTE, g.ARRAY_BUFFER)
    a_weights = add(weights, g.VEC4, g.FLOAT, g.ARRAY_BUFFER)
    a_idx = add(indices, g.SCALAR, g.UNSIGNED_SHORT, g.ELEMENT_ARRAY_BUFFER)
    a_ibm = add(ibm, g.MAT4, g.FLOAT)
    while len(blob) % 4:
        blob += b"\0"

    human_bones = {human: {"node": i} for i, (human, _, _, _) in enumerate(BONES)}
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="libflame tools/make_vrm_avatar.py"),
        scene=0,
        scenes=[g.Scene(nodes=[root, mesh_node])],
        nodes=nodes,
        meshes=[g.Mesh(name="Body", primitives=[g.Primitive(
            attributes=g.Attributes(POSITION=a_pos, JOINTS_0=a_joints, WEIGHTS_0=a_weights),
            indices=a_idx, material=0)])],
        materials=[g.Material(name="Body", pbrMetallicRoughness=g.PbrMetallicRoughness(
            baseColorFactor=[0.8, 0.6, 0.5, 1.0], metallicFactor=0.0, roughnessFactor=0.9))],
        skins=[g.Skin(name="Avatar", joints=list(range(n)), inverseBindMatrices=a_ibm,
                      skeleton=INDEX["hips"])],
        accessors=accessors,
        bufferViews=views,
        buffers=[g.Buffer(byteLength=len(blob))],
        extensionsUsed=["VRMC_vrm"],
        extensions={"VRMC_vrm": {
            "specVersion": "1.0",
            "meta": {
                "name": "libflame test avatar",
                "version": "1",
                "authors": ["libflame"],
                "licenseUrl": "https://vrm.dev/licenses/1.0/",
                "avatarPermission": "everyone",
                "allowExcessivelyViolentUsage": False,
                "allowExcessivelySexualUsage": False,
                "commercialUsage": "corporation",
                "allowPoliticalOrReligiousUsage": False,
                "allowAntisocialOrHateUsage": False,
                "creditNotation": "unnecessary",
                "allowRedistribution": True,
                "modification": "allowModificationRedistribution",
            },
            "humanoid": {"humanBones": human_bones},
        }},
    )
    gltf.set_binary_blob(blob)
    out.parent.mkdir(parents=True, exist_ok=True)
    data = b"".join(gltf.save_to_bytes())
    out.write_bytes(data)
    print(f"{out}: {n} humanoid bones, {len(positions)} vertices, {len(data)} bytes")


if __name__ == "__main__":
    main()
