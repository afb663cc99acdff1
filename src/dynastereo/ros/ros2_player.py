"""Publish a sequence over ROS 2 (DDS, no rclpy): ``dynastereo play --ros2 SOURCE``.

``SOURCE``: a ROS 2 bag (``.db3``, ``.mcap``) or any sequence folder ``dynastereo run``
reads.  Images (``sensor_msgs/Image`` mono8 / bgr8, reliable) and CameraInfo (reliable) go on
``/camera/{left,right}/image_raw`` and ``/camera/{left,right}/camera_info``; every message of
frame k carries one header stamp: the sequence's own (default) or the wall clock at
publication (``stamp="now"``, for latency).  Pacing: ``rate`` Hz (an absolute schedule, frame
k at ``t0 + k / rate``), the stamps' own pace (``rate=None``), or lock-step
(``lockstep=True``): frame k+1 only once the node's odometry of frame k came back on
``/dynastereo/odometry``.  Frames are read and decoded before playing, so reading files does
not disturb the pace.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from .bags import _exact_projections
from .convert import camera_info_fields
from .dds import DdsBuilder, Domain, QosKind, Waiter, decode, idl_type
from .messages import (
    DEFAULT_LEFT_FRAME,
    DEFAULT_LEFT_INFO,
    DEFAULT_LEFT_TOPIC,
    DEFAULT_RIGHT_FRAME,
    DEFAULT_RIGHT_INFO,
    DEFAULT_RIGHT_TOPIC,
    PlayLog,
    OUTPUT_TOPICS,
)


class Ros2Player:
    """Publishes ``frames`` of ``sequence`` over DDS (module doc)."""

    def __init__(self, sequence: Any, frames: list[int] | None = None, *, domain: Domain | None = None,
                 left_topic: str = DEFAULT_LEFT_TOPIC, right_topic: str = DEFAULT_RIGHT_TOPIC,
                 left_info: str | None = DEFAULT_LEFT_INFO, right_info: str | None = DEFAULT_RIGHT_INFO,
                 odometry_topic: str = OUTPUT_TOPICS["odometry"]) -> None:
        self.dom = domain or Domain(node_name="dynastereo_player")
        self.b = DdsBuilder()
        self.seq = sequence
        self.frames = (sequence.available_frames() if hasattr(sequence, "available_frames")
                       else list(range(len(sequence)))) if frames is None else list(frames)
        self.seq_stamps = np.round(np.asarray(sequence.timestamps(), np.float64) * 1e9).astype(np.int64)
        self._images: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for i in dict.fromkeys(self.frames):
            f = sequence.frame(i)
            self._images[i] = (f.left, f.right)
        Pl, Pr = _exact_projections(sequence)
        c = sequence.calibration
        self._info_fields = (camera_info_fields(c, "left", P=Pl), camera_info_fields(c, "right", P=Pr))
        w = self.dom.writer
        self.pub_l = w(left_topic, "sensor_msgs/Image", QosKind.RELIABLE)
        self.pub_r = w(right_topic, "sensor_msgs/Image", QosKind.RELIABLE)
        self.pub_li = w(left_info, "sensor_msgs/CameraInfo", QosKind.RELIABLE) if left_info else None
        self.pub_ri = w(right_info, "sensor_msgs/CameraInfo", QosKind.RELIABLE) if right_info else None
        self.odom = self.dom.reader(odometry_topic, "nav_msgs/Odometry", QosKind.RECORD)
        self._odom_t = idl_type("nav_msgs/Odometry")
        self.odometry: list[tuple[int, np.ndarray]] = []  # (stamp ns, 7: position, quaternion xyzw)
        self.odometry_received: list[float] = []  # wall clock s when each arrived
        self._odom_lock = threading.Lock()
        self._waiter = Waiter(self.dom.participant, [self.odom])
        self._stop = threading.Event()
        self._recorder = threading.Thread(target=self._record, name="odometry-recorder", daemon=True)
        self._recorder.start()
        self.dom.announce()

    def _record(self) -> None:
        """The odometry as it arrives (its receipt time: the latency figures), on its own thread."""
        while not self._stop.is_set():
            if self._waiter.wait(0.1):
                self._take_odometry()

    def close(self) -> None:
        self._stop.set()
        self._recorder.join(1.0)

    def wait_for_subscribers(self, timeout: float = 20.0) -> bool:
        """Until both image topics have a subscriber (CameraInfo goes with every frame: a node
        that reads its calibration from a file subscribes to none)."""
        pubs = [self.pub_l, self.pub_r]
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if all(p.matched() > 0 for p in pubs):
                return True
            time.sleep(0.05)
        return False

    def publish_infos(self, stamp_ns: int) -> None:
        for pub, info, fid in ((self.pub_li, self._info_fields[0], DEFAULT_LEFT_FRAME),
                               (self.pub_ri, self._info_fields[1], DEFAULT_RIGHT_FRAME)):
            if pub is not None:
                pub.publish(self.b.camera_info(info, stamp_ns, fid))

    def publish_frame(self, i: int, stamp_ns: int, seq: int) -> None:
        left, right = self._images[i]
        self.publish_infos(stamp_ns)
        self.pub_l.publish(self.b.image(left, stamp_ns, DEFAULT_LEFT_FRAME))
        self.pub_r.publish(self.b.image(right, stamp_ns, DEFAULT_RIGHT_FRAME))

    def _take_odometry(self) -> None:
        with self._odom_lock:
            for data, _ in self.odom.take(64):
                t = time.time()
                m = decode(self._odom_t, data)
                p, q = m.pose.pose.position, m.pose.pose.orientation
                st = m.header.stamp
                self.odometry.append((int(st.sec) * 1_000_000_000 + int(st.nanosec),
                                      np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w])))
                self.odometry_received.append(t)

    def wait_odometry(self, stamp_ns: int, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while True:
            if any(s == stamp_ns for s, _ in self.odometry[-4:]):
                return True
            if time.monotonic() > end:
                return False
            time.sleep(0.002)

    def play(self, rate_hz: float | None = 10.0, stamp: str = "sequence", lockstep: bool = False,
             frame_timeout: float = 60.0) -> PlayLog:
        """Publish the frames (module doc); ``rate_hz`` None: at the stamps' pace."""
        log = PlayLog()
        t0 = time.monotonic() + 0.01
        s0 = int(self.seq_stamps[self.frames[0]]) if self.frames else 0
        for k, i in enumerate(self.frames):
            if not lockstep:
                when = t0 + (k / float(rate_hz) if rate_hz else (int(self.seq_stamps[i]) - s0) * 1e-9)
                delay = when - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                log.late_ms.append(max(0.0, (time.monotonic() - when) * 1000.0))
            ns = time.time_ns() if stamp == "now" else int(self.seq_stamps[i])
            self.publish_frame(i, ns, k)
            log.frames.append(i)
            log.stamps_ns.append(ns)
            if lockstep:
                if self.wait_odometry(ns, frame_timeout):
                    log.answered += 1
                else:
                    log.timeouts += 1
        return log

    def drain(self, n: int, timeout: float = 10.0) -> None:
        """Take odometry until ``n`` messages in all came, or ``timeout`` s."""
        end = time.monotonic() + timeout
        while len(self.odometry) < n and time.monotonic() < end:
            time.sleep(0.005)


def open_source(source: str, frames: str | None = None, rate: float | None = None) -> tuple[Any, list[int]]:
    """A bag (``.db3``, ``.mcap``, a ROS 2 bag folder) or a sequence folder, and its frames."""
    from pathlib import Path

    from ..io.frames import select_frames
    from ..runtime.sources import open_sequence_source
    from ..runtime.spec import SourceSpec
    from .bagrun import BagSource
    from .bags import bag_format

    p = Path(source)
    try:
        is_bag = bag_format(p) is not None
    except Exception:  # noqa: BLE001 -- not a bag: a sequence folder
        is_bag = False
    spec = SourceSpec(opener=BagSource(p)) if is_bag else SourceSpec(path=p, rate=None)
    seq = open_sequence_source(spec)
    return seq, select_frames(frames, seq)
