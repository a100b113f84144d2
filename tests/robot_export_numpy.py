"""The pipelines' readers on libflame's robot trajectory files (run by tests/robot_export.rs).

    python tests/robot_export_numpy.py DIR ROBOT.urdf

DIR holds beyondmimic.csv, beyondmimic_header.csv, gmr.npz, qpos.csv, qpos.npy, links.npy
(libflame's world position of every link, [frames, links, 3]) and links.txt (their names).

- BeyondMimic: `np.loadtxt(file, delimiter=",")` as HybridRobotics/whole_body_tracking
  (scripts/csv_to_npz.py, MotionLoader._load_motion) reads it; columns 0:3 position, 3:7 the
  base quaternion x, y, z, w, then the joints. The header variant must load to the same array.
- GMR's fields: `np.load`; fps, root_pos, root_rot (x, y, z, w), dof_pos and joint_names, all
  equal to the CSV's columns.
- MuJoCo qpos: the .npy and the CSV agree; MuJoCo (PyPI `mujoco`) compiles the URDF with a free
  joint on its root, takes each row verbatim as `qpos` (so its width must be MuJoCo's nq and
  its order MuJoCo's), and `mj_kinematics` must put every body where libflame put the link.
Exits non-zero on any mismatch.
"""

import re
import sys
from pathlib import Path

import numpy as np


def fail(msg):
    print(msg, file=sys.stderr)
    sys.exit(1)


def mujoco_model(urdf_path):
    import mujoco

    text = Path(urdf_path).read_text()
    # The meshes are not needed; static bodies are kept so every link is a body.
    text = re.sub(r"<visual\b.*?</visual>", "", text, flags=re.S)
    text = re.sub(r"<collision\b.*?</collision>", "", text, flags=re.S)
    compiler = '<mujoco><compiler discardvisual="true" fusestatic="false"/></mujoco>'
    text = re.sub(r"(<robot\b[^>]*>)", r"\1" + compiler, text, count=1)
    spec = mujoco.MjSpec.from_string(text)
    spec.worldbody.first_body().add_freejoint()
    return spec.compile()


def main():
    d = Path(sys.argv[1])
    urdf = sys.argv[2]
    bm = np.loadtxt(d / "beyondmimic.csv", delimiter=",")
    bm_h = np.loadtxt(d / "beyondmimic_header.csv", delimiter=",")
    if not np.array_equal(bm, bm_h):
        fail("the CSV with a header does not load to the same rows")
    header = (d / "beyondmimic_header.csv").read_text().splitlines()[0]
    g = np.load(d / "gmr.npz")
    if sorted(g.files) != sorted(["fps", "root_pos", "root_rot", "dof_pos", "joint_names"]):
        fail(f"gmr.npz keys {g.files}")
    frames, n = g["dof_pos"].shape
    for key, shape in (("root_pos", (frames, 3)), ("root_rot", (frames, 4))):
        if g[key].shape != shape or g[key].dtype != np.float64:
            fail(f"{key}: {g[key].shape} {g[key].dtype}")
    if g["fps"].shape != () or float(g["fps"]) != 30.0:
        fail(f"fps {g['fps']!r}")
    names = [str(s) for s in g["joint_names"]]
    if g["joint_names"].dtype.kind != "U" or len(names) != n:
        fail(f"joint_names {g['joint_names'].dtype} {len(names)}")
    if header != "# " + ",".join(["x", "y", "z", "qx", "qy", "qz", "qw"] + names):
        fail(f"header {header[:80]}")
    if bm.shape != (frames, 7 + n):
        fail(f"beyondmimic.csv shape {bm.shape}")
    # The CSV's text reads back to the very same float64 values.
    for cols, key in ((slice(0, 3), "root_pos"), (slice(3, 7), "root_rot"), (slice(7, None), "dof_pos")):
        if not np.array_equal(bm[:, cols], g[key]):
            fail(f"beyondmimic.csv columns {cols} differ from gmr.npz {key}")
    if not np.allclose(np.linalg.norm(g["root_rot"], axis=1), 1.0, atol=1e-12):
        fail("root_rot is not unit")

    qpos = np.load(d / "qpos.npy")
    qcsv = np.loadtxt(d / "qpos.csv", delimiter=",")
    if qpos.dtype != np.float64 or not np.array_equal(qpos, qcsv):
        fail("qpos.npy and qpos.csv differ")
    if not np.array_equal(qpos[:, 3:7], g["root_rot"][:, [3, 0, 1, 2]]):
        fail("qpos's quaternion is not root_rot with w first")

    import mujoco

    model = mujoco_model(urdf)
    if qpos.shape[1] != model.nq:
        fail(f"qpos rows are {qpos.shape[1]} wide, MuJoCo's nq is {model.nq}")
    qnames = (d / "qpos.csv").read_text().splitlines()[0][2:].split(",")[7:]
    mj_names = [model.joint(j).name for j in range(1, model.njnt)]
    if qnames != mj_names:
        fail(f"qpos header joints {qnames[:5]}... are not MuJoCo's {mj_names[:5]}...")
    links = np.load(d / "links.npy")
    link_names = (d / "links.txt").read_text().split("\n")
    data = mujoco.MjData(model)
    worst = 0.0
    for t in range(frames):
        data.qpos[:] = qpos[t]
        mujoco.mj_kinematics(model, data)
        for i, name in enumerate(link_names):
            b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
            if b < 0:
                fail(f"MuJoCo's model has no body {name}")
            worst = max(worst, float(np.abs(data.xpos[b] - links[t, i]).max()))
    print(f"{frames} frames, {n} joints, {len(link_names)} links")
    print(f"mujoco body max error {worst:.3g} m")
    if worst > 1e-9:
        fail("MuJoCo places the qpos rows elsewhere than libflame")


main()
