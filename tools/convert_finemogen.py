"""`convert.py finemogen`: a FineMoGen checkpoint (mingyuan-zhang/FineMoGen, HumanML3D) to the
libflame file.

  python tools/convert.py finemogen --ckpt latest.pth [--clip HF_DIR | --clip ViT-B-32.pt] \
      [--tokenizer tokenizer.json] --mean mean.npy --std std.npy --out M.safetensors \
      [--text-heads 4] [--clip-heads N] [--topk 2] [--guidance 6.5] [--respacing 15,15,8,6,6] \
      [--frames 196] [--dtype f32|f16|bf16]

Input: the mmcv checkpoint (`{'state_dict': {'model.…': tensor}, 'meta': …}`; a bare state dict
is accepted too). Every tensor below must be present with its shape; any other tensor is an
error naming it. Recognised and not stored: `model.…ca_block.key_motion` (a parameter the
forward never uses; its shape is checked), `model.…_moe.model._num_global_experts` (checked to
equal num_experts) and `model.clip.*` (the OpenAI CLIP; its text tower goes to `text.*`, the
vision tower, `logit_scale` and the ints `input_resolution`, `context_length`, `vocab_size` are
skipped). Every size is read from the shapes and written to the configuration; the head counts
(`--text-heads`, released 4; `--clip-heads` for OpenAI weights, default width / 64) and top-k
(`--topk`, released 2) are not in any shape.

CLIP: the checkpoint's `model.clip.*` when present (OpenAI names, mapped to the Hugging Face
CLIPTextModelWithProjection names: in_proj split into q/k/v, c_fc/c_proj -> fc1/fc2,
ln_1/ln_2 -> layer_norm1/2, ln_final -> final_layer_norm, text_projection transposed), else
--clip: a Hugging Face CLIP folder (config.json, model.safetensors, tokenizer.json; as
`convert.py mdm`) or an OpenAI `ViT-B-32.pt` (TorchScript archive or state dict). The
tokenizer.json comes from --tokenizer, else from the --clip folder. mean/std (263 values) are
the HumanML3D statistics FineMoGen normalises with (`motion.mean`, `motion.std`, always f32).

## File schema, `"architecture": "finemogen"`

P = part_dim, D = 8P (7 body parts + the whole body), E = time_embed_dim, W = clip_width,
M = text_latent_dim, F = text_ff_size, H = ffn_dim, X = num_experts, G = gate_dim,
U = text_expert_hidden, V = motion_expert_hidden, S = max_seq_len, N = max_text_len,
n_part = 24, 36, 48, 48, 48, 48, 11, 263 for head, stem, larm, rarm, lleg, rleg, root, body.
  denoiser.text_pre_proj.{weight [M, W], bias [M]}
  denoiser.textTransEncoder.layers.{i}.self_attn.{in_proj_weight [3M, M], in_proj_bias [3M]}
  denoiser.textTransEncoder.layers.{i}.self_attn.out_proj.{weight [M, M], bias [M]}
  denoiser.textTransEncoder.layers.{i}.linear1.{weight [F, M], bias [F]}
  denoiser.textTransEncoder.layers.{i}.linear2.{weight [M, F], bias [M]}
  denoiser.textTransEncoder.layers.{i}.norm{1,2}.{weight, bias} [M]
  denoiser.text_ln.{weight, bias} [M]
  denoiser.time_embed.0.{weight [E, D], bias [E]}, denoiser.time_embed.2.{weight [E, E], bias}
  denoiser.joint_embed.{part}_embed.{weight [P, n_part], bias [P]}
  denoiser.out.{part}_out.{weight [n_part, P], bias [n_part]}
  denoiser.temporal_decoder_blocks.{l}.ca_block.   (SAMI)
      norm.{weight, bias} [P], text_norm.{weight, bias} [M], sigma [1], t_sigma [1],
      body_weight [8, 8],
      text_moe.embedding [1, N, 1, M], text_moe.proj.{weight [2P, M], bias [2P]},
      text_moe.model.gates.0.{temperature [1], sim_matrix [G, X]},
      text_moe.model.gates.0.cosine_projector.{weight [G, M], bias [G]},
      text_moe.model.experts.{batched_fc1_w [X, U, M], batched_fc1_bias [X, U],
                              batched_fc2_w [X, U, M], batched_fc2_bias [X, M]},
      motion_moe.embedding [1, S, 8, P], motion_moe.proj.{weight [3P, P], bias [3P]},
      motion_moe.model.gates.0.{temperature [1], sim_matrix [G, X]},
      motion_moe.model.gates.0.cosine_projector.{weight [G, P], bias [G]},
      motion_moe.model.experts.{batched_fc1_w [X, V, P], batched_fc1_bias [X, V],
                                batched_fc2_w [X, V, P], batched_fc2_bias [X, P]},
      template_{s,v,a,j}.0.{weight [H, P], bias [H]},
      template_{s,v,a,j}.2.{weight [P, H], bias [P]},
      template_t.0.{weight [H, P], bias [H]}, template_t.2.{weight [1, H], bias [1]},
      proj_out.emb_layers.1.{weight [2D, E], bias [2D]}, proj_out.norm.{weight, bias} [D],
      proj_out.out_layers.2.{weight [D, D], bias [D]}
  denoiser.temporal_decoder_blocks.{l}.ffn.   (SFFN)
      linear1_list.{0..7}.{weight [H, P], bias [H]}, linear2_list.{0..7}.{weight [P, H], bias [P]},
      proj_out.* as in SAMI
  text.*  (HF CLIPTextModelWithProjection: text.text_model.…, text.text_projection.weight)
  motion.mean [263], motion.std [263]
(batched_fc2_w is stored [hidden, out], as tutel keeps it: expert out = GELU(x W1ᵀ + b1) W2 + b2.)

Configuration (`flame.config`):
  {"format_version": 1, "architecture": "finemogen",
   "denoiser": {"input_feats": 263, "dataset": "human_ml3d", "part_dim", "num_layers",
                "time_embed_dim", "max_seq_len", "clip_width", "text_latent_dim", "text_layers",
                "text_heads", "text_ff_size", "max_text_len", "ffn_dim", "num_experts", "topk",
                "capacity_factor": 1.5, "gate_dim", "text_expert_hidden",
                "motion_expert_hidden", "layer_norm_eps": 1e-5},
   "text_encoder": {"kind": "clip", ... as convert.py mdm, "max_length": 77},
   "motion": {"format": "humanml263", "fps": 20.0},
   "diffusion": {"num_timesteps": 1000, "schedule": "linear", "parameterization": "x0",
                 "variance": "fixed_large", "clip_denoised": false, "uncond": "null_text",
                 "spacing": "respace"},
   "defaults": {"sampler": "ddim", "steps": 50, "respacing": "15,15,8,6,6", "guidance": 6.5,
                "eta": 0.0, "frames": 196}}
The KIT-ML model (251 features) is refused: libflame has no KIT skeleton.
"""
import json
import os
import time

import torch

from convert import (DTYPES, FORMAT_VERSION, ConvertError, load_state_dict, read_clip,
                     read_stats, warn)
from convert_latent import indices, shape_of, take, write

PARTS = ("head", "stem", "larm", "rarm", "lleg", "rleg", "root", "body")
HML_PART_SIZES = (24, 36, 48, 48, 48, 48, 11, 263)
CAPACITY_FACTOR = 1.5  # hard-coded in FineMoGen's MOE wrapper
CLIP_SKIPPED = ("visual.",)
CLIP_SKIPPED_NAMES = ("logit_scale", "input_resolution", "context_length", "vocab_size")


# -- CLIP: OpenAI names <-> Hugging Face names ----------------------------------------------------

def openai_clip_text(state, heads, what, prefix=""):
    """OpenAI CLIP state dict (names relative to the CLIP module) -> (text_encoder config,
    {HF CLIPTextModelWithProjection name: tensor}). The vision tower is skipped."""
    known = {k for k in state if k.startswith(CLIP_SKIPPED) or k in CLIP_SKIPPED_NAMES}
    text = {k: v for k, v in state.items() if k not in known}
    vocab, width = shape_of(text, "token_embedding.weight", what, 2)
    context = shape_of(text, "positional_embedding", what, 2)[0]
    layers = indices(text, "transformer.resblocks.")
    inter = shape_of(text, "transformer.resblocks.0.mlp.c_fc.weight", what, 2)[0] \
        if layers else 4 * width
    proj = shape_of(text, "text_projection", what, 2)[1]
    heads = heads or width // 64
    if layers == 0 or heads < 1 or width % heads:
        raise ConvertError(f"{what}: CLIP width {width}, {layers} layers, --clip-heads {heads}: "
                           f"need at least one layer and heads dividing the width")
    shapes = {"token_embedding.weight": (vocab, width), "positional_embedding": (context, width),
              "ln_final.weight": (width,), "ln_final.bias": (width,),
              "text_projection": (width, proj)}
    for n in range(layers):
        p = f"transformer.resblocks.{n}."
        shapes.update({p + "attn.in_proj_weight": (3 * width, width),
                       p + "attn.in_proj_bias": (3 * width,),
                       p + "attn.out_proj.weight": (width, width),
                       p + "attn.out_proj.bias": (width,),
                       p + "mlp.c_fc.weight": (inter, width), p + "mlp.c_fc.bias": (inter,),
                       p + "mlp.c_proj.weight": (width, inter), p + "mlp.c_proj.bias": (width,)})
        for ln in ("ln_1", "ln_2"):
            shapes[p + ln + ".weight"], shapes[p + ln + ".bias"] = (width,), (width,)
    text = take(text, shapes, what, prefix)
    out = {"text_model.embeddings.token_embedding.weight": text["token_embedding.weight"],
           "text_model.embeddings.position_embedding.weight": text["positional_embedding"],
           "text_model.final_layer_norm.weight": text["ln_final.weight"],
           "text_model.final_layer_norm.bias": text["ln_final.bias"],
           "text_projection.weight": text["text_projection"].t().contiguous()}
    for n in range(layers):
        p, q = f"transformer.resblocks.{n}.", f"text_model.encoder.layers.{n}."
        w, b = text[p + "attn.in_proj_weight"], text[p + "attn.in_proj_bias"]
        for i, name in enumerate(("q_proj", "k_proj", "v_proj")):
            out[q + f"self_attn.{name}.weight"] = w[i * width:(i + 1) * width].contiguous()
            out[q + f"self_attn.{name}.bias"] = b[i * width:(i + 1) * width].contiguous()
        for src, dst in (("attn.out_proj", "self_attn.out_proj"), ("mlp.c_fc", "mlp.fc1"),
                         ("mlp.c_proj", "mlp.fc2"), ("ln_1", "layer_norm1"),
                         ("ln_2", "layer_norm2")):
            out[q + dst + ".weight"] = text[p + src + ".weight"]
            out[q + dst + ".bias"] = text[p + src + ".bias"]
    cfg = {"kind": "clip", "vocab_size": vocab, "width": width, "layers": layers,
           "heads": heads, "context_length": context, "projection_dim": proj,
           "layer_norm_eps": 1e-5, "max_length": 77, "intermediate_size": inter}
    if context != 77:
        warn(f"{what}: CLIP context length {context} (OpenAI CLIP: 77)")
    return cfg, out


def hf_to_openai_clip(hf):
    """The inverse of openai_clip_text's name map (for writing official-layout test checkpoints)."""
    out = {"token_embedding.weight": hf["text_model.embeddings.token_embedding.weight"],
           "positional_embedding": hf["text_model.embeddings.position_embedding.weight"],
           "ln_final.weight": hf["text_model.final_layer_norm.weight"],
           "ln_final.bias": hf["text_model.final_layer_norm.bias"],
           "text_projection": hf["text_projection.weight"].t().contiguous()}
    layers = indices(hf, "text_model.encoder.layers.")
    for n in range(layers):
        p, q = f"transformer.resblocks.{n}.", f"text_model.encoder.layers.{n}."
        out[p + "attn.in_proj_weight"] = torch.cat(
            [hf[q + f"self_attn.{s}.weight"] for s in ("q_proj", "k_proj", "v_proj")])
        out[p + "attn.in_proj_bias"] = torch.cat(
            [hf[q + f"self_attn.{s}.bias"] for s in ("q_proj", "k_proj", "v_proj")])
        for dst, src in (("attn.out_proj", "self_attn.out_proj"), ("mlp.c_fc", "mlp.fc1"),
                         ("mlp.c_proj", "mlp.fc2"), ("ln_1", "layer_norm1"),
                         ("ln_2", "layer_norm2")):
            out[p + dst + ".weight"] = hf[q + src + ".weight"]
            out[p + dst + ".bias"] = hf[q + src + ".bias"]
    return out


def load_openai_file(path):
    """OpenAI CLIP weights: a TorchScript archive (ViT-B-32.pt as `clip` downloads it; torch.load
    hands those to torch.jit.load) or a pickled state dict."""
    if not os.path.isfile(path):
        raise ConvertError(f"{path}: no such CLIP file")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001 - report any unreadable file the same way
        raise ConvertError(f"{path}: cannot read ({type(e).__name__}: {e})") from None
    if hasattr(obj, "state_dict") and not isinstance(obj, dict):
        obj = obj.state_dict()
    elif isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict) or "token_embedding.weight" not in obj:
        raise ConvertError(f"{path}: not an OpenAI CLIP checkpoint (no token_embedding.weight)")
    return {k: v for k, v in obj.items() if torch.is_tensor(v)}


def read_tokenizer(path):
    if not os.path.isfile(path):
        raise ConvertError(f"{path}: no such tokenizer.json")
    with open(path) as f:
        text = f.read()
    json.loads(text)
    return text


def text_tower(args, clip_state):
    """(text_encoder config, HF tensors, tokenizer.json text)."""
    if clip_state:
        what = f"{args.ckpt} (model.clip.*)"
        cfg, tensors = openai_clip_text(clip_state, args.clip_heads, what, "model.clip.")
        tokenizer = None
        if args.clip and os.path.isdir(args.clip):
            warn(f"the checkpoint holds model.clip.*; {args.clip} only supplies tokenizer.json")
            tokenizer = read_tokenizer(os.path.join(args.clip, "tokenizer.json"))
    elif args.clip is None:
        raise ConvertError(f"{args.ckpt} has no model.clip.* tensors: give --clip (a Hugging "
                           f"Face CLIP folder or an OpenAI ViT-B-32.pt)")
    elif os.path.isdir(args.clip):
        cfg, tensors, tokenizer = read_clip(args.clip, 77)
    else:
        cfg, tensors = openai_clip_text(load_openai_file(args.clip), args.clip_heads, args.clip)
        tokenizer = None
    if args.tokenizer:
        tokenizer = read_tokenizer(args.tokenizer)
    if tokenizer is None:
        raise ConvertError("no tokenizer.json: give --tokenizer (or --clip with a Hugging Face "
                           "folder holding tokenizer.json)")
    return cfg, tensors, tokenizer


# -- the denoiser ----------------------------------------------------------------------------------

def linear(shapes, name, out, inp):
    shapes[name + ".weight"], shapes[name + ".bias"] = (out, inp), (out,)


def norm(shapes, name, dim):
    shapes[name + ".weight"], shapes[name + ".bias"] = (dim,), (dim,)


def moe_shapes(s, p, dim, seq, heads, out, d):
    s[p + "embedding"] = (1, seq, heads, dim)
    linear(s, p + "proj", out, dim)
    g = p + "model.gates.0."
    s[g + "temperature"], s[g + "sim_matrix"] = (1,), (d["gate_dim"], d["num_experts"])
    linear(s, g + "cosine_projector", d["gate_dim"], dim)
    hidden = d["text_expert_hidden"] if heads == 1 else d["motion_expert_hidden"]
    x = d["num_experts"]
    e = p + "model.experts."
    s[e + "batched_fc1_w"], s[e + "batched_fc1_bias"] = (x, hidden, dim), (x, hidden)
    s[e + "batched_fc2_w"], s[e + "batched_fc2_bias"] = (x, hidden, dim), (x, dim)


def stylization_shapes(s, p, dim, emb):
    linear(s, p + "emb_layers.1", 2 * dim, emb)
    norm(s, p + "norm", dim)
    linear(s, p + "out_layers.2", dim, dim)


def finemogen_shapes(d):
    P, M, H = d["part_dim"], d["text_latent_dim"], d["ffn_dim"]
    D, E = 8 * P, d["time_embed_dim"]
    s = {}
    linear(s, "text_pre_proj", M, d["clip_width"])
    for i in range(d["text_layers"]):
        p = f"textTransEncoder.layers.{i}."
        s[p + "self_attn.in_proj_weight"], s[p + "self_attn.in_proj_bias"] = (3 * M, M), (3 * M,)
        linear(s, p + "self_attn.out_proj", M, M)
        linear(s, p + "linear1", d["text_ff_size"], M)
        linear(s, p + "linear2", M, d["text_ff_size"])
        norm(s, p + "norm1", M)
        norm(s, p + "norm2", M)
    norm(s, "text_ln", M)
    linear(s, "time_embed.0", E, D)
    linear(s, "time_embed.2", E, E)
    for part, n in zip(PARTS, HML_PART_SIZES):
        linear(s, f"joint_embed.{part}_embed", P, n)
        linear(s, f"out.{part}_out", n, P)
    for i in range(d["num_layers"]):
        c = f"temporal_decoder_blocks.{i}.ca_block."
        norm(s, c + "norm", P)
        norm(s, c + "text_norm", M)
        s[c + "sigma"], s[c + "t_sigma"], s[c + "body_weight"] = (1,), (1,), (8, 8)
        moe_shapes(s, c + "text_moe.", M, d["max_text_len"], 1, 2 * P, d)
        moe_shapes(s, c + "motion_moe.", P, d["max_seq_len"], 8, 3 * P, d)
        for t in ("s", "v", "a", "j"):
            linear(s, c + f"template_{t}.0", H, P)
            linear(s, c + f"template_{t}.2", P, H)
        linear(s, c + "template_t.0", H, P)
        linear(s, c + "template_t.2", 1, H)
        stylization_shapes(s, c + "proj_out.", D, E)
        f = f"temporal_decoder_blocks.{i}.ffn."
        for j in range(8):
            linear(s, f + f"linear1_list.{j}", H, P)
            linear(s, f + f"linear2_list.{j}", P, H)
        stylization_shapes(s, f + "proj_out.", D, E)
    return s


def infer_denoiser(net, args, what):
    feats = shape_of(net, "joint_embed.body_embed.weight", what, 2)[1]
    if feats == 251:
        raise ConvertError(f"{what}: 251 input features: this is the KIT-ML model; libflame has "
                           f"no KIT skeleton (only the HumanML3D model, 263 features, converts)")
    if feats != 263:
        raise ConvertError(f"{what}: {feats} input features; want 263 (HumanML3D)")
    part_dim = shape_of(net, "joint_embed.head_embed.weight", what, 2)[0]
    text_latent, clip_width = shape_of(net, "text_pre_proj.weight", what, 2)
    c0 = "temporal_decoder_blocks.0.ca_block."
    gate_dim, experts = shape_of(net, c0 + "motion_moe.model.gates.0.sim_matrix", what, 2)
    d = {"input_feats": feats, "dataset": "human_ml3d", "part_dim": part_dim,
         "num_layers": indices(net, "temporal_decoder_blocks."),
         "time_embed_dim": shape_of(net, "time_embed.0.weight", what, 2)[0],
         "max_seq_len": shape_of(net, c0 + "motion_moe.embedding", what, 4)[1],
         "clip_width": clip_width, "text_latent_dim": text_latent,
         "text_layers": indices(net, "textTransEncoder.layers."),
         "text_heads": args.text_heads,
         "text_ff_size": shape_of(net, "textTransEncoder.layers.0.linear1.weight", what, 2)[0],
         "max_text_len": shape_of(net, c0 + "text_moe.embedding", what, 4)[1],
         "ffn_dim": shape_of(net, c0 + "template_s.0.weight", what, 2)[0],
         "num_experts": experts, "topk": args.topk, "capacity_factor": CAPACITY_FACTOR,
         "gate_dim": gate_dim,
         "text_expert_hidden": shape_of(net, c0 + "text_moe.model.experts.batched_fc1_w",
                                        what, 3)[1],
         "motion_expert_hidden": shape_of(net, c0 + "motion_moe.model.experts.batched_fc1_w",
                                          what, 3)[1],
         "layer_norm_eps": 1e-5}
    if d["num_layers"] == 0 or d["text_layers"] == 0:
        raise ConvertError(f"{what}: {d['num_layers']} decoder layers, {d['text_layers']} text "
                           f"layers; need at least one of each")
    if text_latent % args.text_heads:
        raise ConvertError(f"{what}: text_latent_dim {text_latent} is not divisible by "
                           f"--text-heads {args.text_heads}")
    if not 1 <= args.topk <= experts:
        raise ConvertError(f"--topk {args.topk}: need 1 <= topk <= num_experts ({experts})")
    return d


def pop_buffers(net, d, what):
    """Remove the recognised, unstored tensors after checking them."""
    for i in range(d["num_layers"]):
        c = f"temporal_decoder_blocks.{i}.ca_block."
        name = c + "key_motion"
        if name not in net:
            raise ConvertError(f"{what}: missing tensor 'model.{name}'")
        if tuple(net[name].shape) != (d["max_seq_len"], d["part_dim"]):
            raise ConvertError(f"{what}: tensor 'model.{name}' has shape "
                               f"{tuple(net[name].shape)}, expected "
                               f"{(d['max_seq_len'], d['part_dim'])}")
        del net[name]
        for moe in ("text_moe", "motion_moe"):
            name = c + moe + ".model._num_global_experts"
            if name in net:  # a buffer: present in saved checkpoints
                v = net.pop(name)
                if v.numel() != 1 or int(v) != d["num_experts"]:
                    raise ConvertError(f"{what}: 'model.{name}' = {v.tolist()}, but the gates "
                                       f"have {d['num_experts']} experts")


def convert_finemogen(args):
    t0 = time.perf_counter()
    state = load_state_dict(args.ckpt)
    what = args.ckpt
    others = sorted(k for k in state if not k.startswith("model."))
    if others:
        raise ConvertError(f"{what}: unknown tensor '{others[0]}'"
                           f"{f' (and {len(others) - 1} more)' if len(others) > 1 else ''}")
    clip_state = {k[len("model.clip."):]: v for k, v in state.items()
                  if k.startswith("model.clip.")}
    net = {k[len("model."):]: v for k, v in state.items()
           if k.startswith("model.") and not k.startswith("model.clip.")}
    if not net:
        raise ConvertError(f"{what}: no 'model.*' denoiser tensors")
    d = infer_denoiser(net, args, what)
    pop_buffers(net, d, what)
    kept = take(net, finemogen_shapes(d), what, "model.")
    text_cfg, clip, tokenizer = text_tower(args, clip_state)
    if text_cfg["width"] != d["clip_width"]:
        raise ConvertError(f"CLIP width {text_cfg['width']} != the input of text_pre_proj "
                           f"({d['clip_width']})")
    if text_cfg["context_length"] != d["max_text_len"]:
        raise ConvertError(f"CLIP context length {text_cfg['context_length']} != the text MoE's "
                           f"position table ({d['max_text_len']} rows)")
    try:
        counts = [int(c) for c in args.respacing.split(",")]
    except ValueError:
        raise ConvertError(f"--respacing {args.respacing!r}: want comma-separated step counts")
    if not counts or min(counts) < 1:
        raise ConvertError(f"--respacing {args.respacing!r}: every section needs >= 1 step")
    if not 1 <= args.frames <= d["max_seq_len"]:
        raise ConvertError(f"--frames {args.frames}: must lie in 1..{d['max_seq_len']}")
    tensors = {"denoiser." + k: v for k, v in kept.items()}
    tensors.update({"text." + k: v for k, v in clip.items()})
    tensors["motion.mean"] = read_stats(args.mean, d["input_feats"], "mean")
    tensors["motion.std"] = read_stats(args.std, d["input_feats"], "std")
    config = {"format_version": FORMAT_VERSION, "architecture": "finemogen", "denoiser": d,
              "text_encoder": text_cfg, "motion": {"format": "humanml263", "fps": 20.0},
              "diffusion": {"num_timesteps": 1000, "schedule": "linear", "parameterization": "x0",
                            "variance": "fixed_large", "clip_denoised": False,
                            "uncond": "null_text", "spacing": "respace"},
              "defaults": {"sampler": "ddim", "steps": sum(counts), "respacing": args.respacing,
                           "guidance": float(args.guidance), "eta": 0.0,
                           "frames": args.frames}}
    n, count = write(tensors, config, tokenizer, args.out, args.dtype)
    print(f"wrote {args.out}: finemogen, {count} tensors, {n / 1e6:.2f} M values ({args.dtype}); "
          f"part_dim {d['part_dim']} layers {d['num_layers']} experts {d['num_experts']} "
          f"clip {text_cfg['layers']}x{text_cfg['width']}"
          f"{' (from model.clip.*)' if clip_state else ''}; {time.perf_counter() - t0:.1f} s")
    return 0


def add_parsers(sub):
    p = sub.add_parser("finemogen", help="mingyuan-zhang/FineMoGen HumanML3D checkpoint")
    p.add_argument("--ckpt", required=True, help="official latest.pth (mmcv: 'state_dict')")
    p.add_argument("--clip", help="when the checkpoint has no model.clip.*: a Hugging Face CLIP "
                                  "folder or an OpenAI ViT-B-32.pt")
    p.add_argument("--tokenizer", help="CLIP tokenizer.json (default: the --clip folder's)")
    p.add_argument("--mean", required=True, help="mean.npy (263 values)")
    p.add_argument("--std", required=True, help="std.npy (263 values)")
    p.add_argument("--out", required=True, help="output .safetensors")
    p.add_argument("--text-heads", type=int, default=4,
                   help="heads of the text transformer (not in shapes; released 4)")
    p.add_argument("--clip-heads", type=int, default=None,
                   help="heads of OpenAI CLIP weights (default width / 64)")
    p.add_argument("--topk", type=int, default=2, help="experts per token (released 2)")
    p.add_argument("--guidance", type=float, default=6.5, help="scale of w(t) (released 6.5)")
    p.add_argument("--respacing", default="15,15,8,6,6", help="released 15,15,8,6,6")
    p.add_argument("--frames", type=int, default=196, help="default motion length")
    p.add_argument("--dtype", choices=sorted(DTYPES), default="f32")
    p.set_defaults(func=convert_finemogen)
