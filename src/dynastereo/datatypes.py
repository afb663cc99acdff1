"""Typed data passed between the stages: io -> masking -> slam -> eval.

Conventions
-----------
* Images are numpy arrays, ``uint8``, either ``(H, W)`` grayscale or ``(H, W, 3)`` BGR.
* All images a stage receives are *rectified*: epipolar lines are image rows.
* Disparity maps are ``float32`` in pixels, ``x_left - x_right``; a value ``<= 0``
  means "no valid disparity" (the KITTI convention of 0 = unknown).
* Boxes are ``float32`` arrays ``(N, 4)`` of ``x1, y1, x2, y2`` in pixel coordinates
  of the image they were detected in (x2/y2 exclusive).
* Masks are ``uint8`` with 255 = dynamic, 0 = static.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

# Default dynamic classes (COCO names), thesis + issue: things that move on a street.
DEFAULT_DYNAMIC_CLASSES: tuple[str, ...] = (
    "person",
    "bicycle",
    "car",
    "motorcycle",
    "bus",
    "truck",
    "train",
)


@dataclass(frozen=True)
class StereoCalibration:
    """Calibration of a *rectified* stereo pair (after rectification, if any).

    ``K`` is the 3x3 intrinsic matrix shared by both rectified cameras, ``baseline``
    the distance between the optical centres in metres (positive: right camera
    to the right of the left one), ``width``/``height`` the image size.
    """

    K: np.ndarray
    baseline: float
    width: int
    height: int

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        object.__setattr__(self, "K", K)
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise ValueError(f"focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        if not self.baseline > 0:
            raise ValueError(f"baseline must be positive, got {self.baseline}")

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def bf(self) -> float:
        """Baseline times focal length (ORB-SLAM2's ``Camera.bf``), pixel*metres."""
        return self.baseline * self.fx

    @property
    def size(self) -> tuple[int, int]:
        """(width, height)."""
        return (self.width, self.height)

    def depth_from_disparity(self, disparity: np.ndarray | float) -> np.ndarray:
        """Depth in metres for disparity in pixels (inf where disparity <= 0)."""
        d = np.asarray(disparity, dtype=np.float64)
        with np.errstate(divide="ignore"):
            return np.where(d > 0, self.bf / np.maximum(d, 1e-12), np.inf)

    def disparity_from_depth(self, depth: np.ndarray | float) -> np.ndarray:
        z = np.asarray(depth, dtype=np.float64)
        with np.errstate(divide="ignore"):
            return np.where(z > 0, self.bf / np.maximum(z, 1e-12), 0.0)


@dataclass
class StereoFrame:
    """One rectified stereo pair from a sequence."""

    index: int
    timestamp: float
    left: np.ndarray
    right: np.ndarray
    left_path: Path | None = None
    right_path: Path | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.left.shape[:2]

    @staticmethod
    def _gray(img: np.ndarray) -> np.ndarray:
        if img.ndim == 2:
            return img
        import cv2

        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)

    @property
    def left_gray(self) -> np.ndarray:
        return self._gray(self.left)

    @property
    def right_gray(self) -> np.ndarray:
        return self._gray(self.right)


@dataclass
class Detections:
    """Detector output after post-processing, array-wise (no per-object objects).

    ``class_ids`` index into ``class_names`` (the model's label list).
    """

    boxes: np.ndarray  # (N, 4) float32 x1, y1, x2, y2
    scores: np.ndarray  # (N,) float32
    class_ids: np.ndarray  # (N,) int32
    class_names: tuple[str, ...] = ()
    masks: np.ndarray | None = None  # optional (N, H, W) bool instance masks (seg models)
    # Set by the box tracker (masking.detection.box_tracker): a track id per box (-1: none)
    # and whether the box was carried from earlier frames rather than detected in this one.
    track_ids: np.ndarray | None = None  # (N,) int64
    carried: np.ndarray | None = None  # (N,) bool

    def __post_init__(self) -> None:
        self.boxes = np.asarray(self.boxes, dtype=np.float32).reshape(-1, 4)
        self.scores = np.asarray(self.scores, dtype=np.float32).reshape(-1)
        self.class_ids = np.asarray(self.class_ids, dtype=np.int32).reshape(-1)
        if not (len(self.boxes) == len(self.scores) == len(self.class_ids)):
            raise ValueError("boxes, scores and class_ids must have the same length")
        if self.track_ids is not None:
            self.track_ids = np.asarray(self.track_ids, dtype=np.int64).reshape(-1)
            if len(self.track_ids) != len(self.boxes):
                raise ValueError("track_ids must have one entry per box")
        if self.carried is not None:
            self.carried = np.asarray(self.carried, dtype=bool).reshape(-1)
            if len(self.carried) != len(self.boxes):
                raise ValueError("carried must have one entry per box")

    def track_id(self, i: int) -> int:
        """Track id of box ``i`` (-1 when the boxes are not tracked)."""
        return int(self.track_ids[i]) if self.track_ids is not None else -1

    def source(self, i: int) -> "DetectionSource":
        """``CARRIED`` when box ``i`` was carried from earlier frames, else ``DETECTED``."""
        carried = self.carried is not None and bool(self.carried[i])
        return DetectionSource.CARRIED if carried else DetectionSource.DETECTED

    def __len__(self) -> int:
        return len(self.boxes)

    @classmethod
    def empty(cls, class_names: tuple[str, ...] = ()) -> "Detections":
        return cls(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32), class_names)

    def labels(self) -> list[str]:
        names = self.class_names
        return [names[i] if 0 <= i < len(names) else str(int(i)) for i in self.class_ids]

    def select(self, keep: np.ndarray) -> "Detections":
        """Subset by boolean mask or index array."""
        return Detections(
            self.boxes[keep],
            self.scores[keep],
            self.class_ids[keep],
            self.class_names,
            None if self.masks is None else self.masks[keep],
            None if self.track_ids is None else self.track_ids[keep],
            None if self.carried is None else self.carried[keep],
        )


class MaskMethod(StrEnum):
    """How the masker made an object's mask (``ObjectMask.method``; JSON and the
    pictures write the value): its outline, its whole box, an instance-segmentation
    mask, or its whole box because the outline failed -- ``box-fallback:<reason>``, the
    reasons explained in :mod:`dynastereo.masking.outline`."""

    OUTLINE = "outline"
    BOX = "box"
    SEG = "seg"
    FALLBACK_TINY = "box-fallback:tiny"
    FALLBACK_NO_DISPARITY = "box-fallback:no-disparity"
    FALLBACK_NO_PEAK = "box-fallback:no-object-pixels"
    FALLBACK_SPARSE = "box-fallback:sparse-disparity"
    FALLBACK_RANGE = "box-fallback:beyond-range"
    FALLBACK_SMALL = "box-fallback:small-outline"
    EMPTY = "empty:outside-image"  # the box lies outside the image: nothing masked

    @property
    def is_fallback(self) -> bool:
        """A whole box masked because the outline failed."""
        return self.value.startswith(FALLBACK_PREFIX)


FALLBACK_PREFIX = "box-fallback:"


class DetectionSource(StrEnum):
    """Where an object's box comes from: the detector in this frame, or carried from
    earlier frames by the box tracker (``ObjectMask.source``)."""

    DETECTED = "detected"
    CARRIED = "carried"


@dataclass
class ObjectMask:
    """What the masker decided for one detected object (per-frame record)."""

    box: tuple[float, float, float, float]
    label: str
    score: float
    method: MaskMethod
    disparity: float  # the object's disparity (peak) in pixels, 0 if unknown
    pixels_left: int
    pixels_right: int
    track_id: int = -1  # the box tracker's id (-1: boxes not tracked)
    source: DetectionSource = DetectionSource.DETECTED
    # the motion test's verdict (objects.motion): True moving, False static, None not
    # (yet) decided; whether the object was masked in the images SLAM got; its speed
    moving: bool | None = None
    masked: bool = True
    speed_mps: float | None = None
    speed_sigma_mps: float | None = None  # its standard deviation (stereo and pose noise, along the velocity)
    # where it is in the world and how fast it goes (objects.world.ObjectState), once tracked
    world: Any = None

    def __post_init__(self) -> None:
        self.method = MaskMethod(self.method)
        self.source = DetectionSource(self.source)

    def to_dict(self) -> dict[str, Any]:
        return {
            "box": [round(float(v), 1) for v in self.box],
            "label": self.label,
            "score": round(float(self.score), 4),
            "method": self.method.value,
            "disparity": round(float(self.disparity), 3),
            "pixels_left": int(self.pixels_left),
            "pixels_right": int(self.pixels_right),
            "track_id": int(self.track_id),
            "source": self.source.value,
            "track": int(self.track_id),
            "moving": None if self.moving is None else bool(self.moving),
            "masked": bool(self.masked),
            "speed_mps": None if self.speed_mps is None else round(float(self.speed_mps), 3),
            "speed_sigma_mps": None if self.speed_sigma_mps is None else round(float(self.speed_sigma_mps), 3),
            **(self.world.to_dict() if self.world is not None else {}),
        }


@dataclass
class StereoMasks:
    """Output of a masker for one stereo pair."""

    left: np.ndarray  # uint8 (H, W), 255 = dynamic
    right: np.ndarray  # uint8 (H, W), 255 = dynamic
    objects: list[ObjectMask] = field(default_factory=list)
    detections: Detections | None = None
    disparity: np.ndarray | None = None  # float32 pixels (full frame) if computed
    ground: Any = None  # masking.ground.GroundLine: the road line the outlines left out, when fitted
    # instance labels (int32, k + 1 = objects[k], 0 = none) of the left / right masks, from
    # the maskers that make them: what lets the motion test unmask one object alone
    labels_left: np.ndarray | None = None
    labels_right: np.ndarray | None = None
    # the disparity the masker computed (full frame, 0 where not computed: the boxes'
    # regions with stereo.region "boxes"), for the motion test
    box_disparity: np.ndarray | None = None
    flow: Any = None  # objects.motion.FrameFlow: the objects' points k-1 -> k, when measured

    @classmethod
    def empty(cls, shape: tuple[int, int]) -> "StereoMasks":
        z = np.zeros(shape, np.uint8)
        return cls(z, z.copy())

    @property
    def fraction_left(self) -> float:
        return float(np.count_nonzero(self.left)) / self.left.size


#: Overlay colours (BGR) of the motion test's verdicts (``ObjectMask.moving``): moving
#: objects red, not yet judged orange (both masked), static ones green (left to SLAM).
VERDICT_COLOURS = {True: (0, 0, 255), None: (0, 165, 255), False: (0, 200, 0)}
