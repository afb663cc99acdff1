"""The ORB extractor alone: this tree's beside another's.

CPU and wall time a stereo pair, serial and the way a run extracts (the right image on a
second thread beside the left), and how many of the features the two trees give are the
same.

Each tree runs in its own process (``PYTHONPATH`` = its ``src``), the trees alternated
``--repeats`` times over the same ``--frames`` stereo pairs of each clip, with the SLAM's
default extractor settings (``SlamConfig``: 2000 features, 8 levels, scale 1.2).  Per pair:
CPU (process time, all threads) and wall, medians over the pairs, then medians over the
repeats.  "Same features": keypoints at the same position and level with the same angle
and descriptor bit for bit, as a share of this tree's.

    DYNASTEREO_DATA=/work/shared/data .venv/bin/python benchmarks/bench_orb.py \\
        --against ../other/src [--clips 06,03,raw0001] [--frames 40] [--repeats 3]

Writes benchmarks/results/orb_extract.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from _common import ROOT, clip_dirs, data_dir, load, machine, median, now, results_path, write_json

OUT = results_path("orb_extract")

CHILD = r"""
import json, sys, time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
import cv2, numpy as np
from dynastereo.config import SlamConfig
from dynastereo.slam.orb import ORBExtractor
seq, frames, dump = Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
left = sorted((seq / "image_0").glob("*.png")) or sorted((seq / "image_00" / "data").glob("*.png"))
right = sorted((seq / "image_1").glob("*.png")) or sorted((seq / "image_01" / "data").glob("*.png"))
pairs = [(cv2.imread(str(a), 0), cv2.imread(str(b), 0)) for a, b in list(zip(left, right))[:frames]]
c = SlamConfig()
ex = ORBExtractor(c.n_features, c.scale_factor, c.n_levels, c.ini_th_fast, c.min_th_fast, c.oversample, c.mask_margin)
for l, r in pairs[:2]:
    ex.extract(l), ex.extract(r)
pool = ThreadPoolExecutor(1)
out = {}
for mode in ("serial", "two_threads"):
    cpu, wall = [], []
    for l, r in pairs:
        c0, w0 = time.process_time(), time.perf_counter()
        if mode == "serial":
            ex.extract(l), ex.extract(r)
        else:
            f = pool.submit(ex.extract, r)
            ex.extract(l)
            f.result()
        cpu.append((time.process_time() - c0) * 1e3)
        wall.append((time.perf_counter() - w0) * 1e3)
    out[mode] = {"cpu_ms": float(np.median(cpu)), "wall_ms": float(np.median(wall))}
feats = [ex.extract(l) for l, _ in pairs]
np.savez(dump, uv=np.concatenate([f.uv for f in feats]), octave=np.concatenate([f.octave for f in feats]),
         angle=np.concatenate([f.angle for f in feats]), desc=np.concatenate([f.desc for f in feats]),
         image=np.concatenate([np.full(len(f), i) for i, f in enumerate(feats)]))
out["features_per_image"] = float(np.mean([len(f) for f in feats]))
print(json.dumps(out))
"""


def run_tree(src: Path, seq: Path, frames: int, dump: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(src))
    r = subprocess.run([sys.executable, "-c", CHILD, str(seq), str(frames), str(dump)], capture_output=True,
                       text=True, env=env)
    if r.returncode != 0:
        raise SystemExit(f"{src}: the extractor run failed:\n{r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def same_features(a: Path, b: Path) -> float:
    """Share of ``a``'s keypoints that ``b`` has too (image, position, level, angle, descriptor)."""
    fa, fb = np.load(a), np.load(b)

    def keys(f):
        return {(int(i), round(float(u), 3), round(float(v), 3), int(o), float(g), d.tobytes())
                for i, (u, v), o, g, d in zip(f["image"], f["uv"], f["octave"], f["angle"], f["desc"])}

    ka, kb = keys(fa), keys(fb)
    return len(ka & kb) / max(len(ka), 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--against", type=Path, default=None, help="another tree's source folder")
    ap.add_argument("--clips", default="06,03,raw0001")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    trees = {"this": ROOT / "src"}
    if args.against is not None:
        trees = {"against": args.against.resolve(), **trees}
    clips = {c: clip_dirs(data_dir())[c] for c in args.clips.split(",")}
    runs: dict = {c: {t: [] for t in trees} for c in clips}
    same: dict = {}
    load_before = load()
    with tempfile.TemporaryDirectory(prefix="orb-") as tmp:
        for rep in range(args.repeats):
            for c, seq in clips.items():
                for t, src in trees.items():
                    r = run_tree(src, seq, args.frames, Path(tmp) / f"{c}_{t}.npz")
                    runs[c][t].append(r)
                    print(f"[{rep + 1}/{args.repeats}] {c:8s} {t:8s} serial {r['serial']['cpu_ms']:5.1f} ms CPU "
                          f"{r['serial']['wall_ms']:5.1f} wall; two threads {r['two_threads']['cpu_ms']:5.1f} CPU "
                          f"{r['two_threads']['wall_ms']:5.1f} wall (a pair)", flush=True)
        if len(trees) == 2:
            same = {c: same_features(Path(tmp) / f"{c}_this.npz", Path(tmp) / f"{c}_against.npz") for c in clips}
    summary = {c: {t: {f"{m}_{k}": median(r[m][k] for r in runs[c][t])
                       for m in ("serial", "two_threads") for k in ("cpu_ms", "wall_ms")} for t in trees}
               for c in clips}
    write_json(args.out, {"date": now(), "repeats": args.repeats, "frames": args.frames,
                          "machine": machine(load_before=load_before, load_after=load()),
                          "trees": {t: str(s) for t, s in trees.items()}, "summary": summary,
                          "same_features": same, "runs": runs})
    print(f"\nms a stereo pair, medians of {args.repeats} (each the median over {args.frames} pairs)")
    print("| clip | tree | serial CPU | serial wall | two threads CPU | two threads wall |")
    print("|---|---|---|---|---|---|")
    for c in clips:
        for t in trees:
            s = summary[c][t]
            print(f"| {c} | {t} | {s['serial_cpu_ms']:.1f} | {s['serial_wall_ms']:.1f} | "
                  f"{s['two_threads_cpu_ms']:.1f} | {s['two_threads_wall_ms']:.1f} |")
    for c, v in same.items():
        print(f"{c}: {v:.1%} of this tree's features are the other's, bit for bit")
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
