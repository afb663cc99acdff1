"""README.md against the program: every option of every command is named in it, and the
command blocks a newcomer copies (quick start, your own stereo camera, your own bag) run as
written on generated data.

The blocks run are the fenced ``bash`` blocks right after a ``<!-- test_readme: NAME -->``
comment in README.md; each line is ``source ...`` (skipped: the test calls the CLI in-process)
or a ``dynastereo`` command, run through the real command line in a scratch folder that
holds what the block expects (``mycam/``: a generic stereo folder made from a synthetic
sequence, with nanosecond file names and a rectified calib.yaml; ``mycam.bag``).
``dynastereo models download NAME`` is replaced by ``dynastereo models verify NAME`` against
``DYNASTEREO_MODELS``: nothing is downloaded in tests.
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from dynastereo.cli.main import app

README = Path(__file__).resolve().parents[1] / "README.md"
T0_NS = 1_700_000_000_000_000_000  # the generated camera's first stamp (2023-11-14), as its file names


def _commands(cmd, path: str = "dynastereo"):
    """(``dynastereo sub``, command) for the whole click tree (typer ships its own click:
    duck-typed, not isinstance against the click package)."""
    yield path, cmd
    for name, sub in getattr(cmd, "commands", {}).items():
        yield from _commands(sub, f"{path} {name}")


def help_options() -> dict[str, list[str]]:
    """Every command's options as ``--help`` shows them (``--help`` itself left out)."""
    return {path: [opt for p in cmd.params if p.param_type_name == "option" and not p.hidden
                   for opt in (*p.opts, *p.secondary_opts) if opt != "--help"]
            for path, cmd in _commands(typer.main.get_command(app))}


def test_every_command_and_option_of_help_is_in_the_readme() -> None:
    text = README.read_text()
    options = help_options()
    assert "--no-align" in options["dynastereo eval"] and "--no-wls" in options["dynastereo mask"]
    assert {"dynastereo models download", "dynastereo export-bag"} <= set(options)
    missing = [path for path in options if path != "dynastereo" and path not in text]
    missing += [f"{path} {opt}" for path, opts in options.items() for opt in opts
                if not re.search(rf"(?<![\w-]){re.escape(opt)}(?![\w-])", text)]
    assert not missing, f"named in --help but not in README.md: {', '.join(missing)}"


def readme_block(name: str) -> list[list[str]]:
    """The commands (argument lists) of the bash block marked ``<!-- test_readme: name -->``."""
    m = re.search(rf"<!-- test_readme: {re.escape(name)} -->\s*```bash\n(.*?)```", README.read_text(), re.S)
    assert m, f"README.md has no ```bash block marked <!-- test_readme: {name} -->"
    commands = []
    for line in m.group(1).replace("\\\n", " ").splitlines():
        words = shlex.split(line, comments=True)
        if not words or words[0] == "source":
            continue
        assert words[0] == "dynastereo", f"README block {name!r}: not a dynastereo command: {line!r}"
        commands.append(words[1:])
    assert commands
    return commands


def run_block(name: str, cwd: Path, monkeypatch) -> list[str]:
    monkeypatch.chdir(cwd)
    outputs = []
    for args in readme_block(name):
        if args[:2] == ["models", "download"]:
            args = ["models", "verify", *args[2:]]
        r = CliRunner().invoke(app, args)
        assert r.exit_code == 0, f"`dynastereo {shlex.join(args)}` exited {r.exit_code}:\n{r.output}"
        outputs.append(r.output)
    return outputs


def make_own_camera(root: Path, frames: int = 16) -> Path:
    """``root/mycam``: left/ + right/ with nanosecond file names (30 Hz), calib.yaml (rectified
    form), groundtruth.tum.txt -- made from a synthetic ``crossing`` sequence."""
    from dynastereo.eval.trajectory import read_trajectory, write_tum
    from dynastereo.io import open_sequence
    from dynastereo.synth import generate

    seq = open_sequence(generate(root / "synth", "crossing", frames=frames, seed=1, size=(480, 144)))
    cam = root / "mycam"
    names = [f"{T0_NS + k * 33_333_333}.png" for k in range(len(seq))]
    for side, paths in (("left", seq.left_paths), ("right", seq.right_paths)):
        (cam / side).mkdir(parents=True)
        for p, n in zip(paths, names):
            (cam / side / n).write_bytes(p.read_bytes())
    c = seq.calibration
    (cam / "calib.yaml").write_text(f"fx: {c.fx}\nfy: {c.fy}\ncx: {c.cx}\ncy: {c.cy}\nbaseline: {c.baseline}\n")
    gt = read_trajectory(root / "synth" / "poses" / "00.txt")
    write_tum(cam / "groundtruth.tum.txt", gt.poses, np.array([int(n[:-4]) for n in names]) * 1e-9)
    return cam


def test_quick_start_as_written(tmp_path: Path, monkeypatch) -> None:
    run_block("quickstart", tmp_path, monkeypatch)
    demo = json.loads((tmp_path / "demo" / "demo.json").read_text())
    rows = {r["masker"]: r for r in demo["rows"]}
    assert rows["outline"]["ate_rmse"] < 0.5 * rows["none"]["ate_rmse"]  # masking is what the demo shows
    assert all(Path(p).is_file() for p in demo["reports"].values())


def test_your_own_stereo_camera_and_bag_as_written(tmp_path: Path, monkeypatch, models_dir: Path) -> None:
    cam = make_own_camera(tmp_path)
    outputs = run_block("own-camera", tmp_path, monkeypatch)
    run = json.loads((tmp_path / "mycam_run" / "run.json").read_text())
    assert run["timestamps"] == "file names (ns)" and run["frames_done"] == 16
    tum = np.loadtxt(tmp_path / "mycam_run" / "trajectory.tum.txt")
    assert tum[0, 0] == pytest.approx(T0_NS * 1e-9)  # the camera's own stamps, so TUM ground truth associates
    evaluation = outputs[[a[0] for a in readme_block("own-camera")].index("eval")]
    assert "rmse" in evaluation and (tmp_path / "mycam_run" / "trajectory_vs_gt.png").is_file()
    assert (tmp_path / "mycam_run" / "report.html").is_file()
    assert len(list((tmp_path / "mycam_masks" / "overlays").glob("*.png"))) == 10

    from dynastereo.io import open_sequence
    from dynastereo.ros.bags import export_bag

    export_bag(open_sequence(cam), tmp_path / "mycam.bag", "ros1")
    run_block("own-bag", tmp_path, monkeypatch)
    bag_run = json.loads((tmp_path / "mycam_bag_run" / "run.json").read_text())
    assert bag_run["frames_done"] == 16 and bag_run["timestamps"].startswith("bag header stamps")
    assert np.loadtxt(tmp_path / "mycam_bag_run" / "trajectory.tum.txt")[0, 0] == pytest.approx(T0_NS * 1e-9)


@pytest.mark.parametrize("name, raw", [("calib-rectified", False), ("calib-raw", True)])
def test_readme_calibration_examples_load(tmp_path: Path, name: str, raw: bool) -> None:
    from dynastereo.io.calib import RawStereoCalibration, load_stereo_yaml

    m = re.search(rf"<!-- test_readme: {name} -->\s*```yaml\n(.*?)```", README.read_text(), re.S)
    assert m, f"README.md has no ```yaml block marked <!-- test_readme: {name} -->"
    (tmp_path / "calib.yaml").write_text(m.group(1))
    c = load_stereo_yaml(tmp_path / "calib.yaml")
    assert isinstance(c, RawStereoCalibration) == raw
    if not raw:
        assert (c.fx, c.baseline, c.width, c.height) == (700.0, 0.12, 1280, 720)
