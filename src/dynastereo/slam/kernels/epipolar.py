"""Triangulation's candidate search (ORB-SLAM2 ``SearchForTriangulation``) as one kernel a keyframe pair.

For each unmatched keypoint ``i`` of keyframe 1, :func:`epipolar_best` returns the keypoint
``j`` of keyframe 2 with the smallest Hamming distance (ties: the lower ``j``) among those that

* lie on ``i``'s epipolar line: ``(l·x_j)² / (l_0² + l_1²) < th2_j`` with ``l = F21 x_i``
  (``th2_j`` = 3.84 σ² of ``j``'s level),
* are within ``max_dist`` bits,
* are not, when both keypoints are monocular, within ``near2_j`` px² of the epipole
  (a monocular pair near the epipole has no parallax to triangulate from),
* and are among the ``k_nn`` (4) nearest descriptors of the whole keyframe 2: a match must
  be distinctive, not merely the best of the few keypoints the line crosses.

That is exactly what "the 4 nearest descriptors of each keypoint (``knn_hamming``), then
the line, the epipole and the best" gave (the version before this kernel), at less cost:
the line test (a vectorized pass of float tests) comes first, the Hamming distances of the
few percent on the line next, and only a keypoint with a match on its line is ranked
against all of keyframe 2, stopping once ``k_nn`` nearer ones are found.  ORB-SLAM2
compares the descriptors that share a vocabulary node instead (``tests/test_kernels.py``
checks this kernel against the plain all-pairs reference).
"""

from __future__ import annotations

import numpy as np

from ...compiled import cttz64, jit, popcount64
from .hamming import desc_words


@jit
def _epipolar_best(a, bt, u1, v1, mono1, u2, v2, mono2, th2, near2, F, ex, ey, has_ep, max_dist, k_nn, best, best_d):
    n1 = a.shape[0]
    n2 = bt.shape[1]
    nw = (n2 + 7) // 8
    flags = np.zeros(nw * 8, np.uint8)
    words = flags.view(np.uint64)
    b0, b1, b2, b3 = bt[0], bt[1], bt[2], bt[3]
    for i in range(n1):
        # the line l = F (u, v, 1)
        l0 = F[0, 0] * u1[i] + F[0, 1] * v1[i] + F[0, 2]
        l1 = F[1, 0] * u1[i] + F[1, 1] * v1[i] + F[1, 2]
        l2 = F[2, 0] * u1[i] + F[2, 1] * v1[i] + F[2, 2]
        den = l0 * l0 + l1 * l1
        wide = den * (1.0 + 1e-9)
        for j in range(n2):  # vectorizes: no branch, no division (a slightly wider band)
            num = l0 * u2[j] + l1 * v2[j] + l2
            flags[j] = num * num < th2[j] * wide
        a0, a1, a2, a3 = a[i, 0], a[i, 1], a[i, 2], a[i, 3]
        bd = max_dist + 1
        bj = -1
        for w in range(nw):  # 8 flag bytes a word: the few on the line, by their set bits
            x = words[w]
            while x != 0:
                j = 8 * w + np.int64(cttz64(x) >> np.uint64(3))
                x &= x - np.uint64(1)
                d = popcount64(a0 ^ b0[j]) + popcount64(a1 ^ b1[j]) + popcount64(a2 ^ b2[j]) + popcount64(a3 ^ b3[j])
                if d >= bd:
                    continue
                num = l0 * u2[j] + l1 * v2[j] + l2
                if not num * num / den < th2[j]:  # the exact test, as numpy wrote it
                    continue
                if has_ep and mono1[i] and mono2[j]:
                    dx = u2[j] - ex
                    dy = v2[j] - ey
                    if dx * dx + dy * dy < near2[j]:
                        continue
                bd = d
                bj = j
        if bj >= 0 and k_nn > 0:
            # among the k_nn nearest of all keyframe 2 (ties: the lower index first)?
            rank = 0
            for j0 in range(0, n2, 64):
                for j in range(j0, min(j0 + 64, n2)):
                    d = popcount64(a0 ^ b0[j]) + popcount64(a1 ^ b1[j]) + popcount64(a2 ^ b2[j]) + popcount64(a3 ^ b3[j])
                    rank += (d < bd) | ((d == bd) & (j < bj))
                if rank >= k_nn:
                    bj = -1
                    break
        best[i] = bj
        best_d[i] = bd if bj >= 0 else -1


def epipolar_best(desc1: np.ndarray, uv1: np.ndarray, mono1: np.ndarray, desc2: np.ndarray, uv2: np.ndarray,
                  mono2: np.ndarray, th2: np.ndarray, near2: np.ndarray, F21: np.ndarray,
                  epipole: tuple[float, float] | None, max_dist: int, k_nn: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(best (N1,) int64: index into keyframe 2's rows, -1 none; dist (N1,) int64) -- module doc.
    ``desc*``: (N, 32) uint8; ``uv*``: (N, 2) pixels; ``mono*``: (N,) no stereo depth;
    ``th2`` / ``near2``: (N2,) per keypoint of keyframe 2; ``F21``: 3x3, ``x2ᵀ F21 x1 = 0``;
    ``epipole``: keyframe 1's centre in keyframe 2's image (None: at infinity); ``k_nn``: the
    match must be among the ``k_nn`` nearest descriptors of all keyframe 2 (0: any)."""
    n1 = len(desc1)
    best = np.full(n1, -1, np.int64)
    dist = np.full(n1, -1, np.int64)
    if n1 == 0 or len(desc2) == 0:
        return best, dist
    uv1 = np.asarray(uv1, np.float64)
    uv2 = np.asarray(uv2, np.float64)
    ex, ey = (0.0, 0.0) if epipole is None else (float(epipole[0]), float(epipole[1]))
    _epipolar_best(desc_words(desc1), np.ascontiguousarray(desc_words(desc2).T),
                   np.ascontiguousarray(uv1[:, 0]), np.ascontiguousarray(uv1[:, 1]),
                   np.ascontiguousarray(mono1, np.bool_),
                   np.ascontiguousarray(uv2[:, 0]), np.ascontiguousarray(uv2[:, 1]),
                   np.ascontiguousarray(mono2, np.bool_), np.ascontiguousarray(th2, np.float64),
                   np.ascontiguousarray(near2, np.float64), np.ascontiguousarray(F21, np.float64),
                   ex, ey, epipole is not None, int(max_dist), min(int(k_nn), len(desc2)), best, dist)
    return best, dist
