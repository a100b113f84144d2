#!/usr/bin/env python3
"""Write a random-weight FLAME checkpoint in the official PyTorch-Lightning layout
(docs/official/flame.md#checkpoint-layout).

The file is what tools/convert.py expects from kakaobrain/flame: `state_dict` holds two copies of the
net, `net.*` (raw) and `ema_model.model.*` (EMA, the one sampling uses), each with the LM under
`lm.*` including the int64 `lm.embeddings.position_ids` buffer that transformers 4.19 saved.
The two copies get DIFFERENT values (net = ema + noise) so a converter that took the wrong copy
fails parity.

Presets:
  tiny  C=64, 2 layers, 4 heads, ff 128; LM from --text-model/config.json (the tiny RoBERTa).
  base  FLAME-base: C=768, 8 layers, 8 heads, ff 2048; LM = RoBERTa-base sized (12 x 768, 12 heads,
        3072, vocab 50265, 514 positions), random.
Both: motion_dim 147, max_motion_length 471, max_text_length 20.

Besides the checkpoint it writes a text-model directory for convert.py (--text-model-out, default
`<out without .ckpt>.text/`): config.json of the preset's LM plus the tokenizer files of --text-model.
"""
import argparse
import json
import os
import shutil
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from reference.flame import build_flame  # noqa: E402

ROBERTA_BASE = {
    "architectures": ["RobertaModel"], "model_type": "roberta", "vocab_size": 50265,
    "hidden_size": 768, "num_hidden_layers": 12, "num_attention_heads": 12,
    "intermediate_size": 3072, "hidden_act": "gelu", "hidden_dropout_prob": 0.1,
    "attention_probs_dropout_prob": 0.1, "max_position_embeddings": 514, "type_vocab_size": 1,
    "initializer_range": 0.02, "layer_norm_eps": 1e-05, "pad_token_id": 1, "bos_token_id": 0,
    "eos_token_id": 2, "position_embedding_type": "absolute",
}

PRESETS = {
    "tiny": {"model_channels": 64, "num_layers": 2, "num_heads": 4, "dim_feedforward": 128},
    "base": {"model_channels": 768, "num_layers": 8, "num_heads": 8, "dim_feedforward": 2048},
}
COMMON = {"motion_dim": 147, "max_motion_length": 471, "max_text_length": 20}
TOKENIZER_FILES = ["tokenizer.json", "vocab.json", "merges.txt", "tokenizer_config.json",
                   "special_tokens_map.json"]


@torch.no_grad()
def randomize_(model, generator):
    """Re-draw every parameter so that no term is trivially zero or one (biases and LayerNorm
    affine parameters included), with scales that keep activations of order one."""
    for name, p in model.named_parameters():
        if p.dim() == 1:
            is_norm_weight = name.endswith("weight")  # LayerNorm weights are the only 1-D weights
            base = 1.0 if is_norm_weight else 0.0
            p.copy_(base + 0.1 * torch.randn(p.shape, generator=generator))
        elif name.startswith("lm."):
            # HF's default std 0.02 makes attention uniform; use ~1/sqrt(fan_in) for Linear weights.
            std = 0.5 if "embeddings" in name else p.shape[1] ** -0.5
            p.copy_(std * torch.randn(p.shape, generator=generator))
        elif name == "motion_length_emb.weight":
            p.copy_(torch.randn(p.shape, generator=generator))
        else:
            # Uniform like PyTorch's Linear default: std = 1/sqrt(3 fan_in).
            bound = p.shape[1] ** -0.5
            p.copy_((torch.rand(p.shape, generator=generator) * 2 - 1) * bound)


def text_config_for(preset, text_model_dir):
    if preset == "base":
        return dict(ROBERTA_BASE)
    with open(os.path.join(text_model_dir, "config.json")) as f:
        return json.load(f)


def build_model(preset, text_model_dir, seed=0):
    """Random FLAME (EMA weights) for `preset`; returns (model, text_config)."""
    torch.manual_seed(seed)
    text_config = text_config_for(preset, text_model_dir)
    model = build_flame(text_model_dir, text_config=text_config, **PRESETS[preset], **COMMON)
    randomize_(model, torch.Generator().manual_seed(seed))
    model.eval()
    return model, text_config


def lightning_checkpoint(ema_state, text_config, seed=0, net_noise=0.05):
    """Official-layout checkpoint dict: net.* = ema + noise, ema_model.model.* = ema."""
    gen = torch.Generator().manual_seed(seed + 1)
    position_ids = torch.arange(text_config["max_position_embeddings"], dtype=torch.long)[None]
    state = {}
    for prefix, noise in (("net.", net_noise), ("ema_model.model.", 0.0)):
        for k, v in ema_state.items():
            v = v.detach().clone()
            if noise and v.is_floating_point():
                v = v + noise * torch.randn(v.shape, generator=gen)
            state[prefix + k] = v
        state[prefix + "lm.embeddings.position_ids"] = position_ids.clone()
    return {
        "epoch": 0,
        "global_step": 0,
        "pytorch-lightning_version": "1.8.6",
        "state_dict": state,
        "loops": {},
        "callbacks": {},
        "optimizer_states": [],
        "lr_schedulers": [],
        # The real file pickles the net object here; a plain dict keeps this loadable anywhere.
        "hyper_parameters": {"note": "random-weight checkpoint from tools/make_random_checkpoint.py"},
    }


def write_text_model_dir(out_dir, text_config, tokenizer_dir):
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "config.json"), "w") as f:
        json.dump(text_config, f, indent=2)
        f.write("\n")
    for name in TOKENIZER_FILES:
        src = os.path.join(tokenizer_dir, name)
        if os.path.exists(src):
            shutil.copyfile(src, os.path.join(out_dir, name))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", choices=sorted(PRESETS), required=True)
    ap.add_argument("--out", required=True, help="output .ckpt path")
    ap.add_argument("--text-model", required=True,
                    help="dir with tokenizer.json (and, for --preset tiny, the LM config.json)")
    ap.add_argument("--text-model-out", default=None,
                    help="where to write config.json + tokenizer for convert.py "
                         "(default: <out without .ckpt>.text)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    model, text_config = build_model(args.preset, args.text_model, args.seed)
    t1 = time.perf_counter()
    ckpt = lightning_checkpoint(model.state_dict(), text_config, args.seed)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    torch.save(ckpt, args.out)
    t2 = time.perf_counter()
    text_out = args.text_model_out or (os.path.splitext(args.out)[0] + ".text")
    write_text_model_dir(text_out, text_config, args.text_model)
    n_params = sum(p.numel() for p in model.parameters())
    print(f"preset {args.preset}: {n_params / 1e6:.1f} M parameters per copy; "
          f"init {t1 - t0:.1f} s, save {t2 - t1:.1f} s -> {args.out} "
          f"({os.path.getsize(args.out) / 2**20:.1f} MiB); text model dir {text_out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
