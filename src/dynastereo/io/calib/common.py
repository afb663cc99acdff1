"""What every calibration reader shares: reading the file's text, and numbers, lists of
numbers, intrinsics and image sizes checked with a :class:`~dynastereo.errors.CalibrationError`
naming the file and the key."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...errors import CalibrationError


def _read_calib_text(path: Path) -> str:
    """The text of a calibration file; CalibrationError naming it when missing or unreadable."""
    if not path.is_file():
        raise CalibrationError("calibration file not found" if not path.exists() else "not a file", path)
    try:
        return path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise CalibrationError(f"cannot read: {e.strerror}", path) from None


def _is_float(t: str) -> bool:
    try:
        float(t)
        return True
    except ValueError:
        return False


def _number(value: Any, key: str, path: Path) -> float:
    if isinstance(value, bool) or value is None:
        raise CalibrationError(f"key '{key}': expected a number, got {value!r}", path)
    if isinstance(value, np.ndarray) and value.size == 1:
        value = value.reshape(-1)[0]
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise CalibrationError(f"key '{key}': expected a number, got {value!r}", path) from None
    if not np.isfinite(v):
        raise CalibrationError(f"key '{key}': expected a finite number, got {value!r}", path)
    return v


def _numbers(value: Any, key: str, path: Path, sizes: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise CalibrationError(f"key '{key}': expected a list of numbers, got {value!r}", path) from None
    if a.size not in sizes:
        want = " or ".join(str(s) for s in sizes)
        raise CalibrationError(f"key '{key}': expected {want} numbers, got {a.size}", path)
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"key '{key}': contains non-finite values", path)
    return a


def _intrinsics(value: Any, key: str, path: Path) -> np.ndarray:
    a = _numbers(value, key, path, (4, 9))
    if a.size == 4:
        fx, fy, cx, cy = a
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
    else:
        K = a.reshape(3, 3)
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError(f"key '{key}': focal lengths must be positive", path)
    return K


def _size_from(d: dict[str, Any], wkey: str, hkey: str, path: Path,
               image_size: tuple[int, int] | None) -> tuple[int, int]:
    if wkey in d and hkey in d:
        w, h = int(_number(d[wkey], wkey, path)), int(_number(d[hkey], hkey, path))
        if w <= 0 or h <= 0:
            raise CalibrationError(f"image size must be positive, got {wkey}={w}, {hkey}={h}", path)
        return w, h
    if image_size is not None:
        return int(image_size[0]), int(image_size[1])
    raise CalibrationError(f"keys '{wkey}' and '{hkey}' (image size) are missing", path)
