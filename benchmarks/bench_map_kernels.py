"""The map's bookkeeping kernels (``slam/kernels/bookkeeping.py``), before and after:
this tree against an older source tree, side by side, alternated.

Each repeat runs, for the old tree (``--old-src``: a ``src`` folder, e.g. ``git archive
<commit> src | tar -x -C /tmp/old``) and then this one, each in its own process with
``PYTHONPATH`` pointing at that source:

* ``bench_profile.py --part stages`` (the SLAM's stage table: CPU ms a frame and
  Python-level calls a frame per stage, one timed pass per repeat), and
* ``bench_peers.py --systems none`` (``dynastereo run --masker none`` as a user runs it:
  the frame loop's FPS and the process tree's CPU a frame, start-up left out).

Prints, per clip, the medians over the repeats side by side, and writes
``benchmarks/results/map_kernels.json``.  Speed figures on a shared machine are noisy:
compare the two columns of one run, not runs of different days.

    DYNASTEREO_DATA=... .venv/bin/python benchmarks/bench_map_kernels.py --old-src /tmp/old/src \
        [--sequences 06,03] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from _common import BENCH, ROOT, load, median, now, print_table, results_path, write_json

HERE = BENCH
NEW_SRC = ROOT / "src"
OUT = results_path("map_kernels")
MAP_STAGES = ("map: normals, distances, descriptors (update_points)", "map: add / erase / fuse observations",
              "map: covisibility (update_connections)", "map: observation rows (rows_of)")


def _run(script: str, src: Path, args: list[str], out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(src)}
    subprocess.run([sys.executable, str(HERE / script), *args, "--out", str(out)], env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return json.loads(out.read_text())


def _med(xs: list[float]) -> float:
    m = median(xs, digits=2)
    return float("nan") if m is None else m


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old-src", type=Path, required=True, help="the src folder of the tree to compare with")
    ap.add_argument("--sequences", default="06,03")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    if not (args.old_src / "dynastereo").is_dir():
        raise SystemExit(f"--old-src {args.old_src}: no dynastereo package there")
    seqs = args.sequences.split(",")
    trees = {"before": args.old_src.resolve(), "after": NEW_SRC}
    runs: dict[str, list] = {t: [] for t in trees}
    loads = [load()]
    with tempfile.TemporaryDirectory(prefix="bench_map_kernels_") as tmp:
        for rep in range(args.repeats):
            for tree, src in trees.items():
                prof = _run("bench_profile.py", src, ["--part", "stages", "--sequences", ",".join(seqs),
                                                     "--repeats", "1"], Path(tmp) / f"prof_{tree}_{rep}.json")
                peers = _run("bench_peers.py", src, ["--clips", ",".join(seqs), "--systems", "none", "--repeats", "1"],
                             Path(tmp) / f"peers_{tree}_{rep}.json")
                runs[tree].append({"stages": prof["slam_stages"]["sequences"],
                                   "run": {c: peers["runs"][c]["none"][0] for c in seqs}})
                loads.append(load())
                print(f"repeat {rep + 1} {tree} done (load {loads[-1]:.1f})", flush=True)
    table: dict[str, dict] = {}
    for s in seqs:
        stages = [r["stage"] for r in runs["after"][0]["stages"][s]["rows"]]
        rows = {}
        for st in stages:
            rows[st] = {}
            for tree in trees:
                got = [next(x for x in r["stages"][s]["rows"] if x["stage"] == st) for r in runs[tree]]
                rows[st][tree] = {"cpu_ms": _med([g["cpu_ms_per_frame"] for g in got]),
                                  "calls": _med([g["calls_per_frame"] for g in got])}
        for tree in trees:
            rows.setdefault("map bookkeeping (the four map stages)", {})[tree] = {
                "cpu_ms": _med([sum(x["cpu_ms_per_frame"] for x in r["stages"][s]["rows"] if x["stage"] in MAP_STAGES)
                                for r in runs[tree]]),
                "calls": _med([sum(x["calls_per_frame"] for x in r["stages"][s]["rows"] if x["stage"] in MAP_STAGES)
                               for r in runs[tree]])}
            rows.setdefault("total (stage table)", {})[tree] = {
                "cpu_ms": _med([r["stages"][s]["total_cpu_ms_per_frame"] for r in runs[tree]]),
                "calls": _med([r["stages"][s]["calls_per_frame"] for r in runs[tree]])}
            rows.setdefault("`dynastereo run --masker none`: process CPU a frame", {})[tree] = {
                "cpu_ms": _med([r["run"][s]["cpu_ms"] for r in runs[tree]]), "calls": None}
            rows.setdefault("`dynastereo run --masker none`: frame loop FPS", {})[tree] = {
                "fps": _med([r["run"][s]["fps"] for r in runs[tree]])}
        table[s] = rows
        print(f"\nKITTI {s} (medians of {args.repeats}, before -> after)")
        cells = []
        for st, d in rows.items():
            b, a = d["before"], d["after"]
            if "fps" in b:
                cells.append((st, f"{b['fps']:.2f} -> **{a['fps']:.2f}** FPS", ""))
                continue
            calls = "" if b["calls"] is None else f"{b['calls']:.0f} -> {a['calls']:.0f}"
            cells.append((st, f"{b['cpu_ms']:.1f} -> **{a['cpu_ms']:.1f}**", calls))
        print_table(("stage", "CPU ms / frame", "Python-level calls / frame"), cells, align="lrr")
    res = {"date": now(), "old_src": str(args.old_src),
           "repeats": args.repeats, "load_average": loads, "medians": table, "runs": runs}
    write_json(args.out, res)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
