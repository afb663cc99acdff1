"""The sweep driver: jobs out to an engine, records in, ``results.json`` / ``tables.md`` / plots.

``run_bench(root, out, ...)``:

1. finds the sequences under ``root`` (:func:`~dynastereo.bench.discover.discover`) and
   keeps those of ``sequences``;
2. makes a job per (sequence, masker, repeat), its outputs in
   ``out/runs/<sequence>/<masker>/r<repeat>/``; a job whose ``result.json`` holds a
   finished record of the same configuration is **reused**, not run again;
3. runs the others on the engine, at most ``engine.capacity`` in flight; a job that
   fails (an exception, or its worker process dies) is reported with its error and
   retried once (``retries``); a failure never stops the other jobs;
4. after every finished job rewrites ``out/results.json`` (atomically: a consistent file
   whatever happens -- Ctrl-C, a killed driver); at the end writes ``out/tables.md`` and
   the plots (``out/plots/ate.png``, ``out/plots/trajectories_<sequence>.png``).

On Ctrl-C (KeyboardInterrupt) the jobs in flight are stopped and marked
``"interrupted"``, results.json / tables.md are written with what finished, and the
KeyboardInterrupt is raised again.
"""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

from ..errors import ConfigError, DynastereoError
from .discover import BenchSequence, discover, select
from .jobs import BenchJob, JobState, finished_record, job_config, store_result, write_json_atomic

MASKERS = ("none", "box", "outline", "seg")
RESULTS_NAME = "results.json"
TABLES_NAME = "tables.md"
RESULTS_VERSION = 1


@dataclass
class BenchResult:
    out: Path
    runs: list[dict[str, Any]]
    results_path: Path
    tables_path: Path
    plots: list[Path] = field(default_factory=list)
    wall_s: float = 0.0
    interrupted: bool = False

    def count(self, status: str) -> int:
        return sum(r["status"] == status for r in self.runs)


ProgressFn = Callable[[dict[str, Any]], None]
"""Called with ``{"jobs_done", "jobs_total", "jobs_failed", "frames_done", "frames_total",
"running": [keys], "event": (kind, key) | None}`` whenever something changes."""


def parse_maskers(spec: str | list[str] | tuple[str, ...]) -> list[str]:
    items = [m.strip() for m in (spec.split(",") if isinstance(spec, str) else spec) if m.strip()]
    bad = [m for m in items if m not in MASKERS]
    if bad or not items:
        raise ConfigError(f"--maskers: unknown {', '.join(bad) or '(none given)'}; choose from {', '.join(MASKERS)}")
    return list(dict.fromkeys(items))


def _frame_count(seq: BenchSequence, frames: str | None) -> int:
    """Frames a job of ``seq`` will feed; 0 when the sequence cannot be opened (its jobs then
    fail with the reader's error, reported like any other failure)."""
    from ..io import open_sequence
    from ..io.frames import select_frames

    try:
        return len(select_frames(frames, open_sequence(seq.path)))
    except DynastereoError:
        return 0


def plan_jobs(sequences: list[BenchSequence], maskers: list[str], repeats: int, out: Path,
              config: dict[str, Any], frames: str | None = None, models_dir: str | None = None,
              threads: int = 1) -> list[BenchJob]:
    if repeats < 1:
        raise ConfigError(f"--repeats must be >= 1, got {repeats}")
    jobs = []
    for seq in sequences:
        n = _frame_count(seq, frames)
        for m in maskers:
            for r in range(repeats):
                jobs.append(BenchJob(seq, m, r, out / "runs" / seq.name / m / f"r{r}",
                                     job_config(config, m, r, threads), frames, models_dir, n))
    return jobs


class _Driver:
    def __init__(self, jobs: list[BenchJob], out: Path, meta: dict[str, Any], retries: int,
                 progress: ProgressFn | None) -> None:
        self.states = {j.key: JobState(j) for j in jobs}
        self.out, self.meta, self.retries, self.progress = out, meta, retries, progress
        self.frames_total = sum(j.n_frames for j in jobs)

    def runs(self) -> list[dict[str, Any]]:
        return [s.to_record() for s in self.states.values()]

    def write_results(self, finished: bool) -> Path:
        meta = dict(self.meta, updated=datetime.now(timezone.utc).isoformat(timespec="seconds"), complete=finished)
        path = self.out / RESULTS_NAME
        write_json_atomic(path, {"version": RESULTS_VERSION, "bench": meta, "runs": self.runs()})
        return path

    def report(self, event: tuple[str, str] | None = None) -> None:
        if self.progress is None:
            return
        st = self.states.values()
        self.progress({
            "jobs_done": sum(s.status in ("done", "reused", "failed") for s in st),
            "jobs_total": len(self.states),
            "jobs_failed": sum(s.status == "failed" for s in st),
            "frames_done": sum(s.job.n_frames if s.status in ("done", "reused", "failed") else s.frames_done
                               for s in st),
            "frames_total": self.frames_total,
            "running": [s.job.key for s in st if s.status == "running"],
            "event": event,
        })

    def reuse_finished(self) -> deque[JobState]:
        todo: deque[JobState] = deque()
        for s in self.states.values():
            rec = finished_record(s.job)
            if rec is not None:
                s.status, s.record, s.attempts = "reused", rec, rec.get("attempts", 1)
            else:
                todo.append(s)
        return todo

    def run(self, engine, todo: deque[JobState]) -> None:
        inflight = 0
        while todo or inflight:
            while todo and inflight < engine.capacity:
                s = todo.popleft()
                s.status, s.attempts, s.frames_done = "running", s.attempts + 1, 0
                engine.submit(s.job)
                inflight += 1
            for ev in engine.poll(0.2):
                s = self.states[ev.key]
                if ev.kind == "progress":
                    s.frames_done = int(ev.value)
                    self.report()
                    continue
                inflight -= 1
                if ev.kind == "done":
                    ev.value["attempts"] = s.attempts
                    if s.errors:
                        ev.value["errors"] = list(s.errors)
                    s.status, s.record = "done", store_result(s.job, ev.value)
                else:
                    s.errors.append(str(ev.value))
                    if s.attempts <= self.retries:
                        s.status = "pending"
                        todo.append(s)  # retried once the others queued before it started
                    else:
                        s.status = "failed"
                self.write_results(finished=False)
                self.report((ev.kind, ev.key))


def run_bench(
    root: str | Path,
    out: str | Path,
    *,
    sequences: str | None = None,
    maskers: str | list[str] = "none,box,outline,seg",
    repeats: int = 1,
    config: str | Path | None = None,
    overrides: dict[str, Any] | None = None,
    frames: str | None = None,
    engine: str = "local",
    address: str | None = None,
    workers: int | None = None,
    threads: int = 1,
    retries: int = 1,
    models_dir: str | Path | None = None,
    plots: bool = True,
    progress: ProgressFn | None = None,
) -> BenchResult:
    """Run the sweep (see module doc) and return its records and output paths.

    ``config``: a YAML configuration for every job (``masker.kind`` and ``seed`` are set per
    job: the masker, and ``seed + repeat``); ``overrides``: dotted keys over it.
    ``workers``: processes (local) / CPUs of the local Ray instance; default: the cores.
    ``threads``: threads per job (``detector.threads``, ``slam.threads``).
    """
    from ..config import load_config, to_dict
    from .engines import make_engine
    from .tables import write_plots, write_tables

    t0 = time.perf_counter()
    root, out = Path(root), Path(out)
    cfg = load_config(config).with_overrides(overrides or {})
    chosen = select(discover(root, exclude=(out,)), sequences)
    masker_list = parse_maskers(maskers)
    out.mkdir(parents=True, exist_ok=True)
    jobs = plan_jobs(chosen, masker_list, repeats, out, to_dict(cfg), frames,
                     str(models_dir) if models_dir else None, threads)
    workers = workers or os.cpu_count() or 1
    meta = {"root": str(root), "out": str(out), "engine": engine, "address": address, "workers": workers,
            "threads_per_job": threads, "sequences": [s.to_dict() for s in chosen], "maskers": masker_list,
            "repeats": repeats, "frames": frames, "config_file": str(config) if config else None,
            "started": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    driver = _Driver(jobs, out, meta, retries, progress)
    todo = driver.reuse_finished()
    driver.write_results(finished=False)
    driver.report()
    interrupted = False
    closer = None
    if todo:
        t_engine = time.perf_counter()
        eng = make_engine(engine, workers, address)
        driver.meta["engine_description"] = eng.description
        driver.meta["engine_start_s"] = round(time.perf_counter() - t_engine, 3)
        driver.meta["jobs_started_at_s"] = round(time.perf_counter() - t0, 3)
        try:
            driver.run(eng, todo)
        except KeyboardInterrupt:
            interrupted = True
            for s in driver.states.values():
                if s.status == "running":
                    s.status = "interrupted"
        finally:
            # stopping the workers / Ray (a second or so) overlaps the tables and plots
            closer = threading.Thread(target=eng.close, name="bench-engine-close")
            closer.start()
    runs = driver.runs()
    driver.meta["jobs_done_at_s"] = round(time.perf_counter() - t0, 3)  # seconds since run_bench began
    results_path = driver.write_results(finished=not interrupted)
    tables_path = write_tables(runs, out / TABLES_NAME, meta=driver.meta)
    plot_paths = write_plots(runs, chosen, out / "plots") if plots else []
    if closer is not None:
        closer.join()
    wall = time.perf_counter() - t0
    result = BenchResult(out, runs, results_path, tables_path, plot_paths, wall, interrupted)
    if interrupted:
        raise KeyboardInterrupt
    return result
