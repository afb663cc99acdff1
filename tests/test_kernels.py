"""The SLAM's compiled kernels (slam/kernels): known answers, and agreement with the numpy /
OpenCV code they replace (kept as ``_..._numpy`` references) on random problems."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dynastereo.slam.geometry import desc_u64, se3_exp
from dynastereo import compiled as _numba
from dynastereo.slam.kernels.epipolar import epipolar_best
from dynastereo.slam.kernels.hamming import knn_hamming
from dynastereo.slam.matcher import KeypointGrid, search_by_projection, stereo_match
from dynastereo.slam.optimizer import optimize_pose
from reference.slam_numpy import optimize_pose_numpy, search_by_projection_numpy, stereo_match_numpy
from dynastereo.slam.orb import ORBExtractor

K = np.array([[718.856, 0.0, 607.19], [0.0, 718.856, 185.22], [0.0, 0.0, 1.0]])
BF = 0.5372 * K[0, 0]


def _scene(rng, n, T, stereo_frac=0.7, noise=0.0):
    X = np.c_[rng.uniform(-12, 12, n), rng.uniform(-3, 2, n), rng.uniform(4, 45, n)]
    Xc = X @ T[:3, :3].T + T[:3, 3]
    u = K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 2]
    v = K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]
    ur = u - BF / Xc[:, 2]
    uv = np.c_[u, v] + rng.normal(0, noise, (n, 2)) if noise else np.c_[u, v]
    ur = ur + (rng.normal(0, noise, n) if noise else 0.0)
    ur[rng.random(n) > stereo_frac] = -1.0
    inv_sigma2 = 1.0 / 1.2 ** (2 * rng.integers(0, 8, n))
    return X, uv, ur, inv_sigma2


# ------------------------------------------------------------------------------ pose
def test_pose_from_exact_stereo_correspondences():
    rng = np.random.default_rng(3)
    T_true = se3_exp(np.array([0.02, -0.05, 0.01, 0.3, -0.1, 1.2]))
    X, uv, ur, isg = _scene(rng, 300, T_true, stereo_frac=1.0)
    T0 = se3_exp(np.array([0.0, -0.03, 0.0, 0.1, 0.0, 0.8]))  # 0.4 m and 2 degrees off
    T, inl = optimize_pose(T0, X, uv, ur, isg, K, BF)
    assert inl.all()
    assert np.abs(T - T_true).max() < 1e-6


def test_pose_rejects_outliers_and_agrees_with_numpy():
    rng = np.random.default_rng(4)
    for trial in range(6):
        T_true = se3_exp(rng.normal(0, 0.05, 6))
        X, uv, ur, isg = _scene(rng, 400 + 50 * trial, T_true, noise=0.7)
        bad = rng.random(len(X)) < 0.1
        uv[bad] += rng.normal(0, 40, (bad.sum(), 2))
        out0 = rng.random(len(X)) < 0.05 if trial % 2 else None
        Tk, ik = optimize_pose(np.eye(4), X, uv, ur, isg, K, BF, outlier=out0)
        Tn, inn = optimize_pose_numpy(np.eye(4), X, uv, ur, isg, K, BF, outlier=out0)
        assert np.abs(Tk - Tn).max() < 1e-9
        assert np.array_equal(ik, inn)
        assert (~ik[bad]).mean() > 0.9  # the gross outliers found
        assert np.abs(Tk[:3, 3] - T_true[:3, 3]).max() < 0.05


def test_pose_few_observations_unchanged():
    T0 = se3_exp(np.array([0.1, 0, 0, 1, 0, 0]))
    T, inl = optimize_pose(T0, np.zeros((2, 3)), np.zeros((2, 2)), -np.ones(2), np.ones(2), K, BF)
    assert np.array_equal(T, T0) and inl.all()


# ---------------------------------------------------------------------------- hamming
def _brute_knn(a, b, k):
    """Plain reference: all distances, stable sort (ties: lower index first)."""
    d = np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(axis=2)
    idx = np.argsort(d, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(d, idx, axis=1), idx


@pytest.mark.parametrize("na,nb,k", [(300, 500, 4), (40, 3, 4), (200, 250, 2), (10, 1, 1), (0, 5, 2)])
def test_knn_hamming_matches_opencv_and_brute_force(na, nb, k):
    rng = np.random.default_rng(na + nb)
    a = rng.integers(0, 256, (na, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (nb, 32), dtype=np.uint8)
    if nb > 7:
        b[::7] = b[0]  # exact ties
        a[: min(na, 5)] = b[0]
    d, i = knn_hamming(a, b, k)
    dr, ir = _brute_knn(a, b, min(k, nb))
    assert np.array_equal(d, dr) and np.array_equal(i, ir)
    if na:
        dc, ic = cv2.batchDistance(a, b, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=min(k, nb))
        assert np.array_equal(d, dc) and np.array_equal(i, ic)


# ----------------------------------------------------------------------- epipolar search
def _brute_epipolar(d1, uv1, m1, d2, uv2, m2, th2, near2, F, ep, max_dist, k_nn=4):
    """Plain reference of ``epipolar_best``, as local mapping did it before the kernel:
    the ``k_nn`` nearest descriptors of each row (``_brute_knn``), then the distance bound,
    the line and the epipole tests on them, the first smallest distance."""
    dk, ik = _brute_knn(d1, d2, min(k_nn, len(d2))) if k_nn else (None, None)
    best, dist = np.full(len(d1), -1), np.full(len(d1), -1)
    for i in range(len(d1)):
        x1 = np.array([uv1[i, 0], uv1[i, 1], 1.0])
        l = F @ x1
        js = ik[i] if k_nn else np.arange(len(d2))
        ds = dk[i] if k_nn else np.unpackbits(d1[i] ^ d2, axis=1).sum(axis=1)
        for j, d in zip(js, ds):  # nearest first
            on = (l[0] * uv2[j, 0] + l[1] * uv2[j, 1] + l[2]) ** 2 / (l[0] ** 2 + l[1] ** 2) < th2[j]
            near = ep is not None and m1[i] and m2[j] and (uv2[j, 0] - ep[0]) ** 2 + (uv2[j, 1] - ep[1]) ** 2 < near2[j]
            if d <= max_dist and on and not near and (best[i] < 0 or d < dist[i]):
                best[i], dist[i] = j, d
    return best, dist


@pytest.mark.parametrize("seed", range(6))
def test_epipolar_best_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    n1, n2 = int(rng.integers(1, 150)), int(rng.integers(1, 200))
    d1 = rng.integers(0, 256, (n1, 32), dtype=np.uint8)
    d2 = rng.integers(0, 256, (n2, 32), dtype=np.uint8)
    k = min(n1, n2) // 2
    d2[:k] = d1[:k] ^ np.packbits(rng.random((k, 256)) < 0.1, axis=1)  # near copies: matches to find
    if n2 > 9:
        d2[5:9] = d2[4]  # exact ties: the lower index wins
    uv1, uv2 = rng.uniform(0, 600, (n1, 2)), rng.uniform(0, 600, (n2, 2))
    F = rng.normal(size=(3, 3)) * np.array([[1e-6, 1e-5, 1e-3], [1e-5, 1e-6, 1e-2], [1e-3, 1e-2, 1.0]])
    L = np.c_[uv1[:k], np.ones(k)] @ F.T  # the near copies on (or close to) their epipolar line
    uv2[:k, 1] = -(L[:, 0] * uv2[:k, 0] + L[:, 2]) / L[:, 1] + rng.normal(0, 2, k)
    m1, m2 = rng.random(n1) < 0.5, rng.random(n2) < 0.5
    th2, near2 = rng.uniform(1, 50, n2), rng.uniform(100, 40000, n2)
    ep = (300.0, 300.0) if seed % 2 else None
    for k_nn in (4, 1, 0):
        got = epipolar_best(d1, uv1, m1, d2, uv2, m2, th2, near2, F, ep, 60, k_nn=k_nn)
        ref = _brute_epipolar(d1, uv1, m1, d2, uv2, m2, th2, near2, F, ep, 60, k_nn=k_nn)
        assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1]), k_nn
        assert (got[0] >= 0).sum() > 0


def test_epipolar_best_known_geometry():
    """A rig moved 1 m sideways sees points at known depths: each keypoint's match is its
    own point (on its epipolar line), not an identical descriptor off the line, nor one
    on the line but too far in bits; and only when it is among the 4 nearest descriptors."""
    rng = np.random.default_rng(1)
    Kc = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    X = np.c_[rng.uniform(-4, 4, 40), rng.uniform(-2, 2, 40), rng.uniform(5, 30, 40)]
    t21 = np.array([-1.0, 0.0, 0.0])  # camera 2 one metre to the right of camera 1
    x1 = X @ Kc.T
    x2 = (X + t21) @ Kc.T
    uv1, uv2 = x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]
    Ki = np.linalg.inv(Kc)
    F = Ki.T @ np.array([[0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]) @ Ki  # [t21]x R21 (R21 = I)
    d1 = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    d2 = d1 ^ np.packbits(rng.random((40, 256)) < 0.05, axis=1)
    decoy = np.r_[d1[:10], d1[10:12]]  # exact copies, 30 px off the line; two on it but 90 bits away
    uv_decoy = np.r_[uv2[:10] + [0.0, 30.0], uv2[10:12] + [5.0, 0.0]]
    decoy[10:] ^= np.packbits(np.r_[np.ones(90, bool), np.zeros(166, bool)])
    # keypoint 20 has 4 exact copies off its line, keypoint 21 three: 20's match is not
    # among its 4 nearest descriptors (refused), 21's is (kept)
    decoy = np.r_[decoy, np.repeat(d1[20:21], 4, axis=0), np.repeat(d1[21:22], 3, axis=0)]
    uv_decoy = np.r_[uv_decoy, np.repeat(uv2[20:21] + [0.0, 40.0], 4, axis=0), np.repeat(uv2[21:22] + [0.0, 40.0], 3, axis=0)]
    n2 = 40 + len(decoy)
    args = (d1, uv1, np.zeros(40, bool), np.r_[d2, decoy], np.r_[uv2, uv_decoy], np.zeros(n2, bool),
            np.full(n2, 3.84), np.zeros(n2), F, None, 50)
    best, dist = epipolar_best(*args)
    assert np.array_equal(best, np.where(np.arange(40) == 20, -1, np.arange(40)))
    assert (dist[best >= 0] <= 50).all()
    assert np.array_equal(epipolar_best(*args, k_nn=0)[0], np.arange(40))


# ----------------------------------------------------------------------------- stereo
def _textured_pair(disp, H=240, W=480, seed=0):
    """A smooth random texture and its right view: right(x) = left(x + disp(x, y)) (cubic resampling)."""
    rng = np.random.default_rng(seed)
    base = cv2.resize(rng.uniform(0, 255, (H // 4, W // 4 + 40)).astype(np.float32), (W + 160, H),
                      interpolation=cv2.INTER_CUBIC)
    fine = cv2.GaussianBlur(rng.uniform(0, 255, (H, W + 160)).astype(np.float32), (0, 0), 1.2)
    tex = 0.6 * base + 0.4 * fine
    tex = (tex - tex.min()) / (tex.max() - tex.min()) * 235 + 10
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    left = cv2.remap(tex, xs + 80, ys, cv2.INTER_CUBIC)
    right = cv2.remap(tex, xs + 80 + disp(xs, ys).astype(np.float32), ys, cv2.INTER_CUBIC)
    return np.clip(left, 0, 255).astype(np.uint8), np.clip(right, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("kind", ["constant", "planar"])
def test_stereo_known_disparity(kind):
    disp = (lambda x, y: np.full_like(x, 23.4)) if kind == "constant" else (lambda x, y: 12.3 + 0.02 * x + 0.03 * y)
    left, right = _textured_pair(disp, seed=1 if kind == "constant" else 2)
    orb = ORBExtractor(n_features=1500)
    fl, fr = orb.extract(left), orb.extract(right)
    st = stereo_match(fl.uv, fl.octave, fl.desc, fr.uv, fr.octave, fr.desc, left, right, orb.scales, K[0, 0], BF)
    ok = st.depth > 0
    assert ok.sum() > 0.3 * len(fl.uv)
    # the right image at x shows the left one at x + disp(x): the true disparity d of a left
    # keypoint at x_l solves d = disp(x_l - d)
    xl, yl = fl.uv[ok, 0], fl.uv[ok, 1]
    truth = disp(xl, yl)
    for _ in range(30):
        truth = disp(xl - truth, yl)
    err = np.abs((fl.uv[ok, 0] - st.u_right[ok]) - truth)
    assert np.median(err) < 0.1
    assert np.mean(err < 0.25) > 0.9
    np.testing.assert_allclose(st.depth[ok], BF / (fl.uv[ok, 0] - st.u_right[ok]))
    ref = stereo_match_numpy(fl.uv, fl.octave, fl.desc, fr.uv, fr.octave, fr.desc, left, right, orb.scales, K[0, 0], BF)
    assert np.array_equal(st.u_right, ref.u_right) and np.array_equal(st.depth, ref.depth)


def test_stereo_agrees_with_numpy_on_random_keypoints():
    rng = np.random.default_rng(7)
    left, right = _textured_pair(lambda x, y: 8.0 + 0.05 * x, seed=3)
    H, W = left.shape
    scales = 1.2 ** np.arange(8)
    for trial in range(5):
        n_l, n_r = 400, 450
        uv_l = np.c_[rng.uniform(0, W, n_l), rng.uniform(0, H, n_l)]
        uv_r = np.c_[rng.uniform(0, W, n_r), rng.uniform(0, H, n_r)]
        uv_r[:200] = uv_l[:200] - [[20.0, 0.0]] + rng.normal(0, 0.8, (200, 2))
        oct_l = rng.integers(0, 8, n_l).astype(np.int32)
        oct_r = rng.integers(0, 8, n_r).astype(np.int32)
        oct_r[:200] = oct_l[:200]
        d_l = rng.integers(0, 256, (n_l, 32), dtype=np.uint8)
        d_r = rng.integers(0, 256, (n_r, 32), dtype=np.uint8)
        d_r[:200] = d_l[:200] ^ (rng.random((200, 32)) < 0.05 * trial).astype(np.uint8) * 8
        d_r[200:220] = d_r[0]  # ties
        a = stereo_match(uv_l, oct_l, d_l, uv_r, oct_r, d_r, left, right, scales, K[0, 0], BF)
        b = stereo_match_numpy(uv_l, oct_l, d_l, uv_r, oct_r, d_r, left, right, scales, K[0, 0], BF)
        assert (a.depth > 0).sum() > 20
        assert np.array_equal(a.u_right, b.u_right) and np.array_equal(a.depth, b.depth)


# ------------------------------------------------------------------------- projection
@pytest.mark.parametrize("variant", ["track", "local_map", "fuse", "ratio_any_level"])
def test_search_by_projection_agrees_with_numpy(variant):
    rng = np.random.default_rng(hash(variant) % 1000)
    W, H = 640, 360
    for trial in range(4):
        n_kp, n_q = 900, 500
        kuv = np.c_[rng.uniform(0, W, n_kp), rng.uniform(0, H, n_kp)]
        kuv[100:150] = kuv[50:100].round()  # keypoints on cell borders and duplicates
        koct = rng.integers(0, 8, n_kp)
        kdesc = rng.integers(0, 256, (n_kp, 32), dtype=np.uint8)
        kdesc[::11] = kdesc[0]
        kuR = np.where(rng.random(n_kp) < 0.6, kuv[:, 0] - rng.uniform(1, 60, n_kp), -1.0)
        grid = KeypointGrid(kuv, W, H)
        src = rng.integers(0, n_kp, n_q)
        u = kuv[src, 0] + rng.normal(0, 3, n_q)
        v = kuv[src, 1] + rng.normal(0, 3, n_q)
        ur = kuR[src] + rng.normal(0, 2, n_q)
        qdesc = kdesc[src] ^ (rng.random((n_q, 32)) < 0.08).astype(np.uint8)
        lev = koct[src]
        radius = 1.2 ** lev * rng.choice([2.5, 4.0, 7.0], n_q)
        kw: dict = dict(u_right=ur, min_level=lev - 1, max_level=lev)
        avail = None
        if variant == "track":
            kw.update(th_dist=100, angle_check=(rng.uniform(0, 360, n_q), rng.uniform(0, 360, n_kp)))
            kw.update(min_level=np.maximum(lev - 1, 0), max_level=lev + 1)
        elif variant == "local_map":
            kw.update(th_dist=100, ratio=0.8)
            avail = rng.random(n_kp) < 0.8
        elif variant == "fuse":
            kw.update(th_dist=50, reproj_check=(kuv, 1.0 / 1.44 ** koct))
        else:
            kw.update(th_dist=100, ratio=0.9, ratio_same_level_only=False)
            kw.pop("u_right")
        args = (grid, koct, desc_u64(kdesc), kuR, avail, u, v, radius, desc_u64(qdesc))
        a = search_by_projection(*args, **kw)
        b = search_by_projection_numpy(*args, **kw)
        assert len(a.query) > 30
        for f in ("query", "kp", "dist"):
            assert np.array_equal(getattr(a, f), getattr(b, f)), f
        assert len(np.unique(a.kp)) == len(a.kp)


def test_search_by_projection_empty():
    grid = KeypointGrid(np.zeros((0, 2)), 100, 100)
    z = np.zeros(0)
    m = search_by_projection(grid, np.zeros(0, int), np.zeros((0, 4), np.uint64), None, None, z, z, z,
                             np.zeros((0, 4), np.uint64))
    assert len(m.query) == len(m.kp) == len(m.dist) == 0


# ------------------------------------------------------------------------------ cache
# ------------------------------------------------------------------------------ bucketing
def _bucket_lexsort(u, v, resp, lev, quota, W, H):
    """The corner bucketing as it was written in numpy (two lexsorts): the reference."""
    L = len(quota)
    lev = np.clip(lev, 0, L - 1)
    cell = np.sqrt(W * H / np.maximum(quota, 1))[lev]
    ncx = np.ceil(W / cell).astype(np.int64)
    cx = np.minimum((u / cell).astype(np.int64), ncx - 1)
    cy = (v / cell).astype(np.int64)
    cid = (lev * 1_000_000 + cy * ncx + cx).astype(np.int64)
    order = np.lexsort((-resp, cid))
    c_sorted = cid[order]
    start = np.ones(len(order), bool)
    start[1:] = c_sorted[1:] != c_sorted[:-1]
    first_pos = np.maximum.accumulate(np.where(start, np.arange(len(order)), 0))
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order)) - first_pos
    o2 = np.lexsort((-resp, rank, lev))
    l2 = lev[o2]
    lstart = np.searchsorted(l2, np.arange(L))
    keep = o2[(np.arange(len(o2)) - lstart[l2]) < quota[l2]]
    return np.sort(keep)


@pytest.mark.parametrize("integral", [True, False])
def test_corner_bucketing_agrees_with_the_lexsort_reference(integral):
    from dynastereo.slam.kernels.bucketing import bucket_corners

    rng = np.random.default_rng(11 + integral)
    for trial in range(150):
        n = int(rng.integers(0, 4000))
        W, H = int(rng.integers(64, 1300)), int(rng.integers(48, 400))
        ex = ORBExtractor(int(rng.integers(50, 3000)), n_levels=int(rng.integers(1, 9)))
        u, v = rng.random(n) * W, rng.random(n) * (H + 2)  # coarse levels reach past the last row
        resp = (rng.integers(0, 40, n) if integral else rng.random(n) * 5).astype(np.float32)
        lev = rng.integers(-1, 10, n).astype(np.int32)
        want = _bucket_lexsort(u, v, resp, lev, ex.quota, W, H)
        got = bucket_corners(u, v, resp, lev, ex.quota, W, H)
        np.testing.assert_array_equal(got, want)
        assert len(got) <= ex.quota.sum()


def test_corner_bucketing_spreads_and_prefers_strong_corners():
    """One cell's strong corners do not crowd out the other cells: each cell gives its
    strongest first."""
    from dynastereo.slam.kernels.bucketing import bucket_corners

    W, H = 200, 100
    quota = np.array([8], np.int64)  # cells of 50 px: 4 x 2
    # 40 strong corners in the top-left cell, one weak corner in each other cell
    u = np.r_[np.linspace(1, 40, 40), [60, 110, 160, 10, 60, 110, 160]]
    v = np.r_[np.full(40, 10.0), [10, 10, 10, 60, 60, 60, 60]]
    resp = np.r_[np.full(40, 50.0), np.full(7, 5.0)].astype(np.float32)
    keep = bucket_corners(u, v, resp, np.zeros(47, np.int32), quota, W, H)
    assert len(keep) == 8 and set(range(40, 47)) <= set(keep.tolist())


def test_numba_cache_falls_back_when_nothing_is_writable(monkeypatch, tmp_path):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setattr(_numba._config, "CACHE_DIR", "")
    monkeypatch.setattr(_numba, "_writable", lambda d: False)
    monkeypatch.setattr(_numba.tempfile, "gettempdir", lambda: str(tmp_path))
    d = _numba.cache_dir_fallback()
    assert d is not None and d.startswith(str(tmp_path)) and _numba._config.CACHE_DIR == d
    monkeypatch.setattr(_numba, "_writable", lambda d: True)
    monkeypatch.setattr(_numba._config, "CACHE_DIR", "")
    assert _numba.cache_dir_fallback() is None


def _kernel_signatures() -> dict[str, set[str]]:
    """Every compiled kernel of the SLAM (``slam.kernels.*``, ``objects.world``) and of the
    masking (the outlines', the box tracker's) and its loaded overloads."""
    import importlib
    import pkgutil

    from numba.core.registry import CPUDispatcher

    from dynastereo.slam import kernels

    names = [f"dynastereo.slam.kernels.{m.name}" for m in pkgutil.iter_modules(kernels.__path__)]
    out: dict[str, set[str]] = {}
    others = ["dynastereo.objects.world", "dynastereo.masking.boxkernel", "dynastereo.masking.maskers",
              "dynastereo.masking.transfer", "dynastereo.masking.detection.box_tracker",
              "dynastereo.objects.disparity"]
    for mod in map(importlib.import_module, names + others):
        for name, f in vars(mod).items():
            if isinstance(f, CPUDispatcher) and f.__module__ == mod.__name__:
                out[f"{mod.__name__}.{name}"] = {str(s) for s in f.signatures}
    return out


def test_the_warm_up_loads_every_kernel_a_run_calls(kitti06, models_dir, tmp_path):
    """After the start-up warm-ups (``warm_up_kernels``, the objects' in ``WorldObjects``,
    the masker's ``warm_up`` that a job makes before its frame loop: the outlines', the
    region plan's, the transfer's and the box tracker's kernels), the whole of KITTI 06 tracked and mapped, and its first frames
    with the default masking (objects placed, with their own matching: ``objects.block_size``), load no kernel overload of their own: none is
    loaded from numba's cache (tens of ms, holding the GIL) or compiled inside the frame loop."""
    from dynastereo.api import run_sequence
    from dynastereo.config import Config
    from dynastereo.io import KittiSequence
    from dynastereo.masking import build_masker
    from dynastereo.objects.world import WorldObjects
    from dynastereo.slam.warmup import warm_up_kernels

    warm_up_kernels()
    calib = KittiSequence(kitti06).calibration
    own = Config().with_overrides({"objects.block_size": 11})  # the objects' own matching too
    WorldObjects.from_config(calib, own)
    build_masker(Config(), calib, models_dir=models_dir).warm_up(calib.height, calib.width)
    before = _kernel_signatures()
    run_sequence(kitti06, tmp_path / "r", Config().with_overrides({"masker.kind": "none"}), stereo_check=False)
    run_sequence(kitti06, tmp_path / "m", own, stereo_check=False, frames="0-12", models_dir=models_dir)
    after = _kernel_signatures()
    called = {k: v for k, v in after.items() if v}
    assert len(called) >= 22 and any("objects.world._track_frame" in k for k in called)  # the runs went through them
    assert all(any(name in k for k in called)
               for name in ("boxkernel.outline_frame", "boxkernel.transfer_frame", "_median_flow", "_greedy_regions",
                            "objects.disparity.object_disparity"))
    assert {k: sorted(v - before.get(k, set())) for k, v in after.items() if v - before.get(k, set())} == {}
