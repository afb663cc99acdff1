"""Masking's CPU a stereo pair, and whether two source trees give the same masks.

Runs the default masker (``dynastereo.masking.build_masker`` with the defaults, the
network warmed up first) over frames 1..N of each sequence in a subprocess per tree and
repeat, alternating the trees (``--src`` this checkout's ``src``, ``--against`` another
checkout's, e.g. ``git worktree add ../old <commit>``), and reports per sequence and tree
the **process time a pair** (all threads: the masker's own CPU, the detector's runs
included), mean and median over the frames, medians over the repeats, and a hash of the
outputs (left / right masks, label images, each object's box, method and disparity): equal
hashes mean the same masks bit for bit; and a hash of the mask and label images alone
("pixels": the same masks, boxes that may differ by float rounding).  The masking kernels were measured with it.

Prints a table; writes ``benchmarks/results/mask_cpu.json`` (``--out``).  Run:

    DYNASTEREO_DATA=... DYNASTEREO_MODELS=... .venv/bin/python benchmarks/bench_mask_cpu.py \\
        [--against ../old/src] [--seqs raw0001,06] [--frames 40] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from _common import CLIPS, ROOT, data_dir, machine, models_dir, results_path, write_json

OUT = results_path("mask_cpu")
SEQS = CLIPS

# the child: one tree, one sequence; prints one JSON line
CHILD = r"""
import hashlib, json, os, sys, time
import numpy as np
from dynastereo.config import Config
from dynastereo.io import open_sequence
from dynastereo.masking import build_masker
seq = open_sequence(sys.argv[1]); n = min(int(sys.argv[2]), len(seq))
m = build_masker(Config(), seq.calibration, models_dir=sys.argv[3] or None)
frames = [seq.frame(i) for i in range(n)]
m.warm_up(*frames[0].left.shape[:2])
m.mask(frames[0])
h = hashlib.sha1(); px = hashlib.sha1(); cpu = []
for f in frames[1:]:
    c0 = time.process_time(); r = m.mask(f); cpu.append(time.process_time() - c0)
    for a in (r.left, r.right, r.labels_left, r.labels_right):
        if a is not None:
            b = np.ascontiguousarray(a).tobytes()
            h.update(b); px.update(b)
    h.update(repr([(tuple(o.box), str(o.method), round(float(o.disparity), 6)) for o in r.objects]).encode())
print(json.dumps({"mean_ms": 1e3 * float(np.mean(cpu)), "median_ms": 1e3 * float(np.median(cpu)),
                  "hash": h.hexdigest()[:16], "pixels": px.hexdigest()[:16]}))
"""


def one(src: Path, seq: Path, frames: int) -> dict:
    env = {**os.environ, "PYTHONPATH": str(src)}
    models = models_dir(required=False)
    out = subprocess.run([sys.executable, "-c", CHILD, str(seq), str(frames), str(models or "")], env=env, capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--src", type=Path, default=ROOT / "src", help="this tree's source folder")
    ap.add_argument("--against", type=Path, default=None, help="another tree's source folder, alternated with --src")
    ap.add_argument("--seqs", default="raw0001,06")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    data = data_dir(required=False)
    if not data:
        print("skipped: DYNASTEREO_DATA is not set (the KITTI sequences are needed)")
        return 0
    trees = {"src": args.src.resolve()}
    if args.against is not None:
        trees = {"against": args.against.resolve(), **trees}
    runs: dict[str, dict[str, list[dict]]] = {}
    for name in [s for s in args.seqs.split(",") if s]:
        seq = Path(data) / SEQS[name]
        for r in range(args.repeats):
            for tree, src in trees.items():
                res = one(src, seq, args.frames)
                runs.setdefault(name, {}).setdefault(tree, []).append(res)
                print(f"{name:8s} {tree:8s} repeat {r + 1}: {res['mean_ms']:.1f} ms a pair (mean), "
                      f"{res['median_ms']:.1f} (median), masks {res['hash']}", flush=True)
    summary = {}
    print(f"\nprocess time a pair, frames 1-{args.frames - 1}, medians over {args.repeats} repeats")
    for name, by in runs.items():
        summary[name] = {}
        for tree, rs in by.items():
            hashes = sorted({r["hash"] for r in rs})
            pixels = sorted({r.get("pixels", "") for r in rs})
            summary[name][tree] = {"mean_ms": round(float(np.median([r["mean_ms"] for r in rs])), 2),
                                   "median_ms": round(float(np.median([r["median_ms"] for r in rs])), 2),
                                   "hashes": hashes, "pixels": pixels}
            print(f"  {name:8s} {tree:8s} mean {summary[name][tree]['mean_ms']:.1f} ms  "
                  f"median {summary[name][tree]['median_ms']:.1f} ms  masks {', '.join(hashes)}")
        if len(by) == 2:
            a, b = summary[name]["against"], summary[name]["src"]
            same = a["hashes"] == b["hashes"] and len(a["hashes"]) == 1
            same_px = a["pixels"] == b["pixels"] and len(a["pixels"]) == 1
            print(f"  {name:8s} src / against: {b['mean_ms'] / a['mean_ms']:.3f} (mean), masks "
                  f"{'identical' if same else 'DIFFERENT'} (pixels {'identical' if same_px else 'DIFFERENT'})")
            summary[name]["same_masks"] = same
            summary[name]["same_pixels"] = same_px
    result = {"benchmark": "mask_cpu", "frames": args.frames, "repeats": args.repeats,
              "trees": {k: str(v) for k, v in trees.items()},
              "machine": machine(),
              "runs": runs, "summary": summary}
    write_json(args.out, result)
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
