"""Benchmark the SLAM back-end on KITTI odometry seq 06 (51 frames) and 03 (99 frames).

For every sequence and masker (none / box / outline / seg, through ``build_masker``)
the whole pipeline runs in one process -- frames in, masks, ``System.track``, trajectory
out -- at full resolution with the default configuration (2000 ORB features, 8 levels,
local BA in the worker process):

* accuracy against the official ground truth with ``dynastereo.eval.evaluate``:
  APE RMSE after SE(3) Umeyama alignment (no scale), start-anchored final drift in %
  of the path length, RPE per frame; targets ATE <= 0.25 m and drift <= 1 %;
* time per stage (median / mean ms over frames, frame rate = 1000 / mean): masking
  stages (``detect``, ``disparity``, ``outline``/``boxes``/``segment``, ``transfer``) and
  the SLAM stages ``features``, ``stereo``, ``track``, ``local_mapping``; the end-to-end
  rate is frames / wall time of the tracking loop (images decoded beforehand, their
  reading time is reported apart); target >= 10 frames/s with the outline masker;
* SLAM statistics: frames tracked / lost, keyframes, map points, local BA time in the
  worker, the self-calibrated disparity offset;
* ``dynastereo run``'s own rate (``api.run_sequence``: images read and masked on the
  prefetch thread, files written; ``summary.fps`` of timing.json) for the outline masker;
* revisits and gaps (``--frames``-style orders fed to ``System``): KITTI 06 ``0-11,4-6``,
  03 ``0-98,40-60`` and 06 with ten black frames after image 9: per frame fed again,
  its status / method and the distance of its pose to the first visit's and to the
  ground truth.

Accuracy is deterministic; timings are medians over ``--repeats`` runs (the machine is
shared).  Prints a table; writes benchmarks/results/slam.json.

Run: DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
     .venv/bin/python benchmarks/bench_slam.py [--repeats 3] [--maskers none,outline]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from _common import data_dir, machine, models_dir, results_path, write_json
from dynastereo.config import Config, to_dict
from dynastereo.errors import ModelError
from dynastereo.eval import Trajectory, evaluate, read_trajectory
from dynastereo.io import open_sequence
from dynastereo.masking import build_masker
from dynastereo.io.frames import parse_frame_spec
from dynastereo.slam import System
from dynastereo.timing import StageTimer
from dynastereo.datatypes import StereoFrame

OUT = results_path("slam")
SLAM_STAGES = ("features", "stereo", "track", "local_mapping")
TARGET_ATE_M = 0.25
TARGET_DRIFT_PERCENT = 1.0
TARGET_FPS = 10.0


def bench_pose_optimizer(repeats: int = 10) -> dict:
    """Motion-only BA: the numpy Gauss-Newton (``optimize_pose``) against a gtsam graph
    built per frame (one Pose3 variable, the points held by tight priors, Huber
    stereo / monocular factors, LM), on 800 synthetic observations of a KITTI-like camera."""
    import gtsam

    from dynastereo.slam.geometry import inv_T, se3_exp
    from dynastereo.slam.optimizer import optimize_pose, project

    rng = np.random.default_rng(0)
    fx, cx, cy, b = 707.0, 601.0, 183.0, 0.537
    K = np.array([[fx, 0, cx], [0, fx, cy], [0, 0, 1.0]])
    n = 800
    T_true = se3_exp(np.array([0.01, -0.02, 0.005, 0.1, 0.02, 1.1]))
    X = np.c_[rng.uniform(-10, 10, n), rng.uniform(-2, 2, n), rng.uniform(4, 40, n)]
    _, u, v, ur = project(T_true, X, fx, fx, cx, cy, b * fx)
    uv = np.c_[u, v] + rng.normal(0, 0.7, (n, 2))
    urs = np.where(X[:, 2] < 19, ur + rng.normal(0, 0.7, n), -1.0)

    def with_gtsam() -> np.ndarray:
        Ks = gtsam.Cal3_S2Stereo(fx, fx, 0, cx, cy, b)
        Km = gtsam.Cal3_S2(fx, fx, 0, cx, cy)
        g = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        vals.insert(n, gtsam.Pose3())
        hs = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(np.sqrt(7.815)), gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
        )
        hm = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(np.sqrt(5.991)), gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
        )
        tight = gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)
        for j in range(n):
            vals.insert(j, X[j])
            g.add(gtsam.PriorFactorPoint3(j, X[j], tight))
            if urs[j] >= 0:
                g.add(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(uv[j, 0], urs[j], uv[j, 1]), hs, n, j, Ks))
            else:
                g.add(gtsam.GenericProjectionFactorCal3_S2(gtsam.Point2(uv[j, 0], uv[j, 1]), hm, n, j, Km))
        prm = gtsam.LevenbergMarquardtParams()
        prm.setMaxIterations(10)
        prm.setLinearSolverType("SEQUENTIAL_CHOLESKY")
        res = gtsam.LevenbergMarquardtOptimizer(g, vals, prm).optimize()
        return inv_T(res.atPose3(n).matrix())

    t_np, t_gt = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        T_np, _ = optimize_pose(np.eye(4), X, uv, urs, np.ones(n), K, b * fx)
        t_np.append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        T_gt = with_gtsam()
        t_gt.append((time.perf_counter() - t0) * 1e3)
    return {
        "observations": n,
        "numpy_gauss_newton_ms": round(float(np.median(t_np)), 2),
        "numpy_note": "4 rounds x <= 10 iterations with outlier re-classification (ORB-SLAM2's schedule)",
        "gtsam_lm_ms": round(float(np.median(t_gt)), 2),
        "gtsam_note": "one robust LM pass (<= 10 iterations), graph built per call",
        "translation_error_numpy_m": float(np.abs(T_np[:3, 3] - T_true[:3, 3]).max()),
        "translation_error_gtsam_m": float(np.abs(T_gt[:3, 3] - T_true[:3, 3]).max()),
    }


def run_once(frames, calib, cfg: Config, masker) -> tuple[np.ndarray, StageTimer, float, dict]:
    system = System(cfg, calib)
    timer = StageTimer()
    t0 = time.perf_counter()
    try:
        for f in frames:
            timer.start_frame(f.index)
            masks = masker.mask(f, timer) if masker is not None else None
            system.track(f, masks, timer)
            timer.end_frame()
        wall = time.perf_counter() - t0
    finally:
        system.shutdown()
    return system.trajectory(), timer, wall, system.stats().to_dict()


def run_job_fps(seq_path: Path, kind: str, models: Path, repeats: int) -> dict:
    """``dynastereo run``'s end-to-end rate: ``api.run_sequence`` (what the CLI calls)."""
    import tempfile

    from dynastereo.api import run_sequence

    fps = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as d:
            cfg = Config()
            cfg.masker.kind = kind
            res = run_sequence(seq_path, d, cfg, models_dir=models, overwrite=True)
            summary = json.loads((Path(d) / "timing.json").read_text())["summary"]
            fps.append(float(summary["fps"]))
    return {"fps_median": round(float(np.median(fps)), 2), "fps_runs": [round(f, 2) for f in fps], "frames": len(res.frames)}


REVISITS = (("06", "0-11,4-6"), ("03", "0-98,40-60"), ("06", "0-9,black10,10-19"))


def bench_revisit(kitti: Path, seq_name: str, spec: str) -> dict:
    """Feed a revisit / gap order to ``System`` (unmasked); report each repeated frame."""
    seq = open_sequence(kitti / "sequences" / seq_name)
    gt = read_trajectory(kitti / "poses" / f"{seq_name}.txt").positions
    black = np.zeros((seq.calibration.height, seq.calibration.width), np.uint8)
    order: list[int | None] = []
    for part in spec.split(","):
        if part.startswith("black"):
            order += [None] * int(part[5:])
        else:
            order += parse_frame_spec(part, len(seq))
    system = System(Config(), seq.calibration)
    slam_log = logging.getLogger("dynastereo.slam")
    level = slam_log.level
    slam_log.setLevel(logging.ERROR)  # one WARNING per lost frame otherwise
    try:
        for k, i in enumerate(order):
            system.track(seq.frame(i) if i is not None else StereoFrame(10_000 + k, 0.0, black, black))
    finally:
        system.shutdown()
        slam_log.setLevel(level)
    est = system.trajectory()[:, :, 3]
    states = system.results()
    first: dict[int, int] = {}
    rows = []
    for k, i in enumerate(order):
        if i is not None and i not in first:
            first[i] = k
            if not any(o is None for o in order[:k]):
                continue
        st = states[k]
        rows.append({
            "position": k,
            "image": i,
            "status": st.status,
            "method": st.method,
            "map_id": st.map_id,
            "to_first_visit_m": None if i is None or first[i] == k else round(float(np.linalg.norm(est[k] - est[first[i]])), 3),
            "to_gt_m": None if i is None else round(float(np.linalg.norm(est[k] - gt[i])), 3),
        })
    st = system.stats().to_dict()
    return {"sequence": seq_name, "order": spec, "frames": len(order), "lost": st["lost"],
            "relocalizations": st["relocalizations"], "reinitializations": st["reinitializations"], "rows": rows}


def mask_mean_ms(stages: dict) -> float:
    """Mean ms per frame of the masking stages except the detector (0 when unmasked)."""
    return sum(v["mean_ms"] for k, v in stages.items() if k not in (*SLAM_STAGES, "total", "detect"))

def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sequences", default="06,03")
    ap.add_argument("--maskers", default="none,box,outline,seg")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--frames", type=int, default=0, help="first N frames only (0: all)")
    ap.add_argument("--local-ba", default=None, help="override slam.local_ba (thread | inline | off)")
    ap.add_argument("--features", type=int, default=None, help="override slam.n_features (default 2000)")
    ap.add_argument("--levels", type=int, default=None, help="override slam.n_levels (default 8)")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--no-run-job", action="store_true", help="skip the dynastereo-run rate (run_sequence)")
    ap.add_argument("--no-revisits", action="store_true", help="skip the revisit / gap cases")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    pose_opt = bench_pose_optimizer()
    print(
        f"motion-only BA, {pose_opt['observations']} observations: numpy {pose_opt['numpy_gauss_newton_ms']} ms, "
        f"gtsam {pose_opt['gtsam_lm_ms']} ms"
    )
    data = data_dir()
    models = models_dir()
    kitti = data / "kitti_odometry" / "dataset"
    results = []
    for seq_name in args.sequences.split(","):
        seq = open_sequence(kitti / "sequences" / seq_name)
        n = len(seq) if args.frames <= 0 else min(args.frames, len(seq))
        t0 = time.perf_counter()
        frames = [seq.frame(i) for i in range(n)]
        read_ms = (time.perf_counter() - t0) * 1e3 / n
        gt = read_trajectory(kitti / "poses" / f"{seq_name}.txt")
        for kind in args.maskers.split(","):
            cfg = Config()
            cfg.masker.kind = kind
            if args.local_ba:
                cfg.slam.local_ba = args.local_ba
            if args.features:
                cfg.slam.n_features = args.features
            if args.levels:
                cfg.slam.n_levels = args.levels
            def new_masker():  # one per run: a masker carries boxes and track ids from frame to frame
                return None if kind == "none" else build_masker(cfg, seq.calibration, models_dir=models)

            try:
                first = new_masker()
            except ModelError as e:
                print(f"skip {seq_name}/{kind}: {e}")
                continue
            runs = [run_once(frames, seq.calibration, cfg, first if r == 0 else new_masker())
                    for r in range(max(1, args.repeats))]
            traj = runs[0][0]
            for other in runs[1:]:
                if not np.array_equal(other[0], traj):
                    print(f"WARNING {seq_name}/{kind}: runs differ (non-deterministic)")
            poses = np.tile(np.eye(4), (n, 1, 1))
            poses[:, :3] = traj
            ev = evaluate(Trajectory(poses, name=f"{seq_name}-{kind}"), gt, frame_indices=np.arange(n))
            # stage times: per frame, the median over the repeats; then median / mean over frames
            names = []
            for r in runs:
                for s in r[1].stage_names():
                    if s not in names:
                        names.append(s)
            stages = {}
            for s in names:
                per_run = [np.array([f["ms"].get(s, 0.0) for f in r[1].frames]) for r in runs]
                v = np.median(np.stack(per_run), axis=0)
                stages[s] = {
                    "median_ms": round(float(np.median(v)), 2),
                    "mean_ms": round(float(v.mean()), 2),
                    "p90_ms": round(float(np.percentile(v, 90)), 2),
                    "fps": round(1000.0 / max(float(v.mean()), 1e-9), 1),
                }
            slam_ms = sum(stages[s]["mean_ms"] for s in SLAM_STAGES if s in stages)
            fps_e2e = float(np.median([n / r[2] for r in runs]))
            st = runs[0][3]
            job = None
            if kind == "outline" and not args.no_run_job and args.frames <= 0:
                job = run_job_fps(kitti / "sequences" / seq_name, kind, models, max(1, args.repeats))
            res = {
                "sequence": seq_name,
                "masker": kind,
                "frames": n,
                "path_m": round(ev.path_length_m, 2),
                "ate_rmse_m": round(ev.ape["rmse"], 4),
                "drift_m": round(ev.drift_m, 4),
                "drift_percent": round(float(ev.drift_percent), 3),
                "rpe_trans_mean_m": round(ev.rpe["mean"], 4),
                "rpe_rot_mean_deg": round(ev.rpe_rot_deg["mean"], 4),
                "fps_end_to_end": round(fps_e2e, 2),
                "fps_end_to_end_with_image_reading": round(1000.0 / (1000.0 / fps_e2e + read_ms), 2),
                "fps_slam": round(1000.0 / slam_ms, 1),
                "fps_run_job": job,
                "slam_mean_ms": round(slam_ms, 2),
                "read_ms": round(read_ms, 2),
                "stages": stages,
                "stats": st,
                "pass": {
                    "ate": ev.ape["rmse"] <= TARGET_ATE_M,
                    "drift": float(ev.drift_percent) <= TARGET_DRIFT_PERCENT,
                    "fps": (job["fps_median"] if job else fps_e2e) >= TARGET_FPS if kind == "outline" else None,
                },
            }
            results.append(res)
            print(
                f"{seq_name} {kind:8s} ATE {res['ate_rmse_m']:.3f} m  drift {res['drift_percent']:.2f} %  "
                f"fps {fps_e2e:.1f} (slam {res['fps_slam']:.1f}"
                + (f", dynastereo run {job['fps_median']:.1f}" if job else "")
                + f")  lost {st['lost']}  kf {st['keyframes_created']}  disparity offset {st['disparity_offset']:+.3f} px",
                flush=True,
            )

    # table
    print()
    cols = ["detect", "mask", *SLAM_STAGES, "total"]
    print(f"{'seq':4s} {'masker':8s} {'ATE m':>7s} {'drift%':>7s} {'fps':>6s}  " + " ".join(f"{c:>13s}" for c in cols))
    for r in results:
        st = r["stages"]
        mask_ms = mask_mean_ms(st)
        cells = []
        for c in cols:
            if c == "mask":
                cells.append(f"{mask_ms:6.1f}" + " " * 7 if mask_ms else " " * 13)
            elif c in st:
                cells.append(f"{st[c]['median_ms']:6.1f}/{st[c]['mean_ms']:6.1f}")
            else:
                cells.append(" " * 13)
        print(
            f"{r['sequence']:4s} {r['masker']:8s} {r['ate_rmse_m']:7.3f} {r['drift_percent']:7.2f} "
            f"{r['fps_end_to_end']:6.1f}  " + " ".join(cells)
        )
    print("stage cells: median/mean ms per frame; mask = masking stages except the detector (mean)")
    print()
    fcols = ["detect", "mask", *SLAM_STAGES, "slam", "e2e", "run"]
    print(f"{'seq':4s} {'masker':8s} " + " ".join(f"{c:>13s}" for c in fcols))
    for r in results:
        st = r["stages"]
        mask_ms = mask_mean_ms(st)
        cells = []
        for c in fcols:
            if c == "mask":
                v = 1000.0 / mask_ms if mask_ms else None
            elif c == "slam":
                v = r["fps_slam"]
            elif c == "e2e":
                v = r["fps_end_to_end"]
            elif c == "run":
                v = r["fps_run_job"]["fps_median"] if r["fps_run_job"] else None
            else:
                v = st[c]["fps"] if c in st else None
            cells.append(f"{v:13.1f}" if v is not None else " " * 13)
        print(f"{r['sequence']:4s} {r['masker']:8s} " + " ".join(cells))
    print("frames per second of each stage alone (1000 / mean ms); slam = features+stereo+track+local_mapping;")
    print("e2e = frames / wall time of the in-process loop (masking inline); run = dynastereo run's summary.fps")

    revisits = []
    if not args.no_revisits:
        print()
        for seq_name, spec in REVISITS:
            if seq_name not in args.sequences.split(","):
                continue
            rv = bench_revisit(kitti, seq_name, spec)
            revisits.append(rv)
            print(f"revisit {seq_name} {spec}: lost {rv['lost']}, relocalizations {rv['relocalizations']}, "
                  f"reinitializations {rv['reinitializations']}")
            shown = [r for r in rv["rows"] if r["image"] is not None][:4]
            for row in shown:
                print(f"   #{row['position']:3d} image {row['image']!s:>4s}  {row['status']:8s} {row['method']:9s} "
                      f"to first visit {row['to_first_visit_m']!s:>6s} m  to GT {row['to_gt_m']!s:>6s} m")
            seen = [r for r in rv["rows"] if r["image"] is not None]
            if len(seen) > len(shown):
                d1 = [r["to_first_visit_m"] for r in seen if r["to_first_visit_m"] is not None]
                print(f"   ... {len(seen)} frames fed again: {sum(r['status'] == 'tracked' for r in seen)} tracked, "
                      f"to first visit <= {max(d1) if d1 else float('nan'):.3f} m, "
                      f"to GT <= {max(r['to_gt_m'] for r in seen):.3f} m")

    out = {
        "benchmark": "slam",
        "machine": machine(),
        "targets": {"ate_rmse_m": TARGET_ATE_M, "drift_percent": TARGET_DRIFT_PERCENT, "fps_outline": TARGET_FPS},
        "repeats": args.repeats,
        "config": {**to_dict(Config().slam), **({"n_features": args.features} if args.features else {}),
                   **({"n_levels": args.levels} if args.levels else {})},
        "pose_optimizer": pose_opt,
        "results": results,
        "revisits": revisits,
    }
    write_json(args.out, out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
