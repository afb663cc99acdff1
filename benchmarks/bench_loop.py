"""Benchmark loop closing, relocalization and map reuse (``dynastereo.slam``).

1. **Loop** -- the synthetic ``loop`` scenario (one lap of the ~390 m ring and 60 m over
   the start again, with traffic and pedestrians; 640x192), per seed: the whole pipeline
   (``--masker``, default ``outline``, on the oracle boxes) with loop closing on and off.  ATE = APE RMSE
   after SE(3) alignment; the loop found (frame, loop keyframe, correction), the time per
   loop-detection query (BoW transform + database query, every keyframe), per pose-graph
   optimization and per full BA (worker process).
2. **Kidnapped camera** -- KITTI 03, ``--frames 0-98,40-60``: the frames fed after the jump
   are compared with the same frames of the first pass (frames until the first one
   tracked again; largest pose difference after it).
3. **Localize only** -- KITTI 03 mapped (``save_map``), then re-run on the same frames in
   that map with ``localize_only``: ATE against the ground truth; keyframes added (0).
4. **Black frames** -- KITTI 03 with 10 black frames in the middle: every frame gets a
   row, the frames after them are tracked again.

KITTI parts need ``$DYNASTEREO_DATA``.  Prints tables, writes benchmarks/results/loop.json.

    DYNASTEREO_DATA=/work/shared/data .venv/bin/python benchmarks/bench_loop.py [--seeds 0,1,2]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import data_dir, machine, results_path, write_json
from dynastereo.api import run_sequence
from dynastereo.config import Config
from dynastereo.eval import evaluate_files

RESULTS = results_path("loop")


def _ate(run_dir: Path, gt: Path) -> float:
    return float(evaluate_files(run_dir / "trajectory.kitti.txt", gt).ape["rmse"])


def synthetic_loop(seeds: list[int], size: str, cache: Path, work: Path, masker: str = "outline") -> dict:
    from dynastereo.synth import generate

    rows = []
    for seed in seeds:
        root = cache / f"loop-{size}-s{seed}"
        if not (root / "sequences" / "00" / "times.txt").exists():
            generate(root, "loop", seed=seed, size=size)
        seq = root / "sequences" / "00"
        gt = root / "poses" / "00.txt"
        row: dict = {"seed": seed, "frames": len(np.loadtxt(seq / "times.txt", ndmin=1))}
        for lc in (True, False):
            cfg = Config().with_overrides(
                {"masker.kind": masker, "detector.name": "oracle", "slam.loop_closing": lc}
            )
            out = work / f"loop-s{seed}-{'lc' if lc else 'nolc'}"
            t0 = time.perf_counter()
            res = run_sequence(seq, out, cfg, overwrite=True)
            wall = time.perf_counter() - t0
            run = json.loads((out / "run.json").read_text())
            key = "lc" if lc else "nolc"
            row[f"ate_{key}"] = _ate(out, gt)
            row[f"fps_{key}"] = res.fps
            row[f"wall_s_{key}"] = wall
            if lc:
                row["loops"] = run["loops"]
                row["loop_query_ms_median"] = run["stats"]["loop_query_ms_median"]
                row["loop_candidates_rejected"] = run["stats"]["loop_candidates_rejected"]
        row["ratio"] = row["ate_lc"] / row["ate_nolc"]
        rows.append(row)
        print(
            f"seed {seed}: ATE {row['ate_nolc']:.3f} m without loop closing -> {row['ate_lc']:.3f} m with "
            f"(ratio {row['ratio']:.2f}); loops {[(e['frame'], e['loop_frame_index']) for e in row['loops']]}",
            flush=True,
        )
    loops = [e for r in rows for e in r["loops"]]
    return {
        "masker": masker,
        "size": size,
        "runs": rows,
        "ate_lc_median": float(np.median([r["ate_lc"] for r in rows])),
        "ate_nolc_median": float(np.median([r["ate_nolc"] for r in rows])),
        "ratio_median": float(np.median([r["ratio"] for r in rows])),
        "ratio_max": float(np.max([r["ratio"] for r in rows])),
        "loops_detected": sum(bool(r["loops"]) for r in rows),
        "loop_query_ms_median": float(np.median([r["loop_query_ms_median"] for r in rows])),
        "pose_graph_ms_median": float(np.median([e["pose_graph_ms"] for e in loops])) if loops else None,
        "full_ba_ms_median": (
            float(np.median([e["full_ba_ms"] for e in loops if e["full_ba_ms"]])) if any(e["full_ba_ms"] for e in loops) else None
        ),
        "fps_lc_median": float(np.median([r["fps_lc"] for r in rows])),
        "fps_nolc_median": float(np.median([r["fps_nolc"] for r in rows])),
    }


def _poses(run_dir: Path) -> np.ndarray:
    return np.loadtxt(run_dir / "trajectory.kitti.txt").reshape(-1, 3, 4)


def kitti_parts(seq: Path, gt: Path, work: Path) -> dict:
    cfg = Config().with_overrides({"masker.kind": "outline", "detector.name": "yolox-nano"})
    out: dict = {}
    # kidnapped: 0-98 then 40-60
    d = work / "kidnapped"
    run_sequence(seq, d, cfg, frames="0-98,40-60", overwrite=True)
    run = json.loads((d / "run.json").read_text())
    P = _poses(d)
    first, again = P[40:61], P[99:120]
    diff = np.linalg.norm(first[:, :, 3] - again[:, :, 3], axis=1)
    states_after = run["recoveries"]
    # frames until tracked again: the jump frame is position 99
    lost_after_jump = [x["position"] for x in run["lost"] if x["position"] >= 99]
    first_ok = next((p for p in range(99, 120) if p not in lost_after_jump), None)
    out["kidnapped"] = {
        "frames": "0-98,40-60",
        "lost_after_jump": len(lost_after_jump),
        "frames_to_relocalize": None if first_ok is None else first_ok - 99,
        "relocalizations": run["stats"]["relocalizations"],
        "reloc_ms_median": run["stats"]["relocalization_ms_median"],
        "max_diff_m": float(diff[(first_ok or 99) - 99:].max()),
        "median_diff_m": float(np.median(diff)),
        "recoveries": states_after,
    }
    print(f"kidnapped 03: {out['kidnapped']}", flush=True)
    # map, then localize only
    m = work / "map03"
    map_file = work / "kitti03.dsmap"
    run_sequence(seq, m, cfg, frames="0-98", save_map=map_file, overwrite=True)
    loc = work / "loc03"
    run_sequence(seq, loc, cfg, frames="0-98", load_map=map_file, localize_only=True, overwrite=True)
    run = json.loads((loc / "run.json").read_text())
    out["localize_only"] = {
        "ate_mapping_run": _ate(m, gt),
        "ate_localize_only": _ate(loc, gt),
        "keyframes_created": run["stats"]["keyframes_created"],
        "frames_lost": run["frames_lost"],
        "map_file_mb": map_file.stat().st_size / 1e6,
        "fps": run["fps"],
    }
    print(f"localize only 03: {out['localize_only']}", flush=True)
    return out


def black_frames(seq: Path, work: Path) -> dict:
    """10 black frames in the middle of 03 (a folder sequence with the pairs replaced)."""
    import shutil

    import cv2

    d = work / "black03"
    for cam in ("image_0", "image_1"):
        (d / cam).mkdir(parents=True, exist_ok=True)
    shutil.copy(seq / "calib.txt", d / "calib.txt")
    if (seq / "times.txt").exists():
        shutil.copy(seq / "times.txt", d / "times.txt")
    for cam in ("image_0", "image_1"):
        for i in range(99):
            src = seq / cam / f"{i:06d}.png"
            if 45 <= i < 55:
                img = cv2.imread(str(src), cv2.IMREAD_GRAYSCALE)
                cv2.imwrite(str(d / cam / f"{i:06d}.png"), np.zeros_like(img))
            else:
                os.symlink(src, d / cam / f"{i:06d}.png")
    cfg = Config().with_overrides({"masker.kind": "outline", "detector.name": "yolox-nano"})
    r = d / "run"
    run_sequence(d, r, cfg, frames="0-98", overwrite=True)
    run = json.loads((r / "run.json").read_text())
    res = {
        "rows": int(len(_poses(r))),
        "frames_lost": run["frames_lost"],
        "lost": [x["frame"] for x in run["lost"]],
        "recoveries": run["recoveries"],
        "reinitializations": run["stats"]["reinitializations"],
    }
    print(f"black frames 03: {res}", flush=True)
    return res


def pose_graph_scaling(sizes=(100, 500, 1000, 2000), repeats: int = 3) -> list[dict]:
    """``optimize_pose_graph`` on a drifted ring of N keyframes with the essential graph's
    shape (spanning tree + ~6 covisibility edges per keyframe + loop edges): median ms."""
    from dynastereo.slam.geometry import se3_exp
    from dynastereo.slam.optimizer import optimize_pose_graph

    rng = np.random.default_rng(0)
    rows = []
    for n in sizes:
        step = se3_exp(np.array([0.0, 2 * np.pi / n, 0.0, 0.0, 0.0, 1.0]))
        T = [np.eye(4)]
        for _ in range(n - 1):
            T.append(T[-1] @ step)
        T = np.stack(T)
        edges = [(i, j) for i in range(n) for j in range(i + 1, min(n, i + 7))]
        edges += [(n - 1 - k, k) for k in range(5)]
        e = np.array(edges)
        meas = np.stack([np.linalg.inv(T[i]) @ T[j] for i, j in edges])
        drift = np.stack([T[i] @ se3_exp(np.r_[rng.normal(0, 1e-3, 3), rng.normal(0, 1e-2, 3)] * i / n * 10) for i in range(n)])
        ms = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            optimize_pose_graph(drift, e, meas, np.array([0]))
            ms.append((time.perf_counter() - t0) * 1e3)
        rows.append({"keyframes": n, "edges": len(edges), "ms_median": float(np.median(ms))})
        print(f"pose graph: {n} keyframes, {len(edges)} edges: {np.median(ms):.1f} ms", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--size", default="640x192")
    ap.add_argument("--masker", default="outline", help="masker on the oracle boxes for the synthetic loop")
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "dynastereo-bench-loop"))
    ap.add_argument("--no-synth", action="store_true")
    ap.add_argument("--no-kitti", action="store_true")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    result: dict = {"machine": machine()}
    result["pose_graph"] = pose_graph_scaling()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if not args.no_synth:
            result["synthetic_loop"] = synthetic_loop(
                [int(s) for s in args.seeds.split(",")], args.size, cache, work, args.masker
            )
        data = data_dir(required=False)
        seq = Path(data or "") / "kitti_odometry" / "dataset" / "sequences" / "03"
        if not args.no_kitti and data and seq.is_dir():
            gt = Path(data) / "kitti_odometry" / "dataset" / "poses" / "03.txt"
            result["kitti03"] = kitti_parts(seq, gt, work)
            result["kitti03"]["black_frames"] = black_frames(seq, work)
        elif not args.no_kitti:
            print("KITTI 03 not found under $DYNASTEREO_DATA: kidnapped / localize-only parts skipped")
    if "synthetic_loop" in result:
        s = result["synthetic_loop"]
        print(
            f"\nsynthetic loop ({len(s['runs'])} seeds): ATE median {s['ate_nolc_median']:.3f} m -> "
            f"{s['ate_lc_median']:.3f} m, ratio median {s['ratio_median']:.2f} (max {s['ratio_max']:.2f}); "
            f"loops detected in {s['loops_detected']}/{len(s['runs'])}; query {s['loop_query_ms_median']:.1f} ms, "
            f"pose graph {s['pose_graph_ms_median']} ms, full BA {s['full_ba_ms_median']} ms"
        )
    write_json(args.out, result, default=float)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
