"""Stereo video sources (io.video): a side-by-side file, two files, and a camera through
``cv2.VideoCapture`` -- every video generated here, lossless (FFV1 in .mkv), into tmp."""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from dynastereo.cli.main import app
from dynastereo.errors import InputError, SequenceError
from dynastereo.io import KittiSequence, open_sequence
from dynastereo.io.frames import select_frames
from dynastereo.io.video import UNBOUNDED, CameraSequence, VideoSequence

runner = CliRunner()
N_FRAMES = 10  # of KITTI 06 in the videos


def _write_video(path: Path, frames: list[np.ndarray], fps: float) -> Path:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), fps, (w, h), frames[0].ndim == 3)
    assert writer.isOpened(), "this OpenCV build cannot write FFV1"
    for f in frames:
        writer.write(f)
    writer.release()
    return path


def _calib_yaml(path: Path, calibration) -> Path:
    """The rectified YAML of ``calibration`` (floats written exactly)."""
    K = calibration.K
    path.write_text(f"fx: {float(K[0, 0])!r}\nfy: {float(K[1, 1])!r}\ncx: {float(K[0, 2])!r}\n"
                    f"cy: {float(K[1, 2])!r}\nbaseline: {float(calibration.baseline)!r}\n")
    return path


@pytest.fixture(scope="module")
def videos(kitti06: Path, tmp_path_factory) -> dict[str, Path]:
    """KITTI 06's first frames as a side-by-side video, as two videos, and their calib.yaml."""
    d = tmp_path_factory.mktemp("video")
    seq = KittiSequence(kitti06)
    pairs = [seq.frame(i) for i in range(N_FRAMES)]
    return {
        "sbs": _write_video(d / "stereo.mkv", [np.hstack([p.left, p.right]) for p in pairs], 10),
        "left": _write_video(d / "left.mkv", [p.left for p in pairs], 10),
        "right": _write_video(d / "right.mkv", [p.right for p in pairs], 10),
        "calib": _calib_yaml(d / "calib.yaml", seq.calibration),
        "dir": d,
    }


def test_video_frames_are_the_folders(kitti06: Path, videos: dict[str, Path]) -> None:
    seq = KittiSequence(kitti06)
    sbs = open_sequence(videos["sbs"], calib=videos["calib"])
    two = open_sequence(f"{videos['left']},{videos['right']}", calib=videos["calib"])
    assert isinstance(sbs, VideoSequence) and sbs.side_by_side and not two.side_by_side
    for v in (sbs, two):
        assert len(v) == N_FRAMES and not v.color
        assert np.array_equal(v.calibration.K, seq.calibration.K) and v.calibration.baseline == seq.calibration.baseline
        np.testing.assert_allclose(v.timestamps(), np.arange(N_FRAMES) * 0.1, atol=1e-9)  # the container's
        assert v.timestamp_source == "video container"
        for i in (0, 1, 2, 7, 3, 9):  # in order, forward jumps and back (reopened)
            a, b = seq.frame(i), v.frame(i)
            assert b.index == i and np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right), i
    rated = VideoSequence(videos["sbs"], videos["calib"], rate=4.0)
    np.testing.assert_allclose(rated.timestamps(), np.arange(N_FRAMES) / 4.0)
    assert rated.timestamp_source == "rate 4 Hz (given)"
    assert VideoSequence(videos["sbs"], videos["calib"], color=True).frame(0).left.shape == (370, 1226, 3)


def _trajectory(out: Path) -> np.ndarray:
    return np.loadtxt(out / "trajectory.kitti.txt")


def test_run_on_video_gives_the_folders_trajectory(kitti06: Path, videos: dict[str, Path], tmp_path: Path,
                                                   quiet_slam) -> None:
    base = ["--masker", "none", "--frames", str(N_FRAMES)]
    r = runner.invoke(app, ["run", str(kitti06), "--out", str(tmp_path / "folder"), *base])
    assert r.exit_code == 0, r.output
    ref = _trajectory(tmp_path / "folder")
    assert ref.shape == (N_FRAMES, 12)
    for name, source in (("sbs", str(videos["sbs"])), ("two", f"{videos['left']},{videos['right']}")):
        out = tmp_path / name
        r = runner.invoke(app, ["run", source, "--calib", str(videos["calib"]), "--out", str(out), *base])
        assert r.exit_code == 0, r.output
        assert np.abs(_trajectory(out) - ref).max() <= 1e-6, name
        run = json.loads((out / "run.json").read_text())
        assert run["timestamps"] == "video container" and run["frames_done"] == N_FRAMES
        stamps = np.loadtxt(out / "trajectory.tum.txt")[:, 0]
        np.testing.assert_allclose(stamps, np.arange(N_FRAMES) * 0.1, atol=1e-9)


def test_bad_video_is_one_line_naming_the_file(videos: dict[str, Path], tmp_path: Path) -> None:
    junk = tmp_path / "junk.mkv"
    junk.write_bytes(b"not a video at all" * 100)
    data = videos["sbs"].read_bytes()
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(data[: len(data) // 2])  # truncated: the frames after the cut are gone or broken
    calib = str(videos["calib"])
    for bad in (junk, cut, tmp_path / "missing.mkv"):
        r = runner.invoke(app, ["mask", str(bad), "--calib", calib, "--out", str(tmp_path / "o"), "--masker", "none",
                                "--frames", str(N_FRAMES)])
        assert r.exit_code == 2, r.output
        lines = [ln for ln in r.output.strip().splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("error:") and bad.name in lines[0], r.output
    # two files of different lengths
    short = _write_video(tmp_path / "short.mkv", [np.zeros((370, 1226), np.uint8)] * 3, 10)
    with pytest.raises(SequenceError, match="differ in length"):
        VideoSequence(videos["left"], videos["calib"], right=short)
    # the calibration must be for one image (half a side-by-side frame)
    r = runner.invoke(app, ["run", f"{videos['left']},{videos['right']},{short}", "--calib", calib,
                            "--out", str(tmp_path / "o3")])
    assert r.exit_code == 2 and "left,right" in r.output


# -------------------------------------------------------------------------- the camera

def _numbered_frames(n: int, w: int = 64, h: int = 48) -> list[np.ndarray]:
    """Side-by-side gray frames whose pixels spell their number (k * 4 in the left half)."""
    rng = np.random.default_rng(1)
    tex = rng.integers(0, 60, (h, w), dtype=np.uint8)
    return [np.hstack([tex + np.uint8(4 * k), np.roll(tex, -3, axis=1) + np.uint8(4 * k)]) for k in range(n)]


def _small_calib(path: Path) -> Path:
    path.write_text("fx: 50.0\ncx: 32.0\ncy: 24.0\nbaseline: 0.1\n")
    return path


def test_camera_keeps_the_newest_frame_and_counts_drops(tmp_path: Path) -> None:
    """A generated file opened through VideoCapture as the camera (played at its 20 Hz): a
    consumer taking 0.2 s a frame gets the newest frame each time; the others are dropped
    and counted."""
    frames = _numbered_frames(40)
    video = _write_video(tmp_path / "cam.mkv", frames, 20)
    with open_sequence(f"cam:{video}", calib=_small_calib(tmp_path / "calib.yaml")) as cam:
        assert isinstance(cam, CameraSequence) and len(cam) == UNBOUNDED
        assert cam.calibration.width == 64 and not cam.color
        got, stamps = [], []
        for i in range(6):
            f = cam.frame(i)
            assert f.index == i
            got.append(int(round((int(f.left[0, 0]) - int(frames[0][0, 0])) / 4)))
            assert np.array_equal(f.left, frames[got[-1]][:, :64]) and np.array_equal(f.right, frames[got[-1]][:, 64:])
            stamps.append(f.timestamp)
            time.sleep(0.2)  # the slow consumer
        info = cam.run_info()["source"]
    assert got == sorted(got) and len(set(got)) == 6 and got[-1] - got[0] > 6  # in order, frames skipped
    np.testing.assert_allclose(np.diff(stamps), np.diff(got) / 20.0, atol=1e-6)  # the file's stamps
    assert stamps[0] == 0.0
    assert info["taken"] == 6 and info["dropped"] > 0
    assert info["received"] - info["taken"] - info["dropped"] in (0, 1)  # at most the newest one waits


def test_camera_frame_spec_and_end(tmp_path: Path) -> None:
    video = _write_video(tmp_path / "cam.mkv", _numbered_frames(3), 50)
    cam = CameraSequence(str(video), _small_calib(tmp_path / "calib.yaml"), timeout_s=2.0)
    try:
        assert select_frames(None, cam) == range(UNBOUNDED)  # lazy: no list of that length
        assert select_frames("5", cam) == [0, 1, 2, 3, 4]
        with pytest.raises(InputError, match="count"):
            select_frames("2-4", cam)
        with pytest.raises(SequenceError, match="stopped delivering frames"):
            for i in range(10):
                cam.frame(i)
    finally:
        cam.close()
    with pytest.raises(InputError, match="--calib"):
        open_sequence("cam:0")
    with pytest.raises(SequenceError, match="cannot open the camera"):
        CameraSequence(str(tmp_path / "nothing.mkv"), tmp_path / "calib.yaml")


def test_run_on_camera_writes_drops(kitti06: Path, videos: dict[str, Path], tmp_path: Path, quiet_slam) -> None:
    """`dynastereo run cam:FILE --frames 2`: stops after 2 frames, run.json counts the drops."""
    seq = KittiSequence(kitti06)
    video = _write_video(tmp_path / "cam.mkv", [np.hstack([seq.frame(i).left, seq.frame(i).right]) for i in range(6)],
                         1)  # played at 1 Hz: it outlasts the run's start on a busy machine
    out = tmp_path / "cam"
    r = runner.invoke(app, ["run", f"cam:{video}", "--calib", str(videos["calib"]), "--out", str(out),
                            "--masker", "none", "--frames", "2", "--no-stereo-check"])
    assert r.exit_code == 0, r.output
    run = json.loads((out / "run.json").read_text())
    assert run["frames_done"] == 2 and run["timestamps"] == "camera"
    src = run["source"]
    assert src["kind"] == "camera" and src["taken"] == 2 and src["received"] >= 2
    assert src["received"] - src["taken"] - src["dropped"] in (0, 1)
    assert np.loadtxt(out / "trajectory.kitti.txt").shape == (2, 12)


def test_readme_video_and_camera_as_written(tmp_path: Path, monkeypatch, models_dir: Path) -> None:
    """README's "A stereo video, or the camera itself", run as written (the camera is the
    generated recording: ``cam:0`` -> ``cam:mycam.mkv``)."""
    from test_readme import T0_NS, make_own_camera, readme_block, run_block

    cam = open_sequence(make_own_camera(tmp_path, frames=8))
    pairs = [cam.frame(i) for i in range(len(cam))]
    _write_video(tmp_path / "mycam.mkv", [np.hstack([p.left, p.right]) for p in pairs], 30)
    _write_video(tmp_path / "mycam_left.mkv", [p.left for p in pairs], 30)
    _write_video(tmp_path / "mycam_right.mkv", [p.right for p in pairs], 30)
    run_block("own-video", tmp_path, monkeypatch)
    runs = [json.loads((tmp_path / d / "run.json").read_text()) for d in ("mycam_video_run", "mycam_video_run2")]
    assert [r["frames_done"] for r in runs] == [len(cam)] * 2
    assert [r["timestamps"] for r in runs] == ["video container", "rate 30 Hz (given)"]
    assert T0_NS  # the folder's own stamps are not the video's: the container starts at 0

    monkeypatch.chdir(tmp_path)
    # played as a camera at 1 Hz: the recording outlasts loading the detector on a busy machine
    _write_video(tmp_path / "mycam_live.mkv", [np.hstack([p.left, p.right]) for p in pairs], 1)
    (args,) = readme_block("own-live")
    args = [("cam:mycam_live.mkv" if a == "cam:0" else a) for a in args]
    args[args.index("--frames") + 1] = "3"  # the recording holds 16
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output
    run = json.loads((tmp_path / "live_run" / "run.json").read_text())
    assert run["frames_done"] == 3 and run["source"]["kind"] == "camera"
