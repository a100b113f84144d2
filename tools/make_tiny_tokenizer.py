#!/usr/bin/env python3
"""Train a tiny GPT-2-style byte-level BPE tokenizer laid out like roberta-base.

The real roberta-base vocabulary is not available offline, so the parity fixtures use this small
stand-in: same pre-tokenizer (byte-level, no prefix space), same special tokens and ids
(<s>=0, <pad>=1, </s>=2, <unk>=3, <mask> = last id), same RobertaProcessing post-processor.

Writes into --out-dir (default tests/fixtures/tiny_roberta):
  tokenizer.json, vocab.json, merges.txt, tokenizer_config.json, special_tokens_map.json and the
  config.json of a tiny RobertaModel (hidden 48, 2 layers, 4 heads, intermediate 96, 64 positions).
Deterministic: the corpus is generated from fixed word lists without randomness.
"""
import argparse
import itertools
import json
import os
import sys

from tokenizers import AddedToken, Tokenizer, decoders, models, pre_tokenizers, processors, trainers

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT_OUT = os.path.join(REPO, "tests", "fixtures", "tiny_roberta")

SPECIALS = ["<s>", "<pad>", "</s>", "<unk>"]
MASK = "<mask>"

SUBJECTS = ["a person", "the man", "a woman", "someone", "the figure", "a child", "he", "she",
            "the dancer", "an old man", "a player"]
ACTIONS = ["walks forward", "runs in a circle", "jumps up and down", "waves with the right hand",
           "waves with the left hand", "kicks with the right leg", "sits down on a chair",
           "stands up slowly", "turns around", "walks backward", "jogs in place", "raises both arms",
           "bends down to pick something up", "throws a ball", "crawls on the floor",
           "dances happily", "climbs up the stairs", "walks down the stairs", "spins twice",
           "claps his hands", "claps her hands", "stretches the arms", "punches forward",
           "steps to the left", "steps to the right", "hops on one foot", "squats down",
           "does a cartwheel", "swims breaststroke", "lifts a heavy box", "bows politely",
           "salutes", "shakes hands", "pushes a door", "pulls a rope", "kneels down",
           "looks around", "stumbles and falls", "marches in place", "skips forward"]
MODIFIERS = ["", " quickly", " slowly", " carefully", " then stops", " and waves.",
             " while looking around", " three times", " for 2 seconds", " in a zigzag",
             " and then sits down", " with excitement", ", then turns left.", "!"]
EXTRA = [
    "a person walks forward and waves.",
    "A person walks forward and waves.",
    "the person doesn't move, then it's jumping",
    "they're running; we've seen 12 steps, 3 jumps and 100 waves",
    "a man is walking in a straight line and then turns 90 degrees to the right before stopping",
    "person kicks, punches, and ducks: a boxing combo",
    "someone does jumping jacks (10 reps)",
    "a person walks forward  and waves.",
]
VERBS = ["walking", "running", "jumping", "waving", "kicking", "sitting", "standing", "turning",
         "jogging", "raising", "bending", "throwing", "catching", "crawling", "dancing",
         "climbing", "spinning", "clapping", "stretching", "punching", "stepping", "hopping",
         "squatting", "swimming", "lifting", "bowing", "saluting", "shaking", "pushing", "pulling",
         "kneeling", "looking", "stumbling", "falling", "marching", "skipping", "balancing",
         "leaning", "rotating", "swinging", "tiptoeing", "sprinting", "limping", "strolling",
         "pacing", "lunging", "crouching", "rolling", "sliding", "skating", "boxing", "fencing",
         "juggling", "drinking", "eating", "reading", "writing", "typing", "painting", "sweeping",
         "digging", "rowing", "paddling", "golfing", "bowling", "batting", "pitching", "dribbling",
         "shooting", "serving", "stirring", "chopping", "waiting", "yawning", "sneezing",
         "shivering", "celebrating", "cheering", "pointing", "gesturing", "praying", "meditating"]
PARTS = ["head", "neck", "shoulder", "shoulders", "elbow", "wrist", "hand", "hands", "finger",
         "fingers", "chest", "back", "waist", "hip", "hips", "knee", "knees", "ankle", "foot",
         "feet", "toes", "leg", "legs", "arm", "arms", "torso", "body"]
OBJECTS = ["ball", "chair", "table", "box", "door", "window", "rope", "stick", "bottle", "cup",
           "phone", "book", "bag", "hat", "umbrella", "guitar", "violin", "racket", "bat",
           "sword", "shield", "bucket", "broom", "shovel", "ladder", "bench", "wall", "rail",
           "bicycle", "horse", "dog", "cat", "friend", "partner", "mirror", "camera", "steering wheel"]
PLACES = ["on the beach", "in the park", "around the room", "across the street", "on a treadmill",
          "up a hill", "down a slope", "through the doorway", "along the wall", "over an obstacle",
          "under a bar", "on a balance beam", "near the table", "behind the couch"]
NUMBERS = ["once", "twice", "three times", "four times", "five times", "several times",
           "a few steps", "10 steps", "20 seconds", "45 degrees", "90 degrees", "180 degrees"]


def corpus():
    out = list(EXTRA)
    for i, (s, a) in enumerate(itertools.product(SUBJECTS, ACTIONS)):
        m = MODIFIERS[i % len(MODIFIERS)]
        sentence = f"{s} {a}{m}"
        if i % 3 == 0:
            sentence = sentence[0].upper() + sentence[1:]
        if not sentence.endswith((".", "!")) and i % 2 == 0:
            sentence += "."
        out.append(sentence)
    for i, v in enumerate(VERBS):
        p = PARTS[i % len(PARTS)]
        o = OBJECTS[(3 * i) % len(OBJECTS)]
        pl = PLACES[(5 * i) % len(PLACES)]
        n = NUMBERS[(7 * i) % len(NUMBERS)]
        out.append(f"a person is {v} {pl} while moving the {p}.")
        out.append(f"someone keeps {v} with a {o} {n}")
        out.append(f"The {p} moves during {v}, then the person holds the {o}.")
    for i, p in enumerate(PARTS):
        out.append(f"a person rotates the left {p} and then the right {p} {NUMBERS[i % len(NUMBERS)]}.")
    for i, o in enumerate(OBJECTS):
        out.append(f"a man picks up the {o} {PLACES[i % len(PLACES)]} and puts it down")
    return out


def train(vocab_size):
    tok = Tokenizer(models.BPE(unk_token=None))
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab_size - 1,  # the <mask> token is appended after training
        min_frequency=1,
        special_tokens=SPECIALS,
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        show_progress=False,
    )
    tok.train_from_iterator(corpus(), trainer=trainer)
    tok.add_special_tokens([AddedToken(MASK, lstrip=True, rstrip=False, normalized=False,
                                       special=True)])
    tok.post_processor = processors.RobertaProcessing(
        ("</s>", tok.token_to_id("</s>")), ("<s>", tok.token_to_id("<s>")),
        trim_offsets=True, add_prefix_space=False)
    return tok


def tiny_config(vocab_size):
    return {
        "architectures": ["RobertaModel"],
        "model_type": "roberta",
        "vocab_size": vocab_size,
        "hidden_size": 48,
        "num_hidden_layers": 2,
        "num_attention_heads": 4,
        "intermediate_size": 96,
        "hidden_act": "gelu",
        "hidden_dropout_prob": 0.1,
        "attention_probs_dropout_prob": 0.1,
        "max_position_embeddings": 64,
        "type_vocab_size": 1,
        "initializer_range": 0.02,
        "layer_norm_eps": 1e-05,
        "pad_token_id": 1,
        "bos_token_id": 0,
        "eos_token_id": 2,
        "position_embedding_type": "absolute",
    }


def check(out_dir, max_length=20):
    """"" -> [0, 2, 1 x 18], mask [1, 1, 0 x 18] through the HF fast tokenizer
    (docs/official/flame.md#roberta-prompt-encoding)."""
    from transformers import RobertaTokenizerFast
    hf = RobertaTokenizerFast(tokenizer_file=os.path.join(out_dir, "tokenizer.json"))
    enc = hf([""], padding="max_length", truncation=True, max_length=max_length)
    ids, mask = enc["input_ids"][0], enc["attention_mask"][0]
    want_ids = [0, 2] + [1] * (max_length - 2)
    want_mask = [1, 1] + [0] * (max_length - 2)
    assert ids == want_ids, f"empty prompt tokenized as {ids}, want {want_ids}"
    assert mask == want_mask, f"empty prompt mask {mask}, want {want_mask}"
    assert "token_type_ids" not in enc or all(v == 0 for v in enc["token_type_ids"][0])
    enc = hf(["a person walks forward and waves."], padding="max_length", truncation=True,
             max_length=max_length)
    ids = enc["input_ids"][0]
    assert ids[0] == 0 and 2 in ids and ids[-1] == 1, ids
    long = " ".join(["walk"] * 40)
    ids = hf([long], padding="max_length", truncation=True, max_length=max_length)["input_ids"][0]
    assert len(ids) == max_length and ids[0] == 0 and ids[-1] == 2, ids
    assert hf.pad_token_id == 1 and hf.bos_token_id == 0 and hf.eos_token_id == 2
    assert hf.unk_token_id == 3 and hf.mask_token_id == len(hf) - 1
    return hf


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out-dir", default=DEFAULT_OUT)
    ap.add_argument("--vocab-size", type=int, default=1000)
    args = ap.parse_args(argv)

    os.makedirs(args.out_dir, exist_ok=True)
    tok = train(args.vocab_size)
    tok.save(os.path.join(args.out_dir, "tokenizer.json"))
    tok.model.save(args.out_dir)  # vocab.json + merges.txt
    vocab_size = tok.get_vocab_size(with_added_tokens=True)

    special_map = {"bos_token": "<s>", "eos_token": "</s>", "unk_token": "<unk>",
                   "sep_token": "</s>", "cls_token": "<s>", "pad_token": "<pad>",
                   "mask_token": "<mask>"}
    with open(os.path.join(args.out_dir, "special_tokens_map.json"), "w") as f:
        json.dump(special_map, f, indent=2)
        f.write("\n")
    tok_cfg = dict(special_map, tokenizer_class="RobertaTokenizer", add_prefix_space=False,
                   trim_offsets=True, model_max_length=512, errors="replace")
    with open(os.path.join(args.out_dir, "tokenizer_config.json"), "w") as f:
        json.dump(tok_cfg, f, indent=2)
        f.write("\n")
    with open(os.path.join(args.out_dir, "config.json"), "w") as f:
        json.dump(tiny_config(vocab_size), f, indent=2)
        f.write("\n")

    check(args.out_dir)
    print(f"wrote {args.out_dir}: vocab {vocab_size} (<mask> = {vocab_size - 1})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
