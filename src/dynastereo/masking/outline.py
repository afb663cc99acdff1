"""Object outlines from the dominant disparity peak inside each detected box (thesis 3.3.3).

For every box:

1. the histogram of the valid disparities inside it -- bins ``bin_width`` wide at small
   disparities and ``peak_tolerance_rel * d`` wide for near objects, smoothed [1, 2, 1];
   road pixels (below) are left out, and pixels the box shares with other boxes weigh
   ``overlap_weight`` (a car's box reaching over the truck in front of it);
2. its dominant peak -- the highest bin, or the *nearest* local maximum at least
   ``near_peak_ratio`` as high (the detected object stands in front of the rest of its
   box) -- is the object's disparity, refined by the mean of the values in the peak; the
   accepted range is the peak +- the tolerance, extended over the contiguous bins holding
   at least ``peak_extend_ratio`` of the peak (a car seen from the side is slanted);
3. invalid disparities (no texture, occlusion) are filled along each row from their
   valid neighbours, occlusion-aware (:func:`fill_invalid_rows`, looking
   ``LEFT_CONTEXT`` columns left of the box), and the pixels in the accepted range are
   the object -- except the **road**: with a reliable road line
   (:mod:`.ground`: ``d_road(v) = a v + c`` per frame), pixels whose (measured or
   filled) disparity is less than ``ground_tolerance`` above the road's in their row are
   road (around a car, under it, between a pedestrian's legs: the same disparity as the
   object's bottom).  A line that would take more than ``ground_max_fraction`` of the
   object's own in-peak pixels does not hold there (a slope, a kerb) and is not used
   for that box;
4. its largest connected component is kept, holes are flood-filled (from the border of
   the ROI on the inverted mask) and the mask is dilated a little -- all inside the box;
   neither the filling nor the dilation brings road pixels back.

One peak, one object (:func:`_resolve_claims`): a box whose peak is a neighbouring
box's, and whose in-peak pixels lie mostly at that box (its object seen through this
box, or its disparity spilled past its edge by the matcher -- a car in the occlusion
shadow of the truck beside it), is outlined again without that peak.

The result is an instance *label image* (``int32``, 0 = none, ``i`` = object ``i``,
1-based in the order of the boxes).  Where boxes overlap, nearer objects (larger
disparity) win the shared pixels.  Boxes masked whole record why
(``ObjectMask.method``): ``box-fallback:tiny`` (fewer than ``min_box_pixels``, or a
side shorter than ``min_box_side``), ``box-fallback:no-disparity`` (fewer than
``min_valid_fraction`` of the box valid), ``box-fallback:sparse-disparity`` (fewer than
that on the object's own peak: a dark, shiny near car -- the box is still moved to the
right image by the peak's disparity), ``box-fallback:beyond-range`` (the peak's range
reaches the matcher's largest disparity: the object's nearer parts are beyond what the
matcher can measure, so its outline would keep only the farther ones), and
``box-fallback:small-outline`` (the outline covers less than ``min_outline_fraction`` of
the part of its box no nearer object takes: a detected box is mostly its object, so an
outline that small is more likely the disparity failing -- an object cut by the image
border, a near object with little texture -- than a thin object).

Everything is numpy/OpenCV on the box ROI; the only Python loops are over the boxes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..compiled import jit
from ..config import OutlineConfig
from ..datatypes import MaskMethod
from .ground import GroundLine

# A peak range ending this close (px) to the matcher's largest disparity reaches beyond it.
RANGE_MARGIN = 3.0
# Columns left of each box whose disparity the outline looks at (to tell the background
# band a near object occludes from the object itself); maskers compute disparity there too.
LEFT_CONTEXT = 48
# A box whose peak pixels lie within this many pixels of a neighbouring box holding the
# same peak gives the peak up (:func:`_resolve_claims`): about a block's spill.
CLAIM_MARGIN = 8


@dataclass
class OutlineResult:
    """Left-image outlines of N boxes."""

    labels: np.ndarray  # int32 (H, W): 0 = none, i = object i (1-based, box order)
    disparity: np.ndarray  # float32 (N,): the object's disparity in pixels, 0 = unknown
    methods: list[MaskMethod] = field(default_factory=list)
    rois: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.int32))  # (N, 4) x0 y0 x1 y1
    pixels: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (N,) pixels in labels
    ranges: list[tuple[float, float]] = field(default_factory=list)  # accepted disparity range
    ground: GroundLine | None = None  # the road line given (used only when ``ground.ok``)

    @property
    def mask(self) -> np.ndarray:
        """uint8 mask, 255 = any object."""
        return np.where(self.labels > 0, np.uint8(255), np.uint8(0))


def clip_boxes(boxes: np.ndarray, shape: tuple[int, int], margin: int = 0) -> np.ndarray:
    """Integer ROIs ``(N, 4)`` x0, y0, x1, y1 (exclusive) covering the boxes, inside the image."""
    h, w = shape
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    r = np.empty((len(b), 4), np.int64)
    r[:, 0] = np.floor(b[:, 0]) - margin
    r[:, 1] = np.floor(b[:, 1]) - margin
    r[:, 2] = np.ceil(b[:, 2]) + margin
    r[:, 3] = np.ceil(b[:, 3]) + margin
    r[:, [0, 2]] = np.clip(r[:, [0, 2]], 0, w)
    r[:, [1, 3]] = np.clip(r[:, [1, 3]], 0, h)
    return r.astype(np.int32)


def roi_disparity(disp: np.ndarray, origin: tuple[int, int], roi: tuple[int, int, int, int]) -> np.ndarray:
    """The disparity of ``roi`` (image coords) from a region array whose top-left is ``origin``.

    Parts of the ROI the region array does not cover are 0 (invalid).
    """
    ox, oy = origin
    x0, y0, x1, y1 = roi
    dh, dw = disp.shape
    sx0, sy0 = max(x0 - ox, 0), max(y0 - oy, 0)
    sx1, sy1 = min(x1 - ox, dw), min(y1 - oy, dh)
    if sx0 == x0 - ox and sy0 == y0 - oy and sx1 == x1 - ox and sy1 == y1 - oy:
        return disp[sy0:sy1, sx0:sx1]
    out = np.zeros((y1 - y0, x1 - x0), np.float32)
    if sx1 > sx0 and sy1 > sy0:
        out[sy0 + oy - y0:sy1 + oy - y0, sx0 + ox - x0:sx1 + ox - x0] = disp[sy0:sy1, sx0:sx1]
    return out


def fill_invalid_rows(d: np.ndarray) -> np.ndarray:
    """Fill invalid (<= 0) pixels along each row from the nearest valid pixels.

    A run between a farther left value ``dl`` and a nearer right value ``dr`` (the left
    edge of a near object) holds the background band the near object hides from the right
    camera, ``dr - dl`` pixels wide: those first pixels of the run take ``dl`` and the
    rest, if any, ``dr`` (the object's own textureless part).  A run whose right value is
    the farther one takes it (the usual "farther neighbour" occlusion filling).  A run
    touching an end of the row takes its only neighbour: inside a detected box that is
    mostly the object itself (a textureless car side reaching the box edge).
    """
    d = np.ascontiguousarray(d, np.float32)
    out = np.empty_like(d)
    _fill_rows(d, out)
    return out


def warm_up_kernels() -> None:
    """Load (or compile) the outlines' compiled kernels now, not in the first frames."""
    fill_invalid_rows(np.zeros((1, 2), np.float32))
    dominant_disparity(np.ones(3, np.float32), 1.0, weights=np.ones(3, np.float32))


@jit
def _fill_rows(d, out):  # pragma: no cover - compiled
    """:func:`fill_invalid_rows` into ``out``, row by row: each invalid pixel's nearest
    valid neighbours left (``lv``, 0 if none) and right (``rv``); both: the right value
    where it is the nearer one and the pixel lies beyond the band ``rv - lv`` wide that
    the near object hides, else the farther one; one: that one.  All valid or none: a
    copy."""
    h, w = d.shape
    n_valid = 0
    for y in range(h):
        for x in range(w):
            if d[y, x] > 0:
                n_valid += 1
    if n_valid == 0 or n_valid == h * w:
        out[:, :] = d
        return
    zero = np.float32(0.0)
    for y in range(h):
        # the nearest valid to the right of each pixel: a backward pass
        ri = w
        for x in range(w - 1, -1, -1):
            if d[y, x] > 0:
                ri = x
            out[y, x] = d[y, ri] if ri < w else zero  # rv, for now
        li = -1
        for x in range(w):
            v = d[y, x]
            if v > 0:
                li = x
                out[y, x] = v
                continue
            rv = out[y, x]
            lv = d[y, li] if li >= 0 else zero
            if lv > 0 and rv > 0:
                if rv > lv and not ((x - li) <= (rv - lv)):
                    out[y, x] = rv
                else:
                    out[y, x] = min(lv, rv)
            else:
                out[y, x] = max(lv, rv)


@dataclass(frozen=True)
class Peak:
    disparity: float  # refined (mean within the peak), pixels
    count: int  # valid pixels within the peak bins
    n_valid: int
    lo: float = 0.0  # disparity range of the peak extended over contiguous high bins
    hi: float = 0.0


def _to_bins(v: np.ndarray, bin_width: float, rel: float) -> np.ndarray:
    """Continuous bin coordinate: bins ``bin_width`` wide at small disparity and
    ``rel * d`` wide above ``d_c = bin_width / rel`` (log scale), joined smoothly."""
    u = v * (1.0 / bin_width)
    if rel > 0:
        dc = bin_width / rel
        far = v > dc
        if far.any():
            u = np.where(far, dc / bin_width + np.log(np.maximum(v, dc) / dc) / rel, u)
    return u


def dominant_disparity(
    values: np.ndarray,
    bin_width: float,
    rel: float = 0.0,
    near_ratio: float = 1.0,
    weights: np.ndarray | None = None,
    extend_ratio: float = 1.0,
) -> Peak | None:
    """Dominant peak of a 1-D array of valid (> 0) disparities.

    Histogram with bins ``bin_width`` wide (growing as ``rel * d`` for near, large
    disparities, so a near object's wider spread still forms one peak), smoothed with a
    [1, 2, 1] kernel so a peak split across a bin edge is not missed.  The peak is the
    highest smoothed bin -- or, with ``near_ratio < 1``, the *nearest* (largest disparity)
    local maximum at least ``near_ratio`` times as high: a detected object stands in front
    of what else its box holds.  Its value is the (weighted) mean of the values in the
    peak bin and its two neighbours.  With ``extend_ratio < 1`` the peak's range
    ``lo..hi`` grows over the contiguous bins holding at least that fraction of the
    peak's count (a slanted surface spreads over many disparities).
    """
    v = np.asarray(values, np.float32).ravel()
    if v.size == 0:
        return None
    bw = float(bin_width) if bin_width > 0 else 1.0
    u = _to_bins(v, bw, float(rel))
    w = np.zeros(0, np.float32) if weights is None else np.ascontiguousarray(weights, np.float32).ravel()
    sel = np.empty(v.size, np.bool_)
    ends = np.empty(2)  # v's min over the bin kl, its max over the bin kh (nan: none)
    k, kl, kh = _peak_bins(np.ascontiguousarray(u), np.float32(u.min()), w, float(near_ratio), float(extend_ratio),
                           sel, np.ascontiguousarray(v), ends)
    n = int(np.count_nonzero(sel))
    if weights is not None:
        d = float(np.average(v[sel], weights=np.asarray(weights)[sel] + 1e-12))
    else:
        d = float(v[sel].mean())
    lo = hi = d
    if extend_ratio < 1.0:
        if kl < k and not np.isnan(ends[0]):
            lo = float(ends[0])
        if kh > k and not np.isnan(ends[1]):
            hi = float(ends[1])
    return Peak(d, n, int(v.size), min(lo, d), max(hi, d))


@jit
def _peak_bins(u, u_min, weights, near_ratio, extend_ratio, sel, v, ends):  # pragma: no cover - compiled
    """:func:`dominant_disparity`'s histogram over the bin coordinates ``u`` (float32,
    bins from ``u_min``; ``weights``: empty or one per value): the peak bin ``k`` of the
    [1, 2, 1]-smoothed counts (the nearest local maximum at least ``near_ratio`` of the
    highest, with ``near_ratio`` < 1), the contiguous run ``kl .. kh`` of bins at least
    ``extend_ratio`` of it; in place ``sel`` (the values in bins k - 1 .. k + 1) and
    ``ends`` (the values' min over bin kl, max over bin kh; nan where empty)."""
    m = u.shape[0]
    idx = np.empty(m, np.int64)
    nb = 0
    for i in range(m):
        idx[i] = np.int64(u[i] - u_min)
        nb = max(nb, idx[i] + 1)
    counts = np.zeros(nb)
    if weights.shape[0]:
        for i in range(m):
            counts[idx[i]] += np.float64(weights[i])
    else:
        for i in range(m):
            counts[idx[i]] += 1.0
    if nb >= 3:
        sm = counts * 2.0
        for b in range(1, nb):
            sm[b] += counts[b - 1]
        for b in range(nb - 1):
            sm[b] += counts[b + 1]
    else:
        sm = counts.copy()
    k = 0
    for b in range(1, nb):
        if sm[b] > sm[k]:
            k = b
    if near_ratio < 1.0 and nb >= 3:
        top = near_ratio * sm[k]
        for b in range(nb - 1, -1, -1):
            left = sm[b - 1] if b > 0 else -1.0
            right = sm[b + 1] if b < nb - 1 else -1.0
            if sm[b] >= left and sm[b] >= right and sm[b] >= top:
                k = b
                break
    kl, kh = 0, nb - 1
    if extend_ratio < 1.0:
        th = extend_ratio * sm[k]
        for b in range(k - 1, -1, -1):
            if sm[b] < th:
                kl = b + 1
                break
        for b in range(k + 1, nb):
            if sm[b] < th:
                kh = b - 1
                break
    ends[0] = np.nan
    ends[1] = np.nan
    for i in range(m):
        sel[i] = idx[i] >= k - 1 and idx[i] <= k + 1
        if idx[i] == kl and (np.isnan(ends[0]) or v[i] < ends[0]):
            ends[0] = v[i]
        if idx[i] == kh and (np.isnan(ends[1]) or v[i] > ends[1]):
            ends[1] = v[i]
    return k, kl, kh


def tolerance(peak: float, cfg: OutlineConfig) -> float:
    return max(float(cfg.peak_tolerance), float(cfg.peak_tolerance_rel) * float(peak))


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


def outline_objects(
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


def band_for_boxes(rois: np.ndarray, shape: tuple[int, int], margin: int = 0) -> tuple[int, int, int, int] | None:
    """``(y0, y1, x0, x1)`` of the smallest image region covering all ROIs (+ margin)."""
    if len(rois) == 0:
        return None
    r = np.asarray(rois)
    keep = (r[:, 2] > r[:, 0]) & (r[:, 3] > r[:, 1])
    if not keep.any():
        return None
    r = r[keep]
    h, w = shape
    x0 = max(0, int(r[:, 0].min()) - margin)
    y0 = max(0, int(r[:, 1].min()) - margin)
    x1 = min(w, int(r[:, 2].max()) + margin)
    y1 = min(h, int(r[:, 3].max()) + margin)
    return y0, y1, x0, x1

