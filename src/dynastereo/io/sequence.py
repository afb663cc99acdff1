"""Shared implementation of the :class:`~dynastereo.io.base.Sequence` protocol for a list of
image pairs on disk (KITTI, EuRoC and generic folders all reduce to this)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from ..errors import CalibrationError, SequenceError
from ..datatypes import StereoCalibration, StereoFrame
from .calib import RawStereoCalibration, check_intrinsics
from .images import image_size, list_images, read_image, significant_bits
from .rectify import Rectifier

log = logging.getLogger(__name__)


def is_colour_image(path: str | Path) -> bool:
    """Whether an image file holds colour: for PNG the header's colour type (RGB, RGBA or
    palette) and, if so, the first image decoded (three equal channels count as gray);
    other formats are decoded.  ImageReadError naming the file when it cannot be read."""
    path = Path(path)
    if path.suffix.lower() == ".png":
        image_size(path)  # checks the file and the PNG header
        with open(path, "rb") as f:
            head = f.read(26)
        if len(head) < 26 or head[25] not in (2, 3, 6):  # 0 gray, 4 gray + alpha
            return False
    img = read_image(path, True)
    return not (np.array_equal(img[:, :, 0], img[:, :, 1]) and np.array_equal(img[:, :, 0], img[:, :, 2]))


#: The smallest images dynastereo takes (width, height): the stereo matcher's block and
#: the ORB pyramid need room.
MIN_IMAGE_SIZE = (32, 16)
#: Baselines (m) outside this range get a warning; beyond ``BASELINE_REFUSED`` they are
#: refused (a baseline given in millimetres: 537.2 for KITTI's 0.537 m).
BASELINE_PLAUSIBLE = (0.01, 2.0)
BASELINE_REFUSED = (0.001, 10.0)


def check_plausible(calibration: object, raw_size: tuple[int, int], images: object, calib_path: object) -> None:
    """Refuse images too small to match and baselines that cannot be metres; warn (one
    line) about a baseline outside the usual 1 cm - 2 m."""
    w, h = raw_size
    if w < MIN_IMAGE_SIZE[0] or h < MIN_IMAGE_SIZE[1]:
        raise SequenceError(f"images are {w}x{h}; dynastereo needs at least {MIN_IMAGE_SIZE[0]}x{MIN_IMAGE_SIZE[1]}",
                            images if isinstance(images, (str, Path)) else None)
    b = getattr(calibration, "baseline", None)
    if b is None:
        return
    b = abs(float(b))
    where = f"{calib_path}: " if calib_path else ""
    if not BASELINE_REFUSED[0] <= b <= BASELINE_REFUSED[1]:
        hint = " (millimetres? the calibration wants metres)" if b > BASELINE_REFUSED[1] else ""
        raise CalibrationError(f"baseline {b:g} m is implausible{hint}; expected {BASELINE_PLAUSIBLE[0]:g}-"
                               f"{BASELINE_PLAUSIBLE[1]:g} m", calib_path if calib_path else None)
    if not BASELINE_PLAUSIBLE[0] <= b <= BASELINE_PLAUSIBLE[1]:
        log.warning("%sbaseline %.4g m is outside the usual %g-%g m: check the calibration's units", where, b,
                    *BASELINE_PLAUSIBLE)


def rectified_calibration(calibration: StereoCalibration | RawStereoCalibration, raw_size: tuple[int, int],
                          images: object, calib_path: Path | None = None
                          ) -> tuple[StereoCalibration, Rectifier | None]:
    """The rectified calibration of images of ``raw_size`` (``(width, height)``) and the
    :class:`Rectifier` that rectifies them on read (None when ``calibration`` is already
    rectified), after checking the intrinsics and the size (a CalibrationError naming
    ``calib_path`` and the ``images`` the size came from)."""
    check_intrinsics(calibration, raw_size, calib_path or getattr(calibration, "source", None))
    check_plausible(calibration, raw_size, images, calib_path or getattr(calibration, "source", None))
    if calibration.size != raw_size:
        raise CalibrationError(
            f"calibration is for {calibration.width}x{calibration.height} images, "
            f"the images ({images}) are {raw_size[0]}x{raw_size[1]}",
            calib_path or (calibration.source if isinstance(calibration, RawStereoCalibration) else None),
        )
    if isinstance(calibration, RawStereoCalibration):
        rectifier = Rectifier(calibration)
        return rectifier.calibration, rectifier
    return calibration, None


class ImagePairSequence:
    """Rectified stereo pairs read from two lists of image files.

    ``calibration`` is a rectified ``StereoCalibration`` (images used as they are) or a
    ``RawStereoCalibration`` (a :class:`Rectifier` is built once, frames are rectified on
    read).  At construction the pair lists are checked (same length) and, for PNG files,
    every image's size is read from its header and checked against the calibration, so a
    bad file is reported before processing starts; other formats are checked on read.

    ``color``: ``True`` BGR frames, ``False`` gray frames, ``None`` (auto) BGR when the first
    left image holds colour (see :func:`is_colour_image`), else gray.  ``self.color`` is the
    resolved ``bool``.

    ``timestamp_source`` says where the stamps came from (``"times.txt"``, ``"file names
    (ns)"``, ``"rate 10 Hz (assumed)"``, ...); ``run`` records it in ``run.json``.
    """

    def __init__(
        self,
        name: str,
        path: Path,
        left_paths: list[Path],
        right_paths: list[Path],
        timestamps: np.ndarray,
        calibration: StereoCalibration | RawStereoCalibration,
        color: bool | None = False,
        calib_path: Path | None = None,
        left_dir: Path | None = None,
        right_dir: Path | None = None,
        timestamp_source: str = "given",
        numbers: np.ndarray | None = None,
    ) -> None:
        self.name = name
        self.timestamp_source = timestamp_source
        self.path = Path(path)
        self.left_paths = list(left_paths)
        self.right_paths = list(right_paths)
        ldir = left_dir or (self.left_paths[0].parent if self.left_paths else self.path)
        rdir = right_dir or (self.right_paths[0].parent if self.right_paths else self.path)
        if len(self.left_paths) != len(self.right_paths):
            raise SequenceError(
                f"left and right image counts differ: {len(self.left_paths)} in {ldir}, "
                f"{len(self.right_paths)} in {rdir}",
                self.path,
            )
        if not self.left_paths:
            raise SequenceError(f"no images in {ldir}", self.path)
        self.color: bool = is_colour_image(self.left_paths[0]) if color is None else bool(color)
        self._timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        if len(self._timestamps) != len(self.left_paths):
            raise SequenceError(
                f"{len(self._timestamps)} timestamps for {len(self.left_paths)} image pairs", self.path
            )

        self._numbers: np.ndarray | None = None  # the images' own numbers, when they have gaps
        if numbers is not None:
            nums = np.asarray(numbers, dtype=np.int64).reshape(-1)
            if len(nums) == len(self.left_paths) and not np.array_equal(nums, np.arange(len(nums))):
                if np.any(np.diff(nums) <= 0):
                    raise SequenceError("image numbers are not increasing", ldir)
                self._numbers = nums
                self._position = {int(n): k for k, n in enumerate(nums)}
                full = np.arange(int(nums[-1]) + 1)
                self._timestamps = np.interp(full, nums, self._timestamps)  # missing numbers: never read
                self._timestamps[nums] = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        self.raw_size = self._check_sizes(ldir, rdir)  # (width, height) of the files
        self.bits = significant_bits(self.left_paths[0])  # None: 8-bit files
        if self.bits is not None:
            self.bits = max(self.bits, significant_bits(self.right_paths[0]) or 8)
            self.bits = min(16, self.bits + self.bits % 2)  # camera depths are even: 10, 12, 14 bits
            if self.bits < 16:
                log.warning("%s: 16-bit images holding %d-bit values (largest %d): read as %d-bit data scaled "
                            "to 8 bits", self.left_paths[0], self.bits, 2 ** self.bits - 1, self.bits)
        self.calibration, self.rectifier = rectified_calibration(calibration, self.raw_size, self.left_paths[0],
                                                                 calib_path)
        self.calibration_file = calib_path  # recorded in run.json, printed by `run`

    # -- checks ---------------------------------------------------------------------------

    def _check_sizes(self, ldir: Path, rdir: Path) -> tuple[int, int]:
        first = image_size(self.left_paths[0])
        for paths in (self.left_paths, self.right_paths):
            # PNG headers are cheap: check them all; other formats: the first of each side.
            cand = paths if paths[0].suffix.lower() == ".png" else paths[:1]
            for p in cand:
                s = image_size(p)
                if s != first:
                    raise SequenceError(
                        f"image size {s[0]}x{s[1]} differs from {first[0]}x{first[1]} of {self.left_paths[0]} "
                        f"(left folder {ldir}, right folder {rdir})",
                        p,
                    )
        return first

    # -- protocol -------------------------------------------------------------------------

    def __len__(self) -> int:
        """Frame indices run 0 .. len-1: the images' own numbers (KITTI's 000123.png is
        frame 123, through gaps in the numbering), else their positions."""
        return len(self.left_paths) if self._numbers is None else int(self._numbers[-1]) + 1

    def available_frames(self) -> list[int]:
        """The frame indices that have images (all of ``range(len(self))`` without gaps)."""
        return list(range(len(self))) if self._numbers is None else [int(n) for n in self._numbers]

    @property
    def missing_frames(self) -> list[int]:
        """Frame numbers below the last that have no image (gaps in the numbering)."""
        if self._numbers is None:
            return []
        have = np.zeros(len(self), dtype=bool)
        have[self._numbers] = True
        return [int(i) for i in np.flatnonzero(~have)]

    def timestamps(self) -> np.ndarray:
        """Timestamps in seconds, one per frame (a copy)."""
        return self._timestamps.copy()

    def _read(self, path: Path) -> np.ndarray:
        img = read_image(path, self.color, getattr(self, "bits", None))
        h, w = img.shape[:2]
        if (w, h) != self.raw_size:
            raise SequenceError(
                f"image is {w}x{h}, the sequence's images are {self.raw_size[0]}x{self.raw_size[1]}", path
            )
        return img

    def frame(self, index: int) -> StereoFrame:
        """The ``index``-th rectified pair (negative indices count from the end)."""
        n = len(self)
        i = int(index)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame {index} out of range: {self.name} has {n} frames")
        k = i
        if self._numbers is not None:
            k = self._position.get(i, -1)
            if k < 0:
                raise SequenceError(f"frame {i}: no image of that number (a gap in the numbering)",
                                    self.left_paths[0].parent)
        left = self._read(self.left_paths[k])
        right = self._read(self.right_paths[k])
        if self.rectifier is not None:
            left, right = self.rectifier.rectify(left, right)
        return StereoFrame(
            index=i,
            timestamp=float(self._timestamps[i]),
            left=left,
            right=right,
            left_path=self.left_paths[k],
            right_path=self.right_paths[k],
        )

    def __iter__(self) -> Iterator[StereoFrame]:
        for i in self.available_frames():
            yield self.frame(i)

    def frames(self, indices: Iterable[int]) -> Iterator[StereoFrame]:
        """Frames at ``indices`` in the given order (e.g. from ``parse_frame_spec``)."""
        for i in indices:
            yield self.frame(i)

    def __repr__(self) -> str:
        c = self.calibration
        rect = ", rectified on read" if self.rectifier is not None else ""
        return (
            f"{type(self).__name__}({self.name!r}, {len(self)} frames, {c.width}x{c.height}, "
            f"fx={c.fx:.2f}, baseline={c.baseline:.4f} m{rect})"
        )


def list_image_pairs(left_dir: Path, right_dir: Path, where: Path) -> tuple[list[Path], list[Path]]:
    """The images of two folders as pairs, by file name: the counts and the names must
    agree (a SequenceError naming ``where`` and the first mismatch otherwise)."""
    left, right = list_images(left_dir), list_images(right_dir)
    if len(left) != len(right):
        raise SequenceError(
            f"left and right image counts differ: {len(left)} in {left_dir}, {len(right)} in {right_dir}", where
        )
    if not left:
        raise SequenceError(f"no images in {left_dir}", where)
    lnames, rnames = [p.name for p in left], [p.name for p in right]
    if lnames != rnames:
        i = next(k for k in range(len(lnames)) if lnames[k] != rnames[k])
        raise SequenceError(
            f"left and right file names differ: {left[i]} is paired with {right[i]} "
            f"(folders {left_dir} and {right_dir})",
            where,
        )
    return left, right
