"""NumPy's view of libflame's AMASS exports (run by tests/amass_export.rs).

    python tests/amass_numpy.py SMPLH.npz SMPLX.npz POSITIONS.npy --fps F --frames N

Loads both files with `np.load` as the pipelines do (GMR: `str(d["gender"])`,
`d["mocap_frame_rate"].item()`, `pose_body`, `root_orient`, `trans`; PHC / human2humanoid and
HumanML3D's raw_pose_processing: `poses`, `trans`, `mocap_framerate`), checks every key's dtype
and shape against AMASS's (nghorbani/amass; SMPL-H `*_poses.npz`, SMPL-X `*_stageii.npz`), and
runs SMPL forward kinematics written here with NumPy from the offset table of the neutral SMPL
template (Stanford-TML/EDGE `vis.py` `smpl_offsets`, as docs/official/smpl.md#rest-offsets lists it):
the pelvis at `trans + J_pelvis`, `p(j) = p(parent) + G(parent) offset(j)`, `G(j) =
G(parent) R(pose_j)`. The joints must match the positions libflame wrote (its own joints in the
AMASS world, float32) within 1e-5 m. Exits non-zero on any mismatch.
"""

import argparse
import sys

import numpy as np

# Rows: joint - parent, metres; row 0 the pelvis's rest position (SMPL body frame, Y up).
OFFSETS = np.array([
    [-0.00179506, -0.22333345, 0.02821913],
    [0.06951974, -0.09140623, -0.00681534],
    [-0.06767048, -0.09052168, -0.00431982],
    [-0.00253286, 0.10896323, -0.02669631],
    [0.03427655, -0.37519860, -0.00449580],
    [-0.03829005, -0.38256901, -0.00885003],
    [0.00548703, 0.13518043, 0.00109247],
    [-0.01359570, -0.39796036, -0.04369333],
    [0.01577377, -0.39841465, -0.04231180],
    [0.00145700, 0.05292223, 0.02542457],
    [0.02635814, -0.05579088, 0.11928840],
    [-0.02537175, -0.04814396, 0.12334795],
    [-0.00277839, 0.21387036, -0.04285703],
    [0.07884474, 0.12174930, -0.03408961],
    [-0.08175919, 0.11883283, -0.03861529],
    [0.00515184, 0.06496961, 0.05134897],
    [0.09097693, 0.03046890, -0.00886815],
    [-0.09601238, 0.03255117, -0.00914307],
    [0.25961225, -0.01277206, -0.02745644],
    [-0.25374196, -0.01332922, -0.02140098],
    [0.24923363, 0.00898603, -0.00117092],
    [-0.25529808, 0.00777229, -0.00555919],
])
PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19]


def rodrigues(v):
    """[..., 3] axis-angle vectors -> [..., 3, 3] rotation matrices."""
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    axis = np.divide(v, angle, out=np.zeros_like(v), where=angle > 0)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = np.zeros_like(x)
    k = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(v.shape[:-1] + (3, 3))
    s, c = np.sin(angle)[..., None], np.cos(angle)[..., None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def forward_kinematics(root_orient, pose_body, trans):
    n = trans.shape[0]
    local = rodrigues(np.concatenate([root_orient[:, None], pose_body.reshape(n, 21, 3)], 1))
    world = [local[:, 0]]
    pos = [trans + OFFSETS[0]]
    for j in range(1, 22):
        p = PARENTS[j]
        pos.append(pos[p] + np.einsum("nij,j->ni", world[p], OFFSETS[j]))
        world.append(world[p] @ local[:, j])
    return np.stack(pos, 1)


def expect(cond, what):
    if not cond:
        print(f"FAIL: {what}")
        sys.exit(1)


def check_array(d, key, dtype, shape):
    a = d[key]
    expect(a.dtype == np.dtype(dtype), f"{key}: dtype {a.dtype}, expected {dtype}")
    expect(a.shape == shape, f"{key}: shape {a.shape}, expected {shape}")
    expect(np.all(np.isfinite(a)), f"{key}: not finite")
    return a


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("smplh")
    ap.add_argument("smplx")
    ap.add_argument("positions")
    ap.add_argument("--fps", type=float, required=True)
    ap.add_argument("--frames", type=int, required=True)
    a = ap.parse_args()
    n, fps = a.frames, a.fps
    f8 = "<f8"

    h = np.load(a.smplh)
    expect(sorted(h.files) == sorted(["poses", "trans", "betas", "gender", "mocap_framerate",
                                      "dmpls"]), f"SMPL-H keys {h.files}")
    poses_h = check_array(h, "poses", f8, (n, 156))
    trans_h = check_array(h, "trans", f8, (n, 3))
    expect(not check_array(h, "betas", f8, (16,)).any(), "betas are zeros")
    expect(not check_array(h, "dmpls", f8, (n, 8)).any(), "dmpls are zeros")
    expect(h["gender"].dtype.kind == "U" and h["gender"].shape == (), "gender is a 0-d str")
    expect(str(h["gender"]) == "neutral", f"gender {h['gender']!r}")
    rate = check_array(h, "mocap_framerate", f8, ())
    expect(float(rate) == fps, f"mocap_framerate {rate}")
    # HumanML3D's raw_pose_processing slices the SMPL-H poses so.
    expect(not poses_h[:, 66:].any(), "hands at rest")

    x = np.load(a.smplx)
    want = ["root_orient", "pose_body", "pose_hand", "pose_jaw", "pose_eye", "trans", "betas",
            "num_betas", "gender", "surface_model_type", "mocap_frame_rate",
            "mocap_time_length", "poses"]
    expect(sorted(x.files) == sorted(want), f"SMPL-X keys {x.files}")
    root = check_array(x, "root_orient", f8, (n, 3))
    body = check_array(x, "pose_body", f8, (n, 63))
    trans = check_array(x, "trans", f8, (n, 3))
    for key, width in (("pose_hand", 90), ("pose_jaw", 3), ("pose_eye", 6)):
        expect(not check_array(x, key, f8, (n, width)).any(), f"{key} at rest")
    expect(not check_array(x, "betas", f8, (16,)).any(), "betas are zeros")
    expect(x["num_betas"].dtype == np.int64 and int(x["num_betas"]) == 16, "num_betas")
    expect(str(x["gender"]) == "neutral", "SMPL-X gender")
    expect(str(x["surface_model_type"]) == "smplx", "surface_model_type")
    expect(x["mocap_frame_rate"].item() == fps, "mocap_frame_rate")
    expect(abs(x["mocap_time_length"].item() - n / fps) < 1e-12, "mocap_time_length")
    poses_x = check_array(x, "poses", f8, (n, 165))
    expect(np.array_equal(poses_x[:, :3], root) and np.array_equal(poses_x[:, 3:66], body),
           "SMPL-X poses starts with root_orient and pose_body")
    expect(not poses_x[:, 66:].any(), "SMPL-X poses: jaw, eyes and hands at rest")
    expect(np.array_equal(poses_h[:, :66], poses_x[:, :66]) and np.array_equal(trans_h, trans),
           "both layouts hold the same motion")

    positions = np.load(a.positions).astype(np.float64)
    expect(positions.shape == (n, 22, 3), f"positions shape {positions.shape}")
    err_x = np.abs(forward_kinematics(root, body, trans) - positions).max()
    err_h = np.abs(forward_kinematics(poses_h[:, :3], poses_h[:, 3:66], trans_h)
                   - positions).max()
    print(f"numpy fk max error {err_h:.2e} m (SMPL-H), {err_x:.2e} m (SMPL-X), {n} frames")
    expect(max(err_h, err_x) <= 1e-5, "forward kinematics within 1e-5 m")


if __name__ == "__main__":
    main()
