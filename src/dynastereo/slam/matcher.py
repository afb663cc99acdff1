"""Descriptor matching (ORB-SLAM2's ORBmatcher): one compiled call per search.

* ``stereo_match``: left/right keypoints along the rectified rows by descriptor
  distance, then SAD block matching at full resolution with parabola sub-pixel
  refinement and a median-based outlier rejection (``Frame::ComputeStereoMatches``).
* ``KeypointGrid``: keypoints bucketed in image cells; ``query`` returns every
  (query, keypoint) pair inside square windows, without a Python loop.
* ``search_by_projection``: best keypoint for each projected map point inside its
  window, with level / stereo / ratio / distance checks and one point per keypoint.

``stereo_match`` and ``search_by_projection`` run as numba kernels (``kernels/stereo.py``,
``kernels/projection.py``) on descriptors viewed as (N, 4) uint64; the vectorized numpy
versions they replace are the tests' references (``tests/reference/slam_numpy.py``:
candidate pairs from ``expand_ranges`` over sorted arrays, ``np.bitwise_count``), which the
kernels are tested against: the same matches, in the same order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .kernels.hamming import knn_hamming
from .kernels.projection import search_by_projection_kernel
from .kernels.stereo import stereo_match_kernel
from .geometry import CHI2_MONO, CHI2_STEREO, desc_u64, expand_ranges, rotation_consistent, unique_best

TH_HIGH = 100
TH_LOW = 50


@dataclass
class StereoResult:
    u_right: np.ndarray  # (N,) right-image u of each left keypoint, -1 if none
    depth: np.ndarray  # (N,) metres, -1 if none


def stereo_match(
    uv_l: np.ndarray,
    oct_l: np.ndarray,
    desc_l: np.ndarray,
    uv_r: np.ndarray,
    oct_r: np.ndarray,
    desc_r: np.ndarray,
    img_l: np.ndarray,
    img_r: np.ndarray,
    scales: np.ndarray,
    fx: float,
    bf: float,
    max_disparity: float | None = None,
    th_dist: int = (TH_HIGH + TH_LOW) // 2,
) -> StereoResult:
    """Stereo matches of left keypoints (``Frame::ComputeStereoMatches``), one compiled call.

    Candidates: right keypoints within ``2 * scale[octave]`` rows, at most one octave
    apart, with disparity in ``[0, max_disparity]`` (default ``fx``: depth >= baseline).
    The best descriptor match (<= ``th_dist``) is refined by SAD over 11x11 windows
    along the row of the full-resolution grayscale images ``img_l`` / ``img_r`` and a
    parabola fit; matches whose SAD exceeds 2.1 x the median are dropped.  The kernel
    (``kernels.stereo``) gives the same matches as the numpy reference
    (``tests/reference/slam_numpy.py``).
    """
    n = len(uv_l)
    u_right = np.full(n, -1.0)
    depth = np.full(n, -1.0)
    if n == 0 or len(uv_r) == 0:
        return StereoResult(u_right, depth)
    max_d = float(fx if max_disparity is None else max_disparity)
    uv_l = np.asarray(uv_l, np.float64)
    uv_r = np.asarray(uv_r, np.float64)
    oct_r = np.asarray(oct_r, np.int64)
    order = np.lexsort((uv_r[:, 1], oct_r))
    n_oct = max(int(oct_r.max()), int(np.max(oct_l))) + 1
    oct_start = np.searchsorted(oct_r[order], np.arange(n_oct + 1)).astype(np.int64)
    stereo_match_kernel(
        np.ascontiguousarray(uv_l[:, 0]), np.ascontiguousarray(uv_l[:, 1]),
        np.rint(uv_l[:, 0]).astype(np.int64), np.rint(uv_l[:, 1]).astype(np.int64),
        np.ascontiguousarray(oct_l, np.int64), desc_u64(desc_l),
        np.ascontiguousarray(uv_r[order, 0]), np.ascontiguousarray(uv_r[order, 1]),
        np.rint(uv_r[order, 0]).astype(np.int64), desc_u64(np.asarray(desc_r)[order]), oct_start,
        np.ascontiguousarray(img_l, np.uint8), np.ascontiguousarray(img_r, np.uint8),
        np.ascontiguousarray(scales, np.float64),
        0.0, max_d, int(th_dist), float(bf), u_right, depth,
    )
    return StereoResult(u_right, depth)


class KeypointGrid:
    """Keypoints bucketed in square cells; ``query`` finds all keypoints in windows."""

    def __init__(self, uv: np.ndarray, width: int, height: int, cell: float = 16.0) -> None:
        self.uv = uv
        self.cell = float(cell)
        self.ncx = max(1, int(np.ceil(width / cell)))
        self.ncy = max(1, int(np.ceil(height / cell)))
        cx = np.clip((uv[:, 0] / cell).astype(np.int64), 0, self.ncx - 1)
        cy = np.clip((uv[:, 1] / cell).astype(np.int64), 0, self.ncy - 1)
        cid = cy * self.ncx + cx
        self.order = np.argsort(cid, kind="stable")
        self.start = np.searchsorted(cid[self.order], np.arange(self.ncx * self.ncy + 1))

    def query(self, u: np.ndarray, v: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """All pairs (query index, keypoint index) with ``|du| < r`` and ``|dv| < r``."""
        if len(u) == 0 or len(self.uv) == 0:
            z = np.zeros(0, np.int64)
            return z, z
        c = self.cell
        x0 = np.clip(np.floor((u - r) / c).astype(np.int64), 0, self.ncx - 1)
        x1 = np.clip(np.floor((u + r) / c).astype(np.int64), 0, self.ncx - 1)
        y0 = np.clip(np.floor((v - r) / c).astype(np.int64), 0, self.ncy - 1)
        y1 = np.clip(np.floor((v + r) / c).astype(np.int64), 0, self.ncy - 1)
        nrows = np.maximum(y1 - y0 + 1, 0)
        q_rep, row = expand_ranges(y0, nrows)
        s = self.start[row * self.ncx + x0[q_rep]]
        e = self.start[row * self.ncx + x1[q_rep] + 1]
        g, pos = expand_ranges(s, e - s)
        q = q_rep[g]
        k = self.order[pos]
        ok = (np.abs(self.uv[k, 0] - u[q]) < r[q]) & (np.abs(self.uv[k, 1] - v[q]) < r[q])
        return q[ok], k[ok]


@dataclass
class ProjectionMatches:
    query: np.ndarray  # index into the projected points
    kp: np.ndarray  # keypoint index in the frame
    dist: np.ndarray  # Hamming distance


def search_by_projection(
    grid: KeypointGrid,
    kp_octave: np.ndarray,
    kp_desc64: np.ndarray,
    kp_uR: np.ndarray | None,
    kp_available: np.ndarray | None,
    u: np.ndarray,
    v: np.ndarray,
    radius: np.ndarray,
    q_desc64: np.ndarray,
    min_level: np.ndarray | None = None,
    max_level: np.ndarray | None = None,
    u_right: np.ndarray | None = None,
    th_dist: int = TH_HIGH,
    ratio: float | None = None,
    ratio_same_level_only: bool = True,
    angle_check: tuple[np.ndarray, np.ndarray] | None = None,
    reproj_check: tuple[np.ndarray, np.ndarray] | None = None,
) -> ProjectionMatches:
    """Match projected points to keypoints within their windows (one compiled call,
    ``kernels.projection``; the numpy reference is in ``tests/reference/slam_numpy.py``).

    ``u_right``: the projected right-image u; keypoints with a stereo match must agree
    within the radius.  ``ratio``: best/second-best distance ratio test (by default
    only when both are on the same level, as ORB-SLAM2 does in local-map search).
    ``angle_check``: (query keypoint angles, frame keypoint angles) for the
    rotation-histogram consistency check.  ``reproj_check``: (keypoint uv, keypoint
    1/sigma^2) -- candidates must lie within the chi2 95% bound of the projection
    (stereo when the keypoint has a right match and ``u_right`` is given; ``Fuse``).
    Each keypoint gets at most one point; matches come ordered by keypoint.
    """
    nq = len(u)
    f64 = np.float64
    zf, zi, zb = np.zeros(1, f64), np.zeros(1, np.int64), np.zeros(1, bool)
    nk = len(grid.uv)
    out_q = np.empty(min(nq, nk), np.int64)
    out_k = np.empty(min(nq, nk), np.int64)
    out_d = np.empty(min(nq, nk), np.int32)
    if nq == 0 or nk == 0:
        return ProjectionMatches(out_q, out_k, out_d)
    r = np.empty(nq)
    r[:] = radius

    def c(x, dt, default):  # contiguous arrays of one dtype: one compiled specialization
        return default if x is None else np.ascontiguousarray(x, dt)

    n = search_by_projection_kernel(
        c(grid.uv, f64, None), grid.order, grid.start, grid.ncx, grid.ncy, grid.cell,
        c(kp_octave, np.int64, None), c(kp_desc64, np.uint64, None),
        c(kp_uR, f64, zf), kp_uR is not None, c(kp_available, bool, zb), kp_available is not None,
        c(u, f64, None), c(v, f64, None), r, c(q_desc64, np.uint64, None),
        c(min_level, np.int64, zi), min_level is not None, c(max_level, np.int64, zi), max_level is not None,
        c(u_right, f64, zf), u_right is not None,
        c(reproj_check[1] if reproj_check is not None else None, f64, zf), reproj_check is not None,
        int(th_dist), float(ratio) if ratio is not None else 0.0, ratio is not None, bool(ratio_same_level_only),
        CHI2_MONO, CHI2_STEREO, out_q, out_k, out_d,
    )
    qm, km, dm = out_q[:n], out_k[:n], out_d[:n]
    if angle_check is not None and len(qm):
        qa, ka = angle_check
        ok = rotation_consistent(qa[qm] - ka[km])
        qm, km, dm = qm[ok], km[ok], dm[ok]
    return ProjectionMatches(qm, km, dm)


def keyframe_point_matches(mp, kf, target) -> tuple[np.ndarray, np.ndarray]:
    """Descriptor matches of keyframe ``kf``'s map points (of map ``mp``) to the keypoints
    of ``target`` (a frame or keyframe): nearest of two (ratio 0.7, <= TH_LOW), one point
    per keypoint, rotation consistency.  ORB-SLAM2 restricts this search with the bag of
    words' nodes; a brute-force Hamming search (one compiled call, ``kernels.hamming``,
    as cv2.batchDistance) over one keyframe's points costs about as much here.  Returns ``(target keypoint idx, point ids)``."""
    z = np.zeros(0, np.int64)
    kp_kf = np.flatnonzero(kf.point_ids >= 0)
    pts = mp.points.resolve(kf.point_ids[kp_kf])
    ok = pts >= 0
    kp_kf, pts = kp_kf[ok], pts[ok]
    if len(pts) < 10 or len(target) < 10:
        return z, z
    dnn, inn = knn_hamming(mp.points.desc[pts], target.desc, 2)
    b1, b2, best = dnn[:, 0], dnn[:, 1], inn[:, 0]
    good = (best >= 0) & (b1 <= TH_LOW) & (b1 < 0.7 * b2)
    qi, ki = np.flatnonzero(good), best[good]
    u_idx = unique_best(ki, b1[good])  # one point per keypoint
    qi, ki = qi[u_idx], ki[u_idx]
    if len(qi):
        rot = rotation_consistent(kf.angle[kp_kf[qi]] - target.angle[ki])
        qi, ki = qi[rot], ki[rot]
    return ki.astype(np.int64), pts[qi]
