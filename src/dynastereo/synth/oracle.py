"""Readers of the synthetic ground truth, and the ORACLE detector (GT boxes, no network).

``OracleDetector`` implements the ``Detector`` protocol of ``dynastereo.masking.base`` but
it does not look at the image: it returns the ground-truth boxes of the frame, read from
``gt/objects.json``.  It exists so masking and SLAM can be tested on synthetic
sequences without a neural network -- it is NOT a detector for real data.

Which frame?  ``detect(image)`` cannot know the frame from a detector's point of view,
so the frame is found in this order:

1. ``oracle.frame_index`` if it is set (``oracle.for_frame(i)`` sets it and returns the
   oracle, so ``oracle.for_frame(frame.index).detect(frame.left)`` works; a pipeline that
   knows the index sets it before every ``detect``);
2. otherwise the image itself: the oracle hashes the left images of the sequence once
   (lazily, on the first such call) and looks the image up -- exact for images read
   unchanged from ``image_0`` (grey or grey converted to BGR);
3. otherwise it raises an ``InputError`` that says to bind the frame.

``detect_frame(i)`` is the explicit form.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import ImageReadError, InputError, SequenceError
from ..datatypes import DEFAULT_DYNAMIC_CLASSES, Detections

OBJECTS_FILE = Path("gt") / "objects.json"


@dataclass(frozen=True)
class GTObject:
    """One object as seen in one frame (coordinates: KITTI camera frame, world = first camera)."""

    id: int  # instance id = value in the masks
    label: str  # COCO class name
    moving: bool
    speed: float  # m/s
    box_left: tuple[int, int, int, int] | None  # x1, y1, x2, y2 (exclusive) of the visible pixels
    box_right: tuple[int, int, int, int] | None
    pixels_left: int
    pixels_right: int
    position: tuple[float, float, float]  # box centre, world frame
    yaw: float
    pose: np.ndarray  # 3x4 object -> world
    position_cam: tuple[float, float, float]  # box centre in the current left camera frame
    distance: float  # metres from the left camera centre


@dataclass
class SynthGroundTruth:
    path: Path
    scenario: str
    seed: int
    size: tuple[int, int]
    calibration: dict[str, float]
    objects: dict[int, dict[str, Any]]  # id -> {label, size, moves}
    frames: list[list[GTObject]]
    meta: dict[str, Any]

    def __len__(self) -> int:
        return len(self.frames)

    def frame(self, index: int) -> list[GTObject]:
        if not 0 <= index < len(self.frames):
            raise InputError(f"frame {index} out of range 0..{len(self.frames) - 1}", self.path)
        return self.frames[index]


def _seq_dir(seq_path: str | Path) -> Path:
    """Accept the sequence folder (``.../sequences/00``) or the dataset root above it."""
    p = Path(seq_path)
    if (p / OBJECTS_FILE).is_file():
        return p
    if (p / "sequences" / "00" / OBJECTS_FILE).is_file():
        return p / "sequences" / "00"
    raise SequenceError(f"no synthetic ground truth here (expected {OBJECTS_FILE})", p)


def _box(v: Any) -> tuple[int, int, int, int] | None:
    return None if v is None else tuple(int(x) for x in v)  # type: ignore[return-value]


def read_objects(seq_path: str | Path) -> SynthGroundTruth:
    """Parse ``gt/objects.json`` of a generated sequence."""
    seq = _seq_dir(seq_path)
    path = seq / OBJECTS_FILE
    try:
        data = json.loads(path.read_text())
        frames = [
            [
                GTObject(
                    id=int(o["id"]),
                    label=str(o["label"]),
                    moving=bool(o["moving"]),
                    speed=float(o["speed"]),
                    box_left=_box(o["box_left"]),
                    box_right=_box(o["box_right"]),
                    pixels_left=int(o["pixels_left"]),
                    pixels_right=int(o["pixels_right"]),
                    position=tuple(float(x) for x in o["position"]),  # type: ignore[arg-type]
                    yaw=float(o["yaw"]),
                    pose=np.asarray(o["pose"], float).reshape(3, 4),
                    position_cam=tuple(float(x) for x in o["position_cam"]),  # type: ignore[arg-type]
                    distance=float(o["distance"]),
                )
                for o in fr["objects"]
            ]
            for fr in data["frames_gt"]
        ]
        gt = SynthGroundTruth(
            path=path,
            scenario=str(data["scenario"]),
            seed=int(data["seed"]),
            size=(int(data["size"][0]), int(data["size"][1])),
            calibration={k: float(v) for k, v in data["calibration"].items()},
            objects={int(o["id"]): o for o in data["objects"]},
            frames=frames,
            meta={k: v for k, v in data.items() if k != "frames_gt"},
        )
    except (OSError, ValueError, KeyError, TypeError, IndexError) as e:
        raise SequenceError(f"malformed synthetic ground truth: {e}", path) from None
    return gt


def _read_png(path: Path, flags: int) -> np.ndarray:
    if not path.is_file():
        raise ImageReadError("ground-truth image missing", path)
    img = cv2.imread(str(path), flags)
    if img is None:
        raise ImageReadError("cannot decode ground-truth image", path)
    return img


def read_gt_masks(seq_path: str | Path, index: int) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) uint8 instance masks of frame ``index`` (value = object id, 0 = none)."""
    seq = _seq_dir(seq_path)
    name = f"{index:06d}.png"
    left = _read_png(seq / "gt" / "masks" / "left" / name, cv2.IMREAD_UNCHANGED)
    right = _read_png(seq / "gt" / "masks" / "right" / name, cv2.IMREAD_UNCHANGED)
    return left, right


def read_gt_disparity(seq_path: str | Path, index: int) -> np.ndarray:
    """Left disparity of frame ``index`` in pixels, float32, 0 = no surface (sky)."""
    seq = _seq_dir(seq_path)
    d = _read_png(seq / "gt" / "disparity" / f"{index:06d}.png", cv2.IMREAD_UNCHANGED)
    if d.dtype != np.uint16:
        raise ImageReadError(f"disparity must be uint16, got {d.dtype}", seq / "gt" / "disparity" / f"{index:06d}.png")
    return d.astype(np.float32) / 256.0


def _image_key(image: np.ndarray) -> bytes:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.shape[2] == 3 else img[..., 0]
    img = np.ascontiguousarray(img, dtype=np.uint8)
    h = hashlib.blake2b(img.tobytes(), digest_size=16)
    h.update(np.array(img.shape, np.int64).tobytes())
    return h.digest()


class OracleDetector:
    """Ground-truth "detector" for synthetic sequences -- returns the GT boxes of the frame.

    ``classes`` limits the labels returned (default: the dynamic COCO classes);
    ``min_pixels`` drops objects with fewer visible left-image pixels; ``moving_only``
    returns only objects moving in that frame; ``with_masks`` adds the GT instance masks
    (``Detections.masks``, (N, H, W) bool, left view).  Every box's track id
    (``Detections.track_ids``) is the object's GT instance id.  See the module docstring for how
    the frame is chosen.
    """

    name = "oracle"

    def __init__(
        self,
        sequence_path: str | Path,
        classes: tuple[str, ...] | list[str] = DEFAULT_DYNAMIC_CLASSES,
        min_pixels: int = 1,
        moving_only: bool = False,
        with_masks: bool = False,
    ):
        self.path = _seq_dir(sequence_path)
        self.gt = read_objects(self.path)
        self.class_names: tuple[str, ...] = tuple(DEFAULT_DYNAMIC_CLASSES) + tuple(
            sorted({o["label"] for o in self.gt.objects.values()} - set(DEFAULT_DYNAMIC_CLASSES))
        )
        self.classes = set(classes)
        self.min_pixels = int(min_pixels)
        self.moving_only = bool(moving_only)
        self.with_masks = bool(with_masks)
        self.frame_index: int | None = None
        self._by_hash: dict[bytes, int] | None = None

    def __len__(self) -> int:
        return len(self.gt)

    def for_frame(self, index: int) -> "OracleDetector":
        """Bind the frame the next ``detect`` calls answer for; returns ``self``."""
        self.gt.frame(index)  # range check
        self.frame_index = int(index)
        return self

    def objects(self, index: int) -> list[GTObject]:
        """The GT objects ``detect_frame(index)`` reports (after the filters)."""
        return [
            o
            for o in self.gt.frame(index)
            if o.box_left is not None
            and o.pixels_left >= self.min_pixels
            and o.label in self.classes
            and (o.moving or not self.moving_only)
        ]

    def detect_frame(self, index: int) -> Detections:
        objs = self.objects(index)
        if not objs:
            return Detections.empty(self.class_names)
        boxes = np.array([o.box_left for o in objs], np.float32)
        ids = np.array([self.class_names.index(o.label) for o in objs], np.int32)
        masks = None
        if self.with_masks:
            left, _ = read_gt_masks(self.path, index)
            masks = np.stack([left == o.id for o in objs])
        tracks = np.array([o.id for o in objs], np.int64)  # the GT instance id is the track id
        return Detections(boxes, np.ones(len(objs), np.float32), ids, self.class_names, masks, tracks)

    def detect(self, image: np.ndarray) -> Detections:
        if self.frame_index is not None:
            return self.detect_frame(self.frame_index)
        index = self._lookup(image)
        if index is None:
            raise InputError(
                "oracle detector: this image is not a left image of the sequence; "
                "bind the frame with oracle.for_frame(i) or oracle.frame_index = i",
                self.path,
            )
        return self.detect_frame(index)

    def gt_masks(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(left, right) GT instance masks of frame ``index``."""
        return read_gt_masks(self.path, index)

    def _lookup(self, image: np.ndarray) -> int | None:
        if self._by_hash is None:
            table: dict[bytes, int] = {}
            for i in range(len(self.gt)):
                p = self.path / "image_0" / f"{i:06d}.png"
                img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
                if img is None:
                    raise ImageReadError("cannot read left image", p)
                table.setdefault(_image_key(img), i)
            self._by_hash = table
        return self._by_hash.get(_image_key(image))
