"""Search by projection as one compiled call (ORB-SLAM2 ``ORBmatcher::SearchByProjection`` / ``Fuse``).

``search_by_projection_kernel`` walks, for each projected point, the cells of the
keypoint grid (``matcher.KeypointGrid``: keypoints sorted by cell) under its square
window, applies the level / availability / right-image / chi2 checks, keeps the best and
second-best Hamming distance (and the second's level for the ratio test), then gives each
keypoint to its closest point.  Candidates are visited in the order the numpy version
lists them (rows, then cells, then keypoints by index), ties keep the first, and the
result is ordered by keypoint as ``geometry.unique_best`` orders it: the matches are
identical to the numpy reference's (``tests/reference/slam_numpy.py``).
"""

from __future__ import annotations

import math

import numpy as np

from ...compiled import jit, popcount64


@jit
def search_by_projection_kernel(
    kp_uv, g_order, g_start, ncx, ncy, cell, kp_octave, kp_desc, kp_uR, has_uR, kp_avail, has_avail,
    u, v, radius, q_desc, min_level, has_min, max_level, has_max, u_right, has_ur,
    kis2, has_reproj, th_dist, ratio, has_ratio, same_level_only, chi2_mono, chi2_stereo,
    out_q, out_k, out_d,
):
    """Matches written to ``out_q`` / ``out_k`` / ``out_d`` (ordered by keypoint); returns their count."""
    nq = u.shape[0]
    nk = kp_uv.shape[0]
    best_k = np.full(nq, -1, np.int64)
    best_d = np.zeros(nq, np.int64)
    stereo_chk = has_ur and has_uR
    for q in range(nq):
        uq, vq, rq = u[q], v[q], radius[q]
        x0 = min(max(int(math.floor((uq - rq) / cell)), 0), ncx - 1)
        x1 = min(max(int(math.floor((uq + rq) / cell)), 0), ncx - 1)
        y0 = min(max(int(math.floor((vq - rq) / cell)), 0), ncy - 1)
        y1 = min(max(int(math.floor((vq + rq) / cell)), 0), ncy - 1)
        d1 = 1 << 30
        k1 = -1
        d2 = 1 << 30
        k2 = -1
        for row in range(y0, y1 + 1):
            s = g_start[row * ncx + x0]
            e = g_start[row * ncx + x1 + 1]
            for p in range(s, e):
                k = g_order[p]
                if not (abs(kp_uv[k, 0] - uq) < rq and abs(kp_uv[k, 1] - vq) < rq):
                    continue
                if has_avail and not kp_avail[k]:
                    continue
                if has_min and kp_octave[k] < min_level[q]:
                    continue
                if has_max and kp_octave[k] > max_level[q]:
                    continue
                st = False
                if stereo_chk:
                    st = kp_uR[k] >= 0
                    if st and not (abs(u_right[q] - kp_uR[k]) <= rq):
                        continue
                if has_reproj:
                    e2 = (uq - kp_uv[k, 0]) ** 2 + (vq - kp_uv[k, 1]) ** 2
                    th = chi2_mono
                    if stereo_chk:
                        e2 = e2 + ((u_right[q] - kp_uR[k]) ** 2 if st else 0.0)
                        if st:
                            th = chi2_stereo
                    if not (e2 * kis2[k] <= th):
                        continue
                d = (popcount64(q_desc[q, 0] ^ kp_desc[k, 0]) + popcount64(q_desc[q, 1] ^ kp_desc[k, 1])
                     + popcount64(q_desc[q, 2] ^ kp_desc[k, 2]) + popcount64(q_desc[q, 3] ^ kp_desc[k, 3]))
                if d < d1:
                    d2 = d1
                    k2 = k1
                    d1 = d
                    k1 = k
                elif d < d2:
                    d2 = d
                    k2 = k
        if k1 < 0 or d1 > th_dist:
            continue
        if has_ratio:
            if same_level_only:
                if k2 >= 0 and kp_octave[k2] == kp_octave[k1] and d1 > ratio * d2:
                    continue
            elif not (d1 <= ratio * d2):
                continue
        best_k[q] = k1
        best_d[q] = d1
    # one point per keypoint: the smallest distance, then the lowest query index
    owner = np.full(nk, -1, np.int64)
    for q in range(nq):
        k = best_k[q]
        if k < 0:
            continue
        o = owner[k]
        if o < 0 or best_d[q] < best_d[o]:
            owner[k] = q
    n = 0
    for k in range(nk):
        q = owner[k]
        if q >= 0:
            out_q[n] = q
            out_k[n] = k
            out_d[n] = best_d[q]
            n += 1
    return n
