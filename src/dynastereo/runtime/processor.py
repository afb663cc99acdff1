"""One frame through the stages: read -> mask -> motion -> track (:class:`FrameProcessor`).

Every job runs its frames through this one object: ``dynastereo mask`` (no SLAM), ``run``
on a folder, a video, a camera or a bag, the benchmarks and the live node.  Its two halves
run on two threads when the job is pipelined (:mod:`dynastereo.runtime.pipelining`):

* :meth:`FrameProcessor.mask` -- read the frame from the source, mask both images, and
  measure the objects' flow for the motion test (``motion_flow``); its own timer.  When
  what SLAM will be given is known here (no masker, or every detection masked), the SLAM's
  features and stereo matches of the frame too (``System.features``: they read no map);
* :meth:`FrameProcessor.track` -- give SLAM the masks of the objects judged moving or not
  yet judged (``motion.select``: the verdicts up to the previous frame), track, update the
  verdicts with this frame's camera motion (``motion``) and place the objects in the world
  (``objects``).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from ..datatypes import StereoCalibration, StereoFrame, StereoMasks
from ..masking.maskers import MASK_STAGES
from ..timing import StageTimer

#: The masking stage's derived total in its own timer (not copied into the job's timer).
MASK_TOTAL = "mask"


@dataclass
class FrameItem:
    """A frame the source will deliver: its place in the job and what the source needs to read it."""

    position: int  # 0, 1, ... in the order the source gives them
    index: int | None  # the sequence's frame number (None: a live input, numbered when tracked)
    payload: Any = None  # source-specific (the live node's StereoInput)


class FrameSource(Protocol):
    """What the frame loop reads from (:mod:`dynastereo.runtime.sources`)."""

    calibration: StereoCalibration | None

    def take(self) -> FrameItem | None: ...  # the next frame to read; None: no more

    def read(self, item: FrameItem, timer: StageTimer) -> StereoFrame: ...

    def stamp(self, item: FrameItem, frame: StereoFrame) -> float: ...  # seconds

    def done(self, item: FrameItem) -> None: ...  # processed, failed or given up: the source's accounting


@dataclass
class Masked:
    """A frame after the masking stage."""

    item: FrameItem
    frame: StereoFrame
    masks: StereoMasks | None  # every object, with its verdict so far (None: unmasked job)
    ms: dict[str, float] = field(default_factory=dict)  # the masking stages of this frame
    features: Any = None  # the SLAM's features of the frame, when computed ahead (FrameFeatures)


@dataclass
class Processed:
    """A frame after both stages: what the sinks and observers get."""

    position: int
    index: int
    stamp: float
    frame: StereoFrame
    masks: StereoMasks | None  # every object (objects.jsonl)
    slam_masks: StereoMasks | None  # what SLAM was given (the masks written, the viewers' masks)
    pose: np.ndarray | None  # 3x4 camera-to-world; None without SLAM
    status: str  # "init" | "tracked" | "lost"; "" without SLAM
    ms: dict[str, float] = field(default_factory=dict)  # every stage of this frame
    payload: Any = None  # the source's own data of the frame (the live node's StereoInput)


class FrameProcessor:
    """The stages of one job (module doc).  ``masker`` None: unmasked; ``system`` None: no
    SLAM (``dynastereo mask``); ``motion`` (:class:`~dynastereo.objects.motion.ObjectMotion`)
    None: every detection masked; ``world`` (:class:`~dynastereo.objects.world.WorldObjects`):
    the objects' places in the world.  ``lock`` is held while the SLAM tracks (the live node
    reads the map from other threads)."""

    def __init__(self, source: FrameSource, masker: Any = None, *, system: Any = None, motion: Any = None,
                 world: Any = None) -> None:
        self.source, self.masker, self.system, self.motion, self.world = source, masker, system, motion, world
        self.lock = threading.RLock()

    def mask(self, item: FrameItem) -> Masked:
        """Read and mask one frame, and measure its objects' flow for the motion test; its
        own timer (this runs on the masking thread when the job is pipelined)."""
        t = StageTimer()
        t.add_derived(MASK_TOTAL, MASK_STAGES)
        t.start_frame(item.index if item.index is not None else item.position)
        frame = self.source.read(item, t)
        masker, motion = self.masker, self.motion
        masks = masker.mask(frame, t) if masker is not None else None
        if motion is not None and masks is not None:
            with t.stage("motion_flow"):
                motion.measure(frame, masks)
        feats = None
        if self.system is not None and (masks is None or motion is None):
            # what SLAM will be given is known now (no motion test's selection to wait
            # for): its features and stereo matches too, beside the tracking of the frame before
            feats = self.system.features(frame, masks, t)
        return Masked(item, frame, masks, t.end_frame()["ms"], feats)

    def track(self, m: Masked, timer: StageTimer, position: int) -> Processed:
        """Track one masked frame; its stages go into ``timer`` (the job's), whose frame the
        caller has started.  A live item gets its frame number (``position``) here."""
        item, frame, masks = m.item, m.frame, m.masks
        if item.index is None:
            item.index = frame.index = position
        for name, ms in m.ms.items():
            if name not in ("total", MASK_TOTAL):
                timer.add(name, ms)
        stamp = self.source.stamp(item, frame)
        motion = self.motion if masks is not None else None
        slam_masks = motion.select(masks) if motion is not None else masks
        if self.system is None:
            return Processed(position, item.index, stamp, frame, masks, slam_masks, None, "", payload=item.payload)
        with self.lock:
            tracked = self.system.track(frame, slam_masks, timer, features=m.features)
            if motion is not None:
                with timer.stage("motion"):
                    motion.forgot(apply_map_edits(self.system, motion.update(masks, tracked).edits))
            if self.world is not None and masks is not None:
                with timer.stage("objects"):
                    self.world.update(masks, tracked.pose, str(tracked.status) in ("tracked", "init"), stamp, frame)
        return Processed(position, item.index, stamp, frame, masks, slam_masks, tracked.pose, str(tracked.status),
                         payload=item.payload)


def apply_map_edits(system, edits) -> int:
    """Remove from the SLAM's map the points of the motion test's map edits (objects that
    turned moving), through its public API; returns how many went."""
    return sum(system.forget_region(e.region, e.z_min, e.z_max) for e in edits)
