"""`convert.py omg`: a state dict of the OMG-style model (tools/reference/omg.py) to the libflame
file.

  python tools/convert.py omg --ckpt model.pt --clip CLIP_DIR --out M.safetensors \
      [--mean Mean.npy --std Std.npy] [--format humanml263|smpl24_6d] [--fps 20] \
      [--preset base|large|huge|giant | --heads N] [--rope-dims R] [--rope-base 10000] \
      [--norm-eps 1e-6] [--mlp-activation gelu_tanh|gelu] [--max-frames 300] \
      [--attn-heads 1] [--expert-activation gelu] [--gate-activation gelu] \
      [--mask-gamma 24] [--mask-beta 0.25] [--adain-eps 1e-5] [--text-padding] \
      [--guidance 4.5] [--steps 200] [--frames 196] [--dtype f32|f16|bf16]

No official OMG code or weights exist
(docs/official/omg.md#code-availability): the model is libflame's OMG-style model
of docs/omg.md, and the input is a state dict of `tools/reference/omg.py`'s `OMG` (a plain
dict of tensors, or {'state_dict': dict}). Its names are the file's tensor names without the
`denoiser.` prefix. Every tensor of the layout must be present with its shape; any other tensor
is an error naming it. A state dict without `control.*` tensors is a backbone-only model: the
file says `"control": null` and the runtime samples it unconditionally.

Every size is read from the shapes (d_model, input_feats, layers, ff_size, time_freq_dim;
control_dim, conv_kernel, text_dim, experts, expert_hidden, gate_hidden). What no shape holds
is an option with libflame's default: the heads (`--heads`, default d_model / 128 as in every
paper size, or `--preset`, which also checks the sizes), RoPE base and rotated dims, norm eps,
activations, MoC attention heads, the mask's gamma and beta, Ada-IN eps, text padding.

CLIP_DIR is a Hugging Face CLIP folder (config.json, model.safetensors of a CLIPModel or
CLIPTextModelWithProjection, tokenizer.json) as for `convert.py mdm`: the paper's text encoder
is CLIP ViT-L/14 (width 768 = text_dim). Backbone-only files carry it too (every libflame file
has a text encoder; the runtime refuses a non-blank prompt for them). --mean/--std (the feature
normalisation, `motion.mean`/`motion.std`, f32) are required for humanml263 (z-normalised
features, as MDM) and optional for smpl24_6d.

## File schema, `"architecture": "omg"`

d = d_model, F = input_feats, f = ff_size, Q = time_freq_dim, m = control_dim, k = conv_kernel,
D = text_dim, K = experts, e = expert_hidden, g = gate_hidden, i < layers:
  denoiser.x_embed.{weight [d, F], bias [d]}
  denoiser.t_embed.mlp.0.{weight [d, Q], bias [d]}, denoiser.t_embed.mlp.2.{weight [d, d], bias}
  denoiser.blocks.{i}.adaLN_modulation.1.{weight [6d, d], bias [6d]}
  denoiser.blocks.{i}.attn.qkv.{weight [3d, d], bias [3d]}, .attn.proj.{weight [d, d], bias}
  denoiser.blocks.{i}.mlp.fc1.{weight [f, d], bias [f]}, .mlp.fc2.{weight [d, f], bias [d]}
  denoiser.final_layer.adaLN_modulation.1.{weight [2d, d], bias [2d]}
  denoiser.final_layer.linear.{weight [F, d], bias [F]}
  denoiser.control.blocks.{i}.*           (as denoiser.blocks.{i}.*)
  denoiser.control.down.{i}.{weight [m, d, k], bias [m]}
  denoiser.control.up.{i}.{weight [d, m, k], bias [d]}
  denoiser.control.moc.{i}.q.{weight [m, m], bias [m]}
  denoiser.control.moc.{i}.{k,v}.{weight [m, D], bias [m]}
  denoiser.control.moc.{i}.adain.{gamma,beta}.{weight [m, D], bias [m]}
  denoiser.control.moc.{i}.experts.{w0 [K, m, e], b0 [K, e], w1 [K, e, m], b1 [K, m]}
  denoiser.control.moc.{i}.gate.0.{weight [g, D], bias [g]}, .gate.2.{weight [g, g], bias [g]},
      .gate.4.{weight [K, g], bias [K]}
  text.*  (HF CLIPTextModelWithProjection: text.text_model.…, text.text_projection.weight)
  motion.mean [F], motion.std [F]  (humanml263: required)

Configuration (`flame.config`):
  {"format_version": 1, "architecture": "omg",
   "denoiser": {"input_feats", "d_model", "layers", "heads", "ff_size", "time_freq_dim",
                "rope_base": 10000.0, "rope_dims", "norm_eps": 1e-6,
                "mlp_activation": "gelu_tanh", "max_frames": 300,
                "control": null | {"control_dim", "text_dim", "conv_kernel", "attn_heads": 1,
                   "experts", "expert_hidden", "expert_activation": "gelu", "gate_hidden",
                   "gate_activation": "gelu", "mask_gamma": 24.0, "mask_beta": 0.25,
                   "adain_eps": 1e-5, "text_padding": false}},
   "text_encoder": {"kind": "clip", ... as convert.py mdm, "max_length": 77},
   "motion": {"format": "humanml263", "fps": 20.0},
   "diffusion": {"num_timesteps": 1000, "schedule": "cosine", "parameterization": "x0",
                 "variance": "fixed_small", "clip_denoised": false, "uncond": "backbone",
                 "spacing": "respace"},
   "defaults": {"sampler": "ddim", "steps": 200, "guidance": 4.5, "eta": 0.0, "frames": 196}}
"""
import time

import torch

from convert import DTYPES, FORMAT_VERSION, ConvertError, load_state_dict, read_clip, \
    read_stats, warn
from convert_latent import indices, shape_of, take, write

FORMATS = {"humanml263": 263, "smpl24_6d": 147}
PRESETS = {"base": (8, 1024, 8), "large": (12, 1280, 10), "huge": (16, 1664, 13),
           "giant": (24, 2048, 16)}  # layers, d_model, heads (paper Table 1)
MLP_ACTIVATIONS = ("gelu_tanh", "gelu")
MOC_ACTIVATIONS = ("gelu", "gelu_tanh", "silu")
HEAD_DIM = 128  # every paper size


def linear(s, name, out, inp):
    s[name + ".weight"], s[name + ".bias"] = (out, inp), (out,)


def block_shapes(s, p, d, ff):
    linear(s, p + "adaLN_modulation.1", 6 * d, d)
    linear(s, p + "attn.qkv", 3 * d, d)
    linear(s, p + "attn.proj", d, d)
    linear(s, p + "mlp.fc1", ff, d)
    linear(s, p + "mlp.fc2", d, ff)


def omg_shapes(c):
    d, f, ff = c["d_model"], c["input_feats"], c["ff_size"]
    s = {}
    linear(s, "x_embed", d, f)
    linear(s, "t_embed.mlp.0", d, c["time_freq_dim"])
    linear(s, "t_embed.mlp.2", d, d)
    for i in range(c["layers"]):
        block_shapes(s, f"blocks.{i}.", d, ff)
    linear(s, "final_layer.adaLN_modulation.1", 2 * d, d)
    linear(s, "final_layer.linear", f, d)
    m = c["control"]
    if m is None:
        return s
    dm, k, dt, ne, eh, gh = (m["control_dim"], m["conv_kernel"], m["text_dim"], m["experts"],
                             m["expert_hidden"], m["gate_hidden"])
    for i in range(c["layers"]):
        block_shapes(s, f"control.blocks.{i}.", d, ff)
        s[f"control.down.{i}.weight"], s[f"control.down.{i}.bias"] = (dm, d, k), (dm,)
        s[f"control.up.{i}.weight"], s[f"control.up.{i}.bias"] = (d, dm, k), (d,)
        p = f"control.moc.{i}."
        linear(s, p + "q", dm, dm)
        for name in ("k", "v", "adain.gamma", "adain.beta"):
            linear(s, p + name, dm, dt)
        s[p + "experts.w0"], s[p + "experts.b0"] = (ne, dm, eh), (ne, eh)
        s[p + "experts.w1"], s[p + "experts.b1"] = (ne, eh, dm), (ne, dm)
        linear(s, p + "gate.0", gh, dt)
        linear(s, p + "gate.2", gh, gh)
        linear(s, p + "gate.4", ne, gh)
    return s


def infer(state, args, what):
    """The `denoiser` configuration: sizes from the shapes, the rest from the options."""
    d, f = shape_of(state, "x_embed.weight", what, 2)
    tf = shape_of(state, "t_embed.mlp.0.weight", what, 2)[1]
    layers = indices(state, "blocks.")
    if layers == 0:
        raise ConvertError(f"{what}: no 'blocks.N.*' tensors")
    ff = shape_of(state, "blocks.0.mlp.fc1.weight", what, 2)[0]
    if args.preset:
        p_layers, p_d, p_heads = PRESETS[args.preset]
        if (layers, d, ff) != (p_layers, p_d, 2 * p_d):
            raise ConvertError(f"{what}: {layers} layers x {d} (ff {ff}) is not the "
                               f"{args.preset} preset ({p_layers} x {p_d}, ff {2 * p_d})")
        if args.heads is not None and args.heads != p_heads:
            raise ConvertError(f"--heads {args.heads} contradicts --preset {args.preset} "
                               f"({p_heads} heads)")
        heads = p_heads
    elif args.heads is not None:
        heads = args.heads
    elif d % HEAD_DIM == 0:
        heads = d // HEAD_DIM
    else:
        raise ConvertError(f"d_model {d} is not a multiple of {HEAD_DIM}: give --heads")
    if heads < 1 or d % heads:
        raise ConvertError(f"d_model {d} is not divisible by {heads} heads")
    hd = d // heads
    rope_dims = hd if args.rope_dims is None else args.rope_dims
    if rope_dims % 2 or not 0 <= rope_dims <= hd:
        raise ConvertError(f"--rope-dims {rope_dims}: must be even and at most the head dim {hd}")
    if tf % 2:
        raise ConvertError(f"{what}: time_freq_dim {tf} (t_embed.mlp.0 input) must be even")
    cfg = {"input_feats": f, "d_model": d, "layers": layers, "heads": heads, "ff_size": ff,
           "time_freq_dim": tf, "rope_base": float(args.rope_base), "rope_dims": rope_dims,
           "norm_eps": float(args.norm_eps), "mlp_activation": args.mlp_activation,
           "max_frames": args.max_frames, "control": None}
    if not any(k.startswith("control.") for k in state):
        return cfg
    dm, d_in, k = shape_of(state, "control.down.0.weight", what, 3)
    if d_in != d:
        raise ConvertError(f"{what}: control.down.0.weight has {d_in} input channels, d_model "
                           f"is {d}")
    if k % 2 == 0:
        raise ConvertError(f"{what}: conv kernel {k} is even (the convs must keep the length)")
    dt = shape_of(state, "control.moc.0.k.weight", what, 2)[1]
    ne, _, eh = shape_of(state, "control.moc.0.experts.w0", what, 3)
    gh = shape_of(state, "control.moc.0.gate.0.weight", what, 2)[0]
    for prefix in ("control.blocks.", "control.down.", "control.moc.", "control.up."):
        n = indices(state, prefix)
        if n != layers:
            raise ConvertError(f"{what}: {n} '{prefix}N' entries, the backbone has {layers} "
                               f"blocks (every block has a ControlNet copy)")
    if args.attn_heads < 1 or dm % args.attn_heads:
        raise ConvertError(f"--attn-heads {args.attn_heads} does not divide control_dim {dm}")
    cfg["control"] = {"control_dim": dm, "text_dim": dt, "conv_kernel": k,
                      "attn_heads": args.attn_heads, "experts": ne, "expert_hidden": eh,
                      "expert_activation": args.expert_activation, "gate_hidden": gh,
                      "gate_activation": args.gate_activation,
                      "mask_gamma": float(args.mask_gamma), "mask_beta": float(args.mask_beta),
                      "adain_eps": float(args.adain_eps), "text_padding": bool(args.text_padding)}
    return cfg


def convert_omg(args):
    t0 = time.perf_counter()
    what = args.ckpt
    state = {k: v for k, v in load_state_dict(args.ckpt).items() if torch.is_tensor(v)}
    d = infer(state, args, what)
    kept = take(state, omg_shapes(d), what)
    feats = FORMATS[args.format]
    if d["input_feats"] != feats:
        raise ConvertError(f"--format {args.format} has {feats} features per frame, the model "
                           f"{d['input_feats']} (x_embed.weight)")
    if not 0 < args.fps <= 1000:
        raise ConvertError(f"--fps {args.fps}: must lie in (0, 1000]")
    if not 1 <= args.max_frames <= 100000:
        raise ConvertError(f"--max-frames {args.max_frames}: must lie in 1..100000")
    if not 1 <= args.frames <= args.max_frames:
        raise ConvertError(f"--frames {args.frames}: must lie in 1..--max-frames "
                           f"({args.max_frames})")
    if not 1 <= args.steps <= 1000:
        raise ConvertError(f"--steps {args.steps}: must lie in 1..1000")
    for name in ("norm_eps", "adain_eps"):
        if not 0 < getattr(args, name) <= 1:
            raise ConvertError(f"--{name.replace('_', '-')} must lie in (0, 1]")
    if not 1 < args.rope_base < float("inf"):
        raise ConvertError(f"--rope-base {args.rope_base} must be finite and exceed 1")
    if not 0 <= args.guidance <= 100:
        raise ConvertError(f"--guidance {args.guidance}: must lie in [0, 100]")
    for name in ("mask_gamma", "mask_beta"):
        if not abs(getattr(args, name)) < float("inf"):
            raise ConvertError(f"--{name.replace('_', '-')} must be finite")
    text_cfg, clip, tokenizer = read_clip(args.clip, 77)
    if d["control"] is not None and text_cfg["width"] != d["control"]["text_dim"]:
        raise ConvertError(f"CLIP width {text_cfg['width']} != the MoC's text_dim "
                           f"{d['control']['text_dim']} (control.moc.0.k.weight)")
    if d["control"] is None:
        warn(f"{what}: no control.* tensors: a backbone-only file (unconditional generation)")
    tensors = {"denoiser." + k: v for k, v in kept.items()}
    tensors.update({"text." + k: v for k, v in clip.items()})
    if (args.mean is None) != (args.std is None):
        raise ConvertError("give both --mean and --std, or neither")
    if args.mean is None and args.format == "humanml263":
        raise ConvertError("humanml263 features are z-normalised: --mean and --std are required")
    if args.mean is not None:
        tensors["motion.mean"] = read_stats(args.mean, feats, "mean")
        tensors["motion.std"] = read_stats(args.std, feats, "std")
    config = {"format_version": FORMAT_VERSION, "architecture": "omg", "denoiser": d,
              "text_encoder": text_cfg, "motion": {"format": args.format, "fps": float(args.fps)},
              "diffusion": {"num_timesteps": 1000, "schedule": "cosine", "parameterization": "x0",
                            "variance": "fixed_small", "clip_denoised": False,
                            "uncond": "backbone", "spacing": "respace"},
              "defaults": {"sampler": "ddim", "steps": args.steps,
                           "guidance": float(args.guidance), "eta": 0.0, "frames": args.frames}}
    n, count = write(tensors, config, tokenizer, args.out, args.dtype)
    kind = "backbone only" if d["control"] is None else \
        f"ControlNet {d['control']['control_dim']} wide, {d['control']['experts']} experts"
    print(f"wrote {args.out}: omg, {count} tensors, {n / 1e6:.2f} M values ({args.dtype}); "
          f"{d['layers']} x {d['d_model']} / {d['heads']} heads, {kind}; clip "
          f"{text_cfg['layers']}x{text_cfg['width']}; {time.perf_counter() - t0:.1f} s")
    return 0


def add_parsers(sub):
    p = sub.add_parser("omg", help="libflame's OMG-style model (state dict of "
                                   "tools/reference/omg.py)")
    p.add_argument("--ckpt", required=True, help="state dict (.pt; plain or {'state_dict': ...})")
    p.add_argument("--clip", required=True,
                   help="Hugging Face CLIP folder: config.json, tokenizer.json, model.safetensors")
    p.add_argument("--out", required=True, help="output .safetensors")
    p.add_argument("--mean", help="feature mean (.npy, input_feats values); humanml263: required")
    p.add_argument("--std", help="feature std (.npy); with --mean")
    p.add_argument("--format", choices=sorted(FORMATS), default="humanml263",
                   help="motion features (default humanml263)")
    p.add_argument("--fps", type=float, default=20.0,
                   help="frame rate of the features (default 20; the paper trains at 30)")
    p.add_argument("--preset", choices=sorted(PRESETS),
                   help="a paper size: sets the heads and checks the sizes")
    p.add_argument("--heads", type=int, help="attention heads (default d_model / 128)")
    p.add_argument("--rope-dims", type=int, help="rotated dims per head (default: all)")
    p.add_argument("--rope-base", type=float, default=10000.0)
    p.add_argument("--norm-eps", type=float, default=1e-6)
    p.add_argument("--mlp-activation", choices=MLP_ACTIVATIONS, default="gelu_tanh")
    p.add_argument("--max-frames", type=int, default=300,
                   help="longest motion (default 300 = the paper's 10 s at 30 fps)")
    p.add_argument("--attn-heads", type=int, default=1, help="MoC cross-attention heads")
    p.add_argument("--expert-activation", choices=MOC_ACTIVATIONS, default="gelu")
    p.add_argument("--gate-activation", choices=MOC_ACTIVATIONS, default="gelu")
    p.add_argument("--mask-gamma", type=float, default=24.0)
    p.add_argument("--mask-beta", type=float, default=0.25)
    p.add_argument("--adain-eps", type=float, default=1e-5)
    p.add_argument("--text-padding", action="store_true",
                   help="the MoC sees all 77 CLIP positions (default: SOT..EOT only)")
    p.add_argument("--guidance", type=float, default=4.5, help="default guidance (paper 4.5)")
    p.add_argument("--steps", type=int, default=200, help="default DDIM steps (paper 200)")
    p.add_argument("--frames", type=int, default=196, help="default motion length")
    p.add_argument("--dtype", choices=sorted(DTYPES), default="f32")
    p.set_defaults(func=convert_omg)
