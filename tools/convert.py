#!/usr/bin/env python3
"""Convert official checkpoints to the libflame model file (format v1, a .safetensors file).

  python tools/convert.py flame --ckpt FILE.ckpt --text-model DIR --out M.safetensors \
      [--heads 8] [--max-text-length 20] [--diffusion-steps 1000] [--schedule cosine] \
      [--guidance 8] [--dtype f32|f16|bf16]

flame: kakaobrain/flame PyTorch-Lightning checkpoint. Uses the EMA copy (`ema_model.model.*`), the
one FLAME samples with; the RoBERTa weights come from the checkpoint's `lm.*` (FLAME's pooler is a
random init saved only there), or from DIR/model.safetensors when the checkpoint has none.
DIR holds the text encoder's config.json and tokenizer.json.

File layout: metadata {"format": "libflame", "flame.config": JSON, "flame.tokenizer":
tokenizer.json text}; denoiser tensors under their official names (no prefix); text encoder tensors
under `text.` + the Hugging Face BertModel/RobertaModel names.
Other architectures (mdm, motionfm) are meant to be added as further subcommands.
"""
import argparse
import json
import os
import pickle
import sys
import time
import types

import torch

FORMAT_VERSION = 1
EMA_PREFIX = "ema_model.model."
RAW_PREFIX = "net."
DTYPES = {"f32": torch.float32, "f16": torch.float16, "bf16": torch.bfloat16}
# Buffers and heads that are not part of the text encoder the runtime runs.
TEXT_DROP_SUFFIXES = ("embeddings.position_ids", "embeddings.token_type_ids")
TEXT_DROP_PREFIXES = ("lm_head.", "cls.")


class ConvertError(Exception):
    pass


def warn(msg):
    print(f"warning: {msg}", file=sys.stderr)


# -- reading ------------------------------------------------------------------------------------

class _Stub:
    """Stand-in for a pickled object whose class cannot be imported (e.g. FLAME's own net class
    pickled into Lightning's `hyper_parameters`); keeps whatever state it is given."""

    def __init__(self, *args, **kwargs):
        self._args = args

    def __setstate__(self, state):
        self.__dict__["_state"] = state


_SAFE_MODULES = ("torch", "collections", "builtins", "numpy", "_codecs", "copyreg")


class _StubbingUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if module.split(".")[0] in _SAFE_MODULES:
            return super().find_class(module, name)
        return type(name, (_Stub,), {"__module__": "stub." + module})


_stubbing_pickle = types.SimpleNamespace(
    __name__="stubbing_pickle", Unpickler=_StubbingUnpickler,
    load=lambda f, **kw: _StubbingUnpickler(f, **kw).load())


def load_state_dict(path):
    if not os.path.isfile(path):
        raise ConvertError(f"{path}: no such checkpoint file")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001 - any unpickling failure gets the stubbing retry
        # The official checkpoint pickles FLAME's net object (and config objects) in
        # hyper_parameters; without FLAME's source those classes cannot be imported. Only the
        # tensors matter here, so replace every non-torch class by an inert stub.
        warn(f"{path}: plain unpickling failed ({type(e).__name__}: {e}); retrying with "
             f"non-torch classes stubbed out")
        ckpt = torch.load(path, map_location="cpu", weights_only=False,
                          pickle_module=_stubbing_pickle)
    if isinstance(ckpt, dict) and isinstance(ckpt.get("state_dict"), dict):
        return ckpt["state_dict"]
    if isinstance(ckpt, dict) and ckpt and all(torch.is_tensor(v) for v in ckpt.values()):
        return ckpt  # a bare state dict
    raise ConvertError(f"{path}: no 'state_dict' in checkpoint (top-level keys: "
                       f"{sorted(ckpt)[:10] if isinstance(ckpt, dict) else type(ckpt).__name__})")


def select_net(state, path):
    """The EMA net (sampling uses it, REFERENCE 1.6); the raw net only as a warned fallback."""
    for prefix in (EMA_PREFIX, RAW_PREFIX):
        net = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
        if net:
            if prefix == RAW_PREFIX:
                warn(f"{path}: no EMA weights ('{EMA_PREFIX}*'); falling back to the raw "
                     f"'{RAW_PREFIX}*' copy. FLAME samples with the EMA copy, so outputs will "
                     f"differ from the official ones.")
            return net
    prefixes = sorted({k.split(".", 1)[0] + "." for k in state})
    raise ConvertError(f"{path}: neither '{EMA_PREFIX}*' (EMA) nor '{RAW_PREFIX}*' tensors found; "
                       f"top-level prefixes present: {prefixes}")


def clean_text_state(state, source):
    out = {}
    for k, v in state.items():
        if k.endswith(TEXT_DROP_SUFFIXES) or k.startswith(TEXT_DROP_PREFIXES):
            continue
        out[k] = v
    if not out:
        raise ConvertError(f"{source}: no text encoder tensors")
    return out


def text_weights_from_dir(text_dir, kind):
    path = os.path.join(text_dir, "model.safetensors")
    if not os.path.exists(path):
        raise ConvertError(f"checkpoint has no 'lm.*' tensors and {path} does not exist")
    from safetensors.torch import load_file
    state = load_file(path)
    for prefix in (f"{kind}.", "roberta.", "bert."):
        if any(k.startswith(prefix) for k in state):
            state = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
            break
    return clean_text_state(state, path)


def read_text_config(text_dir, max_length):
    path = os.path.join(text_dir, "config.json")
    if not os.path.exists(path):
        raise ConvertError(f"{path} not found (need the text encoder's Hugging Face config.json)")
    with open(path) as f:
        hf = json.load(f)
    kind = hf.get("model_type")
    if kind not in ("roberta", "bert"):
        raise ConvertError(f"{path}: model_type {kind!r} is not supported (want roberta or bert)")
    try:
        cfg = {
            "kind": kind,
            "vocab_size": hf["vocab_size"],
            "hidden_size": hf["hidden_size"],
            "num_layers": hf["num_hidden_layers"],
            "num_heads": hf["num_attention_heads"],
            "intermediate_size": hf["intermediate_size"],
            "max_position_embeddings": hf["max_position_embeddings"],
            "type_vocab_size": hf.get("type_vocab_size", 2),
            "layer_norm_eps": float(hf.get("layer_norm_eps", 1e-12)),
            "pad_token_id": hf.get("pad_token_id", 1 if kind == "roberta" else 0),
            "max_length": max_length,
            "hidden_act": hf.get("hidden_act", "gelu"),
        }
    except KeyError as e:
        raise ConvertError(f"{path}: missing key {e}") from None
    if cfg["hidden_act"] != "gelu":
        warn(f"{path}: hidden_act {cfg['hidden_act']!r} (FLAME's RoBERTa uses exact 'gelu')")
    if cfg["hidden_size"] % cfg["num_heads"]:
        raise ConvertError(f"{path}: hidden_size {cfg['hidden_size']} not divisible by "
                           f"num_attention_heads {cfg['num_heads']}")
    # RoBERTa positions start at pad_token_id + 1, so max_length real tokens need max_length + 2 rows.
    needed = max_length + (cfg["pad_token_id"] + 1 if kind == "roberta" else 0)
    if needed > cfg["max_position_embeddings"]:
        raise ConvertError(f"--max-text-length {max_length} needs {needed} position embeddings, "
                           f"the text encoder has {cfg['max_position_embeddings']}")
    return cfg


def read_tokenizer_json(text_dir, kind):
    path = os.path.join(text_dir, "tokenizer.json")
    if os.path.exists(path):
        with open(path) as f:
            text = f.read()
        json.loads(text)  # must parse
        return text
    vocab, merges = os.path.join(text_dir, "vocab.json"), os.path.join(text_dir, "merges.txt")
    if kind == "roberta" and os.path.exists(vocab) and os.path.exists(merges):
        from transformers import RobertaTokenizerFast
        warn(f"{path} not found; building it from vocab.json + merges.txt")
        tok = RobertaTokenizerFast(vocab_file=vocab, merges_file=merges)
        return tok.backend_tokenizer.to_str()
    raise ConvertError(f"{path} not found (the libflame file embeds the tokenizer)")


# -- shapes -------------------------------------------------------------------------------------

def count_layers(names, prefix):
    idx = set()
    for k in names:
        if k.startswith(prefix):
            head = k[len(prefix):].split(".", 1)[0]
            if head.isdigit():
                idx.add(int(head))
    if idx and idx != set(range(len(idx))):
        raise ConvertError(f"non-contiguous layer indices under '{prefix}': {sorted(idx)}")
    return len(idx)


def require(state, name, what="checkpoint"):
    if name not in state:
        raise ConvertError(f"{what}: missing tensor '{name}'")
    return state[name]


def infer_denoiser(net, heads):
    w_in = require(net, "input_projection.weight")
    if w_in.dim() != 2:
        raise ConvertError(f"input_projection.weight has shape {tuple(w_in.shape)}, want 2-D")
    channels, motion_dim = w_in.shape
    max_motion_length = require(net, "motion_length_emb.weight").shape[0]
    num_layers = count_layers(net, "tf_decoder.layers.")
    if num_layers == 0:
        raise ConvertError("checkpoint: no 'tf_decoder.layers.N.*' tensors")
    ff = require(net, "tf_decoder.layers.0.linear1.weight").shape[0]
    if channels % heads:
        raise ConvertError(f"model_channels {channels} is not divisible by --heads {heads}")
    return {
        "motion_dim": int(motion_dim), "model_channels": int(channels),
        "num_layers": int(num_layers), "num_heads": int(heads), "dim_feedforward": int(ff),
        "max_motion_length": int(max_motion_length), "activation": "relu",
        "layer_norm_eps": 1e-5,
    }


def denoiser_shapes(d, text_hidden):
    c, m, f = d["model_channels"], d["motion_dim"], d["dim_feedforward"]
    shapes = {
        "motion_length_emb.weight": (d["max_motion_length"], c),
        "input_projection.weight": (c, m), "input_projection.bias": (c,),
        "text_pooler_proj.weight": (c, text_hidden), "text_pooler_proj.bias": (c,),
        "text_h_proj.weight": (c, text_hidden), "text_h_proj.bias": (c,),
        "last_projection.weight": (2 * m, c), "last_projection.bias": (2 * m,),
    }
    for n in range(d["num_layers"]):
        p = f"tf_decoder.layers.{n}."
        for attn in ("self_attn", "multihead_attn"):
            shapes[p + attn + ".in_proj_weight"] = (3 * c, c)
            shapes[p + attn + ".in_proj_bias"] = (3 * c,)
            shapes[p + attn + ".out_proj.weight"] = (c, c)
            shapes[p + attn + ".out_proj.bias"] = (c,)
        shapes[p + "linear1.weight"] = (f, c)
        shapes[p + "linear1.bias"] = (f,)
        shapes[p + "linear2.weight"] = (c, f)
        shapes[p + "linear2.bias"] = (c,)
        for norm in ("norm1", "norm2", "norm3"):
            shapes[p + norm + ".weight"] = (c,)
            shapes[p + norm + ".bias"] = (c,)
    return shapes


def text_shapes(t):
    h, i = t["hidden_size"], t["intermediate_size"]
    shapes = {
        "embeddings.word_embeddings.weight": (t["vocab_size"], h),
        "embeddings.position_embeddings.weight": (t["max_position_embeddings"], h),
        "embeddings.token_type_embeddings.weight": (t["type_vocab_size"], h),
        "embeddings.LayerNorm.weight": (h,), "embeddings.LayerNorm.bias": (h,),
        "pooler.dense.weight": (h, h), "pooler.dense.bias": (h,),
    }
    for n in range(t["num_layers"]):
        p = f"encoder.layer.{n}."
        for lin in ("attention.self.query", "attention.self.key", "attention.self.value",
                    "attention.output.dense"):
            shapes[p + lin + ".weight"] = (h, h)
            shapes[p + lin + ".bias"] = (h,)
        shapes[p + "intermediate.dense.weight"] = (i, h)
        shapes[p + "intermediate.dense.bias"] = (i,)
        shapes[p + "output.dense.weight"] = (h, i)
        shapes[p + "output.dense.bias"] = (h,)
        for ln in ("attention.output.LayerNorm", "output.LayerNorm"):
            shapes[p + ln + ".weight"] = (h,)
            shapes[p + ln + ".bias"] = (h,)
    return shapes


def check_shapes(state, shapes, what, hint=""):
    for name, shape in shapes.items():
        t = require(state, name, what)
        if tuple(t.shape) != tuple(shape):
            raise ConvertError(f"{what}: tensor '{name}' has shape {tuple(t.shape)}, expected "
                               f"{tuple(shape)}{hint}")
        if not t.is_floating_point():
            raise ConvertError(f"{what}: tensor '{name}' has dtype {t.dtype}, expected floating")
    extra = sorted(set(state) - set(shapes))
    if extra:
        warn(f"{what}: ignoring {len(extra)} unexpected tensor(s): {extra[:8]}"
             f"{' ...' if len(extra) > 8 else ''}")


def cast(t, dtype, name):
    t = t.detach().to(torch.float32)
    if not torch.isfinite(t).all():
        raise ConvertError(f"tensor '{name}' contains NaN or Inf")
    if dtype == torch.float16 and t.abs().max() > torch.finfo(torch.float16).max:
        raise ConvertError(f"tensor '{name}' overflows float16 (max |x| = {t.abs().max():.4g})")
    return t.to(dtype).contiguous()


# -- flame --------------------------------------------------------------------------------------

def convert_flame(args):
    t0 = time.perf_counter()
    state = load_state_dict(args.ckpt)
    t_load = time.perf_counter() - t0
    net = select_net(state, args.ckpt)
    text_cfg = read_text_config(args.text_model, args.max_text_length)
    tokenizer = read_tokenizer_json(args.text_model, text_cfg["kind"])

    lm = {k[len("lm."):]: v for k, v in net.items() if k.startswith("lm.")}
    den = {k: v for k, v in net.items() if not k.startswith("lm.")}
    if lm:
        lm = clean_text_state(lm, f"{args.ckpt} (lm.*)")
    else:
        warn(f"{args.ckpt}: no 'lm.*' tensors; taking the text encoder from "
             f"{args.text_model}/model.safetensors (FLAME's trained projections expect the "
             f"checkpoint's own pooler)")
        lm = text_weights_from_dir(args.text_model, text_cfg["kind"])

    denoiser_cfg = infer_denoiser(den, args.heads)
    check_shapes(den, denoiser_shapes(denoiser_cfg, text_cfg["hidden_size"]), "checkpoint",
                 hint=f" (text hidden size {text_cfg['hidden_size']} from config.json)")
    check_shapes(lm, text_shapes(text_cfg), "text encoder (lm.*)",
                 hint=f" (from {args.text_model}/config.json)")

    config = {
        "format_version": FORMAT_VERSION,
        "architecture": "flame",
        "denoiser": denoiser_cfg,
        "text_encoder": text_cfg,
        "motion": {"format": "smpl24_6d", "fps": 20.0},
        "diffusion": {"num_timesteps": args.diffusion_steps, "schedule": args.schedule,
                      "parameterization": "epsilon", "variance": "learned_range",
                      "clip_denoised": True, "uncond": "empty_prompt"},
        "defaults": {"sampler": "ddpm", "steps": args.diffusion_steps,
                     "guidance": float(args.guidance), "eta": 0.0, "frames": args.frames},
    }
    if args.frames > denoiser_cfg["max_motion_length"] - 1:
        raise ConvertError(f"--frames {args.frames} exceeds the motion-length table "
                           f"({denoiser_cfg['max_motion_length']} rows)")

    dtype = DTYPES[args.dtype]
    names = denoiser_shapes(denoiser_cfg, text_cfg["hidden_size"])
    tensors = {k: cast(den[k], dtype, k) for k in names}
    for k in text_shapes(text_cfg):
        tensors["text." + k] = cast(lm[k], dtype, "lm." + k)

    metadata = {"format": "libflame", "flame.config": json.dumps(config),
                "flame.tokenizer": tokenizer}
    from safetensors.torch import save_file
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    save_file(tensors, args.out, metadata=metadata)
    n = sum(t.numel() for t in tensors.values())
    print(f"wrote {args.out}: {len(tensors)} tensors, {n / 1e6:.2f} M values ({args.dtype}); "
          f"C={denoiser_cfg['model_channels']} layers={denoiser_cfg['num_layers']} "
          f"heads={args.heads} ff={denoiser_cfg['dim_feedforward']} text={text_cfg['kind']} "
          f"{text_cfg['num_layers']}x{text_cfg['hidden_size']}; "
          f"load {t_load:.1f} s, total {time.perf_counter() - t0:.1f} s")
    return 0


def build_parser():
    ap = argparse.ArgumentParser(prog="convert.py", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="arch", required=True, metavar="ARCH")
    p = sub.add_parser("flame", help="kakaobrain/flame Lightning checkpoint")
    p.add_argument("--ckpt", required=True, help="official FLAME .ckpt")
    p.add_argument("--text-model", required=True,
                   help="dir with the text encoder's config.json and tokenizer.json "
                        "(model.safetensors only needed when the checkpoint has no lm.*)")
    p.add_argument("--out", required=True, help="output .safetensors")
    p.add_argument("--heads", type=int, default=8, help="decoder attention heads (not in shapes)")
    p.add_argument("--max-text-length", type=int, default=20,
                   help="FLAME max_text_length (tokens incl. <s> and </s>)")
    p.add_argument("--diffusion-steps", type=int, default=1000)
    p.add_argument("--schedule", choices=["cosine", "linear"], default="cosine")
    p.add_argument("--guidance", type=float, default=8.0)
    p.add_argument("--frames", type=int, default=200, help="default motion length")
    p.add_argument("--dtype", choices=sorted(DTYPES), default="f32")
    p.set_defaults(func=convert_flame)
    return ap


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ConvertError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
