"""Publish a stereo sequence folder as live ROS 1 topics at a fixed rate (tests, benchmark,
demos): ``python -m dynastereo.ros.player SEQUENCE --rate 10 [--frames 0-24]``.

Images (``sensor_msgs/Image``, mono8 / bgr8) and CameraInfo go on the default topics
``/camera/{left,right}/image_raw`` and ``/camera/{left,right}/camera_info``; every message
of frame k carries the same header stamp: the wall-clock time of publication
(``stamp="now"``, so that a subscriber can measure latency) or the sequence's own stamp.
Frames are decoded and turned into messages before playing, so reading files does not
disturb the rate; the schedule is absolute (frame k at ``t0 + k / rate``).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import numpy as np

from .bags import _exact_projections
from .convert import camera_info_fields
from .messages import (
    DEFAULT_LEFT_FRAME,
    DEFAULT_LEFT_INFO,
    DEFAULT_LEFT_TOPIC,
    DEFAULT_RIGHT_FRAME,
    DEFAULT_RIGHT_INFO,
    DEFAULT_RIGHT_TOPIC,
    PlayLog,
)
from .ros1 import GenpyBuilder, import_rospy


class StereoPlayer:
    """Publishes ``frames`` of ``sequence`` (call after ``rospy.init_node``)."""

    def __init__(
        self,
        sequence: Any,
        frames: list[int] | None = None,
        *,
        left_topic: str = DEFAULT_LEFT_TOPIC,
        right_topic: str = DEFAULT_RIGHT_TOPIC,
        left_info: str | None = DEFAULT_LEFT_INFO,
        right_info: str | None = DEFAULT_RIGHT_INFO,
    ) -> None:
        rospy = import_rospy()
        from sensor_msgs.msg import CameraInfo, Image

        self.rospy = rospy
        self.b = GenpyBuilder()
        self.seq = sequence
        self.frames = (sequence.available_frames() if hasattr(sequence, "available_frames")
                       else list(range(len(sequence)))) if frames is None else list(frames)
        self.seq_stamps = np.round(np.asarray(sequence.timestamps(), np.float64) * 1e9).astype(np.int64)
        # messages without their stamps, prepared once
        self._msgs: dict[int, tuple[Any, Any]] = {}
        for i in dict.fromkeys(self.frames):
            f = sequence.frame(i)
            self._msgs[i] = (self.b.image(f.left, 0, DEFAULT_LEFT_FRAME), self.b.image(f.right, 0, DEFAULT_RIGHT_FRAME))
        Pl, Pr = _exact_projections(sequence)
        c = sequence.calibration
        self._infos = (self.b.camera_info(camera_info_fields(c, "left", P=Pl), 0, DEFAULT_LEFT_FRAME),
                       self.b.camera_info(camera_info_fields(c, "right", P=Pr), 0, DEFAULT_RIGHT_FRAME))
        self.pub_l = rospy.Publisher(left_topic, Image, queue_size=5)
        self.pub_r = rospy.Publisher(right_topic, Image, queue_size=5)
        self.pub_li = rospy.Publisher(left_info, CameraInfo, queue_size=5) if left_info else None
        self.pub_ri = rospy.Publisher(right_info, CameraInfo, queue_size=5) if right_info else None

    def wait_for_subscribers(self, timeout: float = 20.0) -> bool:
        pubs = [p for p in (self.pub_l, self.pub_r, self.pub_li, self.pub_ri) if p is not None]
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if all(p.get_num_connections() > 0 for p in pubs):
                return True
            time.sleep(0.05)
        return False

    def _stamp(self, msg: Any, ns: int, seq: int) -> None:
        msg.header.stamp = self.b.time(ns)
        msg.header.seq = seq

    def publish_infos(self, stamp_ns: int | None = None) -> None:
        """The CameraInfo pair alone (a driver's first message; lets the node set up)."""
        ns = time.time_ns() if stamp_ns is None else stamp_ns
        for pub, msg in ((self.pub_li, self._infos[0]), (self.pub_ri, self._infos[1])):
            if pub is not None:
                self._stamp(msg, ns, 0)
                pub.publish(msg)

    def play(self, rate_hz: float = 10.0, stamp: str = "now", frames: list[int] | None = None) -> PlayLog:
        """Publish ``frames`` (default: all given at construction) at ``rate_hz``."""
        frames = self.frames if frames is None else frames
        log = PlayLog()
        period = 1.0 / float(rate_hz)
        t0 = time.monotonic() + 0.01
        for k, i in enumerate(frames):
            when = t0 + k * period
            delay = when - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            log.late_ms.append(max(0.0, (time.monotonic() - when) * 1000.0))
            ns = time.time_ns() if stamp == "now" else int(self.seq_stamps[i])
            lm, rm = self._msgs[i]
            for msg in (lm, rm, self._infos[0], self._infos[1]):
                self._stamp(msg, ns, k)
            if self.pub_li is not None:
                self.pub_li.publish(self._infos[0])
                self.pub_ri.publish(self._infos[1])
            self.pub_l.publish(lm)
            self.pub_r.publish(rm)
            log.frames.append(i)
            log.stamps_ns.append(ns)
        return log


def main(argv: list[str] | None = None) -> int:
    from ..io import open_sequence
    from ..io.frames import select_frames

    ap = argparse.ArgumentParser(prog="python -m dynastereo.ros.player", description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence")
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--frames", default=None)
    ap.add_argument("--stamp", choices=("now", "sequence"), default="now")
    ap.add_argument("--no-camera-info", action="store_true")
    ap.add_argument("--wait", type=float, default=20.0, help="seconds to wait for subscribers")
    a = ap.parse_args(argv)
    rospy = import_rospy()
    rospy.init_node("dynastereo_player", anonymous=True, disable_signals=True)
    seq = open_sequence(a.sequence)
    frames = select_frames(a.frames, seq)
    kw = {"left_info": None, "right_info": None} if a.no_camera_info else {}
    player = StereoPlayer(seq, frames, **kw)
    if not player.wait_for_subscribers(a.wait):
        print("no subscribers; publishing anyway", file=sys.stderr)
    player.publish_infos()
    log = player.play(a.rate, a.stamp)
    print(f"published {len(log.frames)} frames at {a.rate:g} Hz "
          f"(late median {float(np.median(log.late_ms)):.1f} ms)")
    time.sleep(0.5)
    rospy.signal_shutdown("done")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
