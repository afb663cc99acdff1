"""What a job writes, frame by frame: the sinks.

A sink's :meth:`Sink.write` gets each processed frame (:class:`~dynastereo.runtime.processor.Processed`)
and adds the files it creates for it to a list.  When one sink fails on a frame (a full disk, a
signal), the frame loop takes that frame back out of every sink -- its new files deleted,
the row files truncated to the frames done -- so all outputs agree on ``frames_done``.

File sinks (the names are a contract that later tools read)::

    DIR/trajectory.{kitti,tum,frames}.txt  one row per frame, appended live (TrajectorySink)
    DIR/objects.jsonl                     one JSON line per frame: what was masked and how
    DIR/objects_tracks.csv                the objects' world tracks (runs; objects.world)
    DIR/masks/{left,right}/NNNNNN.png     uint8, 255 = masked (MaskSink)
    DIR/disparity/NNNNNN.png              uint16, disparity*256 (KITTI) (DisparitySink)
    DIR/overlays/NNNNNN.png               left|right with masks and verdicts (OverlaySink)

Observers (:class:`~dynastereo.observers.FrameObserver`: a bag writer, the rerun viewer,
the live node's publisher, the periodic stereo check) see each frame once its files are
written (:class:`ObserverSink` turns a processed frame into their
:class:`~dynastereo.observers.FrameEvent`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from ..datatypes import StereoMasks
from ..errors import OutputError
from ..io.images import write_disparity_png
from ..io.outputs import RowFile, write_bytes
from ..observers import FrameEvent, FrameObserver, notify
from .processor import Processed


def frame_name(index: int) -> str:
    return f"{index:06d}.png"


def objects_record(idx: int, masks: StereoMasks) -> dict:
    """The ``objects.jsonl`` line of a frame: what was masked and how."""
    record = {
        "frame": idx,
        "objects": [o.to_dict() for o in masks.objects],
        "fallbacks": sum(o.method.is_fallback for o in masks.objects),
    }
    if masks.ground is not None:  # the road line the outlines left out (ok=False: not removed)
        record["road"] = masks.ground.to_dict()
    return record


def write_png(path: Path, img: np.ndarray) -> None:
    """PNG-encode ``img`` and write it; a failed write (disk full, no permission, EIO)
    removes the partial file and raises an OutputError naming it."""
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise OutputError("cannot encode the image as PNG", path)
    write_bytes(path, buf.tobytes())


class Sink(Protocol):
    def write(self, p: Processed, written: list[Path]) -> None: ...  # adds each file it creates to ``written``

    def truncate(self, n_done: int) -> None: ...  # keep the first n_done frames' rows

    def close(self) -> None: ...


class _PngSink:
    """One PNG per frame in each of ``dirs`` (created at start)."""

    def __init__(self, dirs: list[Path]) -> None:
        self.dirs = dirs
        for d in dirs:
            d.mkdir(parents=True, exist_ok=True)

    def images(self, p: Processed) -> list[np.ndarray]:
        raise NotImplementedError

    def write(self, p: Processed, written: list[Path]) -> None:
        for d, img in zip(self.dirs, self.images(p)):
            written.append(d / frame_name(p.index))
            self.save(written[-1], img)

    save = staticmethod(write_png)

    def truncate(self, n_done: int) -> None:
        pass

    def close(self) -> None:
        pass


class MaskSink(_PngSink):
    """``masks/{left,right}/``: the masks SLAM got (a mask job: every object's)."""

    def __init__(self, out: Path) -> None:
        super().__init__([out / "masks" / "left", out / "masks" / "right"])

    def images(self, p: Processed) -> list[np.ndarray]:
        m = p.slam_masks
        return [] if m is None else [m.left, m.right]


class DisparitySink(_PngSink):
    def __init__(self, out: Path, masker_name: str) -> None:
        super().__init__([out / "disparity"])
        self.masker_name = masker_name

    save = staticmethod(write_disparity_png)

    def images(self, p: Processed) -> list[np.ndarray]:
        if p.masks is None or p.masks.disparity is None:
            raise RuntimeError(f"masker {self.masker_name} produced no full-frame disparity")
        return [p.masks.disparity]


class OverlaySink(_PngSink):
    def __init__(self, out: Path) -> None:
        super().__init__([out / "overlays"])

    def images(self, p: Processed) -> list[np.ndarray]:
        from ..viz.draw import draw_overlay

        return [draw_overlay(p.frame, p.masks)]


class RowSink:
    """A row file (one or more rows per frame), truncated back to the frames done."""

    def __init__(self, rows: Any) -> None:
        self.rows = rows

    def truncate(self, n_done: int) -> None:
        self.rows.truncate(n_done)

    def close(self) -> None:
        self.rows.close()


class TrajectorySink(RowSink):
    def __init__(self, out: Path) -> None:
        from ..eval.trajectory import TrajectoryWriter

        super().__init__(TrajectoryWriter(out))

    def write(self, p: Processed, written: list[Path]) -> None:
        self.rows.append(p.pose, frame_index=p.index, timestamp=p.stamp)


class ObjectsLogSink(RowSink):
    def __init__(self, out: Path) -> None:
        super().__init__(RowFile(out / "objects.jsonl"))

    def write(self, p: Processed, written: list[Path]) -> None:
        self.rows.append(json.dumps(objects_record(p.index, p.masks)) + "\n")


class TracksSink:
    """``objects_tracks.csv`` (:class:`~dynastereo.objects.world.TrackWriter`)."""

    def __init__(self, out: Path) -> None:
        from ..objects.world import TRACKS_NAME, TrackWriter

        self.tracks = TrackWriter(out / TRACKS_NAME)

    def write(self, p: Processed, written: list[Path]) -> None:
        self.tracks.write(p.index, p.stamp, p.masks)

    def truncate(self, n_done: int) -> None:
        pass

    def close(self) -> None:
        self.tracks.close()


class ObserverSink:
    """The frame as a :class:`~dynastereo.observers.FrameEvent` to each observer."""

    def __init__(self, observers: tuple[FrameObserver, ...], system: Any, calibration: Any) -> None:
        self.observers, self.system, self.calibration = observers, system, calibration

    def notify(self, p: Processed) -> None:
        if self.observers:
            notify(self.observers, FrameEvent(p.position, p.frame, p.slam_masks, p.ms, p.pose, p.status, self.system,
                                              self.calibration))


def unlink_quietly(paths: list[Path]) -> None:
    for p in paths:
        try:
            p.unlink(missing_ok=True)
        except OSError:
            pass


def write_frame(sinks: list[Sink], p: Processed, n_done: int) -> None:
    """Every sink's output of frame ``p``; on a failure (or a signal) none of this frame's
    outputs stay: the row files back to ``n_done`` frames, its new files deleted."""
    written: list[Path] = []
    try:
        for s in sinks:
            s.write(p, written)
    except BaseException:
        for s in sinks:
            s.truncate(n_done)
        unlink_quietly(written)
        raise
