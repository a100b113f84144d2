"""PyTorch-autograd reference of the reverse-mode products libflame's gradient-guided editing uses
(MoLA's MPGD, sony/MoLA `models/mola_module.py`; docs/official/mola-mld.md#mola-mpgd-editing):
 x0 <- x0 - rho(t) * grad_x0 sum_{frame,joint}
||(J(x0) - c) * m||_2 with J = VAE decoder -> de-normalisation -> joint positions. Every product
here is the forward written from its definition and differentiated by torch.autograd.grad; nothing
is derived by hand.

- Conv1d(in, out, k, dilation d, padding d(k-1)/2) (float32): the gradient w.r.t. the input for a
  random upstream gradient; k = 3 with d = 1, 3, 9 and k = 1, on 7 frames (with d = 9 every tap
  but the centre falls off an end).
- Linear (float32), ReLU (float32, with inputs exactly 0: PyTorch gives gradient 0 there),
  nearest x2 upsampling over time (F.interpolate(scale_factor=2, mode="nearest") on [B, C, T]).
- De-normalisation y = x * std + mean and the loss sum_i ||(pos_i - c_i) * w_i||_2 (float64) with
  zero-weight coordinates, one row with an exactly zero residual and one with every weight 0.
- Joint positions (float64) of de-normalised features: humanml263 by the official
  recover_from_ric (cumulative sums, quaternion rotation by qinv(q_root)), smpl24_6d by pytorch3d's
  rotation_6d_to_matrix and SMPL forward kinematics; their vector-Jacobian products for a random
  position gradient.

The SMPL parents and rest offsets are not typed in here: they are imported from
tools/motion_reference.py, which transcribes the offset table of docs/official/smpl.md#rest-offsets (the
same decimal literals as
the runtime's skeleton, so both sides hold the same doubles).

Usage: python3 tools/reference/grad.py [--out tests/fixtures/grad_expected.safetensors]
Seeded, so reruns give the same file. Tensors use libflame's frame-major layouts ([frames, channels]);
names are listed in the file's metadata.
"""
import argparse
import os
import sys

import torch
import torch.nn.functional as F
from safetensors.torch import save_file

TOOLS = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, TOOLS)
from motion_reference import SMPL_OFFSETS, SMPL_PARENTS  # noqa: E402

GEN = torch.Generator().manual_seed(20240617)

CONV_CASES = [(3, 1), (3, 3), (3, 9), (1, 1)]
CONV_IN, CONV_OUT, CONV_FRAMES = 6, 18, 7


def nonzero(*shape, dtype=torch.float32, lo=0.1, hi=1.0):
    """Uniform magnitudes in [lo, hi) with random signs: never zero."""
    mag = lo + (hi - lo) * torch.rand(*shape, generator=GEN, dtype=torch.float64)
    sign = torch.where(torch.rand(*shape, generator=GEN) < 0.5, -1.0, 1.0).to(torch.float64)
    return (mag * sign).to(dtype)


def vjp(f, x, dy):
    x = x.clone().requires_grad_(True)
    y = f(x)
    (dx,) = torch.autograd.grad(y, x, dy)
    return y.detach(), dx


# -- layers (float32) ------------------------------------------------------------------------------

def conv_cases(out):
    for k, d in CONV_CASES:
        name = f"conv_k{k}_d{d}"
        w = nonzero(CONV_OUT, CONV_IN, k)
        b = nonzero(CONV_OUT)
        x = nonzero(CONV_FRAMES, CONV_IN)  # frame-major, as libflame holds it
        dy = nonzero(CONV_FRAMES, CONV_OUT)

        def conv(x):
            y = F.conv1d(x.T[None], w, b, padding=d * (k - 1) // 2, dilation=d)
            return y[0].T

        _, dx = vjp(conv, x, dy)
        out.update({f"{name}.weight": w, f"{name}.bias": b, f"{name}.x": x,
                    f"{name}.dy": dy, f"{name}.dx": dx})


def linear_case(out):
    rows, n_in, n_out = 5, 7, 20
    w, b = nonzero(n_out, n_in), nonzero(n_out)
    x, dy = nonzero(rows, n_in), nonzero(rows, n_out)
    _, dx = vjp(lambda x: F.linear(x, w, b), x, dy)
    out.update({"linear.weight": w, "linear.bias": b, "linear.x": x, "linear.dy": dy,
                "linear.dx": dx})


def relu_case(out):
    x = nonzero(40)
    x[[3, 17, 31]] = 0.0  # PyTorch's backward at exactly 0 gives 0
    dy = nonzero(40)
    y, dx = vjp(torch.relu, x, dy)
    out.update({"relu.x": x, "relu.y": y, "relu.dy": dy, "relu.dx": dx})


def upsample_case(out):
    frames, width = 4, 5
    x = nonzero(frames, width)
    dy = nonzero(2 * frames, width)

    def up(x):
        return F.interpolate(x.T[None], scale_factor=2, mode="nearest")[0].T

    y, dx = vjp(up, x, dy)
    assert torch.equal(y[1::2], x) and torch.equal(y[0::2], x)
    out.update({"upsample.dy": dy, "upsample.dx": dx})


# -- loss path (float64) ---------------------------------------------------------------------------

def denormalize_case(out):
    rows, dim = 3, 6
    std = nonzero(dim, dtype=torch.float32, lo=0.05, hi=2.0)
    mean = nonzero(dim, dtype=torch.float64)
    x, dy = nonzero(rows, dim, dtype=torch.float64), nonzero(rows, dim, dtype=torch.float64)
    _, dx = vjp(lambda x: x * std.to(torch.float64) + mean, x, dy)
    out.update({"denorm.std": std, "denorm.dy": dy, "denorm.dx": dx})


def l2_case(out):
    n = 10
    pos, target = nonzero(n, 3, dtype=torch.float64), nonzero(n, 3, dtype=torch.float64)
    weight = (torch.rand(n, 3, generator=GEN) < 0.6).to(torch.float64)
    weight[0] = torch.tensor([1.0, 0.0, 1.0])
    weight[4] = 1.0
    target[4] = pos[4]  # an exactly zero residual: torch's norm backward gives 0
    weight[7] = 0.0  # an unconstrained joint
    loss, grad = vjp(lambda p: torch.linalg.vector_norm((p - target) * weight, dim=-1).sum(),
                     pos, torch.tensor(1.0, dtype=torch.float64))
    assert torch.all(grad[4] == 0) and torch.all(grad[7] == 0)
    out.update({"l2.pos": pos, "l2.target": target, "l2.weight": weight, "l2.loss": loss[None],
                "l2.grad": grad})


# -- joint positions (float64) ---------------------------------------------------------------------

def qinv(q):
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def qrot(q, v):
    """Rotates v by the unit quaternion q (w first), HumanML3D's qrot."""
    qvec = q[..., 1:]
    uv = torch.cross(qvec, v, dim=-1)
    uuv = torch.cross(qvec, uv, dim=-1)
    return v + 2 * (q[..., :1] * uv + uuv)


def recover_from_ric(data, joints=22):
    """The official recover_root_rot_pos + recover_from_ric on [T, 263], without in-place writes."""
    rot_vel = data[:, 0]
    angle = torch.cumsum(torch.cat([rot_vel.new_zeros(1), rot_vel[:-1]]), dim=0)
    zero = torch.zeros_like(angle)
    q_root = torch.stack([angle.cos(), zero, angle.sin(), zero], dim=-1)
    vel = data[:-1, 1:3]
    planar = torch.cat([data.new_zeros(1, 3),
                        torch.stack([vel[:, 0], data.new_zeros(len(vel)), vel[:, 1]], dim=-1)])
    planar = torch.cumsum(qrot(qinv(q_root), planar), dim=0)
    r_pos = torch.stack([planar[:, 0], data[:, 3], planar[:, 2]], dim=-1)
    ric = data[:, 4:4 + (joints - 1) * 3].reshape(-1, joints - 1, 3)
    ric = qrot(qinv(q_root)[:, None, :].expand(-1, joints - 1, -1), ric)
    ric = ric + torch.stack([r_pos[:, 0], zero, r_pos[:, 2]], dim=-1)[:, None, :]
    return torch.cat([r_pos[:, None, :], ric], dim=1)


def rotation_6d_to_matrix(d6):
    """pytorch3d's rotation_6d_to_matrix: Gram-Schmidt, the results are the rows."""
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = F.normalize(a1, dim=-1)
    b2 = F.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack((b1, b2, b3), dim=-2)


def smpl_positions(data):
    """[T, 147] -> [T, 24, 3]: pelvis = translation + rest pelvis, SMPL forward kinematics."""
    offsets = torch.tensor(SMPL_OFFSETS, dtype=torch.float64)
    local = rotation_6d_to_matrix(data[:, 3:].reshape(-1, 24, 6))
    world, pos = [local[:, 0]], [data[:, :3] + offsets[0]]
    for j in range(1, 24):
        p = SMPL_PARENTS[j]
        world.append(world[p] @ local[:, j])
        pos.append(pos[p] + (world[p] @ offsets[j][:, None])[..., 0])
    return torch.stack(pos, dim=1)


def kinematics_cases(out):
    for name, frames, dim, joints, f in [("humanml263", 6, 263, 22, recover_from_ric),
                                         ("smpl24_6d", 4, 147, 24, smpl_positions)]:
        x = nonzero(frames, dim, dtype=torch.float64)
        d_pos = nonzero(frames, joints, 3, dtype=torch.float64)
        pos, dx = vjp(f, x, d_pos)
        out.update({f"{name}.x": x, f"{name}.positions": pos, f"{name}.d_pos": d_pos,
                    f"{name}.dx": dx})


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    root = os.path.dirname(TOOLS)
    ap.add_argument("--out", default=os.path.join(root, "tests/fixtures/grad_expected.safetensors"))
    args = ap.parse_args()
    out = {}
    for case in (conv_cases, linear_case, relu_case, upsample_case, denormalize_case, l2_case,
                 kinematics_cases):
        case(out)
    out = {k: v.contiguous() for k, v in out.items()}
    save_file(out, args.out, metadata={
        "generator": "tools/reference/grad.py",
        "conv": f"in {CONV_IN}, out {CONV_OUT}, frames {CONV_FRAMES}, (k, dilation) {CONV_CASES}",
    })
    print(f"wrote {args.out}: {len(out)} tensors, {os.path.getsize(args.out)} bytes")


if __name__ == "__main__":
    main()
