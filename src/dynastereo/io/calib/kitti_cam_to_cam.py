"""**KITTI raw** ``calib_cam_to_cam.txt`` (in a drive's date folder): labelled rows
``P_rect_00: <12 numbers>`` ... ``P_rect_03`` (rectified projections, all from rectified
camera 0's frame) and ``S_rect_00: <width> <height>`` ... (rectified image sizes), beside
the raw ``K_0x``/``D_0x``/``R_0x``/``T_0x`` (unused).  Gray pair 00/01, colour pair 02/03.
See :func:`load_kitti_raw_calib`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...datatypes import StereoCalibration
from ...errors import CalibrationError
from .common import _is_float
from .kitti_txt import _kitti_matrix, _rectified_pair, read_kitti_calib_rows

#: The two stereo pairs of a KITTI raw drive: camera numbers (left, right).
KITTI_RAW_GRAY_PAIR: tuple[str, str] = ("00", "01")
KITTI_RAW_COLOUR_PAIR: tuple[str, str] = ("02", "03")


def kitti_raw_projections(path: str | Path, color: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(P_rect_left, P_rect_right)`` 3x4 of a KITTI raw ``calib_cam_to_cam.txt``: the gray
    pair (``P_rect_00``/``P_rect_01``) or the colour pair (``P_rect_02``/``P_rect_03``)."""
    path = Path(path)
    rows = read_kitti_calib_rows(path)
    cl, cr = KITTI_RAW_COLOUR_PAIR if color else KITTI_RAW_GRAY_PAIR
    pair = f"the {'colour' if color else 'gray'} pair image_{cl}/image_{cr}"
    prows = {k: v for k, v in rows.items() if k.startswith("P_rect")}  # "rows found" lists these only
    return _kitti_matrix(prows, f"P_rect_{cl}", path, pair), _kitti_matrix(prows, f"P_rect_{cr}", path, pair)


def _kitti_raw_size(rows: dict[str, list[str]], key: str, path: Path) -> tuple[int, int] | None:
    """``(width, height)`` from a ``S_..`` row (two numbers, e.g. ``1.242000e+03 3.750000e+02``); None if absent."""
    if key not in rows:
        return None
    toks = rows[key]
    try:
        vals = [float(t) for t in toks]
    except ValueError:
        bad = next(t for t in toks if not _is_float(t))
        raise CalibrationError(f"row '{key}': {bad!r} is not a number", path) from None
    if len(vals) != 2 or not all(np.isfinite(vals)) or min(vals) <= 0 or any(v != round(v) for v in vals):
        raise CalibrationError(f"row '{key}' must hold two positive whole numbers (width height), got {toks}", path)
    return int(vals[0]), int(vals[1])


def load_kitti_raw_calib(path: str | Path, image_size: tuple[int, int], color: bool = False,
                         image_path: str | Path | None = None) -> StereoCalibration:
    """Rectified calibration of a KITTI raw drive from its date folder's ``calib_cam_to_cam.txt``.

    ``color=False``: the gray pair ``image_00``/``image_01`` (``P_rect_00``/``P_rect_01``);
    ``color=True``: the colour pair ``image_02``/``image_03`` (``P_rect_02``/``P_rect_03``).
    The P_rect matrices all project from the rectified camera 0's frame, so the baseline is
    ``(P_rect_l[0,3] - P_rect_r[0,3]) / fx`` (for the gray pair ``-P_rect_01[0,3] / fx``).
    ``image_size`` (``(width, height)`` of the images, ``image_path`` one of them, named in
    errors) must match the rows ``S_rect_0x`` (rectified size) when the file holds them.
    """
    path = Path(path)
    rows = read_kitti_calib_rows(path)
    cl, cr = KITTI_RAW_COLOUR_PAIR if color else KITTI_RAW_GRAY_PAIR
    Pl, Pr = kitti_raw_projections(path, color)
    iw, ih = int(image_size[0]), int(image_size[1])
    what = f"the images ({image_path})" if image_path is not None else "the images"
    for cam in (cl, cr):
        s = _kitti_raw_size(rows, f"S_rect_{cam}", path)
        if s is not None and s != (iw, ih):
            raw = _kitti_raw_size(rows, f"S_{cam}", path)
            hint = ("; they have the unrectified size S_" + cam + ": only rectified drives (*_sync) can be read"
                    if raw == (iw, ih) else "")
            raise CalibrationError(
                f"row 'S_rect_{cam}' gives the rectified size {s[0]}x{s[1]}, {what} are {iw}x{ih}{hint}", path
            )
    return _rectified_pair(Pl, Pr, f"P_rect_{cl}", f"P_rect_{cr}", path, (iw, ih))
