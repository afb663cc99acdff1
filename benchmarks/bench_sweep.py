"""Benchmark ``dynastereo bench`` against the same jobs run one after another by hand.

Renders ``--scenarios`` (default 4: convoy, oncoming, crossing, mixed) with
``dynastereo.synth.generate`` (``--frames`` each, cached under ``--cache``) into one root,
then times, ``--rounds`` times each:

* **sequential**: for every (sequence, masker) ``dynastereo run SEQ --out D --masker M
  --detector oracle`` then ``dynastereo eval D/trajectory.kitti.txt GT --json``, one
  after another, as separate CLI processes (what a user scripts today);
* **bench** (each of ``--engines``, default ray): one ``dynastereo bench ROOT --out O
  --maskers ... --repeats 1 --detector oracle --engine E --workers N`` CLI process, fresh
  output folder, Ray start-up, plots and tables included.

Reported (medians over the rounds): both wall times and their ratio (target <= 0.75 for
ray); the **overhead per job** (target <= 2 s) = ``in_job``, the median over jobs of
``job_s - run_s`` in the worker (opening the sequence, building masker and SLAM,
evaluation, writing the result), + ``idle``, the worker-slot time between jobs (driver
round trip, scheduling) per job: (span from the first submit to the last record x
workers - sum of job_s) / jobs; what is paid **once per sweep** (``fixed``: CLI start,
discovery, engine start, tables, plots, shutdown = wall - that span), and for reference
everything that is not SLAM shared out over the jobs ((wall x workers - sum of run_s) /
jobs: with only 8 jobs the once-per-sweep part dominates it); and whether every number of
results.json equals the sequential ``eval --json``
(and every ATE cell of tables.md its formatted value) -- they must, the runs are
deterministic.  The machine is shared: the load average before and after is recorded.

Writes benchmarks/results/sweep.json.  Run:

    .venv/bin/python benchmarks/bench_sweep.py [--frames 40] [--rounds 1] [--engines ray,local]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import machine, results_path, write_json

CLI = [sys.executable, "-m", "dynastereo.cli.main"]
IGNORED_KEYS = {"plot", "estimate"}  # eval --json's plot path; bench's name of the file evaluated


def _cli(args: list[str]) -> str:
    env = dict(os.environ, MPLBACKEND="Agg")
    p = subprocess.run([*CLI, *args], capture_output=True, text=True, env=env)
    if p.returncode not in (0,):
        raise SystemExit(f"{' '.join(args[:3])} ... failed ({p.returncode}):\n{p.stderr[-2000:]}")
    return p.stdout


def make_root(cache: Path, scenarios: list[str], frames: int) -> Path:
    from dynastereo.synth import generate

    root = cache / f"sweep_{frames}"
    for sc in scenarios:
        if not (root / sc / "poses" / "00.txt").is_file():
            generate(root / sc, sc, frames=frames, seed=0)
    return root


def sequential(root: Path, scenarios: list[str], maskers: list[str], work: Path) -> tuple[float, dict]:
    shutil.rmtree(work, ignore_errors=True)
    out = {}
    t0 = time.perf_counter()
    for sc in scenarios:
        for m in maskers:
            d = work / sc / m
            _cli(["run", str(root / sc / "sequences" / "00"), "--out", str(d), "--masker", m, "--detector", "oracle"])
            out[f"{sc}/00/{m}/r0"] = json.loads(_cli(["eval", str(d / "trajectory.kitti.txt"),
                                                      str(root / sc / "poses" / "00.txt"), "--json"]))
    return time.perf_counter() - t0, out


def bench(root: Path, maskers: list[str], engine: str, workers: int, out: Path) -> tuple[float, dict]:
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    _cli(["bench", str(root), "--out", str(out), "--maskers", ",".join(maskers), "--repeats", "1",
          "--detector", "oracle", "--engine", engine, "--workers", str(workers)])
    wall = time.perf_counter() - t0
    return wall, json.loads((out / "results.json").read_text())


def compare(results: dict, reference: dict, tables: str) -> list[str]:
    """Differences between the sweep's numbers and the sequential eval --json (empty = equal)."""
    from dynastereo.bench.tables import cell

    diffs = []
    runs = {r["key"]: r for r in results["runs"]}
    for key, ref in reference.items():
        r = runs.get(key)
        if r is None or r["status"] != "done":
            diffs.append(f"{key}: not done in the sweep")
            continue
        for k, v in ref.items():
            if k not in IGNORED_KEYS and r["metrics"].get(k) != v:
                diffs.append(f"{key}: {k} {r['metrics'].get(k)!r} != {v!r}")
        seq, masker = r["sequence"], r["masker"]
        row = next((line for line in tables.splitlines() if line.startswith(f"| {seq} |")), "")
        col = results["bench"]["maskers"].index(masker) + 2
        cells = row.split("|")
        if len(cells) <= col or cells[col].strip() != cell([ref["ape.rmse"]]):
            diffs.append(f"{key}: tables.md ATE cell {cells[col].strip() if len(cells) > col else None!r} "
                         f"!= {cell([ref['ape.rmse']])!r}")
    return diffs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", default="convoy,oncoming,crossing,mixed")
    ap.add_argument("--maskers", default="none,box")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--engines", default="ray")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "dynastereo-bench-sweep")
    ap.add_argument("--out", type=Path, default=results_path("sweep"))
    a = ap.parse_args()
    scenarios, maskers, engines = a.scenarios.split(","), a.maskers.split(","), a.engines.split(",")
    root = make_root(a.cache, scenarios, a.frames)
    n_jobs = len(scenarios) * len(maskers)
    load_before = os.getloadavg()
    rounds = []
    for k in range(a.rounds):
        rnd = {}
        t_seq, reference = sequential(root, scenarios, maskers, a.cache / "sequential")
        rnd["sequential_s"] = round(t_seq, 3)
        for eng in engines:
            wall, res = bench(root, maskers, eng, a.workers, a.cache / f"bench_{eng}")
            done = [r for r in res["runs"] if r["status"] == "done"]
            run_sum = sum(r["run_s"] for r in done)
            meta = res["bench"]
            jobs_span = meta["jobs_done_at_s"] - meta["jobs_started_at_s"]  # first submit to last record
            idle = (jobs_span * a.workers - sum(r["job_s"] for r in done)) / len(done)
            diffs = compare(res, reference, (a.cache / f"bench_{eng}" / "tables.md").read_text())
            rnd[eng] = {
                "wall_s": round(wall, 3),
                "ratio": round(wall / t_seq, 3),
                "jobs_done": len(done),
                "overhead_in_job_s": round(float(np.median([r["overhead_s"] for r in done])), 3),
                "overhead_in_job_max_s": round(max(r["overhead_s"] for r in done), 3),
                "idle_per_job_s": round(idle, 3),
                "overhead_per_job_s": round(float(np.median([r["overhead_s"] for r in done])) + idle, 3),
                "engine_start_s": meta["engine_start_s"],
                "fixed_s": round(wall - jobs_span, 3),
                "non_slam_per_job_s": round((wall * a.workers - run_sum) / n_jobs, 3),
                "run_s_sum": round(run_sum, 3),
                "identical_to_run_eval": not diffs,
                "differences": diffs[:20],
            }
        rounds.append(rnd)
        print(f"round {k + 1}: sequential {t_seq:.1f} s; "
              + "; ".join(f"{e} {rnd[e]['wall_s']:.1f} s (x{rnd[e]['ratio']:.2f})" for e in engines), flush=True)
    load_after = os.getloadavg()

    med = {"sequential_s": float(np.median([r["sequential_s"] for r in rounds]))}
    for eng in engines:
        med[eng] = {key: float(np.median([r[eng][key] for r in rounds]))
                    for key in ("wall_s", "ratio", "overhead_in_job_s", "idle_per_job_s", "overhead_per_job_s",
                                "engine_start_s", "fixed_s", "non_slam_per_job_s")}
        med[eng]["identical_to_run_eval"] = all(r[eng]["identical_to_run_eval"] for r in rounds)
    targets = {}
    if "ray" in engines:
        targets = {
            "ray_ratio_max": 0.75, "overhead_per_job_max_s": 2.0,
            "ray_ratio_met": med["ray"]["ratio"] <= 0.75,
            "overhead_met": med["ray"]["overhead_per_job_s"] <= 2.0,
            "identical_met": med["ray"]["identical_to_run_eval"],
        }
    print(f"\n{n_jobs} jobs ({len(scenarios)} synthetic sequences x {len(maskers)} maskers, {a.frames} frames, "
          f"{a.workers} workers, {os.cpu_count()} cores; load {load_before[0]:.1f} -> {load_after[0]:.1f}); "
          f"medians over {a.rounds} round(s):")
    print(f"  sequential run + eval CLI   {med['sequential_s']:7.1f} s")
    for eng in engines:
        m = med[eng]
        print(f"  bench --engine {eng:6s}       {m['wall_s']:7.1f} s   ratio {m['ratio']:.2f}   overhead per job "
              f"{m['overhead_per_job_s']:.2f} s (in the job {m['overhead_in_job_s']:.2f} + idle slot "
              f"{m['idle_per_job_s']:.2f});  once per sweep {m['fixed_s']:.1f} s (engine start "
              f"{m['engine_start_s']:.1f});  all non-SLAM time / job {m['non_slam_per_job_s']:.2f} s;  "
              f"identical to run+eval: {m['identical_to_run_eval']}")
    if targets:
        print(f"  targets: ratio <= 0.75 {'met' if targets['ray_ratio_met'] else 'NOT met'}; overhead <= 2 s "
              f"{'met' if targets['overhead_met'] else 'NOT met'}; "
              f"identical {'yes' if targets['identical_met'] else 'NO'}")
    result = {
        "benchmark": "sweep", "scenarios": scenarios, "maskers": maskers, "frames": a.frames, "jobs": n_jobs,
        "workers": a.workers, "engines": engines, "rounds": rounds, "medians": med, "targets": targets,
        "load_before": load_before, "load_after": load_after, "machine": machine(),
        "command": "python benchmarks/bench_sweep.py " + " ".join(sys.argv[1:]),
    }
    write_json(a.out, result)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
