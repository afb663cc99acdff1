"""Load every SLAM kernel once, on tiny problems, before the first frame.

numba loads a cached kernel (or compiles it, after an install or a change of its source)
on its first call: tens of milliseconds each from the cache, seconds to compile.  Made at
start-up (:class:`~dynastereo.slam.local_mapping.BARunner`'s warm-up thread, beside the
models' loading), those first calls do not land in the first frames -- a camera's or a
live node's first frames, an offline run's frame rate.  Nothing here keeps state.
"""

from __future__ import annotations

import numpy as np
from numba import types as nt

from .geometry import desc_u64
from .kernels import bookkeeping
from .kernels.ba import warm_up as warm_up_ba
from .kernels.bucketing import bucket_corners
from .kernels.epipolar import epipolar_best
from .kernels.hamming import descend_tree, knn_hamming
from .matcher import KeypointGrid, search_by_projection, stereo_match
from .optimizer import optimize_pose


def warm_up_kernels(ba: bool = True) -> None:
    """One small call of every per-frame and local-mapping kernel (the local BA's too
    unless ``ba`` is false), with the argument types of a real run."""
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (60, 120), dtype=np.uint8)
    uv = np.c_[rng.uniform(20, 100, 30), rng.uniform(10, 50, 30)]
    octv = np.zeros(30, np.int32)
    desc = rng.integers(0, 255, (30, 32), dtype=np.uint8)
    scales = 1.2 ** np.arange(8)
    stereo_match(uv, octv, desc, uv - [5.0, 0.0], octv, desc, img, img, scales, 100.0, 50.0)
    K = np.array([[100.0, 0, 60], [0, 100.0, 30], [0, 0, 1]])
    X = np.c_[rng.uniform(-1, 1, (30, 2)), rng.uniform(4, 8, 30)]
    optimize_pose(np.eye(4), X, uv, uv[:, 0] - 5, np.ones(30), K, 50.0)
    knn_hamming(desc, desc, 2)
    epipolar_best(desc, uv, np.zeros(30, bool), desc, uv, np.zeros(30, bool), np.full(30, 3.84), np.full(30, 100.0),
                  np.eye(3), (60.0, 30.0), 50)
    bucket_corners(uv[:, 0].copy(), uv[:, 1].copy(), rng.random(30).astype(np.float32), octv,
                   np.array([20, 10], np.int64), 120, 60)
    g = KeypointGrid(uv, 120, 60)
    d64 = desc_u64(desc)
    search_by_projection(g, octv, d64, uv[:, 0] - 5, np.ones(30, bool), uv[:, 0], uv[:, 1], np.full(30, 4.0), d64,
                         min_level=np.zeros(30, np.int64), max_level=np.ones(30, np.int64), u_right=uv[:, 0] - 5,
                         ratio=0.8, reproj_check=(uv, np.ones(30)))
    search_by_projection(g, octv, d64, uv[:, 0] - 5, None, uv[:, 0], uv[:, 1], np.full(30, 4.0), d64)
    _load_by_signature()
    if ba:
        warm_up_ba()


def _load_by_signature() -> None:
    """The map's bookkeeping kernels and the vocabulary's descent: loaded (or compiled) for
    the argument types a run passes, without a call -- their inputs are the map's own
    tables, which a made-up problem would have to build whole."""
    i1, b1, f1 = nt.int64[::1], nt.boolean[::1], nt.float64[::1]
    f2, u8, u64 = nt.float64[:, ::1], nt.uint8[:, ::1], nt.uint64[:, ::1]
    for kernel, sig in (
        (bookkeeping.rows_of, (i1, i1, b1, i1)),
        (bookkeeping.by_keyframe, (i1,)),
        (bookkeeping.unseen_good, (i1, b1, i1)),
        (bookkeeping.unique_good, (i1, b1)),
        (bookkeeping.new_observations, (i1, i1, i1, b1)),
        (bookkeeping.update_points, (i1, i1, i1, i1, f2, i1, u8, u64, f2, i1, f2, f1, f1, u8, f1, nt.int64)),
        (bookkeeping.redundant_points, (i1, i1, i1, i1, nt.int64)),
        (descend_tree, (u64, nt.UniTuple(nt.uint64[:, :, ::1], 4), nt.UniTuple(nt.int32[:, ::1], 4), nt.int64,
                        nt.int64)),
    ):
        kernel.compile(sig)
