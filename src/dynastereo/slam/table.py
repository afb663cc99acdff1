"""Growable column tables: the storage under :class:`~.map_points.MapPoints` and
:class:`~.observations.Observations`.

A table is a set of numpy columns sharing one row index; rows ``0..n-1`` are used and
the columns grow by doubling.  Each column has its on-disk entry name, dtype and
per-row shape (``docs/reference/map-format.md``), so a table writes itself with ``to_arrays()``
and rebuilds itself, checked, with ``from_arrays()``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..errors import MapFileError


@dataclass(frozen=True)
class Column:
    """One column: its map-file entry, dtype, per-row shape and the value of new rows."""

    entry: str
    dtype: np.dtype
    shape: tuple[int, ...] = ()
    fill: int | bool = 0


def grow(a: np.ndarray, n: int, fill=0) -> np.ndarray:
    """``a`` with room for at least ``n`` rows (doubling), new rows set to ``fill``."""
    cap = len(a)
    if n <= cap:
        return a
    new_cap = max(n, 2 * cap)
    out = np.full((new_cap,) + a.shape[1:], fill, dtype=a.dtype)
    out[:cap] = a
    return out


def check_entry(name: str, a: np.ndarray, dtype: np.dtype | str, shape: tuple, counts: dict[str, int]) -> np.ndarray:
    """``a`` if it has ``dtype`` (or, for ``"i"`` / ``"f"``, that kind) and ``shape``,
    whose names are counts (``"keyframes+1"``: one more); else :class:`MapFileError`
    naming the entry."""
    if isinstance(dtype, str):
        kind = "integer" if dtype == "i" else "floating-point"
        if a.dtype.kind not in ("iu" if dtype == "i" else dtype):
            raise MapFileError(f"entry '{name}' has dtype {a.dtype}, expected a {kind} array")
    elif a.dtype != dtype:
        raise MapFileError(f"entry '{name}' has dtype {a.dtype}, expected {dtype}")
    want = tuple((counts[s[:-2]] + 1 if s.endswith("+1") else counts[s]) if isinstance(s, str) else s for s in shape)
    if a.shape != want:
        raise MapFileError(f"entry '{name}' has shape {a.shape}, the header's counts say {want}")
    return a


class Table:
    """Rows of growable columns (``COLUMNS``: attribute -> :class:`Column`); ``n`` rows used.
    ``COUNT`` names the row count in a map file's header."""

    COLUMNS: ClassVar[dict[str, Column]]
    COUNT: ClassVar[str]

    def __init__(self, capacity: int = 0) -> None:
        self.n = 0
        for name, c in self.COLUMNS.items():
            setattr(self, name, np.full((capacity,) + c.shape, c.fill, c.dtype))

    def _reserve(self, n: int) -> None:
        for name, c in self.COLUMNS.items():
            setattr(self, name, grow(getattr(self, name), n, c.fill))

    @classmethod
    def entries(cls) -> dict[str, tuple[np.dtype, tuple]]:
        """Map-file entry -> (dtype, shape with the header's count names)."""
        return {c.entry: (c.dtype, (cls.COUNT,) + c.shape) for c in cls.COLUMNS.values()}

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The used rows of every column, by map-file entry name (views, not copies)."""
        return {c.entry: getattr(self, name)[: self.n] for name, c in self.COLUMNS.items()}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], counts: dict[str, int] | None = None) -> "Table":
        """The table whose columns are ``arrays`` (entries of :meth:`to_arrays`; the arrays
        are used as they are).  ``counts``: the row counts the arrays must have (default:
        the first column's length).  :class:`MapFileError` naming a missing entry or one
        with another dtype or shape."""
        t = cls(0)
        t._set_columns(arrays, counts)
        return t

    def _set_columns(self, arrays: dict[str, np.ndarray], counts: dict[str, int] | None) -> None:
        counts = dict(counts or {})
        for name, c in self.COLUMNS.items():
            if c.entry not in arrays:
                raise MapFileError(f"corrupt or incomplete map file: entry '{c.entry}' is missing")
            a = np.asarray(arrays[c.entry])
            counts.setdefault(self.COUNT, len(a) if a.ndim else -1)
            setattr(self, name, check_entry(c.entry, a, c.dtype, (self.COUNT,) + c.shape, counts))
        self.n = counts[self.COUNT]
