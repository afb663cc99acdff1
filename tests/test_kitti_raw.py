"""KITTI raw drives as an input format, and colour frames where the stereo pair is colour."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import require
from dynastereo.errors import CalibrationError, SequenceError
from dynastereo.io import (
    FolderSequence,
    KittiRawSequence,
    KittiSequence,
    Sequence,
    detect_format,
    open_sequence,
    read_kitti_raw_timestamps,
)

DRIVE = "2011_09_26_drive_0001_sync"


@pytest.fixture(scope="session")
def raw_drive(data_dir: Path) -> Path:
    return require(data_dir / "kitti_raw/2011_09_26" / DRIVE, "KITTI raw drive 0001")


# --------------------------------------------------------------------------- synthetic drives

W, H = 40, 20
FX = 700.0
# gray pair: baseline 0.5 m; colour pair: P_rect_02[0,3] = +42 (0.06 m left of camera 0),
# P_rect_03[0,3] = -308 (0.44 m right): baseline (42 + 308) / 700 = 0.5 m
P_ROWS = {
    "00": f"{FX} 0 20 0 0 {FX} 10 0 0 0 1 0",
    "01": f"{FX} 0 20 -350 0 {FX} 10 0 0 0 1 0",
    "02": f"{FX} 0 20 42 0 {FX} 10 0.2 0 0 1 0.0027",
    "03": f"{FX} 0 20 -308 0 {FX} 10 2.2 0 0 1 0.0027",
}


def _calib_text(size: tuple[int, int] = (W, H)) -> str:
    lines = ["calib_time: 09-Jan-2012 13:57:47", "corner_dist: 9.950000e-02"]
    for cam, p in P_ROWS.items():
        lines += [f"S_{cam}: 1.392000e+03 5.120000e+02", f"K_{cam}: 9.8e+02 0 690 0 9.8e+02 233 0 0 1",
                  f"S_rect_{cam}: {size[0]:e} {size[1]:e}", f"P_rect_{cam}: {p}"]
    return "\n".join(lines) + "\n"


def _stamps(n: int, start: str = "2011-09-26 13:02:25", step_ns: int = 103_129_856) -> str:
    base = 967_790_592
    out = []
    for i in range(n):
        ns = base + i * step_ns
        sec, frac = divmod(ns, 1_000_000_000)
        hh, mm, ss = start.split(" ")[1].split(":")
        out.append(f"{start.split(' ')[0]} {hh}:{mm}:{int(ss) + sec:02d}.{frac:09d}")
    return "\n".join(out) + "\n"


def make_drive(root: Path, n: int = 3, cams: tuple[str, ...] = ("00", "01"), calib: bool = True,
               date: str = "2011_09_26", drive: str = DRIVE, size: tuple[int, int] = (W, H)) -> Path:
    """A tiny raw drive ``root/date/drive``: PNGs (colour for 02/03), stamps, calib."""
    d = root / date / drive
    rng = np.random.default_rng(0)
    for cam in cams:
        (d / f"image_{cam}" / "data").mkdir(parents=True, exist_ok=True)
        for i in range(n):
            if cam in ("02", "03"):
                img = rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)
            else:
                img = rng.integers(0, 255, (size[1], size[0]), dtype=np.uint8)
            assert cv2.imwrite(str(d / f"image_{cam}" / "data" / f"{i:010d}.png"), img)
        (d / f"image_{cam}" / "timestamps.txt").write_text(_stamps(n))
    if calib:
        (root / date / "calib_cam_to_cam.txt").write_text(_calib_text(size))
    return d


# --------------------------------------------------------------------------- the real drive


def test_real_drive(raw_drive):
    assert detect_format(raw_drive) == "kitti_raw"
    seq = open_sequence(raw_drive)
    assert isinstance(seq, KittiRawSequence) and isinstance(seq, Sequence)
    assert len(seq) == 108 and seq.name == DRIVE
    c = seq.calibration
    assert (c.width, c.height) == (1242, 375)
    assert c.fx == pytest.approx(721.5377) and c.baseline == pytest.approx(0.537, abs=1e-3)
    assert c.baseline == pytest.approx(3.875744e2 / 7.215377e2, rel=1e-12)  # -P_rect_01[0,3] / fx
    assert not seq.color and not seq.uses_colour_pair and seq.cameras == ("00", "01")  # grey only
    ts = seq.timestamps()
    assert ts.dtype == np.float64 and ts.shape == (108,) and ts[0] == 0.0
    dt = np.diff(ts)
    assert np.all(dt > 0) and np.all(np.abs(dt - 0.1) < 0.02)
    # exact nanoseconds: 13:02:26.070920448 - 13:02:25.967790592
    assert seq.timestamps_ns[1] == 103_129_856 and ts[1] == 0.103129856
    f = seq.frame(0)
    assert f.left.shape == (375, 1242) and f.left.dtype == np.uint8 and f.right.shape == f.left.shape
    assert f.left_path.name == "0000000000.png" and f.left_path.parent.parent.name == "image_00"
    assert f.right_path.parent.parent.name == "image_01"
    # the date folder holds this one drive
    assert open_sequence(raw_drive.parent).path == raw_drive
    # no colour pair here: asking for colour says so
    with pytest.raises(SequenceError, match=r"no colour pair image_02/ and image_03/"):
        open_sequence(raw_drive, color=True)


# --------------------------------------------------------------------------- synthetic drives


def test_gray_drive_and_exact_stamps(tmp_path):
    d = make_drive(tmp_path, n=3)
    seq = open_sequence(d)
    assert isinstance(seq, KittiRawSequence) and len(seq) == 3
    assert seq.calibration.baseline == pytest.approx(0.5) and seq.calibration.size == (W, H)
    assert seq.timestamps_ns.tolist() == [0, 103_129_856, 206_259_712]
    assert seq.timestamps()[2] == 0.206259712
    assert seq.frame(2).left.shape == (H, W)
    # stamps indexed by the frame number: a drive holding some images keeps the full file
    (d / "image_00/data/0000000000.png").unlink()
    (d / "image_01/data/0000000000.png").unlink()
    seq = open_sequence(d)
    assert len(seq) == 2 and seq.timestamps_ns.tolist() == [103_129_856, 206_259_712]


def test_colour_pair_read_as_bgr(tmp_path):
    d = make_drive(tmp_path, n=2, cams=("02", "03"))
    seq = open_sequence(d)  # only the colour pair: colour frames
    assert seq.uses_colour_pair and seq.color and seq.cameras == ("02", "03")
    assert seq.calibration.baseline == pytest.approx(0.5)  # (P_rect_02[0,3] - P_rect_03[0,3]) / fx
    f = seq.frame(1)
    assert f.left.shape == (H, W, 3) and f.right.shape == (H, W, 3)
    stored = cv2.imread(str(d / "image_02/data/0000000001.png"), cv2.IMREAD_COLOR)
    assert np.array_equal(f.left, stored)
    assert f.left_gray.shape == (H, W) and f.right_gray.shape == (H, W)
    assert np.array_equal(f.left_gray, cv2.cvtColor(stored, cv2.COLOR_BGR2GRAY))
    # color=False: the same pair, gray frames
    g = open_sequence(d, color=False)
    assert g.uses_colour_pair and not g.color and g.frame(0).left.shape == (H, W)


def test_both_pairs_prefer_gray(tmp_path):
    d = make_drive(tmp_path, n=2, cams=("00", "01", "02", "03"))
    seq = open_sequence(d)
    assert not seq.uses_colour_pair and not seq.color and seq.frame(0).left.ndim == 2
    assert seq.frame(0).left_path.parent.parent.name == "image_00"
    col = open_sequence(d, color=True)
    assert col.uses_colour_pair and col.color and col.frame(0).left.shape == (H, W, 3)
    assert col.frame(0).left_path.parent.parent.name == "image_02"


def test_non_monotonic_timestamps_name_the_file(tmp_path):
    d = make_drive(tmp_path, n=3)
    p = d / "image_00/timestamps.txt"
    lines = p.read_text().splitlines()
    p.write_text("\n".join([lines[0], lines[2], lines[1]]) + "\n")
    with pytest.raises(SequenceError, match=r"image_00/timestamps.txt: line 3: .* is before line 2's") as ei:
        open_sequence(d)
    assert ei.value.path == p and "\n" not in str(ei.value)
    p.write_text("\n".join([lines[0], lines[0], lines[2]]) + "\n")
    with pytest.raises(SequenceError, match=r"line 2: .* equals line 1's"):
        read_kitti_raw_timestamps(p)
    p.write_text("\n".join([lines[0], "2011-09-26 13:02:26", "yesterday"]) + "\n")
    with pytest.raises(SequenceError, match=r"timestamps.txt: line 3: 'yesterday' is not a timestamp"):
        open_sequence(d)
    p.write_text(lines[0] + "\n")
    with pytest.raises(SequenceError, match=r"timestamps.txt: 1 timestamps, but the images go up to frame 2"):
        open_sequence(d)
    # the right camera's file is checked too
    p.write_text("\n".join(lines) + "\n")
    q = d / "image_01/timestamps.txt"
    q.write_text("\n".join([lines[1], lines[0], lines[2]]) + "\n")
    with pytest.raises(SequenceError, match=r"image_01/timestamps.txt: line 2"):
        open_sequence(d)
    q.unlink()
    (d / "image_00/timestamps.txt").unlink()
    with pytest.raises(SequenceError, match=r"image_00/timestamps.txt: timestamps file not found"):
        open_sequence(d)


def test_missing_calib(tmp_path):
    d = make_drive(tmp_path, n=2, calib=False)
    assert detect_format(d) == "kitti_raw"
    with pytest.raises(CalibrationError, match=r"2011_09_26/calib_cam_to_cam.txt: calibration file not found") as ei:
        open_sequence(d)
    assert ei.value.path == d.parent / "calib_cam_to_cam.txt"
    # an explicit YAML stands in for it
    y = tmp_path / "my.yaml"
    y.write_text("fx: 100\ncx: 20\ncy: 10\nbaseline: 0.3\n")
    assert open_sequence(d, calib=y).calibration.baseline == pytest.approx(0.3)


def test_calib_rows_missing(tmp_path):
    d = make_drive(tmp_path, n=2)
    c = d.parent / "calib_cam_to_cam.txt"
    c.write_text("\n".join(l for l in c.read_text().splitlines() if not l.startswith("P_rect_01")) + "\n")
    with pytest.raises(CalibrationError, match=r"calib_cam_to_cam.txt: no row 'P_rect_01:' .*gray pair.*"
                                                r"rows found: P_rect_00, P_rect_02, P_rect_03$"):
        open_sequence(d)


def test_s_rect_size_mismatch(tmp_path):
    d = make_drive(tmp_path, n=2)
    (d.parent / "calib_cam_to_cam.txt").write_text(_calib_text(size=(1242, 375)))
    with pytest.raises(CalibrationError, match=r"calib_cam_to_cam.txt: row 'S_rect_00' gives the rectified size "
                                                r"1242x375, the images \(.*image_00/data/0000000000.png\) are 40x20"):
        open_sequence(d)
    # images of the raw (unrectified) size: said so
    d2 = make_drive(tmp_path / "x", n=1, size=(1392, 512))
    (d2.parent / "calib_cam_to_cam.txt").write_text(_calib_text(size=(1242, 375)))
    with pytest.raises(CalibrationError, match=r"unrectified size S_00"):
        open_sequence(d2)


def test_date_folder(tmp_path):
    d = make_drive(tmp_path, n=2)
    date = d.parent
    assert detect_format(date) == "kitti_raw"
    seq = open_sequence(date)
    assert seq.path == d and seq.name == DRIVE and len(seq) == 2
    assert KittiRawSequence(date).path == d
    make_drive(tmp_path, n=2, drive="2011_09_26_drive_0002_sync")
    with pytest.raises(SequenceError, match=r"2011_09_26: KITTI raw date folder with 2 drives "
                                            r"\(2011_09_26_drive_0001_sync, 2011_09_26_drive_0002_sync\)"):
        open_sequence(date)
    empty = tmp_path / "2011_10_03"
    empty.mkdir()
    (empty / "calib_cam_to_cam.txt").write_text(_calib_text())
    with pytest.raises(SequenceError, match=r"KITTI raw date folder \(calib_cam_to_cam.txt\) without a drive"):
        open_sequence(empty)


def test_count_and_name_mismatch(tmp_path):
    d = make_drive(tmp_path, n=3)
    (d / "image_01/data/0000000002.png").unlink()
    with pytest.raises(SequenceError, match=r"3 in .*image_00/data, 2 in .*image_01/data"):
        open_sequence(d)
    (d / "image_00/data/0000000001.png").unlink()  # left 0, 2 against right 0, 1
    with pytest.raises(SequenceError, match=r"file names differ"):
        open_sequence(d)


# --------------------------------------------------------------------------- colour elsewhere


def _kitti_odometry(root: Path, pairs: tuple[str, ...]) -> Path:
    rng = np.random.default_rng(1)
    for cam in pairs:
        (root / cam).mkdir(parents=True, exist_ok=True)
        for i in range(2):
            colour = cam in ("image_2", "image_3")
            img = rng.integers(0, 255, (H, W, 3) if colour else (H, W), dtype=np.uint8)
            assert cv2.imwrite(str(root / cam / f"{i:06d}.png"), img)
    rows = ["P0: 700 0 20 0 0 700 10 0 0 0 1 0", "P1: 700 0 20 -350 0 700 10 0 0 0 1 0",
            "P2: 700 0 20 42 0 700 10 0 0 0 1 0", "P3: 700 0 20 -308 0 700 10 0 0 0 1 0"]
    (root / "calib.txt").write_text("\n".join(rows) + "\n")
    return root


def test_kitti_odometry_colour_auto(tmp_path):
    only = _kitti_odometry(tmp_path / "a", ("image_2", "image_3"))
    seq = open_sequence(only)
    assert isinstance(seq, KittiSequence) and seq.color and seq.frame(0).left.shape == (H, W, 3)
    assert open_sequence(only, color=False).frame(0).left.shape == (H, W)
    both = _kitti_odometry(tmp_path / "b", ("image_0", "image_1", "image_2", "image_3"))
    seq = open_sequence(both)
    assert not seq.uses_colour_pair and not seq.color and seq.frame(0).left.shape == (H, W)
    assert open_sequence(both, color=True).frame(0).left.shape == (H, W, 3)


def test_folder_colour_auto(tmp_path):
    root = tmp_path / "mine"
    rng = np.random.default_rng(2)
    for side in ("left", "right"):
        (root / side).mkdir(parents=True)
        for i in range(2):
            assert cv2.imwrite(str(root / side / f"{i}.png"), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
    (root / "calib.yaml").write_text("fx: 60\ncx: 20\ncy: 10\nbaseline: 0.1\n")
    seq = open_sequence(root)
    assert isinstance(seq, FolderSequence) and seq.color and seq.frame(0).left.shape == (H, W, 3)
    assert open_sequence(root, color=False).frame(0).left.shape == (H, W)
    # gray content stored as RGB PNGs: gray frames
    for side in ("left", "right"):
        for i in range(2):
            g = rng.integers(0, 255, (H, W), dtype=np.uint8)
            assert cv2.imwrite(str(root / side / f"{i}.png"), cv2.cvtColor(g, cv2.COLOR_GRAY2BGR))
    assert not open_sequence(root).color


def test_detector_sees_colour_slam_gray(tmp_path):
    """The masker hands the detector ``frame.left`` (BGR here) and the matcher gray images."""
    from dynastereo.config import Config
    from dynastereo.masking import build_masker
    from dynastereo.datatypes import Detections

    d = make_drive(tmp_path, n=1, cams=("02", "03"), size=(256, 64))
    frame = open_sequence(d).frame(0)
    assert frame.left.shape == (64, 256, 3)
    seen = []

    class Spy:
        class_names = ("car",)

        def detect(self, img):
            seen.append(img.shape)
            return Detections.empty(self.class_names)

    masker = build_masker(Config(), detector=Spy(), full_disparity=True)  # the matcher runs on the gray pair
    masks = masker.mask(frame)
    assert seen == [(64, 256, 3)] and masks.left.shape == (64, 256)
    assert masks.disparity is not None and masks.disparity.shape == (64, 256)


# --------------------------------------------------------------------------- OXTS ground truth


def _independent_oxts_poses(drive: Path) -> np.ndarray:
    """KITTI raw devkit's convertOxtsToPose + pykitti's camera chain, written out frame by frame
    with scipy's Euler angles (independent of dynastereo.io.kitti_raw)."""
    from scipy.spatial.transform import Rotation

    def rigid(path: Path) -> np.ndarray:
        vals = {ln.split(":")[0]: ln.split(":", 1)[1].split() for ln in path.read_text().splitlines() if ":" in ln}
        T = np.eye(4)
        T[:3, :3] = np.array(vals["R"], float).reshape(3, 3)
        T[:3, 3] = np.array(vals["T"], float)
        return T

    date = drive.parent
    cam_text = (date / "calib_cam_to_cam.txt").read_text().splitlines()
    cam = {ln.split(":")[0]: ln.split(":", 1)[1].split() for ln in cam_text}
    R_rect = np.eye(4)
    R_rect[:3, :3] = np.array(cam["R_rect_00"], float).reshape(3, 3)
    T_imu_to_cam = R_rect @ rigid(date / "calib_velo_to_cam.txt") @ rigid(date / "calib_imu_to_velo.txt")
    files = sorted((drive / "oxts" / "data").glob("*.txt"))
    poses, scale, origin = [], None, None
    for f in files:
        lat, lon, alt, roll, pitch, yaw = (float(v) for v in f.read_text().split()[:6])
        if scale is None:
            scale = np.cos(lat * np.pi / 180.0)
        t = np.array([scale * lon * np.pi * 6378137.0 / 180.0,
                      scale * 6378137.0 * np.log(np.tan((90.0 + lat) * np.pi / 360.0)), alt])
        if origin is None:
            origin = t
        T_w_imu = np.eye(4)
        T_w_imu[:3, :3] = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()  # Rz @ Ry @ Rx
        T_w_imu[:3, 3] = t - origin
        poses.append(T_w_imu @ np.linalg.inv(T_imu_to_cam))
    first_inv = np.linalg.inv(poses[0])
    return np.array([first_inv @ P for P in poses])


def test_oxts_ground_truth_real_drive(raw_drive, tmp_path):
    from dynastereo.api import ground_truth
    from dynastereo.eval.trajectory import find_ground_truth, read_trajectory
    from dynastereo.io.kitti_raw import kitti_raw_ground_truth

    g = kitti_raw_ground_truth(raw_drive, at="packets")
    ref = _independent_oxts_poses(raw_drive)
    assert g.poses.shape == (108, 4, 4) and g.at == "packets"
    assert np.array_equal(g.poses[0], np.eye(4))
    assert np.abs(g.poses - ref).max() < 1e-9
    steps = np.linalg.norm(np.diff(g.poses[:, :3, 3], axis=0), axis=1)
    assert steps.sum() == pytest.approx(107.0, abs=1.0)
    # camera 0 looks forward: the drive goes along +z, with little sideways or vertical motion
    end = g.poses[-1, :3, 3]
    assert end[2] > 100 and abs(end[1]) < 2
    # speeds agree with the packets' own velocity (vf, vl, vu) over the packets' own stamps
    t = (g.oxts_stamps_ns - g.oxts_stamps_ns[0]) * 1e-9
    v_pos = np.linalg.norm(g.poses[2:, :3, 3] - g.poses[:-2, :3, 3], axis=1) / (t[2:] - t[:-2])
    v_oxts = np.linalg.norm(np.column_stack([g.field("vf"), g.field("vl"), g.field("vu")]), axis=1)[1:-1]
    assert np.median(np.abs(v_pos - v_oxts)) < 0.1 and np.abs(v_pos - v_oxts).max() < 0.3
    assert 8 < np.median(v_pos) < 12
    # the stamps are the frames' (as a run's trajectory.tum.txt), 10 Hz
    assert g.stamp_source == "image_00/timestamps.txt" and g.timestamps[0] == 0.0
    assert g.timestamps[1] == pytest.approx(0.103129856) and np.all(np.abs(np.diff(g.timestamps) - 0.1) < 0.02)
    # found by the one rule, read as a trajectory (at the images' stamps), and from the API
    assert find_ground_truth(raw_drive) == raw_drive / "oxts"
    gi = kitti_raw_ground_truth(raw_drive)
    tr = read_trajectory(raw_drive)
    assert gi.at == "images" and np.abs(tr.poses - gi.poses).max() == 0 and tr.timestamps is not None
    assert ground_truth(raw_drive).path_length == pytest.approx(tr.path_length)
    assert np.abs(ground_truth(raw_drive, at="packets").poses - g.poses).max() == 0


def test_oxts_ground_truth_at_the_images_stamps(raw_drive):
    """The packets are up to +-4.7 ms off their images: each pose moved to its image's stamp
    agrees with an independent interpolation (positions linear, rotations slerp) of the
    devkit's poses between neighbouring packets, and the saw-tooth that the offsets put into
    the frame-to-frame speeds is gone."""
    from scipy.spatial.transform import Rotation, Slerp

    from dynastereo.io.kitti_raw import kitti_raw_ground_truth, read_kitti_raw_timestamps

    ref = _independent_oxts_poses(raw_drive)  # at the packets' stamps
    g = kitti_raw_ground_truth(raw_drive)
    t_ox = (g.oxts_stamps_ns - g.oxts_stamps_ns[0]) * 1e-9
    t_im = (read_kitti_raw_timestamps(raw_drive / "image_00" / "timestamps.txt")[:108] - g.oxts_stamps_ns[0]) * 1e-9
    off = t_im - t_ox
    assert 0.002 < np.abs(off).max() < 0.006 and off[0] == pytest.approx(0.0034, abs=1e-4)
    inner = slice(1, 107)  # interpolation needs a packet on both sides
    P = np.tile(np.eye(4), (108, 1, 1))
    P[inner, :3, 3] = np.column_stack([np.interp(t_im[inner], t_ox, ref[:, k, 3]) for k in range(3)])
    P[inner, :3, :3] = Slerp(t_ox, Rotation.from_matrix(ref[:, :3, :3]))(t_im[inner]).as_matrix()
    P0 = np.eye(4)  # frame 0 (3.4 ms after its packet) from packets 0 and 1
    P0[:3, 3] = ref[0, :3, 3] + (ref[1, :3, 3] - ref[0, :3, 3]) * off[0] / (t_ox[1] - t_ox[0])
    P0[:3, :3] = Slerp(t_ox[:2], Rotation.from_matrix(ref[:2, :3, :3]))(t_im[:1]).as_matrix()[0]
    P = np.linalg.inv(P0) @ P
    assert np.abs(g.poses[inner, :3, 3] - P[inner, :3, 3]).max() < 0.01  # the shifts: up to 6 cm
    rot = Rotation.from_matrix(np.transpose(g.poses[inner, :3, :3], (0, 2, 1)) @ P[inner, :3, :3]).magnitude()
    assert np.degrees(rot).max() < 0.01
    # frame-to-frame speeds over the images' stamps: smooth now, saw-toothed at the packets'
    def jitter(poses):
        v = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) / np.diff(t_im)
        return np.median(np.abs(np.diff(v)))
    assert jitter(g.poses) < 0.15 < 0.5 < jitter(ref)  # m/s: 0.085 and 0.69


def test_gt_command_writes_kitti_and_tum(raw_drive, tmp_path):
    from typer.testing import CliRunner

    from dynastereo.cli.main import app
    from dynastereo.eval.trajectory import read_trajectory

    out = tmp_path / "poses.txt"
    r = CliRunner().invoke(app, ["gt", str(raw_drive), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "108 poses" in r.output
    k, t = read_trajectory(out), read_trajectory(tmp_path / "poses.tum.txt")
    assert len(k) == len(t) == 108 and k.timestamps is None and t.timestamps[1] == pytest.approx(0.103129856)
    assert np.abs(k.poses - t.poses).max() < 1e-6 and k.path_length == pytest.approx(106.9, abs=0.5)
    # the devkit's poses at the packets' stamps: up to a packet's offset (4.7 ms, 6 cm) apart
    r = CliRunner().invoke(app, ["gt", str(raw_drive), "--out", str(tmp_path / "dev.txt"), "--at", "packets"])
    assert r.exit_code == 0, r.output
    moved = np.abs(read_trajectory(tmp_path / "dev.txt").poses[:, :3, 3] - k.poses[:, :3, 3]).max()
    assert 0.03 < moved < 0.15
    r = CliRunner().invoke(app, ["gt", str(raw_drive), "--out", str(tmp_path / "x.txt"), "--at", "gps"])
    assert r.exit_code == 2 and "--at: 'gps' is not one of images, packets" in r.output
    # `eval` without a ground truth finds the run's sequence's own (run.json beside the estimate)
    (tmp_path / "run.json").write_text(json.dumps({"sequence": str(raw_drive)}))
    r = CliRunner().invoke(app, ["eval", str(out), "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.output[r.output.index("{"):])
    assert d["ape.rmse"] < 1e-6 and d["drift_percent"] < 1e-6
    (tmp_path / "run.json").write_text(json.dumps({"sequence": str(tmp_path)}))
    r = CliRunner().invoke(app, ["eval", str(out)])
    assert r.exit_code == 2 and "no ground truth given, and none found" in r.output


def test_bench_and_report_find_oxts(raw_drive):
    from dynastereo.bench.discover import discover
    from dynastereo.eval.trajectory import find_ground_truth

    seqs = discover(raw_drive.parent.parent)
    assert [s.ground_truth for s in seqs] == [raw_drive / "oxts"]
    assert find_ground_truth(raw_drive) == raw_drive / "oxts"


def _oxts_drive(tmp_path: Path, n: int = 3) -> Path:
    d = make_drive(tmp_path, n=n)
    date = d.parent
    (date / "calib_cam_to_cam.txt").write_text(_calib_text() + "R_rect_00: 1 0 0 0 1 0 0 0 1\n")
    (date / "calib_imu_to_velo.txt").write_text("calib_time: x\nR: 1 0 0 0 1 0 0 0 1\nT: -0.8 0.3 -0.8\n")
    # velodyne (x fwd, y left, z up) -> camera (x right, y down, z fwd)
    (date / "calib_velo_to_cam.txt").write_text("calib_time: x\nR: 0 -1 0 0 0 -1 1 0 0\nT: 0 -0.07 -0.27\n")
    (d / "oxts" / "data").mkdir(parents=True)
    for i in range(n):  # due east at 1 m per frame (yaw 0 = east): camera moves along +z
        lon = 8.0 + i / (6378137.0 * np.pi / 180.0 * np.cos(np.deg2rad(49.0)))
        vals = [49.0, lon, 100.0, 0, 0, 0] + [0.0] * 24
        (d / "oxts" / "data" / f"{i:010d}.txt").write_text(" ".join(map(str, vals)) + "\n")
    (d / "oxts" / "timestamps.txt").write_text(_stamps(n))
    return d


def test_oxts_synthetic_drive_and_errors(tmp_path):
    from dynastereo.eval.trajectory import read_trajectory
    from dynastereo.io.kitti_raw import kitti_raw_ground_truth

    d = _oxts_drive(tmp_path)
    g = kitti_raw_ground_truth(d)
    assert np.allclose(g.poses[:, :3, 3], [[0, 0, 0], [0, 0, 1], [0, 0, 2]], atol=1e-6)
    assert np.allclose(g.poses[:, :3, :3], np.eye(3), atol=1e-9)
    # a malformed packet names its file
    bad = d / "oxts" / "data" / "0000000001.txt"
    bad.write_text("49.0 8.0 oops\n")
    with pytest.raises(SequenceError, match=r"0000000001\.txt: OXTS packet has 3 numbers, expected 30"):
        kitti_raw_ground_truth(d)
    bad.write_text(" ".join(["49.0", "x"] + ["0"] * 28) + "\n")
    with pytest.raises(SequenceError, match=r"0000000001\.txt: OXTS packet: 'x' is not a number"):
        read_trajectory(d)
    # a missing packet: the gap is named
    bad.unlink()
    with pytest.raises(SequenceError, match=r"OXTS packet 0000000001\.txt missing"):
        kitti_raw_ground_truth(d)
    # a missing calibration file is named
    d2 = _oxts_drive(tmp_path / "b")
    (d2.parent / "calib_imu_to_velo.txt").unlink()
    with pytest.raises(CalibrationError, match=r"calib_imu_to_velo\.txt: calibration file not found"):
        kitti_raw_ground_truth(d2)
    (d2.parent / "calib_imu_to_velo.txt").write_text("R: 1 0 0\nT: 0 0 0\n")
    with pytest.raises(CalibrationError, match=r"calib_imu_to_velo\.txt: row 'R:' has 3 numbers"):
        kitti_raw_ground_truth(d2)
