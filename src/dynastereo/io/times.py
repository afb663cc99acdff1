"""``times.txt``: one timestamp (seconds) per line, strictly increasing.

A malformed line or a stamp that does not increase is a :class:`SequenceError` naming the
file and the line (an out-of-order ``times.txt`` would otherwise be written into
``trajectory.tum.txt`` out of order and break every evaluation tool).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import SequenceError


def read_times(path: str | Path) -> np.ndarray:
    """The stamps of a ``times.txt`` (float64 seconds); blank lines are skipped."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise SequenceError(f"cannot read timestamps: {e.strerror or e}", path) from None
    numbered = [(i, ln.strip()) for i, ln in enumerate(text.splitlines(), 1) if ln.strip()]
    try:
        t = np.array([float(s) for _, s in numbered], dtype=np.float64)
    except ValueError:
        lineno, s = next((i, s) for i, s in numbered if not _is_float(s))
        raise SequenceError(f"line {lineno}: {s[:40]!r} is not a timestamp (one number in seconds per line)",
                            path) from None
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise SequenceError(f"line {numbered[int(bad[0])][0]}: non-finite timestamp", path)
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        k = int(back[0]) + 1
        rel = "equals" if t[k] == t[k - 1] else "is before"
        raise SequenceError(f"line {numbered[k][0]}: timestamp {numbered[k][1]} {rel} line {numbered[k - 1][0]}'s "
                            f"{numbered[k - 1][1]} (timestamps must increase strictly)", path)
    return t


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True
