"""The fault suite's files and signals: truncated model files, calibrations that do not
fit the images, gaps in the frame numbering, interrupts during the shutdown, ``eval`` of
a trajectory away from its run, write errors (disk full, no permission, I/O error), a
broken ``metadata.yaml``, option values without their unit, ``report`` on a killed run,
and the bounded waits of the prefetch hand-over and the live node.  Each on 4-12-frame
copies (symlinks) of KITTI 06 made in a temp dir, through the real command line where
the message matters; no test waits on a clock to signal a process (rows are watched).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import skip_or_fail
from test_faults_inputs import DYN, _env, assert_one_line, cli, stop_then_signal

# --------------------------------------------------------------------------- helpers


def link_copy(kitti06: Path, dst: Path, numbers, times: int | None = None) -> Path:
    """KITTI 06's images ``numbers`` (symlinks, both cameras), calib.txt and the first
    ``times`` lines of times.txt (default: up to the last number) in ``dst``."""
    for cam in ("image_0", "image_1"):
        (dst / cam).mkdir(parents=True)
        for i in numbers:
            (dst / cam / f"{i:06d}.png").symlink_to(kitti06 / cam / f"{i:06d}.png")
    shutil.copy(kitti06 / "calib.txt", dst / "calib.txt")
    n = times if times is not None else max(numbers) + 1
    (dst / "times.txt").write_text("".join(t + "\n" for t in (kitti06 / "times.txt").read_text().split()[:n]))
    return dst


def kitti_layout(kitti06: Path, root: Path, numbers) -> tuple[Path, Path]:
    """``root/sequences/06`` (the images ``numbers``) and ``root/poses/06.txt``: the layout
    in which a ground truth finds its times.txt."""
    seq = link_copy(kitti06, root / "sequences" / "06", numbers)
    (root / "poses").mkdir(parents=True)
    shutil.copy(kitti06.parents[1] / "poses" / "06.txt", root / "poses" / "06.txt")
    return seq, root / "poses" / "06.txt"


def rows(path: Path) -> int:
    return len(path.read_text().splitlines()) if path.is_file() else 0


# --------------------------------------------------------------------------- 2. model files checked for size


def test_darknet_weights_size_follows_from_the_cfg(models_dir: Path, tmp_path: Path) -> None:
    """The expected size matches the official yolov3-tiny file (35,434,956 bytes) and the
    official yolov3 figure (248,007,048 bytes for the standard cfg, built here)."""
    from dynastereo.models.sizecheck import check_darknet_weights, darknet_weights_floats

    d = models_dir / "yolov3-tiny"
    check_darknet_weights(d / "yolov3-tiny.cfg", d / "yolov3-tiny.weights")  # the real file passes

    def conv(f: int, s: int, bn: int = 1) -> str:
        return f"[convolutional]\nbatch_normalize={bn}\nfilters={f}\nsize={s}\nstride=1\npad=1\nactivation=leaky\n"

    cfg = "[net]\nwidth=608\nheight=608\nchannels=3\n" + conv(32, 3)
    for f, n in ((64, 1), (128, 2), (256, 8), (512, 8), (1024, 4)):
        cfg += conv(f, 3) + (conv(f // 2, 1) + conv(f, 3) + "[shortcut]\nfrom=-3\n") * n

    def head(f: int) -> str:
        return (conv(f, 1) + conv(2 * f, 3)) * 3 + conv(255, 1, 0) + "[yolo]\nclasses=80\n"

    cfg += head(512) + "[route]\nlayers=-4\n" + conv(256, 1) + "[upsample]\nstride=2\n[route]\nlayers=-1,61\n"
    cfg += head(256) + "[route]\nlayers=-4\n" + conv(128, 1) + "[upsample]\nstride=2\n[route]\nlayers=-1,36\n"
    cfg += head(128)
    (tmp_path / "yolov3.cfg").write_text(cfg)
    assert 20 + 4 * darknet_weights_floats(tmp_path / "yolov3.cfg") == 248_007_048


def test_truncated_darknet_weights_refused_before_the_first_frame(kitti06: Path, models_dir: Path,
                                                                  tmp_path: Path) -> None:
    d = tmp_path / "m"
    d.mkdir()
    src = models_dir / "yolov3-tiny"
    shutil.copy(src / "yolov3-tiny.cfg", d / "yolov3-tiny.cfg")
    shutil.copy(src / "coco.names", d / "coco.names")
    with open(src / "yolov3-tiny.weights", "rb") as f:
        (d / "yolov3-tiny.weights").write_bytes(f.read(1 << 20))  # 1 MB of the 35 MB
    seq = link_copy(kitti06, tmp_path / "seq", range(4))
    r = cli(["mask", seq, "-o", tmp_path / "out", "--frames", 2, "--detector", d / "yolov3-tiny.cfg"], tmp_path)
    assert_one_line(r, 2, str(d / "yolov3-tiny.weights"), "truncated", "35434956", str(1 << 20))
    assert not (tmp_path / "out" / "masks").exists()


def test_truncated_onnx_refused_with_sizes(kitti06: Path, models_dir: Path, tmp_path: Path) -> None:
    onnx = tmp_path / "FastestDet.onnx"
    data = (models_dir / "fastestdet" / "FastestDet.onnx").read_bytes()
    onnx.write_bytes(data[: len(data) // 3])
    seq = link_copy(kitti06, tmp_path / "seq", range(4))
    r = cli(["mask", seq, "-o", tmp_path / "out", "--frames", 1, "--detector", onnx], tmp_path)
    assert_one_line(r, 2, str(onnx), "truncated", str(len(data) // 3))


# --------------------------------------------------------------------------- 3. calibration sanity


def _kitti_p(fx: float, fy: float, cx: float, cy: float, tx: float) -> str:
    return f"{fx} 0 {cx} {tx} 0 {fy} {cy} 0 0 0 1 0"


@pytest.mark.parametrize("case, p, needles", [
    ("principal-point", (707.0912, 707.0912, 5000, -100), ["principal point", "cx=5000", "1226x370"]),
    ("fx-fy-ratio", (707.0912, 300.0, 601.8873, 183.1104), ["fx=707.091", "fy=300", "ratio"]),
])
def test_kitti_calib_that_does_not_fit_the_images(case: str, p, needles, kitti06: Path, tmp_path: Path) -> None:
    seq = link_copy(kitti06, tmp_path / "seq", range(4))
    fx, fy, cx, cy = p
    (seq / "calib.txt").write_text(f"P0: {_kitti_p(fx, fy, cx, cy, 0)}\nP1: {_kitti_p(fx, fy, cx, cy, -fx * 0.54)}\n")
    r = cli(["run", seq, "-o", tmp_path / "out", "--frames", 2, "--masker", "none"], tmp_path)
    assert_one_line(r, 2, str(seq / "calib.txt"), *needles)


def test_yaml_calib_principal_point_outside_the_image(kitti06: Path, tmp_path: Path) -> None:
    seq = link_copy(kitti06, tmp_path / "seq", range(4))
    y = tmp_path / "calib.yaml"
    y.write_text("fx: 707.0912\nfy: 707.0912\ncx: 5000\ncy: -100\nbaseline: 0.54\n")
    r = cli(["mask", seq, "-o", tmp_path / "out", "--frames", 1, "--masker", "none", "--calib", y], tmp_path)
    assert_one_line(r, 2, str(y), "principal point", "cx=5000", "cy=-100", "margin")
    # inside the margin: accepted
    from dynastereo.io.calib import check_intrinsics, load_stereo_yaml

    y.write_text("fx: 707.0912\nfy: 707.0912\ncx: 1300\ncy: -20\nbaseline: 0.54\n")
    check_intrinsics(load_stereo_yaml(y, (1226, 370)), (1226, 370), y)


# --------------------------------------------------------------------------- 4. gaps in the numbering


def test_gap_keeps_each_images_number_and_stamp(kitti06: Path, models_dir: Path, tmp_path: Path) -> None:
    """000006 missing from both cameras: frames keep their own numbers in every output,
    the TUM stamps are their times.txt lines, run.json names the gap, and eval (run
    folder or a copy away from it) matches the right ground-truth rows."""
    numbers = [0, 1, 2, 3, 4, 5, 7, 8]
    seq, gt = kitti_layout(kitti06, tmp_path / "ds", numbers)
    out = tmp_path / "out"
    r = cli(["run", seq, "-o", out, "--masker", "box", "--save-masks"], tmp_path, models_dir)
    assert r.returncode == 0, r.stderr
    assert "gap" in r.stderr and "000006" in r.stderr  # said, once
    assert [int(x) for x in (out / "trajectory.frames.txt").read_text().split()] == numbers
    times = np.loadtxt(seq / "times.txt")
    stamps = np.loadtxt(out / "trajectory.tum.txt")[:, 0]
    np.testing.assert_allclose(stamps, times[numbers], atol=1e-6)
    assert sorted(p.name for p in (out / "masks" / "left").iterdir()) == [f"{i:06d}.png" for i in numbers]
    assert [json.loads(ln)["frame"] for ln in (out / "objects.jsonl").read_text().splitlines()] == numbers
    run = json.loads((out / "run.json").read_text())
    assert run["frame_gaps"] == [6] and run["status"] == "done" and run["frames_done"] == 8
    # eval in the run folder (frames file / stamps) and a copy away from it (stamps + times.txt)
    away = tmp_path / "away"
    away.mkdir()
    shutil.copy(out / "trajectory.tum.txt", away / "est.tum.txt")
    from dynastereo.eval import evaluate_files
    from dynastereo.eval.trajectory import read_trajectory

    for est in (out / "trajectory.kitti.txt", away / "est.tum.txt"):
        res = evaluate_files(est, gt)
        assert res.n_frames == 8 and "timestamp" in res.matching, (est, res.matching)
        ref = read_trajectory(gt).poses[numbers]
        np.testing.assert_allclose(res.ground_truth.poses, ref)


def test_frames_range_over_a_gap_leaves_the_missing_number_out(kitti06: Path, tmp_path: Path, caplog) -> None:
    from dynastereo.io import KittiSequence
    from dynastereo.io.frames import select_frames

    seq = KittiSequence(link_copy(kitti06, tmp_path / "seq", [0, 1, 2, 4, 5]))
    assert len(seq) == 6 and seq.missing_frames == [3] and seq.available_frames() == [0, 1, 2, 4, 5]
    assert select_frames("3", seq) == [0, 1, 2]  # a count: the first images there are
    assert select_frames(None, seq) == [0, 1, 2, 4, 5]
    with caplog.at_level("WARNING"):
        assert select_frames("2-4", seq) == [2, 4]
    assert "left out" in caplog.text
    assert seq.frame(4).index == 4 and seq.frame(4).left_path.name == "000004.png"
    assert seq.frame(4).timestamp == pytest.approx(float((tmp_path / "seq/times.txt").read_text().split()[4]))
    from dynastereo.errors import InputError, SequenceError

    with pytest.raises(SequenceError, match="gap"):
        seq.frame(3)
    with pytest.raises(InputError, match="gaps"):
        select_frames("3-3", seq)


# --------------------------------------------------------------------------- 5. interrupts are idempotent


def test_signal_handler_is_idempotent_once_stopping() -> None:
    from dynastereo.cli.signals import StopOnSignal
    from dynastereo.errors import Interrupted

    s = StopOnSignal()
    with pytest.raises(Interrupted):
        with s.job():
            s._handle(signal.SIGINT, None)  # deferred: recorded only
            with pytest.raises(Interrupted):
                s.check()  # the frame boundary stops the job ...
            for _ in range(5):  # ... and every later signal during the clean-up is only counted
                s._handle(signal.SIGINT, None)
            assert s.count == 6
            raise Interrupted(signal.SIGINT)


def test_a_shutdown_stuck_for_long_can_still_be_broken(monkeypatch) -> None:
    """The last resort: a signal FORCE_AFTER_S into the shutdown raises again (the job's
    clean-up catches it around the SLAM's shutdown: test below); outside the job, never."""
    from dynastereo.cli import signals
    from dynastereo.errors import Interrupted

    monkeypatch.setattr(signals, "FORCE_AFTER_S", 0.0)
    s = signals.StopOnSignal()
    with pytest.raises(Interrupted):
        with s.job():
            s._handle(signal.SIGTERM, None)
            with pytest.raises(Interrupted):
                s.check()
            with pytest.raises(Interrupted):
                s._handle(signal.SIGTERM, None)
            raise Interrupted(signal.SIGTERM)
    s._handle(signal.SIGTERM, None)  # the job is over: only counted


def test_closing_line_names_only_files_that_exist(tmp_path: Path) -> None:
    from dynastereo.cli.main import _kept_files

    (tmp_path / "trajectory.kitti.txt").write_text("")
    kept = _kept_files(tmp_path, ("run.json", "timing.json", "trajectory.kitti.txt"), "x")()
    assert "trajectory.kitti.txt" in kept and "run.json" not in kept and "timing.json" not in kept
    assert "nothing was written" in _kept_files(tmp_path / "none", ("run.json",), "x")()


def test_many_ctrl_c_during_shutdown_still_write_run_and_timing(kitti06: Path, models_dir: Path,
                                                                tmp_path: Path) -> None:
    out = tmp_path / "out"
    p = subprocess.Popen(DYN + ["run", str(kitti06), "-o", str(out), "--frames", "40", "--masker", "box"],
                         cwd=tmp_path, env=_env(tmp_path, models_dir), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        t0 = time.monotonic()
        while rows(out / "trajectory.frames.txt") < 3:
            assert p.poll() is None, p.stderr.read()
            assert time.monotonic() - t0 < 150, "no 3 rows"
            time.sleep(0.05)
        stop_then_signal(p, signal.SIGINT, group=True)
        sent = 1
        while p.poll() is None and sent < 200:  # Ctrl-C again and again, through the shutdown
            os.killpg(p.pid, signal.SIGINT)
            sent += 1
            time.sleep(0.02)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    line = assert_one_line(subprocess.CompletedProcess(p.args, p.returncode, "", err), 130, "interrupted", "SIGINT")
    for name in ("run.json", "timing.json", "trajectory.kitti.txt"):
        assert name in line and (out / name).is_file(), (name, line)
    run = json.loads((out / "run.json").read_text())
    timing = json.loads((out / "timing.json").read_text())
    n = run["frames_done"]
    assert run["status"] == "interrupted: SIGINT" and 3 <= n < 40
    assert timing["frames_done"] == n == len(timing["frames"])
    for name in ("trajectory.kitti.txt", "trajectory.tum.txt", "trajectory.frames.txt", "objects.jsonl"):
        assert rows(out / name) == n, name


def test_signal_while_the_slam_shuts_down_still_writes_everything(kitti06: Path, tmp_path: Path,
                                                                  monkeypatch) -> None:
    """A second Ctrl-C that lands inside System.shutdown (the BA wait): the files are
    written all the same, consistent with the rows."""
    from dynastereo.api import run_sequence
    from dynastereo.config import Config
    from dynastereo.errors import Interrupted
    from dynastereo.slam.system import System

    real = System.shutdown

    def interrupted_shutdown(self, *a, **kw):
        real(self, *a, **kw)
        raise Interrupted(signal.SIGINT)

    monkeypatch.setattr(System, "shutdown", interrupted_shutdown)
    seq = link_copy(kitti06, tmp_path / "seq", range(4))
    out = tmp_path / "out"
    with pytest.raises(Interrupted):
        run_sequence(seq, out, Config().with_overrides({"masker.kind": "none"}), stereo_check=False)
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "interrupted: SIGINT" and run["frames_done"] == 4
    assert json.loads((out / "timing.json").read_text())["frames_done"] == 4
    assert rows(out / "trajectory.kitti.txt") == 4


# --------------------------------------------------------------------------- 6. eval of a subset away from its run


def test_eval_of_a_subset_copied_away_matches_by_stamp_or_refuses(kitti06: Path, tmp_path: Path) -> None:
    seq, gt = kitti_layout(kitti06, tmp_path / "ds", range(8))
    out = tmp_path / "out"
    r = cli(["run", seq, "-o", out, "--frames", "4-7", "--masker", "none"], tmp_path)
    assert r.returncode == 0, r.stderr
    away = tmp_path / "away"
    away.mkdir()
    shutil.copy(out / "trajectory.tum.txt", away / "sub.tum.txt")
    r = cli(["eval", away / "sub.tum.txt", gt, "--json"], tmp_path)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["n_frames"] == 4 and "timestamp" in d["matching"] and "times.txt" in d["matching"]
    # the same ground truth away from its times.txt: the rows cannot be told apart -> refused
    shutil.copy(gt, away / "gt.txt")
    r = cli(["eval", away / "sub.tum.txt", away / "gt.txt"], tmp_path)
    assert_one_line(r, 2, str(away / "sub.tum.txt"), str(away / "gt.txt"), "no times.txt", "stamps")


def test_eval_refuses_stamps_that_do_not_align(tmp_path: Path) -> None:
    from dynastereo.eval.trajectory import write_tum

    poses = np.tile(np.eye(4), (10, 1, 1))
    poses[:, 0, 3] = np.arange(10)
    write_tum(tmp_path / "gt.tum.txt", poses, np.arange(10) * 0.1)
    write_tum(tmp_path / "est.tum.txt", poses, np.arange(10) * 0.1 + 0.05)  # every stamp 50 ms off
    r = cli(["eval", tmp_path / "est.tum.txt", tmp_path / "gt.tum.txt"], tmp_path)
    assert_one_line(r, 2, "est.tum.txt", "gt.tum.txt", "do not align")


# --------------------------------------------------------------------------- 7. write errors


def _consistent(out: Path, masks: bool) -> int:
    """The outputs of a failed run agree on frames_done; returns it."""
    run = json.loads((out / "run.json").read_text())
    n = run["frames_done"]
    assert run["status"].startswith("failed: ") and "cannot write" in run["status"], run["status"]
    for name in ("trajectory.kitti.txt", "trajectory.tum.txt", "trajectory.frames.txt", "objects.jsonl"):
        assert rows(out / name) == n, (name, rows(out / name), n)
    if (out / "timing.json").is_file():
        assert json.loads((out / "timing.json").read_text())["frames_done"] == n
    if masks:
        for side in ("left", "right"):
            assert len(list((out / "masks" / side).iterdir())) == n, side
    return n


@pytest.fixture
def small_tmpfs(tmp_path: Path):
    """A 100 KiB tmpfs (root only): the disk fills up a few frames into a run."""
    if os.geteuid() != 0:
        skip_or_fail("mounting a tmpfs needs root (disk-full test)")
    d = tmp_path / "small"
    d.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=100k", "tmpfs", str(d)], capture_output=True, text=True)
    if r.returncode != 0:
        skip_or_fail(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield d
    finally:
        subprocess.run(["umount", str(d)], check=False)


@pytest.mark.parametrize("command", ["run", "mask"])
def test_disk_full_names_the_file_and_leaves_a_consistent_folder(command: str, kitti06: Path, models_dir: Path,
                                                                 small_tmpfs: Path, tmp_path: Path) -> None:
    seq = link_copy(kitti06, tmp_path / "seq", range(12))
    out = small_tmpfs / "out"
    extra = ["--save-masks"] if command == "run" else []
    r = cli([command, seq, "-o", out, "--masker", "box", *extra], tmp_path, models_dir)
    line = assert_one_line(r, 2, "no space left on device", "cannot write", str(out))
    if command == "run":
        n = _consistent(out, masks=True)
    else:  # mask: the masks and objects.jsonl agree (timing.json too, when it fit)
        n = rows(out / "objects.jsonl")
        for d in ("masks/left", "masks/right"):
            assert len(list((out / d).iterdir())) == n, d
        if (out / "timing.json").is_file():
            assert json.loads((out / "timing.json").read_text())["frames_done"] == n
    assert 0 < n < 12, line


@pytest.mark.parametrize("command", ["export-bag.bag", "export-bag.db3", "export-bag.mcap", "synth", "eval-plot"])
def test_disk_full_other_commands_name_the_file(command: str, kitti06: Path, small_tmpfs: Path,
                                                tmp_path: Path) -> None:
    gt = kitti06.parents[1] / "poses" / "06.txt"
    if command.startswith("export-bag"):
        target = small_tmpfs / f"x{Path(command).suffix}"
        args = ["export-bag", link_copy(kitti06, tmp_path / "seq", range(5)), target]
    elif command == "synth":
        target = small_tmpfs / "syn"
        args = ["synth", target, "--frames", 30, "--size", "320x96"]
    else:
        target = small_tmpfs / "plot.png"
        args = ["eval", gt, gt, "--plot", target]
        (small_tmpfs / "filler").write_bytes(b"\0" * (96 << 10))  # one page left: less than the plot
    full = "disk is full" if command.endswith("db3") else "no space left on device"
    assert_one_line(cli(args, tmp_path), 2, str(target), full)


SPECIAL = {  # files whose writes fail in the kernel, for root too
    "ENOSPC": Path("/dev/full"),
    "EACCES": Path("/sys/kernel/notes"),
    "EIO": Path("/proc/version"),
}


@pytest.mark.parametrize("err", list(SPECIAL))
@pytest.mark.parametrize("where", ["mask-of-frame-2", "trajectory"])
def test_write_error_on_an_output(err: str, where: str, kitti06: Path, models_dir: Path, tmp_path: Path,
                                  monkeypatch) -> None:
    """ENOSPC / EACCES / EIO from the kernel (an output linked to /dev/full,
    /sys/kernel/notes, /proc/version; EACCES by chmod when not root): OutputError naming
    the file, every output at the frames done, run.json "failed: ..."."""
    import dynastereo.api as api
    import dynastereo.runtime.job as runtime_job
    from dynastereo.config import Config
    from dynastereo.errors import OutputError

    target = SPECIAL[err]
    out = tmp_path / "out"
    (out / "masks" / "left").mkdir(parents=True)
    (out / "masks" / "right").mkdir(parents=True)
    name = out / "masks" / "left" / "000002.png" if where.startswith("mask") else out / "trajectory.tum.txt"
    if err == "EACCES" and os.geteuid() != 0:
        name.write_bytes(b"")
        name.chmod(0o444)
    elif not target.exists():
        pytest.skip(f"{target} not here")
    else:
        name.symlink_to(target)
    monkeypatch.setattr(runtime_job, "prepare_output_dir", lambda out, **kw: Path(out))  # keep the planted file
    seq = link_copy(kitti06, tmp_path / "seq", range(4))
    cfg = Config().with_overrides({"masker.kind": "box"})
    with pytest.raises(OutputError, match=str(name.name)) as e:
        api.run_sequence(seq, out, cfg, models_dir=models_dir, save_masks=True, stereo_check=False)
    assert "\n" not in str(e.value)
    if name.is_symlink() or not name.exists():
        name.unlink(missing_ok=True)
    else:
        name.chmod(0o644)
        name.unlink()
    n = _consistent(out, masks=True)
    assert n == (2 if where.startswith("mask") else 0)


def test_row_file_rolls_back_a_failed_row(tmp_path: Path) -> None:
    from dynastereo.errors import OutputError
    from dynastereo.io.outputs import RowFile

    p = tmp_path / "rows.txt"
    with RowFile(p) as f:
        f.append("a\n")
        f.append("b\n")
        f._f.close()  # the next write fails
        f._f = open(os.devnull, "rb", buffering=0)
        with pytest.raises(OutputError, match="rows.txt"):
            f.append("c\n")
        assert f.rows == 2
    assert p.read_text() == "a\nb\n"


# --------------------------------------------------------------------------- 8. / 9. bags and option units


def test_malformed_metadata_yaml_names_the_line(tmp_path: Path) -> None:
    bag = tmp_path / "bag2"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: {sqlite3\n"
                                       "  duration: 1\n")
    r = cli(["run", "--bag", bag, "-o", tmp_path / "out"], tmp_path)
    line = assert_one_line(r, 2, "metadata.yaml", "yaml syntax error: line")
    assert "storage_identifier" not in line.split("line", 1)[0]


@pytest.mark.parametrize("args, needles", [
    (["run", "--bag", "x.bag", "-o", "o", "--sync-tolerance", "-1"], ["--sync-tolerance", "ms", "-1"]),
    (["eval", "a.txt", "b.txt", "--rpe-delta", "0"], ["--rpe-delta", "frames"]),
    (["report", ".", "--overlays", "-1"], ["--overlays"]),
    (["bench", ".", "-o", "o", "--repeats", "0"], ["--repeats"]),
    (["bench", ".", "-o", "o", "--workers", "0"], ["--workers"]),
    (["vocab", ".", "-o", "v.npz", "--k", "1"], ["--k"]),
    (["vocab", ".", "-o", "v.npz", "--levels", "0"], ["--levels"]),
    (["vocab", ".", "-o", "v.npz", "--features", "0"], ["--features"]),
    (["demo", "--out", "o", "--frames", "1"], ["--frames", "2 poses"]),
])
def test_option_errors_name_the_option_and_unit(args, needles, tmp_path: Path) -> None:
    assert_one_line(cli(args, tmp_path), 2, *needles)


def test_negative_time_offset_names_the_option(kitti06: Path, tmp_path: Path) -> None:
    seq = link_copy(kitti06, tmp_path / "seq", range(2))
    r = cli(["export-bag", seq, tmp_path / "x.bag", "--time-offset", "-5"], tmp_path)
    assert_one_line(r, 2, "--time-offset", "-5 s")


# --------------------------------------------------------------------------- 10. report on a killed run


def test_report_on_a_killed_run_is_partial(kitti06: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    seq = link_copy(kitti06, tmp_path / "seq", range(12))
    p = subprocess.Popen(DYN + ["run", str(seq), "-o", str(out), "--masker", "none"], cwd=tmp_path,
                         env=_env(tmp_path, None), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.monotonic()
        while rows(out / "trajectory.frames.txt") < 3:
            assert p.poll() is None, p.stderr.read()
            assert time.monotonic() - t0 < 150
            time.sleep(0.05)
        p.send_signal(signal.SIGSTOP)  # then killed: no clean-up at all
        p.kill()
        p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    assert json.loads((out / "run.json").read_text())["status"] == "running"
    n = min(rows(out / n) for n in ("trajectory.kitti.txt", "trajectory.tum.txt", "trajectory.frames.txt"))
    r = cli(["report", out, "--gt", kitti06.parents[1] / "poses" / "06.txt"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert "partial" in r.stdout and "interrupted" in r.stdout
    page = (out / "report.html").read_text()
    assert "partial report" in page and f"{n} trajectory rows" in page
    # without run.json at all (killed before: an older run): still a partial report
    (out / "run.json").unlink()
    r = cli(["report", out], tmp_path)
    assert r.returncode == 0 and "partial" in r.stdout, r.stderr


# --------------------------------------------------------------------------- bounded waits


def test_prefetch_hand_over_is_bounded_and_recorded(kitti06: Path, tmp_path: Path, monkeypatch) -> None:
    """The prefetch thread stops answering (a stuck detector): the frame is masked inline
    after the bound, the run goes on without prefetch, run.json records the fallback."""
    import dynastereo.runtime.pipelining as pipelining
    from dynastereo.api import run_sequence
    from dynastereo.config import Config
    from dynastereo.runtime.processor import FrameProcessor

    real = FrameProcessor.mask
    stuck = threading.Event()

    def mask(self, item):
        if item.index == 2 and threading.current_thread().name == "dynastereo-mask":
            stuck.wait(30)  # the masking thread hangs on frame 2
        return real(self, item)

    monkeypatch.setattr(FrameProcessor, "mask", mask)
    monkeypatch.setattr(pipelining, "HAND_OVER_TIMEOUT_S", 0.5)
    seq = link_copy(kitti06, tmp_path / "seq", range(5))
    out = tmp_path / "out"
    try:
        run_sequence(seq, out, Config().with_overrides({"masker.kind": "none"}), stereo_check=False)
    finally:
        stuck.set()
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "done" and run["frames_done"] == 5
    assert [f["frame"] for f in run["fallbacks"]] == [2] and run["fallbacks"][0]["what"] == "prefetch"


def test_live_node_shutdown_does_not_wait_forever_on_a_stuck_tracker(kitti06: Path, monkeypatch) -> None:
    import dynastereo.ros.core as core_mod
    from dynastereo.config import Config
    from dynastereo.io import KittiSequence
    from dynastereo.ros.core import StereoNodeCore

    monkeypatch.setattr(core_mod, "SLAM_LOCK_TIMEOUT_S", 0.3)
    seq = KittiSequence(kitti06)
    core = StereoNodeCore(Config().with_overrides({"masker.kind": "none"}), calibration=seq.calibration)
    held, release = threading.Event(), threading.Event()

    def hold():  # the tracker thread, stuck inside the SLAM
        with core._slam_lock:
            held.set()
            release.wait(30)

    t = threading.Thread(target=hold, daemon=True)
    t.start()
    held.wait(5)
    try:
        t0 = time.monotonic()
        core.shutdown()
        poses, _ = core.trajectory()
        assert time.monotonic() - t0 < 5 and len(poses) == 0
        whats = [f["what"] for f in core.status()["fallbacks"]]
        assert "shutdown" in whats and "trajectory" in whats
    finally:
        release.set()
        t.join(5)
