#!/usr/bin/env python3
"""ONNX Runtime timings of a libflame model file's guided step, for comparison with `flame-bench`
and tools/bench_torch.py.

The step is the one tools/bench_torch.py times, built by its runners from the same file (the
reference modules of tools/reference/ with the converted weights): the two network evaluations
of one denoising step (the guidance batch of 2, or OMG's D_u and D_c), the guidance mix and,
where bench_torch.py's step has it, the sampler's update. That computation is exported with
`torch.onnx.export` (opset 18 by default) at the given frame count, the text features being an
input computed once by PyTorch (libflame and bench_torch.py time text encoding apart from the
step). The ONNX output is checked against PyTorch's on the same inputs (the largest absolute
difference is printed; more than 1e-3 of the output's largest magnitude is an error), then
timed with `onnxruntime.InferenceSession` (CPUExecutionProvider, ORT_ENABLE_ALL,
intra_op_num_threads = --threads, inter_op_num_threads = 1, sequential execution):

    python3 tools/bench_onnx.py --model models/flame_base_random.safetensors \\
        --frames 196 --steps 10 --threads 2 --runs 3

What is timed:
  step      one `session.run` of the exported step (medians over every step of every run).
  gen       `steps` such steps, the output of one fed to the next (FLAME, MDM / Motion Flow
            Matching, OMG: t = 999, 999 - 1000/steps, ...; MoLA, MLD: diffusers' DDIMScheduler
            as bench_torch.py configures it, `scheduler.step` in PyTorch between the ONNX
            denoiser runs, then the exported VAE decoder; `decode` is also timed on its own).
  text      not timed (nan): PyTorch computes the text features once.

FineMoGen's step (`finemogen_bench`) is the network with its in-network guidance batch, the
guidance mix and the eta-0 DDIM update, as bench_torch.py's step with `--text-moe-once` (each
layer's text-MoE output is an input, computed once by PyTorch with the text, as libflame does).
Its mixture-of-experts routing gathers a data-dependent number of tokens per expert, which
`torch.export` cannot trace (the reference's `if rows.numel() == 0`), so the exported MoE
dispatches as tutel itself does (`static_moe`): the reference's routing, then every kept choice
written to its slot of fixed capacity-sized expert buffers, both expert layers as batched GEMMs
over every slot, and the outputs gathered back. Only values depend on the data; the shapes are
fixed by the frame count. It is checked against the reference's own MoE in PyTorch (1e-5) and
in ONNX Runtime (the tolerance above) on two steps whose routings differ (the first step, and
the next one from the reference's output); the whole generation is the respaced schedule (50
steps: "15,15,8,6,6"; other counts: that many evenly spaced).

`--profile PREFIX` runs the step again under ONNX Runtime's profiler and prints the node time
per operator type (FLAME, MDM / Motion Flow Matching, OMG); `--spin 0` stops the intra-op
threads from spinning (the counterpart of PyTorch's OMP_WAIT_POLICY=PASSIVE).

The exported files are written under --cache (default: a temporary folder, deleted), named by
the model file, its size and modification time, the frame count and the guidance, and reused
when present (the check against PyTorch runs every time).

Prints medians in the format bench_torch.py uses and one machine-readable `RESULT impl=ort`
line for tools/bench.sh.
"""
import argparse
import hashlib
import json
import os
import shutil
import statistics
import sys
import tempfile
import time

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__))))
import bench_torch as bt  # noqa: E402

TOLERANCE = 1e-3  # relative to the largest magnitude of PyTorch's output


class Step(torch.nn.Module):
    """bench_torch.py's step as a module: `run.net` registered so its weights are the exported
    graph's initialisers. Outputs (x_next, guided network output), or the guided output alone
    where the sampler update happens outside (latent models)."""

    def __init__(self, run):
        super().__init__()
        self.net = run.net
        self.run = run

    def forward(self, x, t, *feats):
        out = self.run.guided(x, t, *feats)
        if self.run.update is None:
            return out
        return self.run.update(x, out), out


class Fn(torch.nn.Module):
    def __init__(self, net, fn):
        super().__init__()
        self.net, self.fn = net, fn

    def forward(self, *args):
        return self.fn(*args)


def cache_name(a, arch, part):
    st = os.stat(a.model)
    key = f"{os.path.abspath(a.model)}|{st.st_size}|{st.st_mtime_ns}|{a.frames}|{a.guidance}|" \
          f"{a.opset}|{torch.__version__}"
    tag = hashlib.sha256(key.encode()).hexdigest()[:12]
    base = os.path.splitext(os.path.basename(a.model))[0]
    return f"{base}.{arch}.{part}.f{a.frames}.{tag}.onnx"


def export(module, args, names, out_names, path, opset):
    """torch.onnx.export into `path` (weights in `path`.data beside it); returns seconds taken
    (0 when `path` was already there)."""
    if os.path.exists(path):
        return 0.0
    tmp = path + ".partial"
    os.makedirs(tmp, exist_ok=True)
    t0 = time.perf_counter()
    with torch.no_grad():
        torch.onnx.export(module, args, os.path.join(tmp, os.path.basename(path)),
                          input_names=names, output_names=out_names, opset_version=opset,
                          dynamo=True, external_data=True)
    took = time.perf_counter() - t0
    for f in os.listdir(tmp):
        os.replace(os.path.join(tmp, f), os.path.join(os.path.dirname(path), f))
    os.rmdir(tmp)
    return took


def session(path, threads, spin, profile=None):
    import onnxruntime as ort
    so = ort.SessionOptions()
    if profile:
        so.enable_profiling = True
        so.profile_file_prefix = profile
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    if spin is not None:
        so.add_session_config_entry("session.intra_op.allow_spinning", str(spin))
    return ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])


def check(name, got, want):
    """Largest absolute difference and that over PyTorch's largest magnitude; raises past the
    tolerance."""
    want = want.detach().float().numpy()
    diff = float(np.abs(got - want).max())
    rel = diff / max(float(np.abs(want).max()), 1e-30)
    print(f"  check {name:<10} max abs diff {diff:.3e} (relative {rel:.3e}) vs PyTorch")
    if not rel <= TOLERANCE:
        raise SystemExit(f"ONNX Runtime's {name} differs from PyTorch's: max abs diff {diff:.3e},"
                         f" relative {rel:.3e} > {TOLERANCE:g}")
    return diff, rel


def np_inputs(names, tensors):
    return {n: np.ascontiguousarray(v.detach().numpy()) for n, v in zip(names, tensors)}


def timesteps(steps):
    return [999 - i * (1000 // steps) for i in range(steps)]


def direct_bench(arch, a, cache):
    """FLAME, MDM / Motion Flow Matching and OMG: the whole step (guided network evaluations,
    guidance mix, DDIM update) in one graph, its output fed to the next step."""
    runner = {"flame": bt.flame_runner, "omg": bt.omg_runner}.get(arch, bt.mdm_runner)
    with torch.inference_mode():
        run = runner(a.model, a.frames, a.guidance)
    # OMG's time is a float64 (its timestep embedding), the others' an integer step.
    tdt, tnp = (torch.float64, np.float64) if arch == "omg" else (torch.int64, np.int64)
    feats = tuple(run.feats)
    fnames = {"flame": ["pooled", "hidden"], "omg": ["tokens", "eos"]}.get(arch, ["text"])
    names = ["x", "t"] + fnames
    t0 = torch.tensor([500], dtype=tdt)
    path = os.path.join(cache, cache_name(a, arch, "step"))
    export_s = export(Step(run).eval(), (run.x, t0) + feats, names, ["x_next", "guided"], path,
                      a.opset)
    sess = session(path, a.threads, a.spin)
    with torch.inference_mode():
        want_next, want_out = Step(run)(run.x, t0, *feats)
    got_next, got_out = sess.run(None, np_inputs(names, (run.x, t0) + feats))
    diff, rel = check("guided", got_out, want_out)
    check("x_next", got_next, want_next)

    fixed = np_inputs(fnames, feats)
    x0 = np.ascontiguousarray(run.x.numpy())

    def step(x, t):
        return sess.run(["x_next"], {"x": x, "t": np.array([t], dtype=tnp), **fixed})[0]

    step(x0, 500)  # warm-up
    steps, gens = [], []
    for _ in range(a.runs):
        x = x0
        g0 = time.perf_counter()
        for t in timesteps(a.steps):
            s0 = time.perf_counter()
            x = step(x, t)
            steps.append((time.perf_counter() - s0) * 1e3)
        gens.append((time.perf_counter() - g0) * 1e3)
    if a.profile:
        profile_ops(session(path, a.threads, a.spin, a.profile), a.runs,
                    lambda sess: sess.run(["x_next"], {"x": x0, "t": np.array([500], dtype=tnp),
                                                      **fixed}))
    return dict(steps=steps, gens=gens, diff=diff, rel=rel, export_s=export_s)


def profile_ops(sess, runs, run):
    """`runs` profiled runs of the step after a warm-up; prints ONNX Runtime's node time per
    operator type (ms per step, share of the nodes' total)."""
    run(sess)
    for _ in range(runs):
        run(sess)
    path = sess.end_profiling()
    with open(path) as f:
        events = json.load(f)
    per_op, total = {}, 0.0
    for e in events:
        if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time"):
            op = e.get("args", {}).get("op_name", "?")
            per_op[op] = per_op.get(op, 0.0) + e["dur"] / 1e3
            total += e["dur"] / 1e3
    n = runs + 1
    print(f"  ONNX Runtime profile ({path}): node time {total / n:.1f} ms per step")
    for op, t in sorted(per_op.items(), key=lambda kv: -kv[1])[:12]:
        print(f"    {op:<28} {t / n:9.2f} ms  {100 * t / total:5.1f}%")


def latent_bench(arch, a, cache):
    """MoLA, MLD: the guided denoiser in one graph, diffusers' scheduler step in PyTorch between
    runs (as bench_torch.py samples), then the exported VAE decoder."""
    runner = bt.mola_runner if arch == "mola" else bt.mld_runner
    from reference import mola as ref_mola
    with torch.inference_mode():
        run, decode, sch = runner(a.model, a.frames, a.guidance)
    den, dec = run.net
    conds = run.feats[0]
    t0 = torch.tensor([500], dtype=torch.int64)
    path = os.path.join(cache, cache_name(a, arch, "step"))
    export_s = export(Step(run).eval(), (run.x, t0, conds), ["x", "t", "conds"], ["eps"], path,
                      a.opset)
    if arch == "mola":
        dec_fn = Fn(dec, lambda z: dec(z)).eval()
    else:
        dec_fn = Fn(dec, lambda z: dec(z, a.frames)).eval()
    dpath = os.path.join(cache, cache_name(a, arch, "decode"))
    export_s += export(dec_fn, (run.x,), ["z"], ["motion"], dpath, a.opset)
    sess, dsess = session(path, a.threads, a.spin), session(dpath, a.threads, a.spin)
    with torch.inference_mode():
        want = run.guided(run.x, t0, conds)
        want_dec = dec_fn(run.x)
    diff, rel = check("guided", sess.run(None, np_inputs(["x", "t", "conds"],
                                                         (run.x, t0, conds)))[0], want)
    check("decode", dsess.run(None, {"z": run.x.numpy()})[0], want_dec)

    c = np.ascontiguousarray(conds.numpy())

    def denoise(x, t):
        eps = sess.run(None, {"x": x.numpy(), "t": t.reshape(1).numpy(), "conds": c})[0]
        return torch.from_numpy(eps)

    def decode_ort(z):
        out = torch.from_numpy(dsess.run(None, {"z": z.numpy()})[0])
        if arch == "mola":  # the valid-length cut, as ref_mola.decode
            o = out[0]
            n = ref_mola.valid_length(o[-1])
            return o[:-1, :n].transpose(0, 1).contiguous()
        return out

    with torch.inference_mode():
        sch.set_timesteps(a.steps)
        ts = sch.timesteps[0]
        decode_ort(sch.step(denoise(run.x, ts), ts, run.x, eta=0.0).prev_sample)  # warm-up
        steps, gens, decodes = [], [], []
        for _ in range(a.runs):
            g0 = time.perf_counter()
            sch.set_timesteps(a.steps)
            x = run.x
            for t in sch.timesteps:
                s0 = time.perf_counter()
                x = sch.step(denoise(x, t), t, x, eta=0.0).prev_sample
                steps.append((time.perf_counter() - s0) * 1e3)
            d0 = time.perf_counter()
            decode_ort(x)
            decodes.append((time.perf_counter() - d0) * 1e3)
            gens.append((time.perf_counter() - g0) * 1e3)
    return dict(steps=steps, gens=gens, decodes=decodes, diff=diff, rel=rel, export_s=export_s)


def priority(v):
    """Indices of `v` by descending value, ties in index order: the reference's stable sort,
    exported as ONNX TopK over all of `v` (the exporter has no stable sort; TopK breaks ties by
    the lower index, per the ONNX operator's definition)."""
    if torch.compiler.is_exporting():
        return torch.topk(v, v.shape[0]).indices
    return torch.sort(-v, stable=True).indices


def static_moe(moe, x, log=None, tag=None):
    """`TutelMoE.forward` with tutel's own static shapes, so that it exports: the reference's
    routing (`route`: top-2, priority order, capacity drops), every kept choice written to its
    slot of one [experts · capacity, D] buffer (dropped ones to a spare last row), both expert
    layers as batched GEMMs over every capacity slot (empty ones too, as tutel computes them),
    and Σ_k gate_k · out_k gathered back, a dropped choice reading the spare row's zero output.
    Only the values depend on the data, not the shapes: the capacity is a function of the token
    count, fixed by the frame count."""
    n, d = x.shape
    e, cap, topk = moe.num_experts, moe.capacity(x.shape[0]), moe.topk
    scores = torch.softmax(moe.gates[0](x), dim=1)
    experts, gates, slots = bt.ref_fmg.route(scores, topk, cap, priority)
    spare = e * cap
    where = torch.where(slots < cap, experts * cap + slots, torch.full_like(slots, spare))
    buf = x.new_zeros(spare + 1, d)
    buf = buf.index_put((where.reshape(-1),), x.unsqueeze(1).expand(n, topk, d).reshape(-1, d))
    ex = moe.experts
    h = torch.nn.functional.gelu(torch.baddbmm(ex.batched_fc1_bias.unsqueeze(1),
                                               buf[:spare].reshape(e, cap, d),
                                               ex.batched_fc1_w.transpose(1, 2)))
    y = torch.baddbmm(ex.batched_fc2_bias.unsqueeze(1), h, ex.batched_fc2_w).reshape(spare, -1)
    y = torch.cat([y, y.new_zeros(1, y.shape[1])])
    out = x.new_zeros(n, y.shape[1])
    for k in range(topk):
        out = out + gates[:, k:k + 1] * y[where[:, k]]
    return out


class FineMoGenStep(torch.nn.Module):
    """bench_torch.py's FineMoGen step with `--text-moe-once` (as libflame runs it): the network
    with its in-network guidance batch, x0 = null + w·(text − null) and the eta-0 DDIM update.
    Inputs: x, the original step t, w(t), the sampler's three table values at the step, and
    each layer's text-MoE output (computed once with the text). Outputs (x_next, x0)."""

    def __init__(self, net, xf, index, lengths):
        super().__init__()
        self.net, self.xf, self.index, self.lengths = net, xf, index, lengths

    def forward(self, x, t, w, recip, recipm1, abp, *text_moe):
        for blk, out in zip(self.net.temporal_decoder_blocks, text_moe):
            blk.ca_block.text_moe.out = out
        cond, null = self.net(x, t, self.lengths, self.xf, self.index, 1)
        x0 = null + (cond - null) * w
        eps = (recip * x - x0) / recipm1
        return x0 * torch.sqrt(abp) + torch.sqrt(1 - abp) * eps, x0


def finemogen_bench(a, cache):
    """FineMoGen: the whole step in one graph, the MoE dispatched into tutel's fixed
    capacity-sized expert buffers (`static_moe`), checked against the reference's own MoE on
    two steps whose routings differ, then the respaced generation with the output of one step
    fed to the next."""
    fmg = bt.ref_fmg
    with torch.inference_mode():
        net, clip, tok, cfg, _, _ = fmg.load_libflame(a.model)
        stages = [fmg.Stage(bt.PROMPT, a.frames)]

        def enc(text):
            ids = torch.tensor([fmg.clip_ids(tok, text)])
            return net.encode_clip_features(fmg.clip_features(clip, ids))[0]

        xf, index, _ = fmg.condition(stages, enc)
        text_moe = []
        for blk in net.temporal_decoder_blocks:
            s = blk.ca_block
            text_moe.append(s.text_moe(s.text_norm(xf).unsqueeze(2)))
            s.text_moe = bt.TextMoeOnce(s.text_moe)
        torch.manual_seed(0)
        noise = torch.randn(1, a.frames, cfg["denoiser"]["input_feats"])
    respacing = "15,15,8,6,6" if a.steps == 50 else str(a.steps)
    sched = fmg.make_diffusion(respacing)
    n = sched.num_timesteps

    def inputs(x, i):
        """The step's inputs at respaced step i, as ddim_sample computes them."""
        t = int(sched.timestep_map[i])
        tab = [torch.tensor([float(tb[i])], dtype=torch.float64).float()
               for tb in (sched.sqrt_recip_alphas_cumprod, sched.sqrt_recipm1_alphas_cumprod,
                          sched.alphas_cumprod_prev)]
        return (x, torch.tensor([t]), torch.tensor([fmg.guidance_weight(t, a.guidance)],
                                                   dtype=torch.float32), *tab, *text_moe)

    step = FineMoGenStep(net, xf, index, torch.tensor([a.frames])).eval()
    names = ["x", "t", "w", "recip", "recipm1", "abp"] + [f"text_moe{i}" for i in
                                                          range(len(text_moe))]
    moes = [m for m in net.modules() if isinstance(m, fmg.TutelMoE)]
    reference = fmg.TutelMoE.forward

    def use(forward):
        for m in moes:
            m.forward = forward.__get__(m)

    # Two steps' inputs: noise at the first step, and the reference's output of it at the next.
    with torch.inference_mode():
        first = inputs(noise, n - 1)
        use(reference)
        want = [step(*first)]
        second = inputs(want[0][0], n - 2)
        want.append(step(*second))
        use(static_moe)
        eager = [step(*first), step(*second)]
    for (w_next, _), (e_next, _) in zip(want, eager):
        err = float((e_next - w_next).abs().max() / w_next.abs().max())
        if not err <= 1e-5:
            raise SystemExit(f"static MoE differs from the reference's: relative {err:.3g}")
    path = os.path.join(cache, cache_name(a, "finemogen", "step"))
    export_s = export(step, first, names, ["x_next", "x0"], path, a.opset)
    sess = session(path, a.threads, a.spin)
    diffs = []
    for args, (w_next, w_x0) in zip((first, second), want):
        got_next, got_x0 = sess.run(None, np_inputs(names, args))
        diffs.append(check("x0", got_x0, w_x0))
        check("x_next", got_next, w_next)
    diff, rel = max(diffs, key=lambda d: d[1])

    fixed = np_inputs(names[6:], text_moe)
    feeds = [np_inputs(names[1:6], inputs(None, i)[1:6]) for i in range(n)]

    def run_step(x, i):
        return sess.run(["x_next"], {"x": x, **feeds[i], **fixed})[0]

    x_start = np.ascontiguousarray(noise.numpy())
    run_step(x_start, n - 1)  # warm-up
    steps, gens = [], []
    for _ in range(a.runs):
        x = x_start
        g0 = time.perf_counter()
        for i in reversed(range(n)):
            s0 = time.perf_counter()
            x = run_step(x, i)
            steps.append((time.perf_counter() - s0) * 1e3)
        gens.append((time.perf_counter() - g0) * 1e3)
    return dict(steps=steps, gens=gens, diff=diff, rel=rel, export_s=export_s)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--frames", type=int, default=196)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--guidance", type=float, default=2.5)
    ap.add_argument("--opset", type=int, default=18, help="ONNX opset (17 or later)")
    ap.add_argument("--cache", help="folder for the exported files, reused when present "
                    "(default: a temporary folder, deleted at the end)")
    ap.add_argument("--profile", metavar="PREFIX",
                    help="also run the step with ONNX Runtime's profiler (JSON at PREFIX_*.json)"
                         " and print its time per operator type (not for MoLA/MLD)")
    ap.add_argument("--spin", type=int, choices=(0, 1),
                    help="session.intra_op.allow_spinning (default: ONNX Runtime's, 1)")
    a = ap.parse_args()
    if a.opset < 17:
        ap.error("--opset must be 17 or later")
    torch.set_num_threads(a.threads)
    torch.set_num_interop_threads(1)
    import onnx
    import onnxruntime as ort

    from safetensors import safe_open
    with safe_open(a.model, "pt") as f:
        arch = json.loads(f.metadata()["flame.config"])["architecture"]

    tmp = None
    if a.cache:
        os.makedirs(a.cache, exist_ok=True)
        cache = a.cache
    else:
        cache = tmp = tempfile.mkdtemp(prefix="bench_onnx.")
    try:
        if arch in ("mola", "mld"):
            r = latent_bench(arch, a, cache)
        elif arch == "finemogen":
            r = finemogen_bench(a, cache)
        else:
            r = direct_bench(arch, a, cache)
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)

    med = statistics.median
    spin = "default" if a.spin is None else a.spin
    evals = "D_u and D_c" if arch == "omg" else "batch 2"
    print(f"onnxruntime {ort.__version__} (onnx {onnx.__version__}, exported by torch "
          f"{torch.__version__}, opset {a.opset}), CPUExecutionProvider, {arch}, frames "
          f"{a.frames}, {a.steps} steps, guidance {a.guidance} ({evals}), {a.threads} intra-op "
          f"threads, 1 inter-op, spinning {spin}, {a.runs} runs (medians):")
    if r["export_s"]:
        print(f"  export             {r['export_s']:9.1f} s")
    print(f"  one guided step    {med(r['steps']):9.2f} ms")
    if "decodes" in r:
        print(f"  VAE decode         {med(r['decodes']):9.2f} ms")
    print(f"  whole generation   {med(r['gens']):9.2f} ms")
    dec = f" decode_ms={med(r['decodes']):.2f}" if "decodes" in r else ""
    print(f"RESULT impl=ort frames={a.frames} text_ms=nan step_ms={med(r['steps']):.2f} "
          f"gen_ms={med(r['gens']):.2f}{dec} max_abs_diff={r['diff']:.3e} "
          f"rel_diff={r['rel']:.3e}")


if __name__ == "__main__":
    main()
