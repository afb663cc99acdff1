"""KITTI raw drives (the "synced + rectified" downloads) in KITTI's own layout.

::

    2011_09_26/                              the date folder
        calib_cam_to_cam.txt                 P_rect_00..03, S_rect_00..03 (and the raw K/D/R/T)
        2011_09_26_drive_0001_sync/          the drive folder: pass this one
            image_00/ timestamps.txt  data/0000000000.png ...     gray left
            image_01/ timestamps.txt  data/...                    gray right
            image_02/ timestamps.txt  data/...                    colour left   (optional)
            image_03/ timestamps.txt  data/...                    colour right  (optional)

Pass the drive folder (``.../2011_09_26_drive_0001_sync``); the date folder is accepted too
when it holds exactly one drive.

**Which pair, and colour.**  Geometry uses one stereo pair, calibrated with its own rectified
projections: the gray pair 00/01 (``P_rect_00``/``P_rect_01``, baseline
``-P_rect_01[0,3] / fx``) or the colour pair 02/03 (``P_rect_02``/``P_rect_03``, baseline
``(P_rect_02[0,3] - P_rect_03[0,3]) / fx``).  The choice is kept simple:

* ``color=None`` (auto, the default): the gray pair with gray frames when ``image_00``/``image_01``
  exist, else the colour pair with BGR frames;
* ``color=False``: the same pairs, always gray frames;
* ``color=True``: the colour pair with BGR frames (an error when the drive lacks it).

The pairs are never mixed (e.g. gray geometry with the colour camera's image for the
detector): cameras 02 and 00 are 6 cm apart, so a mask made on one does not fit the other.
With BGR frames the detector sees colour while disparity and SLAM use ``frame.left_gray`` /
``frame.right_gray``.

**Timestamps.**  ``image_0x/timestamps.txt`` holds one date-time per image, e.g.
``2011-09-26 13:02:25.967790592``.  They are parsed exactly (integer nanoseconds), must
increase strictly, and are indexed by the number in each image's name (a folder holding
some of a drive's images can keep the full file).  ``timestamps()`` gives seconds since the
file's first stamp (float64); ``timestamps_ns`` the same in exact integer nanoseconds (which
a bag export writes as they are).  The left camera's stamps are the frames' stamps; the right
camera's file, when present, is checked the same way.

**Sizes.**  The rows ``S_rect_0x`` of ``calib_cam_to_cam.txt`` must match the images (an
unrectified "extract" drive is reported as such).

**Ground truth from ``oxts/``.**  A drive's ``oxts/data/NNNNNNNNNN.txt`` (one GPS/IMU packet
per frame: lat, lon, alt, roll, pitch, yaw, vn, ve, vf, vl, vu, ... 30 numbers) gives the
poses of the rectified camera 0 (:func:`kitti_raw_ground_truth`), as KITTI's raw devkit
(``convertOxtsToPose``) and pykitti compute them:

* IMU pose in the world: Mercator projection with the scale of the *first* packet's latitude
  (``s = cos(lat0)``, ``x = s·lon·π·r/180``, ``y = s·r·ln tan((90 + lat)·π/360)``,
  ``z = alt``, ``r = 6378137 m``) and ``R = Rz(yaw)·Ry(pitch)·Rx(roll)``: ``T_w_imu``;
* IMU -> velodyne -> camera 0 -> rectified camera 0: ``T_c0r_imu = R_rect_00 ·
  T_velo_to_cam · T_imu_to_velo`` (``calib_imu_to_velo.txt``, ``calib_velo_to_cam.txt``,
  ``R_rect_00`` of ``calib_cam_to_cam.txt``, all in the date folder);
* camera pose ``T_w_c = T_w_imu · T_c0r_imu⁻¹``, expressed in the first frame's camera:
  ``P_i = T_w_c(0)⁻¹ · T_w_c(i)`` (camera-to-world, x right, y down, z forward).

Packet ``i`` belongs to frame ``i`` (the synced download has one per image).  The poses'
stamps are the frames' (``image_00/timestamps.txt``, seconds since the first image, as a
run's ``trajectory.tum.txt``), else ``oxts/timestamps.txt``'s since its first stamp.

**At the images' times** (``at="images"``, the default).  The synced download pairs each
image with the packet *nearest* in time (the OXTS runs at 100 Hz), not one taken with it:
on drive 0001 the packet is -4.7 to +4.7 ms off its image, at 10-13 m/s up to 6 cm along
the road, a saw-tooth of +-0.1 m over consecutive frames in any visual odometry's error
against the devkit's poses (and the first frame's offset, 3.4 ms, moves the anchor of every
start-anchored figure).  Each packet's pose is therefore moved to its image's stamp with the
packet's own motion -- world velocity ``(ve, vn, vu)`` and body angular rate ``(wx, wy, wz)``
over ``dt = t_image - t_packet`` -- before the change to the camera (linear interpolation
between neighbouring packets agrees to millimetres).  ``at="packets"`` gives the devkit's
poses as they are; so does a drive without both ``timestamps.txt``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np

from ..errors import CalibrationError, SequenceError
from .calib import (
    KITTI_RAW_COLOUR_PAIR,
    KITTI_RAW_GRAY_PAIR,
    load_kitti_raw_calib,
    load_stereo_yaml,
    read_kitti_calib_rows,
)
from .images import image_size
from .sequence import ImagePairSequence, list_image_pairs

CALIB_CAM_TO_CAM = "calib_cam_to_cam.txt"
CALIB_IMU_TO_VELO = "calib_imu_to_velo.txt"
CALIB_VELO_TO_CAM = "calib_velo_to_cam.txt"
TIMESTAMPS = "timestamps.txt"
OXTS = "oxts"
OXTS_FIELDS = 30
OXTS_NAMES = ("lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu", "ax", "ay", "az", "af", "al",
              "au", "wx", "wy", "wz", "wf", "wl", "wu", "pos_accuracy", "vel_accuracy", "navstat", "numsats",
              "posmode", "velmode", "orimode")
GT_AT = ("images", "packets")  # the times the ground truth's poses are for (module doc)
EARTH_RADIUS = 6378137.0  # metres, as KITTI's devkit

_STAMP = re.compile(r"^(\d{4})-(\d{2})-(\d{2})[ T](\d{2}):(\d{2}):(\d{2})(?:\.(\d{1,9}))?$")
_EPOCH = datetime(1970, 1, 1)


def _cam_dir(drive: Path, cam: str) -> Path:
    return drive / f"image_{cam}"


def _data_dir(cam_dir: Path) -> Path:
    """``image_0x/data`` (KITTI's layout), or ``image_0x`` itself when it has no ``data/``."""
    return cam_dir / "data" if (cam_dir / "data").is_dir() else cam_dir


def kitti_raw_pairs(drive: Path) -> dict[str, tuple[Path, Path]]:
    """The stereo pairs present in a drive folder: ``{"gray": (image_00, image_01), "colour": ...}``."""
    out: dict[str, tuple[Path, Path]] = {}
    for kind, (cl, cr) in (("gray", KITTI_RAW_GRAY_PAIR), ("colour", KITTI_RAW_COLOUR_PAIR)):
        l, r = _cam_dir(drive, cl), _cam_dir(drive, cr)
        if l.is_dir() and r.is_dir():
            out[kind] = (l, r)
    return out


def is_kitti_raw_drive(path: Path) -> bool:
    """Whether ``path`` looks like a KITTI raw drive folder (``image_00``+``image_01`` or
    ``image_02``+``image_03``)."""
    return path.is_dir() and bool(kitti_raw_pairs(path))


def kitti_raw_drives(path: Path) -> list[Path]:
    """The drive folders directly inside a date folder, sorted by name."""
    if not path.is_dir():
        return []
    return sorted(p for p in path.iterdir() if p.is_dir() and is_kitti_raw_drive(p))


def resolve_kitti_raw_drive(path: Path) -> Path | None:
    """The drive folder for ``path``: itself if it is a drive, the only drive of a date folder;
    None if neither.  SequenceError for a date folder with several drives (or a
    ``calib_cam_to_cam.txt`` and none)."""
    path = Path(path)
    if is_kitti_raw_drive(path):
        return path
    drives = kitti_raw_drives(path)
    if len(drives) == 1:
        return drives[0]
    if len(drives) > 1:
        names = ", ".join(p.name for p in drives)
        raise SequenceError(
            f"KITTI raw date folder with {len(drives)} drives ({names}); pass one drive folder, e.g. {drives[0]}",
            path,
        )
    if (path / CALIB_CAM_TO_CAM).is_file():
        raise SequenceError(
            f"KITTI raw date folder ({CALIB_CAM_TO_CAM}) without a drive folder "
            "(…_drive_NNNN_sync/ with image_00/+image_01/ or image_02/+image_03/)",
            path,
        )
    return None


def parse_kitti_raw_stamp(text: str) -> int:
    """Nanoseconds since 1970-01-01 of a KITTI raw stamp ``YYYY-MM-DD HH:MM:SS.fffffffff``
    (read as written, without a time zone); ValueError when malformed."""
    m = _STAMP.match(text.strip())
    if m is None:
        raise ValueError("expected 'YYYY-MM-DD HH:MM:SS.fffffffff'")
    y, mo, d, h, mi, s = (int(g) for g in m.groups()[:6])
    whole = datetime(y, mo, d, h, mi, s)  # ValueError for month 13, second 61 ...
    frac = m.group(7) or ""
    days = (whole.date() - _EPOCH.date()).days
    secs = days * 86400 + h * 3600 + mi * 60 + s
    return secs * 1_000_000_000 + int(frac.ljust(9, "0") or 0)


def read_kitti_raw_timestamps(path: str | Path) -> np.ndarray:
    """Exact stamps (int64 nanoseconds since 1970, as written) of a ``timestamps.txt``.

    SequenceError naming the file and line for a missing file, a malformed or blank line,
    or stamps that do not increase strictly.
    """
    path = Path(path)
    if not path.is_file():
        raise SequenceError("timestamps file not found" if not path.exists() else "not a file", path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise SequenceError(f"cannot read: {e.strerror}", path) from None
    lines = text.rstrip().splitlines()
    if not lines:
        raise SequenceError("no timestamps (the file is empty)", path)
    stamps: list[int] = []
    for lineno, line in enumerate(lines, 1):
        s = line.strip()
        if not s:
            raise SequenceError(f"line {lineno} is empty (one 'YYYY-MM-DD HH:MM:SS.fffffffff' per image)", path)
        try:
            ns = parse_kitti_raw_stamp(s)
        except ValueError as e:
            raise SequenceError(f"line {lineno}: {s[:60]!r} is not a timestamp ({e})", path) from None
        if stamps and ns <= stamps[-1]:
            rel = "equals" if ns == stamps[-1] else "is before"
            raise SequenceError(
                f"line {lineno}: timestamp {s} {rel} line {lineno - 1}'s {lines[lineno - 2].strip()} "
                "(timestamps must increase strictly)",
                path,
            )
        stamps.append(ns)
    return np.array(stamps, dtype=np.int64)


def _frame_numbers(paths: list[Path]) -> np.ndarray:
    """Frame numbers from the names (0000000123.png -> 123); positions if not all numeric."""
    stems = [p.stem for p in paths]
    if all(s.isdigit() for s in stems):
        return np.array([int(s) for s in stems], dtype=np.int64)
    return np.arange(len(paths), dtype=np.int64)


def _check_pair_stamps(left: np.ndarray, right: np.ndarray, lpath: Path, rpath: Path) -> None:
    """The pairs are matched by image number: the two cameras' stamps of a pair must agree
    (within a third of the median frame interval; KITTI's differ by well under a
    millisecond), else SequenceError naming the first pair that does not."""
    if len(left) < 2:
        return
    period = float(np.median(np.diff(left))) * 1e-9
    off = np.abs(left.astype(np.int64) - right.astype(np.int64)) * 1e-9
    bad = np.flatnonzero(off > max(period / 3.0, 1e-3))
    if bad.size:
        k = int(bad[0])
        raise SequenceError(f"the left and right stamps of pair {k} differ by {off[k]:.3f} s ({lpath} vs {rpath}; "
                            f"frames {period:.3f} s apart): the images would be paired across time", rpath)


def _stamps_for(stamps_path: Path, numbers: np.ndarray) -> np.ndarray:
    ns = read_kitti_raw_timestamps(stamps_path)
    top = int(numbers.max())
    if len(ns) <= top:
        raise SequenceError(
            f"{len(ns)} timestamps, but the images go up to frame {top} ({len(numbers)} images)", stamps_path
        )
    return ns


class KittiRawSequence(ImagePairSequence):
    """A KITTI raw drive (synced + rectified): frames are returned as stored (module doc).

    ``color``: ``None`` auto (gray pair 00/01 when present, else colour pair 02/03 as BGR),
    ``False`` gray frames, ``True`` the colour pair as BGR.  ``calib``: an optional YAML
    calibration (see :func:`~dynastereo.io.calib.load_stereo_yaml`) used instead of
    ``calib_cam_to_cam.txt``.

    Attributes beyond :class:`ImagePairSequence`'s: ``drive`` (the drive folder),
    ``uses_colour_pair``, ``cameras`` (``("00", "01")`` or ``("02", "03")``),
    ``timestamps_ns`` (int64 ns since the first stamp of the left ``timestamps.txt``),
    ``start_time_ns`` (that first stamp, ns since 1970 as written), ``times_path``.
    """

    def __init__(self, path: str | Path, color: bool | None = None, calib: str | Path | None = None) -> None:
        path = Path(path)
        if not path.is_dir():
            raise SequenceError("KITTI raw drive folder not found", path)
        drive = resolve_kitti_raw_drive(path)
        if drive is None:
            raise SequenceError(
                "not a KITTI raw drive folder: image_00/ and image_01/ (or image_02/ and image_03/) not found", path
            )
        pairs = kitti_raw_pairs(drive)
        if color is True:
            if "colour" not in pairs:
                raise SequenceError(
                    "colour frames asked for, but the drive has no colour pair image_02/ and image_03/ "
                    "(only image_00/ and image_01/, gray)",
                    drive,
                )
            kind = "colour"
        else:
            kind = "gray" if "gray" in pairs else "colour"
        colour_pair = kind == "colour"
        self.drive = drive
        self.uses_colour_pair = colour_pair
        self.cameras = KITTI_RAW_COLOUR_PAIR if colour_pair else KITTI_RAW_GRAY_PAIR
        lcam, rcam = pairs[kind]
        left_dir, right_dir = _data_dir(lcam), _data_dir(rcam)
        left, right = list_image_pairs(left_dir, right_dir, drive)
        size = image_size(left[0])
        if calib is not None:
            calibration = load_stereo_yaml(calib, size)
            calib_path = Path(calib)
        else:
            calib_path = drive.parent / CALIB_CAM_TO_CAM
            calibration = load_kitti_raw_calib(calib_path, size, color=colour_pair, image_path=left[0])
        numbers = _frame_numbers(left)
        self.times_path = lcam / TIMESTAMPS
        ns = _stamps_for(self.times_path, numbers)
        if (rcam / TIMESTAMPS).is_file():  # checked like the left one; the frames use the left stamps
            rns = _stamps_for(rcam / TIMESTAMPS, numbers)
            _check_pair_stamps(ns[numbers], rns[numbers], self.times_path, rcam / TIMESTAMPS)
        self.start_time_ns = int(ns[0])
        self.timestamps_ns = (ns - ns[0])[numbers]
        super().__init__(
            name=drive.name,
            path=drive,
            left_paths=left,
            right_paths=right,
            timestamps=self.timestamps_ns.astype(np.float64) * 1e-9,
            calibration=calibration,
            color=colour_pair if color is None else bool(color),
            calib_path=calib_path,
            left_dir=left_dir,
            right_dir=right_dir,
            timestamp_source="timestamps.txt",
        )


# --------------------------------------------------------------------------- OXTS ground truth


@dataclass(frozen=True)
class OxtsGroundTruth:
    """Poses of a KITTI raw drive's rectified camera 0 from its ``oxts/`` (module doc).

    ``poses``: ``(N, 4, 4)`` camera-to-first-camera; ``timestamps``: ``(N,)`` seconds (the
    frames' stamps, see ``stamp_source``); ``oxts_stamps_ns``: the packets' own stamps (int64
    ns since 1970 as written, or None without ``oxts/timestamps.txt``); ``packets``: ``(N, 30)``
    raw packets; ``T_cam_imu``: the 4x4 IMU -> rectified camera 0 transform; ``drive``;
    ``at``: ``"images"`` when each pose was moved to its image's stamp, else ``"packets"``.
    """

    poses: np.ndarray
    timestamps: np.ndarray
    stamp_source: str
    oxts_stamps_ns: np.ndarray | None
    packets: np.ndarray
    T_cam_imu: np.ndarray
    drive: Path
    at: str = "packets"  # "images" when the poses were moved to the images' stamps

    def field(self, name: str) -> np.ndarray:
        """One packet column by its dataformat name (``"vf"``, ``"lat"``, ...)."""
        return self.packets[:, OXTS_NAMES.index(name)]


def oxts_dir(path: str | Path) -> Path | None:
    """The ``oxts/`` folder (with ``data/``) of a drive folder, of its date folder's only drive,
    or ``path`` itself when it is one; None otherwise."""
    path = Path(path)
    if path.name == OXTS and (path / "data").is_dir():
        return path
    try:
        drive = resolve_kitti_raw_drive(path)
    except SequenceError:
        return None
    if drive is not None and (drive / OXTS / "data").is_dir():
        return drive / OXTS
    return None


def read_oxts_packets(oxts: str | Path) -> np.ndarray:
    """``(N, 30)`` float64 packets of ``oxts/data/0000000000.txt ...`` (frames 0..N-1, each
    file one line of 30 numbers).  SequenceError naming the file for a missing, empty or
    malformed one, or a gap in the numbering."""
    data = Path(oxts) / "data"
    files = sorted(data.glob("*.txt")) if data.is_dir() else []
    if not files:
        raise SequenceError("no OXTS packets (expected data/0000000000.txt, ...)", Path(oxts))
    numbers = _frame_numbers(files)
    gap = np.flatnonzero(numbers != np.arange(len(files)))
    if gap.size:
        k = int(gap[0])
        raise SequenceError(f"OXTS packet {k:010d}.txt missing (packets must be numbered 0..N-1 like the frames)", data)
    out = np.empty((len(files), OXTS_FIELDS), dtype=np.float64)
    for k, f in enumerate(files):
        try:
            toks = f.read_text(encoding="utf-8", errors="replace").split()
        except OSError as e:
            raise SequenceError(f"cannot read OXTS packet: {e.strerror}", f) from None
        if len(toks) != OXTS_FIELDS:
            raise SequenceError(f"OXTS packet has {len(toks)} numbers, expected {OXTS_FIELDS} (see dataformat.txt)", f)
        try:
            out[k] = [float(t) for t in toks]
        except ValueError:
            bad = next(t for t in toks if not _is_number(t))
            raise SequenceError(f"OXTS packet: {bad[:30]!r} is not a number", f) from None
        if not np.isfinite(out[k, :6]).all():
            raise SequenceError("OXTS packet: non-finite position or orientation", f)
    return out


def _is_number(t: str) -> bool:
    try:
        float(t)
        return True
    except ValueError:
        return False


def oxts_imu_poses(packets: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` IMU-to-world poses ``T_w_imu`` of OXTS packets: Mercator with the first
    packet's latitude scale, translation relative to the first packet, ``Rz·Ry·Rx``."""
    p = np.asarray(packets, dtype=np.float64)
    lat, lon, alt = p[:, 0], p[:, 1], p[:, 2]
    scale = np.cos(np.deg2rad(lat[0]))
    t = np.column_stack([scale * lon * np.pi * EARTH_RADIUS / 180.0,
                         scale * EARTH_RADIUS * np.log(np.tan((90.0 + lat) * np.pi / 360.0)),
                         alt])
    cr, sr = np.cos(p[:, 3]), np.sin(p[:, 3])
    cp, sp = np.cos(p[:, 4]), np.sin(p[:, 4])
    cy, sy = np.cos(p[:, 5]), np.sin(p[:, 5])
    R = np.empty((len(p), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[:, 1, 0], R[:, 1, 1], R[:, 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = -sp, cp * sr, cp * cr
    T = np.broadcast_to(np.eye(4), (len(p), 4, 4)).copy()
    T[:, :3, :3] = R
    T[:, :3, 3] = t - t[0]
    return T


def _rigid(path: Path) -> np.ndarray:
    """The 4x4 transform of a KITTI raw ``R: ...``/``T: ...`` calibration file."""
    rows = read_kitti_calib_rows(path)
    T = np.eye(4)
    for key, n in (("R", 9), ("T", 3)):
        toks = rows.get(key)
        if toks is None or len(toks) != n:
            what = "missing" if toks is None else f"has {len(toks)} numbers"
            raise CalibrationError(f"row '{key}:' {what}, expected {n} numbers", path)
        try:
            v = np.array([float(x) for x in toks])
        except ValueError:
            raise CalibrationError(f"row '{key}:' holds a value that is not a number", path) from None
        if key == "R":
            T[:3, :3] = v.reshape(3, 3)
        else:
            T[:3, 3] = v
    return T


def kitti_raw_cam0_from_imu(date_dir: str | Path) -> np.ndarray:
    """The 4x4 IMU -> rectified camera 0 transform ``R_rect_00 · T_velo_to_cam · T_imu_to_velo``
    from the calibration files of a date folder."""
    d = Path(date_dir)
    T_velo_imu = _rigid(d / CALIB_IMU_TO_VELO)
    T_cam_velo = _rigid(d / CALIB_VELO_TO_CAM)
    path = d / CALIB_CAM_TO_CAM
    toks = read_kitti_calib_rows(path).get("R_rect_00")
    if toks is None or len(toks) != 9 or not all(_is_number(t) for t in toks):
        raise CalibrationError("row 'R_rect_00:' missing or not 9 numbers (needed for OXTS ground truth)", path)
    R_rect = np.eye(4)
    R_rect[:3, :3] = np.array([float(t) for t in toks]).reshape(3, 3)
    return R_rect @ T_cam_velo @ T_velo_imu


def oxts_shift(T_w_imu: np.ndarray, packets: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """IMU poses ``T_w_imu`` (N, 4, 4) moved by ``dt`` (N,) seconds with each packet's own
    motion: world velocity ``(ve, vn, vu)`` (the Mercator frame's east, north, up) and body
    angular rate ``(wx, wy, wz)`` (rotation ``R · Exp(w dt)``)."""
    p = np.asarray(packets, dtype=np.float64)
    dt = np.asarray(dt, dtype=np.float64)
    col = OXTS_NAMES.index
    out = T_w_imu.copy()
    out[:, :3, 3] += p[:, [col("ve"), col("vn"), col("vu")]] * dt[:, None]
    phi = p[:, [col("wx"), col("wy"), col("wz")]] * dt[:, None]  # rotation vectors, body frame
    th = np.linalg.norm(phi, axis=1)
    K = np.zeros((len(p), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    K -= K.transpose(0, 2, 1)
    safe = np.where(th > 1e-12, th, 1.0)
    a = np.where(th > 1e-12, np.sin(th) / safe, 1.0)
    b = np.where(th > 1e-12, (1.0 - np.cos(th)) / safe**2, 0.5)
    Exp = np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)
    out[:, :3, :3] = T_w_imu[:, :3, :3] @ Exp
    return out


def kitti_raw_ground_truth(path: str | Path, at: str = "images") -> OxtsGroundTruth:
    """The rectified camera-0 poses of a KITTI raw drive from its ``oxts/`` (module doc).

    ``path``: the drive folder, its date folder (one drive) or the ``oxts/`` folder.  ``at``:
    ``"images"`` (each packet's pose moved to its image's stamp) or ``"packets"`` (the
    devkit's poses, at the packets' own stamps).  SequenceError / CalibrationError naming the
    file that is missing or malformed.
    """
    if at not in GT_AT:
        raise ValueError(f"at must be one of {', '.join(GT_AT)}, not {at!r}")
    path = Path(path)
    ox = oxts_dir(path)
    if ox is None:
        raise SequenceError("no KITTI raw OXTS ground truth here (expected a drive folder with oxts/data/)", path)
    drive = ox.parent
    packets = read_oxts_packets(ox)
    T_cam_imu = kitti_raw_cam0_from_imu(drive.parent)
    n = len(packets)
    oxts_ns = read_kitti_raw_timestamps(ox / TIMESTAMPS) if (ox / TIMESTAMPS).is_file() else None
    if oxts_ns is not None and len(oxts_ns) < n:
        raise SequenceError(f"{len(oxts_ns)} timestamps for {n} OXTS packets", ox / TIMESTAMPS)
    img_times = drive / f"image_{KITTI_RAW_GRAY_PAIR[0]}" / TIMESTAMPS
    if not img_times.is_file():
        img_times = drive / f"image_{KITTI_RAW_COLOUR_PAIR[0]}" / TIMESTAMPS
    img_ns = read_kitti_raw_timestamps(img_times) if img_times.is_file() else None
    from_images = img_ns is not None and len(img_ns) >= n
    if from_images:
        ns, source = img_ns[:n], str(img_times.relative_to(drive))
    elif oxts_ns is not None:
        ns, source = oxts_ns[:n], f"{OXTS}/{TIMESTAMPS}"
    else:
        ns, source = np.arange(n, dtype=np.int64) * 100_000_000, "10 Hz (no timestamps.txt)"
    T_w_imu = oxts_imu_poses(packets)
    shifted = at == "images" and from_images and oxts_ns is not None
    if shifted:
        T_w_imu = oxts_shift(T_w_imu, packets, (ns - oxts_ns[:n]).astype(np.float64) * 1e-9)
    T_w_cam = T_w_imu @ np.linalg.inv(T_cam_imu)
    poses = np.linalg.inv(T_w_cam[0]) @ T_w_cam
    poses[:, 3] = (0.0, 0.0, 0.0, 1.0)
    poses[0] = np.eye(4)
    return OxtsGroundTruth(poses=poses, timestamps=(ns - ns[0]).astype(np.float64) * 1e-9, stamp_source=source,
                           oxts_stamps_ns=None if oxts_ns is None else oxts_ns[:n], packets=packets,
                           T_cam_imu=T_cam_imu, drive=drive, at="images" if shifted else "packets")
