"""The detection stage of a frame: contrast, scale, schedule and boxes carried between runs.

:class:`DetectionStage` is what the maskers call once per stereo pair
(``detect_frame(frame, timer)``).  Per frame:

1. **Contrast** (``detector.contrast: clahe``): the detector sees the left image after
   CLAHE (contrast-limited adaptive histogram equalization, on the luminance of a colour
   image), so dark cars in shade are found; disparity and SLAM keep the original images.
2. **Schedule** (``detector.schedule``): ``every`` runs the network on every frame;
   ``interval`` every ``detector.interval``-th frame; ``rotate`` (with ``canvas: tiles``)
   one tile per frame in turn.  Frames are counted as they come (revisits included).
3. **Scale**: the network sees the frame (or the tile) at about its native scale
   (:class:`~.scale.ScaledDetector`).
4. **Carry** (``detector.track``): a :class:`~.box_tracker.BoxTracker` moves the boxes of
   earlier frames into this one by sparse optical flow; a detection confirms (same track
   id) or corrects a carried box; boxes the detector did not confirm are carried for
   ``detector.max_carry`` detector runs.  Every box has a track id and a ``carried`` flag
   (``objects.jsonl``: ``track_id``, ``source``).

Stage times: ``detect`` (the network, with tiling and merging), ``contrast`` and
``carry`` (parts of ``mask``).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ...config import DetectorConfig
from ...timing import StageTimer, timed
from ...datatypes import Detections, StereoFrame
from .scale import ScaledDetector
from .box_tracker import BoxTracker, TrackerParams, warm_up_kernels


_stage = timed


class Contrast:
    """CLAHE on a grey image or on the L channel of a BGR one (``clip``, ``grid`` tiles)."""

    def __init__(self, clip: float = 2.0, grid: int = 8):
        self.clahe = cv2.createCLAHE(clipLimit=float(clip), tileGridSize=(int(grid), int(grid)))

    def __call__(self, image: np.ndarray) -> np.ndarray:
        if image.ndim == 2:
            return self.clahe.apply(image)
        if image.ndim == 3 and image.shape[2] == 1:
            return self.clahe.apply(np.ascontiguousarray(image[:, :, 0]))
        rows = image[::16]  # a grey image stored as colour (a bag's rgb8 of a grey camera):
        if np.array_equal(rows[:, :, 0], rows[:, :, 1]) and np.array_equal(rows[:, :, 0], rows[:, :, 2]):
            return self.clahe.apply(np.ascontiguousarray(image[:, :, 0]))  # the same as grey input
        lab = cv2.cvtColor(image[:, :, :3], cv2.COLOR_BGR2LAB)
        lab[:, :, 0] = self.clahe.apply(np.ascontiguousarray(lab[:, :, 0]))
        return cv2.cvtColor(lab, cv2.COLOR_LAB2BGR)


class DetectionStage:
    """Detections for each frame (module docstring).  ``detector``: any object with
    ``detect(image) -> Detections`` (a plain YOLO detector is wrapped in a
    :class:`ScaledDetector` per ``cfg``; an oracle or a test double is used as it is)."""

    def __init__(self, detector: Any, cfg: DetectorConfig | None = None):
        self.cfg = cfg = cfg or DetectorConfig()
        cfg.validate()  # (a configuration changed after it was made)
        # a network detector gets the scale, schedule, contrast and carrying; anything else
        # (the synthetic oracle, test doubles) is used as it is
        self.network = hasattr(detector, "detect_batch") or isinstance(detector, ScaledDetector)
        if self.network and not isinstance(detector, ScaledDetector):
            detector = ScaledDetector(detector, cfg.canvas, cfg.scale, cfg.tiles, cfg.tile_overlap, cfg.band_top)
        self.detector = detector
        self.name = getattr(detector, "name", type(detector).__name__)
        self.class_names = tuple(getattr(detector, "class_names", ()))
        self.contrast = Contrast() if cfg.contrast == "clahe" and self.network else None
        half = cfg.carry_downscale == 2  # the flow on the half-size image: a smaller window, one level less
        self.tracker = (BoxTracker(TrackerParams(max_carry=int(cfg.max_carry), min_hits=2,
                                                 lk_downscale=int(cfg.carry_downscale),
                                                 lk_win=11 if half else 15, lk_levels=2 if half else 3))
                        if cfg.track and self.network else None)
        self._count = 0

    def reset(self) -> None:
        """Forget the carried boxes and restart the schedule (a new sequence)."""
        self._count = 0
        if self.tracker is not None:
            self.tracker.reset()

    def _runs(self, k: int) -> bool:
        """Whether the network runs on the ``k``-th frame of the schedule."""
        return not (self.cfg.schedule == "interval" and k % self.cfg.interval)

    def _detect(self, image: np.ndarray, k: int) -> tuple[Detections, tuple[float, ...] | None]:
        """(detections of frame ``k``, the region searched when only one tile was)."""
        if self.cfg.schedule == "rotate" and isinstance(self.detector, ScaledDetector):
            h, w = image.shape[:2]
            windows, _ = self.detector.plan(w, h)
            t = windows[k % len(windows)]
            return self.detector.detect_window(image, k % len(windows)), (t.x0, t.y0, t.x1, t.y1)
        return self.detector.detect(image), None

    def detect_frame(self, frame: StereoFrame, timer: StageTimer | None = None) -> Detections:
        """The boxes to mask on ``frame`` (its left image), with track ids when tracking."""
        k = self._count
        self._count += 1
        image = frame.left
        if not self.network:  # the oracle or a test double: its boxes as they are
            with _stage(timer, "detect"):
                if hasattr(self.detector, "detect_frame"):
                    return self.detector.detect_frame(frame.index)
                return self.detector.detect(image)
        dets, region = None, None
        if self._runs(k):
            if self.contrast is not None:
                with _stage(timer, "contrast"):
                    image = self.contrast(image)
            with _stage(timer, "detect"):
                dets, region = self._detect(image, k)
        if self.tracker is None:
            return dets if dets is not None else Detections.empty(self.class_names)
        with _stage(timer, "carry"):
            return self.tracker.update(frame.left_gray, dets, region=region)

    def warm_up(self, height: int, width: int) -> None:
        """One inference on a black ``height`` x ``width`` frame, before the first real one: a
        network's first call initializes lazily (onnxruntime: ~0.4 s on KITTI frames), which
        would otherwise land in the frame loop (a live source's first frames, an offline
        run's FPS).  The schedule and the carried boxes are untouched; nothing for the
        oracle or a test double.  The box tracker's compiled kernel is loaded too.  A network
        with a graph of its own for grey frames (YOLOX, ``detector.grey_input``) gets a grey
        black frame as well."""
        warm_up_kernels()
        if self.network and height > 0 and width > 0:
            self.detector.detect(np.zeros((int(height), int(width), 3), np.uint8))
            if getattr(self.detector, "grey_graph", False):
                self.detector.detect(np.zeros((int(height), int(width)), np.uint8))

    def detect(self, image: np.ndarray) -> Detections:
        """One image alone (no schedule, no carrying): the detector at its scale."""
        if self.contrast is not None:
            image = self.contrast(image)
        return self.detector.detect(image)

    def __repr__(self) -> str:
        return f"DetectionStage({self.detector!r}, schedule={self.cfg.schedule!r}, track={self.cfg.track})"
