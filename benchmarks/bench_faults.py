"""What the fault handling costs a clean run: ``dynastereo run`` on KITTI 06 (all 51
frames, default settings) with the code before and after, alternated, in their own
processes; the end-to-end FPS of each run from its ``run.json``, medians printed.

    python benchmarks/bench_faults.py --before /work/main/src --after src [--repeats 3]

Writes benchmarks/results/faults.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from _common import CLIPS, ROOT, data_path, median, results_path, write_json


def run_once(src: str, seq: Path, out: Path) -> float:
    env = dict(os.environ, PYTHONPATH=str(Path(src).resolve()))
    r = subprocess.run([sys.executable, "-m", "dynastereo.cli.main", "run", str(seq), "-o", str(out), "--overwrite"],
                       env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{src}: run failed: {r.stderr[-2000:]}")
    return float(json.loads((out / "run.json").read_text())["fps"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", required=True, help="src folder of the code before (PYTHONPATH)")
    ap.add_argument("--after", default=str(ROOT / "src"), help="src folder of the code after")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sequence", default=None, help="default: $DYNASTEREO_DATA/kitti_odometry/dataset/sequences/06")
    a = ap.parse_args()
    seq = Path(a.sequence) if a.sequence else data_path(CLIPS["06"])
    fps: dict[str, list[float]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as tmp:
        run_once(a.after, seq, Path(tmp) / "warm")  # kernels compiled and cached once
        for k in range(a.repeats):
            order = ("before", "after") if k % 2 == 0 else ("after", "before")
            for name in order:
                f = run_once(a.before if name == "before" else a.after, seq, Path(tmp) / name)
                fps[name].append(f)
                print(f"run {k + 1} {name:6s} {f:.2f} FPS", flush=True)
    med = {k: median(v) for k, v in fps.items()}
    print(f"median FPS: before {med['before']:.2f}, after {med['after']:.2f} "
          f"({100 * (med['after'] / med['before'] - 1):+.1f} %)")
    res = {"sequence": str(seq), "frames": "all (51)", "repeats": a.repeats, "fps": fps, "median_fps": med}
    write_json(results_path("faults"), res)


if __name__ == "__main__":
    main()
