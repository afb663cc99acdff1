"""The objects' own disparity: block matching with a smaller block inside each outline.

The masks want a 15-px matching block (the outline's dominant peak and the motion test's
per-object disparity are steadier with it); an object's *position* wants a smaller one: on
the synthetic scenes with exact object positions, the same outlines with StereoBM's 11-px
values instead of its 15-px ones place the objects 2-4 cm better (development seeds' runs
0.255 m instead of 0.273 m), while the masks and the motion test made from an 11-px disparity get
worse (the motion test's decisions on ``mixed`` 0.911 instead of 0.955).  A second matcher pass over
the frame costs more than the objects' budget, so this module matches each outline's pixels
again, compiled, in one call a frame, searching only a window around the disparities the
masker found there: ``[p2 - 2, p98 + 2]`` of the outline's disparities, at least 16
disparities wide (an object's surface spans a few pixels of disparity; the window keeps the
uniqueness test meaningful).

It is StereoBM's matching, restricted to the window: x-Sobel prefilter capped at
``pre_filter_cap``, SAD over ``block`` x ``block``, BM's uniqueness test (no other
disparity outside the best's neighbours within ``uniqueness_ratio`` % of its cost), BM's
sub-pixel step (the equiangular fit BM uses, not a parabola), the left-right check
(``disp12_max_diff``) among the box's own pixels and the speckle filter
(``speckle_window_size``, ``speckle_range`` in 1/16 px, as BM applies them) over the box.
All of them matter: replayed over the development seeds' masks, a plain SAD search with a
parabola made the positions worse (0.290-0.300 m against 0.273), the speckle filter alone is
worth 4 cm.  Pixels that fail a check get no disparity (0), as BM's do.

What is matched: the outlines in boxes of at most ``max_area`` pixels (the configuration's:
20 of the masker's blocks -- a larger object gains nothing from a smaller block, and the
large boxes were most of the cost), on about ``samples`` (1,500) pixels of a box at most (a
larger box on every st-th row and column, each pixel taking its sample's value; the speckle
filter's region size and range follow the grid; 2,000 cost 0.03-0.06 ms a frame more for
the same positions, development seeds replayed: 0.268 m both), within a frame's budget: the
boxes smallest first while their areas with the block's margin add up to at most
``FRAME_BUDGET`` (20,000) pixels, the larger ones beyond keeping the masker's disparity -- on
the development seeds' crossing scenes the median frame's boxes add up to 17,000 px and the
90th percentile's to 34,000; with the budget the positions came out 0.264 m against 0.267
(runs' median, replayed) and the dense held-out scenes' stage 0.77-0.83 ms instead of 0.95-1.05 ms.  An
outline matched on fewer than 30 % of its pixels keeps the masker's disparity: the objects'
stage would not measure it otherwise (``objects.world.MIN_VALID_FRACTION``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..compiled import jit
from ..config import StereoConfig
from ..masking.disparity import MatcherParams, params_at_scale

if TYPE_CHECKING:
    from ..config import ObjectsConfig

__all__ = ["ObjectStereo", "object_disparity"]

INVALID = -1  # a box pixel without a disparity (the crop's int16 disparities, 1/16 px)
HIST_BIN = 0.25  # px: the window's percentiles from a histogram of the outline's disparities
HIST_BINS = 1024  # up to 256 px
WINDOW_P = 0.02  # the window: the outline's 2nd-98th percentile disparities ...
WINDOW_MARGIN = 2  # ... widened by this many pixels on each side
WINDOW_MIN = 16  # disparities searched at least (a multiple of 16 as BM's)
MIN_PIXELS = 10  # an outline with fewer disparities keeps the masker's
SAMPLES = 1500  # pixels matched in a box at most, about (a larger box: every st-th row and column)
KEEP_FRACTION = 0.3  # matched on fewer of an outline's pixels: the masker's kept (objects.MIN_VALID_FRACTION)
MAX_BOX_BLOCKS = 20  # a box larger than this many of the masker's blocks keeps the masker's disparity
FRAME_BUDGET = 20000  # px a frame: boxes matched smallest first while their areas (with the block's margin) fit


@jit
def _prefilter(img, y0, y1, x0, x1, cap, out):
    """BM's x-Sobel prefilter of ``img``'s rows y0..y1, columns x0..x1 (outside the image:
    the border pixel), capped at +-cap and shifted by cap (0..2cap) into ``out``."""
    H, W = img.shape
    fcap = np.float32(cap)
    xa = min(max(x0, 1), x1)  # columns xa..xb have both neighbours inside the image
    xb = max(min(x1, W - 1), xa)
    for y in range(y0, y1):
        r0 = img[min(max(y - 1, 0), H - 1)]
        r1 = img[min(max(y, 0), H - 1)]
        r2 = img[min(max(y + 1, 0), H - 1)]
        o = out[y - y0]
        mid = o[xa - x0:xb - x0]
        # the interior as slices: indices from 0 (no negative-index wrap test), vectorised
        a0, b0 = r0[xa + 1:xb + 1], r0[xa - 1:xb - 1]
        a1, b1 = r1[xa + 1:xb + 1], r1[xa - 1:xb - 1]
        a2, b2 = r2[xa + 1:xb + 1], r2[xa - 1:xb - 1]
        for i in range(xb - xa):  # float32: exact for these integers, twice the lanes of numba's int64
            v = (np.float32(a0[i]) - np.float32(b0[i]) + np.float32(2.0) * (np.float32(a1[i]) - np.float32(b1[i]))
                 + np.float32(a2[i]) - np.float32(b2[i]))
            mid[i] = min(max(v, -fcap), fcap) + fcap
        for x in range(x0, x1):  # the columns at or beyond the image's sides
            if xa <= x < xb:
                continue
            a = min(max(x + 1, 0), W - 1)
            b = min(max(x - 1, 0), W - 1)
            v = (np.int32(r0[a]) - np.int32(r0[b]) + 2 * (np.int32(r1[a]) - np.int32(r1[b]))
                 + np.int32(r2[a]) - np.int32(r2[b]))
            o[x - x0] = min(max(v, -cap), cap) + cap


@jit
def _window(labels, disp, k, x0, y0, x1, y1, step, hist):
    """(lo, n): the disparities to search for object ``k`` (label ``k + 1``) in its box
    (every step-th row and column of it), or n = 0 when its outline has fewer than
    MIN_PIXELS disparities there."""
    hist[:] = 0
    total = 0
    for y in range(y0, y1, step):
        lab = labels[y, x0:x1]  # indices from 0: no negative-index wrap test
        dis = disp[y, x0:x1]
        for i in range(0, x1 - x0, step):
            if lab[i] == k + 1:
                d = dis[i]
                if d > 0.0:
                    b = min(int(d / HIST_BIN), HIST_BINS - 1)
                    hist[b] += 1
                    total += 1
    if total < MIN_PIXELS:
        return 0, 0
    lo_rank = WINDOW_P * (total - 1)
    hi_rank = (1.0 - WINDOW_P) * (total - 1)
    acc = 0
    b_lo = -1
    b_hi = HIST_BINS - 1
    for b in range(HIST_BINS):
        acc += hist[b]
        if b_lo < 0 and acc > lo_rank:
            b_lo = b
        if acc > hi_rank:
            b_hi = b
            break
    lo = max(0, int(np.floor(b_lo * HIST_BIN)) - WINDOW_MARGIN)
    hi = int(np.ceil((b_hi + 1) * HIST_BIN)) + WINDOW_MARGIN
    n = max(WINDOW_MIN, ((hi - lo + 1 + 15) // 16) * 16)
    return lo, n


@jit
def _match_box(L, R, labels, disp, k, x0, y0, x1, y1, lo, n, block, cap, uniq, lr_max, spk_size, spk_diff, st,
               out, parent, count):
    """Object k's box: BM over the window lo..lo+n-1, checks as BM's; writes its outline's
    pixels into ``out`` (px; 0: a check failed).  Returns the number of pixels matched, or -1
    when fewer than KEEP_FRACTION of the outline's pixels were (the masker's values kept)."""
    h = block // 2
    bw = x1 - x0
    bh = y1 - y0
    cw = bw + 2 * h
    # float32 throughout the sums: exact for these integers (< 2^24) and, unlike numba's
    # int32 arithmetic (widened to int64), kept at the vector width
    lc = np.empty((bh + 2 * h, cw), np.float32)
    rc = np.empty((bh + 2 * h, cw + n - 1), np.float32)
    _prefilter(L, y0 - h, y1 + h, x0 - h, x1 + h, cap, lc)
    _prefilter(R, y0 - h, y1 + h, x0 - h - (lo + n - 1), x1 + h - lo, cap, rc)
    col = np.zeros((cw, n), np.float32)
    sad = np.empty(n, np.float32)
    gh = (bh + st - 1) // st
    gw = (bw + st - 1) // st
    dc = np.empty((gh, gw), np.int32)  # every st-th row and column's disparity * 16 (INVALID: none)
    cost = np.empty(gw, np.float32)
    r_cost = np.empty(bw + n, np.float32)
    r_disp = np.empty(bw + n, np.int32)
    # column sums over the first block of rows
    # (index j of ``col`` / ``sad`` is disparity lo + n - 1 - j: the right pixels in
    # increasing order, so the inner loops run over contiguous memory and vectorise)
    for r in range(block):
        for i in range(cw):
            a = lc[r, i]
            for j in range(n):
                col[i, j] += abs(a - rc[r, i + j])
    for yy in range(bh):
        if yy > 0:
            ra = yy + 2 * h
            rs = yy - 1
            for i in range(cw):
                a = lc[ra, i]
                s = lc[rs, i]
                for j in range(n):
                    col[i, j] += abs(a - rc[ra, i + j]) - abs(s - rc[rs, i + j])
        if yy % st != 0:
            continue
        gy = yy // st
        sad[:] = 0
        for i in range(block):
            for j in range(n):
                sad[j] += col[i, j]
        for xo in range(bw):
            if xo > 0:
                for j in range(n):
                    sad[j] += col[xo + 2 * h, j] - col[xo - 1, j]
            if xo % st != 0:
                continue
            gx = xo // st
            # the least cost: eight independent chains (n is a multiple of 16; one chain
            # of dependent min's waits on each one's latency), then its first index
            m0, m1, m2, m3 = sad[0], sad[1], sad[2], sad[3]
            m4, m5, m6, m7 = sad[4], sad[5], sad[6], sad[7]
            for j in range(8, n, 8):
                m0 = min(m0, sad[j])
                m1 = min(m1, sad[j + 1])
                m2 = min(m2, sad[j + 2])
                m3 = min(m3, sad[j + 3])
                m4 = min(m4, sad[j + 4])
                m5 = min(m5, sad[j + 5])
                m6 = min(m6, sad[j + 6])
                m7 = min(m7, sad[j + 7])
            best = min(min(min(m0, m1), min(m2, m3)), min(min(m4, m5), min(m6, m7)))
            jb = 0
            while sad[jb] != best:
                jb += 1
            ok = True
            if uniq > 0:
                ib = np.int32(best)
                thresh = np.float32(ib + (ib * uniq) // 100)
                below = 0
                for j in range(n):
                    below += sad[j] <= thresh
                for j in range(max(jb - 1, 0), min(jb + 2, n)):
                    below -= sad[j] <= thresh
                ok = below == 0
            D = lo + n - 1 - jb
            if D > x0 + xo:  # a match outside the right image
                ok = False
            if not ok:
                dc[gy, gx] = INVALID
                continue
            p = sad[jb + 1] if jb < n - 1 else sad[n - 2]  # the cost one disparity lower (BM mirrors at the ends)
            q = sad[jb - 1] if jb > 0 else sad[1]  # ... one higher
            pi = np.int32(p)
            qi = np.int32(q)
            den = pi + qi - 2 * np.int32(best) + abs(pi - qi)
            frac = int(((pi - qi) * 256) / den) if den != 0 else 0  # C's division: toward zero
            dc[gy, gx] = (D * 256 + frac + 15) >> 4
            cost[gx] = best
        # left-right check among the row's pixels: the right pixel each one matched keeps
        # its cheapest left pixel's disparity (BM's validateDisparity)
        if lr_max >= 0:
            r_cost[:] = np.inf
            r_disp[:] = -1
            for gx in range(gw):
                d16 = dc[gy, gx]
                if d16 == INVALID:
                    continue
                c = cost[gx]
                xo = gx * st
                for d in ((d16 >> 4), (d16 + 15) >> 4):
                    xr = xo - d + lo + n - 1  # the right pixel's index in r_cost (>= 0)
                    if 0 <= xr < bw + n and r_cost[xr] > c:
                        r_cost[xr] = c
                        r_disp[xr] = d
            for gx in range(gw):
                xo = gx * st
                d16 = dc[gy, gx]
                if d16 == INVALID:
                    continue
                d = d16 >> 4
                d_ = (d16 + 15) >> 4
                x_a = xo - d + lo + n - 1
                x_b = xo - d_ + lo + n - 1
                if (0 <= x_a < bw + n and r_disp[x_a] >= 0 and abs(r_disp[x_a] - d) > lr_max
                        and 0 <= x_b < bw + n and r_disp[x_b] >= 0 and abs(r_disp[x_b] - d_) > lr_max):
                    dc[gy, gx] = INVALID
    if spk_size > 0:
        # on the grid: a region of spk_size pixels has spk_size / st^2 samples, st pixels apart
        _remove_speckles(dc, spk_size // (st * st), spk_diff * st, parent, count)
    m = 0
    total = 0
    for yy in range(bh):
        lab = labels[y0 + yy]
        o = out[y0 + yy]
        g = dc[yy // st]
        gx = 0
        c = 0
        for xo in range(bw):
            if lab[x0 + xo] == k + 1:
                total += 1
                v = g[gx]
                if v != INVALID:
                    o[x0 + xo] = v / 16.0
                    m += 1
                else:
                    o[x0 + xo] = 0.0
            c += 1
            if c == st:
                c = 0
                gx += 1
    if m < KEEP_FRACTION * total:
        # too few pixels passed the checks for the objects' stage to measure the outline
        # (objects.MIN_VALID_FRACTION): the masker's disparity, which it may measure, stays
        for yy in range(bh):
            lab = labels[y0 + yy]
            for xo in range(bw):
                if lab[x0 + xo] == k + 1:
                    out[y0 + yy, x0 + xo] = disp[y0 + yy, x0 + xo]
        return -1
    return m


@jit(inline="always")
def _root(parent, i):  # pragma: no cover - compiled
    """The root of pixel ``i``'s set (path halving)."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@jit(inline="always")
def _join(parent, i, j):  # pragma: no cover - compiled
    """Pixels ``i`` and ``j`` into one set, rooted at the earlier pixel."""
    a = _root(parent, i)
    b = _root(parent, j)
    if a < b:
        parent[b] = a
    elif b < a:
        parent[a] = b


@jit
def _remove_speckles(dc, max_size, max_diff, parent, count):
    """BM's speckle filter over one box's int16 disparities (1/16 px): 4-connected regions
    whose neighbours differ by at most ``max_diff``, of at most ``max_size`` pixels, become
    INVALID.  The regions by union-find in raster order (each pixel joined to its left and
    upper neighbours: the same regions as a flood fill, without its stack); ``parent`` /
    ``count``: (>= bh * bw,) int32 scratch."""
    bh, bw = dc.shape
    for y in range(bh):
        row = dc[y]
        for x in range(bw):
            i = y * bw + x
            v = row[x]
            if v == INVALID:
                parent[i] = -1
                continue
            parent[i] = i
            count[i] = 0
            if x > 0:
                u = row[x - 1]
                if u != INVALID and abs(u - v) <= max_diff:
                    _join(parent, i, i - 1)
            if y > 0:
                u = dc[y - 1, x]
                if u != INVALID and abs(u - v) <= max_diff:
                    _join(parent, i, i - bw)
    n = bh * bw
    for i in range(n):
        if parent[i] >= 0:
            r = _root(parent, i)
            parent[i] = r
            count[r] += 1
    for i in range(n):
        if parent[i] >= 0 and count[parent[i]] <= max_size:
            dc[i // bw, i % bw] = INVALID


@jit
def object_disparity(L, R, labels, disp, boxes, block, cap, uniq, lr_max, spk_size, spk_diff, st, samples,
                     max_area, budget, out):
    """Every object's outline matched again (module doc), one call a frame.

    ``L`` / ``R``: the rectified gray images (uint8); ``labels``: the left instance labels
    (``k + 1`` = object k); ``disp``: the masker's disparity (float32 px, full frame);
    ``boxes`` (N, 4) int64: x0, y0, x1, y1 around each object's pixels (clipped to the
    image); ``st``: every st-th row and column matched (a pixel takes its sample's value),
    more apart in a box of more than ``samples`` pixels (0: no limit) so that about that
    many are matched; a box of more than ``max_area`` pixels (0: no limit) keeps the
    masker's disparity, and so do the largest boxes beyond the frame's ``budget`` (0: none):
    the boxes are matched smallest first while their areas with the block's margin,
    ``(w + block) (h + block)``, add up to at most ``budget`` pixels.  In ``out`` (like ``disp``; a buffer kept between frames saves the
    page faults of a new one) the outlines of the objects matched again are written (0
    where a check failed); the rest keeps what it held (the objects' stage reads an
    object's disparities there only where it was matched: copying the rest from ``disp``
    cost 0.1 ms a frame, more at KITTI's size).  Returns (N,) the pixels matched per object
    (-1: the masker's kept, its outline in ``out`` as it was or the masker's -- too few
    disparities to set a window, too few pixels passing the checks, a box too large, or one
    beyond the frame's budget)."""
    N = boxes.shape[0]
    res = np.full(N, -1, np.int64)
    hist = np.zeros(HIST_BINS, np.int64)
    # each box matched: its grid step (a box of more than ``samples`` pixels on every
    # sk-th row and column); the speckle filter's scratch sized to the largest grid (one
    # sized to the largest box, matched or not, took page faults every frame)
    step = np.zeros(N, np.int64)
    gh_max = 1
    gw_max = 1
    area = np.empty(N, np.int64)
    for k in range(N):
        area[k] = (boxes[k, 2] - boxes[k, 0]) * (boxes[k, 3] - boxes[k, 1])
    work = 0
    for k in np.argsort(area, kind="mergesort"):  # smallest first, within the frame's budget
        x0, y0, x1, y1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
        if x1 <= x0 or y1 <= y0 or (max_area > 0 and area[k] > max_area):
            continue
        work += (x1 - x0 + block) * (y1 - y0 + block)
        if budget > 0 and work > budget:
            break
        sk = st
        if samples > 0:
            sk = max(st, int(np.ceil(np.sqrt(area[k] / samples))))
        step[k] = sk
        gh_max = max(gh_max, (y1 - y0 + sk - 1) // sk)
        gw_max = max(gw_max, (x1 - x0 + sk - 1) // sk)
    parent = np.empty(gh_max * gw_max, np.int32)
    count = np.empty(gh_max * gw_max, np.int32)
    for k in range(N):
        sk = step[k]
        if sk == 0:
            continue
        x0, y0, x1, y1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
        lo, n = _window(labels, disp, k, x0, y0, x1, y1, sk, hist)
        if n > 0:
            res[k] = _match_box(L, R, labels, disp, k, x0, y0, x1, y1, lo, n, block, cap, uniq, lr_max, spk_size,
                                spk_diff, sk, out, parent, count)
    return res


@dataclass(frozen=True)
class ObjectStereo:
    """The objects' own block matching (module doc): its own ``block`` / ``stride``
    (``objects.*``), the samples per box, the largest box matched (``max_area``, 0: any)
    and the frame's budget (``budget`` px, 0: none), StereoBM's checks from ``checks`` --
    the masker's matcher parameters (:func:`~dynastereo.masking.disparity.params_at_scale`;
    default: the default configuration's): prefilter cap, uniqueness ratio, left-right
    difference, speckle window and range."""

    block: int
    stride: int = 1
    samples: int = SAMPLES
    max_area: int = 0
    budget: int = FRAME_BUDGET
    checks: MatcherParams = field(default_factory=lambda: params_at_scale(StereoConfig(), 1))

    @classmethod
    def from_config(cls, objects: ObjectsConfig, stereo: StereoConfig) -> "ObjectStereo | None":
        """None when ``objects.block_size`` is 0 (positions from the masker's disparity)."""
        if not objects.block_size:
            return None
        return cls(int(objects.block_size), int(objects.stride), max_area=MAX_BOX_BLOCKS * int(stereo.block_size) ** 2,
                   checks=params_at_scale(stereo, 1))

    def __call__(self, left: np.ndarray, right: np.ndarray, labels: np.ndarray, disp: np.ndarray,
                 boxes: np.ndarray, out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(disparity, pixels matched per object): :func:`object_disparity` over gray uint8
        images and int64 boxes.  Without ``out``: a copy of ``disp`` with the outlines
        matched again; with it (float32 like ``disp``, kept between frames): only the
        outlines of the objects matched (``matched >= 0``) are written."""
        if left.shape != labels.shape or right.shape != labels.shape or disp.shape != labels.shape:
            raise ValueError(f"object disparity: images {left.shape} / {right.shape}, labels {labels.shape} and "
                             f"disparity {disp.shape} must have one shape")
        if out is None or out.shape != disp.shape or out.dtype != np.float32 or not out.flags.c_contiguous:
            out = np.array(disp, np.float32, order="C")
        c = self.checks
        matched = object_disparity(np.ascontiguousarray(left, np.uint8), np.ascontiguousarray(right, np.uint8),
                                   np.ascontiguousarray(labels, np.int32), np.ascontiguousarray(disp, np.float32),
                                   np.ascontiguousarray(boxes, np.int64).reshape(-1, 4), self.block,
                                   c.pre_filter_cap, c.uniqueness_ratio, c.disp12_max_diff, c.speckle_window_size,
                                   c.speckle_range, self.stride, self.samples, self.max_area, self.budget, out)
        return out, matched

    def warm_up(self) -> None:
        """The kernel loaded (compiled or from the cache) before the frame loop."""
        z = np.zeros((8, 8), np.uint8)
        lab = np.zeros((8, 8), np.int32)
        lab[2:6, 2:6] = 1
        d = np.where(lab > 0, 1.0, 0.0).astype(np.float32)
        self(z, z, lab, d, np.array([[2, 2, 6, 6]], np.int64))
