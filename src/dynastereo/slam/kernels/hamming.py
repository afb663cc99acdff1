"""Hamming distances of ORB descriptors: k nearest neighbours by brute force.

``knn_hamming(a, b, k)`` is ``cv2.batchDistance(a, b, CV_32S, NORM_HAMMING, K=k)``:
the same distances, the same neighbours and the same order of ties (the lower index
first), ``k`` capped at the rows of ``b`` as OpenCV does -- without OpenCV's
per-pair function call and K-insertion over every candidate.
"""

from __future__ import annotations

import numpy as np

from ._numba import jit, popcount64

INT_MAX = np.iinfo(np.int32).max


def desc_words(desc: np.ndarray) -> np.ndarray:
    """(N, 32) uint8 descriptors as (N, 4) uint64 words (a view where possible)."""
    d = np.ascontiguousarray(desc, dtype=np.uint8)
    return d.reshape(len(d), 32).view(np.uint64)


@jit
def hamming64(a, i, b, j):
    """Hamming distance of rows ``a[i]`` and ``b[j]`` (uint64 words)."""
    s = 0
    for w in range(a.shape[1]):
        s += popcount64(a[i, w] ^ b[j, w])
    return s


@jit
def _knn(a, b, k, dist, idx):
    na, nb = a.shape[0], b.shape[0]
    for i in range(na):
        for t in range(k):
            dist[i, t] = INT_MAX
            idx[i, t] = -1
        a0, a1, a2, a3 = a[i, 0], a[i, 1], a[i, 2], a[i, 3]
        for j in range(nb):
            d = np.int32(popcount64(a0 ^ b[j, 0]) + popcount64(a1 ^ b[j, 1]) + popcount64(a2 ^ b[j, 2]) + popcount64(a3 ^ b[j, 3]))
            if d < dist[i, k - 1]:
                t = k - 2
                while t >= 0 and dist[i, t] > d:
                    dist[i, t + 1] = dist[i, t]
                    idx[i, t + 1] = idx[i, t]
                    t -= 1
                dist[i, t + 1] = d
                idx[i, t + 1] = j


def knn_hamming(a: np.ndarray, b: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(dist (Na, k) int32, idx (Na, k) int32) of the ``k`` nearest rows of ``b`` for each
    row of ``a`` ((N, 32) uint8 descriptors), as ``cv2.batchDistance`` with ``K=k``."""
    a64, b64 = desc_words(a), desc_words(b)
    k = min(int(k), len(b64))  # as OpenCV: at most as many neighbours as rows of b
    dist = np.empty((len(a64), k), np.int32)
    idx = np.empty((len(a64), k), np.int32)
    if k > 0 and len(a64):
        _knn(a64, b64, k, dist, idx)
    return dist, idx
