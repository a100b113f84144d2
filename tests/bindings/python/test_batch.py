"""flame.batch (flame_batch_*) and bindings/python/examples/ray_batch.py against `flame batch`:
the same jobs give the same bytes in every output, from the Python package and from Ray actors
(a local instance, 2 CPUs, 2 actors, one of them killed mid-run and restarted by Ray); bad jobs
are reported in the manifest while the others run; resume skips finished jobs; a cancel stops
the run it reaches. Model: tests/fixtures/flame_tiny.safetensors (random weights).

Environment: FLAME_CLI, the `flame` executable (else next to the library)."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import flame
from flame import Status

ROOT = Path(__file__).resolve().parents[3]
MODEL = str(ROOT / "tests/fixtures/flame_tiny.safetensors")
EXAMPLES = ROOT / "bindings/python/examples"


def cli_path() -> str:
    env = os.environ.get("FLAME_CLI")
    if env:
        return env
    exe = Path(flame.library_path()).with_name("flame")
    if not exe.is_file():
        pytest.skip(f"no flame CLI next to {flame.library_path()} (set FLAME_CLI)")
    return str(exe)


def jobs(n, steps=4, frames=16):
    kinds = ["bvh", "glb", "json", "npy", "npz"]
    return [{"prompt": f"a person walks {i}", "seed": i, "steps": steps, "frames": frames,
             "out": f"out/{i}.{kinds[i % len(kinds)]}"} for i in range(n)]


def cli_batch(tmp: Path, job_list) -> Path:
    """`flame batch` run on the jobs in `tmp` (relative outputs land in tmp/out)."""
    (tmp / "out").mkdir(parents=True)
    path = tmp / "jobs.jsonl"
    path.write_text("".join(json.dumps(j) + "\n" for j in job_list))
    r = subprocess.run([cli_path(), "batch", "--model", MODEL, "--jobs", "jobs.jsonl"],
                       cwd=tmp, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return tmp


def assert_same_outputs(a: Path, b: Path, job_list):
    for j in job_list:
        got, want = (a / j["out"]).read_bytes(), (b / j["out"]).read_bytes()
        assert got == want, j["out"]


def test_the_package_writes_what_the_cli_writes(tmp_path):
    job_list = jobs(6)
    cli = cli_batch(tmp_path / "cli", job_list)
    py = tmp_path / "py"
    (py / "out").mkdir(parents=True)
    with flame.Model.load(MODEL) as m:
        records = flame.batch(job_list, py / "manifest.jsonl", m, base_dir=py, workers=2)
    assert [r["status"] for r in records] == ["ok"] * 6
    by_job = {r["job"]: r for r in records}  # in the order jobs finished
    assert sorted(by_job) == ["1", "2", "3", "4", "5", "6"]
    assert by_job["1"]["outputs"] == [str(py / "out/0.bvh")] and by_job["1"]["line"] == 1
    assert by_job["1"]["prompt"]["unconditional"] is False
    assert_same_outputs(py, cli, job_list)
    # The jobs file given by path, the model by path: the same.
    again = tmp_path / "again"
    (again / "out").mkdir(parents=True)
    records = flame.batch(cli / "jobs.jsonl", again / "m.jsonl", MODEL, base_dir=again)
    assert sum(r["status"] == "ok" for r in records) == 6
    assert_same_outputs(again, cli, job_list)


def test_bad_jobs_are_in_the_manifest_and_the_others_run(tmp_path):
    (tmp_path / "out").mkdir()
    job_list = [
        {"prompt": "walks", "steps": 2, "frames": 8, "out": "out/a.bvh"},
        '{"prompt": "walks", "out": ',
        {"prompt": "walks", "steps": 2, "out": "out/b.bvh", "colour": "red"},
        {"prompt": "walks", "steps": 2, "out": "missing/c.bvh"},
        {"prompt": "runs", "steps": 2, "out": "out/a.bvh"},
    ]
    records = flame.batch(job_list, tmp_path / "m.jsonl", MODEL, base_dir=tmp_path)
    by_job = {r["job"]: r for r in records}
    assert by_job["1"]["status"] == "ok"
    assert (tmp_path / "out/a.bvh").is_file()
    errors = {k: by_job[k]["error"] for k in "2345"}
    assert errors["2"] == "line 2: EOF while parsing a value at column 26"
    assert errors["3"].startswith("line 3: unknown field `colour`, expected one of")
    assert errors["4"].endswith("missing does not exist")
    assert errors["5"].endswith("out/a.bvh is also an output of job 1")
    assert all(by_job[k]["status"] == "failed" for k in "2345")


def test_resume_skips_what_is_done(tmp_path):
    (tmp_path / "out").mkdir()
    job_list = jobs(3)
    flame.batch(job_list, tmp_path / "m.jsonl", MODEL, base_dir=tmp_path)
    first = (tmp_path / "out/1.glb").read_bytes()
    (tmp_path / "out/1.glb").unlink()
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "out").iterdir()}
    records = flame.batch(job_list, tmp_path / "m.jsonl", MODEL, base_dir=tmp_path, resume=True)
    assert [r["status"] for r in records] == ["ok"] * 3
    assert (tmp_path / "out/1.glb").read_bytes() == first
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps, "done jobs were not rewritten"
    lines = (tmp_path / "m.jsonl").read_text().splitlines()
    keys = [json.loads(l)["job"] for l in lines]
    assert sorted(keys[:3]) == ["1", "2", "3"] and keys[3:] == ["2"], keys


def test_a_cancel_before_a_run_stops_that_run_only(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # NULL params: job paths start from the current folder
    (tmp_path / "out").mkdir()
    m = flame.Model.load(MODEL)
    # Cancel before the run: the runner starts no job and says so.
    from flame import _batch

    lib = flame._lib()
    h = _batch._P()
    flame._check(lib.flame_batch_new(m._h(), _batch.ctypes.byref(h)))
    flame._check(lib.flame_batch_cancel(h))
    path = tmp_path / "jobs.jsonl"
    path.write_text("".join(json.dumps(j) + "\n" for j in jobs(4)))
    status = lib.flame_batch_run(h, os.fsencode(path), os.fsencode(tmp_path / "m.jsonl"), None,
                                 None)
    assert status == Status.CANCELLED
    assert list((tmp_path / "out").iterdir()) == []
    # The cancel was for that run: the next one runs every job.
    flame._check(lib.flame_batch_run(h, os.fsencode(path), os.fsencode(tmp_path / "m.jsonl"),
                                     None, None))
    lib.flame_batch_free(h)
    assert len(list((tmp_path / "out").iterdir())) == 4


def test_ray_actors_write_what_flame_batch_writes_even_when_one_is_killed(tmp_path):
    ray = pytest.importorskip("ray")
    from ray.util import ActorPool

    # Ray's worker processes import the example module: they inherit this environment.
    os.environ["PYTHONPATH"] = os.pathsep.join(
        [str(EXAMPLES)] + [p for p in [os.environ.get("PYTHONPATH")] if p])
    sys.path.insert(0, str(EXAMPLES))
    import ray_batch

    job_list = jobs(16, steps=30, frames=40)
    job_list[5] = dict(job_list[5], out="nowhere/5.bvh")
    cli = tmp_path / "cli"
    (cli / "out").mkdir(parents=True)
    path = cli / "jobs.jsonl"
    path.write_text("".join(json.dumps(j) + "\n" for j in job_list) + "{broken\n")
    r = subprocess.run([cli_path(), "batch", "--model", MODEL, "--jobs", "jobs.jsonl"],
                       cwd=cli, capture_output=True, text=True)
    assert r.returncode == 1 and "15 written, 2 failed" in r.stderr, r.stderr

    out = tmp_path / "ray"
    (out / "out").mkdir(parents=True)
    (out / "manifests").mkdir()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        all_jobs = ray_batch.read_jobs(path)
        sendable = [(line, j) for line, j in all_jobs if isinstance(j, dict)]
        actors = [ray_batch.FlameWorker.remote(MODEL) for _ in range(2)]
        pids = ray.get([a.pid.remote() for a in actors])
        pool = ActorPool(actors)
        for shard in ray_batch.shards(sendable, 2):
            pool.submit(lambda a, s: a.run.remote(s[0], s[1], str(out)), shard)
        results = [pool.get_next_unordered()]
        # Killed mid-run (its shard in flight): Ray restarts it and runs the shard again,
        # which resumes from the shard's manifest.
        ray.kill(actors[0], no_restart=False)
        while pool.has_next():
            results.append(pool.get_next_unordered())
        assert ray.get(actors[0].pid.remote()) != pids[0], "the actor was restarted"
        merged = ray_batch.merge(all_jobs, results, out)
    finally:
        ray.shutdown()
    assert len(merged) == 17
    cli_records = {r["job"]: r for r in flame.read_manifest(cli / "jobs.jsonl.manifest.jsonl")}
    for r in merged:
        assert r["status"] == cli_records[r["job"]]["status"], r
        assert r["line"] == cli_records[r["job"]]["line"]
    assert merged[5]["error"].startswith("line 6: `out` ")
    assert merged[5]["error"].endswith("nowhere does not exist")
    assert cli_records["6"]["error"].endswith("nowhere does not exist")
    assert merged[16]["error"].startswith("line 17: ")
    ok = [j for i, j in enumerate(job_list) if i != 5]
    assert_same_outputs(out, cli, ok)
    leftovers = [p.name for p in (out / "out").iterdir() if p.name.startswith(".")]
    assert leftovers == [], "no temporary file left"
