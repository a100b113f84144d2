"""`convert.py motionlcm`: MotionLCM checkpoints (Dai et al., ECCV 2024) to the libflame file.

  python tools/convert.py motionlcm --ckpt motionlcm_humanml.ckpt --t5 SENTENCE_T5_DIR \
      --mean Mean.npy --std Std.npy --out M.safetensors [--heads 4] [--dtype f32|f16|bf16] \
      [--frames 196] [--latent-tokens 16] [--skip-prefix P ...] \
      [--control-mean Mean_raw.npy --control-std Std_raw.npy]   (trajectory-control checkpoints)

Both releases of github.com/Dai-Wenxun/MotionLCM are read: v1.0 (f534a7f) and v2.0 (086f8db).
The release is told by the tensors: `denoiser.latent_pre.weight` present -> v2, else v1.
Sources (official repository, file at the tag):
- denoiser: mld/models/architectures/mld_denoiser.py (v1.0 and v2.0) with
  mld/models/architectures/tools/embeddings.py (v1.0) / mld/models/operator/embeddings.py (v2.0);
  configs/modules/denoiser.yaml (v2.0: hidden_dim 256, force_pre_post_proj true, text_act_fn null;
  v1.0: no text_act_fn, so emb_proj = Sequential(ReLU, Linear)).
- guidance embedding: mld/utils/utils.py get_guidance_scale_embedding (both tags); the embedded
  scale is guidance_scale - 1 (mld/models/modeltype/mld.py, _diffusion_reverse); with the
  `cond_proj` present the model runs without classifier-free guidance (do_classifier_free_guidance).
- VAE: mld/models/architectures/mld_vae.py (decode; v2.0 applies `latent_post` first).
- sampler: configs/modules/scheduler.yaml (v1.0: diffusers LCMScheduler, 1 step, guidance 7.5 in
  configs/motionlcm_t2m.yaml) and configs/modules/scheduler_lcm.yaml + mld/models/schedulers/
  scheduling_lcm.py (v2.0: the timesteps_step_map table and cfg_step_map 1 -> 8.0, 2 -> 12.5,
  4 -> 13.5, original_inference_steps 10).
- text encoder: mld/models/architectures/mld_clip.py (SentenceTransformer(t5_path).encode) with
  t5_path ./deps/sentence-t5-large (prepare/prepare_t5.sh clones
  huggingface.co/sentence-transformers/sentence-t5-large).
- trajectory control (ControlNet): mld/models/architectures/mld_denoiser.py with
  is_controlnet=True (the `controlnet` copy of the denoiser: no final encoder norm,
  `controlnet_cond_embedding`, `controlnet_down_mid_blocks`), mld/models/architectures/
  mld_traj_encoder.py (`traj_encoder`), mld/models/modeltype/mld.py (the copy is built from the
  denoiser's configuration with is_controlnet set; v1.0 `control_scale` from
  configs/motionlcm_control.yaml, 1.0; the frame mask: v1.0 _diffusion_reverse `hint.sum(-1) != 0`,
  v2.0 forward `hint_mask.view(bs, frames, -1).sum(-1) != 0`), configs/modules/traj_encoder.yaml
  and configs/modules/denoiser.yaml (v2.0: hidden_dim 256, force_post_proj true,
  controlnet_embed_dim 256, controlnet_act_fn silu), mld/data/humanml/dataset.py (the hint:
  (joints - Mean_raw) / Std_raw times the 0/1 mask) and datasets/humanml_spatial_norm/
  {Mean_raw,Std_raw}.npy (66 values at v1.0, [22, 3] at v2.0, the same numbers).

## Input

`--ckpt`: the torch pickle {'state_dict': {...}} the official training scripts save
(train_motionlcm.py: dict(state_dict=base_model.state_dict()) after on_save_checkpoint).
- `denoiser.*`: every tensor below must be present with its shape; `denoiser.mem_pos.pe` is
  recognised and dropped (only a `trans_dec` denoiser creates it, so the released trans_enc
  checkpoints normally lack it); any other `denoiser.*` tensor is an error naming it.
  Without `denoiser.time_embedding.cond_proj.weight` it is an MLD checkpoint: refused (convert.py
  mld takes ChenFengYe/motion-latent-diffusion's CLIP-conditioned MLD).
- `vae.*`: the decoder tensors below must be present; the encoder side (`vae.encoder.*`,
  `vae.skel_embedding.*`, `vae.global_motion_token`, `vae.query_pos_encoder.*`, `vae.dist*`, and
  v2's `vae.latent_pre.*`, which maps the encoder's width to the latent channels) is skipped.
- `t2m_textencoder.*`, `t2m_moveencoder.*`, `t2m_motionencoder.*` (the evaluators) and
  `text_encoder.*` (should a checkpoint carry the frozen text encoder) are skipped.
- `controlnet.*`, `traj_encoder.*` (the trajectory-control checkpoints, configs/
  motionlcm_control*.yaml): converted with --control-mean / --control-std (without them:
  refused, naming the options); both prefixes must be present. `controlnet.latent_post.*` (v2:
  the copy's unused output projection; its output is the residuals) and `controlnet.mem_pos.pe`
  (trans_dec only) are recognised and dropped; any other unexpected `controlnet.*` /
  `traj_encoder.*` tensor is an error naming it. `--skip-prefix controlnet. --skip-prefix
  traj_encoder.` converts the text-to-motion part alone (the file is then the one a text-to-motion
  checkpoint of the same denoiser gives).
- anything else is an error naming it (`--skip-prefix P` skips more).

`--t5`: a sentence-transformers folder as sentence-transformers/sentence-t5-large is published:
modules.json listing exactly Transformer, Pooling, Dense, Normalize in that order; at the
Transformer's path config.json (model_type t5, feed_forward_proj relu: T5 v1.0, not v1.1's gated
GELU), the T5EncoderModel weights (model.safetensors, else pytorch_model.bin; the tied copy
`encoder.embed_tokens.weight` must equal `shared.weight`), tokenizer.json (T5's fast tokenizer:
Unigram, `<pad>` 0, `</s>` 1 appended), sentence_bert_config.json (max_seq_length, else 256;
do_lower_case must be false); the Pooling config with pooling_mode_mean_tokens alone; the Dense
config {in_features = d_model, out_features = the denoiser's text_dim, bias false,
activation_function torch.nn.modules.linear.Identity} and its weight `linear.weight` [out, in]
(model.safetensors, else pytorch_model.bin). The Normalize module has no files (its folder may be
absent). T5's sizes come from the shapes and are checked against config.json.

`--mean`, `--std`: HumanML3D Mean.npy / Std.npy (263 values) -> `motion.mean`, `motion.std`.

`--control-mean`, `--control-std` (control checkpoints only): datasets/humanml_spatial_norm/
Mean_raw.npy / Std_raw.npy of the MotionLCM repository, 66 values each (either [66] or [22, 3]),
read as [22, 3] (joint, axis) -> `control.mean_raw`, `control.std_raw`; the std must be finite
and > 0, the mean finite.

## Tensors of the file

D = denoiser width, T = text_dim (= time_dim, the sinusoid's width), G = cond_dim, P = denoiser
position rows, L x C = the latent (v1: 1 x D; v2: latent_pre's input), D' = VAE width,
P' = VAE position rows, B = (layers - 1) / 2:
  denoiser.time_embedding.linear_1.{weight [D, T], bias [D]}
  denoiser.time_embedding.linear_2.{weight [D, D], bias [D]}
  denoiser.time_embedding.cond_proj.weight [T, G]             (no bias)
  denoiser.emb_proj.1.{weight [D, T], bias [D]}               (after ReLU: v1; Identity: v2)
  denoiser.query_pos.pe [P, 1, D]
  denoiser.encoder.{input_blocks.b, middle_block, output_blocks.b}.{self_attn.*, linear{1,2}.*,
      norm{1,2}.*}, denoiser.encoder.linear_blocks.b.*, denoiser.encoder.norm.*   (as MLD's,
      tools/convert_latent.py)
  denoiser.latent_pre.{weight [D, C], bias [D]}               (v2)
  denoiser.latent_post.{weight [C, D], bias [C]}              (v2)
  vae.query_pos_decoder.pe [P', 1, D'], vae.decoder.* (MLD's decoder skip stack),
      vae.final_layer.{weight [263, D'], bias [263]}
  vae.latent_post.{weight [D', C], bias [D']}                 (v2)
  text.shared.weight [V, d_model]
  text.encoder.block.{i}.layer.0.SelfAttention.{q,k,v}.weight [H*d_kv, d_model], .o.weight
      [d_model, H*d_kv]; text.encoder.block.0.layer.0.SelfAttention.relative_attention_bias.weight
      [buckets, H]; text.encoder.block.{i}.layer.0.layer_norm.weight [d_model];
      text.encoder.block.{i}.layer.1.DenseReluDense.{wi [d_ff, d_model], wo [d_model, d_ff]}.weight;
      text.encoder.block.{i}.layer.1.layer_norm.weight; text.encoder.final_layer_norm.weight
  text.dense.weight [T, d_model]                              (sentence-transformers' Dense)
  motion.mean [263], motion.std [263]                         (float32 whatever --dtype)
With trajectory control (E = the ControlNet's embed width: v1 D, v2 controlnet_embed_dim;
N_t, F_t, P_t = the trajectory encoder's layers, ff size, position rows; its width must be D):
  controlnet.{time_embedding.*, emb_proj.1.*, query_pos.pe, encoder.{input_blocks, middle_block,
      output_blocks, linear_blocks}.*, latent_pre.* (v2)}   (the copy, the denoiser's names and
      shapes, NO encoder.norm)
  controlnet.controlnet_cond_embedding.{k}.{weight, bias}   v1: k = 0, 1, 2 each [D, D] (three
      Linear, no activation); v2: 0 [E, C], 2 [E, E], 4 [C, E] (SiLU after 0 and 2)
  controlnet.controlnet_down_mid_blocks.{i}.{weight [D, D], bias [D]}   i < layers
  traj_encoder.skel_embedding.{weight [D, 66], bias [D]}
  traj_encoder.global_motion_token [L, D]
  traj_encoder.query_pos_encoder.pe [P_t, 1, D]
  traj_encoder.encoder.* (the skip stack, with encoder.norm.{weight, bias})
  traj_encoder.latent_proj.{weight [C, D], bias [C]}        (v2)
  control.mean_raw [22, 3], control.std_raw [22, 3]          (float32 whatever --dtype)
Metadata: `format` = `libflame`, `flame.config` (below), `flame.tokenizer` = tokenizer.json.

## Configuration (`flame.config`)

  {"format_version": 1, "architecture": "motionlcm",
   "denoiser": {"latent_dim": D, "latent_tokens": L, "latent_channels": C, "text_dim": T,
                "cond_dim": G, "layers", "heads" (--heads), "ff_size", "max_len": P,
                "text_activation": "relu" (v1) | "none" (v2), "activation": "gelu",
                "layer_norm_eps": 1e-5},
   "vae": {"latent_dim": D', "latent_channels": C, "layers", "heads", "ff_size", "nfeats": 263,
           "max_len": P', "final_norm", "activation": "gelu", "layer_norm_eps": 1e-5},
   "text_encoder": {"kind": "t5", "max_length": max_seq_length,
                    "relative_attention_max_distance": config.json's (default 128)},
   "motion": {"format": "humanml263", "fps": 20.0},
   "diffusion": {"num_timesteps": 1000, "schedule": "scaled_linear", "parameterization":
                 "epsilon", "variance": "fixed_small", "clip_denoised": false,
                 "uncond": "empty_prompt", "spacing": "lcm", "set_alpha_to_one": false,
                 "lcm_timesteps": "grid" (v1) | "motionlcm_v2" (v2),
                 "original_inference_steps": 50 (v1) | 10 (v2), "timestep_scaling": 10.0},
   "defaults": {"sampler": "lcm", "steps": 1, "guidance": 7.5 (v1) | 8.0 (v2), "eta": 0.0,
                "frames": --frames, "guidance_by_steps": null (v1) |
                {"1": 8.0, "2": 12.5, "4": 13.5} (v2)},
   "control": (trajectory-control files only; absent otherwise)
               {"joints": 22, "layers": N_t, "heads" (--heads), "ff_size": F_t, "max_len": P_t,
                "embed_activation": "none" (v1) | "silu" (v2), "embed_dim": E,
                "frame_mask": "row_sum" (v1: a frame is attended when its 66 normalised masked
                values do not sum to 0) | "mask" (v2: when any of its values is hinted),
                "scale": 1.0 (v1 multiplies the residuals by control_scale 1.0; v2 does not)}}
L: 1 for v1; for v2 the VAE's `global_motion_token` rows / 2 (its encoder makes mu and logvar
tokens), else --latent-tokens (default 16, the released [16, 32]) - the denoiser's shapes do not
tell it; a trajectory encoder's `global_motion_token` must have L rows. The head counts are not in
any shape (--heads, official 4; also used for the ControlNet and the trajectory encoder). The text
activation is told by the release (v2.0's configs/modules/denoiser.yaml sets text_act_fn null).
"""
import json
import os
import time

import torch

from convert import DTYPES, FORMAT_VERSION, ConvertError, cast, read_stats, warn
from convert_latent import (MLD_SKIP_TOP, MLD_VAE_ENCODER, load_dict, mld_denoiser_shapes,
                            mld_stack_layers, mld_stack_shapes, mld_vae_shapes, shape_of, take)

CONTROL_TOP = ("controlnet.", "traj_encoder.")
F32_TOP = ("motion.", "control.")  # statistics stay float32 whatever --dtype
JOINTS = 22  # HumanML3D's joints (the hint's 66 = 22 x 3 values per frame)
SKIP_TOP = MLD_SKIP_TOP
VAE_ENCODER = MLD_VAE_ENCODER + ("vae.latent_pre.",)
COND_PROJ = "time_embedding.cond_proj.weight"
ST_TYPES = ["sentence_transformers.models.Transformer", "sentence_transformers.models.Pooling",
            "sentence_transformers.models.Dense", "sentence_transformers.models.Normalize"]
IDENTITY = "torch.nn.modules.linear.Identity"
T5_EPS = 1e-6
V2_GUIDANCE = {"1": 8.0, "2": 12.5, "4": 13.5}


# -- sentence-t5 ----------------------------------------------------------------------------------

def _json(path, what):
    if not os.path.isfile(path):
        raise ConvertError(f"{path} not found ({what})")
    with open(path) as f:
        try:
            return json.load(f)
        except json.JSONDecodeError as e:
            raise ConvertError(f"{path}: not JSON ({e})") from None


def _weights(folder, what):
    """{name: tensor} from folder/model.safetensors, else folder/pytorch_model.bin."""
    st, pt = os.path.join(folder, "model.safetensors"), os.path.join(folder, "pytorch_model.bin")
    if os.path.isfile(st):
        from safetensors.torch import load_file
        return load_file(st), st
    if os.path.isfile(pt):
        state = torch.load(pt, map_location="cpu", weights_only=True)
        if not isinstance(state, dict):
            raise ConvertError(f"{pt}: not a state dict")
        return {k: v for k, v in state.items() if torch.is_tensor(v)}, pt
    raise ConvertError(f"{folder}: neither model.safetensors nor pytorch_model.bin ({what})")


def t5_shapes(d, inner, heads, buckets, d_ff, layers, vocab):
    s = {"shared.weight": (vocab, d), "encoder.final_layer_norm.weight": (d,),
         "encoder.block.0.layer.0.SelfAttention.relative_attention_bias.weight": (buckets, heads)}
    for i in range(layers):
        p = f"encoder.block.{i}.layer."
        for n in ("q", "k", "v"):
            s[f"{p}0.SelfAttention.{n}.weight"] = (inner, d)
        s[f"{p}0.SelfAttention.o.weight"] = (d, inner)
        s[f"{p}0.layer_norm.weight"] = (d,)
        s[f"{p}1.DenseReluDense.wi.weight"] = (d_ff, d)
        s[f"{p}1.DenseReluDense.wo.weight"] = (d, d_ff)
        s[f"{p}1.layer_norm.weight"] = (d,)
    return s


def read_sentence_t5(folder, text_dim):
    """(text_encoder config, {name under text.: tensor}, tokenizer.json text, summary)."""
    if not os.path.isdir(folder):
        raise ConvertError(f"--t5 {folder}: not a directory")
    mpath = os.path.join(folder, "modules.json")
    mods = _json(mpath, "the sentence-transformers module list")
    if not isinstance(mods, list) or [m.get("type") for m in mods] != ST_TYPES:
        got = [m.get("type") for m in mods] if isinstance(mods, list) else mods
        raise ConvertError(f"{mpath}: modules {got}; want exactly {ST_TYPES} (sentence-t5's "
                           f"Transformer, mean Pooling, Dense, Normalize)")
    mods = sorted(mods, key=lambda m: m.get("idx", 0))
    tdir, pdir, ddir = (os.path.join(folder, m.get("path", "")) for m in mods[:3])

    # T5 encoder: config.json and weights
    cpath = os.path.join(tdir, "config.json")
    hf = _json(cpath, "the T5 configuration")
    if hf.get("model_type") != "t5":
        raise ConvertError(f"{cpath}: model_type {hf.get('model_type')!r}, want 't5'")
    ffp = hf.get("feed_forward_proj", "relu")
    if ffp != "relu":
        raise ConvertError(f"{cpath}: feed_forward_proj {ffp!r}; only T5 v1.0's 'relu' "
                           f"feed-forward is supported (sentence-t5), not a gated one (T5 v1.1)")
    eps = float(hf.get("layer_norm_epsilon", T5_EPS))
    if eps != T5_EPS:
        raise ConvertError(f"{cpath}: layer_norm_epsilon {eps}; the format assumes T5's 1e-6")
    max_distance = int(hf.get("relative_attention_max_distance", 128))
    state, wpath = _weights(tdir, "the T5 encoder")
    gated = sorted(k for k in state if ".DenseReluDense.wi_0." in k or ".DenseReluDense.wi_1." in k)
    if gated:
        raise ConvertError(f"{wpath}: '{gated[0]}' is a gated feed-forward (T5 v1.1); only T5 "
                           f"v1.0 (ReLU, `wi`) is supported")
    tied = state.pop("encoder.embed_tokens.weight", None)
    if tied is not None:
        if "shared.weight" not in state or not torch.equal(tied, state["shared.weight"]):
            raise ConvertError(f"{wpath}: 'encoder.embed_tokens.weight' differs from "
                               f"'shared.weight' (T5 ties them)")
    what = f"T5 encoder ({wpath})"
    vocab, d = shape_of(state, "shared.weight", what, 2)
    buckets, heads = shape_of(
        state, "encoder.block.0.layer.0.SelfAttention.relative_attention_bias.weight", what, 2)
    inner = shape_of(state, "encoder.block.0.layer.0.SelfAttention.q.weight", what, 2)[0]
    d_ff = shape_of(state, "encoder.block.0.layer.1.DenseReluDense.wi.weight", what, 2)[0]
    layers = len({k.split(".")[2] for k in state if k.startswith("encoder.block.")})
    if heads == 0 or inner % heads or buckets < 4 or buckets % 2:
        raise ConvertError(f"{what}: {heads} heads over {inner} and {buckets} buckets do not fit")
    for key, have in (("d_model", d), ("num_heads", heads), ("d_kv", inner // heads),
                      ("d_ff", d_ff), ("num_layers", layers), ("vocab_size", vocab),
                      ("relative_attention_num_buckets", buckets)):
        if key in hf and int(hf[key]) != have:
            raise ConvertError(f"{cpath}: {key} = {hf[key]} but the weights have {have}")
    if max_distance <= buckets // 4:
        raise ConvertError(f"{cpath}: relative_attention_max_distance {max_distance} must exceed "
                           f"the {buckets // 4} exact buckets")
    tensors = take(state, t5_shapes(d, inner, heads, buckets, d_ff, layers, vocab), what)

    # tokenizer and sentence_bert_config
    tpath = os.path.join(tdir, "tokenizer.json")
    if not os.path.isfile(tpath):
        raise ConvertError(f"{tpath} not found (the libflame file embeds T5's fast tokenizer)")
    with open(tpath) as f:
        tokenizer = f.read()
    tok_json = json.loads(tokenizer)
    if (tok_json.get("model") or {}).get("type") != "Unigram":
        raise ConvertError(f"{tpath}: model type {(tok_json.get('model') or {}).get('type')!r}, "
                           f"want T5's Unigram")
    from tokenizers import Tokenizer
    tok = Tokenizer.from_str(tokenizer)
    if tok.token_to_id("<pad>") != 0 or tok.token_to_id("</s>") != 1:
        raise ConvertError(f"{tpath}: want T5's '<pad>' = 0 and '</s>' = 1, have "
                           f"{tok.token_to_id('<pad>')} and {tok.token_to_id('</s>')}")
    probe = tok.encode("a").ids
    if not probe or probe[-1] != 1:
        raise ConvertError(f"{tpath}: '</s>' (1) is not appended to an encoded text ({probe})")
    if tok.get_vocab_size() > vocab:
        raise ConvertError(f"{tpath}: {tok.get_vocab_size()} tokens but only {vocab} embedding "
                           f"rows")
    sb = os.path.join(tdir, "sentence_bert_config.json")
    sbc = _json(sb, "sentence-transformers' settings") if os.path.isfile(sb) else {}
    max_length = int(sbc.get("max_seq_length") or 256)
    if sbc.get("do_lower_case"):
        raise ConvertError(f"{sb}: do_lower_case true is not supported (sentence-t5: false)")
    if not 2 <= max_length <= 4096:
        raise ConvertError(f"{sb}: max_seq_length {max_length} outside 2..4096")

    # Pooling: mean over the tokens the attention mask keeps, nothing else
    ppath = os.path.join(pdir, "config.json")
    pool = _json(ppath, "the Pooling configuration")
    modes = {k: v for k, v in pool.items() if k.startswith("pooling_mode_")}
    if modes.get("pooling_mode_mean_tokens") is not True or any(
            v for k, v in modes.items() if k != "pooling_mode_mean_tokens"):
        raise ConvertError(f"{ppath}: pooling modes {modes}; only mean pooling "
                           f"(pooling_mode_mean_tokens alone) is supported")
    if int(pool.get("word_embedding_dimension", d)) != d:
        raise ConvertError(f"{ppath}: word_embedding_dimension {pool['word_embedding_dimension']}"
                           f" != d_model {d}")

    # Dense: [text_dim, d_model], no bias, identity activation
    dpath = os.path.join(ddir, "config.json")
    dense = _json(dpath, "the Dense configuration")
    if dense.get("bias", True) is not False:
        raise ConvertError(f"{dpath}: bias {dense.get('bias', True)}; sentence-t5's Dense has none")
    if dense.get("activation_function") != IDENTITY:
        raise ConvertError(f"{dpath}: activation_function {dense.get('activation_function')!r}, "
                           f"want {IDENTITY}")
    if dense.get("in_features") != d:
        raise ConvertError(f"{dpath}: in_features {dense.get('in_features')} != the T5 width {d}")
    if dense.get("out_features") != text_dim:
        raise ConvertError(f"{dpath}: out_features {dense.get('out_features')} != the denoiser's "
                           f"text_dim {text_dim}")
    dstate, dw = _weights(ddir, "the Dense layer")
    tensors["dense.weight"] = take(dstate, {"linear.weight": (text_dim, d)},
                                   f"Dense ({dw})")["linear.weight"]

    cfg = {"kind": "t5", "max_length": max_length, "relative_attention_max_distance": max_distance}
    summary = f"T5 {layers}x{d} heads {heads} ff {d_ff} -> {text_dim}"
    return cfg, tensors, tokenizer, summary


# -- checkpoint -----------------------------------------------------------------------------------

def split_checkpoint(state, what, skip_prefix, control_ok=False):
    """(denoiser, vae, controlnet, traj_encoder, skipped count, vae.global_motion_token): the
    tensors under each prefix with the prefix removed. A `controlnet.*` / `traj_encoder.*` tensor
    not skipped is refused unless `control_ok` (--control-mean and --control-std given)."""
    den, vae, ctl, traj, skipped, gmt = {}, {}, {}, {}, 0, None
    skip = SKIP_TOP + tuple(skip_prefix or ())
    control = sorted(k for k in state if k.startswith(CONTROL_TOP) and not k.startswith(skip))
    if control and not control_ok:
        raise ConvertError(f"{what}: '{control[0]}' is a trajectory-control (ControlNet) tensor; "
                           f"converting trajectory control needs --control-mean Mean_raw.npy "
                           f"--control-std Std_raw.npy (datasets/humanml_spatial_norm/ in the "
                           f"MotionLCM repository); --skip-prefix controlnet. --skip-prefix "
                           f"traj_encoder. converts the text-to-motion part alone")
    for k, v in state.items():
        if k.startswith("denoiser."):
            den[k[len("denoiser."):]] = v
        elif k.startswith(VAE_ENCODER) or k.startswith(skip):
            if k == "vae.global_motion_token":
                gmt = v
            skipped += 1
        elif k.startswith("controlnet."):
            ctl[k[len("controlnet."):]] = v
        elif k.startswith("traj_encoder."):
            traj[k[len("traj_encoder."):]] = v
        elif k.startswith("vae."):
            vae[k[len("vae."):]] = v
        else:
            raise ConvertError(f"{what}: unknown tensor '{k}' (--skip-prefix to skip it)")
    if not den:
        raise ConvertError(f"{what}: no 'denoiser.*' tensors")
    if COND_PROJ not in den:
        raise ConvertError(f"{what}: no 'denoiser.{COND_PROJ}' (the guidance-scale embedding's "
                           f"projection every MotionLCM denoiser has): this is an MLD checkpoint; "
                           f"convert MLD checkpoints with `convert.py mld`")
    if any(k.startswith("decoder.") for k in den):
        raise ConvertError(f"{what}: a 'trans_dec' denoiser ('denoiser.decoder.*'); only the "
                           f"released 'trans_enc' denoiser is supported")
    if bool(ctl) != bool(traj):
        have, lack = ("controlnet", "traj_encoder") if ctl else ("traj_encoder", "controlnet")
        raise ConvertError(f"{what}: '{have}.*' tensors without '{lack}.*' ones; trajectory "
                           f"control needs both (or --skip-prefix both)")
    return den, vae, ctl, traj, skipped, gmt


def read_control_stats(path, what):
    """Mean_raw.npy / Std_raw.npy: 66 values ([66] at v1.0, [22, 3] at v2.0) -> [22, 3] float32."""
    import numpy as np
    if not path or not os.path.isfile(path):
        raise ConvertError(f"{path}: no such {what} file")
    try:
        a = np.load(path)
    except Exception as e:  # noqa: BLE001 - any unreadable file
        raise ConvertError(f"{path}: not a .npy array ({e})") from None
    if a.size != 3 * JOINTS or a.shape not in ((3 * JOINTS,), (JOINTS, 3)):
        raise ConvertError(f"{path}: {what} has shape {a.shape}, want [{3 * JOINTS}] or "
                           f"[{JOINTS}, 3] (HumanML3D's 22 joints x 3 axes)")
    a = a.astype(np.float64).reshape(JOINTS, 3)
    if not np.isfinite(a).all():
        raise ConvertError(f"{path}: {what} has NaN or Inf entries")
    if what == "Std_raw" and (a <= 0).any():
        j, x = (int(i) for i in np.argwhere(a <= 0)[0])
        raise ConvertError(f"{path}: Std_raw must be > 0; joint {j} axis {x} is {a[j, x]}")
    return torch.from_numpy(a).float()


def control_part(ctl, traj, what, v2, dc, dshapes, heads, frames):
    """Checks the ControlNet copy and the trajectory encoder against the denoiser's sizes;
    returns ({file name: tensor}, the `control` configuration)."""
    d, c, layers, tokens = (dc["latent_dim"], dc["latent_channels"], dc["layers"],
                            dc["latent_tokens"])
    # The copy: the denoiser's tensors without the final norm (is_controlnet) and without the
    # unused output projection / memory positions.
    ctl = dict(ctl)
    for k in [k for k in ctl if k.startswith(("latent_post.", "mem_pos."))]:
        ctl.pop(k)
    cw = what + " controlnet.*"
    if v2:
        keys, acts = ("0", "2", "4"), "silu"
        e = shape_of(ctl, "controlnet_cond_embedding.0.weight", cw, 2)[0]
        emb = {"0": (e, c), "2": (e, e), "4": (c, e)}
    else:
        keys, acts, e = ("0", "1", "2"), "none", d
        emb = {k: (d, d) for k in keys}
    got = sorted({k.split(".")[1] for k in ctl if k.startswith("controlnet_cond_embedding.")})
    if got != sorted(keys):
        raise ConvertError(f"{what}: controlnet.controlnet_cond_embedding has modules {got}; the "
                           f"{'v2' if v2 else 'v1'} ControlNet has Linear layers {list(keys)} "
                           f"({'Linear, SiLU, Linear, SiLU, Linear' if v2 else 'three Linear'})")
    shapes = {k: v for k, v in dshapes.items()
              if not k.startswith(("encoder.norm.", "latent_post."))}
    for k, (o, i) in emb.items():
        shapes[f"controlnet_cond_embedding.{k}.weight"] = (o, i)
        shapes[f"controlnet_cond_embedding.{k}.bias"] = (o,)
    for i in range(layers):
        shapes[f"controlnet_down_mid_blocks.{i}.weight"] = (d, d)
        shapes[f"controlnet_down_mid_blocks.{i}.bias"] = (d,)
    tensors = {"controlnet." + k: v
               for k, v in take(ctl, shapes, what, "controlnet.").items()}

    # The trajectory encoder.
    tw = what + " traj_encoder.*"
    dt, nin = shape_of(traj, "skel_embedding.weight", tw, 2)
    if nin != 3 * JOINTS:
        raise ConvertError(f"{what}: traj_encoder.skel_embedding.weight [{dt}, {nin}], want "
                           f"[D, {3 * JOINTS}] (22 joints x 3)")
    if dt != d:
        raise ConvertError(f"{what}: the trajectory encoder's width {dt} != the denoiser's {d} "
                           f"(the format has one width)")
    lt = shape_of(traj, "global_motion_token", tw, 2)[0]
    if lt != tokens:
        raise ConvertError(f"{what}: traj_encoder.global_motion_token has {lt} rows, the latent "
                           f"has {tokens} tokens (the encoder's output is the ControlNet's "
                           f"condition, one row per latent token)")
    if v2 != ("latent_proj.weight" in traj):
        raise ConvertError(f"{what}: traj_encoder.latent_proj "
                           f"{'missing' if v2 else 'present'}; the {'v2' if v2 else 'v1'} "
                           f"trajectory encoder {'projects' if v2 else 'does not project'} its "
                           f"output to the latent channels")
    tc = {"joints": JOINTS, "layers": mld_stack_layers(traj, "encoder.", tw), "heads": heads,
          "ff_size": shape_of(traj, "encoder.middle_block.linear1.weight", tw, 2)[0],
          "max_len": shape_of(traj, "query_pos_encoder.pe", tw, 3)[0],
          "embed_activation": acts, "embed_dim": e, "frame_mask": "mask" if v2 else "row_sum",
          "scale": 1.0}
    tshapes = {"skel_embedding.weight": (d, 3 * JOINTS), "skel_embedding.bias": (d,),
               "global_motion_token": (tokens, d), "query_pos_encoder.pe": (tc["max_len"], 1, d)}
    tshapes.update(mld_stack_shapes("encoder.", tc["layers"], d, tc["ff_size"], False, True))
    if v2:
        tshapes.update({"latent_proj.weight": (c, d), "latent_proj.bias": (c,)})
    elif c != d:
        raise ConvertError(f"{what}: the trajectory encoder's output width {d} != the latent "
                           f"channels {c}")
    tensors.update({"traj_encoder." + k: v
                    for k, v in take(traj, tshapes, what, "traj_encoder.").items()})
    if tc["max_len"] < tokens + frames:
        raise ConvertError(f"{what}: traj_encoder.query_pos_encoder.pe has {tc['max_len']} rows; "
                           f"{tokens} tokens + --frames {frames} need {tokens + frames}")
    return tensors, tc


def write_file(tensors, config, tokenizer, out, dtype_name):
    """convert_latent.write, with `control.*` statistics kept float32 like `motion.*`."""
    from safetensors.torch import save_file
    dtype = DTYPES[dtype_name]
    t = {k: (v.float().contiguous() if k.startswith(F32_TOP) else cast(v, dtype, k))
         for k, v in tensors.items()}
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    save_file(t, out, metadata={"format": "libflame", "flame.config": json.dumps(config),
                                "flame.tokenizer": tokenizer})
    return sum(v.numel() for v in t.values()), len(t)


def convert_motionlcm(args):
    t0 = time.perf_counter()
    state = load_dict(args.ckpt, "state_dict")
    what = f"{args.ckpt} (state_dict)"
    control_ok = bool(args.control_mean and args.control_std)
    den, vae, ctl, traj, skipped, gmt = split_checkpoint(state, what, args.skip_prefix,
                                                         control_ok)
    if (args.control_mean or args.control_std) and not ctl:
        raise ConvertError(f"{what}: --control-mean / --control-std given but the checkpoint has "
                           f"no (unskipped) 'controlnet.*' / 'traj_encoder.*' tensors")
    v2 = "latent_pre.weight" in den
    den.pop("mem_pos.pe", None)  # trans_dec only; recognised, unused by trans_enc
    heads = args.heads
    dw = what + " denoiser.*"
    d, t = shape_of(den, "time_embedding.linear_1.weight", dw, 2)
    t_out, g = shape_of(den, COND_PROJ, dw, 2)
    e_out, e_in = shape_of(den, "emb_proj.1.weight", dw, 2)
    if t_out != t or e_in != t or e_out != d:
        raise ConvertError(f"{what}: cond_proj [{t_out}, {g}], emb_proj.1 [{e_out}, {e_in}] with "
                           f"linear_1 [{d}, {t}]: the format wants time_dim = text_dim = {t} and "
                           f"width {d}")
    if v2:
        pre_out, c = shape_of(den, "latent_pre.weight", dw, 2)
        if pre_out != d:
            raise ConvertError(f"{what}: denoiser.latent_pre.weight [{pre_out}, {c}], want "
                               f"[{d}, C]")
    else:
        c = d
    vw = what + " vae.* (decoder)"
    vd = shape_of(vae, "final_layer.weight", vw, 2)
    vc = {"latent_dim": vd[1], "latent_channels": c,
          "layers": mld_stack_layers(vae, "decoder.", vw), "heads": heads,
          "ff_size": shape_of(vae, "decoder.middle_block.linear1.weight", vw, 2)[0],
          "nfeats": vd[0], "max_len": shape_of(vae, "query_pos_decoder.pe", vw, 3)[0],
          "final_norm": "decoder.norm.weight" in vae, "activation": "gelu",
          "layer_norm_eps": 1e-5}
    dv = vc["latent_dim"]

    # latent tokens
    if gmt is not None and (gmt.dim() != 2 or gmt.shape[0] % 2 or gmt.shape[1] != dv):
        raise ConvertError(f"{what}: vae.global_motion_token has shape {tuple(gmt.shape)}, want "
                           f"[2L, {dv}]")
    from_vae = None if gmt is None else gmt.shape[0] // 2
    if v2:
        if from_vae is not None:
            if args.latent_tokens is not None and args.latent_tokens != from_vae:
                raise ConvertError(f"--latent-tokens {args.latent_tokens} but the VAE's "
                                   f"global_motion_token says {from_vae}")
            lat_tokens = from_vae
        else:
            lat_tokens = 16 if args.latent_tokens is None else args.latent_tokens
            warn(f"{what}: no vae.global_motion_token; latent tokens {lat_tokens} from "
                 f"--latent-tokens (the shapes do not tell it; released v2: 16)")
    else:
        if from_vae not in (None, 1) or args.latent_tokens not in (None, 1):
            raise ConvertError(f"{what}: a v1 (no latent_pre) model has one latent token; the "
                               f"VAE / --latent-tokens say {from_vae} / {args.latent_tokens}")
        lat_tokens = 1
    if lat_tokens < 1:
        raise ConvertError(f"latent tokens {lat_tokens} must be >= 1")

    dc = {"latent_dim": d, "latent_tokens": lat_tokens, "latent_channels": c, "text_dim": t,
          "cond_dim": g, "layers": mld_stack_layers(den, "encoder.", dw), "heads": heads,
          "ff_size": shape_of(den, "encoder.middle_block.linear1.weight", dw, 2)[0],
          "max_len": shape_of(den, "query_pos.pe", dw, 3)[0],
          "text_activation": "none" if v2 else "relu", "activation": "gelu",
          "layer_norm_eps": 1e-5}
    if heads < 1 or d % heads or dv % heads:
        raise ConvertError(f"{what}: --heads {heads} must divide the widths {d} and {dv}")
    if t % 2 or g % 2:
        raise ConvertError(f"{what}: time/text dim {t} and cond_dim {g} must be even")
    if vc["nfeats"] != 263:
        raise ConvertError(f"{what}: the VAE makes {vc['nfeats']} features, want 263")
    if not v2 and dv != d:
        raise ConvertError(f"{what}: VAE width {dv} != the denoiser's latent width {d} (v1 "
                           f"decodes the denoiser's latent directly)")
    if dc["max_len"] < lat_tokens + 2:
        raise ConvertError(f"{what}: denoiser.query_pos.pe has {dc['max_len']} rows, the sequence "
                           f"needs {lat_tokens + 2}")
    if not 1 <= args.frames <= vc["max_len"]:
        raise ConvertError(f"--frames {args.frames} outside 1..{vc['max_len']} (the VAE's "
                           f"position rows)")

    dshapes = mld_denoiser_shapes(dc)
    dshapes[COND_PROJ] = (t, g)
    vshapes = mld_vae_shapes(vc)
    if v2:
        dshapes.update({"latent_pre.weight": (d, c), "latent_pre.bias": (d,),
                        "latent_post.weight": (c, d), "latent_post.bias": (c,)})
        vshapes.update({"latent_post.weight": (dv, c), "latent_post.bias": (dv,)})
    tensors = {"denoiser." + k: v for k, v in take(den, dshapes, what, "denoiser.").items()}
    tensors.update({"vae." + k: v for k, v in take(vae, vshapes, what, "vae.").items()})
    control_cfg = None
    if ctl:
        ctensors, control_cfg = control_part(ctl, traj, what, v2, dc, dshapes, heads, args.frames)
        tensors.update(ctensors)
        tensors["control.mean_raw"] = read_control_stats(args.control_mean, "Mean_raw")
        tensors["control.std_raw"] = read_control_stats(args.control_std, "Std_raw")

    text_cfg, text, tokenizer, text_summary = read_sentence_t5(args.t5, t)
    tensors.update({"text." + k: v for k, v in text.items()})
    tensors["motion.mean"] = read_stats(args.mean, 263, "mean")
    tensors["motion.std"] = read_stats(args.std, 263, "std")

    config = {
        "format_version": FORMAT_VERSION, "architecture": "motionlcm", "denoiser": dc, "vae": vc,
        "text_encoder": text_cfg, "motion": {"format": "humanml263", "fps": 20.0},
        "diffusion": {"num_timesteps": 1000, "schedule": "scaled_linear",
                      "parameterization": "epsilon", "variance": "fixed_small",
                      "clip_denoised": False, "uncond": "empty_prompt", "spacing": "lcm",
                      "set_alpha_to_one": False,
                      "lcm_timesteps": "motionlcm_v2" if v2 else "grid",
                      "original_inference_steps": 10 if v2 else 50, "timestep_scaling": 10.0},
        "defaults": {"sampler": "lcm", "steps": 1, "guidance": 8.0 if v2 else 7.5, "eta": 0.0,
                     "frames": args.frames,
                     "guidance_by_steps": dict(V2_GUIDANCE) if v2 else None},
    }
    if control_cfg is not None:
        config["control"] = control_cfg
    n, count = write_file(tensors, config, tokenizer, args.out, args.dtype)
    print(f"wrote {args.out}: motionlcm {'v2' if v2 else 'v1'}, {count} tensors, {n / 1e6:.2f} M "
          f"values ({args.dtype}); latent [{lat_tokens}, {c}] width {d}/{dv} layers "
          f"{dc['layers']}/{vc['layers']} heads {heads} cond {g}; {text_summary}; "
          f"{control_summary(control_cfg)}skipped "
          f"{skipped} tensors (VAE encoder, evaluators); {time.perf_counter() - t0:.1f} s")
    return 0


def control_summary(tc):
    if tc is None:
        return ""
    return (f"trajectory control: encoder {tc['layers']} layers ff {tc['ff_size']} rows "
            f"{tc['max_len']}, embed {tc['embed_dim']} ({tc['embed_activation']}), frame mask "
            f"{tc['frame_mask']}; ")


def add_parsers(sub):
    p = sub.add_parser("motionlcm", help="Dai-Wenxun/MotionLCM v1.0 / v2.0 checkpoint")
    p.add_argument("--ckpt", required=True, help="official .ckpt ({'state_dict': ...})")
    p.add_argument("--t5", required=True,
                   help="sentence-transformers folder of sentence-t5-large (modules.json, "
                        "config.json, weights, tokenizer.json, 1_Pooling, 2_Dense)")
    p.add_argument("--mean", required=True, help="HumanML3D Mean.npy (263 values)")
    p.add_argument("--std", required=True, help="HumanML3D Std.npy (263 values)")
    p.add_argument("--out", required=True, help="output .safetensors")
    p.add_argument("--heads", type=int, default=4, help="attention heads (not in shapes)")
    p.add_argument("--dtype", choices=sorted(DTYPES), default="f32")
    p.add_argument("--frames", type=int, default=196,
                   help="default motion length (at most the VAE's position rows)")
    p.add_argument("--skip-prefix", action="append",
                   help="also skip tensors whose name starts with this (repeatable)")
    p.add_argument("--latent-tokens", type=int, default=None,
                   help="v2 latent tokens when the checkpoint has no vae.global_motion_token "
                        "(default 16)")
    p.add_argument("--control-mean", default=None,
                   help="trajectory control: Mean_raw.npy (datasets/humanml_spatial_norm/, 66 "
                        "values); required with a controlnet.* checkpoint")
    p.add_argument("--control-std", default=None,
                   help="trajectory control: Std_raw.npy (66 values, > 0)")
    p.set_defaults(func=convert_motionlcm)
