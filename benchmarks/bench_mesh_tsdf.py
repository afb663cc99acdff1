"""The mesh's TSDF: dynastereo's compiled volume against Open3D's, on the same depth maps.

Why ``dynastereo.mesh.tsdf`` and not Open3D's ``ScalableTSDFVolume`` (the issue left the
choice to a measurement): both fuse the very same keyframe depth maps (the mesh's own
disparity, movers masked with the GT masks; keyframes every ``--every`` frames; GT poses)
of a synthetic sequence at KITTI's image size, with the same voxel (0.1 m) and truncation
(0.3 m), then extract their marching-cubes mesh.  Reported per engine: CPU seconds (all
threads: ``time.process_time``) and wall seconds for the fusion and the extraction, the
vertices, accuracy (median / 90th percentile distance of the vertices to the GT surface)
and completeness (GT static points within 0.2 m of a vertex); for Open3D also its import
time and its installed size.

Open3D is no dependency of dynastereo: put an install on ``PYTHONPATH`` (e.g. ``pip install
--target /tmp/o3d open3d-cpu`` and its dependencies ``dash werkzeug flask nbformat
configargparse ipywidgets plotly``); without it only ours runs.  Writes
benchmarks/results/mesh_tsdf.json.  Run:

    PYTHONPATH=src:/tmp/o3d:/tmp/o3d_deps .venv/bin/python benchmarks/bench_mesh_tsdf.py
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_mesh as bm  # noqa: E402 -- the synthetic sequence and its GT points

from dynastereo.api import load_sequence  # noqa: E402
from dynastereo.config import Config  # noqa: E402
from dynastereo.mesh import KeyframeView, TSDFVolume  # noqa: E402
from dynastereo.mesh.fusion import downscale, keyframe_depth, mesh_matcher, scaled_K  # noqa: E402
from dynastereo.synth import read_gt_masks, read_objects  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "mesh_tsdf.json"


def _dir_mb(paths: list[Path]) -> float:
    return round(sum(f.stat().st_size for p in paths for f in p.rglob("*") if f.is_file()) / 1e6, 1)


def score(V: np.ndarray, pts: dict) -> dict:
    world = np.concatenate([pts["static"], pts["parked"]])
    d, _ = cKDTree(world).query(V)
    dv, _ = cKDTree(V).query(pts["static"])
    return {"vertices": int(len(V)), "accuracy_median_m": round(float(np.median(d)), 4),
            "accuracy_p90_m": round(float(np.percentile(d, 90)), 4), "completeness": round(float(np.mean(dv <= 0.2)), 4)}


def ours(frames, cfg) -> tuple[dict, np.ndarray]:
    m = cfg.mesh
    vol = TSDFVolume(m.voxel_size, m.truncation, m.min_weight)
    vol.integrate(frames[0][0], frames[0][1], frames[0][2], frames[0][3])  # compiled kernels loaded (cache)
    vol = TSDFVolume(m.voxel_size, m.truncation, m.min_weight)
    c0, w0 = time.process_time(), time.perf_counter()
    for z, img, K, pose in frames:
        vol.integrate(z, img, K, pose)
    c1, w1 = time.process_time(), time.perf_counter()
    mesh = vol.mesh()
    c2, w2 = time.process_time(), time.perf_counter()
    return {"fusion_cpu_s": round(c1 - c0, 3), "fusion_wall_s": round(w1 - w0, 3), "extract_cpu_s": round(c2 - c1, 3),
            "extract_wall_s": round(w2 - w1, 3), "voxel_grid_mb": round(vol.peak_bytes / 1e6, 1)}, mesh.vertices


def open3d_engine(frames, cfg) -> tuple[dict, np.ndarray] | None:
    t0 = time.perf_counter()
    try:
        import open3d as o3d
    except ImportError:
        return None
    imp = time.perf_counter() - t0
    m = cfg.mesh
    vol = o3d.pipelines.integration.ScalableTSDFVolume(voxel_length=m.voxel_size, sdf_trunc=m.truncation,
                                                       color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8)
    c0, w0 = time.process_time(), time.perf_counter()
    for z, img, K, pose in frames:
        h, w = z.shape
        rgb = np.ascontiguousarray(np.dstack([img] * 3) if img.ndim == 2 else img[:, :, ::-1])
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(rgb), o3d.geometry.Image(np.ascontiguousarray(z)), depth_scale=1.0,
            depth_trunc=m.max_depth, convert_rgb_to_intensity=False)
        intr = o3d.camera.PinholeCameraIntrinsic(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        T = np.vstack([pose, [0, 0, 0, 1]])
        vol.integrate(rgbd, intr, np.linalg.inv(T))
    c1, w1 = time.process_time(), time.perf_counter()
    mesh = vol.extract_triangle_mesh()
    c2, w2 = time.process_time(), time.perf_counter()
    return {"fusion_cpu_s": round(c1 - c0, 3), "fusion_wall_s": round(w1 - w0, 3), "extract_cpu_s": round(c2 - c1, 3),
            "extract_wall_s": round(w2 - w1, 3), "import_s": round(imp, 3), "version": o3d.__version__,
            "installed_mb": _dir_mb([Path(o3d.__file__).parent])}, np.asarray(mesh.vertices)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="oncoming")
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--every", type=int, default=3)
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "dynastereo-synth-cache")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    seq = bm.sequence(args.cache, args.scenario, args.frames, 0)
    S, gt, cfg = load_sequence(seq), read_objects(seq), Config()
    poses = np.loadtxt(seq.parent.parent / "poses" / "00.txt").reshape(-1, 3, 4)
    matcher, m = mesh_matcher(cfg), cfg.mesh
    frames = []
    for i in range(0, len(gt), args.every):
        f = S.frame(i)
        ids, _ = read_gt_masks(seq, i)
        mask = (np.isin(ids, [o.id for o in gt.frame(i) if o.moving]) * 255).astype(np.uint8)
        z = keyframe_depth(KeyframeView(i, f.left, f.right, mask), mask, S.calibration, matcher, m)
        frames.append((z, downscale(f.left, m.scale), scaled_K(S.calibration.K, m.scale), poses[i]))
    pts = bm.gt_points(seq)
    res = {"scenario": args.scenario, "frames": args.frames, "keyframes": len(frames), "voxel_size": m.voxel_size,
           "truncation": m.truncation, "machine": "2 shared cores (timings noisy: compare side by side)"}
    t, V = ours(frames, cfg)
    res["dynastereo"] = {**t, **score(V, pts)}
    o3 = open3d_engine(frames, cfg)
    if o3 is None:
        res["open3d"] = "not importable (put an install on PYTHONPATH)"
    else:
        t, V = o3
        res["open3d"] = {**t, **score(V, pts)}
    for k in ("dynastereo", "open3d"):
        print(k, json.dumps(res[k]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1))
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
