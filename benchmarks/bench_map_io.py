"""Benchmark map files (``dynastereo.slam.map_io``): save / load time and file size.

Maps:
* ``synthetic-100kf``: built through the Map API to the size of a long run -- 100
  keyframes x 2000 keypoints, 50 000 map points (each seen by ~3 keyframes), 10 % of
  the points culled, 5 keyframes culled, covisibility from the observations; random
  descriptors (incompressible, as real ORB descriptors nearly are);
* ``kitti06``: the SLAM's map of KITTI 06 (all frames there), when DYNASTEREO_DATA is set.

For each: median save / load ms over repeats, file size, and for comparison the same
arrays written with ``np.savez_compressed`` (deflate level 6 on everything).

Prints a table; writes benchmarks/results/map_io.json.
Run: [DYNASTEREO_DATA=/work/shared/data] .venv/bin/python benchmarks/bench_map_io.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import CLIPS, data_dir, machine, results_path, write_json
from dynastereo.slam import map_io
from dynastereo.slam.keyframe import KeyFrame
from dynastereo.slam.map import Map
from dynastereo.slam.map_io import MapFile, load_map, save_map
from dynastereo.datatypes import StereoCalibration

OUT = results_path("map_io")


def synthetic_map(n_kf: int = 100, n_kp: int = 2000, new_per_kf: int = 500, seed: int = 0) -> MapFile:
    rng = np.random.default_rng(seed)
    K = np.array([[718.856, 0, 607.19], [0, 718.856, 185.22], [0, 0, 1]])
    calib = StereoCalibration(K, 0.5372, 1241, 376)
    mp = Map(1.2 ** np.arange(8))
    for k in range(n_kf):
        T = np.eye(4)
        T[2, 3] = -0.8 * k
        uv = np.column_stack([rng.uniform(0, 1241, n_kp), rng.uniform(0, 376, n_kp)])
        disp = rng.uniform(2, 80, n_kp)
        stereo = rng.random(n_kp) < 0.7
        kf = KeyFrame(
            id=mp.new_kf_id(), frame_index=2 * k, uv=uv, octave=rng.integers(0, 8, n_kp).astype(np.int32),
            angle=rng.uniform(0, 360, n_kp).astype(np.float32), desc=rng.integers(0, 256, (n_kp, 32), dtype=np.uint8),
            u_right=np.where(stereo, uv[:, 0] - disp, -1.0), depth=np.where(stereo, calib.bf / disp, -1.0),
            calib=calib, T_cw=T,
        )
        mp.add_keyframe(kf)
        # observe points of the last keyframes (~1000), then make new ones from free stereo keypoints
        if mp.points.n:
            lo = max(0, mp.points.n - 3 * new_per_kf)
            old = rng.choice(np.arange(lo, mp.points.n), size=min(1000, mp.points.n - lo), replace=False)
            kp = rng.choice(n_kp, size=len(old), replace=False)
            mp.add_observations(kf, kp, old)
        free = np.flatnonzero((kf.point_ids < 0) & stereo)[:new_per_kf]
        ids = mp.new_points(kf.unproject(free), kf.desc[free], kf.id)
        mp.add_observations(kf, free, ids)
    mp.update_points(np.arange(mp.points.n))
    mp.set_bad(rng.choice(mp.points.n, mp.points.n // 10, replace=False))  # culled points: dead observation rows
    for kf in mp.keyframes.values():
        mp.update_connections(kf)
    for kid in (10, 30, 50, 70, 90):  # culled keyframes, as local mapping culls them
        kf = mp.keyframes[kid]
        parent = mp.keyframes[kf.best_covisibles()[0]]
        mp.culled[kid] = (parent.id, kf.T_cw @ np.linalg.inv(parent.T_cw))
        mp.set_bad_keyframe(kf)
    return MapFile(mp, calib, 0.15, {"n_features": n_kp, "scale_factor": 1.2, "n_levels": 8}, meta={"bench": True})


def kitti06_map() -> MapFile | None:
    data = data_dir(required=False)
    if data is None or not (data / CLIPS["06"]).exists():
        return None
    seq_dir = data / CLIPS["06"]
    from dynastereo.config import Config
    from dynastereo.io import open_sequence
    from dynastereo.slam import System

    logging.getLogger("dynastereo").setLevel(logging.ERROR)
    seq = open_sequence(seq_dir)
    sysm = System(Config(), seq.calibration)
    try:
        for i in range(len(seq)):
            sysm.track(seq.frame(i))
    finally:
        sysm.shutdown()
    return map_io.map_file_from_system(sysm, meta={"sequence": str(seq_dir), "frames": len(seq)})


def bench(name: str, mf: MapFile, repeats: int, tmp: Path) -> dict:
    mp = mf.map
    path = tmp / f"{name}.dsmap"
    save_ms, load_ms = [], []
    for _ in range(repeats):
        t = time.perf_counter()
        save_map(path, mf)
        save_ms.append(1e3 * (time.perf_counter() - t))
        t = time.perf_counter()
        back = load_map(path)
        load_ms.append(1e3 * (time.perf_counter() - t))
    assert back.map.points.n == mp.points.n and list(back.map.keyframes) == list(mp.keyframes)
    # the same arrays with np.savez_compressed (deflate 6 everywhere), for comparison
    _, arrays = map_io._collect(mf)
    ref = tmp / f"{name}.npz"
    ref_ms = []
    for _ in range(max(1, repeats // 2)):
        t = time.perf_counter()
        np.savez_compressed(ref, **arrays)
        ref_ms.append(1e3 * (time.perf_counter() - t))
    raw = sum(a.nbytes for a in arrays.values())
    return {
        "map": name,
        "keyframes": len(mp.keyframes),
        "keypoints": int(sum(len(kf.uv) for kf in mp.keyframes.values())),
        "points": int(mp.points.n),
        "observations": int(mp.obs.n),
        "raw_mb": round(raw / 1e6, 2),
        "file_mb": round(path.stat().st_size / 1e6, 2),
        "save_ms": round(float(np.median(save_ms)), 1),
        "load_ms": round(float(np.median(load_ms)), 1),
        "savez_compressed_ms": round(float(np.median(ref_ms)), 1),
        "savez_compressed_mb": round(ref.stat().st_size / 1e6, 2),
        "repeats": repeats,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        rows.append(bench("synthetic-100kf", synthetic_map(), args.repeats, tmp))
        k = kitti06_map()
        if k is not None:
            rows.append(bench("kitti06", k, args.repeats, tmp))
        else:
            print("(kitti06 skipped: DYNASTEREO_DATA not set or seq 06 absent)")
    cols = ["map", "keyframes", "keypoints", "points", "observations", "raw_mb", "file_mb", "save_ms", "load_ms",
            "savez_compressed_ms", "savez_compressed_mb"]
    print(" | ".join(f"{c:>12}" for c in cols))
    for r in rows:
        print(" | ".join(f"{r[c]!s:>12}" for c in cols))
    write_json(OUT, {"machine": machine(), "results": rows})
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
