"""Benchmark dynastereo.eval on official KITTI ground-truth poses (06: 1101, 00: 4541 poses).

Estimate = ground truth composed with noisy relative motions (drifting odometry).
Prints median wall times (ms) over repeats; writes benchmarks/results/eval.json.
Run: DYNASTEREO_DATA=/work/shared/data .venv/bin/python benchmarks/bench_eval.py
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import numpy as np

from _common import data_path, results_path, write_json
from _common import median_ms as _median_ms
from dynastereo.eval import Trajectory, evaluate, kitti_odometry_error, plot_trajectories, read_trajectory

REPEATS = 7


def median_ms(fn, repeats=REPEATS):
    return _median_ms(fn, repeats)


def perturb(poses, rng):
    rel = np.linalg.inv(poses[:-1]) @ poses[1:]
    rel[:, :3, 3] += rng.normal(0, 0.02, (len(rel), 3))
    out = [poses[0]]
    for r in rel:
        out.append(out[-1] @ r)
    return np.array(out)


def devkit_loop(gt, est, lengths=(100, 200, 300, 400, 500, 600, 700, 800), step=10):
    """The devkit's calcSequenceErrors transcribed with Python loops (the 'before')."""
    dist = [0.0]
    for i in range(1, len(gt)):
        dist.append(dist[-1] + float(np.linalg.norm(gt[i - 1, :3, 3] - gt[i, :3, 3])))
    t, r = [], []
    for first in range(0, len(gt), step):
        for length in lengths:
            last = next((i for i in range(first, len(dist)) if dist[i] > dist[first] + length), -1)
            if last == -1:
                continue
            e = np.linalg.inv(np.linalg.inv(est[first]) @ est[last]) @ (np.linalg.inv(gt[first]) @ gt[last])
            r.append(math.acos(max(min(0.5 * (np.trace(e[:3, :3]) - 1.0), 1.0), -1.0)) / length)
            t.append(float(np.linalg.norm(e[:3, 3])) / length)
    return 100 * np.mean(t), 100 * 180 / math.pi * np.mean(r)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=results_path("eval"))
    args = ap.parse_args()
    poses_dir = data_path("kitti_odometry/dataset/poses")
    rng = np.random.default_rng(0)
    rows = []
    for seq in ("06", "00"):
        path = poses_dir / f"{seq}.txt"
        gt = read_trajectory(path)

        est = Trajectory(perturb(gt.poses, rng), name="est")
        res = evaluate(est, gt)
        vec = kitti_odometry_error(est.poses, gt.poses)
        loop = devkit_loop(gt.poses, est.poses)
        assert abs(vec.t_err_percent - loop[0]) < 1e-9 * loop[0]
        with tempfile.TemporaryDirectory() as tmp:
            plot_ms = median_ms(lambda: plot_trajectories(res.estimate, res.ground_truth, Path(tmp) / "p.png"), 3)
        rows.append(
            {
                "sequence": seq,
                "poses": len(gt),
                "read_ms": median_ms(lambda: read_trajectory(path)),
                "evaluate_ms": median_ms(lambda: evaluate(est, gt)),
                "kitti_vectorised_ms": median_ms(lambda: kitti_odometry_error(est.poses, gt.poses)),
                "kitti_loop_ms": median_ms(lambda: devkit_loop(gt.poses, est.poses), 3),
                "plot_ms": plot_ms,
                "ape_rmse_m": res.ape["rmse"],
                "kitti_t_err_percent": vec.t_err_percent,
            }
        )
    keys = ["poses", "read_ms", "evaluate_ms", "kitti_vectorised_ms", "kitti_loop_ms", "plot_ms"]
    print(f"{'seq':>4} " + " ".join(f"{k:>20}" for k in keys))
    for r in rows:
        print(f"{r['sequence']:>4} " + " ".join(f"{r[k]:>20.1f}" for k in keys))
    out = write_json(args.out, {"repeats": REPEATS, "rows": rows}, indent=2)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
