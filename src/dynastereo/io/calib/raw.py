"""Calibration of a raw (unrectified) stereo pair: :class:`RawStereoCalibration`,
which :class:`~dynastereo.io.rectify.Rectifier` turns into rectification maps."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


@dataclass(frozen=True)
class RawStereoCalibration:
    """Calibration of a raw (unrectified) stereo pair.

    ``K1, D1`` / ``K2, D2``: intrinsics and OpenCV distortion of the left / right camera.
    Either ``R, T`` (pose of the left camera in the right camera's frame: ``X_r = R X_l + T``,
    metres -- OpenCV's ``stereoRectify`` convention) or a ready-made rectification
    ``R1, R2, P1, P2`` (then ``R, T`` may be absent).  ``width, height``: raw image size.
    """

    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    width: int
    height: int
    R: np.ndarray | None = None
    T: np.ndarray | None = None
    R1: np.ndarray | None = None
    R2: np.ndarray | None = None
    P1: np.ndarray | None = None
    P2: np.ndarray | None = None
    alpha: float = 0.0  # free scaling for cv2.stereoRectify (ignored with a ready-made R1..P2)
    source: Path | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        def arr(v: Any, shape: tuple[int, ...] | None) -> np.ndarray | None:
            if v is None:
                return None
            a = np.asarray(v, dtype=np.float64)
            return a.reshape(shape) if shape is not None else a.reshape(-1)

        for name, shape in (("K1", (3, 3)), ("K2", (3, 3)), ("R", (3, 3)), ("T", (3,)), ("R1", (3, 3)),
                            ("R2", (3, 3)), ("P1", (3, 4)), ("P2", (3, 4)), ("D1", None), ("D2", None)):
            object.__setattr__(self, name, arr(getattr(self, name), shape))
        for name in ("D1", "D2"):
            if getattr(self, name).size not in (0, 4, 5, 8, 12, 14):
                raise ValueError(f"{name} must have 4, 5, 8, 12 or 14 coefficients, got {getattr(self, name).size}")
        if self.has_rectification:
            pass
        elif self.R is None or self.T is None:
            raise ValueError("need either R and T, or all of R1, R2, P1, P2")
        if not (self.width > 0 and self.height > 0):
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")

    @property
    def has_rectification(self) -> bool:
        return all(getattr(self, k) is not None for k in ("R1", "R2", "P1", "P2"))

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    @property
    def baseline(self) -> float:
        """Distance between the optical centres in metres."""
        if self.T is not None:
            return float(np.linalg.norm(self.T))
        return float(-self.P2[0, 3] / self.P2[0, 0])  # type: ignore[index]
