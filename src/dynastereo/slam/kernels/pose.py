"""Motion-only BA of one frame as one compiled call (ORB-SLAM2 ``Optimizer::PoseOptimization``).

``optimize_pose_kernel`` runs the whole schedule -- ``rounds`` x ``iterations``
Gauss-Newton steps on SE(3) (left perturbation ``xi = (omega, rho)``), Huber weights in the
first two rounds, outliers re-classified by chi2 after each round -- in scalar loops over the
observations: no per-iteration (N, 3, 6) Jacobian arrays.  The arithmetic is the numpy
version's (``tests/reference/slam_numpy.py``), term by term; sums run in observation order,
so poses agree with it to rounding (~1e-12) and the inlier sets are the same unless a chi2
lies within rounding of its threshold.
"""

from __future__ import annotations

import math

import numpy as np

from ...compiled import jit


@jit
def se3_exp_left(xi, T, E, out):
    """``out = exp(xi) @ T`` for a twist ``xi = (omega, rho)`` (``geometry.se3_exp`` term by
    term, in scalar code; ``E`` is a 4x4 work array)."""
    wx, wy, wz = xi[0], xi[1], xi[2]
    th = math.sqrt(wx * wx + wy * wy + wz * wz)
    small = th < 1e-10
    a = b = c = 0.0
    if not small:
        a = math.sin(th) / th
        b = (1.0 - math.cos(th)) / th**2
        c = (th - math.sin(th)) / th**3
    for i in range(3):
        acc = 0.0
        for j in range(3):
            # W = skew(w) and (W @ W)[i, j]
            wij = _skew(wx, wy, wz, i, j)
            w2 = _skew(wx, wy, wz, i, 0) * _skew(wx, wy, wz, 0, j) + _skew(wx, wy, wz, i, 1) * _skew(wx, wy, wz, 1, j) \
                + _skew(wx, wy, wz, i, 2) * _skew(wx, wy, wz, 2, j)
            e = 1.0 if i == j else 0.0
            if small:
                E[i, j] = e + wij
                v = e + 0.5 * wij
            else:
                E[i, j] = (e + a * wij) + b * w2
                v = (e + b * wij) + c * w2
            acc += v * xi[3 + j]  # V @ rho
        E[i, 3] = acc
    E[3, 0] = 0.0
    E[3, 1] = 0.0
    E[3, 2] = 0.0
    E[3, 3] = 1.0
    for i in range(4):
        for j in range(4):
            s = 0.0
            for k in range(4):
                s += E[i, k] * T[k, j]
            out[i, j] = s


@jit
def _skew(wx, wy, wz, i, j):
    """Element (i, j) of the skew matrix of (wx, wy, wz)."""
    if i == 0:
        return 0.0 if j == 0 else (-wz if j == 1 else wy)
    if i == 1:
        return wz if j == 0 else (0.0 if j == 1 else -wx)
    return -wy if j == 0 else (wx if j == 1 else 0.0)


@jit
def solve_spd6(H, b, x):
    """Solve the 6x6 system ``H x = b`` by Gaussian elimination with partial pivoting;
    False when singular."""
    n = 6
    A = np.empty((6, 6))
    y = np.empty(6)
    for r in range(n):
        y[r] = b[r]
        for k in range(n):
            A[r, k] = H[r, k]
    for c in range(n):
        p = c
        best = abs(A[c, c])
        for r in range(c + 1, n):
            if abs(A[r, c]) > best:
                best = abs(A[r, c])
                p = r
        if not (best > 0.0) or best == np.inf:
            return False
        if p != c:
            for k in range(n):
                t = A[c, k]
                A[c, k] = A[p, k]
                A[p, k] = t
            t = y[c]
            y[c] = y[p]
            y[p] = t
        for r in range(c + 1, n):
            f = A[r, c] / A[c, c]
            if f != 0.0:
                for k in range(c, n):
                    A[r, k] -= f * A[c, k]
                y[r] -= f * y[c]
    for c in range(n - 1, -1, -1):
        s = y[c]
        for k in range(c + 1, n):
            s -= A[c, k] * x[k]
        x[c] = s / A[c, c]
    return True


@jit
def reprojection_chi2_kernel(T, X, uv, ur_obs, inv_sigma2, fx, fy, cx, cy, bf, chi2, front):
    """chi2 of each observation (stereo where ``ur_obs >= 0``; inf behind the camera)."""
    for n in range(X.shape[0]):
        x = T[0, 0] * X[n, 0] + T[0, 1] * X[n, 1] + T[0, 2] * X[n, 2] + T[0, 3]
        y = T[1, 0] * X[n, 0] + T[1, 1] * X[n, 1] + T[1, 2] * X[n, 2] + T[1, 3]
        z = T[2, 0] * X[n, 0] + T[2, 1] * X[n, 1] + T[2, 2] * X[n, 2] + T[2, 3]
        if z > 0:
            iz = 1.0 / z
            u = fx * x * iz + cx
            v = fy * y * iz + cy
            e2 = (uv[n, 0] - u) ** 2 + (uv[n, 1] - v) ** 2
            if ur_obs[n] >= 0:
                e2 += (ur_obs[n] - (u - bf * iz)) ** 2
            chi2[n] = e2 * inv_sigma2[n]
            front[n] = True
        else:
            chi2[n] = np.inf
            front[n] = False


@jit
def optimize_pose_kernel(T0, X, uv, ur_obs, inv_sigma2, fx, fy, cx, cy, bf, rounds, iterations, outlier,
                         chi2_mono, chi2_stereo):
    """The whole pose optimization; returns ``(T, outlier)`` (T not yet orthonormalized)."""
    n = X.shape[0]
    T = np.empty((4, 4))
    for i in range(4):
        for j in range(4):
            T[i, j] = T0[i, j]
    Tn = np.empty((4, 4))
    E = np.empty((4, 4))
    out = np.empty(n, np.bool_)
    for i in range(n):
        out[i] = outlier[i]
    d_mono = math.sqrt(chi2_mono)
    d_stereo = math.sqrt(chi2_stereo)
    H = np.zeros((6, 6))
    g = np.zeros(6)
    dx = np.zeros(6)
    J = np.zeros((3, 6))
    e = np.zeros(3)
    chi2 = np.empty(n)
    front = np.empty(n, np.bool_)
    for rnd in range(rounds):
        robust = rnd < 2
        na = 0
        for i in range(n):
            if not out[i]:
                na += 1
        if na < 3:
            break
        for _it in range(iterations):
            for p in range(6):
                g[p] = 0.0
                for q in range(6):
                    H[p, q] = 0.0
            for i in range(n):
                if out[i]:
                    continue
                x = T[0, 0] * X[i, 0] + T[0, 1] * X[i, 1] + T[0, 2] * X[i, 2] + T[0, 3]
                y = T[1, 0] * X[i, 0] + T[1, 1] * X[i, 1] + T[1, 2] * X[i, 2] + T[1, 3]
                z = T[2, 0] * X[i, 0] + T[2, 1] * X[i, 1] + T[2, 2] * X[i, 2] + T[2, 3]
                if not (z > 1e-6):
                    continue  # weight 0: no contribution
                iz = 1.0 / z
                u = fx * x * iz + cx
                v = fy * y * iz + cy
                st = ur_obs[i] >= 0
                e[0] = uv[i, 0] - u
                e[1] = uv[i, 1] - v
                e[2] = (ur_obs[i] - (u - bf * iz)) if st else 0.0
                c2 = (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]) * inv_sigma2[i]
                w = 1.0
                if robust:
                    s = math.sqrt(c2)
                    da = d_stereo if st else d_mono
                    if not (s <= da):
                        w = da / max(s, 1e-12)
                w = w * inv_sigma2[i]
                iz2 = iz * iz
                # Jp (d(u, v, ur)/d(Xc)) @ Jx (d(Xc)/d(xi) = [-[Xc]x, I])
                a0 = fx * iz
                a2 = -fx * x * iz2
                b1 = fy * iz
                b2 = -fy * y * iz2
                c0 = fx * iz
                c2_ = -(fx * x - bf) * iz2
                # row u: a0 * [0, z, -y, 1, 0, 0] + a2 * [y, -x, 0, 0, 0, 1]
                J[0, 0] = a2 * y
                J[0, 1] = a0 * z - a2 * x
                J[0, 2] = -a0 * y
                J[0, 3] = a0
                J[0, 4] = 0.0
                J[0, 5] = a2
                # row v: b1 * [-z, 0, x, 0, 1, 0] + b2 * [y, -x, 0, 0, 0, 1]
                J[1, 0] = -b1 * z + b2 * y
                J[1, 1] = -b2 * x
                J[1, 2] = b1 * x
                J[1, 3] = 0.0
                J[1, 4] = b1
                J[1, 5] = b2
                if st:
                    J[2, 0] = c2_ * y
                    J[2, 1] = c0 * z - c2_ * x
                    J[2, 2] = -c0 * y
                    J[2, 3] = c0
                    J[2, 4] = 0.0
                    J[2, 5] = c2_
                else:
                    for k in range(6):
                        J[2, k] = 0.0
                for r in range(3):
                    for p in range(6):
                        wp = w * J[r, p]
                        g[p] += wp * e[r]
                        for q in range(p, 6):
                            H[p, q] += wp * J[r, q]
            for p in range(6):
                for q in range(p + 1, 6):
                    H[q, p] = H[p, q]
            for p in range(6):
                H[p, p] += 1e-9 + 1e-6 * H[p, p]
            if not solve_spd6(H, g, dx):
                break
            se3_exp_left(dx, T, E, Tn)
            for p in range(4):
                for q in range(4):
                    T[p, q] = Tn[p, q]
            nrm = 0.0
            for p in range(6):
                nrm += dx[p] * dx[p]
            if math.sqrt(nrm) < 1e-7:
                break
        reprojection_chi2_kernel(T, X, uv, ur_obs, inv_sigma2, fx, fy, cx, cy, bf, chi2, front)
        nin = 0
        for i in range(n):
            th = chi2_stereo if ur_obs[i] >= 0 else chi2_mono
            out[i] = (chi2[i] > th) or not front[i]
            if not out[i]:
                nin += 1
        if nin < 10:
            break
    return T, out
