"""The road in the disparity: a line in v-disparity space (ground removal for the outlines).

For a flat road and a camera looking along it, a road point seen in image row ``v`` has
disparity ``d = (fx / fy) * (B / h) * (v - v_h)``: linear in the row, with slope
``B / h`` (baseline over camera height -- 0.54 / 1.65 = 0.33 px per row for KITTI, at
any image resolution) and zero at the horizon row ``v_h``.  Objects standing on the road
touch it where their disparity equals the road's, so the road pixels inside a detected
box -- around a car, under it, between a pedestrian's legs -- share the disparity of
the object's bottom and a disparity-peak outline keeps them.  A point at disparity ``d``
in row ``v`` lies ``h * (d - d_road(v)) / d`` metres above the road: the outline drops
pixels less than ``ground_tolerance`` pixels above it (:mod:`.outline`).

:func:`road_samples` takes a coarse, cheap disparity of the image's lower part (the
road is a large smooth surface) and :func:`fit_ground_line` fits ``d = a v + c`` to it:
a v-disparity Hough vote (slopes restricted to the range a camera ``min_height ..
max_height`` metres above the road gives -- a truck filling the view, constant
disparity, is no road; votes weighted by disparity; lines with points below them
penalized: nothing is seen below the road), refined by least squares on the inliers.
A fit with too little support, or whose slope wants out of the range, is *unreliable*
and not used (``GroundLine.ok`` False, ``reason`` says why).  Vectorized numpy; about
1.2 ms for a KITTI frame, coarse disparity included.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

# Default stereo baseline (metres) when the masker is not told the rig's: KITTI's.
DEFAULT_BASELINE = 0.54


@dataclass(frozen=True)
class GroundLine:
    """The road's disparity ``d(v) = slope * v + offset`` (image rows ``v``, pixels)."""

    slope: float = 0.0  # disparity pixels per image row
    offset: float = 0.0
    ok: bool = False  # reliable: use it
    reason: str = "not-fitted"  # "ok" or why not
    inliers: int = 0  # sampled points within the tolerance of the line
    points: int = 0  # sampled valid points
    rows: int = 0  # distinct image rows (in bins of 4) holding inliers
    baseline: float = 0.0  # the rig's baseline (m) when known: gives the camera height

    @property
    def horizon(self) -> float:
        """Image row where the road's disparity is 0."""
        return -self.offset / self.slope if self.slope > 0 else float("nan")

    def at(self, rows: np.ndarray) -> np.ndarray:
        """Road disparity (float32) of image rows ``rows``."""
        return (np.asarray(rows, np.float32) * np.float32(self.slope) + np.float32(self.offset)).astype(np.float32)

    @property
    def camera_height(self) -> float:
        """Camera height over the road implied by the slope (fx = fy), metres; 0 if the
        baseline is unknown."""
        return self.baseline / self.slope if self.slope > 0 and self.baseline > 0 else 0.0

    def to_dict(self) -> dict[str, object]:
        return {"ok": self.ok, "reason": self.reason, "slope": round(self.slope, 5),
                "offset": round(self.offset, 3), "horizon": round(self.horizon, 2) if self.slope > 0 else None,
                "inliers": self.inliers, "points": self.points}


def slope_range(baseline: float, min_height: float, max_height: float, fx_over_fy: float = 1.0) -> tuple[float, float]:
    """Road slopes (px per row) for a camera ``min_height .. max_height`` m above the road."""
    return fx_over_fy * baseline / max_height, fx_over_fy * baseline / min_height


def sample_valid(disp: np.ndarray, max_points: int = 6000, row0: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Rows (image coords, ``row0`` = the array's first row) and values of a regular
    subsample of the valid (> 0) disparities: at most about ``max_points``."""
    valid = disp > 0
    n = int(np.count_nonzero(valid))
    if n == 0:
        return np.zeros(0, np.float32), np.zeros(0, np.float32)
    step = max(1, int(np.ceil(np.sqrt(n / float(max_points)))))
    sub = disp[::step, ::step]
    ys, xs = np.nonzero(sub > 0)
    return (ys * step + row0).astype(np.float32), sub[ys, xs].astype(np.float32)


def coarse_scale(width: int, min_width: int = 300) -> int:
    """The largest of 1, 2, 4 leaving the image at least ``min_width`` pixels wide."""
    s = 1
    for c in (2, 4):
        if width / c >= min_width:
            s = c
    return s


def road_samples(
    matcher,
    left_gray: np.ndarray,
    right_gray: np.ndarray,
    top_fraction: float = 0.4,
    scale: int | None = None,
    max_points: int = 3000,
) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, disparities)`` sampled from a coarse disparity of the image's lower part.

    The road is a large smooth surface: a disparity at ``scale`` (default: the coarsest
    leaving >= 300 columns -- 4 for KITTI's 1241, 2 for 640) of the rows below
    ``top_fraction * H``, full width, is enough and cheap (about 1 ms for KITTI with BM).
    Rows are the image rows of the coarse cells' centres.
    """
    h, w = left_gray.shape[:2]
    s = int(scale) if scale else coarse_scale(w)
    y0 = min(max(0, int(top_fraction * h)), h - 1)
    d = matcher.compute_coarse(left_gray, right_gray, y0, scale=s)
    row0 = (y0 - y0 % s) + (s - 1) / 2.0
    v, val = sample_valid(d, max_points)
    return (row0 + v * s).astype(np.float32), val


def _hough_vote(v: np.ndarray, d: np.ndarray, a: np.ndarray, hi: float, height: int, tol: float,
                below_weight: float, weight_by_disparity: bool) -> tuple[int, float, float]:
    """The best cell of the Hough vote (see :func:`fit_ground_line`): (slope index, the
    offset at the centre of its 2-bin window, its support: the window's votes)."""
    c = d[None, :] - a[:, None] * v[None, :]  # (K, N) offsets
    # offsets c = -a * horizon of a road seen in this image: horizon row within -H .. H
    c_min, c_max = -hi * float(height), hi * float(height)
    cb = np.floor((c - c_min) / tol).astype(np.int64)
    nb = int(np.floor((c_max - c_min) / tol)) + 2
    ok = (cb >= 0) & (cb < nb)
    k_idx = np.broadcast_to(np.arange(a.size)[:, None], cb.shape)
    wts = None
    if weight_by_disparity:
        wts = np.broadcast_to(d[None, :], cb.shape)[ok]
    votes = np.bincount((k_idx[ok] * nb + cb[ok]), weights=wts, minlength=a.size * nb).reshape(a.size, nb)
    votes = votes.astype(np.float64, copy=False)
    sm = votes.copy()
    sm[:, 1:] += votes[:, :-1]  # two adjacent bins = a window 2 tolerances wide
    if below_weight > 0:
        # votes more than 2 tolerances below the line of cell b: offset bins < b - 2
        cum = np.zeros((a.size, nb + 1))
        np.cumsum(votes, axis=1, out=cum[:, 1:])
        below = np.zeros_like(sm)
        below[:, 2:] = cum[:, :nb - 2]
        score = sm - below_weight * below
    else:
        score = sm
    k, b = np.unravel_index(int(np.argmax(score)), sm.shape)
    return int(k), c_min + float(b) * tol, float(sm[k, b])  # the window: bins b-1 and b


def _least_squares(v: np.ndarray, d: np.ndarray, a0: float, c0: float, tol: float, lo: float,
                   hi: float) -> tuple[float, float, np.ndarray, bool]:
    """Twice: least squares on the line's inliers (within ``tol``); a slope outside
    ``[lo, hi]`` keeps the Hough one (flagged).  ``(slope, offset, inliers, out of range)``."""
    sel = np.abs(d - (a0 * v + c0)) <= tol
    out_of_range = False
    for _ in range(2):
        if np.count_nonzero(sel) < 3:
            break
        vs, ds = v[sel].astype(np.float64), d[sel].astype(np.float64)
        A = np.stack([vs, np.ones_like(vs)], axis=1)
        (a1, c1), *_ = np.linalg.lstsq(A, ds, rcond=None)
        out_of_range = not (lo <= a1 <= hi)
        if out_of_range:  # the points want another slope: keep the Hough one (flagged below)
            a1 = a0
            c1 = float(np.median(ds - a0 * vs))
        a0, c0 = float(a1), float(c1)
        sel = np.abs(d - (a0 * v + c0)) <= tol
    return a0, c0, sel, out_of_range


def fit_ground_line(
    rows: np.ndarray,
    values: np.ndarray,
    slopes: tuple[float, float],
    height: int,
    tolerance: float = 1.0,
    min_inliers: int = 150,
    min_inlier_fraction: float = 0.05,
    min_rows: int = 6,
    n_slopes: int = 24,
    below_weight: float = 1.0,
    weight_by_disparity: bool = True,
) -> GroundLine:
    """Robust fit of ``d = a v + c`` with ``a`` in ``slopes`` to sampled ``(row, value)``.

    Hough vote: for each of ``n_slopes`` candidate slopes, the offsets ``c = d - a v`` are
    binned ``tolerance`` wide; each point votes with its disparity as weight (near road
    points say more than the clutter at the horizon, where everything has a small
    disparity).  A cell's score is its vote summed with its offset neighbour (a line on
    a bin edge is not split) minus ``below_weight`` times the votes more than two
    tolerances *below* the line: nothing is seen below the road, so a line through a
    car's side or a wall above the real road, which has the road's points below it,
    loses.  The best cell's inliers are fitted by least squares, twice (the second time
    on the first fit's inliers).

    The fit is reliable (``ok``) when it has at least ``min_inliers`` inliers, at least
    ``min_inlier_fraction`` of the points, inliers in at least ``min_rows`` distinct
    4-row bins (a road spans many rows; a vertical surface cut by a line does not), and
    neither the vote's best slope is a limit of the range nor the least-squares slope of
    its inliers leaves it (a road seen from a camera higher or lower than allowed is
    fitted at the range's limit).
    """
    v = np.asarray(rows, np.float32).ravel()
    d = np.asarray(values, np.float32).ravel()
    n = int(v.size)
    lo, hi = float(min(slopes)), float(max(slopes))
    if n < min_inliers:
        return GroundLine(ok=False, reason="few-points", points=n)
    tol = float(tolerance)
    a = np.linspace(lo, hi, int(n_slopes), dtype=np.float32)
    k, c0, support = _hough_vote(v, d, a, hi, height, tol, below_weight, weight_by_disparity)
    if support <= 0:
        return GroundLine(ok=False, reason="no-support", points=n)
    a0, c0, sel, out_of_range = _least_squares(v, d, float(a[k]), c0, tol, lo, hi)
    n_in = int(np.count_nonzero(sel))
    n_rows = int(np.unique((v[sel] // 4).astype(np.int64)).size) if n_in else 0
    line = GroundLine(slope=a0, offset=c0, ok=False, reason="ok", inliers=n_in, points=n, rows=n_rows)
    if n_in < min_inliers:
        return _with(line, "few-inliers")
    if n_in < min_inlier_fraction * n:
        return _with(line, "weak-support")
    if n_rows < min_rows:
        return _with(line, "few-rows")
    if out_of_range or not (lo <= a0 <= hi):
        return _with(line, "slope-out-of-range")
    if k in (0, a.size - 1):  # the vote's best slope is a limit: the road's may be beyond it
        return _with(line, "slope-at-limit")
    return GroundLine(a0, c0, True, "ok", n_in, n, n_rows)


def _with(line: GroundLine, reason: str) -> GroundLine:
    return replace(line, ok=False, reason=reason)
