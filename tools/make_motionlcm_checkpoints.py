#!/usr/bin/env python3
"""Write full-size random MotionLCM checkpoints shaped like the released ones and one random
full-size sentence-t5-large folder, for the converter and the benchmark (no released weights
needed; nothing is downloaded).

  python tools/make_motionlcm_checkpoints.py --out DIR [--release v1|v2|both] [--seed 0]
      -> DIR/motionlcm_v1.ckpt, DIR/motionlcm_v2.ckpt   {'state_dict': ...} (official layout)
         DIR/sentence-t5-large/                          sentence-transformers folder
         DIR/mean.npy, DIR/std.npy                       263 values each
so that `tools/convert.py motionlcm --ckpt DIR/motionlcm_vN.ckpt --t5 DIR/sentence-t5-large
--mean DIR/mean.npy --std DIR/std.npy --out M.safetensors` runs on DIR
(tools/make_motionlcm_base_models.sh does all of it).

Sizes (tools/convert_motionlcm.py's sources: configs/modules/denoiser.yaml, motion_vae.yaml of
Dai-Wenxun/MotionLCM v1.0 / v2.0, and sentence-transformers/sentence-t5-large):
- denoiser: MLD's skip transformer, width 256, 9 layers, 4 heads, ff 1024, text and time dim
  768, cond_dim 256 (the guidance embedding), query_pos 500 rows; v1 latent [1, 256], v2 latent
  [16, 32] with latent_pre / latent_post (C 32 <-> D 256), v2's text projection without ReLU.
- VAE decoder: 9-layer skip decoder 256 wide, 4 heads, ff 1024, 500 position rows, final norm,
  263 features; v2 with vae.latent_post (32 -> 256). Stand-ins for the encoder side, an
  evaluator tensor and v1's unused `denoiser.mem_pos.pe`, all of which the converter skips.
  Built by tools/make_motionlcm_fixtures.py's `checkpoint` (weights by make_latent_fixtures'
  `randomize`: matrices uniform +-1/sqrt(fan_in), norms 1 + 0.1 N, biases 0.1 N, tables N(0, 0.5)).
- sentence-t5-large: T5 v1.0 encoder (d_model 1024, 24 layers, 16 heads, d_kv 64, d_ff 4096,
  ReLU feed-forward, 32 buckets, max distance 128, vocab 32128, eps 1e-6) + Dense 1024 -> 768
  without bias, written by make_motionlcm_fixtures' `write_folder` (modules.json, 1_Pooling,
  2_Dense, 3_Normalize, sentence_bert_config.json max_seq_length 256, model.safetensors) plus the
  tokenizer_config.json, special_tokens_map.json and config_sentence_transformers.json the
  published folder has. Weights: matrices uniform +-1/sqrt(fan_in), the embedding N(0, 1), the
  relative-position bias 0.5 N, RMSNorm scales 1 + 0.1 N: activations stay finite over the
  24 layers and the attention is neither uniform nor one-hot.
- tokenizer.json: 32128 ids laid out as T5's fast tokenizer (Unigram, `<pad>` 0, `</s>` 1,
  `<unk>` 2, WhitespaceSplit + Metaspace pre-tokenizer, `$A </s>` post-processor,
  `<extra_id_99>`..`<extra_id_0>` as the last 100 ids and added tokens): a Unigram model trained
  here with the `tokenizers` library on motion captions, plus every caption word as a piece scored
  by its frequency (so a caption is split into words, about as many tokens as T5's own tokenizer
  gives), then made reproducible by
  make_motionlcm_fixtures' `canonical_tokenizer`, then filler pieces of a score below every
  trained one up to 32028 pieces.
- With --control: DIR/motionlcm_vN_control.ckpt as well, the checkpoint plus a full-size random
  ControlNet (`controlnet.*`: a copy of the denoiser, the condition embedding and the 9
  zero-initialised-in-training Linear(256, 256) down blocks, here random) and trajectory encoder
  (`traj_encoder.*`: Linear 66 -> 256, 9-layer skip encoder 256 wide, 4 heads, ff 1024, 500
  position rows), built by tools/reference/motionlcm_control.py's modules as the tiny control
  fixtures are; DIR/mean_raw.npy and DIR/std_raw.npy ([22, 3]) for --control-mean/--control-std.
"""
import argparse
import json
import math
import os
import sys
import time

import numpy as np
import torch

TOOLS = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, TOOLS)
import make_motionlcm_fixtures as fx  # noqa: E402

T5_LARGE = dict(d_model=1024, d_kv=64, d_ff=4096, num_layers=24, num_heads=16,
                relative_attention_num_buckets=32, relative_attention_max_distance=128)
VOCAB = 32128
EXTRA_IDS = 100
TEXT_DIM = 768
DEN = dict(latent_dim=256, text_dim=TEXT_DIM, cond_dim=256, layers=9, heads=4, ff_size=1024,
           max_len=500)
VAE = dict(latent_dim=256, layers=9, heads=4, ff_size=1024, nfeats=263, max_len=500,
           final_norm=True)
LATENT = {"v1": (1, 256), "v2": (16, 32)}

SUBJECTS = ["a person", "a man", "a woman", "someone", "the person", "a figure", "the man",
            "a child", "an old man", "a dancer", "the woman", "a soldier"]
ACTIONS = ["walks forward", "walks backward", "runs in a circle", "jumps twice in place",
           "turns around", "waves with the right hand", "waves with the left hand",
           "kicks with the left leg", "kicks with the right foot", "crouches down",
           "picks something up", "stands up slowly", "sits down on a chair", "climbs stairs",
           "throws a ball", "catches an object", "dances happily", "stretches both arms",
           "bows politely", "steps to the side", "jogs in place", "spins on one foot",
           "raises both hands above the head", "claps the hands", "punches forward",
           "hops on one leg", "walks in a zigzag", "lies down on the floor", "does a cartwheel",
           "swims with the arms", "plays the guitar", "drinks from a cup", "looks around",
           "shakes the head", "nods", "limps to the left", "sneaks quietly", "marches proudly",
           "balances on a beam", "pushes a heavy box", "pulls a rope", "lifts a weight"]
LINKS = [", then", " and", " and then", ", after that", " before he", " while she", ", and"]
MANNERS = ["slowly", "quickly", "carefully", "angrily", "happily", "twice", "three times",
           "again", "with both hands", "with the right arm", "with the left arm", ""]


def corpus():
    """Deterministic captions from the lists above (every subject, action, link and manner)."""
    out = []
    for i, s in enumerate(SUBJECTS):
        for j, a in enumerate(ACTIONS):
            b = ACTIONS[(i * 7 + j * 3 + 1) % len(ACTIONS)]
            link = LINKS[(i + j) % len(LINKS)]
            manner = MANNERS[(i * 5 + j) % len(MANNERS)]
            out.append(f"{s} {a}{link} {b} {manner}".strip() + ".")
    return out


def t5_tokenizer():
    """The 32128-id tokenizer described in the module docstring."""
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, processors, trainers
    tok = Tokenizer(models.Unigram())
    tok.pre_tokenizer = pre_tokenizers.Metaspace(replacement="\u2581", prepend_scheme="always")
    tok.decoder = decoders.Metaspace(replacement="\u2581", prepend_scheme="always")
    trainer = trainers.UnigramTrainer(vocab_size=2000, special_tokens=["<pad>", "</s>", "<unk>"],
                                      unk_token="<unk>", shrinking_factor=0.75)
    tok.train_from_iterator(corpus(), trainer)
    tok.post_processor = processors.TemplateProcessing(single="$A </s>", pair="$A </s> $B </s>",
                                                       special_tokens=[("</s>", 1)])
    # The trainer keeps few whole words of so small a corpus; T5's vocabulary has every common
    # English word as one piece: each corpus word becomes a piece `\u2581word` scored by its
    # frequency (log p), unless it already is one.
    j = json.loads(tok.to_str())
    have = {p for p, _ in j["model"]["vocab"]}
    words = {}
    for line in corpus():
        for w in line.replace(",", " ").replace(".", " ").split():
            words[w] = words.get(w, 0) + 1
    total = sum(words.values())
    j["model"]["vocab"] += [["\u2581" + w, math.log(c / total)] for w, c in sorted(words.items())
                            if "\u2581" + w not in have]
    tok = fx.canonical_tokenizer(Tokenizer.from_str(json.dumps(j)), digest=None)
    j = json.loads(tok.to_str())
    vocab = j["model"]["vocab"]
    trained = len(vocab)
    floor = min(s for _, s in vocab[3:]) - 10.0
    pieces = VOCAB - EXTRA_IDS - trained
    # Filler pieces: a private-use character no caption contains, so they never match.
    for n in range(pieces):
        vocab.append([f"\u2581\ue000{n:05d}", round(floor - n * 1e-4, 4)])
    extra = [f"<extra_id_{i}>" for i in reversed(range(EXTRA_IDS))]
    vocab.extend([p, 0.0] for p in extra)
    j["model"]["vocab"] = vocab
    j["normalizer"] = {"type": "Sequence", "normalizers": [
        {"type": "Replace", "pattern": {"Regex": " {2,}"}, "content": " "}]}
    j["pre_tokenizer"] = {"type": "Sequence", "pretokenizers": [
        {"type": "WhitespaceSplit"},
        {"type": "Metaspace", "replacement": "\u2581", "prepend_scheme": "always",
         "split": True}]}
    j["added_tokens"] = [
        {"id": i, "content": c, "single_word": False, "lstrip": False, "rstrip": False,
         "normalized": False, "special": True}
        for i, c in [(0, "<pad>"), (1, "</s>"), (2, "<unk>")]
        + [(VOCAB - EXTRA_IDS + k, p) for k, p in enumerate(extra)]]
    tok = Tokenizer.from_str(json.dumps(j))
    assert tok.get_vocab_size() == VOCAB, tok.get_vocab_size()
    assert tok.token_to_id("<pad>") == 0 and tok.token_to_id("</s>") == 1
    assert tok.token_to_id("<extra_id_0>") == VOCAB - 1
    return tok, trained


def large_init(name, p, gen):
    """sentence-t5-large-sized random weights (see the module docstring)."""
    if "layer_norm" in name:
        p.copy_(1.0 + 0.1 * torch.randn(p.shape, generator=gen))
    elif name == "shared.weight":
        p.copy_(torch.randn(p.shape, generator=gen))
    elif "relative_attention_bias" in name:
        p.copy_(0.5 * torch.randn(p.shape, generator=gen))
    else:
        p.copy_((torch.rand(p.shape, generator=gen) * 2 - 1) / math.sqrt(p.shape[1]))
    p.masked_fill_(p == 0, 1e-3)


def write_t5(folder, seed):
    tok, trained = t5_tokenizer()
    model, dense = fx.t5_encoder(tok, T5_LARGE, TEXT_DIM, seed, large_init)
    d = T5_LARGE["d_model"]
    fx.write_folder(folder, model, dense, tok, binary=False,
                    dense_cfg=dict(fx.DENSE, in_features=d, out_features=TEXT_DIM),
                    pooling=dict(fx.POOLING, word_embedding_dimension=d))
    extra = [f"<extra_id_{i}>" for i in range(EXTRA_IDS)]
    fx.dump(os.path.join(folder, "tokenizer_config.json"),
            {"eos_token": "</s>", "unk_token": "<unk>", "pad_token": "<pad>",
             "extra_ids": EXTRA_IDS, "additional_special_tokens": extra,
             "model_max_length": 512, "tokenizer_class": "T5Tokenizer"})
    fx.dump(os.path.join(folder, "special_tokens_map.json"),
            {"eos_token": "</s>", "unk_token": "<unk>", "pad_token": "<pad>",
             "additional_special_tokens": extra})
    fx.dump(os.path.join(folder, "config_sentence_transformers.json"),
            {"__version__": {"sentence_transformers": "2.2.0", "transformers": "4.7.0",
                             "pytorch": "1.9.0+cu102"}})
    # A sanity check of the scale: a caption's sentence vector is finite and the hidden states
    # neither explode nor collapse.
    from reference import motionlcm
    ids = torch.tensor([tok.encode(fx.PROMPTS[0]).ids])
    with torch.no_grad():
        hidden = model(input_ids=ids, attention_mask=torch.ones_like(ids)).last_hidden_state
        vec = motionlcm.SentenceT5(model, dense)(ids, torch.ones_like(ids))
    assert torch.isfinite(hidden).all() and torch.isfinite(vec).all()
    spread = float(hidden[0].std(0).mean())
    assert spread > 1e-3, spread
    n_t5 = sum(p.numel() for p in model.parameters()) + dense.numel()
    return (f"sentence-t5-large {n_t5 / 1e6:.1f} M values, tokenizer {VOCAB} ids ({trained} "
            f"trained and word pieces); prompt 0 -> {ids.shape[1]} tokens, hidden std over tokens "
            f"{spread:.3f}, max |h| {float(hidden.abs().max()):.3g}")


def control_checkpoint(ckpt, release, seed):
    """`ckpt` plus a full-size random ControlNet and trajectory encoder (module docstring)."""
    from make_latent_fixtures import randomize
    from reference import motionlcm_control as mc
    tokens, channels = LATENT[release]
    v2 = release == "v2"
    d = DEN
    torch.manual_seed(seed)
    cn = mc.ControlNet(d["latent_dim"], tokens, channels, d["text_dim"], d["cond_dim"],
                       d["layers"], d["heads"], d["ff_size"], d["max_len"],
                       "none" if v2 else "relu", v2, 32 if v2 else d["latent_dim"],
                       "silu" if v2 else "none")
    traj = mc.TrajEncoder(d["latent_dim"], tokens, channels, d["layers"], d["heads"],
                          d["ff_size"], d["max_len"], v2)
    gen = torch.Generator().manual_seed(seed)
    randomize(cn, gen)
    randomize(traj, gen)
    state = dict(ckpt["state_dict"])
    state.update({"controlnet." + k: v.clone() for k, v in cn.state_dict().items()})
    state.update({"traj_encoder." + k: v.clone() for k, v in traj.state_dict().items()})
    return {"state_dict": state}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--release", choices=["v1", "v2", "both"], default="both")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--control", action="store_true",
                    help="also write motionlcm_vN_control.ckpt, mean_raw.npy and std_raw.npy")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    os.makedirs(args.out, exist_ok=True)
    releases = ["v1", "v2"] if args.release == "both" else [args.release]
    for r in releases:
        # A release's weights do not depend on which releases are written.
        ckpt = fx.checkpoint(r, DEN, VAE, LATENT[r], args.seed + {"v1": 1, "v2": 2}[r])
        state = ckpt["state_dict"]
        n_den = sum(v.numel() for k, v in state.items() if k.startswith("denoiser."))
        n_vae = sum(v.numel() for k, v in state.items() if k.startswith("vae."))
        torch.save(ckpt, os.path.join(args.out, f"motionlcm_{r}.ckpt"))
        if args.control:
            control = control_checkpoint(ckpt, r, args.seed + {"v1": 21, "v2": 22}[r])
            torch.save(control, os.path.join(args.out, f"motionlcm_{r}_control.ckpt"))
            n = sum(v.numel() for k, v in control["state_dict"].items()
                    if k.startswith(("controlnet.", "traj_encoder.")))
            print(f"{r} control: controlnet.* and traj_encoder.* {n / 1e6:.2f} M values",
                  flush=True)
        print(f"{r}: latent {list(LATENT[r])}, denoiser.* {n_den / 1e6:.2f} M values, vae.* "
              f"{n_vae / 1e6:.2f} M (with the skipped encoder stand-ins)", flush=True)
    t1 = time.perf_counter()
    folder = os.path.join(args.out, "sentence-t5-large")
    if os.path.isdir(folder):
        import shutil
        shutil.rmtree(folder)
    print(write_t5(folder, args.seed + 10), flush=True)
    rng = np.random.default_rng(args.seed)
    np.save(os.path.join(args.out, "mean.npy"), rng.normal(0, 0.5, 263).astype(np.float32))
    np.save(os.path.join(args.out, "std.npy"), rng.uniform(0.05, 1.0, 263).astype(np.float32))
    if args.control:
        # Joint positions in metres: mean within a body's reach, spread 0.05..0.5 m.
        np.save(os.path.join(args.out, "mean_raw.npy"),
                rng.normal(0, 0.3, (22, 3)).astype(np.float32))
        np.save(os.path.join(args.out, "std_raw.npy"),
                rng.uniform(0.05, 0.5, (22, 3)).astype(np.float32))
    t2 = time.perf_counter()
    print(f"wrote {args.out}: checkpoints {t1 - t0:.1f} s, sentence-t5-large {t2 - t1:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
