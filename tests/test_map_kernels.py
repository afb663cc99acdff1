"""The map's bookkeeping kernels (``slam/kernels/bookkeeping.py``) against the plain
numpy code they replaced (kept here, in the tests, as the reference): equal results --
to the bit, the bookkeeping is exact -- on random tables and on a real map (the SLAM
on the first frames of KITTI 06)."""

from __future__ import annotations

import copy
from types import SimpleNamespace

import numpy as np
import pytest

from dynastereo.slam.geometry import desc_u64
from dynastereo.slam.kernels import bookkeeping as bk
from dynastereo.slam.map import Map
from dynastereo.slam.observations import Observations

SCALES = 1.2 ** np.arange(8)


# ------------------------------------------------------------- the references
def ref_rows_of(obs: Observations, pts: np.ndarray) -> np.ndarray:
    pts = np.asarray(pts, np.int64)
    cur = obs.head[np.unique(pts[pts >= 0])]
    out = []
    while len(cur):
        cur = cur[cur >= 0]
        if not len(cur):
            break
        out.append(cur)
        cur = obs.next_row[cur]
    if not out:
        return np.zeros(0, np.int64)
    r = np.concatenate(out)
    return np.sort(r[obs.alive[r]])


def ref_new_observations(kf_point_ids, kp, pts, bad) -> np.ndarray:
    good = (pts >= 0) & ~bad[np.maximum(pts, 0)]
    keep = (kf_point_ids[kp] < 0) & good
    keep &= ~np.isin(pts, kf_point_ids[kf_point_ids >= 0])
    if keep.any():
        idx = np.flatnonzero(keep)
        _, first = np.unique(pts[idx], return_index=True)
        idx = idx[first]
        _, first = np.unique(kp[idx], return_index=True)
        idx = idx[first]
        keep[:] = False
        keep[idx] = True
    return keep


def ref_update_points(mp: Map, pts: np.ndarray, max_obs: int = 12) -> None:
    """``Map.update_points`` as it was before the kernel."""
    pts = np.unique(np.asarray(pts, np.int64))
    pts = pts[(pts >= 0) & ~mp.points.bad[pts]]
    if len(pts) == 0:
        return
    rows = ref_rows_of(mp.obs, pts)
    if len(rows) == 0:
        return
    kf_ids, kps, ptr = mp.obs.kf[rows], mp.obs.kp[rows], mp.obs.pt[rows]
    centers = np.zeros((len(rows), 3))
    levels = np.zeros(len(rows), np.int64)
    descs = np.zeros((len(rows), 32), np.uint8)
    for kid in np.unique(kf_ids):
        kf = mp.keyframes[int(kid)]
        sel = kf_ids == kid
        centers[sel] = kf.center
        levels[sel] = kf.octave[kps[sel]]
        descs[sel] = kf.desc[kps[sel]]
    v = mp.points.pos[ptr] - centers
    nv = np.linalg.norm(v, axis=1, keepdims=True)
    v /= np.maximum(nv, 1e-12)
    loc = np.searchsorted(pts, ptr)
    acc = np.zeros((len(pts), 3))
    np.add.at(acc, loc, v)
    cnt = np.bincount(loc, minlength=len(pts))
    acc /= np.maximum(cnt, 1)[:, None]
    nrm = np.linalg.norm(acc, axis=1, keepdims=True)
    has = cnt > 0
    mp.points.normal[pts[has]] = acc[has] / np.maximum(nrm[has], 1e-12)
    is_ref = mp.points.ref_kf[ptr] == kf_ids
    missing = np.setdiff1d(pts, ptr[is_ref])
    if len(missing):
        r = ref_rows_of(mp.obs, missing)
        order = np.argsort(mp.obs.pt[r], kind="stable")
        r = r[order]
        p = mp.obs.pt[r]
        first = np.ones(len(p), bool)
        first[1:] = p[1:] != p[:-1]
        mp.points.ref_kf[p[first]] = mp.obs.kf[r[first]]
        is_ref = mp.points.ref_kf[ptr] == kf_ids
    r_idx = np.flatnonzero(is_ref)
    max_d = nv[r_idx, 0] * mp.scales[levels[r_idx]]
    mp.points.max_dist[ptr[r_idx]] = max_d
    mp.points.min_dist[ptr[r_idx]] = max_d / mp.scales[-1]
    order = np.lexsort((-rows, loc))
    loc_s = loc[order]
    start = np.searchsorted(loc_s, np.arange(len(pts)))
    rank = np.arange(len(order)) - start[loc_s]
    keep = rank < max_obs
    order, loc_s, rank = order[keep], loc_s[keep], rank[keep]
    K, P = int(rank.max()) + 1, len(pts)
    D = np.zeros((P, K, 4), np.uint64)
    valid = np.zeros((P, K), bool)
    D[loc_s, rank] = desc_u64(descs[order])
    valid[loc_s, rank] = True
    dd = np.zeros((P, K, K), np.int32)
    for w in range(4):
        dd += np.bitwise_count(np.bitwise_xor(D[:, :, None, w], D[:, None, :, w])).astype(np.int32)
    big = 1 << 20
    dd = np.where(valid[:, None, :], dd, big)
    dd.sort(axis=2)
    med_idx = np.maximum((valid.sum(axis=1) - 1) // 2, 0)
    med = np.take_along_axis(dd, np.broadcast_to(med_idx[:, None, None], (P, K, 1)), axis=2)[:, :, 0]
    best = np.argmin(np.where(valid, med, big), axis=1)
    src = np.full((P, K), -1, np.int64)
    src[loc_s, rank] = order
    bi = src[np.arange(P), best]
    okp = bi >= 0
    mp.points.desc[pts[okp]] = descs[bi[okp]]


def ref_redundant(mp_n: int, pts, lev_pts, ptr, lev_rows, th_obs: int) -> int:
    lev_here = np.zeros(mp_n, np.int64)
    lev_here[pts] = lev_pts
    good = lev_rows <= lev_here[ptr] + 1
    cnt = np.bincount(ptr[good], minlength=mp_n)[pts]
    return int(np.count_nonzero(cnt >= th_obs))


# ------------------------------------------------------------- random maps
def _random_map(seed: int, n_kf: int = 9, n_kp: int = 300, n_pts: int = 900) -> Map:
    """A map of fake keyframes (what the bookkeeping reads: centre, octave, desc,
    u_right, point_ids, obs_row) with random observations, some erased, some points bad."""
    rng = np.random.default_rng(seed)
    mp = Map(SCALES, capacity=8)
    mp.new_points(rng.normal(0, 10, (n_pts, 3)), rng.integers(0, 256, (n_pts, 32), dtype=np.uint8), 0)
    for k in range(n_kf):
        kf = SimpleNamespace(
            id=k, center=rng.normal(0, 2, 3), octave=rng.integers(0, 8, n_kp).astype(np.int32),
            desc=rng.integers(0, 256, (n_kp, 32), dtype=np.uint8),
            u_right=np.where(rng.random(n_kp) < 0.5, rng.random(n_kp) * 100, -1.0),
            point_ids=np.full(n_kp, -1, np.int64), obs_row=np.full(n_kp, -1, np.int64))
        mp.keyframes[k] = kf
        # candidates with repeated points and keypoints, and ids of bad points
        m = n_kp // 2
        mp.add_observations(kf, rng.integers(0, n_kp, m), rng.integers(0, n_pts, m))
    mp.points.ref_kf[:n_pts] = rng.integers(0, n_kf, n_pts)  # some references lost
    mp.obs.erase(rng.choice(mp.obs.n, mp.obs.n // 10, replace=False))
    mp.points.bad[rng.choice(n_pts, n_pts // 20, replace=False)] = True
    return mp


@pytest.mark.parametrize("seed", range(4))
def test_rows_of_equals_the_list_walk(seed: int) -> None:
    mp = _random_map(seed)
    rng = np.random.default_rng(100 + seed)
    for size in (0, 1, 7, 200, 2000):
        pts = rng.integers(-1, mp.points.n, size)
        got = mp.obs.rows_of(pts)
        np.testing.assert_array_equal(got, ref_rows_of(mp.obs, pts))
        assert got.dtype == np.int64
    np.testing.assert_array_equal(mp.obs.rows_of(np.arange(mp.points.n)), np.flatnonzero(mp.obs.alive[: mp.obs.n]))
    # what the rows give: covisibility counts, the points of keyframes
    pts = rng.integers(0, mp.points.n, 300)
    ids, counts = np.unique(mp.obs.kf[ref_rows_of(mp.obs, pts)], return_counts=True)
    assert mp.covisible_counts(pts) == dict(zip(ids.tolist(), counts.tolist()))
    allp = np.unique(np.concatenate([mp.keyframes[k].point_ids for k in (1, 4, 5)]))
    np.testing.assert_array_equal(mp.points_of([1, 4, 5]), allp[mp.points.good(allp)])
    with pytest.raises(IndexError):
        mp.obs.rows_of(np.array([mp.points.n]))


@pytest.mark.parametrize("seed", range(6))
def test_new_observations_keep_the_same_pairs(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n_kp, n_pts = 200, 150
    bad = rng.random(n_pts + 5) < 0.1
    kf_point_ids = np.where(rng.random(n_kp) < 0.4, rng.integers(0, n_pts, n_kp), -1).astype(np.int64)
    for m in (0, 1, 50, 400):
        kp = rng.integers(0, n_kp, m).astype(np.int64)
        pts = rng.integers(-1, n_pts, m).astype(np.int64)
        np.testing.assert_array_equal(bk.new_observations(kf_point_ids, kp, pts, bad),
                                      ref_new_observations(kf_point_ids, kp, pts, bad))
        good = (pts >= 0) & ~bad[np.maximum(pts, 0)] & ~np.isin(pts, kf_point_ids)
        np.testing.assert_array_equal(bk.unseen_good(pts, bad, kf_point_ids), good)
        u = np.unique(pts)
        np.testing.assert_array_equal(bk.unique_good(pts, bad), u[(u >= 0) & ~bad[np.maximum(u, 0)]])


def _same_points(a: Map, b: Map) -> None:
    for name in ("normal", "min_dist", "max_dist", "desc", "ref_kf", "pos", "nobs", "bad"):
        x, y = getattr(a.points, name)[: a.points.n], getattr(b.points, name)[: b.points.n]
        assert np.array_equal(x, y), name  # to the bit


@pytest.mark.parametrize("seed", range(4))
def test_update_points_equals_the_numpy_version(seed: int) -> None:
    mp = _random_map(seed)
    ref = copy.deepcopy(mp)
    rng = np.random.default_rng(200 + seed)
    for size in (1, 40, mp.points.n):
        pts = rng.integers(-1, mp.points.n, size)
        mp.update_points(pts)
        ref_update_points(ref, pts)
        _same_points(mp, ref)
    assert (mp.points.min_dist[: mp.points.n] > 0).any()
    # max_obs below the number of observations: the newest ones only
    mp.update_points(np.arange(mp.points.n), max_obs=3)
    ref_update_points(ref, np.arange(mp.points.n), max_obs=3)
    _same_points(mp, ref)


def test_by_keyframe_groups_stably() -> None:
    rng = np.random.default_rng(3)
    kfs = rng.integers(0, 12, 500).astype(np.int64)
    order, ids, starts = bk.by_keyframe(kfs)
    np.testing.assert_array_equal(ids, np.unique(kfs))
    for g, k in enumerate(ids):
        np.testing.assert_array_equal(order[starts[g]:starts[g + 1]], np.flatnonzero(kfs == k))
    o, i, s = bk.by_keyframe(np.zeros(0, np.int64))
    assert len(o) == len(i) == 0 and list(s) == [0]


@pytest.mark.parametrize("seed", range(4))
def test_redundant_points_count(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 400
    pts = rng.choice(n, 120, replace=False).astype(np.int64)
    lev_pts = rng.integers(0, 8, 120).astype(np.int64)
    ptr = rng.choice(pts, 900).astype(np.int64)
    lev_rows = rng.integers(0, 8, 900).astype(np.int64)
    for th in (1, 3, 5):
        assert bk.redundant_points(pts, lev_pts, ptr, lev_rows, th) == ref_redundant(n, pts, lev_pts, ptr, lev_rows, th)


# ------------------------------------------------------------- a real map
@pytest.fixture(scope="module")
def kitti06_map(kitti06):
    from dynastereo.config import Config
    from dynastereo.io import KittiSequence
    from dynastereo.slam import System

    seq = KittiSequence(kitti06)
    cfg = Config().with_overrides({"masker.kind": "none", "slam.local_ba": "inline"})
    system = System(cfg, seq.calibration)
    try:
        for i in range(14):
            system.track(seq.frame(i), None)
    finally:
        system.shutdown()
    return system.map


@pytest.mark.realdata
def test_kernels_equal_the_numpy_code_on_a_real_map(kitti06_map: Map) -> None:
    mp = copy.deepcopy(kitti06_map)
    ref = copy.deepcopy(kitti06_map)
    assert len(mp.keyframes) >= 4 and mp.obs.n > 1000
    every = np.arange(mp.points.n)
    np.testing.assert_array_equal(mp.obs.rows_of(every), ref_rows_of(ref.obs, every))
    mp.update_points(every)
    ref_update_points(ref, every)
    _same_points(mp, ref)
    # a keyframe's candidate observations: its own points, other keyframes' points, repeats
    rng = np.random.default_rng(0)
    kf = mp.keyframes[max(mp.keyframes)]
    kp = rng.integers(0, len(kf.point_ids), 3000).astype(np.int64)
    pts = rng.integers(-1, mp.points.n, 3000).astype(np.int64)
    np.testing.assert_array_equal(bk.new_observations(kf.point_ids, kp, pts, mp.points.bad),
                                  ref_new_observations(kf.point_ids, kp, pts, mp.points.bad))
