"""The ROS 2 node over DDS (``dynastereo node --ros2``) and its wire format.

Codec: the hand-written XCDR1 encoders of the image-carrying messages and cyclonedds' own
serializer (the other messages) against rosbags' ROS 2 Humble serializer, byte for byte;
the numpy decoders on rosbags' bytes.  Live: the node and a player in separate processes on
loopback (an explicit Cyclone DDS configuration, no multicast, a domain id of this run); what
the node publishes is decoded with rosbags' typestore (written independently of both)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cyclonedds", reason="the ros2 extra (cyclonedds) is not installed")


from dynastereo.errors import ConfigError, InputError  # noqa: E402
from dynastereo.ros import dds  # noqa: E402
from dynastereo.ros.messages import OdometryData, RosbagsBuilder  # noqa: E402
from dynastereo.ros.ros2 import StampPairer, _Half, load_params  # noqa: E402

RB = RosbagsBuilder(ros1=False)
TS = RB.typestore
DB = dds.DdsBuilder()


def _rosbags_bytes(msg) -> bytes:
    return bytes(TS.serialize_cdr(msg, msg.__msgtype__))


def _same(ours: bytes, theirs: bytes) -> None:
    """Ours is rosbags' sample padded with zeros to a multiple of 4 (as cyclonedds sends it)."""
    assert ours[:len(theirs)] == theirs
    assert len(ours) == (len(theirs) + 3) & ~3 and not any(ours[len(theirs):])


# --------------------------------------------------------------------------- codec


def test_image_codec_matches_rosbags_byte_for_byte() -> None:
    rng = np.random.default_rng(0)
    for k in range(60):
        h, w = int(rng.integers(1, 40)), int(rng.integers(1, 50))
        kind = k % 4
        img = (rng.integers(0, 255, (h, w), np.uint8) if kind == 0 else
               rng.integers(0, 255, (h, w, 3), np.uint8) if kind == 1 else
               rng.integers(0, 65535, (h, w), np.uint16) if kind == 2 else rng.random((h, w), np.float32))
        stamp = int(rng.integers(0, 2 ** 31 * 10 ** 9))  # int32 seconds
        fid = "cam" * int(rng.integers(0, 4))  # frame ids of every length mod 4 (alignment)
        ours = dds.encode(DB.image(img, stamp, fid))
        _same(ours, _rosbags_bytes(RB.image(img, stamp, fid)))
        back = dds.decode_image(ours)
        assert (back.stamp_ns, back.frame_id, back.height, back.width) == (stamp, fid, h, w)
        assert back.data.tobytes() == np.ascontiguousarray(img).tobytes()
        # and rosbags' own bytes decode the same
        theirs = dds.decode_image(_rosbags_bytes(RB.image(img, stamp, fid)))
        assert theirs.encoding == back.encoding and np.array_equal(theirs.data, back.data)


def test_compressed_cloud_and_disparity_match_rosbags() -> None:
    from dynastereo.ros.messages import DisparityData

    rng = np.random.default_rng(1)
    for k in range(20):
        img = rng.integers(0, 255, (int(rng.integers(2, 30)), int(rng.integers(2, 30))), np.uint8)
        fid = "x" * k
        _same(dds.encode(DB.compressed(img, 7 + k, fid)), _rosbags_bytes(RB.compressed(img, 7 + k, fid)))
        msg = DB.compressed(img, 7 + k, fid)
        c = dds.decode_compressed(dds.encode(msg))
        assert (c.stamp_ns, c.frame_id, c.format) == (7 + k, fid, msg.format) and np.array_equal(c.data, msg.data)
        from dynastereo.ros.convert import ImageDecoder

        assert np.array_equal(ImageDecoder().decode(c, "t"), img)  # what the node does with compressed: true
        pts = rng.normal(size=(int(rng.integers(0, 50)), 3))
        _same(dds.encode(DB.point_cloud(pts, 11, fid)), _rosbags_bytes(RB.point_cloud(pts, 11, fid)))
        d = DisparityData(rng.random((5, 7), np.float32) * 50 - 5, 707.0, 0.54, 0.0, 96.0)
        _same(dds.encode(DB.disparity(d, 13, fid)), _rosbags_bytes(RB.disparity(d, 13, fid)))


def test_generic_messages_match_rosbags() -> None:
    """The small messages go through cyclonedds' serializer: the same bytes as rosbags'."""
    from dynastereo.ros.convert import camera_info_fields
    from dynastereo.datatypes import StereoCalibration

    T = np.eye(4)
    T[:3, 3] = (1.5, -2.0, 30.25)
    o = OdometryData(1_700_000_000_123_456_789, T, linear=np.array([1.0, 2.0, 3.0]), child_frame_id="camera_left")
    for build in (lambda b: b.odometry(o), lambda b: b.tf(o), lambda b: b.path([T, T], [5, 6], "odom"),
                  lambda b: b.object_markers([], 5, "odom"), lambda b: b.make("std_msgs/Bool", data=True)):
        _same(dds.encode(build(DB)), _rosbags_bytes(build(RB)))
    calib = StereoCalibration(np.array([[707.0912, 0, 601.8873], [0, 707.0912, 183.1104], [0, 0, 1]]), 0.5372,
                              1226, 370)
    info = camera_info_fields(calib, "right")
    _same(dds.encode(DB.camera_info(info, 9, "camera_right")), _rosbags_bytes(RB.camera_info(info, 9, "camera_right")))
    assert dds.dds_type_name("sensor_msgs/Image") == "sensor_msgs::msg::dds_::Image_"
    assert dds.topic_name("/camera/left/image_raw") == "rt/camera/left/image_raw"
    assert dds.service_topics("/dynastereo/status") == ("rq/dynastereo/statusRequest", "rr/dynastereo/statusReply")


def test_decoder_refuses_a_truncated_or_foreign_sample() -> None:
    img = np.zeros((4, 4), np.uint8)
    b = dds.encode(DB.image(img, 1, "c"))
    with pytest.raises(InputError, match="truncated"):
        dds.decode_image(b[:-8])
    with pytest.raises(InputError, match="XCDR1"):
        dds.decode_image(b"\x07\x07" + b[2:])


# --------------------------------------------------------------------------- parameters, pairing


def test_params_file_both_forms_and_errors(tmp_path: Path) -> None:
    f = tmp_path / "p.yaml"
    f.write_text("/**:\n  ros__parameters:\n    queue_size: 3\n    stereo:\n      block_size: 21\n"
                 "dynastereo:\n  ros__parameters:\n    left_topic: /l\n    stereo.num_disparities: 64\n")
    p = load_params(f)
    assert p["queue_size"] == 3 and p["left_topic"] == "/l" and p["sync_slop"] == 0.01  # the ROS 1 default
    assert p["_sections"] == {"stereo.block_size": 21, "stereo.num_disparities": 64}
    from dynastereo.ros.ros2 import config_from_params

    cfg = config_from_params(p)
    assert cfg.stereo.block_size == 21 and cfg.stereo.num_disparities == 64
    f.write_text("/**:\n  ros__parameters:\n    queue_sise: 3\n")
    with pytest.raises(ConfigError, match=r"p\.yaml: unknown parameter 'queue_sise'"):
        load_params(f)
    f.write_text("other_node:\n  ros__parameters: {}\n")
    with pytest.raises(ConfigError, match="no '/\\*\\*' or 'dynastereo' entry"):
        load_params(f)


def test_stamp_pairer() -> None:
    pr = StampPairer(0.01, 3)
    h = lambda s: _Half(s, np.zeros(1), "", 0.0)  # noqa: E731
    assert pr.add("left", h(100)) is None
    assert pr.add("left", h(200_000_000)) is None
    l, r = pr.add("right", h(200_000_000 + 5_000_000))  # within the slop
    assert (l.stamp_ns, r.stamp_ns) == (200_000_000, 205_000_000)
    assert pr.unpaired == {"left": 1, "right": 0}  # 100 ns is older than the pair: never paired
    assert pr.add("right", h(900_000_000)) is None and pr.add("left", h(950_000_000)) is None  # 50 ms apart


# --------------------------------------------------------------------------- live

LOCKSTEP = 8  # frames played in lock-step (odometry compared with the offline run)
RATE_FRAMES = 16  # then played at 10 Hz (drops counted)

CDDS_XML = """<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>
<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>
<MaxAutoParticipantIndex>40</MaxAutoParticipantIndex><Peers><Peer address="127.0.0.1"/></Peers></Discovery>
</Domain></CycloneDDS>"""


def _stop(p: subprocess.Popen) -> int | None:
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
        try:
            return p.wait(60)
        except subprocess.TimeoutExpired:
            p.kill()
    return p.wait(10)


def offline_run_poses(kitti06: Path, models_dir: Path, out: Path) -> np.ndarray:
    """The per-frame poses (what tracking returned, as the node's odometry) of the offline
    ``dynastereo run`` job on frames 0..LOCKSTEP-1: the same runtime, read from the folder."""
    from dynastereo.config import Config
    from dynastereo.runtime import JobKind, JobSpec, OutputSpec, SourceSpec, run

    poses: list[np.ndarray] = []

    class Poses:
        def on_frame(self, ev) -> None:
            poses.append(np.asarray(ev.pose, np.float64))

    run(JobSpec(JobKind.RUN, SourceSpec(path=kitti06), OutputSpec(out), Config(), frames=f"0-{LOCKSTEP - 1}",
                models_dir=models_dir), observers=(Poses(),))
    return np.array(poses)


@pytest.fixture(scope="module")
def live(kitti06: Path, models_dir: Path, tmp_path_factory) -> dict:
    """The node (its own process) and, here, a player and a recorder: bad inputs, lock-step,
    10 Hz, the services, SIGINT."""
    work = tmp_path_factory.mktemp("ros2")
    (work / "cdds.xml").write_text(CDDS_XML)
    domain = 100 + os.getpid() % 120  # this run's own domain: no cross-talk with others
    os.environ["CYCLONEDDS_URI"] = (work / "cdds.xml").as_uri()
    (work / "params.yaml").write_text(
        "/**:\n  ros__parameters:\n    input_reliability: reliable\n"
        f"    save_dir: {work / 'save'}\n    queue_size: 1\n    pipelined: false\n    mesh: true\n")
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), DYNASTEREO_MODELS=str(models_dir),
               PYTHONPATH=os.pathsep.join([str(Path(dds.__file__).parents[2]), os.environ.get("PYTHONPATH", "")]))
    log_path = work / "node.log"
    node = subprocess.Popen([sys.executable, "-m", "dynastereo.cli.main", "node", "--ros2", "--params",
                             str(work / "params.yaml")], env=env, stdout=log_path.open("wb"),
                            stderr=subprocess.STDOUT)
    res: dict = {"work": work}
    try:
        from dynastereo.io import KittiSequence
        from dynastereo.ros.ros2 import TriggerClient
        from dynastereo.ros.ros2_player import Ros2Player

        dom = dds.Domain(domain, node_name="test_player")
        seq = KittiSequence(kitti06)
        player = Ros2Player(seq, list(range(LOCKSTEP + RATE_FRAMES)), domain=dom)
        rec = {k: dom.reader(t, ty, dds.QosKind.RECORD if k != "mask" else dds.QosKind.SENSOR) for k, t, ty in (
            ("tf", "/tf", "tf2_msgs/TFMessage"), ("mask", "/dynastereo/left/mask", "sensor_msgs/Image"),
            ("path", "/dynastereo/path", "nav_msgs/Path"), ("objects", "/dynastereo/objects",
                                                           "visualization_msgs/MarkerArray"),
            ("odometry", "/dynastereo/odometry", "nav_msgs/Odometry"))}
        rec["disparity"] = dom.reader("/dynastereo/disparity", "stereo_msgs/DisparityImage", dds.QosKind.SENSOR)
        rec["map"] = dom.reader("/dynastereo/map_points", "sensor_msgs/PointCloud2", dds.QosKind.LATCHED)
        rec["ready"] = dom.reader("/dynastereo/ready", "std_msgs/Bool", dds.QosKind.LATCHED)
        rec["mesh"] = dom.reader("/dynastereo/mesh", "visualization_msgs/Marker", dds.QosKind.LATCHED)
        rec["dense"] = dom.reader("/dynastereo/dense_cloud", "sensor_msgs/PointCloud2", dds.QosKind.LATCHED)
        disc_t = dds.discovery_types(24)[2]
        disc = dom.reader("", disc_t, dds.QosKind.LATCHED, dds_name="ros_discovery_info")
        assert player.wait_for_subscribers(90), "the node did not subscribe within 90 s:\n" + log_path.read_text()
        end = time.monotonic() + 30
        while not (player.pub_li.matched() and player.pub_ri.matched()) and time.monotonic() < end:
            time.sleep(0.05)  # the CameraInfo subscriptions too (the player waits for the images' only)
        # bad inputs first: a CameraInfo of zeros, and a String on an image topic
        zero = {"width": 1226, "height": 370, "distortion_model": "plumb_bob", "D": np.zeros(5), "K": np.zeros(9),
                "R": np.zeros(9), "P": np.zeros(12)}
        player.pub_li.publish(DB.camera_info(zero, 1, "camera_left"))
        player.pub_ri.publish(DB.camera_info(zero, 1, "camera_right"))
        other = dds.Domain(domain, node_name="test_wrong_type")  # a topic has one type per participant
        wrong = other.writer("/camera/right/image_raw", "std_msgs/String", dds.QosKind.RELIABLE)
        wrong.publish(DB.make("std_msgs/String", data="not an image"))
        time.sleep(1.5)
        player.frames = list(range(LOCKSTEP))
        lock = player.play(stamp="sequence", lockstep=True, frame_timeout=120)
        status = TriggerClient(dom, "/dynastereo/status")
        res["status_lockstep"] = json.loads(status.call(30)[1])
        player.frames = list(range(LOCKSTEP, LOCKSTEP + RATE_FRAMES))
        rate = player.play(10.0, stamp="now")
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # until every received pair is processed or dropped
            st = json.loads(status.call(30)[1])
            if st["processed"] + st["dropped"] + st["errors"] >= st["received"] and \
                    st["received"] >= LOCKSTEP + RATE_FRAMES - 2:
                break
            time.sleep(0.5)
        time.sleep(1.0)
        player._take_odometry()
        res["status_rate"] = json.loads(status.call(30)[1])
        res["save"] = TriggerClient(dom, "/dynastereo/save_trajectory").call(60)
        res["mesh"] = TriggerClient(dom, "/dynastereo/build_mesh").call(180)
        time.sleep(1.0)
        res["lock"], res["rate"] = lock.summary(), rate.summary()
        res["lock_stamps"] = lock.stamps_ns
        res["odometry"] = list(player.odometry)
        res["raw"] = {k: [bytes(d) for d, _ in r.take(1000)] for k, r in rec.items()}
        res["discovery"] = [disc_t.deserialize(d) for d, _ in disc.take(50)]
        player.close()
        res["reference"] = offline_run_poses(kitti06, models_dir, work / "offline")
    finally:
        res["rc"] = _stop(node)
        res["log"] = log_path.read_text(errors="replace")
    return res


def test_lockstep_odometry_equals_the_offline_run(live: dict) -> None:
    """In lock-step, the node's odometry is the offline `dynastereo run` job's per-frame poses."""
    odo = [o for o in live["odometry"] if o[0] in set(live["lock_stamps"])]
    assert live["lock"]["answered"] == LOCKSTEP and [s for s, _ in odo] == live["lock_stamps"], live["log"][-3000:]
    st = live["status_lockstep"]
    assert (st["received"], st["processed"], st["dropped"], st["errors"]) == (LOCKSTEP,) * 2 + (0, 0)
    from scipy.spatial.transform import Rotation

    ref = live["reference"]
    v = np.array([x for _, x in odo])
    dpos = np.abs(v[:, :3] - ref[:, :3, 3]).max()
    dang = (Rotation.from_quat(v[:, 3:]).inv() * Rotation.from_matrix(ref[:, :3, :3])).magnitude().max()
    assert dpos == 0.0 and dang < 1e-12, (dpos, dang)  # bit for bit (the rotation through a quaternion)
    assert np.linalg.norm(v[-1, :3] - v[0, :3]) > 5  # it moved


def test_at_10hz_drops_are_counted_and_reported(live: dict) -> None:
    st, n = live["status_rate"], LOCKSTEP + RATE_FRAMES
    assert live["rate"]["published"] == RATE_FRAMES
    lost_in_transport = n - st["topics"]["pairs"]
    assert lost_in_transport == 0  # reliable input on loopback
    assert st["processed"] + st["dropped"] + st["errors"] == st["received"] == n and st["errors"] == 0
    assert st["processed"] == len({s for s, _ in live["odometry"]})  # one odometry per processed pair
    print(f"\n10 Hz: {RATE_FRAMES} published, {st['dropped']} dropped by the node's one-frame queue")


def test_published_messages_decode_with_rosbags(live: dict) -> None:
    raw = live["raw"]
    odo = [TS.deserialize_cdr(b, "nav_msgs/msg/Odometry") for b in raw["odometry"]]
    assert [o.header.stamp.sec * 10 ** 9 + o.header.stamp.nanosec for o in odo] == [s for s, _ in live["odometry"]]
    p = odo[-1].pose.pose.position
    assert np.allclose([p.x, p.y, p.z], live["odometry"][-1][1][:3], rtol=0, atol=0)
    assert odo[0].header.frame_id == "odom" and odo[0].child_frame_id == "camera_left"
    disp = [TS.deserialize_cdr(b, "stereo_msgs/msg/DisparityImage") for b in raw["disparity"]]
    assert disp and disp[-1].image.encoding == "32FC1" and (disp[-1].image.height, disp[-1].image.width) == (370, 1226)
    assert disp[-1].t == pytest.approx(0.5371506532679237, rel=1e-6) and disp[-1].max_disparity == 96
    tf = [TS.deserialize_cdr(b, "tf2_msgs/msg/TFMessage") for b in raw["tf"]]
    assert len(tf) == live["status_rate"]["processed"] and tf[-1].transforms[0].child_frame_id == "camera_left"
    masks = [TS.deserialize_cdr(b, "sensor_msgs/msg/Image") for b in raw["mask"]]
    assert masks and all((m.height, m.width, m.encoding) == (370, 1226, "mono8") for m in masks)
    assert set(np.unique(masks[-1].data)) <= {0, 255}
    path = [TS.deserialize_cdr(b, "nav_msgs/msg/Path") for b in raw["path"]]
    assert path and len(path[-1].poses) == live["status_rate"]["processed"]
    assert all(m.markers[0].action == 3 for m in (TS.deserialize_cdr(b, "visualization_msgs/msg/MarkerArray")
                                                  for b in raw["objects"]))
    cloud = TS.deserialize_cdr(raw["map"][-1], "sensor_msgs/msg/PointCloud2")
    assert cloud.point_step == 12 and cloud.width > 100 and len(cloud.data) == 12 * cloud.width
    assert TS.deserialize_cdr(raw["ready"][-1], "std_msgs/msg/Bool").data is True
    names = [(n.node_namespace, n.node_name) for d in live["discovery"] for n in d.node_entities_info_seq]
    assert ("/", "dynastereo") in names


def test_bad_inputs_give_one_line_each_and_the_node_goes_on(live: dict) -> None:
    log = live["log"]
    refused = [ln for ln in log.splitlines() if "CameraInfo refused" in ln]
    assert len(refused) == 1, log[-3000:]
    wrong = [ln for ln in log.splitlines() if "std_msgs/msg/String" in ln]
    assert len(wrong) == 1 and "expects sensor_msgs/msg/Image" in wrong[0], log[-3000:]
    assert live["status_lockstep"]["topics"]["bad_messages"] >= 2
    assert live["lock"]["answered"] == LOCKSTEP  # and it went on


def test_build_mesh_service_publishes_the_static_world(live: dict) -> None:
    """With ``mesh: true`` the ``build_mesh`` service writes ``save_dir/mesh.ply`` and
    publishes the mesh (Marker TRIANGLE_LIST) and its vertices (PointCloud2), transient
    local; both decode with rosbags' typestore and agree with the counts in the reply."""
    ok, msg = live["mesh"]
    assert ok, msg + live["log"][-3000:]
    info = json.loads(msg)
    assert Path(info["file"]).is_file() and info["vertices"] > 1000 and info["keyframes"] >= 2
    marker = TS.deserialize_cdr(live["raw"]["mesh"][-1], "visualization_msgs/msg/Marker")
    assert marker.type == 11 and marker.header.frame_id == "odom"
    assert len(marker.points) == len(marker.colors) == 3 * min(info["triangles"], 100_000)
    dense = TS.deserialize_cdr(live["raw"]["dense"][-1], "sensor_msgs/msg/PointCloud2")
    assert dense.width * dense.height == info["vertices"]


def test_services_save_and_sigint(live: dict) -> None:
    ok, msg = live["save"]
    assert ok, msg
    paths = json.loads(msg)
    rows = Path(paths["kitti"]).read_text().splitlines()
    assert len(rows) == live["status_rate"]["processed"]
    assert live["rc"] == 0, live["log"][-3000:]
    assert "trajectory saved" in live["log"]


# --------------------------------------------------------------------------- player source, CLI


def test_player_reads_a_ros2_bag_like_the_folder(kitti06: Path, tmp_path: Path) -> None:
    """``dynastereo play --ros2`` takes a .db3 (or .mcap) bag: the same frames and stamps as the folder."""
    from dynastereo.io import KittiSequence
    from dynastereo.ros.bags import export_bag
    from dynastereo.ros.ros2_player import open_source

    folder = KittiSequence(kitti06)
    export_bag(folder, tmp_path / "k.db3", "ros2", frames=range(3))
    seq, frames = open_source(str(tmp_path / "k.db3"))
    assert frames == [0, 1, 2]
    assert np.array_equal(seq.frame(1).left, folder.frame(1).left)
    assert np.allclose(seq.timestamps()[:3], folder.timestamps()[:3], atol=1e-9)
    assert seq.calibration.baseline == pytest.approx(folder.calibration.baseline, rel=1e-9)
    seq2, frames2 = open_source(str(kitti06), "0-4")
    assert frames2 == [0, 1, 2, 3, 4]


def test_cli_errors_are_one_line(tmp_path: Path, monkeypatch) -> None:
    from typer.testing import CliRunner

    from dynastereo.cli.main import app

    bad = tmp_path / "bad.yaml"
    bad.write_text("/**:\n  ros__parameters:\n    no_such_parameter: 1\n")
    r = CliRunner().invoke(app, ["node", "--ros2", "--params", str(bad)])
    assert r.exit_code == 2 and "bad.yaml: unknown parameter 'no_such_parameter'" in r.output
    monkeypatch.setenv("ROS_DOMAIN_ID", "999")
    r = CliRunner().invoke(app, ["node", "--ros2"])
    assert r.exit_code == 2 and "ROS_DOMAIN_ID must be in 0..232, got 999" in r.output
    r = CliRunner().invoke(app, ["play", str(tmp_path)])
    assert r.exit_code == 2 and "play needs --ros2" in r.output
    import sys as _sys

    monkeypatch.setitem(_sys.modules, "cyclonedds.domain", None)  # as if the ros2 extra were missing
    with pytest.raises(dds.RosUnavailable, match=r"pip install 'dynastereo\[ros2\]'"):
        dds.import_cyclonedds()
