"""Move each left-image object mask into the right image by its own disparity.

A left pixel ``(x, y)`` with disparity ``d`` is seen at ``(x - d, y)`` in the right image
(thesis 3.3.3).  Forward-warping every pixel by its own noisy disparity leaves gaps and
ragged edges, so each object is moved by a *model* of its disparity and the right mask is
built by *backward* sampling (every right pixel asks which left pixel it comes from), which
leaves no gaps by construction:

* ``rigid``: the object's peak disparity, rounded to whole pixels -- a pure shift, exact
  for a fronto-parallel object (a car seen from behind) and for whole-box fallbacks;
* ``affine``: ``d(x, y) = a + b x + c y`` least-squares fitted to the object's valid
  disparities within its peak range (a car seen from the side: its disparity changes
  along it); the right pixel ``x_r`` then comes from ``x_l = (x_r + a + c y) / (1 - b)``.
  A poor fit (few pixels, implausible slope) falls back to ``rigid``.

Objects with unknown disparity (no valid pixel in the box) are swept over the matcher's
whole disparity range: the right mask is the union of all the shifts, wide but safe.
Objects partly leaving the right image (``x - d < 0``) are clipped there; objects cut by
the *left* image's right border continue in the right image (which sees ``d`` more
columns there), so their rows touching that border are extended to the right border.  Where objects
overlap in the right image the nearer one (larger disparity) wins, as in the left.  With
``occluded`` an object hidden in part behind a nearer one in the left image also covers
the band the right camera sees past the nearer object's right edge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..compiled import jit
from ..config import TRANSFER_MODES
from .outline import roi_disparity

MODES = TRANSFER_MODES  # masker.outline.transfer (config)
# A box ending this close to the right border is taken as cut by it.
BORDER_TOUCH = 3


@dataclass
class TransferResult:
    labels: np.ndarray  # int32 (H, W) right image: 0 = none, i = object i
    pixels: np.ndarray  # (N,) pixels of each object in ``labels``
    models: list[tuple[float, float, float]] = field(default_factory=list)  # (a, b, c) per object


def _sweep_rows(m: np.ndarray, k: int) -> np.ndarray:
    """Row-wise union of ``m`` shifted left by ``0 .. k-1`` columns, on a canvas ``k - 1``
    columns wider whose column ``j`` is ``m``'s column ``j - (k - 1)``:
    ``out[:, j] = any(m[:, j - t] for t in 0..k-1)`` (prefix sums, no loop)."""
    h, w = m.shape
    pad = np.zeros((h, w + 2 * (k - 1)), np.int32)
    pad[:, k - 1:k - 1 + w] = m
    c = np.concatenate([np.zeros((h, 1), np.int64), np.cumsum(pad, axis=1)], axis=1)
    # window sum over columns j .. j + k - 1 of pad, for j in 0 .. w + k - 2
    win = c[:, k:k + w + k - 1] - c[:, 0:w + k - 1]
    return win > 0


def fit_affine_disparity(
    d: np.ndarray, sel: np.ndarray, x0: int, y0: int, max_points: int = 4000
) -> tuple[float, float, float, int] | None:
    """Least-squares ``d = a + b x + c y`` (image coords) over the pixels ``sel`` of ROI ``d``."""
    ys, xs = np.nonzero(sel)
    n = ys.size
    if n < 30:
        return None
    if n > max_points:
        step = n // max_points + 1
        ys, xs = ys[::step], xs[::step]
    z = d[ys, xs].astype(np.float64)
    A = np.stack([np.ones_like(z), (xs + x0).astype(np.float64), (ys + y0).astype(np.float64)], axis=1)
    sol, *_ = np.linalg.lstsq(A, z, rcond=None)
    return float(sol[0]), float(sol[1]), float(sol[2]), int(n)


def transfer_labels(
    left_labels: np.ndarray,
    disparities: np.ndarray,
    rois: np.ndarray,
    *,
    mode: str = "rigid",
    disp: np.ndarray | None = None,
    origin: tuple[int, int] = (0, 0),
    ranges: list[tuple[float, float]] | None = None,
    sweep: tuple[float, float] = (0.0, 95.0),
    max_slope: float = 0.25,
    occluded: bool = False,
    occluded_margin: float = 1.0,
) -> TransferResult:
    """Right-image label image from the left one.

    ``disparities[i]`` is object ``i+1``'s disparity (pixels; ``<= 0`` unknown -> swept
    over ``sweep = (dmin, dmax)``).  ``rois[i]`` is its left box ROI (x0, y0, x1, y1), within
    which its label pixels lie.  ``mode="affine"`` needs the disparity ``disp`` (region
    array with top-left ``origin``) and optionally each object's accepted disparity range
    ``ranges[i] = (lo, hi)`` used to select the pixels to fit.

    ``occluded``: an object partly hidden in the left image behind a nearer object (larger
    disparity, by more than ``occluded_margin`` px) is seen further in the right image --
    the right camera looks past the nearer object's right edge.  Its box's pixels the
    nearer object covers are moved with it, so that band, ``d_near - d`` pixels wide, is
    masked too (the nearer object, painted later, keeps its own pixels): a car behind a
    truck, a pedestrian behind another.
    """
    if mode not in MODES:
        raise ValueError(f"transfer mode must be one of {MODES}, got {mode!r}")
    h, w = left_labels.shape
    n = len(rois)
    right = np.zeros((h, w), np.int32)
    models: list[tuple[float, float, float]] = [(float(disparities[i]), 0.0, 0.0) for i in range(n)]
    rects: list[tuple[int, int, int, int]] = [(0, 0, 0, 0)] * n
    order = sorted(range(n), key=lambda i: float(disparities[i]))
    label_disp = np.concatenate([[0.0], np.asarray(disparities, np.float64)]) if occluded else None
    for i in order:
        roi = tuple(int(v) for v in rois[i])
        x0, y0, x1, y1 = roi
        if x1 <= x0 or y1 <= y0:
            continue
        lab = left_labels[y0:y1, x0:x1]
        own = lab == i + 1
        if not own.any():
            continue
        d = float(disparities[i])
        m = own
        if label_disp is not None and d > 0:
            # the pixels of its box a nearer object covers in the left image may hide it;
            # moved with it, they give the band the right camera sees past the nearer
            # object's right edge (the nearer object, painted later, keeps its own pixels)
            hidden = label_disp[lab] > d + occluded_margin
            if hidden.any():
                m = own | hidden
        if d <= 0:
            rects[i], models[i] = _paint_swept(right, m, x0, y0, sweep, i + 1), (0.0, 0.0, 0.0)
            continue
        model = None
        if mode == "affine" and disp is not None:
            model = _affine_model(disp, origin, roi, own, None if ranges is None else ranges[i], max_slope)
        if model is None:
            rects[i], models[i] = _paint_rigid(right, m, own, roi, d, i + 1)
        else:
            rects[i], models[i] = _paint_affine(right, m, own, roi, model, i + 1), model
    pixels = np.zeros(n, np.int64)
    for i, (rx0, ry0, rx1, ry1) in enumerate(rects):
        if rx1 > rx0:
            pixels[i] = int(np.count_nonzero(right[ry0:ry1, rx0:rx1] == i + 1))
    return TransferResult(right, pixels, models)


def _paint_swept(right: np.ndarray, m: np.ndarray, x0: int, y0: int, sweep: tuple[float, float],
                 value: int) -> tuple[int, int, int, int]:
    """Unknown disparity: ``m`` (ROI at x0, y0) swept over the whole range ``sweep``."""
    dmin, dmax = int(np.floor(max(sweep[0], 0.0))), int(np.ceil(sweep[1]))
    k = dmax - dmin + 1
    wide = _sweep_rows(m, k)  # canvas column j <-> left column x0 - (k - 1) + j
    return _paint(right, wide, x0 - (k - 1) - dmin, y0, value)


def _affine_model(disp: np.ndarray, origin: tuple[int, int], roi: tuple[int, int, int, int], own: np.ndarray,
                  rng: tuple[float, float] | None, max_slope: float) -> tuple[float, float, float] | None:
    """``(a, b, c)`` of ``d = a + b x + c y`` fitted to the object's valid disparities
    (within its peak range ``rng``); None for a poor fit (few pixels, a slope beyond
    ``max_slope``)."""
    x0, y0, x1, y1 = roi
    droi = roi_disparity(disp, origin, roi)
    sel = own & (droi > 0)
    if rng is not None:
        lo, hi = rng
        sel &= (droi >= lo) & (droi <= hi)
    fit = fit_affine_disparity(droi, sel, x0, y0)
    if fit is None:
        return None
    a, b, c, _ = fit
    return (a, b, c) if abs(b) <= max_slope and abs(c) <= max_slope else None


def _paint_rigid(right: np.ndarray, m: np.ndarray, own: np.ndarray, roi: tuple[int, int, int, int], d: float,
                 value: int) -> tuple[tuple[int, int, int, int], tuple[float, float, float]]:
    """``m`` shifted by the whole-pixel disparity; (painted rect, model)."""
    x0, y0, x1, y1 = roi
    w = right.shape[1]
    s = int(round(d))
    rect = _paint(right, m, x0 - s, y0, value)
    if x1 >= w - BORDER_TOUCH:
        rect = _extend_to_border(right, own[:, -1], y0, np.full(y1 - y0, x1 - s), value, rect)
    return rect, (float(s), 0.0, 0.0)


def _paint_affine(right: np.ndarray, m: np.ndarray, own: np.ndarray, roi: tuple[int, int, int, int],
                  model: tuple[float, float, float], value: int) -> tuple[int, int, int, int]:
    """``m`` moved by the affine disparity model, sampled backwards from the right image."""
    x0, y0, x1, y1 = roi
    w = right.shape[1]
    a, b, c = model
    rect = _affine_paint(right, np.ascontiguousarray(m), x0, y0, x1, y1, float(a), float(b), float(c), int(value))
    if x1 >= w - BORDER_TOUCH:
        ys = np.arange(y0, y1, dtype=np.float64)
        start = np.rint((x1 - 1) - (a + b * (x1 - 1) + c * ys)).astype(np.int64) + 1
        rect = _extend_to_border(right, own[:, -1], y0, start, value, rect)
    return rect


def warm_up_kernels() -> None:
    """Load (or compile) the transfer's compiled kernel now, not in the first frames."""
    _paint_affine(np.zeros((2, 8), np.int32), np.ones((1, 1), bool), np.ones((1, 1), bool), (0, 0, 1, 1),
                  (1.0, 0.0, 0.0), 1)


@jit
def _affine_paint(right, m, x0, y0, x1, y1, a, b, c, value):  # pragma: no cover - compiled
    """:func:`_paint_affine`'s sampling and painting in one pass: the right image's columns
    the ROI's corners map to (a column's margin either side), each right pixel sampled
    back in ``m`` at ``rint((x + a + c y) / (1 - b))``; ``right`` painted with ``value``
    where that is set; returns the painted rectangle as :func:`_paint` does (the sampled
    block clipped to the image; (0, 0, 0, 0) when outside it)."""
    h, w = right.shape
    lo, hi = np.inf, -np.inf
    for xc in (x0, x1 - 1):
        for yc in (y0, y1 - 1):
            xr = xc - (a + b * xc + c * yc)
            lo, hi = min(lo, xr), max(hi, xr)
    rx0 = int(np.floor(lo)) - 1
    rx1 = int(np.ceil(hi)) + 2
    cx0, cy0 = max(rx0, 0), max(y0, 0)
    cx1, cy1 = min(rx1, w), min(y1, h)
    if cx1 <= cx0 or cy1 <= cy0:
        return (0, 0, 0, 0)
    mw = x1 - x0
    for y in range(cy0, cy1):
        c_y = c * np.float64(y)
        for x in range(cx0, cx1):
            xl = np.int64(np.rint(((np.float64(x) + a) + c_y) / (1.0 - b))) - x0  # numpy's order of the sums
            if 0 <= xl < mw and m[y - y0, xl]:
                right[y, x] = value
    return (cx0, cy0, cx1, cy1)


def _extend_to_border(
    labels: np.ndarray, rows: np.ndarray, y0: int, start: np.ndarray, value: int,
    rect: tuple[int, int, int, int],
) -> tuple[int, int, int, int]:
    """An object cut by the left image's right border continues, in the right image,
    up to the right border: paint ``labels[y0 + r, start[r]:]`` for the rows ``r`` where the
    object touches the border.  Returns ``rect`` grown to cover what was painted."""
    h, w = labels.shape
    r = np.flatnonzero(rows)
    if r.size == 0:
        return rect
    st = np.clip(start[r], 0, w)
    cols = np.arange(w)[None, :]
    sel = cols >= st[:, None]
    block = labels[y0 + r]
    block[sel] = value
    labels[y0 + r] = block
    x0 = int(st.min())
    if rect[2] <= rect[0]:
        return (x0, y0 + int(r.min()), w, y0 + int(r.max()) + 1)
    return (min(rect[0], x0), min(rect[1], y0 + int(r.min())), w, max(rect[3], y0 + int(r.max()) + 1))


def _paint(labels: np.ndarray, m: np.ndarray, x0: int, y0: int, value: int) -> tuple[int, int, int, int]:
    """``labels[y0:, x0:][m] = value`` with ``m`` clipped to the image; returns the
    painted rectangle (x0, y0, x1, y1), empty when ``m`` falls outside the image."""
    h, w = labels.shape
    mh, mw = m.shape
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x0 + mw, w), min(y0 + mh, h)
    if cx1 <= cx0 or cy1 <= cy0:
        return (0, 0, 0, 0)
    sub = m[cy0 - y0:cy1 - y0, cx0 - x0:cx1 - x0]
    labels[cy0:cy1, cx0:cx1][sub] = value
    return (cx0, cy0, cx1, cy1)
