"""Stereo matching of one frame as one compiled call (ORB-SLAM2 ``Frame::ComputeStereoMatches``).

``stereo_match_kernel`` does every step of ``matcher.stereo_match`` for all left keypoints:

1. candidates: right keypoints of the octaves ``o-1..o+1`` whose row lies within
   ``2 * scale[o]`` (``o`` the right keypoint's octave) of the left row, disparity in
   ``[min_d, max_d]``; the right keypoints come sorted by (octave, row) so that each band
   is a binary search;
2. the smallest Hamming distance (<= ``th_dist``); ties go to the candidate the numpy
   version lists first (lower octave, then lower row, then lower index);
3. SAD of 11x11 windows (brightness offset removed with the centre pixel) at
   ``2L + 1`` shifts along the row of the full-resolution images, parabola through the
   minimum and its neighbours;
4. the disparity checks and the median-based SAD outlier rejection.

Integers are the same as numpy's and the floats are computed term by term in the same
order, so the matches and sub-pixel positions are identical to the numpy version's.
"""

from __future__ import annotations

import numpy as np

from ...compiled import jit, popcount64


@jit
def stereo_match_kernel(u_l, v_l, ul_i, vl_i, oct_l, d_l, u_r_s, v_r_s, ur_i_s, d_r_s, oct_start,
                        img_l, img_r, scales, min_d, max_d, th_dist, bf, u_right, depth):
    """Fill ``u_right`` / ``depth`` (preset to -1) for the left keypoints.

    Left keypoints: ``u_l``/``v_l`` (float), ``ul_i``/``vl_i`` (rounded), ``oct_l``, ``d_l``
    ((N, 4) uint64 descriptor words).  Right keypoints sorted by (octave, row): ``u_r_s``,
    ``v_r_s``, ``ur_i_s`` (rounded u), ``d_r_s``;
    ``oct_start[o]:oct_start[o+1]`` is octave ``o``.  Returns the number of matches.
    """
    n = u_l.shape[0]
    n_oct = oct_start.shape[0] - 1
    best_j = np.full(n, -1, np.int64)  # position in the sorted right arrays
    nm = 0
    max_oct = -1
    for i in range(n):
        ol = oct_l[i]
        bd = 1 << 30
        bj = -1
        for o in range(max(0, ol - 1), min(n_oct, ol + 2)):
            s, e = oct_start[o], oct_start[o + 1]
            if s == e:
                continue
            r = 2.0 * scales[o]
            lo_v = v_l[i] - r
            hi_v = v_l[i] + r
            # first row >= lo_v (searchsorted left)
            a, b = s, e
            while a < b:
                m = (a + b) >> 1
                if v_r_s[m] < lo_v:
                    a = m + 1
                else:
                    b = m
            j = a
            while j < e and v_r_s[j] <= hi_v:
                disp = u_l[i] - u_r_s[j]
                if disp >= min_d and disp <= max_d:
                    d = (popcount64(d_l[i, 0] ^ d_r_s[j, 0]) + popcount64(d_l[i, 1] ^ d_r_s[j, 1])
                         + popcount64(d_l[i, 2] ^ d_r_s[j, 2]) + popcount64(d_l[i, 3] ^ d_r_s[j, 3]))
                    if d < bd:
                        bd = d
                        bj = j
                j += 1
        if bj >= 0 and bd <= th_dist:
            best_j[i] = bj
            nm += 1
            if ol > max_oct:
                max_oct = ol
    if nm == 0:
        return 0
    w = 5
    L = 5 + int(np.ceil(0.5 * scales[max_oct]))
    H0, W0 = img_l.shape
    ns = 2 * L + 1
    sad = np.empty(ns, np.float64)
    PL = np.empty((2 * w + 1, 2 * w + 1), np.int64)
    li = np.empty(nm, np.int64)
    ur_best = np.empty(nm, np.float64)
    sad_best = np.empty(nm, np.float64)
    k = 0
    for i in range(n):
        j = best_j[i]
        if j < 0:
            continue
        li[k] = i
        ul = ul_i[i]
        vl = vl_i[i]
        ur0 = ur_i_s[j]
        valid = (vl - w >= 0) and (vl + w < H0) and (ul - w >= 0) and (ul + w < W0) and (ur0 - L - w >= 0) and (ur0 + L + w < W0)
        if not valid:
            ur_best[k] = np.nan
            sad_best[k] = np.inf
            k += 1
            continue
        c = np.int64(img_l[vl, ul])
        for dy in range(2 * w + 1):
            for dx in range(2 * w + 1):
                PL[dy, dx] = np.int64(img_l[vl - w + dy, ul - w + dx]) - c
        bsad = np.inf
        b = 0
        for t in range(ns):
            x0 = ur0 - L - w + t  # left column of the window at shift t
            cr = np.int64(img_r[vl, x0 + w])
            acc = 0
            for dy in range(2 * w + 1):
                row = vl - w + dy
                for dx in range(2 * w + 1):
                    acc += abs(np.int64(img_r[row, x0 + dx]) - cr - PL[dy, dx])
            sad[t] = acc
            if sad[t] < bsad:
                bsad = sad[t]
                b = t
        bi = min(max(b, 1), 2 * L - 1)
        d1, d2, d3 = sad[bi - 1], sad[bi], sad[bi + 1]
        den = 2.0 * (d1 + d3 - 2.0 * d2)
        delta = (d1 - d3) / den if den != 0 else 0.0
        if b > 0 and b < 2 * L and abs(delta) <= 1.0:
            sad_best[k] = sad[b]
            ur_best[k] = u_l[i] - (ul - ((ur0 + (b - L)) + delta))
        else:
            sad_best[k] = np.inf
            ur_best[k] = np.nan
        k += 1
    # disparity range, then SAD > 1.5 * 1.4 * median dropped
    ok = np.zeros(nm, np.bool_)
    disp = np.empty(nm, np.float64)
    nok = 0
    for k in range(nm):
        disp[k] = u_l[li[k]] - ur_best[k]
        if np.isfinite(ur_best[k]) and disp[k] >= min_d and disp[k] < max_d:
            ok[k] = True
            nok += 1
    if nok == 0:
        return 0
    vals = np.empty(nok, np.float64)
    t = 0
    for k in range(nm):
        if ok[k]:
            vals[t] = sad_best[k]
            t += 1
    med = np.median(vals)
    th = 1.5 * 1.4 * med
    out = 0
    for k in range(nm):
        if ok[k] and sad_best[k] <= th:
            dk = disp[k] if disp[k] > 0 else 0.01
            u_right[li[k]] = u_l[li[k]] - dk
            depth[li[k]] = bf / dk
            out += 1
    return out
