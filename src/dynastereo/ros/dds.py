"""ROS 2 on the wire, without rclpy: message types, codecs and QoS over Cyclone DDS.

ROS 2 topics are DDS topics.  A ROS 2 message ``pkg/msg/Name`` travels as the DDS type
``pkg::msg::dds_::Name_`` in XCDR1 (little endian, the 4-byte encapsulation header
``00 01 00 00``), a topic ``/a/b`` as ``rt/a/b``, a service ``/s`` as the topic pair
``rq/sRequest`` / ``rr/sReply`` whose samples start with a 16-byte request header (the
client's 64-bit id and the request's sequence number), as ``rmw_cyclonedds_cpp`` lays them
out.  So a process that speaks DDS with these names and bytes is, on the wire, a ROS 2
node; ``rmw_fastrtps_cpp`` nodes reach it through RTPS as well.

* :func:`idl_type` -- the ``cyclonedds`` IdlStruct of a ROS 2 message, made from the
  definitions of rosbags' ROS 2 Humble typestore (their field names, types and order);
  the topic is created with it (DDS matches writers and readers by type name and type).
* :func:`encode` -- a message's serialized bytes.  The image-carrying messages (``Image``,
  ``CompressedImage``, ``PointCloud2``, ``DisparityImage``) are written here with numpy
  (:class:`CdrWriter`: the pixels are copied once, at memory speed); the others, small,
  by cyclonedds' own serializer.  ``tests/test_ros2.py`` checks both against rosbags' ROS 2
  serializer, byte for byte.
* :func:`decode_image` / :func:`decode_compressed` -- the received image messages as numpy
  views of the sample's bytes (cyclonedds' generic decoder would make a Python list of
  every byte); the rest with cyclonedds (:func:`decode`).
* :class:`DdsBuilder` -- :class:`~dynastereo.ros.messages.MessageBuilder` for these types:
  the node publishes what the bag writer and the ROS 1 node publish.
* :func:`qos` -- ROS 2's QoS conventions (sensor data best effort, state reliable, latched
  topics transient local); :class:`Domain` -- the participant (``ROS_DOMAIN_ID``), raw
  writers and readers (bytes in, bytes out) and ``ros_discovery_info``.

``cyclonedds`` is the ``ros2`` extra (``pip install 'dynastereo[ros2]'``);
:func:`import_cyclonedds` says so in one line when it is missing.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass, fields as dc_fields
from functools import lru_cache
from typing import Any

import numpy as np

from ..errors import InputError, RosUnavailable
from .convert import stamp_split
from .messages import MessageBuilder, msg_type_name

ENCAPSULATION_LE = b"\x00\x01\x00\x00"  # CDR_LE (XCDR1), options 0

#: ROS 2 distributions whose ``ros_discovery_info`` layout is known: the Gid's length.
GID_BYTES = {"humble": 24, "iron": 24, "jazzy": 16, "kilted": 16, "rolling": 16}


def import_cyclonedds():
    """The ``cyclonedds`` package, or a RosUnavailable saying how to install it."""
    try:
        import cyclonedds.domain  # noqa: F401
        import cyclonedds.idl  # noqa: F401

        return cyclonedds
    except ImportError as e:
        raise RosUnavailable(f"the ROS 2 node needs cyclonedds ({e}): pip install 'dynastereo[ros2]' "
                             "(or pip install cyclonedds==11.0.1)") from None


# --------------------------------------------------------------------------- names


def dds_type_name(name: str) -> str:
    """``sensor_msgs/Image`` -> ``sensor_msgs::msg::dds_::Image_``; ``std_srvs/srv/Trigger_Request``
    -> ``std_srvs::srv::dds_::Trigger_Request_``."""
    parts = msg_type_name(name).split("/") if "/srv/" not in name else name.split("/")
    pkg, kind, base = parts
    return f"{pkg}::{kind}::dds_::{base}_"


def topic_name(ros_topic: str, namespace: str = "/") -> str:
    """The DDS topic of a ROS 2 topic: ``/camera/left/image_raw`` -> ``rt/camera/left/image_raw``;
    a relative name goes below ``namespace``."""
    t = ros_topic if ros_topic.startswith("/") else namespace.rstrip("/") + "/" + ros_topic
    return "rt" + t


def service_topics(service: str) -> tuple[str, str]:
    """``(request topic, reply topic)`` of a service (``rmw_cyclonedds_cpp``)."""
    s = service if service.startswith("/") else "/" + service
    return f"rq{s}Request", f"rr{s}Reply"


# --------------------------------------------------------------------------- types


@lru_cache(maxsize=1)
def _typestore():
    from .messages import rosbags_typestore

    return rosbags_typestore(ros1=False)


_PRIMITIVES: dict[str, Any] = {}


def _primitive(t: str) -> Any:
    if not _PRIMITIVES:
        from cyclonedds.idl import types as T

        _PRIMITIVES.update(bool=bool, byte=T.byte, char=T.char, int8=T.int8, uint8=T.uint8, int16=T.int16,
                           uint16=T.uint16, int32=T.int32, uint32=T.uint32, int64=T.int64, uint64=T.uint64,
                           float32=T.float32, float64=T.float64, string=str)
    return _PRIMITIVES[t]


def _field_type(node: tuple) -> Any:
    from cyclonedds.idl import types as T

    kind, detail = node
    k = int(kind)
    if k == 1:  # BASE: (type, string bound)
        t, bound = detail
        if t == "string" and bound:
            return T.bounded_str[bound]
        return _primitive(t)
    if k == 2:  # NAME
        return idl_type(detail)
    if k == 3:  # ARRAY
        inner, n = detail
        return T.array[_field_type(inner), n]
    if k == 4:  # SEQUENCE
        inner, bound = detail
        return T.sequence[_field_type(inner), bound] if bound else T.sequence[_field_type(inner)]
    raise ValueError(f"unknown field kind {kind!r}")


@lru_cache(maxsize=None)
def idl_type(name: str) -> type:
    """The IdlStruct of ROS 2 message ``name`` (``sensor_msgs/Image`` or ``sensor_msgs/msg/Image``)."""
    import_cyclonedds()
    from cyclonedds.idl import make_idl_struct

    full = msg_type_name(name)
    ts = _typestore()
    if full not in ts.fielddefs:
        raise KeyError(f"unknown ROS 2 message type {name!r}")
    _, fdefs = ts.fielddefs[full]
    fields = {fname: _field_type(node) for fname, node in fdefs}
    return make_idl_struct(full.replace("/", "_"), dds_type_name(full), fields)


@lru_cache(maxsize=None)
def service_types(srv: str = "std_srvs/srv/Trigger") -> tuple[type, type]:
    """``(request, reply)`` IdlStructs of a service as ``rmw_cyclonedds_cpp`` sends them: the
    request header (``client_guid`` uint64, ``sequence_number`` int64) before the fields.
    Only ``std_srvs/srv/Trigger`` is defined (the node's two services)."""
    import_cyclonedds()
    from cyclonedds.idl import make_idl_struct
    from cyclonedds.idl import types as T

    if srv != "std_srvs/srv/Trigger":
        raise KeyError(srv)
    hdr = {"client_guid": T.uint64, "sequence_number": T.int64}
    req = make_idl_struct("Trigger_Request", dds_type_name(srv + "_Request"),
                          {**hdr, "structure_needs_at_least_one_member": T.uint8})
    rep = make_idl_struct("Trigger_Response", dds_type_name(srv + "_Response"),
                          {**hdr, "success": bool, "message": str})
    return req, rep


def field_names(cls: type) -> set[str]:
    return {f.name for f in dc_fields(cls)}


# --------------------------------------------------------------------------- the fast codec


class CdrWriter:
    """XCDR1 little-endian writer (alignment counted from after the encapsulation header);
    large ``uint8``/float arrays go in as one copy."""

    def __init__(self) -> None:
        self.parts: list[bytes | memoryview] = [ENCAPSULATION_LE]
        self.pos = 0

    def _align(self, n: int) -> None:
        pad = -self.pos % n
        if pad:
            self.parts.append(b"\0" * pad)
            self.pos += pad

    def _put(self, fmt: str, size: int, v: Any) -> None:
        self._align(size)
        self.parts.append(struct.pack(fmt, v))
        self.pos += size

    def u8(self, v: int) -> None:
        self._put("<B", 1, int(v))

    def u32(self, v: int) -> None:
        self._put("<I", 4, int(v))

    def i32(self, v: int) -> None:
        self._put("<i", 4, int(v))

    def f32(self, v: float) -> None:
        self._put("<f", 4, float(v))

    def f64(self, v: float) -> None:
        self._put("<d", 8, float(v))

    def string(self, s: str) -> None:
        b = str(s).encode() + b"\0"
        self.u32(len(b))
        self.parts.append(b)
        self.pos += len(b)

    def blob(self, data: np.ndarray) -> None:
        """``sequence<uint8>``: the length, then the bytes (one copy into the sample)."""
        a = np.ascontiguousarray(data).reshape(-1).view(np.uint8)
        self.u32(a.size)
        self.parts.append(memoryview(a))
        self.pos += a.size

    def header(self, h: Any) -> None:
        self.i32(h.stamp.sec)
        self.u32(h.stamp.nanosec)
        self.string(h.frame_id)

    def bytes(self) -> bytes:
        self._align(4)  # a sample's length is a multiple of 4 (as cyclonedds writes it)
        return b"".join(self.parts)


def _enc_image_body(w: CdrWriter, m: Any) -> None:
    w.header(m.header)
    w.u32(m.height)
    w.u32(m.width)
    w.string(m.encoding)
    w.u8(m.is_bigendian)
    w.u32(m.step)
    w.blob(_as_u8(m.data))


def _as_u8(data: Any) -> np.ndarray:
    if isinstance(data, np.ndarray):
        return data
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, np.uint8)
    return np.asarray(data, np.uint8)


def encode_image(m: Any) -> bytes:
    w = CdrWriter()
    _enc_image_body(w, m)
    return w.bytes()


def encode_compressed(m: Any) -> bytes:
    w = CdrWriter()
    w.header(m.header)
    w.string(m.format)
    w.blob(_as_u8(m.data))
    return w.bytes()


def encode_point_cloud(m: Any) -> bytes:
    w = CdrWriter()
    w.header(m.header)
    w.u32(m.height)
    w.u32(m.width)
    w.u32(len(m.fields))
    for f in m.fields:
        w.string(f.name)
        w.u32(f.offset)
        w.u8(f.datatype)
        w.u32(f.count)
    w.u8(bool(m.is_bigendian))
    w.u32(m.point_step)
    w.u32(m.row_step)
    w.blob(_as_u8(m.data))
    w.u8(bool(m.is_dense))
    return w.bytes()


def encode_disparity(m: Any) -> bytes:
    w = CdrWriter()
    w.header(m.header)
    _enc_image_body(w, m.image)
    w.f32(m.f)
    w.f32(m.T if hasattr(m, "T") else m.t)
    r = m.valid_window
    for v in (r.x_offset, r.y_offset, r.height, r.width):
        w.u32(v)
    w.u8(bool(r.do_rectify))
    w.f32(m.min_disparity)
    w.f32(m.max_disparity)
    w.f32(m.delta_d)
    return w.bytes()


FAST_ENCODERS = {
    "sensor_msgs::msg::dds_::Image_": encode_image,
    "sensor_msgs::msg::dds_::CompressedImage_": encode_compressed,
    "sensor_msgs::msg::dds_::PointCloud2_": encode_point_cloud,
    "stereo_msgs::msg::dds_::DisparityImage_": encode_disparity,
}


def encode(msg: Any) -> bytes:
    """The sample's bytes (module doc): the fast path for image-carrying types, else cyclonedds."""
    enc = FAST_ENCODERS.get(type(msg).__idl_typename__)
    if enc is not None:
        return enc(msg)
    b = msg.serialize(use_version_2=False)
    return b.ljust((len(b) + 3) & ~3, b"\0")


class CdrReader:
    """XCDR1 little-endian reader over a sample's bytes (numpy views, no copies)."""

    def __init__(self, data: bytes | memoryview, where: str = "") -> None:
        self.buf = memoryview(data)
        self.where = where
        if len(self.buf) < 4 or bytes(self.buf[:2]) not in (b"\x00\x01", b"\x00\x00"):
            raise InputError(f"not a little-endian XCDR1 sample (header {bytes(self.buf[:4]).hex()})", where or None)
        self.big = bytes(self.buf[:2]) == b"\x00\x00"
        self.pos = 0  # from after the header

    def _get(self, fmt: str, size: int) -> Any:
        self.pos += -self.pos % size
        end = 4 + self.pos + size
        if end > len(self.buf):
            raise InputError("sample truncated (is the topic's type what it says?)", self.where or None)
        v = struct.unpack_from((">" if self.big else "<") + fmt, self.buf, 4 + self.pos)[0]
        self.pos += size
        return v

    def u8(self) -> int:
        return self._get("B", 1)

    def u32(self) -> int:
        return self._get("I", 4)

    def i32(self) -> int:
        return self._get("i", 4)

    def string(self) -> str:
        n = self.u32()
        start = 4 + self.pos
        if n == 0 or start + n > len(self.buf):
            raise InputError("bad string in sample (is the topic's type what it says?)", self.where or None)
        s = bytes(self.buf[start:start + n - 1]).decode("utf-8", "replace")
        self.pos += n
        return s

    def blob(self) -> np.ndarray:
        n = self.u32()
        start = 4 + self.pos
        if start + n > len(self.buf):
            raise InputError(f"sample truncated: {n} bytes of data announced, {len(self.buf) - start} present",
                             self.where or None)
        self.pos += n
        return np.frombuffer(self.buf, np.uint8, n, start)

    def header(self) -> tuple[int, str]:
        sec = self.i32()
        nsec = self.u32()
        return sec * 1_000_000_000 + nsec, self.string()


@dataclass
class ImageMsg:
    """A received ``sensor_msgs/Image`` (``data``: a view of the sample)."""

    stamp_ns: int
    frame_id: str
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: np.ndarray


@dataclass
class CompressedImageMsg:
    stamp_ns: int
    frame_id: str
    format: str
    data: np.ndarray


def decode_image(data: bytes | memoryview, where: str = "") -> ImageMsg:
    r = CdrReader(data, where)
    stamp, fid = r.header()
    h, w = r.u32(), r.u32()
    enc = r.string()
    big = r.u8()
    step = r.u32()
    return ImageMsg(stamp, fid, h, w, enc, big, step, r.blob())


def decode_compressed(data: bytes | memoryview, where: str = "") -> CompressedImageMsg:
    r = CdrReader(data, where)
    stamp, fid = r.header()
    fmt = r.string()
    return CompressedImageMsg(stamp, fid, fmt, r.blob())


def decode(cls: type, data: bytes) -> Any:
    """Any other message, with cyclonedds (small messages: CameraInfo, service requests)."""
    return cls.deserialize(data)


def stamp_ns_of(msg: Any) -> int:
    """A decoded message's header stamp in ns (either decoder)."""
    if hasattr(msg, "stamp_ns"):
        return int(msg.stamp_ns)
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


# --------------------------------------------------------------------------- builder


class DdsBuilder(MessageBuilder):
    """Messages as the IdlStruct types of :func:`idl_type` (serialize with :func:`encode`)."""

    def __init__(self) -> None:
        self._fields: dict[type, set[str]] = {}

    def cls(self, name: str) -> type:
        return idl_type(name)

    def fields(self, cls: type) -> set[str]:
        f = self._fields.get(cls)
        if f is None:
            f = self._fields[cls] = field_names(cls)
        return f

    def time(self, stamp_ns: int) -> Any:
        s, ns = stamp_split(stamp_ns)
        return self.make("builtin_interfaces/Time", sec=s, nanosec=ns)

    def duration(self, ns: int) -> Any:
        s, n = stamp_split(ns)
        return self.make("builtin_interfaces/Duration", sec=s, nanosec=n)

    def floats(self, values: Any) -> Any:
        return [float(v) for v in np.asarray(values, dtype=np.float64).reshape(-1)]

    def blob(self, data: np.ndarray) -> Any:
        # image-carrying types keep the array (the fast encoder); an empty blob elsewhere
        # (a marker's texture) must be a list for cyclonedds' serializer
        a = np.ascontiguousarray(data, dtype=np.uint8).reshape(-1)
        return a if a.size else []


# --------------------------------------------------------------------------- QoS


class QosKind:
    SENSOR = "sensor"  # best effort, keep last 5, volatile (rclcpp's SensorDataQoS)
    RELIABLE = "reliable"  # reliable, keep last 10, volatile (the default)
    LATCHED = "latched"  # reliable, keep last 1, transient local (path, map, ready)
    TF = "tf"  # reliable, keep last 100 (tf2_ros' broadcaster)
    SERVICE = "service"  # reliable, keep last 10, volatile (rmw's services_default)
    RECORD = "record"  # reliable, keep last 1000: a recorder that reads now and then (tests, the player)


def qos(kind: str) -> Any:
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration

    if kind == QosKind.SENSOR:
        return Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5), Policy.Durability.Volatile)
    if kind == QosKind.LATCHED:
        return Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.History.KeepLast(1),
                   Policy.Durability.TransientLocal)
    depth = {QosKind.RELIABLE: 10, QosKind.TF: 100, QosKind.SERVICE: 10, QosKind.RECORD: 1000}[kind]
    return Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.History.KeepLast(depth),
               Policy.Durability.Volatile)


def domain_id(default: int = 0) -> int:
    """``ROS_DOMAIN_ID`` (0 when unset), checked."""
    v = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not v:
        return default
    try:
        d = int(v)
    except ValueError:
        raise InputError(f"ROS_DOMAIN_ID must be an integer 0..232, got {v!r}") from None
    if not 0 <= d <= 232:
        raise InputError(f"ROS_DOMAIN_ID must be in 0..232, got {d}")
    return d


# --------------------------------------------------------------------------- participant


class RawWriter:
    """A DataWriter that takes serialized samples (bytes from :func:`encode`)."""

    def __init__(self, writer: Any) -> None:
        from cyclonedds._clayer import ddspy_write

        self.writer = writer
        self._write = ddspy_write

    def write(self, data: bytes) -> None:
        ret = self._write(self.writer._ref, data)
        if ret < 0:
            from cyclonedds.core import DDSException

            raise DDSException(ret, f"writing a sample on {self.writer.topic.name}")

    def publish(self, msg: Any) -> None:
        self.write(encode(msg))

    def matched(self) -> int:
        try:
            return int(self.writer.get_matched_subscriptions().__len__())
        except Exception:  # noqa: BLE001 -- an older cyclonedds: assume someone listens
            return 1


class RawReader:
    """A DataReader whose samples come out as bytes (decoded by the caller)."""

    def __init__(self, reader: Any) -> None:
        from cyclonedds._clayer import ddspy_take
        from cyclonedds.core import InstanceState, SampleState, ViewState

        self.reader = reader
        self._take = ddspy_take
        self._mask = SampleState.Any | ViewState.Any | InstanceState.Any

    def take(self, n: int = 64) -> list[tuple[bytes, Any]]:
        ret = self._take(self.reader._ref, self._mask, n)
        if isinstance(ret, int):
            from cyclonedds.core import DDSException

            raise DDSException(ret, f"taking samples on {self.reader.topic.name}")
        return [(data, info) for data, info in ret if info.valid_data]


@lru_cache(maxsize=None)
def discovery_types(gid_bytes: int) -> tuple[type, type, type]:
    """``(Gid, NodeEntitiesInfo, ParticipantEntitiesInfo)`` of rmw_dds_common."""
    from cyclonedds.idl import make_idl_struct
    from cyclonedds.idl import types as T

    gid_t = make_idl_struct("Gid", "rmw_dds_common::msg::dds_::Gid_", {"data": T.array[T.uint8, gid_bytes]})
    node_t = make_idl_struct("NodeEntitiesInfo", "rmw_dds_common::msg::dds_::NodeEntitiesInfo_",
                             {"node_namespace": T.bounded_str[256], "node_name": T.bounded_str[256],
                              "reader_gid_seq": T.sequence[gid_t], "writer_gid_seq": T.sequence[gid_t]})
    info_t = make_idl_struct("ParticipantEntitiesInfo", "rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_",
                             {"gid": gid_t, "node_entities_info_seq": T.sequence[node_t]})
    return gid_t, node_t, info_t


class Waiter:
    """Blocks (the GIL released) until one of ``readers`` has data, or ``timeout_s``."""

    def __init__(self, participant: Any, readers: list[RawReader]) -> None:
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet

        self.ws = WaitSet(participant)
        mask = SampleState.NotRead | ViewState.Any | InstanceState.Any
        self._conds = [ReadCondition(r.reader, mask) for r in readers]
        for c in self._conds:
            self.ws.attach(c)

    def wait(self, timeout_s: float) -> int:
        return int(self.ws.wait(int(timeout_s * 1e9)))


class Domain:
    """One DDS participant in ``ROS_DOMAIN_ID`` (or ``domain``) with ROS 2 names: raw writers and
    readers, and the ``ros_discovery_info`` entry that makes ``ros2 node list`` show the node."""

    def __init__(self, domain: int | None = None, *, node_name: str = "", namespace: str = "/",
                 distro: str = "humble") -> None:
        import_cyclonedds()
        from cyclonedds.core import Policy, Qos
        from cyclonedds.domain import DomainParticipant

        self.domain_id = domain_id() if domain is None else int(domain)
        # the security enclave in the participant's user data, as rmw_cyclonedds_cpp sets it
        self.participant = DomainParticipant(self.domain_id, qos=Qos(Policy.Userdata(b"enclave=/;")))
        self.namespace = namespace if namespace.startswith("/") else "/" + namespace
        self.node_name = node_name
        if distro not in GID_BYTES:
            raise InputError(f"ros_distro must be one of {', '.join(GID_BYTES)}, got {distro!r}")
        self.distro = distro
        self._topics: dict[str, Any] = {}
        self._readers: list[Any] = []
        self._writers: list[Any] = []
        self._discovery: Any = None

    def _topic(self, name: str, cls: type) -> Any:
        from cyclonedds.topic import Topic

        t = self._topics.get(name)
        if t is None:
            t = self._topics[name] = Topic(self.participant, name, cls)
        return t

    def writer(self, ros_topic: str, msg_type: str | type, kind: str = QosKind.RELIABLE, *,
               dds_name: str | None = None) -> RawWriter:
        from cyclonedds.pub import DataWriter

        cls = idl_type(msg_type) if isinstance(msg_type, str) else msg_type
        w = DataWriter(self.participant, self._topic(dds_name or topic_name(ros_topic, self.namespace), cls),
                       qos=qos(kind))
        self._writers.append(w)
        return RawWriter(w)

    def reader(self, ros_topic: str, msg_type: str | type, kind: str = QosKind.SENSOR, *,
               dds_name: str | None = None, listener: Any = None) -> RawReader:
        from cyclonedds.sub import DataReader

        cls = idl_type(msg_type) if isinstance(msg_type, str) else msg_type
        r = DataReader(self.participant, self._topic(dds_name or topic_name(ros_topic, self.namespace), cls),
                       qos=qos(kind), listener=listener)
        self._readers.append(r)
        return RawReader(r)

    # ------------------------------------------------------------------ ros_discovery_info
    def _gid(self, entity: Any) -> list[int]:
        n = GID_BYTES[self.distro]
        g = list(entity.guid.bytes)[:16]
        return g + [0] * (n - len(g))

    def announce(self) -> None:
        """Publish (latched) the node's entry on ``ros_discovery_info`` (rmw_dds_common's
        ParticipantEntitiesInfo): its name, namespace and the GIDs of its readers and writers.
        The Gid's size differs between distributions (``distro``)."""
        from cyclonedds.core import Policy, Qos
        from cyclonedds.pub import DataWriter

        gid_t, node_t, info_t = discovery_types(GID_BYTES[self.distro])
        if self._discovery is None:
            q = Qos(Policy.Reliability.Reliable(0), Policy.History.KeepLast(1), Policy.Durability.TransientLocal)
            self._discovery = DataWriter(self.participant, self._topic("ros_discovery_info", info_t), qos=q)
        node = node_t(node_namespace=self.namespace, node_name=self.node_name,
                      reader_gid_seq=[gid_t(data=self._gid(r)) for r in self._readers],
                      writer_gid_seq=[gid_t(data=self._gid(w)) for w in self._writers])
        self._discovery.write(info_t(gid=gid_t(data=self._gid(self.participant)), node_entities_info_seq=[node]))
