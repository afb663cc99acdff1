"""The fault suite's hangs, tracebacks and unclear endings: each ends at once in one line
naming the file or option and the problem (or, where the input is fine, in a correct
result that says what it left out).

* hangs: a map whose observation lists form a cycle (refused at load; the compiled walk
  over the lists is bounded too); an unbounded configuration value
  (``masker.outline.dilate: 100000``: every numeric key has bounds);
* tracebacks: a small map file that inflates far beyond its counts, MemoryError /
  ImportError in any command (``main()``), 1x1 images, an unwritable ``--rrd``, a run
  whose ``timing.json`` is not a JSON object;
* unclear: a map with NaN point positions (refused, not "done" with every frame lost), a
  complete video whose container guesses a larger frame count (read, not "truncated"),
  ``report`` on a folder with only run.json left (it names the missing files).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from dynastereo.errors import InputError, MapFileError
from dynastereo.slam.map_io import load_map
from test_faults_inputs import assert_one_line, cli, mini06
from test_map_io import _rewrite, built  # noqa: F401 -- ``built``: a saved map of a short synthetic run


def _arrays(path: Path) -> dict[str, np.ndarray]:
    import io
    import zipfile

    with zipfile.ZipFile(path) as z:
        return {n[:-4]: np.lib.format.read_array(io.BytesIO(z.read(n))) for n in z.namelist() if n.endswith(".npy")}


def _cyclic(b, p: Path) -> Path:
    a = _arrays(b.path)
    head, nxt = a["points/head"], a["obs/next_row"].copy()
    r = int(head[head >= 0][0])
    nxt[r] = r  # the point's list leads back to itself: a walk would never end
    return _rewrite(b.path, p, replace={"obs/next_row.npy": nxt})


def _nan_points(b, p: Path) -> Path:
    pos = _arrays(b.path)["points/pos"].copy()
    pos[3] = np.nan
    return _rewrite(b.path, p, replace={"points/pos.npy": pos})


def _inflating(b, p: Path) -> Path:
    return _rewrite(b.path, p, replace={"points/pos.npy": np.zeros((3_000_000, 3))})  # 72 MB of zeros, 70 KB zipped


MAP_FAULTS = {
    "observation lists in a cycle": (_cyclic, "observation lists form a cycle"),
    "NaN point positions": (_nan_points, r"non-finite values \(nan/inf\) in points/pos"),
    "an entry that inflates past its counts": (_inflating, r"entry 'points/pos.npy' would inflate to .* GiB; the "
                                                           "header's counts allow"),
}


@pytest.mark.parametrize("case", list(MAP_FAULTS))
def test_a_map_that_would_hang_or_mislead_is_refused_at_load(case: str, built, tmp_path: Path) -> None:  # noqa: F811
    make, pattern = MAP_FAULTS[case]
    path = make(built, tmp_path / "bad.dsmap")
    with pytest.raises(MapFileError, match=pattern) as e:
        load_map(path)
    assert str(e.value).startswith(f"{path}: ") and "\n" not in str(e.value)


def test_the_observation_list_walk_is_bounded() -> None:
    """A cycle that slipped past the checks ends in an error, not a loop SIGINT cannot stop."""
    from dynastereo.slam.kernels.bookkeeping import rows_of

    head = np.array([2, -1], np.int64)
    nxt = np.array([-1, 2, 1], np.int64)  # row 2 -> 1 -> 2 -> ...
    alive = np.ones(3, np.bool_)
    with pytest.raises(ValueError, match="cycle"):
        rows_of(head, nxt, alive, np.array([0], np.int64))
    assert rows_of(head, np.array([-1, -1, 1], np.int64), alive, np.array([0], np.int64)).tolist() == [1, 2]


def test_a_cyclic_map_ends_the_run_in_one_line(built, kitti06: Path, tmp_path: Path) -> None:  # noqa: F811
    seq = mini06(kitti06, tmp_path / "seq", 2)
    bad = _cyclic(built, tmp_path / "cyclic.dsmap")
    r = cli(["run", seq, "--out", tmp_path / "out", "--masker", "none", "--load-map", bad], tmp_path, timeout=120)
    assert_one_line(r, 2, "cyclic.dsmap", "cycle")


def test_every_numeric_configuration_key_is_bounded() -> None:
    from dynastereo.config import BOUNDS, Config, numeric_keys

    keys = [k for k, _ in numeric_keys(Config())]
    assert sorted(keys) == sorted(BOUNDS), set(keys) ^ set(BOUNDS)
    for key, (lo, hi) in BOUNDS.items():
        assert np.isfinite(lo) and np.isfinite(hi) and lo < hi, key


@pytest.mark.parametrize("key, value", [("masker.outline.dilate", 100000), ("stereo.num_disparities", 1 << 20),
                                        ("slam.n_features", 10**9), ("motion.chi2", float("inf")),
                                        ("detector.score_threshold", float("nan")), ("slam.ba_wait_s", 1e300)])
def test_out_of_bounds_values_are_refused_naming_the_key(key: str, value, tmp_path: Path) -> None:
    from dynastereo.config import Config, load_config
    from dynastereo.errors import ConfigError

    with pytest.raises(ConfigError, match=rf"{key} must be .*(finite|nan)"):
        Config().with_overrides({key: value})
    sec, _, name = key.rpartition(".")
    text = "".join(f"{'  ' * i}{part}:\n" for i, part in enumerate(sec.split(".")))
    p = tmp_path / "c.yaml"
    p.write_text(text + f"{'  ' * len(sec.split('.'))}{name}: {value!r}\n".replace("inf", ".inf").replace("nan", ".nan"))
    with pytest.raises(ConfigError, match=rf"c\.yaml: {key} must be .*(finite|nan)"):
        load_config(p)


@pytest.mark.parametrize("exc, needles", [
    (MemoryError("Unable to allocate 40.0 GiB for an array with shape (100001, 100001)"),
     ("out of memory", "40.0 GiB", "ulimit -v")),
    (ImportError("libgomp.so.1: failed to map segment from shared object", name="onnxruntime"),
     ("cannot load onnxruntime", "failed to map segment", "ulimit -v")),
    (ImportError("No module named 'rerun'", name="rerun"), ("cannot load rerun", "installed")),
])
def test_memory_and_import_errors_end_in_one_line(exc: BaseException, needles, monkeypatch, capsys) -> None:
    from dynastereo.cli import main as cli_main

    def boom() -> None:
        raise exc

    monkeypatch.setattr(cli_main, "app", boom)
    with pytest.raises(SystemExit) as e:
        cli_main.main()
    assert e.value.code == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("error:") and "Traceback" not in err[0], err
    for n in needles:
        assert n in err[0], (n, err[0])


def test_a_tight_memory_limit_ends_in_one_line(kitti06: Path, tmp_path: Path) -> None:
    """``ulimit -v`` too tight for the libraries: one line naming what failed to load."""
    seq = mini06(kitti06, tmp_path / "seq", 2)
    src = str(Path(__file__).resolve().parents[1] / "src")
    code = ("import resource, runpy, sys; resource.setrlimit(resource.RLIMIT_AS, (400 << 20, 400 << 20)); "
            "sys.argv = ['dynastereo', 'run', sys.argv[1], '--out', sys.argv[2], '--masker', 'none']; "
            "import dynastereo.cli.main as m; m.main()")
    r = subprocess.run([sys.executable, "-c", code, str(seq), str(tmp_path / "out")], capture_output=True, text=True,
                       timeout=120, env={"PYTHONPATH": src, "PATH": "/usr/bin:/bin"}, cwd=tmp_path)
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(err) == 1 and "Traceback" not in r.stderr, r.stderr
    assert err[0].startswith("error:") and ("cannot load" in err[0] or "memory" in err[0]), err


def test_one_pixel_images_are_refused(tmp_path: Path) -> None:
    from dynastereo.errors import SequenceError
    from dynastereo.io import open_sequence

    seq = tmp_path / "seq"
    for side in ("left", "right"):
        (seq / side).mkdir(parents=True)
        for i in range(3):
            cv2.imwrite(str(seq / side / f"{i:06d}.png"), np.full((1, 1), 128, np.uint8))
    (seq / "calib.yaml").write_text("fx: 1.0\nfy: 1.0\ncx: 0.5\ncy: 0.5\nbaseline: 0.5\n")
    with pytest.raises(SequenceError, match="images are 1x1; dynastereo needs at least 32x16"):
        open_sequence(seq, rate=10)
    r = cli(["run", seq, "--out", tmp_path / "out", "--rate", 10], tmp_path)
    assert_one_line(r, 2, "1x1")


def test_an_unwritable_rrd_is_refused_before_the_run(kitti06: Path, tmp_path: Path) -> None:
    from dynastereo.api import run_sequence
    from dynastereo.config import Config
    from dynastereo.errors import OutputError

    seq = mini06(kitti06, tmp_path / "seq", 2)
    with pytest.raises(OutputError, match=r"recording \(--rrd\)"):
        run_sequence(seq, tmp_path / "out", Config().with_overrides({"masker.kind": "none"}),
                     rrd=Path("/proc/self/no/such/rec.rrd"))
    assert not (tmp_path / "out").exists()


@pytest.fixture
def finished_run(tmp_path: Path) -> Path:
    """A run folder as `dynastereo run` leaves it (3 frames, identity poses)."""
    run = tmp_path / "run"
    run.mkdir()
    row = " ".join(f"{v:.6f}" for v in np.eye(4)[:3].reshape(-1)) + "\n"
    (run / "trajectory.kitti.txt").write_text(row * 3)
    (run / "trajectory.tum.txt").write_text("".join(f"{0.1 * i:.6f} 0 0 0 0 0 0 1\n" for i in range(3)))
    (run / "trajectory.frames.txt").write_text("0\n1\n2\n")
    (run / "timing.json").write_text(json.dumps({"frames": [], "summary": {}}))
    (run / "run.json").write_text(json.dumps({"status": "done", "frames_done": 3, "frames_requested": 3,
                                              "sequence": "", "masker": "none"}))
    return run


def test_report_on_a_run_whose_timing_json_is_not_an_object(finished_run: Path, tmp_path: Path) -> None:
    (finished_run / "timing.json").write_text("[1, 2, 3]\n")
    assert_one_line(cli(["report", finished_run], tmp_path), 2, "timing.json", "not a JSON object")


def test_report_on_a_folder_with_only_run_json_names_what_is_missing(finished_run: Path, tmp_path: Path) -> None:
    for name in ("trajectory.kitti.txt", "trajectory.tum.txt", "trajectory.frames.txt", "timing.json"):
        (finished_run / name).unlink()
    r = cli(["report", finished_run], tmp_path)
    assert r.returncode == 0, r.stderr
    assert "partial: timing.json, trajectory.kitti.txt, trajectory.tum.txt, trajectory.frames.txt are missing" \
        in r.stdout.replace("\n", " ")
    assert "are missing from the run folder" in (finished_run / "report.html").read_text()


def test_a_video_whose_container_guesses_more_frames_is_read_whole() -> None:
    """The container's count is its duration x nominal rate: a variable-rate file whose
    frames run to its end is complete; one whose frames stop half-way is truncated."""
    from dynastereo.io.video import _Reader

    def reader(fps: float) -> SimpleNamespace:
        cap = SimpleNamespace(get=lambda prop: fps if prop == cv2.CAP_PROP_FPS else 0.0)
        return SimpleNamespace(cap=cap)

    rng = np.random.default_rng(0)
    stamps = list(np.cumsum(rng.uniform(0.05, 0.15, 40)) - 0.05)  # ~10 fps, variable, to ~4 s
    duration = stamps[-1] + 0.1
    assert _Reader._covers(reader(15.0), stamps, int(duration * 15))  # 60 guessed, 40 there, to the end
    assert not _Reader._covers(reader(10.0), stamps[:20], int(duration * 10))  # stops half-way: truncated


def test_the_missing_default_model_names_every_way_to_supply_it(tmp_path: Path) -> None:
    from dynastereo.config import Config
    from dynastereo.errors import ModelError
    from dynastereo.masking.detection import create_detector

    with pytest.raises(ModelError) as e:
        create_detector(Config().detector, models_dir=tmp_path / "empty")
    msg = str(e.value)
    assert "yolox-nano" in msg and "dynastereo models download yolox-nano" in msg
    assert "--models-dir" in msg and "$DYNASTEREO_MODELS" in msg and "\n" not in msg
