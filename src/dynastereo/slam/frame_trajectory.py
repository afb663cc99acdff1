"""The per-frame trajectory of a SLAM run: one row per frame fed, in order.

Poses of tracked frames are kept relative to their reference keyframe (as ORB-SLAM2
does), so later local BA, loop correction and full BA refine them too; lost frames and
frames of a dropped map are absolute.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import inv_T, orthonormalize
from .map import Map


@dataclass
class _Row:
    ref_kf: int | None
    T: np.ndarray  # T_c_ref if ref_kf is not None, else absolute T_cw


class FrameTrajectory:
    """Rows ``T_c_ref`` (with the reference keyframe's id) or absolute ``T_cw``."""

    def __init__(self) -> None:
        self._rows: list[_Row] = []

    def __len__(self) -> int:
        return len(self._rows)

    def add(self, T: np.ndarray, ref_kf: int | None = None) -> None:
        """A frame's row: ``T`` relative to keyframe ``ref_kf``, or absolute without one."""
        self._rows.append(_Row(ref_kf, T))

    def _absolute(self, row: _Row, mp: Map) -> np.ndarray | None:
        """``T_cw`` of a relative row in ``mp`` (None when its keyframe is gone)."""
        T_ref = mp.keyframe_pose(row.ref_kf)
        return None if T_ref is None else orthonormalize(row.T @ T_ref)

    def last_pose(self, mp: Map) -> np.ndarray | None:
        """The last row's ``T_cw`` from its reference keyframe now (None: absolute or gone)."""
        if not self._rows or self._rows[-1].ref_kf is None:
            return None
        return self._absolute(self._rows[-1], mp)

    def bake(self, mp: Map) -> None:
        """Make every row absolute (before ``mp``, their keyframes' map, is dropped)."""
        for r in self._rows:
            if r.ref_kf is not None:
                T_ref = mp.keyframe_pose(r.ref_kf)
                r.T = r.T @ T_ref if T_ref is not None else r.T
                r.ref_kf = None

    def poses(self, mp: Map) -> np.ndarray:
        """(N, 3, 4) camera-to-world poses of the left camera, one per frame fed."""
        out = np.zeros((len(self._rows), 3, 4))
        for i, r in enumerate(self._rows):
            T_cw = r.T
            if r.ref_kf is not None:
                T = self._absolute(r, mp)
                T_cw = T if T is not None else T_cw
            out[i] = inv_T(T_cw)[:3]
        return out
