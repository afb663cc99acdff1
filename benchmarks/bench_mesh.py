"""Benchmark the dense, mover-free mesh of the static world (``run --save-mesh``, ``dynastereo.mesh``).

Every figure comes from a whole ``dynastereo run`` with ``--save-mesh`` (the runtime's own
job, :func:`dynastereo.runtime.run`): the mesh it writes is the *masked* one.  The same
run's keyframes are tapped by an observer and fused again with the masks ignored
(*unmasked*: the same keyframes, poses and settings) -- what the masks remove.

**Synthetic scenes** with exact ground truth (``dynastereo.synth`` at KITTI's image size
and focal length; ``--scenarios``, default oncoming and crossing, ``--seeds``, ``--frames``;
oracle boxes, the outline masker and the motion test, as a default run):

* the GT *static surface*: the GT disparity of the pixels outside every GT instance mask,
  within 20 m, back-projected with the GT poses (every frame; 5 cm grid); the *parked*
  objects' pixels (objects that never move) likewise -- the mesh keeps parked cars, so a
  vertex is judged against the static surface and the parked objects together;
* **accuracy**: distance of each mesh vertex to the nearest of those points (median, 90th
  percentile); **completeness**: share of the GT static points within 0.2 m of a vertex;
* **ghosts**: vertices within 0.3 m of a *mover's* GT points (its pixels in the frames it
  moves in) at any frame, as a share of all vertices; beside it the same share counting
  only ghosts off the static world (farther than one voxel from its GT points: the road
  under a wheel or a foot is not a ghost); masked and unmasked.  And the first share for
  the GT static surface itself (``ghost_fraction_of_gt_surface``): what a perfect mesh
  scores, the road the movers touch.
* the same with the GT poses (``gt_poses``): the fusion's error without the SLAM's drift.

**KITTI raw drive 0001** (an oncoming tram, cyclists, a passing car; parked cars), the
default configuration: the vertices inside the boxes of the objects that moved (tracks of
``objects_tracks.csv`` with a moving verdict; every row a box of the class's size, heading
from the velocity above 1 m/s, grown by 0.3 m), masked against unmasked (target <= 5 %);
beside it the same off the road (tracks moving in at least 3 frames, each box's bottom
0.3 m above the object's: grown boxes hold the road under the wheels and, for the tram's
20-m class box, the rail bed and what stands beside it), per track too;
and, not the issue's measure but beside it, the vertices in the grown boxes decomposed
(:func:`decompose`): the road (within 0.3 m of its plane), the static world (seen as a
surface by a keyframe while no mover's box held the spot) and the rest -- the ghosts, and
static surfaces never seen without a mover's box around them -- masked against unmasked,
per track too; the mesh's CPU time (disparity + fusion + marching cubes; target <= 5 s)
and the voxel grid's peak memory; pictures side by side (``docs/mesh_raw0001_*.png``;
``_boxes.png``: the decomposition from above).

Writes benchmarks/results/mesh.json (a part skipped keeps its figures from the file).  Run:

    DYNASTEREO_DATA=/work/shared/data DYNASTEREO_MODELS=/work/shared/models \\
        .venv/bin/python benchmarks/bench_mesh.py [--seeds 0,1] [--frames 100] [--skip-kitti]
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from _common import CLIPS, ROOT, data_dir, machine, models_dir, results_path, write_json
from _shared_mesh import gt_points, sequence  # the synthetic sequence and its GT points
from dynastereo.config import Config
from dynastereo.mesh import KeyframeRecorder, fuse, read_ply, write_mesh_ply
from dynastereo.mesh.render import render_camera, render_top, top_pixels
from dynastereo.runtime import JobKind, JobSpec, OutputSpec, SourceSpec, run

OUT = results_path("mesh")
DOCS = ROOT / "docs"
NEAR = 0.2  # completeness
GHOST = 0.3
GROW = 0.3
CLASS_SIZE = {"car": (1.8, 1.5, 4.4), "truck": (2.5, 3.0, 8.0), "bus": (2.6, 3.2, 12.0), "train": (2.6, 3.5, 20.0),
              "person": (0.6, 1.7, 0.5), "bicycle": (0.6, 1.7, 1.8), "motorcycle": (0.8, 1.5, 2.1)}


class KeyframeTap:
    """An observer that keeps the run's keyframes as ``--save-mesh`` does (the unmasked fusion's input)."""

    def __init__(self) -> None:
        self.recorder = KeyframeRecorder()
        self.system = None

    def on_frame(self, ev) -> None:
        self.system = ev.system
        tr = ev.system.tracker.results[ev.position]
        ok = ev.status in ("tracked", "init")
        self.recorder.add(ev.position, ev.frame.left, ev.frame.right, ev.masks, ev.masks, bool(tr.keyframe) and ok)


def run_with_mesh(seq: Path, work: Path, cfg: Config, models_dir: Path | None) -> dict:
    """A default run with --save-mesh; its result, run.json's mesh entry, the masked mesh
    (read back from the file), the unmasked one, the tap."""
    shutil.rmtree(work, ignore_errors=True)
    tap = KeyframeTap()
    ply = work / "mesh.ply"
    spec = JobSpec(JobKind.RUN, SourceSpec(path=seq), OutputSpec(work, save_mesh=ply), cfg, models_dir=models_dir)
    res = run(spec, observers=(tap,))
    info = json.loads((work / "run.json").read_text())["mesh"]
    sysm = tap.system
    ok = np.array([str(s.status) in ("tracked", "init") for s in sysm.results()], bool)
    t0 = time.process_time()
    unmasked = fuse(tap.recorder, res.poses, sysm.calib, cfg, disparity_offset=float(sysm.disparity_offset),
                    masked=False, ok=ok)
    return {"result": res, "info": info, "masked": read_ply(ply), "unmasked": unmasked.mesh,
            "unmasked_s": time.process_time() - t0, "tap": tap, "ok": ok,
            "keyframe_bytes": int(sum(v.left.nbytes + v.right.nbytes + (v.mask.nbytes if v.mask is not None else 0)
                                      for v in tap.recorder.views))}


# ----------------------------------------------------------------------------- synthetic


def score_synthetic(V: np.ndarray, pts: dict[str, np.ndarray], voxel: float) -> dict:
    world = np.concatenate([pts["static"], pts["parked"]])
    tw, ts = cKDTree(world), cKDTree(pts["static"])
    if not len(V):
        return {"vertices": 0}
    dist, _ = tw.query(V)
    dv, _ = cKDTree(V).query(pts["static"])
    rec = {"vertices": int(len(V)), "accuracy_median_m": round(float(np.median(dist)), 4),
           "accuracy_p90_m": round(float(np.percentile(dist, 90)), 4),
           "completeness": round(float(np.mean(dv <= NEAR)), 4)}
    if len(pts["movers"]):
        dm, _ = cKDTree(pts["movers"]).query(V)
        ghost = dm <= GHOST
        rec["ghost_fraction"] = round(float(np.mean(ghost)), 5)
        rec["ghost_fraction_off_static"] = round(float(np.mean(ghost & (dist > voxel))), 5)
        rec["ghost_vertices"] = int(ghost.sum())
    return rec


def synthetic(args, cache: Path, work: Path) -> list[dict]:
    rows = []
    for scenario in args.scenarios.split(","):
        for seed in [int(s) for s in args.seeds.split(",")]:
            seq = sequence(cache, scenario, args.frames, seed)
            cfg = Config().with_overrides({"detector.name": "oracle", "masker.kind": "outline", "seed": seed})
            r = run_with_mesh(seq, work / f"{scenario}_{seed}", cfg, None)
            pts = gt_points(seq)
            gt_poses = np.loadtxt(seq.parent.parent / "poses" / "00.txt").reshape(-1, 3, 4)
            tap = r["tap"]
            at_gt = {m: fuse(tap.recorder, gt_poses, tap.system.calib, cfg, masked=m).mesh for m in (True, False)}
            vox = cfg.mesh.voxel_size
            floor = None  # the ghost share a perfect mesh (the GT static surface itself) would get
            if len(pts["movers"]):
                dm, _ = cKDTree(pts["movers"]).query(pts["static"])
                floor = round(float(np.mean(dm <= GHOST)), 5)
            row = {"scenario": scenario, "seed": seed, "frames": args.frames, "keyframes": r["info"]["keyframes"],
                   "gt_points": {k: int(len(v)) for k, v in pts.items()}, "ghost_fraction_of_gt_surface": floor,
                   "masked": score_synthetic(r["masked"].vertices, pts, vox),
                   "unmasked": score_synthetic(r["unmasked"].vertices, pts, vox),
                   "gt_poses": {"masked": score_synthetic(at_gt[True].vertices, pts, vox),
                                "unmasked": score_synthetic(at_gt[False].vertices, pts, vox)},
                   "mesh": r["info"]}
            rows.append(row)
            m, u = row["masked"], row["unmasked"]
            print(f"{scenario:9s} seed {seed}: {m['vertices']} vertices, accuracy median {m['accuracy_median_m']:.3f} m "
                  f"(p90 {m['accuracy_p90_m']:.3f}), completeness {m['completeness']:.3f}, ghosts "
                  f"{m.get('ghost_fraction', 0):.4f} ({m.get('ghost_fraction_off_static', 0):.4f} off the static world)"
                  f" | unmasked ghosts {u.get('ghost_fraction', 0):.4f} ({u.get('ghost_fraction_off_static', 0):.4f})"
                  f" | the GT surface's own 'ghost' share {floor}"
                  f" | at GT poses: accuracy {row['gt_poses']['masked']['accuracy_median_m']:.3f} m, "
                  f"completeness {row['gt_poses']['masked']['completeness']:.3f}", flush=True)
    return rows


# ----------------------------------------------------------------------------- KITTI raw 0001


def mover_boxes(tracks_csv: Path, min_rows: int = 1) -> list[tuple[np.ndarray, np.ndarray, float, str, str, int]]:
    """(centre, half extents, yaw, track id, label, frame) of every row of the tracks judged moving in at
    least ``min_rows`` frames (module doc): the class's size grown by 0.3 m, heading from the
    velocity above 1 m/s."""
    rows = list(csv.DictReader(open(tracks_csv, newline="")))
    n_moving: dict[str, int] = {}
    for r in rows:
        n_moving[r["track_id"]] = n_moving.get(r["track_id"], 0) + (r["moving"] == "1")
    boxes = []
    for r in rows:
        if n_moving[r["track_id"]] < max(min_rows, 1):
            continue
        c = np.array([float(r["x"]), float(r["y"]), float(r["z"])])
        if not np.isfinite(c).all():
            continue
        w, h, l = CLASS_SIZE.get(r["label"], (1.0, 1.5, 1.0))
        vx, vz = float(r["vx"] or 0.0), float(r["vz"] or 0.0)
        yaw = float(np.arctan2(vx, vz)) if np.hypot(vx, vz) > 1.0 else 0.0
        boxes.append((c, np.array([w / 2 + GROW, h / 2 + GROW, l / 2 + GROW]), yaw, r["track_id"], r["label"],
                      int(r["frame"])))
    return boxes


def inside_boxes(V: np.ndarray, boxes, lift: float | None = None) -> np.ndarray:
    """Which vertices lie in any of ``boxes``; ``lift``: the box's bottom face raised to
    ``lift`` m above the object's own bottom (the road it stands on left out)."""
    inside = np.zeros(len(V), bool)
    if not len(V):
        return inside
    tree = cKDTree(V)
    for c, half, yaw, *_ in boxes:
        idx = np.asarray(tree.query_ball_point(c, float(np.linalg.norm(half))), np.int64)
        if not len(idx):
            continue
        d = V[idx] - c
        co, si = np.cos(yaw), np.sin(yaw)
        across = co * d[:, 0] - si * d[:, 2]
        along = si * d[:, 0] + co * d[:, 2]
        low = half[1] if lift is None else half[1] - GROW - lift  # y points down
        ins = (np.abs(across) <= half[0]) & (d[:, 1] >= -half[1]) & (d[:, 1] <= low) & (np.abs(along) <= half[2])
        inside[idx[ins]] = True
    return inside


def box_footprints(boxes) -> list[np.ndarray]:
    """The boxes' corners from above (x, z), for the pictures."""
    out = []
    for c, half, yaw, *_ in boxes:
        co, si = np.cos(yaw), np.sin(yaw)
        local = np.array([[-half[0], -half[2]], [half[0], -half[2]], [half[0], half[2]], [-half[0], half[2]]])
        x = co * local[:, 0] + si * local[:, 1]
        z = -si * local[:, 0] + co * local[:, 1]
        out.append(np.stack([c[0] + x, c[2] + z], 1))
    return out


# what the grown boxes hold: the road, the static world, the rest (the off-static decomposition)
SLAB = 10.0  # m along z: one road plane per slab
ROAD_BAND = 0.08  # m: a plane's inliers
SEEN = 0.25  # m along the ray: a keyframe sees a surface at the vertex
THROUGH = 0.4  # m: ... or a surface this far behind it (the vertex is free space there)
ELSEWHERE = 0.5  # m: a box grown by this much more must not hold the vertex for the keyframe to judge it
GROUND, STATIC, OFF_STATIC = 0, 1, 2


def road_height(V: np.ndarray, ref: np.ndarray, seed: int = 0) -> np.ndarray:
    """Height (m, up) of each vertex of ``V`` above the road: per :data:`SLAB` m of z, the
    near-horizontal plane (normal within 18 degrees of the vertical) through most of the
    ``ref`` vertices around them (RANSAC, then a least-squares fit to its inliers)."""
    h = np.full(len(V), np.inf)
    if not len(V):
        return h
    rng = np.random.default_rng(seed)
    for z0 in np.arange(np.floor(V[:, 2].min() / SLAB) * SLAB, V[:, 2].max() + SLAB, SLAB):
        sel = (V[:, 2] >= z0) & (V[:, 2] < z0 + SLAB)
        if not sel.any():
            continue
        x0, x1 = V[sel, 0].min() - 6.0, V[sel, 0].max() + 6.0
        R = ref[(ref[:, 2] >= z0 - 5) & (ref[:, 2] < z0 + SLAB + 5) & (ref[:, 0] >= x0) & (ref[:, 0] <= x1)]
        R = R[rng.choice(len(R), min(len(R), 20000), replace=False)].astype(np.float64)
        best, n_best = None, 0
        for _ in range(200 if len(R) >= 3 else 0):
            p = R[rng.choice(len(R), 3, replace=False)]
            n = np.cross(p[1] - p[0], p[2] - p[0])
            if np.linalg.norm(n) < 1e-9:
                continue
            n = n / np.linalg.norm(n)
            if abs(n[1]) < 0.95:
                continue
            n = -n if n[1] > 0 else n  # up: -y
            cnt = int(np.count_nonzero(np.abs(R @ n - n @ p[0]) < ROAD_BAND))
            if cnt > n_best:
                best, n_best = (n, float(n @ p[0])), cnt
        if best is None:
            continue
        inl = R[np.abs(R @ best[0] - best[1]) < ROAD_BAND]
        c = inl.mean(0)
        n = np.linalg.svd(inl - c, full_matrices=False)[2][2]
        h[sel] = (V[sel] - c) @ (-n if n[1] > 0 else n)
    return h


def in_box(V: np.ndarray, box, extra: float = 0.0) -> np.ndarray:
    c, half, yaw = box[0], box[1] + extra, box[2]
    d = V - c
    co, si = np.cos(yaw), np.sin(yaw)
    return ((np.abs(co * d[:, 0] - si * d[:, 2]) <= half[0]) & (np.abs(d[:, 1]) <= half[1])
            & (np.abs(si * d[:, 0] + co * d[:, 2]) <= half[2]))


def witnesses(V: np.ndarray, boxes, depths: dict[int, np.ndarray], K: np.ndarray, poses: np.ndarray):
    """Per vertex, the keyframes that saw its spot while no mover's box held it (the box of
    that frame grown by :data:`ELSEWHERE`; in a gap of a track's rows, its nearest row's
    grown by 1 m more; before its first row or after its last, the track counts as
    elsewhere): how many saw a surface there (within :data:`SEEN` m along the ray, in the
    keyframe's depth without masks) and how many saw through it."""
    per_track: dict[str, dict[int, tuple]] = {}
    for b in boxes:
        per_track.setdefault(b[3], {})[b[5]] = b
    seen = np.zeros(len(V), np.int32)
    through = np.zeros(len(V), np.int32)
    for p, depth in depths.items():
        held = np.zeros(len(V), bool)
        for rows in per_track.values():
            if p in rows:
                held |= in_box(V, rows[p], ELSEWHERE)
            elif min(rows) <= p <= max(rows):
                held |= in_box(V, rows[min(rows, key=lambda f: abs(f - p))], ELSEWHERE + 1.0)
        T = poses[p]
        pc = (V - T[:3, 3]) @ T[:3, :3]
        z = np.maximum(pc[:, 2], 1e-6)
        u = np.floor(K[0, 0] * pc[:, 0] / z + K[0, 2] + 0.5).astype(np.int64)
        v = np.floor(K[1, 1] * pc[:, 1] / z + K[1, 2] + 0.5).astype(np.int64)
        ok = (pc[:, 2] > 0.5) & (u >= 0) & (v >= 0) & (u < depth.shape[1]) & (v < depth.shape[0]) & ~held
        d = np.zeros(len(V), np.float64)
        d[ok] = depth[v[ok], u[ok]]
        ok &= d > 0
        seen += ok & (np.abs(d - pc[:, 2]) <= SEEN)
        through += ok & (d - pc[:, 2] > THROUGH)
    return seen, through


def decompose(V: np.ndarray, boxes, depths: dict[int, np.ndarray], K: np.ndarray, poses: np.ndarray,
              road_ref: np.ndarray) -> np.ndarray:
    """What each vertex (inside the boxes) is: :data:`GROUND` (within 0.3 m of the road's
    plane), :data:`STATIC` (a keyframe that saw the spot while the movers were elsewhere saw
    a surface there, at least as often as one saw through it), :data:`OFF_STATIC` (the rest:
    the ghosts, and static world no keyframe saw without a mover's box around it)."""
    code = np.full(len(V), OFF_STATIC, np.int8)
    ground = road_height(V, road_ref) <= GROW
    seen, through = witnesses(V, boxes, depths, K, poses)
    code[~ground & (seen > 0) & (seen >= through)] = STATIC
    code[ground] = GROUND
    return code


def keyframe_depths(tap: "KeyframeTap", cfg: Config, ok: np.ndarray) -> tuple[dict[int, np.ndarray], np.ndarray]:
    """Every fused keyframe's depth without masks (the fusion's own filters) and the intrinsics it is at."""
    from dynastereo.mesh.fusion import depth_and_movers, mesh_matcher, scaled_K

    sysm, matcher = tap.system, mesh_matcher(cfg)
    out = {}
    for view in tap.recorder.views:
        if view.position < len(ok) and ok[view.position]:
            out[view.position] = depth_and_movers(view, None, sysm.calib, matcher, cfg.mesh,
                                                  float(sysm.disparity_offset))[0]
    return out, scaled_K(sysm.calib.K, cfg.mesh.scale)


CLASS_BGR = {GROUND: (150, 150, 150), STATIC: (90, 190, 60), OFF_STATIC: (40, 40, 235)}


def box_picture(parts: dict[str, tuple[np.ndarray, np.ndarray]], boxes) -> str:
    """From above, the vertices inside the movers' grown boxes, masked | unmasked: grey the
    road, green the static world seen without a mover there, red the rest (docs/mesh_raw0001_boxes.png)."""
    allv = np.concatenate([v for v, _ in parts.values()])
    bounds = (float(allv[:, 0].min()) - 2, float(allv[:, 0].max()) + 2, float(allv[:, 2].min()) - 2,
              float(allv[:, 2].max()) + 2)
    th = 900
    size = (max(200, int(th * (bounds[1] - bounds[0]) / (bounds[3] - bounds[2]))), th)
    tiles = []
    for name, (V, code) in parts.items():
        img = np.full((size[1], size[0], 3), 40, np.uint8)
        for f in box_footprints(boxes):
            cv2.polylines(img, [np.round(top_pixels(f, bounds, size)).astype(np.int32)], True, (80, 80, 80), 1)
        for k in (GROUND, STATIC, OFF_STATIC):
            px = np.round(top_pixels(V[code == k][:, [0, 2]], bounds, size)).astype(np.int64)
            ok = (px[:, 0] >= 0) & (px[:, 1] >= 0) & (px[:, 0] < size[0]) & (px[:, 1] < size[1])
            if k == OFF_STATIC:  # the few that matter, drawn larger
                for u, v in px[ok]:
                    cv2.circle(img, (int(u), int(v)), 1, CLASS_BGR[k], -1)
            else:
                img[px[ok, 1], px[ok, 0]] = CLASS_BGR[k]
        n = np.bincount(code, minlength=3)
        for i, text in enumerate((name, f"road {n[GROUND]}", f"static {n[STATIC]}", f"rest {n[OFF_STATIC]}")):
            col = (255, 255, 255) if i == 0 else CLASS_BGR[(GROUND, STATIC, OFF_STATIC)[i - 1]]
            cv2.putText(img, text, (8, 24 + 24 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.6, col, 2, cv2.LINE_AA)
        tiles.append(img)
    path = DOCS / "mesh_raw0001_boxes.png"
    cv2.imwrite(str(path), np.hstack([tiles[0], np.full((size[1], 6, 3), 255, np.uint8), tiles[1]]))
    return str(path.relative_to(ROOT))


def pictures(masked, unmasked, boxes, K: np.ndarray, size: tuple[int, int]) -> dict[str, str]:
    """Top views (where the movers' grown boxes went outlined in red) and the first camera's
    view, masked | unmasked side by side: docs/mesh_raw0001_top.png, docs/mesh_raw0001_camera.png."""
    from dynastereo.mesh.render import mesh_bounds

    bounds = mesh_bounds(masked, 2.0)
    x0, x1, z0, z1 = bounds
    th = 900
    tsize = (max(200, int(th * (x1 - x0) / (z1 - z0))), th)
    area = np.zeros((tsize[1], tsize[0]), np.uint8)
    for f in box_footprints(boxes):
        cv2.fillPoly(area, [np.round(top_pixels(f, bounds, tsize)).astype(np.int32)], 255)
    contours, _ = cv2.findContours(area, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    tiles = []
    for name, m in (("movers left out", masked), ("no masks", unmasked)):
        img = render_top(m, tsize, bounds)
        cv2.drawContours(img, contours, -1, (60, 60, 235), 1, cv2.LINE_AA)
        cv2.putText(img, name, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
        tiles.append(img)
    top = np.hstack([tiles[0], np.full((tsize[1], 6, 3), 255, np.uint8), tiles[1]])
    cams = []
    for name, m in (("movers left out", masked), ("no masks", unmasked)):
        img = render_camera(m, K, size)
        cv2.putText(img, name, (10, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2, cv2.LINE_AA)
        cams.append(img)
    cam = np.vstack([cams[0], np.full((6, size[0], 3), 255, np.uint8), cams[1]])
    paths = {"top": DOCS / "mesh_raw0001_top.png", "camera": DOCS / "mesh_raw0001_camera.png"}
    cv2.imwrite(str(paths["top"]), top)
    cv2.imwrite(str(paths["camera"]), cam)
    return {k: str(p.relative_to(ROOT)) for k, p in paths.items()}


def kitti(args, work: Path) -> dict:
    data = data_dir(required=False)
    seq = data / CLIPS["raw0001"] if data is not None else None
    if seq is None or not seq.is_dir():
        where = seq if seq is not None else f"{CLIPS['raw0001']}, no data folder"
        print(f"KITTI raw 0001 missing ({where}): skipped")
        return {"skipped": f"missing {where}"}
    models = models_dir(required=False)
    cfg = Config()
    r = run_with_mesh(seq, work / "raw0001", cfg, models)
    write_mesh_ply(work / "raw0001" / "mesh_unmasked.ply", r["unmasked"])
    csv_path = work / "raw0001" / "objects_tracks.csv"
    boxes = mover_boxes(csv_path)
    ins_m = inside_boxes(r["masked"].vertices, boxes)
    ins_u = inside_boxes(r["unmasked"].vertices, boxes)
    info = r["info"]
    cpu = info["disparity_s"] + info["fusion_s"] + info["marching_s"]
    # the same off the road (the boxes' bottoms 0.3 m above the objects'), tracks moving in >= 3 frames
    firm = mover_boxes(csv_path, min_rows=3)
    lm, lu = inside_boxes(r["masked"].vertices, firm, GROW), inside_boxes(r["unmasked"].vertices, firm, GROW)
    per_track = {}
    for tid in sorted({b[3] for b in firm}, key=int):
        bx = [b for b in firm if b[3] == tid]
        a = int(inside_boxes(r["masked"].vertices, bx, GROW).sum())
        u = int(inside_boxes(r["unmasked"].vertices, bx, GROW).sum())
        per_track[tid] = {"label": bx[0][4], "rows": len(bx), "masked": a, "unmasked": u, "ratio": round(a / max(u, 1), 4)}
    tracks_text = ", ".join(f"#{k} {v['label']} {v['ratio']:.0%}" for k, v in per_track.items())
    # the vertices in the grown boxes decomposed: the road, the static world, the rest
    t0 = time.process_time()
    depths, Ks = keyframe_depths(r["tap"], cfg, r["ok"])
    poses = np.asarray(r["result"].poses)
    codes = {}
    for part, M, ins in (("masked", r["masked"], ins_m), ("unmasked", r["unmasked"], ins_u)):
        codes[part] = (M.vertices[ins], decompose(M.vertices[ins], boxes, depths, Ks, poses, r["unmasked"].vertices))
    split = {part: {"road": int((c == GROUND).sum()), "static_world": int((c == STATIC).sum()),
                    "rest": int((c == OFF_STATIC).sum())} for part, (_, c) in codes.items()}
    per_track_rest = {}
    for tid in sorted({b[3] for b in firm}, key=int):
        bx = [b for b in boxes if b[3] == tid]
        n = {part: int(((c == OFF_STATIC) & inside_boxes(V, bx)).sum()) for part, (V, c) in codes.items()}
        per_track_rest[tid] = {"label": bx[0][4], "masked": n["masked"], "unmasked": n["unmasked"],
                               "ratio": round(n["masked"] / max(n["unmasked"], 1), 4)}
    decomposed = {
        "what": ("the vertices of in_mover_boxes split three ways: 'road', within 0.3 m of the road's plane "
                 "(RANSAC per 10 m of z through the unmasked mesh); 'static_world', where a keyframe that saw the "
                 "spot while no mover's box held it (that frame's box grown 0.5 m more) saw a surface within "
                 "0.25 m along its ray, at least as often as one saw through it; 'rest', everything else: the "
                 "ghosts, and static surfaces no keyframe saw without a mover's box around them. The ratio "
                 "compares the rests. Not the issue's measure, beside it."),
        **split, "ratio": round(split["masked"]["rest"] / max(split["unmasked"]["rest"], 1), 4),
        "per_track": per_track_rest, "cpu_s": round(time.process_time() - t0, 2)}
    rest_text = ", ".join(f"#{k} {v['label']} {v['masked']} / {v['unmasked']}" for k, v in per_track_rest.items())
    calib = r["tap"].system.calib
    pics = pictures(r["masked"], r["unmasked"], boxes, calib.K, (calib.width, calib.height))
    pics["boxes"] = box_picture({"movers left out": codes["masked"], "no masks": codes["unmasked"]}, boxes)
    out = {"frames": len(r["result"].frames), "keyframes": info["keyframes"],
           "moving_tracks": len({int(k) for k in r["tap"].recorder.moving_tracks}),
           "mover_boxes": len(boxes),
           "vertices": {"masked": int(len(r["masked"].vertices)), "unmasked": int(len(r["unmasked"].vertices))},
           "in_mover_boxes": {"masked": int(ins_m.sum()), "unmasked": int(ins_u.sum()),
                              "ratio": round(float(ins_m.sum() / max(ins_u.sum(), 1)), 4)},
           "in_mover_boxes_off_road": {"masked": int(lm.sum()), "unmasked": int(lu.sum()),
                                       "ratio": round(float(lm.sum() / max(lu.sum(), 1)), 4),
                                       "what": "tracks moving in >= 3 frames; each box's bottom 0.3 m above the object's",
                                       "per_track": per_track},
           "in_mover_boxes_decomposed": decomposed,
           "cpu_s": round(cpu, 3), "cpu_split_s": {k: info[k] for k in ("disparity_s", "fusion_s", "marching_s")},
           "voxel_grid_peak_mb": round(info["voxel_bytes"] / 1e6, 1), "blocks": info["blocks"],
           "keyframe_images_mb": round(r["keyframe_bytes"] / 1e6, 1),
           "tracking_fps": round(float(r["result"].fps), 2), "pictures": pics}
    print(f"raw 0001: {out['keyframes']} keyframes, {out['vertices']['masked']} vertices; in the movers' boxes "
          f"{ins_m.sum()} masked vs {ins_u.sum()} unmasked = {out['in_mover_boxes']['ratio']:.1%} (target <= 5 %); "
          f"off the road, firm movers: {lm.sum()} vs {lu.sum()} = {out['in_mover_boxes_off_road']['ratio']:.1%} "
          f"({tracks_text}); decomposed (not the issue's measure): masked road {split['masked']['road']}, static world "
          f"{split['masked']['static_world']}, rest {split['masked']['rest']} vs unmasked rest "
          f"{split['unmasked']['rest']} = {decomposed['ratio']:.1%} ({rest_text}); "
          f"mesh CPU {cpu:.2f} s (target <= 5 s: disparity {info['disparity_s']:.2f}, fusion {info['fusion_s']:.2f}, "
          f"marching cubes {info['marching_s']:.2f}); voxel grid peak {out['voxel_grid_peak_mb']} MB, keyframe images "
          f"held {out['keyframe_images_mb']} MB", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenarios", default="oncoming,crossing")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "dynastereo-synth-cache")
    ap.add_argument("--skip-kitti", action="store_true")
    ap.add_argument("--skip-synthetic", action="store_true")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--keep", type=Path, default=None, help="keep the runs' folders (and raw 0001's unmasked mesh) here")
    args = ap.parse_args()
    logging.getLogger("dynastereo").setLevel(logging.ERROR)
    args.cache.mkdir(parents=True, exist_ok=True)
    res: dict = {"config": Config().mesh.__dict__, "machine": machine()}
    with tempfile.TemporaryDirectory(prefix="bench_mesh_") as tmp:
        work = args.keep or Path(tmp)
        if not args.skip_synthetic:
            rows = synthetic(args, args.cache, work)
            res["synthetic"] = rows

            def med(key, part="masked"):
                vals = [r[part][key] for r in rows if key in r[part]]
                return round(float(np.median(vals)), 5) if vals else None

            res["synthetic_medians"] = {
                "accuracy_median_m": med("accuracy_median_m"), "accuracy_p90_m": med("accuracy_p90_m"),
                "completeness": med("completeness"), "ghost_fraction": med("ghost_fraction"),
                "ghost_fraction_off_static": med("ghost_fraction_off_static"),
                "unmasked_ghost_fraction": med("ghost_fraction", "unmasked"),
                "unmasked_ghost_fraction_off_static": med("ghost_fraction_off_static", "unmasked"),
                "ghost_fraction_of_gt_surface": round(float(np.median([r["ghost_fraction_of_gt_surface"] for r in rows
                                                                       if r["ghost_fraction_of_gt_surface"] is not None])), 5)}
            print("synthetic medians:", json.dumps(res["synthetic_medians"]))
        if not args.skip_kitti:
            res["kitti_raw_0001"] = kitti(args, work)
    if args.out.exists():  # a part skipped keeps its figures from the last run
        last = json.loads(args.out.read_text())
        for key in (("synthetic", "synthetic_medians") if args.skip_synthetic else ()) + (
                ("kitti_raw_0001",) if args.skip_kitti else ()):
            if key in last:
                res[key] = last[key]
    write_json(args.out, res, default=float)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
