"""The compiled bundle adjustment (``slam.kernels.ba``) on known answers, against gtsam,
and the BA thread's bounded waits (``local_mapping.BARunner``)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from dynastereo.slam import System
from dynastereo.slam import local_mapping
from dynastereo.config import SlamConfig
from dynastereo.slam.kernels.ba import solve
from dynastereo.slam.geometry import inv_T, se3_exp
from dynastereo.slam.local_mapping import BARunner
from dynastereo.slam.optimizer import LocalBAProblem, local_ba, local_ba_gtsam, project

K = np.array([[700.0, 0.0, 610.0], [0.0, 700.0, 185.0], [0.0, 0.0, 1.0]])
W, H = 1220, 370
BASELINE = 0.54
BF = K[0, 0] * BASELINE


def _scene(seed: int, n_kf: int = 6, n_pts: int = 500, mono_beyond: float = 25.0, step: float = 0.8):
    """Keyframes 0.8 m apart along z looking at points 5-40 m away; exact observations
    (stereo up to ``mono_beyond`` m, monocular beyond).  Returns the true ``T_cw``,
    points, and the observation arrays."""
    rng = np.random.default_rng(seed)
    T_wc = np.stack([se3_exp(np.r_[0.0, 0.01 * i, 0.0, 0.05 * i, 0.0, step * i]) for i in range(n_kf)])
    T_cw = np.stack([inv_T(T) for T in T_wc])
    X = np.c_[rng.uniform(-12, 12, n_pts), rng.uniform(-3, 2, n_pts), rng.uniform(5, 40, n_pts)]
    kf, pt, uv, ur = [], [], [], []
    for i in range(n_kf):
        Xc, u, v, r = project(T_cw[i], X, K[0, 0], K[1, 1], K[0, 2], K[1, 2], BF)
        vis = np.flatnonzero((Xc[:, 2] > 1) & (u > 0) & (u < W) & (v > 0) & (v < H))
        kf.append(np.full(len(vis), i))
        pt.append(vis)
        uv.append(np.c_[u[vis], v[vis]])
        ur.append(np.where(Xc[vis, 2] < mono_beyond, r[vis], -1.0))
    kf, pt, uv, ur = map(np.concatenate, (kf, pt, uv, ur))
    seen = np.bincount(pt, minlength=n_pts) >= 2
    keep = seen[pt]
    new_id = np.cumsum(seen) - 1
    return T_cw, X[seen], kf[keep], new_id[pt[keep]], uv[keep], ur[keep]


def _perturb(T_cw, X, fixed, seed, rot=0.005, trans=0.05, pts=0.1):
    rng = np.random.default_rng(seed)
    T0 = T_cw.copy()
    for i in np.flatnonzero(~fixed):
        T0[i] = se3_exp(np.r_[rng.normal(0, rot, 3), rng.normal(0, trans, 3)]) @ T0[i]
    return T0, X + rng.normal(0, pts, X.shape)


def test_exact_observations_converge_back_to_the_known_minimum():
    T_true, X_true, kf, pt, uv, ur = _scene(1)
    fixed = np.zeros(len(T_true), bool)
    fixed[0] = True
    T0, X0 = _perturb(T_true, X_true, fixed, 2)
    T, X, inl, st = solve(T0, X0, kf, pt, uv, ur, np.ones(len(kf)), fixed, K, BF, 30, 0, 1e-14)
    assert st[1] > 1e3 and st[2] < 1e-12  # cost before / after: the minimum is 0
    assert inl.all() and st[3] == 0
    np.testing.assert_allclose(T, T_true, atol=1e-8)
    np.testing.assert_allclose(X, X_true, atol=1e-6)


def test_a_big_camera_system_converges():
    """52 keyframes (306 camera unknowns, a full BA's size), every one seeing the points."""
    T_true, X_true, kf, pt, uv, ur = _scene(41, n_kf=52, n_pts=250, step=0.1)
    assert len(np.unique(kf)) == 52
    fixed = np.zeros(len(T_true), bool)
    fixed[0] = True
    T0, X0 = _perturb(T_true, X_true, fixed, 42, rot=0.002, trans=0.02, pts=0.05)
    T, X, inl, st = solve(T0, X0, kf, pt, uv, ur, np.ones(len(kf)), fixed, K, BF, 30, 0, 1e-14)
    assert st[1] > 1e3 and st[2] < 1e-10
    np.testing.assert_allclose(T, T_true, atol=1e-7)


def test_fixed_keyframes_do_not_move():
    T_true, X_true, kf, pt, uv, ur = _scene(3)
    fixed = np.zeros(len(T_true), bool)
    fixed[[0, 2]] = True
    T0, X0 = _perturb(T_true, X_true, fixed, 4)
    T0[2] = se3_exp(np.r_[0, 0, 0, 0.02, 0, 0]) @ T0[2]  # a fixed keyframe that is off: it stays off
    T, X, inl, st = solve(T0, X0, kf, pt, uv + np.random.default_rng(5).normal(0, 0.5, uv.shape), ur,
                          np.full(len(kf), 4.0), fixed, K, BF, 5, 10, 1e-6)
    assert np.array_equal(T[fixed], T0[fixed])
    assert st[2] < st[1] and np.abs(T[~fixed] - T0[~fixed]).max() > 1e-3


def test_injected_outliers_are_dropped():
    T_true, X_true, kf, pt, uv, ur = _scene(6)
    rng = np.random.default_rng(7)
    uv = uv + rng.normal(0, 0.5, uv.shape)
    ur = np.where(ur >= 0, ur + rng.normal(0, 0.5, len(ur)), -1.0)
    bad = rng.random(len(kf)) < 0.05
    uv[bad] += rng.choice([-1, 1], (bad.sum(), 2)) * rng.uniform(15, 40, (bad.sum(), 2))
    fixed = np.zeros(len(T_true), bool)
    fixed[0] = True
    T0, X0 = _perturb(T_true, X_true, fixed, 8)
    T, X, inl, st = solve(T0, X0, kf, pt, uv, ur, np.full(len(kf), 4.0), fixed, K, BF, 5, 10, 1e-6)
    assert not (inl & bad).any()  # every injected outlier dropped
    # good ones dropped with them: the chi2 95% bounds drop ~5% of the noise by design
    assert (~inl & ~bad).sum() <= 0.06 * (~bad).sum()
    assert st[4] == (~inl).sum()
    err = max(np.linalg.norm(inv_T(T[i])[:3, 3] - inv_T(T_true[i])[:3, 3]) for i in range(len(T)))
    assert err < 0.01


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_kernel_agrees_with_gtsam_on_random_problems(seed: int):
    """Noisy observations, no gross outliers: gtsam's LM and the kernel reach the same
    minimum of the same (Huber) cost."""
    T_true, X_true, kf, pt, uv, ur = _scene(seed, n_kf=5, n_pts=300)
    rng = np.random.default_rng(seed + 100)
    uv = uv + rng.normal(0, 1.0, uv.shape)
    ur = np.where(ur >= 0, ur + rng.normal(0, 1.0, len(ur)), -1.0)
    sigma = 1.2 ** rng.integers(0, 4, len(kf))
    fixed = np.zeros(len(T_true), bool)
    fixed[0] = True
    T0, X0 = _perturb(T_true, X_true, fixed, seed + 200, rot=0.002, trans=0.03, pts=0.05)
    prob = LocalBAProblem(np.arange(len(T0)), np.stack([inv_T(T) for T in T0]), fixed, np.arange(len(X0)), X0,
                          kf, pt, uv, ur, sigma, K, BASELINE, iterations=100, rel_tol=1e-12)
    ref = local_ba_gtsam(prob)
    res = local_ba(prob)
    assert res.error_before == pytest.approx(ref.error_before, rel=1e-9)  # the same cost function
    assert res.error_after == pytest.approx(ref.error_after, rel=1e-6)
    assert res.error_after < 0.5 * res.error_before
    np.testing.assert_allclose(res.T_wc, ref.T_wc, atol=1e-5)
    rel = np.linalg.norm(res.X - ref.X, axis=1) / np.linalg.norm(ref.X, axis=1)
    # a point whose errors sit at the Huber corner has a flat minimum: a few 1e-4
    assert np.median(rel) < 1e-6 and np.quantile(rel, 0.99) < 1e-4 and rel.max() < 1e-3


def test_abort_flag_stops_the_solve():
    T_true, X_true, kf, pt, uv, ur = _scene(21)
    fixed = np.zeros(len(T_true), bool)
    fixed[0] = True
    T0, X0 = _perturb(T_true, X_true, fixed, 22)
    abort = np.ones(1, np.int64)
    T, X, inl, st = solve(T0, X0, kf, pt, uv, ur, np.ones(len(kf)), fixed, K, BF, 5, 10, 1e-6, abort=abort)
    assert st[0] == 0 and st[3] == 1 and st[1] == st[2]
    assert np.array_equal(T, T0) and np.array_equal(X, X0)


def _slow_ba(problem, abort):
    """A BA that never finishes on its own: it ends when aborted."""
    while not abort[0]:
        time.sleep(0.005)
    return None


def test_a_stalled_ba_is_skipped_recorded_and_does_not_hang(monkeypatch):
    runner = BARunner("thread", wait_s=0.05)
    T_true, X_true, kf, pt, uv, ur = _scene(31, n_kf=3, n_pts=100)
    prob = LocalBAProblem(np.arange(3), np.stack([inv_T(T) for T in T_true]), np.array([True, False, False]),
                          np.arange(len(X_true)), X_true, kf, pt, uv, ur, np.ones(len(kf)), K, BASELINE)
    monkeypatch.setattr(local_mapping, "run_ba", _slow_ba)
    job = runner.submit(prob)
    t0 = time.perf_counter()
    assert runner.wait(job, 17) is None
    assert time.perf_counter() - t0 < 5.0
    assert job.abort[0] == 1
    job._thread.join(5.0)
    assert not job._thread.is_alive()  # the abort flag ended it
    (fb,) = runner.fallbacks
    assert fb["frame"] == 17 and fb["ba"] == "local" and fb["action"] == "result skipped"
    monkeypatch.undo()
    ok = runner.submit(prob)  # the next job runs normally
    res = runner.wait(ok, 20, wait_s=60.0)
    assert res is not None and res.error_after <= res.error_before + 1e-9 and len(runner.fallbacks) == 1


def test_system_with_a_stalled_ba_thread_finishes_and_records_the_frames(monkeypatch):
    from test_slam import CALIB, _sequence

    frames, _ = _sequence()
    monkeypatch.setattr(local_mapping, "run_ba", _slow_ba)
    sysm = System(SlamConfig(n_features=1000, local_ba="thread", ba_wait_s=0.05), CALIB)
    try:
        for f in frames[:12]:
            sysm.track(f)
    finally:
        t0 = time.perf_counter()
        sysm.shutdown()
        assert time.perf_counter() - t0 < 10.0
    st = sysm.stats()
    assert st.lost == 0 and st.local_ba_runs == 0
    fb = st.local_ba_fallbacks
    assert len(fb) >= 2 and all(r["action"] == "result skipped" for r in fb)
    frames_at = [r["frame"] for r in fb]
    assert frames_at == sorted(frames_at) and 0 < frames_at[0] < 12
    deadline = time.perf_counter() + 5.0  # shutdown aborted the BA threads: they end
    while any(t.name == "local-ba" for t in threading.enumerate()) and time.perf_counter() < deadline:
        time.sleep(0.01)
    assert not any(t.name == "local-ba" for t in threading.enumerate())


def test_the_kernel_releases_the_gil():
    from dynastereo.slam.kernels.ba import ba_solve

    assert ba_solve.targetoptions.get("nogil") is True
