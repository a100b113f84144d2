"""Pinocchio's kinematics of the configurations tests/robot_urdf.rs asks for: the independent
reference of flame::robot.

    python tests/robot_pinocchio.py REQUEST.json > ANSWER.json

REQUEST is a list of robots: {"name", "urdf" (path), "links" (names), "cases": [{"base_position":
[x, y, z], "base_quat_xyzw": [x, y, z, w], "q": {joint name: value}}]}. For each robot the
answer has "nq", "nv" of the model Pinocchio builds with a free-flyer root
(`buildModelFromUrdf(path, JointModelFreeFlyer())`), "joint_order" (its movable joints in its
configuration order), "limits" per joint name (lowerPositionLimit, upperPositionLimit,
velocityLimit, effortLimit at the joint's index) and per case every named link's world placement
after `forwardKinematics` + `updateFramePlacements` ({"rotation": 3x3 rows, "translation"}).

Pinocchio's free-flyer configuration is [x, y, z, qx, qy, qz, qw, joints...] (quaternion x, y,
z, w); a continuous joint takes (cos q, sin q). Exits 77 when Pinocchio cannot be imported.
"""

import json
import math
import sys

try:
    import numpy as np
    import pinocchio as pin
except ImportError as e:  # the caller skips, naming the reason
    print(f"cannot import pinocchio: {e}", file=sys.stderr)
    sys.exit(77)


def answer(robot):
    model = pin.buildModelFromUrdf(robot["urdf"], pin.JointModelFreeFlyer())
    data = model.createData()
    movable = [j for j in range(2, model.njoints)]  # 0: universe, 1: the free flyer
    limits = {}
    for j in movable:
        joint = model.joints[j]
        name = model.names[j]
        iq, iv = joint.idx_q, joint.idx_v
        limits[name] = {
            "lower": float(model.lowerPositionLimit[iq]),
            "upper": float(model.upperPositionLimit[iq]),
            "velocity": float(model.velocityLimit[iv]),
            "effort": float(model.effortLimit[iv]),
        }
        if joint.nq == 2:  # continuous: unbounded, whatever Pinocchio stores for cos/sin
            limits[name]["lower"], limits[name]["upper"] = -math.inf, math.inf
    frames = {}
    for name in robot["links"]:
        if not model.existFrame(name, pin.BODY):
            raise SystemExit(f"Pinocchio has no body frame named {name}")
        frames[name] = model.getFrameId(name, pin.BODY)

    cases = []
    for case in robot["cases"]:
        q = pin.neutral(model)
        q[0:3] = case["base_position"]
        q[3:7] = case["base_quat_xyzw"]
        for name, value in case["q"].items():
            joint = model.joints[model.getJointId(name)]
            if joint.nq == 2:
                q[joint.idx_q : joint.idx_q + 2] = [math.cos(value), math.sin(value)]
            else:
                q[joint.idx_q] = value
        pin.forwardKinematics(model, data, q)
        pin.updateFramePlacements(model, data)
        placed = {}
        for name, f in frames.items():
            m = data.oMf[f]
            placed[name] = {
                "rotation": np.asarray(m.rotation).tolist(),
                "translation": np.asarray(m.translation).tolist(),
            }
        cases.append(placed)
    return {
        "name": robot["name"],
        "nq": model.nq,
        "nv": model.nv,
        "joint_order": [model.names[j] for j in movable],
        "limits": limits,
        "cases": cases,
    }


def main():
    with open(sys.argv[1]) as f:
        robots = json.load(f)
    json.dump([answer(r) for r in robots], sys.stdout)


if __name__ == "__main__":
    main()
