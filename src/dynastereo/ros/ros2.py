"""ROS 2 node ``dynastereo`` over DDS, without rclpy: a thin adapter over :class:`StereoNodeCore`.

``dynastereo node --ros2 [--params FILE]``.  It speaks ROS 2's wire protocol through Cyclone
DDS (:mod:`.dds`: the ``ros2`` extra), so ROS 2 Humble / Jazzy nodes on ``rmw_cyclonedds_cpp``
(and, through RTPS, ``rmw_fastrtps_cpp``) see it as a ROS 2 node.  Same runtime as the ROS 1
node and the offline runs: one :class:`~dynastereo.runtime.loop.FrameLoop`, one processor,
the stages from :func:`~dynastereo.runtime.assembly.assemble_stages`.

Subscribes (QoS: best effort, keep last 5 -- ROS 2's sensor data; ``input_reliability:
reliable`` for reliable delivery)
    ``left_topic`` / ``right_topic``: sensor_msgs/Image, default ``/camera/{left,right}/image_raw``
    (``compressed: true``: sensor_msgs/CompressedImage on ``<topic>/compressed``), paired by
    stamp (``sync_slop`` s; ``exact_sync``); ``left_info_topic`` / ``right_info_topic``:
    sensor_msgs/CameraInfo (``use_camera_info``), the first pair sets the calibration.

Publishes, under ``/dynastereo/``
    ``odometry`` (nav_msgs/Odometry, reliable) and ``/tf`` (reliable, keep last 100);
    ``left/masked``, ``right/masked``, ``left/mask``, ``right/mask``, ``left/objects``
    (sensor_msgs/Image), ``disparity`` (stereo_msgs/DisparityImage) -- best effort, sent only
    while someone subscribes; ``objects`` (visualization_msgs/MarkerArray, reliable);
    ``path`` (nav_msgs/Path), ``map_points`` (sensor_msgs/PointCloud2) and ``ready``
    (std_msgs/Bool) -- reliable, transient local (late subscribers get the last one).

Services (std_srvs/srv/Trigger, laid out as ``rmw_cyclonedds_cpp`` lays them out)
    ``/dynastereo/save_trajectory`` -- trajectory, timing.json, node.json into ``save_dir``;
    ``/dynastereo/status`` -- statistics and configuration (JSON in ``message``);
    ``/dynastereo/build_mesh`` (with ``mesh: true``) -- the static world's mesh so far into
    ``save_dir/mesh.ply``, published on ``/dynastereo/mesh`` (visualization_msgs/Marker
    TRIANGLE_LIST) and ``/dynastereo/dense_cloud`` (PointCloud2), both transient local.

Parameters: those of the ROS 1 node, with its defaults, from a ROS 2 parameters file
(``/**: ros__parameters:`` and/or ``dynastereo: ros__parameters:``); see :data:`PARAMS`.
They are read at start-up (ROS 2's parameter services are not served: restart to change
one).  ``ROS_DOMAIN_ID`` is honoured; ``ros_distro`` (humble, jazzy, ...) sets the layout of
the ``ros_discovery_info`` entry that makes ``ros2 node list`` show the node.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..config import Config, load_config
from ..dotted import flatten_dotted
from ..yamlcheck import yaml_error_line
from ..errors import ConfigError, DynastereoError, InputError
from .convert import CameraInfoData, ImageDecoder, calibration_from_camera_info, image_outputs
from .core import LIVE_SECTIONS, NodeResult, StereoInput, StereoNodeCore
from .dds import (
    GID_BYTES,
    DdsBuilder,
    Domain,
    QosKind,
    Waiter,
    decode,
    decode_compressed,
    decode_image,
    dds_type_name,
    idl_type,
    service_topics,
    service_types,
    topic_name,
)
from .messages import (
    DEFAULT_LEFT_INFO,
    DEFAULT_LEFT_TOPIC,
    DEFAULT_RIGHT_INFO,
    DEFAULT_RIGHT_TOPIC,
    MAP_EVERY,
    ODOM_FRAME,
    DisparityData,
)

log = logging.getLogger("dynastereo.ros")

NODE_NAME = "dynastereo"

#: The node's parameters and their defaults (the ROS 1 node's, plus the last three).
PARAMS: dict[str, Any] = {
    "config": "", "calib": "", "models_dir": "", "seed": None,
    "left_topic": DEFAULT_LEFT_TOPIC, "right_topic": DEFAULT_RIGHT_TOPIC,
    "left_info_topic": DEFAULT_LEFT_INFO, "right_info_topic": DEFAULT_RIGHT_INFO,
    "compressed": False, "use_camera_info": True, "rectify": "auto", "mono16_shift": None,
    "queue_size": 1, "pipelined": True, "sync_slop": 0.01, "sync_queue_size": 10, "exact_sync": False,
    "odom_frame": ODOM_FRAME, "camera_frame": "", "publish_tf": True,
    "save_dir": "", "save_on_shutdown": True,
    "input_reliability": "best_effort", "ros_distro": "humble", "namespace": "/dynastereo", "mesh": False,
}
SECTIONS = LIVE_SECTIONS + ("slam", "objects", "motion")


# --------------------------------------------------------------------------- parameters


def load_params(path: str | Path | None, node_name: str = NODE_NAME) -> dict[str, Any]:
    """The node's parameters: :data:`PARAMS` with a ROS 2 parameters file on top (``/**``
    first, then the node's own entry).  Config sections may be nested (``stereo:
    {block_size: 21}``) or dotted (``stereo.block_size: 21``).  A bad file or an unknown
    parameter raises ConfigError naming the file and the key."""
    params = dict(PARAMS)
    sections: dict[str, Any] = {}
    if path is None:
        params["_sections"] = sections
        return params
    import yaml

    p = Path(path)
    where = str(p)
    try:
        doc = yaml.safe_load(p.read_text(encoding="utf-8"))
    except OSError as e:
        raise ConfigError(f"{where}: cannot read the parameters file ({e.strerror or e})") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{where}: not valid YAML ({yaml_error_line(e)})") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"{where}: expected a ROS 2 parameters file ('/**: ros__parameters: ...' or "
                          f"'{node_name}: ros__parameters: ...')")
    entries = [k for k in ("/**", node_name, "/" + node_name) if k in doc]
    if not entries:
        raise ConfigError(f"{where}: no '/**' or '{node_name}' entry (keys: {', '.join(map(str, doc)) or 'none'})")
    for k in entries:
        body = doc[k]
        if not isinstance(body, dict) or not isinstance(body.get("ros__parameters"), dict):
            raise ConfigError(f"{where}: '{k}' needs a 'ros__parameters:' mapping")
        for key, v in flatten_dotted(body["ros__parameters"], skip_none=False).items():
            section = key.split(".", 1)[0]
            if section in SECTIONS:
                sections[key] = v
            elif key in PARAMS:
                params[key] = v
            else:
                raise ConfigError(f"{where}: unknown parameter '{key}' (known: {', '.join(sorted(PARAMS))}, "
                                  f"and the sections {', '.join(s + '.*' for s in SECTIONS)})")
    if params["input_reliability"] not in ("best_effort", "reliable"):
        raise ConfigError(f"{where}: input_reliability must be best_effort or reliable, "
                          f"got {params['input_reliability']!r}")
    if params["ros_distro"] not in GID_BYTES:
        raise ConfigError(f"{where}: ros_distro must be one of {', '.join(GID_BYTES)}, got {params['ros_distro']!r}")
    params["_sections"] = sections
    return params


def config_from_params(params: dict[str, Any]) -> Config:
    """``config`` (YAML) with the sections and ``seed`` on top, as the ROS 1 node does."""
    cfg = load_config(params.get("config") or None)
    overrides = dict(params.get("_sections", {}))
    if params.get("seed") is not None:
        overrides["seed"] = params["seed"]
    return cfg.with_overrides(overrides) if overrides else cfg


# --------------------------------------------------------------------------- pairing


@dataclass
class _Half:
    stamp_ns: int
    image: np.ndarray  # decoded
    frame_id: str
    received: float


class StampPairer:
    """Left and right images paired by stamp (``slop`` s; 0: exact), ``depth`` waiting per
    side; an image left without a partner is counted (``unpaired``)."""

    def __init__(self, slop_s: float, depth: int) -> None:
        self.slop_ns = int(round(max(0.0, float(slop_s)) * 1e9))
        self.depth = max(1, int(depth))
        self.waiting: dict[str, OrderedDict[int, _Half]] = {"left": OrderedDict(), "right": OrderedDict()}
        self.unpaired = {"left": 0, "right": 0}

    def add(self, side: str, half: _Half) -> tuple[_Half, _Half] | None:
        other = "right" if side == "left" else "left"
        cand = self.waiting[other]
        best = None
        if cand:
            stamps = np.fromiter(cand.keys(), np.int64, len(cand))
            k = int(np.argmin(np.abs(stamps - half.stamp_ns)))
            if abs(int(stamps[k]) - half.stamp_ns) <= self.slop_ns:
                best = int(stamps[k])
        if best is None:
            mine = self.waiting[side]
            mine[half.stamp_ns] = half
            while len(mine) > self.depth:
                mine.popitem(last=False)
                self.unpaired[side] += 1
            return None
        mate = cand.pop(best)
        for s in list(cand):  # older than the pair: never paired now
            if s < best:
                cand.pop(s)
                self.unpaired[other] += 1
        return (half, mate) if side == "left" else (mate, half)


# --------------------------------------------------------------------------- node


class Ros2Node:
    """The DDS side: readers, writers, services, discovery (module doc)."""

    def __init__(self, params: dict[str, Any], domain: int | None = None) -> None:
        self.params = p = params
        self.cfg = config_from_params(p)
        ns = str(p["namespace"]).rstrip("/") or ""
        self.ns = ns
        self.dom = Domain(domain, node_name=NODE_NAME, namespace="/", distro=str(p["ros_distro"]))
        self.b = DdsBuilder()
        models_dir = p["models_dir"] or os.environ.get("DYNASTEREO_MODELS") or None
        self.save_dir = Path(os.path.expanduser(p["save_dir"] or os.path.join(
            os.environ.get("ROS_HOME") or os.path.join(os.path.expanduser("~"), ".ros"), "dynastereo")))
        self.publish_tf = bool(p["publish_tf"])
        self.use_info = bool(p["use_camera_info"])
        calibration = None
        if p["calib"]:
            from ..io.calib import load_stereo_yaml

            calibration = load_stereo_yaml(p["calib"])
            self.use_info = False
        self.core = StereoNodeCore(self.cfg, models_dir=models_dir, queue_size=int(p["queue_size"]),
                                   pipelined=bool(p["pipelined"]), sink=self, odom_frame=str(p["odom_frame"]),
                                   camera_frame=str(p["camera_frame"]), mesh=bool(p["mesh"]))
        self.decoder = ImageDecoder(p["mono16_shift"])
        self.pairer = StampPairer(0.0 if p["exact_sync"] else float(p["sync_slop"]), int(p["sync_queue_size"]))
        self.counts = {"left": 0, "right": 0, "pairs": 0, "bad_messages": 0, "calibration_changes": 0,
                       "waiting_for_calibration": 0}
        self._info: dict[str, Any] = {}
        self._info0: tuple[CameraInfoData, CameraInfoData] | None = None
        self._info_error = ""
        self._held: list[StereoInput] = []  # pairs that came before the calibration
        self._logged: set[str] = set()
        self._stop = threading.Event()
        self._path: tuple[list[np.ndarray], list[int]] = ([], [])
        from ..objects.world import ObjectPaths

        self._object_paths = ObjectPaths()

        self._make_publishers()
        self._subscribe()
        self._serve()

        if calibration is not None:
            self.core.set_calibration(calibration)
            self.core.warm_up()
            self._ready(True)
        else:
            from ..slam.warmup import warm_up_kernels

            self.core.warm_up()
            warm_up_kernels()
        self.core.start()
        log.info("dynastereo (ROS 2, domain %d): listening on %s + %s%s; masker %s, detector %s, queue_size %d",
                 self.dom.domain_id, self.topics["left"], self.topics["right"],
                 f" with CameraInfo {self.info_topics['left']}, {self.info_topics['right']}" if self.use_info else "",
                 self.cfg.masker.kind, self.cfg.detector.name, self.core.queue_size)

    def _make_publishers(self) -> None:
        """The writers, with ROS 2's QoS conventions (module doc)."""
        w = self.dom.writer
        self.pub_odom = w(self._t("odometry"), "nav_msgs/Odometry", QosKind.RELIABLE)
        self.pub_tf = w("/tf", "tf2_msgs/TFMessage", QosKind.TF) if self.publish_tf else None
        self.pub_img = {k: w(self._t(k), "sensor_msgs/Image", QosKind.SENSOR)
                        for k in ("left/masked", "right/masked", "left/mask", "right/mask", "left/objects")}
        self.pub_disp = w(self._t("disparity"), "stereo_msgs/DisparityImage", QosKind.SENSOR)
        self.pub_path = w(self._t("path"), "nav_msgs/Path", QosKind.LATCHED)
        self.pub_map = w(self._t("map_points"), "sensor_msgs/PointCloud2", QosKind.LATCHED)
        self.pub_objects = w(self._t("objects"), "visualization_msgs/MarkerArray", QosKind.RELIABLE)
        self.pub_ready = w(self._t("ready"), "std_msgs/Bool", QosKind.LATCHED)
        self.pub_mesh = self.pub_dense = None
        if self.core.mesh_recorder is not None:  # mesh: true -- built on the build_mesh service
            self.pub_mesh = w(self._t("mesh"), "visualization_msgs/Marker", QosKind.LATCHED)
            self.pub_dense = w(self._t("dense_cloud"), "sensor_msgs/PointCloud2", QosKind.LATCHED)
        self._ready(False)


    def _subscribe(self) -> None:
        """The image and CameraInfo readers, and the type each input topic must carry."""
        p = self.params
        in_qos = QosKind.RELIABLE if p["input_reliability"] == "reliable" else QosKind.SENSOR
        self.compressed = bool(p["compressed"])
        img_type = "sensor_msgs/CompressedImage" if self.compressed else "sensor_msgs/Image"
        suffix = "/compressed" if self.compressed else ""
        self.topics = {"left": str(p["left_topic"]) + suffix, "right": str(p["right_topic"]) + suffix}
        self.info_topics = {"left": str(p["left_info_topic"]), "right": str(p["right_info_topic"])}
        self.readers = {side: self.dom.reader(t, img_type, in_qos) for side, t in self.topics.items()}
        self.expected = {topic_name(t): dds_type_name(img_type) for t in self.topics.values()}
        self.info_readers: dict[str, Any] = {}
        if self.use_info:
            self._info_cls = idl_type("sensor_msgs/CameraInfo")
            for side, t in self.info_topics.items():
                self.info_readers[side] = self.dom.reader(t, "sensor_msgs/CameraInfo", in_qos)
                self.expected[topic_name(t)] = dds_type_name("sensor_msgs/CameraInfo")


    def _serve(self) -> None:
        """The services (request / reply topics as rmw_cyclonedds_cpp lays them out), the
        reader of other nodes' publications, the wait set, the discovery entry."""
        req_t, self._rep_t = service_types()
        self._req_t = req_t
        self.services: dict[str, tuple[Any, Any, Any]] = {}
        served = [("save_trajectory", self._srv_save), ("status", self._srv_status)]
        if self.core.mesh_recorder is not None:
            served.append(("build_mesh", self._srv_mesh))
        for name, fn in served:
            rq, rr = service_topics(self._t(name))
            self.services[name] = (self.dom.reader("", req_t, QosKind.SERVICE, dds_name=rq),
                                   self.dom.writer("", self._rep_t, QosKind.SERVICE, dds_name=rr), fn)
        self._publications = self._publication_reader()
        self._waiter = Waiter(self.dom.participant, [*self.info_readers.values(), *self.readers.values(),
                                                     *(req for req, _, _ in self.services.values())])
        self.dom.announce()

    def _t(self, name: str) -> str:
        return f"{self.ns}/{name}"

    def _ready(self, v: bool) -> None:
        self.pub_ready.publish(self.b.make("std_msgs/Bool", data=bool(v)))

    def _once(self, key: str, level: int, msg: str) -> None:
        """One log line per distinct problem (a bad stream says so once, not per message)."""
        if key not in self._logged:
            self._logged.add(key)
            log.log(level, "%s", msg)

    # ------------------------------------------------------------------ input
    def _publication_reader(self) -> Any:
        try:
            from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication

            return BuiltinDataReader(self.dom.participant, BuiltinTopicDcpsPublication)
        except Exception as e:  # noqa: BLE001 -- a diagnosis only
            log.debug("no builtin publication reader: %s", e)
            return None

    def _check_publications(self) -> None:
        """A publisher on one of our topics with another type: one clear line (DDS never
        matches it, so its messages would vanish silently)."""
        if self._publications is None:
            return
        for ep in self._publications.take(64):
            want = self.expected.get(getattr(ep, "topic_name", None))
            got = getattr(ep, "type_name", None)
            if want is not None and got and got != want:
                self.counts["bad_messages"] += 1
                ros = ep.topic_name[2:] if ep.topic_name.startswith("rt/") else ep.topic_name
                self._once(f"type:{ep.topic_name}:{got}", logging.ERROR,
                           f"dynastereo: {ros}: a publisher sends {_ros_type(got)}, the node expects "
                           f"{_ros_type(want)}; its messages are ignored")

    def spin_once(self, timeout_s: float = 0.1) -> int:
        """Wait up to ``timeout_s`` for input, then take and handle whatever arrived."""
        self._waiter.wait(timeout_s)
        n = 0
        for side, r in self.info_readers.items():
            for data, _ in r.take(8):
                n += 1
                self._on_info(side, data)
        for side, r in self.readers.items():
            for data, info in r.take(16):
                n += 1
                self._on_image(side, data, time.time())
        for name, (req, rep, fn) in self.services.items():
            for data, _ in req.take(8):
                n += 1
                self._on_request(name, data, rep, fn)
        if n == 0:
            self._check_publications()
        return n

    def _on_info(self, side: str, data: bytes) -> None:
        try:
            msg = decode(self._info_cls, data)
        except Exception as e:  # noqa: BLE001 -- a malformed sample: said once, the node goes on
            self.counts["bad_messages"] += 1
            self._once(f"info:{side}:decode", logging.ERROR,
                       f"dynastereo: {self.info_topics[side]}: not a sensor_msgs/CameraInfo ({type(e).__name__}: {e})")
            return
        self._info[side] = msg
        if "left" in self._info and "right" in self._info:
            self._ensure_calibration(self._info["left"], self._info["right"])

    def _ensure_calibration(self, linfo: Any, rinfo: Any) -> None:
        li, ri = CameraInfoData.from_msg(linfo), CameraInfoData.from_msg(rinfo)
        if self._info0 is not None:
            if not (li.same(self._info0[0]) and ri.same(self._info0[1])):
                self.counts["calibration_changes"] += 1
                self._once("info:changed", logging.WARNING, "dynastereo: CameraInfo changed; keeping the first calibration")
            return
        try:
            calib = calibration_from_camera_info(li, ri, str(self.params["rectify"]),
                                                 where=f"{self.info_topics['left']}, {self.info_topics['right']}")
            self.core.set_calibration(calib)
        except DynastereoError as e:
            self.counts["bad_messages"] += 1
            self._info_error = str(e)
            self.core.stats.last_error = str(e)
            # one line for a camera that sends bad CameraInfo (each message would say the same)
            self._once("info:refused", logging.ERROR, f"dynastereo: CameraInfo refused: {e}")
            return
        self.core.warm_up()
        self._info0 = (li, ri)
        self._ready(True)
        c = self.core.calibration
        log.info("dynastereo: calibration from CameraInfo: fx %.3f, baseline %.4f m, %dx%d%s", c.fx, c.baseline,
                 c.width, c.height, ", rectifying" if self.core.rectifier is not None else "")
        held, self._held = self._held, []
        for inp in held:
            self.core.submit(inp)

    def _on_image(self, side: str, data: bytes, received: float) -> None:
        self.counts[side] += 1
        where = self.topics[side]
        try:
            msg = decode_compressed(data, where) if self.compressed else decode_image(data, where)
            img = self.decoder.decode(msg, where)
        except DynastereoError as e:
            self.counts["bad_messages"] += 1
            self.core.stats.last_error = str(e)
            self._once(f"img:{side}:{e}", logging.ERROR, f"dynastereo: {e}")
            return
        pair = self.pairer.add(side, _Half(msg.stamp_ns, img, msg.frame_id, received))
        if pair is None:
            return
        left, right = pair
        self.counts["pairs"] += 1
        inp = StereoInput(left.image, right.image, left.stamp_ns, left.frame_id, max(left.received, right.received))
        if not self.core.ready:
            self.counts["waiting_for_calibration"] += 1
            self._held.append(inp)
            depth = max(1, int(self.params["sync_queue_size"]))
            if len(self._held) > depth:
                self._held.pop(0)
                self.core.stats.dropped += 1
            self._once("no-calib", logging.WARNING,
                       "dynastereo: images before a calibration: waiting for CameraInfo on "
                       f"{self.info_topics['left']} and {self.info_topics['right']}"
                       + (f" ({self._info_error})" if self._info_error else ""))
            return
        self.core.submit(inp)

    # ------------------------------------------------------------------ NodeSink
    def publish_pose(self, r: NodeResult) -> None:
        self.pub_odom.publish(self.b.odometry(r.odometry))
        if self.pub_tf is not None:
            self.pub_tf.publish(self.b.tf(r.odometry))

    def wants_disparity(self) -> bool:
        return self.pub_disp.matched() > 0

    def publish_images(self, r: NodeResult, disparity: DisparityData | None) -> None:
        fid = r.odometry.child_frame_id
        for key, img, enc in image_outputs(r.frame, r.masks):
            pub = self.pub_img[key]
            if pub.matched() > 0:
                pub.publish(self.b.image(img(), r.stamp_ns, fid, enc))
        if disparity is not None:
            self.pub_disp.publish(self.b.disparity(disparity, r.stamp_ns, fid))
        odom = r.odometry.frame_id
        self._path[0].append(r.odometry.pose)
        self._path[1].append(r.stamp_ns)
        if self.pub_path.matched() > 0:
            self.pub_path.publish(self.b.path(*self._path, odom))
        objs = r.masks.objects if r.masks is not None else []
        self._object_paths.add(objs)
        if self.pub_objects.matched() > 0:
            self.pub_objects.publish(self.b.object_markers(objs, r.stamp_ns, odom, r.position,
                                                           self._object_paths.paths()))
        if r.position % MAP_EVERY == 0 and self.pub_map.matched() > 0:
            self.pub_map.publish(self.b.point_cloud(self.core.map_points(), r.stamp_ns, odom))

    # ------------------------------------------------------------------ services
    def status(self) -> dict[str, Any]:
        d = self.core.status()
        d["topics"] = dict(self.counts)
        d["unpaired_left"] = self.pairer.unpaired["left"]
        d["unpaired_right"] = self.pairer.unpaired["right"]
        d["domain_id"] = self.dom.domain_id
        return d

    def _srv_save(self) -> tuple[bool, str]:
        try:
            return True, json.dumps(self.core.save(self.save_dir))
        except Exception as e:  # noqa: BLE001 - reported to the caller
            return False, f"{type(e).__name__}: {e}"

    def _srv_mesh(self) -> tuple[bool, str]:
        return self.core.mesh_service(self.b, self.save_dir, self.pub_mesh, self.pub_dense)

    def _srv_status(self) -> tuple[bool, str]:
        return True, json.dumps(self.status(), default=float)

    def _on_request(self, name: str, data: bytes, rep: Any, fn: Any) -> None:
        try:
            req = decode(self._req_t, data)
        except Exception as e:  # noqa: BLE001
            self._once(f"srv:{name}", logging.ERROR, f"dynastereo: a malformed {name} request ({e})")
            return
        ok, message = fn()
        # discovery is not symmetric: the caller's reply reader may be known to it before it is
        # known here, and a volatile reply to an unmatched reader is lost -- wait briefly for it
        end = time.monotonic() + 2.0
        while rep.matched() == 0 and time.monotonic() < end:
            time.sleep(0.01)
        rep.publish(self._rep_t(client_guid=req.client_guid, sequence_number=req.sequence_number, success=ok,
                                message=message))

    # ------------------------------------------------------------------ run
    def spin(self) -> None:
        while not self._stop.is_set():
            self.spin_once()

    def stop(self) -> None:
        self._stop.set()

    def shutdown(self) -> None:
        self.core.shutdown()
        if self.params["save_on_shutdown"] and self.core.ready and self.core.stats.processed:
            try:
                self.core.save(self.save_dir)
                log.info("dynastereo: trajectory saved to %s", self.save_dir)
            except Exception as e:  # noqa: BLE001
                log.error("dynastereo: saving the trajectory failed: %s", e)


def _ros_type(dds: str) -> str:
    """``sensor_msgs::msg::dds_::Image_`` -> ``sensor_msgs/msg/Image``."""
    parts = dds.split("::")
    if len(parts) == 4 and parts[2] == "dds_":
        return f"{parts[0]}/{parts[1]}/{parts[3].rstrip('_')}"
    return dds


# --------------------------------------------------------------------------- service client


class TriggerClient:
    """Calls a node's std_srvs/Trigger service over DDS (tests, ``dynastereo node --ros2 --call``)."""

    def __init__(self, dom: Domain, service: str) -> None:
        req_t, self._rep_t = service_types()
        self._req_t = req_t
        rq, rr = service_topics(service)
        self.w = dom.writer("", req_t, QosKind.SERVICE, dds_name=rq)
        self.r = dom.reader("", self._rep_t, QosKind.SERVICE, dds_name=rr)
        self.guid = int.from_bytes(bytes(self.w.writer.guid.bytes[8:16]), "little")
        self.seq = 0

    def call(self, timeout: float = 10.0, resend_s: float = 2.0) -> tuple[bool, str]:
        """The reply to one request. The request goes again every ``resend_s`` until a reply comes
        (a reply may be lost while discovery settles); a reply to any of the tries counts."""
        end = time.monotonic() + timeout
        while self.w.matched() == 0 or not self.r.reader.get_matched_publications():
            if time.monotonic() > end:
                raise TimeoutError("the service is not available")
            time.sleep(0.05)
        sent: set[int] = set()
        next_send = 0.0
        while time.monotonic() < end:
            if time.monotonic() >= next_send:
                self.seq += 1
                sent.add(self.seq)
                self.w.publish(self._req_t(client_guid=self.guid, sequence_number=self.seq,
                                           structure_needs_at_least_one_member=0))
                next_send = time.monotonic() + resend_s
            for data, _ in self.r.take(8):
                rep = decode(self._rep_t, data)
                if rep.client_guid == self.guid and rep.sequence_number in sent:
                    return bool(rep.success), str(rep.message)
            time.sleep(0.02)
        raise TimeoutError("no reply")


# --------------------------------------------------------------------------- entry point


def _python_logging() -> None:
    lg = logging.getLogger("dynastereo")
    if not any(getattr(h, "_dynastereo", False) for h in lg.handlers):
        h = logging.StreamHandler()
        h.setFormatter(logging.Formatter("[dynastereo] %(levelname)s %(name)s: %(message)s"))
        h._dynastereo = True  # type: ignore[attr-defined]
        lg.addHandler(h)
    lg.setLevel(os.environ.get("DYNASTEREO_LOG", "INFO").upper())
    lg.propagate = False


def main(params_file: str | None = None) -> int:
    """``dynastereo node --ros2``: run until SIGINT / SIGTERM, then the final BA and the save."""
    import sys

    _python_logging()
    try:
        params = load_params(params_file)
        node = Ros2Node(params)
    except (DynastereoError, InputError, ConfigError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except Exception as e:  # a DDS start-up failure (a bad CYCLONEDDS_URI, no usable interface): one line
        if type(e).__module__.split(".")[0] != "cyclonedds":
            raise
        print(f"error: DDS could not start ({e}); check CYCLONEDDS_URI and ROS_DOMAIN_ID", file=sys.stderr)
        return 2
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: node.stop())
    try:
        node.spin()
    finally:
        node.shutdown()
    return 0
