"""The runtime refactor, bit for bit: the same jobs with an older tree and this
one, outputs compared byte by byte, trajectories as numbers (max abs difference), and the
folder run's FPS side by side.

Cases (KITTI 06 and a generated ``loop`` scenario; ``DYNASTEREO_DATA`` / ``_MODELS``):

* ``run06``: ``dynastereo run 06 --save-masks`` (default configuration, 51 frames);
* ``mask06``: ``dynastereo mask 06 --frames 0-19 --overlays``;
* ``bag06``: ``export-bag 06 --frames 0-29`` then ``run --bag`` (the output bag too);
* ``loop``: ``dynastereo run`` on the synthetic ``loop`` scenario (576 frames, a loop closed);
* ``node_serial`` / ``node_pipe``: the live node's core fed 06 one pair at a time.

    python benchmarks/bench_runtime.py --before 68b5895 [--repeats 3] [--quick]

``--before`` is a git ref (exported with ``git archive`` into a temporary folder) or a
``src`` folder; ``--after`` defaults to this tree's ``src``.  Prints the table and writes
``benchmarks/results/runtime_refactor.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT_JSON = ROOT / "benchmarks" / "results" / "runtime_refactor.json"
FILES = ("trajectory.kitti.txt", "trajectory.tum.txt", "trajectory.frames.txt", "objects.jsonl",
         "objects_tracks.csv", "output.bag")
NODE = r"""
import sys
from pathlib import Path
from dynastereo.config import Config
from dynastereo.io import KittiSequence
from dynastereo.ros.core import StereoInput, StereoNodeCore
seq, out = KittiSequence(Path(sys.argv[1])), Path(sys.argv[2])
st = seq.timestamps()
for pipelined in (False, True):
    core = StereoNodeCore(Config(), calibration=seq.calibration, pipelined=pipelined)
    core.start()
    for i in range(len(seq)):
        f = seq.frame(i)
        core.submit(StereoInput(f.left, f.right, int(round(st[i] * 1e9))))
        assert core.wait_idle(300)
    core.save(out / ("node_pipe" if pipelined else "node_serial"))
    core.shutdown()
"""


def _src(ref: str, tmp: Path) -> Path:
    if Path(ref).is_dir():
        return Path(ref).resolve()
    dst = tmp / "before"
    dst.mkdir()
    data = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "src"], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dst)], input=data, check=True)
    return dst / "src"


def _cli(src: Path, *args: str) -> float:
    env = dict(os.environ, PYTHONPATH=str(src))
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "dynastereo.cli.main", *args], env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    return time.perf_counter() - t0


def run_cases(src: Path, out: Path, data: Path, loop_seq: Path, quick: bool) -> dict[str, float]:
    """Every case into ``out``; returns the folder run's FPS (from its timing.json)."""
    k06 = data / "kitti_odometry/dataset/sequences/06"
    _cli(src, "run", str(k06), "--out", str(out / "run06"), "--save-masks", "--overwrite")
    _cli(src, "mask", str(k06), "--out", str(out / "mask06"), "--frames", "0-19", "--overlays", "--overwrite")
    _cli(src, "export-bag", str(k06), str(out / "in06.bag"), "--frames", "0-29", "--overwrite")
    _cli(src, "run", "--bag", str(out / "in06.bag"), "--out", str(out / "bag06"), "--overwrite")
    if not quick:
        _cli(src, "run", str(loop_seq), "--out", str(out / "loop"), "--save-masks", "--overwrite")
        subprocess.run([sys.executable, "-c", NODE, str(k06), str(out)], env=dict(os.environ, PYTHONPATH=str(src)),
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    return json.loads((out / "run06" / "timing.json").read_text())["summary"]["fps"]


def _traj(p: Path) -> np.ndarray:
    return np.loadtxt(p, ndmin=2)


def compare(a: Path, b: Path) -> list[dict]:
    """Every output file of both trees: byte-identical?  trajectories: max abs difference."""
    rows = []
    for case in sorted(d.name for d in a.iterdir() if d.is_dir()):
        files = [case + "/" + n for n in FILES if (a / case / n).is_file()]
        for sub in ("masks", "overlays"):
            files += sorted(str(p.relative_to(a)) for p in (a / case / sub).rglob("*.png"))
        for f in files:
            fa, fb = a / f, b / f
            row = {"file": f, "same": fb.is_file() and fa.read_bytes() == fb.read_bytes()}
            if f.endswith((".kitti.txt", ".tum.txt")) and fb.is_file():
                ta, tb = _traj(fa), _traj(fb)
                row["max_abs_diff"] = float(np.abs(ta - tb).max()) if ta.shape == tb.shape else float("inf")
            rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", required=True, help="git ref or src folder of the older tree")
    ap.add_argument("--after", default=str(ROOT / "src"))
    ap.add_argument("--repeats", type=int, default=1, help="folder runs per tree for the FPS (alternated)")
    ap.add_argument("--quick", action="store_true", help="leave out the 576-frame loop and the node")
    args = ap.parse_args()
    data = Path(os.environ.get("DYNASTEREO_DATA", ROOT.parent / "shared" / "data"))
    with tempfile.TemporaryDirectory(prefix="bench-runtime-") as tmp_s:
        tmp = Path(tmp_s)
        trees = {"before": _src(args.before, tmp), "after": Path(args.after).resolve()}
        loop_seq = tmp / "synth_loop"
        _cli(trees["after"], "synth", str(loop_seq), "--scenario", "loop")
        k06 = data / "kitti_odometry/dataset/sequences/06"
        for name, src in trees.items():  # warm-up: numba's cache of a freshly exported tree is empty
            _cli(src, "run", str(k06), "--frames", "0-9", "--out", str(tmp / f"warm_{name}"), "--overwrite")
        fps: dict[str, list[float]] = {k: [] for k in trees}
        for r in range(args.repeats):
            for name, src in (trees.items() if r % 2 == 0 else reversed(trees.items())):
                fps[name].append(run_cases(src, tmp / f"{name}{r}", data, loop_seq / "sequences" / "00", args.quick))
        rows = compare(tmp / "before0", tmp / "after0")
    differ = [r for r in rows if not r["same"]]
    worst = max((r.get("max_abs_diff", 0.0) for r in rows), default=0.0)
    res = {"before": args.before, "after": args.after, "files_compared": len(rows), "files_differing": len(differ),
           "differing": [r["file"] for r in differ], "max_abs_trajectory_difference": worst,
           "fps_run06": {k: {"runs": v, "median": round(statistics.median(v), 3)} for k, v in fps.items()},
           "cases": sorted({r["file"].split("/")[0] for r in rows})}
    OUT_JSON.parent.mkdir(parents=True, exist_ok=True)
    OUT_JSON.write_text(json.dumps(res, indent=1))
    print(f"{len(rows)} files compared over {', '.join(res['cases'])}: {len(differ)} differ; "
          f"largest trajectory difference {worst:g}")
    for k, v in res["fps_run06"].items():
        print(f"run06 FPS {k}: median {v['median']} of {v['runs']}")
    print(f"-> {OUT_JSON}")


if __name__ == "__main__":
    main()
