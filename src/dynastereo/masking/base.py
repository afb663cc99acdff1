"""Protocols of the masking stages; each is swappable.

Disparity:  ``DisparityEstimator.compute(left_gray, right_gray, rows=None, cols=None) -> float32``
Detector:   ``Detector.detect(image) -> Detections`` (left image only, BGR or gray)
Masker:     ``Masker.mask(frame, timer) -> StereoMasks`` (both images)
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from ..timing import StageTimer
from ..datatypes import Detections, StereoFrame, StereoMasks


@runtime_checkable
class DisparityEstimator(Protocol):
    name: str

    def compute(self, left_gray: np.ndarray, right_gray: np.ndarray) -> np.ndarray:
        """Full-frame disparity, float32 pixels, <= 0 invalid."""
        ...


@runtime_checkable
class Detector(Protocol):
    name: str
    class_names: tuple[str, ...]

    def detect(self, image: np.ndarray) -> Detections:
        """Dynamic-class detections in ``image`` coordinates, after score filter and NMS."""
        ...


@runtime_checkable
class Masker(Protocol):
    name: str

    def mask(self, frame: StereoFrame, timer: StageTimer | None = None) -> StereoMasks:
        """Masks of the dynamic objects in both images of ``frame``.

        Records stage times in ``timer``: ``detect`` for the network alone; the
        other stages (``disparity``, ``outline``, ``transfer``, ...) add up to ``mask``.
        """
        ...
