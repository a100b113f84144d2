"""flame.Rig, flame.BoneMap and Model.retarget (flame_rig_*, flame_bone_map_*, flame_retarget_*).

Independent reference: forward kinematics in numpy of the local rotations and translations a
retarget returns, compared with the joint positions the session itself reads
(Layout.GLOBAL_POSITIONS in Convention.GLTF, same cleanup): a rig of SMPL's proportions, given
as Unity holds it (left-handed), must point its limbs where the source's point. Fixtures:
tests/fixtures/flame_tiny.safetensors, tests/fixtures/rigs/mixamo.glb (skipped when absent).
"""

from pathlib import Path

import numpy as np
import pytest

import flame
from flame import Convention, FlameError, Layout, Status

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"
MIXAMO = FIXTURES / "rigs" / "mixamo.glb"

# SMPL-24's joints 0..21 under Mixamo's names; rest offsets of SMPL's neutral body in glTF axes
# (src/motion/skeleton.rs).
NAMES = ["Hips", "LeftUpLeg", "RightUpLeg", "Spine", "LeftLeg", "RightLeg", "Spine1",
         "LeftFoot", "RightFoot", "Spine2", "LeftToeBase", "RightToeBase", "Neck",
         "LeftShoulder", "RightShoulder", "Head", "LeftArm", "RightArm", "LeftForeArm",
         "RightForeArm", "LeftHand", "RightHand"]
PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19]
OFFSETS = np.array([
    [-0.00179506, -0.22333345, 0.02821913], [0.06951974, -0.09140623, -0.00681534],
    [-0.06767048, -0.09052168, -0.00431982], [-0.00253286, 0.10896323, -0.02669631],
    [0.03427655, -0.37519860, -0.00449580], [-0.03829005, -0.38256901, -0.00885003],
    [0.00548703, 0.13518043, 0.00109247], [-0.01359570, -0.39796036, -0.04369333],
    [0.01577377, -0.39841465, -0.04231180], [0.00145700, 0.05292223, 0.02542457],
    [0.02635814, -0.05579088, 0.11928840], [-0.02537175, -0.04814396, 0.12334795],
    [-0.00277839, 0.21387036, -0.04285703], [0.07884474, 0.12174930, -0.03408961],
    [-0.08175919, 0.11883283, -0.03861529], [0.00515184, 0.06496961, 0.05134897],
    [0.09097693, 0.03046890, -0.00886815], [-0.09601238, 0.03255117, -0.00914307],
    [0.25961225, -0.01277206, -0.02745644], [-0.25374196, -0.01332922, -0.02140098],
    [0.24923363, 0.00898603, -0.00117092], [-0.25529808, 0.00777229, -0.00555919]])
LIMBS = [(1, 4), (4, 7), (2, 5), (5, 8), (16, 18), (18, 20), (17, 19), (19, 21)]
FRAMES = 20


def quat_matrix(q):
    """Rotation matrices of quaternions [..., 4] x y z w."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def forward_kinematics(rot, trans, parents):
    """World positions [frames, bones, 3] from local rotations and translations."""
    r = quat_matrix(rot)
    frames, bones = rot.shape[:2]
    world = np.zeros((frames, bones, 3, 3))
    pos = np.zeros((frames, bones, 3))
    for b, p in enumerate(parents):
        if p < 0:
            world[:, b], pos[:, b] = r[:, b], trans[:, b]
        else:
            world[:, b] = world[:, p] @ r[:, b]
            pos[:, b] = pos[:, p] + np.einsum("fij,fj->fi", world[:, p], trans[:, b])
    return pos


def unity_bones():
    """The humanoid as Unity holds it: glTF's axes with x negated (left-handed, Y up, metres),
    a rest roll on every bone (rotation about a tilted axis in glTF, mirrored for Unity:
    q = (x, -y, -z, w))."""
    world_pos = np.zeros((len(NAMES), 3))
    for b, p in enumerate(PARENTS):
        world_pos[b] = (world_pos[p] if p >= 0 else np.array([0, 0.95, 0])) + OFFSETS[b]
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    quats = [np.r_[axis * np.sin(0.075 * b), np.cos(0.075 * b)] for b in range(len(NAMES))]
    mats = quat_matrix(np.array(quats))
    bones = []
    for b, p in enumerate(PARENTS):
        if p < 0:
            local, t = mats[b], world_pos[b]
        else:
            local = mats[p].T @ mats[b]
            t = mats[p].T @ (world_pos[b] - world_pos[p])
        # Matrix → quaternion (local is a rotation whose trace is well above -1 here).
        w = np.sqrt(max(1 + np.trace(local), 1e-12)) / 2
        q = np.array([local[2, 1] - local[1, 2], local[0, 2] - local[2, 0],
                      local[1, 0] - local[0, 1]]) / (4 * w)
        bones.append(flame.RigBone(NAMES[b], p, (-t[0], t[1], t[2]),
                                   (q[0], -q[1], -q[2], w)))
    return bones


@pytest.fixture(scope="module")
def model():
    with flame.Model.load(str(FIXTURES / "flame_tiny.safetensors")) as m:
        yield m


@pytest.fixture(scope="module")
def session(model):
    # Two of ten steps: the tiny model's final motion saturates (see tests/c/test_cleanup.c).
    with model.session(frames=FRAMES, steps=10, sampler="ddim", seed=11, threads=1) as s:
        s.set_prompt("a person walks forward and waves.")
        s.step()
        s.step()
        yield s


def test_a_unity_rig_points_its_limbs_where_the_source_does(model, session):
    rig = flame.Rig.from_bones(unity_bones(), Convention.UNITY)
    assert rig.names == NAMES and rig.parents == PARENTS
    cleanup = flame.Cleanup()
    with model.retarget(rig) as r:
        rot, trans = r.read(session, cleanup=cleanup)
    assert rot.shape == (FRAMES, len(NAMES), 4) and trans.shape == (FRAMES, len(NAMES), 3)
    pos = forward_kinematics(rot, trans, PARENTS)
    pos[..., 0] *= -1  # Unity → glTF
    src = session.read(layout=Layout.GLOBAL_POSITIONS, convention=Convention.GLTF,
                       cleanup=cleanup)
    worst = 0.0
    for a, b in LIMBS:
        want, got = src[:, b] - src[:, a], pos[:, b] - pos[:, a]
        cos = np.sum(want * got, -1) / np.linalg.norm(want, axis=-1) / np.linalg.norm(got, axis=-1)
        worst = max(worst, np.degrees(np.arccos(np.clip(cos, -1, 1))).max())
    assert worst < 0.05, worst
    # The hips follow the source's pelvis (same proportions, hips at 0.95 m vs SMPL's).
    travel_src = src[-1, 0] - src[0, 0]
    travel_rig = pos[-1, 0] - pos[0, 0]
    assert np.linalg.norm(travel_src) > 0.05
    assert np.allclose(travel_rig, travel_src, atol=0.02 * np.linalg.norm(travel_src) + 1e-3)


def test_one_frame_from_any_source_is_that_frame_of_a_read(model, session):
    rig = flame.Rig.from_bones(unity_bones(), Convention.UNITY)
    r = model.retarget(rig)
    rot, trans = r.read(session, 3, 2)
    q = session.read(layout=Layout.GLOBAL_QUAT_XYZW, convention=Convention.GLTF)
    p = session.read(layout=Layout.GLOBAL_POSITIONS, convention=Convention.GLTF)
    one_rot, one_trans = r.pose(q[4], p[4])
    assert np.abs(one_rot - rot[1]).max() < 1e-4
    assert np.abs(one_trans - trans[1]).max() < 1e-4
    with pytest.raises(FlameError) as e:
        r.pose(q[4][:-1], p[4])
    assert e.value.status == Status.INVALID_ARGUMENT
    with pytest.raises(FlameError) as e:
        r.read(session, FRAMES - 1, 2)
    assert e.value.status == Status.INVALID_ARGUMENT
    r.close()
    with pytest.raises(ValueError):
        r.read(session)


def test_bone_maps_name_what_is_missing_and_mend_it(model):
    bones = unity_bones()
    bones[20].name = "Prop_L"
    rig = flame.Rig.from_bones(bones, Convention.UNITY)
    with pytest.raises(FlameError) as e:
        model.retarget(rig)
    assert e.value.status == Status.INVALID_ARGUMENT and "leftHand" in e.value.message
    with pytest.raises(FlameError) as e:
        flame.BoneMap.from_json(rig, '{"leftHand": "Hand_L"}')
    assert "Hand_L" in e.value.message
    m = flame.BoneMap.from_json(rig, '{"leftHand": "Prop_L"}', flame.BoneMap.auto(rig))
    text = m.to_json()
    assert '"leftHand": "Prop_L"' in text and '"hips": "Hips"' in text
    assert flame.BoneMap.from_json(rig, text).to_json() == text
    with model.retarget(rig, map=m, feet=False) as r:
        assert r.bone_count == len(NAMES)


def test_bad_rigs_are_errors(model):
    with pytest.raises(FlameError) as e:
        flame.Rig.from_bones(unity_bones(), Convention.NATIVE)
    assert e.value.status == Status.INVALID_ARGUMENT
    bones = unity_bones()
    bones[3].parent = 40
    with pytest.raises(FlameError) as e:
        flame.Rig.from_bones(bones, Convention.UNITY)
    assert "Spine" in e.value.message
    with pytest.raises(FlameError):
        flame.Rig.load(b"not a rig")
    with pytest.raises(FlameError):
        flame.Rig.from_bones([], Convention.UNITY)


@pytest.mark.skipif(not MIXAMO.is_file(), reason="no tests/fixtures/rigs/mixamo.glb")
def test_mixamo_glb_by_path_and_bytes(model, session):
    by_path = flame.Rig.load(MIXAMO)
    data = MIXAMO.read_bytes()
    by_bytes = flame.Rig.load(data, flame.RigFormat.GLTF)
    assert by_path.names == by_bytes.names and by_path.bone_count > 22
    hips = by_path.names.index("mixamorig:Hips")
    with model.retarget(by_path, hands=True) as r:
        rot, trans = r.read(session, cleanup=flame.Cleanup())
    assert np.allclose(np.linalg.norm(rot, axis=-1), 1, atol=1e-5)
    assert np.abs(trans[-1, hips] - trans[0, hips]).max() > 0.01
    for cut in (10, len(data) // 2, len(data) - 1):
        with pytest.raises(FlameError) as e:
            flame.Rig.load(data[:cut], flame.RigFormat.GLTF)
        assert e.value.status == Status.INVALID_ARGUMENT


def test_a_stream_read_is_the_streams_frames_on_the_rig(model):
    rig = flame.Rig.from_bones(unity_bones(), Convention.UNITY)
    with flame.Stream(model, chunk=40, overlap=10, lookahead=1000, window=10000, steps=2,
                      sampler="ddim", seed=5, threads=1) as s, model.retarget(rig) as r:
        with pytest.raises(FlameError) as e:
            r.read_stream(s, 0, 5)
        assert e.value.status == Status.WRONG_STATE
        s.push("a person walks forward.", 40)
        s.pump()
        rot, trans = r.read_stream(s, 0, 10)
        q = s.read(0, 10, Layout.GLOBAL_QUAT_XYZW, Convention.GLTF)
        p = s.read(0, 10, Layout.GLOBAL_POSITIONS, Convention.GLTF)
        for t in (0, 9):
            one_rot, _ = r.pose(q[t], p[t])
            assert np.abs(one_rot - rot[t]).max() < 1e-6
