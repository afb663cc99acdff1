"""Generic YAML calibration of a pair of image folders (:func:`load_stereo_yaml`):
dynastereo's own format (rectified or raw; the module doc of :mod:`dynastereo.io.calib`)
or an ORB-SLAM2 settings file (:mod:`.orbslam2`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ...datatypes import StereoCalibration
from ...errors import CalibrationError
from .common import _intrinsics, _number, _numbers, _size_from
from .opencv_yaml import read_yaml_file
from .orbslam2 import is_orbslam2_settings, load_orbslam2_settings, orbslam2_calibration
from .raw import RawStereoCalibration

_OWN_RECTIFIED_KEYS = {"fx", "fy", "cx", "cy", "baseline", "bf", "width", "height"}
_OWN_RAW_KEYS = {"left", "right", "R", "T", "width", "height", "alpha"}


def load_stereo_yaml(path: str | Path,
                     image_size: tuple[int, int] | None = None) -> StereoCalibration | RawStereoCalibration:
    """Calibration from a generic YAML file: dynastereo's format or ORB-SLAM2 settings (module doc).

    ``image_size`` (``(width, height)`` of the images, if known) fills in a missing size.
    """
    path = Path(path)
    d = read_yaml_file(path)
    if is_orbslam2_settings(d):
        return orbslam2_calibration(load_orbslam2_settings(path), path, image_size)
    if "left" in d or "right" in d:
        return _own_raw(d, path, image_size)
    if "fx" in d:
        return _own_rectified(d, path, image_size)
    raise CalibrationError(
        "unrecognized calibration YAML: expected 'fx, cx, cy, baseline' (rectified), "
        "'left: {K, D}, right: {K, D}, R, T' (raw) or an ORB-SLAM2 settings file with 'Camera.fx'; "
        f"found keys {', '.join(map(str, d)) or 'none'}",
        path,
    )


def _check_keys(d: dict[str, Any], allowed: set[str], path: Path, form: str) -> None:
    unknown = [str(k) for k in d if k not in allowed]
    if unknown:
        raise CalibrationError(
            f"unknown key(s) {', '.join(unknown)} in the {form} form (allowed: {', '.join(sorted(allowed))})", path
        )


def _own_rectified(d: dict[str, Any], path: Path, image_size: tuple[int, int] | None) -> StereoCalibration:
    _check_keys(d, _OWN_RECTIFIED_KEYS, path, "rectified")
    for key in ("cx", "cy"):
        if key not in d:
            raise CalibrationError(f"key '{key}' is missing (rectified form)", path)
    fx = _number(d["fx"], "fx", path)
    fy = _number(d.get("fy", fx), "fy", path)
    cx, cy = _number(d["cx"], "cx", path), _number(d["cy"], "cy", path)
    if not (fx > 0 and fy > 0):
        raise CalibrationError(f"focal lengths must be positive (fx={fx}, fy={fy})", path)
    if "baseline" in d:
        baseline = _number(d["baseline"], "baseline", path)
    elif "bf" in d:
        baseline = _number(d["bf"], "bf", path) / fx
    else:
        raise CalibrationError("key 'baseline' (metres) or 'bf' (baseline * fx) is missing", path)
    if not baseline > 0:
        raise CalibrationError(f"baseline must be positive, got {baseline}", path)
    w, h = _size_from(d, "width", "height", path, image_size)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
    return StereoCalibration(K=K, baseline=baseline, width=w, height=h)


def _own_raw(d: dict[str, Any], path: Path, image_size: tuple[int, int] | None) -> RawStereoCalibration:
    _check_keys(d, _OWN_RAW_KEYS, path, "raw")
    cams = []
    for side in ("left", "right"):
        c = d.get(side)
        if not isinstance(c, dict):
            raise CalibrationError(f"key '{side}' must be a mapping with K (and D), got {c!r}", path)
        unknown = [str(k) for k in c if k not in ("K", "D")]
        if unknown:
            raise CalibrationError(f"unknown key(s) {', '.join(unknown)} under '{side}' (allowed: K, D)", path)
        if "K" not in c:
            raise CalibrationError(f"key '{side}.K' is missing", path)
        K = _intrinsics(c["K"], f"{side}.K", path)
        D = _numbers(c.get("D", [0.0] * 5), f"{side}.D", path, (0, 4, 5, 8, 12, 14))
        cams.append((K, D))
    for key in ("R", "T"):
        if key not in d:
            raise CalibrationError(f"key '{key}' is missing (raw form: rotation and translation left -> right)", path)
    r = _numbers(d["R"], "R", path, (3, 9))
    R = cv2.Rodrigues(r.reshape(3, 1))[0] if r.size == 3 else r.reshape(3, 3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
        raise CalibrationError("key 'R' is not a rotation matrix (R R^T != I or det < 0)", path)
    T = _numbers(d["T"], "T", path, (3,))
    if not T[0] < 0:
        raise CalibrationError(
            f"key 'T': the right camera must be to the right of the left one (T[0] < 0, metres), got {T.tolist()}",
            path,
        )
    w, h = _size_from(d, "width", "height", path, image_size)
    alpha = _number(d.get("alpha", 0.0), "alpha", path)
    return RawStereoCalibration(K1=cams[0][0], D1=cams[0][1], K2=cams[1][0], D2=cams[1][1], width=w, height=h,
                                R=R, T=T, alpha=alpha, source=path)
