"""A refactoring, bit for bit: the same jobs with an older tree and this one, outputs
compared byte by byte (trajectories, ``objects.jsonl``, ``objects_tracks.csv``, masks, the
output bag), trajectories also as numbers (max abs difference), and the folder run's FPS
side by side.

Cases (KITTI 06, 03, raw 0001 and generated scenes; ``DYNASTEREO_DATA`` / ``_MODELS``):

* ``run06``: ``dynastereo run 06 --save-masks`` (default configuration, 51 frames);
* ``run03``: ``dynastereo run 03 --save-masks`` (99 frames);
* ``raw0001``: ``dynastereo run`` on KITTI raw drive 0001 (108 frames of traffic), masks saved;
* ``synth``: ``dynastereo run --detector oracle`` on a generated ``crossing`` scene (60 frames);
* ``mask06``: ``dynastereo mask 06 --frames 0-19 --overlays``;
* ``bag06``: ``export-bag 06 --frames 0-29`` then ``run --bag`` (the output bag too);
* ``video06``: 06's frames 0-29 as a lossless side-by-side stereo video (FFV1), ``run`` on it;
* ``node_serial`` / ``node_pipe``: the live node's core fed 06 one pair at a time;
* ``loop`` (not with ``--quick``): the synthetic ``loop`` scenario (576 frames, a loop closed).

    python benchmarks/bench_runtime.py --before 68b5895 [--repeats 3] [--quick] [--cases run06,bag06]

``--before`` is a git ref (exported with ``git archive`` into a temporary folder) or a
``src`` folder; ``--after`` defaults to this tree's ``src``.  Prints the table and writes
``benchmarks/results/runtime_refactor.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import ROOT, data_dir, median, results_path, write_json

OUT_JSON = results_path("runtime_refactor")
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


CASES = ("run06", "run03", "raw0001", "synth", "mask06", "bag06", "video06", "node", "loop")


def run_cases(src: Path, out: Path, data: Path, inputs: dict[str, Path], cases: tuple[str, ...]) -> float | None:
    """Every case into ``out``; returns the folder run's FPS of 06 (from its timing.json)."""
    k06 = data / "kitti_odometry/dataset/sequences/06"
    seqs = {"run06": k06, "run03": data / "kitti_odometry/dataset/sequences/03",
            "raw0001": data / "kitti_raw/2011_09_26/2011_09_26_drive_0001_sync"}
    for case, seq in seqs.items():
        if case in cases:
            _cli(src, "run", str(seq), "--out", str(out / case), "--save-masks", "--overwrite")
    if "synth" in cases:
        _cli(src, "run", str(inputs["synth"]), "--out", str(out / "synth"), "--detector", "oracle", "--save-masks",
             "--overwrite")
    if "mask06" in cases:
        _cli(src, "mask", str(k06), "--out", str(out / "mask06"), "--frames", "0-19", "--overlays", "--overwrite")
    if "bag06" in cases:
        _cli(src, "export-bag", str(k06), str(out / "in06.bag"), "--frames", "0-29", "--overwrite")
        _cli(src, "run", "--bag", str(out / "in06.bag"), "--out", str(out / "bag06"), "--overwrite")
    if "video06" in cases:
        _cli(src, "run", str(inputs["video"]), "--calib", str(inputs["video_calib"]), "--out", str(out / "video06"),
             "--save-masks", "--overwrite")
    if "loop" in cases:
        _cli(src, "run", str(inputs["loop"]), "--out", str(out / "loop"), "--save-masks", "--overwrite")
    if "node" in cases:
        subprocess.run([sys.executable, "-c", NODE, str(k06), str(out)], env=dict(os.environ, PYTHONPATH=str(src)),
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    timing = out / "run06" / "timing.json"
    return json.loads(timing.read_text())["summary"]["fps"] if timing.is_file() else None


def make_inputs(src: Path, tmp: Path, data: Path, cases: tuple[str, ...]) -> dict[str, Path]:
    """The inputs both trees share: the generated scenes, 06 as a stereo video."""
    inputs: dict[str, Path] = {}
    if "synth" in cases:
        _cli(src, "synth", str(tmp / "synth_crossing"), "--scenario", "crossing", "--frames", "60", "--seed", "4")
        inputs["synth"] = tmp / "synth_crossing" / "sequences" / "00"
    if "loop" in cases:
        _cli(src, "synth", str(tmp / "synth_loop"), "--scenario", "loop")
        inputs["loop"] = tmp / "synth_loop" / "sequences" / "00"
    if "video06" in cases:
        import cv2

        k06 = data / "kitti_odometry/dataset/sequences/06"
        left = sorted((k06 / "image_0").glob("*.png"))[:30]
        first = cv2.imread(str(left[0]), cv2.IMREAD_GRAYSCALE)
        h, w = first.shape
        inputs["video"] = tmp / "stereo06.mkv"
        writer = cv2.VideoWriter(str(inputs["video"]), cv2.VideoWriter_fourcc(*"FFV1"), 10, (2 * w, h), False)
        for p in left:
            writer.write(np.hstack([cv2.imread(str(p), cv2.IMREAD_GRAYSCALE),
                                    cv2.imread(str(k06 / "image_1" / p.name), cv2.IMREAD_GRAYSCALE)]))
        writer.release()
        P = [np.array(line.split()[1:], float).reshape(3, 4) for line in (k06 / "calib.txt").read_text().splitlines()[:2]]
        fx = P[0][0, 0]
        inputs["video_calib"] = tmp / "stereo06.yaml"
        inputs["video_calib"].write_text(f"fx: {fx!r}\nfy: {P[0][1, 1]!r}\ncx: {P[0][0, 2]!r}\ncy: {P[0][1, 2]!r}\n"
                                         f"baseline: {-P[1][0, 3] / fx!r}\n")
    return inputs


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
    ap.add_argument("--quick", action="store_true", help="leave out the 576-frame loop")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma list of {', '.join(CASES)}")
    args = ap.parse_args()
    cases = tuple(c for c in args.cases.split(",") if c and not (args.quick and c == "loop"))
    bad = [c for c in cases if c not in CASES]
    if bad:
        ap.error(f"unknown case(s) {', '.join(bad)}; choose from {', '.join(CASES)}")
    data = data_dir()
    with tempfile.TemporaryDirectory(prefix="bench-runtime-") as tmp_s:
        tmp = Path(tmp_s)
        trees = {"before": _src(args.before, tmp), "after": Path(args.after).resolve()}
        inputs = make_inputs(trees["after"], tmp, data, cases)
        k06 = data / "kitti_odometry/dataset/sequences/06"
        for name, src in trees.items():  # warm-up: numba's cache of a freshly exported tree is empty
            _cli(src, "run", str(k06), "--frames", "0-9", "--out", str(tmp / f"warm_{name}"), "--overwrite")
        fps: dict[str, list[float]] = {k: [] for k in trees}
        for r in range(args.repeats):
            for name, src in (trees.items() if r % 2 == 0 else reversed(trees.items())):
                fps[name].append(run_cases(src, tmp / f"{name}{r}", data, inputs, cases))
        rows = compare(tmp / "before0", tmp / "after0")
    differ = [r for r in rows if not r["same"]]
    worst = max((r.get("max_abs_diff", 0.0) for r in rows), default=0.0)
    res = {"before": args.before, "after": args.after, "files_compared": len(rows), "files_differing": len(differ),
           "differing": [r["file"] for r in differ], "max_abs_trajectory_difference": worst,
           "fps_run06": {k: {"runs": v, "median": median(v, digits=3)} for k, v in fps.items()},
           "cases": sorted({r["file"].split("/")[0] for r in rows})}
    write_json(OUT_JSON, res)
    print(f"{len(rows)} files compared over {', '.join(res['cases'])}: {len(differ)} differ; "
          f"largest trajectory difference {worst:g}")
    for k, v in res["fps_run06"].items():
        print(f"run06 FPS {k}: median {v['median']} of {v['runs']}")
    print(f"-> {OUT_JSON}")


if __name__ == "__main__":
    main()
