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
the mesh's CPU time (disparity + fusion + marching cubes; target <= 5 s) and the voxel
grid's peak memory; pictures side by side (``docs/mesh_raw0001_*.png``).

Writes benchmarks/results/mesh.json.  Run:

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


def mover_boxes(tracks_csv: Path, min_rows: int = 1) -> list[tuple[np.ndarray, np.ndarray, float, str, str]]:
    """(centre, half extents, yaw, track id, label) of every row of the tracks judged moving in at least
    ``min_rows`` frames (module doc): the class's size grown by 0.3 m, heading from the
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
        boxes.append((c, np.array([w / 2 + GROW, h / 2 + GROW, l / 2 + GROW]), yaw, r["track_id"], r["label"]))
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
    calib = r["tap"].system.calib
    pics = pictures(r["masked"], r["unmasked"], boxes, calib.K, (calib.width, calib.height))
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
           "cpu_s": round(cpu, 3), "cpu_split_s": {k: info[k] for k in ("disparity_s", "fusion_s", "marching_s")},
           "voxel_grid_peak_mb": round(info["voxel_bytes"] / 1e6, 1), "blocks": info["blocks"],
           "keyframe_images_mb": round(r["keyframe_bytes"] / 1e6, 1),
           "tracking_fps": round(float(r["result"].fps), 2), "pictures": pics}
    print(f"raw 0001: {out['keyframes']} keyframes, {out['vertices']['masked']} vertices; in the movers' boxes "
          f"{ins_m.sum()} masked vs {ins_u.sum()} unmasked = {out['in_mover_boxes']['ratio']:.1%} (target <= 5 %); "
          f"off the road, firm movers: {lm.sum()} vs {lu.sum()} = {out['in_mover_boxes_off_road']['ratio']:.1%} "
          f"({tracks_text}); "
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
    write_json(args.out, res, default=float)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
