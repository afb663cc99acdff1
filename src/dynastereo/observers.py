"""Per-frame hook of the jobs: what leaves the pipeline after each frame.

The frame loop (``runtime/loop.py``, every job) calls ``observer.on_frame(event)``
for every observer they are given, once per frame, after the frame's results are
written.  Viewers and recorders (``dynastereo.viz.rerun``) are observers; the
pipeline itself knows nothing about them, and with no observer nothing is imported.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Protocol, runtime_checkable

import numpy as np

from .datatypes import StereoFrame, StereoMasks


@dataclass
class FrameEvent:
    """One frame done by a job."""

    position: int  # in the order fed (0, 1, ...)
    frame: StereoFrame
    masks: StereoMasks | None  # None: unmasked run
    ms: dict[str, float] = field(default_factory=dict)  # stage -> milliseconds of this frame
    pose: np.ndarray | None = None  # 3x4 camera-to-world (SLAM jobs), else None
    status: str = ""  # SLAM: "init" / "tracked" / "lost"
    system: Any = None  # the SLAM System (``System.frame_view()`` gives features and local map)
    calibration: Any = None  # the sequence's rectified Calibration


@runtime_checkable
class FrameObserver(Protocol):
    def on_frame(self, event: FrameEvent) -> None: ...


@runtime_checkable
class OutputObserver(FrameObserver, Protocol):
    """An observer that writes files of its own into a run's output folder (a bag run's
    output bag, :class:`dynastereo.ros.bagrun.BagOutput`).  The runtime calls ``open``
    once the folder is ready and the run's own files are open, ``on_frame`` per frame, and
    ``close`` after the run's last files (the SLAM's final bundle adjustment done): what
    ``close`` returns is the run's result's ``outputs[name]``."""

    name: str

    def open(self, out_dir: Path, n_frames: int) -> None: ...

    def close(self) -> dict: ...


def notify(observers: Iterable[FrameObserver], event: FrameEvent) -> None:
    for ob in observers:
        ob.on_frame(event)
