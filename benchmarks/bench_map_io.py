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
from _shared_maps import synthetic_map
from dynastereo.slam import map_io
from dynastereo.slam.map_io import MapFile, load_map, save_map

OUT = results_path("map_io")


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
