"""Where a sequence's timestamps come from: times.txt, timestamp file names, or a rate."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from dynastereo.cli.main import app
from dynastereo.errors import InputError, SequenceError
from dynastereo.io import open_sequence
from dynastereo.io.times import stamps_from_names

CALIB = "fx: 60\ncx: 32\ncy: 24\nbaseline: 0.1\n"


def make_folder(root: Path, names: list[str], calib: str = CALIB) -> Path:
    """A generic stereo folder: left/ + right/ with the same file names, and calib.yaml."""
    rng = np.random.default_rng(0)
    for side in ("left", "right"):
        (root / side).mkdir(parents=True, exist_ok=True)
        for name in names:
            assert cv2.imwrite(str(root / side / name), rng.integers(0, 255, (48, 64), dtype=np.uint8))
    (root / "calib.yaml").write_text(calib)
    return root


T0_NS = 1_403_636_579_763_555_584  # a EuRoC stamp


@pytest.mark.parametrize("unit, per_s", [("ns", 10**9), ("µs", 10**6), ("ms", 10**3), ("s", 1)])
def test_file_names_are_stamps_in_any_unit(tmp_path: Path, unit: str, per_s: int) -> None:
    step = per_s // 20 if per_s > 1 else 1  # 20 Hz (1 Hz for whole seconds)
    first = T0_NS * per_s // 10**9
    values = [first + k * step for k in range(4)]
    seq = open_sequence(make_folder(tmp_path / unit, [f"{v}.png" for v in values]))
    assert seq.timestamp_source == f"file names ({unit})"
    assert np.allclose(seq.timestamps(), np.array(values, np.float64) / per_s, rtol=0, atol=1e-6)
    assert np.array_equal(seq.timestamps_ns, np.array(values, np.int64) * (10**9 // per_s))  # exact


def test_decimal_file_names_are_seconds(tmp_path: Path) -> None:
    seq = open_sequence(make_folder(tmp_path / "tum", ["1305031102.175304.png", "1305031102.211214.png"]))
    assert seq.timestamp_source == "file names (s)"
    assert seq.timestamps() == pytest.approx([1305031102.175304, 1305031102.211214], abs=1e-6)


def test_times_txt_wins_over_names_and_a_given_rate_is_ignored(tmp_path: Path, caplog) -> None:
    root = make_folder(tmp_path / "seq", [f"{T0_NS + k * 50_000_000}.png" for k in range(3)])
    (root / "times.txt").write_text("0.5\n0.6\n0.75\n")
    with caplog.at_level(logging.WARNING, logger="dynastereo"):
        seq = open_sequence(root, rate=30)
    assert seq.timestamp_source == "times.txt" and list(seq.timestamps()) == [0.5, 0.6, 0.75]
    assert "--rate 30 ignored: the timestamps come from times.txt" in caplog.text


def test_frame_counters_fall_back_to_the_rate_with_a_warning(tmp_path: Path, caplog) -> None:
    root = make_folder(tmp_path / "seq", [f"{k:06d}.png" for k in range(4)])
    with caplog.at_level(logging.WARNING, logger="dynastereo"):
        seq = open_sequence(root)
    assert seq.timestamp_source == "rate 10 Hz (assumed)"
    assert np.allclose(seq.timestamps(), [0, 0.1, 0.2, 0.3])
    assert "no times.txt and the image names are not timestamps: assuming 10 Hz" in caplog.text
    assert "--rate" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="dynastereo"):
        seq = open_sequence(root, rate=25)
    assert seq.timestamp_source == "rate 25 Hz (given)" and np.allclose(seq.timestamps(), [0, 0.04, 0.08, 0.12])
    assert caplog.text == ""
    assert not hasattr(seq, "timestamps_ns")


def test_names_that_are_not_stamps(tmp_path: Path) -> None:
    p = [tmp_path / n for n in ("frame_1.png", "frame_2.png")]
    assert stamps_from_names(p) is None  # not numbers
    assert stamps_from_names([tmp_path / "1403636579.png"]) is None  # one frame: no interval
    assert stamps_from_names([tmp_path / f"{n}.png" for n in (10, 20, 30)]) is None  # too small for a date
    # Unix seconds 100 s apart: no camera, not stamps
    assert stamps_from_names([tmp_path / f"{1_600_000_000 + 100 * k}.png" for k in range(3)]) is None


def test_stamp_names_out_of_order_are_an_error_naming_the_files(tmp_path: Path) -> None:
    # sorted by name, 1000000000.png comes before 999999999.png: the stamps go backwards
    root = make_folder(tmp_path / "seq", ["999999999.png", "1000000000.png"])
    with pytest.raises(SequenceError, match=r"left: the image names are timestamps \(s\) but do not increase "
                                            r"in name order: 999999999.png comes after 1000000000.png"):
        open_sequence(root)


@pytest.mark.parametrize("rate", [0.0, -5.0, float("nan"), 1e-300, 1e9, float("inf")])
def test_bad_rate(tmp_path: Path, rate: float) -> None:
    root = make_folder(tmp_path / "seq", ["a.png", "b.png"])
    with pytest.raises(InputError, match="--rate must be a frame rate in Hz within"):
        open_sequence(root, rate=rate)


def test_kitti_without_times_takes_the_rate(tmp_path: Path) -> None:
    root = tmp_path / "kitti"
    make_folder(root, [f"{k:06d}.png" for k in range(3)])
    (root / "left").rename(root / "image_0")
    (root / "right").rename(root / "image_1")
    (root / "calib.txt").write_text("P0: 60 0 32 0 0 60 24 0 0 0 1 0\nP1: 60 0 32 -6 0 60 24 0 0 0 1 0\n")
    seq = open_sequence(root)
    assert seq.timestamp_source == "rate 10 Hz (KITTI's, assumed)" and np.allclose(seq.timestamps(), [0, 0.1, 0.2])
    seq = open_sequence(root, rate=5)
    assert seq.timestamp_source == "rate 5 Hz (given)" and np.allclose(seq.timestamps(), [0, 0.2, 0.4])
    (root / "times.txt").write_text("3\n4\n5\n")
    assert open_sequence(root).timestamp_source == "times.txt"


def test_export_bag_from_stamp_zero_says_so_and_offset_shifts(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    from dynastereo.ros.bags import BagStereoSequence

    root = make_folder(tmp_path / "seq", [f"{k:06d}.png" for k in range(3)])
    r = CliRunner().invoke(app, ["export-bag", str(root), str(tmp_path / "a.mcap"), "--rate", "20"])
    assert r.exit_code == 0, r.output
    assert "stamps start at 0 s (1970)" in r.output and "--time-offset" in r.output
    r = CliRunner().invoke(app, ["export-bag", str(root), str(tmp_path / "b.mcap"), "--rate", "20",
                                 "--time-offset", "1.7e9"])
    assert r.exit_code == 0, r.output
    assert "1970" not in r.output
    bag = BagStereoSequence(tmp_path / "b.mcap", calib=root / "calib.yaml")
    assert bag.timestamps() == pytest.approx([1.7e9, 1.7e9 + 0.05, 1.7e9 + 0.1], abs=1e-6)
    assert bag.timestamp_source.startswith("bag header stamps")


def test_run_records_where_the_stamps_came_from(tmp_path: Path) -> None:
    """run.json's "timestamps" (a small generic folder with ns names; no masks, SLAM only)."""
    from dynastereo.api import run_sequence
    from dynastereo.config import Config
    from dynastereo.synth import generate

    synth = open_sequence(generate(tmp_path / "synth", "static", frames=4, seed=0, size=(320, 96)))
    root = tmp_path / "mine"
    c = synth.calibration
    names = [f"{T0_NS + k * 100_000_000}.png" for k in range(len(synth))]
    for side, paths in (("left", synth.left_paths), ("right", synth.right_paths)):
        (root / side).mkdir(parents=True)
        for p, n in zip(paths, names):
            (root / side / n).write_bytes(p.read_bytes())
    (root / "calib.yaml").write_text(f"fx: {c.fx}\nfy: {c.fy}\ncx: {c.cx}\ncy: {c.cy}\nbaseline: {c.baseline}\n")
    run_sequence(root, tmp_path / "run", Config().with_overrides({"masker.kind": "none"}))
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["timestamps"] == "file names (ns)"
    first = (tmp_path / "run" / "trajectory.tum.txt").read_text().split()[0]
    assert float(first) == pytest.approx(T0_NS * 1e-9, abs=1e-6)
