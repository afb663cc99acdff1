"""All of a frame's boxes in one compiled call: the outlines (:func:`outline_frame`) and
their transfer into the right image (:func:`transfer_frame`).

The per-box numpy / OpenCV path they replace (a dozen calls a box, about 0.4 ms each
whatever its size) is kept as the tests' reference in ``tests/reference/masking_numpy.py``;
:mod:`.outline` and :mod:`.transfer` describe what is computed.  The kernels give the same
masks: the same float32 arithmetic where numpy used float32 (a python float compared with
a float32 array is rounded to float32; sums are numpy's pairwise sums, :func:`_pairwise`),
the same labelling order as OpenCV's connected components (2x2 blocks in raster order)
and the same ellipse for the dilation.  Two things are not bit for bit:

* the histogram's bin coordinate takes the log of near disparities, and numpy's SIMD
  float32 log is not OpenCV's nor LLVM's: it is tabulated (:func:`bin_table`, numpy's own
  values) for every disparity on the matchers' 1/16 px grid, and only values off that grid
  use float32(log(float64));
* the transfer's affine fit solves the normal equations (centred coordinates) instead of
  numpy's SVD least squares: the same model to about 1e-12.

This module is a leaf: numpy and :mod:`..compiled` only.  Its kernels run over arrays
(the boxes as an ``(N, 4)`` ROI array, the masks packed in one buffer); the only loops over
the boxes are inside them.
"""

from __future__ import annotations

import numpy as np

from ..compiled import jit

# method codes (:data:`.outline.METHOD_CODES` maps them to MaskMethod)
EMPTY, OUTLINE, TINY, NO_DISPARITY, SPARSE, RANGE, NO_PEAK, SMALL = range(8)

# the outline parameters, in the order of the ``prm`` array (:func:`.outline.outline_params`)
(P_BIN_WIDTH, P_REL, P_NEAR, P_EXTEND, P_TOL, P_MIN_VALID, P_MIN_PIXELS, P_MIN_SIDE, P_OVERLAP, P_CLAIM,
 P_MIN_OUTLINE, P_GROUND_TOL, P_GROUND_MAX, P_MAX_DISP, P_FILL_HOLES, P_LARGEST, P_GROUND_AFTER, P_USE_ROAD,
 P_ROAD_SLOPE, P_ROAD_OFFSET, P_LEFT_CONTEXT, P_CLAIM_MARGIN, P_RANGE_MARGIN, N_PARAMS) = range(24)

#: disparities tabulated by :func:`bin_table`: k / 16 for k < TABLE_SIZE (up to 1024 px)
TABLE_STEPS = 16
TABLE_SIZE = 1024 * TABLE_STEPS + 1


def to_bins_numpy(v: np.ndarray, bin_width: float, rel: float) -> np.ndarray:
    """Continuous bin coordinate (float32): bins ``bin_width`` wide at small disparity and
    ``rel * d`` wide above ``d_c = bin_width / rel`` (log scale), joined smoothly."""
    u = v * (1.0 / bin_width)
    if rel > 0:
        dc = bin_width / rel
        far = v > dc
        if far.any():
            u = np.where(far, dc / bin_width + np.log(np.maximum(v, dc) / dc) / rel, u)
    return u


_TABLES: dict[tuple[float, float], np.ndarray] = {}


def bin_table(bin_width: float, rel: float) -> np.ndarray:
    """:func:`to_bins_numpy` of every disparity ``k / 16`` (float32, numpy's own log), cached."""
    key = (float(bin_width), float(rel))
    t = _TABLES.get(key)
    if t is None:
        v = (np.arange(TABLE_SIZE, dtype=np.float32) / np.float32(TABLE_STEPS)).astype(np.float32)
        t = _TABLES[key] = np.ascontiguousarray(to_bins_numpy(v, key[0], key[1]), np.float32)
    return t


# --------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------
@jit
def _pairwise_leaf(a, lo, n):  # pragma: no cover - compiled
    """numpy's pairwise sum of at most 128 values: 8 accumulators (sequential below 8)."""
    if n < 8:
        res = np.float32(0.0)
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    m = n - n % 8
    i = 8
    while i < m:
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@jit
def _pairwise(a, lo, n):  # pragma: no cover - compiled
    """numpy's pairwise float32 sum of ``a[lo:lo + n]`` (``np.add.reduce``: 8 accumulators
    over blocks of at most 128, halves above, each half's length a multiple of 8), the
    same float32 to the last bit.  The recursion unrolled on a stack (a recursive kernel
    crashes when numba loads it from its cache)."""
    if n <= 128:
        return _pairwise_leaf(a, lo, n)
    ops_lo = np.empty(256, np.int64)
    ops_n = np.empty(256, np.int64)  # -1: add the two last sums
    vals = np.empty(128, np.float32)
    no, nv = 1, 0
    ops_lo[0], ops_n[0] = lo, n
    while no > 0:
        no -= 1
        olo, on = ops_lo[no], ops_n[no]
        if on < 0:
            nv -= 1
            vals[nv - 1] = vals[nv - 1] + vals[nv]
        elif on <= 128:
            vals[nv] = _pairwise_leaf(a, olo, on)
            nv += 1
        else:
            n2 = on // 2
            n2 -= n2 % 8
            ops_lo[no], ops_n[no] = 0, -1  # then their sum, left + right
            ops_lo[no + 1], ops_n[no + 1] = olo + n2, on - n2  # the right half second
            ops_lo[no + 2], ops_n[no + 2] = olo, n2  # the left half first
            no += 3
    return vals[0]


@jit(inline="always")
def _at(disp, ox, oy, x, y):  # pragma: no cover - compiled
    """The region array's disparity at image pixel (x, y); 0 outside it."""
    yy = y - oy
    xx = x - ox
    if 0 <= yy < disp.shape[0] and 0 <= xx < disp.shape[1]:
        return disp[yy, xx]
    return np.float32(0.0)


@jit
def _to_bin(v, table, bw32, inv_bw32, dc32, dcb32, rel32, rel):  # pragma: no cover - compiled
    """One value's bin coordinate: the table's (numpy's) on the 1/16 px grid, else float32
    arithmetic as :func:`to_bins_numpy` with float32(log(float64))."""
    k = v * np.float32(TABLE_STEPS)
    if k >= 0 and k < table.shape[0] and k == np.floor(k):
        return table[np.int64(k)]
    if rel > 0 and v > dc32:
        return dcb32 + np.float32(np.log(np.float64(max(v, dc32) / dc32))) / rel32
    return v * inv_bw32


@jit
def fill_rows(d, out):  # pragma: no cover - compiled
    """:func:`.outline.fill_invalid_rows` into ``out``, row by row: each invalid pixel's nearest
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
        # one pass a row: valid pixels copied, each run of invalid ones filled from the
        # valid pixels either side of it
        li = -1
        x = 0
        while x < w:
            v = d[y, x]
            if v > 0:
                out[y, x] = v
                li = x
                x += 1
                continue
            s = x
            while x < w and not d[y, x] > 0:
                x += 1
            lv = d[y, li] if li >= 0 else zero
            rv = d[y, x] if x < w else zero
            if lv > 0 and rv > 0:
                near = min(lv, rv)
                if rv > lv:
                    band = rv - lv
                    for t in range(s, x):
                        out[y, t] = rv if not ((t - li) <= band) else near
                else:
                    out[y, s:x] = near
            else:
                out[y, s:x] = max(lv, rv)


@jit
def peak_bins(u, u_min, weights, near_ratio, extend_ratio, sel, v, ends):  # pragma: no cover - compiled
    """:func:`.outline.dominant_disparity`'s histogram over the bin coordinates ``u`` (float32,
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


@jit
def dominant_peak(v, w, table, prm):  # pragma: no cover - compiled
    """:func:`.outline.dominant_disparity` of the float32 values ``v`` (weights ``w``: empty
    or one per value): ``(disparity, lo, hi)`` as python floats would hold them (the
    mean in float32, numpy's pairwise sums)."""
    m = v.shape[0]
    bw = prm[P_BIN_WIDTH] if prm[P_BIN_WIDTH] > 0 else 1.0
    rel = prm[P_REL]
    inv_bw32 = np.float32(1.0 / bw)
    dc = bw / rel if rel > 0 else 0.0
    dc32, dcb32, rel32 = np.float32(dc), np.float32(dc / bw), np.float32(rel)
    u = np.empty(m, np.float32)
    u_min = np.float32(np.inf)
    for i in range(m):
        u[i] = _to_bin(v[i], table, np.float32(bw), inv_bw32, dc32, dcb32, rel32, rel)
        u_min = min(u_min, u[i])
    sel = np.empty(m, np.bool_)
    ends = np.empty(2)
    k, kl, kh = peak_bins(u, u_min, w, prm[P_NEAR], prm[P_EXTEND], sel, v, ends)
    ns = 0
    for i in range(m):
        if sel[i]:
            ns += 1
    a = np.empty(ns, np.float32)
    j = 0
    if w.shape[0]:
        b = np.empty(ns, np.float32)
        for i in range(m):
            if sel[i]:
                a[j] = v[i] * w[i]
                b[j] = w[i]
                j += 1
        d = np.float64(_pairwise(a, 0, ns) / _pairwise(b, 0, ns))
    else:
        for i in range(m):
            if sel[i]:
                a[j] = v[i]
                j += 1
        d = np.float64(_pairwise(a, 0, ns) / np.float32(ns))
    lo = d
    hi = d
    if prm[P_EXTEND] < 1.0:
        if kl < k and not np.isnan(ends[0]):
            lo = ends[0]
        if kh > k and not np.isnan(ends[1]):
            hi = ends[1]
    return d, min(lo, d), max(hi, d)


# --------------------------------------------------------------------------------------
# the shape of one outline: components, holes, dilation
# --------------------------------------------------------------------------------------
@jit
def _find(parent, a):  # pragma: no cover - compiled
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@jit
def _largest_component(m, lab, stack):  # pragma: no cover - compiled
    """Keep the largest 8-connected component of ``m`` (uint8 0/1, in place); on a tie the
    one OpenCV labels first (its first 2x2 block in raster order).  Over the rows' runs
    of set pixels (union-find, runs of consecutive rows touching or diagonal), not the
    pixels; ``lab`` / ``stack`` are unused scratch (the signature of the pixel version)."""
    h, w = m.shape
    cap = h * ((w + 1) // 2) + 1
    rr = np.empty(cap, np.int64)  # each run's row, first column, end (exclusive)
    r0 = np.empty(cap, np.int64)
    r1 = np.empty(cap, np.int64)
    row_start = np.empty(h + 1, np.int64)
    n = _runs(m, True, rr, r0, r1, row_start)
    if n <= 1:
        return
    parent = np.arange(n)
    _join_rows(parent, row_start, r0, r1, h, True)
    area = np.zeros(n, np.int64)
    key = np.full(n, np.iinfo(np.int64).max)
    n_comp = 0
    for k in range(n):
        r = _find(parent, k)
        if r == k:
            n_comp += 1
        area[r] += r1[k] - r0[k]
        kk = (rr[k] // 2) * w + r0[k] // 2
        if kk < key[r]:
            key[r] = kk
    if n_comp <= 1:
        return
    best = -1
    for k in range(n):
        if parent[k] == k and (best < 0 or area[k] > area[best] or (area[k] == area[best] and key[k] < key[best])):
            best = k
    for k in range(n):
        if _find(parent, k) != best:
            for x in range(r0[k], r1[k]):
                m[rr[k], x] = 0


@jit
def _runs(m, value, rr, r0, r1, row_start):  # pragma: no cover - compiled
    """The rows' runs of pixels equal to ``value`` (row, first column, end) in raster
    order, ``row_start[y]`` the first of row ``y``; returns their number."""
    h, w = m.shape
    n = 0
    for y in range(h):
        row_start[y] = n
        x = 0
        while x < w:
            if (m[y, x] != 0) != value:
                x += 1
                continue
            s = x
            while x < w and (m[y, x] != 0) == value:
                x += 1
            rr[n], r0[n], r1[n] = y, s, x
            n += 1
    row_start[h] = n
    return n


@jit
def _join_rows(parent, row_start, r0, r1, h, diagonal):  # pragma: no cover - compiled
    """Union the runs of consecutive rows that touch: overlapping columns (4-connected),
    or also diagonally adjacent ones with ``diagonal`` (8-connected); the smaller index
    is the root."""
    g = 1 if diagonal else 0
    for y in range(1, h):
        a, a_end = row_start[y - 1], row_start[y]
        b, b_end = row_start[y], row_start[y + 1]
        while a < a_end and b < b_end:
            if r0[a] < r1[b] + g and r0[b] < r1[a] + g:
                ra, rb = _find(parent, a), _find(parent, b)
                if ra != rb:
                    if ra < rb:
                        parent[rb] = ra
                    else:
                        parent[ra] = rb
            if r1[a] < r1[b]:
                a += 1
            else:
                b += 1


@jit
def _fill_holes(m, seen, stack):  # pragma: no cover - compiled
    """Fill the holes of ``m`` (uint8 0/1, in place): the 0s not 4-connected to its border
    (OpenCV's flood fill from the padded corner).  Over the rows' runs of 0s
    (union-find); ``seen`` / ``stack`` are unused scratch."""
    h, w = m.shape
    cap = h * ((w + 1) // 2) + 1
    rr = np.empty(cap, np.int64)
    r0 = np.empty(cap, np.int64)
    r1 = np.empty(cap, np.int64)
    row_start = np.empty(h + 1, np.int64)
    n = _runs(m, False, rr, r0, r1, row_start)
    if n == 0:
        return
    parent = np.arange(n)
    _join_rows(parent, row_start, r0, r1, h, False)
    outside = np.zeros(n, np.bool_)
    for k in range(n):
        if rr[k] == 0 or rr[k] == h - 1 or r0[k] == 0 or r1[k] == w:
            outside[_find(parent, k)] = True
    for k in range(n):
        if not outside[_find(parent, k)]:
            for x in range(r0[k], r1[k]):
                m[rr[k], x] = 1


@jit
def _dilate(m, out, dist, se_lo, se_hi):  # pragma: no cover - compiled
    """``out`` = ``m`` dilated by the structuring element whose row ``i`` (offset ``i - r``)
    spans columns ``se_lo[i] .. se_hi[i]`` (``-k .. k``: symmetric, as OpenCV's ellipse)
    around the anchor; nothing beyond ``m``'s edges (OpenCV's border for dilation).  Each
    run of set pixels paints its row span grown by ``k_i`` into the rows it reaches (a
    blobby mask has a few runs a row: span fills, not per-pixel tests); ``dist`` is unused
    scratch."""
    h, w = m.shape
    out[:, :] = 0
    r = (se_lo.shape[0] - 1) // 2
    for y in range(h):
        x = 0
        while x < w:
            if m[y, x] == 0:
                x += 1
                continue
            s = x
            while x < w and m[y, x] != 0:
                x += 1
            for i in range(se_lo.shape[0]):
                yd = y - (i - r)  # out(yd) looks at row yd + i - r = y
                k = se_hi[i]
                if yd < 0 or yd >= h or k < se_lo[i]:
                    continue
                out[yd, max(s - k, 0):min(x + k, w)] = 1  # a slice: vectorized


# --------------------------------------------------------------------------------------
# one box's outline
# --------------------------------------------------------------------------------------
@jit
def _median_valid(d, n_valid):  # pragma: no cover - compiled
    """The median of the ``n_valid`` valid (> 0) values of ``d`` as np.median gives it
    (float32: the mean of the middle two); 0 without any."""
    if n_valid == 0:
        return 0.0
    vals = np.empty(n_valid, np.float32)
    j = 0
    for r in range(d.shape[0]):
        for c in range(d.shape[1]):
            if d[r, c] > 0:
                vals[j] = d[r, c]
                j += 1
    k = n_valid // 2
    p = np.partition(vals, k)  # O(n): p[k] in place, the smaller ones before it
    if n_valid % 2:
        return np.float64(p[k])
    below = p[0]
    for i in range(1, k):
        below = max(below, p[i])
    return np.float64((below + p[k]) / np.float32(2.0))


@jit
def _outline_box(disp, ox, oy, rois, ib, has_cover, has_ex, ex_lo, ex_hi,
                 prm, table, se_lo, se_hi, mask):  # pragma: no cover - compiled
    """:func:`.outline.object_mask_in_roi` of the box ``rois[ib]`` (its disparity read from
    the region array ``disp`` at ``ox, oy``; with ``has_cover`` its pixels inside other
    boxes weigh less; disparities in ``ex_lo .. ex_hi`` invalid with ``has_ex``):
    ``(method, disparity, lo, hi, support)``, the mask (uint8 0/1) in ``mask`` when the
    method is OUTLINE."""
    x0, y0, x1, y1 = rois[ib, 0], rois[ib, 1], rois[ib, 2], rois[ib, 3]
    bh, bw = y1 - y0, x1 - x0
    area = bh * bw
    exl, exh = np.float32(ex_lo), np.float32(ex_hi)
    d = np.empty((bh, bw), np.float32)
    # the valid values in raster order (numpy's boolean indexing) and whether other boxes
    # share their pixel, gathered branch-free (half the disparities are holes)
    vbuf = np.empty(area, np.float32)
    sbuf = np.empty(area, np.bool_)
    shared = np.zeros((bh if has_cover else 0, bw if has_cover else 0), np.bool_)  # inside other boxes too
    if has_cover:
        for j in range(rois.shape[0]):
            ax0, ax1 = max(x0, rois[j, 0]), min(x1, rois[j, 2])
            ay0, ay1 = max(y0, rois[j, 1]), min(y1, rois[j, 3])
            if j == ib or ax1 <= ax0 or ay1 <= ay0:
                continue
            for y in range(ay0, ay1):
                for x in range(ax0, ax1):
                    shared[y - y0, x - x0] = True
    n_valid = 0
    n_shared = 0
    dh, dw = disp.shape
    for r in range(bh):
        yy = y0 + r - oy
        row_in = 0 <= yy < dh
        for c in range(bw):
            xx = x0 + c - ox
            v = disp[yy, xx] if row_in and 0 <= xx < dw else np.float32(0.0)
            if has_ex:
                v = np.float32(0.0) if (v >= exl and v <= exh) else v
            d[r, c] = v
            sh = has_cover and shared[r, c]
            vbuf[n_valid] = v
            sbuf[n_valid] = sh
            ok = v > 0
            n_valid += ok
            n_shared += ok & sh
    tiny = area < prm[P_MIN_PIXELS] or min(bh, bw) < prm[P_MIN_SIDE]
    if tiny or n_valid < max(prm[P_MIN_VALID] * area, 8.0):
        med = _median_valid(d, n_valid)
        return (TINY if tiny else NO_DISPARITY), med, med, med, 0
    # the road's disparity + its tolerance, per row (float32 as GroundLine.at)
    use_top = prm[P_USE_ROAD] > 0
    top = np.empty(bh, np.float32)
    if use_top:
        slope, offset, gt = np.float32(prm[P_ROAD_SLOPE]), np.float32(prm[P_ROAD_OFFSET]), np.float32(prm[P_GROUND_TOL])
        for r in range(bh):
            top[r] = (np.float32(y0 + r) * slope + offset) + gt
        n_above = 0
        for r in range(bh):
            for c in range(bw):
                if d[r, c] > 0 and d[r, c] >= top[r]:
                    n_above += 1
        if n_above < max(prm[P_MIN_VALID] * bh * bw, 8.0):
            use_top = False
    ns = n_valid
    if use_top:  # the values above the road only
        ns = 0
        n_shared = 0
        for r in range(bh):
            for c in range(bw):
                x = d[r, c]
                if x > 0 and x >= top[r]:
                    sh = has_cover and shared[r, c]
                    vbuf[ns] = x
                    sbuf[ns] = sh
                    ns += 1
                    n_shared += sh
    weighted = has_cover and prm[P_OVERLAP] < 1.0 and n_shared > 0 and n_shared < ns
    wts = np.empty(ns if weighted else 0, np.float32)
    if weighted:
        ow = np.float32(prm[P_OVERLAP])
        for j in range(ns):
            wts[j] = ow if sbuf[j] else np.float32(1.0)
    v = vbuf[:ns]
    pd, plo, phi = dominant_peak(v, wts, table, prm)
    tol = max(prm[P_TOL], prm[P_REL] * pd)
    lo = max(min(pd - tol, plo), 1e-3)  # lo > 0: never the invalid
    hi = max(pd + tol, phi)
    lo32, hi32 = np.float32(lo), np.float32(hi)
    support = 0
    for r in range(bh):
        for c in range(bw):
            if d[r, c] >= lo32 and d[r, c] <= hi32:
                support += 1
    if not np.isnan(prm[P_MAX_DISP]) and hi >= prm[P_MAX_DISP] - prm[P_RANGE_MARGIN]:
        return RANGE, pd, lo, hi, support
    if support < prm[P_MIN_VALID] * area:
        return SPARSE, pd, lo, hi, support
    if use_top and prm[P_GROUND_MAX] < 1.0:
        on_road = 0
        for r in range(bh):
            for c in range(bw):
                if d[r, c] >= lo32 and d[r, c] <= hi32 and d[r, c] < top[r]:
                    on_road += 1
        if on_road > prm[P_GROUND_MAX] * support:
            use_top = False
    # the shape: invalid pixels filled along the rows (the context left of the box too)
    cx0 = max(0, x0 - np.int64(prm[P_LEFT_CONTEXT]))
    cw = x0 - cx0
    cat = np.empty((bh, cw + bw), np.float32)
    for r in range(bh):
        for c in range(cw):
            x = _at(disp, ox, oy, cx0 + c, y0 + r)
            if has_ex and x >= exl and x <= exh:
                x = np.float32(0.0)
            cat[r, c] = x
        for c in range(bw):
            cat[r, cw + c] = d[r, c]
    filled = np.empty((bh, cw + bw), np.float32)
    fill_rows(cat, filled)
    any_set = False
    for r in range(bh):
        for c in range(bw):
            f = filled[r, cw + c]
            k = f >= lo32 and f <= hi32
            if k and use_top and f < top[r]:
                k = False
            mask[r, c] = 1 if k else 0
            any_set = any_set or k
    if any_set:
        stack = np.empty(area, np.int64)
        work = np.empty((bh, bw), np.int32)
        if prm[P_LARGEST] > 0:
            _largest_component(mask, work, stack)
        if prm[P_FILL_HOLES] > 0:
            _fill_holes(mask, work, stack)
            if use_top:
                for r in range(bh):
                    for c in range(bw):
                        if filled[r, cw + c] < top[r]:
                            mask[r, c] = 0
        if se_lo.shape[0] > 0:
            src = mask.copy()
            _dilate(src, mask, work, se_lo, se_hi)
        if use_top and prm[P_GROUND_AFTER] > 0:
            for r in range(bh):
                for c in range(bw):
                    if filled[r, cw + c] < top[r]:
                        mask[r, c] = 0
        any_set = False
        for r in range(bh):
            for c in range(bw):
                if mask[r, c]:
                    any_set = True
                    break
            if any_set:
                break
    if not any_set:
        return NO_PEAK, pd, lo, hi, support
    return OUTLINE, pd, lo, hi, support


@jit(inline="always")
def _tol(d, prm):  # pragma: no cover - compiled
    """:func:`.outline.tolerance` of the disparity ``d``."""
    return max(prm[P_TOL], prm[P_REL] * d)


@jit
def outline_frame(disp, ox, oy, rois, prm, table, se_lo, se_hi, labels, mask, disparity, method, lo, hi,
                  pixels):  # pragma: no cover - compiled
    """:func:`.outline.outline_objects` of all the boxes ``rois`` (N, 4) in one call: the
    outlines, one peak one object (the claims), small outlines to boxes, the label image
    ``labels`` painted far to near (box fallbacks first; ``mask``: 255 where any is) and
    each object's ``disparity`` (float32), ``method`` (code), accepted range ``lo .. hi``
    and ``pixels``."""
    n = rois.shape[0]
    h, w = labels.shape
    offs = np.zeros(n + 1, np.int64)
    for i in range(n):
        x0, y0, x1, y1 = rois[i, 0], rois[i, 1], rois[i, 2], rois[i, 3]
        offs[i + 1] = offs[i] + ((x1 - x0) * (y1 - y0) if x1 > x0 and y1 > y0 else 0)
    has_cover = n > 1 and prm[P_OVERLAP] < 1.0
    masks = np.zeros(offs[n], np.uint8)  # the boxes' masks, packed
    sup = np.zeros(n, np.int64)
    for i in range(n):
        method[i] = EMPTY
        disparity[i] = 0.0
        lo[i] = 0.0
        hi[i] = 0.0
        pixels[i] = 0
    for i in range(n):
        x0, y0, x1, y1 = rois[i, 0], rois[i, 1], rois[i, 2], rois[i, 3]
        if x1 <= x0 or y1 <= y0:
            continue
        m = masks[offs[i]:offs[i + 1]].reshape((y1 - y0, x1 - x0))
        method[i], disparity[i], lo[i], hi[i], sup[i] = _outline_box(
            disp, ox, oy, rois, i, has_cover, False, 0.0, 0.0, prm, table, se_lo, se_hi, m)
    # one peak, one object: a box whose in-peak pixels lie mostly at a neighbour holding
    # the same peak gives it up (decided on the first outlines)
    if n > 1 and prm[P_CLAIM] < 1.0:
        inside = np.zeros((n, n))
        cm = np.int64(prm[P_CLAIM_MARGIN])
        for i in range(n):
            if method[i] == EMPTY or sup[i] <= 0:
                continue
            x0, y0, x1, y1 = rois[i, 0], rois[i, 1], rois[i, 2], rois[i, 3]
            lo32, hi32 = np.float32(lo[i]), np.float32(hi[i])
            for j in range(n):
                if j == i or method[j] == EMPTY or sup[j] <= 0:
                    continue
                di, dj = np.float64(disparity[i]), np.float64(disparity[j])
                if abs(di - dj) > max(_tol(di, prm), _tol(dj, prm)):
                    continue
                ax0, ax1 = max(rois[j, 0] - cm, x0), min(rois[j, 2] + cm, x1)
                ay0, ay1 = max(rois[j, 1] - cm, y0), min(rois[j, 3] + cm, y1)
                if ax1 <= ax0 or ay1 <= ay0:
                    continue
                cnt = 0
                for y in range(ay0, ay1):
                    for x in range(ax0, ax1):
                        v = _at(disp, ox, oy, x, y)
                        if v >= lo32 and v <= hi32:
                            cnt += 1
                inside[i, j] = cnt / sup[i]
        for i in range(n):
            bj = -1
            for j in range(n):
                if inside[i, j] > prm[P_CLAIM] and inside[j, i] < inside[i, j]:
                    if bj < 0 or inside[i, j] > inside[i, bj]:
                        bj = j
            if bj >= 0:
                x0, y0, x1, y1 = rois[i, 0], rois[i, 1], rois[i, 2], rois[i, 3]
                m = masks[offs[i]:offs[i + 1]].reshape((y1 - y0, x1 - x0))
                method[i], disparity[i], lo[i], hi[i], sup[i] = _outline_box(
                    disp, ox, oy, rois, i, has_cover, True, lo[bj], hi[bj], prm, table, se_lo, se_hi, m)
    # outlines much smaller than the part of their box no nearer object takes: boxes
    if prm[P_MIN_OUTLINE] > 0:
        small = np.zeros(n, np.bool_)
        for i in range(n):
            if method[i] != OUTLINE:
                continue
            x0, y0, x1, y1 = rois[i, 0], rois[i, 1], rois[i, 2], rois[i, 3]
            bh, bw = y1 - y0, x1 - x0
            taken = np.zeros((bh, bw), np.bool_)
            for j in range(n):
                if j == i or method[j] == EMPTY or disparity[j] <= disparity[i]:
                    continue
                jx0, jy0, jx1, jy1 = rois[j, 0], rois[j, 1], rois[j, 2], rois[j, 3]
                ax0, ax1, ay0, ay1 = max(x0, jx0), min(x1, jx1), max(y0, jy0), min(y1, jy1)
                if ax1 <= ax0 or ay1 <= ay0:
                    continue
                mj = masks[offs[j]:offs[j + 1]].reshape((jy1 - jy0, jx1 - jx0))
                for y in range(ay0, ay1):
                    for x in range(ax0, ax1):
                        if method[j] != OUTLINE or mj[y - jy0, x - jx0] > 0:
                            taken[y - y0, x - x0] = True
            mi = masks[offs[i]:offs[i + 1]].reshape((bh, bw))
            free = 0
            own = 0
            for r in range(bh):
                for c in range(bw):
                    if not taken[r, c]:
                        free += 1
                        if mi[r, c] > 0:
                            own += 1
            if own < prm[P_MIN_OUTLINE] * free:
                small[i] = True
        for i in range(n):
            if small[i]:
                method[i] = SMALL
    # paint far to near, box fallbacks first (nearer objects win shared pixels)
    order = np.argsort(disparity, kind="mergesort")
    for outline_pass in range(2):
        for t in range(n):
            i = order[t]
            if method[i] == EMPTY or (method[i] == OUTLINE) != (outline_pass == 1):
                continue
            x0, y0, x1, y1 = rois[i, 0], rois[i, 1], rois[i, 2], rois[i, 3]
            m = masks[offs[i]:offs[i + 1]].reshape((y1 - y0, x1 - x0))
            for y in range(y0, y1):
                for x in range(x0, x1):
                    if method[i] != OUTLINE or m[y - y0, x - x0] > 0:
                        labels[y, x] = i + 1
                        mask[y, x] = 255
    for i in range(n):
        c = 0
        for y in range(rois[i, 1], rois[i, 3]):
            for x in range(rois[i, 0], rois[i, 2]):
                if labels[y, x] == i + 1:
                    c += 1
        pixels[i] = c


# --------------------------------------------------------------------------------------
# the transfer into the right image
# --------------------------------------------------------------------------------------
@jit
def affine_paint(right, m, x0, y0, x1, y1, a, b, c, value):  # pragma: no cover - compiled
    """:func:`.transfer._paint_affine`'s sampling and painting in one pass: the right image's
    columns the ROI's corners map to (a column's margin either side), each right pixel
    sampled back in ``m`` at ``rint((x + a + c y) / (1 - b))``; ``right`` painted with
    ``value`` where that is set; returns the painted rectangle (the sampled block clipped
    to the image; (0, 0, 0, 0) when outside it)."""
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


@jit
def _affine_fit(disp, ox, oy, x0, y0, x1, y1, lab, value, lo, hi, has_range, weak):  # pragma: no cover - compiled
    """``(ok, a, b, c)``: ``d = a + b x + c y`` least squares over the object's valid
    disparities (label ``value`` in ``lab``, within ``lo .. hi`` with ``has_range``;
    ``weak``: the range compared in float32, as a python float is) -- every
    ``n // 4000 + 1``-th in raster order above 4000, none below 30 (the normal equations on
    centred coordinates)."""
    bh, bw = y1 - y0, x1 - x0
    lo32, hi32 = np.float32(lo), np.float32(hi)
    px = np.empty(bh * bw, np.int64)
    py = np.empty(bh * bw, np.int64)
    pz = np.empty(bh * bw, np.float32)
    n = 0
    dh, dw = disp.shape
    for r in range(bh):
        yy = y0 + r - oy
        row_in = 0 <= yy < dh
        for c in range(bw):
            xx = x0 + c - ox
            v = disp[yy, xx] if row_in and 0 <= xx < dw else np.float32(0.0)
            if has_range:
                if weak:
                    inr = v >= lo32 and v <= hi32
                else:
                    inr = np.float64(v) >= lo and np.float64(v) <= hi
            else:
                inr = True
            # branch-free (half the disparities are holes: a branch mispredicts)
            px[n], py[n], pz[n] = c + x0, r + y0, v
            n += (lab[y0 + r, x0 + c] == value) & (v > 0) & inr
    if n < 30:
        return False, 0.0, 0.0, 0.0
    step = n // 4000 + 1 if n > 4000 else 1
    cnt = 0
    sx = sy = sz = 0.0
    for k in range(0, n, step):
        cnt += 1
        sx += np.float64(px[k])
        sy += np.float64(py[k])
        sz += np.float64(pz[k])
    mx, my, mz = sx / cnt, sy / cnt, sz / cnt
    sxx = sxy = syy = sxz = syz = 0.0
    for k in range(0, n, step):
        dx, dy, dz = np.float64(px[k]) - mx, np.float64(py[k]) - my, np.float64(pz[k]) - mz
        sxx += dx * dx
        sxy += dx * dy
        syy += dy * dy
        sxz += dx * dz
        syz += dy * dz
    if sxx == 0.0 or syy == 0.0:
        # the points on one row or column (or one pixel): lstsq's minimum-norm
        # solution, the constant shared by the collinear columns
        b = sxz / sxx if sxx > 0 else 0.0
        cc = syz / syy if syy > 0 else 0.0
        alpha = mz - b * mx - cc * my  # = a + b X0 (one column) / a + c Y0 (one row)
        qx = mx if sxx == 0.0 else 0.0
        qy = my if syy == 0.0 else 0.0
        q = 1.0 + qx * qx + qy * qy
        return True, alpha / q, b + alpha * qx / q, cc + alpha * qy / q
    det = sxx * syy - sxy * sxy
    if det == 0.0:  # collinear along a slant: left to the rigid shift
        return False, 0.0, 0.0, 0.0
    b = (sxz * syy - syz * sxy) / det
    cc = (syz * sxx - sxz * sxy) / det
    return True, mz - b * mx - cc * my, b, cc


@jit
def _grow(rect, i, rx0, ry0, rx1, ry1):  # pragma: no cover - compiled
    """Grow box ``i``'s painted rectangle by ``rx0, ry0, rx1, ry1`` (ignored when empty)."""
    if rx1 <= rx0 or ry1 <= ry0:
        return
    if rect[i, 2] <= rect[i, 0]:
        rect[i, 0], rect[i, 1], rect[i, 2], rect[i, 3] = rx0, ry0, rx1, ry1
    else:
        rect[i, 0], rect[i, 1] = min(rect[i, 0], rx0), min(rect[i, 1], ry0)
        rect[i, 2], rect[i, 3] = max(rect[i, 2], rx1), max(rect[i, 3], ry1)


@jit
def transfer_frame(left, disparities, rois, affine, disp, ox, oy, ranges, has_range, weak, dmin, dmax, max_slope,
                   occluded, occluded_margin, right, mask, pixels, models):  # pragma: no cover - compiled
    """:func:`.transfer.transfer_labels` of all the objects in one call: far to near, each
    object's left pixels (label ``i + 1`` in its ROI; with ``occluded`` also those of its box
    a nearer object covers) moved into ``right`` -- swept over ``dmin .. dmax`` without a
    disparity, by the affine model with ``affine`` (a good fit), else by the whole-pixel
    disparity -- and continued to the right border when the box touches the left image's;
    ``pixels`` and ``models`` (a, b, c) per object; ``mask``: 255 where any object is."""
    h, w = right.shape
    n = rois.shape[0]
    rect = np.zeros((n, 4), np.int64)
    for i in range(n):
        models[i, 0], models[i, 1], models[i, 2] = disparities[i], 0.0, 0.0
        pixels[i] = 0
    order = np.argsort(disparities, kind="mergesort")
    for t in range(n):
        i = order[t]
        x0, y0, x1, y1 = rois[i, 0], rois[i, 1], rois[i, 2], rois[i, 3]
        if x1 <= x0 or y1 <= y0:
            continue
        bh, bw = y1 - y0, x1 - x0
        value = i + 1
        d = disparities[i]
        m = np.zeros((bh, bw), np.bool_)
        n_own = 0
        for r in range(bh):
            for c in range(bw):
                lv = left[y0 + r, x0 + c]
                if lv == value:
                    m[r, c] = True
                    n_own += 1
                elif occluded and d > 0 and lv > 0 and disparities[lv - 1] > d + occluded_margin:
                    m[r, c] = True  # hidden behind a nearer object: the band past its edge
        if n_own == 0:
            continue
        if d <= 0:
            # unknown disparity: every shift over the matcher's range (a row's prefix counts)
            k = dmax - dmin + 1
            ox0 = x0 - (k - 1) - dmin  # the canvas' first column, in the right image
            cx0, cx1 = max(ox0, 0), min(ox0 + bw + k - 1, w)
            cy0, cy1 = max(y0, 0), min(y1, h)
            if cx1 > cx0 and cy1 > cy0:
                pre = np.zeros(bw + 1, np.int64)
                for r in range(bh):
                    for c in range(bw):
                        pre[c + 1] = pre[c] + (1 if m[r, c] else 0)
                    for x in range(cx0, cx1):
                        j = x - ox0  # canvas column: any m[:, j - s] for s in 0 .. k - 1
                        a, b = max(j - k + 1, 0), min(j + 1, bw)
                        if b > a and pre[b] - pre[a] > 0:
                            right[y0 + r, x] = value
                _grow(rect, i, cx0, cy0, cx1, cy1)
            models[i, 0], models[i, 1], models[i, 2] = 0.0, 0.0, 0.0
            continue
        ok = False
        a = b = cc = 0.0
        if affine:
            ok, a, b, cc = _affine_fit(disp, ox, oy, x0, y0, x1, y1, left, value, ranges[i, 0], ranges[i, 1],
                                       has_range, weak[i])
            ok = ok and abs(b) <= max_slope and abs(cc) <= max_slope
        border = x1 >= w - 3  # BORDER_TOUCH: the box is cut by the left image's right border
        if not ok:
            s = np.int64(np.rint(d))
            cx0, cy0 = max(x0 - s, 0), max(y0, 0)
            cx1, cy1 = min(x0 - s + bw, w), min(y1, h)
            if cx1 > cx0 and cy1 > cy0:
                for y in range(cy0, cy1):
                    for x in range(cx0, cx1):
                        if m[y - y0, x - x0 + s]:
                            right[y, x] = value
                _grow(rect, i, cx0, cy0, cx1, cy1)
            models[i, 0], models[i, 1], models[i, 2] = np.float64(s), 0.0, 0.0
        else:
            rx0, ry0, rx1, ry1 = affine_paint(right, m, x0, y0, x1, y1, a, b, cc, value)
            _grow(rect, i, rx0, ry0, rx1, ry1)
            models[i, 0], models[i, 1], models[i, 2] = a, b, cc
        if border:
            for r in range(bh):
                if left[y0 + r, x1 - 1] != value:
                    continue
                if ok:
                    st = np.int64(np.rint((x1 - 1) - ((a + b * (x1 - 1)) + cc * np.float64(y0 + r)))) + 1
                else:
                    st = x1 - np.int64(np.rint(d))
                st = min(max(st, 0), w)
                for x in range(st, w):
                    right[y0 + r, x] = value
                _grow(rect, i, st, y0 + r, w, y0 + r + 1)
    for i in range(n):
        c = 0
        for y in range(rect[i, 1], rect[i, 3]):
            for x in range(rect[i, 0], rect[i, 2]):
                if right[y, x] == i + 1:
                    c += 1
                if right[y, x] > 0:
                    mask[y, x] = 255
        pixels[i] = c
