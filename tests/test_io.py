"""Input layer: images, disparity files, frame specs, calibration, rectification, sequences."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import require
from dynastereo.errors import CalibrationError, ImageReadError, InputError, SequenceError
from dynastereo.io import (
    EurocSequence,
    FolderSequence,
    KittiSequence,
    RawStereoCalibration,
    Rectifier,
    Sequence,
    load_euroc_calib,
    load_kitti_calib,
    load_middlebury_calib,
    load_orbslam2_settings,
    load_stereo_yaml,
    open_sequence,
    pair_by_timestamp,
    parse_frame_spec,
    read_disparity_png,
    read_image,
    read_pfm,
    write_disparity_png,
    write_pfm,
)
from dynastereo.datatypes import StereoCalibration

# --------------------------------------------------------------------------- helpers

P0 = "P0: 7.0e+02 0 3.0e+01 0 0 7.0e+02 1.2e+01 0 0 0 1 0"
P1 = "P1: 7.0e+02 0 3.0e+01 -3.5e+02 0 7.0e+02 1.2e+01 0 0 0 1 0"  # baseline 0.5 m


def _png(path: Path, w: int = 48, h: int = 24, seed: int = 0) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.random.default_rng(seed).integers(0, 255, (h, w), dtype=np.uint8)
    assert cv2.imwrite(str(path), img)


def make_kitti(root: Path, n: int = 3, calib: str | None = f"{P0}\n{P1}\n", times: bool = False) -> Path:
    for i in range(n):
        _png(root / "image_0" / f"{i:06d}.png", seed=i)
        _png(root / "image_1" / f"{i:06d}.png", seed=100 + i)
    if calib is not None:
        (root / "calib.txt").write_text(calib)
    if times:
        (root / "times.txt").write_text("\n".join(f"{0.25 * i:e}" for i in range(n + 2)) + "\n")
    return root


def row_error(left: np.ndarray, right: np.ndarray) -> tuple[float, float, int]:
    """Median and 90th percentile |y_left - y_right| of ORB matches (F-RANSAC inliers)."""
    orb = cv2.ORB_create(1500)
    kl, dl = orb.detectAndCompute(left, None)
    kr, dr = orb.detectAndCompute(right, None)
    m = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr)
    pl = np.float32([kl[x.queryIdx].pt for x in m])
    pr = np.float32([kr[x.trainIdx].pt for x in m])
    # outlier removal that does not assume rectification (a fundamental matrix fits both)
    _, inl = cv2.findFundamentalMat(pl, pr, cv2.FM_RANSAC, 1.0, 0.999)
    inl = inl.ravel().astype(bool)
    dy = np.abs(pl[inl, 1] - pr[inl, 1])
    return float(np.median(dy)), float(np.percentile(dy, 90)), int(inl.sum())


# ORB-SLAM2's Examples/Stereo/EuRoC.yaml (calibration part, with its OpenCV-YAML quirks:
# "data:[" without a space, "Viewer.PointSize:2").
ORBSLAM2_EUROC = """%YAML:1.0
Camera.type: "PinHole"
Camera.fx: 435.2046959714599
Camera.fy: 435.2046959714599
Camera.cx: 367.4517211914062
Camera.cy: 252.2008514404297
Camera.k1: 0.0
Camera.k2: 0.0
Camera.p1: 0.0
Camera.p2: 0.0
Camera.width: 752
Camera.height: 480
Camera.fps: 20.0
Camera.bf: 47.90639384423901
Camera.RGB: 1
ThDepth: 35.0
LEFT.height: 480
LEFT.width: 752
LEFT.D: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data:[-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0]
LEFT.K: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [458.654, 0.0, 367.215, 0.0, 457.296, 248.375, 0.0, 0.0, 1.0]
LEFT.R:  !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [0.999966347530033, -0.001422739138722922, 0.008079580483432283, 0.001365741834644127, 0.9999741760894847, 0.007055629199258132, -0.008089410156878961, -0.007044357138835809, 0.9999424675829176]
LEFT.P:  !!opencv-matrix
   rows: 3
   cols: 4
   dt: d
   data: [435.2046959714599, 0, 367.4517211914062, 0,  0, 435.2046959714599, 252.2008514404297, 0,  0, 0, 1, 0]
RIGHT.height: 480
RIGHT.width: 752
RIGHT.D: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data:[-0.28368365, 0.07451284, -0.00010473, -3.555907e-05, 0.0]
RIGHT.K: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [457.587, 0.0, 379.999, 0.0, 456.134, 255.238, 0.0, 0.0, 1]
RIGHT.R:  !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [0.9999633526194376, -0.003625811871560086, 0.007755443660172947, 0.003680398547259526, 0.9999684752771629, -0.007035845251224894, -0.007729688520722713, 0.007064130529506649, 0.999945173484644]
RIGHT.P:  !!opencv-matrix
   rows: 3
   cols: 4
   dt: d
   data: [435.2046959714599, 0, 367.4517211914062, -47.90639384423901, 0, 435.2046959714599, 252.2008514404297, 0, 0, 0, 1, 0]
ORBextractor.nFeatures: 1200
ORBextractor.scaleFactor: 1.2
ORBextractor.nLevels: 8
ORBextractor.iniThFAST: 20
ORBextractor.minThFAST: 7
Viewer.PointSize:2
"""

# ORB-SLAM2's KITTI04-12.yaml, calibration part (rectified images; its width/height are
# not those of every sequence it is used for -- ORB-SLAM2 takes the images' size).
ORBSLAM2_KITTI = """%YAML:1.0
Camera.fx: 707.0912
Camera.fy: 707.0912
Camera.cx: 601.8873
Camera.cy: 183.1104
Camera.width: 1241
Camera.height: 376
Camera.bf: 379.8145
ThDepth: 40.0
ORBextractor.nFeatures: 2000
"""

# --------------------------------------------------------------------------- images / disparity


def test_read_image_gray_and_color(tmp_path):
    img = np.random.default_rng(1).integers(0, 255, (20, 30, 3), dtype=np.uint8)
    p = tmp_path / "c.png"
    cv2.imwrite(str(p), img)
    c = read_image(p, color=True)
    g = read_image(p, color=False)
    assert c.shape == (20, 30, 3) and c.dtype == np.uint8 and np.array_equal(c, img)
    assert g.shape == (20, 30) and g.dtype == np.uint8
    assert np.abs(g.astype(int) - cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(int)).max() <= 1


def test_read_image_errors_name_the_file(tmp_path):
    with pytest.raises(ImageReadError, match="nope.png.*not found"):
        read_image(tmp_path / "nope.png")
    bad = tmp_path / "garbage.png"
    bad.write_bytes(b"this is not an image at all")
    with pytest.raises(ImageReadError, match="garbage.png.*cannot decode") as ei:
        read_image(bad)
    assert ei.value.path == bad


def test_disparity_png_roundtrip_kitti_convention(tmp_path):
    d = np.array([[0.0, -3.0, 1.5, 255.99], [np.nan, np.inf, 0.001, 42.25]], np.float32)
    p = tmp_path / "d.png"
    write_disparity_png(p, d)
    raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    assert raw.tolist() == [[0, 0, 384, 65533], [0, 0, 1, 10816]]  # d*256, 0 = invalid
    back = read_disparity_png(p)
    assert back.dtype == np.float32
    valid = np.isfinite(d) & (d > 0)
    assert np.all(back[~valid] == 0) and np.all(back[valid] > 0)
    assert np.allclose(back[valid], d[valid], atol=1 / 256)
    # an 8-bit PNG is not a KITTI disparity map
    cv2.imwrite(str(tmp_path / "u8.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(ImageReadError, match="u8.png.*16-bit"):
        read_disparity_png(tmp_path / "u8.png")


def test_pfm_roundtrip_and_inf_invalid(tmp_path):
    a = np.arange(12, dtype=np.float32).reshape(3, 4) + 0.5
    a[0, 0] = np.inf
    write_pfm(tmp_path / "a.pfm", a)
    b = read_pfm(tmp_path / "a.pfm")
    assert b.shape == (3, 4) and b.dtype == np.float32
    assert b[0, 0] == 0  # inf -> invalid
    assert np.array_equal(b.ravel()[1:], a.ravel()[1:])  # top row first after the flip
    (tmp_path / "bad.pfm").write_bytes(b"P6\n3 3\n255\n")
    with pytest.raises(ImageReadError, match="bad.pfm.*not a PFM"):
        read_pfm(tmp_path / "bad.pfm")
    (tmp_path / "short.pfm").write_bytes(b"Pf\n4 3\n-1.0\n" + b"\0" * 20)
    with pytest.raises(ImageReadError, match="short.pfm.*truncated"):
        read_pfm(tmp_path / "short.pfm")


def test_real_ground_truth_files(data_dir):
    mb = require(data_dir / "middlebury2014/trainingQ/Motorcycle", "Middlebury Motorcycle")
    gt = read_pfm(mb / "disp0GT.pfm")
    cal = load_middlebury_calib(mb / "calib.txt")
    assert gt.shape == (cal.calibration.height, cal.calibration.width) == (497, 741)
    valid = gt > 0
    assert 0.5 < valid.mean() < 1.0  # Middlebury marks unknown pixels inf -> 0
    # the file says disparities lie within vmin..vmax (quarter resolution: 7..65)
    assert np.percentile(gt[valid], 1) >= cal.vmin - 1 and np.percentile(gt[valid], 99) <= cal.vmax + 1
    assert cal.calibration.baseline == pytest.approx(0.193001) and cal.doffs == pytest.approx(32.778)
    # non-occluded mask agrees with the ground truth's valid pixels
    nocc = cv2.imread(str(mb / "mask0nocc.png"), cv2.IMREAD_GRAYSCALE) == 255
    assert valid[nocc].mean() > 0.99

    k15 = require(data_dir / "kitti_stereo2015/training", "KITTI stereo 2015")
    d = read_disparity_png(k15 / "disp_occ_0/000046_10.png")
    assert d.shape == (375, 1242)
    assert 0.1 < (d > 0).mean() < 0.6 and 1 < d.max() < 256


# --------------------------------------------------------------------------- frame specs


def test_frame_spec():
    assert parse_frame_spec(None, 5) == [0, 1, 2, 3, 4]
    assert parse_frame_spec("all", 3) == [0, 1, 2]
    assert parse_frame_spec("3", 10) == [0, 1, 2]
    assert parse_frame_spec(4, 10) == [0, 1, 2, 3]
    assert parse_frame_spec("2-4, 7", 10) == [2, 3, 4, 7]
    assert parse_frame_spec("8-", 10) == [8, 9]
    # revisit kept in the given order, with repeats
    spec = parse_frame_spec("0-98,40-60", 99)
    assert spec == list(range(99)) + list(range(40, 61))
    assert parse_frame_spec("5-5,1-2,5-5", 10) == [5, 1, 2, 5]


@pytest.mark.parametrize(
    "spec, pattern",
    [
        ("0-99", "out of range.*99 frames"),
        ("100", "only 99"),
        (200, "only 99"),
        ("0", "positive"),
        ("5-2", "reversed"),
        ("1-3,x", "malformed.*'x'"),
        ("1-3,", "malformed"),
        ("-3", "malformed"),
        ("1.5", "malformed"),
        ("", "empty"),
        (True, "frame spec"),
    ],
)
def test_frame_spec_errors(spec, pattern):
    with pytest.raises(InputError, match=pattern):
        parse_frame_spec(spec, 99)


# --------------------------------------------------------------------------- KITTI


def test_kitti03_real(kitti03):
    seq = open_sequence(kitti03)
    assert isinstance(seq, KittiSequence) and isinstance(seq, Sequence)
    assert len(seq) == 99 and seq.name == "03"
    c = seq.calibration
    assert (c.width, c.height) == (1242, 375)
    assert c.fx == pytest.approx(721.5377) and c.cx == pytest.approx(609.5593) and c.cy == pytest.approx(172.854)
    assert c.baseline == pytest.approx(387.5744 / 721.5377, rel=1e-9) and 0.53 < c.baseline < 0.55
    ts = seq.timestamps()  # no times.txt: 10 Hz
    assert ts.shape == (99,) and np.allclose(np.diff(ts), 0.1) and ts[0] == 0
    f = seq.frame(98)
    assert f.index == 98 and f.left.shape == (375, 1242) and f.left.dtype == np.uint8 and f.right.shape == f.left.shape
    assert f.left_path.name == "000098.png" and f.right_path.parent.name == "image_1"
    assert seq.frame(-1).index == 98
    with pytest.raises(IndexError):
        seq.frame(99)
    # the colour pair P2/P3 of this calib.txt (its images are not here)
    cc = load_kitti_calib(kitti03 / "calib.txt", (1242, 375), color=True)
    assert cc.baseline == pytest.approx((44.85728 + 339.5242) / 721.5377)
    with pytest.raises(SequenceError, match="image_2/ and image_3/"):
        KittiSequence(kitti03, color=True)


def test_kitti06_real(kitti06):
    seq = open_sequence(kitti06)
    assert len(seq) == 51
    c = seq.calibration
    assert (c.width, c.height) == (1226, 370)
    assert c.fx == pytest.approx(707.0912) and c.baseline == pytest.approx(379.8145 / 707.0912)
    assert c.bf == pytest.approx(379.8145)
    ts = seq.timestamps()
    assert ts.shape == (51,) and ts[1] == pytest.approx(0.1044989) and np.all(np.diff(ts) > 0.09)
    frames = list(seq.frames([50, 0]))
    assert [f.index for f in frames] == [50, 0] and frames[0].timestamp == pytest.approx(ts[50])
    # only P0/P1 in this calib.txt: the colour pair cannot be calibrated, and the error says why
    with pytest.raises(CalibrationError, match=r"calib.txt: no row 'P2:'.*rows found: P0, P1"):
        load_kitti_calib(kitti06 / "calib.txt", (1226, 370), color=True)


def test_kitti_object_calib_extra_rows(data_dir):
    p = require(data_dir / "kitti_object_pair/calib.txt", "KITTI object pair")
    c = load_kitti_calib(p, (1242, 375), color=True)  # R0_rect / Tr_* rows are ignored
    assert c.fx == pytest.approx(721.5377) and c.baseline == pytest.approx(0.5327, abs=1e-3)
    g = load_kitti_calib(p, (1242, 375))
    assert g.baseline == pytest.approx(387.5744 / 721.5377)


def test_kitti_synthetic_times_and_override(tmp_path):
    root = make_kitti(tmp_path / "seq", n=3, times=True)
    seq = open_sequence(root)
    assert len(seq) == 3 and seq.calibration.baseline == pytest.approx(0.5)
    assert seq.timestamps().tolist() == [0.0, 0.25, 0.5]  # times.txt may hold more rows than frames
    (root / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(SequenceError, match="times.txt.*2 timestamps"):
        open_sequence(root)
    (root / "times.txt").unlink()
    # an explicit YAML replaces calib.txt
    y = tmp_path / "my.yaml"
    y.write_text("fx: 100\ncx: 24\ncy: 12\nbaseline: 0.2\n")
    seq = open_sequence(root, calib=y)
    assert seq.calibration.fx == 100 and seq.calibration.baseline == pytest.approx(0.2)
    assert seq.calibration.size == (48, 24)


def test_kitti_colour_pair_only(tmp_path):
    root = tmp_path / "seq"
    for i in range(2):
        img = np.random.default_rng(i).integers(0, 255, (24, 48, 3), dtype=np.uint8)
        for side in ("image_2", "image_3"):
            (root / side).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / side / f"{i:06d}.png"), img)
    p2 = "P2: 7.0e+02 0 3.0e+01 4.0e+01 0 7.0e+02 1.2e+01 0 0 0 1 0"
    p3 = "P3: 7.0e+02 0 3.0e+01 -3.1e+02 0 7.0e+02 1.2e+01 0 0 0 1 0"
    (root / "calib.txt").write_text(f"{P0}\n{P1}\n{p2}\n{p3}\nTr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    gray = open_sequence(root, color=False)  # no image_0/1: the colour pair read as gray, with P2/P3
    assert gray.frame(0).left.shape == (24, 48) and gray.calibration.baseline == pytest.approx(0.5)
    assert open_sequence(root).frame(0).left.shape == (24, 48, 3)  # the default (auto): colour, it is the pair used
    col = open_sequence(root, color=True)
    assert col.frame(1).right.shape == (24, 48, 3) and col.calibration.baseline == pytest.approx(0.5)


@pytest.mark.parametrize(
    "calib, pattern",
    [
        (f"{P0}\n", r"calib.txt: no row 'P1:'"),
        (f"{P0}\nP1: 7.0e+02 0 3.0e+01 -3.5e+02 0 7.0e+02 1.2e+01 0 0 0 1\n", r"calib.txt: row 'P1' has 11 numbers"),
        (f"{P0}\nP1: 7.0e+02 0 3.0e+01 abc 0 7.0e+02 1.2e+01 0 0 0 1 0\n", r"calib.txt: row 'P1': 'abc' is not a number"),
        (f"{P0}\nthis line has no label\n{P1}\n", r"calib.txt: line 2 is not a labelled row"),
        (f"{P0}\n{P0.replace('P0', 'P1')}\n", r"calib.txt: baseline .* is 0.0000"),
    ],
)
def test_kitti_malformed_calib(tmp_path, calib, pattern):
    root = make_kitti(tmp_path / "seq", n=2, calib=calib)
    with pytest.raises(CalibrationError, match=pattern) as ei:
        KittiSequence(root)
    assert ei.value.path == root / "calib.txt"


def test_kitti_missing_calib(tmp_path):
    root = make_kitti(tmp_path / "seq", n=2, calib=None)
    with pytest.raises(CalibrationError, match=r"seq/calib.txt: calibration file not found"):
        KittiSequence(root)
    with pytest.raises(SequenceError, match="no calib.txt"):
        open_sequence(root)


def test_kitti_count_mismatch(tmp_path):
    root = make_kitti(tmp_path / "seq", n=3)
    (root / "image_1" / "000002.png").unlink()
    with pytest.raises(SequenceError, match=r"3 in .*image_0, 2 in .*image_1"):
        open_sequence(root)


def test_kitti_size_mismatch_names_file(tmp_path):
    root = make_kitti(tmp_path / "seq", n=3)
    _png(root / "image_1" / "000001.png", w=50, h=24)
    with pytest.raises(SequenceError, match=r"image_1/000001.png: image size 50x24 differs from 48x24"):
        open_sequence(root)


def test_kitti_unreadable_image(tmp_path):
    root = make_kitti(tmp_path / "seq", n=3)
    p = root / "image_0" / "000002.png"
    p.write_bytes(p.read_bytes()[:60])  # valid header, truncated pixels: found on read
    seq = open_sequence(root)
    seq.frame(1)
    with pytest.raises(ImageReadError, match=r"image_0/000002.png: cannot decode"):
        seq.frame(2)
    (root / "image_1" / "000000.png").write_bytes(b"garbage")  # bad header: found on open
    with pytest.raises(ImageReadError, match=r"image_1/000000.png"):
        open_sequence(root)


def test_unknown_folder(tmp_path):
    (tmp_path / "stuff").mkdir()
    (tmp_path / "stuff" / "a.png").write_bytes(b"")
    with pytest.raises(SequenceError, match=r"stuff: unrecognized sequence folder; looked for KITTI.*EuRoC.*generic"):
        open_sequence(tmp_path / "stuff")
    with pytest.raises(SequenceError, match="not found"):
        open_sequence(tmp_path / "missing")
    (tmp_path / "dataset" / "sequences").mkdir(parents=True)
    with pytest.raises(SequenceError, match="KITTI dataset root"):
        open_sequence(tmp_path / "dataset")


# --------------------------------------------------------------------------- calibration YAML


def test_own_yaml_rectified_and_raw(tmp_path):
    r = tmp_path / "rect.yaml"
    r.write_text("fx: 718.856\ncx: 607.19\ncy: 185.22\nbf: 386.14\nwidth: 1241\nheight: 376\n")
    c = load_stereo_yaml(r)
    assert isinstance(c, StereoCalibration)
    assert c.fy == c.fx == 718.856 and c.baseline == pytest.approx(386.14 / 718.856) and c.size == (1241, 376)

    raw = tmp_path / "raw.yaml"
    raw.write_text(
        "width: 752\nheight: 480\n"
        "left:\n  K: [458.654, 457.296, 367.215, 248.375]\n  D: [-0.2834, 0.0740, 0.0002, 1.8e-5]\n"
        "right:\n  K: [[457.587, 0, 379.999], [0, 456.134, 255.238], [0, 0, 1]]\n"
        "R: [0.0, 0.0, 1e-3]\nT: [-0.11, 0.0, 0.0]\n"
    )
    c = load_stereo_yaml(raw)
    assert isinstance(c, RawStereoCalibration)
    assert c.K1[0, 0] == 458.654 and c.K2[1, 2] == 255.238 and c.D1[3] == pytest.approx(1.8e-5)
    assert np.allclose(c.D2, 0) and c.D2.size == 5  # D optional
    assert c.R[1, 0] == pytest.approx(1e-3, rel=1e-3) and c.baseline == pytest.approx(0.11)
    rect = Rectifier(c)
    assert rect.calibration.baseline == pytest.approx(0.11) and rect.calibration.size == (752, 480)


@pytest.mark.parametrize(
    "text, pattern",
    [
        ("fx: 700\ncx: 10\ncy: 5\nbaseline: 0.5\nwidht: 3\n", r"unknown key\(s\) widht"),
        ("fx: 700\ncx: 10\ncy: 5\n", r"'baseline' \(metres\) or 'bf'"),
        ("fx: abc\ncx: 10\ncy: 5\nbaseline: 0.5\n", r"key 'fx': expected a number"),
        ("fx: 700\ncx: 10\ncy: 5\nbaseline: -0.5\n", r"baseline must be positive"),
        ("left: {K: [1, 1, 1]}\nright: {K: [1, 1, 1, 1]}\nR: [0, 0, 0]\nT: [-1, 0, 0]\n", r"'left.K': expected 4 or 9"),
        ("left: {K: [1, 1, 1, 1]}\nright: {K: [1, 1, 1, 1]}\nR: [0, 0, 0]\nT: [1, 0, 0]\n", r"right camera must be to the right"),
        ("foo: 1\n", r"unrecognized calibration YAML.*found keys foo"),
        ("fx: [1, 2\n", r"invalid YAML"),
    ],
)
def test_own_yaml_errors(tmp_path, text, pattern):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(CalibrationError, match=pattern) as ei:
        load_stereo_yaml(p, image_size=(20, 10))
    assert ei.value.path == p and str(p) in str(ei.value)


def test_orbslam2_settings(tmp_path):
    p = tmp_path / "EuRoC.yaml"
    p.write_text(ORBSLAM2_EUROC)
    s = load_orbslam2_settings(p)
    assert s["ThDepth"] == 35.0 and s["ORBextractor.nFeatures"] == 1200 and s["ORBextractor.scaleFactor"] == 1.2
    assert s["Camera.type"] == "PinHole" and s["Viewer.PointSize"] == 2
    assert s["LEFT.K"].shape == (3, 3) and s["RIGHT.P"].shape == (3, 4) and s["LEFT.D"].shape == (1, 5)
    raw = load_stereo_yaml(p)
    assert isinstance(raw, RawStereoCalibration) and raw.has_rectification and raw.size == (752, 480)
    r = Rectifier(raw)
    assert np.array_equal(r.R1, s["LEFT.R"]) and np.array_equal(r.P2, s["RIGHT.P"])
    assert r.calibration.fx == pytest.approx(435.2046959714599)
    assert r.calibration.bf == pytest.approx(47.90639384423901)

    k = tmp_path / "KITTI04-12.yaml"
    k.write_text(ORBSLAM2_KITTI)
    c = load_stereo_yaml(k)
    assert isinstance(c, StereoCalibration) and c.size == (1241, 376) and c.baseline == pytest.approx(0.53715, abs=1e-5)
    assert load_stereo_yaml(k, image_size=(1226, 370)).size == (1226, 370)  # like ORB-SLAM2: the images' size
    k.write_text(ORBSLAM2_KITTI.replace("Camera.bf: 379.8145\n", ""))
    with pytest.raises(CalibrationError, match=r"KITTI04-12.yaml: key 'Camera.bf' is missing"):
        load_stereo_yaml(k)
    p.write_text(ORBSLAM2_EUROC.replace("LEFT.R:", "LEFT.Rx:"))
    with pytest.raises(CalibrationError, match=r"EuRoC.yaml: rectification keys LEFT.R are missing"):
        load_stereo_yaml(p)
    p.write_text("%YAML:1.0\nCamera.fx: [1,\n  bad: : :\n")
    with pytest.raises(CalibrationError, match=r"EuRoC.yaml: cannot parse OpenCV YAML: line 3"):
        load_orbslam2_settings(p)


# --------------------------------------------------------------------------- rectification


def _synthetic_raw() -> RawStereoCalibration:
    K1 = np.array([[450.0, 0, 330], [0, 452, 245], [0, 0, 1]])
    K2 = np.array([[455.0, 0, 318], [0, 451, 238], [0, 0, 1]])
    D1 = np.array([-0.28, 0.07, 2e-4, 1e-5, 0])
    D2 = np.array([-0.27, 0.065, -1e-4, -3e-5, 0])
    R = cv2.Rodrigues(np.array([0.01, -0.02, 0.015]))[0]
    T = np.array([-0.12, 0.003, -0.002])
    return RawStereoCalibration(K1=K1, D1=D1, K2=K2, D2=D2, width=640, height=480, R=R, T=T)


def test_rectifier_known_geometry():
    raw = _synthetic_raw()
    rect = Rectifier(raw)
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-1.5, 1.5, 300), rng.uniform(-1, 1, 300), rng.uniform(2, 20, 300)])
    xl = cv2.projectPoints(X, np.zeros(3), np.zeros(3), raw.K1, raw.D1)[0].reshape(-1, 2)
    xr = cv2.projectPoints(X, cv2.Rodrigues(raw.R)[0], raw.T, raw.K2, raw.D2)[0].reshape(-1, 2)
    inside = np.all((xl > 20) & (xl < [620, 460]) & (xr > 20) & (xr < [620, 460]), axis=1)
    assert inside.sum() > 50
    ul, ur = rect.rectify_points(xl[inside], "left"), rect.rectify_points(xr[inside], "right")
    assert np.abs(ul[:, 1] - ur[:, 1]).max() < 1e-3  # same rows
    # disparity gives the true depth (in the rectified left frame)
    z = (rect.R1 @ X[inside].T)[2]
    depth = rect.calibration.depth_from_disparity(ul[:, 0] - ur[:, 0])
    assert np.allclose(depth, z, rtol=1e-4)
    assert rect.calibration.baseline == pytest.approx(np.linalg.norm(raw.T), rel=1e-9)
    # the image maps agree with the point mapping: a blob drawn at a raw position lands
    # at its rectified position
    img = np.zeros((480, 640), np.uint8)
    p = xl[inside][0]
    yy, xx = np.mgrid[0:480, 0:640]
    img[:] = np.clip(255 * np.exp(-((xx - p[0]) ** 2 + (yy - p[1]) ** 2) / (2 * 2.0**2)), 0, 255).astype(np.uint8)
    out = rect.rectify_left(img).astype(np.float64)
    m = cv2.moments(out)
    assert np.hypot(m["m10"] / m["m00"] - ul[0, 0], m["m01"] / m["m00"] - ul[0, 1]) < 0.3
    with pytest.raises(ValueError, match="calibration is for 640x480"):
        rect.rectify(img[:, :600], img)


def test_rectifier_rejects_swapped_cameras():
    raw = _synthetic_raw()
    swapped = RawStereoCalibration(K1=raw.K1, D1=raw.D1, K2=raw.K2, D2=raw.D2, width=640, height=480,
                                   R=raw.R, T=-raw.T)
    with pytest.raises(CalibrationError, match="not to the right"):
        Rectifier(swapped)


# --------------------------------------------------------------------------- EuRoC


def test_pair_by_timestamp():
    left = np.array([0, 50, 100, 150, 200, 250], np.int64) * 1_000_000
    right = np.array([1, 49, 150, 151, 260, 400], np.int64) * 1_000_000  # jitter, a gap, a duplicate
    il, ir = pair_by_timestamp(left, right, 2_500_000)
    assert il.tolist() == [0, 1, 3] and ir.tolist() == [0, 1, 2]
    il, ir = pair_by_timestamp(left, right, 20_000_000)
    assert il.tolist() == [0, 1, 3, 5] and ir.tolist() == [0, 1, 2, 4]


def test_euroc_real_rectification_aligns_rows(euroc_dir):
    seq = open_sequence(euroc_dir)
    assert isinstance(seq, EurocSequence) and seq.name == "V1_01_easy_first40"
    assert len(seq) == 40 and seq.unpaired_left == 0 and seq.unpaired_right == 0
    ts = seq.timestamps()
    assert ts[0] == pytest.approx(1403715273.262142976, abs=1e-6) and np.allclose(np.diff(ts), 0.05, atol=1e-4)
    raw = load_euroc_calib(euroc_dir / "mav0/cam0/sensor.yaml", euroc_dir / "mav0/cam1/sensor.yaml")
    assert raw.T[0] == pytest.approx(-0.110, abs=0.002) and np.allclose(raw.R, np.eye(3), atol=0.02)
    c = seq.calibration
    assert c.size == (752, 480) and 400 < c.fx < 470 and c.baseline == pytest.approx(0.110, abs=0.002)
    # our stereoRectify of the sensor.yaml poses reproduces ORB-SLAM2's published LEFT.R / RIGHT.R
    assert np.allclose(seq.rectifier.R1, [[0.999966347530033, -0.001422739138722922, 0.008079580483432283],
                                          [0.001365741834644127, 0.9999741760894847, 0.007055629199258132],
                                          [-0.008089410156878961, -0.007044357138835809, 0.9999424675829176]],
                       atol=1e-6)
    for i in (0, 20, 39):
        f = seq.frame(i)
        assert f.left.shape == (480, 752) and f.left.dtype == np.uint8
        med, p90, n = row_error(f.left, f.right)
        assert n > 200 and med < 0.5 and p90 < 1.5, (i, med, p90, n)
        raw_med, raw_p90, _ = row_error(read_image(f.left_path), read_image(f.right_path))
        assert raw_med > 5.0 and raw_med > 10 * (med + 0.1), (i, raw_med, med)


def test_euroc_with_orbslam2_settings(euroc_dir, tmp_path):
    p = tmp_path / "EuRoC.yaml"
    p.write_text(ORBSLAM2_EUROC)
    seq = EurocSequence(euroc_dir, calib=p)
    assert seq.calibration.fx == pytest.approx(435.2046959714599)
    med, p90, _ = row_error(*(lambda f: (f.left, f.right))(seq.frame(10)))
    assert med < 0.5 and p90 < 1.5


def _copy_euroc(src: Path, dst: Path, n: int = 3) -> Path:
    for cam in ("cam0", "cam1"):
        d = dst / "mav0" / cam
        (d / "data").mkdir(parents=True)
        shutil.copy(src / "mav0" / cam / "sensor.yaml", d)
        lines = (src / "mav0" / cam / "data.csv").read_text().splitlines()
        (d / "data.csv").write_text("\n".join(lines[: n + 1]) + "\n")
        for line in lines[1 : n + 1]:
            name = line.split(",")[1]
            shutil.copy(src / "mav0" / cam / "data" / name, d / "data" / name)
    return dst


def test_euroc_errors(euroc_dir, tmp_path):
    root = _copy_euroc(euroc_dir, tmp_path / "seq")
    assert len(open_sequence(root)) == 3
    assert len(open_sequence(root / "mav0")) == 3  # mav0 itself is accepted
    # an unpaired right image is skipped and counted
    csv1 = root / "mav0/cam1/data.csv"
    lines = csv1.read_text().splitlines()
    name = lines[3].split(",")[1]
    shifted = str(int(lines[3].split(",")[0]) + 20_000_000)
    csv1.write_text("\n".join(lines[:3] + [f"{shifted},{name}"]) + "\n")
    seq = open_sequence(root)
    assert len(seq) == 2 and seq.unpaired_left == 1 and seq.unpaired_right == 1
    # data.csv naming a missing file
    csv1.write_text("\n".join(lines[:3] + [f"{lines[3].split(',')[0]},missing.png"]) + "\n")
    with pytest.raises(SequenceError, match=r"cam1/data.csv: line 4: image .*missing.png not found"):
        open_sequence(root)
    csv1.write_text("\n".join(lines) + "\n")
    # a malformed sensor.yaml
    y = root / "mav0/cam1/sensor.yaml"
    y.write_text(y.read_text().replace("intrinsics: [457.587, 456.134, 379.999, 255.238]", "intrinsics: [457.587]"))
    with pytest.raises(CalibrationError, match=r"cam1/sensor.yaml: key 'intrinsics': expected 4 or 9 numbers, got 1"):
        open_sequence(root)
    y.unlink()
    with pytest.raises(CalibrationError, match=r"cam1/sensor.yaml: calibration file not found"):
        open_sequence(root)



def test_euroc_T_BS_as_written_or_as_a_list_and_bad_ones_named(tmp_path):
    """``T_BS`` of a sensor.yaml (one reader for the calibration and bench's ground truth)."""
    from dynastereo.io.calib import read_euroc_T_BS

    T = np.arange(16.0).reshape(4, 4)
    row = "[" + ", ".join(str(v) for v in T.ravel()) + "]"
    y = tmp_path / "sensor.yaml"
    y.write_text(f"T_BS:\n  cols: 4\n  rows: 4\n  data: {row}\n")
    np.testing.assert_array_equal(read_euroc_T_BS(y), T)
    y.write_text(f"T_BS: {row}\n")
    np.testing.assert_array_equal(read_euroc_T_BS(y), T)
    y.write_text("T_BS:\n  data: [1, 2, 3]\n")
    with pytest.raises(CalibrationError, match=r"sensor.yaml: key 'T_BS.data': expected 16 numbers, got 3"):
        read_euroc_T_BS(y)
    y.write_text("intrinsics: [1, 2, 3, 4]\n")
    with pytest.raises(CalibrationError, match=r"sensor.yaml: key 'T_BS' is missing \(EuRoC sensor.yaml\)"):
        read_euroc_T_BS(y)


# --------------------------------------------------------------------------- generic folders


def test_folder_sequence_rectified_and_raw(tmp_path):
    root = tmp_path / "mine"
    for i in range(4):
        _png(root / "left" / f"l{i:03d}.png", w=64, h=48, seed=i)
        _png(root / "right" / f"r{i:03d}.png", w=64, h=48, seed=50 + i)
    (root / "calib.yaml").write_text("fx: 60\ncx: 32\ncy: 24\nbaseline: 0.1\n")
    seq = open_sequence(root)
    assert isinstance(seq, FolderSequence) and len(seq) == 4 and seq.calibration.size == (64, 48)
    assert seq.rectifier is None and np.allclose(seq.timestamps(), [0, 0.1, 0.2, 0.3])
    f = seq.frame(3)
    assert f.left_path.name == "l003.png" and f.right_path.name == "r003.png"
    assert np.array_equal(f.left, read_image(root / "left" / "l003.png"))
    (root / "times.txt").write_text("1\n2\n3\n4.5\n")
    assert open_sequence(root).timestamps()[-1] == 4.5
    (root / "times.txt").unlink()
    # colour frames on request
    assert open_sequence(root, color=True).frame(0).left.shape == (48, 64, 3)
    # a raw calibration: rectified on read, with the maps built once
    (root / "calib.yaml").write_text(
        "left: {K: [60, 60, 32, 24], D: [-0.1, 0.01, 0, 0]}\nright: {K: [60, 60, 31, 25]}\n"
        "R: [0, 0.01, 0]\nT: [-0.1, 0, 0]\n"
    )
    seq = open_sequence(root)
    assert seq.rectifier is not None and seq.calibration.size == (64, 48)
    assert seq.rectifier.map_left[0].dtype == np.int16  # fixed-point maps, computed in __init__
    assert seq.frame(0).left.shape == (48, 64)
    # cam0/cam1 + a single differently named yaml + an explicit calib
    root2 = tmp_path / "other"
    shutil.copytree(root / "left", root2 / "cam0")
    shutil.copytree(root / "right", root2 / "cam1")
    shutil.copy(root / "calib.yaml", root2 / "stereo.yml")
    assert len(open_sequence(root2)) == 4
    (root2 / "second.yaml").write_text("fx: 1\n")
    with pytest.raises(SequenceError, match=r"several YAML files.*second.yaml, stereo.yml"):
        open_sequence(root2)
    assert len(open_sequence(root2, calib=root2 / "stereo.yml")) == 4


def test_folder_sequence_errors(tmp_path):
    root = tmp_path / "mine"
    for i in range(3):
        _png(root / "left" / f"{i}.png", seed=i)
        _png(root / "right" / f"{i}.png", seed=i)
    with pytest.raises(SequenceError, match="mine: found left/right image folders but no calibration"):
        open_sequence(root)
    (root / "calib.yaml").write_text("fx: 60\ncx: 32\ncy: 24\nbaseline: 0.1\nwidth: 640\nheight: 480\n")
    with pytest.raises(CalibrationError, match=r"calib.yaml: calibration is for 640x480 images, .* are 48x24"):
        open_sequence(root)
    (root / "calib.yaml").write_text("fx: 60\ncx: 32\ncy: 24\nbaseline: 0.1\n")
    _png(root / "right" / "3.png", seed=3)
    with pytest.raises(SequenceError, match=r"3 in .*left, 4 in .*right"):
        open_sequence(root)
    (root / "right" / "3.png").unlink()
    _png(root / "right" / "2.png", w=40, seed=3)
    with pytest.raises(SequenceError, match=r"right/2.png: image size 40x24 differs"):
        open_sequence(root)
