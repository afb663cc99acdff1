"""The mesh benchmarks' synthetic ground truth, shared by ``bench_mesh.py`` and
``bench_mesh_tsdf.py``: the cached synthetic sequence at KITTI's image size
(:func:`sequence`) and its GT static surface, parked objects' and movers' points
(:func:`gt_points`).  ``dynastereo`` is imported when they are called, not at import time."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from _shared_runs import sequence as _cached_sequence

SIZE = (1241, 376)  # KITTI's camera (fx 719 px, baseline 0.54 m): the mesh's defaults are for it
MAX_RANGE = 20.0  # GT points within this depth, m
GRID = 0.05  # GT points thinned to one per cell of this grid, m


def sequence(cache: Path, scenario: str, frames: int, seed: int) -> Path:
    """The synthetic sequence ``scenario`` (``frames``, ``seed``) at :data:`SIZE`, cached
    under ``cache`` (generated when absent or when the generator changed)."""
    return _cached_sequence(cache, scenario, frames, seed, SIZE)[0]


def _grid(p: np.ndarray) -> np.ndarray:
    if not len(p):
        return p.reshape(0, 3)
    _, first = np.unique(np.floor(p / GRID).astype(np.int64), axis=0, return_index=True)
    return p[first]


def gt_points(seq: Path) -> dict[str, np.ndarray]:
    """The GT points of every frame of the synthetic sequence ``seq`` in the world (the GT
    poses; one per :data:`GRID` cell): ``static`` (the GT disparity of the pixels outside
    every GT instance mask, within :data:`MAX_RANGE`), ``parked`` (the pixels of objects
    that never move) and ``movers`` (the pixels of each object in the frames it moves in)."""
    from dynastereo.synth import read_gt_disparity, read_gt_masks, read_objects

    gt = read_objects(seq)
    c = gt.calibration
    bf = c["fx"] * c["baseline"]
    poses = np.loadtxt(seq.parent.parent / "poses" / "00.txt").reshape(-1, 3, 4)
    ever_moving = {int(i) for i, o in gt.objects.items() if o.get("moves")}
    out: dict[str, list[np.ndarray]] = {"static": [], "parked": [], "movers": []}
    for i in range(len(gt)):
        d = read_gt_disparity(seq, i)
        ids, _ = read_gt_masks(seq, i)
        h, w = d.shape
        v, u = np.mgrid[0:h, 0:w]
        z = np.where(d > 0, bf / np.maximum(d, 1e-6), 0.0)
        ok = (z > 0) & (z <= MAX_RANGE)
        moving_now = [o.id for o in gt.frame(i) if o.moving]
        sel = {"static": ok & (ids == 0), "parked": ok & (ids > 0) & ~np.isin(ids, list(ever_moving)),
               "movers": ok & np.isin(ids, moving_now)}
        for k, m in sel.items():
            zz = z[m]
            P = np.stack([(u[m] - c["cx"]) / c["fx"] * zz, (v[m] - c["cy"]) / c["fy"] * zz, zz], 1)
            out[k].append(_grid(P @ poses[i][:, :3].T + poses[i][:, 3]))
    return {k: _grid(np.concatenate(v)) if v else np.zeros((0, 3)) for k, v in out.items()}
