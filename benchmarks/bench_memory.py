"""Memory over a long run: the synthetic ``loop`` scenario driven several laps.

The same lap of the ~390 m block (``dynastereo synth --scenario loop``) is fed again and
again through ``run`` (``--frames 0-N,0-N,...``: every lap the same place), the way a
user runs it (``api.run_sequence``: masking, SLAM with local BA and loop closing, the
files written as it goes).  At the end of every lap the resident memory (RSS) of the
process and of its workers (local BA, the loop's full BA) is read from ``/proc``, with
the map's size.  A map that does not double where the camera drives twice, and workers
that give their memory back, make the growth per lap after the first a small fraction of
the first lap's (target: <= 10 %).

    .venv/bin/python benchmarks/bench_memory.py [--laps 6] [--masker none] [--size 640x192]

Prints a table per lap and writes benchmarks/results/memory.json.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import machine, results_path, write_json
from dynastereo.api import run_sequence
from dynastereo.config import Config
from dynastereo.observers import FrameEvent

RESULTS = results_path("memory")


def _rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        if ppid == pid:
            out.append(int(d.name))
    return out + [g for c in out for g in _children(c)]


class LapProbe:
    """Observer: RSS and map size at the end of every lap."""

    def __init__(self, lap_frames: int) -> None:
        self.lap = lap_frames
        self.rows: list[dict] = []
        self.t0 = time.perf_counter()
        gc.collect()
        self.start = {"main_mb": _rss_mb(os.getpid())}

    def on_frame(self, ev: FrameEvent) -> None:
        if (ev.position + 1) % self.lap:
            return
        gc.collect()
        workers = _children(os.getpid())
        mp = ev.system.map
        self.rows.append({
            "lap": (ev.position + 1) // self.lap,
            "frames": ev.position + 1,
            "keyframes": len(mp.keyframes),
            "map_points": int(mp.stats()["map_points"]),
            "main_mb": round(_rss_mb(os.getpid()), 1),
            "workers_mb": round(sum(_rss_mb(p) for p in workers), 1),
            "workers": len(workers),
            "s": round(time.perf_counter() - self.t0, 1),
        })
        r = self.rows[-1]
        print(f"lap {r['lap']}: {r['frames']} frames, {r['keyframes']} keyframes, {r['map_points']} points, "
              f"RSS main {r['main_mb']} MB + workers {r['workers_mb']} MB ({r['workers']}), {r['s']} s", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--laps", type=int, default=6)
    ap.add_argument("--masker", default="none", help="none (SLAM alone) or outline / box on the oracle boxes")
    ap.add_argument("--size", default="640x192")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "dynastereo" / "bench")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()

    from dynastereo.synth import generate

    root = args.cache / f"loop-{args.size}-s{args.seed}"
    if not (root / "sequences" / "00" / "times.txt").exists():
        generate(root, "loop", seed=args.seed, size=args.size)
    seq = root / "sequences" / "00"
    n = len(np.loadtxt(seq / "times.txt", ndmin=1))
    spec = ",".join([f"0-{n - 1}"] * args.laps)
    cfg = Config().with_overrides({"masker.kind": args.masker, "detector.name": "oracle"})
    probe = LapProbe(n)
    with tempfile.TemporaryDirectory() as tmp:
        res = run_sequence(seq, Path(tmp) / "run", cfg, frames=spec, observers=(probe,), overwrite=True)
    rows = probe.rows
    first = rows[0]["main_mb"] + rows[0]["workers_mb"] - probe.start["main_mb"]
    later = [(b["main_mb"] + b["workers_mb"]) - (a["main_mb"] + a["workers_mb"]) for a, b in zip(rows, rows[1:])]
    kf_later = [b["keyframes"] - a["keyframes"] for a, b in zip(rows, rows[1:])]
    summary = {
        "frames_per_lap": n,
        "laps": args.laps,
        "start_mb": round(probe.start["main_mb"], 1),
        "first_lap_growth_mb": round(first, 1),
        "later_lap_growth_mb": [round(x, 1) for x in later],
        "later_lap_growth_median_mb": round(float(np.median(later)), 1) if later else None,
        "later_over_first": round(float(np.median(later)) / first, 3) if later and first > 0 else None,
        "keyframes_added_per_later_lap": kf_later,
        "lost": len(res.lost),
        "fps": round(res.fps, 2),
    }
    print(json.dumps(summary, indent=1))
    write_json(args.out, {"summary": summary, "laps": rows, "masker": args.masker, "size": args.size,
                          "seed": args.seed, "machine": machine()})
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
