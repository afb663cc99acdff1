"""ROS 1 node ``dynastereo_node``: a thin ``rospy`` adapter over :class:`StereoNodeCore`.

Run it with ``roslaunch dynastereo dynastereo.launch`` (see ``dynastereo node --launch``),
``dynastereo node``, or ``python -m dynastereo.ros.ros1``.  Needs ROS 1's Python packages
(Debian bookworm: ``python3-rospy python3-message-filters python3-sensor-msgs
python3-nav-msgs python3-stereo-msgs python3-tf2-msgs python3-std-srvs``) importable next to
dynastereo: a venv made with ``/usr/bin/python3 -m venv --system-site-packages``.  Images are
converted with numpy (:mod:`.convert`), not cv_bridge.

Subscribes (message_filters, approximate-time synchronized; ``~exact_sync`` for exact)
    ``~left_topic`` / ``~right_topic``   sensor_msgs/Image (or CompressedImage on
    ``<topic>/compressed`` with ``~compressed: true``), default ``/camera/{left,right}/image_raw``;
    ``~left_info_topic`` / ``~right_info_topic``  sensor_msgs/CameraInfo (``~use_camera_info``).

Publishes
    ``~odometry`` nav_msgs/Odometry, ``/tf`` (``~odom_frame`` -> camera frame), ``~left/masked``,
    ``~right/masked``, ``~left/mask``, ``~right/mask`` (sensor_msgs/Image; the masks SLAM got:
    objects judged moving or not yet judged), ``~left/objects`` (bgr8: the left image with
    the objects in the colours of the motion test's verdicts, ``viz.draw.VERDICT_COLOURS``:
    moving red, undecided orange, static green), ``~disparity``
    (stereo_msgs/DisparityImage), ``~path`` (nav_msgs/Path, the trajectory so far, latched),
    ``~map_points`` (sensor_msgs/PointCloud2, the map every ``MAP_EVERY``-th frame, latched),
    ``~objects`` (visualization_msgs/MarkerArray: each object's box, label with its speed
    and path in ``odom``, in the verdict's colour; ``objects.world``),
    ``~ready`` (std_msgs/Bool, latched: true once the SLAM has its calibration).  Images,
    disparity, path and map are computed and sent only while someone subscribes.

Services (std_srvs/Trigger)
    ``~save_trajectory`` -- trajectory (KITTI, TUM), timing.json, node.json into ``~save_dir``;
    ``~status`` -- statistics (received, processed, dropped, latency), configuration (JSON);
    ``~build_mesh`` (with ``~mesh: true``, which keeps the keyframes from the start) -- the
    static world's mesh so far (``dynastereo.mesh``) into ``~save_dir/mesh.ply``, published
    on ``~mesh`` (visualization_msgs/Marker TRIANGLE_LIST, latched, at most
    ``messages.MESH_MARKER_MAX`` triangles) and ``~dense_cloud`` (sensor_msgs/PointCloud2, latched); replies its counts (JSON).

Parameters (private)
    ``~stereo/*``, ``~masker/*``, ``~detector/*`` -- the Config sections; changed at run time
    (``rosparam set /dynastereo/stereo/block_size 21``), polled every ``~param_poll_period``
    s; a bad value is refused (logged) and set back.  ``~queue_size`` (default 1) is live too.
    ``~slam/*``, ``~objects/*``, ``~seed``, ``~config`` (YAML), ``~calib`` (calibration YAML used instead of
    CameraInfo), ``~models_dir``, ``~rectify`` (auto/yes/no), ``~pipelined``, ``~sync_slop``,
    ``~sync_queue_size``, ``~odom_frame``, ``~camera_frame``, ``~publish_tf``, ``~save_dir``,
    ``~save_on_shutdown`` are read at start-up.  On start-up the node writes the complete
    effective configuration back to the parameter server.
"""

from __future__ import annotations

import importlib
import json
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..config import Config, load_config, to_dict
from ..dotted import flatten_dotted, nest_dotted
from ..errors import DynastereoError, RosUnavailable
from ..slam.warmup import warm_up_kernels
from .convert import CameraInfoData, ImageDecoder, calibration_from_camera_info, image_outputs, stamp_split
from .core import LIVE_SECTIONS, NodeResult, StereoInput, StereoNodeCore, flatten_live
from .messages import (
    DEFAULT_LEFT_INFO,
    DEFAULT_LEFT_TOPIC,
    DEFAULT_RIGHT_INFO,
    DEFAULT_RIGHT_TOPIC,
    MAP_EVERY,
    ODOM_FRAME,
    DisparityData,
    MessageBuilder,
)

log = logging.getLogger("dynastereo.ros")

ROS1_PACKAGES = ("python3-rospy", "python3-rosmaster", "python3-roslaunch", "rosout", "python3-message-filters",
                 "python3-sensor-msgs", "python3-nav-msgs", "python3-stereo-msgs", "python3-tf2-msgs",
                 "python3-std-srvs", "python3-rostopic", "python3-rosbag", "python3-visualization-msgs")


def import_rospy():
    """``rospy`` or a RosUnavailable naming the packages to install."""
    try:
        import rospy  # noqa: F401

        return rospy
    except ImportError as e:
        raise RosUnavailable(
            f"ROS 1 is not importable ({e}). On Debian bookworm: apt-get install {' '.join(ROS1_PACKAGES)}; "
            "then use a venv created with '/usr/bin/python3 -m venv --system-site-packages' (make venv does)") from None



class GenpyBuilder(MessageBuilder):
    """Messages as rospy's (genpy) classes."""

    def __init__(self) -> None:
        self._classes: dict[str, type] = {}

    def cls(self, name: str) -> type:
        c = self._classes.get(name)
        if c is None:
            pkg, _, base = name.partition("/")
            base = base.split("/")[-1]
            c = self._classes[name] = getattr(importlib.import_module(f"{pkg}.msg"), base)
        return c

    def fields(self, cls: type) -> set[str]:
        return set(cls.__slots__)

    def time(self, stamp_ns: int) -> Any:
        import rospy

        s, ns = stamp_split(stamp_ns)
        return rospy.Time(s, ns)

    def floats(self, values: Any) -> Any:
        return [float(v) for v in np.asarray(values, dtype=np.float64).reshape(-1)]

    def blob(self, data: np.ndarray) -> Any:
        return np.ascontiguousarray(data, dtype=np.uint8).tobytes()

    def duration(self, ns: int) -> Any:
        import rospy

        s, n = stamp_split(ns)
        return rospy.Duration(s, n)


def stamp_ns_of(msg: Any) -> int:
    st = msg.header.stamp
    return int(st.secs) * 1_000_000_000 + int(st.nsecs)


def _nested(d: dict[str, Any]) -> dict[str, Any]:
    """Config dict for the parameter server: None values left out (not representable)."""
    return nest_dotted(flatten_dotted(d, skip_none=True))


def config_from_params(rospy: Any) -> Config:
    """``~config`` YAML (if any) with the ``~stereo``, ``~masker``, ``~detector``, ``~slam``,
    ``~objects`` and ``~seed`` parameters on top."""
    path = rospy.get_param("~config", "") or None
    cfg = load_config(path)
    overrides: dict[str, Any] = {}
    for section in LIVE_SECTIONS + ("slam", "objects"):
        v = rospy.get_param("~" + section, None)
        if isinstance(v, dict):
            overrides.update(flatten_dotted(v, section))
    if rospy.has_param("~seed"):
        overrides["seed"] = rospy.get_param("~seed")
    return cfg.with_overrides(overrides)


class Ros1Node:
    """The rospy side: subscriptions, publishers, services, parameters (module doc)."""

    def __init__(self) -> None:
        rospy = import_rospy()
        self.rospy = rospy
        calibration = self._read_params()
        self._make_publishers()
        self._publish_config(calibration)
        lt, rt = self._subscribe()
        self._serve()
        rospy.loginfo("dynastereo: listening on %s + %s%s; masker %s, detector %s, queue_size %d", lt, rt,
                      f" with CameraInfo {self.info_topics[0]}, {self.info_topics[1]}" if self.use_info else "",
                      self.cfg.masker.kind, self.cfg.detector.name, self.core.queue_size)

    def _read_params(self) -> Any:
        """The node's parameters, its configuration and its core; the calibration given by
        ``~calib`` (or an ORB-SLAM2 ``~config`` without CameraInfo), else None."""
        from std_srvs.srv import TriggerResponse

        rospy = self.rospy
        self._TriggerResponse = TriggerResponse
        self.b = GenpyBuilder()
        p = rospy.get_param
        self.cfg = config_from_params(rospy)
        models_dir = p("~models_dir", "") or os.environ.get("DYNASTEREO_MODELS") or None
        self.save_dir = Path(os.path.expanduser(p("~save_dir", "") or os.path.join(_ros_home(), "dynastereo")))
        self.save_on_shutdown = bool(p("~save_on_shutdown", True))
        self.publish_tf = bool(p("~publish_tf", True))
        self.rectify = str(p("~rectify", "auto"))
        self.use_info = bool(p("~use_camera_info", True))
        calib_file = p("~calib", "") or None
        config_file = p("~config", "") or None
        calibration = None
        if calib_file:
            from ..io.calib import load_stereo_yaml

            calibration = load_stereo_yaml(calib_file)
            self.use_info = False
        elif config_file and not self.use_info:
            from ..io.calib import load_stereo_yaml

            calibration = load_stereo_yaml(config_file)  # an ORB-SLAM2 settings file carries the camera
        self.core = StereoNodeCore(self.cfg, models_dir=models_dir, queue_size=int(p("~queue_size", 1)),
                                   pipelined=bool(p("~pipelined", True)), sink=self,
                                   odom_frame=str(p("~odom_frame", ODOM_FRAME)), camera_frame=str(p("~camera_frame", "")),
                                   mesh=bool(p("~mesh", False)))
        self.decoder = ImageDecoder(p("~mono16_shift", None))
        self._info0: tuple[CameraInfoData, CameraInfoData] | None = None
        self._info_warned = False
        self.counts = {"left": 0, "right": 0, "pairs": 0, "calibration_changes": 0}
        self._calib_lock = threading.Lock()
        return calibration

    def _make_publishers(self) -> None:
        from nav_msgs.msg import Odometry, Path as PathMsg
        from sensor_msgs.msg import Image, PointCloud2
        from std_msgs.msg import Bool
        from stereo_msgs.msg import DisparityImage
        from tf2_msgs.msg import TFMessage

        rospy = self.rospy
        self.pub_odom = rospy.Publisher("~odometry", Odometry, queue_size=10)
        self.pub_tf = rospy.Publisher("/tf", TFMessage, queue_size=100) if self.publish_tf else None
        self.pub_img = {k: rospy.Publisher("~" + k, Image, queue_size=2)
                        for k in ("left/masked", "right/masked", "left/mask", "right/mask", "left/objects")}
        self.pub_disp = rospy.Publisher("~disparity", DisparityImage, queue_size=2)
        self.pub_path = rospy.Publisher("~path", PathMsg, queue_size=1, latch=True)
        self.pub_map = rospy.Publisher("~map_points", PointCloud2, queue_size=1, latch=True)
        from ..objects.world import ObjectPaths

        try:
            from visualization_msgs.msg import MarkerArray
        except ImportError:  # a minimal ROS install: no ~objects markers, said once
            rospy.logwarn("visualization_msgs not installed (Debian: python3-visualization-msgs): "
                          "~objects markers are not published")
            self.pub_objects = None
        else:
            self.pub_objects = rospy.Publisher("~objects", MarkerArray, queue_size=2)
        self._object_paths = ObjectPaths()
        self._path: tuple[list[np.ndarray], list[int]] = ([], [])
        self.pub_ready = rospy.Publisher("~ready", Bool, queue_size=1, latch=True)
        self._Bool = Bool
        self.pub_ready.publish(Bool(False))


    def _publish_config(self, calibration: Any) -> None:
        """The complete effective configuration on the parameter server; the calibration set
        and the node ready, when it was given; the kernels warmed up."""
        rospy = self.rospy
        d = _nested(to_dict(self.cfg))
        for section in LIVE_SECTIONS + ("slam", "objects"):
            rospy.set_param("~" + section, d[section])
        rospy.set_param("~seed", self.cfg.seed)
        rospy.set_param("~queue_size", self.core.queue_size)

        if calibration is not None:
            self.core.set_calibration(calibration)
            self.core.warm_up()
            self.pub_ready.publish(self._Bool(True))
        else:  # before the first CameraInfo: what does not need the camera's size
            self.core.warm_up()
            warm_up_kernels()

    def _subscribe(self) -> tuple[str, str]:
        """The image (and CameraInfo) subscriptions, synchronized; returns the image topics."""
        import message_filters
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image

        p = self.rospy.get_param
        compressed = bool(p("~compressed", False))
        img_type = CompressedImage if compressed else Image
        suffix = "/compressed" if compressed else ""
        lt = p("~left_topic", DEFAULT_LEFT_TOPIC) + suffix
        rt = p("~right_topic", DEFAULT_RIGHT_TOPIC) + suffix
        self.topics = (lt, rt)
        sub_kw = dict(queue_size=int(p("~subscriber_queue_size", 10)), buff_size=2 ** 24, tcp_nodelay=True)
        self.sub_l = message_filters.Subscriber(lt, img_type, **sub_kw)
        self.sub_r = message_filters.Subscriber(rt, img_type, **sub_kw)
        self.sub_l.registerCallback(lambda m: self._count("left"))
        self.sub_r.registerCallback(lambda m: self._count("right"))
        filters = [self.sub_l, self.sub_r]
        self.info_topics = (p("~left_info_topic", DEFAULT_LEFT_INFO), p("~right_info_topic", DEFAULT_RIGHT_INFO))
        self._info_subs = []
        if self.use_info:
            fl = message_filters.Subscriber(self.info_topics[0], CameraInfo, queue_size=5, tcp_nodelay=True)
            fr = message_filters.Subscriber(self.info_topics[1], CameraInfo, queue_size=5, tcp_nodelay=True)
            filters += [fl, fr]
            self._latest_info: dict[str, Any] = {}
            fl.registerCallback(lambda m: self._on_info("left", m))
            fr.registerCallback(lambda m: self._on_info("right", m))
        qs = int(p("~sync_queue_size", 10))
        if bool(p("~exact_sync", False)):
            self.sync = message_filters.TimeSynchronizer(filters, qs)
        else:
            self.sync = message_filters.ApproximateTimeSynchronizer(filters, qs, float(p("~sync_slop", 0.01)))
        self.sync.registerCallback(self._on_pair)
        return lt, rt

    def _serve(self) -> None:
        """The services, the parameter polling and the shutdown hook; the core started."""
        from sensor_msgs.msg import PointCloud2
        from std_srvs.srv import Trigger

        rospy, p = self.rospy, self.rospy.get_param
        self.srv_save = rospy.Service("~save_trajectory", Trigger, self._srv_save)
        self.srv_status = rospy.Service("~status", Trigger, self._srv_status)
        self.pub_mesh = self.pub_dense = None
        if self.core.mesh_recorder is not None:
            if self.pub_objects is not None:  # visualization_msgs is there
                from visualization_msgs.msg import Marker

                self.pub_mesh = rospy.Publisher("~mesh", Marker, queue_size=1, latch=True)
            self.pub_dense = rospy.Publisher("~dense_cloud", PointCloud2, queue_size=1, latch=True)
            self.srv_mesh = rospy.Service("~build_mesh", Trigger, self._srv_mesh)
        self._poll_timer = rospy.Timer(rospy.Duration(float(p("~param_poll_period", 0.5))), self._poll_params)
        rospy.on_shutdown(self._on_shutdown)
        self.core.start()

    # ------------------------------------------------------------------ input
    def _count(self, side: str) -> None:
        self.counts[side] += 1

    def _on_info(self, side: str, msg: Any) -> None:
        """The first CameraInfo pair sets the calibration (before the first image pair
        needs it, when the camera driver sends CameraInfo ahead)."""
        if self.core.ready:
            return
        self._latest_info[side] = msg
        if "left" in self._latest_info and "right" in self._latest_info:
            self._ensure_calibration(self._latest_info["left"], self._latest_info["right"])

    def _ensure_calibration(self, linfo: Any, rinfo: Any) -> None:
        with self._calib_lock:
            li, ri = CameraInfoData.from_msg(linfo), CameraInfoData.from_msg(rinfo)
            if self._info0 is None:
                calib = calibration_from_camera_info(li, ri, self.rectify, where=f"{self.info_topics}")
                self.core.set_calibration(calib)
                self.core.warm_up()
                self._info0 = (li, ri)
                self.pub_ready.publish(self._Bool(True))
                c = self.core.calibration
                self.rospy.loginfo("dynastereo: calibration from CameraInfo: fx %.3f, baseline %.4f m, %dx%d%s",
                                   c.fx, c.baseline, c.width, c.height,
                                   ", rectifying" if self.core.rectifier is not None else "")
            elif not (li.same(self._info0[0]) and ri.same(self._info0[1])):
                self.counts["calibration_changes"] += 1
                if not self._info_warned:
                    self._info_warned = True
                    self.rospy.logwarn("dynastereo: CameraInfo changed; keeping the first calibration")

    def _on_pair(self, lmsg: Any, rmsg: Any, linfo: Any = None, rinfo: Any = None) -> None:
        received = time.time()
        self.counts["pairs"] += 1
        try:
            if linfo is not None:
                self._ensure_calibration(linfo, rinfo)
            left = self.decoder.decode(lmsg, self.topics[0])
            right = self.decoder.decode(rmsg, self.topics[1])
        except DynastereoError as e:
            self.core.stats.errors += 1
            self.core.stats.last_error = str(e)
            self.rospy.logerr_throttle(5.0, f"dynastereo: {e}")
            return
        self.core.submit(StereoInput(left, right, stamp_ns_of(lmsg), str(lmsg.header.frame_id or ""), received))

    # ------------------------------------------------------------------ NodeSink
    def publish_pose(self, r: NodeResult) -> None:
        self.pub_odom.publish(self.b.odometry(r.odometry))
        if self.pub_tf is not None:
            self.pub_tf.publish(self.b.tf(r.odometry))

    def wants_disparity(self) -> bool:
        return self.pub_disp.get_num_connections() > 0

    def publish_images(self, r: NodeResult, disparity: DisparityData | None) -> None:
        fid = r.odometry.child_frame_id
        for key, img, enc in image_outputs(r.frame, r.masks):
            pub = self.pub_img[key]
            if pub.get_num_connections() > 0:
                pub.publish(self.b.image(img(), r.stamp_ns, fid, enc, seq=r.position))
        if disparity is not None:
            self.pub_disp.publish(self.b.disparity(disparity, r.stamp_ns, fid, seq=r.position))
        odom = r.odometry.frame_id
        self._path[0].append(r.odometry.pose)
        self._path[1].append(r.stamp_ns)
        if self.pub_path.get_num_connections() > 0:
            self.pub_path.publish(self.b.path(*self._path, odom, seq=r.position))
        objs = r.masks.objects if r.masks is not None else []
        self._object_paths.add(objs)
        if self.pub_objects is not None and self.pub_objects.get_num_connections() > 0:
            self.pub_objects.publish(self.b.object_markers(objs, r.stamp_ns, odom, r.position,
                                                           self._object_paths.paths()))
        if r.position % MAP_EVERY == 0 and self.pub_map.get_num_connections() > 0:
            self.pub_map.publish(self.b.point_cloud(self.core.map_points(), r.stamp_ns, odom, seq=r.position))

    # ------------------------------------------------------------------ services, params
    def status(self) -> dict[str, Any]:
        d = self.core.status()
        d["topics"] = dict(self.counts)
        d["unpaired_left"] = max(0, self.counts["left"] - self.counts["pairs"])
        d["unpaired_right"] = max(0, self.counts["right"] - self.counts["pairs"])
        return d

    def _srv_save(self, _req: Any) -> Any:
        try:
            paths = self.core.save(self.save_dir)
            return self._TriggerResponse(True, json.dumps(paths))
        except Exception as e:  # noqa: BLE001 - reported to the caller
            return self._TriggerResponse(False, f"{type(e).__name__}: {e}")

    def _srv_mesh(self, _req: Any) -> Any:
        ok, message = self.core.mesh_service(self.b, self.save_dir, self.pub_mesh, self.pub_dense)
        return self._TriggerResponse(ok, message)

    def _srv_status(self, _req: Any) -> Any:
        return self._TriggerResponse(True, json.dumps(self.status(), default=float))

    def _poll_params(self, _event: Any = None) -> None:
        rospy = self.rospy
        try:
            wanted: dict[str, Any] = {}
            for section in LIVE_SECTIONS:
                v = rospy.get_param("~" + section, None)
                if isinstance(v, dict):
                    wanted.update(flatten_dotted(v, section))
            q = rospy.get_param("~queue_size", self.core.queue_size)
        except Exception as e:  # noqa: BLE001 - master gone during shutdown
            log.debug("parameter poll failed: %s", e)
            return
        current = flatten_live(self.core.cfg)
        diff = {k: v for k, v in wanted.items() if current.get(k) != v}
        if diff:
            try:
                applied = self.core.update_params(diff)
                if applied:
                    rospy.loginfo("dynastereo: parameters applied: %s", applied)
            except DynastereoError as e:
                rospy.logerr("dynastereo: parameters refused (%s); set back", e)
                for k in diff:
                    if k in current:
                        rospy.set_param("~" + k.replace(".", "/"), current[k])
                    else:
                        rospy.delete_param("~" + k.replace(".", "/"))
        if q != self.core.queue_size:
            try:
                self.core.set_queue_size(int(q))
                rospy.loginfo("dynastereo: queue_size %d", self.core.queue_size)
            except (DynastereoError, TypeError, ValueError) as e:
                rospy.logerr("dynastereo: queue_size refused (%s); set back", e)
                rospy.set_param("~queue_size", self.core.queue_size)

    def _on_shutdown(self) -> None:
        try:
            self._poll_timer.shutdown()
        except Exception:  # noqa: BLE001
            pass
        self.core.shutdown()
        if self.save_on_shutdown and self.core.ready and self.core.stats.processed:
            try:
                self.core.save(self.save_dir)
                log.info("dynastereo: trajectory saved to %s", self.save_dir)
            except Exception as e:  # noqa: BLE001
                log.error("dynastereo: saving the trajectory failed: %s", e)


def _python_logging() -> None:
    """dynastereo's Python logging to stderr (roslaunch's screen / log).  rospy's logging
    set-up (fileConfig) disables loggers created before init_node: re-enable ours."""
    lg = logging.getLogger("dynastereo")
    for name, other in logging.root.manager.loggerDict.items():
        if name.startswith("dynastereo") and isinstance(other, logging.Logger):
            other.disabled = False
    lg.disabled = False
    if not any(getattr(h, "_dynastereo", False) for h in lg.handlers):
        h = logging.StreamHandler()
        h.setFormatter(logging.Formatter("[dynastereo] %(levelname)s %(name)s: %(message)s"))
        h._dynastereo = True  # type: ignore[attr-defined]
        lg.addHandler(h)
    lg.setLevel(os.environ.get("DYNASTEREO_LOG", "INFO").upper())
    lg.propagate = False


def _ros_home() -> str:
    return os.environ.get("ROS_HOME") or os.path.join(os.path.expanduser("~"), ".ros")


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``dynastereo_node``."""
    import sys

    try:
        rospy = import_rospy()
    except RosUnavailable as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    rospy.init_node("dynastereo", argv=argv if argv is not None else sys.argv)
    _python_logging()
    try:
        Ros1Node()
    except DynastereoError as e:
        rospy.logfatal(f"dynastereo: {e}")
        return 2
    rospy.spin()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
