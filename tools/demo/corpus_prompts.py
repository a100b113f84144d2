#!/usr/bin/env python3
"""Write a family<TAB>prompt file of TRAINING sentences for crates/flame-demo/tests/demo_eval.rs
(`FLAME_DEMO_EVAL_PROMPTS`): settings such as the guidance scale are chosen on these, never on
the held-out prompts of tests/fixtures/demo_eval_prompts.tsv.

  python3 tools/demo/corpus_prompts.py --corpus target/demo/corpus [--per-family 3] [--seed 0] > P.tsv

Picks, per family, single-action motions at random (seeded) and one of their sentences each.
"""
import argparse
import json
import os
import random


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", required=True)
    ap.add_argument("--per-family", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    by_family = {}
    with open(os.path.join(args.corpus, "corpus.jsonl")) as f:
        for line in f:
            r = json.loads(line)
            if len(r["actions"]) == 1:
                by_family.setdefault(r["family"], []).append(r)
    print("# training sentences, tools/demo/corpus_prompts.py "
          f"--per-family {args.per_family} --seed {args.seed}")
    for family in sorted(by_family):
        for r in rng.sample(by_family[family], args.per_family):
            print(f"{family}\t{rng.choice(r['texts'])}")


if __name__ == "__main__":
    main()
