"""KITTI odometry sequences in the official layout.

::

    sequences/06/
        calib.txt        P0..P3 (some copies hold only P0 and P1)
        times.txt        optional: one timestamp (s) per frame
        image_0/ image_1/    gray left / right   (000000.png ...)
        image_2/ image_3/    colour left / right

Pass the sequence folder itself (``.../sequences/06``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import SequenceError
from .calib import load_kitti_calib, load_stereo_yaml
from .images import image_size
from .sequence import ImagePairSequence, list_image_pairs
from .times import DEFAULT_RATE_HZ, check_rate, read_times

log = logging.getLogger(__name__)


def kitti_image_dirs(path: Path, color: bool | None) -> tuple[Path, Path, bool] | None:
    """``(left_dir, right_dir, uses_colour_pair)`` for a KITTI sequence folder, or None.

    ``color=True`` needs image_2/image_3.  ``color=False`` or ``None`` prefers image_0/image_1
    and falls back to image_2/image_3 (calibrated with P2/P3) when only those exist.
    """
    gray = (path / "image_0", path / "image_1")
    colour = (path / "image_2", path / "image_3")
    if not color and gray[0].is_dir() and gray[1].is_dir():
        return gray[0], gray[1], False
    if colour[0].is_dir() and colour[1].is_dir():
        return colour[0], colour[1], True
    return None


class KittiSequence(ImagePairSequence):
    """A KITTI odometry sequence (already rectified: frames are returned as stored).

    ``color=None`` (the default, auto): the gray pair ``image_0``/``image_1`` with P0/P1 when
    present, gray frames; else the colour pair ``image_2``/``image_3`` with P2/P3, BGR frames.
    ``color=False``: the same pairs, always gray frames (a colour-only folder read as gray).
    ``color=True``: the colour pair ``image_2``/``image_3`` with P2/P3, as BGR (an error
    when it is absent).  ``uses_colour_pair`` says which pair was chosen.

    Timestamps come from ``times.txt`` when present (indexed by the frame number in the
    file name, so a folder holding the first N frames of a sequence can use the full
    ``times.txt``); without it they are ``frame_number / rate`` s (``rate`` None: KITTI's
    ~10 Hz).  ``timestamp_source`` says which.

    ``calib``: an optional YAML calibration (see :func:`~dynastereo.io.calib.load_stereo_yaml`)
    used instead of ``calib.txt``.
    """

    def __init__(self, path: str | Path, color: bool | None = None, calib: str | Path | None = None,
                 rate: float | None = None) -> None:
        path = Path(path)
        if not path.is_dir():
            raise SequenceError("KITTI sequence folder not found", path)
        dirs = kitti_image_dirs(path, color)
        if dirs is None:
            want = ("image_2/ and image_3/ (colour pair)" if color is True
                    else "image_0/ and image_1/ (or image_2/ and image_3/)")
            raise SequenceError(f"not a KITTI sequence folder: {want} not found", path)
        left_dir, right_dir, colour_pair = dirs
        left, right = list_image_pairs(left_dir, right_dir, path)
        size = image_size(left[0])
        if calib is not None:
            calibration = load_stereo_yaml(calib, size)
            calib_path = Path(calib)
        else:
            calib_path = path / "calib.txt"
            calibration = load_kitti_calib(calib_path, size, color=colour_pair)
        self.times_path: Path | None = path / "times.txt" if (path / "times.txt").is_file() else None
        numbers = _frame_numbers(left)
        rate = check_rate(rate)
        times = _kitti_times(self.times_path, numbers, rate or DEFAULT_RATE_HZ)
        if self.times_path is not None:
            source = "times.txt"
        else:
            source = f"rate {rate:g} Hz (given)" if rate else f"rate {DEFAULT_RATE_HZ:g} Hz (KITTI's, assumed)"
        self.uses_colour_pair = colour_pair
        super().__init__(
            name=path.name,
            path=path,
            left_paths=left,
            right_paths=right,
            timestamps=times,
            calibration=calibration,
            color=colour_pair if color is None else bool(color),
            calib_path=calib_path,
            left_dir=left_dir,
            right_dir=right_dir,
            timestamp_source=source,
            numbers=numbers,
        )
        if self.missing_frames:
            miss = self.missing_frames
            shown = ", ".join(f"{i:06d}" for i in miss[:5]) + (", ..." if len(miss) > 5 else "")
            log.warning("%s: the image numbering has %d gap(s) (%s missing): every frame keeps its own number "
                        "and stamp in the outputs; --frames counts the images there are", left_dir, len(miss), shown)


def _frame_numbers(paths: list[Path]) -> np.ndarray:
    """Frame numbers from KITTI file names (000123.png -> 123); positions if not all numeric."""
    stems = [p.stem for p in paths]
    if all(s.isdigit() for s in stems):
        return np.array([int(s) for s in stems], dtype=np.int64)
    return np.arange(len(paths), dtype=np.int64)


def _kitti_times(times_path: Path | None, numbers: np.ndarray, rate: float) -> np.ndarray:
    if times_path is None:
        return numbers.astype(np.float64) / rate
    t = read_times(times_path)
    if len(t) <= int(numbers.max()):
        raise SequenceError(
            f"{len(t)} timestamps, but the images go up to frame {int(numbers.max())} "
            f"({len(numbers)} images)",
            times_path,
        )
    return t[numbers]
