"""**Middlebury 2014** ``calib.txt`` (``cam0=[...]``, ``baseline`` in mm, ``doffs``...):
:func:`load_middlebury_calib`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...datatypes import StereoCalibration
from ...errors import CalibrationError
from .common import _number


@dataclass(frozen=True)
class MiddleburyCalibration:
    """Middlebury 2014 ``calib.txt``: rectified pair with a principal-point offset ``doffs``.

    ``depth = baseline * fx / (disparity + doffs)``; ``calibration`` is cam0's ``K`` with the
    baseline in metres (the file gives millimetres).
    """

    calibration: StereoCalibration
    K1: np.ndarray
    doffs: float
    ndisp: int
    vmin: float | None = None
    vmax: float | None = None


def load_middlebury_calib(path: str | Path) -> MiddleburyCalibration:
    path = Path(path)
    if not path.is_file():
        raise CalibrationError("calibration file not found" if not path.exists() else "not a file", path)
    vals: dict[str, str] = {}
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        key, sep, rest = s.partition("=")
        if not sep:
            raise CalibrationError(f"line {lineno} is not 'key=value': {s[:60]!r}", path)
        vals[key.strip()] = rest.strip()

    def mat(key: str) -> np.ndarray:
        if key not in vals:
            raise CalibrationError(f"key '{key}' is missing", path)
        toks = vals[key].strip("[]").replace(";", " ").split()
        try:
            a = np.array([float(t) for t in toks], dtype=np.float64)
        except ValueError:
            raise CalibrationError(f"key '{key}': not a 3x3 matrix of numbers: {vals[key]!r}", path) from None
        if a.size != 9:
            raise CalibrationError(f"key '{key}': expected 9 numbers, got {a.size}", path)
        return a.reshape(3, 3)

    def num(key: str, required: bool = True) -> float | None:
        if key not in vals:
            if required:
                raise CalibrationError(f"key '{key}' is missing", path)
            return None
        return _number(vals[key], key, path)

    K0, K1 = mat("cam0"), mat("cam1")
    baseline_mm = num("baseline")
    calib = StereoCalibration(K=K0, baseline=float(baseline_mm) / 1000.0, width=int(num("width")),
                              height=int(num("height")))
    return MiddleburyCalibration(calibration=calib, K1=K1, doffs=float(num("doffs")), ndisp=int(num("ndisp")),
                                 vmin=num("vmin", False), vmax=num("vmax", False))
