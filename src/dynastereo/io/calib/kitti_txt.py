"""**KITTI** ``calib.txt`` (odometry and object benchmarks): labelled rows
``P0: <12 numbers>`` ... ``P3: ...`` (3x4 row-major projection matrices of the rectified
cameras).  Other rows (``Tr``, ``R0_rect``, ``Tr_velo_to_cam`` ...) are ignored.  The gray
pair ``image_0``/``image_1`` uses P0/P1, the colour pair ``image_2``/``image_3`` P2/P3;
``baseline = (Pl[0,3] - Pr[0,3]) / fx``.  See :func:`load_kitti_calib`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...datatypes import StereoCalibration
from ...errors import CalibrationError
from .common import _is_float, _read_calib_text


def read_kitti_calib_rows(path: str | Path) -> dict[str, list[str]]:
    """The labelled rows of a KITTI ``calib.txt`` as raw tokens: ``{"P0": ["7.07e+02", ...], ...}``.

    Blank lines and ``#`` comments are skipped; a non-empty line without ``NAME:`` is an error.
    """
    path = Path(path)
    text = _read_calib_text(path)
    rows: dict[str, list[str]] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        key, sep, rest = s.partition(":")
        if not sep or not key.strip() or " " in key.strip():
            raise CalibrationError(f"line {lineno} is not a labelled row 'NAME: numbers': {s[:60]!r}", path)
        rows[key.strip()] = rest.split()
    return rows


def _kitti_matrix(rows: dict[str, list[str]], key: str, path: Path, needed_for: str) -> np.ndarray:
    if key not in rows:
        found = ", ".join(rows) or "none"
        raise CalibrationError(f"no row '{key}:' (needed for {needed_for}); rows found: {found}", path)
    toks = rows[key]
    if len(toks) != 12:
        raise CalibrationError(f"row '{key}' has {len(toks)} numbers, expected 12 (a 3x4 projection matrix)", path)
    try:
        vals = [float(t) for t in toks]
    except ValueError:
        bad = next(t for t in toks if not _is_float(t))
        raise CalibrationError(f"row '{key}': {bad!r} is not a number", path) from None
    P = np.array(vals, dtype=np.float64).reshape(3, 4)
    if not np.all(np.isfinite(P)):
        raise CalibrationError(f"row '{key}' contains non-finite values", path)
    return P


def kitti_projections(path: str | Path, color: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(P_left, P_right)`` 3x4 for the gray (P0, P1) or colour (P2, P3) pair."""
    path = Path(path)
    rows = read_kitti_calib_rows(path)
    kl, kr = ("P2", "P3") if color else ("P0", "P1")
    pair = "the colour pair image_2/image_3" if color else "the gray pair image_0/image_1"
    return _kitti_matrix(rows, kl, path, pair), _kitti_matrix(rows, kr, path, pair)


def load_kitti_calib(path: str | Path, image_size: tuple[int, int], color: bool = False) -> StereoCalibration:
    """Rectified calibration from a KITTI ``calib.txt``.

    ``image_size`` is ``(width, height)`` of the images (the file does not hold it);
    ``color`` selects P2/P3 (image_2/image_3) instead of P0/P1 (image_0/image_1).
    """
    path = Path(path)
    Pl, Pr = kitti_projections(path, color)
    kl, kr = ("P2", "P3") if color else ("P0", "P1")
    return _rectified_pair(Pl, Pr, kl, kr, path, image_size)


def _rectified_pair(Pl: np.ndarray, Pr: np.ndarray, kl: str, kr: str, path: Path,
                    image_size: tuple[int, int]) -> StereoCalibration:
    """``StereoCalibration`` of a rectified pair from its two 3x4 projections (rows ``kl``, ``kr``)."""
    K, Kr = Pl[:, :3], Pr[:, :3]
    fx = K[0, 0]
    if not (fx > 0 and K[1, 1] > 0):
        raise CalibrationError(f"row '{kl}': focal lengths must be positive (fx={fx}, fy={K[1, 1]})", path)
    if not np.allclose(K, Kr, rtol=1e-6, atol=1e-6):
        raise CalibrationError(f"rows '{kl}' and '{kr}' have different intrinsics: not a rectified pair", path)
    baseline = (Pl[0, 3] - Pr[0, 3]) / fx
    if not baseline > 0:
        raise CalibrationError(
            f"baseline from rows '{kl}'/'{kr}' is {baseline:.4f} m; the right camera must be to the right "
            f"({kr}[0,3] < {kl}[0,3])",
            path,
        )
    w, h = image_size
    return StereoCalibration(K=K.copy(), baseline=float(baseline), width=int(w), height=int(h))
