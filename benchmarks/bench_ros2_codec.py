"""ROS 2 image messages on the wire: encode and decode times, and a loopback round trip.

Codec (this process): one KITTI 06 left image (1226x370 mono8, a 453,644-byte
``sensor_msgs/Image`` sample) encoded by the project's numpy XCDR1 encoder
(``dynastereo.ros.dds.encode``), by cyclonedds' generic serializer (the same IdlStruct, the
pixels as a list) and by rosbags' ROS 2 serializer; decoded by the project's numpy decoder
(``decode_image``: a view of the sample) and by cyclonedds' generic decoder.

Round trip (two processes, loopback, an explicit Cyclone DDS configuration without
multicast): this process publishes a left + right Image pair (reliable); an echo process
takes both, decodes them with ``decode_image`` and answers with a ``nav_msgs/Odometry``
stamped like the pair; the time from publishing the pair to receiving the answer is the
transport's share of the node's latency (no masking, no tracking).

Run: DYNASTEREO_DATA=... .venv/bin/python benchmarks/bench_ros2_codec.py [--repeats 200] [--pairs 100]
Writes benchmarks/results/ros2_codec.json.  The machine is shared: medians.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import CLIPS, data_path, load, machine, median_ms, results_path, write_json

CDDS_XML = """<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>
<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>
<MaxAutoParticipantIndex>40</MaxAutoParticipantIndex><Peers><Peer address="127.0.0.1"/></Peers></Discovery>
</Domain></CycloneDDS>"""


def _median_ms(fn, n: int) -> float:
    return median_ms(fn, n)


def codec(img: np.ndarray, repeats: int) -> dict:
    from dynastereo.ros import dds
    from dynastereo.ros.messages import RosbagsBuilder

    rb, db = RosbagsBuilder(ros1=False), dds.DdsBuilder()
    ours = db.image(img, 1_700_000_000_000_000_000, "camera_left")
    generic = db.image(img, 1_700_000_000_000_000_000, "camera_left")
    generic.data = img.reshape(-1).tolist()
    theirs = rb.image(img, 1_700_000_000_000_000_000, "camera_left")
    sample = dds.encode(ours)
    assert generic.serialize(use_version_2=False) == sample[:len(generic.serialize(use_version_2=False))]
    cls = dds.idl_type("sensor_msgs/Image")
    slow = max(3, repeats // 20)  # the generic paths are slow: fewer repeats
    return {
        "sample_bytes": len(sample),
        "encode_ms": {"numpy (dds.encode)": _median_ms(lambda: dds.encode(ours), repeats),
                      "cyclonedds generic": _median_ms(lambda: generic.serialize(use_version_2=False), slow),
                      "rosbags serialize_cdr": _median_ms(lambda: rb.typestore.serialize_cdr(theirs, theirs.__msgtype__),
                                                          repeats)},
        "decode_ms": {"numpy (dds.decode_image)": _median_ms(lambda: dds.decode_image(sample), repeats),
                      "cyclonedds generic": _median_ms(lambda: cls.deserialize(sample), slow)},
    }


ECHO = r"""
import sys, time
from dynastereo.ros import dds
dom = dds.Domain(int(sys.argv[1]), node_name="echo")
b = dds.DdsBuilder()
rl = dom.reader("/camera/left/image_raw", "sensor_msgs/Image", dds.QosKind.RECORD)
rr = dom.reader("/camera/right/image_raw", "sensor_msgs/Image", dds.QosKind.RECORD)
out = dom.writer("/echo/odometry", "nav_msgs/Odometry", dds.QosKind.RELIABLE)
w = dds.Waiter(dom.participant, [rl, rr])
from dynastereo.ros.messages import OdometryData
import numpy as np
half = {}
end = time.monotonic() + float(sys.argv[2])
while time.monotonic() < end:
    w.wait(0.1)
    for side, r in (("l", rl), ("r", rr)):
        for data, _ in r.take(16):
            m = dds.decode_image(data)
            half.setdefault(m.stamp_ns, set()).add(side)
            if len(half[m.stamp_ns]) == 2:
                del half[m.stamp_ns]
                out.publish(b.odometry(OdometryData(m.stamp_ns, np.eye(4))))
"""


def round_trip(left: np.ndarray, right: np.ndarray, pairs: int) -> dict:
    from dynastereo.ros import dds

    with tempfile.TemporaryDirectory(prefix="bench_ros2_rt_") as work:
        (Path(work) / "cdds.xml").write_text(CDDS_XML)
        os.environ["CYCLONEDDS_URI"] = (Path(work) / "cdds.xml").as_uri()
        domain = 100 + os.getpid() % 120
        echo = subprocess.Popen([sys.executable, "-c", ECHO, str(domain), str(60 + pairs)], env=dict(os.environ))
        try:
            dom = dds.Domain(domain, node_name="bench")
            b = dds.DdsBuilder()
            pl = dom.writer("/camera/left/image_raw", "sensor_msgs/Image", dds.QosKind.RELIABLE)
            pr = dom.writer("/camera/right/image_raw", "sensor_msgs/Image", dds.QosKind.RELIABLE)
            back = dom.reader("/echo/odometry", "nav_msgs/Odometry", dds.QosKind.RECORD)
            w = dds.Waiter(dom.participant, [back])
            end = time.monotonic() + 60
            while (pl.matched() == 0 or pr.matched() == 0 or not back.reader.get_matched_publications()) \
                    and time.monotonic() < end:
                time.sleep(0.05)
            rts = []
            for k in range(pairs):
                stamp = 1_000_000_000 + k
                t = time.perf_counter()
                pl.publish(b.image(left, stamp, "camera_left"))
                pr.publish(b.image(right, stamp, "camera_right"))
                got = False
                while not got and time.perf_counter() - t < 5.0:
                    w.wait(1.0)
                    got = bool(back.take(8))
                rts.append((time.perf_counter() - t) * 1000.0 if got else float("nan"))
                time.sleep(0.02)
        finally:
            echo.kill()
            echo.wait(10)
    a = np.asarray(rts)
    ok = a[np.isfinite(a)]
    return {"pairs": pairs, "answered": int(ok.size), "median_ms": float(np.median(ok)),
            "p95_ms": float(np.percentile(ok, 95)), "max_ms": float(ok.max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--pairs", type=int, default=100)
    ap.add_argument("--out", type=Path, default=results_path("ros2_codec"))
    args = ap.parse_args()
    seq = data_path(CLIPS["06"])
    from dynastereo.io import KittiSequence

    f = KittiSequence(seq).frame(0)
    c = codec(f.left, args.repeats)
    rt = round_trip(f.left, f.right, args.pairs)
    print(f"KITTI 06 left image as sensor_msgs/Image: {c['sample_bytes']} bytes (medians, ms)")
    for k, v in c["encode_ms"].items():
        print(f"  encode  {k:28s} {v:9.3f}")
    for k, v in c["decode_ms"].items():
        print(f"  decode  {k:28s} {v:9.3f}")
    print(f"round trip, image pair -> echo process -> Odometry, loopback: median {rt['median_ms']:.2f} ms, "
          f"p95 {rt['p95_ms']:.2f} ms, max {rt['max_ms']:.2f} ms ({rt['answered']}/{rt['pairs']} answered); "
          f"load {load():.1f}")
    write_json(args.out, {
        "benchmark": "ros2_codec",
        "machine": machine(),
        "image": "KITTI 06 frame 0, 1226x370 mono8", "codec": c, "round_trip": rt,
    })
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
