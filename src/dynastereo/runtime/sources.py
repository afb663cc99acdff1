"""Where a job's stereo frames come from: :class:`SequenceSource` over any
:class:`~dynastereo.io.base.Sequence` (KITTI odometry and raw, EuRoC, generic folders,
stereo video files, cameras, ROS bags) and :class:`LiveSource` (the live node's input: a
bounded queue that drops the oldest pair when full).

:func:`open_sequence_source` opens what a :class:`~dynastereo.runtime.spec.SourceSpec`
names.  Both kinds of source give the frame loop :class:`~dynastereo.runtime.processor.FrameItem`\\ s
(``take``), read them (``read``, on the masking thread) and give each frame's stamp.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..datatypes import StereoCalibration, StereoFrame
from ..io.base import Sequence
from ..io.queues import DropOldestQueue
from ..timing import StageTimer
from .processor import FrameItem
from .spec import SourceSpec


def open_sequence_source(spec: SourceSpec) -> Sequence:
    """The sequence ``spec`` names: a folder, video or camera (:func:`dynastereo.io.open_sequence`),
    a source that opens itself (``spec.opener``: a ROS bag), or the Sequence object given."""
    if spec.sequence is not None:
        return spec.sequence
    if spec.opener is not None:
        return spec.opener.open(spec.calib)
    from ..io import open_sequence

    return open_sequence(Path(spec.path), calib=Path(spec.calib) if spec.calib else None, color=spec.color,
                         rate=spec.rate)


class SequenceSource:
    """``frames`` of ``sequence``, in that order (revisits allowed)."""

    def __init__(self, sequence: Sequence, frames: list[int]) -> None:
        self.sequence, self.frames = sequence, frames
        self.calibration = getattr(sequence, "calibration", None)
        # a live sequence (a camera) has no stamps before its frames: each frame carries its own
        self._stamps = None if getattr(sequence, "live", False) else np.asarray(sequence.timestamps(), np.float64)
        self._next = 0
        self._lock = threading.Lock()

    def take(self) -> FrameItem | None:
        with self._lock:
            k = self._next
            if k >= len(self.frames):
                return None
            self._next += 1
            return FrameItem(k, int(self.frames[k]))

    def read(self, item: FrameItem, timer: StageTimer) -> StereoFrame:
        with timer.stage("read"):
            return self.sequence.frame(item.index)

    def stamp(self, item: FrameItem, frame: StereoFrame) -> float:
        return frame.timestamp if self._stamps is None else float(self._stamps[item.index])

    def done(self, item: FrameItem) -> None:
        pass

    def stamps_of(self, stamps: list[float]) -> np.ndarray:
        """The stamps of the whole sequence by frame number (a live one: those of the frames done)."""
        return np.asarray(stamps, np.float64) if self._stamps is None else self._stamps


# --------------------------------------------------------------------------- live input


@dataclass
class StereoInput:
    """One stereo pair as the transport delivered it (raw or rectified, per calibration)."""

    left: np.ndarray  # uint8 gray (H, W) or BGR (H, W, 3)
    right: np.ndarray
    stamp_ns: int  # the left image's header stamp
    frame_id: str = ""
    received: float = field(default_factory=time.time)  # wall clock (s) when the pair was complete


class LiveSource:
    """Pairs pushed by a transport (:meth:`submit`, never blocks), read by the frame loop in
    arrival order; a full queue drops its oldest pair (counted).  ``prepare(inp, timer)``
    turns a pair into a rectified :class:`StereoFrame` (the node's rectifier and checks);
    ``in_flight`` counts the pairs submitted and not yet processed, failed or dropped."""

    def __init__(self, prepare: Callable[[StereoInput, StageTimer], StereoFrame], queue_size: int = 1) -> None:
        self.prepare = prepare
        self.queue = DropOldestQueue(queue_size)
        self.calibration: StereoCalibration | None = None
        self._position = 0
        self._idle = threading.Condition()
        self.in_flight = 0

    def submit(self, inp: StereoInput) -> int:
        """Queue a pair; returns how many older waiting pairs were dropped for it."""
        with self._idle:
            self.in_flight += 1
        n = self.queue.put(inp)
        if n:
            self._settle(n)
        return n

    def take(self) -> FrameItem | None:
        inp = self.queue.get()
        if inp is None:
            return None
        self._position += 1
        return FrameItem(self._position - 1, None, inp)

    def read(self, item: FrameItem, timer: StageTimer) -> StereoFrame:
        return self.prepare(item.payload, timer)

    def stamp(self, item: FrameItem, frame: StereoFrame) -> float:
        return item.payload.stamp_ns * 1e-9

    def done(self, item: FrameItem) -> None:
        self._settle(1)

    def _settle(self, n: int) -> None:
        with self._idle:
            self.in_flight -= n
            self._idle.notify_all()

    def resize(self, queue_size: int) -> int:
        """A new queue size; returns the waiting pairs dropped for it."""
        n = self.queue.resize(queue_size)
        if n:
            self._settle(n)
        return n

    def close(self) -> int:
        """No more pairs: the loop ends after the pair in hand; returns the pairs discarded."""
        n = self.queue.close()
        if n:
            self._settle(n)
        return n

    def wait_idle(self, timeout: float) -> bool:
        """Wait until every submitted pair is processed, failed or dropped; False on timeout."""
        with self._idle:
            return self._idle.wait_for(lambda: self.in_flight <= 0, timeout)
