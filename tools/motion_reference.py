#!/usr/bin/env python3
"""Independent NumPy reference of libflame's motion decoding, written from the official procedures
(docs/official/flame.md#output-post-processing, docs/official/flame.md#motion-representation,
docs/official/humanml3d.md and docs/official/smpl.md) without reading the Rust code.

It synthesises two real-looking motions (a walk with root travel and turning, smooth sinusoidal
joint angles on every axis), encodes them to model features, decodes them with the official
procedures and writes what libflame must reproduce to tests/fixtures/motion_reference.safetensors
(float32 tensors; the decoding runs in float64 from the float32 features):

smpl24_6d (FLAME; docs/official/flame.md#motion-representation), 36 frames:
  smpl_features [T,147]          translation (AMASS Z-up, metres) + 24 x 6D ROW convention
  smpl_root [T,3]                pelvis world position = trans + rest pelvis (SMPL FK)
  smpl_local_wxyz [T,24,4]       parent-relative rotations, pytorch3d matrix->quaternion, w >= 0
  smpl_global_wxyz [T,24,4]      world rotations, world_R(j) = world_R(parent) . R_local(j)
  smpl_positions [T,24,3]        SMPL FK with the rest offsets of docs/official/smpl.md#rest-offsets
  smpl_local_wxyz_continuous     the same with q[t] flipped when dot(q[t], q[t-1]) < 0
  smpl_smooth_features [T,147]   scipy gaussian_filter1d(sigma=1, mode reflect, truncate 4) over time
  smpl_smooth_positions, smpl_smooth_local_wxyz   decoded from the smoothed features

humanml263 (HumanML3D, docs/official/humanml3d.md#feature-layout), features built
directly (smooth root velocities,
ric positions, column-convention cont6d rotations, local velocities, 0/1 contacts), 30 frames:
  hml_features [T,263] (normalised), hml_mean [263], hml_std [263]
  hml_positions [T,22,3]         recover_from_ric after x * std + mean
  hml_root [T,3]                 recover_root_rot_pos position
  hml_local_wxyz, hml_global_wxyz, hml_local_wxyz_continuous   see "HumanML3D tree rotations"
  hml_contacts [T,4]             dims 259..262 de-normalised

HumanML3D tree rotations (libflame's documented derivation; docs/official/humanml3d.md#rotation-features
states the raw data):
the official recover_from_rot chain product gives, for every joint j >= 1, the world rotation B(j)
of the bone that ends at j: per kinematic chain, M = R(q_root), then M = M . R6(j) for each next
joint j, B(j) = M. A standard parent-relative hierarchy needs one world rotation per joint:
  G(0) = R(q_root)^T (the body's facing yaw, consistent with recover_from_ric's qinv(q_root)),
  G(j) = B(next joint of j in its kinematic chain) when j has one (9 -> 12, the neck chain),
  G(leaf) = G(parent(leaf)) for 10, 11, 15, 20, 21,
  local(0) = G(0), local(j) = G(parent)^T G(j).

Usage: python3 tools/motion_reference.py [--out tests/fixtures/motion_reference.safetensors]
Byte-for-byte reproducible (seeded; the safetensors file is written here with sorted keys);
needs numpy and scipy.
"""
import argparse
import json
import os
import struct

import numpy as np
from scipy.ndimage import gaussian_filter1d

# ---------------------------------------- skeletons (docs/official/smpl.md, docs/official/humanml3d.md#skeleton)

SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
SMPL_OFFSETS = np.array([
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
    [0.08404218, -0.00816154, -0.01494537],
    [-0.08462193, -0.00611726, -0.01031508],
])

HML_PARENTS = SMPL_PARENTS[:22]
HML_CHAINS = [[0, 2, 5, 8, 11], [0, 1, 4, 7, 10], [0, 3, 6, 9, 12, 15],
              [9, 14, 17, 19, 21], [9, 13, 16, 18, 20]]
HML_DIRS = np.array([
    [0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0], [0, -1, 0],
    [0, -1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1],
    [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0]], dtype=np.float64)
# Bone lengths are in no repository: each HumanML3D bone takes the length of the same SMPL joint's
# rest offset (libflame's documented choice).
HML_OFFSETS = HML_DIRS * np.linalg.norm(SMPL_OFFSETS[:22], axis=1, keepdims=True)
HML_OFFSETS[0] = 0.0

# ---------------------------------------------------------------- rotation math


def normalize(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def rot6d_rows_to_matrix(d6):
    """pytorch3d rotation_6d_to_matrix: b1, b2, b3 are the ROWS (docs/official/flame.md#6d-to-rotation-matrix)."""
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = normalize(a1)
    b2 = normalize(a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1)
    b3 = np.cross(b1, b2)
    return np.stack([b1, b2, b3], axis=-2)


def matrix_to_rot6d_rows(m):
    return np.concatenate([m[..., 0, :], m[..., 1, :]], axis=-1)


def cont6d_to_matrix(d6):
    """HumanML3D cont6d: COLUMN convention (docs/official/humanml3d.md#cont6d-column-convention)."""
    x = normalize(d6[..., :3])
    z = normalize(np.cross(x, d6[..., 3:]))
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def matrix_to_cont6d(m):
    return np.concatenate([m[..., :, 0], m[..., :, 1]], axis=-1)


def matrix_to_quat_wxyz(m):
    """pytorch3d matrix_to_quaternion (docs/official/flame.md#rotation-matrix-to-quaternion), then w >= 0."""
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    q_abs = np.sqrt(np.maximum(0.0, np.stack([
        1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)))
    cands = np.stack([
        np.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1),
        np.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], -1),
        np.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m12 + m21], -1),
        np.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], -1),
    ], -2)
    cands = cands / (2.0 * np.maximum(q_abs[..., None], 0.1))
    best = np.argmax(q_abs, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    return np.where(q[..., :1] < 0, -q, q)


def quat_to_matrix(q):
    """HumanML3D quaternion_to_matrix (docs/official/humanml3d.md#quaternion-conventions), w first."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    s = 2.0 / np.sum(q * q, axis=-1)
    return np.stack([
        np.stack([1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)], -1),
        np.stack([s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)], -1),
        np.stack([s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)], -1),
    ], -2)


def qinv(q):
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def qrot(q, v):
    """Active rotation of v by unit q (docs/official/humanml3d.md#quaternion-conventions)."""
    w = q[..., :1]
    u = q[..., 1:]
    uv = np.cross(u, v)
    return v + 2.0 * (w * uv + np.cross(u, uv))


def axis_angle_to_matrix(aa):
    theta = np.linalg.norm(aa, axis=-1, keepdims=True)
    k = aa / np.maximum(theta, 1e-12)
    kx, ky, kz = k[..., 0], k[..., 1], k[..., 2]
    zero = np.zeros_like(kx)
    K = np.stack([np.stack([zero, -kz, ky], -1), np.stack([kz, zero, -kx], -1),
                  np.stack([-ky, kx, zero], -1)], -2)
    th = theta[..., None]
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + np.sin(th) * K + (1 - np.cos(th)) * (K @ K)


def rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def continuous(q):
    """Flip q[t] when dot(q[t], q[t-1]) < 0, frame by frame along axis 0."""
    q = q.copy()
    for t in range(1, q.shape[0]):
        flip = np.sum(q[t] * q[t - 1], axis=-1) < 0
        q[t][flip] = -q[t][flip]
    return q


# ---------------------------------------------------------------- smpl24_6d decoding


def smpl_decode(features):
    f = features.astype(np.float64)
    T = f.shape[0]
    trans = f[:, :3]
    local = rot6d_rows_to_matrix(f[:, 3:].reshape(T, 24, 6))
    glob = np.zeros_like(local)
    pos = np.zeros((T, 24, 3))
    for j, p in enumerate(SMPL_PARENTS):
        if p < 0:
            glob[:, j] = local[:, j]
            # The root rotation acts about the rest pelvis: pelvis_world = trans + J_pelvis.
            pos[:, j] = trans + SMPL_OFFSETS[0]
        else:
            glob[:, j] = glob[:, p] @ local[:, j]
            pos[:, j] = pos[:, p] + np.einsum("tij,j->ti", glob[:, p], SMPL_OFFSETS[j])
    return {
        "root": pos[:, 0],
        "local_wxyz": matrix_to_quat_wxyz(local),
        "global_wxyz": matrix_to_quat_wxyz(glob),
        "positions": pos,
    }


# ---------------------------------------------------------------- humanml263 decoding


def hml_root(d):
    """recover_root_rot_pos (docs/official/humanml3d.md#recovering-joint-positions): q_root [T,4] and root
    position [T,3]."""
    T = d.shape[0]
    theta = np.zeros(T)
    theta[1:] = np.cumsum(d[:-1, 0])
    q = np.stack([np.cos(theta), np.zeros(T), np.sin(theta), np.zeros(T)], -1)
    v = np.zeros((T, 3))
    v[1:, 0] = d[:-1, 1]
    v[1:, 2] = d[:-1, 2]
    v = qrot(qinv(q), v)
    pos = np.cumsum(v, axis=0)
    pos[:, 1] = d[:, 3]
    return q, pos


def hml_decode(norm_features, mean, std):
    d = norm_features.astype(np.float64) * std.astype(np.float64) + mean.astype(np.float64)
    T = d.shape[0]
    q_root, root = hml_root(d)
    ric = d[:, 4:67].reshape(T, 21, 3)
    ric = qrot(np.repeat(qinv(q_root)[:, None], 21, axis=1), ric)
    ric[..., 0] += root[:, None, 0]
    ric[..., 2] += root[:, None, 2]
    positions = np.concatenate([root[:, None], ric], axis=1)

    rot = cont6d_to_matrix(d[:, 67:193].reshape(T, 21, 6))
    r_root = quat_to_matrix(q_root)
    bone = np.zeros((T, 22, 3, 3))
    for chain in HML_CHAINS:
        m = r_root
        for j in chain[1:]:
            m = m @ rot[:, j - 1]
            bone[:, j] = m
    glob = np.zeros((T, 22, 3, 3))
    glob[:, 0] = np.swapaxes(r_root, -1, -2)
    next_in_chain = {}
    for chain in HML_CHAINS:
        for a, b in zip(chain[1:-1], chain[2:]):
            next_in_chain[a] = b
    next_in_chain[9] = 12
    for j in range(1, 22):
        glob[:, j] = bone[:, next_in_chain[j]] if j in next_in_chain else glob[:, HML_PARENTS[j]]
    local = np.zeros_like(glob)
    local[:, 0] = glob[:, 0]
    for j in range(1, 22):
        local[:, j] = np.swapaxes(glob[:, HML_PARENTS[j]], -1, -2) @ glob[:, j]
    return {
        "root": root,
        "positions": positions,
        "local_wxyz": matrix_to_quat_wxyz(local),
        "global_wxyz": matrix_to_quat_wxyz(glob),
        "contacts": d[:, 259:263],
    }


# ---------------------------------------------------------------- synthetic motions


def smooth_angles(rng, t, n, amp):
    """n smooth angle tracks: a sum of two sinusoids with random phases and frequencies."""
    f = rng.uniform(0.3, 1.5, size=(2, n))
    ph = rng.uniform(0, 2 * np.pi, size=(2, n))
    a = rng.uniform(0.3, 1.0, size=(2, n)) * amp
    return sum(a[k] * np.sin(2 * np.pi * f[k] * t[:, None] + ph[k]) for k in range(2))


def synth_smpl(T=36, fps=20.0, seed=7):
    rng = np.random.default_rng(seed)
    t = np.arange(T) / fps
    phase = 2 * np.pi * 0.9 * t
    aa = smooth_angles(rng, t, 24 * 3, 0.15).reshape(T, 24, 3)  # every joint, every axis
    # A walk on top: hips and knees flex about the body's X (left) axis, arms hang (about Z) and
    # swing, elbows bend, the spine twists.
    aa[:, 1, 0] += 0.5 * np.sin(phase)
    aa[:, 2, 0] -= 0.5 * np.sin(phase)
    aa[:, 4, 0] += 0.45 + 0.35 * np.sin(phase + 1.2)
    aa[:, 5, 0] += 0.45 - 0.35 * np.sin(phase + 1.2)
    aa[:, 16, 2] -= 1.1
    aa[:, 17, 2] += 1.1
    aa[:, 16, 0] -= 0.4 * np.sin(phase)
    aa[:, 17, 0] += 0.4 * np.sin(phase)
    aa[:, 18, 1] += 0.6
    aa[:, 19, 1] -= 0.6
    aa[:, 3, 1] += 0.12 * np.sin(phase)
    local = axis_angle_to_matrix(aa)
    # Root: the +90 deg X tilt that stands the Y-up body in AMASS's Z-up world, a turn about Z of
    # about 160 deg over the clip, and a little body sway.
    yaw = 1.5 * t + 0.25 * np.sin(1.7 * t)
    for i in range(T):
        local[i, 0] = rot_z(yaw[i]) @ rot_x(np.pi / 2) @ local[i, 0]
    facing = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros(T)], -1)  # Rz(yaw) . (0, -1, 0)
    trans = np.array([0.013, 0.348, 0.964]) + np.cumsum(1.3 / fps * facing, axis=0)
    trans[:, 2] = 0.93 + 0.02 * np.cos(2 * phase)
    d6 = matrix_to_rot6d_rows(local)
    # A denoiser's 6D output is not orthonormal: scale the rows and skew the second a little.
    d6[..., :3] *= rng.uniform(0.8, 1.2, size=(1, 24, 1))
    d6[..., 3:] = d6[..., 3:] * rng.uniform(0.8, 1.2, size=(1, 24, 1)) + 0.05 * d6[..., :3]
    feats = np.concatenate([trans, d6.reshape(T, 144)], axis=1)
    return feats.astype(np.float32)


def synth_hml(T=30, fps=20.0, seed=11):
    rng = np.random.default_rng(seed)
    t = np.arange(T) / fps
    phase = 2 * np.pi * 0.9 * t
    d = np.zeros((T, 263))
    d[:, 0] = 0.035 + 0.02 * np.sin(1.3 * t)            # half the yaw change per frame
    d[:, 1] = 0.01 * np.sin(phase)                       # sideways velocity (facing frame)
    d[:, 2] = 0.065 + 0.01 * np.cos(2 * phase)           # forward velocity (+Z)
    d[:, 3] = 0.95 + 0.02 * np.cos(2 * phase)            # root height
    rest = np.zeros((22, 3))
    for j in range(1, 22):
        rest[j] = rest[HML_PARENTS[j]] + HML_OFFSETS[j]
    ric = rest[1:][None] + smooth_angles(rng, t, 63, 0.05).reshape(T, 21, 3)
    ric[..., 1] += d[:, 3:4]
    d[:, 4:67] = ric.reshape(T, 63)
    rot = axis_angle_to_matrix(smooth_angles(rng, t, 63, 0.6).reshape(T, 21, 3))
    c6 = matrix_to_cont6d(rot)
    # Model outputs are not orthonormal: scale each half and skew the second column a little so
    # the Gram-Schmidt step matters.
    c6[..., :3] *= rng.uniform(0.7, 1.3, size=(1, 21, 1))
    c6[..., 3:] = c6[..., 3:] * rng.uniform(0.7, 1.3, size=(1, 21, 1)) + 0.1 * c6[..., :3]
    d[:, 67:193] = c6.reshape(T, 126)
    d[:, 193:259] = smooth_angles(rng, t, 66, 0.03)
    d[:, 259:263] = (np.sin(phase[:, None] + np.array([0.0, 0.4, np.pi, np.pi + 0.4])) > 0)
    mean = rng.normal(0.0, 0.3, size=263)
    std = rng.uniform(0.1, 1.5, size=263)
    norm = ((d - mean) / std).astype(np.float32)
    return norm, mean.astype(np.float32), std.astype(np.float32)


# ---------------------------------------------------------------- fixture


def save_safetensors(tensors, path, metadata):
    """float32 tensors in the safetensors layout (8-byte header length, JSON header, data), keys
    sorted so the file is the same on every run."""
    header, blobs, offset = {"__metadata__": metadata}, [], 0
    for name in sorted(tensors):
        blob = np.ascontiguousarray(tensors[name], dtype="<f4").tobytes()
        header[name] = {"dtype": "F32", "shape": list(tensors[name].shape),
                        "data_offsets": [offset, offset + len(blob)]}
        blobs.append(blob)
        offset += len(blob)
    text = json.dumps(header, sort_keys=True, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(text)) + text + b"".join(blobs))



def main():
    ap = argparse.ArgumentParser()
    here = os.path.dirname(os.path.abspath(__file__))
    ap.add_argument("--out", default=os.path.join(here, "..", "tests", "fixtures",
                                                  "motion_reference.safetensors"))
    args = ap.parse_args()

    out = {}
    sf = synth_smpl()
    out["smpl_features"] = sf
    ref = smpl_decode(sf)
    for k in ("root", "local_wxyz", "global_wxyz", "positions"):
        out["smpl_" + k] = ref[k]
    out["smpl_local_wxyz_continuous"] = continuous(ref["local_wxyz"])
    out["smpl_global_wxyz_continuous"] = continuous(ref["global_wxyz"])
    # FLAME's official post-processing (docs/official/flame.md#temporal-smoothing), computed by scipy
    # itself.
    smooth = gaussian_filter1d(sf.astype(np.float64), 1.0, axis=0, mode="reflect", truncate=4.0)
    out["smpl_smooth_features"] = smooth
    sref = smpl_decode(smooth)
    out["smpl_smooth_positions"] = sref["positions"]
    out["smpl_smooth_local_wxyz"] = sref["local_wxyz"]

    hf, mean, std = synth_hml()
    out["hml_features"], out["hml_mean"], out["hml_std"] = hf, mean, std
    href = hml_decode(hf, mean, std)
    for k in ("root", "positions", "local_wxyz", "global_wxyz", "contacts"):
        out["hml_" + k] = href[k]
    out["hml_local_wxyz_continuous"] = continuous(href["local_wxyz"])

    # Quaternion signs are only comparable away from w = 0 (w >= 0 is ambiguous there).
    for k in ("smpl_local_wxyz", "smpl_global_wxyz", "hml_local_wxyz", "hml_global_wxyz"):
        assert np.min(np.abs(out[k][..., 0])) > 1e-3, k
    travel = np.linalg.norm(ref["root"][-1, :2] - ref["root"][0, :2])
    meta = {
        "generator": "tools/motion_reference.py",
        "smpl_frames": str(sf.shape[0]), "hml_frames": str(hf.shape[0]),
        "smpl_root_travel_m": f"{travel:.3f}",
        "quaternion_sign": "pytorch3d matrix_to_quaternion, then w >= 0",
        "notes": json.dumps("float64 decoding of the float32 features; tensors stored as float32"),
    }
    tensors = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}
    save_safetensors(tensors, args.out, meta)
    print(f"wrote {args.out}: " + ", ".join(f"{k} {list(v.shape)}" for k, v in tensors.items()))
    print(f"smpl root travel {travel:.3f} m; hml root travel "
          f"{np.linalg.norm(href['root'][-1] - href['root'][0]):.3f} m")


if __name__ == "__main__":
    main()
