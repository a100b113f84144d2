"""`convert.py mola` and `convert.py mld`: latent-diffusion checkpoints to the libflame file.

  python tools/convert.py mola --vae STAGE1.pth --denoiser STAGE2.pth --clip CLIP_DIR \
      --mean mean.npy --std std.npy --out M.safetensors [--heads 4] [--dtype f32|f16|bf16]
  python tools/convert.py mld --ckpt mld_humanml3d.ckpt --clip CLIP_DIR \
      --mean Mean.npy --std Std.npy --out M.safetensors [--heads 4] [--dtype ..]

CLIP_DIR is a Hugging Face CLIP folder as for `convert.py mdm` (MoLA: ViT-B/32, projection 512;
MLD: ViT-L/14, projection 768); its text tower goes under `text.` with the HF names and its
tokenizer.json into the `flame.tokenizer` metadata. Mean/Std (263 values) go to `motion.mean`,
`motion.std` (MoLA: the evaluator meta statistics, docs/official/mola-mld.md#mola-normalisation; MLD:
HumanML3D Mean/Std).
Every size is read from the tensors, checked against the other tensors, and written to the
configuration; the head counts and MoLA's dilation growth are not in any shape (--heads,
--dilation-growth).

## MoLA (sony/MoLA), `"architecture": "mola"`

Input: the stage-1 checkpoint (dict key `net`) and the stage-2 checkpoint (dict key `trans`).
- `trans`: every `denoiser.*` tensor below must be present with its shape; the buffers
  `denoiser.transformer.rotary_pos_emb.inv_freq` (checked to be 10000^(-2i/rotary_dim)) and the
  LayerNorm `*.beta` (checked to be zero) are recognised and not stored; the wrapper's unused
  top-level copies (`timestep_features.weight`, `to_timestep_embed.{0,2}.*`,
  `to_global_embed.{0,2}.weight`, `preprocess_conv.weight`, `postprocess_conv.weight`) are
  recognised and not stored. Any other tensor is an error naming it.
- `net`: every `vae.decoder.model.*` tensor below must be present and no other under that prefix;
  the rest of `net` (the encoder side, not used for text-to-motion) is skipped.

Tensors of the file (E = embed_dim, C = latent_channels, F = ff_dim, G = cond_dim,
N = time_features, W = vae.width, O = vae.output_dim, U = upsample_layers, R = res_blocks):
  denoiser.timestep_features.weight                 [N, 1]
  denoiser.to_timestep_embed.0.{weight [E, 2N], bias [E]}
  denoiser.to_timestep_embed.2.{weight [E, E], bias [E]}
  denoiser.to_global_embed.0.weight [E, G], denoiser.to_global_embed.2.weight [E, E]
  denoiser.preprocess_conv.weight [C, C, 1], denoiser.postprocess_conv.weight [C, C, 1]
  denoiser.transformer.project_in.weight [E, C], denoiser.transformer.project_out.weight [C, E]
  denoiser.transformer.layers.{i}.pre_norm.gamma [E], .ff_norm.gamma [E]
  denoiser.transformer.layers.{i}.self_attn.to_qkv.weight [3E, E], .self_attn.to_out.weight [E, E]
  denoiser.transformer.layers.{i}.ff.ff.0.proj.{weight [2F, E], bias [2F]}  (value rows first,
                                                                             then gate rows)
  denoiser.transformer.layers.{i}.ff.ff.2.{weight [E, F], bias [E]}
  vae.decoder.model.0.{weight [W, C, 3], bias [W]}
  vae.decoder.model.{2+u}.0.model.{j}.conv1.{weight [W, W, 3], bias}   u < U, j < R
  vae.decoder.model.{2+u}.0.model.{j}.conv2.{weight [W, W, 1], bias}
  vae.decoder.model.{2+u}.2.{weight [W, W, 3], bias}
  vae.decoder.model.{2+U}.{weight [W, W, 3], bias}
  vae.decoder.model.{4+U}.{weight [O, W, 3], bias [O]}
  text.*  (HF CLIPTextModelWithProjection text tower), motion.mean [263], motion.std [263]
Block j of each Resnet1D has dilation growth^(R-1-j) (9, 3, 1).

Configuration (`flame.config`):
  {"format_version": 1, "architecture": "mola",
   "denoiser": {"latent_channels", "embed_dim", "depth", "num_heads", "rotary_dim" (2 × the
                inv_freq length), "ff_dim", "cond_dim", "time_features", "layer_norm_eps",
                "max_latent_frames" (a bound of this format: 1024)},
   "vae": {"width", "output_dim", "upsample_layers", "res_blocks", "dilation_growth",
           "flag_threshold": 0.999, "min_frames": 10},
   "text_encoder": {"kind": "clip", ... as convert.py mdm, "max_length": 77},
   "motion": {"format": "humanml263", "fps": 20.0},
   "diffusion": {"num_timesteps": 1000, "schedule": "scaled_linear", "parameterization":
                 "epsilon", "variance": "fixed_small", "clip_denoised": false, "uncond": "zeros",
                 "spacing": "trailing", "steps_offset": 1, "set_alpha_to_one": false},
   "defaults": {"sampler": "ddim", "steps": 50, "guidance": 11.0, "eta": 0.0, "frames": 196}}

## MLD (ChenFengYe/motion-latent-diffusion), `"architecture": "mld"`

Input: the Lightning checkpoint's `state_dict`. Every `denoiser.*` tensor below must be present
and no other under `denoiser.` except the unused `denoiser.mem_pos.pe` (recognised, not stored).
The VAE's decoder part below must be present; the VAE's encoder side (`vae.encoder.*`,
`vae.skel_embedding.*`, `vae.global_motion_token`, `vae.query_pos_encoder.*`, `vae.dist*`) and
the modules `text_encoder.*`, `t2m_textencoder.*`, `t2m_moveencoder.*`, `t2m_motionencoder.*`
(the frozen CLIP and the evaluators) are skipped; any other tensor is an error naming it
(--skip-prefix P skips more).

Tensors of the file (D = latent_dim, T = text_dim, F = ff_size, P = max_len, B = (layers-1)/2):
  denoiser.time_embedding.linear_1.{weight [D, T], bias [D]}
  denoiser.time_embedding.linear_2.{weight [D, D], bias [D]}
  denoiser.emb_proj.1.{weight [D, T], bias [D]}
  denoiser.query_pos.pe [P, 1, D]
  denoiser.encoder.{input_blocks.b, middle_block, output_blocks.b}.   b < B
      self_attn.{in_proj_weight [3D, D], in_proj_bias [3D]},
      self_attn.out_proj.{weight [D, D], bias [D]}
      linear1.{weight [F, D], bias [F]}, linear2.{weight [D, F], bias [D]}, norm{1,2}.{weight, bias}
  denoiser.encoder.linear_blocks.b.{weight [D, 2D], bias [D]}
  denoiser.encoder.norm.{weight, bias} [D]
  vae.query_pos_decoder.pe [P', 1, D']
  vae.decoder.{input_blocks.b, middle_block, output_blocks.b}.   (decoder layers)
      self_attn.*, multihead_attn.* (as self_attn), linear1.*, linear2.*, norm{1,2,3}.*
  vae.decoder.linear_blocks.b.{weight [D', 2D'], bias}
  vae.decoder.norm.{weight, bias}   (when present: vae.final_norm true)
  vae.final_layer.{weight [263, D'], bias [263]}
  text.*, motion.mean, motion.std as above.

Configuration:
  {"format_version": 1, "architecture": "mld",
   "denoiser": {"latent_dim", "latent_tokens": 1, "text_dim", "layers", "heads", "ff_size",
                "max_len", "activation": "gelu", "layer_norm_eps": 1e-5},
   "vae": {"latent_dim", "layers", "heads", "ff_size", "nfeats", "max_len", "final_norm",
           "activation": "gelu", "layer_norm_eps": 1e-5},
   "text_encoder": {"kind": "clip", ..., "max_length": 77},
   "motion": {"format": "humanml263", "fps": 20.0},
   "diffusion": {"num_timesteps": 1000, "schedule": "scaled_linear", "parameterization":
                 "epsilon", "variance": "fixed_small", "clip_denoised": false,
                 "uncond": "empty_prompt", "spacing": "leading", "steps_offset": 1,
                 "set_alpha_to_one": false},
   "defaults": {"sampler": "ddim", "steps": 50, "guidance": 7.5, "eta": 0.0, "frames": 196}}
(`frames`: --frames, default 196; MLD needs it <= vae.max_len, MoLA <= 4·max_latent_frames - 4.)
"""
import json
import os
import time

import torch

from convert import DTYPES, FORMAT_VERSION, ConvertError, cast, read_clip, read_stats, warn

MOLA_MAX_LATENT_FRAMES = 1024
MOLA_UNUSED_TOP = ("timestep_features.", "to_timestep_embed.", "to_global_embed.",
                   "preprocess_conv.", "postprocess_conv.")
MLD_SKIP_TOP = ("text_encoder.", "t2m_textencoder.", "t2m_moveencoder.", "t2m_motionencoder.")
MLD_VAE_ENCODER = ("vae.encoder.", "vae.skel_embedding.", "vae.global_motion_token",
                   "vae.query_pos_encoder.", "vae.dist")


def load_dict(path, key):
    if not os.path.isfile(path):
        raise ConvertError(f"{path}: no such checkpoint file")
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get(key), dict):
        top = sorted(ckpt)[:10] if isinstance(ckpt, dict) else type(ckpt).__name__
        raise ConvertError(f"{path}: no '{key}' state dict in the checkpoint (top level: {top})")
    return {k: v for k, v in ckpt[key].items() if torch.is_tensor(v)}


def take(state, shapes, what, prefix=""):
    """Check that `state` holds exactly `shapes` (name -> shape); returns the tensors. Errors
    name the tensor with `prefix` (its checkpoint name)."""
    for name, shape in shapes.items():
        if name not in state:
            raise ConvertError(f"{what}: missing tensor '{prefix}{name}'")
        t = state[name]
        if tuple(t.shape) != tuple(shape):
            raise ConvertError(f"{what}: tensor '{prefix}{name}' has shape {tuple(t.shape)}, "
                               f"expected {tuple(shape)}")
        if not t.is_floating_point():
            raise ConvertError(f"{what}: tensor '{prefix}{name}' has dtype {t.dtype}, expected "
                               f"floating")
    extra = sorted(set(state) - set(shapes))
    if extra:
        raise ConvertError(f"{what}: unknown tensor '{prefix}{extra[0]}'"
                           f"{f' (and {len(extra) - 1} more)' if len(extra) > 1 else ''}")
    return dict(state)


def shape_of(state, name, what, dims):
    if name not in state:
        raise ConvertError(f"{what}: missing tensor '{name}'")
    t = state[name]
    if t.dim() != dims:
        raise ConvertError(f"{what}: tensor '{name}' has shape {tuple(t.shape)}, want {dims}-D")
    return [int(s) for s in t.shape]


def indices(names, prefix):
    idx = sorted({int(k[len(prefix):].split(".", 1)[0]) for k in names
                  if k.startswith(prefix) and k[len(prefix):].split(".", 1)[0].isdigit()})
    if idx != list(range(len(idx))):
        raise ConvertError(f"non-contiguous indices under '{prefix}': {idx}")
    return len(idx)


def write(tensors, config, tokenizer, out, dtype_name):
    from safetensors.torch import save_file
    dtype = DTYPES[dtype_name]
    t = {k: (v.float().contiguous() if k.startswith("motion.") else cast(v, dtype, k))
         for k, v in tensors.items()}
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    save_file(t, out, metadata={"format": "libflame", "flame.config": json.dumps(config),
                                "flame.tokenizer": tokenizer})
    return sum(v.numel() for v in t.values()), len(t)


def text_and_stats(args, cond_dim, tensors):
    text_cfg, clip, tokenizer = read_clip(args.clip, 77)
    if text_cfg["projection_dim"] != cond_dim:
        raise ConvertError(f"CLIP projection_dim {text_cfg['projection_dim']} != the denoiser's "
                           f"text input {cond_dim}")
    for k, v in clip.items():
        tensors["text." + k] = v
    tensors["motion.mean"] = read_stats(args.mean, 263, "mean")
    tensors["motion.std"] = read_stats(args.std, 263, "std")
    return text_cfg, tokenizer


def scheduler_cfg(spacing, uncond):
    return {"num_timesteps": 1000, "schedule": "scaled_linear", "parameterization": "epsilon",
            "variance": "fixed_small", "clip_denoised": False, "uncond": uncond,
            "spacing": spacing, "steps_offset": 1, "set_alpha_to_one": False}


# -- MoLA ------------------------------------------------------------------------------------------

def mola_denoiser_shapes(d):
    e, c, f, g, n = (d["embed_dim"], d["latent_channels"], d["ff_dim"], d["cond_dim"],
                     d["time_features"])
    s = {"timestep_features.weight": (n, 1),
         "to_timestep_embed.0.weight": (e, 2 * n), "to_timestep_embed.0.bias": (e,),
         "to_timestep_embed.2.weight": (e, e), "to_timestep_embed.2.bias": (e,),
         "to_global_embed.0.weight": (e, g), "to_global_embed.2.weight": (e, e),
         "preprocess_conv.weight": (c, c, 1), "postprocess_conv.weight": (c, c, 1),
         "transformer.project_in.weight": (e, c), "transformer.project_out.weight": (c, e)}
    for i in range(d["depth"]):
        p = f"transformer.layers.{i}."
        s[p + "pre_norm.gamma"] = (e,)
        s[p + "ff_norm.gamma"] = (e,)
        s[p + "self_attn.to_qkv.weight"] = (3 * e, e)
        s[p + "self_attn.to_out.weight"] = (e, e)
        s[p + "ff.ff.0.proj.weight"] = (2 * f, e)
        s[p + "ff.ff.0.proj.bias"] = (2 * f,)
        s[p + "ff.ff.2.weight"] = (e, f)
        s[p + "ff.ff.2.bias"] = (e,)
    return s


def mola_vae_shapes(v, c):
    w, o, u, r = v["width"], v["output_dim"], v["upsample_layers"], v["res_blocks"]
    s = {"0.weight": (w, c, 3), "0.bias": (w,)}
    for k in range(u):
        p = f"{2 + k}."
        for j in range(r):
            s[p + f"0.model.{j}.conv1.weight"] = (w, w, 3)
            s[p + f"0.model.{j}.conv1.bias"] = (w,)
            s[p + f"0.model.{j}.conv2.weight"] = (w, w, 1)
            s[p + f"0.model.{j}.conv2.bias"] = (w,)
        s[p + "2.weight"] = (w, w, 3)
        s[p + "2.bias"] = (w,)
    s[f"{2 + u}.weight"], s[f"{2 + u}.bias"] = (w, w, 3), (w,)
    s[f"{4 + u}.weight"], s[f"{4 + u}.bias"] = (o, w, 3), (o,)
    return s


def convert_mola(args):
    t0 = time.perf_counter()
    trans = load_dict(args.denoiser, "trans")
    what = f"{args.denoiser} (trans)"
    den = {k[len("denoiser."):]: v for k, v in trans.items() if k.startswith("denoiser.")}
    others = sorted(k for k in trans if not k.startswith("denoiser."))
    for k in others:
        if not k.startswith(MOLA_UNUSED_TOP):
            raise ConvertError(f"{what}: unknown tensor '{k}'")
    if not den:
        raise ConvertError(f"{what}: no 'denoiser.*' tensors")
    inv = den.pop("transformer.rotary_pos_emb.inv_freq", None)
    if inv is None:
        raise ConvertError(f"{what}: missing tensor 'denoiser.transformer.rotary_pos_emb.inv_freq'")
    rotary_dim = 2 * inv.numel()
    want = 1.0 / (10000 ** (torch.arange(0, rotary_dim, 2).double() / rotary_dim))
    if not torch.allclose(inv.double().reshape(-1), want, rtol=1e-6, atol=0):
        raise ConvertError(f"{what}: inv_freq is not 10000^(-2i/{rotary_dim})")
    depth = indices(den, "transformer.layers.")
    for i in range(depth):
        for norm in ("pre_norm", "ff_norm"):
            name = f"transformer.layers.{i}.{norm}.beta"
            b = den.pop(name, None)
            if b is None:
                raise ConvertError(f"{what}: missing buffer 'denoiser.{name}'")
            if b.abs().max() != 0:
                raise ConvertError(f"{what}: LayerNorm bias 'denoiser.{name}' is not zero")
    e, c = shape_of(den, "transformer.project_in.weight", what, 2)
    heads = args.heads
    if depth == 0 or e % heads or rotary_dim > e // heads or rotary_dim % 2:
        raise ConvertError(f"{what}: depth {depth}, embed_dim {e}, --heads {heads}, rotary_dim "
                           f"{rotary_dim}: need depth >= 1, heads dividing embed_dim and an even "
                           f"rotary_dim <= the head size")
    d = {"latent_channels": c, "embed_dim": e, "depth": depth, "num_heads": heads,
         "rotary_dim": rotary_dim,
         "ff_dim": shape_of(den, "transformer.layers.0.ff.ff.2.weight", what, 2)[1],
         "cond_dim": shape_of(den, "to_global_embed.0.weight", what, 2)[1],
         "time_features": shape_of(den, "timestep_features.weight", what, 2)[0],
         "layer_norm_eps": 1e-5, "max_latent_frames": MOLA_MAX_LATENT_FRAMES}
    tensors = {"denoiser." + k: v for k, v in
               take(den, mola_denoiser_shapes(d), what, "denoiser.").items()}
    # The wrapper's copies: recognised by name and shape, not stored.
    top = {k: v for k, v in trans.items() if not k.startswith("denoiser.")}
    top_shapes = {k: s for k, s in mola_denoiser_shapes(d).items() if k.startswith(MOLA_UNUSED_TOP)}
    take(top, {k: s for k, s in top_shapes.items() if k in top}, what + " (unused copies)")

    net = load_dict(args.vae, "net")
    vwhat = f"{args.vae} (net)"
    pre = "vae.decoder.model."
    dec = {k[len(pre):]: v for k, v in net.items() if k.startswith(pre)}
    skipped = len(net) - len(dec)
    if not dec:
        raise ConvertError(f"{vwhat}: no '{pre}*' tensors")
    w, c_in, _ = shape_of(dec, "0.weight", vwhat, 3)
    if c_in != c:
        raise ConvertError(f"{vwhat}: the decoder takes {c_in} latent channels, the denoiser "
                           f"makes {c}")
    ups = 0
    while f"{2 + ups}.0.model.0.conv1.weight" in dec:
        ups += 1
    res = indices(dec, "2.0.model.") if ups else 0
    o = shape_of(dec, f"{4 + ups}.weight", vwhat, 3)[0]
    if ups == 0 or res == 0 or o != 264:
        raise ConvertError(f"{vwhat}: {ups} upsampling stages, {res} residual blocks, output "
                           f"{o} channels; want >= 1, >= 1 and 264 (263 features + the flag)")
    v = {"width": w, "output_dim": o, "upsample_layers": ups, "res_blocks": res,
         "dilation_growth": args.dilation_growth, "flag_threshold": 0.999, "min_frames": 10}
    for k, t in take(dec, mola_vae_shapes(v, c), vwhat, pre).items():
        tensors[pre + k] = t

    if not 1 <= args.frames <= 4 * MOLA_MAX_LATENT_FRAMES - 4:
        raise ConvertError(f"--frames {args.frames} outside 1..{4 * MOLA_MAX_LATENT_FRAMES - 4}")
    text_cfg, tokenizer = text_and_stats(args, d["cond_dim"], tensors)
    config = {"format_version": FORMAT_VERSION, "architecture": "mola", "denoiser": d, "vae": v,
              "text_encoder": text_cfg, "motion": {"format": "humanml263", "fps": 20.0},
              "diffusion": scheduler_cfg("trailing", "zeros"),
              "defaults": {"sampler": "ddim", "steps": 50, "guidance": 11.0, "eta": 0.0,
                           "frames": args.frames}}
    n, count = write(tensors, config, tokenizer, args.out, args.dtype)
    print(f"wrote {args.out}: mola, {count} tensors, {n / 1e6:.2f} M values ({args.dtype}); "
          f"embed {e} depth {depth} heads {heads} rotary {rotary_dim}; vae width {w}; skipped "
          f"{len(others)} unused copies and {skipped} encoder-side tensors; "
          f"{time.perf_counter() - t0:.1f} s")
    return 0


# -- MLD -------------------------------------------------------------------------------------------

def mld_layer_shapes(p, d, f, cross):
    s = {}
    for attn in ("self_attn", "multihead_attn") if cross else ("self_attn",):
        s[p + attn + ".in_proj_weight"] = (3 * d, d)
        s[p + attn + ".in_proj_bias"] = (3 * d,)
        s[p + attn + ".out_proj.weight"] = (d, d)
        s[p + attn + ".out_proj.bias"] = (d,)
    s[p + "linear1.weight"], s[p + "linear1.bias"] = (f, d), (f,)
    s[p + "linear2.weight"], s[p + "linear2.bias"] = (d, f), (d,)
    for norm in ("norm1", "norm2", "norm3") if cross else ("norm1", "norm2"):
        s[p + norm + ".weight"], s[p + norm + ".bias"] = (d,), (d,)
    return s


def mld_stack_shapes(p, layers, d, f, cross, final_norm):
    s = {}
    for b in range((layers - 1) // 2):
        s.update(mld_layer_shapes(f"{p}input_blocks.{b}.", d, f, cross))
        s.update(mld_layer_shapes(f"{p}output_blocks.{b}.", d, f, cross))
        s[f"{p}linear_blocks.{b}.weight"], s[f"{p}linear_blocks.{b}.bias"] = (d, 2 * d), (d,)
    s.update(mld_layer_shapes(p + "middle_block.", d, f, cross))
    if final_norm:
        s[p + "norm.weight"], s[p + "norm.bias"] = (d,), (d,)
    return s


def mld_denoiser_shapes(c):
    d, t, p = c["latent_dim"], c["text_dim"], c["max_len"]
    s = {"time_embedding.linear_1.weight": (d, t), "time_embedding.linear_1.bias": (d,),
         "time_embedding.linear_2.weight": (d, d), "time_embedding.linear_2.bias": (d,),
         "emb_proj.1.weight": (d, t), "emb_proj.1.bias": (d,), "query_pos.pe": (p, 1, d)}
    s.update(mld_stack_shapes("encoder.", c["layers"], d, c["ff_size"], False, True))
    return s


def mld_vae_shapes(c):
    d = c["latent_dim"]
    s = {"query_pos_decoder.pe": (c["max_len"], 1, d),
         "final_layer.weight": (c["nfeats"], d), "final_layer.bias": (c["nfeats"],)}
    s.update(mld_stack_shapes("decoder.", c["layers"], d, c["ff_size"], True, c["final_norm"]))
    return s


def mld_stack_layers(state, prefix, what):
    nb = indices(state, prefix + "input_blocks.")
    if nb != indices(state, prefix + "output_blocks.") or nb != indices(state,
                                                                        prefix + "linear_blocks."):
        raise ConvertError(f"{what}: '{prefix}' has unequal input/output/linear block counts")
    return 2 * nb + 1


def convert_mld(args):
    t0 = time.perf_counter()
    state = load_dict(args.ckpt, "state_dict")
    what = f"{args.ckpt} (state_dict)"
    skip = MLD_SKIP_TOP + tuple(args.skip_prefix or ())
    den, vae, skipped = {}, {}, 0
    for k, v in state.items():
        if k.startswith("denoiser."):
            den[k[len("denoiser."):]] = v
        elif k.startswith(MLD_VAE_ENCODER) or k.startswith(skip):
            skipped += 1
        elif k.startswith("vae."):
            vae[k[len("vae."):]] = v
        else:
            raise ConvertError(f"{what}: unknown tensor '{k}' (--skip-prefix to skip it)")
    if den.pop("mem_pos.pe", None) is None:
        warn(f"{what}: no 'denoiser.mem_pos.pe' (unused by the official forward)")
    heads = args.heads
    dw = what + " denoiser.*"
    lat, text_dim = shape_of(den, "time_embedding.linear_1.weight", dw, 2)
    dc = {"latent_dim": lat, "latent_tokens": 1, "text_dim": text_dim,
          "layers": mld_stack_layers(den, "encoder.", dw), "heads": heads,
          "ff_size": shape_of(den, "encoder.middle_block.linear1.weight", dw, 2)[0],
          "max_len": shape_of(den, "query_pos.pe", dw, 3)[0], "activation": "gelu",
          "layer_norm_eps": 1e-5}
    vw = what + " vae.* (decoder)"
    vd = shape_of(vae, "final_layer.weight", vw, 2)
    vc = {"latent_dim": vd[1], "layers": mld_stack_layers(vae, "decoder.", vw), "heads": heads,
          "ff_size": shape_of(vae, "decoder.middle_block.linear1.weight", vw, 2)[0],
          "nfeats": vd[0], "max_len": shape_of(vae, "query_pos_decoder.pe", vw, 3)[0],
          "final_norm": "decoder.norm.weight" in vae, "activation": "gelu",
          "layer_norm_eps": 1e-5}
    if lat % heads or vc["latent_dim"] % heads or text_dim % 2:
        raise ConvertError(f"{what}: --heads {heads} must divide the widths {lat} and "
                           f"{vc['latent_dim']}; text_dim {text_dim} must be even")
    if vc["latent_dim"] != lat or vc["nfeats"] != 263:
        raise ConvertError(f"{what}: VAE width {vc['latent_dim']} / {vc['nfeats']} features; "
                           f"want the denoiser's {lat} and 263")
    if dc["max_len"] < dc["latent_tokens"] + 2 or not 1 <= args.frames <= vc["max_len"]:
        raise ConvertError(f"{what}: position tables of {dc['max_len']} / {vc['max_len']} rows; "
                           f"need >= 3 / >= --frames {args.frames}")
    kept = take(den, mld_denoiser_shapes(dc), what, "denoiser.")
    tensors = {"denoiser." + k: v for k, v in kept.items()}
    tensors.update({"vae." + k: v for k, v in take(vae, mld_vae_shapes(vc), what, "vae.").items()})
    text_cfg, tokenizer = text_and_stats(args, text_dim, tensors)
    config = {"format_version": FORMAT_VERSION, "architecture": "mld", "denoiser": dc, "vae": vc,
              "text_encoder": text_cfg, "motion": {"format": "humanml263", "fps": 20.0},
              "diffusion": scheduler_cfg("leading", "empty_prompt"),
              "defaults": {"sampler": "ddim", "steps": 50, "guidance": 7.5, "eta": 0.0,
                           "frames": args.frames}}
    n, count = write(tensors, config, tokenizer, args.out, args.dtype)
    print(f"wrote {args.out}: mld, {count} tensors, {n / 1e6:.2f} M values ({args.dtype}); "
          f"latent {lat} layers {dc['layers']}/{vc['layers']} heads {heads}; skipped {skipped} "
          f"tensors (VAE encoder, CLIP, evaluators); {time.perf_counter() - t0:.1f} s")
    return 0


def add_parsers(sub):
    p = sub.add_parser("mola", help="sony/MoLA stage-1 (VAE) + stage-2 (denoiser) checkpoints")
    p.add_argument("--vae", required=True, help="stage-1 checkpoint (dict key 'net')")
    p.add_argument("--denoiser", required=True, help="stage-2 checkpoint (dict key 'trans')")
    p.add_argument("--dilation-growth", type=int, default=3,
                   help="VAE residual dilation growth (not in shapes; official 3)")
    add_common(p)
    p.set_defaults(func=convert_mola)
    p = sub.add_parser("mld", help="ChenFengYe/motion-latent-diffusion Lightning checkpoint")
    p.add_argument("--ckpt", required=True, help="official .ckpt (Lightning, key 'state_dict')")
    p.add_argument("--skip-prefix", action="append",
                   help="also skip tensors whose name starts with this (repeatable)")
    add_common(p)
    p.set_defaults(func=convert_mld)


def add_common(p):
    p.add_argument("--clip", required=True,
                   help="Hugging Face CLIP folder: config.json, tokenizer.json, model.safetensors")
    p.add_argument("--mean", required=True, help="mean (.npy, 263 values)")
    p.add_argument("--std", required=True, help="std (.npy, 263 values)")
    p.add_argument("--out", required=True, help="output .safetensors")
    p.add_argument("--heads", type=int, default=4, help="attention heads (not in shapes)")
    p.add_argument("--dtype", choices=sorted(DTYPES), default="f32")
    p.add_argument("--frames", type=int, default=196,
                   help="default motion length (MLD: at most the VAE's position rows)")
