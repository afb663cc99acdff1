"""EuRoC MAV sequences (ASL layout), raw stereo rectified on read.

::

    V1_01_easy/            (the folder passed; or mav0/ itself)
        mav0/
            cam0/ sensor.yaml  data.csv  data/<timestamp_ns>.png     left
            cam1/ sensor.yaml  data.csv  data/<timestamp_ns>.png     right

``data.csv``: ``#timestamp [ns],filename`` then one ``<ns>,<file>`` row per image (without
it the ``data/*.png`` names are read as nanosecond timestamps).  Left and right images
are paired by timestamp: equal, or the nearest within ``sync_tolerance_ns`` (one-to-one);
the unpaired counts are kept in ``unpaired_left`` / ``unpaired_right`` and logged.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import SequenceError
from .calib import RawStereoCalibration, load_euroc_calib, load_stereo_yaml
from .images import image_size, list_images
from .sequence import ImagePairSequence

log = logging.getLogger(__name__)

DEFAULT_SYNC_TOLERANCE_NS = 2_500_000  # 2.5 ms


def euroc_mav_dir(path: Path) -> Path | None:
    """The folder holding ``cam0``/``cam1`` (``mav0`` or the folder itself), or None."""
    for cand in (path / "mav0", path):
        if (cand / "cam0").is_dir() and (cand / "cam1").is_dir() and (
            (cand / "cam0" / "sensor.yaml").is_file() or (cand / "cam0" / "data").is_dir()
        ):
            return cand
    return None


def read_euroc_csv(cam_dir: Path) -> tuple[np.ndarray, list[Path]]:
    """``(timestamps_ns int64 sorted, image paths)`` of one EuRoC camera folder."""
    data_dir = cam_dir / "data"
    csv = cam_dir / "data.csv"
    if not data_dir.is_dir():
        raise SequenceError("image folder 'data/' not found", cam_dir)
    stamps: list[int] = []
    paths: list[Path] = []
    if csv.is_file():
        present = {p.name for p in data_dir.iterdir()}
        for lineno, line in enumerate(csv.read_text().splitlines(), 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = [p.strip() for p in s.split(",")]
            if len(parts) < 2 or not parts[0].isdigit():
                raise SequenceError(f"line {lineno}: expected '<timestamp_ns>,<filename>', got {s[:80]!r}", csv)
            if parts[1] not in present:
                raise SequenceError(f"line {lineno}: image {data_dir / parts[1]} not found", csv)
            stamps.append(int(parts[0]))
            paths.append(data_dir / parts[1])
    else:
        for p in list_images(data_dir):
            if not p.stem.isdigit():
                raise SequenceError(
                    f"no data.csv and the image name {p.name!r} is not a nanosecond timestamp", cam_dir
                )
            stamps.append(int(p.stem))
            paths.append(p)
    if not stamps:
        raise SequenceError("no images", csv if csv.is_file() else data_dir)
    t = np.array(stamps, dtype=np.int64)
    order = np.argsort(t, kind="stable")
    return t[order], [paths[i] for i in order]


def pair_by_timestamp(left_ns: np.ndarray, right_ns: np.ndarray, tolerance_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(il, ir)`` matching sorted timestamps one-to-one within ``tolerance_ns``.

    Each left stamp takes its nearest right stamp; when two left stamps want the same right
    one, the closer keeps it.  Vectorized (searchsorted), result sorted by left index.
    """
    left_ns = np.asarray(left_ns, np.int64)
    right_ns = np.asarray(right_ns, np.int64)
    if len(left_ns) == 0 or len(right_ns) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pos = np.searchsorted(right_ns, left_ns)
    lo = np.clip(pos - 1, 0, len(right_ns) - 1)
    hi = np.clip(pos, 0, len(right_ns) - 1)
    d_lo = np.abs(left_ns - right_ns[lo])
    d_hi = np.abs(left_ns - right_ns[hi])
    ir = np.where(d_hi < d_lo, hi, lo)
    dt = np.minimum(d_lo, d_hi)
    il = np.nonzero(dt <= tolerance_ns)[0]
    ir, dt = ir[il], dt[il]
    # one-to-one: for each right index keep the left with the smallest |dt|
    order = np.lexsort((dt, ir))
    first = np.ones(len(order), bool)
    first[1:] = ir[order][1:] != ir[order][:-1]
    keep = np.sort(order[first])
    return il[keep], ir[keep]


class EurocSequence(ImagePairSequence):
    """A EuRoC MAV stereo sequence; frames are rectified on read (maps computed once).

    Timestamps are seconds (``timestamps_ns`` keeps the exact nanoseconds of the left image).
    ``calib``: optional YAML (e.g. ORB-SLAM2's ``EuRoC.yaml`` with ``LEFT.*``/``RIGHT.*``)
    used instead of ``cam0/sensor.yaml`` + ``cam1/sensor.yaml``.
    """

    def __init__(
        self,
        path: str | Path,
        calib: str | Path | None = None,
        sync_tolerance_ns: int = DEFAULT_SYNC_TOLERANCE_NS,
        color: bool = False,
    ) -> None:
        path = Path(path)
        if not path.is_dir():
            raise SequenceError("EuRoC sequence folder not found", path)
        mav = euroc_mav_dir(path)
        if mav is None:
            raise SequenceError("not a EuRoC folder: mav0/cam0 and mav0/cam1 (with sensor.yaml, data/) not found", path)
        cam0, cam1 = mav / "cam0", mav / "cam1"
        tl, pl = read_euroc_csv(cam0)
        tr, pr = read_euroc_csv(cam1)
        il, ir = pair_by_timestamp(tl, tr, sync_tolerance_ns)
        self.unpaired_left = len(tl) - len(il)
        self.unpaired_right = len(tr) - len(ir)
        if len(il) == 0:
            raise SequenceError(
                f"no left/right image pairs within {sync_tolerance_ns / 1e6:g} ms "
                f"({len(tl)} images in {cam0}, {len(tr)} in {cam1})",
                path,
            )
        if self.unpaired_left or self.unpaired_right:
            log.warning(
                "%s: %d left and %d right images have no partner within %g ms and are skipped",
                path, self.unpaired_left, self.unpaired_right, sync_tolerance_ns / 1e6,
            )
        self.timestamps_ns = tl[il]
        if calib is not None:
            calibration = load_stereo_yaml(calib, image_size(pl[il[0]]))
            calib_path: Path | None = Path(calib)
        else:
            calibration = load_euroc_calib(cam0 / "sensor.yaml", cam1 / "sensor.yaml")
            calib_path = cam0 / "sensor.yaml"
        self.raw_calibration = calibration if isinstance(calibration, RawStereoCalibration) else None
        name = mav.parent.name if mav.name == "mav0" else mav.name
        super().__init__(
            name=name,
            path=path,
            left_paths=[pl[i] for i in il],
            right_paths=[pr[i] for i in ir],
            timestamps=self.timestamps_ns.astype(np.float64) * 1e-9,
            calibration=calibration,
            color=color,
            calib_path=calib_path,
            left_dir=cam0 / "data",
            right_dir=cam1 / "data",
            timestamp_source="data.csv (ns)" if (cam0 / "data.csv").is_file() else "file names (ns)",
        )
