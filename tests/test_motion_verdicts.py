"""The motion test's verdict rate on synthetic streets (``dynastereo.eval.verdicts``).

* the scorer: counts driven by the ground truth (objects under 300 px and each object's
  first 3 frames left out, a box must match with IoU >= 0.5, unmatched and undecided
  count as wrong), on records made from the ground truth and then spoiled;
* the floor: the default pipeline with oracle boxes on one fixed seed of ``mixed``
  (150 frames at 640x192, the size the benchmark runs) judges at least 90 % of its
  object-frames right (``bench_moving.py`` reports the rate over many seeds).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dynastereo.api import run_sequence
from dynastereo.config import Config
from dynastereo.errors import InputError
from dynastereo.eval.verdicts import VerdictScore, score_verdicts
from dynastereo.synth import generate, read_objects

pytestmark = pytest.mark.usefixtures("quiet_slam")

# the guarded sequence: held out from the motion test's tuning (seed 0)
FLOOR = 0.90
FLOOR_SEED = 5
FLOOR_FRAMES = 150
FLOOR_SIZE = (640, 192)


@pytest.fixture(scope="module")
def short_mixed(tmp_path_factory) -> Path:
    return generate(tmp_path_factory.mktemp("mixed_short"), "mixed", frames=12, seed=1, size=(320, 96))


def _write_records(run: Path, seq: Path, verdict, box=lambda o: o.box_left) -> None:
    """An ``objects.jsonl`` with every visible ground-truth object reported (``verdict(o)``
    as its ``moving``, ``box(o)`` as its box; None: not reported)."""
    gt = read_objects(seq)
    run.mkdir(parents=True, exist_ok=True)
    lines = []
    for f, objs in enumerate(gt.frames):
        rep = [{"box": list(box(o)), "track": o.id, "moving": verdict(o)}
               for o in objs if o.box_left is not None and box(o) is not None]
        lines.append(json.dumps({"frame": f, "objects": rep}))
    (run / "objects.jsonl").write_text("\n".join(lines) + "\n")


def _counted(seq: Path) -> list:
    """The ground-truth object-frames the scorer counts (module doc), by hand."""
    gt = read_objects(seq)
    first: dict[int, int] = {}
    out = []
    for f, objs in enumerate(gt.frames):
        for o in objs:
            if o.box_left is None:
                continue
            first.setdefault(o.id, f)
            if o.pixels_left >= 300 and f - first[o.id] >= 3:
                out.append(o)
    return out


def test_the_scorer_counts_ground_truth_object_frames(short_mixed: Path, tmp_path: Path) -> None:
    counted = _counted(short_mixed)
    movers = sum(o.moving for o in counted)
    assert counted and 0 < movers < len(counted)  # the sequence has both kinds
    n = len(counted)

    _write_records(tmp_path / "right", short_mixed, lambda o: o.moving)
    assert score_verdicts(tmp_path / "right", short_mixed) == VerdictScore(n, n, 0, 0, 0, 0)

    _write_records(tmp_path / "flipped", short_mixed, lambda o: not o.moving)
    s = score_verdicts(tmp_path / "flipped", short_mixed)
    assert (s.right, s.moving_judged_static, s.static_judged_moving) == (0, movers, n - movers)

    _write_records(tmp_path / "undecided", short_mixed, lambda o: None)
    s = score_verdicts(tmp_path / "undecided", short_mixed)
    assert (s.right, s.undecided, s.rate) == (0, n, 0.0)

    # a box moved by more than half its width no longer matches: unmatched, wrong
    def shifted(o):
        x1, y1, x2, y2 = o.box_left
        return (x1 + 0.6 * (x2 - x1), y1, x2 + 0.6 * (x2 - x1), y2) if o.moving else o.box_left

    _write_records(tmp_path / "shifted", short_mixed, lambda o: o.moving, shifted)
    s = score_verdicts(tmp_path / "shifted", short_mixed)
    assert (s.right, s.unmatched) == (n - movers, movers)

    # objects never reported count against the rate too
    _write_records(tmp_path / "missing", short_mixed, lambda o: o.moving, lambda o: None if o.moving else o.box_left)
    s = score_verdicts(tmp_path / "missing", short_mixed)
    assert (s.object_frames, s.right, s.unmatched) == (n, n - movers, movers)
    assert (s + s).object_frames == 2 * n


def test_a_bad_objects_file_is_named(short_mixed: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="objects.jsonl"):
        score_verdicts(tmp_path, short_mixed)
    (tmp_path / "objects.jsonl").write_text('{"frame": 0}\n')
    with pytest.raises(InputError, match="line 1"):
        score_verdicts(tmp_path, short_mixed)


@pytest.fixture(scope="module")
def floor_mixed(tmp_path_factory) -> Path:
    return generate(tmp_path_factory.mktemp("mixed_floor"), "mixed", frames=FLOOR_FRAMES, seed=FLOOR_SEED,
                    size=FLOOR_SIZE)


def test_the_default_motion_test_judges_a_mixed_street_right(floor_mixed: Path, tmp_path: Path) -> None:
    cfg = Config().with_overrides({"detector.name": "oracle"})
    run_sequence(floor_mixed, tmp_path / "run", cfg, stereo_check=False)
    s = score_verdicts(tmp_path / "run", floor_mixed)
    assert s.object_frames > 400
    assert s.rate >= FLOOR, s
