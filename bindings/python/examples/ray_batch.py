"""Bulk generation on a Ray cluster: a JSONL file of `flame batch` jobs, sharded over actors
that each load the model once, writing into one shared folder.

    python ray_batch.py jobs.jsonl --model /shared/flame_demo.safetensors \
        --out-dir /shared/run1 [--address auto] [--actors 8] [--shard-size 16]

Every worker needs only the libflame wheel (`pip install libflame-*.whl ray`) and the model
file at the same path (a shared or copied folder). Relative paths in the jobs are under
--out-dir, which every node must see at the same path (NFS, a mounted bucket). Each shard keeps
its own manifest in OUT_DIR/manifests/ and runs with `resume`, so a shard that Ray retries (an
actor that died is restarted, its task run again) skips the jobs it had finished; rerunning the
whole script after a crash does the same. At the end the shards' manifests are merged into
OUT_DIR/manifest.jsonl, one record per job in the file's order, the line numbers the file's.

Each job's output is the same bytes as `flame batch` (and `flame generate`) writes for it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import List, Tuple

import ray
from ray.util import ActorPool


def read_jobs(path) -> List[Tuple[int, object]]:
    """(line, job) of every non-blank line; a job without an `id` gets its line number, the
    name `flame batch` gives it, so a shard's manifest names jobs as a single run would. A line
    that is not a JSON object gets the reason instead (a string); it is reported, not sent."""
    jobs = []
    with open(path, encoding="utf-8") as f:
        for line, text in enumerate(f, start=1):
            if not text.strip():
                continue
            try:
                job = json.loads(text)
            except ValueError as e:
                job = f"line {line}: {e}"
            if isinstance(job, dict) and not isinstance(job.get("id", ""), str):
                job = f"line {line}: `id` must be a string"
            elif isinstance(job, dict):
                job.setdefault("id", str(line))
            elif not isinstance(job, str):
                job = f"line {line}: a job is a JSON object"
            jobs.append((line, job))
    return jobs


@ray.remote(num_cpus=1, max_restarts=-1, max_task_retries=-1)
class FlameWorker:
    """One model per worker process, loaded once; shards run one after another on it."""

    def __init__(self, model_path: str, threads: int = 1):
        import flame

        self.flame = flame
        self.model = flame.Model.load(model_path, threads=threads)
        self.name = Path(model_path).name
        self.threads = threads

    def pid(self) -> int:
        return os.getpid()

    def run(self, shard: int, jobs: list, out_dir: str) -> List[dict]:
        manifest = Path(out_dir) / "manifests" / f"shard-{shard:05d}.jsonl"
        return self.flame.batch([job for _, job in jobs], manifest, self.model,
                                workers=1, threads=self.threads, resume=True,
                                base_dir=out_dir, model_name=self.name)


def shards(jobs, size: int):
    return [(i, jobs[k:k + size]) for i, k in enumerate(range(0, len(jobs), size))]


def merge(jobs, results, out_dir) -> List[dict]:
    """One record per job in the file's order, with the file's line numbers."""
    by_key = {}
    for records in results:
        for r in records:
            by_key[r["job"]] = r
    merged = []
    for line, job in jobs:
        if isinstance(job, dict):
            r = by_key[str(job["id"])]
            # The runner saw a shard: its messages name the shard's lines, not the file's.
            if r.get("error"):
                r = dict(r, error=f"line {line}: " + r["error"].split(": ", 1)[-1])
        else:
            r = {"job": str(line), "status": "failed", "outputs": [], "seconds": 0.0,
                 "prompt": None, "error": job}
        merged.append(dict(r, line=line))
    with open(Path(out_dir) / "manifest.jsonl", "w", encoding="utf-8") as f:
        for r in merged:
            f.write(json.dumps(r) + "\n")
    return merged


def run(jobs_path, model_path, out_dir, actors: int = 2, shard_size: int = 8,
        threads: int = 1) -> List[dict]:
    """Runs the jobs of `jobs_path` on `actors` Ray actors (ray.init must have run) and returns
    the merged manifest."""
    jobs = read_jobs(jobs_path)
    sendable = [(line, job) for line, job in jobs if isinstance(job, dict)]
    (Path(out_dir) / "manifests").mkdir(parents=True, exist_ok=True)
    workers = [FlameWorker.remote(str(model_path), threads) for _ in range(actors)]
    pool = ActorPool(workers)
    results = list(pool.map_unordered(lambda a, s: a.run.remote(s[0], s[1], str(out_dir)),
                                      shards(sendable, shard_size)))
    return merge(jobs, results, out_dir)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("jobs", help="JSONL file of flame batch jobs")
    ap.add_argument("--model", required=True, help="model file, at this path on every node")
    ap.add_argument("--out-dir", required=True, help="shared folder for outputs and manifests")
    ap.add_argument("--address", default=None, help="Ray cluster address (default: local)")
    ap.add_argument("--actors", type=int, default=2, help="model-holding actors")
    ap.add_argument("--shard-size", type=int, default=8, help="jobs per Ray task")
    ap.add_argument("--threads", type=int, default=1, help="kernel threads per actor")
    a = ap.parse_args()
    ray.init(address=a.address)
    merged = run(a.jobs, a.model, a.out_dir, a.actors, a.shard_size, a.threads)
    failed = [r for r in merged if r["status"] != "ok"]
    for r in failed:
        print(f"{r['job']}: {r['status']}: {r.get('error')}", file=sys.stderr)
    print(f"{len(merged) - len(failed)} of {len(merged)} jobs written; "
          f"manifest {Path(a.out_dir) / 'manifest.jsonl'}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
