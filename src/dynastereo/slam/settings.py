"""ORB-SLAM2 stereo settings files -> ``SlamConfig`` + ``StereoCalibration``.

An ORB-SLAM2 settings file (OpenCV FileStorage YAML, ``%YAML:1.0``) holds::

    Camera.fx, Camera.fy, Camera.cx, Camera.cy, Camera.bf   -> StereoCalibration
    Camera.width, Camera.height (else the images' size)
    Camera.fps                                              -> SlamConfig.max_frames
    ThDepth                                                 -> SlamConfig.th_depth
    ORBextractor.nFeatures / scaleFactor / nLevels / iniThFAST / minThFAST
                                                            -> n_features, scale_factor, ...

``dynastereo.config.load_config`` applies the same SLAM keys (one adapter,
``config.orbslam2_slam_values``) when such a file is given as the configuration; the file is read by ``dynastereo.io.calib`` (which also
handles ``LEFT.*`` / ``RIGHT.*`` rectification for raw input).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from ..config import SlamConfig, orbslam2_slam_values
from ..errors import ConfigError
from ..datatypes import StereoCalibration
from ..io.calib import RawStereoCalibration, load_orbslam2_settings, orbslam2_calibration


def slam_config_from_orbslam(
    settings: dict[str, Any], base: SlamConfig | None = None, path: str | Path | None = None
) -> SlamConfig:
    """``base`` (default ``SlamConfig()``) with the ORB-SLAM2 keys of ``settings`` applied
    (:func:`dynastereo.config.orbslam2_slam_values`)."""
    values = orbslam2_slam_values(settings, path)
    try:
        return dataclasses.replace(base or SlamConfig(), **values)  # validated again
    except ConfigError as e:
        if path is None or e.path is not None:
            raise
        raise ConfigError(str(e), path) from None


def load_orbslam_settings(
    path: str | Path, base: SlamConfig | None = None, image_size: tuple[int, int] | None = None
) -> tuple[SlamConfig, StereoCalibration]:
    """``(SlamConfig, rectified StereoCalibration)`` from an ORB-SLAM2 stereo settings file.

    Raises ``CalibrationError`` / ``ConfigError`` naming the file for a missing or bad key.
    A file with ``LEFT.*`` / ``RIGHT.*`` rectification describes *raw* cameras: open the
    sequence with it through ``dynastereo.io`` (which rectifies) and pass
    ``sequence.calibration`` to ``System`` instead.
    """
    p = Path(path)
    settings = load_orbslam2_settings(p)
    calib = orbslam2_calibration(settings, p, image_size)
    if isinstance(calib, RawStereoCalibration):
        raise ConfigError(
            "settings describe raw (unrectified) cameras (LEFT.*/RIGHT.*): open the sequence with them "
            "through dynastereo.io and use sequence.calibration",
            p,
        )
    return slam_config_from_orbslam(settings, base, p), calib
