"""The rerun viewer as a job's observer, opened and closed around the job."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np

from ..observers import FrameObserver


@contextmanager
def viewers(observers: tuple[FrameObserver, ...] = (), *, viewer: bool = False, rrd: str | Path | None = None,
            gt: np.ndarray | None = None, name: str = "dynastereo") -> Iterator[tuple[FrameObserver, ...]]:
    """``observers`` plus, with ``viewer`` (spawn the rerun viewer) or ``rrd`` (record to a
    file), a :class:`dynastereo.viz.rerun.RerunObserver` (needs ``pip install
    dynastereo[viz]``), flushed and closed on exit.  Neither: rerun is not imported.
    ``gt``: the ground truth's positions (N, 3), drawn once."""
    if not viewer and rrd is None:
        yield tuple(observers)
        return
    from .rerun import RerunObserver

    rec = RerunObserver(spawn=viewer, rrd=rrd, gt=gt, name=name)
    try:
        yield (*observers, rec)
    finally:
        rec.close()
