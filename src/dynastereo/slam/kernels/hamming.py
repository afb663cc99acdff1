"""Hamming distances of ORB descriptors: k nearest neighbours by brute force.

``knn_hamming(a, b, k)`` is ``cv2.batchDistance(a, b, CV_32S, NORM_HAMMING, K=k)``:
the same distances, the same neighbours and the same order of ties (the lower index
first), ``k`` capped at the rows of ``b`` as OpenCV does -- without OpenCV's
per-pair function call and K-insertion over every candidate.
"""

from __future__ import annotations

import numpy as np

from ...compiled import jit, popcount64

INT_MAX = np.iinfo(np.int32).max


def desc_words(desc: np.ndarray) -> np.ndarray:
    """(N, 32) uint8 descriptors as (N, 4) uint64 words (a view where possible)."""
    d = np.ascontiguousarray(desc, dtype=np.uint8)
    return d.reshape(len(d), 32).view(np.uint64)


@jit
def _knn(a, bt, k, dist, idx):
    """k nearest columns of ``bt`` ((4, Nb) words: the loop over them vectorizes) for each row of ``a``."""
    na = a.shape[0]
    nb = bt.shape[1]
    buf = np.empty(nb, np.int16)  # distances <= 256: half the int32 buffer's traffic (~15 % faster)
    b0, b1, b2, b3 = bt[0], bt[1], bt[2], bt[3]
    for i in range(na):
        a0, a1, a2, a3 = a[i, 0], a[i, 1], a[i, 2], a[i, 3]
        for j in range(nb):
            buf[j] = np.int16(popcount64(a0 ^ b0[j]) + popcount64(a1 ^ b1[j]) + popcount64(a2 ^ b2[j]) + popcount64(a3 ^ b3[j]))
        for t in range(k):
            dist[i, t] = INT_MAX
            idx[i, t] = -1
        worst = INT_MAX
        for j in range(nb):  # OpenCV's insertion: strict <, ties keep the lower index
            d = buf[j]
            if d < worst:
                t = k - 2
                while t >= 0 and dist[i, t] > d:
                    dist[i, t + 1] = dist[i, t]
                    idx[i, t + 1] = idx[i, t]
                    t -= 1
                dist[i, t + 1] = d
                idx[i, t + 1] = j
                worst = dist[i, k - 1]


def knn_hamming(a: np.ndarray, b: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(dist (Na, k) int32, idx (Na, k) int32) of the ``k`` nearest rows of ``b`` for each
    row of ``a`` ((N, 32) uint8 descriptors), as ``cv2.batchDistance`` with ``K=k``."""
    a64, b64 = desc_words(a), desc_words(b)
    k = min(int(k), len(b64))  # as OpenCV: at most as many neighbours as rows of b
    dist = np.empty((len(a64), k), np.int32)
    idx = np.empty((len(a64), k), np.int32)
    if k > 0 and len(a64):
        _knn(a64, np.ascontiguousarray(b64.T), k, dist, idx)
    return dist, idx


@jit
def descend_tree(d64, centres, penalty, k, record_level):
    """A vocabulary tree's descent (``Vocabulary._descend``) for every descriptor:
    ``d64`` (N, 4) words; ``centres[l]`` ((k**l, k, 4) words) and ``penalty[l]``
    ((k**l, k) int32, large for an invalid child) of level ``l + 1``.  At each level the
    nearest child (Hamming + penalty; ties to the lower child, as ``argmin``).  Returns
    (leaf slot, slot at ``record_level``) per descriptor."""
    n = d64.shape[0]
    leaf = np.zeros(n, np.int64)
    rec = np.zeros(n, np.int64)
    levels = len(centres)
    for i in range(n):
        a0, a1, a2, a3 = d64[i, 0], d64[i, 1], d64[i, 2], d64[i, 3]
        node = np.int64(0)
        for lv in range(levels):
            C = centres[lv]
            P = penalty[lv]
            best = np.int32(0)
            bd = np.int32(0)
            for c in range(k):
                d = np.int32(popcount64(a0 ^ C[node, c, 0]) + popcount64(a1 ^ C[node, c, 1])
                             + popcount64(a2 ^ C[node, c, 2]) + popcount64(a3 ^ C[node, c, 3])) + P[node, c]
                if c == 0 or d < bd:
                    bd = d
                    best = c
            node = node * k + best
            if lv + 1 == record_level:
                rec[i] = node
        leaf[i] = node
    return leaf, rec
