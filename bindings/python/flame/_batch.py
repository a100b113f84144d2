"""Bulk generation (flame_batch_*): the runner of `flame batch`, from Python.

    manifest = flame.batch(
        [{"prompt": "a person walks", "seed": 1, "out": "out/walk.bvh"},
         {"prompt": "a person waves", "out": "out/wave.glb", "steps": 20}],
        manifest="out/manifest.jsonl", model="models/demo/flame_demo.safetensors")

Jobs are the JSON objects of `flame batch --jobs` (docs/batch.md): a list of dicts, or the path
of a JSONL file. The model is loaded once and the jobs run on sessions over it; every output
is the same bytes as `flame batch` (and `flame generate`) writes for that job.
"""

from __future__ import annotations

import ctypes
import json
import os
import threading
from pathlib import Path
from typing import Iterable, List, Optional, Union

from . import FlameError, Model, Status, _P, _check, _lib, _status

__all__ = ["batch"]


class _BatchParams(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("workers", ctypes.c_uint32),
        ("threads", ctypes.c_uint32),
        ("resume", ctypes.c_uint32),
        ("base_dir", ctypes.c_char_p),
        ("model_name", ctypes.c_char_p),
    ]


class _BatchSummary(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("total", ctypes.c_uint64),
        ("ok", ctypes.c_uint64),
        ("failed", ctypes.c_uint64),
        ("skipped", ctypes.c_uint64),
    ]


def _signatures() -> dict:
    """(restype, argtypes) of the batch functions of flame.h, by name."""
    return {
        "flame_batch_params_default": (_status, [ctypes.POINTER(_BatchParams)]),
        "flame_batch_new": (_status, [_P, ctypes.POINTER(_P)]),
        "flame_batch_free": (None, [_P]),
        "flame_batch_run": (
            _status,
            [_P, ctypes.c_char_p, ctypes.c_char_p, ctypes.POINTER(_BatchParams),
             ctypes.POINTER(_BatchSummary)],
        ),
        "flame_batch_cancel": (_status, [_P]),
    }


def _write_jobs(jobs: Iterable, path: Path) -> None:
    with open(path, "w", encoding="utf-8") as f:
        for job in jobs:
            line = job if isinstance(job, str) else json.dumps(job)
            if "\n" in line:
                raise ValueError("a job given as text must be one line of JSON")
            f.write(line + "\n")


def read_manifest(path: Union[str, os.PathLike]) -> List[dict]:
    """The manifest's records, the last one of each job, in the order jobs were first seen.
    A line a run stopped in the middle of writing is passed over."""
    records = {}
    with open(path, encoding="utf-8") as f:
        for line in f:
            try:
                rec = json.loads(line)
            except ValueError:
                continue
            records[rec["job"]] = rec
    return list(records.values())


def batch(jobs: Union[str, os.PathLike, Iterable], manifest: Union[str, os.PathLike],
          model: Union[Model, str, os.PathLike], *, workers: int = 0, threads: int = 0,
          resume: bool = False, base_dir: Union[None, str, os.PathLike] = None,
          model_name: Optional[str] = None) -> List[dict]:
    """Runs `jobs` (a JSONL path, or dicts / JSON lines) on sessions over one model and returns
    the manifest (`read_manifest`): one dict per job with `job`, `line`, `status` ("ok",
    "failed", "cancelled"), `outputs`, `seconds`, `prompt`, `error`. A failed job is in the
    manifest and does not raise; FlameError is raised when the run itself cannot go on (the
    manifest cannot be written) or is cancelled. `model` is a Model or a model file's path
    (loaded here, once). `workers` sessions run at once with `threads` kernel threads each (0:
    one session per core, the cores left shared among them). `resume` skips the jobs the
    manifest records as done whose outputs exist. Relative paths in jobs start from `base_dir`
    (default: the current folder). `model_name` is recorded in glTF outputs (default: the
    model file's name, as `flame batch` records it). Ctrl-C (KeyboardInterrupt) cancels the
    run: the running jobs write nothing, and the interrupt is raised again."""
    own = not isinstance(model, Model)
    m = Model.load(model) if own else model
    if model_name is None:
        model_name = Path(model).name if own else getattr(m, "_file_name", "")
    manifest = Path(manifest)
    tmp = None
    try:
        if isinstance(jobs, (str, os.PathLike)):
            jobs_path = Path(jobs)
        else:
            tmp = manifest.parent / f".{manifest.name}.jobs-{os.getpid()}.jsonl"
            _write_jobs(jobs, tmp)
            jobs_path = tmp
        _run(m, jobs_path, manifest, workers, threads, resume, base_dir, model_name)
    finally:
        if tmp is not None:
            tmp.unlink(missing_ok=True)
        if own:
            m.close()
    return read_manifest(manifest)


def _run(m: Model, jobs_path: Path, manifest: Path, workers: int, threads: int, resume: bool,
         base_dir, model_name: str) -> None:
    lib = _lib()  # bound with every signature, these included (flame._signatures)
    p = _BatchParams()
    _check(lib.flame_batch_params_default(ctypes.byref(p)))
    p.workers, p.threads, p.resume = workers, threads, int(bool(resume))
    p.base_dir = os.fsencode(base_dir) if base_dir is not None else None
    p.model_name = model_name.encode("utf-8")
    handle = _P()
    _check(lib.flame_batch_new(m._h(), ctypes.byref(handle)))
    outcome = {}

    def work():
        summary = _BatchSummary(struct_size=ctypes.sizeof(_BatchSummary))
        status = lib.flame_batch_run(handle, os.fsencode(jobs_path), os.fsencode(manifest),
                                     ctypes.byref(p), ctypes.byref(summary))
        # flame_last_error is per thread: read it on the thread that made the call.
        raw = lib.flame_last_error() if status != Status.OK else b""
        outcome["status"], outcome["message"] = status, (raw or b"").decode("utf-8", "replace")

    # The run goes on another thread so that Ctrl-C reaches this one (a C call does not see
    # Python's signal handlers) and can cancel it.
    t = threading.Thread(target=work, name="flame-batch")
    try:
        t.start()
        try:
            while t.is_alive():
                t.join(0.1)
        except KeyboardInterrupt:
            _check(lib.flame_batch_cancel(handle))
            t.join()
            raise
    finally:
        if not t.is_alive():
            lib.flame_batch_free(handle)
    if outcome["status"] != Status.OK:
        raise FlameError(outcome["status"], outcome["message"])
