"""Stereo sanity check: is this really a rectified left/right pair?

A broken driver that publishes one camera twice, a left/right mix-up or a pair that was
never rectified all give images SLAM happily tracks -- with a wrong scale, or a
trajectory that jumps by metres per frame -- and report success.  This check looks at a
few sparse ORB matches of the first frames, matched without any epipolar constraint
(nearest Hamming neighbour + ratio test), and reads three numbers off them:

* **zero shift**: the share of matches with the same position in both images (|dx|,
  |dy| < 0.5 px).  Real stereo keeps only very distant points there (< 5 % on KITTI,
  EuRoC); the same image twice gives ~100 %  ->  *identical*.
* **row agreement**: the share of matches on the same row (|dy| <= 1.5 px).  Rectified
  pairs: >= 80 %; a 1 degree roll or a 4 px vertical offset: < 40 %  ->  *unrectified*.
* **negative disparity**: among the matches that moved (|dx| > 1 px), the share with
  x_right > x_left.  Rectified pairs: < 6 %; swapped: > 90 %  ->  *swapped*.

The thresholds sit in the middle of those gaps (measured on KITTI 03/06, KITTI raw 0001
and EuRoC V1_01 frames 0/10/20, with the faults made from them).  Too few matches
(texture-less images) is inconclusive and passes.  Cost: one ORB detection per image and
a brute-force match of 1000 x 1000 descriptors, ~20 ms a frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from enum import Enum
from typing import Iterable

import cv2
import numpy as np

from ..errors import StereoCheckError
from ..datatypes import StereoFrame

log = logging.getLogger(__name__)

N_FEATURES = 1000
RATIO = 0.8  # nearest / second-nearest Hamming distance
MAX_DISTANCE = 50  # of 256 bits
MIN_MATCHES = 40  # fewer: inconclusive
IDENTICAL_SHARE = 0.8  # zero-shift share above which the images are one and the same
ROW_SHARE = 0.5  # row-agreement share below which the rows do not line up
NEGATIVE_SHARE = 0.6  # negative-disparity share above which left and right are swapped
CHECK_FRAMES = 2  # frames the offline check looks at
CHECK_EVERY = 100  # frames between the checks of a running job (~20 ms each: 0.2 ms a frame)


class StereoFault(str, Enum):
    OK = "ok"
    INCONCLUSIVE = "inconclusive"
    IDENTICAL = "identical"
    UNRECTIFIED = "unrectified"
    SWAPPED = "swapped"


CAUSES = {
    StereoFault.IDENTICAL: "left and right images are identical ({zero:.0%} of {n} matches have zero disparity): "
                           "one camera published or copied twice?",
    StereoFault.UNRECTIFIED: "the rows of the left and right images do not line up (only {rows:.0%} of {n} matches "
                             "on the same row): images not rectified, or the wrong calibration?",
    StereoFault.SWAPPED: "left and right look swapped ({neg:.0%} of {n} matches have negative disparity): "
                         "exchange the left and right images / topics",
}


@dataclass
class StereoVerdict:
    fault: StereoFault
    matches: int = 0
    zero_share: float = 0.0
    row_share: float = 0.0
    negative_share: float = 0.0
    frames: list[int] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.fault in (StereoFault.OK, StereoFault.INCONCLUSIVE)

    def describe(self) -> str:
        if self.fault not in CAUSES:
            return f"stereo check {self.fault.value} ({self.matches} matches)"
        return CAUSES[self.fault].format(zero=self.zero_share, rows=self.row_share, neg=self.negative_share,
                                         n=self.matches)

    def to_dict(self) -> dict:
        return {"fault": self.fault.value, "matches": self.matches, "zero_share": round(self.zero_share, 4),
                "row_share": round(self.row_share, 4), "negative_share": round(self.negative_share, 4),
                "frames": self.frames}


def pair_shifts(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """``(M, 2)`` shifts ``(x_left - x_right, y_right - y_left)`` of the sparse ORB matches
    of one grayscale pair (no epipolar constraint: any match anywhere in the image)."""
    orb = cv2.ORB_create(nfeatures=N_FEATURES, nlevels=1, fastThreshold=10)
    kl, dl = orb.detectAndCompute(left, None)
    kr, dr = orb.detectAndCompute(right, None)
    if dl is None or dr is None or len(kl) < 2 or len(kr) < 2:
        return np.zeros((0, 2))
    dist, idx = cv2.batchDistance(dl, dr, cv2.CV_32S, normType=cv2.NORM_HAMMING, K=2)
    good = (dist[:, 0] < RATIO * dist[:, 1]) & (dist[:, 0] < MAX_DISTANCE)
    pl = cv2.KeyPoint_convert(kl)[good]
    pr = cv2.KeyPoint_convert(kr)[idx[good, 0]]
    return np.column_stack([pl[:, 0] - pr[:, 0], pr[:, 1] - pl[:, 1]]).astype(np.float64)


def judge(shifts: np.ndarray, frames: list[int] | None = None) -> StereoVerdict:
    """The verdict on the pooled shifts of one or more pairs (module doc)."""
    n = int(len(shifts))
    frames = list(frames or [])
    if n < MIN_MATCHES:
        return StereoVerdict(StereoFault.INCONCLUSIVE, n, frames=frames)
    dx, dy = shifts[:, 0], shifts[:, 1]
    zero = float(np.mean((np.abs(dx) < 0.5) & (np.abs(dy) < 0.5)))
    rows = float(np.mean(np.abs(dy) <= 1.5))
    moved = np.abs(dx) > 1.0
    neg = float(np.mean(dx[moved] < 0)) if moved.sum() >= MIN_MATCHES // 2 else 0.0
    v = StereoVerdict(StereoFault.OK, n, zero, rows, neg, frames)
    if zero > IDENTICAL_SHARE:
        v.fault = StereoFault.IDENTICAL
    elif rows < ROW_SHARE:
        v.fault = StereoFault.UNRECTIFIED
    elif neg > NEGATIVE_SHARE:
        v.fault = StereoFault.SWAPPED
    return v


def check_frames(frames: Iterable[StereoFrame]) -> StereoVerdict:
    """The verdict on ``frames`` pooled (their matches together)."""
    shifts, idx = [], []
    for f in frames:
        shifts.append(pair_shifts(f.left_gray, f.right_gray))
        idx.append(int(f.index))
    return judge(np.concatenate(shifts) if shifts else np.zeros((0, 2)), idx)


def check_sequence(sequence, frames: list[int], n: int = CHECK_FRAMES) -> StereoVerdict:
    """Check the first ``n`` of the requested ``frames`` of ``sequence``; raises
    :class:`StereoCheckError` naming the sequence and the likely cause on a fault."""
    verdict = check_frames(sequence.frame(i) for i in frames[:n])
    log.debug("stereo check of %s: %s", getattr(sequence, "path", ""), verdict.to_dict())
    if not verdict.ok:
        shown = ",".join(str(i) for i in verdict.frames)
        raise StereoCheckError(f"stereo check failed on frame(s) {shown}: {verdict.describe()} "
                               "(--no-stereo-check to run anyway)", getattr(sequence, "path", None))
    return verdict


class StereoWatch:
    """The same check for a live stream: pools the first frames' matches until the verdict
    is conclusive (or ``max_frames`` went by) and logs one warning on a fault."""

    def __init__(self, source: str = "stereo input", min_frames: int = CHECK_FRAMES, max_frames: int = 10) -> None:
        self.source = source
        self.min_frames = min_frames
        self.max_frames = max_frames
        self.verdict: StereoVerdict | None = None
        self._shifts: list[np.ndarray] = []

    @property
    def done(self) -> bool:
        return self.verdict is not None

    def observe(self, frame: StereoFrame) -> StereoVerdict | None:
        """Add one frame; the verdict once reached (None before)."""
        if self.verdict is not None:
            return self.verdict
        self._shifts.append(pair_shifts(frame.left_gray, frame.right_gray))
        if len(self._shifts) < self.min_frames:
            return None
        v = judge(np.concatenate(self._shifts))
        if v.fault is StereoFault.INCONCLUSIVE and len(self._shifts) < self.max_frames:
            return None
        self.verdict, self._shifts = v, []
        if not v.ok:
            log.warning("%s: stereo check failed: %s", self.source, v.describe())
        return v


class PeriodicStereoCheck:
    """A job's observer (:class:`~dynastereo.observers.FrameObserver`): the check again on
    every ``every``-th frame after the first ones, so a camera that fails mid-run (a driver
    that starts publishing one image twice) stops the job with a
    :class:`StereoCheckError` naming the frame, its results so far kept."""

    def __init__(self, source=None, every: int | None = None) -> None:
        self.source = source
        self.every = int(every or CHECK_EVERY)

    def on_frame(self, event) -> None:
        if event.position == 0 or event.position % self.every:
            return
        v = check_frames([event.frame])
        if not v.ok:
            raise StereoCheckError(f"stereo check failed at frame {event.frame.index} (the {event.position + 1}-th "
                                   f"fed): {v.describe()} (--no-stereo-check to run anyway)", self.source)
