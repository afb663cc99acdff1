"""What a person looks at: the HTML report of a run (also in headless Chromium), the
rerun recording (read back with rerun's own reader), no rerun import when it is off.

One small synthetic run (``convoy``, oracle boxes, outline masks) is shared by the file.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import REQUIRE
from dynastereo.cli.main import app
from dynastereo.eval import evaluate_files
from dynastereo.synth import generate

SIZE = (480, 144)
FRAMES = 14
runner = CliRunner()
pytestmark = pytest.mark.usefixtures("quiet_slam")


class _Keys(HTMLParser):
    """``data-key`` -> cell text; and every ``src`` of the page."""

    def __init__(self) -> None:
        super().__init__()
        self.values: dict[str, str] = {}
        self.srcs: list[str] = []
        self._key: str | None = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self._key = a.get("data-key")
        if "src" in a:
            self.srcs.append(a["src"])
        if "href" in a:
            self.srcs.append(a["href"])

    def handle_data(self, data):
        if self._key is not None:
            self.values[self._key] = self.values.get(self._key, "") + data

    def handle_endtag(self, tag):
        self._key = None


def page_keys(text: str) -> _Keys:
    p = _Keys()
    p.feed(text)
    return p


def need(what: str, reason: str) -> None:
    """Skip (fail under DYNASTEREO_REQUIRE_DATA=1) when a tool the test needs is absent."""
    msg = f"{what} not available: {reason}"
    if REQUIRE:
        pytest.fail(msg + " [DYNASTEREO_REQUIRE_DATA=1]")
    pytest.skip(msg)


@pytest.fixture(scope="module")
def synth_seq(tmp_path_factory) -> Path:
    return generate(tmp_path_factory.mktemp("convoy"), "convoy", frames=FRAMES, seed=0, size=SIZE)


@pytest.fixture(scope="module")
def run_dir(synth_seq: Path, tmp_path_factory) -> Path:
    """``dynastereo run ... --save-masks --report`` from the command line."""
    out = tmp_path_factory.mktemp("run") / "run"
    r = runner.invoke(app, ["run", str(synth_seq), "--out", str(out), "--masker", "outline", "--detector", "oracle",
                            "--save-masks", "--report"])
    assert r.exit_code == 0, r.output
    assert f"report: {out / 'report.html'}" in r.output.replace("\n", "")
    return out


def assert_page_matches_run(values: dict[str, str], run_dir: Path, gt: Path) -> None:
    """The key numbers shown equal run.json, timing.json and the evaluation."""
    run = json.loads((run_dir / "run.json").read_text())
    for k in ("frames_requested", "frames_done", "frames_tracked", "frames_lost", "keyframes", "map_points"):
        assert int(values[k]) == run[k], k
    assert float(values["fps"]) == pytest.approx(run["fps"], rel=1e-3)
    assert int(values["loops"]) == len(run["loops"]) and int(values["recoveries"]) == len(run["recoveries"])
    assert values["masker"] == "outline" and values["detector"] == "oracle"
    assert values["sequence"] == run["sequence"]
    timing = json.loads((run_dir / "timing.json").read_text())
    for stage in ("track", "features", "masking", "total"):
        assert float(values[f"timing.{stage}.median"]) == pytest.approx(timing["summary"][stage]["median"], rel=1e-3)
    ev = evaluate_files(run_dir / "trajectory.kitti.txt", gt)
    for k in ("rmse", "mean", "max"):
        assert float(values[f"ape.{k}"]) == pytest.approx(ev.ape[k], rel=1e-3)
        assert float(values[f"rpe.{k}"]) == pytest.approx(ev.rpe[k], rel=1e-3)
    assert float(values["drift_percent"]) == pytest.approx(ev.drift_percent, rel=1e-3)
    assert int(values["n_frames"]) == FRAMES


def test_report_shows_the_run_and_is_self_contained(run_dir: Path, synth_seq: Path) -> None:
    text = (run_dir / "report.html").read_text()
    page = page_keys(text)
    gt = synth_seq.parent.parent / "poses" / "00.txt"  # found by itself beside the KITTI layout
    assert_page_matches_run(page.values, run_dir, gt)
    assert page.srcs and all(s.startswith("data:") for s in page.srcs), [s[:40] for s in page.srcs]
    assert "http://" not in text and "https://" not in text
    for section in ("Summary", "Trajectory", "Accuracy", "Time per stage", "Masks", "Objects"):
        assert f"<h2>{section}</h2>" in text, section
    # overlays: the first frame, the worst one (largest APE) and evenly spaced ones
    assert "frame 0 (first)" in text and "(worst: largest APE)" in text and text.count("<figure>") == 6
    # the SLAM run logs its objects too: the truck of the convoy, every frame
    objects = [json.loads(line) for line in (run_dir / "objects.jsonl").read_text().splitlines()]
    assert len(objects) == FRAMES and all(r["objects"] for r in objects)


def test_report_cli_other_ground_truth_and_out(run_dir: Path, synth_seq: Path, tmp_path: Path) -> None:
    gt = synth_seq.parent.parent / "poses" / "00.txt"
    moved = tmp_path / "gt.txt"
    moved.write_text(gt.read_text())
    out = tmp_path / "sub" / "r.html"
    r = runner.invoke(app, ["report", str(run_dir), "--gt", str(moved), "--out", str(out), "--overlays", "2"])
    assert r.exit_code == 0, r.output
    text = out.read_text()
    assert str(moved) in text and text.count("<figure>") == 2
    assert_page_matches_run(page_keys(text).values, run_dir, moved)
    # no ground truth: no accuracy section, the trajectory alone
    r = runner.invoke(app, ["report", str(run_dir), "--no-auto-gt", "--out", str(out)])
    assert r.exit_code == 0, r.output
    text = out.read_text()
    assert "<h2>Accuracy</h2>" not in text and "<h2>Trajectory</h2>" in text and "ape.rmse" not in text


def test_report_errors_name_the_file(tmp_path: Path) -> None:
    r = runner.invoke(app, ["report", str(tmp_path)])
    assert r.exit_code == 2 and "neither run.json nor timing.json" in r.output and str(tmp_path) in r.output
    (tmp_path / "run.json").write_text("{broken")
    r = runner.invoke(app, ["report", str(tmp_path)])
    assert r.exit_code == 2 and "run.json" in r.output and "not valid JSON" in r.output
    (tmp_path / "run.json").write_text("{}")
    r = runner.invoke(app, ["report", str(tmp_path), "--gt", str(tmp_path / "nope.txt")])
    assert r.exit_code == 2 and "nope.txt" in r.output


def test_report_of_a_mask_job(synth_seq: Path, tmp_path: Path) -> None:
    """``dynastereo mask`` output (no run.json): timing, objects; API entry point."""
    from dynastereo.api import make_report, mask_sequence
    from dynastereo.config import Config

    out = tmp_path / "m"
    mask_sequence(synth_seq, out, Config().with_overrides({"detector.name": "oracle"}), frames=4)
    path = make_report(out)
    text = path.read_text()
    assert path == out / "report.html" and "<h2>Time per stage</h2>" in text and "<h2>Objects</h2>" in text
    timing = json.loads((out / "timing.json").read_text())
    assert float(page_keys(text).values["timing.mask.median"]) == pytest.approx(timing["summary"]["mask"]["median"],
                                                                               rel=1e-3)


def test_report_in_headless_chromium(run_dir: Path, synth_seq: Path) -> None:
    """As a person sees it: loads without console errors or broken images, the
    screenshot is not blank, and the numbers in the DOM equal run.json's."""
    from dynastereo.viz.browser import find_chromium, load_page

    if find_chromium() is None:
        need("chromium", "Debian: apt-get install chromium (.ci/run installs it)")
    page = load_page(run_dir / "report.html")
    assert page.errors == [], page.errors
    img = cv2.imdecode(np.frombuffer(page.screenshot, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[1] == 1200 and img.shape[0] > 2000  # the whole page, not one screen
    ink = np.any(img < 200, axis=2)
    assert 0.05 < ink.mean() < 0.9, ink.mean()  # text, plots and images drawn, not blank
    colourful = (img.max(axis=2).astype(int) - img.min(axis=2)) > 60
    assert colourful.mean() > 0.01  # the plots' colours and the red masks are there
    assert_page_matches_run(page_keys(page.dom).values, run_dir, synth_seq.parent.parent / "poses" / "00.txt")


def _rerun_or_skip() -> None:
    try:
        import rerun  # noqa: F401
    except ImportError:
        need("rerun-sdk", "pip install 'dynastereo[viz]' (make test installs it)")


def test_rrd_recording_reads_back_with_rerun(synth_seq: Path, tmp_path: Path) -> None:
    _rerun_or_skip()
    from dynastereo.viz.rerun import recorded_entities

    rrd = tmp_path / "run.rrd"
    r = runner.invoke(app, ["run", str(synth_seq), "--out", str(tmp_path / "r"), "--masker", "outline",
                            "--detector", "oracle", "--frames", "6", "--rrd", str(rrd)])
    assert r.exit_code == 0, r.output
    ent = recorded_entities(rrd)
    per_frame = ["/camera/left", "/camera/right", "/camera/left/mask", "/camera/right/mask", "/camera/left/boxes",
                 "/camera/left/features", "/world/camera", "/world/camera/image", "/world/trajectory",
                 "/world/local_map", "/timing/track", "/timing/masking", "/status"]
    for e in per_frame:
        assert ent.get(e) == 6, (e, ent.get(e))
    assert "/world/ground_truth" in ent  # static, found beside the KITTI layout

    rrd = tmp_path / "mask.rrd"
    r = runner.invoke(app, ["mask", str(synth_seq), "--out", str(tmp_path / "m"), "--detector", "oracle",
                            "--frames", "3", "--save-disparity", "--rrd", str(rrd)])
    assert r.exit_code == 0, r.output
    ent = recorded_entities(rrd)
    for e in ("/camera/left", "/camera/left/mask", "/camera/left/boxes", "/camera/disparity", "/timing/mask"):
        assert ent.get(e) == 3, (e, ent.get(e))
    assert "/world/trajectory" not in ent  # no poses from masking alone


def test_rerun_is_not_imported_when_off(synth_seq: Path, tmp_path: Path) -> None:
    code = (
        "import sys\n"
        "from dynastereo.api import run_sequence\n"
        "from dynastereo.config import Config\n"
        f"run_sequence({str(synth_seq)!r}, {str(tmp_path / 'r')!r}, "
        "Config().with_overrides({'detector.name': 'oracle'}), frames=3, report=True)\n"
        "print('rerun' in sys.modules)\n"
    )
    env = dict(os.environ, MPLBACKEND="Agg")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "False"
