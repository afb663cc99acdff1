"""Offline ROS bags (no ROS installation): message conversions, CameraInfo calibration,
left/right pairing, and the round trip export-bag -> run --bag -> output bag read back,
in all three formats (ROS 1 .bag, ROS 2 .db3, .mcap)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import track_offline
from dynastereo.cli.main import app
from dynastereo.config import Config
from dynastereo.errors import CalibrationError, InputError, SequenceError
from dynastereo.eval.trajectory import read_trajectory
from dynastereo.io import EurocSequence, KittiSequence, load_kitti_calib
from dynastereo.io.calib import RawStereoCalibration, kitti_projections
from dynastereo.api import run_bag
from dynastereo.ros import BagStereoSequence, BagWriter, bag_topics, export_bag, read_messages, read_odometry
from dynastereo.ros.bags import bag_format, header_ns
from dynastereo.ros.convert import (
    ImageDecoder,
    calibration_from_camera_info,
    camera_info_fields,
    image_fields,
    image_to_array,
)
from dynastereo.datatypes import StereoCalibration

runner = CliRunner()
N_FRAMES = 5


def _img_msg(arr: np.ndarray, encoding: str, pad: int = 0, big: bool = False) -> SimpleNamespace:
    """An Image-like message for ``arr`` already in ``encoding``'s layout, rows padded."""
    a = np.ascontiguousarray(arr)
    if big:
        a = a.astype(a.dtype.newbyteorder(">"))
    h, w = a.shape[:2]
    row = a.reshape(h, -1).view(np.uint8)
    data = np.zeros((h, row.shape[1] + pad), np.uint8)
    data[:, : row.shape[1]] = row
    return SimpleNamespace(height=h, width=w, encoding=encoding, is_bigendian=int(big), step=data.shape[1],
                           data=data.tobytes())


# --------------------------------------------------------------------------- conversions


def test_image_decoder_all_encodings_with_row_padding() -> None:
    rng = np.random.default_rng(0)
    gray = rng.integers(0, 256, (7, 9), dtype=np.uint8)
    bgr = rng.integers(0, 256, (7, 9, 3), dtype=np.uint8)
    dec = ImageDecoder()
    assert np.array_equal(dec.decode(_img_msg(gray, "mono8", pad=3)), gray)
    assert np.array_equal(dec.decode(_img_msg(gray, "8UC1")), gray)
    assert np.array_equal(dec.decode(_img_msg(bgr, "bgr8", pad=5)), bgr)
    assert np.array_equal(dec.decode(_img_msg(bgr, "8UC3")), bgr)
    assert np.array_equal(dec.decode(_img_msg(bgr[:, :, ::-1], "rgb8", pad=1)), bgr)  # -> BGR
    bgra = np.dstack([bgr, np.full((7, 9), 200, np.uint8)])
    assert np.array_equal(dec.decode(_img_msg(bgra, "bgra8")), bgr)
    rgba = np.dstack([bgr[:, :, ::-1], np.zeros((7, 9), np.uint8)])
    assert np.array_equal(dec.decode(_img_msg(rgba, "rgba8")), bgr)
    # 16 bit, both byte orders, row padding: kept exact by image_to_array
    g16 = rng.integers(0, 4096, (7, 9), dtype=np.uint16)
    for big in (False, True):
        m = _img_msg(g16, "mono16", pad=2, big=big)
        assert np.array_equal(image_to_array(m), g16)
    # output fields round trip
    for img, enc in ((gray, None), (bgr, None), (bgr, "rgb8"), (g16, None)):
        f = image_fields(img, enc)
        back = image_to_array(SimpleNamespace(**f))
        want = img[:, :, ::-1] if enc == "rgb8" else img
        assert np.array_equal(back, want) and f["step"] == img.shape[1] * (img.itemsize * (3 if img.ndim == 3 else 1))


def test_mono16_shift_is_chosen_once_from_the_first_image() -> None:
    dec = ImageDecoder()
    first = np.array([[0, 4095], [2048, 16]], np.uint16)  # a 12-bit camera
    out = dec.decode(_img_msg(first, "16UC1"))
    assert dec.mono16_shift == 4
    assert out.dtype == np.uint8 and out.tolist() == [[0, 255], [128, 1]]
    # a later, darker frame keeps the shift (no per-frame brightness change)
    out2 = dec.decode(_img_msg(np.array([[1024, 32]], np.uint16), "mono16"))
    assert out2.tolist() == [[64, 2]] and dec.mono16_shift == 4
    # the full 16-bit range of an 8-bit image times 257 comes back exactly
    v = np.arange(256, dtype=np.uint16).reshape(16, 16)
    assert np.array_equal(ImageDecoder().decode(_img_msg(v * 257, "mono16")), v.astype(np.uint8))
    with pytest.raises(ValueError):
        ImageDecoder(9)


def test_compressed_png_exact_and_jpeg_close() -> None:
    rng = np.random.default_rng(1)
    gray = cv2.resize(rng.integers(0, 256, (8, 12), dtype=np.uint8), (60, 40), interpolation=cv2.INTER_CUBIC)
    bgr = cv2.merge([gray, 255 - gray, (gray // 2 + 60).astype(np.uint8)])
    dec = ImageDecoder()
    for img in (gray, bgr):
        ok, png = cv2.imencode(".png", img)
        assert np.array_equal(dec.decode(SimpleNamespace(format="png", data=png.tobytes())), img)
        ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        back = dec.decode(SimpleNamespace(format="jpeg", data=jpg.tobytes()))
        err = np.abs(back.astype(int) - img).mean()
        assert back.shape == img.shape and err < 8  # lossy, chroma subsampled
        if img.ndim == 3:  # channel order kept (a B/R swap is far worse)
            assert np.abs(back[:, :, ::-1].astype(int) - img).mean() > 2 * err
    with pytest.raises(InputError, match="cannot decode CompressedImage"):
        dec.decode(SimpleNamespace(format="png", data=b"not an image"), "/cam/compressed")


def test_bad_image_messages_name_the_problem() -> None:
    dec = ImageDecoder()
    g = np.zeros((4, 5), np.uint8)
    with pytest.raises(InputError, match="unsupported image encoding 'bayer_rggb8'"):
        dec.decode(_img_msg(g, "bayer_rggb8"), "/left")
    m = _img_msg(g, "mono8")
    m.data = m.data[:-3]
    with pytest.raises(InputError, match="expected height\\*step"):
        dec.decode(m, "/left")
    m = _img_msg(g, "mono8")
    m.step = 3
    with pytest.raises(InputError, match="step 3 is smaller"):
        dec.decode(m, "/left")
    with pytest.raises(InputError, match="32FC1"):
        dec.decode(_img_msg(np.zeros((2, 2), np.float32), "32FC1"))


def test_camera_info_of_kitti_gives_the_exact_calibration(kitti06: Path) -> None:
    calib = load_kitti_calib(kitti06 / "calib.txt", (1226, 370))
    Pl, Pr = kitti_projections(kitti06 / "calib.txt")
    li = SimpleNamespace(**camera_info_fields(calib, "left", P=Pl), binning_x=0, binning_y=0)
    ri = SimpleNamespace(**camera_info_fields(calib, "right", P=Pr), binning_x=0, binning_y=0)
    c = calibration_from_camera_info(li, ri)
    assert isinstance(c, StereoCalibration)
    assert np.array_equal(c.K, calib.K) and c.baseline == calib.baseline and c.size == calib.size
    # from a calibration alone: P_right[0,3] = -fx*B, same baseline to rounding
    li2 = SimpleNamespace(**camera_info_fields(calib, "left"))
    ri2 = SimpleNamespace(**camera_info_fields(calib, "right"))
    assert calibration_from_camera_info(li2, ri2).baseline == pytest.approx(calib.baseline, rel=1e-12)
    # rectify="yes" forces a raw calibration (identity rectification)
    assert isinstance(calibration_from_camera_info(li, ri, "yes"), RawStereoCalibration)
    # swapped cameras and missing P are explained
    with pytest.raises(CalibrationError, match="right camera must be to the right"):
        calibration_from_camera_info(ri, li)
    bad = SimpleNamespace(**dict(vars(ri), P=np.zeros(12)))
    with pytest.raises(CalibrationError, match="no projection matrix P"):
        calibration_from_camera_info(li, bad)


def test_raw_euroc_bag_is_rectified_like_the_folder(euroc_dir: Path, tmp_path: Path) -> None:
    seq = EurocSequence(euroc_dir)
    out = export_bag(seq, tmp_path / "euroc.db3", "ros2", frames=[0, 7], raw=True)
    with BagStereoSequence(out.path) as b:
        assert b.report.rectified_on_read and b.rectifier is not None
        assert np.array_equal(b.calibration.K, seq.calibration.K)
        assert b.calibration.baseline == pytest.approx(seq.calibration.baseline, rel=1e-12)
        for i, j in ((0, 0), (1, 7)):
            fb, fs = b.frame(i), seq.frame(j)
            assert np.array_equal(fb.left, fs.left) and np.array_equal(fb.right, fs.right)
            assert b.stamps_ns[i] == seq.timestamps_ns[j]  # exact nanoseconds kept
    with pytest.raises(InputError, match="rectified already"):
        export_bag(KittiSequence(euroc_dir.parent.parent / "kitti_odometry/dataset/sequences/06"),
                   tmp_path / "k.bag", raw=True)


# --------------------------------------------------------------------------- pairing


def _synthetic_bag(path: Path, fmt: str, with_info: bool = True) -> None:
    """10 left images (value k) at k*100 ms; right images (value 100+k): k=3 missing,
    k=5 20 ms late, the others within 2 ms; one extra right image at 1050 ms."""
    calib = StereoCalibration(K=np.array([[100.0, 0, 16], [0, 100.0, 12], [0, 0, 1]]), baseline=0.1,
                              width=32, height=24)
    ms = 1_000_000
    with BagWriter(path, fmt) as w:
        b = w.builder
        for k in range(10):
            t = k * 100 * ms
            w.write("/cam/left/image_raw", t + 3 * ms, b.image(np.full((24, 32), k, np.uint8), t, "cl"))
            if with_info:
                w.write("/cam/left/camera_info", t, b.camera_info(camera_info_fields(calib, "left"), t, "cl"))
                w.write("/cam/right/camera_info", t, b.camera_info(camera_info_fields(calib, "right"), t, "cr"))
            if k == 3:
                continue
            tr = t + (20 * ms if k == 5 else (ms if k % 2 == 0 else -2 * ms))
            w.write("/cam/right/image_raw", tr + 3 * ms, b.image(np.full((24, 32), 100 + k, np.uint8), tr, "cr"))
        w.write("/cam/right/image_raw", 1050 * ms, b.image(np.full((24, 32), 199, np.uint8), 1050 * ms, "cr"))


@pytest.mark.parametrize("fmt,name", [("ros1", "s.bag"), ("mcap", "s.mcap")])
def test_pairing_by_stamp_counts_unpaired_never_mixes(tmp_path: Path, fmt: str, name: str) -> None:
    path = tmp_path / name
    _synthetic_bag(path, fmt)
    assert bag_format(path) == fmt
    with BagStereoSequence(path, "/cam/left/image_raw", "/cam/right/image_raw", tolerance_s=0.005) as s:
        assert len(s) == 8 and (s.unpaired_left, s.unpaired_right) == (2, 2)
        assert s.report.pairs == 8 and s.report.left_messages == 10 and s.report.right_messages == 10
        assert s.report.left_info == "/cam/left/camera_info"  # found beside the image topic
        ks = []
        for i in range(len(s)):
            f = s.frame(i)
            k = int(f.left[0, 0])
            assert int(f.right[0, 0]) == 100 + k  # never a neighbour's right image
            assert f.timestamp == pytest.approx(k * 0.1)
            ks.append(k)
        assert ks == [0, 1, 2, 4, 6, 7, 8, 9]
        assert s.calibration.baseline == pytest.approx(0.1)
    with BagStereoSequence(path, "/cam/left/image_raw", "/cam/right/image_raw", tolerance_s=0.025) as s:
        assert len(s) == 9 and (s.unpaired_left, s.unpaired_right) == (1, 1)
    with pytest.raises(SequenceError, match="no left/right pairs within 0.5 ms"):
        BagStereoSequence(path, "/cam/left/image_raw", "/cam/right/image_raw", tolerance_s=0.0005)
    with pytest.raises(SequenceError, match="left image topic '/nope' not in the bag.*/cam/left/image_raw"):
        BagStereoSequence(path, "/nope", "/cam/right/image_raw")


def test_calibration_needed_from_camera_info_or_a_file(tmp_path: Path) -> None:
    path = tmp_path / "noinfo.db3"
    _synthetic_bag(path, "ros2", with_info=False)
    with pytest.raises(CalibrationError, match="no CameraInfo in the bag"):
        BagStereoSequence(path, "/cam/left/image_raw", "/cam/right/image_raw")
    y = tmp_path / "calib.yaml"
    y.write_text("fx: 100.0\ncx: 16\ncy: 12\nbaseline: 0.2\nwidth: 32\nheight: 24\n")
    with BagStereoSequence(path, "/cam/left/image_raw", "/cam/right/image_raw", fallback_calib=y) as s:
        assert s.calibration.baseline == pytest.approx(0.2) and s.report.calibration_source == str(y)
    bad = tmp_path / "bad.yaml"
    bad.write_text("fx: 100.0\ncx: 16\ncy: 12\nbaseline: 0.2\nwidth: 64\nheight: 48\n")
    with pytest.raises(CalibrationError, match="64x48"):
        BagStereoSequence(path, "/cam/left/image_raw", "/cam/right/image_raw", calib=bad)


@pytest.mark.parametrize("encoding", ["mono8", "mono16", "bgr8", "rgb8", "png", "jpeg"])
def test_export_encodings_decode_back(kitti06: Path, tmp_path: Path, encoding: str) -> None:
    seq = KittiSequence(kitti06)
    r = export_bag(seq, tmp_path / "k.bag", "ros1", frames=[2], encoding=encoding)
    suffix = "/compressed" if encoding in ("png", "jpeg") else ""
    topics = bag_topics(r.path)
    assert topics["/camera/left/image_raw" + suffix][1] == 1 and topics["/camera/right/camera_info"][1] == 1
    with BagStereoSequence(r.path) as b:  # default topics (+ /compressed found automatically)
        f, g = b.frame(0), seq.frame(2)
        left = cv2.cvtColor(f.left, cv2.COLOR_BGR2GRAY) if f.left.ndim == 3 else f.left
        if encoding == "jpeg":
            assert np.abs(left.astype(int) - g.left).mean() < 2
        else:
            assert np.array_equal(left, g.left) and np.array_equal(f.right_gray, g.right)
        assert f.timestamp == pytest.approx(seq.timestamps()[2], abs=1e-9)


# --------------------------------------------------------------------------- round trip


@pytest.fixture(scope="module")
def kitti_reference(kitti06: Path, models_dir: Path) -> dict:
    """SLAM on the first frames of KITTI 06 straight from the folder: the poses tracking
    returned (what odometry carries) and the final trajectory."""
    live, system = track_offline(kitti06, models_dir, N_FRAMES)
    seq = KittiSequence(kitti06)
    return {"live": live, "final": system.trajectory(),
            "stamps_ns": np.round(seq.timestamps()[:N_FRAMES] * 1e9).astype(np.int64)}


@pytest.mark.parametrize("fmt,name,encoding", [("ros1", "in.bag", "mono8"), ("ros2", "in.db3", "png"),
                                               ("mcap", "in.mcap", "rgb8")])
def test_round_trip_export_run_read_back(kitti06: Path, models_dir: Path, kitti_reference: dict, tmp_path: Path,
                                         fmt: str, name: str, encoding: str) -> None:
    src = export_bag(KittiSequence(kitti06), tmp_path / name, fmt, frames=range(N_FRAMES), encoding=encoding)
    assert src.frames == N_FRAMES
    res = run_bag(src.path, tmp_path / "out", Config(), models_dir=models_dir)
    out_bag = tmp_path / "out" / ("output" + Path(name).suffix)
    assert res.output_bag == out_bag and bag_format(out_bag) == fmt
    rep = json.loads((tmp_path / "out" / "bag.json").read_text())
    assert rep["pairs"] == N_FRAMES and rep["unpaired_left"] == 0 and rep["format"] == fmt
    assert rep["calibration_source"].startswith("CameraInfo")

    # odometry: one per frame, the image stamps, the poses tracking returned
    stamps, T = read_odometry(out_bag)
    ref = kitti_reference
    assert np.array_equal(stamps, ref["stamps_ns"])
    assert np.abs(T[:, :3, :] - ref["live"]).max() < 1e-9
    # the trajectory files hold the final (bundle-adjusted) poses, as for a folder run
    est = read_trajectory(tmp_path / "out" / "trajectory.kitti.txt")
    assert np.abs(est.poses[:, :3, :] - ref["final"]).max() < 1e-6
    assert json.loads((tmp_path / "out" / "run.json").read_text())["frames_done"] == N_FRAMES

    # every output topic, per frame, with consistent content
    topics = bag_topics(out_bag)
    for t, ty in (("/dynastereo/odometry", "nav_msgs/msg/Odometry"), ("/tf", "tf2_msgs/msg/TFMessage"),
                  ("/dynastereo/left/masked", "sensor_msgs/msg/Image"), ("/dynastereo/right/mask", "sensor_msgs/msg/Image"),
                  ("/dynastereo/disparity", "stereo_msgs/msg/DisparityImage")):
        assert topics[t] == (ty, N_FRAMES), t
    msgs: dict[str, list] = {}
    for topic, _, m in read_messages(out_bag, ["/dynastereo/left/masked", "/dynastereo/left/mask",
                                               "/dynastereo/disparity", "/tf"]):
        msgs.setdefault(topic, []).append(m)
    seq = KittiSequence(kitti06)
    masked_px = 0
    for k in range(N_FRAMES):
        img = ImageDecoder().decode(msgs["/dynastereo/left/masked"][k])
        mask = ImageDecoder().decode(msgs["/dynastereo/left/mask"][k])
        assert mask.shape == (370, 1226) and set(np.unique(mask)) <= {0, 255}
        gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
        assert np.all(gray[mask > 0] == 0)
        assert np.array_equal(gray[mask == 0], seq.frame(k).left[mask == 0])
        masked_px += int(np.count_nonzero(mask))
        d = msgs["/dynastereo/disparity"][k]
        disp = image_to_array(d.image)
        assert disp.dtype == np.float32 and disp.shape == (370, 1226)
        assert np.count_nonzero(disp > 0) > 0.3 * disp.size and np.all((disp > 0) | (disp == -1))
        assert getattr(d, "T", getattr(d, "t", None)) == pytest.approx(seq.calibration.baseline)
        tf = msgs["/tf"][k].transforms[0]
        assert tf.header.frame_id == "odom" and tf.child_frame_id == "camera_left"
        assert header_ns(tf) == ref["stamps_ns"][k]
    assert masked_px > 1000  # KITTI 06 starts beside parked cars: something is masked


def test_folder_run_and_bag_run_give_the_same_trajectory(kitti06: Path, models_dir: Path, tmp_path: Path) -> None:
    """``run`` on a folder and ``run --bag`` on the same frames build their masker the same
    way (the rig's calibration included: with the road line on, its slopes follow the
    baseline, 0.537 m on KITTI 06 against the 0.54 m fallback), so the trajectories agree."""
    from dynastereo.api import run_sequence

    cfg = Config().with_overrides({"masker.outline.ground_removal": True})
    folder = run_sequence(kitti06, tmp_path / "folder", cfg, frames=N_FRAMES, models_dir=models_dir)
    src = export_bag(KittiSequence(kitti06), tmp_path / "in.bag", "ros1", frames=range(N_FRAMES))
    run_bag(src.path, tmp_path / "bag", cfg, models_dir=models_dir)
    a = read_trajectory(tmp_path / "folder" / "trajectory.kitti.txt").poses
    b = read_trajectory(tmp_path / "bag" / "trajectory.kitti.txt").poses
    assert len(a) == len(b) == N_FRAMES and np.abs(a - b).max() < 1e-6
    assert np.linalg.norm(a[-1][:3, 3]) > 0.5  # it moved: the comparison is not between two standstills
    assert folder.frames == list(range(N_FRAMES))
    # the live node builds its masker with the same factory, for the rig it is given
    from dynastereo.ros.core import StereoNodeCore

    calib = KittiSequence(kitti06).calibration
    core = StereoNodeCore(cfg, calibration=calib, models_dir=models_dir)
    try:
        assert core._masker.baseline == pytest.approx(calib.baseline) and abs(calib.baseline - 0.54) > 1e-3
    finally:
        core.shutdown()


def test_cli_export_bag_and_run_bag(kitti06: Path, models_dir: Path, tmp_path: Path) -> None:
    bag = tmp_path / "k06.bag"
    r = runner.invoke(app, ["export-bag", str(kitti06), str(bag), "--frames", "3", "--format", "ros1"])
    assert r.exit_code == 0, r.output
    assert "wrote" in r.output and "/camera/left/camera_info 3" in r.output
    r = runner.invoke(app, ["export-bag", str(kitti06), str(bag), "--frames", "3"])
    assert r.exit_code == 2 and "exists already" in r.output
    r = runner.invoke(app, ["export-bag", str(kitti06), str(tmp_path / "x.db3"), "--format", "mcap"])
    assert r.exit_code == 2 and "must be named *.mcap" in r.output
    out = tmp_path / "run"
    r = runner.invoke(app, ["run", "--bag", str(bag), "--out", str(out), "--bag-outputs", "odometry,tf",
                            "--models-dir", str(models_dir)])
    assert r.exit_code == 0, r.output
    assert "3 stereo pairs" in r.output and "unpaired: 0 left, 0 right" in r.output
    assert set(bag_topics(out / "output.bag")) == {"/dynastereo/odometry", "/tf"}
    assert len(read_trajectory(out / "trajectory.tum.txt")) == 3
    r = runner.invoke(app, ["run", str(kitti06), "--bag", str(bag), "--out", str(out)])
    assert r.exit_code == 2 and "either a SEQUENCE folder or --bag" in r.output
    r = runner.invoke(app, ["run", "--bag", str(bag), "--out", str(out), "--left-topic", "/cam0"])
    assert r.exit_code == 2 and "'/cam0' not in the bag" in r.output
    r = runner.invoke(app, ["run", "--bag", str(bag), "--out", str(out), "--bag-outputs", "odometry,video"])
    assert r.exit_code == 2 and "unknown bag output(s) video" in r.output


@pytest.mark.parametrize("fmt,name", [("ros1", "s.bag"), ("mcap", "s.mcap")])
def test_rviz_topics_path_and_map_points_read_back(tmp_path: Path, fmt: str, name: str) -> None:
    """``/dynastereo/path`` (nav_msgs/Path) grows by one pose per frame and equals the
    odometry; ``/dynastereo/map_points`` (sensor_msgs/PointCloud2, x y z float32) every
    MAP_EVERY-th frame and once more after the final BA, that one the run's map."""
    from dynastereo.ros.messages import MAP_EVERY
    from dynastereo.synth import generate

    n = 12
    seq = generate(tmp_path / "synth", "static", frames=n, seed=0, size=(480, 144))
    src = export_bag(KittiSequence(seq), tmp_path / name, fmt)
    res = run_bag(src.path, tmp_path / "out", Config().with_overrides({"masker.kind": "none"}),
                  outputs="odometry,path,map_points")
    out_bag = res.output_bag
    topics = bag_topics(out_bag)
    assert topics["/dynastereo/path"] == ("nav_msgs/msg/Path", n)
    n_maps = len(range(0, n, MAP_EVERY)) + 1
    assert topics["/dynastereo/map_points"] == ("sensor_msgs/msg/PointCloud2", n_maps)
    stamps, T = read_odometry(out_bag)
    paths = [m for _, _, m in read_messages(out_bag, ["/dynastereo/path"])]
    assert [len(p.poses) for p in paths] == list(range(1, n + 1))
    last = paths[-1]
    assert last.header.frame_id == "odom" and header_ns(last) == stamps[-1]
    pos = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in last.poses])
    assert np.abs(pos - T[:, :3, 3]).max() < 1e-9 and [header_ns(p) for p in last.poses] == stamps.tolist()
    assert np.linalg.norm(pos[-1]) > 1.0  # the rig drove
    clouds = [m for _, _, m in read_messages(out_bag, ["/dynastereo/map_points"])]
    for c in clouds:
        assert c.header.frame_id == "odom" and c.height == 1 and c.point_step == 12 and not c.is_bigendian
        assert [(f.name, f.offset, f.datatype) for f in c.fields] == [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
        assert len(c.data) == 12 * c.width == c.row_step
    xyz = np.frombuffer(bytes(clouds[-1].data), "<f4").reshape(-1, 3)
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert len(xyz) == run["map_points"] > 200 and np.isfinite(xyz).all()
    assert np.median(xyz[:, 2]) > 2.0  # in front of the camera (odom = the first left camera, z forward)
