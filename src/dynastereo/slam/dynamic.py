"""Forgetting what turned out to move: the map points on an object judged moving.

An object judged static takes part in tracking and mapping (``objects.motion``); when it
later starts to move, its map points would pull the poses along with it.
:func:`forget_region` marks bad every good map point of the current map that projects,
from the last tracked frame, into the object's left-image pixels at the object's depth,
and drops the last frame's keypoints there (their matches and their stereo depth, so
they are not used as temporary points for the next frame either).
"""

from __future__ import annotations

import numpy as np

from .frame import Frame
from .map import Map


def points_in_region(mp: Map, T_cw: np.ndarray, K: np.ndarray, region: np.ndarray, z_min: float,
                     z_max: float) -> np.ndarray:
    """Ids of the good map points that project into the bool image ``region`` from the
    camera ``T_cw`` (4x4 or 3x4, world -> camera) with depth in ``[z_min, z_max]``."""
    ids = mp.points.good_ids()
    if len(ids) == 0:
        return ids
    Xc = mp.points.pos[ids] @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = Xc[:, 2]
    front = (z >= max(z_min, 1e-3)) & (z <= z_max)
    ids, Xc, z = ids[front], Xc[front], z[front]
    h, w = region.shape
    u = np.rint(K[0, 0] * Xc[:, 0] / z + K[0, 2]).astype(np.int64)
    v = np.rint(K[1, 1] * Xc[:, 1] / z + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    ids, u, v = ids[inside], u[inside], v[inside]
    return ids[region[v, u]]


def forget_region(mp: Map, last: Frame | None, region: np.ndarray, z_min: float, z_max: float) -> int:
    """Mark bad the map points in ``region`` at depths ``[z_min, z_max]`` seen from the last
    frame ``last``, and unmatch its keypoints there; returns how many points were removed."""
    if last is None or last.T_cw is None:
        return 0
    region = np.asarray(region, bool)
    ids = points_in_region(mp, last.T_cw, last.calib.K, region, z_min, z_max)
    if len(ids):
        mp.set_bad(ids)
    h, w = region.shape
    u = np.clip(np.rint(last.uv[:, 0]).astype(np.int64), 0, w - 1)
    v = np.clip(np.rint(last.uv[:, 1]).astype(np.int64), 0, h - 1)
    on = region[v, u] & (last.depth > 0) & (last.depth >= z_min) & (last.depth <= z_max)
    sel = np.flatnonzero(on)
    last.clear_matches(sel)
    last.depth = last.depth.copy()  # (a keyframe made from this frame shares the array: keep it)
    last.depth[sel] = -1.0
    return int(len(ids))
