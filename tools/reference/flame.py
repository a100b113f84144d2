"""PyTorch reference of the FLAME text-to-motion denoiser (kakaobrain/flame `Text2MotionTransformer`).

Written from kakaobrain/flame `src/models/components/text2motion_model.py` as described in
docs/official/flame.md and docs/official/text-encoders.md#roberta-base; it is the oracle the Rust
parity tests are generated from (tools/make_fixtures.py). Submodule names are the official ones, so
`state_dict()` has exactly the keys of an official checkpoint's net (docs/official/flame.md#state-dict-names):
`lm.*`, `motion_length_emb`, `input_projection`, `text_pooler_proj`, `text_h_proj`, `tf_decoder`,
`last_projection`.

Not here: the diffusion sampler (tools/reference/diffusion.py) and the checkpoint converter
(tools/convert.py). `load_libflame` reads a converted libflame file back into this module, which is
how the fixtures check the converter end to end.
"""
import json
import math
import os

import torch
from torch import nn

NUM_AUX_TOKENS = 3  # motion-length token, timestep token, text pooler token


def sinusoid(s, dim, max_period=10000.0):
    """Cos in the first half, sin in the second; frequencies computed in float32
    (kakaobrain/flame `src/models/components/nn.py`; docs/official/flame.md#sinusoidal-embedding).

    `s` is a 1-D tensor of (integer or real) positions/timesteps; returns `[len(s), dim]` float32.
    """
    half = dim // 2
    exponent = -math.log(max_period) * torch.arange(half, dtype=torch.float32) / half
    freqs = torch.exp(exponent)
    args = s[:, None].float() * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=-1)
    return emb


class Text2MotionTransformer(nn.Module):
    """FLAME denoiser: x_t `[B, motion_dim, L]` -> `[B, 2*motion_dim, L]` (eps ; variance value v)."""

    def __init__(self, lm, tokenizer, motion_dim=147, lm_hidden_size=768, model_channels=768,
                 max_motion_length=471, max_text_length=20, num_heads=8, dim_feedforward=2048,
                 dropout=0.1, num_layers=8):
        super().__init__()
        self.motion_dim = motion_dim
        self.model_channels = model_channels
        self.max_text_length = max_text_length
        self.lm = lm
        # Plain attribute, not a module: tokenizers are not part of the state dict.
        self.tokenizer = tokenizer
        self.motion_length_emb = nn.Embedding(max_motion_length, model_channels)
        self.input_projection = nn.Linear(motion_dim, model_channels)
        self.text_pooler_proj = nn.Linear(lm_hidden_size, model_channels)
        self.text_h_proj = nn.Linear(lm_hidden_size, model_channels)
        layer = nn.TransformerDecoderLayer(
            d_model=model_channels, nhead=num_heads, dim_feedforward=dim_feedforward,
            dropout=dropout, activation="relu", layer_norm_eps=1e-5, batch_first=True,
            norm_first=False)
        self.tf_decoder = nn.TransformerDecoder(layer, num_layers=num_layers, norm=None)
        self.last_projection = nn.Linear(model_channels, 2 * motion_dim)

    # -- text ---------------------------------------------------------------------------------
    def tokenize(self, texts):
        """<s> tokens </s> <pad>..., padded/truncated to max_text_length
        (docs/official/flame.md#roberta-prompt-encoding)."""
        enc = self.tokenizer(list(texts), padding="max_length", truncation=True,
                             max_length=self.max_text_length, return_tensors="pt",
                             return_token_type_ids=False)
        return enc["input_ids"], enc["attention_mask"]

    def encode_text(self, texts):
        """Returns (pooler_output `[B, H]`, last_hidden_state `[B, max_text_length, H]`)."""
        input_ids, attention_mask = self.tokenize(texts)
        self.lm.eval()  # FLAME puts the frozen LM in eval mode on every call
        out = self.lm(input_ids=input_ids, attention_mask=attention_mask)
        return out.pooler_output, out.last_hidden_state

    # -- denoiser -----------------------------------------------------------------------------
    def forward(self, x, timesteps, motion_length, texts=None, mask=None, text_features=None):
        """`Text2MotionTransformer.forward` (docs/official/flame.md#denoiser-forward-pass).

        x `[B, motion_dim, L]`; timesteps `[B]` ORIGINAL diffusion step indices; motion_length `[B]`
        int; texts: B strings (or `text_features` = encode_text output); mask `[B, L]` bool, True =
        valid frame (all True when None).
        """
        batch, _, frames = x.shape
        if mask is None:
            mask = torch.ones(batch, frames, dtype=torch.bool)
        if text_features is None:
            text_features = self.encode_text(texts)
        pooler_output, last_hidden = text_features

        motion_tokens = self.input_projection(x.permute(0, 2, 1))
        ml_token = self.motion_length_emb(motion_length.long())[:, None, :]
        timestep_token = sinusoid(timesteps, self.model_channels)[:, None, :]
        pooler_token = self.text_pooler_proj(pooler_output)[:, None, :]
        lm_out = self.text_h_proj(last_hidden)

        # Memory: no positional encoding, no key-padding mask (padded text positions are attended).
        memory = torch.cat([ml_token, timestep_token, pooler_token, lm_out], dim=1)
        target = torch.cat([ml_token, timestep_token, pooler_token, motion_tokens], dim=1)
        positions = torch.arange(frames + NUM_AUX_TOKENS)
        target = target + sinusoid(positions, self.model_channels)[None]

        aux_valid = torch.ones(batch, NUM_AUX_TOKENS, dtype=torch.bool)
        tgt_key_padding_mask = ~torch.cat([aux_valid, mask.bool()], dim=1)
        h = self.tf_decoder(target, memory, tgt_key_padding_mask=tgt_key_padding_mask)

        frame_mask = mask[:, :, None].to(h.dtype)
        h = h[:, NUM_AUX_TOKENS:] * frame_mask
        out = self.last_projection(h) * frame_mask
        return out.permute(0, 2, 1)


# -- construction helpers -------------------------------------------------------------------------

def text_encoder_from_config(cfg):
    """Random-init RobertaModel/BertModel (with pooler) from a HF config dict."""
    from transformers import BertConfig, BertModel, RobertaConfig, RobertaModel
    kind = cfg.get("model_type", "roberta")
    if kind == "roberta":
        return RobertaModel(RobertaConfig(**cfg), add_pooling_layer=True)
    if kind == "bert":
        return BertModel(BertConfig(**cfg), add_pooling_layer=True)
    raise ValueError(f"unsupported text encoder model_type {kind!r} (want roberta or bert)")


def tokenizer_from_json(text, kind):
    """HF fast tokenizer around a tokenizer.json string (RobertaTokenizerFast for roberta)."""
    from tokenizers import Tokenizer
    from transformers import BertTokenizerFast, RobertaTokenizerFast
    backend = Tokenizer.from_str(text)
    if kind == "roberta":
        return RobertaTokenizerFast(tokenizer_object=backend, bos_token="<s>", eos_token="</s>",
                                    sep_token="</s>", cls_token="<s>", unk_token="<unk>",
                                    pad_token="<pad>", mask_token="<mask>")
    if kind == "bert":
        return BertTokenizerFast(tokenizer_object=backend, unk_token="[UNK]", sep_token="[SEP]",
                                 pad_token="[PAD]", cls_token="[CLS]", mask_token="[MASK]")
    raise ValueError(f"unsupported tokenizer kind {kind!r}")


def build_flame(text_model_dir, text_config=None, **net_kwargs):
    """A random-init FLAME whose LM follows `text_config` (default: text_model_dir/config.json) and
    whose tokenizer is text_model_dir/tokenizer.json."""
    if text_config is None:
        with open(os.path.join(text_model_dir, "config.json")) as f:
            text_config = json.load(f)
    with open(os.path.join(text_model_dir, "tokenizer.json")) as f:
        tokenizer = tokenizer_from_json(f.read(), text_config.get("model_type", "roberta"))
    lm = text_encoder_from_config(text_config)
    return Text2MotionTransformer(lm, tokenizer, lm_hidden_size=text_config["hidden_size"],
                                  **net_kwargs)


def load_libflame(path):
    """Build the reference module from a libflame v1 file (float32 weights). Returns (model, config)."""
    from safetensors import safe_open
    with safe_open(path, framework="pt") as f:
        meta = f.metadata()
        tensors = {k: f.get_tensor(k).float() for k in f.keys()}
    if meta.get("format") != "libflame":
        raise ValueError(f"{path}: not a libflame file (format={meta.get('format')!r})")
    config = json.loads(meta["flame.config"])
    den, te = config["denoiser"], config["text_encoder"]
    hf_cfg = {
        "model_type": te["kind"], "vocab_size": te["vocab_size"], "hidden_size": te["hidden_size"],
        "num_hidden_layers": te["num_layers"], "num_attention_heads": te["num_heads"],
        "intermediate_size": te["intermediate_size"],
        "max_position_embeddings": te["max_position_embeddings"],
        "type_vocab_size": te["type_vocab_size"], "layer_norm_eps": te["layer_norm_eps"],
        "pad_token_id": te["pad_token_id"], "hidden_act": te["hidden_act"],
    }
    lm = text_encoder_from_config(hf_cfg)
    tokenizer = tokenizer_from_json(meta["flame.tokenizer"], te["kind"])
    model = Text2MotionTransformer(
        lm, tokenizer, motion_dim=den["motion_dim"], lm_hidden_size=te["hidden_size"],
        model_channels=den["model_channels"], max_motion_length=den["max_motion_length"],
        max_text_length=te["max_length"], num_heads=den["num_heads"],
        dim_feedforward=den["dim_feedforward"], num_layers=den["num_layers"])
    state = {("lm." + k[len("text."):]) if k.startswith("text.") else k: v
             for k, v in tensors.items()}
    model.load_state_dict(state, strict=True)
    model.eval()
    return model, config
