"""The fault suite: wrong inputs, unusable outputs and interrupts, each through the real
``dynastereo`` command line in a subprocess, on small copies of KITTI 06 built in a temp
dir.  Every fault must end in one line on stderr (no traceback) with exit 2 -- or 130 /
143 for SIGINT / SIGTERM -- and keep what was done complete.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

N_FRAMES = 4  # frames copied into each mini sequence
DYN = [sys.executable, "-m", "dynastereo.cli.main"]


# --------------------------------------------------------------------------- helpers


def _env(tmp_path: Path, models_dir: Path | None) -> dict[str, str]:
    env = dict(os.environ)
    src = str(Path(__file__).resolve().parents[1] / "src")
    env["PYTHONPATH"] = os.pathsep.join([src, env["PYTHONPATH"]]) if env.get("PYTHONPATH") else src
    env["DYNASTEREO_CACHE_DIR"] = str(tmp_path / "cache")
    env.pop("DYNASTEREO_LOG", None)
    env["MPLBACKEND"] = "Agg"
    if models_dir is not None:
        env["DYNASTEREO_MODELS"] = str(models_dir)
    return env


def cli(args: list, tmp_path: Path, models_dir: Path | None = None, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run(DYN + [str(a) for a in args], cwd=tmp_path, env=_env(tmp_path, models_dir),
                          capture_output=True, text=True, timeout=timeout)


def lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.strip()]


def assert_one_line(r: subprocess.CompletedProcess, rc: int, *needles: str) -> str:
    """Exit code ``rc``, one stderr line without a traceback, holding every needle."""
    err = lines(r.stderr)
    assert "Traceback" not in r.stderr and "Error:" not in r.stderr.replace("error:", ""), r.stderr
    assert r.returncode == rc, (r.returncode, r.stderr, r.stdout[-2000:])
    assert len(err) == 1, r.stderr
    for n in needles:
        assert n.lower() in err[0].lower(), (n, err[0])
    return err[0]


def mini06(kitti06: Path, dst: Path, n: int = N_FRAMES) -> Path:
    """The first ``n`` frames of KITTI 06 (gray pair, calib.txt, times.txt) in ``dst``."""
    for cam in ("image_0", "image_1"):
        (dst / cam).mkdir(parents=True)
        for i in range(n):
            shutil.copy(kitti06 / cam / f"{i:06d}.png", dst / cam / f"{i:06d}.png")
    shutil.copy(kitti06 / "calib.txt", dst / "calib.txt")
    (dst / "times.txt").write_text("".join(ln + "\n" for ln in (kitti06 / "times.txt").read_text().split()[:n]))
    return dst


@pytest.fixture
def seq(kitti06: Path, tmp_path: Path) -> Path:
    return mini06(kitti06, tmp_path / "seq")


def _images(seq: Path, cam: str) -> list[Path]:
    return sorted((seq / cam).glob("*.png"))


def _unwritable_dir(tmp_path: Path) -> Path:
    """A folder nobody may write in (as root, where permissions do not apply: /proc/self)."""
    if os.geteuid() == 0:
        return Path("/proc/self")
    d = tmp_path / "readonly"
    d.mkdir()
    d.chmod(0o555)
    return d


# --------------------------------------------------------------------------- faults of the input pair

def _identical(seq: Path) -> None:
    for p in _images(seq, "image_0"):
        shutil.copy(p, seq / "image_1" / p.name)


def _swapped(seq: Path) -> None:
    tmp = seq / "swap"
    (seq / "image_0").rename(tmp)
    (seq / "image_1").rename(seq / "image_0")
    tmp.rename(seq / "image_1")


def _unrectified(seq: Path) -> None:  # right camera 4 px lower: the rows no longer line up
    for p in _images(seq, "image_1"):
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(p), cv2.warpAffine(img, np.float32([[1, 0, 0], [0, 1, 4]]), img.shape[1::-1]))


STEREO_FAULTS = {"identical": (_identical, "identical"), "swapped": (_swapped, "swapped"),
                 "unrectified": (_unrectified, "do not line up")}


@pytest.mark.parametrize("fault, command", [("identical", "run"), ("identical", "mask"), ("swapped", "run"),
                                            ("swapped", "mask"), ("unrectified", "run")])
def test_stereo_fault_refused(fault: str, command: str, seq: Path, models_dir: Path, tmp_path: Path) -> None:
    make, needle = STEREO_FAULTS[fault]
    make(seq)
    r = cli([command, seq, "-o", tmp_path / "out", "--frames", 2], tmp_path, models_dir)
    line = assert_one_line(r, 2, needle, "stereo check", "--no-stereo-check", str(seq.name))
    assert "frame" in line
    assert not (tmp_path / "out" / "trajectory.kitti.txt").exists()


def test_a_camera_failing_mid_run_stops_the_run_keeping_what_was_done(seq: Path, tmp_path: Path,
                                                                        monkeypatch) -> None:
    """The check runs again every CHECK_EVERY frames: the right camera starts sending the
    left image at frame 2 -> the run stops at the next check (frame 3) with the one-line
    error, and the rows, run.json and timing.json of the frames done are kept."""
    import json

    from dynastereo.api import run_sequence
    from dynastereo.config import Config
    from dynastereo.errors import StereoCheckError
    from dynastereo.io import stereo_check

    for p in _images(seq, "image_0")[2:]:
        shutil.copy(p, seq / "image_1" / p.name)
    monkeypatch.setattr(stereo_check, "CHECK_EVERY", 3)
    out = tmp_path / "out"
    with pytest.raises(StereoCheckError, match=r"frame 3 .*identical"):
        run_sequence(seq, out, Config().with_overrides({"masker.kind": "none"}))
    run = json.loads((out / "run.json").read_text())
    rows = (out / "trajectory.kitti.txt").read_text().splitlines()
    assert run["frames_done"] == len(rows) == 4 and "StereoCheckError" in run["error"]
    assert json.loads((out / "timing.json").read_text())["frames_done"] == 4


def test_no_stereo_check_overrides(seq: Path, tmp_path: Path) -> None:
    _identical(seq)
    r = cli(["run", seq, "-o", tmp_path / "out", "--frames", 2, "--masker", "none", "--no-stereo-check"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert len((tmp_path / "out" / "trajectory.kitti.txt").read_text().splitlines()) == 2


def test_a_good_run_passes_and_writes_0644(seq: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    r = cli(["run", seq, "-o", out, "--frames", 3, "--masker", "none"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    umask = os.umask(0)
    os.umask(umask)
    for p in out.iterdir():
        assert p.stat().st_mode & 0o777 == 0o666 & ~umask, p
    assert json.loads((out / "run.json").read_text())["frames_done"] == 3


# --------------------------------------------------------------------------- models


def _models_copy(models_dir: Path, dst: Path, name: str = "fastestdet") -> Path:
    shutil.copytree(models_dir / name, dst / name)
    for p in (dst / name).iterdir():
        p.chmod(0o644)
    return dst


def test_model_with_a_wrong_checksum_is_refused(seq: Path, models_dir: Path, tmp_path: Path) -> None:
    d = _models_copy(models_dir, tmp_path / "models")
    onnx = d / "fastestdet" / "FastestDet.onnx"
    data = bytearray(onnx.read_bytes())
    data[len(data) // 2] ^= 0xFF  # same size, another sha256
    onnx.write_bytes(bytes(data))
    r = cli(["mask", seq, "-o", tmp_path / "out", "--frames", 1, "--detector", "fastestdet", "--models-dir", d],
            tmp_path)
    assert_one_line(r, 2, str(onnx), "sha256", "models download fastestdet")


def test_model_checksum_is_cached(models_dir: Path, tmp_path: Path, monkeypatch) -> None:
    from dynastereo.models import registry

    monkeypatch.setenv(registry.ENV_CACHE, str(tmp_path / "cache"))
    onnx = models_dir / "fastestdet" / "FastestDet.onnx"
    first = registry.cached_sha256(onnx)
    assert first == registry.get_spec("fastestdet").main_file.sha256
    calls = []
    monkeypatch.setattr(registry, "sha256_file", lambda p: calls.append(p) or "x")
    assert registry.cached_sha256(onnx) == first and not calls  # unchanged file: no hashing
    copy = tmp_path / "m.onnx"
    shutil.copy(onnx, copy)
    registry.cached_sha256(copy)
    os.utime(copy, ns=(time.time_ns(), time.time_ns() + 10**9))  # touched: hashed again
    assert registry.cached_sha256(copy) == "x" and len(calls) == 2


def test_model_not_in_the_registry_loads_with_a_warning(seq: Path, models_dir: Path, tmp_path: Path) -> None:
    onnx = pytest.importorskip("onnx")
    model = onnx.load(str(models_dir / "fastestdet" / "FastestDet.onnx"))
    model.producer_name = "retrained-by-a-user"
    mine = tmp_path / "mine.onnx"
    onnx.save(model, str(mine))
    r = cli(["mask", seq, "-o", tmp_path / "out", "--frames", 1, "--detector", mine], tmp_path, models_dir)
    assert r.returncode == 0, r.stderr
    assert "not in the model registry" in r.stderr and str(mine) in r.stderr
    assert (tmp_path / "out" / "masks" / "left" / "000000.png").is_file()


# --------------------------------------------------------------------------- output folders and paths


def test_earlier_run_refused_then_replaced_with_overwrite(seq: Path, models_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    args = ["mask", seq, "-o", out, "--masker", "box", "--overlays"]
    assert cli(args + ["--frames", 4], tmp_path, models_dir).returncode == 0
    (out / "notes.txt").write_text("mine")  # not ours: kept
    r = cli(args + ["--frames", 2], tmp_path, models_dir)
    assert_one_line(r, 2, "earlier run", "--overwrite", str(out.name))
    assert len(list((out / "masks" / "left").iterdir())) == 4  # refused: nothing touched
    r = cli(args + ["--frames", 2, "--overwrite"], tmp_path, models_dir)
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in (out / "masks" / "left").iterdir()) == ["000000.png", "000001.png"]
    assert len(list((out / "overlays").iterdir())) == 2
    assert (out / "notes.txt").read_text() == "mine"


def test_run_into_a_mask_folder_refused(seq: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    (out / "masks" / "left").mkdir(parents=True)
    r = cli(["run", seq, "-o", out, "--frames", 2, "--masker", "none"], tmp_path)
    assert_one_line(r, 2, "earlier run", "--overwrite")


def test_synth_earlier_sequence_refused(tmp_path: Path) -> None:
    out = tmp_path / "syn"
    (out / "sequences" / "00").mkdir(parents=True)
    r = cli(["synth", out, "--frames", 2, "--size", "320x96"], tmp_path)
    assert_one_line(r, 2, "earlier run", "--overwrite")


def test_export_bag_existing_refused(seq: Path, tmp_path: Path) -> None:
    bag = tmp_path / "x.bag"
    bag.write_bytes(b"old")
    r = cli(["export-bag", seq, bag, "--frames", 1], tmp_path)
    assert_one_line(r, 2, "exists", "--overwrite")
    r = cli(["export-bag", seq, bag, "--frames", 2, "--overwrite"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert bag.read_bytes().startswith(b"#ROSBAG V2.0")


def _plot_cmd(seq, out, tmp_path, kitti06):
    gt = kitti06.parents[1] / "poses" / "06.txt"
    est = tmp_path / "est.txt"
    shutil.copy(gt, est)
    return ["eval", est, gt, "--plot", out / "plot.png"]


OUTPUT_COMMANDS = {
    "mask": lambda seq, out, tmp_path, k: ["mask", seq, "-o", out, "--frames", 1],
    "run": lambda seq, out, tmp_path, k: ["run", seq, "-o", out, "--frames", 1, "--masker", "none"],
    "run-save-map": lambda seq, out, tmp_path, k: ["run", seq, "-o", tmp_path / "ok", "--frames", 2, "--masker",
                                                   "none", "--save-map", out / "map.dsmap"],
    "export-bag": lambda seq, out, tmp_path, k: ["export-bag", seq, out / "x.bag", "--frames", 1],
    "synth": lambda seq, out, tmp_path, k: ["synth", out, "--frames", 2, "--size", "320x96"],
    "eval-plot": _plot_cmd,
}


@pytest.mark.parametrize("command", list(OUTPUT_COMMANDS))
@pytest.mark.parametrize("kind", ["file", "unwritable"])
def test_unusable_output_path(command: str, kind: str, seq: Path, kitti06: Path, models_dir: Path,
                              tmp_path: Path) -> None:
    if kind == "file":  # the output, or a folder on its path, is a file
        out = tmp_path / "afile"
        out.write_text("x")
        needle = "a file, not a folder"
    else:
        out = _unwritable_dir(tmp_path)
        needle = "not writable"
    r = cli(OUTPUT_COMMANDS[command](seq, out, tmp_path, kitti06), tmp_path, models_dir)
    assert_one_line(r, 2, needle)
    # checked before the first frame: no run started
    assert not (tmp_path / "ok" / "run.json").exists()


# --------------------------------------------------------------------------- input files


def _non_monotonic_times(seq: Path) -> None:
    t = (seq / "times.txt").read_text().split()
    t[1], t[2] = t[2], t[1]
    (seq / "times.txt").write_text("\n".join(t) + "\n")


def _corrupt_image(seq: Path) -> None:
    p = seq / "image_1" / "000001.png"
    p.write_bytes(p.read_bytes()[:200])


def _missing_image(seq: Path) -> None:
    (seq / "image_1" / "000002.png").unlink()


def _size_mismatch(seq: Path) -> None:
    p = seq / "image_1" / "000001.png"
    img = cv2.imread(str(p), 0)
    cv2.imwrite(str(p), cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2)))


def _no_calib(seq: Path) -> None:
    (seq / "calib.txt").unlink()


def _bad_calib(seq: Path) -> None:
    (seq / "calib.txt").write_text("P0: 1 2 3\nP1: a b c\n")


def _bad_times(seq: Path) -> None:
    (seq / "times.txt").write_text("0.0\n0.1\nabc\n0.3\n")


INPUT_FAULTS = {
    # name: (make fault, extra args, needles)
    "times-not-monotonic": (_non_monotonic_times, [], ["times.txt", "line 3", "increase"]),
    "times-not-a-number": (_bad_times, [], ["times.txt", "line 3"]),
    "corrupt-image": (_corrupt_image, [], ["000001.png"]),
    "missing-image": (_missing_image, [], ["image"]),
    "size-mismatch": (_size_mismatch, [], ["000001.png"]),
    "no-calibration": (_no_calib, [], ["calib"]),
    "bad-calibration": (_bad_calib, [], ["calib.txt"]),
    "frames-reversed": (None, ["--frames", "3-1"], ["frame spec", "reversed"]),
    "frames-not-a-number": (None, ["--frames", "abc"], ["frame spec"]),
    "frames-out-of-range": (None, ["--frames", "40"], ["frame"]),
}


@pytest.mark.parametrize("fault", list(INPUT_FAULTS))
def test_bad_input(fault: str, seq: Path, tmp_path: Path) -> None:
    make, extra, needles = INPUT_FAULTS[fault]
    if make is not None:
        make(seq)
    args = extra or ["--frames", N_FRAMES]
    r = cli(["run", seq, "-o", tmp_path / "out", "--masker", "none", *args], tmp_path)
    assert_one_line(r, 2, *needles)
    out = tmp_path / "out"
    if (out / "run.json").exists():  # failed mid-sequence: what was done is complete
        run = json.loads((out / "run.json").read_text())
        assert "error" in run
        assert len((out / "trajectory.kitti.txt").read_text().splitlines()) == run["frames_done"]


def test_bad_config_key(seq: Path, tmp_path: Path) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("stereo:\n  blok_size: 5\n")
    r = cli(["run", seq, "-o", tmp_path / "out", "--frames", 2, "--masker", "none", "-c", cfg], tmp_path)
    assert_one_line(r, 2, "blok_size")


@pytest.mark.parametrize("option,text", [
    ("-c", "stereo: [\n"),                 # a flow sequence never closed
    ("-c", 'detector:\n  name: "yolox\n'),  # a quoted string never closed
    ("--calib", "fx: 718\n\tfy: 718\n"),   # a tab as indentation
    ("--calib", "fx: [718, 0\n"),
])
def test_yaml_syntax_error_is_one_line_with_its_place(option: str, text: str, seq: Path, tmp_path: Path) -> None:
    """PyYAML's own message spans several lines (a snippet and a caret): the error is one
    line that names the file and the line, and nothing earlier is touched."""
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    r = cli(["run", seq, "-o", tmp_path / "out", "--frames", 2, "--masker", "none", option, f], tmp_path)
    line = assert_one_line(r, 2, "bad.yaml", "line ")
    assert "^" not in line
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("fault", ["missing-gt", "bad-columns"])
def test_bad_eval_files(fault: str, kitti06: Path, tmp_path: Path) -> None:
    gt = kitti06.parents[1] / "poses" / "06.txt"
    est = tmp_path / "est.txt"
    if fault == "missing-gt":
        shutil.copy(gt, est)
        gt = tmp_path / "nope.txt"
    else:
        est.write_text("1 2 3 4 5\n")
    r = cli(["eval", est, gt], tmp_path)
    assert_one_line(r, 2, gt.name if fault == "missing-gt" else "est.txt")


def test_random_bytes_bag(tmp_path: Path) -> None:
    bag = tmp_path / "random.bag"
    bag.write_bytes(np.random.default_rng(0).integers(0, 256, 20000, dtype=np.uint8).tobytes())
    r = cli(["run", "--bag", bag, "-o", tmp_path / "out"], tmp_path)
    assert_one_line(r, 2, "random.bag", "not a ros 1 bag")


def test_truncated_bag(seq: Path, tmp_path: Path) -> None:
    bag = tmp_path / "x.bag"
    assert cli(["export-bag", seq, bag, "--frames", 3], tmp_path).returncode == 0
    bag.write_bytes(bag.read_bytes()[: bag.stat().st_size // 3])
    r = cli(["run", "--bag", bag, "-o", tmp_path / "out", "--masker", "none"], tmp_path)
    assert_one_line(r, 2, "x.bag")


def test_damaged_map_file(seq: Path, tmp_path: Path) -> None:
    m = tmp_path / "bad.dsmap"
    m.write_bytes(b"\x00garbage" * 100)
    r = cli(["run", seq, "-o", tmp_path / "out", "--frames", 2, "--masker", "none", "--load-map", m], tmp_path)
    assert_one_line(r, 2, "bad.dsmap")


# --------------------------------------------------------------------------- interrupts


def _wait_rows(path: Path, rows: int, proc: subprocess.Popen, timeout: float = 120) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if proc.poll() is not None:
            pytest.fail(f"ended before the signal: rc {proc.returncode}: {proc.stderr.read()}")
        if path.is_file() and len(path.read_text().splitlines()) >= rows:
            return
        time.sleep(0.1)
    pytest.fail(f"{path}: not {rows} rows after {timeout} s")


def stop_then_signal(p: subprocess.Popen, sig: int, group: bool = False) -> None:
    """Signal a process that cannot finish meanwhile, however fast the machine: stopped
    (SIGSTOP) first, then the signal, then continued (SIGCONT) -- the signal lands while
    the run is still going, not after a sleep that a faster core may outrun."""
    send = (lambda s: os.killpg(p.pid, s)) if group else p.send_signal
    send(signal.SIGSTOP)
    send(sig)
    send(signal.SIGCONT)


@pytest.mark.parametrize("how", ["SIGINT-group", "SIGTERM"])
def test_run_interrupted(how: str, kitti06: Path, models_dir: Path, tmp_path: Path) -> None:
    """Ctrl-C (SIGINT to the process group) or SIGTERM mid-run (the BA thread aborted):
    one line, 130 / 143, and run.json / timing.json / trajectory agree on the frames done."""
    out = tmp_path / "out"
    sig = signal.SIGINT if how.startswith("SIGINT") else signal.SIGTERM
    p = subprocess.Popen(DYN + ["run", str(kitti06), "-o", str(out), "--frames", "40", "--masker", "box"],
                         cwd=tmp_path, env=_env(tmp_path, models_dir), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        _wait_rows(out / "trajectory.frames.txt", 3, p)
        stop_then_signal(p, sig, group=how.endswith("group"))
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    r = subprocess.CompletedProcess(p.args, p.returncode, "", err)
    assert_one_line(r, 128 + sig, "interrupted", signal.Signals(sig).name, str(out.name))
    run = json.loads((out / "run.json").read_text())
    timing = json.loads((out / "timing.json").read_text())
    n = run["frames_done"]
    assert 3 <= n < 40
    assert signal.Signals(sig).name in run["error"] and signal.Signals(sig).name in timing["error"]
    assert timing["frames_done"] == n and len(timing["frames"]) == n
    for name in ("trajectory.kitti.txt", "trajectory.tum.txt", "trajectory.frames.txt"):
        assert len((out / name).read_text().splitlines()) == n, name


def test_mask_interrupted(kitti06: Path, models_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    p = subprocess.Popen(DYN + ["mask", str(kitti06), "-o", str(out), "--frames", "40", "--masker", "box"],
                         cwd=tmp_path, env=_env(tmp_path, models_dir), stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        _wait_rows(out / "objects.jsonl", 2, p)
        stop_then_signal(p, signal.SIGTERM)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert_one_line(subprocess.CompletedProcess(p.args, p.returncode, "", err), 143, "interrupted", "SIGTERM")
    timing = json.loads((out / "timing.json").read_text())
    n = timing["frames_done"]
    assert "SIGTERM" in timing["error"]
    assert len(list((out / "masks" / "left").iterdir())) == n == len((out / "objects.jsonl").read_text().splitlines())


# --------------------------------------------------------------------------- the check itself, and the live node


def test_stereo_check_verdicts_on_real_pairs(kitti06: Path) -> None:
    from dynastereo.io import KittiSequence
    from dynastereo.io.stereo_check import StereoFault, check_frames
    from dynastereo.datatypes import StereoFrame

    seq = KittiSequence(kitti06)
    frames = [seq.frame(0), seq.frame(1)]
    good = check_frames(frames)
    assert good.fault is StereoFault.OK and good.matches > 200
    assert good.row_share > 0.8 and good.zero_share < 0.05 and good.negative_share < 0.1
    swapped = check_frames([StereoFrame(index=f.index, timestamp=0.0, left=f.right, right=f.left) for f in frames])
    assert swapped.fault is StereoFault.SWAPPED and swapped.negative_share > 0.9
    blank = np.zeros_like(frames[0].left)
    assert check_frames([StereoFrame(index=0, timestamp=0.0, left=blank, right=blank)]).fault is StereoFault.INCONCLUSIVE


def test_live_node_warns_on_identical_images(kitti06: Path, caplog) -> None:
    from dynastereo.config import Config
    from dynastereo.io import KittiSequence
    from dynastereo.ros.core import StereoInput, StereoNodeCore

    seq = KittiSequence(kitti06)
    core = StereoNodeCore(Config().with_overrides({"masker.kind": "none"}), calibration=seq.calibration)
    try:
        with caplog.at_level("WARNING"):
            for i in range(3):
                left = seq.frame(i).left
                core.process(StereoInput(left, left.copy(), int(i * 100_000_000)))
    finally:
        core.shutdown()
    warnings = [r for r in caplog.records if "stereo check failed" in r.getMessage()]
    assert len(warnings) == 1 and "identical" in warnings[0].getMessage()
    assert core.status()["stereo_check"]["fault"] == "identical"
