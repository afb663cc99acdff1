"""Input layer: stereo sequences, calibration, images, frame selection.

``open_sequence(path)`` recognizes the folder's format and returns a
:class:`~dynastereo.io.base.Sequence` of rectified pairs:

* **KITTI** odometry: ``calib.txt`` + ``image_0/``,``image_1/`` (gray) or ``image_2/``,``image_3/`` (colour);
* **KITTI raw** drives: ``image_00/``,``image_01/`` (gray) or ``image_02/``,``image_03/`` (colour), each
  with ``data/`` and ``timestamps.txt``, and ``calib_cam_to_cam.txt`` in the date folder above
  (the drive folder, or a date folder holding one drive);
* **EuRoC** MAV: ``mav0/`` (or ``cam0/sensor.yaml`` directly inside); raw, rectified on read;
* **video**: a side-by-side stereo video file (``stereo.mkv``), two files (``left.mkv,right.mkv``)
  or a camera (``cam:0``) with a generic folder's YAML calibration (:mod:`dynastereo.io.video`);
* **generic**: ``left/``+``right/`` (or ``cam0/``+``cam1/``) with ``calib.yaml`` / one ``*.yaml``,
  or any of these layouts with an explicit ``calib`` YAML.

Colour: ``open_sequence(path, color=None)`` (the default, auto) gives BGR frames when the
images the reader uses are colour (KITTI's colour pair when it is the one used, colour
images in a generic folder), gray frames otherwise; ``color=False`` forces gray, ``color=True``
asks for colour (KITTI: the colour pair, an error without it).  Disparity and SLAM read
``frame.left_gray`` / ``frame.right_gray``; the detector gets ``frame.left`` as it is.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ..errors import SequenceError
from .base import Sequence
from .calib import (
    MiddleburyCalibration,
    RawStereoCalibration,
    kitti_projections,
    load_euroc_calib,
    kitti_raw_projections,
    load_kitti_calib,
    load_kitti_raw_calib,
    load_middlebury_calib,
    load_orbslam2_settings,
    load_stereo_yaml,
    orbslam2_calibration,
    read_kitti_calib_rows,
    read_yaml_file,
)
from .euroc import EurocSequence, euroc_mav_dir, pair_by_timestamp
from .folder import FolderSequence, find_calib_yaml, find_pair_dirs
from .frames import parse_frame_spec
from .images import (
    image_size,
    list_images,
    read_disparity_png,
    read_image,
    read_pfm,
    write_disparity_png,
    write_pfm,
)
from .kitti import KittiSequence, kitti_image_dirs
from .kitti_raw import KittiRawSequence, read_kitti_raw_timestamps, resolve_kitti_raw_drive
from .rectify import Rectifier
from .sequence import ImagePairSequence, is_colour_image
from .video import is_video_source, open_video_source

__all__ = [
    "EurocSequence",
    "FolderSequence",
    "ImagePairSequence",
    "KittiRawSequence",
    "KittiSequence",
    "MiddleburyCalibration",
    "RawStereoCalibration",
    "Rectifier",
    "Sequence",
    "detect_format",
    "image_size",
    "is_colour_image",
    "kitti_projections",
    "kitti_raw_projections",
    "list_images",
    "load_euroc_calib",
    "load_kitti_calib",
    "load_kitti_raw_calib",
    "load_middlebury_calib",
    "load_orbslam2_settings",
    "load_stereo_yaml",
    "open_sequence",
    "orbslam2_calibration",
    "pair_by_timestamp",
    "parse_frame_spec",
    "read_disparity_png",
    "read_image",
    "read_kitti_calib_rows",
    "read_kitti_raw_timestamps",
    "read_pfm",
    "read_yaml_file",
    "write_disparity_png",
    "write_pfm",
]

log = logging.getLogger(__name__)

_LOOKED_FOR = (
    "KITTI: calib.txt with image_0/+image_1/ or image_2/+image_3/; "
    "KITTI raw: a drive folder with image_00/+image_01/ or image_02/+image_03/ (or a date folder with one drive); "
    "EuRoC: mav0/cam0, mav0/cam1 (or cam0/sensor.yaml inside the folder); "
    "generic: left/+right/ (or cam0/+cam1/) with calib.yaml or a single *.yaml, or an explicit calibration YAML"
)


def detect_format(path: str | Path, calib: str | Path | None = None) -> str:
    """``"kitti"``, ``"kitti_raw"``, ``"euroc"`` or ``"folder"`` for a sequence folder; SequenceError if
    none fits (or a KITTI raw date folder holds several drives)."""
    path = Path(path)
    if not path.exists():
        raise SequenceError("sequence folder not found", path)
    if not path.is_dir():
        raise SequenceError("expected a sequence folder or a video file (.mkv, .avi, .mp4, ...), got another file",
                            path)
    has_kitti_images = kitti_image_dirs(path, False) is not None  # either pair; KittiSequence checks colour
    if has_kitti_images and ((path / "calib.txt").is_file() or calib is not None):
        return "kitti"
    if not has_kitti_images and resolve_kitti_raw_drive(path) is not None:
        return "kitti_raw"
    if (path / "mav0").is_dir() or (path / "cam0" / "sensor.yaml").is_file():
        if euroc_mav_dir(path) is None:
            raise SequenceError("looks like EuRoC but mav0/cam0 and mav0/cam1 are incomplete", path)
        return "euroc"
    if find_pair_dirs(path) is not None:
        if calib is not None or find_calib_yaml(path) is not None:
            return "folder"
        raise SequenceError(
            "found left/right image folders but no calibration (calib.yaml or a single *.yaml); pass one explicitly",
            path,
        )
    if has_kitti_images:
        raise SequenceError("found KITTI image folders but no calib.txt (or pass a calibration YAML)", path)
    if (path / "sequences").is_dir():
        raise SequenceError(
            "this is a KITTI dataset root; pass one sequence folder, e.g. " f"{path / 'sequences' / '06'}", path
        )
    raise SequenceError(f"unrecognized sequence folder; looked for {_LOOKED_FOR}", path)


def open_sequence(path: str | Path, calib: str | Path | None = None, color: bool | None = None,
                  rate: float | None = None) -> Sequence:
    """Open a stereo sequence folder in any supported format (see module doc).

    ``calib``: a YAML calibration overriding the folder's own (or supplying a missing one).
    ``color``: ``None`` (auto) BGR frames when the images used are colour, else gray;
    ``False`` gray; ``True`` BGR (KITTI: the colour pair).
    ``rate``: frame rate (Hz) for the stamps of a KITTI or generic folder that has no
    ``times.txt`` (and, generic, no timestamp file names); ignored, with a warning, by
    formats that always carry stamps.  ``seq.timestamp_source`` says where they came from.
    """
    if is_video_source(path):
        return open_video_source(path, calib=calib, color=color, rate=rate)
    path = Path(path)
    fmt = detect_format(path, calib)
    if fmt == "kitti":
        return KittiSequence(path, color=color, calib=calib, rate=rate)
    if fmt == "folder":
        return FolderSequence.from_root(path, calib=calib, color=color, rate=rate)
    if rate is not None:
        log.warning("%s: --rate %g ignored: %s folders carry their own timestamps", path, rate, fmt)
    if fmt == "kitti_raw":
        return KittiRawSequence(path, color=color, calib=calib)
    return EurocSequence(path, calib=calib, color=color)
