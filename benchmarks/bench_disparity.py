"""Benchmark disparity estimation against ground truth (thesis 3.3.1/3.3.2, 4.3).

Pairs: KITTI stereo 2015 000046_10 (``disp_occ_0``) and Middlebury 2014 Motorcycle at
quarter resolution (``disp0GT.pfm``; numDisparities from ``calib.txt``'s ndisp).
Matchers: StereoBM, StereoSGBM, StereoSGBM 3-way -- each with and without the WLS
filter, at full and at half resolution (the masking fast path).

Metrics over the GT-valid pixels: ``bad3`` = |err| > 3 px with missing estimates
counted as bad; ``bad3_est`` = the same over the estimated pixels only; ``density`` =
fraction estimated; ``ms`` = median wall time of ``compute`` over repeats.

Prints a table; writes benchmarks/results/disparity.json.
Run: DYNASTEREO_DATA=/work/shared/data .venv/bin/python benchmarks/bench_disparity.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from _common import data_dir, machine, median, print_table, results_path, write_json
from dynastereo.config import StereoConfig
from dynastereo.io.images import read_pfm
from dynastereo.masking.disparity import StereoMatcher

OUT = results_path("disparity")

MATCHERS = [  # name, algorithm, block size
    ("BM", "bm", 15),
    ("SGBM", "sgbm", 5),
    ("SGBM-3way", "sgbm3way", 5),
]


def _read_gray(p: Path) -> np.ndarray:
    img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
    if img is None:
        sys.exit(f"cannot read {p}")
    return img


def load_pairs(root: Path) -> list[dict]:
    pairs = []
    k = root / "kitti_stereo2015/training"
    name = "000046_10.png"
    gt = cv2.imread(str(k / "disp_occ_0" / name), cv2.IMREAD_UNCHANGED)
    if gt is None:
        sys.exit(f"cannot read {k / 'disp_occ_0' / name}")
    pairs.append({
        "name": "kitti2015/000046_10",
        "left": _read_gray(k / "image_2" / name),
        "right": _read_gray(k / "image_3" / name),
        "gt": gt.astype(np.float32) / 256.0,
        "num_disparities": 96,
    })
    m = root / "middlebury2014/trainingQ/Motorcycle"
    calib = dict(
        line.strip().split("=", 1) for line in (m / "calib.txt").read_text().splitlines() if "=" in line
    )
    ndisp = int(calib["ndisp"])
    gt = read_pfm(m / "disp0GT.pfm").astype(np.float32)
    gt[~np.isfinite(gt)] = 0.0
    pairs.append({
        "name": "middlebury2014Q/Motorcycle",
        "left": _read_gray(m / "im0.png"),
        "right": _read_gray(m / "im1.png"),
        "gt": gt,
        "num_disparities": int(math.ceil(ndisp / 16.0)) * 16,
    })
    return pairs


def metrics(d: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    v = gt > 0
    est = v & (d > 0)
    bad = np.abs(d - gt) > 3.0
    return {
        "bad3": round(float((v & (bad | (d <= 0))).sum() / v.sum()), 4),
        "bad3_est": round(float((est & bad).sum() / max(est.sum(), 1)), 4),
        "density": round(float(est.sum() / v.sum()), 4),
    }


def timed(fn, repeats: int) -> tuple[float, np.ndarray]:
    out = fn()  # warm-up (allocations, thread pool)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        ts.append((time.perf_counter() - t0) * 1000.0)
    return median(ts), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", type=int, default=0, help="cv2.setNumThreads (0: OpenCV default)")
    args = ap.parse_args()
    if args.threads:
        cv2.setNumThreads(args.threads)
    pairs = load_pairs(data_dir())
    rows = []
    for pair in pairs:
        for label, alg, block in MATCHERS:
            for wls in (False, True):
                for scale in (1, 2):
                    cfg = StereoConfig(algorithm=alg, block_size=block, wls=wls,
                                       num_disparities=pair["num_disparities"])
                    m = StereoMatcher(cfg)
                    slow = alg == "sgbm" or wls
                    reps = max(3, args.repeats // 2) if slow and scale == 1 else args.repeats
                    ms, d = timed(lambda: m.compute(pair["left"], pair["right"], scale=scale), reps)
                    row = {"pair": pair["name"], "matcher": label + ("+WLS" if wls else ""), "scale": scale,
                           "algorithm": alg, "block_size": block, "wls": wls,
                           "num_disparities": pair["num_disparities"], "ms": round(ms, 2), "repeats": reps}
                    row.update(metrics(d, pair["gt"]))
                    rows.append(row)
                    print(f"{pair['name']:28s} {row['matcher']:14s} x1/{scale}  bad3 {row['bad3']:.3f}  "
                          f"bad3_est {row['bad3_est']:.3f}  density {row['density']:.3f}  {ms:7.1f} ms",
                          flush=True)
    print()
    print_table(("pair", "matcher", "scale", "bad3 (missing = bad)", "bad3 over estimates", "density", "median ms"),
                [(r["pair"], r["matcher"], f"1/{r['scale']}", f"{r['bad3']:.3f}", f"{r['bad3_est']:.3f}",
                  f"{r['density']:.3f}", f"{r['ms']:.1f}") for r in rows])
    result = {
        "benchmark": "disparity",
        "metric": "bad3 = |d - gt| > 3 px over GT-valid pixels (missing estimates count as bad); "
                  "bad3_est over estimated pixels only; density = estimated / GT-valid",
        "machine": machine(cv2_threads=cv2.getNumThreads()),
        "rows": rows,
    }
    write_json(OUT, result)
    print(f"\nwrote {OUT}")


if __name__ == "__main__":
    main()
