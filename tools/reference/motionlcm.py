"""PyTorch reference of MotionLCM's text-to-motion inference (Dai et al., ECCV 2024;
github.com/Dai-Wenxun/MotionLCM, v1.0 f534a7f and v2.0 086f8db), run on a converted libflame file
(tools/convert_motionlcm.py documents its tensors and configuration).

Facts, with the official file they come from:
- Denoiser (mld/models/architectures/mld_denoiser.py, both tags; `trans_enc`): MLD's skip
  transformer, reused here from reference/mld.py (EncoderLayer, SkipStack, LearnedPE,
  time_sinusoid). The sequence is [latent tokens..., time, text] plus the learned `query_pos.pe`;
  the output is the first L tokens. v2 wraps it in `latent_pre` Linear(C -> D) before and
  `latent_post` Linear(D -> C) after (configs/modules/denoiser.yaml at v2.0: force_pre_post_proj).
- Time token (mld/models/operator/embeddings.py at v2.0, mld/models/architectures/tools/
  embeddings.py at v1.0, TimestepEmbedding): linear_2(SiLU(linear_1(sinusoid(t) +
  cond_proj(e(w))))), the sinusoid time_dim wide, cos half first, frequency shift 0;
  `cond_proj` Linear(cond_dim -> time_dim) without bias.
- Text token: emb_proj = Sequential(act, Linear(text_dim -> D)); act ReLU at v1.0 (hard-coded in
  mld_denoiser.py), Identity at v2.0 (configs/modules/denoiser.yaml: text_act_fn null).
- Guidance embedding e(w) (mld/utils/utils.py get_guidance_scale_embedding, both tags): w·1000
  times exp(-ln(10000)/(half-1)·i), i < half = cond_dim/2, float32, [sin, cos]. The embedded w is
  guidance_scale - 1 (mld/models/modeltype/mld.py, _diffusion_reverse); one denoiser pass per
  step, no classifier-free guidance (do_classifier_free_guidance is false with a cond_proj).
- VAE decoder (mld/models/architectures/mld_vae.py, decode): reference/mld.py's VaeDecoder; v2
  first applies `vae.latent_post` Linear(C -> D').
- Sampler: diffusers' LCMScheduler through reference/diffusers_lcm.py: v1 its grid
  (original_inference_steps 50; configs/modules/scheduler.yaml at v1.0), v2 the table of
  configs/modules/scheduler_lcm.yaml at v2.0 (1: [799], 2: [699, 299], 4: [699, 399, 299, 299])
  set as mld/models/schedulers/scheduling_lcm.py does; the re-noising draws are given.
- Text encoder (mld/models/architectures/mld_clip.py: SentenceTransformer(sentence-t5-large)
  .encode): transformers' T5EncoderModel, mean pooling over the attention mask, the Dense layer
  without bias, L2 normalisation.
"""
import json
import math
from contextlib import contextmanager

import torch
import torch.nn.functional as F
from torch import nn

from reference import diffusers_lcm
from reference.mld import EncoderLayer, LearnedPE, SkipStack, VaeDecoder, time_sinusoid

V1_GUIDANCE = 7.5
V2_GUIDANCE = {1: 8.0, 2: 12.5, 4: 13.5}
V2_TIMESTEPS = {1: [799], 2: [699, 299], 4: [699, 399, 299, 299]}


def guidance_embedding(w, dim):
    """`[B]` guidance values (already guidance_scale - 1) -> `[B, dim]`: sin half first."""
    half = dim // 2
    step = torch.log(torch.tensor(10000.0)) / (half - 1)
    freqs = torch.exp(torch.arange(half, dtype=torch.float32) * -step)
    a = (w.to(torch.float32) * 1000.0)[:, None] * freqs[None, :]
    out = torch.cat([a.sin(), a.cos()], dim=1)
    return F.pad(out, (0, 1)) if dim % 2 else out


class Denoiser(nn.Module):
    """Module names = the file's `denoiser.*` names. `projected`: v2's latent_pre (C -> D) and
    latent_post (D -> C) around the stack (v1: the latent is the width itself)."""

    def __init__(self, latent_dim, latent_tokens, latent_channels, text_dim, cond_dim, layers,
                 heads, ff_size, max_len, text_activation, projected):
        super().__init__()
        d, self.text_dim, self.tokens = latent_dim, text_dim, latent_tokens
        self.time_embedding = nn.Module()
        self.time_embedding.linear_1 = nn.Linear(text_dim, d)
        self.time_embedding.linear_2 = nn.Linear(d, d)
        self.time_embedding.cond_proj = nn.Linear(cond_dim, text_dim, bias=False)
        act = {"relu": nn.ReLU(), "none": nn.Identity()}[text_activation]
        self.emb_proj = nn.Sequential(act, nn.Linear(text_dim, d))
        self.query_pos = LearnedPE(max_len, d)
        self.encoder = SkipStack(EncoderLayer, layers, d, heads, ff_size)
        self.projected = projected
        if projected:  # v2
            self.latent_pre = nn.Linear(latent_channels, d)
            self.latent_post = nn.Linear(d, latent_channels)

    def forward(self, z, t, cond, text):
        """z `[B, L, C]`, t `[B]`, cond = e(w) `[B, cond_dim]`, text `[B, text_dim]` -> eps
        `[B, L, C]`."""
        x = z.transpose(0, 1)
        if self.projected:
            x = self.latent_pre(x)
        te = self.time_embedding
        h = time_sinusoid(t, self.text_dim) + te.cond_proj(cond)
        time = te.linear_2(F.silu(te.linear_1(h)))
        seq = torch.cat([x, time[None], self.emb_proj(text)[None]], dim=0)
        out = self.encoder(self.query_pos(seq))[: x.shape[0]]
        if self.projected:
            out = self.latent_post(out)
        return out.transpose(0, 1)


class Decoder(VaeDecoder):
    """reference/mld.py's VAE decoder, with v2's `latent_post` Linear(C -> D') in front."""

    def __init__(self, latent_dim, latent_channels, layers, heads, ff_size, nfeats, max_len,
                 final_norm, projected):
        super().__init__(latent_dim, layers, heads, ff_size, nfeats, max_len, final_norm)
        self.latent_post = nn.Linear(latent_channels, latent_dim) if projected else None

    def forward(self, z, frames):
        """z `[B, L, C]` -> features `[B, frames, nfeats]` (model space)."""
        if self.latent_post is not None:
            z = self.latent_post(z)
        return super().forward(z, frames)


class SentenceT5(nn.Module):
    """transformers' T5EncoderModel + mean pooling + Dense (no bias) + L2 normalisation."""

    def __init__(self, encoder, dense_weight):
        super().__init__()
        self.encoder = encoder
        self.dense = nn.Linear(dense_weight.shape[1], dense_weight.shape[0], bias=False)
        with torch.no_grad():
            self.dense.weight.copy_(dense_weight)

    def forward(self, ids, mask):
        hidden = self.encoder(input_ids=ids, attention_mask=mask).last_hidden_state
        m = mask[..., None].to(hidden.dtype)
        pooled = (hidden * m).sum(1) / m.sum(1).clamp(min=1e-9)
        return F.normalize(self.dense(pooled), p=2, dim=1)


def t5_from_tensors(t, max_distance):
    """A T5EncoderModel from `{T5EncoderModel name: tensor}`, sizes read from the shapes."""
    from transformers import T5Config, T5EncoderModel
    vocab, d = t["shared.weight"].shape
    buckets, heads = t["encoder.block.0.layer.0.SelfAttention.relative_attention_bias.weight"].shape
    inner = t["encoder.block.0.layer.0.SelfAttention.q.weight"].shape[0]
    d_ff = t["encoder.block.0.layer.1.DenseReluDense.wi.weight"].shape[0]
    layers = len({k.split(".")[2] for k in t if k.startswith("encoder.block.")})
    cfg = T5Config(vocab_size=vocab, d_model=d, d_kv=inner // heads, d_ff=d_ff, num_layers=layers,
                   num_heads=heads, relative_attention_num_buckets=buckets,
                   relative_attention_max_distance=max_distance, feed_forward_proj="relu",
                   layer_norm_epsilon=1e-6, dropout_rate=0.0, is_encoder_decoder=False,
                   use_cache=False)
    model = T5EncoderModel(cfg)
    state = dict(t)
    state["encoder.embed_tokens.weight"] = t["shared.weight"]
    model.load_state_dict(state, strict=True)
    return model.eval()


def tokenizer_from(text, max_length):
    from tokenizers import Tokenizer
    tok = Tokenizer.from_str(text)
    tok.enable_truncation(max_length)
    return tok


def encode_text(model, tok, prompt):
    """One prompt -> (ids `[S]`, sentence vector `[text_dim]`)."""
    enc = tok.encode(prompt)
    ids = torch.tensor([enc.ids])
    with torch.no_grad():
        vec = model(ids, torch.ones_like(ids))
    return ids[0], vec[0]


def load_libflame(path):
    """A converted motionlcm file -> (Denoiser, Decoder, SentenceT5, tokenizer, config)."""
    from safetensors import safe_open
    with safe_open(path, "pt") as f:
        meta = f.metadata()
        tensors = {k: f.get_tensor(k).float() for k in f.keys()}
    config = json.loads(meta["flame.config"])
    assert config["architecture"] == "motionlcm", config["architecture"]
    d, v = config["denoiser"], config["vae"]
    den = Denoiser(d["latent_dim"], d["latent_tokens"], d["latent_channels"], d["text_dim"],
                   d["cond_dim"], d["layers"], d["heads"], d["ff_size"], d["max_len"],
                   d["text_activation"], "denoiser.latent_pre.weight" in tensors)
    den.load_state_dict({k[len("denoiser."):]: x for k, x in tensors.items()
                         if k.startswith("denoiser.")}, strict=True)
    dec = Decoder(v["latent_dim"], v["latent_channels"], v["layers"], v["heads"], v["ff_size"],
                  v["nfeats"], v["max_len"], v["final_norm"], den.projected)
    dec.load_state_dict({k[len("vae."):]: x for k, x in tensors.items() if k.startswith("vae.")},
                        strict=True)
    te = config["text_encoder"]
    t5 = {k[len("text."):]: x for k, x in tensors.items()
          if k.startswith("text.") and k != "text.dense.weight"}
    text = SentenceT5(t5_from_tensors(t5, te["relative_attention_max_distance"]),
                      tensors["text.dense.weight"]).eval()
    tok = tokenizer_from(meta["flame.tokenizer"], te["max_length"])
    return den.eval(), dec.eval(), text, tok, config


def timesteps_for(config, steps):
    """What the scheduler runs: v1 `set_timesteps(n)` (an int), v2 its table (a list)."""
    if config["diffusion"]["lcm_timesteps"] == "motionlcm_v2":
        return V2_TIMESTEPS[steps]
    return steps


def guidance_for(config, steps):
    table = config["defaults"].get("guidance_by_steps")
    if table and str(steps) in table:
        return float(table[str(steps)])
    return float(config["defaults"]["guidance"])


@contextmanager
def _network(fn):
    """reference/diffusers_lcm.run() calls `fake_eps(x, t, bias)` as its network; run it with
    `fn(x, t)` instead (`bias` unused), so the loop, the timestep table and the injected
    re-noising draws are diffusers_lcm's own."""
    saved = diffusers_lcm.fake_eps
    diffusers_lcm.fake_eps = lambda x, t, bias: fn(x, t)
    try:
        yield
    finally:
        diffusers_lcm.fake_eps = saved


def sample(den, config, z_T, text, guidance, steps, renoise):
    """Latent consistency sampling: z_T `[1, L, C]`, text `[1, text_dim]`, `renoise` the draws
    used after each step but the last (`[k, L, C]`). Returns (timesteps, every step's sample,
    every step's consistency estimate `denoised`); the final latent is the last `denoised`."""
    cond = guidance_embedding(torch.tensor([guidance - 1.0]), config["denoiser"]["cond_dim"])

    def net(x, t):
        return den(x, torch.tensor([t]), cond, text)

    with torch.no_grad(), _network(net):
        return diffusers_lcm.run(diffusers_lcm.scheduler(), timesteps_for(config, steps),
                                 z_T, None, [r[None] for r in renoise])


def check_scheduler():
    """The scheduler diffusers_lcm builds is the one both releases configure (scaled_linear
    0.00085-0.012, 1000 steps, epsilon, no clipping, set_alpha_to_one False)."""
    s = diffusers_lcm.scheduler()
    c = s.config
    assert (c.num_train_timesteps, c.beta_schedule, c.prediction_type, c.clip_sample,
            c.set_alpha_to_one, c.timestep_scaling) == (1000, "scaled_linear", "epsilon", False,
                                                        False, 10.0), c
    assert math.isclose(c.beta_start, 0.00085) and math.isclose(c.beta_end, 0.012)
    return s
