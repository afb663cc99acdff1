"""The ORB extractor's spreading of corners over the image (``ORBExtractor._bucket``) as one
compiled call: per pyramid level, grid cells of about one quota-th of the image; corners
ranked within their cell by FAST response; rank 0 of every cell first, then rank 1, ...,
strongest first, until the level's quota is met.

It gives the indices that two ``np.lexsort`` passes gave (cell then response; level then
rank then response; ties always to the lower index) -- the same corners -- with one
stable sort by response and counting passes.
"""

from __future__ import annotations

import math

import numpy as np

from ...compiled import jit


@jit
def _strongest_first(resp):
    """Indices by decreasing response, ties to the lower index (a stable sort of -resp):
    a counting sort when the responses are small whole numbers (FAST scores), else a
    merge sort."""
    n = resp.shape[0]
    integral = True
    top = 0
    for i in range(n):
        r = resp[i]
        if not (r >= 0.0 and r <= 4096.0 and r == math.floor(r)):
            integral = False
            break
        if np.int64(r) > top:
            top = np.int64(r)
    if not integral:
        return np.argsort(-resp, kind="mergesort")
    start = np.zeros(top + 2, np.int64)
    for i in range(n):
        start[top - np.int64(resp[i]) + 1] += 1
    for b in range(1, top + 2):
        start[b] += start[b - 1]
    out = np.empty(n, np.int64)
    for i in range(n):
        b = top - np.int64(resp[i])
        out[start[b]] = i
        start[b] += 1
    return out


@jit
def bucket_corners(u, v, resp, lev, quota, W, H):
    """Indices (sorted) of the corners kept: ``u``, ``v`` level-0 positions, ``resp`` FAST
    responses (float32), ``lev`` pyramid levels (clipped to the quota's levels),
    ``quota`` (L,) corners wanted per level, ``W`` x ``H`` the image size."""
    n = u.shape[0]
    L = quota.shape[0]
    keep = np.empty(0, np.int64)
    if n == 0:
        return keep
    # cells per level: cell side sqrt(W H / quota) in level-0 pixels
    cell = np.empty(L, np.float64)
    ncx = np.empty(L, np.int64)
    for lv in range(L):
        q = quota[lv] if quota[lv] > 1 else 1
        cell[lv] = math.sqrt(W * H / q)
        ncx[lv] = np.int64(math.ceil(W / cell[lv]))
    lv_of = np.empty(n, np.int64)
    cx = np.empty(n, np.int64)
    cy = np.empty(n, np.int64)
    ncy = np.ones(L, np.int64)
    for i in range(n):
        lv = min(max(np.int64(lev[i]), 0), L - 1)
        lv_of[i] = lv
        cx[i] = min(np.int64(u[i] / cell[lv]), ncx[lv] - 1)
        cy[i] = np.int64(v[i] / cell[lv])
        if cy[i] + 1 > ncy[lv]:
            ncy[lv] = cy[i] + 1
    first = np.empty(L + 1, np.int64)  # each level's first cell id
    first[0] = 0
    for lv in range(L):
        first[lv + 1] = first[lv] + ncx[lv] * ncy[lv]
    cid = np.empty(n, np.int64)
    for i in range(n):
        cid[i] = first[lv_of[i]] + cy[i] * ncx[lv_of[i]] + cx[i]
    by_resp = _strongest_first(resp)
    # rank within the cell, in that order
    count = np.zeros(first[L], np.int64)
    rank = np.empty(n, np.int64)
    for r in range(n):
        i = by_resp[r]
        rank[i] = count[cid[i]]
        count[cid[i]] += 1
    # level, then rank, then response: per level, every corner of rank < R and the
    # strongest of rank R, R the rank at which the level's quota is met
    maxr = 0
    for i in range(n):
        if rank[i] > maxr:
            maxr = rank[i]
    hist = np.zeros((L, maxr + 1), np.int64)
    for i in range(n):
        hist[lv_of[i], rank[i]] += 1
    R = np.full(L, maxr + 1, np.int64)
    rem = np.zeros(L, np.int64)
    for lv in range(L):
        acc = 0
        for r in range(maxr + 1):
            if acc + hist[lv, r] > quota[lv]:
                R[lv] = r
                rem[lv] = quota[lv] - acc
                break
            acc += hist[lv, r]
    sel = np.zeros(n, np.bool_)
    m = 0
    for r in range(n):
        i = by_resp[r]
        lv = lv_of[i]
        if rank[i] < R[lv]:
            sel[i] = True
            m += 1
        elif rank[i] == R[lv] and rem[lv] > 0:
            rem[lv] -= 1
            sel[i] = True
            m += 1
    keep = np.empty(m, np.int64)
    m = 0
    for i in range(n):
        if sel[i]:
            keep[m] = i
            m += 1
    return keep
