"""ORB-SLAM2 stereo settings files (OpenCV FileStorage YAML, first line ``%YAML:1.0``):
``Camera.fx, Camera.fy, Camera.cx, Camera.cy, Camera.bf`` and ``Camera.width/height`` for
rectified images; with ``LEFT.K, LEFT.D, LEFT.R, LEFT.P`` and ``RIGHT.*`` (``!!opencv-matrix``),
as in ORB-SLAM2's ``EuRoC.yaml``, the images are raw and are rectified with exactly those R/P
(like ORB-SLAM2 does).  ORB-SLAM2 itself ignores ``Camera.width/height`` for stereo and uses
the images' size; so do we when the images are at hand.  :func:`load_orbslam2_settings`
returns every key of such a file (``ThDepth``, ``ORBextractor.*``...) as a flat dict.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...datatypes import StereoCalibration
from ...errors import CalibrationError
from .common import _number, _numbers, _size_from
from ...dotted import flatten_dotted
from .opencv_yaml import read_yaml_file
from .raw import RawStereoCalibration


def load_orbslam2_settings(path: str | Path) -> dict[str, Any]:
    """Every key of an ORB-SLAM2 settings file, flat as written (``"Camera.fx"``, ``"ThDepth"``,
    ``"ORBextractor.nFeatures"``, ``"LEFT.K"`` -> 3x3 ``np.ndarray`` ...)."""
    path = Path(path)
    flat = flatten_dotted(read_yaml_file(path))  # files written as nested maps are flattened with dots
    if "Camera.fx" not in flat:
        raise CalibrationError("not an ORB-SLAM2 settings file: key 'Camera.fx' is missing", path)
    return flat


def is_orbslam2_settings(d: dict[str, Any]) -> bool:
    return "Camera.fx" in d or ("Camera" in d and isinstance(d["Camera"], dict) and "fx" in d["Camera"])


def orbslam2_calibration(settings: dict[str, Any], path: str | Path,
                         image_size: tuple[int, int] | None = None) -> StereoCalibration | RawStereoCalibration:
    """Calibration from ORB-SLAM2 settings (see :func:`load_orbslam2_settings`).

    Without ``LEFT.*``/``RIGHT.*``: rectified ``StereoCalibration`` (size = ``image_size`` if given,
    as ORB-SLAM2 reads it from the images, else ``Camera.width/height``).  With them: a
    ``RawStereoCalibration`` carrying ``LEFT.R/P`` and ``RIGHT.R/P`` as the rectification.
    """
    path = Path(path)
    s = settings
    for key in ("Camera.fx", "Camera.fy", "Camera.cx", "Camera.cy", "Camera.bf"):
        if key not in s:
            raise CalibrationError(f"key '{key}' is missing (ORB-SLAM2 stereo settings)", path)
    fx, fy, cx, cy, bf = (_number(s[k], k, path) for k in
                          ("Camera.fx", "Camera.fy", "Camera.cx", "Camera.cy", "Camera.bf"))
    if not (fx > 0 and fy > 0):
        raise CalibrationError(f"focal lengths must be positive (Camera.fx={fx}, Camera.fy={fy})", path)
    if not bf > 0:
        raise CalibrationError(f"key 'Camera.bf' must be positive (baseline * fx), got {bf}", path)
    rect_keys = [f"{side}.{m}" for side in ("LEFT", "RIGHT") for m in ("K", "D", "R", "P")]
    present = [k for k in rect_keys if k in s]
    if not present:
        if image_size is not None:
            w, h = int(image_size[0]), int(image_size[1])
        else:
            w, h = _size_from(s, "Camera.width", "Camera.height", path, None)
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
        return StereoCalibration(K=K, baseline=bf / fx, width=w, height=h)
    missing = [k for k in rect_keys if k not in s]
    if missing:
        raise CalibrationError(f"rectification keys {', '.join(missing)} are missing (found {', '.join(present)})",
                               path)
    mats: dict[str, np.ndarray] = {}
    for k, sizes in (("K", (9,)), ("D", (4, 5, 8)), ("R", (9,)), ("P", (12,))):
        for side in ("LEFT", "RIGHT"):
            mats[f"{side}.{k}"] = _numbers(s[f"{side}.{k}"], f"{side}.{k}", path, sizes)
    if "LEFT.width" in s and "LEFT.height" in s:
        w, h = _size_from(s, "LEFT.width", "LEFT.height", path, None)
    else:  # the raw size: ORB-SLAM2 rectifies to LEFT.width/height; fall back to Camera.* or the images
        w, h = _size_from(s, "Camera.width", "Camera.height", path, image_size)
    if "RIGHT.width" in s and "RIGHT.height" in s:
        if _size_from(s, "RIGHT.width", "RIGHT.height", path, None) != (w, h):
            raise CalibrationError("LEFT.width/height and RIGHT.width/height differ", path)
    P1 = mats["LEFT.P"].reshape(3, 4)
    P2 = mats["RIGHT.P"].reshape(3, 4)
    if not np.allclose([P1[0, 0], P1[1, 1], P1[0, 2], P1[1, 2]], [fx, fy, cx, cy], rtol=1e-4, atol=1e-3):
        raise CalibrationError(
            "Camera.fx/fy/cx/cy must equal LEFT.P's intrinsics (the rectified camera): "
            f"{[fx, fy, cx, cy]} vs {[P1[0, 0], P1[1, 1], P1[0, 2], P1[1, 2]]}",
            path,
        )
    if not (P2[0, 3] < 0):
        raise CalibrationError(f"RIGHT.P[0,3] must be -bf (negative), got {P2[0, 3]}", path)
    return RawStereoCalibration(
        K1=mats["LEFT.K"].reshape(3, 3), D1=mats["LEFT.D"], K2=mats["RIGHT.K"].reshape(3, 3), D2=mats["RIGHT.D"],
        width=w, height=h, R1=mats["LEFT.R"].reshape(3, 3), R2=mats["RIGHT.R"].reshape(3, 3), P1=P1, P2=P2,
        source=path,
    )
