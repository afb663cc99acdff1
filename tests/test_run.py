"""`dynastereo run` and `dynastereo demo`: the output contracts, end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from dynastereo.cli.main import app
from dynastereo.demo import run_demo
from dynastereo.eval import evaluate_files, read_trajectory

runner = CliRunner()


def test_run_cli_writes_the_contract_with_a_revisit(kitti06: Path, models_dir: Path, data_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    r = runner.invoke(app, ["run", str(kitti06), "--out", str(out), "--frames", "0-11,4-6",
                            "--masker", "outline", "--detector", "yolox-nano", "--models-dir", str(models_dir)])
    assert r.exit_code == 0, r.output
    kitti = np.loadtxt(out / "trajectory.kitti.txt")
    tum = np.loadtxt(out / "trajectory.tum.txt")
    assert kitti.shape == (15, 12) and tum.shape == (15, 8)
    assert np.allclose(kitti[0], np.eye(4)[:3].ravel(), atol=1e-9)  # world = first frame
    times = np.loadtxt(kitti06 / "times.txt")
    assert np.allclose(tum[:, 0], times[list(range(12)) + [4, 5, 6]])
    timing = json.loads((out / "timing.json").read_text())
    assert timing["summary"]["fps"] > 0
    for stage in ("detect", "features", "stereo", "track", "masking"):
        assert stage in timing["summary"], stage
    assert len(timing["frames"]) == 15
    run = json.loads((out / "run.json").read_text())
    assert run["frames_done"] == 15 and run["frames_tracked"] + run["frames_lost"] == 15
    assert run["keyframes"] >= 1 and run["map_points"] > 100
    assert run["config"]["masker"]["kind"] == "outline" and "gtsam" in run["versions"]
    # eval reads the trajectory with its frame indices (revisit-aware)
    res = evaluate_files(out / "trajectory.kitti.txt", data_dir / "kitti_odometry/dataset/poses/06.txt")
    assert res.n_frames == 15 and np.isfinite(res.ape["rmse"])
    assert "FPS" in r.output


def test_run_api_unmasked_short(kitti06: Path, tmp_path: Path) -> None:
    from dynastereo.api import run_sequence
    from dynastereo.config import Config

    res = run_sequence(kitti06, tmp_path / "r", Config().with_overrides({"masker.kind": "none"}), frames=6)
    assert res.poses.shape == (6, 3, 4) and res.frames == list(range(6))
    traj = read_trajectory(tmp_path / "r/trajectory.kitti.txt")
    assert len(traj) == 6
    # KITTI 06 drives forward (+z) about 1 m per frame
    assert 3.0 < traj.positions[-1, 2] < 7.0


def test_demo_runs_offline_with_the_oracle(tmp_path: Path) -> None:
    from rich.console import Console

    console = Console(record=True, width=160)
    rows = run_demo(tmp_path / "demo", frames=16, size=(480, 144), models_dir=tmp_path / "no-models",
                    maskers=("none", "outline"), console=console)
    text = console.export_text()
    assert "ORACLE" in text and "ATE RMSE" in text
    assert [r.masker for r in rows] == ["none", "outline"]
    assert rows[0].iou_left is None and rows[1].iou_left > 0.5 and rows[1].iou_right > 0.4
    assert all(np.isfinite(r.ate_rmse) and r.fps > 0 for r in rows)
    # convoy: the truck ahead at the camera's speed breaks the unmasked SLAM; masking fixes it
    assert rows[1].ate_rmse < 0.3 and rows[0].ate_rmse > 3 * rows[1].ate_rmse
    assert (tmp_path / "demo/trajectories.png").read_bytes()[:4] == b"\x89PNG"
    d = json.loads((tmp_path / "demo/demo.json").read_text())
    assert d["detector"] == "oracle" and len(d["rows"]) == 2
    # an HTML report per run, its path printed
    for label in ("none", "outline"):
        report = tmp_path / f"demo/run_{label}/report.html"
        assert d["reports"][label] == str(report) and f"report ({label}): {report}" in text
        assert '<td data-key="ape.rmse">' in report.read_text()
