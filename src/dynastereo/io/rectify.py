"""Stereo rectification of raw image pairs, with the maps computed once.

``Rectifier(raw)`` runs ``cv2.stereoRectify`` (``CALIB_ZERO_DISPARITY``; ``alpha`` from the
calibration, 0 = only valid pixels, no black borders) -- or takes the ready-made
``R1, R2, P1, P2`` of the calibration (ORB-SLAM2's ``LEFT.R/P``) -- and builds the two
``cv2.initUndistortRectifyMap`` maps once (fixed-point ``CV_16SC2`` by default, the fastest
for ``cv2.remap``).  ``rectify(left, right)`` is then two ``cv2.remap`` calls.

``Rectifier.calibration`` is the rectified :class:`~dynastereo.datatypes.StereoCalibration`:
``K = P1[:, :3]``, ``baseline = -P2[0, 3] / P2[0, 0]``.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import CalibrationError
from ..datatypes import StereoCalibration
from .calib import RawStereoCalibration


class Rectifier:
    """Rectification maps for one raw stereo calibration (see module doc)."""

    def __init__(
        self,
        raw: RawStereoCalibration,
        alpha: float | None = None,
        map_type: int = cv2.CV_16SC2,
        interpolation: int = cv2.INTER_LINEAR,
    ) -> None:
        self.raw = raw
        size = raw.size
        self.interpolation = interpolation
        self.Q: np.ndarray | None = None
        self.roi1: tuple[int, int, int, int] | None = None
        self.roi2: tuple[int, int, int, int] | None = None
        if raw.has_rectification:
            R1, R2, P1, P2 = raw.R1, raw.R2, raw.P1, raw.P2
        else:
            a = raw.alpha if alpha is None else alpha
            R1, R2, P1, P2, Q, roi1, roi2 = cv2.stereoRectify(
                raw.K1, raw.D1, raw.K2, raw.D2, size, raw.R, raw.T,
                flags=cv2.CALIB_ZERO_DISPARITY, alpha=float(a), newImageSize=size,
            )
            self.Q, self.roi1, self.roi2 = Q, tuple(roi1), tuple(roi2)
        self.R1, self.R2 = np.asarray(R1, np.float64), np.asarray(R2, np.float64)
        self.P1, self.P2 = np.asarray(P1, np.float64).reshape(3, 4), np.asarray(P2, np.float64).reshape(3, 4)
        src = raw.source
        if abs(self.P2[1, 3]) > abs(self.P2[0, 3]):
            raise CalibrationError("the cameras are stacked vertically; only horizontal stereo is supported", src)
        K = self.P1[:, :3].copy()
        if not np.allclose(K, self.P2[:, :3], rtol=1e-6, atol=1e-6):
            raise CalibrationError("rectified projections P1/P2 have different intrinsics", src)
        baseline = -self.P2[0, 3] / self.P2[0, 0]
        if not baseline > 0:
            raise CalibrationError(
                f"rectified baseline is {baseline:.4f} m: the right camera is not to the right of the left one "
                "(left and right swapped?)",
                src,
            )
        self.calibration = StereoCalibration(K=K, baseline=float(baseline), width=size[0], height=size[1])
        self.map_left = cv2.initUndistortRectifyMap(raw.K1, raw.D1, self.R1, self.P1, size, map_type)
        self.map_right = cv2.initUndistortRectifyMap(raw.K2, raw.D2, self.R2, self.P2, size, map_type)

    @property
    def size(self) -> tuple[int, int]:
        return self.raw.size

    def _check(self, img: np.ndarray, side: str) -> None:
        h, w = img.shape[:2]
        if (w, h) != self.raw.size:
            raise ValueError(f"{side} image is {w}x{h}, the calibration is for {self.raw.width}x{self.raw.height}")

    def rectify_left(self, img: np.ndarray) -> np.ndarray:
        self._check(img, "left")
        return cv2.remap(img, self.map_left[0], self.map_left[1], self.interpolation)

    def rectify_right(self, img: np.ndarray) -> np.ndarray:
        self._check(img, "right")
        return cv2.remap(img, self.map_right[0], self.map_right[1], self.interpolation)

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rectified ``(left, right)``; gray or colour, same dtype as given."""
        return self.rectify_left(left), self.rectify_right(right)

    def rectify_points(self, points: np.ndarray, side: str = "left") -> np.ndarray:
        """Raw pixel coordinates ``(N, 2)`` -> rectified pixel coordinates ``(N, 2)``."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 1, 2)
        if side == "left":
            K, D, R, P = self.raw.K1, self.raw.D1, self.R1, self.P1
        elif side == "right":
            K, D, R, P = self.raw.K2, self.raw.D2, self.R2, self.P2
        else:
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)  # accurate also near the borders
        return cv2.undistortPointsIter(pts, K, D, R, P, crit).reshape(-1, 2)
