"""The observation table: one row per (keyframe id, keypoint index, point id), with an
alive flag (erased rows are kept), and per point a linked list of its rows, newest
first (``head[point]``, ``next_row[row]``), so a point's observations are found at a
cost proportional to their number, not to the map size.
"""

from __future__ import annotations

import numpy as np

from ..errors import MapFileError
from .kernels.bookkeeping import rows_of as _rows_of
from .table import Column, Table, check_entry, grow

_I8, _B = np.dtype("<i8"), np.dtype("?")
HEAD = "points/head"


class Observations(Table):
    COUNT = "observations"
    COLUMNS = {
        "kf": Column("obs/kf", _I8),
        "kp": Column("obs/kp", _I8),
        "pt": Column("obs/pt", _I8),
        "alive": Column("obs/alive", _B, fill=False),
        "next_row": Column("obs/next_row", _I8, fill=-1),
    }

    def __init__(self, capacity: int = 0, point_capacity: int = 0) -> None:
        super().__init__(capacity)
        self.n_points = 0  # points that have a list (all the map's points)
        self.head = np.full(point_capacity, -1, np.int64)

    def add_points(self, n_points: int) -> None:
        """Empty lists for the new points up to id ``n_points - 1``."""
        self.head = grow(self.head, n_points, -1)
        self.head[self.n_points:n_points] = -1
        self.n_points = n_points

    def add(self, kf_id: int, kp: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """Alive rows (kf_id, kp[i], pts[i]) at the heads of the points' lists (``pts``
        without duplicates); their row numbers."""
        r0, r1 = self.n, self.n + len(kp)
        self._reserve(r1)
        self.next_row[r0:r1] = self.head[pts]
        self.head[pts] = np.arange(r0, r1)
        self.kf[r0:r1] = kf_id
        self.kp[r0:r1] = kp
        self.pt[r0:r1] = pts
        self.alive[r0:r1] = True
        self.n = r1
        return np.arange(r0, r1)

    def erase(self, rows: np.ndarray) -> None:
        """Mark rows erased (they stay in the table and in their lists)."""
        self.alive[rows] = False

    def rows_of(self, pts: np.ndarray) -> np.ndarray:
        """Alive observation rows of the given points (sorted; duplicates and -1 in
        ``pts`` are ignored), walking the per-point lists (one compiled call,
        ``kernels.bookkeeping.rows_of``): cost proportional to those points'
        observations, not to the map size."""
        pts = np.ascontiguousarray(pts, np.int64)
        if len(pts) and int(pts.max()) >= self.n_points:
            raise IndexError(f"point id {int(pts.max())} beyond the {self.n_points} points of the observation lists")
        return _rows_of(self.head, self.next_row, self.alive, pts)

    def first_observers(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(points, keyframe ids): the first alive observer (lowest row) of each of the
        given points that has one."""
        rows = self.rows_of(pts)
        order = np.argsort(self.pt[rows], kind="stable")
        r = rows[order]
        p = self.pt[r]
        first = np.ones(len(p), bool)
        first[1:] = p[1:] != p[:-1]
        return p[first], self.kf[r[first]]

    def n_alive(self) -> int:
        return int(self.alive[: self.n].sum())

    # ------------------------------------------------------------ map files
    @classmethod
    def entries(cls) -> dict[str, tuple[np.dtype, tuple]]:
        return {HEAD: (_I8, ("points",)), **super().entries()}

    def to_arrays(self) -> dict[str, np.ndarray]:
        """``points/head`` (the first row of each point's list, -1 none) and the rows."""
        return {HEAD: self.head[: self.n_points], **super().to_arrays()}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], counts: dict[str, int] | None = None) -> "Observations":
        t = cls()
        if HEAD not in arrays:
            raise MapFileError(f"corrupt or incomplete map file: entry '{HEAD}' is missing")
        head = np.asarray(arrays[HEAD])
        counts = {"points": len(head) if head.ndim else -1, **(counts or {})}
        t.head = check_entry(HEAD, head, _I8, ("points",), counts)
        t.n_points = counts["points"]
        t._set_columns(arrays, counts)
        return t
