"""libflame's humanoid retargeter against the anchor, mink differential IK as GMR drives it, on
the same machine, motions, robot, body pairs, weights and scales.

    target/test-venv/bin/python tools/robot_bench.py [--robot gr1t2] [--runs 5] [--frames 120]

What runs:
- `flame-bench robot-retarget` (release build, one thread) generates the demo model's motions
  once (cached in target/robot-bench/), retargets them onto the robot with
  robots/<robot>.json, and writes per motion the human frames it gave the retargeter and the
  trajectory (GMR's fields); it prints the retargeting time alone.
- mink 1.3 (PyPI) on MuJoCo's model of the same URDF (tests/robot_retarget_check.py builds it:
  visuals dropped, a free joint on the root link), as GMR's `GeneralMotionRetargeting.retarget`
  (general_motion_retargeting/motion_retarget.py) runs it: one `FrameTask` per table entry with a
  non-zero weight (frame type "body", the entry's position and rotation costs, lm_damping 1),
  solver daqp, damping 0.5, dt = the model's timestep, `ConfigurationLimit` plus `VelocityLimit`
  of 3π rad/s on every hinge; table 1 then table 2, each one step and then up to 10 more while
  the norm of the stage's task errors drops by more than 1e-3; warm-started frame to frame.
  GMR passes its limits as the sixth positional argument of `solve_ik`, which mink reads as
  `safety_break` (GMR issues 83 and 138), so GMR as published runs with mink's default
  configuration limit only; here the limits go by keyword, as GMR means them. The targets are
  GMR's (`scale_human_data`, `offset_human_data`, each entry its own offsets) and are computed
  before the clock starts, so mink is timed on `set_target`, `solve_ik` and
  `integrate_inplace` alone. Each motion starts from the joints at zero and the free joint at
  the first frame's root target (GMR starts at the model's qpos0 wherever the human is).
- Runs are interleaved (libflame, mink, libflame, ...); frames per second are medians over
  runs. The tracking error of both is measured the same way, by MuJoCo's kinematics of the
  joint values each wrote: hands' and feet's positions relative to the root body against the
  targets relative to the root target (median and max in cm).

Prints the machine (CPU model, cores) and one `RESULT` line.
"""

import argparse
import json
import math
import os
import platform
import re
import statistics
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.join(ROOT, "tests"))
import robot_retarget_check as check  # noqa: E402


def cpu_model():
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def flame_run(bench, args, out_dir):
    """One `flame-bench robot-retarget` run: its RESULT fields and the motions it wrote."""
    cmd = [
        bench, "robot-retarget",
        "--urdf", args.urdf, "--config", args.config, "--model", args.model,
        "--frames", str(args.frames), "--dir", out_dir, "--runs", "1",
    ]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=ROOT).stdout
    result = [l for l in out.splitlines() if l.startswith("RESULT ")]
    if not result:
        raise SystemExit(f"flame-bench printed no RESULT line:\n{out}")
    fields = dict(kv.split("=", 1) for kv in result[-1].split()[1:])
    motions = [l.split("=", 1)[1] for l in out.splitlines() if l.startswith("MOTION=")]
    return fields, motions, out


class Mink:
    """GMR's use of mink on MuJoCo's model of the URDF."""

    def __init__(self, urdf, config):
        import mink

        self.mink = mink
        self.model = check.mujoco_model(urdf)
        self.config = config
        hinges = [
            self.model.joint(j).name
            for j in range(self.model.njnt)
            if self.model.jnt_type[j] != 0  # 0: the free joint
        ]
        self.limits = [
            mink.ConfigurationLimit(self.model),
            mink.VelocityLimit(self.model, {n: 3 * math.pi for n in hinges}),
        ]
        self.stages = []
        for table in config.tables:
            entries = [e for e in table if e["pos_weight"] != 0 or e["rot_weight"] != 0]
            tasks = [
                mink.FrameTask(
                    frame_name=e["body"], frame_type="body",
                    position_cost=e["pos_weight"], orientation_cost=e["rot_weight"],
                    lm_damping=1,
                )
                for e in entries
            ]
            self.stages.append((entries, tasks))
        self.hinge_names = hinges

    def targets(self, names, positions, rotations):
        """Per frame, per stage, the SE3 targets (computed before timing)."""
        mink = self.mink
        out = []
        for t in range(positions.shape[0]):
            per_stage = []
            for entries, _ in self.stages:
                tg = self.config.targets(positions[t], rotations[t], names, entries)
                per_stage.append([
                    mink.SE3.from_rotation_and_translation(mink.SO3.from_matrix(tg[e["body"]][1]), tg[e["body"]][0])
                    for e in entries
                ])
            out.append(per_stage)
        return out

    def run(self, targets, start):
        """The joint trajectory [N, nq] (MuJoCo qpos) and the seconds the IK took."""
        mink = self.mink
        q0 = self.model.qpos0.copy()
        q0[0:3] = start[0]
        x, y, z, w = start[1]
        q0[3:7] = [w, x, y, z]
        configuration = mink.Configuration(self.model, q=q0)
        dt = self.model.opt.timestep
        out = np.empty((len(targets), self.model.nq))
        began = time.perf_counter()
        for t, per_stage in enumerate(targets):
            for (entries, tasks), goals in zip(self.stages, per_stage):
                if not tasks:
                    continue
                for task, goal in zip(tasks, goals):
                    task.set_target(goal)

                def error():
                    return np.linalg.norm(np.concatenate([k.compute_error(configuration) for k in tasks]))

                current = error()
                v = mink.solve_ik(configuration, tasks, dt, "daqp", 0.5, limits=self.limits)
                configuration.integrate_inplace(v, dt)
                after = error()
                steps = 0
                while current - after > 1e-3 and steps < 10:
                    current = after
                    v = mink.solve_ik(configuration, tasks, dt, "daqp", 0.5, limits=self.limits)
                    configuration.integrate_inplace(v, dt)
                    after = error()
                    steps += 1
            out[t] = configuration.q
        return out, time.perf_counter() - began


def matrix_to_xyzw(m):
    import mujoco

    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(m).reshape(9))
    return np.array([q[1], q[2], q[3], q[0]])


def mujoco_errors(model, config, names, hpos, hrot, qpos_rows):
    """Tracking errors from MuJoCo's kinematics of qpos rows (the same measure for both)."""
    import mujoco

    data = mujoco.MjData(model)
    bodies = {}
    for t, q in enumerate(qpos_rows):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        bodies[t] = data.xpos.copy()

    def body_position(t, body):
        return bodies[t][model.body(body).id]

    return check.tracking_errors(config, names, hpos, hrot, body_position)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--robot", default="gr1t2")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--model", default="models/demo/flame_demo.safetensors")
    p.add_argument("--bench", default="target/release/flame-bench")
    p.add_argument("--config", help="default: robots/<robot>.json")
    p.add_argument("--no-build", action="store_true")
    args = p.parse_args()
    os.chdir(ROOT)
    args.urdf = f"target/robots/{args.robot}.urdf"
    args.config = args.config or f"robots/{args.robot}.json"
    if not os.path.isfile(args.urdf):
        subprocess.run(["bash", "tools/fetch_robots.sh"], check=True)
    if not args.no_build:
        subprocess.run(["cargo", "build", "--quiet", "--release", "--bin", "flame-bench"], check=True)
    out_dir = f"target/robot-bench/{args.robot}"
    os.makedirs(out_dir, exist_ok=True)

    config = check.Config(args.config)
    solver = Mink(args.urdf, config)
    model = solver.model

    flame_fps, mink_fps = [], []
    motions, prepared, flame_info = None, None, None
    for run in range(args.runs):
        fields, motions, text = flame_run(args.bench, args, out_dir)
        flame_fps.append(float(fields["fps"]))
        flame_info = fields
        if prepared is None:
            prepared = []
            for m in motions:
                names, hpos, hrot, _ = check.load_human(m + ".human.npz")
                tg = solver.targets(names, hpos, hrot)
                root = config.targets(hpos[0], hrot[0], names, [config.final_entries()[config.robot_root]])
                p0, r0 = root[config.robot_root]
                prepared.append((m, names, hpos, hrot, tg, (p0, matrix_to_xyzw(r0))))
        frames, seconds, mink_rows = 0, 0.0, []
        for m, names, hpos, hrot, tg, start in prepared:
            rows, s = solver.run(tg, start)
            frames += len(tg)
            seconds += s
            mink_rows.append(rows)
        mink_fps.append(frames / seconds)
        print(f"run {run + 1}: libflame {flame_fps[-1]:.0f} frames/s, mink {mink_fps[-1]:.1f} frames/s", flush=True)

    # Errors: the last run's outputs of both, by MuJoCo's kinematics.
    flame_err = {"hands": [], "feet": []}
    mink_err = {"hands": [], "feet": []}
    adr = None
    for (m, names, hpos, hrot, tg, start), rows in zip(prepared, mink_rows):
        traj = check.load_trajectory(m + ".trajectory.npz")
        if adr is None:
            adr = check.mujoco_qpos(model, traj["joint_names"])
        flame_rows = [
            check.fill_qpos(model, adr, traj["root_pos"][t], traj["root_rot"][t], traj["dof_pos"][t])
            for t in range(traj["root_pos"].shape[0])
        ]
        for err, qrows in ((flame_err, flame_rows), (mink_err, rows)):
            e = mujoco_errors(model, config, names, hpos, hrot, qrows)
            for k in ("hands", "feet"):
                err[k].append(e[k])

    def pooled(parts):
        med = statistics.median(p["median"] for p in parts)
        return med * 100, max(p["max"] for p in parts) * 100

    f_fps, k_fps = statistics.median(flame_fps), statistics.median(mink_fps)
    total_frames = sum(len(p[4]) for p in prepared)
    from importlib.metadata import version

    print(f"machine: {cpu_model()}, {os.cpu_count()} logical CPUs, Python {platform.python_version()}")
    print(f"libflame: release build, one thread, scalar f64 retargeting (AVX2 compiled in: "
          f"{flame_info.get('avx2_compiled', '?')}; the generation kernel, not timed here: "
          f"{flame_info.get('kernel', '?')}); mink {version('mink')}, MuJoCo {version('mujoco')}, "
          f"qpsolvers {version('qpsolvers')}, daqp {version('daqp')}")
    print(f"robot {args.robot}: {len(prepared)} motions, {total_frames} frames, {args.runs} interleaved runs")
    print(f"{'':10} {'frames/s':>10} {'hands median/max cm':>22} {'feet median/max cm':>22}")
    for name, fps, err in (("libflame", f_fps, flame_err), ("mink", k_fps, mink_err)):
        h, f = pooled(err["hands"]), pooled(err["feet"])
        print(f"{name:10} {fps:10.1f} {h[0]:10.2f} / {h[1]:8.2f} {f[0]:10.2f} / {f[1]:8.2f}")
    ratio = f_fps / k_fps
    print(f"ratio libflame / mink: {ratio:.1f}x")
    fh, ff = pooled(flame_err["hands"]), pooled(flame_err["feet"])
    mh, mf = pooled(mink_err["hands"]), pooled(mink_err["feet"])
    print(
        f"RESULT robot={args.robot} frames={total_frames} runs={args.runs} flame_fps={f_fps:.1f} "
        f"mink_fps={k_fps:.1f} ratio={ratio:.2f} flame_hands_cm={fh[0]:.2f}/{fh[1]:.2f} "
        f"flame_feet_cm={ff[0]:.2f}/{ff[1]:.2f} mink_hands_cm={mh[0]:.2f}/{mh[1]:.2f} "
        f"mink_feet_cm={mf[0]:.2f}/{mf[1]:.2f}"
    )


if __name__ == "__main__":
    main()
