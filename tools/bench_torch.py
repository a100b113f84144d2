#!/usr/bin/env python3
"""PyTorch eager timings of a libflame model file, for comparison with `flame-bench`.

Runs the same converted checkpoint through the reference modules (tools/reference/flame.py,
mdm.py, mola.py, mld.py, motionlcm.py, finemogen.py or omg.py) with `torch.set_num_threads(N)`,
the same frames, steps and guidance batch (conditional + unconditional rows in one batch of 2;
MotionLCM: one row, its guidance embedded), and prints medians in the format flame-bench uses,
plus one machine-readable `RESULT` line.

    python3 tools/bench_torch.py --model models/flame_base_random.safetensors \
        --frames 196 --steps 10 --threads 2 --runs 3

What is timed (as people run these models today):
  text      FLAME: `encode_text` of the prompt (RoBERTa) — MDM: not timed (CLIP is not in the
            reference module; the MDM row uses a random text vector).
  step      one guided denoising step: the batch-2 network forward, the guidance mix and a DDIM
            (eta 0) update.
  gen       `steps` such steps, text features computed once.

MoLA and MLD (latent models) run the whole generation as the references sample: `steps` guided
DDIM (eta 0) steps through `diffusers`' DDIMScheduler configured as each release (set_timesteps,
then `scheduler.step` per step), then the VAE decode of the final latent (MoLA: with its
valid-length cut). `gen` includes the decode, `decode` is also timed on its own (RESULT
`decode_ms`). The text vector is random (CLIP is not in the reference modules; text is not timed).

MotionLCM (v1 and v2) runs tools/reference/motionlcm.py as the releases sample: `text` is the
sentence-t5-large vector of the prompt (tokenizer.json from the file, transformers'
T5EncoderModel, mean pooling, the Dense layer, L2 normalisation; the prompt of flame-bench);
a step is one denoiser pass with the guidance scale embedded through `cond_proj` (no
unconditional row: the distilled model has none) and diffusers' LCMScheduler `step` (v1 its
grid, v2 its timestep table; the re-noising draw between steps included); `decode` is the VAE
decode of `--frames` frames; `gen` is the whole motion: the scheduler's timesteps, the guidance
embedding, `steps` steps and the decode (the text computed once before, not included). The
guidance is the file's for the step count (v1 7.5; v2 8.0 / 12.5 / 13.5 for 1 / 2 / 4 steps):
the value does not change the time. RESULT as the latent models' (with `decode_ms`).

FineMoGen runs tools/reference/finemogen.py as the release samples: `text` is CLIP (all 77
positions) and the text encoder of the prompt (`condition`); a step is the network forward with
its in-network guidance batch (text rows + null rows), x0 = null + w(t)·(text − null) and the
eta-0 DDIM update on x0; the whole generation is the respaced schedule (50 steps:
"15,15,8,6,6"; other counts: that many evenly spaced). Every mixture-of-experts call (the
wrapper: embedding, gate, routing, experts, GELU, projection) is timed through module hooks;
RESULT `moe_ms` is their time per step (`motion_moe_ms`, `text_moe_ms` the two kinds). The
release runs the text MoE in every step (its input, the text features, does not change);
`--text-moe-once` computes it once with the text instead (timed with `text`), as libflame does.
`--moe sorted` (the default) dispatches the routed tokens sorted by expert (one gather, two
GEMMs per expert, one index_add) instead of the reference's boolean mask per expert; the
routing is the reference's own `route`, and a check forward compares every call's output with
the reference's MoE before timing (`--moe reference` times the reference's MoE as written).

    python3 tools/bench_torch.py --gemm [--threads 2] [--runs 9]

prints GFLOP/s of `torch.nn.functional.linear` (x · Wᵀ + b, f32) on the shapes
`flame-bench gemm` times (FLAME-base and MDM-sized layers at 196 frames, a 1536³ square),
medians of `runs`: the BLAS side of "the machine's GEMM peak".
"""
import argparse
import json
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__))))
from reference import finemogen as ref_fmg  # noqa: E402
from reference import flame as ref_flame  # noqa: E402
from reference import mdm as ref_mdm  # noqa: E402
from reference import mld as ref_mld  # noqa: E402
from reference import mola as ref_mola  # noqa: E402

PROMPT = "a person walks forward, turns around and waves with the right hand"


def ms(f):
    t = time.perf_counter()
    f()
    return (time.perf_counter() - t) * 1e3


def ddim_update(x, out, abar, abar_prev):
    """eta-0 DDIM from an eps prediction (the arithmetic a sampler adds to a step)."""
    x0 = (x - (1 - abar) ** 0.5 * out) / abar ** 0.5
    return abar_prev ** 0.5 * x0 + (1 - abar_prev) ** 0.5 * out


def pair(t):
    """The timestep of both rows of a guidance batch: a number or a 0-d/1-element tensor -> [2]
    (a tensor input when tools/bench_onnx.py exports the step)."""
    return torch.as_tensor(t).reshape(1).expand(2)


class Runner:
    """One family's guided step, split so tools/bench_onnx.py can export the same computation:
    `guided(x, t, *feats)` is the two network evaluations (one batch of 2, or D_u and D_c) and
    the guidance mix; `update(x, out)` is the sampler arithmetic after it (None for the latent
    models, whose diffusers scheduler updates outside); `step(x, t, feats)` is both. `net` holds
    every module the step uses; `feats` are the text features, computed once (`encode`)."""

    def __init__(self, net, encode, feats, x, guided, update):
        self.net, self.encode, self.feats, self.x = net, encode, feats, x
        self.guided, self.update = guided, update

    def step(self, x, t, feats):
        return self.update(x, self.guided(x, t, *feats))


def flame_runner(path, frames, guidance):
    net, cfg = ref_flame.load_libflame(path)
    d = cfg["denoiser"]["motion_dim"]
    torch.manual_seed(0)
    x = torch.randn(1, d, frames)
    length = torch.tensor([frames, frames])

    def encode():
        pooled, hidden = net.encode_text([PROMPT, ""])
        return pooled, hidden

    def guided(x, t, pooled, hidden):
        out = net(torch.cat([x, x]), pair(t), length, text_features=(pooled, hidden))
        eps_c, eps_u = out[:1, :d], out[1:, :d]
        return eps_u + guidance * (eps_c - eps_u)

    return Runner(net, encode, encode(), x, guided, lambda x, eps: ddim_update(x, eps, 0.5, 0.6))


def mdm_runner(path, frames, guidance):
    net, cfg = ref_mdm.load_libflame(path)
    d = cfg["denoiser"]
    torch.manual_seed(0)
    x = torch.randn(1, d["njoints"], 1, frames)
    cond = torch.randn(1, d["clip_dim"])
    feats = torch.cat([cond, torch.zeros_like(cond)])

    def guided(x, t, feats):
        out = net(torch.cat([x, x]), pair(t), feats)
        o_c, o_u = out[:1], out[1:]
        return o_u + guidance * (o_c - o_u)

    return Runner(net, None, (feats,), x, guided, lambda x, out: ddim_update(x, out, 0.5, 0.6))


def mola_runner(path, frames, guidance):
    """-> (Runner (guided(x, t, conds) -> eps), decode(z), scheduler) for one guided MoLA
    generation."""
    den, dec, cfg = ref_mola.load_libflame(path)
    d = cfg["denoiser"]
    torch.manual_seed(0)
    x = torch.randn(1, d["latent_channels"], ref_mola.latent_frames(frames))
    cond = torch.randn(1, d["cond_dim"])
    conds = torch.cat([cond, torch.zeros_like(cond)])
    cfg_on = not (guidance == 0 or guidance == 1.0)

    def guided(x, t, conds):
        tt = t.reshape(1)
        if not cfg_on:
            return den(x, tt, conds[:1])
        e = den(torch.cat([x, x]), torch.cat([tt, tt]), conds)
        return e[1:] + guidance * (e[:1] - e[1:])

    run = Runner(torch.nn.ModuleList([den, dec]), None, (conds,), x, guided, None)
    return run, lambda z: ref_mola.decode(dec, z), ref_mola.make_scheduler()


def mld_runner(path, frames, guidance):
    den, dec, cfg = ref_mld.load_libflame(path)
    d = cfg["denoiser"]
    torch.manual_seed(0)
    z = torch.randn(1, d["latent_tokens"], d["latent_dim"])
    cond, uncond = torch.randn(1, d["text_dim"]), torch.randn(1, d["text_dim"])
    conds = torch.cat([uncond, cond])

    def guided(z, t, conds):
        tt = t.reshape(1)
        if guidance <= 1.0:
            return den(z, tt, conds[1:])
        e = den(torch.cat([z, z]), torch.cat([tt, tt]), conds)
        return e[:1] + guidance * (e[1:] - e[:1])

    run = Runner(torch.nn.ModuleList([den, dec]), None, (conds,), z, guided, None)
    return run, lambda z: dec(z, frames), ref_mld.make_scheduler()


def latent_bench(arch, a):
    """The whole generation of a latent model: `steps` scheduler steps, then the VAE decode."""
    runner = mola_runner if arch == "mola" else mld_runner
    with torch.inference_mode():
        run, decode, sch = runner(a.model, a.frames, a.guidance)
        x_t = run.x

        def denoise(x, t):
            return run.guided(x, t, *run.feats)

        # Warm-up: one step and one decode.
        sch.set_timesteps(a.steps)
        decode(sch.step(denoise(x_t, sch.timesteps[0]), sch.timesteps[0], x_t, eta=0.0)
               .prev_sample)
        steps, gens, decodes = [], [], []
        for _ in range(a.runs):
            t0 = time.perf_counter()
            sch.set_timesteps(a.steps)
            x = x_t
            for t in sch.timesteps:
                ts = time.perf_counter()
                x = sch.step(denoise(x, t), t, x, eta=0.0).prev_sample
                steps.append((time.perf_counter() - ts) * 1e3)
            td = time.perf_counter()
            decode(x)
            decodes.append((time.perf_counter() - td) * 1e3)
            gens.append((time.perf_counter() - t0) * 1e3)
    med = statistics.median
    print(f"torch {torch.__version__} eager, {arch}, frames {a.frames}, {a.steps} DDIM steps "
          f"(diffusers), guidance {a.guidance}, {a.threads} threads, {a.runs} runs (medians):")
    print(f"  one guided step    {med(steps):9.2f} ms")
    print(f"  VAE decode         {med(decodes):9.2f} ms")
    print(f"  whole generation   {med(gens):9.2f} ms  ({a.steps} steps and the decode)")
    print(f"RESULT impl=torch frames={a.frames} text_ms=nan step_ms={med(steps):.2f} "
          f"gen_ms={med(gens):.2f} decode_ms={med(decodes):.2f}")


def lcm_timesteps(ref, sch, cfg, steps):
    """Sets `sch` (diffusers' LCMScheduler) for `steps` steps as tools/reference/diffusers_lcm.py
    runs it: v1 `set_timesteps(n)` on its grid, v2 its table written into `timesteps`."""
    table = ref.timesteps_for(cfg, steps)
    if isinstance(table, int):
        sch.set_timesteps(table)
    else:
        sch.set_timesteps(timesteps=[table[0]])
        sch.timesteps = torch.tensor(table, dtype=torch.int64)
        sch.num_inference_steps = len(table)
    return sch.timesteps


def motionlcm_bench(a):
    """MotionLCM (v1 and v2): sentence-t5-large's vector of the prompt (`text`), one latent
    consistency step (one denoiser pass with the guidance embedded, the LCMScheduler step),
    the VAE decode and the whole motion (`steps` steps and the decode; the text once, before)."""
    from diffusers.utils import logging as diffusers_logging
    from reference import diffusers_lcm
    from reference import motionlcm as ref_lcm
    # v2's table starts below 999, which set_timesteps warns about on every run.
    diffusers_logging.set_verbosity_error()
    with torch.inference_mode():
        den, dec, t5, tok, cfg = ref_lcm.load_libflame(a.model)
        if a.int8:
            # PyTorch's own int8 CPU route: dynamic quantisation swaps every nn.Linear for an
            # int8 one (weights per tensor, activations quantised per call). nn.MultiheadAttention
            # keeps its in_proj and out_proj float (its out_proj is a
            # NonDynamicallyQuantizableLinear).
            import warnings
            from torch.ao.quantization import quantize_dynamic
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                den = quantize_dynamic(den, {torch.nn.Linear}, dtype=torch.qint8)
                dec = quantize_dynamic(dec, {torch.nn.Linear}, dtype=torch.qint8)
        d = cfg["denoiser"]
        release = "v2" if cfg["diffusion"]["lcm_timesteps"] == "motionlcm_v2" else "v1"
        guidance = ref_lcm.guidance_for(cfg, a.steps)
        sch = diffusers_lcm.scheduler()
        torch.manual_seed(0)
        z_t = torch.randn(1, d["latent_tokens"], d["latent_channels"])

        def encode():
            return ref_lcm.encode_text(t5, tok, PROMPT)

        ids, vec = encode()  # warm-up
        text = [ms(encode) for _ in range(a.runs)]
        vec = vec[None]

        def embed():
            return ref_lcm.guidance_embedding(torch.tensor([guidance - 1.0]), d["cond_dim"])

        def step(x, t, cond):
            return sch.step(den(x, t.reshape(1), cond, vec), t, x).prev_sample

        # Warm-up: one generation.
        cond = embed()
        x = z_t
        for t in lcm_timesteps(ref_lcm, sch, cfg, a.steps):
            x = step(x, t, cond)
        dec(x, a.frames)
        steps, gens, decodes = [], [], []
        for _ in range(a.runs):
            t0 = time.perf_counter()
            timesteps = lcm_timesteps(ref_lcm, sch, cfg, a.steps)
            cond = embed()
            x = z_t
            for t in timesteps:
                ts = time.perf_counter()
                x = step(x, t, cond)
                steps.append((time.perf_counter() - ts) * 1e3)
            td = time.perf_counter()
            dec(x, a.frames)
            decodes.append((time.perf_counter() - td) * 1e3)
            gens.append((time.perf_counter() - t0) * 1e3)
    med = statistics.median
    print(f"torch {torch.__version__} eager{' int8 dynamic' if a.int8 else ''}, motionlcm {release}, frames {a.frames}, {a.steps} "
          f"LCM steps {[int(t) for t in timesteps]} (diffusers), guidance {guidance} embedded "
          f"(one pass per step), prompt {len(ids)} tokens, {a.threads} threads, {a.runs} runs "
          f"(medians):")
    print(f"  text encoding      {med(text):9.2f} ms  (sentence-t5-large)")
    print(f"  one step           {med(steps):9.2f} ms")
    print(f"  VAE decode         {med(decodes):9.2f} ms")
    print(f"  whole generation   {med(gens):9.2f} ms  ({a.steps} steps and the decode)")
    print(f"RESULT impl=torch frames={a.frames} text_ms={med(text):.2f} step_ms={med(steps):.2f} "
          f"gen_ms={med(gens):.2f} decode_ms={med(decodes):.2f}")


def sorted_moe(moe, x):
    """`TutelMoE.forward` with the routed tokens sorted by expert: the reference's routing
    (`route`, capacity drops), one gather, GELU(x W1ᵀ + b1) W2 + b2 per expert on its rows, and
    Σ_k gate_k · out_k by one index_add (with top-2, two terms: their order is moot)."""
    n = x.shape[0]
    scores = torch.softmax(moe.gates[0](x), dim=1)
    cap = moe.capacity(n)
    experts, gates, slots = ref_fmg.route(scores, moe.topk, cap)
    kept = slots < cap
    e_k, g_k = experts[kept], gates[kept]
    tok = torch.arange(n).unsqueeze(1).expand(n, moe.topk)[kept]
    order = torch.argsort(e_k, stable=True)
    tok, g_k = tok[order], g_k[order]
    counts = torch.bincount(e_k, minlength=moe.num_experts).tolist()
    xs, ex, outs, start = x[tok], moe.experts, [], 0
    for e, c in enumerate(counts):
        if c:
            h = torch.nn.functional.gelu(
                torch.addmm(ex.batched_fc1_bias[e], xs[start:start + c], ex.batched_fc1_w[e].t()))
            outs.append(torch.addmm(ex.batched_fc2_bias[e], h, ex.batched_fc2_w[e]))
        start += c
    y = x.new_zeros(n, ex.batched_fc2_bias.shape[1])
    if outs:  # else every choice was dropped
        y.index_add_(0, tok, torch.cat(outs) * g_k.unsqueeze(1))
    return y


def install_sorted_moe(net, check):
    """Replaces every TutelMoE's forward by `sorted_moe`; `check()` runs one forward in which
    each call also runs the reference MoE and must match it (same routing, f32 rounding)."""
    reference = ref_fmg.TutelMoE.forward
    worst = [0.0]

    def forward(self, x, log=None, tag=None):
        if log is not None:
            return reference(self, x, log, tag)
        y = sorted_moe(self, x)
        if worst[0] is not None:
            r = reference(self, x)
            err = (y - r).abs().max() / r.abs().max().clamp(min=1e-30)
            worst[0] = max(worst[0], float(err))
            return r
        return y

    for m in net.modules():
        if isinstance(m, ref_fmg.TutelMoE):
            m.forward = forward.__get__(m)
    check()
    err, worst[0] = worst[0], None
    if not err <= 1e-5:
        raise SystemExit(f"sorted MoE differs from the reference's: max relative error {err:.3g}")
    return err


class MoeTimer:
    """Wall time of every FineMoGen MOE wrapper call, by kind (text, motion), via hooks."""

    def __init__(self, net):
        self.total = {"text": 0.0, "motion": 0.0}
        self.on = False
        for blk in net.temporal_decoder_blocks:
            for kind, m in (("text", blk.ca_block.text_moe), ("motion", blk.ca_block.motion_moe)):
                m.register_forward_pre_hook(self.pre)
                m.register_forward_hook(lambda mod, i, o, k=kind: self.post(k))

    def pre(self, mod, inputs):
        self.t = time.perf_counter()

    def post(self, kind):
        if self.on:
            self.total[kind] += time.perf_counter() - self.t


class TextMoeOnce(torch.nn.Module):
    """A text MoE whose output is computed once per prompt (`prime`), then reused by every
    step: its input, LN(xf) + embedding, is the same at every step."""

    def __init__(self, moe):
        super().__init__()
        self.moe, self.out = moe, None

    def prime(self, x):
        self.out = self.moe(x)

    def forward(self, x, log=None, tag=None):
        return self.out


def finemogen_bench(a):
    """FineMoGen: text, one guided step and the whole respaced generation, MoE on its own."""
    with torch.inference_mode():
        net, clip, tok, cfg, _, _ = ref_fmg.load_libflame(a.model)
        stages = [ref_fmg.Stage(PROMPT, a.frames)]
        respacing = "15,15,8,6,6" if a.steps == 50 else str(a.steps)
        diff = ref_fmg.make_diffusion(respacing)
        if a.text_moe_once:
            for blk in net.temporal_decoder_blocks:
                blk.ca_block.text_moe = TextMoeOnce(blk.ca_block.text_moe)

        def enc(text):
            ids = torch.tensor([ref_fmg.clip_ids(tok, text)])
            return net.encode_clip_features(ref_fmg.clip_features(clip, ids))[0]

        def encode():
            xf, index, _ = ref_fmg.condition(stages, enc)
            if a.text_moe_once:
                for blk in net.temporal_decoder_blocks:
                    s = blk.ca_block
                    s.text_moe.prime(s.text_norm(xf).unsqueeze(2))
            return xf, index

        torch.manual_seed(0)
        noise = torch.randn(1, a.frames, cfg["denoiser"]["input_feats"])
        lengths = torch.tensor([a.frames])
        xf, index = encode()
        moe_err = None
        if a.moe == "sorted":
            moe_err = install_sorted_moe(net, lambda: net(noise, 999, lengths, xf, index, 1))
        text = [ms(encode) for _ in range(a.runs)]
        xf, index = encode()
        # The sampler's float64 tables, gathered and cast as ddim_sample does, per kept step.
        tabs = [tuple(torch.tensor(float(tb[i]), dtype=torch.float64).float()
                      for tb in (diff.sqrt_recip_alphas_cumprod, diff.sqrt_recipm1_alphas_cumprod,
                                 diff.alphas_cumprod_prev))
                for i in range(diff.num_timesteps)]

        def step(x, i):
            t = int(diff.timestep_map[i])
            w = ref_fmg.guidance_weight(t, a.guidance)
            cond, null = net(x, t, lengths, xf, index, 1)
            x0 = null + (cond - null) * w
            recip, recipm1, abp = tabs[i]
            eps = (recip * x - x0) / recipm1
            return x0 * torch.sqrt(abp) + torch.sqrt(1 - abp) * eps

        timer = MoeTimer(net)
        step(noise, diff.num_timesteps - 1)  # warm-up
        timer.on = True
        steps, gens = [], []
        for _ in range(a.runs):
            x = noise
            t0 = time.perf_counter()
            for i in reversed(range(diff.num_timesteps)):
                ts = time.perf_counter()
                x = step(x, i)
                steps.append((time.perf_counter() - ts) * 1e3)
            gens.append((time.perf_counter() - t0) * 1e3)
    med = statistics.median
    n = a.runs * diff.num_timesteps
    motion, txt = (timer.total[k] * 1e3 / n for k in ("motion", "text"))
    where = "with the text" if a.text_moe_once else "every step"
    print(f"torch {torch.__version__} eager, finemogen, frames {a.frames}, {diff.num_timesteps} "
          f"DDIM steps ({respacing}), in-network guidance batch 2 (scale {a.guidance}), "
          f"{a.threads} threads, {a.runs} runs (medians), MoE: {a.moe}"
          + (f" (max relative error vs the reference's {moe_err:.1e})" if moe_err is not None
             else ""))
    print(f"  text encoding      {med(text):9.2f} ms")
    print(f"  one guided step    {med(steps):9.2f} ms")
    print(f"  whole generation   {med(gens):9.2f} ms")
    share = (motion + txt) / (sum(steps) / n) * 100
    print(f"  mixture of experts {motion + txt:9.2f} ms per step ({share:.0f}% of the time: "
          f"motion {motion:.2f}, text {txt:.2f} ({where}))")
    print(f"RESULT impl=torch frames={a.frames} text_ms={med(text):.2f} step_ms={med(steps):.2f} "
          f"gen_ms={med(gens):.2f} moe_ms={motion + txt:.2f} motion_moe_ms={motion:.2f} "
          f"text_moe_ms={txt:.2f}")


def omg_runner(path, frames, guidance):
    """OMG-style: `guided` is D_u and D_c on x_t and x0 = D_u + s (D_c - D_u); `update` an eta-0
    DDIM update on x0; the text features are CLIP's token states of the prompt (tokens, eos)."""
    from reference import omg as ref_omg
    net, clip, tok, cfg, _, _ = ref_omg.load_libflame(path)
    net.eval()
    d = cfg["denoiser"]
    padding = (d.get("control") or {}).get("text_padding", False)
    torch.manual_seed(0)
    x0 = torch.randn(1, frames, d["input_feats"])

    def encode():
        text = ref_omg.batch_texts([ref_omg.encode_text(clip, tok, PROMPT, padding)])
        assert "mask" not in text  # one prompt: every token kept
        return text["tokens"], text["eos"]

    def guided(x, t, tokens, eos):
        return ref_omg.guided_x0(net, x, t, {"tokens": tokens, "eos": eos}, guidance)

    def update(x, x0_hat):
        return 0.8 ** 0.5 * x0_hat + 0.2 ** 0.5 * (x - 0.5 ** 0.5 * x0_hat) / 0.5 ** 0.5

    return Runner(net, encode, encode(), x0, guided, update)


def omg_bench(a):
    """OMG-style: CLIP's token states of the prompt (`text`), one guided step (D_u and D_c on
    x_t, x0 = D_u + s (D_c - D_u), an eta-0 DDIM update on x0) and `steps` such steps."""
    import resource
    with torch.inference_mode():
        run = omg_runner(a.model, a.frames, a.guidance)
        x0 = run.x
        texts = []
        text = [ms(lambda: texts.append(run.encode())) for _ in range(a.runs)]
        feats = texts[-1]

        def step(x, t):
            return run.step(x, float(t), feats)

        step(x0, 500)  # warm-up
        steps, gens = [], []
        for _ in range(a.runs):
            x = x0
            t0 = time.perf_counter()
            for i in range(a.steps):
                ts = time.perf_counter()
                x = step(x, 999 - i * (1000 // a.steps))
                steps.append((time.perf_counter() - ts) * 1e3)
            gens.append((time.perf_counter() - t0) * 1e3)
    med = statistics.median
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"torch {torch.__version__} eager, omg, frames {a.frames}, {a.steps} guided steps "
          f"(D_u + D_c, scale {a.guidance}), {a.threads} threads, {a.runs} runs (medians)")
    print(f"  text encoding      {med(text):9.2f} ms")
    print(f"  one guided step    {med(steps):9.2f} ms")
    print(f"  whole generation   {med(gens):9.2f} ms")
    print(f"  peak RSS           {rss:9.1f} MiB")
    print(f"RESULT impl=torch frames={a.frames} text_ms={med(text):.2f} step_ms={med(steps):.2f} "
          f"gen_ms={med(gens):.2f} hwm_mib={rss:.1f}")


# The shapes of `flame-bench gemm` (M x K x N).
GEMM_SHAPES = [
    ("attn qkv", 398, 768, 2304), ("attn q/out", 398, 768, 768), ("ffn up", 398, 768, 2048),
    ("ffn down", 398, 2048, 768), ("mdm qkv", 394, 512, 1536), ("mdm out", 394, 512, 512),
    ("mdm ffn up", 394, 512, 1024), ("mdm ffn down", 394, 1024, 512),
    ("text 20x768x3072", 20, 768, 3072), ("square 1536", 1536, 1536, 1536),
]


def gemm(runs):
    gen = torch.Generator().manual_seed(0)
    print(f"torch {torch.__version__} linear GFLOP/s, {torch.get_num_threads()} threads, "
          f"median of {runs}:")
    for name, m, k, n in GEMM_SHAPES:
        x, w, b = (torch.randn(*s, generator=gen) for s in ((m, k), (n, k), (n,)))
        torch.nn.functional.linear(x, w, b)
        times = []
        for _ in range(runs):
            t = time.perf_counter()
            torch.nn.functional.linear(x, w, b)
            times.append(time.perf_counter() - t)
        print(f"  {name:<18} {f'{m}x{k}x{n}':>16} {2 * m * k * n / statistics.median(times) / 1e9:10.1f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gemm", action="store_true", help="time linear layers only (no model)")
    ap.add_argument("--model")
    ap.add_argument("--frames", type=int, default=196)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs", type=int, help="default 3 (model) or 9 (--gemm)")
    ap.add_argument("--guidance", type=float, default=2.5,
                    help="guidance scale (FineMoGen: s of w(t) = 1 + s·t/1000)")
    ap.add_argument("--moe", choices=("sorted", "reference"), default="sorted",
                    help="FineMoGen: the MoE's expert dispatch (see above)")
    ap.add_argument("--text-moe-once", action="store_true",
                    help="FineMoGen: the text MoE once per prompt instead of every step")
    ap.add_argument("--int8", action="store_true",
                    help="MotionLCM: the denoiser and decoder dynamically quantised to int8 "
                         "(torch.ao.quantization.quantize_dynamic on nn.Linear)")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    torch.set_num_interop_threads(1)
    if a.gemm:
        gemm(a.runs or 9)
        return
    a.runs = a.runs or 3
    if not a.model:
        ap.error("--model is required (or --gemm)")

    from safetensors import safe_open
    with safe_open(a.model, "pt") as f:
        arch = json.loads(f.metadata()["flame.config"])["architecture"]
    if arch in ("mola", "mld"):
        latent_bench(arch, a)
        return
    if arch == "motionlcm":
        motionlcm_bench(a)
        return
    if arch == "finemogen":
        finemogen_bench(a)
        return
    if arch == "omg":
        omg_bench(a)
        return
    runner = flame_runner if arch == "flame" else mdm_runner
    with torch.inference_mode():
        run = runner(a.model, a.frames, a.guidance)
        encode, feats, x0, step = run.encode, run.feats, run.x, run.step
        text = [ms(encode) for _ in range(a.runs)] if encode else [float("nan")]
        step(x0, 500, feats)  # warm-up
        steps, gens = [], []
        for _ in range(a.runs):
            x = x0
            t0 = time.perf_counter()
            for i in range(a.steps):
                t = time.perf_counter()
                x = step(x, 999 - i * (1000 // a.steps), feats)
                steps.append((time.perf_counter() - t) * 1e3)
            gens.append((time.perf_counter() - t0) * 1e3)
    med = statistics.median
    print(f"torch {torch.__version__} eager, {arch}, frames {a.frames}, {a.steps} steps, "
          f"guidance batch 2, {a.threads} threads, {a.runs} runs (medians):")
    print(f"  text encoding      {med(text):9.2f} ms")
    print(f"  one guided step    {med(steps):9.2f} ms")
    print(f"  whole generation   {med(gens):9.2f} ms")
    print(f"RESULT impl=torch frames={a.frames} text_ms={med(text):.2f} "
          f"step_ms={med(steps):.2f} gen_ms={med(gens):.2f}")


if __name__ == "__main__":
    main()
