"""Pictures of a mesh (the report, README): a compiled z-buffer rasterizer.

:func:`render_top` looks straight down (orthographic, the first camera's forward axis up
the picture), :func:`render_camera` through the first camera (its intrinsics, the world
frame's origin).  Each triangle is shaded flat -- its vertices' mean colour times a light
from above and behind the viewer -- so shape reads even on a grey mesh.  BGR uint8 out.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .tsdf import Mesh

BACKGROUND = (40, 40, 40)


@nb.njit(cache=True, nogil=True)
def _raster(sx, sy, sz, faces, shade, out, zbuf):  # pragma: no cover - compiled
    h, w = zbuf.shape
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        if not (np.isfinite(sz[a]) and np.isfinite(sz[b]) and np.isfinite(sz[c])):
            continue
        x0, y0, x1, y1, x2, y2 = sx[a], sy[a], sx[b], sy[b], sx[c], sy[c]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-12:
            continue
        u0 = max(int(np.floor(min(x0, x1, x2))), 0)
        u1 = min(int(np.ceil(max(x0, x1, x2))), w - 1)
        v0 = max(int(np.floor(min(y0, y1, y2))), 0)
        v1 = min(int(np.ceil(max(y0, y1, y2))), h - 1)
        if u1 - u0 > w // 2 or v1 - v0 > h // 2:  # a sliver across the view (behind the camera)
            continue
        for v in range(v0, v1 + 1):
            for u in range(u0, u1 + 1):
                px, py = u + 0.5, v + 0.5
                l1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) / area
                l2 = ((x0 - px) * (y1 - py) - (x1 - px) * (y0 - py)) / area
                l0 = 1.0 - l1 - l2
                if l0 < -1e-6 or l1 < -1e-6 or l2 < -1e-6:
                    continue
                z = l0 * sz[a] + l1 * sz[b] + l2 * sz[c]
                if z < zbuf[v, u]:
                    zbuf[v, u] = z
                    for q in range(3):
                        out[v, u, q] = shade[f, q]


def _shade(mesh: Mesh, light: np.ndarray) -> np.ndarray:
    V, F = mesh.vertices.astype(np.float64), mesh.faces
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    lam = 0.35 + 0.65 * np.abs(n @ (light / np.linalg.norm(light)))
    col = mesh.colors[F].astype(np.float64).mean(axis=1)
    col = 0.5 * col + 0.5 * 200.0  # texture kept, shape readable
    return np.clip(col[:, ::-1] * lam[:, None], 0, 255).astype(np.uint8)  # RGB -> BGR


def _draw(sx, sy, sz, mesh: Mesh, light: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    w, h = size
    out = np.empty((h, w, 3), np.uint8)
    out[:] = BACKGROUND
    if len(mesh.faces):
        zbuf = np.full((h, w), np.inf)
        _raster(sx.astype(np.float64), sy.astype(np.float64), sz.astype(np.float64),
                np.ascontiguousarray(mesh.faces, np.int64), _shade(mesh, light), out, zbuf)
    return out


def mesh_bounds(mesh: Mesh, margin: float = 1.0) -> tuple[float, float, float, float]:
    """``(x0, x1, z0, z1)`` of the mesh from above, with ``margin`` m around."""
    V = mesh.vertices
    if not len(V):
        return (-margin, margin, -margin, margin)
    lo, hi = V.min(0), V.max(0)
    return (float(lo[0]) - margin, float(hi[0]) + margin, float(lo[2]) - margin, float(hi[2]) + margin)


def top_pixels(xz: np.ndarray, bounds: tuple[float, float, float, float], size: tuple[int, int]) -> np.ndarray:
    """World (x, z) (N, 2) -> pixel (u, v) of :func:`render_top` with the same ``bounds``
    and ``size``: the same scale on both axes, the bounds centred."""
    w, h = size
    x0, x1, z0, z1 = bounds
    s = max((x1 - x0) / w, (z1 - z0) / h)  # metres per pixel
    cx, cz = (x0 + x1) / 2, (z0 + z1) / 2
    return np.stack([(xz[:, 0] - cx) / s + w / 2, h / 2 - (xz[:, 1] - cz) / s], 1)


def render_top(mesh: Mesh, size: tuple[int, int] = (480, 640), bounds: tuple[float, float, float, float] | None = None,
               ) -> np.ndarray:
    """The mesh seen from above: x right, z (the first camera's forward) up; ``bounds``
    ``(x0, x1, z0, z1)`` m (default: :func:`mesh_bounds`)."""
    V = mesh.vertices.astype(np.float64)
    uv = top_pixels(V[:, [0, 2]], bounds or mesh_bounds(mesh), size)
    return _draw(uv[:, 0], uv[:, 1], V[:, 1], mesh, np.array([0.3, -1.0, 0.2]), size)


def render_camera(mesh: Mesh, K: np.ndarray, size: tuple[int, int], near: float = 0.5) -> np.ndarray:
    """The mesh through the first camera (intrinsics ``K``, image ``size`` (w, h))."""
    V = mesh.vertices.astype(np.float64)
    z = V[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        sx = K[0, 0] * V[:, 0] / z + K[0, 2]
        sy = K[1, 1] * V[:, 1] / z + K[1, 2]
    sz = np.where(z > near, z, np.inf)
    return _draw(sx, sy, sz, mesh, np.array([0.3, -1.0, -0.6]), size)
