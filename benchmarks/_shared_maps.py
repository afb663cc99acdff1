"""Map files the benchmarks share: :func:`synthetic_map`, a map the size of a long run
built through the Map API (``bench_map_io.py`` saves and loads it, ``bench_map_load_checks.py``
times the load-time checks on it).  ``dynastereo`` is imported when a map is built, not at
import time."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from dynastereo.slam.map_io import MapFile


def synthetic_map(n_kf: int = 100, n_kp: int = 2000, new_per_kf: int = 500, seed: int = 0) -> MapFile:
    """A map built through the Map API to the size of a long run: ``n_kf`` keyframes x
    ``n_kp`` keypoints, ``new_per_kf`` new points per keyframe (each seen by ~3 keyframes),
    10 % of the points culled, 5 keyframes culled, covisibility from the observations;
    random descriptors (incompressible, as real ORB descriptors nearly are)."""
    from dynastereo.datatypes import StereoCalibration
    from dynastereo.slam.keyframe import KeyFrame
    from dynastereo.slam.map import Map
    from dynastereo.slam.map_io import MapFile

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
