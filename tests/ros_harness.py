"""Drive ``dynastereo_node`` live, for the tests and the latency benchmark.

Everything runs on 127.0.0.1 with a private master at a free port (``ROS_MASTER_URI``,
``ROS_IP``/``ROS_HOSTNAME`` and ``ROS_HOME`` set for this process and its children, so
nothing else on the machine is touched); every process started is in its own process
group and is stopped (SIGINT, then SIGKILL) on the way out, also on errors and timeouts.

:class:`LiveSession` (a context manager) starts ``roscore``, the node through its launch
file (``dynastereo node --launch``), and a client node in *this* process that plays a
sequence (:class:`~dynastereo.ros.player.StereoPlayer`) and records what the node
publishes.  ``rospy`` can join only one master per process, so a scenario runs in its own
process: ``python tests/ros_harness.py check|latency ... --json OUT`` (the tests and
``benchmarks/bench_ros_latency.py`` call it that way and read the JSON).  Test code: it
lives in ``tests/``, not in the package.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import time
import xmlrpc.client
from pathlib import Path
from typing import Any

import numpy as np


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def stop_process(p: subprocess.Popen | None, sig: int = signal.SIGINT, timeout: float = 15.0,
                 group: bool = True) -> int | None:
    """Stop ``p`` (its whole process group when ``group``): ``sig``, then SIGKILL."""
    if p is None:
        return None
    if p.poll() is None:
        try:
            if group:
                os.killpg(p.pid, sig)
            else:
                p.send_signal(sig)
        except ProcessLookupError:
            pass
        try:
            p.wait(timeout)
        except subprocess.TimeoutExpired:
            pass
    try:  # leftovers of the group (children of the process), always
        os.killpg(p.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    try:
        return p.wait(5)
    except subprocess.TimeoutExpired:
        return None


def _tail(path: Path, n: int = 3000) -> str:
    try:
        return path.read_text(errors="replace")[-n:]
    except OSError:
        return ""


class LiveSession:
    """roscore + dynastereo_node (roslaunch) + a player/recorder client (module doc)."""

    def __init__(self, workdir: str | Path, launch_args: list[str] | None = None, startup_timeout: float = 60.0,
                 record_images: bool = False) -> None:
        self.work = Path(workdir)
        self.work.mkdir(parents=True, exist_ok=True)
        self.launch_args = list(launch_args or [])
        self.startup_timeout = startup_timeout
        self.record_images = record_images
        self.master: subprocess.Popen | None = None
        self.node: subprocess.Popen | None = None
        self.odometry: list[dict[str, Any]] = []
        self.counts = {"tf": 0, "left_mask": 0, "disparity": 0}
        self.last: dict[str, Any] = {}
        self.ready = False

    # ------------------------------------------------------------------ processes
    def __enter__(self) -> "LiveSession":
        try:
            self._start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _start(self) -> None:
        port = free_port()
        self.uri = f"http://127.0.0.1:{port}/"
        env = {"ROS_MASTER_URI": self.uri, "ROS_IP": "127.0.0.1", "ROS_HOSTNAME": "127.0.0.1",
               "ROS_HOME": str(self.work / "ros_home"), "ROS_LOG_DIR": str(self.work / "ros_home" / "log"),
               "PYTHONUNBUFFERED": "1"}
        os.environ.update(env)
        self.master_log = self.work / "roscore.log"
        self.node_log = self.work / "node.log"
        self.master = subprocess.Popen(["roscore", "-p", str(port)], stdout=open(self.master_log, "w"),
                                       stderr=subprocess.STDOUT, start_new_session=True)
        end = time.monotonic() + self.startup_timeout
        proxy = xmlrpc.client.ServerProxy(self.uri)
        while True:
            if self.master.poll() is not None:
                raise RuntimeError(f"roscore exited ({self.master.returncode}):\n{_tail(self.master_log)}")
            try:
                if proxy.getSystemState("/harness")[0] == 1:
                    break
            except OSError:
                pass
            if time.monotonic() > end:
                raise RuntimeError(f"roscore did not answer within {self.startup_timeout:g} s:\n{_tail(self.master_log)}")
            time.sleep(0.1)
        cmd = [sys.executable, "-m", "dynastereo.cli.main", "node", "--launch", *self.launch_args]
        self.node = subprocess.Popen(cmd, stdout=open(self.node_log, "w"), stderr=subprocess.STDOUT,
                                     start_new_session=True)
        import rospy
        from nav_msgs.msg import Odometry
        from std_msgs.msg import Bool
        from tf2_msgs.msg import TFMessage

        self.rospy = rospy
        rospy.init_node("dynastereo_harness", anonymous=True, disable_signals=True)
        rospy.Subscriber("/dynastereo/odometry", Odometry, self._on_odom, queue_size=1000, tcp_nodelay=True)
        rospy.Subscriber("/tf", TFMessage, self._on_tf, queue_size=1000)
        rospy.Subscriber("/dynastereo/ready", Bool, self._on_ready, queue_size=1)
        if self.record_images:
            from sensor_msgs.msg import Image
            from stereo_msgs.msg import DisparityImage

            rospy.Subscriber("/dynastereo/left/mask", Image, self._on_mask, queue_size=100, buff_size=2 ** 24)
            rospy.Subscriber("/dynastereo/disparity", DisparityImage, self._on_disp, queue_size=100,
                             buff_size=2 ** 26)
        self.wait_for(lambda: self._service_up("/dynastereo/status"), self.startup_timeout, "the node's services")

    def _service_up(self, name: str) -> bool:
        if self.node is not None and self.node.poll() is not None:
            raise RuntimeError(f"the node exited ({self.node.returncode}):\n{_tail(self.node_log)}")
        try:
            self.rospy.wait_for_service(name, timeout=0.2)
            return True
        except self.rospy.ROSException:
            return False

    def wait_for(self, cond, timeout: float, what: str, poll: float = 0.05) -> None:
        end = time.monotonic() + timeout
        while not cond():
            if self.node is not None and self.node.poll() is not None:
                raise RuntimeError(f"the node exited ({self.node.returncode}) waiting for {what}:\n{_tail(self.node_log)}")
            if time.monotonic() > end:
                raise TimeoutError(f"timed out after {timeout:g} s waiting for {what}:\n{_tail(self.node_log)}")
            time.sleep(poll)

    def stop_node(self, timeout: float = 30.0) -> int | None:
        """SIGINT to roslaunch only (it stops the node, which saves and stops its workers)."""
        rc = stop_process(self.node, signal.SIGINT, timeout, group=False)
        self.node = None
        return rc

    def close(self) -> None:
        try:
            import rospy

            if rospy.core.is_initialized():
                rospy.signal_shutdown("harness done")
        except Exception:  # noqa: BLE001
            pass
        stop_process(self.node, signal.SIGINT, 20.0, group=False)
        self.node = None
        stop_process(self.master, signal.SIGINT, 10.0)
        self.master = None

    # ------------------------------------------------------------------ recording
    def _on_odom(self, m: Any) -> None:
        t = time.time()
        p, q = m.pose.pose.position, m.pose.pose.orientation
        self.odometry.append({"stamp_ns": m.header.stamp.to_nsec(), "received": t, "p": [p.x, p.y, p.z],
                              "q": [q.x, q.y, q.z, q.w], "child": m.child_frame_id, "frame": m.header.frame_id})

    def _on_tf(self, m: Any) -> None:
        for tr in m.transforms:
            if tr.header.frame_id == "odom":
                self.counts["tf"] += 1
                self.last["tf_child"] = tr.child_frame_id

    def _on_ready(self, m: Any) -> None:
        self.ready = bool(m.data)

    def _on_mask(self, m: Any) -> None:
        self.counts["left_mask"] += 1
        a = np.frombuffer(m.data, np.uint8)
        self.last["mask"] = {"encoding": m.encoding, "shape": [m.height, m.width],
                             "values": sorted(int(v) for v in np.unique(a)), "masked": int(np.count_nonzero(a))}

    def _on_disp(self, m: Any) -> None:
        self.counts["disparity"] += 1
        d = np.frombuffer(m.image.data, np.float32)
        self.last["disparity"] = {"encoding": m.image.encoding, "shape": [m.image.height, m.image.width],
                                  "valid_fraction": float(np.mean(d > 0)), "f": m.f, "T": m.T,
                                  "min_disparity": m.min_disparity, "max_disparity": m.max_disparity}

    # ------------------------------------------------------------------ node API
    def call(self, service: str) -> tuple[bool, str]:
        from std_srvs.srv import Trigger

        r = self.rospy.ServiceProxy(service, Trigger)()
        return bool(r.success), str(r.message)

    def status(self) -> dict[str, Any]:
        ok, msg = self.call("/dynastereo/status")
        return json.loads(msg)

    def player(self, sequence: Any, frames: list[int]):
        from dynastereo.ros.player import StereoPlayer

        pl = StereoPlayer(sequence, frames)
        self.wait_for(lambda: pl.wait_for_subscribers(0.1), 30.0, "the node's subscriptions")
        return pl

    def start_streaming(self, pl: Any) -> None:
        """CameraInfo first (as a driver does), then wait for the node to be ready."""
        pl.publish_infos()
        self.wait_for(lambda: self.ready, 30.0, "/dynastereo/ready")
        time.sleep(0.2)


# --------------------------------------------------------------------------- scenarios


def _settled(s: LiveSession, quiet_s: float = 1.0):
    """A condition: every pair the node received is processed, dropped or failed, and no
    new message arrived for ``quiet_s`` (the transport may lose some of a burst)."""
    state = {"key": None, "since": time.monotonic()}

    def cond() -> bool:
        st = s.status()
        key = (st["topics"]["left"], st["topics"]["right"], st["received"])
        now = time.monotonic()
        if key != state["key"]:
            state["key"], state["since"] = key, now
        done = st["processed"] + st["dropped"] + st["errors"] >= st["received"]
        return done and now - state["since"] >= quiet_s

    return cond


def _frames(spec: str, n: int) -> list[int]:
    from dynastereo.io.frames import parse_frame_spec

    return parse_frame_spec(spec, n)


def scenario_check(a: argparse.Namespace) -> dict[str, Any]:
    """The CI check: 10 Hz play with a roomy queue (poses must equal the offline run);
    live parameters (a bad value refused and set back, a good one applied); a burst
    with queue_size 1 (drops counted); save service; SIGINT -> final save."""
    from dynastereo.io import open_sequence

    seq = open_sequence(a.sequence)
    first = _frames(a.frames, len(seq))
    burst = _frames(a.burst, len(seq)) if a.burst else []
    out: dict[str, Any] = {"frames": first, "burst_frames": burst}
    save_dir = Path(a.workdir) / "node_out"
    args = [f"queue_size:={a.queue_size}", f"save_dir:={save_dir}", "output:=screen"] + list(a.launch_arg or [])
    with LiveSession(a.workdir, args, record_images=True) as s:
        pl = s.player(seq, first + burst)
        s.start_streaming(pl)
        log = pl.play(a.rate, frames=first)
        out["play_stamps_ns"] = log.stamps_ns
        out["play_late_ms_max"] = max(log.late_ms)
        s.wait_for(lambda: len(s.odometry) >= len(first), a.timeout, f"{len(first)} odometry messages")
        time.sleep(0.3)
        s.wait_for(lambda: s.status()["processed"] >= len(first), 10.0, "processing")
        out["odometry"] = list(s.odometry)
        out["status_play"] = s.status()
        out["counts"] = dict(s.counts)
        out["last"] = dict(s.last)

        # live parameters: a bad one is refused and set back; a good one applied
        rp = s.rospy
        rp.set_param("/dynastereo/stereo/num_disparities", 100)
        s.wait_for(lambda: rp.get_param("/dynastereo/stereo/num_disparities") == 96, 10.0, "the bad value set back")
        rp.set_param("/dynastereo/stereo/block_size", 21)
        s.wait_for(lambda: s.status()["config"]["stereo"]["block_size"] == 21, 10.0, "block_size applied")
        st = s.status()
        out["params"] = {"num_disparities": rp.get_param("/dynastereo/stereo/num_disparities"),
                         "block_size": st["config"]["stereo"]["block_size"],
                         "param_updates": st["param_updates"], "param_rejections": st["param_rejections"]}

        # a burst with a one-frame queue: frames are dropped, counted, never queued up
        if burst:
            rp.set_param("/dynastereo/queue_size", 1)
            s.wait_for(lambda: s.status()["queue_size"] == 1, 10.0, "queue_size 1")
            blog = pl.play(a.burst_rate, frames=burst)
            out["burst_published"] = len(blog.stamps_ns)
            s.wait_for(_settled(s), a.timeout, "the burst processed or dropped", poll=0.25)
            out["status_burst"] = s.status()

        ok, msg = s.call("/dynastereo/save_trajectory")
        out["save"] = {"ok": ok, "message": msg}
        if ok:
            paths = json.loads(msg)
            out["save"]["rows"] = len(Path(paths["kitti"]).read_text().splitlines())
        processed = s.status()["processed"]
        t0 = time.monotonic()
        rc = s.stop_node(30.0)
        out["shutdown"] = {"rc": rc, "seconds": round(time.monotonic() - t0, 2), "processed": processed}
        kitti = save_dir / "trajectory.kitti.txt"
        node_json = save_dir / "node.json"
        if kitti.is_file():
            out["shutdown"]["rows"] = len(kitti.read_text().splitlines())
            out["shutdown"]["final_poses"] = [list(map(float, ln.split())) for ln in kitti.read_text().splitlines()]
        if node_json.is_file():
            out["shutdown"]["node_json"] = json.loads(node_json.read_text())
    out["node_log_tail"] = _tail(Path(a.workdir) / "node.log", 4000)
    return out


def scenario_latency(a: argparse.Namespace) -> dict[str, Any]:
    """Play at ``--rate`` with the node's defaults (queue_size 1); per frame latency =
    odometry receipt time - image stamp (the wall clock at publication)."""
    from dynastereo.io import open_sequence

    seq = open_sequence(a.sequence)
    frames = _frames(a.frames, len(seq))
    args = [f"queue_size:={a.queue_size}", f"save_dir:={Path(a.workdir) / 'node_out'}", "output:=screen"] \
        + list(a.launch_arg or [])
    with LiveSession(a.workdir, args) as s:
        pl = s.player(seq, frames)
        s.start_streaming(pl)
        log = pl.play(a.rate, frames=frames)
        n = len(frames)
        s.wait_for(_settled(s), a.timeout, "all frames processed or dropped", poll=0.25)
        time.sleep(0.3)
        st = s.status()
        lat = [(o["received"] - o["stamp_ns"] * 1e-9) * 1000.0 for o in s.odometry]
        s.stop_node(30.0)
    timing = Path(a.workdir) / "node_out" / "timing.json"
    stages = json.loads(timing.read_text())["summary"] if timing.is_file() else {}
    return {"frames": n, "rate_hz": a.rate, "published": len(log.stamps_ns), "odometry": len(s.odometry),
            "latency_ms": lat, "late_ms_max": max(log.late_ms), "status": st, "stages": stages}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python tests/ros_harness.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("scenario", choices=("check", "latency"))
    ap.add_argument("--sequence", required=True)
    ap.add_argument("--frames", default="25")
    ap.add_argument("--burst", default="")
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--burst-rate", type=float, default=200.0)
    ap.add_argument("--queue-size", type=int, default=1)
    ap.add_argument("--timeout", type=float, default=60.0)
    ap.add_argument("--workdir", required=True)
    ap.add_argument("--launch-arg", action="append", help="extra roslaunch arg:=value (repeatable)")
    ap.add_argument("--json", required=True, help="where to write the result")
    a = ap.parse_args(argv)
    fn = scenario_check if a.scenario == "check" else scenario_latency
    try:
        res = fn(a)
        res["ok"] = True
    except Exception as e:  # noqa: BLE001 - reported in the JSON for the caller
        import traceback

        res = {"ok": False, "error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc(),
               "node_log_tail": _tail(Path(a.workdir) / "node.log", 4000)}
    Path(a.json).write_text(json.dumps(res, default=float))
    return 0 if res["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
