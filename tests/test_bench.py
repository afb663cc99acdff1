"""``dynastereo bench``: discovery, the local pool and Ray give the same numbers, a killed
job is retried and reported, a failing job never stops the others, a second invocation
reuses finished jobs, tables.md holds the numbers of results.json."""

from __future__ import annotations

import json
import math
import shutil

import pytest

from conftest import REQUIRE
from dynastereo.bench import discover, run_bench, select
from dynastereo.bench.tables import cell
from dynastereo.errors import InputError

FRAMES = 12
SEQS = ("convoy", "oncoming")


@pytest.fixture(scope="module")
def synth_root(tmp_path_factory):
    """Two small synthetic sequences, plus one whose calibration is unreadable."""
    from dynastereo.synth import generate

    root = tmp_path_factory.mktemp("bench_root")
    for name in SEQS:
        generate(root / name, name, frames=FRAMES, seed=0)
    shutil.copytree(root / "convoy", root / "zbad")
    (root / "zbad" / "sequences" / "00" / "calib.txt").write_text("P0: not a matrix\n")
    return root


def _bench(root, out, engine, **kw):
    return run_bench(root, out, maskers="none,box", repeats=1, overrides={"detector.name": "oracle"},
                     engine=engine, workers=2, plots=engine == "local", **kw)


def _metrics(result):
    return {r["key"]: r["metrics"] for r in result.runs if r["status"] == "done"}


@pytest.fixture(scope="module")
def local_run(synth_root, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_local")
    mp = pytest.MonkeyPatch()
    mp.setenv("DYNASTEREO_BENCH_FAULT", "convoy/00/box/r0")  # its first attempt SIGKILLs its worker
    seen: list[dict] = []
    try:
        return out, _bench(synth_root, out, "local", progress=seen.append), seen
    finally:
        mp.undo()


def test_discovery_of_synth_outputs_and_selection(synth_root):
    seqs = discover(synth_root)
    assert [s.name for s in seqs] == ["convoy/00", "oncoming/00", "zbad/00"]
    assert all(s.format == "kitti" and s.ground_truth.name == "00.txt" for s in seqs)
    assert [s.name for s in select(seqs, "convoy/*,oncoming/00")] == ["convoy/00", "oncoming/00"]
    assert [s.name for s in select(seqs, "00-10")] == [s.name for s in seqs]  # ranges match the last part
    with pytest.raises(InputError, match="matches none"):
        select(seqs, "07")


def test_discovery_of_real_layouts(data_dir):
    kitti = discover(data_dir / "kitti_odometry" / "dataset")
    assert [s.name for s in kitti] == ["03", "06"]
    assert [s.ground_truth.name for s in kitti] == ["03.txt", "06.txt"]
    assert [s.name for s in select(kitti, "00-05")] == ["03"]
    everything = {s.name: s for s in discover(data_dir)}
    assert everything["kitti_odometry/dataset/03"].format == "kitti"
    raw = [s for s in everything.values() if s.format == "kitti_raw"]
    assert [s.path.name for s in raw] == ["2011_09_26_drive_0001_sync"] and raw[0].ground_truth == raw[0].path / "oxts"
    euroc = [s for s in everything.values() if s.format == "euroc"]
    assert [s.name for s in euroc] == ["euroc/V1_01_easy_first40"]


def test_killed_job_is_retried_and_failures_do_not_stop_the_others(local_run):
    out, res, _ = local_run
    runs = {r["key"]: r for r in res.runs}
    assert len(runs) == 6
    killed = runs["convoy/00/box/r0"]
    assert killed["status"] == "done" and killed["attempts"] == 2
    assert "killed by SIGKILL" in killed["errors"][0]
    for key in ("zbad/00/none/r0", "zbad/00/box/r0"):  # bad calibration: fails on both attempts
        assert runs[key]["status"] == "failed" and runs[key]["attempts"] == 2
        assert "CalibrationError" in runs[key]["error"] and "calib.txt" in runs[key]["error"]
    good = [r for k, r in runs.items() if not k.startswith("zbad")]
    assert all(r["status"] == "done" for r in good)
    # the masks matter on the convoy (a truck at the rig's speed fills the view)
    assert runs["convoy/00/box/r0"]["metrics"]["ape.rmse"] < 0.2 < runs["convoy/00/none/r0"]["metrics"]["ape.rmse"]
    stored = json.loads((out / "results.json").read_text())
    assert stored["bench"]["complete"] is True
    assert {r["key"]: r["status"] for r in stored["runs"]} == {k: r["status"] for k, r in runs.items()}
    assert (out / "plots" / "ate.png").is_file() and (out / "plots" / "trajectories_convoy_00.png").is_file()


def test_progress_counts_frames_and_jobs(local_run):
    _, _, seen = local_run
    last = seen[-1]
    assert last["jobs_done"] == last["jobs_total"] == 6 and last["jobs_failed"] == 2
    assert last["frames_total"] == 4 * FRAMES  # the zbad sequence cannot be opened: 0 frames
    assert last["frames_done"] == last["frames_total"] and not last["running"]
    assert any(0 < p["frames_done"] < last["frames_total"] and p["running"] for p in seen)  # frames as they go
    assert ("failed", "convoy/00/box/r0") in [p["event"] for p in seen]


def test_job_numbers_are_those_of_run_and_eval(local_run, synth_root):
    from dynastereo.api import run_sequence
    from dynastereo.config import Config
    from dynastereo.eval import evaluate_files, to_json_dict

    out, res, _ = local_run
    rec = next(r for r in res.runs if r["key"] == "oncoming/00/box/r0")
    single = out / "single"
    cfg = Config().with_overrides({"detector.name": "oracle", "masker.kind": "box"})
    run_sequence(synth_root / "oncoming" / "sequences" / "00", single, cfg)
    ref = to_json_dict(evaluate_files(single / "trajectory.kitti.txt", synth_root / "oncoming" / "poses" / "00.txt"))
    assert {k: rec["metrics"][k] for k in ref} == ref
    assert rec["frames"] == FRAMES and rec["overhead_s"] >= 0 and rec["timing_ms"]["track"] > 0


def test_tables_hold_the_numbers_of_results(local_run):
    out, res, _ = local_run
    tables = (out / "tables.md").read_text()
    for r in res.runs:
        if r["status"] != "done":
            continue
        m = r["metrics"]
        row = next(line for line in tables.splitlines() if line.startswith(f"| {r['sequence']} |")
                   and cell([m["ape.rmse"]]) in line)
        assert math.isclose(float(row.split("|")[2 if r["masker"] == "none" else 3]), m["ape.rmse"], abs_tol=1e-4)
    assert "| zbad/00/box/r0 | failed | 2 | CalibrationError" in tables
    assert "convoy/00/box/r0: WorkerDied" in tables


def test_second_invocation_skips_finished_jobs(local_run, synth_root):
    out, first, _ = local_run
    stamp = (out / "runs" / "oncoming" / "00" / "none" / "r0" / "result.json").stat().st_mtime_ns
    again = _bench(synth_root, out, "local", sequences="convoy/*,oncoming/*")
    assert len(again.runs) == 4 and all(r.get("reused") for r in again.runs)
    killed = next(r for r in again.runs if r["key"] == "convoy/00/box/r0")
    assert killed["attempts"] == 2 and "WorkerDied" in killed["errors"][0]  # the record keeps its history
    assert _metrics(again) == {k: v for k, v in _metrics(first).items() if not k.startswith("zbad")}
    assert (out / "runs" / "oncoming" / "00" / "none" / "r0" / "result.json").stat().st_mtime_ns == stamp


def test_ray_gives_the_numbers_of_the_process_pool(local_run, synth_root, tmp_path, monkeypatch):
    try:
        import ray  # noqa: F401
    except ImportError:
        if REQUIRE:
            pytest.fail("ray is not installed (pip install -e '.[bench]') [DYNASTEREO_REQUIRE_DATA=1]")
        pytest.skip("ray is not installed (pip install -e '.[bench]')")
    monkeypatch.setenv("DYNASTEREO_BENCH_FAULT", "oncoming/00/none/r0")
    res = _bench(synth_root, tmp_path, "ray", sequences="oncoming/*")
    runs = {r["key"]: r for r in res.runs}
    assert all(r["status"] == "done" for r in runs.values())
    assert runs["oncoming/00/none/r0"]["attempts"] == 2 and "WorkerDied" in runs["oncoming/00/none/r0"]["errors"][0]
    _, local, _ = local_run
    assert _metrics(res) == {k: v for k, v in _metrics(local).items() if k.startswith("oncoming")}


def test_cli_bench_prints_the_tables(local_run, synth_root):
    from typer.testing import CliRunner

    from dynastereo.cli.main import app

    out, _, _ = local_run
    r = CliRunner().invoke(app, ["bench", str(synth_root), "--out", str(out), "--maskers", "none,box",
                                 "--repeats", "1", "--detector", "oracle", "--no-plots", "--sequences", "c*,o*"])
    assert r.exit_code == 0, r.output
    assert "ATE RMSE" in r.output and "4 of 4 runs done (4 reused), 0 failed" in r.output
    bad = CliRunner().invoke(app, ["bench", str(synth_root), "--out", str(out), "--maskers", "none,orb"])
    assert bad.exit_code == 2 and "--maskers: unknown orb" in bad.output


def test_euroc_ground_truth_becomes_rectified_left_camera_poses(euroc_dir, tmp_path):
    import numpy as np

    from dynastereo.bench.discover import euroc_ground_truth_tum
    from dynastereo.eval import read_trajectory
    from dynastereo.io import open_sequence
    from dynastereo.io.calib import read_yaml_file

    seq = open_sequence(euroc_dir)
    ns = seq.timestamps_ns[:3]
    rows = np.zeros((3, 17))
    rows[:, 0] = ns
    rows[:, 1:4] = [[0, 0, 0], [1, 0, 0], [1, 2, 0]]
    rows[:, 4] = 1.0  # identity body rotation (q = w, x, y, z)
    csv = tmp_path / "data.csv"
    np.savetxt(csv, rows, delimiter=",", header="timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z,...")
    traj = read_trajectory(euroc_ground_truth_tum(csv, seq, tmp_path / "gt.tum.txt"))
    T_BS = np.asarray(read_yaml_file(euroc_dir / "mav0" / "cam0" / "sensor.yaml")["T_BS"]["data"]).reshape(4, 4)
    np.testing.assert_allclose(traj.timestamps, ns * 1e-9, atol=1e-9)
    np.testing.assert_allclose(traj.positions, rows[:, 1:4] + T_BS[:3, 3], atol=1e-6)
    np.testing.assert_allclose(traj.poses[0][:3, :3], T_BS[:3, :3] @ seq.rectifier.R1.T, atol=1e-6)
