"""The node: its transport-agnostic core (bounded queue, drops, live parameters, saving)
and, for real, the ROS 1 node on a private rosmaster fed KITTI 06 at 10 Hz -- its
odometry must equal an offline run on the same frames."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import REQUIRE, track_offline
from dynastereo.config import Config
from dynastereo.errors import ConfigError
from dynastereo.eval.trajectory import read_trajectory
from dynastereo.io import KittiSequence
from dynastereo.ros.core import DropOldestQueue, StereoInput, StereoNodeCore
from dynastereo.datatypes import StereoMasks

LIVE_FRAMES = 25  # KITTI 06 frames 0..24 at 10 Hz
BURST = "25-44"  # then 20 frames at 200 Hz with queue_size 1


def _require_ros1() -> None:
    """Skip (locally) or fail (CI: DYNASTEREO_REQUIRE_DATA=1) without ROS 1."""
    why = ""
    try:
        import rospy  # noqa: F401
        import message_filters  # noqa: F401
        import nav_msgs.msg  # noqa: F401
        import stereo_msgs.msg  # noqa: F401
        import std_srvs.srv  # noqa: F401
        import tf2_msgs.msg  # noqa: F401
    except ImportError as e:
        why = f"ROS 1 not importable ({e})"
    for exe in ("roscore", "roslaunch"):
        if not why and shutil.which(exe) is None:
            why = f"{exe} not on PATH"
    if why:
        msg = (why + ": install Debian's ROS 1 packages (as .ci/run does) and use a venv made with "
               "'/usr/bin/python3 -m venv --system-site-packages'")
        if REQUIRE:
            pytest.fail(msg + " [DYNASTEREO_REQUIRE_DATA=1]")
        pytest.skip(msg)


# --------------------------------------------------------------------------- core, no ROS


def test_drop_oldest_queue_is_bounded_and_counts() -> None:
    q = DropOldestQueue(2)
    assert [q.put(i) for i in range(5)] == [0, 0, 1, 1, 1]
    assert len(q) == 2 and q.dropped == 3 and q.high_water == 2
    assert q.get() == 3 and q.get() == 4 and q.get(timeout=0.01) is None
    q.put(5)
    q.put(6)
    assert q.resize(1) == 1 and q.dropped == 4 and q.get() == 6
    q.put(7)
    assert q.close() == 1 and q.get() is None and q.put(8) == 0
    with pytest.raises(ConfigError):
        DropOldestQueue(0)


class _BlockingMasker:
    """Masks nothing; the first call waits for ``gate`` (a slow frame)."""

    name = "blocking"

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.entered = threading.Event()

    def mask(self, frame, timer=None):
        self.entered.set()
        self.gate.wait(30)
        return StereoMasks.empty(frame.shape)


class _Sink:
    def __init__(self) -> None:
        self.poses: list[tuple[int, np.ndarray]] = []
        self.images = 0

    def publish_pose(self, r) -> None:
        self.poses.append((r.stamp_ns, r.pose))

    def publish_images(self, r, disparity) -> None:
        self.images += 1
        assert disparity is None

    def wants_disparity(self) -> bool:
        return False


def _inputs(kitti06: Path, idx) -> list[StereoInput]:
    seq = KittiSequence(kitti06)
    return [StereoInput(seq.frame(i).left, seq.frame(i).right, int(i * 100_000_000)) for i in idx]


@pytest.mark.parametrize("pipelined", [True, False])
def test_core_drops_the_oldest_when_busy(kitti06: Path, pipelined: bool) -> None:
    seq = KittiSequence(kitti06)
    masker, sink = _BlockingMasker(), _Sink()
    core = StereoNodeCore(Config(), calibration=seq.calibration, masker=masker, queue_size=1,
                          pipelined=pipelined, sink=sink)
    frames = _inputs(kitti06, range(5))
    core.start()
    try:
        core.submit(frames[0])
        assert masker.entered.wait(10)  # frame 0 is being processed, blocked
        drops = [core.submit(f) for f in frames[1:]]
        assert drops == [0, 1, 1, 1]  # 1 waits; 2, 3, 4 each evict the oldest waiting one
        assert len(core.source.queue) == 1
        masker.gate.set()
        assert core.wait_idle(60)
    finally:
        core.shutdown()
    st = core.status()
    assert (st["received"], st["processed"], st["dropped"], st["errors"]) == (5, 2, 3, 0)
    assert [s for s, _ in sink.poses] == [0, 400_000_000]  # the newest frame won, in order
    assert sink.images == 2 and st["queue_high_water"] == 1
    assert st["latency_receipt_ms"]["n"] == 2


def test_core_warm_up_goes_through_the_masker(kitti06: Path) -> None:
    """The node's warm-up runs the masker's detection stage (the frames' own tiles and batch):
    on a 640x480 black frame before the calibration is known, at the camera's size after."""

    class _WarmMasker(_BlockingMasker):
        def __init__(self) -> None:
            super().__init__()
            self.warmed: list[tuple[int, int]] = []

        def warm_up(self, height: int, width: int) -> None:
            self.warmed.append((height, width))

    seq = KittiSequence(kitti06)
    masker = _WarmMasker()
    core = StereoNodeCore(Config(), masker=masker, pipelined=False, sink=_Sink())
    try:
        core.warm_up()
        core.set_calibration(seq.calibration)
        core.warm_up()
    finally:
        core.shutdown()
    c = seq.calibration
    assert masker.warmed == [(480, 640), (c.height, c.width)]
    assert not masker.entered.is_set()  # no frame was masked


def test_core_live_parameters(kitti06: Path, models_dir: Path, tmp_path: Path) -> None:
    seq = KittiSequence(kitti06)
    core = StereoNodeCore(Config(), calibration=seq.calibration, models_dir=models_dir, pipelined=False)
    f3 = _inputs(kitti06, [3])[0]
    r = core.process(f3)
    assert r.masks is not None and np.count_nonzero(r.masks.left) > 500  # parked car masked
    det = core._detector
    # a bad value is refused with the reason; nothing changes
    with pytest.raises(ConfigError, match="num_disparities"):
        core.update_params({"stereo.num_disparities": 100})
    with pytest.raises(ConfigError, match="restart"):
        core.update_params({"slam.n_features": 500})
    with pytest.raises(ConfigError, match="unknown configuration key"):
        core.update_params({"stereo.no_such_key": 1})
    assert core.cfg.stereo.num_disparities == 96 and core.stats.param_rejections == 3
    # good values apply at the next frame: masking off, then on again with another matcher
    assert core.update_params({"masker.kind": "none"}) == {"masker.kind": "none"}
    assert core.update_params({"masker.kind": "none"}) == {}  # no change, nothing rebuilt
    r = core.process(_inputs(kitti06, [4])[0])
    assert r.masks is not None and np.count_nonzero(r.masks.left) == 0
    core.update_params({"masker.kind": "outline", "stereo.block_size": 21})
    r = core.process(_inputs(kitti06, [5])[0])
    assert np.count_nonzero(r.masks.left) > 500
    assert core._masker_cfg.stereo.block_size == 21 and core._detector is det  # detector not reloaded
    core.update_params({"detector.score_threshold": 0.5})
    assert core._detector is not det  # a detector.* change reloads it
    # save: trajectory rows = frames processed, statistics and config in node.json
    paths = core.save(tmp_path)
    core.shutdown()
    assert len(read_trajectory(paths["kitti"])) == 3 and len(read_trajectory(paths["tum"])) == 3
    node = json.loads(Path(paths["node"]).read_text())
    assert node["processed"] == 3 and node["param_updates"] == 3 and node["config"]["stereo"]["block_size"] == 21


def test_core_refuses_a_changed_calibration(kitti06: Path) -> None:
    from dynastereo.datatypes import StereoCalibration

    seq = KittiSequence(kitti06)
    core = StereoNodeCore(Config(), calibration=seq.calibration, masker=_BlockingMasker())
    assert core.set_calibration(seq.calibration) is False  # the same again: fine
    other = StereoCalibration(K=seq.calibration.K, baseline=0.3, width=1226, height=370)
    with pytest.raises(ConfigError, match="calibration changed"):
        core.set_calibration(other)
    core.shutdown()


# --------------------------------------------------------------------------- ROS 1, live


def test_ros1_bags_read_with_rospy_and_rosbag(kitti06: Path, tmp_path: Path) -> None:
    """ROS 1 bags we write carry the definitions rospy expects and ROS 1's own reader
    (python3-rosbag: what `rosbag play` uses, with its LZ4) reads them."""
    _require_ros1()
    import nav_msgs.msg
    import sensor_msgs.msg
    import stereo_msgs.msg
    import tf2_msgs.msg
    import visualization_msgs.msg
    from rosbags.highlevel import AnyReader

    from dynastereo.ros import export_bag
    from dynastereo.ros.bagrun import BagOutput

    bag = export_bag(KittiSequence(kitti06), tmp_path / "k.bag", "ros1", frames=[0]).path
    seq = KittiSequence(kitti06)
    out = BagOutput(tmp_path / "o.bag", "ros1", Config(), seq.calibration, "camera_left")
    f = seq.frame(0)
    out.write(0, f, StereoMasks.empty(f.shape), np.eye(4)[:3], 5, map_points=lambda: np.ones((3, 3)))
    out.close()
    want = {"sensor_msgs/msg/Image": sensor_msgs.msg.Image, "sensor_msgs/msg/CameraInfo": sensor_msgs.msg.CameraInfo,
            "nav_msgs/msg/Odometry": nav_msgs.msg.Odometry, "tf2_msgs/msg/TFMessage": tf2_msgs.msg.TFMessage,
            "stereo_msgs/msg/DisparityImage": stereo_msgs.msg.DisparityImage,
            "nav_msgs/msg/Path": nav_msgs.msg.Path, "sensor_msgs/msg/PointCloud2": sensor_msgs.msg.PointCloud2,
            "visualization_msgs/msg/MarkerArray": visualization_msgs.msg.MarkerArray}
    seen = set()
    for p in (bag, tmp_path / "o.bag"):
        with AnyReader([p]) as r:
            for c in r.connections:
                assert c.digest == want[c.msgtype]._md5sum, c.msgtype
                seen.add(c.msgtype)
    assert seen == set(want)
    try:
        import rosbag
    except ImportError as e:
        if REQUIRE:
            pytest.fail(f"python3-rosbag not importable ({e}) [DYNASTEREO_REQUIRE_DATA=1]")
        pytest.skip(f"python3-rosbag not importable ({e})")
    from dynastereo.ros import read_odometry

    counts: dict[str, int] = {}
    for p in (bag, tmp_path / "o.bag"):
        with rosbag.Bag(str(p)) as b:
            assert b.get_compression_info().compression in ("lz4", "none")
            for topic, m, t in b.read_messages():
                counts[topic] = counts.get(topic, 0) + 1
                if topic == "/dynastereo/odometry":
                    assert m.header.stamp.to_nsec() == 5 and m.pose.pose.orientation.w == pytest.approx(1.0)
                if topic == "/camera/left/image_raw":
                    assert np.array_equal(np.frombuffer(m.data, np.uint8).reshape(370, 1226), f.left)
    assert counts == {"/camera/left/image_raw": 1, "/camera/right/image_raw": 1, "/camera/left/camera_info": 1,
                      "/camera/right/camera_info": 1, "/dynastereo/odometry": 1, "/tf": 1,
                      "/dynastereo/left/masked": 1, "/dynastereo/right/masked": 1, "/dynastereo/left/mask": 1,
                      "/dynastereo/right/mask": 1, "/dynastereo/disparity": 1, "/dynastereo/path": 1,
                      "/dynastereo/map_points": 1, "/dynastereo/objects": 1}
    assert read_odometry(tmp_path / "o.bag")[0].tolist() == [5]


def test_genpy_messages_with_numpy2_round_trip() -> None:
    """rospy's message classes from Debian work in the venv (numpy 2, not Debian's numpy 1)."""
    _require_ros1()
    from io import BytesIO

    import nav_msgs.msg
    import sensor_msgs.msg
    import stereo_msgs.msg

    from dynastereo.ros.messages import DisparityData, OdometryData
    from dynastereo.ros.ros1 import GenpyBuilder

    assert int(np.__version__.split(".")[0]) >= 2 and "/usr/lib/python3/dist-packages" not in np.__file__
    b = GenpyBuilder()
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [0.1, -0.2, 0.3]).as_matrix()
    T[:3, 3] = [1.5, -2.0, 30.25]
    img = np.arange(12 * 7, dtype=np.uint8).reshape(7, 12)
    disp = np.where(img > 40, img.astype(np.float32) / 4, 0).astype(np.float32)
    msgs = [
        (b.odometry(OdometryData(1_700_000_000_123_456_789, T, linear=np.array([1.0, 2, 3]))), nav_msgs.msg.Odometry),
        (b.image(img, 5, "cam", seq=3), sensor_msgs.msg.Image),
        (b.camera_info({"width": 12, "height": 7, "distortion_model": "plumb_bob", "D": np.zeros(5),
                        "K": np.eye(3).reshape(-1), "R": np.eye(3).reshape(-1), "P": np.ones(12)}, 5, "cam"),
         sensor_msgs.msg.CameraInfo),
        (b.disparity(DisparityData(disp, 700.0, 0.54, 0, 96), 5, "cam"), stereo_msgs.msg.DisparityImage),
    ]
    back = []
    for m, cls in msgs:
        buf = BytesIO()
        m.serialize(buf)
        back.append(cls().deserialize(buf.getvalue()))
    odo, im, ci, di = back
    assert odo.header.stamp.to_nsec() == 1_700_000_000_123_456_789 and odo.header.frame_id == "odom"
    q = odo.pose.pose.orientation
    assert np.allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), T[:3, :3], atol=1e-12)
    assert odo.pose.pose.position.z == 30.25 and odo.twist.twist.linear.y == 2.0
    assert np.array_equal(np.frombuffer(im.data, np.uint8).reshape(7, 12), img) and im.encoding == "mono8"
    assert list(ci.P) == [1.0] * 12 and ci.width == 12
    d = np.frombuffer(di.image.data, np.float32).reshape(7, 12)
    assert np.array_equal(d, np.where(disp > 0, disp, -1)) and di.T == pytest.approx(0.54)


@pytest.fixture(scope="module")
def live_run(kitti06: Path, models_dir: Path, tmp_path_factory) -> dict:
    """The node on a private master: KITTI 06 frames 0..24 at 10 Hz, then parameters, a
    burst, save, SIGINT (``tests/ros_harness.py check``, its own process: rospy joins
    one master per process).  Meanwhile the offline reference runs here."""
    _require_ros1()
    work = tmp_path_factory.mktemp("live")
    env = dict(os.environ, DYNASTEREO_MODELS=str(models_dir))
    cmd = [sys.executable, str(Path(__file__).with_name("ros_harness.py")), "check", "--sequence", str(kitti06),
           "--frames", str(LIVE_FRAMES), "--burst", BURST, "--queue-size", "40", "--rate", "10",
           "--timeout", "90", "--workdir", str(work), "--json", str(work / "live.json")]
    p = subprocess.Popen(cmd, env=env, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        ref = _offline_reference(kitti06, models_dir)
        out, _ = p.communicate(timeout=240)
    finally:
        from ros_harness import stop_process

        stop_process(p, timeout=5)  # bounded: whatever is left of the group goes
    res = json.loads((work / "live.json").read_text()) if (work / "live.json").is_file() else {}
    assert res.get("ok"), f"live run failed: {res.get('error')}\n{res.get('traceback', '')}\n" \
                          f"{res.get('node_log_tail', '')}\n{out.decode(errors='replace')[-3000:]}"
    res["reference"] = ref
    return res


def _offline_reference(kitti06: Path, models_dir: Path) -> dict:
    return {"poses": track_offline(kitti06, models_dir, LIVE_FRAMES)[0]}


def test_live_node_odometry_equals_the_offline_run(live_run: dict) -> None:
    odo = live_run["odometry"]
    assert len(odo) == LIVE_FRAMES
    st = live_run["status_play"]
    assert (st["received"], st["processed"], st["dropped"], st["errors"]) == (LIVE_FRAMES, LIVE_FRAMES, 0, 0)
    assert st["unpaired_left"] == 0 and st["unpaired_right"] == 0 and st["topics"]["pairs"] == LIVE_FRAMES
    assert st["calibration"]["baseline"] == pytest.approx(0.5371506532679237, rel=1e-12)  # from CameraInfo
    # one odometry per frame, stamped with its image's stamp, in order
    assert [o["stamp_ns"] for o in odo] == live_run["play_stamps_ns"]
    assert all(o["frame"] == "odom" and o["child"] == "camera_left" for o in odo)
    ref = live_run["reference"]["poses"]
    pos = np.array([o["p"] for o in odo])
    rot = Rotation.from_quat(np.array([o["q"] for o in odo]))
    dpos = np.abs(pos - ref[:, :, 3]).max()
    dang = (rot.inv() * Rotation.from_matrix(ref[:, :, :3])).magnitude().max()
    assert dpos < 1e-3, f"live vs offline position differs by {dpos:.3g} m"
    assert dang < 1e-5, f"live vs offline rotation differs by {dang:.3g} rad"
    assert np.linalg.norm(pos[-1] - pos[0]) > 20  # it moved (KITTI 06, 2.5 s of driving)
    # TF, masks and disparity were published for every frame (someone subscribed)
    c, last = live_run["counts"], live_run["last"]
    assert c["tf"] >= LIVE_FRAMES and last["tf_child"] == "camera_left"
    assert c["left_mask"] == LIVE_FRAMES and c["disparity"] == LIVE_FRAMES
    assert last["mask"]["shape"] == [370, 1226] and set(last["mask"]["values"]) <= {0, 255}
    d = last["disparity"]
    assert d["encoding"] == "32FC1" and d["valid_fraction"] > 0.3 and d["max_disparity"] == 96
    assert st["latency_receipt_ms"]["n"] == LIVE_FRAMES


def test_live_parameters_drops_save_and_shutdown(live_run: dict) -> None:
    p = live_run["params"]
    assert p["num_disparities"] == 96  # 100 was refused and set back on the server
    assert p["block_size"] == 21 and p["param_updates"] == 1 and p["param_rejections"] == 1
    b = live_run["status_burst"]
    assert live_run["burst_published"] == 20 and b["queue_size"] == 1
    # the transport may lose part of a burst (rospy's bounded subscriber queues); most arrives
    assert LIVE_FRAMES + 10 <= b["received"] <= LIVE_FRAMES + 20 and b["received"] == b["topics"]["pairs"]
    assert b["dropped"] > 0, "a 200 Hz burst into a one-frame queue must drop frames"
    assert b["processed"] + b["dropped"] + b["errors"] == b["received"] and b["errors"] == 0
    assert b["processed"] > LIVE_FRAMES
    sv = live_run["save"]
    assert sv["ok"] and sv["rows"] == b["processed"]
    sd = live_run["shutdown"]
    assert sd["rc"] == 0 and sd["rows"] == b["processed"]  # saved again on SIGINT, after the final BA
    assert np.isfinite(np.array(sd["final_poses"])).all()
    assert sd["node_json"]["processed"] == b["processed"] and sd["node_json"]["slam"]["frames"] == b["processed"]
