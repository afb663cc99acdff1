"""Live ROS 1 node latency: image stamp -> odometry, at 10 Hz on KITTI frames.

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
     [--repeats 2] [--frames 51] [--rate 10] [--modes serial,pipelined]
Writes benchmarks/results/ros_latency.json.  Needs ROS 1 (Debian packages, see .ci/run).
"""

from __future__ import annotations

import argparse
import json
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


def run_once(seq: Path, frames: int, rate: float, pipelined: bool, timeout: float) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench_ros_") as work:
        out = Path(work) / "res.json"
        cmd = [sys.executable, str(HARNESS), "latency", "--sequence", str(seq),
               "--frames", str(frames), "--rate", str(rate), "--queue-size", "1", "--workdir", work,
               "--json", str(out), "--launch-arg", f"pipelined:={'true' if pipelined else 'false'}",
               "--timeout", str(timeout)]
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout + 120, start_new_session=True)
        if not out.is_file():
            raise SystemExit(f"harness failed ({p.returncode}):\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}")
        res = json.loads(out.read_text())
        if not res.get("ok"):
            raise SystemExit(f"harness failed: {res.get('error')}\n{res.get('traceback')}\n{res.get('node_log_tail')}")
        return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--frames", type=int, default=51)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--modes", default="serial,pipelined")
    ap.add_argument("--timeout", type=float, default=120.0)
    ap.add_argument("--out", type=Path, default=results_path("ros_latency"))
    args = ap.parse_args()
    data, _ = data_dir(), models_dir()
    try:
        import rospy  # noqa: F401
    except ImportError as e:
        raise SystemExit(f"ROS 1 not importable ({e}); install the Debian packages as .ci/run does")
    seq = data / "kitti_odometry/dataset/sequences/06"
    rows = []
    for mode in [m.strip() for m in args.modes.split(",") if m.strip()]:
        lat: list[float] = []
        settled: list[float] = []  # without each run's first SETTLE frames (the start-up transient)
        runs = []
        for r in range(args.repeats):
            res = run_once(seq, args.frames, args.rate, mode == "pipelined", args.timeout)
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
            print(f"  {mode} run {r + 1}: median {runs[-1]['median_ms']:.1f} ms, p95 {runs[-1]['p95_ms']:.1f} ms, "
                  f"dropped {st['dropped']}, transport lost {runs[-1]['transport_lost']}, "
                  f"load {runs[-1]['loadavg']:.1f}", flush=True)
        a = np.asarray(lat)
        b = np.asarray(settled) if settled else a
        rows.append({
            "mode": mode, "rate_hz": args.rate, "frames_per_run": args.frames, "repeats": args.repeats,
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
    print(f"\nROS 1 node latency, image stamp -> odometry receipt, KITTI 06 1226x370 at {args.rate:g} Hz, "
          f"queue_size 1 (target: median <= {TARGET_MEDIAN_MS:g} ms, no drops)")
    print(f"{'mode':10s} {'median':>8s} {'p95':>8s} {'max':>8s} {'dropped':>8s} {'lost(tr)':>8s} {'frames':>7s}  pass"
          f"  | after start-up (frames {SETTLE}+ of each run): median / p95 / max")
    for r in rows:
        print(f"{r['mode']:10s} {r['latency_median_ms']:8.1f} {r['latency_p95_ms']:8.1f} {r['latency_max_ms']:8.1f} "
              f"{r['dropped']:8d} {r['transport_lost']:8d} {r['frames_total']:7d}  {r['pass']}"
              f"  | {r['after_start_median_ms']:.1f} / {r['after_start_p95_ms']:.1f} / {r['after_start_max_ms']:.1f}")
    for r in rows:
        st = r["runs"][0]["stages_median_ms"]
        keep = ("detect", "disparity", "outline", "transfer", "features", "stereo", "track", "local_mapping", "total")
        print(f"  {r['mode']} node stages (median ms, run 1): " + ", ".join(f"{k} {st[k]:.1f}" for k in keep if k in st))
    write_json(args.out, {
        "benchmark": "ros_latency",
        "machine": machine(),
        "target": {"median_ms": TARGET_MEDIAN_MS, "p95_ms": TARGET_P95_MS, "drops": 0},
        "sequence": "KITTI 06 (gray 1226x370)",
        "config": "default (outline masker, yolox-nano, StereoBM, 2000 ORB features); queue_size 1",
        "results": rows,
    })
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
