"""Live ROS node latency (ROS 1 and ROS 2): image stamp -> odometry, at 10 Hz on KITTI frames.

``--transports ros1,ros2`` (default both, side by side in one run).  ROS 2: the node is
``dynastereo node --ros2`` (DDS, its own process, reliable input, the same parameters), the
player (:class:`~dynastereo.ros.ros2_player.Ros2Player`) and the odometry subscriber run in
this process, on loopback with an explicit Cyclone DDS configuration (no multicast) and a
domain id of this run.  ROS 1 as follows.

For each mode (``serial``: one processing thread, the default; ``pipelined``: masking of
frame k+1 overlaps tracking of frame k) and each repeat, a fresh private rosmaster
and ``dynastereo_node`` (launch file, default configuration: outline masker, yolox-nano,
StereoBM, **queue_size 1**) are started (``tests/ros_harness.py latency``, its own
process), KITTI 06 (51 frames, 1226x370, gray) is published at 10 Hz as
``sensor_msgs/Image`` + ``CameraInfo`` stamped with the wall clock at publication, and a
subscriber records when each ``nav_msgs/Odometry`` arrives.

Per frame: latency = odometry receipt time - image stamp (includes both transports,
masking, tracking).  Reported: median / p95 / max over all frames of all repeats, frames
dropped by the node's one-frame queue, frames lost by the transport (published - received),
and the node's per-stage medians (from its timing.json).  Targets: median <= 100 ms and no
drops at 10 Hz.  The machine is shared (2 cores): medians over repeats; the load average
is recorded.

Run: DYNASTEREO_DATA=... DYNASTEREO_MODELS=... .venv/bin/python benchmarks/bench_ros_latency.py
     [--repeats 2] [--frames 51] [--rate 10] [--modes serial,pipelined] [--transports ros1,ros2]
     [--config FILE.yaml]
Writes benchmarks/results/ros_latency.json.  Needs ROS 1 (Debian packages, see .ci/run).
``--config`` gives both nodes a configuration: the latency without the network on the
critical path, for instance (``detector: {interval: 1000}``: one network run, then nothing
detected), ``--transports ros2 --modes pipelined --config ... --out
benchmarks/results/ros_latency_no_network.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from _common import ROOT, data_dir, load, machine, models_dir, results_path, write_json

TARGET_MEDIAN_MS = 100.0
TARGET_P95_MS = 100.0  # target: image stamp -> odometry p95, no drops
SETTLE = 5  # odometry messages left out of the "after start-up" figures: the first CameraInfo builds the SLAM
HARNESS = ROOT / "tests" / "ros_harness.py"  # test code, not in the package


def run_once(seq: Path, frames: int, rate: float, pipelined: bool, timeout: float, config: Path | None = None) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench_ros_") as work:
        out = Path(work) / "res.json"
        cmd = [sys.executable, str(HARNESS), "latency", "--sequence", str(seq),
               "--frames", str(frames), "--rate", str(rate), "--queue-size", "1", "--workdir", work,
               "--json", str(out), "--launch-arg", f"pipelined:={'true' if pipelined else 'false'}",
               "--timeout", str(timeout)]
        if config is not None:
            cmd += ["--launch-arg", f"config:={config}"]
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout + 120, start_new_session=True)
        if not out.is_file():
            raise SystemExit(f"harness failed ({p.returncode}):\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}")
        res = json.loads(out.read_text())
        if not res.get("ok"):
            raise SystemExit(f"harness failed: {res.get('error')}\n{res.get('traceback')}\n{res.get('node_log_tail')}")
        return res


CDDS_XML = """<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>
<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>
<MaxAutoParticipantIndex>40</MaxAutoParticipantIndex><Peers><Peer address="127.0.0.1"/></Peers></Discovery>
</Domain></CycloneDDS>"""


def run_once_ros2(seq: Path, frames: int, rate: float, pipelined: bool, timeout: float,
                  config: Path | None = None) -> dict:
    """The ROS 2 node in its own process, the player and the odometry recorder here."""
    import signal
    import time

    from dynastereo.io import KittiSequence
    from dynastereo.ros.dds import Domain
    from dynastereo.ros.ros2 import TriggerClient
    from dynastereo.ros.ros2_player import Ros2Player

    with tempfile.TemporaryDirectory(prefix="bench_ros2_") as work:
        w = Path(work)
        (w / "cdds.xml").write_text(CDDS_XML)
        os.environ["CYCLONEDDS_URI"] = (w / "cdds.xml").as_uri()
        domain = 100 + os.getpid() % 120
        (w / "params.yaml").write_text("/**:\n  ros__parameters:\n    queue_size: 1\n    input_reliability: reliable\n"
                                       f"    pipelined: {'true' if pipelined else 'false'}\n    save_dir: {w / 'save'}\n"
                                       + (f"    config: {config}\n" if config is not None else ""))
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
        log = (w / "node.log").open("wb")
        node = subprocess.Popen([sys.executable, "-m", "dynastereo.cli.main", "node", "--ros2", "--params",
                                 str(w / "params.yaml")], env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            dom = Domain(domain, node_name="bench_player")
            player = Ros2Player(KittiSequence(seq), list(range(frames)), domain=dom)
            if not player.wait_for_subscribers(timeout):
                raise SystemExit("the ROS 2 node did not subscribe:\n" + (w / "node.log").read_text()[-3000:])
            player.publish_infos(time.time_ns())  # a driver's first message: the node sets up
            time.sleep(3.0)
            plog = player.play(rate, stamp="now")
            status = TriggerClient(dom, "/dynastereo/status")
            end = time.monotonic() + timeout
            while time.monotonic() < end:
                st = json.loads(status.call(30)[1])
                if st["processed"] + st["dropped"] + st["errors"] >= st["received"]:
                    break
                time.sleep(0.2)
            player.drain(st["processed"], 5.0)
            stamps = {s: k for k, s in enumerate(plog.stamps_ns)}
            lat = [(t - s * 1e-9) * 1000.0 for (s, _), t in zip(player.odometry, player.odometry_received)
                   if s in stamps]
            player.close()
            del dom, player
        finally:
            node.send_signal(signal.SIGINT)
            try:
                node.wait(60)
            except subprocess.TimeoutExpired:
                node.kill()
        timing = {}
        tj = w / "save" / "timing.json"
        if tj.is_file():
            timing = json.loads(tj.read_text()).get("summary", {})
        return {"published": len(plog.frames), "status": st, "latency_ms": lat, "late_ms_max": plog.summary()["late_ms_max"],
                "stages": timing}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--frames", type=int, default=51)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--modes", default="serial,pipelined")
    ap.add_argument("--timeout", type=float, default=120.0)
    ap.add_argument("--transports", default="ros1,ros2")
    ap.add_argument("--config", type=Path, default=None,
                    help="a dynastereo YAML configuration for both nodes (default: the defaults)")
    ap.add_argument("--out", type=Path, default=results_path("ros_latency"))
    args = ap.parse_args()
    data, _ = data_dir(), models_dir()
    transports = [t.strip() for t in args.transports.split(",") if t.strip()]
    if "ros1" in transports:
        try:
            import rospy  # noqa: F401
        except ImportError as e:
            raise SystemExit(f"ROS 1 not importable ({e}); install the Debian packages as .ci/run does")
    seq = data / "kitti_odometry/dataset/sequences/06"
    rows = []
    for transport, mode in [(t, m.strip()) for m in args.modes.split(",") if m.strip() for t in transports]:
        lat: list[float] = []
        settled: list[float] = []  # without each run's first SETTLE frames (the start-up transient)
        runs = []
        for r in range(args.repeats):
            once = run_once_ros2 if transport == "ros2" else run_once
            res = once(seq, args.frames, args.rate, mode == "pipelined", args.timeout, args.config)
            st = res["status"]
            runs.append({
                "published": res["published"], "received": st["received"], "processed": st["processed"],
                "dropped": st["dropped"], "transport_lost": res["published"] - st["received"],
                "errors": st["errors"], "lost_tracking": st["lost"],
                "median_ms": round(float(np.median(res["latency_ms"])), 1),
                "p95_ms": round(float(np.percentile(res["latency_ms"], 95)), 1),
                "node_stamp_to_publish_ms": st["latency_stamp_ms"], "player_late_ms_max": round(res["late_ms_max"], 1),
                "stages_median_ms": {k: v["median"] for k, v in res.get("stages", {}).items()
                                     if isinstance(v, dict) and "median" in v},
                "loadavg": load(),
            })
            lat += res["latency_ms"]
            settled += res["latency_ms"][SETTLE:]
            print(f"  {transport} {mode} run {r + 1}: median {runs[-1]['median_ms']:.1f} ms, p95 {runs[-1]['p95_ms']:.1f} ms, "
                  f"dropped {st['dropped']}, transport lost {runs[-1]['transport_lost']}, "
                  f"load {runs[-1]['loadavg']:.1f}", flush=True)
        a = np.asarray(lat)
        b = np.asarray(settled) if settled else a
        rows.append({
            "transport": transport, "mode": mode, "rate_hz": args.rate, "frames_per_run": args.frames, "repeats": args.repeats,
            "latency_median_ms": round(float(np.median(a)), 1), "latency_p95_ms": round(float(np.percentile(a, 95)), 1),
            "latency_max_ms": round(float(a.max()), 1),
            "after_start_median_ms": round(float(np.median(b)), 1),
            "after_start_p95_ms": round(float(np.percentile(b, 95)), 1),
            "after_start_max_ms": round(float(b.max()), 1),
            "dropped": int(sum(r["dropped"] for r in runs)), "transport_lost": int(sum(r["transport_lost"] for r in runs)),
            "frames_total": int(sum(r["published"] for r in runs)),
            "median_of_run_medians_ms": float(np.median([r["median_ms"] for r in runs])),
            "pass": bool(np.median(a) <= TARGET_MEDIAN_MS and sum(r["dropped"] for r in runs) == 0),
            "pass_p95": bool(np.percentile(a, 95) <= TARGET_P95_MS and sum(r["dropped"] for r in runs) == 0),
            "runs": runs,
        })
    print(f"\nROS node latency (ROS 1: rospy/TCPROS; ROS 2: DDS, reliable), image stamp -> odometry receipt, KITTI 06 1226x370 at {args.rate:g} Hz, "
          f"queue_size 1 (target: median <= {TARGET_MEDIAN_MS:g} ms, no drops)")
    print(f"{'transport':9s} {'mode':10s} {'median':>8s} {'p95':>8s} {'max':>8s} {'dropped':>8s} {'lost(tr)':>8s} {'frames':>7s}  pass"
          f"  | after start-up (frames {SETTLE}+ of each run): median / p95 / max")
    for r in rows:
        print(f"{r['transport']:9s} {r['mode']:10s} {r['latency_median_ms']:8.1f} {r['latency_p95_ms']:8.1f} {r['latency_max_ms']:8.1f} "
              f"{r['dropped']:8d} {r['transport_lost']:8d} {r['frames_total']:7d}  {r['pass']}"
              f"  | {r['after_start_median_ms']:.1f} / {r['after_start_p95_ms']:.1f} / {r['after_start_max_ms']:.1f}")
    for r in rows:
        st = r["runs"][0]["stages_median_ms"]
        keep = ("detect", "disparity", "outline", "transfer", "features", "stereo", "track", "local_mapping", "total")
        print(f"  {r['transport']} {r['mode']} node stages (median ms, run 1): " + ", ".join(f"{k} {st[k]:.1f}" for k in keep if k in st))
    write_json(args.out, {
        "benchmark": "ros_latency",
        "machine": machine(),
        "target": {"median_ms": TARGET_MEDIAN_MS, "p95_ms": TARGET_P95_MS, "drops": 0},
        "sequence": "KITTI 06 (gray 1226x370)",
        "config": (str(args.config) if args.config else "default (outline masker, yolox-nano, StereoBM, 2000 ORB "
                   "features)") + "; queue_size 1",
        "results": rows,
    })
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
