#!/usr/bin/env python3
"""Generate the MoLA MPGD-editing parity fixture tests/fixtures/mola_mpgd_expected.{safetensors,
json} on tests/fixtures/mola_tiny.safetensors (written by tools/make_latent_fixtures.py), from
tools/reference/mola_mpgd.py (seeded, deterministic).

Steps:
 1. Load the tiny model as tools/reference/mola.py `load_libflame` does, and the file's motion
    statistics (motion.mean / motion.std: the de-normalisation inside the editing loss).
 2. A reference motion: the decoder's raw features (first FRAMES frames, flag dropped,
    normalised space) of an unedited CFG-11 sample from its own noise; its joints by
    recover_from_ric; the controls of the tasks path, inbetweening and upper_edit built from
    them.
 3. Self-checks: recover_from_ric against the float64 numpy one of tools/motion_reference.py;
    the editing gradient against central finite differences in float64; edit scale 0
    reproduces mola.sample bit for bit; the float32 run against a float64 run of the same
    algorithm.
 4. For each task, the edited sampling (CFG 11, 50 steps, edit scale EDIT_SCALE) from x_T, and
    the expected values (frame-major) to mola_mpgd_expected.*; the unedited control errors go
    to the json for comparison.

Run from anywhere: python tools/make_mpgd_fixtures.py
"""
import copy
import json
import math
import os
import sys

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import save_file

TOOLS = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(TOOLS)
FIX = os.path.join(REPO, "tests", "fixtures")
sys.path.insert(0, TOOLS)

import motion_reference  # noqa: E402
from reference import mola, ric  # noqa: E402
from reference import mola_mpgd as mpgd  # noqa: E402

MODEL = "mola_tiny.safetensors"
STEM = "mola_mpgd_expected"
# (choice) 24 frames: latent (24 + 4)//4 = 7 rows, 28 decoded frames, so the loss window lies
# strictly inside the decoded range and the file stays small.
FRAMES = 24
STEPS = 50
GUIDANCE = 11.0
EDIT_SCALE = mpgd.DEFAULT_EDIT_SCALE
TASKS = ("path", "inbetweening", "upper_edit")
SEEDS = {"text": 40, "noise": 41, "reference_noise": 42, "fd_direction": 43}
MAX_BYTES = 300_000
THR_LOGIT = math.log(0.999 / 0.001)
MARGIN = 0.02  # every flag logit deciding the cut this far from the threshold


def log(msg):
    print(msg, file=sys.stderr)


def fm(x):
    """`[C, T]` -> `[T, C]`."""
    return x.transpose(0, 1).contiguous()


def rel(a, b):
    return float((a.double() - b.double()).abs().max() / b.double().abs().max())


def load():
    path = os.path.join(FIX, MODEL)
    den, dec, cfg = mola.load_libflame(path)
    with safe_open(path, "pt") as f:
        mean, std = f.get_tensor("motion.mean").float(), f.get_tensor("motion.std").float()
    return den, dec, cfg, mean, std


def check_ric(features, mean, std):
    want = motion_reference.hml_decode(features.numpy(), mean.numpy(), std.numpy())["positions"]
    got = ric.feats2joints(features.double(), mean.double(), std.double()).numpy()
    err = float(np.abs(got - want).max())
    log(f"recover_from_ric torch float64 vs numpy: max err {err:.2e}")
    assert err < 1e-12, err


def check_gradient(dec, x0, control, mean, std):
    """Directional derivatives of the loss (float64) by central differences vs autograd."""
    d64 = copy.deepcopy(dec).double()
    z, c, m, s = x0.double(), control.double(), mean.double(), std.double()
    g, _ = mpgd.mpgd_gradient(d64, z, c, m, s)
    gen = torch.Generator().manual_seed(SEEDS["fd_direction"])
    worst = 0.0
    with torch.no_grad():
        for _ in range(3):
            v = torch.randn(z.shape, generator=gen, dtype=torch.float64)
            h = 1e-6
            fd = (mpgd.control_loss(d64, z + h * v, c, m, s)
                  - mpgd.control_loss(d64, z - h * v, c, m, s)) / (2 * h)
            ad = (g * v).sum()
            worst = max(worst, float((fd - ad).abs() / ad.abs()))
    log(f"editing gradient vs central differences (float64): worst rel err {worst:.2e}")
    assert worst < 1e-6, worst


def control_error(dec, x, control, mean, std):
    """(mean ‖(J − c)⊙m‖₂ over the constrained joints, mean pelvis distance to the control's
    pelvis over its constrained frames) on the first FRAMES decoded frames."""
    mask = control != 0
    with torch.no_grad():
        j = mpgd.control_joints(dec, x, control.shape[1], mean, std)
    per_joint = torch.norm((j - control) * mask, dim=-1)
    joint_mask = mask.any(-1)
    pelvis = joint_mask[..., 0]
    d0 = torch.norm(j[..., 0, :] - control[..., 0, :], dim=-1)
    return (float(per_joint.sum() / joint_mask.sum()),
            float(d0[pelvis].mean()) if pelvis.any() else None)


def main():
    torch.set_num_threads(1)
    den, dec, cfg, mean, std = load()
    rows = mola.latent_frames(FRAMES)
    assert FRAMES < 4 * rows
    cond = torch.randn(1, cfg["denoiser"]["cond_dim"],
                       generator=torch.Generator().manual_seed(SEEDS["text"]))
    x_T = torch.randn(1, cfg["denoiser"]["latent_channels"], rows,
                      generator=torch.Generator().manual_seed(SEEDS["noise"]))
    x_R = torch.randn(x_T.shape, generator=torch.Generator().manual_seed(SEEDS["reference_noise"]))
    with torch.no_grad():
        ref_latent = mola.sample(den, x_R, cond, GUIDANCE, STEPS)[-1]["x"]
        ref_features = fm(dec(ref_latent)[0, :-1, :FRAMES])  # [FRAMES, 263], normalised
        ref_joints = ric.feats2joints(ref_features, mean, std)
        unedited = mola.sample(den, x_T, cond, GUIDANCE, STEPS)
    check_ric(ref_features, mean, std)

    t = {"text": cond[0], "noise": fm(x_T[0]), "edit_scale": torch.tensor(EDIT_SCALE),
         "reference_features": ref_features, "reference_joints": ref_joints,
         "mean": mean, "std": std}
    errors, lengths, masks = {}, {}, {}
    for task in TASKS:
        control = mpgd.CONTROLS[task](ref_joints)[None]  # [1, FRAMES, 22, 3]
        masks[task] = {"coordinates": int((control != 0).sum()),
                       "joints_any": int((control != 0).any(-1).sum())}
        tr = mpgd.sample_mpgd(den, dec, x_T, cond, control, mean, std, EDIT_SCALE, GUIDANCE,
                              STEPS)
        if task == TASKS[0]:
            check_gradient(dec, tr[0]["x0"], control, mean, std)
            zero = mpgd.sample_mpgd(den, dec, x_T, cond, control, mean, std, 0.0, GUIDANCE,
                                    STEPS)
            for a, b in zip(zero, unedited):
                assert torch.equal(a["x"], b["x"]) and torch.equal(a["x0_edit"], b["x0"])
            log("edit scale 0 == mola.sample (bit-identical)")
            d64, v64 = copy.deepcopy(den).double(), copy.deepcopy(dec).double()
            tr64 = mpgd.sample_mpgd(d64, v64, x_T.double(), cond.double(), control.double(),
                                    mean.double(), std.double(), EDIT_SCALE, GUIDANCE, STEPS)
            worst = max(rel(a["x"], b["x"]) for a, b in zip(tr, tr64))
            log(f"{task}: float32 vs float64 run, worst rel diff of the latents {worst:.2e}")
            assert worst < 1e-4, worst
        x = tr[-1]["x"]
        with torch.no_grad():
            feats, n, raw = mola.decode(dec, x)
            joints = ric.feats2joints(feats, mean, std)
        t[f"{task}_control"] = control[0]
        t[f"{task}_rho"] = torch.stack([s["rho"] for s in tr]).float()
        t[f"{task}_loss"] = torch.stack([s["loss"] for s in tr])
        t[f"{task}_x0_first"] = fm(tr[0]["x0"][0])
        t[f"{task}_grad_first"] = fm(tr[0]["grad"][0])
        t[f"{task}_x0s"] = torch.stack([fm(s["x0_edit"][0]) for s in tr])
        t[f"{task}_xs"] = torch.stack([fm(s["x"][0]) for s in tr])
        t[f"{task}_flag_logits"] = raw[-1]
        t[f"{task}_features"] = feats
        t[f"{task}_length"] = torch.tensor(float(n))
        t[f"{task}_joints"] = joints
        lengths[task] = n
        errors[task] = {"edited": control_error(dec, x, control, mean, std),
                        "unedited": control_error(dec, unedited[-1]["x"], control, mean, std)}
        log(f"{task}: control error (mean over constrained joints, pelvis) edited "
            f"{errors[task]['edited']} vs unedited {errors[task]['unedited']}; cut {n}")
        assert errors[task]["edited"][0] < 0.8 * errors[task]["unedited"][0], errors[task]
        assert 10 <= n < 4 * rows
        margin = float((raw[-1][:n + 1] - THR_LOGIT).abs().min())
        assert margin >= MARGIN, (task, margin)

    info = {
        "description": "MoLA MPGD editing parity fixture; generated by tools/make_mpgd_fixtures.py "
                       "from tools/reference/mola_mpgd.py on mola_tiny.safetensors. Frame-major: "
                       "latents [latent_frames, 16], features [frames, 263] normalised.",
        "model": MODEL, "frames": FRAMES, "latent_frames": rows, "decoded_frames": 4 * rows,
        "steps": STEPS, "guidance": GUIDANCE, "edit_scale": EDIT_SCALE, "tasks": list(TASKS),
        "inputs": "text [512] (the conditioning vector; uncond = zeros), noise = x_T "
                  "[latent_frames, 16], edit_scale, mean/std = the model file's motion.mean/"
                  "motion.std (used inside the loss)",
        "reference": "reference_features [frames, 263]: raw decoder features (flag dropped, "
                     "first `frames` frames) of an unedited CFG-11 sample from another noise; "
                     "reference_joints [frames, 22, 3] = recover_from_ric(features*std + mean)",
        "controls": "<task>_control [frames, 22, 3]; zeros = unconstrained, mask per coordinate "
                    "(c != 0). path: joint 0 (xyz) on every frame; inbetweening: all joints on "
                    "frames 0..3 and frames-4..frames-1; upper_edit: joints 0,1,2,4,5,7,8,10,11 "
                    "on every frame. The reference root starts at x = z = 0, so frame 0's pelvis "
                    "x and z are unconstrained in every task.",
        "algorithm": "per step k (t = 999 - 20k): eps = u + 11(c - u); x0 = (x - sqrt(1-abar_t) "
                     "eps)/sqrt(abar_t); loss = sum_{frame,joint} ||(J(x0) - c)*m||_2 (xyz), J = "
                     "recover_from_ric(decoder(x0)[:frames, :263]*std + mean) without flag "
                     "sigmoid; rho = -t(t-1000)/1000/1000*4*s; x0' = x0 - rho*grad; x = "
                     "sqrt(abar_prev) x0' + sqrt(1-abar_prev) eps (original eps; abar_prev = "
                     "abar_0 at t = 19)",
        "trajectories": "<task>_xs[k] = latent after step k (start = noise); <task>_x0s[k] = "
                        "the EDITED x0' at step k; <task>_rho[k], <task>_loss[k] = rho(t_k) and "
                        "the loss at the unedited x0 of step k; <task>_x0_first / "
                        "<task>_grad_first = the unedited x0 of step 0 and its loss gradient",
        "output": "<task>_features = decode(xs[-1]) cut by the flag as without editing (first "
                  "frame with sigmoid(flag) <= 0.999, min 10; not by `frames`), <task>_length "
                  "that cut, <task>_flag_logits the raw flag of all decoded frames, "
                  "<task>_joints = recover_from_ric of <task>_features",
        "session": "session frames = `frames` (the control's length); latent rows = "
                   "(frames + 4)//4",
        "mask_counts": masks,
        "lengths": lengths,
        "control_errors": {k: {"note": "(mean ||(J - c)*m|| over constrained joints, mean "
                                       "pelvis distance over frames with a pelvis control) on "
                                       "the first `frames` decoded frames", **v}
                           for k, v in errors.items()},
        "seeds": SEEDS,
    }
    tensors = {k: v.float().contiguous() for k, v in t.items()}
    for k, v in tensors.items():
        assert torch.isfinite(v).all(), k
        log(f"  {k:28s} {str(list(v.shape)):14s} max|x| {v.abs().max():.4g}")
    out = os.path.join(FIX, STEM + ".safetensors")
    save_file(tensors, out, metadata={"generator": "tools/make_mpgd_fixtures.py"})
    info["tensors"] = {k: list(v.shape) for k, v in tensors.items()}
    with open(os.path.join(FIX, STEM + ".json"), "w") as f:
        json.dump(info, f, indent=1)
        f.write("\n")
    size = os.path.getsize(out) + os.path.getsize(os.path.join(FIX, STEM + ".json"))
    log(f"MPGD fixture {size / 1e3:.1f} kB")
    assert size < MAX_BYTES, size
    return 0


if __name__ == "__main__":
    sys.exit(main())
