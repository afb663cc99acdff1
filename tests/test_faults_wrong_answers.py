"""The fault suite's confident-wrong-answer cases: inputs that used to give a plausible
result that was wrong, now refused in one line or read right, with a warning where the
input is only unusual.

* stereo pairs matched by index although their stamps disagree: two videos at 10 and 5
  fps (refused); a bag whose header stamps jump back (ordered by bag time instead);
* a calibration or ground truth picked up implicitly: a stray YAML beside a video (not
  taken); a relative sequence path in run.json (never resolved against the current
  folder); what was used is recorded in run.json;
* duplicate YAML keys in a configuration or a calibration (refused);
* implausible values: a baseline in millimetres (refused), 12-bit data in 16-bit PNGs
  (scaled from 12 bits, with a warning), ``motion.chi2: .inf`` and ``--rate 1e-300``
  (refused), an ORB-SLAM2 ``--config`` whose camera contradicts calib.txt (a warning).
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from test_faults_inputs import assert_one_line, cli, mini06


def _write_video(path: Path, frames: list[np.ndarray], fps: float) -> Path:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), fps, (w, h), frames[0].ndim == 3)
    assert writer.isOpened(), "this OpenCV build cannot write FFV1"
    for f in frames:
        writer.write(f)
    writer.release()
    return path


def _calib_yaml(path: Path, calibration, baseline: float | None = None) -> Path:
    K = calibration.K
    b = calibration.baseline if baseline is None else baseline
    path.write_text(f"fx: {float(K[0, 0])!r}\nfy: {float(K[1, 1])!r}\ncx: {float(K[0, 2])!r}\n"
                    f"cy: {float(K[1, 2])!r}\nbaseline: {float(b)!r}\n")
    return path


@pytest.fixture(scope="module")
def pairs(kitti06: Path) -> tuple[list, object]:
    from dynastereo.io import KittiSequence

    seq = KittiSequence(kitti06)
    return [seq.frame(i) for i in range(4)], seq.calibration


def test_two_videos_whose_stamps_disagree_are_refused(pairs, tmp_path: Path) -> None:
    from dynastereo.errors import SequenceError
    from dynastereo.io import open_sequence

    frames, calib = pairs
    left = _write_video(tmp_path / "left.mkv", [p.left for p in frames], 10)
    right = _write_video(tmp_path / "right.mkv", [p.right for p in frames], 5)
    c = _calib_yaml(tmp_path / "calib.yaml", calib)
    with pytest.raises(SequenceError, match=r"stamps disagree: frame 1 is at 0\.100 s .* 0\.200 s .*10 vs 5 fps"):
        open_sequence(f"{left},{right}", calib=c)
    _write_video(right, [p.right for p in frames], 10)  # the same rate: paired, the frames are the folder's
    two = open_sequence(f"{left},{right}", calib=c)
    assert len(two) == 4 and np.array_equal(two.frame(3).right, frames[3].right)


def test_a_stray_yaml_beside_a_video_is_not_taken_as_its_calibration(pairs, tmp_path: Path) -> None:
    from dynastereo.errors import SequenceError
    from dynastereo.io import open_sequence

    frames, calib = pairs
    video = _write_video(tmp_path / "stereo.mkv", [np.hstack([p.left, p.right]) for p in frames], 10)
    _calib_yaml(tmp_path / "params.yaml", calib)
    with pytest.raises(SequenceError, match=r"no calibration: pass --calib .*params\.yaml beside it is not taken"):
        open_sequence(video)
    seq = open_sequence(video, calib=tmp_path / "params.yaml")  # named: taken, and said which
    assert seq.calibration_file == tmp_path / "params.yaml"
    shutil.copy(tmp_path / "params.yaml", tmp_path / "calib.yaml")
    assert open_sequence(video).calibration_file == tmp_path / "calib.yaml"


def test_bag_header_stamps_that_jump_back_do_not_shuffle_the_frames(kitti06: Path, tmp_path: Path, caplog) -> None:
    """A camera clock reset half-way: header stamps 0.0 .. 0.4 s, then 0.05 .. 0.45 s.  Sorted
    by them the frames would run 0, 5, 1, 6, ...; they are fed in the order recorded."""
    from dynastereo.io import KittiSequence
    from dynastereo.ros.bags import (DEFAULT_LEFT_FRAME, DEFAULT_LEFT_INFO, DEFAULT_LEFT_TOPIC, DEFAULT_RIGHT_FRAME,
                                     DEFAULT_RIGHT_INFO, DEFAULT_RIGHT_TOPIC, BagStereoSequence, BagWriter,
                                     _export_camera_infos, _image_message)

    seq = KittiSequence(kitti06)
    infos = _export_camera_infos(seq, False)
    bag = tmp_path / "reset.bag"
    n = 10
    with BagWriter(bag, "ros1") as w:
        b = w.builder
        for k in range(n):
            f = seq.frame(k)
            head = int(round((k * 0.1 if k < 5 else (k - 5) * 0.1 + 0.05) * 1e9)) + 10**9
            t = 2 * 10**9 + k * 10**8  # bag (receive) time: in order
            w.write(DEFAULT_LEFT_TOPIC, t, _image_message(b, f.left, head, DEFAULT_LEFT_FRAME, "auto", k))
            w.write(DEFAULT_RIGHT_TOPIC, t, _image_message(b, f.right, head, DEFAULT_RIGHT_FRAME, "auto", k))
            w.write(DEFAULT_LEFT_INFO, t, b.camera_info(infos[0], head, DEFAULT_LEFT_FRAME, seq=k))
            w.write(DEFAULT_RIGHT_INFO, t, b.camera_info(infos[1], head, DEFAULT_RIGHT_FRAME, seq=k))
    with caplog.at_level(logging.WARNING):
        s = BagStereoSequence(bag)
    assert "jump back" in caplog.text and s.report.stamps == "bag time"
    assert len(s) == n and np.all(np.diff(s.timestamps()) > 0)
    for k in (1, 5, 6):
        assert np.array_equal(s.frame(k).left, seq.frame(k).left), k


def test_eval_never_resolves_a_relative_sequence_path_against_the_current_folder(kitti06: Path,
                                                                                tmp_path: Path) -> None:
    """run.json from an older run names its sequence relatively: ``eval`` from another
    folder holding another ``sequences/06`` must not score against that folder's poses."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "trajectory.kitti.txt").write_text("".join(
        " ".join(f"{v:.6f}" for v in np.eye(4)[:3].reshape(-1)) + "\n" for _ in range(3)))
    (run / "run.json").write_text(json.dumps({"sequence": "data/sequences/06", "status": "done"}))
    decoy = tmp_path / "data"
    (decoy / "sequences" / "06").mkdir(parents=True)
    (decoy / "poses").mkdir()
    (decoy / "poses" / "06.txt").write_text((kitti06.parents[1] / "poses" / "06.txt").read_text())
    r = cli(["eval", run / "trajectory.kitti.txt"], tmp_path)  # cwd: tmp_path, where data/ resolves
    assert_one_line(r, 2, "run.json", "relative path", "give the ground truth")
    # an absolute path (what run.json records now) is used, and named
    (run / "run.json").write_text(json.dumps({"sequence": str(decoy / "sequences" / "06"), "status": "done"}))
    r = cli(["eval", run / "trajectory.kitti.txt"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert f"ground truth: {decoy / 'poses' / '06.txt'}" in r.stdout


def test_a_run_records_its_sequence_calibration_and_ground_truth_absolutely(kitti06: Path, tmp_path: Path) -> None:
    from dynastereo.api import run_sequence
    from dynastereo.config import Config

    root = tmp_path / "k"
    seq = mini06(kitti06, root / "sequences" / "06")
    (root / "poses").mkdir()
    shutil.copy(kitti06.parents[1] / "poses" / "06.txt", root / "poses" / "06.txt")
    r = cli(["run", Path("k/sequences/06"), "--out", "out", "--masker", "none", "--frames", 2], tmp_path)
    assert r.returncode == 0, r.stderr
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert run["sequence"] == str(seq) and run["calibration"] == str(seq / "calib.txt")
    assert run["ground_truth"] == str(root / "poses" / "06.txt")
    assert f"calibration: {seq / 'calib.txt'}" in r.stdout and "accuracy: ATE" in r.stdout
    assert str(root / "poses" / "06.txt") in r.stdout


@pytest.mark.parametrize("what", ["config", "calibration"])
def test_duplicate_yaml_keys_are_refused(what: str, tmp_path: Path) -> None:
    from dynastereo.config import load_config
    from dynastereo.errors import InputError
    from dynastereo.io.calib import load_stereo_yaml

    p = tmp_path / f"{what}.yaml"
    if what == "config":
        p.write_text("masker:\n  outline:\n    dilate: 3\n  kind: box\n  outline:\n    dilate: 5\n")
        load, key, line = load_config, "masker.outline", 5
    else:
        p.write_text("fx: 700.0\nfy: 700.0\ncx: 600.0\ncy: 180.0\nbaseline: 0.54\nbaseline: 0.12\n")
        load, key, line = (lambda q: load_stereo_yaml(q, (1226, 370))), "baseline", 6
    with pytest.raises(InputError, match=rf"{p.name}: line {line}: key '{key}' is given twice"):
        load(p)


def test_a_baseline_in_millimetres_is_refused_an_unusual_one_warned(kitti06: Path, tmp_path: Path, caplog) -> None:
    from dynastereo.errors import CalibrationError
    from dynastereo.io import KittiSequence, open_sequence

    calib = KittiSequence(kitti06).calibration
    seq = tmp_path / "seq"
    for side, cam in (("left", "image_0"), ("right", "image_1")):
        (seq / side).mkdir(parents=True)
        for i in range(2):
            shutil.copy(kitti06 / cam / f"{i:06d}.png", seq / side / f"{i:06d}.png")
    _calib_yaml(seq / "calib.yaml", calib, baseline=537.2)
    with pytest.raises(CalibrationError, match=r"calib\.yaml: baseline 537\.2 m is implausible \(millimetres\?"):
        open_sequence(seq, rate=10)
    _calib_yaml(seq / "calib.yaml", calib, baseline=3.5)
    with caplog.at_level(logging.WARNING):
        open_sequence(seq, rate=10)
    assert "baseline 3.5 m is outside the usual 0.01-2 m" in caplog.text


def test_twelve_bit_data_in_sixteen_bit_pngs_is_read_as_twelve_bits(kitti06: Path, tmp_path: Path, caplog) -> None:
    from dynastereo.io import KittiSequence

    seq = mini06(kitti06, tmp_path / "seq", 2)
    for p in seq.glob("image_*/*.png"):  # the 8-bit values x 16: 12-bit data, max <= 4080
        cv2.imwrite(str(p), cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).astype(np.uint16) * 16)
    with caplog.at_level(logging.WARNING):
        s = KittiSequence(seq)
    assert s.bits == 12 and "16-bit images holding 12-bit values" in caplog.text
    f, ref = s.frame(1), KittiSequence(kitti06).frame(1)
    assert f.left.dtype == np.uint8 and np.array_equal(f.left, ref.left) and np.array_equal(f.right, ref.right)


def test_non_finite_or_absurd_values_are_refused(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text("motion:\n  chi2: .inf\n")
    assert_one_line(cli(["config", p], tmp_path), 2, "motion.chi2", "finite")
    p.write_text("masker:\n  outline:\n    dilate: 100000\n")
    assert_one_line(cli(["config", p], tmp_path), 2, "masker.outline.dilate", "[0, 64]")
    from dynastereo.errors import InputError
    from dynastereo.io.times import check_rate

    for rate in (1e-300, 1e12, float("inf")):
        with pytest.raises(InputError, match="--rate must be a frame rate in Hz within"):
            check_rate(rate)


def test_an_orbslam2_config_whose_camera_contradicts_the_calibration_is_named(kitti06: Path, tmp_path: Path,
                                                                             caplog) -> None:
    from dynastereo.io import KittiSequence
    from dynastereo.runtime.spec import settings_disagreement

    calib = KittiSequence(kitti06).calibration
    fx = float(calib.K[0, 0])
    p = tmp_path / "settings.yaml"
    p.write_text(f"%YAML:1.0\nCamera.fx: {fx}\nCamera.fy: {fx}\nCamera.cx: 600.0\nCamera.cy: 180.0\n"
                 f"Camera.bf: {fx * 0.8}\nORBextractor.nFeatures: 2000\n")
    msg = settings_disagreement(p, calib, kitti06 / "calib.txt")
    assert msg is not None and "Camera.bf" in msg and "baseline 0.8 m" in msg and "the sequence's is used" in msg
    p.write_text(f"%YAML:1.0\nCamera.fx: {fx}\nCamera.fy: {fx}\nCamera.cx: 600.0\nCamera.cy: 180.0\n"
                 f"Camera.bf: {fx * calib.baseline}\n")
    assert settings_disagreement(p, calib, kitti06 / "calib.txt") is None
