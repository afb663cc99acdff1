"""Small vectorized geometry helpers: SE(3), projection, Hamming distances, index ranges, PnP-RANSAC.

Poses are 4x4 float64 matrices.  ``T_cw`` maps world points into the camera
(ORB-SLAM2's convention inside the SLAM); the trajectory the System returns is
``T_wc`` (camera-to-world).
"""

from __future__ import annotations

import cv2
import numpy as np

# chi-square 95% thresholds (2 and 3 degrees of freedom), as in ORB-SLAM2
CHI2_MONO = 5.991
CHI2_STEREO = 7.815


def skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    W = skew(w)
    if th < 1e-10:
        return np.eye(3) + W
    return np.eye(3) + np.sin(th) / th * W + (1.0 - np.cos(th)) / th**2 * (W @ W)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Exp of a twist ``xi = (omega, rho)`` as a 4x4 matrix."""
    w, rho = xi[:3], xi[3:]
    th = float(np.linalg.norm(w))
    W = skew(w)
    if th < 1e-10:
        R = np.eye(3) + W
        V = np.eye(3) + 0.5 * W
    else:
        W2 = W @ W
        R = np.eye(3) + np.sin(th) / th * W + (1.0 - np.cos(th)) / th**2 * W2
        V = np.eye(3) + (1.0 - np.cos(th)) / th**2 * W + (th - np.sin(th)) / th**3 * W2
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = V @ rho
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def transform(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points."""
    return X @ T[:3, :3].T + T[:3, 3]


def camera_center(T_cw: np.ndarray) -> np.ndarray:
    return -T_cw[:3, :3].T @ T_cw[:3, 3]


def orthonormalize(T: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = -R
    out = T.copy()
    out[:3, :3] = R
    return out


def desc_u64(desc: np.ndarray) -> np.ndarray:
    """(N, 32) uint8 ORB descriptors as (N, 4) uint64 for fast Hamming distances."""
    d = np.ascontiguousarray(desc, dtype=np.uint8)
    return d.reshape(len(d), 32).view(np.uint64)  # (N, 4); also for N = 0


def hamming_pairs(a64: np.ndarray, ia: np.ndarray, b64: np.ndarray, ib: np.ndarray) -> np.ndarray:
    """Hamming distances between rows ``a64[ia]`` and ``b64[ib]`` (pairwise, same length)."""
    if len(ia) == 0:
        return np.zeros(0, np.int32)
    x = np.bitwise_xor(a64[ia], b64[ib])
    return np.bitwise_count(x).sum(axis=1, dtype=np.int32)


def expand_ranges(starts: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For ranges ``[starts[g], starts[g] + counts[g])`` return (group, index) of every element."""
    counts = np.asarray(counts, dtype=np.int64)
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    group = np.repeat(np.arange(len(counts)), counts)
    offs = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    return group, np.repeat(np.asarray(starts, np.int64), counts) + offs


def best_two_per_group(group: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best element per group and the runner-up distance.

    Returns ``(pos, groups, second)``: ``pos`` indexes the input arrays (the best
    candidate of each group present), ``groups`` the group ids, ``second`` the second
    smallest distance in the group (large if none).
    """
    if len(group) == 0:
        z = np.zeros(0, np.int64)
        return z, z, np.zeros(0, np.int64)
    order = np.lexsort((dist, group))
    g = group[order]
    d = dist[order]
    first = np.ones(len(g), bool)
    first[1:] = g[1:] != g[:-1]
    fi = np.flatnonzero(first)
    nxt = np.minimum(fi + 1, len(g) - 1)
    has2 = (fi + 1 < len(g)) & (g[nxt] == g[fi])
    second = np.where(has2, d[nxt], 1 << 30)
    return order[fi], g[fi], second


def unique_best(key: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Indices keeping, for each distinct ``key``, the element of smallest ``dist``."""
    if len(key) == 0:
        return np.zeros(0, np.int64)
    order = np.lexsort((dist, key))
    k = key[order]
    first = np.ones(len(k), bool)
    first[1:] = k[1:] != k[:-1]
    return order[first]


def rotation_consistent(angle_diff_deg: np.ndarray, bins: int = 30) -> np.ndarray:
    """ORB-SLAM2's rotation-histogram check: keep matches in the (up to) three most
    populated bins of keypoint-angle differences (bins with < 10% of the top one dropped)."""
    n = len(angle_diff_deg)
    if n == 0:
        return np.zeros(0, bool)
    rot = np.mod(angle_diff_deg, 360.0)
    b = np.minimum((rot * (bins / 360.0)).astype(np.int64), bins - 1)
    hist = np.bincount(b, minlength=bins)
    order = np.argsort(-hist, kind="stable")
    top = hist[order[0]]
    keep_bins = np.zeros(bins, bool)
    keep_bins[order[0]] = True
    for k in (1, 2):
        if hist[order[k]] > 0.1 * top:
            keep_bins[order[k]] = True
    return keep_bins[b]


def triangulate_dlt(P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Linear triangulation of (N, 2) normalized-pixel pairs with 3x4 projection matrices
    (world -> normalized image); returns (N, 3) world points (nan where degenerate)."""
    A = np.empty((len(x1), 4, 4))
    A[:, 0] = x1[:, 0, None] * P1[2] - P1[0]
    A[:, 1] = x1[:, 1, None] * P1[2] - P1[1]
    A[:, 2] = x2[:, 0, None] * P2[2] - P2[0]
    A[:, 3] = x2[:, 1, None] * P2[2] - P2[1]
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:4]
    X[~np.isfinite(X).all(axis=1)] = np.nan
    return X


def pnp_ransac(
    X: np.ndarray, uv: np.ndarray, K: np.ndarray, seed: int, iterations: int = 200, min_inliers: int = 10
) -> tuple[np.ndarray | None, int]:
    """Prior-free PnP-RANSAC (EPnP, 3 px, fixed seed): ``(T_cw or None, inliers)``; None
    with fewer than ``min_inliers`` inliers."""
    cv2.setRNGSeed(seed)
    okp, rvec, tvec, inl = cv2.solvePnPRansac(
        X.astype(np.float64),
        uv.astype(np.float64),
        K,
        None,
        iterationsCount=iterations,
        reprojectionError=3.0,
        confidence=0.999,
        flags=cv2.SOLVEPNP_EPNP,
    )
    if not okp or inl is None or len(inl) < min_inliers:
        return None, 0 if inl is None else len(inl)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T, len(inl)
