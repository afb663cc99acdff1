"""Map points, array-wise: one row per point id (never reused; culled and fused points
keep their rows, flagged ``bad``).

Columns: position, distinctive descriptor, viewing normal, scale-invariance distance
range, observation count (ORB-SLAM2's: a stereo observation counts 2), visible / found
counters, first and reference keyframe, bad flag and the point a fused one was
replaced by.  Everything that touches many points works on these columns at once.
"""

from __future__ import annotations

import numpy as np

from .geometry import desc_u64
from .table import Column, Table

_F8, _I8, _I4, _U1, _B = (np.dtype(t) for t in ("<f8", "<i8", "<i4", "u1", "?"))


class MapPoints(Table):
    COUNT = "points"
    COLUMNS = {
        "pos": Column("points/pos", _F8, (3,)),
        "desc": Column("points/desc", _U1, (32,)),
        "normal": Column("points/normal", _F8, (3,)),
        "min_dist": Column("points/min_dist", _F8),
        "max_dist": Column("points/max_dist", _F8),
        "nobs": Column("points/nobs", _I4),
        "visible": Column("points/visible", _I4),
        "found": Column("points/found", _I4),
        "first_kf": Column("points/first_kf", _I8),
        "ref_kf": Column("points/ref_kf", _I8),
        "bad": Column("points/bad", _B, fill=False),
        "replaced": Column("points/replaced", _I8, fill=-1),
    }
    pos: np.ndarray
    desc: np.ndarray
    normal: np.ndarray
    min_dist: np.ndarray
    max_dist: np.ndarray
    nobs: np.ndarray
    visible: np.ndarray
    found: np.ndarray
    first_kf: np.ndarray
    ref_kf: np.ndarray
    bad: np.ndarray
    replaced: np.ndarray

    def add(self, pos: np.ndarray, desc: np.ndarray, kf_id: int) -> np.ndarray:
        """New points made by keyframe ``kf_id`` (seen and found once, no observations
        yet); their ids."""
        n0, n1 = self.n, self.n + len(pos)
        self._reserve(n1)
        self.pos[n0:n1] = pos
        self.desc[n0:n1] = desc
        self.nobs[n0:n1] = 0
        self.visible[n0:n1] = 1
        self.found[n0:n1] = 1
        self.first_kf[n0:n1] = kf_id
        self.ref_kf[n0:n1] = kf_id
        self.bad[n0:n1] = False
        self.replaced[n0:n1] = -1
        self.n = n1
        return np.arange(n0, n1, dtype=np.int64)

    @property
    def desc64(self) -> np.ndarray:
        return desc_u64(self.desc[: self.n])

    def good(self, ids: np.ndarray) -> np.ndarray:
        """Per id: a point (``>= 0``) that is not bad."""
        ids = np.asarray(ids, np.int64)
        return (ids >= 0) & ~self.bad[np.maximum(ids, 0)]

    def good_ids(self) -> np.ndarray:
        """The ids of all good points."""
        return np.flatnonzero(~self.bad[: self.n])

    def resolve(self, ids: np.ndarray) -> np.ndarray:
        """Follow ``replaced`` links (fused points); -1 for bad points."""
        ids = np.asarray(ids, np.int64).copy()
        for _ in range(8):
            ok = ids >= 0
            r = np.where(ok, self.replaced[np.maximum(ids, 0)], -1)
            mv = ok & (r >= 0)
            if not mv.any():
                break
            ids[mv] = r[mv]
        ok = ids >= 0
        ids[ok & self.bad[np.maximum(ids, 0)]] = -1
        return ids

    def mark_visible(self, ids: np.ndarray) -> None:
        """Points predicted visible in a frame (``IncreaseVisible``; once per distinct id)."""
        self.visible[ids] += 1

    def mark_found(self, ids: np.ndarray) -> None:
        """Points matched in a frame (``IncreaseFound``; once per distinct id)."""
        self.found[ids] += 1

    def found_ratio(self, ids: np.ndarray) -> np.ndarray:
        """found / visible (``GetFoundRatio``)."""
        return self.found[ids] / np.maximum(self.visible[ids], 1)

    def transform(self, ids: np.ndarray, T: np.ndarray) -> None:
        """Move points (position and viewing normal) by the rigid ``T`` (4x4, old world ->
        new world), or by ``T[i]`` each ((len(ids), 4, 4)), e.g. a loop correction."""
        if T.ndim == 2:
            self.pos[ids] = self.pos[ids] @ T[:3, :3].T + T[:3, 3]
            self.normal[ids] = self.normal[ids] @ T[:3, :3].T
        else:
            R, t = T[:, :3, :3], T[:, :3, 3]
            self.pos[ids] = np.einsum("nij,nj->ni", R, self.pos[ids]) + t
            self.normal[ids] = np.einsum("nij,nj->ni", R, self.normal[ids])
