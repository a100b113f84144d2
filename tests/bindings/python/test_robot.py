"""Robots through the Python bindings (flame_robot_*): Robot.load and its names, RobotRetarget
with the shipped configuration, retarget() returning GMR's dict (its pickle's fields, float64,
root_rot x, y, z, w), write() of every file read back with NumPy (np.loadtxt as BeyondMimic's
csv_to_npz.py reads the CSV; the .npz and .npy with np.load) and agreeing with the dict, the
per-frame reads (the same frames from a reset state, in chunks or one by one) and the refusals.
On the tiny FLAME fixture and the real GR1T2 URDF (tools/fetch_robots.sh into target/robots;
skipped when it cannot be had).
"""

import io
import subprocess
from pathlib import Path

import numpy as np
import pytest

import flame
from flame import Cleanup, FlameError, RobotFile, Status

ROOT = Path(__file__).resolve().parents[3]
FIXTURES = ROOT / "tests/fixtures"
URDF = ROOT / "target/robots/gr1t2.urdf"
CONFIG = ROOT / "robots/gr1t2.json"
FRAMES = 16


@pytest.fixture(scope="module")
def robot():
    if not URDF.is_file():
        subprocess.run(["bash", str(ROOT / "tools/fetch_robots.sh")], check=False)
    if not URDF.is_file():
        pytest.skip(f"{URDF} is missing and tools/fetch_robots.sh could not fetch it")
    with flame.Robot.load(URDF) as r:
        yield r


@pytest.fixture(scope="module")
def session():
    model = flame.Model.load(FIXTURES / "flame_tiny.safetensors")
    s = model.session(frames=FRAMES, steps=4, sampler="ddim", seed=5, threads=1)
    s.set_prompt("a person walks forward and waves.")
    # Two steps of four: the tiny model's final motion saturates.
    s.step()
    s.step()
    yield s
    s.close()
    model.close()


def test_robot_names(robot):
    assert robot.name == "gr1t2"
    names = robot.dof_names
    assert len(names) == 32 and names[0] == "left_hip_roll_joint"


def test_retarget_gives_gmrs_dict(robot, session):
    with flame.RobotRetarget(robot, CONFIG) as r:
        assert r.dof_count == 32
        d = r.retarget(session, cleanup=Cleanup(fps=30.0))
    assert set(d) == {"fps", "root_pos", "root_rot", "dof_pos", "joint_names"}
    n = d["dof_pos"].shape[0]
    assert d["fps"] == 30.0 and n == 23  # 16 frames at 20 fps span 0.75 s
    assert d["root_pos"].shape == (n, 3) and d["root_rot"].shape == (n, 4)
    assert d["dof_pos"].shape == (n, 32) and d["dof_pos"].dtype == np.float64
    assert d["joint_names"] == robot.dof_names
    assert np.allclose(np.linalg.norm(d["root_rot"], axis=1), 1.0, atol=1e-12)


def test_files_read_back_with_numpy(robot, session, tmp_path):
    r = flame.RobotRetarget(robot, CONFIG.read_text())
    d = r.retarget(session)
    csv = r.write(session, tmp_path / "walk.csv")
    rows = np.loadtxt(tmp_path / "walk.csv", delimiter=",")
    assert rows.shape == (FRAMES, 39)
    assert np.array_equal(rows[:, :3], d["root_pos"])
    assert np.array_equal(rows[:, 3:7], d["root_rot"])
    assert np.array_equal(rows[:, 7:], d["dof_pos"])
    with_header = r.write(session, file=RobotFile.BEYONDMIMIC_CSV_XYZW, header=True)
    assert with_header.startswith(b"# x,y,z,qx,qy,qz,qw,left_hip_roll_joint,")
    assert with_header.split(b"\n", 1)[1] == csv
    qpos = np.load(io.BytesIO(r.write(session, tmp_path / "walk.npy")))
    assert qpos.shape == (FRAMES, 39)
    assert np.array_equal(qpos[:, 3:7], d["root_rot"][:, [3, 0, 1, 2]])  # w first
    qcsv = np.loadtxt(io.BytesIO(r.write(session, file=RobotFile.QPOS_CSV_WXYZ)), delimiter=",")
    assert np.array_equal(qcsv, qpos)
    r.write(session, tmp_path / "walk.npz")
    with np.load(tmp_path / "walk.npz") as z:
        assert np.array_equal(z["dof_pos"], d["dof_pos"])
        assert [str(s) for s in z["joint_names"]] == d["joint_names"]
    r.close()


def test_per_frame_reads_are_deterministic(robot, session):
    r = flame.RobotRetarget(robot, CONFIG)
    st = r.state()
    a = [r.read(session, st, f, 4) for f in range(0, FRAMES, 4)]
    st.reset()
    b = [r.read(session, st, f, 1) for f in range(FRAMES)]
    for k in range(4):
        chunked = np.concatenate([x[k] for x in a])
        single = np.concatenate([x[k] for x in b])
        assert np.array_equal(chunked, single)
    pos, rot, q, res = a[0]
    assert pos.shape == (4, 3) and rot.shape == (4, 4) and q.shape == (4, 32)
    assert np.all(np.isfinite(res)) and np.all(res >= 0)
    assert np.allclose(np.linalg.norm(rot, axis=1), 1.0)


def test_refusals(robot, session):
    with pytest.raises(FlameError) as e:
        flame.Robot.load(b"<robot name='x'><link name='a'/><joint name='j' type='fixed'>"
                         b"<parent link='a'/><child link='missing'/></joint></robot>")
    assert e.value.status == Status.INVALID_ARGUMENT and "missing" in e.value.message
    with pytest.raises(FlameError) as e:
        flame.RobotRetarget(robot, '{"robot_root_name": "no_such_body"}')
    assert "no_such_body" in e.value.message
    r = flame.RobotRetarget(robot, CONFIG)
    other = flame.RobotRetarget(robot, CONFIG)
    with pytest.raises(FlameError) as e:
        r.read(session, other.state(), 0, 1)
    assert "another retarget" in e.value.message
    with pytest.raises(FlameError) as e:
        r.read(session, r.state(), FRAMES, 1)
    assert "past" in e.value.message
    with pytest.raises(FlameError):
        r.write(session, file=RobotFile.GMR_NPZ_XYZW, header=True)
    with pytest.raises(ValueError):
        r.write(session, "walk.bvh")
