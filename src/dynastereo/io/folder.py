"""Generic stereo sequences: two folders of images and a YAML calibration.

Layout recognized by :func:`find_folder_layout` / :meth:`FolderSequence.from_root`::

    root/
        left/  right/        (or cam0/ cam1/; a data/ subfolder inside each is used if present)
        calib.yaml           (or calibration.yaml, or the only *.yaml / *.yml in root)
        times.txt            optional: one timestamp (s) per frame

Images are paired in sorted-name order (the counts must match).  Timestamps
(:func:`~dynastereo.io.times.sequence_timestamps`): ``times.txt`` when present, else the
left image names when they are Unix times (``1403636579763555584.png``: s, ms, µs or ns by
magnitude), else ``index / rate`` (10 Hz unless ``rate`` is given, with a warning);
``timestamp_source`` says which.  The YAML is read by
:func:`~dynastereo.io.calib.load_stereo_yaml`: dynastereo's own format (rectified or raw)
or an ORB-SLAM2 settings file; raw calibrations are rectified on read.

``color=None`` (the default) gives BGR frames when the images hold colour (the first left
image decides, see :func:`~dynastereo.io.sequence.is_colour_image`), gray frames otherwise;
``color=True`` / ``False`` force BGR / gray.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import SequenceError
from .calib import load_stereo_yaml
from .images import image_size, list_images
from .sequence import ImagePairSequence
from .times import Timestamps, sequence_timestamps

PAIR_DIR_NAMES: tuple[tuple[str, str], ...] = (("left", "right"), ("cam0", "cam1"))
CALIB_NAMES: tuple[str, ...] = ("calib.yaml", "calib.yml", "calibration.yaml", "calibration.yml")


def _image_dir(d: Path) -> Path:
    return d / "data" if (d / "data").is_dir() else d


def find_pair_dirs(root: Path) -> tuple[Path, Path] | None:
    for l, r in PAIR_DIR_NAMES:
        if (root / l).is_dir() and (root / r).is_dir():
            return _image_dir(root / l), _image_dir(root / r)
    return None


def find_calib_yaml(root: Path) -> Path | None:
    """``calib.yaml`` (or a listed alias) in ``root``, else its only ``*.yaml``/``*.yml``; None if none.

    Several candidate YAML files and none of the standard names -> SequenceError listing them.
    """
    for n in CALIB_NAMES:
        if (root / n).is_file():
            return root / n
    ymls = sorted(p for p in root.iterdir() if p.suffix.lower() in (".yaml", ".yml") and p.is_file())
    if len(ymls) == 1:
        return ymls[0]
    if len(ymls) > 1:
        raise SequenceError(
            f"several YAML files and no calib.yaml: {', '.join(p.name for p in ymls)}; "
            "name the calibration calib.yaml or pass it explicitly",
            root,
        )
    return None


class FolderSequence(ImagePairSequence):
    """Stereo pairs from ``left_dir`` and ``right_dir`` with the calibration ``calib_yaml``."""

    def __init__(
        self,
        left_dir: str | Path,
        right_dir: str | Path,
        calib_yaml: str | Path,
        color: bool | None = None,
        times: str | Path | np.ndarray | None = None,
        rate: float | None = None,
        name: str | None = None,
    ) -> None:
        left_dir, right_dir = Path(left_dir), Path(right_dir)
        for d in (left_dir, right_dir):
            if not d.is_dir():
                raise SequenceError("image folder not found", d)
        left, right = list_images(left_dir), list_images(right_dir)
        if len(left) != len(right):
            raise SequenceError(
                f"left and right image counts differ: {len(left)} in {left_dir}, {len(right)} in {right_dir}",
                left_dir.parent,
            )
        if not left:
            raise SequenceError("no images (png, jpg, ...) in the folder", left_dir)
        root = left_dir.parent if left_dir.name != "data" else left_dir.parent.parent
        calibration = load_stereo_yaml(calib_yaml, image_size(left[0]))
        if isinstance(times, np.ndarray):
            stamps = Timestamps(np.asarray(times, np.float64), "given")
        else:
            stamps = sequence_timestamps(len(left), Path(times) if times is not None else root / "times.txt",
                                         left, rate, where=root, required=times is not None)
        if stamps.ns is not None:
            self.timestamps_ns = stamps.ns  # exact, for bag export
        super().__init__(
            name=name or root.name,
            path=root,
            left_paths=left,
            right_paths=right,
            timestamps=stamps.seconds,
            calibration=calibration,
            color=color,
            calib_path=Path(calib_yaml),
            left_dir=left_dir,
            right_dir=right_dir,
            timestamp_source=stamps.source,
        )

    @classmethod
    def from_root(cls, root: str | Path, calib: str | Path | None = None,
                  color: bool | None = None, rate: float | None = None) -> "FolderSequence":
        """Open ``root`` with ``left/``+``right/`` (or ``cam0/``+``cam1/``) and a YAML calibration;
        ``rate`` (Hz) for stamps when neither ``times.txt`` nor the file names give them."""
        root = Path(root)
        dirs = find_pair_dirs(root)
        if dirs is None:
            raise SequenceError("no left/ and right/ (or cam0/ and cam1/) image folders", root)
        calib_path = Path(calib) if calib is not None else find_calib_yaml(root)
        if calib_path is None:
            raise SequenceError("no calibration: put calib.yaml in the folder or pass one explicitly", root)
        return cls(dirs[0], dirs[1], calib_path, color=color, rate=rate, name=root.name)
