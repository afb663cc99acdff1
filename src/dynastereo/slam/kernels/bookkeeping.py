"""The map's bookkeeping as compiled kernels: exact integer / array work over the map's
tables, one call per operation instead of chains of small numpy calls.

* ``rows_of``: the alive observation rows of a set of points (walking the per-point
  linked lists of :class:`~..observations.Observations`), sorted;
* ``new_observations``: which of the candidate ``(keypoint, point)`` pairs a keyframe
  takes (``Map.add_observations``'s rule: free keypoint, good point not yet observed by
  the keyframe, one keypoint per point and one point per keypoint);
* ``update_points``: viewing normals, scale-invariance distances and distinctive
  descriptors of points from their observations (``Map.update_points``);
* ``by_keyframe``: observation rows grouped by keyframe (a stable counting order).

They do what the numpy code they replaced did, in the same order, so the map's contents
are the same to the bit (the normals are summed in row order, as ``np.add.at`` did; the
norms as ``np.linalg.norm``: ``(x*x + y*y) + z*z``); ``tests/test_map_kernels.py``
compares them with plain numpy references on random and real maps.
"""

from __future__ import annotations

import numpy as np

from ...compiled import jit, popcount64


@jit
def rows_of(head, next_row, alive, pts):
    """Alive rows of the points ``pts`` (any order, duplicates and ``-1`` allowed),
    sorted: the union of their lists, as ``Observations.rows_of``.  Sorted by marking
    them over the rows when there are many (a pass over the table), else by a sort."""
    s = np.sort(pts)
    total = 0
    top = -1
    prev = -1
    for i in range(s.shape[0]):
        p = s[i]
        if p < 0 or p == prev:
            continue
        prev = p
        r = head[p]
        steps = 0
        while r >= 0:
            if alive[r]:
                total += 1
                if r > top:
                    top = r
            r = next_row[r]
            steps += 1
            if steps > next_row.shape[0]:  # a list longer than the table loops: never walk it forever
                raise ValueError("observation list of a point forms a cycle")
    out = np.empty(total, np.int64)
    if total == 0:
        return out
    use_marks = 6.0 * total * np.log2(total + 1.0) > top + 1
    mark = np.zeros(top + 1 if use_marks else 0, np.bool_)
    k = 0
    prev = -1
    for i in range(s.shape[0]):
        p = s[i]
        if p < 0 or p == prev:
            continue
        prev = p
        r = head[p]
        steps = 0
        while r >= 0 and steps <= next_row.shape[0]:
            steps += 1
            if alive[r]:
                if use_marks:
                    mark[r] = True
                else:
                    out[k] = r
                    k += 1
            r = next_row[r]
    if use_marks:
        for r in range(top + 1):
            if mark[r]:
                out[k] = r
                k += 1
    else:
        out.sort()
    return out


@jit
def by_keyframe(kfs):
    """(order, keyframe ids, starts): ``kfs[order]`` grouped by keyframe id (ids >= 0),
    ascending, each group in the rows' own order (a counting sort, stable); group ``g``
    is ``order[starts[g]:starts[g + 1]]``."""
    n = kfs.shape[0]
    top = -1
    for i in range(n):
        if kfs[i] > top:
            top = kfs[i]
    cnt = np.zeros(top + 2, np.int64)
    for i in range(n):
        cnt[kfs[i] + 1] += 1
    ng = 0
    for k in range(top + 1):
        if cnt[k + 1] > 0:
            ng += 1
    ids = np.empty(ng, np.int64)
    starts = np.empty(ng + 1, np.int64)
    g = 0
    for k in range(top + 1):  # cnt becomes each id's first position
        c = cnt[k + 1]
        if c > 0:
            ids[g] = k
            starts[g] = cnt[k]
            g += 1
        cnt[k + 1] = cnt[k] + c
    starts[ng] = n
    order = np.empty(n, np.int64)
    for i in range(n):
        k = kfs[i]
        order[cnt[k]] = i
        cnt[k] += 1
    return order, ids, starts


@jit
def unseen_good(pts, bad, kf_point_ids):
    """Mask of ``pts``: a good point (``>= 0``, not bad) that the keyframe whose
    per-keypoint points are ``kf_point_ids`` does not observe.  The queried points are
    sorted, not the keyframe's: a pass over the keyframe's keypoints with a binary
    search each (``pts`` is often a handful, the keyframe's keypoints thousands)."""
    n = pts.shape[0]
    out = np.zeros(n, np.bool_)
    if n == 0:
        return out
    order = np.argsort(pts)
    sp = pts[order]
    seen = np.zeros(n, np.bool_)  # by sorted position
    for j in range(kf_point_ids.shape[0]):
        q = kf_point_ids[j]
        if q < 0:
            continue
        t = np.searchsorted(sp, q)
        while t < n and sp[t] == q and not seen[t]:
            seen[t] = True
            t += 1
    for t in range(n):
        i = order[t]
        p = sp[t]
        out[i] = p >= 0 and not bad[p] and not seen[t]
    return out


@jit
def unique_good(ids, bad):
    """The distinct good points (``>= 0``, not bad) of ``ids``, sorted, as
    ``np.unique`` then the good test (a mark per point id, then one pass over them)."""
    top = -1
    for i in range(ids.shape[0]):
        if ids[i] > top:
            top = ids[i]
    mark = np.zeros(top + 1, np.bool_)
    m = 0
    for i in range(ids.shape[0]):
        p = ids[i]
        if p >= 0 and not mark[p] and not bad[p]:
            mark[p] = True
            m += 1
    out = np.empty(m, np.int64)
    k = 0
    for p in range(top + 1):
        if mark[p]:
            out[k] = p
            k += 1
    return out


@jit
def new_observations(kf_point_ids, kp, pts, bad):
    """Which pairs ``(kp[i], pts[i])`` keyframe a keyframe takes, as a mask: its keypoint
    is free, the point is good and not yet observed by the keyframe; of pairs naming the
    same point the first is taken, then of the remaining pairs naming the same keypoint
    the one with the lowest point id (``np.unique``'s first occurrence, in that order)."""
    n = kp.shape[0]
    keep = np.zeros(n, np.bool_)
    fresh = unseen_good(pts, bad, kf_point_ids)
    cand = np.empty(n, np.int64)
    c = 0
    for i in range(n):
        if fresh[i] and kf_point_ids[kp[i]] < 0:
            cand[c] = i
            c += 1
    if c == 0:
        return keep
    cand = cand[:c]
    # by point id, then by position: the first pair of each point
    order = np.argsort(pts[cand], kind="mergesort")
    taken = np.zeros(kf_point_ids.shape[0], np.bool_)
    prev = -1
    for t in range(c):
        i = cand[order[t]]
        p = pts[i]
        if p == prev:
            continue
        prev = p
        if taken[kp[i]]:
            continue
        taken[kp[i]] = True
        keep[i] = True
    return keep


@jit
def update_points(pts, rows, ptr, kf_ids, centers, levels, descs, w, pos, ref_kf, normal, max_dist, min_dist,
                  desc, scales, max_obs):
    """``Map.update_points`` over the alive rows ``rows`` (sorted) of the points ``pts``
    (sorted, unique, good): per row its point ``ptr``, keyframe ``kf_ids``, that
    keyframe's centre ``centers``, the keypoint's level and descriptor (``descs``,
    (R, 32) uint8; ``w`` the same as (R, 4) uint64 words).  Writes the points' ``normal``, ``max_dist`` / ``min_dist`` (from
    the reference keyframe's observation; a point whose reference keyframe no longer
    observes it gets its first observer, lowest row, as reference) and ``desc`` (the
    observation, among the newest ``max_obs``, with the least median Hamming distance
    to the others)."""
    P = pts.shape[0]
    R = rows.shape[0]
    loc = np.searchsorted(pts, ptr)
    cnt = np.zeros(P, np.int64)
    for r in range(R):
        cnt[loc[r]] += 1
    start = np.zeros(P + 1, np.int64)
    for p in range(P):
        start[p + 1] = start[p] + cnt[p]
    # rows of each point, ascending (rows are sorted): a stable counting sort
    grp = np.empty(R, np.int64)
    fill = start[:P].copy()
    for r in range(R):
        grp[fill[loc[r]]] = r
        fill[loc[r]] += 1
    nv = np.zeros(R)
    dd = np.empty((max_obs, max_obs), np.int64)
    med = np.empty(max_obs, np.int64)
    tmp = np.empty(max_obs, np.int64)
    for p in range(P):
        a, b = start[p], start[p + 1]
        if a == b:
            continue
        pid = pts[p]
        ax = 0.0
        ay = 0.0
        az = 0.0
        has_ref = False
        for t in range(a, b):
            r = grp[t]
            vx = pos[pid, 0] - centers[r, 0]
            vy = pos[pid, 1] - centers[r, 1]
            vz = pos[pid, 2] - centers[r, 2]
            n = np.sqrt(vx * vx + vy * vy + vz * vz)
            nv[r] = n
            d = max(n, 1e-12)
            ax += vx / d
            ay += vy / d
            az += vz / d
            if ref_kf[pid] == kf_ids[r]:
                has_ref = True
        c = float(b - a)
        ax /= c
        ay /= c
        az /= c
        nn = max(np.sqrt(ax * ax + ay * ay + az * az), 1e-12)
        normal[pid, 0] = ax / nn
        normal[pid, 1] = ay / nn
        normal[pid, 2] = az / nn
        if not has_ref:
            ref_kf[pid] = kf_ids[grp[a]]
        for t in range(a, b):
            r = grp[t]
            if ref_kf[pid] == kf_ids[r]:
                md = nv[r] * scales[levels[r]]
                max_dist[pid] = md
                min_dist[pid] = md / scales[scales.shape[0] - 1]
        # distinctive descriptor: the newest max_obs observations, newest first
        k = min(b - a, max_obs)
        for i in range(k):
            ri = grp[b - 1 - i]
            for j in range(k):
                rj = grp[b - 1 - j]
                dd[i, j] = (popcount64(w[ri, 0] ^ w[rj, 0]) + popcount64(w[ri, 1] ^ w[rj, 1])
                            + popcount64(w[ri, 2] ^ w[rj, 2]) + popcount64(w[ri, 3] ^ w[rj, 3]))
        mi = (k - 1) // 2
        best = 0
        for i in range(k):
            for j in range(k):  # insertion sort of the row (k <= max_obs)
                x = dd[i, j]
                q = j - 1
                while q >= 0 and tmp[q] > x:
                    tmp[q + 1] = tmp[q]
                    q -= 1
                tmp[q + 1] = x
            med[i] = tmp[mi]
            if med[i] < med[best]:
                best = i
        rb = grp[b - 1 - best]
        for q in range(32):
            desc[pid, q] = descs[rb, q]
    return nv


@jit
def redundant_points(pts, lev_pts, ptr, lev_rows, th_obs):
    """How many of the points ``pts`` (distinct) are observed, at level ``lev_rows <=
    lev_pts + 1``, by at least ``th_obs`` of the rows ``(ptr, lev_rows)`` (the other
    keyframes' observations): ``LocalMapping::KeyFrameCulling``'s redundancy count."""
    n = pts.shape[0]
    order = np.argsort(pts)
    sp = pts[order]
    cnt = np.zeros(n, np.int64)
    for r in range(ptr.shape[0]):
        j = np.searchsorted(sp, ptr[r])
        if j < n and sp[j] == ptr[r] and lev_rows[r] <= lev_pts[order[j]] + 1:
            cnt[j] += 1
    out = 0
    for j in range(n):
        if cnt[j] >= th_obs:
            out += 1
    return out

