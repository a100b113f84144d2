"""HumanML3D `recover_from_ric` in torch (GuyTevet/motion-diffusion-model
`data_loaders/humanml/scripts/motion_process.py`; docs/official/humanml3d.md#recovering-joint-positions),
differentiable, in the dtype
of its input (float32 or float64).

Features `[..., T, 263]` (denormalised) -> joint positions `[..., T, 22, 3]`:
- θ[t] = Σ_{s<t} ω[s] (exclusive cumulative sum of channel 0, the root's yaw velocity);
  q_root[t] = (cos θ, 0, sin θ, 0) (w, x, y, z).
- root x, z: p[0] = 0, p[t] = Σ_{s=1..t} qinv(q_root[s]) ⊗ (v_x[s-1], 0, v_z[s-1]) (channels 1, 2
  of the PREVIOUS frame, rotated by the current frame's inverse root rotation); root y = channel 3.
- joints 1..21: channels 4..66 as 21 xyz triples, rotated by qinv(q_root[t]), plus root x, z.

Written without in-place writes so autograd sees plain ops (the official version assigns into
zero tensors, which gives the same values and gradients).
"""
import torch


def qinv(q):
    """(w, x, y, z) -> (w, -x, -y, -z)."""
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


def qrot(q, v):
    """Rotate v `[..., 3]` by the unit quaternion q `[..., 4]` (w first):
    v + 2·(w·(u × v) + u × (u × v)), u = q's vector part."""
    u = q[..., 1:]
    uv = torch.linalg.cross(u, v, dim=-1)
    uuv = torch.linalg.cross(u, uv, dim=-1)
    return v + 2 * (q[..., :1] * uv + uuv)


def root_rotation_and_position(data):
    """data `[..., T, C]` -> (q_root `[..., T, 4]`, root position `[..., T, 3]`)."""
    rot_vel = data[..., 0]
    shifted = torch.cat([torch.zeros_like(rot_vel[..., :1]), rot_vel[..., :-1]], dim=-1)
    theta = torch.cumsum(shifted, dim=-1)  # exclusive: θ[0] = 0
    zero = torch.zeros_like(theta)
    q = torch.stack([torch.cos(theta), zero, torch.sin(theta), zero], dim=-1)
    v = data[..., :-1, 1:3]  # planar velocity of frames 0..T-2
    vz = torch.zeros_like(v[..., :1])
    step = torch.cat([v[..., :1], vz, v[..., 1:2]], dim=-1)  # (v_x, 0, v_z)
    step = torch.cat([torch.zeros_like(step[..., :1, :]), step], dim=-2)  # frame 0 moves 0
    pos = torch.cumsum(qrot(qinv(q), step), dim=-2)
    pos = torch.stack([pos[..., 0], data[..., 3], pos[..., 2]], dim=-1)  # y = root height
    return q, pos


def recover_from_ric(data, joints=22):
    """data `[..., T, C]` (C >= 4 + 3·(joints-1), denormalised) -> `[..., T, joints, 3]`."""
    q, root = root_rotation_and_position(data)
    local = data[..., 4:4 + 3 * (joints - 1)]
    local = local.reshape(local.shape[:-1] + (joints - 1, 3))
    qj = qinv(q)[..., None, :].expand(local.shape[:-1] + (4,))
    world = qrot(qj, local)
    world = world + torch.stack([root[..., 0], torch.zeros_like(root[..., 0]), root[..., 2]],
                                dim=-1)[..., None, :]
    return torch.cat([root[..., None, :], world], dim=-2)


def feats2joints(features, mean, std, joints=22):
    """Normalised features `[..., T, 263]` -> joints `[..., T, joints, 3]` (x·std + mean first)."""
    return recover_from_ric(features * std + mean, joints)
