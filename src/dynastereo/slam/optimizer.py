"""Optimization: motion-only BA (numpy) and bundle adjustment (compiled kernel).

Motion-only BA (``optimize_pose``; numba kernel ``kernels/pose.py``) is ORB-SLAM2's ``Optimizer::PoseOptimization``:
stereo observations (u, v, u_right) and monocular ones (u, v), information
``1 / sigma^2`` of the keypoint's level, Huber kernel (delta = sqrt(chi2 95%)),
4 rounds of 10 Gauss-Newton iterations with outliers re-classified by chi2 after each
round and the kernel dropped in the last rounds.  It is a Gauss-Newton on SE(3) in one
compiled call (about 0.5 ms a frame's call); its vectorized numpy form
(``tests/reference/slam_numpy.py``, the tests' reference) was chosen over gtsam by measurement: 1.7 ms
for 800 observations with the whole 4-round schedule, against 14 ms for a single robust LM
pass of a gtsam graph built per frame, same pose (``benchmarks/bench_slam.py``).

Bundle adjustment (``local_ba``: the local BA, the self-calibrating BA's solves, the
loop's full BA and the final BA of a saved map) is one call of the compiled kernel
:func:`.kernels.ba.ba_solve` (Levenberg-Marquardt, points eliminated by the Schur
complement, ORB-SLAM2's robust + refine schedule; it releases the GIL, so local mapping
runs it in a thread).  ``local_ba_gtsam`` is the former gtsam solver
(``GenericStereoFactor3D`` / ``GenericProjectionFactorCal3_S2`` with Huber kernels, LM
with SEQUENTIAL_CHOLESKY, fixed keyframes by tight priors), kept as the reference for
tests and ``benchmarks/bench_ba.py``.  ``self_calibrating_ba`` also estimates the stereo
disparity offset.  All of them work on plain arrays (``LocalBAProblem``).
"""

from __future__ import annotations

import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .geometry import CHI2_MONO, CHI2_STEREO, orthonormalize

DELTA_MONO = float(np.sqrt(CHI2_MONO))
DELTA_STEREO = float(np.sqrt(CHI2_STEREO))


def project(T_cw: np.ndarray, X: np.ndarray, fx: float, fy: float, cx: float, cy: float, bf: float):
    Xc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        iz = 1.0 / z
        u = fx * Xc[:, 0] * iz + cx
        v = fy * Xc[:, 1] * iz + cy
        ur = u - bf * iz
    return Xc, u, v, ur


def reprojection_chi2(
    T_cw: np.ndarray,
    X: np.ndarray,
    uv: np.ndarray,
    ur_obs: np.ndarray,
    inv_sigma2: np.ndarray,
    K: np.ndarray,
    bf: float,
) -> tuple[np.ndarray, np.ndarray]:
    """chi2 of each observation (stereo where ``ur_obs >= 0``) and depth-positive flag."""
    Xc, u, v, ur = project(T_cw, X, K[0, 0], K[1, 1], K[0, 2], K[1, 2], bf)
    st = ur_obs >= 0
    e2 = (uv[:, 0] - u) ** 2 + (uv[:, 1] - v) ** 2 + np.where(st, (ur_obs - ur) ** 2, 0.0)
    chi2 = e2 * inv_sigma2
    front = Xc[:, 2] > 0
    return np.where(front, chi2, np.inf), front


def optimize_pose(
    T_cw: np.ndarray,
    X: np.ndarray,
    uv: np.ndarray,
    ur_obs: np.ndarray,
    inv_sigma2: np.ndarray,
    K: np.ndarray,
    bf: float,
    rounds: int = 4,
    iterations: int = 10,
    outlier: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Motion-only BA.  Returns ``(T_cw, inlier)``.

    One compiled call (``kernels.pose.optimize_pose_kernel``); the vectorized numpy
    version it replaces is the tests' reference (``tests/reference/slam_numpy.py``)."""
    n = len(X)
    T = np.ascontiguousarray(T_cw, dtype=np.float64)
    out = np.zeros(n, bool) if outlier is None else np.asarray(outlier, bool)
    if n < 3:
        return T.copy(), ~out
    # imported here: the local-BA worker process imports this module but never needs numba
    from .kernels.pose import optimize_pose_kernel

    T, out = optimize_pose_kernel(
        T, np.ascontiguousarray(X, np.float64), np.ascontiguousarray(uv, np.float64),
        np.ascontiguousarray(ur_obs, np.float64), np.ascontiguousarray(inv_sigma2, np.float64),
        float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), float(bf),
        int(rounds), int(iterations), out, CHI2_MONO, CHI2_STEREO,
    )
    return orthonormalize(T), ~out


# ---------------------------------------------------------------- bundle adjustment
@dataclass
class LocalBAProblem:
    """A local bundle adjustment, as plain arrays.

    ``kf_ids`` / ``T_wc`` (K, 4, 4) / ``fixed`` (K,) bool; ``pt_ids`` / ``X`` (P, 3);
    observations: ``obs_kf`` / ``obs_pt`` (indices into the above), ``uv`` (M, 2),
    ``ur`` (M,) (< 0: monocular), ``sigma`` (M,) pixels; camera ``K`` and ``baseline``.
    """

    kf_ids: np.ndarray
    T_wc: np.ndarray
    fixed: np.ndarray
    pt_ids: np.ndarray
    X: np.ndarray
    obs_kf: np.ndarray
    obs_pt: np.ndarray
    uv: np.ndarray
    ur: np.ndarray
    sigma: np.ndarray
    K: np.ndarray
    baseline: float
    iterations: int = 5  # LM iterations with Huber kernels (ORB-SLAM2: 5)
    rel_tol: float = 1e-3  # a stage stops when the relative cost decrease falls below it
    # then the outliers (chi2 above the 95% bound, behind the camera) are dropped and this
    # many iterations run without the kernel (ORB-SLAM2: 10); 0: the robust stage only
    refine_iterations: int = 0
    tag: int = 0
    # self-calibration: also estimate the stereo disparity offset (``self_calibrating_ba``)
    offset_grid: tuple[float, ...] | None = None
    offset_prior_sigma: float = 0.25
    # an estimate within this many sigmas of 0 is not significant: no offset applied
    offset_min_sigmas: float = 2.0

    @property
    def bf(self) -> float:
        """Baseline times focal length (px m), the kernels' stereo constant."""
        return float(self.K[0, 0]) * float(self.baseline)

    @property
    def inv_sigma2(self) -> np.ndarray:
        """The observations' information weights ``1 / sigma^2``."""
        sig = np.asarray(self.sigma, np.float64)
        return 1.0 / (sig * sig)


@dataclass
class LocalBAResult:
    kf_ids: np.ndarray
    T_wc: np.ndarray
    pt_ids: np.ndarray
    X: np.ndarray
    iterations: int
    error_before: float
    error_after: float
    ms: float
    tag: int = 0
    offset: float | None = None  # disparity offset (px) the result was computed with
    offset_sigma: float | None = None
    offset_costs: list[float] | None = None
    inlier: np.ndarray | None = None  # (M,) observations kept by the robust stage (kernel only)
    aborted: bool = False  # the abort flag stopped the solve (the last accepted state)


def shift_disparity(uv_u: np.ndarray, ur: np.ndarray, delta: float) -> np.ndarray:
    """Right-image u of stereo observations (``ur >= 0``) whose disparity grows by
    ``delta`` px (kept >= 0.01 px); monocular ones (``ur < 0``) unchanged."""
    st = ur >= 0
    disp = np.maximum(uv_u - ur + delta, 0.01)
    return np.where(st, uv_u - disp, ur)


def self_calibrating_ba(p: LocalBAProblem, abort: np.ndarray | None = None) -> LocalBAResult:
    """Bundle adjustment that also estimates a constant disparity offset ``delta`` (px
    added to every measured disparity: a right-camera principal-point error of the
    rectification).  Such an offset is not a change of scale -- it shifts inverse depth,
    ``1/z = (d + delta) / bf`` -- so points seen from several keyframes at different
    depths observe it.

    The BA is solved at each offset of ``p.offset_grid`` (three); the cost (half the
    chi2) is quadratic in the offset, so the parabola through the three gives the
    estimate and its sigma ``1 / sqrt(curvature)``.  The estimate is shrunk towards 0 by
    a Gaussian prior of ``p.offset_prior_sigma`` px; poses and points are interpolated
    (linearly in the offset) between the two solves around it.  A cost that is not
    convex, an estimate beyond twice the grid, or one within ``p.offset_min_sigmas``
    sigmas of 0 (not significant: a rig without offset, e.g. the synthetic scenes, gave
    -0.03 +- 0.07 px) gives ``offset = None`` and the solve at offset 0."""
    t0 = time.perf_counter()
    grid = np.asarray(p.offset_grid, np.float64)
    problems = [dataclasses.replace(p, ur=shift_disparity(p.uv[:, 0], p.ur, float(d)), offset_grid=None)
                for d in grid]
    # the solves are independent and the kernel releases the GIL: side by side, each
    # on its own thread (the same results; half the wait where a core is free)
    with ThreadPoolExecutor(max_workers=len(problems), thread_name_prefix="selfcal-ba") as pool:
        sols = list(pool.map(lambda q: local_ba(q, abort), problems))
    c = _common_costs(problems, sols)
    a, b, c0 = np.polyfit(grid, c, 2)
    curv = 2.0 * a
    offset = sigma = None
    i0 = int(np.argmin(np.abs(grid)))
    res = sols[i0]
    if curv > 0 and abs(-b / (2.0 * a)) <= 2.0 * np.abs(grid).max():
        prior = 1.0 / p.offset_prior_sigma**2
        offset = float((-b / (2.0 * a)) * curv / (curv + prior))
        sigma = float(1.0 / np.sqrt(curv + prior))
    if offset is not None and abs(offset) < p.offset_min_sigmas * sigma:
        offset = None
    if offset is not None:
        j = int(np.clip(np.searchsorted(grid, offset) - 1, 0, len(grid) - 2))
        w = (offset - grid[j]) / (grid[j + 1] - grid[j])
        r0, r1 = sols[j], sols[j + 1]
        T = (1.0 - w) * r0.T_wc + w * r1.T_wc
        T = np.stack([orthonormalize(t) for t in T])
        res = LocalBAResult(
            r0.kf_ids, T, r0.pt_ids, (1.0 - w) * r0.X + w * r1.X, r0.iterations,
            float(sols[i0].error_before), float(a * offset**2 + b * offset + c0), 0.0, p.tag,
        )
    res.offset, res.offset_sigma, res.offset_costs = offset, sigma, [float(x) for x in c]
    res.aborted = any(r.aborted for r in sols)
    res.ms = (time.perf_counter() - t0) * 1e3  # all the solves
    return res


def _common_costs(problems: list[LocalBAProblem], sols: list[LocalBAResult]) -> np.ndarray:
    """The grid solves' costs (half the chi2) over the same observations: those every solve
    kept after its robust stage (in front of the camera, chi2 under ORB-SLAM2's 95 %
    bounds: the kernel's ``inlier``).  Each solve's own Huber cost over all observations
    let one degenerate point decide the offset: on KITTI 06 a far point beyond infinity
    (behind the cameras at -6,800 m, fitting its pixels) flipped to 2 m behind them in the
    -0.3 px solve and added 600 to that cost alone (an offset of +0.14 px on top of +0.14,
    a path 0.5 % too short)."""
    from .kernels.ba import chi2_cost

    keep = np.logical_and.reduce([s.inlier for s in sols])
    return np.array([chi2_cost(np.linalg.inv(s.T_wc), s.X, q.obs_kf, q.obs_pt, q.uv, q.ur, q.inv_sigma2, keep, q.K,
                               q.bf)
                     for q, s in zip(problems, sols)])


def run_ba(p: LocalBAProblem, abort: np.ndarray | None = None) -> LocalBAResult:
    """``self_calibrating_ba`` when the problem asks for it, else ``local_ba``."""
    return self_calibrating_ba(p, abort) if p.offset_grid else local_ba(p, abort)


def local_ba(p: LocalBAProblem, abort: np.ndarray | None = None) -> LocalBAResult:
    """Solve the BA with the compiled kernel (:func:`.kernels.ba.ba_solve`):
    ``p.iterations`` robust LM iterations, then ``p.refine_iterations`` without the
    kernel on the inliers.  ``abort``: a 1-element int64 array; set non-zero (by another
    thread) it stops the solve between iterations.  ``error_before`` / ``error_after``
    are the Huber cost over all observations (gtsam's ``graph.error`` convention)."""
    from .kernels.ba import solve

    t0 = time.perf_counter()
    T_cw = np.linalg.inv(np.asarray(p.T_wc, np.float64))
    T, X, inl, st = solve(T_cw, p.X, p.obs_kf, p.obs_pt, p.uv, p.ur, p.inv_sigma2, p.fixed, p.K, p.bf,
                          p.iterations, p.refine_iterations, p.rel_tol, abort)
    T_wc = np.linalg.inv(T)
    T_wc[:, 3, :] = (0.0, 0.0, 0.0, 1.0)
    fixed = np.asarray(p.fixed, bool)
    T_wc[fixed] = p.T_wc[fixed]  # exactly as given
    return LocalBAResult(
        p.kf_ids, T_wc, p.pt_ids, X, int(st[0]), float(st[1]), float(st[2]), (time.perf_counter() - t0) * 1e3,
        p.tag, inlier=inl, aborted=bool(st[3]),
    )


def local_ba_gtsam(p: LocalBAProblem) -> LocalBAResult:
    """The reference solver: the BA with gtsam (Levenberg-Marquardt, SEQUENTIAL_CHOLESKY).

    The graph is built with one factor per observation: gtsam's Python API has no
    batch constructor for stereo factors (monocular ones go in per keyframe and level
    through ``gtsam.utilities.insertProjectionFactors``).
    """
    import gtsam

    t0 = time.perf_counter()
    P = len(p.pt_ids)
    Kn = len(p.kf_ids)
    # keys: points 0..P-1, poses P..P+K-1 (plain integers, exact in float64)
    fx, fy, cx, cy = p.K[0, 0], p.K[1, 1], p.K[0, 2], p.K[1, 2]
    Ks = gtsam.Cal3_S2Stereo(fx, fy, 0.0, cx, cy, p.baseline)
    Km = gtsam.Cal3_S2(fx, fy, 0.0, cx, cy)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    # the per-factor loops read Python lists: indexing numpy arrays one scalar at a time
    # costs about as much as making the factor
    for j, X in enumerate(np.asarray(p.X, np.float64)):
        values.insert(j, X)
    for i in range(Kn):
        values.insert(P + i, gtsam.Pose3(p.T_wc[i]))
        if p.fixed[i]:
            graph.add(gtsam.PriorFactorPose3(P + i, gtsam.Pose3(p.T_wc[i]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    sig_levels = np.unique(p.sigma)
    huber_s = gtsam.noiseModel.mEstimator.Huber.Create(DELTA_STEREO)
    huber_m = gtsam.noiseModel.mEstimator.Huber.Create(DELTA_MONO)
    st = p.ur >= 0
    for s in sig_levels:
        model_s = gtsam.noiseModel.Robust.Create(huber_s, gtsam.noiseModel.Isotropic.Sigma(3, float(s)))
        model_m = gtsam.noiseModel.Robust.Create(huber_m, gtsam.noiseModel.Isotropic.Sigma(2, float(s)))
        at_s = p.sigma == s
        sel = np.flatnonzero(at_s & st)
        for u, ur, v, kf, pt in zip(p.uv[sel, 0].tolist(), p.ur[sel].tolist(), p.uv[sel, 1].tolist(),
                                    (P + p.obs_kf[sel]).tolist(), p.obs_pt[sel].tolist()):
            graph.add(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(u, ur, v), model_s, int(kf), int(pt), Ks))
        mono = np.flatnonzero(at_s & ~st)
        if len(mono):
            for i in np.unique(p.obs_kf[mono]):
                sel = mono[p.obs_kf[mono] == i]
                gtsam.utilities.insertProjectionFactors(
                    graph,
                    int(P + i),
                    p.obs_pt[sel].astype(np.float64).reshape(-1, 1),
                    np.ascontiguousarray(p.uv[sel].T),
                    model_m,
                    Km,
                )
    params = gtsam.LevenbergMarquardtParams()
    params.setLinearSolverType("SEQUENTIAL_CHOLESKY")
    # eliminate the points first, then the poses (the Schur complement of BA): 35-40%
    # faster than COLAMD's ordering on our local BA problems, same solution
    params.setOrdering(gtsam.Ordering(list(range(P + Kn))))
    params.setMaxIterations(int(p.iterations))
    params.setRelativeErrorTol(p.rel_tol)  # local BA converges in 2-3 iterations; stop there
    params.setVerbosityLM("SILENT")
    err0 = graph.error(values)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    try:
        res = opt.optimize()
        err1 = graph.error(res)
        its = opt.iterations()
    except RuntimeError:  # indeterminant system etc.: keep the input
        res, err1, its = values, err0, 0
    X = gtsam.utilities.extractPoint3(res).reshape(-1, 3)
    poses = gtsam.utilities.extractPose3(res).reshape(-1, 4, 3)  # rows: R (3x3 row-major), t
    T_wc = np.tile(np.eye(4), (Kn, 1, 1))
    T_wc[:, :3, :3] = poses[:, :3, :]
    T_wc[:, :3, 3] = poses[:, 3, :]
    return LocalBAResult(
        p.kf_ids, T_wc, p.pt_ids, X, int(its), float(err0), float(err1), (time.perf_counter() - t0) * 1e3, p.tag
    )


def optimize_pose_graph(
    T_wc: np.ndarray,
    edges: np.ndarray,
    T_ij: np.ndarray,
    fixed: np.ndarray,
    iterations: int = 20,
    sigma_rot: float = 0.01,
    sigma_trans: float = 0.05,
) -> tuple[np.ndarray, float, float, int]:
    """SE(3) pose graph (ORB-SLAM2's ``OptimizeEssentialGraph`` for a stereo rig: no
    scale) with gtsam, Levenberg-Marquardt with SEQUENTIAL_CHOLESKY.

    ``T_wc`` (K, 4, 4) initial camera-to-world poses; ``edges`` (E, 2) node indices with
    measurements ``T_ij`` (E, 4, 4) = ``T_wc[i]^-1 @ T_wc[j]``; ``fixed`` node indices
    held by tight priors.  Every edge has the same information (rotation ``sigma_rot`` rad,
    translation ``sigma_trans`` m).  Returns ``(T_wc, error before, error after, iterations)``.
    """
    import gtsam

    K = len(T_wc)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i in range(K):
        values.insert(i, gtsam.Pose3(T_wc[i]))
    prior = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    for i in np.unique(np.asarray(fixed, np.int64)):
        graph.add(gtsam.PriorFactorPose3(int(i), gtsam.Pose3(T_wc[i]), prior))
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_rot] * 3 + [sigma_trans] * 3))
    for (i, j), T in zip(np.asarray(edges, np.int64), T_ij):
        graph.add(gtsam.BetweenFactorPose3(int(i), int(j), gtsam.Pose3(T), noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setLinearSolverType("SEQUENTIAL_CHOLESKY")
    params.setMaxIterations(int(iterations))
    params.setVerbosityLM("SILENT")
    err0 = graph.error(values)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    try:
        res = opt.optimize()
        err1, its = graph.error(res), opt.iterations()
    except RuntimeError:  # indeterminant system: keep the input
        return T_wc.copy(), float(err0), float(err0), 0
    poses = gtsam.utilities.extractPose3(res).reshape(-1, 4, 3)
    out = np.tile(np.eye(4), (K, 1, 1))
    out[:, :3, :3] = poses[:, :3, :]
    out[:, :3, 3] = poses[:, 3, :]
    return out, float(err0), float(err1), int(its)
