"""The statistics of the motion test: a static object's predicted flow against its
measurement (:func:`static_chi2`, frame to frame) and its world velocity over the window
(:func:`world_velocity`), vectorized over all objects' points."""

from __future__ import annotations

import numpy as np

from ...datatypes import StereoCalibration
from .flow import ObjectFlow


def _project(uv: np.ndarray, d: np.ndarray, T: np.ndarray, K: np.ndarray, bf: float) -> np.ndarray:
    """``(u, v, d)`` (n, 3) of the stereo points ``(uv, d)`` moved by the 4x4 ``T`` (NaN behind)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Z = bf / d
    X = np.stack([(uv[:, 0] - cx) * Z / fx, (uv[:, 1] - cy) * Z / fy, Z], axis=1)
    Y = X @ T[:3, :3].T + T[:3, 3]
    z = np.where(Y[:, 2] > 1e-6, Y[:, 2], np.nan)
    return np.stack([fx * Y[:, 0] / z + cx, fy * Y[:, 1] / z + cy, bf / z], axis=1)


def _points(uv: np.ndarray, d: np.ndarray, K: np.ndarray, bf: float) -> np.ndarray:
    Z = bf / d
    return np.stack([(uv[:, 0] - K[0, 2]) * Z / K[0, 0], (uv[:, 1] - K[1, 2]) * Z / K[1, 1], Z], axis=1)


def static_residuals(flow: ObjectFlow, T_10: np.ndarray, calib: StereoCalibration, sigma_px: float,
                     sigma_d: float, keep: bool = False):
    """Per point, the residual ``(n, 3)`` of ``(u, v, d)`` at k against a static object's
    prediction from k-1 under the camera motion ``T_10`` (k-1 camera -> k camera, 4x4) and
    its covariance ``(n, 3, 3)``; rows with a prediction behind the camera are dropped
    (``keep``: kept, and their flags returned third)."""
    K, bf = calib.K, calib.bf
    # the prediction and its Jacobian w.r.t. (u0, v0, d0) by forward differences: one
    # projection of the points and of their 3 nudged copies
    n = len(flow.d0)
    steps = np.array([0.5, 0.5, 0.05])
    uvd = np.tile(np.column_stack([flow.uv0, flow.d0]), (4, 1))
    uvd[n:] += np.repeat(np.eye(3) * steps, n, axis=0)
    q = _project(uvd[:, :2], uvd[:, 2], T_10, K, bf).reshape(4, n, 3)
    p = q[0]
    J = ((q[1:] - p) / steps[:, None, None]).transpose(1, 2, 0)  # (n, 3 outputs, 3 inputs)
    S = np.array([sigma_px**2, sigma_px**2, sigma_d**2])
    C = np.einsum("nij,j,nkj->nik", J, S, J) + np.diag(S)
    r = np.stack([flow.uv1[:, 0], flow.uv1[:, 1], flow.d1], axis=1) - p
    ok = np.isfinite(r).all(axis=1) & np.isfinite(C).all(axis=(1, 2))
    return (r, C, ok) if keep else (r[ok], C[ok])


def _mahalanobis(r: np.ndarray, C: np.ndarray) -> np.ndarray:
    return np.einsum("ni,ni->n", r, np.linalg.solve(C, r[:, :, None])[:, :, 0])


def static_chi2(flow: ObjectFlow, T_10: np.ndarray, calib: StereoCalibration, sigma_px: float,
                sigma_d: float) -> np.ndarray:
    """Per point, the chi-square (3 dof) of the static hypothesis (:func:`static_residuals`)."""
    r, C = static_residuals(flow, T_10, calib, sigma_px, sigma_d)
    return _mahalanobis(r, C) if len(r) else np.zeros(0)


def _point_cov(uv: np.ndarray, d: np.ndarray, calib: StereoCalibration, S: np.ndarray) -> np.ndarray:
    """Covariances ``(n, 3, 3)`` of the stereo points ``(uv, d)`` (camera frame) for pixel /
    disparity variances ``S`` = (su^2, sv^2, sd^2): sigma_Z = Z^2 sigma_d / bf, lateral Z
    sigma_px / f, and their correlation."""
    fx, fy, cx, cy = calib.fx, calib.fy, calib.cx, calib.cy
    Z = calib.bf / d
    J = np.zeros((len(d), 3, 3))
    J[:, 0, 0] = Z / fx
    J[:, 1, 1] = Z / fy
    J[:, 0, 2] = -(uv[:, 0] - cx) * Z / (fx * d)
    J[:, 1, 2] = -(uv[:, 1] - cy) * Z / (fy * d)
    J[:, 2, 2] = -Z / d
    return np.einsum("nij,j,nkj->nik", J, S, J)


def _point_velocities(flow: ObjectFlow, seq: int, poses: dict[int, np.ndarray], calib: StereoCalibration,
                      S: np.ndarray):
    """Per point with a known anchor pose: (which points (n,) bool, world displacement per
    frame since the anchor (m, 3), its covariance (m, 3, 3), age in frames (m,), the
    point at k in the camera frame (m, 3))."""
    anchor = flow.seqa.copy()
    anchor[anchor < 0] = seq - 1
    known = np.array(sorted(poses), np.int64)
    use = np.isin(anchor, known)
    K, bf = calib.K, calib.bf
    T1 = poses[seq]
    R1 = T1[:3, :3]
    stack = np.stack([poses[int(k)] for k in known]) if len(known) else np.zeros((0, 4, 4))
    Ta = stack[np.searchsorted(known, anchor[use])]
    Ra = Ta[:, :3, :3]
    age = (seq - anchor[use]).astype(np.float64)
    uva, da, uv1, d1 = flow.uva[use], flow.da[use], flow.uv1[use], flow.d1[use]
    Xa = np.einsum("nij,nj->ni", Ra, _points(uva, da, K, bf)) + Ta[:, :3, 3]
    X1 = _points(uv1, d1, K, bf)
    V = ((X1 @ R1.T + T1[:3, 3]) - Xa) / age[:, None]
    Ca = np.einsum("nij,njk,nlk->nil", Ra, _point_cov(uva, da, calib, S), Ra)
    C = (Ca + R1 @ _point_cov(uv1, d1, calib, S) @ R1.T) / (age**2)[:, None, None]
    return use, V, C, age, X1


def _group_median(v: np.ndarray, group: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Per group, the median of the rows ``v`` (m, c) (``np.median``'s value: the mean of
    the two middle ones for an even count); ``group`` (m,) non-decreasing, ``starts`` /
    ``counts`` its groups' first rows and sizes (all > 0)."""
    lo, hi = starts + (counts - 1) // 2, starts + counts // 2
    out = np.empty((len(counts), v.shape[1]))
    for c in range(v.shape[1]):
        sv = v[np.lexsort((v[:, c], group)), c]
        out[:, c] = 0.5 * (sv[lo] + sv[hi])
    return out


def _object_velocities(V, C, age, X1, group, n_groups, R1, max_points, sigma_rot, sigma_t, median_cov=False):
    """Per object (``group`` (m,) non-decreasing in ``range(n_groups)``: each point's
    object) with points: (which objects (G,) bool, median velocity (g, 3), its covariance
    (g, 3, 3), points used (g,)) -- :func:`world_velocity`'s model, for all objects at once.

    ``median_cov``: the stereo part is the covariance of a *median* of points of unequal
    noise rather than of their mean: ``(pi / 2) / n * s^2`` with ``s = 1 / mean(1 / s_i)``
    (the median of zero-mean normals of deviations ``s_i`` has the variance ``1 / (4 n
    f(0)^2)``, ``f`` their mixture's density), the points' covariances taken as one shape
    scaled by their traces.  The mean covariance is dominated by the few points first seen
    a frame or two ago (their variance goes as ``1 / age^2``), which barely move the median:
    a car driving away 30 m ahead at 10 m/s, its points 1-14 frames old, measured at 1.05 m
    a frame, had a chi-square of 2.7 instead of ~30 and was judged at rest.  With it, the
    mean's covariance is returned fifth (the speed's reported sigma is scaled on it)."""
    counts_all = np.bincount(group, minlength=n_groups)
    has = counts_all > 0
    counts = counts_all[has]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    f = counts.astype(np.float64)
    n = np.minimum(counts, max_points).astype(np.float64)
    X = np.add.reduceat(X1, starts) / f[:, None]
    I3 = np.eye(3)
    pose = (sigma_rot**2 * (np.einsum("gi,gi->g", X, X)[:, None, None] * I3 - X[:, :, None] * X[:, None, :])
            + sigma_t**2 * I3)  # camera frame
    mean_age = np.add.reduceat(age, starts) / f
    Cs = np.add.reduceat(C, starts) / f[:, None, None] * ((np.pi / 2) / n)[:, None, None]
    Cp = R1 @ pose @ R1.T / mean_age[:, None, None]
    v = _group_median(V, group, starts, counts)
    if not median_cov:
        return has, v, Cs + Cp, counts
    tr = np.maximum(np.einsum("nii->n", C), 1e-300)
    scale = 1.0 / ((np.add.reduceat(tr**-0.5, starts) / f) ** 2 * (np.add.reduceat(tr, starts) / f))
    # and the mean's (the speed's reported sigma is calibrated on it)
    return has, v, Cs * np.minimum(scale, 1.0)[:, None, None] + Cp, counts, Cs + Cp


def world_velocity(flow: ObjectFlow, seq: int, poses: dict[int, np.ndarray], calib: StereoCalibration,
                   sigma_px: float, sigma_d: float, max_points: int, sigma_rot: float = 0.0,
                   sigma_t: float = 0.0) -> tuple[np.ndarray, np.ndarray, int] | None:
    """(the object's world displacement per frame (3,), its covariance (3, 3), points used)
    from its points' displacements since they were first seen (``flow.uva`` / ``da`` at
    frame ``seqa``; ``poses``: seq -> 4x4 camera-to-world of the frames tracked, ``seq``
    this frame's): the median of ``(X_k - X_a) / age`` over the points; the covariance is
    the mean point covariance (stereo at both ends, / age^2) * (pi / 2) / n with n at
    most ``max_points`` (the points' errors are not independent: the pose's and the
    disparity's biases are shared), plus the camera motion's own error per frame:
    ``sigma_rot`` (rad) about any axis moves the object's median point X by ``dw x X``,
    ``sigma_t`` (m) shifts it, both as a random walk over the age.  None: no point has
    a known anchor pose."""
    if seq not in poses:
        return None
    S = np.array([sigma_px**2, sigma_px**2, sigma_d**2])
    use, V, C, age, X1 = _point_velocities(flow, seq, poses, calib, S)
    if not use.any():
        return None
    _, v, Cm, n = _object_velocities(V, C, age, X1, np.zeros(len(V), np.int64), 1, poses[seq][:3, :3],
                                     max_points, sigma_rot, sigma_t)
    return v[0], Cm[0], int(n[0])
