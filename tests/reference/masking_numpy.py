"""The per-box numpy / OpenCV masking path that :mod:`dynastereo.masking.boxkernel`
replaced (a dozen calls a box), kept as the tests' reference.

``outline_objects_numpy`` and ``transfer_labels_numpy`` are ``outline_objects`` and
``transfer_labels`` as they were before the one-call kernels (each box's disparity ROI,
histogram peak, row fill, OpenCV's connected components, flood fill and dilation; the
affine fit by ``np.linalg.lstsq`` and the paint).  ``tests/test_box_kernel.py`` compares
the kernels with them on real frames and synthetic boxes.  Nothing in ``src/`` calls them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from dynastereo.config import OutlineConfig
from dynastereo.datatypes import MaskMethod
from dynastereo.masking.ground import GroundLine
from dynastereo.masking.outline import (
    CLAIM_MARGIN,
    LEFT_CONTEXT,
    RANGE_MARGIN,
    OutlineResult,
    clip_boxes,
    dominant_disparity,
    fill_invalid_rows,
    roi_disparity,
    tolerance,
)
from dynastereo.masking.transfer import BORDER_TOUCH, MODES, TransferResult
from dynastereo.masking.boxkernel import affine_paint as _affine_paint


def _fill_holes(m: np.ndarray) -> np.ndarray:
    """Fill the holes of a binary uint8 mask (0/1): background not reachable from the border."""
    h, w = m.shape
    pad = np.zeros((h + 2, w + 2), np.uint8)
    pad[1:-1, 1:-1] = m
    ff_mask = np.zeros((h + 4, w + 4), np.uint8)
    cv2.floodFill(pad, ff_mask, (0, 0), 2)
    inner = pad[1:-1, 1:-1]
    return (inner != 2).astype(np.uint8)


def _largest_component(m: np.ndarray) -> np.ndarray:
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 2:
        return m
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return (lab == k).astype(np.uint8)


def _dilate(m: np.ndarray, r: int) -> np.ndarray:
    if r <= 0:
        return m
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate(m, k)


@dataclass
class RoiOutline:
    """One box's outline: ``mask`` (uint8 0/1, ROI-shaped) or None = the whole box."""

    mask: np.ndarray | None
    disparity: float  # the object's disparity; for fallbacks the median valid one, 0 if none
    method: MaskMethod
    lo: float = 0.0  # accepted disparity range
    hi: float = 0.0
    support: int = 0  # valid pixels measured in the range


def object_mask_in_roi(
    droi: np.ndarray,
    cfg: OutlineConfig,
    context: np.ndarray | None = None,
    road: np.ndarray | None = None,
    shared: np.ndarray | None = None,
    exclude: tuple[float, float] | None = None,
    max_disparity: float | None = None,
) -> RoiOutline:
    """The object's mask in one box ROI of the disparity (see the module docstring).

    ``context`` is the disparity of the same rows left of the box (any width, may be
    empty): it lets :func:`fill_invalid_rows` see the background beyond the box's edge.
    ``road`` is the road's disparity in each ROI row (``(h,)``, from a reliable
    :class:`~.ground.GroundLine`) or None: pixels less than ``cfg.ground_tolerance``
    above it -- measured, or filled along their row -- are road, never the object.
    ``shared`` (bool, ROI-shaped) marks pixels inside other boxes too: they weigh
    ``cfg.overlap_weight`` in the histogram (a car's box reaching over the truck in
    front of it must not take the truck's peak).  Disparities in ``exclude`` (a
    neighbour's range, see :func:`outline_objects`) count as invalid.  ``max_disparity``
    is the largest disparity the matcher can report (None: unknown): a peak range
    reaching it (within ``RANGE_MARGIN``) is a box fallback.
    """
    if exclude is not None:
        droi = np.where((droi >= exclude[0]) & (droi <= exclude[1]), np.float32(0), droi)
        if context is not None:
            context = np.where((context >= exclude[0]) & (context <= exclude[1]), np.float32(0), context)
    h, w = droi.shape
    area = h * w
    valid = droi > 0
    n_valid = int(np.count_nonzero(valid))
    med = float(np.median(droi[valid])) if n_valid else 0.0
    if area < cfg.min_box_pixels or min(h, w) < cfg.min_box_side:
        return RoiOutline(None, med, MaskMethod.FALLBACK_TINY, med, med)
    if n_valid < max(cfg.min_valid_fraction * area, 8):
        return RoiOutline(None, med, MaskMethod.FALLBACK_NO_DISPARITY, med, med)
    top = _road_top(droi, valid, road, cfg)
    sel = valid if top is None else valid & (droi >= top)
    d, lo, hi = _peak_range(droi, sel, shared, cfg)
    in_range = (droi >= lo) & (droi <= hi)
    support = int(np.count_nonzero(in_range))
    if max_disparity is not None and hi >= max_disparity - RANGE_MARGIN:
        # the object reaches nearer than the matcher sees (a car beside the rig): only its
        # farther parts have a disparity, the outline would cut it there -- mask the box
        return RoiOutline(None, d, MaskMethod.FALLBACK_RANGE, lo, hi, support)
    if support < cfg.min_valid_fraction * area:
        # too few pixels measured on the object itself (a dark, shiny near car): its
        # outline would be a guess -- mask the box, moved by the peak disparity
        return RoiOutline(None, d, MaskMethod.FALLBACK_SPARSE, lo, hi, support)
    if top is not None and cfg.ground_max_fraction < 1.0:
        # the object's own pixels the road would take: a line that does not hold here
        # (a slope, a kerb, a wrong fit) would cut the object -- then leave it alone
        on_road = np.count_nonzero(in_range & (droi < top))
        if on_road > cfg.ground_max_fraction * support:
            top = None
    m = _shape(droi, context, lo, hi, top, cfg)
    if not m.any():
        return RoiOutline(None, d, MaskMethod.FALLBACK_NO_PEAK, lo, hi, support)
    return RoiOutline(m, d, MaskMethod.OUTLINE, lo, hi, support)


def _road_top(droi: np.ndarray, valid: np.ndarray, road: np.ndarray | None, cfg: OutlineConfig) -> np.ndarray | None:
    """Per ROI row (``(h, 1)``): disparities below this are the road (or below it); None
    without a road line or when (nearly) all of the box is road-like (the line does not fit)."""
    if road is None:
        return None
    h, w = droi.shape
    top = np.asarray(road, np.float32).reshape(h, 1) + np.float32(cfg.ground_tolerance)
    if np.count_nonzero(valid & (droi >= top)) < max(cfg.min_valid_fraction * h * w, 8):
        return None
    return top


def _peak_range(droi: np.ndarray, sel: np.ndarray, shared: np.ndarray | None,
                cfg: OutlineConfig) -> tuple[float, float, float]:
    """``(peak disparity, lo, hi)``: the dominant histogram peak of ``droi[sel]`` (pixels
    shared with other boxes weigh ``overlap_weight``) and the range taken as the object."""
    weights = None
    if shared is not None and cfg.overlap_weight < 1.0:
        sh = shared[sel]
        if sh.any() and not sh.all():
            weights = np.where(sh, np.float32(cfg.overlap_weight), np.float32(1.0))
    peak = dominant_disparity(
        droi[sel],
        cfg.bin_width,
        rel=cfg.peak_tolerance_rel,
        near_ratio=cfg.near_peak_ratio,
        weights=weights,
        extend_ratio=cfg.peak_extend_ratio,
    )
    assert peak is not None
    d = peak.disparity
    tol = tolerance(d, cfg)
    return d, max(min(d - tol, peak.lo), 1e-3), max(d + tol, peak.hi)  # lo > 0: never the invalid


def _shape(droi: np.ndarray, context: np.ndarray | None, lo: float, hi: float, top: np.ndarray | None,
           cfg: OutlineConfig) -> np.ndarray:
    """The object's uint8 mask: pixels in ``[lo, hi]`` after filling invalid ones along
    their row (``context``: the rows left of the box), less the road, then the largest
    component, holes filled and dilated."""
    if context is not None and context.shape[1] > 0:
        filled = fill_invalid_rows(np.concatenate([context, droi], axis=1))[:, context.shape[1]:]
    else:
        filled = fill_invalid_rows(droi)
    keep = (filled >= lo) & (filled <= hi)
    road_px = None
    if top is not None:
        # road: measured on or below the road, or filled (along the row) from such a pixel
        # or with a value below the road (an object's value carried past its footprint)
        road_px = filled < top
        keep &= ~road_px
    m = keep.astype(np.uint8)
    if cfg.keep_largest_component:
        m = _largest_component(m)
    if cfg.fill_holes:
        m = _fill_holes(m)
        if road_px is not None:
            m[road_px] = 0  # filling must not bring the road back
    m = _dilate(m, int(cfg.dilate))
    if road_px is not None and cfg.ground_after_dilate:
        m[road_px] = 0
    return m


def outline_objects_numpy(
    disp: np.ndarray,
    boxes: np.ndarray,
    image_shape: tuple[int, int],
    cfg: OutlineConfig | None = None,
    origin: tuple[int, int] = (0, 0),
    ground: GroundLine | None = None,
    max_disparity: float | None = None,
) -> OutlineResult:
    """Outline every box from the disparity.

    ``disp`` is float32 pixels (<= 0 invalid) of the whole image (``origin=(0, 0)``) or
    of a region whose top-left image pixel is ``origin = (x, y)``; pixels outside it count
    as invalid.  ``boxes`` are ``(N, 4)`` x1, y1, x2, y2 in image pixels.  ``ground``: the
    road's disparity line (:func:`.ground.fit_ground_line`); with ``cfg.ground_removal``
    and a reliable (``ok``) line, road pixels are removed from every object.
    ``max_disparity``: the matcher's largest disparity (see :func:`object_mask_in_roi`).
    """
    cfg = cfg or OutlineConfig()
    use_road = ground is not None and ground.ok and cfg.ground_removal
    h, w = image_shape
    rois = clip_boxes(boxes, (h, w))
    n = len(rois)
    cover = None  # how many boxes cover each pixel
    if n > 1 and cfg.overlap_weight < 1.0:
        cover = np.zeros((h, w), np.uint16)
        for x0, y0, x1, y1 in rois:
            cover[y0:y1, x0:x1] += 1
    labels = np.zeros((h, w), np.int32)
    disparity = np.zeros(n, np.float32)
    methods: list[MaskMethod] = [MaskMethod.EMPTY] * n
    masks: list[np.ndarray | None] = [None] * n
    ranges: list[tuple[float, float]] = [(0.0, 0.0)] * n
    inputs: list[tuple | None] = [None] * n
    results: list[RoiOutline | None] = [None] * n
    for i in range(n):
        x0, y0, x1, y1 = (int(v) for v in rois[i])
        if x1 <= x0 or y1 <= y0:
            continue
        cx0 = max(0, x0 - LEFT_CONTEXT)
        inputs[i] = (
            roi_disparity(disp, origin, (x0, y0, x1, y1)), cfg,
            roi_disparity(disp, origin, (cx0, y0, x0, y1)) if cx0 < x0 else None,
            ground.at(np.arange(y0, y1)) if use_road else None,  # type: ignore[union-attr]
            cover[y0:y1, x0:x1] > 1 if cover is not None else None,
        )
        results[i] = object_mask_in_roi(*inputs[i], max_disparity=max_disparity)
    if n > 1 and cfg.claim_fraction < 1.0:
        _resolve_claims(rois, inputs, results, cfg, max_disparity)
    if cfg.min_outline_fraction > 0:
        _small_outlines_to_boxes(rois, results, cfg.min_outline_fraction)
    for i, r in enumerate(results):
        if r is not None:
            masks[i], disparity[i], methods[i], ranges[i] = r.mask, r.disparity, r.method, (r.lo, r.hi)
    # Paint far to near so nearer objects win overlaps; whole-box fallbacks first.
    order = sorted(
        (i for i in range(n) if methods[i] != MaskMethod.EMPTY),
        key=lambda i: (masks[i] is not None, float(disparity[i])),
    )
    for i in order:
        x0, y0, x1, y1 = (int(v) for v in rois[i])
        view = labels[y0:y1, x0:x1]
        if masks[i] is None:
            view[...] = i + 1
        else:
            view[masks[i] > 0] = i + 1
    pixels = np.zeros(n, np.int64)
    for i in range(n):
        x0, y0, x1, y1 = (int(v) for v in rois[i])
        if x1 > x0 and y1 > y0:
            pixels[i] = int(np.count_nonzero(labels[y0:y1, x0:x1] == i + 1))
    return OutlineResult(labels, disparity, methods, rois, pixels, ranges, ground)


def _resolve_claims(
    rois: np.ndarray, inputs: list, results: list, cfg: OutlineConfig, max_disparity: float | None = None
) -> None:
    """One disparity peak, one object.  Boxes ``i`` and ``j`` holding the same peak: when
    more than ``cfg.claim_fraction`` of ``i``'s in-peak pixels lie in ``j``'s box (grown
    by ``CLAIM_MARGIN`` px) -- ``j``'s object seen through ``i``'s box, or its disparity
    spilled past its edge by the matcher (a car in the occlusion shadow of the truck
    beside it) -- and a smaller fraction of ``j``'s in-peak pixels lie in ``i``'s, the
    peak is ``j``'s: ``i`` is outlined again without it.  Decided on the first outlines
    (no chains); in place; a loop over the handful of boxes.
    """
    n = len(results)
    inside = np.zeros((n, n))  # inside[i, j]: fraction of i's in-peak pixels in j's grown box
    for i in range(n):
        ri = results[i]
        if ri is None or ri.support <= 0:
            continue
        x0, y0, x1, y1 = (int(v) for v in rois[i])
        droi = inputs[i][0]
        for j in range(n):
            rj = results[j]
            if j == i or rj is None or rj.support <= 0:
                continue
            if abs(ri.disparity - rj.disparity) > max(tolerance(ri.disparity, cfg), tolerance(rj.disparity, cfg)):
                continue
            jx0, jy0, jx1, jy1 = (int(v) for v in rois[j])
            ax0, ax1 = max(jx0 - CLAIM_MARGIN, x0), min(jx1 + CLAIM_MARGIN, x1)
            ay0, ay1 = max(jy0 - CLAIM_MARGIN, y0), min(jy1 + CLAIM_MARGIN, y1)
            if ax1 <= ax0 or ay1 <= ay0:
                continue
            near_j = droi[ay0 - y0:ay1 - y0, ax0 - x0:ax1 - x0]
            inside[i, j] = np.count_nonzero((near_j >= ri.lo) & (near_j <= ri.hi)) / ri.support
    for i in range(n):
        cand = [j for j in range(n) if inside[i, j] > cfg.claim_fraction and inside[j, i] < inside[i, j]]
        if cand:
            j = max(cand, key=lambda k: inside[i, k])
            rj = results[j]
            results[i] = object_mask_in_roi(*inputs[i], exclude=(rj.lo, rj.hi), max_disparity=max_disparity)


def _small_outlines_to_boxes(rois: np.ndarray, results: list, fraction: float) -> None:
    """Outlines covering less than ``fraction`` of the part of their box that no nearer
    object takes (its outline, or its whole box for a fallback) become box fallbacks
    (``MaskMethod.FALLBACK_SMALL``), in place: a detected box is mostly its object, so a
    much smaller outline is the disparity failing (an object cut by the image border, a
    near one with little texture) rather than a thin object.  A loop over the handful of
    boxes."""
    n = len(results)
    small = []
    for i in range(n):
        ri = results[i]
        if ri is None or ri.mask is None:
            continue
        x0, y0, x1, y1 = (int(v) for v in rois[i])
        taken = np.zeros((y1 - y0, x1 - x0), bool)  # by nearer objects
        for j in range(n):
            rj = results[j]
            if j == i or rj is None or rj.disparity <= ri.disparity:
                continue
            jx0, jy0, jx1, jy1 = (int(v) for v in rois[j])
            ax0, ax1, ay0, ay1 = max(x0, jx0), min(x1, jx1), max(y0, jy0), min(y1, jy1)
            if ax1 <= ax0 or ay1 <= ay0:
                continue
            sub = taken[ay0 - y0:ay1 - y0, ax0 - x0:ax1 - x0]
            if rj.mask is None:
                sub[...] = True
            else:
                sub |= rj.mask[ay0 - jy0:ay1 - jy0, ax0 - jx0:ax1 - jx0] > 0
        free = taken.size - int(np.count_nonzero(taken))
        if np.count_nonzero((ri.mask > 0) & ~taken) < fraction * free:
            small.append(i)
    for i in small:  # decided on the outlines as they were: no order dependence
        ri = results[i]
        results[i] = RoiOutline(None, ri.disparity, MaskMethod.FALLBACK_SMALL, ri.lo, ri.hi, ri.support)


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


def transfer_labels_numpy(
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
