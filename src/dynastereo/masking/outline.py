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

All of a frame's boxes are outlined in one compiled call (:func:`.boxkernel.outline_frame`);
the per-box numpy / OpenCV path it replaced is the tests' reference
(``tests/reference/masking_numpy.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..config import OutlineConfig
from ..datatypes import MaskMethod
from . import boxkernel as bk
from .boxkernel import fill_rows, outline_frame, peak_bins, to_bins_numpy
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
    painted: np.ndarray | None = None  # uint8 (H, W), 255 = any object, when the kernel made it

    @property
    def mask(self) -> np.ndarray:
        """uint8 mask, 255 = any object."""
        if self.painted is not None:
            return self.painted
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
    fill_rows(d, out)
    return out


def warm_up_kernels() -> None:
    """Load (or compile) the outlines' compiled kernels now, not in the first frames."""
    fill_invalid_rows(np.zeros((1, 2), np.float32))
    dominant_disparity(np.ones(3, np.float32), 1.0, weights=np.ones(3, np.float32))
    disp = np.full((24, 32), 5.0, np.float32)
    outline_objects(disp, np.array([[2.0, 2.0, 20.0, 20.0], [10.0, 4.0, 30.0, 22.0]]), disp.shape)


@dataclass(frozen=True)
class Peak:
    disparity: float  # refined (mean within the peak), pixels
    count: int  # valid pixels within the peak bins
    n_valid: int
    lo: float = 0.0  # disparity range of the peak extended over contiguous high bins
    hi: float = 0.0


_to_bins = to_bins_numpy  # (the tests' name)


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
    k, kl, kh = peak_bins(np.ascontiguousarray(u), np.float32(u.min()), w, float(near_ratio), float(extend_ratio),
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


def tolerance(peak: float, cfg: OutlineConfig) -> float:
    return max(float(cfg.peak_tolerance), float(cfg.peak_tolerance_rel) * float(peak))


#: the kernel's method codes (:mod:`.boxkernel`) as :class:`MaskMethod`
METHOD_CODES = {
    bk.EMPTY: MaskMethod.EMPTY,
    bk.OUTLINE: MaskMethod.OUTLINE,
    bk.TINY: MaskMethod.FALLBACK_TINY,
    bk.NO_DISPARITY: MaskMethod.FALLBACK_NO_DISPARITY,
    bk.SPARSE: MaskMethod.FALLBACK_SPARSE,
    bk.RANGE: MaskMethod.FALLBACK_RANGE,
    bk.NO_PEAK: MaskMethod.FALLBACK_NO_PEAK,
    bk.SMALL: MaskMethod.FALLBACK_SMALL,
}

_ELLIPSES: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def dilation_rows(r: int) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's elliptic structuring element of radius ``r`` as row spans (int64 column
    offsets ``lo[i] .. hi[i]`` around the anchor for row offset ``i - r``; ``hi < lo``: an
    empty row); empty arrays for ``r <= 0`` (no dilation).  Cached."""
    if r <= 0:
        z = np.zeros(0, np.int64)
        return z, z
    if r not in _ELLIPSES:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        lo = np.zeros(2 * r + 1, np.int64)
        hi = np.full(2 * r + 1, -1, np.int64)
        for i, row in enumerate(k):
            cols = np.flatnonzero(row)
            if cols.size:
                assert cols[-1] - cols[0] + 1 == cols.size, "the ellipse's rows are spans"
                assert cols[0] + cols[-1] == 2 * r, "the ellipse's rows are centred"
                lo[i], hi[i] = cols[0] - r, cols[-1] - r
        _ELLIPSES[r] = (lo, hi)
    return _ELLIPSES[r]


def outline_params(cfg: OutlineConfig, ground: GroundLine | None = None,
                   max_disparity: float | None = None) -> np.ndarray:
    """The outline kernel's parameters (float64, in :mod:`.boxkernel`'s ``P_*`` order)."""
    use_road = ground is not None and ground.ok and cfg.ground_removal
    p = np.zeros(bk.N_PARAMS, np.float64)
    p[bk.P_BIN_WIDTH] = cfg.bin_width
    p[bk.P_REL] = cfg.peak_tolerance_rel
    p[bk.P_NEAR] = cfg.near_peak_ratio
    p[bk.P_EXTEND] = cfg.peak_extend_ratio
    p[bk.P_TOL] = cfg.peak_tolerance
    p[bk.P_MIN_VALID] = cfg.min_valid_fraction
    p[bk.P_MIN_PIXELS] = cfg.min_box_pixels
    p[bk.P_MIN_SIDE] = cfg.min_box_side
    p[bk.P_OVERLAP] = cfg.overlap_weight
    p[bk.P_CLAIM] = cfg.claim_fraction
    p[bk.P_MIN_OUTLINE] = cfg.min_outline_fraction
    p[bk.P_GROUND_TOL] = cfg.ground_tolerance
    p[bk.P_GROUND_MAX] = cfg.ground_max_fraction
    p[bk.P_MAX_DISP] = np.nan if max_disparity is None else float(max_disparity)
    p[bk.P_FILL_HOLES] = bool(cfg.fill_holes)
    p[bk.P_LARGEST] = bool(cfg.keep_largest_component)
    p[bk.P_GROUND_AFTER] = bool(cfg.ground_after_dilate)
    p[bk.P_USE_ROAD] = bool(use_road)
    if use_road:
        p[bk.P_ROAD_SLOPE] = ground.slope  # type: ignore[union-attr]
        p[bk.P_ROAD_OFFSET] = ground.offset  # type: ignore[union-attr]
    p[bk.P_LEFT_CONTEXT] = LEFT_CONTEXT
    p[bk.P_CLAIM_MARGIN] = CLAIM_MARGIN
    p[bk.P_RANGE_MARGIN] = RANGE_MARGIN
    return p


def outline_objects(
    disp: np.ndarray,
    boxes: np.ndarray,
    image_shape: tuple[int, int],
    cfg: OutlineConfig | None = None,
    origin: tuple[int, int] = (0, 0),
    ground: GroundLine | None = None,
    max_disparity: float | None = None,
) -> OutlineResult:
    """Outline every box from the disparity, all of them in one compiled call
    (:func:`.boxkernel.outline_frame`).

    ``disp`` is float32 pixels (<= 0 invalid) of the whole image (``origin=(0, 0)``) or
    of a region whose top-left image pixel is ``origin = (x, y)``; pixels outside it count
    as invalid.  ``boxes`` are ``(N, 4)`` x1, y1, x2, y2 in image pixels.  ``ground``: the
    road's disparity line (:func:`.ground.fit_ground_line`); with ``cfg.ground_removal``
    and a reliable (``ok``) line, road pixels are removed from every object.
    ``max_disparity``: the matcher's largest disparity: a peak range reaching it (within
    ``RANGE_MARGIN``) is a box fallback (None: unknown).
    """
    cfg = cfg or OutlineConfig()
    h, w = image_shape
    rois = clip_boxes(boxes, (h, w))
    n = len(rois)
    labels = np.zeros((h, w), np.int32)
    mask = np.zeros((h, w), np.uint8)
    disparity = np.zeros(n, np.float32)
    codes = np.zeros(n, np.int64)
    lo = np.zeros(n, np.float64)
    hi = np.zeros(n, np.float64)
    pixels = np.zeros(n, np.int64)
    se_lo, se_hi = dilation_rows(int(cfg.dilate))
    outline_frame(np.ascontiguousarray(disp, np.float32), int(origin[0]), int(origin[1]),
                  np.ascontiguousarray(rois, np.int64), outline_params(cfg, ground, max_disparity),
                  bk.bin_table(cfg.bin_width if cfg.bin_width > 0 else 1.0, cfg.peak_tolerance_rel),
                  se_lo, se_hi, labels, mask, disparity, codes, lo, hi, pixels)
    methods = [METHOD_CODES[int(c)] for c in codes]
    ranges = list(zip(lo.tolist(), hi.tolist()))
    return OutlineResult(labels, disparity, methods, rois, pixels, ranges, ground, mask)


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

