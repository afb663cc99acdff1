"""One benchmark job: run a (sequence, masker, repeat) in-process and evaluate it.

``execute(job)`` is what every engine's worker calls.  It runs
:func:`dynastereo.runtime.run` into ``job.out`` (trajectory, ``timing.json``,
``run.json``: the files of ``dynastereo run``), evaluates the trajectory against the
sequence's ground truth with :func:`dynastereo.eval.evaluate_files` (the numbers of
``dynastereo eval --json``) and returns the job's **record** -- a JSON-able dict, the line
of ``results.json`` -- with the small output files attached under ``"files"`` so that a
driver on another machine (a Ray cluster without a shared folder) can write them too.

The driver writes ``job.out/result.json`` (the record without ``"files"``) when a job
finished; it is what makes a sweep resumable (:func:`finished_record`).

Threads: a job is single-threaded (:data:`THREAD_ENV` in the worker's environment before
numpy / OpenCV / onnxruntime load, ``cv2.setNumThreads(1)``, ``detector.threads`` and
``slam.threads`` = ``threads`` in its configuration) so that N workers use N cores.

Fault injection (tests): with ``DYNASTEREO_BENCH_FAULT=PATTERN`` in the workers'
environment, the first attempt of each job whose key matches the shell pattern kills its
own worker process (SIGKILL) after the run started; ``job.out/.fault`` records that it did.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import os
import platform
import signal
import socket
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..io.outputs import atomic_write_text
from .discover import BenchSequence

THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "NUMEXPR_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1"}
FAULT_ENV = "DYNASTEREO_BENCH_FAULT"
RESULT_NAME = "result.json"
RECORD_VERSION = 1
RETURNED_FILES = ("trajectory.kitti.txt", "trajectory.tum.txt", "trajectory.frames.txt", "timing.json", "run.json")


@dataclass(frozen=True)
class BenchJob:
    """A (sequence, masker, repeat): everything a worker needs, picklable."""

    sequence: BenchSequence
    masker: str
    repeat: int
    out: Path
    config: dict[str, Any]  # to_dict(Config) with masker.kind, seed and threads set
    frames: str | None = None
    models_dir: str | None = None
    n_frames: int = 0  # frames the run will feed (for the progress bar)

    @property
    def key(self) -> str:
        return f"{self.sequence.name}/{self.masker}/r{self.repeat}"

    @property
    def config_hash(self) -> str:
        """What decides whether a finished result can be reused."""
        gt = self.sequence.ground_truth
        blob = json.dumps({"config": self.config, "frames": self.frames, "sequence": str(self.sequence.path.resolve()),
                           "ground_truth": str(gt.resolve()) if gt else None}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]


def job_config(base: dict[str, Any], masker: str, repeat: int, threads: int) -> dict[str, Any]:
    """The configuration of one job: ``base`` with the masker, ``seed + repeat`` and the
    per-job thread counts.  Validated by :class:`~dynastereo.config.Config`."""
    from ..config import Config, from_dict, to_dict

    cfg = from_dict(Config, base, "<bench>")
    cfg = cfg.with_overrides({"masker.kind": masker, "seed": cfg.seed + repeat,
                              "detector.threads": threads, "slam.threads": threads})
    return to_dict(cfg)


def finished_record(job: BenchJob) -> dict[str, Any] | None:
    """The stored record of ``job`` when it finished with this configuration, else None."""
    path = job.out / RESULT_NAME
    try:
        rec = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if rec.get("status") == "done" and rec.get("config_hash") == job.config_hash and rec.get("key") == job.key:
        return rec
    return None


def write_json_atomic(path: Path, data: Any) -> None:
    atomic_write_text(path, json.dumps(data, indent=1, default=float), fsync=False)


def store_result(job: BenchJob, record: dict[str, Any]) -> dict[str, Any]:
    """Write the files a worker returned (unless already there, i.e. a shared folder) and
    ``result.json``; returns the record without the files."""
    files = record.pop("files", {}) or {}
    job.out.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        p = job.out / name
        if not p.is_file() or p.read_text() != text:
            p.write_text(text)
    write_json_atomic(job.out / RESULT_NAME, record)
    return record


def set_single_thread() -> None:
    """What a worker process does once, first."""
    os.environ.update(THREAD_ENV)
    import cv2

    cv2.setNumThreads(1)


def _maybe_fault(job: BenchJob) -> None:
    pattern = os.environ.get(FAULT_ENV)
    if not pattern or not fnmatch.fnmatchcase(job.key, pattern):
        return
    marker = job.out / ".fault"
    if marker.exists():
        return
    marker.write_text(f"killed pid {os.getpid()} on purpose ({FAULT_ENV}={pattern})\n")
    os.kill(os.getpid(), signal.SIGKILL)


def _ground_truth(job: BenchJob, sequence) -> Path | None:
    gt = job.sequence.ground_truth
    if gt is not None and job.sequence.format == "euroc" and gt.suffix == ".csv":
        from .discover import euroc_ground_truth_tum

        gt = euroc_ground_truth_tum(gt, sequence, job.out / "groundtruth.tum.txt")
    return gt


def _evaluate(job: BenchJob, gt: Path) -> dict[str, Any]:
    """``eval --json``'s dict (plus ``estimate``: the file evaluated); the TUM estimate (time matching)
    when the ground truth has timestamps, else the KITTI one (row / frame-index matching)."""
    from ..eval import evaluate_files, read_trajectory, to_json_dict

    timed = read_trajectory(gt).timestamps is not None
    est = job.out / ("trajectory.tum.txt" if timed else "trajectory.kitti.txt")
    r = evaluate_files(est, gt)
    d = to_json_dict(r)
    d["estimate"] = est.name
    return d


def execute(job: BenchJob, progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Run and evaluate ``job`` (see module doc); exceptions propagate (the engine reports them)."""
    from ..config import Config, from_dict
    from ..io import open_sequence
    from ..runtime import JobKind, JobSpec, OutputSpec, SourceSpec, run

    t0 = time.perf_counter()
    job.out.mkdir(parents=True, exist_ok=True)
    cfg = from_dict(Config, job.config, "<bench job>")
    seq = open_sequence(job.sequence.path)
    fault_at = 1

    def on_frame(done: int, total: int, rec: dict) -> None:
        if done == fault_at:
            _maybe_fault(job)
        if progress is not None:
            progress(done, total)

    spec = JobSpec(JobKind.RUN, SourceSpec(sequence=seq), OutputSpec(job.out), cfg, frames=job.frames,
                   models_dir=job.models_dir)
    res = run(spec, progress=on_frame)
    t_run = time.perf_counter()
    metrics, gt_used = {}, _ground_truth(job, seq)
    if gt_used is not None and len(res.frames) >= 2:
        metrics = _evaluate(job, gt_used)
    t_eval = time.perf_counter()
    run_info = json.loads((job.out / "run.json").read_text())
    record = {
        "key": job.key,
        "sequence": job.sequence.name,
        "masker": job.masker,
        "repeat": job.repeat,
        "status": "done",
        "metrics": metrics,
        "ground_truth": str(gt_used) if gt_used else None,
        "fps": round(res.fps, 3),
        "frames": len(res.frames),
        "frames_lost": len(res.lost),
        "keyframes": res.stats.get("keyframes"),
        "map_points": res.stats.get("map_points"),
        "loops": res.stats.get("loops", 0),
        "timing_ms": {k: v["median"] for k, v in res.summary.items()},
        "run_s": round(res.wall_s, 3),
        "eval_s": round(t_eval - t_run, 3),
        "job_s": round(t_eval - t0, 3),
        "overhead_s": round((t_eval - t0) - res.wall_s, 3),
        "dir": str(job.out),
        "config_hash": job.config_hash,
        "config": job.config,
        "versions": run_info.get("versions", {}),
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "python": platform.python_version(),
        "record_version": RECORD_VERSION,
    }
    record["files"] = {n: (job.out / n).read_text() for n in RETURNED_FILES if (job.out / n).is_file()}
    return record


def error_text(e: BaseException) -> str:
    """One line for the table, the traceback's last lines for results.json."""
    tb = traceback.format_exception(type(e), e, e.__traceback__)
    return f"{type(e).__name__}: {e}\n" + "".join(tb[-3:])


@dataclass
class JobState:
    """The driver's view of a job: its attempts, and its record when finished or failed."""

    job: BenchJob
    attempts: int = 0
    status: str = "pending"  # pending | running | done | failed | interrupted | reused
    errors: list[str] = field(default_factory=list)
    record: dict[str, Any] | None = None
    frames_done: int = 0

    def to_record(self) -> dict[str, Any]:
        if self.record is not None:  # attempts and errors are in the record (store_result)
            return dict(self.record, reused=True) if self.status == "reused" else dict(self.record)
        return {"key": self.job.key, "sequence": self.job.sequence.name, "masker": self.job.masker,
                "repeat": self.job.repeat, "status": self.status, "attempts": self.attempts,
                "error": self.errors[-1].splitlines()[0] if self.errors else None, "errors": self.errors,
                "metrics": {}, "dir": str(self.job.out), "config_hash": self.job.config_hash,
                "config": self.job.config}
