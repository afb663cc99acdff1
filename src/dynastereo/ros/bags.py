"""Bag files without a ROS installation (the ``rosbags`` library): ROS 1 ``.bag``,
ROS 2 ``.db3`` (sqlite3) and ``.mcap``.

* :func:`bag_format` -- ``"ros1"``, ``"ros2"`` or ``"mcap"`` for a path (a ``.bag`` file; a
  ``.db3`` / ``.mcap`` storage file; or a ROS 2 bag directory with ``metadata.yaml``).
* :class:`BagStereoSequence` -- the :class:`~dynastereo.io.base.Sequence` protocol over two
  image topics of a bag: left and right messages are paired by header stamp within a
  tolerance (one-to-one, nearest first); unpaired messages are counted
  (``unpaired_left``/``unpaired_right``) and skipped, never mixed.  Calibration comes from
  an explicit YAML/ORB-SLAM2 file, else from the bag's ``sensor_msgs/CameraInfo`` (raw
  images are rectified with it), else it is an error naming what is missing.
* :class:`BagWriter` -- writes messages built by
  :class:`~dynastereo.ros.messages.RosbagsBuilder` into any of the three formats.  ROS 2
  outputs are single storage files (``X.db3`` / ``X.mcap``, readable by ``rosbags``
  and by ``ros2 bag`` of Humble and later) -- no ``metadata.yaml`` directory.
* :func:`export_bag` -- a stereo sequence folder (KITTI layout, EuRoC, generic) as a bag
  on ``/camera/{left,right}/image_raw`` + ``/camera/{left,right}/camera_info`` with the
  sequence's stamps (KITTI: ``times.txt``).
* :func:`read_odometry`, :func:`bag_topics`, :func:`read_messages` -- for reading results.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import CalibrationError, InputError, SequenceError
from ..io.calib import RawStereoCalibration, check_intrinsics, load_stereo_yaml
from ..io.euroc import pair_by_timestamp
from ..io.rectify import Rectifier
from ..io.sequence import check_plausible
from ..yamlcheck import yaml_error_line
from ..datatypes import StereoCalibration, StereoFrame
from .convert import ImageDecoder, calibration_from_camera_info, CameraInfoData, camera_info_fields
from .messages import (
    DEFAULT_LEFT_FRAME,
    DEFAULT_LEFT_INFO,
    DEFAULT_LEFT_TOPIC,
    DEFAULT_RIGHT_FRAME,
    DEFAULT_RIGHT_INFO,
    DEFAULT_RIGHT_TOPIC,
    RosbagsBuilder,
    msg_type_name,
    rosbags_typestore,
)

log = logging.getLogger("dynastereo.ros")

BAG_FORMATS = ("ros1", "ros2", "mcap")
BAG_SUFFIX = {"ros1": ".bag", "ros2": ".db3", "mcap": ".mcap"}
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
DEFAULT_SYNC_TOLERANCE_S = 0.005
EXPORT_ENCODINGS = ("auto", "mono8", "mono16", "bgr8", "rgb8", "png", "jpeg")


# --------------------------------------------------------------------------- formats


def _storage_identifier(text: str, meta: Path) -> str | None:
    """``storage_identifier`` of a ROS 2 bag's ``metadata.yaml``; InputError naming the
    file and the line for a YAML syntax error."""
    import yaml

    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise InputError(f"YAML syntax error: {yaml_error_line(e)}", meta) from None
    info = d.get("rosbag2_bagfile_information", d) if isinstance(d, dict) else None
    if not isinstance(info, dict):
        raise InputError("not a ROS 2 bag's metadata (no rosbag2_bagfile_information mapping)", meta)
    sid = info.get("storage_identifier")
    return str(sid) if sid is not None else None


def bag_format(path: str | Path) -> str:
    """``"ros1"``, ``"ros2"`` (sqlite3) or ``"mcap"`` for a bag path; InputError otherwise."""
    p = Path(path)
    if not p.exists():
        raise InputError("bag not found", p)
    if p.is_dir():
        meta = p / "metadata.yaml"
        if not meta.is_file():
            raise InputError("a directory, but not a ROS 2 bag (no metadata.yaml)", p)
        text = meta.read_text(errors="replace")
        sid = _storage_identifier(text, meta)
        if sid == "mcap":
            return "mcap"
        if sid == "sqlite3":
            return "ros2"
        raise InputError(f"ROS 2 bag with an unknown storage_identifier {sid!r} (sqlite3 and mcap are supported)",
                         meta)
    suffix = p.suffix.lower()
    for fmt, s in BAG_SUFFIX.items():
        if suffix == s:
            return fmt
    raise InputError(f"unknown bag type {suffix!r}: expected .bag (ROS 1), .db3 (ROS 2) or .mcap", p)


def check_format(fmt: str) -> str:
    f = str(fmt).lower()
    aliases = {"bag": "ros1", "rosbag": "ros1", "db3": "ros2", "sqlite3": "ros2", "rosbag2": "ros2"}
    f = aliases.get(f, f)
    if f not in BAG_FORMATS:
        raise InputError(f"bag format must be one of {', '.join(BAG_FORMATS)}, got {fmt!r}")
    return f


# The first bytes of each bag file format (a ROS 2 bag folder's storage file included).
BAG_MAGIC = {"ros1": (b"#ROSBAG V2.0\n", "a ROS 1 bag (no '#ROSBAG V2.0' header)"),
             "ros2": (b"SQLite format 3\x00", "a ROS 2 sqlite3 bag (not an SQLite database)"),
             "mcap": (b"\x89MCAP0\r\n", "an MCAP file (no MCAP magic)")}


def check_bag_magic(path: Path) -> None:
    """InputError unless the bag file (or each storage file of a bag folder) starts with
    its format's magic bytes: a damaged or foreign file gets a plain message instead of
    the reader's decoding error."""
    fmt = bag_format(path)
    files = sorted(p for p in path.iterdir() if p.suffix in (".db3", ".mcap")) if path.is_dir() else [path]
    magic, what = BAG_MAGIC[fmt]
    for f in files:
        try:
            with open(f, "rb") as fh:
                head = fh.read(len(magic))
        except OSError as e:
            raise InputError(f"cannot read bag: {e.strerror or e}", f) from None
        if head != magic:
            raise InputError(f"not {what}: the file is damaged, truncated or of another kind "
                             f"(it starts with {head[:8]!r})", f)


def _open_reader(path: Path):
    from rosbags.highlevel import AnyReader

    check_bag_magic(path)
    try:
        r = AnyReader([path], default_typestore=rosbags_typestore(False))
        r.open()
    except Exception as e:  # rosbags raises its own error classes
        raise InputError(f"cannot open bag (damaged or truncated?): {e}", path) from None
    return r


def bag_topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """``{topic: (message type, message count)}`` of a bag."""
    r = _open_reader(Path(path))
    try:
        out: dict[str, tuple[str, int]] = {}
        for c in r.connections:
            t, n = out.get(c.topic, (c.msgtype, 0))
            out[c.topic] = (t, n + int(c.msgcount))
        return out
    finally:
        r.close()


def read_messages(path: str | Path, topics: list[str] | None = None) -> Iterator[tuple[str, int, Any]]:
    """``(topic, bag time ns, deserialized message)`` for ``topics`` (all when None), in time order."""
    r = _open_reader(Path(path))
    try:
        conns = [c for c in r.connections if topics is None or c.topic in topics]
        if topics is not None:
            missing = set(topics) - {c.topic for c in conns}
            if missing:
                raise InputError(f"topics not in the bag: {', '.join(sorted(missing))}", path)
        for c, t, raw in r.messages(connections=conns):
            yield c.topic, t, r.deserialize(raw, c.msgtype)
    finally:
        r.close()


def header_ns(msg: Any) -> int:
    st = msg.header.stamp
    sec = getattr(st, "sec", None)
    if sec is None:
        sec = st.secs
    nsec = getattr(st, "nanosec", None)
    if nsec is None:
        nsec = st.nsecs
    return int(sec) * 1_000_000_000 + int(nsec)


def read_odometry(path: str | Path, topic: str = "/dynastereo/odometry") -> tuple[np.ndarray, np.ndarray]:
    """``(stamps ns (N,), poses (N, 4, 4))`` of the ``nav_msgs/Odometry`` on ``topic``."""
    from scipy.spatial.transform import Rotation

    stamps, pos, quat = [], [], []
    for _, _, m in read_messages(path, [topic]):
        stamps.append(header_ns(m))
        p, q = m.pose.pose.position, m.pose.pose.orientation
        pos.append((p.x, p.y, p.z))
        quat.append((q.x, q.y, q.z, q.w))
    T = np.broadcast_to(np.eye(4), (len(stamps), 4, 4)).copy()
    if stamps:
        T[:, :3, :3] = Rotation.from_quat(np.asarray(quat)).as_matrix()
        T[:, :3, 3] = np.asarray(pos)
    return np.asarray(stamps, dtype=np.int64), T


# --------------------------------------------------------------------------- writing


def _ros1_lz4(writer: Any) -> None:
    """LZ4 chunks that ROS 1's own reader (roslz4: ``rosbag play``, ``rosbag.Bag``) accepts:
    independent blocks, content checksum, no stored size.  rosbags' default LZ4 frames are
    refused by roslz4 ("malformed data"), so its compressor is replaced; without the
    hook (another rosbags version) the bag is written uncompressed."""
    if not hasattr(writer, "compressor"):
        return
    import lz4.frame

    writer.set_compression(type(writer).CompressionFormat.LZ4)
    writer.compressor = lambda data: lz4.frame.compress(data, store_size=False, content_checksum=True,
                                                        block_linked=False)


class BagWriter:
    """Write messages into a ``ros1`` / ``ros2`` / ``mcap`` bag at ``path`` (a file).

    ``overwrite``: replace an existing file (else InputError).  Use as a context manager;
    ``add(topic, type)`` before ``write(topic, stamp_ns, msg)``; ``builder`` builds messages.
    The bag is written under a temporary name beside ``path`` and renamed into place when
    it is closed: an earlier bag at ``path`` is replaced only by a complete one.  A write
    that fails (or a signal) leaves an earlier bag as it was; without one, the frames
    written so far are kept at ``path`` (a closed, readable bag).
    """

    def __init__(self, path: str | Path, fmt: str, overwrite: bool = False) -> None:
        import secrets

        self.fmt = check_format(fmt)
        self.path = Path(path)
        self._earlier = self.path.exists() or self.path.is_symlink()
        if self._earlier:
            if not overwrite:
                raise InputError("output bag exists already (--overwrite replaces it, or choose another name)",
                                 self.path)
            if self.path.is_dir():
                raise InputError("output bag is a folder, not a file", self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.builder = RosbagsBuilder(ros1=self.fmt == "ros1")
        self.counts: dict[str, int] = {}
        self._conns: dict[str, Any] = {}
        self._tmp: Path | None = None
        self._part: Path | None = None
        if self.fmt == "ros1":
            from rosbags.rosbag1 import Writer

            self._part = self.path.with_name(f".{self.path.stem}.{secrets.token_hex(4)}.part{self.path.suffix}")
            self._writer = Writer(self._part)
            _ros1_lz4(self._writer)
        else:
            from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

            # rosbags writes <dir>/<dir name>.<ext> + metadata.yaml; we keep the storage file
            self._tmp = Path(tempfile.mkdtemp(prefix=".bagtmp-", dir=self.path.parent))
            plugin = StoragePlugin.SQLITE3 if self.fmt == "ros2" else StoragePlugin.MCAP
            self._writer = Writer(self._tmp / self.path.stem, version=9, storage_plugin=plugin)
            if self.fmt == "mcap":  # zstd-compressed chunks inside the file (standard MCAP)
                self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        try:
            self._writer.open()
        except BaseException:
            self._discard()
            raise

    def add(self, topic: str, msgtype: str) -> None:
        if topic in self._conns:
            return
        t = msg_type_name(msgtype)
        self._conns[topic] = self._writer.add_connection(topic, t, typestore=self.builder.typestore)
        self.counts[topic] = 0

    def write(self, topic: str, stamp_ns: int, msg: Any) -> None:
        if topic not in self._conns:
            self.add(topic, msg.__msgtype__)
        self._writer.write(self._conns[topic], int(stamp_ns), self.builder.serialize(msg))
        self.counts[topic] += 1

    def _produced(self) -> Path:
        if self._part is not None:
            return self._part
        assert self._tmp is not None
        return self._tmp / self.path.stem / (self.path.stem + BAG_SUFFIX[self.fmt])

    def _discard(self) -> None:
        """Remove the temporary bag (an earlier bag at ``path`` stays)."""
        if self._part is not None:
            self._part.unlink(missing_ok=True)
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)

    def close(self, keep: bool = True) -> None:
        """Close the bag and rename it into place (``keep=False``: discard it)."""
        if self._writer is None:
            return
        w, self._writer = self._writer, None
        try:
            w.close()
            if keep:
                os.replace(self._produced(), self.path)
        finally:
            self._discard()

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, exc_type: Any, *exc: object) -> None:
        # a failed or interrupted export: an earlier bag stays whole; else the frames so far are kept
        self.close(keep=exc_type is None or not self._earlier)


# --------------------------------------------------------------------------- reading stereo


@dataclass
class _Msg:
    stamp_ns: int  # header stamp (bag time when the header is unset)
    bag_ns: int  # bag (receive) time: where to find the message again


def _jumps_back(msgs: list[_Msg], topic: str) -> str | None:
    """Where the header stamps of ``msgs`` (in bag order) first go back in time, or None."""
    if len(msgs) < 2:
        return None
    h = np.array([m.stamp_ns for m in msgs], np.int64)[np.argsort([m.bag_ns for m in msgs], kind="stable")]
    back = np.flatnonzero(np.diff(h) < 0)
    if not back.size:
        return None
    k = int(back[0])
    return f"{topic} message {k + 1}: {h[k] * 1e-9:.3f} s -> {h[k + 1] * 1e-9:.3f} s"


def _sibling_info(topic: str) -> str:
    base = topic[: -len("/compressed")] if topic.endswith("/compressed") else topic
    return base.rsplit("/", 1)[0] + "/camera_info" if "/" in base.strip("/") else "camera_info"


@dataclass
class PairingReport:
    """How left/right messages were paired (``bag.json``)."""

    left_topic: str
    right_topic: str
    left_messages: int
    right_messages: int
    pairs: int
    unpaired_left: int
    unpaired_right: int
    tolerance_s: float
    left_info: str | None
    right_info: str | None
    calibration_source: str
    rectified_on_read: bool
    stamps: str  # "header" or "bag time"
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        from dataclasses import asdict

        return asdict(self)


class BagStereoSequence:
    """Stereo pairs from two image topics of a bag (the Sequence protocol; module doc).

    ``left_info``/``right_info``: CameraInfo topics; ``"auto"`` = ``camera_info`` beside the
    image topic if the bag has it; ``None`` = ignore CameraInfo.  ``calib``: a calibration
    YAML / ORB-SLAM2 settings file (or a calibration object) that wins over CameraInfo.
    ``tolerance_s``: largest left/right stamp difference of a pair.  ``rectify``: ``auto``,
    ``yes``, ``no`` (see :func:`~dynastereo.ros.convert.calibration_from_camera_info`).
    ``fallback_calib``: a calibration file used only when the bag has no CameraInfo.
    """

    timestamp_source = "bag header stamps (left image)"

    def __init__(
        self,
        path: str | Path,
        left_topic: str = DEFAULT_LEFT_TOPIC,
        right_topic: str = DEFAULT_RIGHT_TOPIC,
        left_info: str | None = "auto",
        right_info: str | None = "auto",
        calib: str | Path | StereoCalibration | RawStereoCalibration | None = None,
        tolerance_s: float = DEFAULT_SYNC_TOLERANCE_S,
        rectify: str = "auto",
        mono16_shift: int | None = None,
        fallback_calib: str | Path | None = None,
    ) -> None:
        self.path = Path(path)
        self.format = bag_format(self.path)
        self.name = self.path.stem
        if not tolerance_s >= 0:
            raise InputError(f"pairing tolerance (--sync-tolerance, in ms) must be >= 0 ms, got {tolerance_s * 1000:g} ms")
        self._reader = _open_reader(self.path)
        self.decoder = ImageDecoder(mono16_shift)
        try:
            self._fallback_calib = fallback_calib
            self._setup(left_topic, right_topic, left_info, right_info, calib, float(tolerance_s), rectify)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ setup
    def _conn(self, topic: str, kinds: tuple[str, ...], what: str):
        conns = [c for c in self._reader.connections if c.topic == topic]
        if not conns and kinds == IMAGE_TYPES:
            alt = topic.rstrip("/") + "/compressed"
            conns = [c for c in self._reader.connections if c.topic == alt]
        if not conns:
            have = sorted({c.topic for c in self._reader.connections if c.msgtype in kinds})
            raise SequenceError(
                f"{what} topic {topic!r} not in the bag; {', '.join(kinds)} topics there: {', '.join(have) or 'none'}",
                self.path)
        types = {c.msgtype for c in conns}
        if not types <= set(kinds):
            raise SequenceError(f"{what} topic {conns[0].topic!r} has type {', '.join(sorted(types))}, "
                                f"expected {' or '.join(kinds)}", self.path)
        return conns

    def _scan(self, conns) -> tuple[list[_Msg], int]:
        out: list[_Msg] = []
        zero = 0
        for c, t, raw in self._reader.messages(connections=conns):
            m = self._reader.deserialize(raw, c.msgtype)
            h = header_ns(m)
            zero += h == 0
            out.append(_Msg(h, int(t)))
        return out, zero

    def _setup(self, left_topic, right_topic, left_info, right_info, calib, tol, rectify) -> None:
        n_left, n_right, n_pairs, stamps, notes = self._pair(left_topic, right_topic, tol)
        calibration, raw_size, source, li, ri = self._calibrate(left_info, right_info, calib, rectify)
        self.rectifier: Rectifier | None = None
        if isinstance(calibration, RawStereoCalibration):
            self.rectifier = Rectifier(calibration)
            self.calibration: StereoCalibration = self.rectifier.calibration
        else:
            self.calibration = calibration
        self.raw_size = raw_size
        self.frame_id = self._frame_id(self._lconns, self._left[0]) or DEFAULT_LEFT_FRAME
        self.report = PairingReport(
            left_topic=self.left_topic, right_topic=self.right_topic, left_messages=n_left,
            right_messages=n_right, pairs=n_pairs, unpaired_left=self.unpaired_left,
            unpaired_right=self.unpaired_right, tolerance_s=tol, left_info=li, right_info=ri,
            calibration_source=source, rectified_on_read=self.rectifier is not None, stamps=stamps, notes=notes)

    def _pair(self, left_topic: str, right_topic: str, tol: float) -> tuple[int, int, int, str, list[str]]:
        """The left and right image messages paired by stamp (within ``tol`` seconds):
        ``self._left`` / ``self._right`` / ``self.stamps_ns``.  Returns ``(left messages,
        right messages, pairs, which stamps paired them, notes)``."""
        self._lconns = self._conn(left_topic, IMAGE_TYPES, "left image")
        self._rconns = self._conn(right_topic, IMAGE_TYPES, "right image")
        self.left_topic, self.right_topic = self._lconns[0].topic, self._rconns[0].topic
        lmsgs, lzero = self._scan(self._lconns)
        rmsgs, rzero = self._scan(self._rconns)
        notes: list[str] = []
        stamps = "header"
        self._bag_time_stamps = False
        if (lmsgs and lzero == len(lmsgs)) or (rmsgs and rzero == len(rmsgs)):
            stamps = "bag time"
            self._bag_time_stamps = True
            notes.append("image headers carry no stamps: paired by bag (receive) time")
            for m in lmsgs + rmsgs:
                m.stamp_ns = m.bag_ns
        back = _jumps_back(lmsgs, self.left_topic) or _jumps_back(rmsgs, self.right_topic)
        if back is not None and not self._bag_time_stamps:
            # sorted by them, frames recorded later would be fed between earlier ones (0, 5, 1, 6, ...)
            stamps = "bag time"
            self._bag_time_stamps = True
            notes.append(f"image header stamps jump back ({back}): ordered and paired by bag (receive) time")
            log.warning("%s: image header stamps jump back (%s): the frames are ordered and paired by bag "
                        "(receive) time instead", self.path, back)
            for m in lmsgs + rmsgs:
                m.stamp_ns = m.bag_ns
        if self._bag_time_stamps:  # run.json's "timestamps" says where they came from
            self.timestamp_source = "bag (receive) time of the left images"
        lmsgs.sort(key=lambda m: (m.stamp_ns, m.bag_ns))
        rmsgs.sort(key=lambda m: (m.stamp_ns, m.bag_ns))
        lns = np.array([m.stamp_ns for m in lmsgs], np.int64)
        rns = np.array([m.stamp_ns for m in rmsgs], np.int64)
        il, ir = pair_by_timestamp(lns, rns, int(round(tol * 1e9)))
        if len(il) == 0:
            raise SequenceError(
                f"no left/right pairs within {tol * 1e3:g} ms ({len(lmsgs)} messages on {self.left_topic}, "
                f"{len(rmsgs)} on {self.right_topic}); raise the tolerance?", self.path)
        self._left = [lmsgs[i] for i in il]
        self._right = [rmsgs[i] for i in ir]
        self.stamps_ns = lns[il]
        self.unpaired_left = len(lmsgs) - len(il)
        self.unpaired_right = len(rmsgs) - len(ir)
        if self.unpaired_left or self.unpaired_right:
            log.warning("%s: %d left and %d right images have no partner within %g ms and are skipped",
                        self.path, self.unpaired_left, self.unpaired_right, tol * 1e3)
        return len(lmsgs), len(rmsgs), len(il), stamps, notes

    def _calibrate(self, left_info, right_info, calib, rectify):
        """The rig's calibration: ``calib`` (a file or a calibration), else the bag's
        CameraInfo, else the fallback file; checked against the images' size.  Returns
        ``(calibration, raw image size, its source, left and right CameraInfo topics)``."""
        topics = {c.topic for c in self._reader.connections}
        li = _sibling_info(self.left_topic) if left_info == "auto" else left_info
        ri = _sibling_info(self.right_topic) if right_info == "auto" else right_info
        if left_info == "auto" and li not in topics:
            li = None
        if right_info == "auto" and ri not in topics:
            ri = None
        first = self._decode(self._lconns, self._left[0])
        raw_size = (first.shape[1], first.shape[0])
        source = ""
        if calib is not None:
            if isinstance(calib, (StereoCalibration, RawStereoCalibration)):
                calibration, source = calib, "given calibration"
            else:
                calibration, source = load_stereo_yaml(calib, raw_size), str(calib)
            if rectify == "no" and isinstance(calibration, RawStereoCalibration):
                raise CalibrationError("rectify=no, but the calibration describes raw cameras", source)
        elif li and ri:
            linfo = self._camera_info(li)
            rinfo = self._camera_info(ri)
            calibration = calibration_from_camera_info(linfo, rinfo, rectify, where=f"{self.path} [{li}, {ri}]")
            source = f"CameraInfo {li} {ri}"
        elif self._fallback_calib is not None:
            calibration, source = load_stereo_yaml(self._fallback_calib, raw_size), str(self._fallback_calib)
        else:
            looked = ", ".join(t for t in (li, ri) if t) or f"{_sibling_info(self.left_topic)}, " \
                                                             f"{_sibling_info(self.right_topic)}"
            raise CalibrationError(
                f"no calibration: no CameraInfo in the bag (looked for {looked}) and no calibration file "
                "given (--left-info/--right-info, --calib YAML, or an ORB-SLAM2 settings file as --config)",
                self.path)
        check_intrinsics(calibration, raw_size, source)
        check_plausible(calibration, raw_size, self.path, source)
        if calibration.size != raw_size:
            raise CalibrationError(f"calibration is for {calibration.width}x{calibration.height} images, "
                                   f"{self.left_topic} carries {raw_size[0]}x{raw_size[1]}", source)
        return calibration, raw_size, source, li, ri

    def _camera_info(self, topic: str) -> CameraInfoData:
        conns = self._conn(topic, (CAMERA_INFO_TYPE,), "CameraInfo")
        first: CameraInfoData | None = None
        changed = 0
        for c, _, raw in self._reader.messages(connections=conns):
            info = CameraInfoData.from_msg(self._reader.deserialize(raw, c.msgtype))
            if first is None:
                first = info
            elif not info.same(first):
                changed += 1
        if first is None:
            raise CalibrationError(f"CameraInfo topic {topic!r} has no messages", self.path)
        if changed:
            raise CalibrationError(f"the calibration on {topic!r} changes during the bag ({changed} messages differ "
                                   "from the first): not supported", self.path)
        return first

    # ------------------------------------------------------------------ reading
    def _message(self, conns, m: _Msg) -> Any:
        """The message ``m`` again: by its bag time, then its header stamp (several
        messages may share a bag time)."""
        for c, t, raw in self._reader.messages(connections=conns, start=m.bag_ns, stop=m.bag_ns + 1):
            msg = self._reader.deserialize(raw, c.msgtype)
            if self._bag_time_stamps or header_ns(msg) == m.stamp_ns:
                return msg
        raise SequenceError(f"message at bag time {m.bag_ns} ns not found again", self.path)

    def _decode(self, conns, m: _Msg) -> np.ndarray:
        topic = conns[0].topic
        return self.decoder.decode(self._message(conns, m), f"{self.path} [{topic}]")

    def _frame_id(self, conns, m: _Msg) -> str:
        return str(getattr(self._message(conns, m).header, "frame_id", "") or "")

    def __len__(self) -> int:
        return len(self._left)

    def timestamps(self) -> np.ndarray:
        return self.stamps_ns.astype(np.float64) * 1e-9

    def frame(self, index: int) -> StereoFrame:
        n = len(self)
        i = int(index) + (n if int(index) < 0 else 0)
        if not 0 <= i < n:
            raise IndexError(f"frame {index} out of range: {self.name} has {n} stereo pairs")
        left = self._decode(self._lconns, self._left[i])
        right = self._decode(self._rconns, self._right[i])
        if left.ndim != right.ndim:  # one side colour, the other gray: use gray for both
            import cv2

            left = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY) if left.ndim == 3 else left
            right = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY) if right.ndim == 3 else right
        for side, img in (("left", left), ("right", right)):
            if (img.shape[1], img.shape[0]) != self.raw_size:
                raise SequenceError(f"{side} image of pair {i} is {img.shape[1]}x{img.shape[0]}, the first was "
                                    f"{self.raw_size[0]}x{self.raw_size[1]}", self.path)
        if self.rectifier is not None:
            left, right = self.rectifier.rectify(left, right)
        return StereoFrame(index=i, timestamp=float(self.stamps_ns[i]) * 1e-9, left=left, right=right)

    def __iter__(self) -> Iterator[StereoFrame]:
        for i in range(len(self)):
            yield self.frame(i)

    def close(self) -> None:
        r, self._reader = getattr(self, "_reader", None), None
        if r is not None:
            r.close()

    def __enter__(self) -> "BagStereoSequence":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        c = self.calibration
        return (f"BagStereoSequence({str(self.path)!r}, {len(self)} pairs, {c.width}x{c.height}, "
                f"unpaired {self.unpaired_left}/{self.unpaired_right})")


# --------------------------------------------------------------------------- export


@dataclass
class ExportResult:
    path: Path
    format: str
    frames: int
    topics: dict[str, int]  # topic -> messages written
    first_stamp_ns: int | None = None  # the first frame's stamp as written


def _exact_projections(seq: Any) -> tuple[np.ndarray | None, np.ndarray | None]:
    """KITTI's own P0/P1 (or P2/P3), so that the baseline round-trips bit-exactly."""
    from ..io.calib import kitti_projections
    from ..io.kitti import KittiSequence

    if isinstance(seq, KittiSequence):
        cp = getattr(seq, "calib_path", None) or Path(seq.path) / "calib.txt"
        if Path(cp).name == "calib.txt" and Path(cp).is_file():
            Pl, Pr = kitti_projections(cp, color=getattr(seq, "uses_colour_pair", False))
            return Pl, Pr
    return None, None


def _convert_for_export(img: np.ndarray, encoding: str) -> tuple[np.ndarray, str | None]:
    if encoding == "auto":
        return img, None
    if encoding == "mono8":
        import cv2

        return (cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img), "mono8"
    if encoding == "mono16":
        import cv2

        g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
        return g.astype(np.uint16) * np.uint16(257), "mono16"
    if encoding in ("bgr8", "rgb8"):
        return img, encoding
    return img, None


def export_bag(
    sequence: Any,
    out: str | Path,
    fmt: str = "ros1",
    *,
    frames: list[int] | None = None,
    encoding: str = "auto",
    raw: bool = False,
    time_offset_s: float = 0.0,
    overwrite: bool = False,
    left_topic: str = DEFAULT_LEFT_TOPIC,
    right_topic: str = DEFAULT_RIGHT_TOPIC,
    left_info: str = DEFAULT_LEFT_INFO,
    right_info: str = DEFAULT_RIGHT_INFO,
    progress: Any = None,
) -> ExportResult:
    """Write ``frames`` of a stereo ``sequence`` (a :class:`~dynastereo.io.base.Sequence`)
    into a bag at ``out`` with its stamps (+ ``time_offset_s``) and CameraInfo.

    ``encoding``: ``auto`` (``mono8`` for gray, ``bgr8`` for colour), ``mono8``, ``mono16``
    (8-bit values times 257), ``bgr8``, ``rgb8``, or ``png``/``jpeg``
    (``sensor_msgs/CompressedImage`` on ``<topic>/compressed``).  ``raw``: for sequences
    that rectify on read (EuRoC), write the raw images and the raw cameras' CameraInfo
    (K, D, R, P) instead of rectified images.
    """
    from ..io.images import read_image

    fmt = check_format(fmt)
    if encoding not in EXPORT_ENCODINGS:
        raise InputError(f"encoding must be one of {', '.join(EXPORT_ENCODINGS)}, got {encoding!r}")
    frames = _all_frames(sequence) if frames is None else list(frames)
    if not frames:
        raise InputError("no frames to export")
    stamps_ns = _export_stamps_ns(sequence, time_offset_s)
    infos = _export_camera_infos(sequence, raw)
    compressed = encoding in ("png", "jpeg")
    lt = left_topic + ("/compressed" if compressed else "")
    rt = right_topic + ("/compressed" if compressed else "")
    color = bool(getattr(sequence, "color", False))
    out = Path(out)
    with BagWriter(out, fmt, overwrite=overwrite) as w:
        b = w.builder
        img_type = "sensor_msgs/CompressedImage" if compressed else "sensor_msgs/Image"
        for t, ty in ((lt, img_type), (rt, img_type), (left_info, "sensor_msgs/CameraInfo"),
                      (right_info, "sensor_msgs/CameraInfo")):
            w.add(t, ty)
        for k, idx in enumerate(frames):
            if raw:
                left = read_image(sequence.left_paths[idx], color)
                right = read_image(sequence.right_paths[idx], color)
            else:
                f = sequence.frame(idx)
                left, right = f.left, f.right
            ns = int(stamps_ns[idx])
            for topic, img, frame_id in ((lt, left, DEFAULT_LEFT_FRAME), (rt, right, DEFAULT_RIGHT_FRAME)):
                w.write(topic, ns, _image_message(b, img, ns, frame_id, encoding, k))
            w.write(left_info, ns, b.camera_info(infos[0], ns, DEFAULT_LEFT_FRAME, seq=k))
            w.write(right_info, ns, b.camera_info(infos[1], ns, DEFAULT_RIGHT_FRAME, seq=k))
            if progress is not None:
                progress(k + 1, len(frames))
        counts = dict(w.counts)
    return ExportResult(out, fmt, len(frames), counts, int(stamps_ns[frames[0]]))


def _all_frames(sequence: Any) -> list[int]:
    """Every frame index that has images (KITTI numbering may have gaps)."""
    available = getattr(sequence, "available_frames", None)
    return list(available()) if available is not None else list(range(len(sequence)))


def _export_stamps_ns(sequence: Any, time_offset_s: float) -> np.ndarray:
    """Every frame's stamp in nanoseconds, shifted by ``time_offset_s`` (exact nanoseconds
    where the sequence keeps them, as EuRoC does); InputError for negative stamps."""
    exact = getattr(sequence, "timestamps_ns", None)
    if exact is not None and len(exact) == len(sequence):
        stamps_ns = np.asarray(exact, np.int64) + int(round(float(time_offset_s) * 1e9))
    else:
        stamps = np.asarray(sequence.timestamps(), dtype=np.float64) + float(time_offset_s)
        stamps_ns = np.round(stamps * 1e9).astype(np.int64)
    if np.any(stamps_ns < 0):
        raise InputError(f"timestamps must be >= 0 s: the time offset (--time-offset, in s) of {float(time_offset_s):g} s "
                         f"makes the first {float(-stamps_ns.min()) * 1e-9:g} s negative")
    return stamps_ns


def _export_camera_infos(sequence: Any, raw: bool) -> tuple[dict[str, Any], dict[str, Any]]:
    """Left and right CameraInfo fields: the rectified cameras, or with ``raw`` the raw
    ones (K, D, R, P) of a sequence that rectifies on read."""
    rect = getattr(sequence, "rectifier", None)
    if raw:
        if rect is None:
            raise InputError("--raw: this sequence is rectified already (no raw calibration to export)",
                             getattr(sequence, "path", None))
        rc = rect.raw
        return (camera_info_fields(P=rect.P1, K=rc.K1, D=rc.D1, R=rect.R1, width=rc.width, height=rc.height),
                camera_info_fields(P=rect.P2, K=rc.K2, D=rc.D2, R=rect.R2, width=rc.width, height=rc.height))
    Pl, Pr = _exact_projections(sequence)
    return (camera_info_fields(sequence.calibration, "left", P=Pl),
            camera_info_fields(sequence.calibration, "right", P=Pr))


def _image_message(b: Any, img: np.ndarray, ns: int, frame_id: str, encoding: str, seq: int) -> Any:
    """One image as ``sensor_msgs/CompressedImage`` (png, jpeg) or ``sensor_msgs/Image``."""
    if encoding in ("png", "jpeg"):
        return b.compressed(img, ns, frame_id, encoding, seq=seq)
    conv, enc = _convert_for_export(img, encoding)
    return b.image(conv, ns, frame_id, enc, seq=seq)
