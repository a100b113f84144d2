#!/usr/bin/env python3
"""Generate tests/fixtures/t5_tiny.safetensors, t5_tiny_tokenizer.json and t5_expected.safetensors
for tests/t5.rs: a tiny random T5 v1.0 encoder run by transformers' own `T5EncoderModel`, with a
sentence-transformers head as sentence-t5 has it (mean pooling with the attention mask, a Dense
layer without bias, L2 normalisation; MotionLCM's text encoder, sentence-t5-large).

- Tokenizer: a Unigram model trained here with the `tokenizers` library on a few motion
  captions, laid out as T5's fast tokenizer is (Metaspace pre-tokenizer and decoder, `<pad>` 0,
  `</s>` 1 appended by a TemplateProcessing post-processor, `<unk>` 2).
- Encoder: `T5Config` with ReLU feed-forward (v1.0, not v1.1's gated GELU), 3 layers, d_model 32,
  4 heads of 8, d_ff 64, 32 relative-position buckets, max distance 128, eps 1e-6. Every weight
  drawn from a seeded normal, the RMSNorm weights around 1, so that none is zero or one.
- Sentences: a short caption, one past 8 tokens (the logarithmic buckets), one of about 100
  tokens (distances past the last bucket's start, where the bucket index is clamped to 15), and
  one of a single word.
- Expected per sentence: the token ids, `last_hidden_state` ([tokens, 32]) and the normalised
  sentence vector ([24]).

Deterministic; needs torch, transformers, tokenizers, safetensors.
Run from anywhere: python tools/make_t5_fixtures.py
"""
import json
import os

import torch
import torch.nn.functional as F
from safetensors.torch import save_file
from tokenizers import Tokenizer, decoders, models, pre_tokenizers, processors, trainers
from transformers import T5Config, T5EncoderModel

TOOLS = os.path.dirname(os.path.abspath(__file__))
FIX = os.path.join(os.path.dirname(TOOLS), "tests", "fixtures")

CORPUS = [
    "a person walks forward slowly and then turns around",
    "a man jumps twice in place with both feet",
    "someone waves the right hand above the head",
    "a woman runs in a circle and stops",
    "the person kicks with the left leg and steps back",
    "a person crouches down, picks something up and stands",
]
SENTENCES = [
    "a person walks forward.",
    "a man jumps twice in place, then waves the right hand and walks back slowly",
    " ".join(["a person runs in a circle and waves"] * 12),
    "jump",
]
DENSE_OUT = 24


def tokenizer():
    tok = Tokenizer(models.Unigram())
    tok.pre_tokenizer = pre_tokenizers.Metaspace(replacement="\u2581", prepend_scheme="always")
    tok.decoder = decoders.Metaspace(replacement="\u2581", prepend_scheme="always")
    trainer = trainers.UnigramTrainer(vocab_size=90, special_tokens=["<pad>", "</s>", "<unk>"],
                                      unk_token="<unk>", shrinking_factor=0.75)
    tok.train_from_iterator(CORPUS, trainer)
    tok.post_processor = processors.TemplateProcessing(single="$A </s>", pair="$A </s> $B </s>",
                                                       special_tokens=[("</s>", 1)])
    return tok


def main():
    tok = tokenizer()
    assert tok.token_to_id("<pad>") == 0 and tok.token_to_id("</s>") == 1
    vocab = tok.get_vocab_size()
    torch.manual_seed(7)
    config = T5Config(vocab_size=vocab, d_model=32, d_kv=8, d_ff=64, num_layers=3, num_heads=4,
                      relative_attention_num_buckets=32, relative_attention_max_distance=128,
                      feed_forward_proj="relu", layer_norm_epsilon=1e-6, dropout_rate=0.0,
                      is_encoder_decoder=False, use_cache=False)
    model = T5EncoderModel(config).eval()
    with torch.no_grad():
        for name, p in model.named_parameters():
            if "layer_norm" in name:
                p.copy_(1.0 + 0.3 * torch.randn_like(p))
            else:
                p.copy_(0.3 * torch.randn_like(p))
    dense = 0.3 * torch.randn(DENSE_OUT, 32)
    weights = {k: v.contiguous() for k, v in model.state_dict().items()}
    # `encoder.embed_tokens` is `shared` under another name.
    weights.pop("encoder.embed_tokens.weight", None)
    weights["dense.weight"] = dense
    save_file(weights, os.path.join(FIX, "t5_tiny.safetensors"),
              metadata={"vocab_size": str(vocab)})
    tok.save(os.path.join(FIX, "t5_tiny_tokenizer.json"))

    expected, meta = {}, []
    with torch.no_grad():
        for i, text in enumerate(SENTENCES):
            enc = tok.encode(text)
            ids = torch.tensor([enc.ids])
            mask = torch.tensor([enc.attention_mask])
            hidden = model(input_ids=ids, attention_mask=mask).last_hidden_state
            m = mask.unsqueeze(-1).float()
            pooled = (hidden * m).sum(1) / torch.clamp(m.sum(1), min=1e-9)
            vec = F.normalize(pooled @ dense.T, p=2, dim=1)
            expected[f"s{i}.ids"] = ids[0].to(torch.float32)  # small ids, exact in f32
            expected[f"s{i}.hidden"] = hidden[0].contiguous()
            expected[f"s{i}.embedding"] = vec[0].contiguous()
            meta.append(len(enc.ids))
    save_file(expected, os.path.join(FIX, "t5_expected.safetensors"),
              metadata={"sentences": json.dumps(SENTENCES), "lengths": json.dumps(meta)})


if __name__ == "__main__":
    main()
