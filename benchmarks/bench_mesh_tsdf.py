"""The mesh's TSDF: dynastereo's compiled volume against Open3D's, on the same depth maps.

Why ``dynastereo.mesh.tsdf`` and not Open3D's TSDF (the issue left the choice to a
measurement): both fuse the very same keyframe depth maps (the mesh's own
disparity, movers masked with the GT masks; keyframes every ``--every`` frames; GT poses)
of a synthetic sequence at KITTI's image size (its first ``--first`` frames: Open3D's
volume that works here is dense, a ``--cube`` m cube), with the same voxel (0.1 m) and
truncation (0.3 m), then extract their marching-cubes mesh; both scored in that cube.  Reported per engine: CPU seconds (all
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
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from _common import machine, results_path, write_json
from _shared_mesh import gt_points, sequence  # the synthetic sequence and its GT points
from dynastereo.api import load_sequence
from dynastereo.config import Config
from dynastereo.mesh import KeyframeView, TSDFVolume
from dynastereo.mesh.fusion import downscale, keyframe_depth, mesh_matcher, scaled_K
from dynastereo.synth import read_gt_masks, read_objects

OUT = results_path("mesh_tsdf")


def _dir_mb(paths: list[Path]) -> float:
    return round(sum(f.stat().st_size for p in paths for f in p.rglob("*") if f.is_file()) / 1e6, 1)


def score(V: np.ndarray, pts: dict, box: tuple[np.ndarray, float] | None = None) -> dict:
    """Accuracy over ``V``; completeness over the GT static points inside ``box`` (origin, side)."""
    world = np.concatenate([pts["static"], pts["parked"]])
    d, _ = cKDTree(world).query(V)
    st = pts["static"]
    if box is not None:
        st = st[((st >= box[0]) & (st <= box[0] + box[1])).all(1)]
    dv, _ = cKDTree(V).query(st)
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


def _o3d_plane_check(o3d) -> dict:
    """Open3D's three TSDF volumes on one fronto-parallel plane 5 m away (vertices out)."""
    z = np.full((100, 200), 5.0, np.float32)
    rgb = np.full((100, 200, 3), 128, np.uint8)
    rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(o3d.geometry.Image(rgb), o3d.geometry.Image(z),
                                                              depth_scale=1.0, depth_trunc=20.0,
                                                              convert_rgb_to_intensity=False)
    intr = o3d.camera.PinholeCameraIntrinsic(200, 100, 100.0, 100.0, 100.0, 50.0)
    ct = o3d.pipelines.integration.TSDFVolumeColorType.RGB8
    out = {}
    for name, vol in (("ScalableTSDFVolume", o3d.pipelines.integration.ScalableTSDFVolume(
            voxel_length=0.1, sdf_trunc=0.3, color_type=ct)),
                      ("UniformTSDFVolume", o3d.pipelines.integration.UniformTSDFVolume(
                          length=20.0, resolution=200, sdf_trunc=0.3, color_type=ct, origin=np.array([-10.0, -10.0, 0.0])))):
        for _ in range(3):
            vol.integrate(rgbd, intr, np.eye(4))
        out[name] = len(vol.extract_triangle_mesh().vertices)
    vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight", "color"),
                                        attr_dtypes=(o3d.core.float32, o3d.core.float32, o3d.core.float32),
                                        attr_channels=((1), (1), (3)), voxel_size=0.1, block_resolution=8,
                                        block_count=20000)
    dt = o3d.t.geometry.Image(o3d.core.Tensor(z))
    cimg = o3d.t.geometry.Image(o3d.core.Tensor(rgb.astype(np.float32)))
    K = o3d.core.Tensor(intr.intrinsic_matrix, o3d.core.float64)
    E = o3d.core.Tensor(np.eye(4))
    for _ in range(3):
        fb = vbg.compute_unique_block_coordinates(dt, K, E, 1.0, 20.0, 3.0)
        vbg.integrate(fb, dt, cimg, K, E, 1.0, 20.0, 3.0)
    out["t.VoxelBlockGrid"] = int(vbg.extract_triangle_mesh(weight_threshold=1.0).vertex.positions.shape[0])
    return out


def open3d_engine(frames, cfg, cube: tuple[np.ndarray, float]) -> tuple[dict, np.ndarray] | None:
    """Open3D's dense UniformTSDFVolume over ``cube`` (origin, side m): its legacy sparse
    ScalableTSDFVolume gives no surface at all in this build (``plane_check_vertices``); the
    tensor VoxelBlockGrid does, and is not timed here."""
    t0 = time.perf_counter()
    try:
        import open3d as o3d
    except ImportError:
        return None
    imp = time.perf_counter() - t0
    m = cfg.mesh
    origin, side = cube
    vol = o3d.pipelines.integration.UniformTSDFVolume(
        length=side, resolution=int(round(side / m.voxel_size)), sdf_trunc=m.truncation,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8, origin=origin)
    c0, w0 = time.process_time(), time.perf_counter()
    for z, img, K, pose in frames:
        h, w = z.shape
        rgb = np.ascontiguousarray(np.dstack([img] * 3) if img.ndim == 2 else img[:, :, ::-1])
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(rgb), o3d.geometry.Image(np.ascontiguousarray(z)), depth_scale=1.0,
            depth_trunc=m.max_depth, convert_rgb_to_intensity=False)
        intr = o3d.camera.PinholeCameraIntrinsic(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        vol.integrate(rgbd, intr, np.linalg.inv(np.vstack([pose, [0, 0, 0, 1]])))
    c1, w1 = time.process_time(), time.perf_counter()
    mesh = vol.extract_triangle_mesh()
    c2, w2 = time.process_time(), time.perf_counter()
    return {"volume": f"UniformTSDFVolume, a {side:g} m cube", "fusion_cpu_s": round(c1 - c0, 3),
            "fusion_wall_s": round(w1 - w0, 3), "extract_cpu_s": round(c2 - c1, 3), "extract_wall_s": round(w2 - w1, 3),
            "voxel_grid_mb": round(int(round(side / m.voxel_size)) ** 3 * 11 / 1e6, 1),
            "import_s": round(imp, 3), "version": o3d.__version__, "plane_check_vertices": _o3d_plane_check(o3d),
            "installed_mb": _dir_mb([Path(o3d.__file__).parent])}, np.asarray(mesh.vertices)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="oncoming")
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--every", type=int, default=3)
    ap.add_argument("--first", type=int, default=30, help="frames fused (Open3D's dense cube must hold them)")
    ap.add_argument("--cube", type=float, default=40.0, help="side of Open3D's dense volume, m")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "dynastereo-synth-cache")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    seq = sequence(args.cache, args.scenario, args.frames, 0)
    S, gt, cfg = load_sequence(seq), read_objects(seq), Config()
    poses = np.loadtxt(seq.parent.parent / "poses" / "00.txt").reshape(-1, 3, 4)
    matcher, m = mesh_matcher(cfg), cfg.mesh
    frames = []
    for i in range(0, min(len(gt), args.first), args.every):
        f = S.frame(i)
        ids, _ = read_gt_masks(seq, i)
        mask = (np.isin(ids, [o.id for o in gt.frame(i) if o.moving]) * 255).astype(np.uint8)
        z = keyframe_depth(KeyframeView(i, f.left, f.right, mask), mask, S.calibration, matcher, m)
        frames.append((z, downscale(f.left, m.scale), scaled_K(S.calibration.K, m.scale), poses[i]))
    pts = gt_points(seq)  # the GT surface of every frame; completeness: the points inside the cube
    res = {"scenario": args.scenario, "frames": args.frames, "keyframes": len(frames), "voxel_size": m.voxel_size,
           "truncation": m.truncation, "machine": machine()}
    # the cube: centred on the cameras' mean x, from 2 m behind the first camera, y +-half
    cams = np.array([f[3][:, 3] for f in frames])
    origin = np.array([cams[:, 0].mean() - args.cube / 2, -args.cube / 2, cams[:, 2].min() - 2.0])
    t, V = ours(frames, cfg)
    box = (origin, args.cube)
    V = V[((V >= origin) & (V <= origin + args.cube)).all(1)]  # the same region for both
    res["dynastereo"] = {**t, **score(V, pts, box)}
    o3 = open3d_engine(frames, cfg, (origin, args.cube))
    if o3 is None:
        res["open3d"] = "not importable (put an install on PYTHONPATH)"
    else:
        t, V = o3
        res["open3d"] = {**t, **score(V, pts, box)}
    for k in ("dynastereo", "open3d"):
        print(k, json.dumps(res[k]))
    write_json(args.out, res)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
