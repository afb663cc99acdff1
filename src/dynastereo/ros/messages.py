"""What dynastereo publishes, built once for every message library.

The output of one frame is plain data (:class:`OdometryData`, :class:`DisparityData`,
numpy images); :class:`MessageBuilder` turns it into ROS messages.  Three builders exist:
:class:`RosbagsBuilder` (the ``rosbags`` dataclasses, for ROS 1 ``.bag`` and ROS 2
``.db3``/``.mcap`` files) here, ``GenpyBuilder`` (``rospy``'s classes) in
:mod:`dynastereo.ros.ros1` and ``DdsBuilder`` (the ROS 2 node's DDS types) in :mod:`dynastereo.ros.dds`.  The
builders differ only in how a time, a float array and a byte blob are represented and in
field spellings (``K``/``k``, ``T``/``t``, ``seq``), which :meth:`MessageBuilder.make`
smooths over.

Topic names (bags; the node publishes the same under its private namespace
``/dynastereo/...``):

=============================  =========================  ==============================
topic                          type                       content
=============================  =========================  ==============================
``/dynastereo/odometry``       nav_msgs/Odometry          left camera in ``odom``
``/tf``                        tf2_msgs/TFMessage         ``odom`` -> camera frame
``/dynastereo/left/masked``    sensor_msgs/Image          left image, dynamic pixels = 0
``/dynastereo/right/masked``   sensor_msgs/Image          right image, dynamic pixels = 0
``/dynastereo/left/mask``      sensor_msgs/Image mono8    255 = dynamic
``/dynastereo/right/mask``     sensor_msgs/Image mono8    255 = dynamic
``/dynastereo/disparity``      stereo_msgs/DisparityImage 32FC1 pixels, -1 = invalid
``/dynastereo/path``           nav_msgs/Path              the trajectory so far, in ``odom``
``/dynastereo/map_points``     sensor_msgs/PointCloud2    the map points (x, y, z float32)
                                                          in ``odom``, every ``MAP_EVERY``-th
                                                          frame and (bags) after the final BA
``/dynastereo/objects``        visualization_msgs/        the objects in ``odom``: a box (ns
                               MarkerArray                ``objects``), a label with the speed
                                                          (``labels``) and the path so far
                                                          (``paths``) per track; moving red,
                                                          static green, undecided orange
=============================  =========================  ==============================

In rviz: Fixed Frame ``odom``; add *Path* on ``/dynastereo/path``, *PointCloud2* on
``/dynastereo/map_points``, *MarkerArray* on ``/dynastereo/objects``, *Odometry*, *TF*, *Image* on the masked images.

``odom`` is the first frame's (rectified) left camera: the KITTI convention, camera axes
x right, y down, z forward.  The odometry of frame k is the pose tracking returned for
it, i.e. what a live node publishes; the trajectory files of ``run`` hold the final,
bundle-adjusted poses.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .convert import camera_info_fields, encode_compressed, image_fields, pose_quaternion, stamp_split

#: The input topics' defaults (``~left_topic`` / ``--left-topic`` ...).
DEFAULT_LEFT_TOPIC = "/camera/left/image_raw"
DEFAULT_RIGHT_TOPIC = "/camera/right/image_raw"
DEFAULT_LEFT_INFO = "/camera/left/camera_info"
DEFAULT_RIGHT_INFO = "/camera/right/camera_info"
DEFAULT_LEFT_FRAME = "camera_left"
DEFAULT_RIGHT_FRAME = "camera_right"
ODOM_FRAME = "odom"



@dataclass
class PlayLog:
    """What a player (``dynastereo play``, ROS 1 or ROS 2) published, and how late."""

    frames: list[int] = field(default_factory=list)
    stamps_ns: list[int] = field(default_factory=list)
    late_ms: list[float] = field(default_factory=list)  # publication later than scheduled
    answered: int = 0  # lock-step: frames whose odometry came back
    timeouts: int = 0  # lock-step: frames whose odometry did not come back in time

    def summary(self) -> dict[str, Any]:
        late = np.asarray(self.late_ms) if self.late_ms else np.zeros(1)
        return {"published": len(self.frames), "answered": self.answered, "timeouts": self.timeouts,
                "late_ms_median": round(float(np.median(late)), 3), "late_ms_max": round(float(late.max()), 3)}


OUTPUT_TOPICS: dict[str, str] = {
    "odometry": "/dynastereo/odometry",
    "tf": "/tf",
    "left_masked": "/dynastereo/left/masked",
    "right_masked": "/dynastereo/right/masked",
    "left_mask": "/dynastereo/left/mask",
    "right_mask": "/dynastereo/right/mask",
    "disparity": "/dynastereo/disparity",
    "path": "/dynastereo/path",
    "map_points": "/dynastereo/map_points",
    "objects": "/dynastereo/objects",
}
OUTPUT_TYPES: dict[str, str] = {
    "odometry": "nav_msgs/Odometry",
    "tf": "tf2_msgs/TFMessage",
    "left_masked": "sensor_msgs/Image",
    "right_masked": "sensor_msgs/Image",
    "left_mask": "sensor_msgs/Image",
    "right_mask": "sensor_msgs/Image",
    "disparity": "stereo_msgs/DisparityImage",
    "path": "nav_msgs/Path",
    "map_points": "sensor_msgs/PointCloud2",
    "objects": "visualization_msgs/MarkerArray",
}
MAP_EVERY = 10  # frames between two map point clouds (the whole map each time)

INVALID_DISPARITY = -1.0


@dataclass
class OdometryData:
    """One odometry sample: the left camera's pose in ``frame_id`` (camera-to-world)."""

    stamp_ns: int
    pose: np.ndarray  # 3x4 or 4x4 camera-to-world
    frame_id: str = ODOM_FRAME
    child_frame_id: str = DEFAULT_LEFT_FRAME
    linear: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m/s, child frame
    angular: np.ndarray = field(default_factory=lambda: np.zeros(3))  # rad/s, child frame
    seq: int = 0


@dataclass
class DisparityData:
    """A full-frame disparity map for ``stereo_msgs/DisparityImage``."""

    image: np.ndarray  # float32 pixels, <= 0 invalid (written as -1)
    f: float  # focal length, pixels
    T: float  # baseline, metres
    min_disparity: float
    max_disparity: float
    delta_d: float = 1.0 / 16.0  # StereoBM/SGBM resolution

    def ros_image(self) -> np.ndarray:
        d = np.asarray(self.image, dtype=np.float32)
        return np.where(d > 0, d, np.float32(INVALID_DISPARITY)).astype(np.float32)


MESH_MARKER_MAX = 100_000  # triangles in a mesh marker

class MessageBuilder:
    """Builds ROS messages for one message library (subclass per library)."""

    def cls(self, name: str) -> type:  # "sensor_msgs/Image"
        raise NotImplementedError

    def fields(self, cls: type) -> set[str]:
        raise NotImplementedError

    def time(self, stamp_ns: int) -> Any:
        raise NotImplementedError

    def floats(self, values: Any) -> Any:
        """A float64[] field value."""
        raise NotImplementedError

    def duration(self, ns: int) -> Any:
        raise NotImplementedError

    def blob(self, data: np.ndarray) -> Any:
        """A uint8[] field value."""
        raise NotImplementedError

    def make(self, name: str, /, **kw: Any) -> Any:
        """``name`` built from ``kw``; a key the type lacks is matched case-insensitively
        (``D`` -> ``d``) or dropped (``seq`` in ROS 2)."""
        c = self.cls(name)
        names = self.fields(c)
        out = {}
        for k, v in kw.items():
            if k in names:
                out[k] = v
            elif k.lower() in names:
                out[k.lower()] = v
            elif k.upper() in names:
                out[k.upper()] = v
        return c(**out)

    # ------------------------------------------------------------------ messages
    def header(self, stamp_ns: int, frame_id: str, seq: int = 0) -> Any:
        return self.make("std_msgs/Header", seq=int(seq), stamp=self.time(stamp_ns), frame_id=str(frame_id))

    def image(self, img: np.ndarray, stamp_ns: int, frame_id: str, encoding: str | None = None, seq: int = 0) -> Any:
        f = image_fields(img, encoding)
        return self.make("sensor_msgs/Image", header=self.header(stamp_ns, frame_id, seq), height=f["height"],
                         width=f["width"], encoding=f["encoding"], is_bigendian=f["is_bigendian"], step=f["step"],
                         data=self.blob(f["data"]))

    def compressed(self, img: np.ndarray, stamp_ns: int, frame_id: str, fmt: str = "png", seq: int = 0) -> Any:
        form, data = encode_compressed(img, fmt)
        return self.make("sensor_msgs/CompressedImage", header=self.header(stamp_ns, frame_id, seq), format=form,
                         data=self.blob(data))

    def camera_info(self, info: dict[str, Any], stamp_ns: int, frame_id: str, seq: int = 0) -> Any:
        """From :func:`~dynastereo.ros.convert.camera_info_fields`."""
        roi = self.make("sensor_msgs/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.make("sensor_msgs/CameraInfo", header=self.header(stamp_ns, frame_id, seq), height=info["height"],
                         width=info["width"], distortion_model=info["distortion_model"], D=self.floats(info["D"]),
                         K=self.floats(info["K"]), R=self.floats(info["R"]), P=self.floats(info["P"]),
                         binning_x=0, binning_y=0, roi=roi)

    def _vec3(self, name: str, v: np.ndarray) -> Any:
        return self.make(name, x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def _quat(self, q: np.ndarray) -> Any:
        return self.make("geometry_msgs/Quaternion", x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))

    def odometry(self, o: OdometryData) -> Any:
        p, q = pose_quaternion(o.pose)
        pose = self.make("geometry_msgs/Pose", position=self._vec3("geometry_msgs/Point", p), orientation=self._quat(q))
        twist = self.make("geometry_msgs/Twist", linear=self._vec3("geometry_msgs/Vector3", o.linear),
                          angular=self._vec3("geometry_msgs/Vector3", o.angular))
        zeros = self.floats(np.zeros(36))
        return self.make(
            "nav_msgs/Odometry",
            header=self.header(o.stamp_ns, o.frame_id, o.seq),
            child_frame_id=o.child_frame_id,
            pose=self.make("geometry_msgs/PoseWithCovariance", pose=pose, covariance=zeros),
            twist=self.make("geometry_msgs/TwistWithCovariance", twist=twist, covariance=self.floats(np.zeros(36))),
        )

    def transform(self, o: OdometryData) -> Any:
        p, q = pose_quaternion(o.pose)
        tr = self.make("geometry_msgs/Transform", translation=self._vec3("geometry_msgs/Vector3", p),
                       rotation=self._quat(q))
        return self.make("geometry_msgs/TransformStamped", header=self.header(o.stamp_ns, o.frame_id, o.seq),
                         child_frame_id=o.child_frame_id, transform=tr)

    def tf(self, o: OdometryData) -> Any:
        return self.make("tf2_msgs/TFMessage", transforms=[self.transform(o)])

    def pose_stamped(self, pose: np.ndarray, stamp_ns: int, frame_id: str, seq: int = 0) -> Any:
        p, q = pose_quaternion(pose)
        return self.make("geometry_msgs/PoseStamped", header=self.header(stamp_ns, frame_id, seq),
                         pose=self.make("geometry_msgs/Pose", position=self._vec3("geometry_msgs/Point", p),
                                        orientation=self._quat(q)))

    def path(self, poses: list[np.ndarray], stamps_ns: list[int], frame_id: str, seq: int = 0) -> Any:
        """``nav_msgs/Path`` of camera-to-world ``poses`` (the trajectory so far), stamped
        with the last stamp."""
        return self.make("nav_msgs/Path", header=self.header(stamps_ns[-1] if stamps_ns else 0, frame_id, seq),
                         poses=[self.pose_stamped(T, t, frame_id, k) for k, (T, t) in enumerate(zip(poses, stamps_ns))])

    def point_cloud(self, points: np.ndarray, stamp_ns: int, frame_id: str, seq: int = 0) -> Any:
        """``sensor_msgs/PointCloud2``: an unordered cloud of float32 x, y, z (little endian)."""
        xyz = np.ascontiguousarray(np.asarray(points, dtype="<f4").reshape(-1, 3))
        fields = [self.make("sensor_msgs/PointField", name=n, offset=4 * i, datatype=7, count=1)  # 7 = FLOAT32
                  for i, n in enumerate("xyz")]
        return self.make("sensor_msgs/PointCloud2", header=self.header(stamp_ns, frame_id, seq), height=1,
                         width=len(xyz), fields=fields, is_bigendian=False, point_step=12, row_step=12 * len(xyz),
                         data=self.blob(xyz.view(np.uint8).reshape(-1)), is_dense=True)

    def _marker(self, stamp_ns: int, frame_id: str, ns: str, mid: int, mtype: int, action: int = 0, *,
                pos=(0.0, 0.0, 0.0), quat=(0.0, 0.0, 0.0, 1.0), scale=(1.0, 1.0, 1.0), rgba=(1.0, 1.0, 1.0, 1.0),
                points=(), text: str = "", lifetime_ns: int = 0, seq: int = 0) -> Any:
        c = self.cls("visualization_msgs/Marker")
        extra = {}
        names = self.fields(c)
        if "texture" in names:  # ROS 2 (Humble+): the texture and mesh fields, empty
            extra = dict(texture_resource="", uv_coordinates=[],
                         texture=self.make("sensor_msgs/CompressedImage", header=self.header(0, ""), format="",
                                           data=self.blob(np.zeros(0, np.uint8))),
                         mesh_file=self.make("visualization_msgs/MeshFile", filename="",
                                             data=self.blob(np.zeros(0, np.uint8))))
        return self.make(
            "visualization_msgs/Marker", header=self.header(stamp_ns, frame_id, seq), ns=ns, id=int(mid),
            type=int(mtype), action=int(action),
            pose=self.make("geometry_msgs/Pose", position=self._vec3("geometry_msgs/Point", pos),
                           orientation=self._quat(quat)),
            scale=self._vec3("geometry_msgs/Vector3", scale),
            color=self.make("std_msgs/ColorRGBA", r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]),
                            a=float(rgba[3])),
            lifetime=self.duration(lifetime_ns), frame_locked=False,
            points=[self._vec3("geometry_msgs/Point", p) for p in points], colors=[], text=text, mesh_resource="",
            mesh_use_embedded_materials=False, **extra)

    def mesh_marker(self, mesh: Any, stamp_ns: int, frame_id: str, seq: int = 0) -> Any:
        """``visualization_msgs/Marker`` TRIANGLE_LIST of a :class:`dynastereo.mesh.Mesh`
        (vertex colours), at most :data:`MESH_MARKER_MAX` triangles (evenly spaced beyond)."""
        F = mesh.faces
        if len(F) > MESH_MARKER_MAX:
            F = F[np.linspace(0, len(F) - 1, MESH_MARKER_MAX).astype(np.int64)]
        idx = F.reshape(-1)
        m = self._marker(stamp_ns, frame_id, "static_world", 0, 11, seq=seq,  # 11: TRIANGLE_LIST
                         points=mesh.vertices[idx].astype(float).tolist())
        m.colors = [self.make("std_msgs/ColorRGBA", r=r, g=g, b=b, a=1.0)
                    for r, g, b in (mesh.colors[idx].astype(float) / 255.0).tolist()]
        return m

    def object_markers(self, objects: list, stamp_ns: int, frame_id: str, seq: int = 0,
                       paths: list | None = None) -> Any:
        """``visualization_msgs/MarkerArray`` of the objects with a world state
        (``ObjectMask.world``, :mod:`dynastereo.objects.world`): first a DELETEALL (objects
        gone from view vanish), then per object a CUBE (ns ``objects``, id = track id), a
        TEXT_VIEW_FACING label (``labels``: class, id, speed) and, from ``paths`` (``[(track,
        (n, 3), moving)]``, :class:`~dynastereo.objects.world.ObjectPaths`), a LINE_STRIP (``paths``)."""
        from ..objects.world import verdict_rgb

        CUBE, LINE_STRIP, TEXT, DELETEALL = 1, 4, 9, 3
        rgba = lambda moving: (*(v / 255.0 for v in verdict_rgb(moving)), 0.8)  # noqa: E731
        ms = [self._marker(stamp_ns, frame_id, "", 0, CUBE, DELETEALL, seq=seq)]
        for k, o in enumerate(objects):
            s = getattr(o, "world", None)
            if s is None:
                continue
            mid = int(o.track_id) if o.track_id >= 0 else 1_000_000 + k
            yaw = float(np.arctan2(s.heading[0], s.heading[2]))
            q = (0.0, np.sin(yaw / 2), 0.0, np.cos(yaw / 2))  # about y (down): z -> the heading
            ms.append(self._marker(stamp_ns, frame_id, "objects", mid, CUBE, pos=s.world, quat=q, scale=s.extent,
                                   rgba=rgba(o.moving), seq=seq))
            sp = f" {s.speed:.1f} m/s" if s.speed is not None else ""
            top = np.asarray(s.world, float) - (0.0, 0.5 * float(s.extent[1]) + 0.6, 0.0)
            ms.append(self._marker(stamp_ns, frame_id, "labels", mid, TEXT, pos=top, scale=(0.0, 0.0, 0.8),
                                   rgba=(1.0, 1.0, 1.0, 1.0), text=f"{o.label} #{o.track_id}{sp}", seq=seq))
        for t, pts, moving in paths or []:
            ms.append(self._marker(stamp_ns, frame_id, "paths", int(t), LINE_STRIP, scale=(0.15, 0.0, 0.0),
                                   rgba=rgba(moving), points=pts, seq=seq))
        return self.make("visualization_msgs/MarkerArray", markers=ms)

    def disparity(self, d: DisparityData, stamp_ns: int, frame_id: str, seq: int = 0) -> Any:
        img = d.ros_image()
        h, w = img.shape
        roi = self.make("sensor_msgs/RegionOfInterest", x_offset=0, y_offset=0, height=int(h), width=int(w),
                        do_rectify=False)
        return self.make("stereo_msgs/DisparityImage", header=self.header(stamp_ns, frame_id, seq),
                         image=self.image(img, stamp_ns, frame_id, "32FC1", seq), f=float(d.f), T=float(d.T),
                         valid_window=roi, min_disparity=float(d.min_disparity),
                         max_disparity=float(d.max_disparity), delta_d=float(d.delta_d))


# --------------------------------------------------------------------------- rosbags


_TF_MSG = "geometry_msgs/TransformStamped[] transforms\n"


def rosbags_typestore(ros1: bool):
    """The ``rosbags`` typestore for ROS 1 (Noetic, + tf2_msgs/TFMessage) or ROS 2 (Humble)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:
        ts.register(get_types_from_msg(_TF_MSG, "tf2_msgs/msg/TFMessage"))
    return ts


def msg_type_name(name: str) -> str:
    """``sensor_msgs/Image`` -> ``sensor_msgs/msg/Image`` (rosbags' spelling)."""
    pkg, _, base = name.partition("/")
    return name if base.startswith("msg/") else f"{pkg}/msg/{base}"


class RosbagsBuilder(MessageBuilder):
    def __init__(self, ros1: bool) -> None:
        self.ros1 = ros1
        self.typestore = rosbags_typestore(ros1)
        self._fields: dict[type, set[str]] = {}

    def cls(self, name: str) -> type:
        return self.typestore.types[msg_type_name(name)]

    def fields(self, cls: type) -> set[str]:
        f = self._fields.get(cls)
        if f is None:
            f = self._fields[cls] = {k for k in cls.__dataclass_fields__ if not k.startswith("__")}
        return f

    def time(self, stamp_ns: int) -> Any:
        sec, nsec = stamp_split(stamp_ns)
        return self.make("builtin_interfaces/Time", sec=sec, nanosec=nsec)

    def floats(self, values: Any) -> Any:
        return np.asarray(values, dtype=np.float64).reshape(-1)

    def blob(self, data: np.ndarray) -> Any:
        return np.ascontiguousarray(data, dtype=np.uint8).reshape(-1)

    def duration(self, ns: int) -> Any:
        sec, nsec = stamp_split(ns)
        return self.make("builtin_interfaces/Duration", sec=sec, nanosec=nsec)

    def serialize(self, msg: Any) -> bytes:
        t = msg.__msgtype__
        if self.ros1:
            return bytes(self.typestore.serialize_ros1(msg, t))
        return bytes(self.typestore.serialize_cdr(msg, t))


def stereo_camera_info(calib, P_left: np.ndarray | None = None, P_right: np.ndarray | None = None):
    """``(left, right)`` CameraInfo field dicts for a rectified calibration (exact P optional)."""
    return (camera_info_fields(calib, "left", P=P_left), camera_info_fields(calib, "right", P=P_right))
