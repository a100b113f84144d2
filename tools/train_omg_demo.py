#!/usr/bin/env python3
"""Train a tiny OMG-style model on the demo corpus, convert it and run it with libflame's CLI.

A test model, not a demo claim: it shows that the whole path works end to end on a CPU in
minutes (train -> `convert.py omg` -> `flame generate`), and that the ControlNet changes what
the backbone generates. Training follows the paper's two phases (sections 3.1 and 3.2;
docs/official/omg.md#unconditional-denoiser, docs/official/omg.md#motion-controlnet):

 1. the DiT backbone D_u alone, unconditionally: x0 prediction, cosine schedule (T = 1000),
    L2 on x0, t uniform over 0..999;
 2. the backbone frozen, the ControlNet copies initialised from the backbone blocks and the
    up-projections zero (so D_c starts as D_u, as ControlNet), trained on (motion, sentence)
    pairs of the single-action clips with the same loss on D_c.

The text tower is a small random Hugging Face CLIPTextModelWithProjection with the real CLIP
tokenizer (tests/fixtures/clip_tokenizer), frozen as the paper freezes CLIP: its features are
deterministic per sentence, which is all the ControlNet needs. Motions are the corpus's
smpl24_6d features [frames, 147] at 20 fps, z-normalised with the corpus mean/std (stored in
the file as motion.mean / motion.std). Training windows are WINDOW frames: shorter clips are
padded with their last frame (every clip ends standing still), longer ones cropped at random.

Then: the state dict is converted with `python tools/convert.py omg`; `flame generate` samples
a few corpus sentences of different families (guided at each --eval-guidance) and the empty
prompt (the backbone alone) for several seeds; `flame-corpus classify` labels the joint
positions; and the reference (tools/reference/omg.py) re-runs one sampling from the same noise
on the converted file as a parity check of the trained weights.

  python tools/train_omg_demo.py [--work target/omg-demo] [--count 1500] [--steps1 N]
      [--steps2 N] [--threads 1] [--stage all|train|eval]

Writes WORK/corpus/ (flame-corpus generate), WORK/clip/ (the random CLIP folder),
WORK/omg_demo.pt (state dict), WORK/mean.npy, WORK/std.npy, WORK/omg_demo.safetensors,
WORK/eval/ (generated motions) and WORK/summary.json (sizes, times, losses, classifier rates).
The binaries come from `cargo build --release` in $CARGO_TARGET_DIR (default target).
"""
import argparse
import json
import os
import subprocess
import sys
import time
import zlib

import numpy as np
import torch

TOOLS = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(TOOLS)
sys.path.insert(0, TOOLS)
sys.path.insert(0, os.path.join(TOOLS, "demo"))

import common  # noqa: E402  (tools/demo: the corpus reader and feature statistics)
from reference import omg  # noqa: E402
from reference.diffusion import cosine_betas  # noqa: E402

TOKENIZER = os.path.join(REPO, "tests", "fixtures", "clip_tokenizer", "tokenizer.json")
NUM_TIMESTEPS = 1000
# One prompt per family in this order (different kinds of action: travel, vertical, arms, legs,
# turning); each is a corpus sentence of a single-action clip, picked with the seed.
EVAL_FAMILIES = ("walk", "jump", "wave", "squat", "turn")


def log(msg):
    print(msg, flush=True)


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default=os.path.join(REPO, "target", "omg-demo"))
    ap.add_argument("--stage", choices=("all", "train", "eval"), default="all")
    ap.add_argument("--count", type=int, default=1500, help="corpus clips")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--window", type=int, default=120, help="training window, frames")
    ap.add_argument("--d-model", type=int, default=64)
    ap.add_argument("--layers", type=int, default=3)
    ap.add_argument("--heads", type=int, default=2)
    ap.add_argument("--time-freq-dim", type=int, default=64)
    ap.add_argument("--control-dim", type=int, default=32)
    ap.add_argument("--experts", type=int, default=4)
    ap.add_argument("--expert-hidden", type=int, default=64)
    ap.add_argument("--gate-hidden", type=int, default=64)
    ap.add_argument("--text-width", type=int, default=64, help="the random CLIP's width")
    ap.add_argument("--text-layers", type=int, default=2)
    ap.add_argument("--steps1", type=int, default=700, help="backbone steps")
    ap.add_argument("--batch1", type=int, default=32)
    ap.add_argument("--lr1", type=float, default=1e-3)
    ap.add_argument("--steps2", type=int, default=600, help="ControlNet steps")
    ap.add_argument("--batch2", type=int, default=16)
    ap.add_argument("--lr2", type=float, default=3e-3)
    ap.add_argument("--warmup", type=int, default=30)
    ap.add_argument("--log-every", type=int, default=50)
    ap.add_argument("--eval-seeds", type=int, default=4)
    ap.add_argument("--eval-guidance", default="1,2.5,4.5")
    ap.add_argument("--eval-frames", type=int, default=120)
    ap.add_argument("--eval-steps", type=int, default=50)
    return ap.parse_args(argv)


# -- corpus and text ------------------------------------------------------------------------------

def binaries():
    """Builds (if needed) and returns the paths of `flame` and `flame-corpus`."""
    target = os.environ.get("CARGO_TARGET_DIR", os.path.join(REPO, "target"))
    # One invocation: built separately, the two would rebuild the runtime with different
    # features each time.
    subprocess.run(["cargo", "build", "--release", "--quiet", "-p", "flame", "--bin", "flame",
                    "-p", "flame-demo", "--bin", "flame-corpus"], cwd=REPO, check=True)
    rel = os.path.join(os.path.abspath(target), "release")
    return os.path.join(rel, "flame"), os.path.join(rel, "flame-corpus")


def ensure_corpus(args, flame_corpus):
    corpus = os.path.join(args.work, "corpus")
    if os.path.exists(os.path.join(corpus, "corpus.jsonl")):
        with open(os.path.join(corpus, "summary.json")) as f:
            s = json.load(f)
        if (s["count"], s["seed"]) != (args.count, args.seed):
            raise SystemExit(f"{corpus} holds {s['count']} clips of seed {s['seed']}, not "
                             f"{args.count} of seed {args.seed}: delete it or change --work")
        log(f"reusing {corpus}")
    else:
        subprocess.run([flame_corpus, "generate", "--out", corpus, "--count", str(args.count),
                        "--seed", str(args.seed)], check=True)
    return corpus


def random_clip(args, folder):
    """A small random CLIP text tower (Hugging Face default init, seeded) with the real CLIP
    tokenizer, written as a folder the converter reads; returns (model, tokenizer)."""
    from tokenizers import Tokenizer
    from transformers import CLIPTextConfig, CLIPTextModelWithProjection
    w = args.text_width
    cfg = CLIPTextConfig(vocab_size=49408, hidden_size=w, intermediate_size=4 * w,
                         num_hidden_layers=args.text_layers, num_attention_heads=max(1, w // 32),
                         max_position_embeddings=77, projection_dim=w, hidden_act="quick_gelu",
                         layer_norm_eps=1e-5, bos_token_id=omg.SOT, eos_token_id=omg.EOT,
                         pad_token_id=0, attn_implementation="eager")
    torch.manual_seed(args.seed + 1)
    clip = CLIPTextModelWithProjection(cfg).eval()
    clip.requires_grad_(False)
    os.makedirs(folder, exist_ok=True)
    clip.save_pretrained(folder, safe_serialization=True)
    with open(TOKENIZER) as src, open(os.path.join(folder, "tokenizer.json"), "w") as dst:
        dst.write(src.read())
    return clip, Tokenizer.from_file(TOKENIZER)


@torch.no_grad()
def encode_all(clip, tokenizer, sentences, batch=256):
    """omg.encode_text of every sentence, batched: CLIP's causal mask makes the SOT..EOT
    features independent of what follows, so the batch is cut after its longest EOT."""
    out = {}
    for i in range(0, len(sentences), batch):
        part = sentences[i:i + batch]
        ids = [omg.clip_ids(tokenizer, s) for s in part]
        eots = [x.index(omg.EOT) for x in ids]
        n = max(eots) + 1
        h = clip.text_model(input_ids=torch.tensor([x[:n] for x in ids])).last_hidden_state
        for s, x, e, f in zip(part, ids, eots, h):
            out[s] = {"ids": x[:e + 1], "tokens": f[:e + 1].float().clone(),
                      "eos": f[e].float().clone()}
    return out


def window(motion, length, rng):
    """A [length, F] window: padded with the last frame (the clip's rest pose) or cropped."""
    n = motion.shape[0]
    if n >= length:
        s = int(rng.integers(0, n - length + 1))
        return motion[s:s + length]
    return np.concatenate([motion, np.repeat(motion[-1:], length - n, axis=0)])


# -- training -------------------------------------------------------------------------------------

class Schedule:
    """The cosine schedule's sqrt(abar), sqrt(1 - abar) per original step (float64 -> f32)."""

    def __init__(self):
        abar = np.cumprod(1.0 - cosine_betas(NUM_TIMESTEPS))
        self.a = torch.tensor(np.sqrt(abar), dtype=torch.float32)
        self.s = torch.tensor(np.sqrt(1.0 - abar), dtype=torch.float32)

    def noisy(self, x0, t, noise):
        return self.a[t][:, None, None] * x0 + self.s[t][:, None, None] * noise


def lr_at(step, total, peak, warmup):
    """Linear warm-up, then cosine decay to 10 % of the peak."""
    if step < warmup:
        return peak * (step + 1) / warmup
    p = (step - warmup) / max(1, total - warmup)
    return peak * (0.1 + 0.45 * (1 + np.cos(np.pi * p)))


def train_phase(name, net, params, batches, steps, peak, seed, args, text_of=None):
    """AdamW on x0-L2; batches() -> (x0 [B, T, F], sentences or None); t and the noise drawn
    from `seed`. Returns (the loss log, seconds)."""
    sched = Schedule()
    opt = torch.optim.AdamW(params, lr=peak, weight_decay=0.0)
    gen = torch.Generator().manual_seed(seed)
    losses, window_losses = [], []
    t0 = time.perf_counter()
    for step in range(steps):
        for g in opt.param_groups:
            g["lr"] = lr_at(step, steps, peak, args.warmup)
        x0, texts = batches()
        t = torch.randint(0, NUM_TIMESTEPS, (x0.shape[0],), generator=gen)
        noise = torch.randn(x0.shape, generator=gen)
        pred = net(sched.noisy(x0, t, noise), t.double(), text_of(texts) if texts else None)
        loss = ((pred - x0) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        window_losses.append(loss.item())
        if (step + 1) % args.log_every == 0 or step + 1 == steps:
            mean = float(np.mean(window_losses))
            losses.append({"step": step + 1, "loss": round(mean, 5)})
            log(f"  {name} step {step + 1}/{steps}: loss {mean:.4f} "
                f"({time.perf_counter() - t0:.0f} s)")
            window_losses = []
    return losses, time.perf_counter() - t0


@torch.no_grad()
def val_loss(net, x0, texts, text_of, seed):
    """Held-out x0-L2 with fixed noise: the mean over 10 t spread over 50..950 and the value at
    t = 950 (where the text matters most), for D_u and, given texts, D_c with each clip's own
    sentence and with the sentences shuffled among the clips (how much D_c uses the text)."""
    sched = Schedule()
    gen = torch.Generator().manual_seed(seed)
    kinds = ["uncond"] if texts is None else ["uncond", "cond", "cond_shuffled"]
    if texts is not None:
        perm = np.random.default_rng(seed).permutation(len(texts))
        shuffled = [texts[i] for i in perm]
    out = {}
    ts = np.linspace(50, 950, 10).astype(int)
    for t_val in ts:
        t = torch.full((x0.shape[0],), int(t_val))
        xt = sched.noisy(x0, t, torch.randn(x0.shape, generator=gen))
        for k in kinds:
            text = None if k == "uncond" else text_of(texts if k == "cond" else shuffled)
            err = ((net(xt, t.double(), text) - x0) ** 2).mean().item()
            out[k] = out.get(k, 0.0) + err / len(ts)
            if t_val == ts[-1]:
                out[k + "_t950"] = err
    return {k: round(v, 5) for k, v in out.items()}


def train(args, corpus, summary):
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    records = common.load_corpus(corpus)
    mean, std = common.feature_stats(records, 0.01)
    np.save(os.path.join(args.work, "mean.npy"), mean)
    np.save(os.path.join(args.work, "std.npy"), std)
    for r in records:
        r["motion"] = (r["motion"] - mean) / std
    # The last 5 % of the clips are held out (validation losses only).
    n_val = max(8, len(records) // 20)
    train_recs, val_recs = records[:-n_val], records[-n_val:]
    single = [r for r in train_recs if len(r["actions"]) == 1]
    val_single = [r for r in val_recs if len(r["actions"]) == 1]
    log(f"corpus: {len(records)} clips ({sum(r['frames'] for r in records)} frames), "
        f"{len(train_recs)} for training ({len(single)} single-action), {len(val_recs)} held out")

    t_text = time.perf_counter()
    clip, tokenizer = random_clip(args, os.path.join(args.work, "clip"))
    sentences = sorted({s for r in single + val_single for s in r["texts"]})
    feats = encode_all(clip, tokenizer, sentences)
    t_text = time.perf_counter() - t_text
    log(f"text: {len(sentences)} sentences encoded by the frozen random CLIP "
        f"({args.text_layers} x {args.text_width}) in {t_text:.1f} s")

    cfg = dict(input_feats=common.MOTION_DIM, d_model=args.d_model, layers=args.layers,
               heads=args.heads, ff_size=2 * args.d_model, time_freq_dim=args.time_freq_dim,
               max_frames=300,
               control=dict(control_dim=args.control_dim, text_dim=args.text_width,
                            experts=args.experts, expert_hidden=args.expert_hidden,
                            gate_hidden=args.gate_hidden))
    net = omg.OMG(cfg)
    backbone = [p for n, p in net.named_parameters() if not n.startswith("control.")]
    control = [p for n, p in net.named_parameters() if n.startswith("control.")]
    n_bb, n_ctrl = sum(p.numel() for p in backbone), sum(p.numel() for p in control)
    log(f"model: {args.layers} x {args.d_model} / {args.heads} heads, backbone {n_bb / 1e6:.3f} M"
        f", ControlNet {n_ctrl / 1e6:.3f} M (d_m {args.control_dim}, {args.experts} experts)")

    vrng = np.random.default_rng(args.seed + 2)
    val_x = torch.from_numpy(np.stack([window(r["motion"], args.window, vrng)
                                       for r in val_single]))
    val_t = [vrng.choice(r["texts"]) for r in val_single]

    def text_of(texts):
        return omg.batch_texts([feats[s] for s in texts])

    def batches_all():
        idx = rng.integers(0, len(train_recs), args.batch1)
        x = np.stack([window(train_recs[i]["motion"], args.window, rng) for i in idx])
        return torch.from_numpy(x), None

    def batches_text():
        idx = rng.integers(0, len(single), args.batch2)
        x = np.stack([window(single[i]["motion"], args.window, rng) for i in idx])
        return torch.from_numpy(x), [single[i]["texts"][rng.integers(len(single[i]["texts"]))]
                                     for i in idx]

    # Phase 1: the backbone, unconditionally (the ControlNet is not used).
    net.train()
    net.control.requires_grad_(False)
    log(f"phase 1: backbone, {args.steps1} steps of batch {args.batch1} x {args.window} frames")
    loss1, time1 = train_phase("backbone", net, backbone, batches_all, args.steps1, args.lr1,
                               args.seed + 10, args)
    val1 = val_loss(net, val_x, None, text_of, args.seed + 3)

    # Phase 2: ControlNet copies = the backbone blocks, up-projections zero, backbone frozen.
    with torch.no_grad():
        for blk, copy in zip(net.blocks, net.control.blocks):
            copy.load_state_dict(blk.state_dict())
        for up in net.control.up:
            up.weight.zero_()
            up.bias.zero_()
    for p in backbone:
        p.requires_grad_(False)
    net.control.requires_grad_(True)
    zero = val_loss(net, val_x, val_t, text_of, args.seed + 3)
    assert zero["cond"] == zero["uncond"], zero  # zero up-projections: D_c is D_u
    log(f"phase 2: ControlNet, {args.steps2} steps of batch {args.batch2} (backbone frozen)")
    loss2, time2 = train_phase("control", net, control, batches_text, args.steps2, args.lr2,
                               args.seed + 11, args, text_of)
    val2 = val_loss(net, val_x, val_t, text_of, args.seed + 3)
    net.eval()
    log(f"held-out x0-L2 ({len(val_single)} clips, mean over 10 t | at t = 950): backbone "
        f"{val1['uncond']:.4f} | {val1['uncond_t950']:.4f}; D_c {val2['cond']:.4f} | "
        f"{val2['cond_t950']:.4f}; D_c with shuffled sentences {val2['cond_shuffled']:.4f} | "
        f"{val2['cond_shuffled_t950']:.4f}")
    log(f"time: text {t_text:.0f} s, phase 1 {time1:.0f} s, phase 2 {time2:.0f} s "
        f"({args.threads} thread(s))")
    omg.save_state_dict(net, os.path.join(args.work, "omg_demo.pt"))
    summary.update({
        "corpus": {"clips": len(records), "train": len(train_recs), "single_action": len(single),
                   "held_out": len(val_recs), "sentences_encoded": len(sentences)},
        "model": {"denoiser": net.cfg, "backbone_params": n_bb, "control_params": n_ctrl,
                  "clip": {"width": args.text_width, "layers": args.text_layers}},
        "training": {"threads": args.threads, "window": args.window,
                     "phase1": {"steps": args.steps1, "batch": args.batch1, "lr": args.lr1,
                                "seconds": round(time1, 1), "loss": loss1},
                     "phase2": {"steps": args.steps2, "batch": args.batch2, "lr": args.lr2,
                                "seconds": round(time2, 1), "loss": loss2},
                     "text_seconds": round(t_text, 1),
                     "held_out": {"backbone_after_phase1": val1, "after_phase2": val2}},
    })


# -- conversion and evaluation --------------------------------------------------------------------

def convert(args, model):
    cmd = [sys.executable, os.path.join(TOOLS, "convert.py"), "omg",
           "--ckpt", os.path.join(args.work, "omg_demo.pt"),
           "--clip", os.path.join(args.work, "clip"), "--format", "smpl24_6d", "--fps", "20",
           "--mean", os.path.join(args.work, "mean.npy"),
           "--std", os.path.join(args.work, "std.npy"), "--heads", str(args.heads),
           "--frames", str(args.eval_frames), "--steps", str(args.eval_steps),
           "--out", model]
    subprocess.run(cmd, check=True)


def eval_prompts(corpus, seed):
    rng = np.random.default_rng(seed)
    by_family = {}
    with open(os.path.join(corpus, "corpus.jsonl")) as f:
        for line in f:
            r = json.loads(line)
            if len(r["actions"]) == 1:
                by_family.setdefault(r["family"], []).append(r)
    out = []
    for fam in EVAL_FAMILIES:
        r = by_family[fam][int(rng.integers(len(by_family[fam])))]
        out.append((fam, r["texts"][int(rng.integers(len(r["texts"])))]))
    return out


def generate(flame, flame_corpus, model, prompt, guidance, seed, out_dir, args, noise=None):
    """flame generate -> (family by the classifier, features [T, F] from the .npy, seconds)."""
    tag = "blank" if guidance is None else f"s{guidance}"
    stem = os.path.join(out_dir, f"{tag}_{zlib.crc32(prompt.encode()):08x}_seed{seed}")
    cmd = [flame, "generate", "--model", model, "--prompt", prompt or "",
           "--frames", str(args.eval_frames), "--steps", str(args.eval_steps),
           "--seed", str(seed), "--threads", str(args.threads),
           "--out", stem + ".npy", "--positions", stem + "_pos.npy"]
    if guidance is not None:
        cmd += ["--guidance", str(guidance)]
    if noise is not None:
        cmd += ["--noise", noise]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    secs = time.perf_counter() - t0
    fam = subprocess.run([flame_corpus, "classify", stem + "_pos.npy"], check=True,
                         capture_output=True, text=True).stdout.strip()
    return fam, np.load(stem + ".npy"), secs


def parity(args, model, flame, flame_corpus, prompt, out_dir):
    """The reference sampler on the converted file vs `flame generate` from the same noise."""
    net, clip, tok, cfg, _, _ = omg.load_libflame(model)
    noise = torch.from_numpy(np.random.default_rng(args.seed + 7).standard_normal(
        (args.eval_frames, common.MOTION_DIM)).astype(np.float32))
    path = os.path.join(out_dir, "parity_noise.npy")
    np.save(path, noise.numpy())
    text = omg.batch_texts([omg.encode_text(clip, tok, prompt)])
    ref = omg.ddim_sample(net, noise[None], text, guidance=cfg["defaults"]["guidance"],
                          steps=args.eval_steps)[-1]["x"][0].numpy()
    _, rust, _ = generate(flame, flame_corpus, model, prompt, None, 0, out_dir, args, noise=path)
    return float(np.abs(rust - ref).max()), float(np.abs(ref).max())


def evaluate(args, corpus, flame, flame_corpus, summary):
    torch.set_num_threads(args.threads)
    model = os.path.join(args.work, "omg_demo.safetensors")
    t0 = time.perf_counter()
    convert(args, model)
    t_convert = time.perf_counter() - t0
    out_dir = os.path.join(args.work, "eval")
    os.makedirs(out_dir, exist_ok=True)
    prompts = eval_prompts(corpus, args.seed)
    seeds = list(range(args.eval_seeds))
    guidances = [float(g) for g in args.eval_guidance.split(",")]
    gen_secs = []
    # The backbone alone (blank prompt) does not depend on the prompt: one run per seed,
    # scored against every prompt's family.
    blank = {}
    for seed in seeds:
        fam, x, secs = generate(flame, flame_corpus, model, "", None, seed, out_dir, args)
        blank[seed] = (fam, x)
        gen_secs.append(secs)
    results = {"backbone": {"labels": [blank[s][0] for s in seeds]}}
    hits = sum(blank[s][0] == fam for fam, _ in prompts for s in seeds)
    results["backbone"]["rate"] = hits / (len(prompts) * len(seeds))
    for g in guidances:
        rows, hits, diffs = [], 0, []
        for fam, prompt in prompts:
            labels = []
            for seed in seeds:
                got, x, secs = generate(flame, flame_corpus, model, prompt, g, seed, out_dir,
                                        args)
                labels.append(got)
                hits += got == fam
                diffs.append(float(np.abs(x - blank[seed][1]).mean()))
                gen_secs.append(secs)
            rows.append({"family": fam, "prompt": prompt, "labels": labels})
        results[f"s={g}"] = {"rate": hits / (len(prompts) * len(seeds)), "prompts": rows,
                             "mean_abs_diff_from_backbone": round(float(np.mean(diffs)), 4)}
    par, scale = parity(args, model, flame, flame_corpus, prompts[0][1], out_dir)
    summary["evaluation"] = {
        "model_bytes": os.path.getsize(model), "convert_seconds": round(t_convert, 1),
        "frames": args.eval_frames, "steps": args.eval_steps, "seeds": seeds,
        "generate_seconds_mean": round(float(np.mean(gen_secs)), 2),
        "results": results,
        "parity_max_abs": par, "parity_scale": scale}
    log(f"converted {model} ({os.path.getsize(model) / 1e6:.2f} MB) in {t_convert:.1f} s; "
        f"flame generate {np.mean(gen_secs):.2f} s per motion ({args.eval_frames} frames, "
        f"{args.eval_steps} steps, {args.threads} thread(s))")
    log(f"backbone alone (blank prompt): {results['backbone']['labels']} -> "
        f"{100 * results['backbone']['rate']:.0f}% of {len(prompts)} prompts x {len(seeds)} seeds")
    for g in guidances:
        r = results[f"s={g}"]
        log(f"guided s = {g}: {100 * r['rate']:.0f}%; mean |guided - backbone| "
            f"{r['mean_abs_diff_from_backbone']:.3f}")
        for row in r["prompts"]:
            log(f"    {row['family']:>6} {row['prompt']!r}: {row['labels']}")
    log(f"parity, reference vs flame generate (same noise, s = default, {args.eval_steps} steps):"
        f" max |diff| {par:.2e} (values up to {scale:.2f})")


def main(argv=None):
    args = parse_args(argv)
    args.work = os.path.abspath(args.work)
    os.makedirs(args.work, exist_ok=True)
    flame, flame_corpus = binaries()
    corpus = ensure_corpus(args, flame_corpus)
    path = os.path.join(args.work, "summary.json")
    summary = {}
    if args.stage == "eval" and os.path.exists(path):
        with open(path) as f:
            summary = json.load(f)
    if args.stage in ("all", "train"):
        train(args, corpus, summary)
    if args.stage in ("all", "eval"):
        evaluate(args, corpus, flame, flame_corpus, summary)
    with open(path, "w") as f:
        json.dump(summary, f, indent=1)
    log(f"summary: {path}")


if __name__ == "__main__":
    main()
