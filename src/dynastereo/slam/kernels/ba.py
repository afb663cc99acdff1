"""Local bundle adjustment as one compiled kernel (numba, ``nogil``).

``ba_solve`` is a Levenberg-Marquardt bundle adjustment with the points eliminated by the
Schur complement (g2o's 6x3 block solver, as ORB-SLAM2 uses it): each point's 3x3 block
is inverted, the reduced 6Kx6K camera system is solved by a dense Cholesky, and the point
updates follow by back-substitution.  Residuals are stereo ``(u, v, u_right)`` or
monocular ``(u, v)`` reprojection errors with information ``1 / sigma^2``; poses are
``T_cw`` updated by a left-multiplied se(3) increment ``exp(xi) @ T`` (``xi = (omega,
rho)``, as ``optimizer.optimize_pose``).

ORB-SLAM2's schedule (``Optimizer::LocalBundleAdjustment``):

1. ``n_robust`` iterations with Huber kernels (delta = sqrt of the chi2 95 % bound:
   7.815 stereo, 5.991 mono);
2. observations with chi2 above that bound or a point behind the camera are dropped;
3. ``n_refine`` iterations without the robust kernel on the rest.

Either stage ends early when an accepted step lowers the cost by less than ``rel_tol`` of
it (or after 10 rejected damping increases).  The damping follows gtsam's defaults
(``LAMBDA_INITIAL``, ``LAMBDA_FACTOR``).  ``abort`` (a 1-element int array) is read
between iterations: non-zero stops the solve, leaving the last accepted state.  The
kernel is one call per problem; everything it needs is allocated once at its start.

The cost reported (``stats[1]``, ``stats[2]``) is the Huber cost over every observation
(a point behind its camera included), ``sum rho(sqrt(chi2))`` with ``rho(x) = x^2/2``
below delta and ``delta |x| - delta^2/2`` above -- gtsam's ``graph.error`` convention.
``chi2_cost`` gives half the chi2 of chosen observations (``self_calibrating_ba`` compares
its three solves over the inliers of all three).
"""

from __future__ import annotations

import math

import numpy as np

from ...compiled import jit

CHI2_MONO = 5.991
CHI2_STEREO = 7.815
# Levenberg-Marquardt damping (H + lambda I), gtsam's defaults: start at 1e-5, /10 after an
# accepted step, x10 after a rejected one.  g2o's start (1e-5 x the largest diagonal entry)
# damps the points far too much here: camera blocks are ~1e6 times larger than point blocks
LAMBDA_INITIAL = 1e-5
LAMBDA_FACTOR = 10.0


@jit(inline="always")
def _huber_rho(chi2: float, delta: float) -> float:
    """0.5 * rho(chi2) (g2o's Huber on the squared error, halved: gtsam's loss)."""
    if chi2 <= delta * delta:
        return 0.5 * chi2
    return delta * math.sqrt(chi2) - 0.5 * delta * delta


@jit
def _project(Tcw, X, k, p, fx, fy, cx, cy, bf, out):
    """Camera coordinates and projection of point ``p`` in keyframe ``k``:
    out = (xc, yc, zc, u, v, ur); returns False when the depth is (numerically) 0.  A
    point behind the camera is projected all the same (as g2o and gtsam do): its large
    error keeps the solver from moving points behind cameras."""
    xw, yw, zw = X[p, 0], X[p, 1], X[p, 2]
    xc = Tcw[k, 0, 0] * xw + Tcw[k, 0, 1] * yw + Tcw[k, 0, 2] * zw + Tcw[k, 0, 3]
    yc = Tcw[k, 1, 0] * xw + Tcw[k, 1, 1] * yw + Tcw[k, 1, 2] * zw + Tcw[k, 1, 3]
    zc = Tcw[k, 2, 0] * xw + Tcw[k, 2, 1] * yw + Tcw[k, 2, 2] * zw + Tcw[k, 2, 3]
    out[0], out[1], out[2] = xc, yc, zc
    if abs(zc) <= 1e-9:
        return False
    iz = 1.0 / zc
    u = fx * xc * iz + cx
    out[3] = u
    out[4] = fy * yc * iz + cy
    out[5] = u - bf * iz
    return True


@jit
def _obs_chi2(Tcw, X, k, p, meas, stereo, isig2, i, fx, fy, cx, cy, bf, tmp):
    """chi2 of observation ``i`` (``tmp[2]``: the depth); 1e12 at depth 0."""
    if not _project(Tcw, X, k, p, fx, fy, cx, cy, bf, tmp):
        return 1e12
    du = meas[i, 0] - tmp[3]
    dv = meas[i, 1] - tmp[4]
    e2 = du * du + dv * dv
    if stereo[i]:
        dr = meas[i, 2] - tmp[5]
        e2 += dr * dr
    return e2 * isig2[i]


@jit
def ba_cost(Tcw, X, obs_kf, obs_pt, meas, stereo, isig2, active, fx, fy, cx, cy, bf, mode, tmp):
    """Cost of the observations: ``mode`` 0 = Huber over the active ones (stage 1),
    1 = plain chi2/2 over the active ones (stage 2), 2 = Huber over all (the reported
    cost)."""
    c = 0.0
    for i in range(obs_kf.shape[0]):
        if mode != 2 and active[i] == 0:
            continue
        chi2 = _obs_chi2(Tcw, X, obs_kf[i], obs_pt[i], meas, stereo, isig2, i, fx, fy, cx, cy, bf, tmp)
        if mode == 1:
            c += 0.5 * chi2
        else:
            c += _huber_rho(chi2, 2.7955321496988725 if stereo[i] else 2.4476519360399265)
    return c


@jit
def _linearize(Tcw, X, obs_kf, obs_pt, meas, stereo, isig2, active, robust, fx, fy, cx, cy, bf,
               cam_var, Jc, Jp, E, Wt, tmp):
    """Residuals, Jacobians and weights of every observation (weight 0: not used)."""
    for i in range(obs_kf.shape[0]):
        Wt[i] = 0.0
        if active[i] == 0:
            continue
        k, p = obs_kf[i], obs_pt[i]
        if not _project(Tcw, X, k, p, fx, fy, cx, cy, bf, tmp):
            continue
        xc, yc, zc = tmp[0], tmp[1], tmp[2]
        iz = 1.0 / zc
        iz2 = iz * iz
        st = stereo[i]
        E[i, 0] = meas[i, 0] - tmp[3]
        E[i, 1] = meas[i, 1] - tmp[4]
        E[i, 2] = meas[i, 2] - tmp[5] if st else 0.0
        chi2 = (E[i, 0] * E[i, 0] + E[i, 1] * E[i, 1] + E[i, 2] * E[i, 2]) * isig2[i]
        w = isig2[i]
        if robust:
            delta = 2.7955321496988725 if st else 2.4476519360399265
            s = math.sqrt(chi2)
            if s > delta:
                w *= delta / s
        Wt[i] = w
        # d(u, v, ur) / d(Xc)
        a00 = fx * iz
        a02 = -fx * xc * iz2
        a11 = fy * iz
        a12 = -fy * yc * iz2
        a20 = fx * iz if st else 0.0
        a22 = -(fx * xc - bf) * iz2 if st else 0.0
        # point Jacobian: d/dXc @ R
        for c in range(3):
            r0 = Tcw[k, 0, c]
            r1 = Tcw[k, 1, c]
            r2 = Tcw[k, 2, c]
            Jp[i, 0, c] = a00 * r0 + a02 * r2
            Jp[i, 1, c] = a11 * r1 + a12 * r2
            Jp[i, 2, c] = a20 * r0 + a22 * r2
        if cam_var[k] >= 0:
            # d(Xc)/d(xi) = [-[Xc]x, I]: columns omega (0..2), rho (3..5)
            # -[Xc]x = [[0, zc, -yc], [-zc, 0, xc], [yc, -xc, 0]]
            Jc[i, 0, 0] = a02 * yc
            Jc[i, 0, 1] = a00 * zc - a02 * xc
            Jc[i, 0, 2] = -a00 * yc
            Jc[i, 0, 3] = a00
            Jc[i, 0, 4] = 0.0
            Jc[i, 0, 5] = a02
            Jc[i, 1, 0] = -a11 * zc + a12 * yc
            Jc[i, 1, 1] = -a12 * xc
            Jc[i, 1, 2] = a11 * xc
            Jc[i, 1, 3] = 0.0
            Jc[i, 1, 4] = a11
            Jc[i, 1, 5] = a12
            Jc[i, 2, 0] = a22 * yc
            Jc[i, 2, 1] = a20 * zc - a22 * xc
            Jc[i, 2, 2] = -a20 * yc
            Jc[i, 2, 3] = a20
            Jc[i, 2, 4] = 0.0
            Jc[i, 2, 5] = a22


@jit
def _build(obs_kf, obs_pt, cam_var, Jc, Jp, E, Wt, Hcc, bc, Hpp, bp, Hcp):
    Hcc[:] = 0.0
    bc[:] = 0.0
    Hpp[:] = 0.0
    bp[:] = 0.0
    for i in range(obs_kf.shape[0]):
        w = Wt[i]
        if w == 0.0:
            continue
        p = obs_pt[i]
        c = cam_var[obs_kf[i]]
        for a in range(3):
            s = 0.0
            for r in range(3):
                s += Jp[i, r, a] * E[i, r]
            bp[p, a] += w * s
            for b in range(a, 3):
                s = 0.0
                for r in range(3):
                    s += Jp[i, r, a] * Jp[i, r, b]
                Hpp[p, a, b] += w * s
        if c < 0:
            continue
        for a in range(6):
            s = 0.0
            for r in range(3):
                s += Jc[i, r, a] * E[i, r]
            bc[c, a] += w * s
            for b in range(a, 6):
                s = 0.0
                for r in range(3):
                    s += Jc[i, r, a] * Jc[i, r, b]
                Hcc[c, a, b] += w * s
            for b in range(3):
                s = 0.0
                for r in range(3):
                    s += Jc[i, r, a] * Jp[i, r, b]
                Hcp[i, a, b] = w * s
    # symmetric halves
    for p in range(Hpp.shape[0]):
        for a in range(3):
            for b in range(a):
                Hpp[p, a, b] = Hpp[p, b, a]
    for c in range(Hcc.shape[0]):
        for a in range(6):
            for b in range(a):
                Hcc[c, a, b] = Hcc[c, b, a]


@jit
def _cholesky_solve(S, r, n):
    """Solve S x = r (n x n, SPD) in place: S becomes its Cholesky factor, r the
    solution.  Returns False when S is not positive definite."""
    for j in range(n):
        d = S[j, j]
        for k in range(j):
            d -= S[j, k] * S[j, k]
        if not d > 1e-300:
            return False
        d = math.sqrt(d)
        S[j, j] = d
        inv = 1.0 / d
        for i in range(j + 1, n):
            s = S[i, j]
            for k in range(j):
                s -= S[i, k] * S[j, k]
            S[i, j] = s * inv
    for i in range(n):
        s = r[i]
        for k in range(i):
            s -= S[i, k] * r[k]
        r[i] = s / S[i, i]
    for i in range(n - 1, -1, -1):
        s = r[i]
        for k in range(i + 1, n):
            s -= S[k, i] * r[k]
        r[i] = s / S[i, i]
    return True


@jit
def _solve_damped(lam, obs_kf, obs_pt, pt_start, pt_obs, cam_var, nc, Hcc, bc, Hpp, bp, Hcp, Wt,
                  Pinv, Y, S, rhs, dx_c, dx_p):
    """The LM step at damping ``lam`` (H + lam I) by the Schur complement.  Returns False
    when the reduced camera system is not positive definite."""
    P = Hpp.shape[0]
    n = 6 * nc
    for a in range(n):
        for b in range(n):
            S[a, b] = 0.0
    for c in range(nc):
        for a in range(6):
            rhs[6 * c + a] = bc[c, a]
            for b in range(6):
                S[6 * c + a, 6 * c + b] = Hcc[c, a, b]
            S[6 * c + a, 6 * c + a] += lam
    for p in range(P):
        a00 = Hpp[p, 0, 0] + lam
        a01 = Hpp[p, 0, 1]
        a02 = Hpp[p, 0, 2]
        a11 = Hpp[p, 1, 1] + lam
        a12 = Hpp[p, 1, 2]
        a22 = Hpp[p, 2, 2] + lam
        c00 = a11 * a22 - a12 * a12
        c01 = a02 * a12 - a01 * a22
        c02 = a01 * a12 - a02 * a11
        det = a00 * c00 + a01 * c01 + a02 * c02
        if not det > 1e-30:
            for a in range(3):
                for b in range(3):
                    Pinv[p, a, b] = 0.0
            continue
        idet = 1.0 / det
        Pinv[p, 0, 0] = c00 * idet
        Pinv[p, 0, 1] = c01 * idet
        Pinv[p, 0, 2] = c02 * idet
        Pinv[p, 1, 0] = c01 * idet
        Pinv[p, 1, 1] = (a00 * a22 - a02 * a02) * idet
        Pinv[p, 1, 2] = (a01 * a02 - a00 * a12) * idet
        Pinv[p, 2, 0] = c02 * idet
        Pinv[p, 2, 1] = (a01 * a02 - a00 * a12) * idet
        Pinv[p, 2, 2] = (a00 * a11 - a01 * a01) * idet
        # Y_i = Hcp_i Pinv for the point's observations by free cameras
        for q in range(pt_start[p], pt_start[p + 1]):
            i = pt_obs[q]
            ci = cam_var[obs_kf[i]]
            if ci < 0 or Wt[i] == 0.0:
                continue
            for a in range(6):
                for b in range(3):
                    Y[i, a, b] = Hcp[i, a, 0] * Pinv[p, 0, b] + Hcp[i, a, 1] * Pinv[p, 1, b] + Hcp[i, a, 2] * Pinv[p, 2, b]
                rhs[6 * ci + a] -= Y[i, a, 0] * bp[p, 0] + Y[i, a, 1] * bp[p, 1] + Y[i, a, 2] * bp[p, 2]
        for q in range(pt_start[p], pt_start[p + 1]):
            i = pt_obs[q]
            ci = cam_var[obs_kf[i]]
            if ci < 0 or Wt[i] == 0.0:
                continue
            for q2 in range(pt_start[p], pt_start[p + 1]):
                j = pt_obs[q2]
                cj = cam_var[obs_kf[j]]
                if cj < 0 or Wt[j] == 0.0 or cj > ci:
                    continue
                for a in range(6):
                    for b in range(6):
                        S[6 * ci + a, 6 * cj + b] -= (
                            Y[i, a, 0] * Hcp[j, b, 0] + Y[i, a, 1] * Hcp[j, b, 1] + Y[i, a, 2] * Hcp[j, b, 2]
                        )
    # S's lower triangle (block rows ci >= cj) is complete; the factorization reads only it
    # a scalar Cholesky, not LAPACK's: LAPACK's threads fight tracking's for the cores (on a
    # busy 2-core machine potrf of 300 unknowns took 8x longer with them than without)
    if n > 0:
        if not _cholesky_solve(S, rhs, n):
            return False
    for c in range(nc):
        for a in range(6):
            dx_c[c, a] = rhs[6 * c + a]
    # back-substitution: dp = Pinv (bp - sum Hcp^T dc)
    for p in range(P):
        g0, g1, g2 = bp[p, 0], bp[p, 1], bp[p, 2]
        for q in range(pt_start[p], pt_start[p + 1]):
            i = pt_obs[q]
            ci = cam_var[obs_kf[i]]
            if ci < 0 or Wt[i] == 0.0:
                continue
            for a in range(6):
                d = dx_c[ci, a]
                g0 -= Hcp[i, a, 0] * d
                g1 -= Hcp[i, a, 1] * d
                g2 -= Hcp[i, a, 2] * d
        for a in range(3):
            dx_p[p, a] = Pinv[p, a, 0] * g0 + Pinv[p, a, 1] * g1 + Pinv[p, a, 2] * g2
    return True


@jit
def _exp_left(T, k, xi, c, tmp):
    """T[k] = exp(xi[c]) @ T[k] (xi = (omega, rho)); tmp: (3, 3, 3) scratch."""
    w0, w1, w2 = xi[c, 0], xi[c, 1], xi[c, 2]
    p0, p1, p2 = xi[c, 3], xi[c, 4], xi[c, 5]
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    th = math.sqrt(th2)
    if th < 1e-10:
        A = 1.0
        B = 0.5
        C = 1.0 / 6.0
    else:
        A = math.sin(th) / th
        B = (1.0 - math.cos(th)) / th2
        C = (th - math.sin(th)) / (th2 * th)
    # W = [w]x, W2 = W @ W
    W = tmp[0]
    R = tmp[1]
    V = tmp[2]
    W[0, 0], W[0, 1], W[0, 2] = 0.0, -w2, w1
    W[1, 0], W[1, 1], W[1, 2] = w2, 0.0, -w0
    W[2, 0], W[2, 1], W[2, 2] = -w1, w0, 0.0
    for a in range(3):
        for b in range(3):
            w2ab = W[a, 0] * W[0, b] + W[a, 1] * W[1, b] + W[a, 2] * W[2, b]
            eye = 1.0 if a == b else 0.0
            R[a, b] = eye + A * W[a, b] + B * w2ab
            V[a, b] = eye + B * W[a, b] + C * w2ab
    t0 = V[0, 0] * p0 + V[0, 1] * p1 + V[0, 2] * p2
    t1 = V[1, 0] * p0 + V[1, 1] * p1 + V[1, 2] * p2
    t2 = V[2, 0] * p0 + V[2, 1] * p1 + V[2, 2] * p2
    for b in range(4):
        m0, m1, m2 = T[k, 0, b], T[k, 1, b], T[k, 2, b]
        T[k, 0, b] = R[0, 0] * m0 + R[0, 1] * m1 + R[0, 2] * m2
        T[k, 1, b] = R[1, 0] * m0 + R[1, 1] * m1 + R[1, 2] * m2
        T[k, 2, b] = R[2, 0] * m0 + R[2, 1] * m1 + R[2, 2] * m2
    T[k, 0, 3] += t0
    T[k, 1, 3] += t1
    T[k, 2, 3] += t2


@jit
def ba_solve(Tcw, X, obs_kf, obs_pt, meas, stereo, isig2, fixed, fx, fy, cx, cy, bf,
             n_robust, n_refine, rel_tol, abort, active, stats):
    """Bundle adjustment in place (module doc).

    ``Tcw`` (K, 4, 4) world-to-camera poses, ``X`` (P, 3) points, observations
    ``obs_kf`` / ``obs_pt`` (M,) indices, ``meas`` (M, 3) = (u, v, u_right), ``stereo``
    (M,) bool, ``isig2`` (M,) information, ``fixed`` (K,) bool.  ``active`` (M,) uint8:
    in: 1 = use the observation; out: 0 for the outliers found after the robust stage
    (chi2 above its bound or point behind the camera).  ``stats`` (5,) out: iterations,
    cost before, cost after (Huber over all, module doc), aborted (0/1), outliers.
    """
    K = Tcw.shape[0]
    P = X.shape[0]
    M = obs_kf.shape[0]
    cam_var = np.full(K, -1, np.int64)
    nc = 0
    for k in range(K):
        if not fixed[k]:
            cam_var[k] = nc
            nc += 1
    # observations grouped by point
    pt_start = np.zeros(P + 1, np.int64)
    for i in range(M):
        pt_start[obs_pt[i] + 1] += 1
    for p in range(P):
        pt_start[p + 1] += pt_start[p]
    fill = pt_start[:-1].copy()
    pt_obs = np.empty(M, np.int64)
    for i in range(M):
        p = obs_pt[i]
        pt_obs[fill[p]] = i
        fill[p] += 1
    # buffers, allocated once
    Jc = np.zeros((M, 3, 6))
    Jp = np.zeros((M, 3, 3))
    E = np.zeros((M, 3))
    Wt = np.zeros(M)
    Hcc = np.zeros((max(nc, 1), 6, 6))
    bc = np.zeros((max(nc, 1), 6))
    Hpp = np.zeros((P, 3, 3))
    bp = np.zeros((P, 3))
    Hcp = np.zeros((M, 6, 3))
    Y = np.zeros((M, 6, 3))
    Pinv = np.zeros((P, 3, 3))
    S = np.zeros((6 * nc, 6 * nc))
    rhs = np.zeros(6 * nc)
    dx_c = np.zeros((max(nc, 1), 6))
    dx_p = np.zeros((P, 3))
    T_old = Tcw.copy()
    X_old = X.copy()
    tmp = np.zeros(6)
    tmp44 = np.zeros((3, 3, 3))

    stats[1] = ba_cost(Tcw, X, obs_kf, obs_pt, meas, stereo, isig2, active, fx, fy, cx, cy, bf, 2, tmp)
    stats[3] = 0.0
    its = 0
    aborted = False
    for stage in range(2):
        n_it = n_robust if stage == 0 else n_refine
        robust = stage == 0
        mode = 0 if robust else 1
        if stage == 1:
            # ORB-SLAM2: outliers of the robust stage leave; the rest without the kernel
            n_out = 0
            for i in range(M):
                if active[i] == 0:
                    continue
                chi2 = _obs_chi2(Tcw, X, obs_kf[i], obs_pt[i], meas, stereo, isig2, i, fx, fy, cx, cy, bf, tmp)
                th = CHI2_STEREO if stereo[i] else CHI2_MONO
                if tmp[2] <= 0.0 or chi2 > th:
                    active[i] = 0
                    n_out += 1
            stats[4] = n_out
        if n_it <= 0 or aborted:
            continue
        F0 = ba_cost(Tcw, X, obs_kf, obs_pt, meas, stereo, isig2, active, fx, fy, cx, cy, bf, mode, tmp)
        lam = -1.0
        for it in range(n_it):
            if abort[0] != 0:
                aborted = True
                break
            its += 1
            _linearize(Tcw, X, obs_kf, obs_pt, meas, stereo, isig2, active, robust, fx, fy, cx, cy, bf,
                       cam_var, Jc, Jp, E, Wt, tmp)
            _build(obs_kf, obs_pt, cam_var, Jc, Jp, E, Wt, Hcc, bc, Hpp, bp, Hcp)
            if lam < 0.0:
                lam = LAMBDA_INITIAL
            accepted = False
            F1 = F0
            for _try in range(10):
                ok = _solve_damped(lam, obs_kf, obs_pt, pt_start, pt_obs, cam_var, nc, Hcc, bc, Hpp, bp, Hcp,
                                   Wt, Pinv, Y, S, rhs, dx_c, dx_p)
                if ok:
                    for k in range(K):
                        for a in range(4):
                            for b in range(4):
                                T_old[k, a, b] = Tcw[k, a, b]
                    for p in range(P):
                        for a in range(3):
                            X_old[p, a] = X[p, a]
                    for k in range(K):
                        c = cam_var[k]
                        if c >= 0:
                            _exp_left(Tcw, k, dx_c, c, tmp44)
                    for p in range(P):
                        for a in range(3):
                            X[p, a] += dx_p[p, a]
                    F1 = ba_cost(Tcw, X, obs_kf, obs_pt, meas, stereo, isig2, active, fx, fy, cx, cy, bf, mode, tmp)
                    # predicted decrease of the quadratic model: dx . (lam dx + b) / 2
                    pred = 0.0
                    for c in range(nc):
                        for a in range(6):
                            pred += dx_c[c, a] * (lam * dx_c[c, a] + bc[c, a])
                    for p in range(P):
                        for a in range(3):
                            pred += dx_p[p, a] * (lam * dx_p[p, a] + bp[p, a])
                    pred *= 0.5
                    rho = (F0 - F1) / pred if pred > 0.0 else -1.0
                    if F1 < F0 and rho > 0.0 and math.isfinite(F1):
                        lam = max(lam / LAMBDA_FACTOR, 1e-12)
                        accepted = True
                        break
                    # rejected: back to the state before the step
                    for k in range(K):
                        for a in range(4):
                            for b in range(4):
                                Tcw[k, a, b] = T_old[k, a, b]
                    for p in range(P):
                        for a in range(3):
                            X[p, a] = X_old[p, a]
                lam *= LAMBDA_FACTOR
            if not accepted:
                break
            dec = F0 - F1
            F0 = F1
            if dec <= rel_tol * F1:
                break
    stats[0] = its
    stats[2] = ba_cost(Tcw, X, obs_kf, obs_pt, meas, stereo, isig2, active, fx, fy, cx, cy, bf, 2, tmp)
    stats[3] = 1.0 if aborted else 0.0


def _observations(obs_kf, obs_pt, uv, ur, inv_sigma2):
    """The kernels' observation arrays: ``(obs_kf, obs_pt, meas, stereo, isig2)``."""
    ur = np.asarray(ur, np.float64)
    meas = np.ascontiguousarray(np.c_[np.asarray(uv, np.float64), ur])
    return (np.ascontiguousarray(obs_kf, np.int64), np.ascontiguousarray(obs_pt, np.int64), meas, ur >= 0,
            np.ascontiguousarray(inv_sigma2, np.float64))


def solve(T_cw, X, obs_kf, obs_pt, uv, ur, inv_sigma2, fixed, K, bf, n_robust, n_refine, rel_tol,
          abort=None):
    """``ba_solve`` on numpy arrays (copies); returns ``(T_cw, X, inlier, stats)``."""
    T = np.ascontiguousarray(T_cw, np.float64).copy()
    Xo = np.ascontiguousarray(X, np.float64).copy()
    obs = _observations(obs_kf, obs_pt, uv, ur, inv_sigma2)
    active = np.ones(len(obs[0]), np.uint8)
    stats = np.zeros(5)
    ab = np.zeros(1, np.int64) if abort is None else abort
    ba_solve(T, Xo, *obs, np.ascontiguousarray(fixed, np.bool_),
             float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), float(bf),
             int(n_robust), int(n_refine), float(rel_tol), ab, active, stats)
    return T, Xo, active.astype(bool), stats


def chi2_cost(T_cw, X, obs_kf, obs_pt, uv, ur, inv_sigma2, active, K, bf) -> float:
    """Half the chi2 of the ``active`` observations (``ba_cost``'s mode 1) on numpy arrays."""
    return float(ba_cost(np.ascontiguousarray(T_cw, np.float64), np.ascontiguousarray(X, np.float64),
                         *_observations(obs_kf, obs_pt, uv, ur, inv_sigma2),
                         np.ascontiguousarray(active, np.uint8), float(K[0, 0]), float(K[1, 1]),
                         float(K[0, 2]), float(K[1, 2]), float(bf), 1, np.zeros(6)))


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel on a tiny problem."""
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    T = np.tile(np.eye(4), (2, 1, 1))
    T[1, 0, 3] = -0.5
    X = np.array([[0.0, 0.0, 10.0], [1.0, 0.5, 12.0], [-1.0, -0.5, 8.0]])
    kf = np.array([0, 0, 0, 1, 1, 1])
    pt = np.array([0, 1, 2, 0, 1, 2])
    uv = np.zeros((6, 2))
    ur = np.zeros(6)
    for i in range(6):
        Xc = T[kf[i], :3, :3] @ X[pt[i]] + T[kf[i], :3, 3]
        uv[i] = K[0, 0] * Xc[0] / Xc[2] + K[0, 2], K[1, 1] * Xc[1] / Xc[2] + K[1, 2]
        ur[i] = uv[i, 0] - 250.0 / Xc[2]
    ur[-1] = -1.0
    solve(T, X + 0.01, kf, pt, uv, ur, np.ones(6), np.array([True, False]), K, 250.0, 2, 2, 1e-6)
    chi2_cost(T, X, kf, pt, uv, ur, np.ones(6), np.ones(6, np.uint8), K, 250.0)  # the self-calibrating BA's costs
