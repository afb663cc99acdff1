"""**EuRoC** ``mav0/cam0/sensor.yaml`` + ``mav0/cam1/sensor.yaml``: ``T_BS`` (camera to
body, 4x4), ``intrinsics: [fu, fv, cu, cv]``, ``distortion_model: radial-tangential``,
``distortion_coefficients: [k1, k2, p1, p2]``, ``resolution: [w, h]``.  The camera-to-camera
pose is ``T_21 = inv(T_BS_cam1) @ T_BS_cam0``.  See :func:`load_euroc_calib`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...errors import CalibrationError
from .common import _intrinsics, _numbers
from .opencv_yaml import read_yaml_file
from .raw import RawStereoCalibration


def euroc_T_BS(sensor: dict[str, Any], path: str | Path) -> np.ndarray:
    """The camera's pose in the body frame, ``T_BS`` (4x4), of a EuRoC ``sensor.yaml`` read by
    :func:`~.opencv_yaml.read_yaml_file` (``path``: that file, named in errors)."""
    if "T_BS" not in sensor:
        raise CalibrationError("key 'T_BS' is missing (EuRoC sensor.yaml)", path)
    T = sensor["T_BS"]
    T_data = T.get("data") if isinstance(T, dict) else T
    return _numbers(T_data, "T_BS.data", Path(path), (16,)).reshape(4, 4)


def read_euroc_T_BS(path: str | Path) -> np.ndarray:
    """``T_BS`` (4x4, camera to body) of a EuRoC ``sensor.yaml`` file."""
    return euroc_T_BS(read_yaml_file(path), path)


def _euroc_camera(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    d = read_yaml_file(path)
    for key in ("T_BS", "intrinsics", "resolution"):
        if key not in d:
            raise CalibrationError(f"key '{key}' is missing (EuRoC sensor.yaml)", path)
    model = d.get("camera_model", "pinhole")
    if model != "pinhole":
        raise CalibrationError(f"camera_model {model!r} is not supported (only 'pinhole')", path)
    dist_model = d.get("distortion_model", "radial-tangential")
    if dist_model not in ("radial-tangential", "radtan", "plumb_bob"):
        raise CalibrationError(
            f"distortion_model {dist_model!r} is not supported (only 'radial-tangential')", path
        )
    T_BS = euroc_T_BS(d, path)
    K = _intrinsics(d["intrinsics"], "intrinsics", path)
    D = _numbers(d.get("distortion_coefficients", [0, 0, 0, 0]), "distortion_coefficients", path, (4, 5, 8))
    res = _numbers(d["resolution"], "resolution", path, (2,))
    return T_BS, K, D, (int(res[0]), int(res[1]))


def load_euroc_calib(cam0_yaml: str | Path, cam1_yaml: str | Path) -> RawStereoCalibration:
    """Raw stereo calibration from EuRoC's ``cam0/sensor.yaml`` (left) and ``cam1/sensor.yaml`` (right)."""
    p0, p1 = Path(cam0_yaml), Path(cam1_yaml)
    T0, K1, D1, size0 = _euroc_camera(p0)
    T1, K2, D2, size1 = _euroc_camera(p1)
    if size0 != size1:
        raise CalibrationError(f"resolution {size1} differs from {p0}'s {size0}", p1)
    T_21 = np.linalg.inv(T1) @ T0  # left camera -> right camera
    R, t = T_21[:3, :3], T_21[:3, 3]
    if not t[0] < 0:
        raise CalibrationError(
            f"cam1 is not to the right of cam0 (translation cam0->cam1 = {np.round(t, 4).tolist()})", p1
        )
    return RawStereoCalibration(K1=K1, D1=D1, K2=K2, D2=D2, width=size0[0], height=size0[1], R=R, T=t,
                                source=p0.parent.parent)
