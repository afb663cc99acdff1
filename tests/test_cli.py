"""The CLI and the Python API end to end: file contracts, errors, partial output on failure."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from dynastereo.api import mask_sequence
from dynastereo.cli.main import app
from dynastereo.config import Config
from dynastereo.errors import ImageReadError
from dynastereo.io.images import read_disparity_png

runner = CliRunner()


def _mini_kitti(src: Path, dst: Path, n: int) -> Path:
    """Copy the first n frames of a KITTI sequence (and its calib) into dst."""
    for cam in ("image_0", "image_1"):
        (dst / cam).mkdir(parents=True)
        for i in range(n):
            shutil.copy(src / cam / f"{i:06d}.png", dst / cam / f"{i:06d}.png")
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    return dst


def test_mask_cli_writes_the_contract(kitti06: Path, models_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    r = runner.invoke(app, ["mask", str(kitti06), "--out", str(out), "--frames", "3-5,0",
                            "--detector", "yolox-nano", "--save-disparity", "--overlays",
                            "--models-dir", str(models_dir)])
    assert r.exit_code == 0, r.output
    for i in (0, 3, 4, 5):
        left = cv2.imread(str(out / "masks/left" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        right = cv2.imread(str(out / "masks/right" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert left.dtype == np.uint8 and left.shape == (370, 1226)
        assert set(np.unique(left)) <= {0, 255} and set(np.unique(right)) <= {0, 255}
        disp = cv2.imread(str(out / "disparity" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert disp.dtype == np.uint16
        assert (out / "overlays" / f"{i:06d}.png").is_file()
    assert not (out / "masks/left/000001.png").exists()
    # KITTI 06 frame 0..5: the parked car on the right is detected and masked in both views
    left = cv2.imread(str(out / "masks/left/000003.png"), 0)
    right = cv2.imread(str(out / "masks/right/000003.png"), 0)
    assert left.mean() > 2 and right.mean() > 2
    # the right mask is the left one moved left by the object's disparity
    cols_l = np.nonzero(left.any(0))[0]
    cols_r = np.nonzero(right.any(0))[0]
    assert cols_r.max() < cols_l.max()
    d = read_disparity_png(out / "disparity/000003.png")
    assert np.count_nonzero(d > 0) > 0.3 * d.size

    timing = json.loads((out / "timing.json").read_text())
    assert [f["frame"] for f in timing["frames"]] == [3, 4, 5, 0]
    for stage in ("detect", "mask", "disparity"):
        assert {"median", "p90"} <= set(timing["summary"][stage])
    assert timing["frames_done"] == 4
    lines = (out / "objects.jsonl").read_text().splitlines()
    assert len(lines) == 4 and json.loads(lines[0])["frame"] == 3
    assert "median" in r.output and "detect" in r.output


def test_mask_api_box_and_none(kitti06: Path, models_dir: Path, tmp_path: Path) -> None:
    cfg = Config().with_overrides({"masker.kind": "box", "detector.name": "yolox-nano"})
    res = mask_sequence(kitti06, tmp_path / "box", cfg, frames=2, models_dir=models_dir)
    assert res.frames_done == [0, 1]
    box = cv2.imread(str(tmp_path / "box/masks/left/000000.png"), 0)
    # a box mask is made of rectangles: every masked row segment of one object is full width
    assert box.mean() > 2
    res = mask_sequence(kitti06, tmp_path / "none", Config().with_overrides({"masker.kind": "none"}), frames=1)
    assert cv2.imread(str(tmp_path / "none/masks/left/000000.png"), 0).max() == 0


def test_failing_frame_keeps_what_was_written(kitti06: Path, models_dir: Path, tmp_path: Path) -> None:
    seq = _mini_kitti(kitti06, tmp_path / "seq", 4)
    (seq / "image_0/000002.png").write_bytes((seq / "image_0/000002.png").read_bytes()[:200])  # truncated
    out = tmp_path / "out"
    cfg = Config().with_overrides({"detector.name": "fastestdet"})
    with pytest.raises(ImageReadError) as e:
        mask_sequence(seq, out, cfg, models_dir=models_dir)
    assert "000002.png" in str(e.value)
    assert (out / "masks/left/000000.png").is_file() and (out / "masks/right/000001.png").is_file()
    timing = json.loads((out / "timing.json").read_text())
    assert timing["frames_done"] == 2 and "ImageReadError" in timing["error"]
    # the CLI says it in one line, exit code 2
    r = runner.invoke(app, ["mask", str(seq), "--out", str(tmp_path / "o2"), "--detector", "fastestdet",
                            "--models-dir", str(models_dir)])
    assert r.exit_code == 2 and "000002.png" in r.output


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--detector", "yolov9000"], "yolov9000"),
        (["--masker", "magic"], "masker.kind"),
        (["--stereo", "census"], "census"),
        (["--frames", "5-2"], "5-2"),
    ],
)
def test_mask_cli_bad_options(kitti06: Path, models_dir: Path, tmp_path: Path, args: list[str], needle: str) -> None:
    r = runner.invoke(app, ["mask", str(kitti06), "--out", str(tmp_path / "o"), "--models-dir", str(models_dir), *args])
    assert r.exit_code == 2, r.output
    assert needle in r.output


def test_mask_cli_missing_calib(kitti06: Path, tmp_path: Path) -> None:
    seq = _mini_kitti(kitti06, tmp_path / "seq", 2)
    (seq / "calib.txt").unlink()
    r = runner.invoke(app, ["mask", str(seq), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "calib" in r.output


def test_models_list_and_verify(models_dir: Path) -> None:
    r = runner.invoke(app, ["models", "--models-dir", str(models_dir)])
    assert r.exit_code == 0, r.output
    for name in ("yolov3-tiny", "yolox-nano", "fastestdet", "yolo11n-int8", "yolov3"):
        assert name in r.output
    r = runner.invoke(app, ["models", "verify", "yolox-nano", "fastestdet", "--models-dir", str(models_dir)])
    assert r.exit_code == 0, r.output


def test_eval_cli_json_and_plot(data_dir: Path, tmp_path: Path) -> None:
    gt = data_dir / "kitti_odometry/dataset/poses/06.txt"
    rows = np.loadtxt(gt)[:40]
    rows[:, 3] += 0.1  # constant x offset: removed by the SE(3) alignment
    est = tmp_path / "est.kitti.txt"
    np.savetxt(est, rows)
    r = runner.invoke(app, ["eval", str(est), str(gt), "--json", "--plot", str(tmp_path / "p.png")])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout[r.stdout.index("{"):])
    assert d["ape.rmse"] < 1e-6 and d["n_frames"] == 40
    assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
    r = runner.invoke(app, ["eval", str(est), str(gt), "--no-align"])
    assert r.exit_code == 0 and "rmse" in r.output


def test_mask_cli_on_raw_euroc(euroc_dir: Path, models_dir: Path, tmp_path: Path) -> None:
    """EuRoC is raw stereo: the sequence is detected, rectified on read, and masked."""
    out = tmp_path / "euroc"
    r = runner.invoke(app, ["mask", str(euroc_dir), "--out", str(out), "--frames", "0-2", "--overlays",
                            "--save-disparity", "--detector", "fastestdet", "--models-dir", str(models_dir)])
    assert r.exit_code == 0, r.output
    left = cv2.imread(str(out / "masks/left/000000.png"), cv2.IMREAD_UNCHANGED)
    assert left.shape == (480, 752)
    d = read_disparity_png(out / "disparity/000001.png")
    # an indoor room 2-8 m away: a dense, plausible disparity after rectification
    assert np.count_nonzero(d > 0) > 0.3 * d.size and 2 < np.median(d[d > 0]) < 60


def test_config_file_documents_every_default(tmp_path: Path) -> None:
    """configs/default.yaml (docs/guide/configuration.md) is exactly what `dynastereo config` prints."""
    shipped = Path(__file__).resolve().parent.parent / "configs" / "default.yaml"
    r = runner.invoke(app, ["config"])
    assert r.exit_code == 0
    assert shipped.read_text() == r.stdout
    bad = tmp_path / "bad.yaml"
    bad.write_text("stereo:\n  blocksize: 9\n")
    r = runner.invoke(app, ["config", str(bad)])
    assert r.exit_code == 2 and "stereo.blocksize" in r.output and "bad.yaml" in r.output


def test_fast_profile_loads_and_differs_only_in_the_measured_key() -> None:
    """configs/fast.yaml (docs/design/masking-cost.md, "Where the 20 ms goes"): a valid configuration that changes
    the one measured setting (the masks' disparity at half size) and nothing else;
    `dynastereo config` prints it back."""
    from dynastereo.config import Config, load_config

    fast = Path(__file__).resolve().parent.parent / "configs" / "fast.yaml"
    cfg, base = load_config(fast), Config()
    assert cfg.stereo.scale == 2
    changed = {f"stereo.{k}" for k in vars(base.stereo) if getattr(cfg.stereo, k) != getattr(base.stereo, k)}
    assert changed == {"stereo.scale"}
    for section in ("detector", "masker", "slam", "motion"):
        assert getattr(cfg, section) == getattr(base, section)
    r = runner.invoke(app, ["config", str(fast)])
    assert r.exit_code == 0 and "scale: 2" in r.stdout


def test_synth_list_needs_no_out(tmp_path: Path) -> None:
    from dynastereo.synth import SCENARIOS

    for args in (["synth", "--list"], ["synth", str(tmp_path / "unused"), "--scenario", "list"]):
        r = runner.invoke(app, args)
        assert r.exit_code == 0, r.output
        assert [ln.split()[0] for ln in r.output.splitlines() if ln.strip()] == list(SCENARIOS)
    assert not (tmp_path / "unused").exists()
    r = runner.invoke(app, ["synth"])
    assert r.exit_code == 2 and "synth needs an output folder OUT (or --list)" in r.output


def test_rate_is_for_folders_not_bags(tmp_path: Path) -> None:
    r = runner.invoke(app, ["run", "--bag", str(tmp_path / "x.bag"), "--out", str(tmp_path / "o"), "--rate", "30"])
    assert r.exit_code == 2 and "--rate is for sequence folders" in r.output
