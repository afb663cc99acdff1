"""A sparse TSDF volume (compiled) and its marching-cubes surface.

The volume is a set of 8x8x8-voxel blocks, allocated where a depth map's surface lies (its
points +- the truncation): memory follows the surface seen, not the space the camera
crossed.  Block keys are kept sorted (``numpy.searchsorted``), so the compiled kernels
need no hash table: :meth:`TSDFVolume.integrate` passes them the blocks in the camera's
view, :meth:`TSDFVolume.mesh` each block's seven upper neighbours.

Integration is projective (KinectFusion, Curless & Levoy): every voxel of a block in view
is projected into the depth map; ``sdf = depth - z``; voxels further than the truncation
behind the surface are left alone, the others get the running average of
``min(1, sdf / truncation)`` -- free space in front of a surface (+1) too, so a surface
seen once and seen through later fades (what a mask missed is carved out again).

Voxel ``(i, j, k)`` samples the world point ``(i, j, k) * voxel_size``; the surface is the
zero level of the averaged values, taken only between voxels observed ``min_weight``
times (:mod:`.tables` gives the triangles).  Vertices on the same voxel edge are shared.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from ..errors import DynastereoError
from .tables import CORNERS, EDGES, TRIS

BLOCK = 8  # voxels per block side
B3 = BLOCK ** 3
BLOCK_BYTES = 3 * 8 + B3 * (4 + 4 + 3)  # a block's coordinates, distances, weights and colours
_OFF_B = 1 << 20  # block coordinates packed 21 bits each
_OFF_V = 1 << 19  # voxel coordinates packed 20 bits each (edge keys)
MAX_WEIGHT = 255.0
MIN_INCIDENCE = 0.15  # a ray's distance shrinks to the plane's by at most this factor (~81 degrees)


def block_keys(coords: np.ndarray) -> np.ndarray:
    c = coords.astype(np.int64) + _OFF_B
    return (c[..., 0] << 42) | (c[..., 1] << 21) | c[..., 2]


def key_coords(keys: np.ndarray) -> np.ndarray:
    m = (1 << 21) - 1
    return np.stack([(keys >> 42) & m, (keys >> 21) & m, keys & m], -1).astype(np.int64) - _OFF_B


@nb.njit(cache=True, nogil=True)
def _touched_blocks(depth, incidence, stride, fx, fy, cx, cy, R, t, trunc, block_m, out):  # pragma: no cover
    """Keys of the blocks along each valid pixel's ray within the truncation of its surface
    (``trunc / incidence`` along the ray); returns how many were written into ``out``."""
    h, w = depth.shape
    n = 0
    for v in range(0, h, stride):
        for u in range(0, w, stride):
            d = depth[v, u]
            if d <= 0.0:
                continue
            rx = (u - cx) / fx
            ry = (v - cy) / fy
            band = trunc / incidence[v, u]
            ns = int(np.ceil(2.0 * band / (0.9 * block_m))) + 1
            for s in range(ns):
                z = d - band + 2.0 * band * s / (ns - 1)
                if z <= 0.0:
                    continue
                px, py = rx * z, ry * z
                wx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * z + t[0]
                wy = R[1, 0] * px + R[1, 1] * py + R[1, 2] * z + t[1]
                wz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * z + t[2]
                bx = np.int64(np.floor(wx / block_m)) + _OFF_B
                by = np.int64(np.floor(wy / block_m)) + _OFF_B
                bz = np.int64(np.floor(wz / block_m)) + _OFF_B
                out[n] = (bx << 42) | (by << 21) | bz
                n += 1
    return n


@nb.njit(cache=True, nogil=True)
def _integrate(blocks, coords, tsdf, weight, color, depth, incidence, image, fx, fy, cx, cy, Rcw, tcw, voxel,
               trunc):  # pragma: no cover - compiled
    h, w = depth.shape
    ch = image.shape[2]
    for bi in blocks:
        ox = coords[bi, 0] * BLOCK
        oy = coords[bi, 1] * BLOCK
        oz = coords[bi, 2] * BLOCK
        for k in range(B3):
            px = (ox + (k & 7)) * voxel
            py = (oy + ((k >> 3) & 7)) * voxel
            pz = (oz + (k >> 6)) * voxel
            z = Rcw[2, 0] * px + Rcw[2, 1] * py + Rcw[2, 2] * pz + tcw[2]
            if z <= 0.0:
                continue
            x = Rcw[0, 0] * px + Rcw[0, 1] * py + Rcw[0, 2] * pz + tcw[0]
            y = Rcw[1, 0] * px + Rcw[1, 1] * py + Rcw[1, 2] * pz + tcw[1]
            u = int(np.floor(fx * x / z + cx + 0.5))
            v = int(np.floor(fy * y / z + cy + 0.5))
            if u < 0 or v < 0 or u >= w or v >= h:
                continue
            d = depth[v, u]
            if d <= 0.0:
                continue
            sdf = (d - z) * incidence[v, u]  # along the ray -> to the surface's plane
            if sdf < -trunc:
                continue
            val = min(1.0, sdf / trunc)
            w0 = weight[bi, k]
            w1 = w0 + 1.0
            tsdf[bi, k] = (tsdf[bi, k] * w0 + val) / w1
            for c in range(3):  # the colour of the surface the voxel's ray meets
                g = image[v, u, c if ch == 3 else 0]
                color[bi, k, c] = np.uint8(min(255.0, (color[bi, k, c] * w0 + g) / w1 + 0.5))
            weight[bi, k] = min(w1, MAX_WEIGHT)


@nb.njit(cache=True, nogil=True)
def _cube(b, i, j, l, nbr, tsdf, weight, min_weight, vals, cols, color):  # pragma: no cover - compiled
    """The cube at voxel (i, j, l) of block b: its 8 values into ``vals`` (and colours);
    its case (-1: a corner missing or seen too rarely)."""
    case = 0
    for c in range(8):
        ci = i + (c & 1)
        cj = j + ((c >> 1) & 1)
        cl = l + ((c >> 2) & 1)
        blk = nbr[b, (ci >> 3) | ((cj >> 3) << 1) | ((cl >> 3) << 2)]
        if blk < 0:
            return -1
        kk = (ci & 7) | ((cj & 7) << 3) | ((cl & 7) << 6)
        if weight[blk, kk] < min_weight:
            return -1
        vals[c] = tsdf[blk, kk]
        for q in range(3):
            cols[c, q] = color[blk, kk, q]
        if vals[c] < 0.0:
            case |= 1 << c
    return case


@nb.njit(cache=True, nogil=True)
def _march(coords, nbr, tsdf, weight, color, min_weight, voxel, tris, edges, corners, fill, keys, pos,
           rgb):  # pragma: no cover - compiled
    """Marching cubes over every block; ``fill`` False: only count the triangles."""
    vals = np.zeros(8, np.float64)
    cols = np.zeros((8, 3), np.float64)
    n = 0
    for b in range(coords.shape[0]):
        for k in range(B3):
            i, j, l = k & 7, (k >> 3) & 7, k >> 6
            case = _cube(b, i, j, l, nbr, tsdf, weight, min_weight, vals, cols, color)
            if case <= 0 or case == 255:
                continue
            for q in range(0, 15, 3):
                if tris[case, q] < 0:
                    break
                if fill:
                    for r in range(3):
                        e = tris[case, q + r]
                        a, bb = edges[e, 0], edges[e, 1]
                        s = vals[a] / (vals[a] - vals[bb])
                        gx = coords[b, 0] * BLOCK + i + corners[a, 0]
                        gy = coords[b, 1] * BLOCK + j + corners[a, 1]
                        gz = coords[b, 2] * BLOCK + l + corners[a, 2]
                        axis = e // 4
                        m = 3 * n + r
                        keys[m] = ((((gx + _OFF_V) << 40) | ((gy + _OFF_V) << 20) | (gz + _OFF_V)) << 2) | axis
                        pos[m, 0] = (gx + (s if axis == 0 else 0.0)) * voxel
                        pos[m, 1] = (gy + (s if axis == 1 else 0.0)) * voxel
                        pos[m, 2] = (gz + (s if axis == 2 else 0.0)) * voxel
                        for c in range(3):
                            rgb[m, c] = cols[a, c] + s * (cols[bb, c] - cols[a, c])
                n += 1
    return n


@dataclass
class Mesh:
    """A triangle mesh: ``vertices`` (V, 3) float32 m, ``faces`` (F, 3) int32, ``colors``
    (V, 3) uint8 RGB (grey: three equal channels)."""

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray

    @classmethod
    def empty(cls) -> "Mesh":
        return cls(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.uint8))

    def __len__(self) -> int:
        return len(self.vertices)


def incidence(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float, step: int = 4) -> np.ndarray:
    """Per pixel, |cos| of the angle between its ray and its surface's normal (from the
    depth map's neighbours ``step`` px away; 1 where they are missing), at least
    :data:`MIN_INCIDENCE`: a distance along the ray times it is the distance to the
    surface's plane -- so a road seen at a grazing angle keeps a band of voxels behind it
    as thick as a wall's (a projective distance alone leaves it a sliver, and no surface)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    z = depth
    P = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1)
    out = np.ones((h, w), np.float32)
    s = step
    a, b = P[s:-s, 2 * s:] - P[s:-s, :-2 * s], P[2 * s:, s:-s] - P[:-2 * s, s:-s]
    ok = (z[s:-s, 2 * s:] > 0) & (z[s:-s, :-2 * s] > 0) & (z[2 * s:, s:-s] > 0) & (z[:-2 * s, s:-s] > 0)
    n = np.cross(a, b)
    ray = P[s:-s, s:-s]
    c = np.abs((n * ray).sum(-1)) / np.maximum(np.linalg.norm(n, axis=-1) * np.linalg.norm(ray, axis=-1), 1e-12)
    out[s:-s, s:-s] = np.where(ok, np.maximum(c, MIN_INCIDENCE), 1.0)
    return out


#: the voxel grid's memory budget: a volume that would need more stops with one line
#: (the run's other outputs are written before the mesh is built)
MAX_GRID_BYTES = 4 << 30


class TSDFVolume:
    """The sparse volume (module doc); ``voxel_size`` and ``truncation`` in metres."""

    def __init__(self, voxel_size: float, truncation: float, min_weight: float = 1.0,
                 max_bytes: int = MAX_GRID_BYTES) -> None:
        self.voxel, self.trunc, self.min_weight = float(voxel_size), float(truncation), float(min_weight)
        self.max_bytes = int(max_bytes)
        self.block_m = self.voxel * BLOCK
        self.n = 0
        self._grow(1024)
        self.sorted_keys = np.zeros(0, np.int64)
        self.sorted_idx = np.zeros(0, np.int64)
        self.peak_bytes = 0

    def _grow(self, cap: int) -> None:
        if cap * BLOCK_BYTES > self.max_bytes:  # grow to the budget, never past it
            cap = max(self.n, self.max_bytes // BLOCK_BYTES)
        old = self.n
        coords = np.zeros((cap, 3), np.int64)
        tsdf = np.ones((cap, B3), np.float32)
        weight = np.zeros((cap, B3), np.float32)
        color = np.zeros((cap, B3, 3), np.uint8)
        if old:
            coords[:old], tsdf[:old], weight[:old], color[:old] = (self.coords[:old], self.tsdf[:old],
                                                                   self.weight[:old], self.color[:old])
        self.coords, self.tsdf, self.weight, self.color = coords, tsdf, weight, color

    @property
    def nbytes(self) -> int:
        """The voxel grid's memory (allocated capacity)."""
        return int(self.coords.nbytes + self.tsdf.nbytes + self.weight.nbytes + self.color.nbytes)

    @property
    def n_blocks(self) -> int:
        return self.n

    def _allocate(self, keys: np.ndarray) -> None:
        keys = np.unique(keys)
        if len(self.sorted_keys):
            at = np.searchsorted(self.sorted_keys, keys).clip(max=len(self.sorted_keys) - 1)
            keys = keys[self.sorted_keys[at] != keys]
        if not len(keys):
            return
        need = self.n + len(keys)
        if need * BLOCK_BYTES > self.max_bytes:
            raise DynastereoError(
                f"the mesh's voxel grid would need more than {self.max_bytes / 2**30:.1f} GiB "
                f"(mesh.voxel_size {self.voxel:g} m, mesh.truncation {self.trunc:g} m, "
                f"mesh.max_depth): raise mesh.voxel_size or lower mesh.max_depth")
        if need > len(self.coords):
            self._grow(max(need, int(len(self.coords) * 1.5)))
        idx = np.arange(self.n, need)
        self.coords[self.n:need] = key_coords(keys)
        self.n = need
        allk = np.concatenate([self.sorted_keys, keys])
        alli = np.concatenate([self.sorted_idx, idx])
        order = np.argsort(allk, kind="stable")
        self.sorted_keys, self.sorted_idx = allk[order], alli[order]
        self.peak_bytes = max(self.peak_bytes, self.nbytes)

    def integrate(self, depth: np.ndarray, image: np.ndarray, K: np.ndarray, pose: np.ndarray,
                  stride: int = 2) -> None:
        """Fuse one depth map (float32 m, ``<= 0`` invalid) seen at ``pose`` (3x4
        camera-to-world); ``image`` (H, W) grey or (H, W, 3) BGR gives the colour."""
        depth = np.ascontiguousarray(depth, np.float32)
        img = image[:, :, ::-1] if image.ndim == 3 else image[:, :, None]  # BGR -> RGB
        img = np.ascontiguousarray(img)
        fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        R = np.ascontiguousarray(pose[:3, :3], np.float64)
        t = np.ascontiguousarray(pose[:3, 3], np.float64)
        h, w = depth.shape
        inc = incidence(depth, fx, fy, cx, cy)
        band = self.trunc / MIN_INCIDENCE
        per_px = int(np.ceil(2.0 * band / (0.9 * self.block_m))) + 1
        out = np.empty(per_px * ((h + stride - 1) // stride) * ((w + stride - 1) // stride), np.int64)
        n = _touched_blocks(depth, inc, stride, fx, fy, cx, cy, R, t, self.trunc, self.block_m, out)
        self._allocate(out[:n])
        if not self.n:
            return
        Rcw = np.ascontiguousarray(R.T)
        tcw = -Rcw @ t
        valid = depth[depth > 0]
        if not len(valid):
            return
        blocks = self._in_view(Rcw, tcw, fx, fy, cx, cy, w, h, float(valid.max()) + self.trunc)
        _integrate(blocks, self.coords, self.tsdf, self.weight, self.color, depth, inc, img, fx, fy, cx, cy, Rcw,
                   tcw, self.voxel, self.trunc)

    def _in_view(self, Rcw, tcw, fx, fy, cx, cy, w, h, z_max) -> np.ndarray:
        """The blocks whose box may meet the view (centre test with a block's half-diagonal)."""
        c = (self.coords[:self.n] * BLOCK + (BLOCK - 1) / 2.0) * self.voxel
        p = c @ Rcw.T + tcw
        r = self.block_m * 0.8661  # half the block's diagonal
        z = p[:, 2]
        zs = np.maximum(z, 1e-6)
        mu, mv = fx * r / zs, fy * r / zs
        u, v = fx * p[:, 0] / zs + cx, fy * p[:, 1] / zs + cy
        ok = (z > -r) & (z < z_max + r)
        ok &= (z <= r) | ((u > -mu) & (u < w + mu) & (v > -mv) & (v < h + mv))
        return np.flatnonzero(ok).astype(np.int64)

    def _neighbours(self) -> np.ndarray:
        """(n, 8) each block's block at offset (c & 1, c >> 1 & 1, c >> 2 & 1), -1 if none."""
        coords = self.coords[:self.n]
        off = CORNERS[None, :, :]
        keys = block_keys(coords[:, None, :] + off)
        at = np.searchsorted(self.sorted_keys, keys).clip(max=max(len(self.sorted_keys) - 1, 0))
        found = self.sorted_keys[at] == keys
        return np.where(found, self.sorted_idx[at], -1).astype(np.int64)

    def mesh(self) -> Mesh:
        """The zero level as a triangle mesh (module doc)."""
        if not self.n:
            return Mesh.empty()
        nbr = self._neighbours()
        args = (self.coords[:self.n], nbr, self.tsdf, self.weight, self.color, self.min_weight, self.voxel,
                TRIS, EDGES, CORNERS)
        z = (np.zeros(0, np.int64), np.zeros((0, 3), np.float64), np.zeros((0, 3), np.float64))
        n = _march(*args, False, *z)
        keys, pos, rgb = np.empty(3 * n, np.int64), np.empty((3 * n, 3), np.float64), np.empty((3 * n, 3), np.float64)
        _march(*args, True, keys, pos, rgb)
        uniq, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
        return Mesh(pos[first].astype(np.float32), inverse.reshape(-1, 3).astype(np.int32),
                    np.clip(rgb[first] + 0.5, 0, 255).astype(np.uint8))
