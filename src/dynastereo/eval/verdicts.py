"""The motion test's verdicts scored against a synthetic sequence's ground truth.

``score_verdicts(run_dir, seq_dir)`` reads a run's ``objects.jsonl`` (each reported box with
its ``moving``: true, false or null for undecided) and the sequence's ``gt/objects.json``
and counts, per ground-truth object-frame:

* an object gets ``skip_frames`` (3) frames after it first shows in the left image to be
  judged, and object-frames under ``min_pixels`` (300) visible left pixels are left out;
* each remaining object-frame must be matched by a reported box with IoU >= ``min_iou``
  (0.5; one to one, the assignment of the largest total IoU) whose ``moving`` equals the
  ground truth's;
* unmatched and undecided object-frames count as wrong.

The count is driven by the ground truth, so an object the run never reported, or
reported with a box that drifted off it, counts against the rate as much as a wrong
verdict does.  ``bench_moving.py`` reports it over many seeds and a test holds a floor.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..errors import InputError
from ..masking.boxes import box_iou
from ..synth.oracle import read_objects

MIN_PIXELS = 300
SKIP_FRAMES = 3
MIN_IOU = 0.5


@dataclass(frozen=True)
class VerdictScore:
    """Counts of ground-truth object-frames (module doc); ``rate`` = right / object_frames."""

    object_frames: int
    right: int
    undecided: int  # matched, moving is null
    unmatched: int  # no reported box with IoU >= min_iou
    moving_judged_static: int  # matched, the costly error: a mover left to SLAM
    static_judged_moving: int  # matched, masked for nothing

    @property
    def rate(self) -> float | None:
        return self.right / self.object_frames if self.object_frames else None

    def __add__(self, other: VerdictScore) -> VerdictScore:
        return VerdictScore(*(a + b for a, b in zip(asdict(self).values(), asdict(other).values())))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["rate"] = None if self.rate is None else round(self.rate, 4)
        return d


def _read_reports(path: Path) -> dict[int, list[dict]]:
    """frame -> the objects reported in it (``objects.jsonl``)."""
    try:
        lines = path.read_text().splitlines()
    except OSError as e:
        raise InputError(f"cannot read the run's objects ({e.strerror or e})", path) from e
    out: dict[int, list[dict]] = {}
    for n, line in enumerate(lines, 1):
        try:
            rec = json.loads(line)
            out[int(rec["frame"])] = list(rec["objects"])
        except (ValueError, KeyError, TypeError) as e:
            raise InputError(f"line {n} is not an objects record ({e})", path) from e
    return out


def score_verdicts(run_dir: str | Path, seq_dir: str | Path, *, min_pixels: int = MIN_PIXELS,
                   skip_frames: int = SKIP_FRAMES, min_iou: float = MIN_IOU) -> VerdictScore:
    """Score ``run_dir/objects.jsonl`` against the synthetic ground truth of ``seq_dir``."""
    gt = read_objects(seq_dir)
    reports = _read_reports(Path(run_dir) / "objects.jsonl")
    first: dict[int, int] = {}
    n = right = undecided = unmatched = m_static = s_moving = 0
    for f, objs in enumerate(gt.frames):
        seen = [o for o in objs if o.box_left is not None]
        for o in seen:
            first.setdefault(o.id, f)
        todo = [o for o in seen if o.pixels_left >= min_pixels and f - first[o.id] >= skip_frames]
        if not todo:
            continue
        n += len(todo)
        rep = reports.get(f, [])
        matched = np.full(len(todo), -1)
        if rep:
            iou = box_iou(np.array([o.box_left for o in todo], float), np.array([r["box"] for r in rep], float))
            rows, cols = linear_sum_assignment(-iou)
            ok = iou[rows, cols] >= min_iou
            matched[rows[ok]] = cols[ok]
        gt_moving = np.array([o.moving for o in todo])
        verdict = np.array([None if j < 0 else rep[j]["moving"] for j in matched], dtype=object)
        has = matched >= 0
        unmatched += int((~has).sum())
        undecided += int((has & np.array([v is None for v in verdict])).sum())
        said_moving = np.array([v is True for v in verdict])
        said_static = np.array([v is False for v in verdict])
        right += int((said_moving & gt_moving).sum() + (said_static & ~gt_moving).sum())
        m_static += int((said_static & gt_moving).sum())
        s_moving += int((said_moving & ~gt_moving).sum())
    return VerdictScore(n, right, undecided, unmatched, m_static, s_moving)
