"""Stereo video: a video file (side by side, or two files) and a live camera, read through
OpenCV's ``cv2.VideoCapture``.

**Video file** (:class:`VideoSequence`, ``open_sequence("stereo.mkv")``): one file whose
frames hold the left image in the left half and the right image in the right half, or two
files named ``"left.mkv,right.mkv"`` (one path with a comma; the API also takes
``VideoSequence(left, calib, right=right)``).  The calibration is the YAML a generic folder
takes (:func:`~dynastereo.io.calib.load_stereo_yaml`, rectified or raw; raw is rectified
on read with the same :class:`~dynastereo.io.rectify.Rectifier`): ``calib`` when given,
else ``calib.yaml`` (or the only ``*.yaml``) beside the video.  Its size is one image's
(half the frame's width when side by side).

When opened, the file's packets are scanned once without decoding (``CAP_PROP_FORMAT = -1``,
well under a millisecond a frame): the frames are counted and checked against the container's
``CAP_PROP_FRAME_COUNT`` (an estimate for some containers: fewer frames by more than 1 %
whose stamps stop short of the container's duration is a truncated file, a SequenceError;
frames that run to its end are a complete file whose count was guessed high, logged) and the stamps are the
container's (``CAP_PROP_POS_MSEC`` of each packet, in presentation order), or ``i / rate``
with ``rate`` given; the first frame is decoded.  A file OpenCV cannot open, that holds no
frame or whose first frame cannot be decoded is a SequenceError naming it; two files of
different lengths too.  Frames are then decoded in
order, the capture kept open between calls: ``frame(i + 1)`` after ``frame(i)`` is one
``read``; a frame behind the last one read reopens the file and skips forward with ``grab``
(frame-exact whatever the codec).  A frame that cannot be decoded (a truncated file) is a
SequenceError naming the file and the frame.

**Camera** (:class:`CameraSequence`, ``open_sequence("cam:0")``): any ``VideoCapture``
source (a device index, a URL, a file) delivering side-by-side frames, as UVC stereo cameras
(ZED, ELP) do.  A thread reads the camera as fast as it delivers and keeps only the newest
frame (the live node's policy: a queue of one, ``io.queues.DropOldestQueue``); a frame
replaced before the pipeline took it is *dropped* and counted (``dropped``, in ``run.json``'s
``source``).  Frames are numbered in the order they are taken; stamps are the capture's
(``CAP_PROP_POS_MSEC`` when the backend gives it, else the host clock), relative to the
first frame.  A video file given as the camera (``cam:video.mkv``) plays at its own frame
rate, as a camera would deliver it.  The source is unbounded (``len`` is :data:`UNBOUNDED`): ``--frames N`` stops
after N frames, Ctrl-C stops cleanly; the camera's end (unplugged) is a SequenceError.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from ..errors import InputError, SequenceError
from ..datatypes import StereoCalibration, StereoFrame
from .calib import RawStereoCalibration, load_stereo_yaml
from .folder import CALIB_NAMES
from .queues import DropOldestQueue
from .sequence import rectified_calibration
from .times import check_rate

log = logging.getLogger(__name__)

#: File suffixes ``open_sequence`` takes as a video file.
VIDEO_SUFFIXES: tuple[str, ...] = (".mkv", ".avi", ".mp4", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".ts", ".wmv")
#: ``open_sequence`` prefix of a camera source: ``cam:0`` (device 0), ``cam:URL``.
CAMERA_PREFIX = "cam:"
#: ``len`` of a camera: no end (frames are taken until ``--frames N`` or Ctrl-C).
UNBOUNDED = sys.maxsize


def is_video_source(path: str | Path) -> bool:
    """Whether ``open_sequence`` reads ``path`` as a video file, two (``a.mkv,b.mkv``) or a camera."""
    text = str(path)
    if text.startswith(CAMERA_PREFIX):
        return True
    if Path(text).is_dir():
        return False
    return all(Path(p).suffix.lower() in VIDEO_SUFFIXES for p in text.split(","))


def split_side_by_side(img: np.ndarray, where: object) -> tuple[np.ndarray, np.ndarray]:
    """The left and right halves of a side-by-side frame (views, no copy)."""
    w = img.shape[1]
    if w % 2:
        raise SequenceError(f"a side-by-side frame must have an even width, got {w}", where)
    return img[:, : w // 2], img[:, w // 2 :]


def _as_color(img: np.ndarray, color: bool) -> np.ndarray:
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if color else img
    return img if color else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


def _is_colour(img: np.ndarray) -> bool:
    """Three channels that differ (a gray video decodes to three equal ones)."""
    return img.ndim == 3 and not (np.array_equal(img[:, :, 0], img[:, :, 1])
                                  and np.array_equal(img[:, :, 0], img[:, :, 2]))


def _calibration_path(calib: str | Path | None, video: Path) -> Path:
    """``calib``, else ``calib.yaml`` (or ``calibration.yaml``) beside the video -- by that
    name only: any other YAML file there (a stray one) is not taken as the calibration."""
    if calib is not None:
        return Path(calib)
    folder = video.parent if video.parent != Path("") else Path(".")
    found = next((folder / n for n in CALIB_NAMES if (folder / n).is_file()), None)
    if found is None:
        others = sorted(p.name for p in folder.iterdir() if p.suffix.lower() in (".yaml", ".yml") and p.is_file())
        also = (f" ({', '.join(others)} beside it {'is' if len(others) == 1 else 'are'} not taken without --calib)"
                if others else "")
        raise SequenceError(f"no calibration: pass --calib FILE.yaml (or put calib.yaml beside the video){also}",
                            video)
    return found


def check_pair_stamps(left: np.ndarray, right: np.ndarray, lpath: Path, rpath: Path) -> None:
    """Two videos' frames are paired by index: their container stamps must agree (within a
    third of a frame interval), else the pairs would join images taken at other times (a
    10 fps and a 5 fps file).  SequenceError naming both files and the first frame that
    disagrees."""
    if len(left) < 2:
        return
    period = float(np.median(np.diff(left)))
    off = np.abs(left - right)
    bad = np.flatnonzero(off > max(period / 3.0, 1e-3))
    if bad.size:
        k = int(bad[0])
        rp = float(np.median(np.diff(right))) if len(right) > 1 else float("nan")
        raise SequenceError(f"left and right videos' stamps disagree: frame {k} is at {left[k]:.3f} s in {lpath}, "
                            f"{right[k]:.3f} s in {rpath} ({1 / period:.3g} vs {1 / rp:.3g} fps); the frames "
                            "would be paired across time", rpath)


class _Reader:
    """One video file read in order through ``cv2.VideoCapture`` (see module doc)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        if not path.is_file():
            raise SequenceError("video file not found", path)
        self.cap: cv2.VideoCapture | None = None
        self.next = 0  # the index the next read returns
        self._open()

    def _open(self) -> None:
        if self.cap is not None:
            self.cap.release()
        self.cap = cv2.VideoCapture(str(self.path), cv2.CAP_FFMPEG)
        if not self.cap.isOpened():
            raise SequenceError("cannot open the video (corrupt, or a codec OpenCV's FFmpeg cannot read)", self.path)
        self.next = 0

    def scan(self) -> tuple[np.ndarray, tuple[int, int]]:
        """Every frame's container stamp (s, presentation order) and the frame size, from one
        pass over the packets (``CAP_PROP_FORMAT = -1``: demuxed, not decoded)."""
        estimate = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))
        w, h = int(self.cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(self.cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        raw = cv2.VideoCapture(str(self.path), cv2.CAP_FFMPEG, [cv2.CAP_PROP_FORMAT, -1])
        stamps: list[float] = []
        try:
            while raw.grab():
                stamps.append(raw.get(cv2.CAP_PROP_POS_MSEC) / 1000.0)
        finally:
            raw.release()
        if not stamps:
            raise SequenceError("the video holds no frame (empty or truncated file)", self.path)
        if estimate - len(stamps) > max(1, estimate // 100) and not self._covers(stamps, estimate):
            raise SequenceError(f"truncated video: the container says {estimate} frames, the file holds "
                                f"{len(stamps)}", self.path)
        if estimate > 0 and estimate != len(stamps):
            log.warning("%s: the container says %d frames, it holds %d; using %d",
                        self.path, estimate, len(stamps), len(stamps))
        return np.sort(np.asarray(stamps, dtype=np.float64)), (w, h)  # packets come in decoding order

    def _covers(self, stamps: list[float], estimate: int) -> bool:
        """Whether the frames found run to the container's end (its duration: the estimate
        is duration x nominal rate, too large for a variable or wrongly declared rate): a
        complete file whose count was guessed high, not a truncated one (whose frames stop
        well before its duration)."""
        fps = float(self.cap.get(cv2.CAP_PROP_FPS) or 0.0)
        if not fps > 0 or len(stamps) < 2:
            return False
        s = np.sort(np.asarray(stamps, dtype=np.float64))
        period = float(np.median(np.diff(s)))
        duration = estimate / fps
        return bool(s[-1] + period >= duration - max(2.0 * period, 0.01 * duration))

    def read(self, index: int) -> np.ndarray:
        """Frame ``index``: one ``read`` when it is the next one, else reopen / ``grab`` up to it."""
        if index < self.next:
            self._open()
        while self.next < index:
            if not self.cap.grab():
                raise SequenceError(f"frame {self.next} cannot be decoded (truncated or corrupt file)", self.path)
            self.next += 1
        ok, img = self.cap.read()
        if not ok or img is None:
            raise SequenceError(f"frame {index} cannot be decoded (truncated or corrupt file)", self.path)
        self.next += 1
        return img

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None


class VideoSequence:
    """A stereo video file, side by side or two files, as a rectified :class:`~dynastereo.io.base.Sequence`.

    ``left``: the side-by-side video, or the left one with ``right`` given.  ``calib``: the
    YAML calibration (default: ``calib.yaml`` beside the video).  ``color``: ``None`` BGR
    frames when the video holds colour, ``True`` / ``False`` BGR / gray.  ``rate``: stamps
    ``i / rate`` instead of the container's.
    """

    def __init__(self, left: str | Path, calib: str | Path | None = None, *, right: str | Path | None = None,
                 color: bool | None = None, rate: float | None = None, name: str | None = None) -> None:
        rate = check_rate(rate)
        self.path = Path(left)
        self.side_by_side = right is None
        self._readers = [_Reader(self.path)] + ([] if right is None else [_Reader(Path(right))])
        self._lock = threading.Lock()
        scans = [r.scan() for r in self._readers]
        stamps, size = scans[0]
        if not self.side_by_side:
            (rs, rsize), rpath = scans[1], self._readers[1].path
            if len(rs) != len(stamps):
                raise SequenceError(f"left and right videos differ in length: {len(stamps)} frames in {self.path}, "
                                    f"{len(rs)} in {rpath}", rpath)
            if rsize != size:
                raise SequenceError(f"right video is {rsize[0]}x{rsize[1]}, the left one {size[0]}x{size[1]}", rpath)
            check_pair_stamps(stamps, rs, self.path, rpath)
        elif size[0] % 2:
            raise SequenceError(f"a side-by-side video must have an even width, got {size[0]}", self.path)
        self.raw_size = (size[0] // 2, size[1]) if self.side_by_side else size
        self.name = name or self.path.stem
        if rate is not None:
            self._timestamps = np.arange(len(stamps), dtype=np.float64) / rate
            self.timestamp_source = f"rate {rate:g} Hz (given)"
        else:
            if len(stamps) > 1 and np.any(np.diff(stamps) <= 0):
                raise SequenceError("the container's frame stamps do not increase; pass --rate HZ", self.path)
            self._timestamps = stamps
            self.timestamp_source = "video container"
        calib_path = _calibration_path(calib, self.path)
        calibration: StereoCalibration | RawStereoCalibration = load_stereo_yaml(calib_path, self.raw_size)
        self.calibration, self.rectifier = rectified_calibration(calibration, self.raw_size, self.path, calib_path)
        self.calibration_file = calib_path
        self.color = False
        first = self._pair(0, True)
        self.color = (_is_colour(first[0]) or _is_colour(first[1])) if color is None else bool(color)

    def _pair(self, index: int, color: bool) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:  # the prefetch thread and the stereo check may both read
            if self.side_by_side:
                left, right = split_side_by_side(self._readers[0].read(index), self.path)
            else:
                left, right = (r.read(index) for r in self._readers)
        return _as_color(left, color), _as_color(right, color)

    def __len__(self) -> int:
        return len(self._timestamps)

    def timestamps(self) -> np.ndarray:
        return self._timestamps.copy()

    def frame(self, index: int) -> StereoFrame:
        """The ``index``-th rectified pair (negative indices count from the end)."""
        n = len(self)
        i = int(index) + (n if int(index) < 0 else 0)
        if not 0 <= i < n:
            raise IndexError(f"frame {index} out of range: {self.name} has {n} frames")
        left, right = self._pair(i, self.color)
        if self.rectifier is not None:
            left, right = self.rectifier.rectify(left, right)
        return StereoFrame(index=i, timestamp=float(self._timestamps[i]), left=np.ascontiguousarray(left),
                           right=np.ascontiguousarray(right))

    def __iter__(self) -> Iterator[StereoFrame]:
        for i in range(len(self)):
            yield self.frame(i)

    def close(self) -> None:
        for r in self._readers:
            r.close()

    def __repr__(self) -> str:
        c = self.calibration
        form = "side by side" if self.side_by_side else "two files"
        rect = ", rectified on read" if self.rectifier is not None else ""
        return (f"VideoSequence({self.name!r}, {form}, {len(self)} frames, {c.width}x{c.height}, "
                f"fx={c.fx:.2f}, baseline={c.baseline:.4f} m{rect})")


def _capture_source(source: int | str | Path) -> int | str:
    """``0`` / ``"0"`` -> device 0; anything else (a URL, a file) as a string."""
    if isinstance(source, int):
        return source
    text = str(source)
    return int(text) if text.isdigit() else text


class CameraSequence:
    """A live side-by-side stereo camera through ``cv2.VideoCapture`` (see module doc).

    ``source``: a device index, or anything ``VideoCapture`` opens (a URL; a video file plays
    as a camera would deliver it, at its container's stamps: the tests use this).
    ``calib``: the YAML calibration of one image (half the frame).  ``color``: ``None`` BGR
    when the first frame holds colour.  ``size``: ask the camera for this frame size
    ``(width, height)`` (both images side by side).  ``timeout_s``: the longest wait for a
    frame (a SequenceError past it).
    """

    live = True

    def __init__(self, source: int | str | Path, calib: str | Path, *, color: bool | None = None,
                 size: tuple[int, int] | None = None, timeout_s: float = 5.0, name: str | None = None) -> None:
        self.source = _capture_source(source)
        self.paced = isinstance(self.source, str) and Path(self.source).is_file()
        self.path = Path(f"{CAMERA_PREFIX}{self.source}")
        self.name = name or f"camera {self.source}"
        self.timeout_s = float(timeout_s)
        self.timestamp_source = "camera"
        self.cap = cv2.VideoCapture(self.source)
        if not self.cap.isOpened():
            raise SequenceError("cannot open the camera (no such device, or busy)", self.path)
        if size is not None:
            self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, size[0])
            self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, size[1])
        self._queue = DropOldestQueue(1)
        self.received = 0  # frames read from the camera
        self.taken = 0  # frames handed to the pipeline
        self._t0: float | None = None
        self._ended = threading.Event()
        self._stop = threading.Event()
        self._error = ""
        self._thread = threading.Thread(target=self._grab_loop, name="camera", daemon=True)
        self._thread.start()
        try:
            first = self._next()
            l0, r0 = split_side_by_side(first[1], self.path)
            self.raw_size = (l0.shape[1], l0.shape[0])
            calibration = load_stereo_yaml(calib, self.raw_size)
            self.calibration, self.rectifier = rectified_calibration(calibration, self.raw_size, self.path,
                                                                     Path(calib))
        except BaseException:
            self.close()
            raise
        self.color = (_is_colour(l0) or _is_colour(r0)) if color is None else bool(color)
        self._pending: tuple[float, np.ndarray] | None = first  # frame 0, unless a newer one comes first
        self._stale = 0  # pending first frames replaced by a newer one

    @property
    def dropped(self) -> int:
        """Frames replaced by a newer one before the pipeline took them."""
        return self._queue.dropped + self._stale

    def _grab_loop(self) -> None:
        use_pos: bool | None = None  # the capture's own stamps (decided on the first frame), else the host clock
        start = 0.0
        try:
            while not self._stop.is_set():
                ok, img = self.cap.read()
                if not ok or img is None:
                    self._error = f"the camera stopped delivering frames after {self.received}"
                    break
                now = time.monotonic()
                ms = self.cap.get(cv2.CAP_PROP_POS_MSEC)
                if use_pos is None:
                    use_pos = self.paced or (ms is not None and ms > 0)
                    start = now - (ms / 1000.0 if use_pos else now)  # the wall clock at stamp 0
                t = ms / 1000.0 if use_pos else now
                if self.paced:  # a file plays at its own rate, as a camera would deliver it
                    self._stop.wait(max(0.0, start + t - time.monotonic()))
                self._queue.put((t, img))
                self.received += 1  # after the put: received - taken - dropped is 0 or 1 at any time
        finally:
            self._ended.set()

    def _next(self) -> tuple[float, np.ndarray]:
        """The newest frame not yet taken (waits for one)."""
        while True:
            item = self._queue.get(timeout=0.05 if self._ended.is_set() else self.timeout_s)
            if item is not None:
                return item
            if self._ended.is_set():
                if len(self._queue):
                    continue
                raise SequenceError(self._error or "the camera was closed", self.path)
            raise SequenceError(f"no frame from the camera for {self.timeout_s:g} s", self.path)

    def __len__(self) -> int:
        return UNBOUNDED

    def timestamps(self) -> np.ndarray:
        raise SequenceError("a camera has no stamps before its frames come (each frame carries its own)", self.path)

    def frame(self, index: int) -> StereoFrame:
        """The newest camera frame, numbered ``index`` (frames are taken in order: ``index``
        only names it)."""
        if self._pending is not None and len(self._queue):  # a newer frame came while setting up
            self._pending, self._stale = None, self._stale + 1
        if self._pending is not None:
            item, self._pending = self._pending, None
        else:
            item = self._next()
        t, img = item
        if self._t0 is None:
            self._t0 = t
        self.taken += 1
        left, right = split_side_by_side(img, self.path)
        left, right = _as_color(left, self.color), _as_color(right, self.color)
        if self.rectifier is not None:
            left, right = self.rectifier.rectify(left, right)
        return StereoFrame(index=int(index), timestamp=float(t - self._t0), left=np.ascontiguousarray(left),
                           right=np.ascontiguousarray(right))

    def run_info(self) -> dict:
        """``run.json``'s ``source`` entry: frames received, taken and dropped."""
        return {"source": {"kind": "camera", "device": str(self.source), "received": self.received,
                           "taken": self.taken, "dropped": self.dropped}}

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        if not self._thread.is_alive():  # a read blocked in the driver: the daemon thread keeps the capture
            self.cap.release()

    def __enter__(self) -> "CameraSequence":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        c = self.calibration
        return (f"CameraSequence({self.source!r}, {c.width}x{c.height}, fx={c.fx:.2f}, "
                f"baseline={c.baseline:.4f} m, dropped {self.dropped})")


def open_video_source(path: str | Path, calib: str | Path | None = None, color: bool | None = None,
                      rate: float | None = None) -> VideoSequence | CameraSequence:
    """``cam:N`` -> :class:`CameraSequence`; ``a.mkv,b.mkv`` -> two-file, ``a.mkv`` ->
    side-by-side :class:`VideoSequence`."""
    text = str(path)
    if text.startswith(CAMERA_PREFIX):
        if rate is not None:
            raise InputError("--rate is for sequence folders and video files; a camera stamps its frames")
        if calib is None:
            raise InputError(f"{text}: a camera needs --calib calib.yaml")
        return CameraSequence(text[len(CAMERA_PREFIX):], calib, color=color)
    parts = text.split(",")
    if len(parts) == 2:
        return VideoSequence(parts[0], calib, right=parts[1], color=color, rate=rate)
    if len(parts) > 2:
        raise InputError(f"{text}: give one side-by-side video or two, left,right")
    return VideoSequence(text, calib, color=color, rate=rate)
