"""Sanity of a calibration against the images it is used with."""

from __future__ import annotations

from pathlib import Path

from ...datatypes import StereoCalibration
from ...errors import CalibrationError
from .raw import RawStereoCalibration

#: rectification with a free scaling moves it a little); farther out is a typo.
PRINCIPAL_POINT_MARGIN = 0.1
#: fx / fy outside [1/FOCAL_RATIO_MAX, FOCAL_RATIO_MAX] is no camera of this project.
FOCAL_RATIO_MAX = 1.5


def check_intrinsics(calibration: "StereoCalibration | RawStereoCalibration", size: tuple[int, int],
                     source: str | Path | None) -> None:
    """CalibrationError naming ``source`` and the value when a camera's principal point
    lies outside the ``size`` = ``(width, height)`` image by more than
    :data:`PRINCIPAL_POINT_MARGIN` of its size, or its fx/fy ratio is beyond
    :data:`FOCAL_RATIO_MAX` -- a calibration that would track, drifting, without a word."""
    w, h = size
    if isinstance(calibration, RawStereoCalibration):
        cams = (("left K", calibration.K1), ("right K", calibration.K2))
    else:
        cams = (("", calibration.K),)
    mx, my = PRINCIPAL_POINT_MARGIN * w, PRINCIPAL_POINT_MARGIN * h
    for label, K in cams:
        fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        where = f"{label}: " if label else ""
        if not (-mx <= cx <= w + mx and -my <= cy <= h + my):
            raise CalibrationError(
                f"{where}principal point cx={cx:g}, cy={cy:g} lies outside the {w}x{h} image (allowed "
                f"cx {-mx:g}..{w + mx:g}, cy {-my:g}..{h + my:g}: a margin of {PRINCIPAL_POINT_MARGIN:.0%})", source)
        if not 1 / FOCAL_RATIO_MAX <= fx / fy <= FOCAL_RATIO_MAX:
            raise CalibrationError(
                f"{where}fx={fx:g}, fy={fy:g}: the ratio fx/fy={fx / fy:.3g} is outside "
                f"{1 / FOCAL_RATIO_MAX:.3g}..{FOCAL_RATIO_MAX:g} (pixels that far from square are a typo)", source)
