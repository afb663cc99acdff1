"""Scoring against reference instance masks of real frames (``shared/reference/refmasks``).

A reference folder holds, per frame, ``NNNNNN.png`` (uint8 instance ids, 0 = background)
and ``NNNNNN.json`` (``instances``: ``class``, ``box`` [x0, y0, x1, y1], ...), made by a
segmentation network at high resolution (see that folder's README for its limits).

The yardstick is the one of ``shared/tools/score_masks.py`` (what the project's checks
run), computed here without writing a ``mask`` output first:

* **near-vehicle recall**: reference vehicles (car, truck, bus) whose box has at least
  ``min_area`` (2000) px; one is found when some output box has IoU >= 0.5 with it;
* **mask IoU**: per near vehicle, inside its reference box grown by 10 % on each side,
  the IoU of the output mask with all reference object pixels there; a missed vehicle
  (no output mask pixels there) simply scores what the mask gives -- usually 0;
* **person/bike recall** (``person``, ``bicycle``, ``motorcycle``; any size);
* **false boxes per frame**: output boxes that overlap no reference object of a
  dynamic class (IoU < 0.1 with every reference box) -- an upper bound, since the
  references miss some far and half-hidden vehicles.

Misses always count: nothing is averaged over found objects only.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..masking.boxes import box_iou

VEHICLES = frozenset({"car", "truck", "bus"})
RIDERS = frozenset({"person", "bicycle", "motorcycle"})
NEAR_AREA = 2000.0
MATCH_IOU = 0.5
FALSE_BOX_IOU = 0.1

__all__ = ["RecallScore", "ReferenceFrame", "box_iou", "load_references", "score_frame"]


@dataclass
class ReferenceFrame:
    """One reference frame: its instance map and instances (class, box)."""

    index: int
    ids: np.ndarray  # uint8 (H, W)
    classes: list[str]
    boxes: np.ndarray  # (N, 4) float64

    @property
    def shape(self) -> tuple[int, int]:
        return self.ids.shape[:2]  # type: ignore[return-value]


def load_references(ref_dir: str | Path) -> list[ReferenceFrame]:
    """All ``NNNNNN.json``/``.png`` pairs of a reference folder, by frame index."""
    d = Path(ref_dir)
    if not d.is_dir():
        raise InputError("reference mask folder not found", d)
    out = []
    for js in sorted(d.glob("*.json")):
        try:
            meta = json.loads(js.read_text())
            index = int(js.stem)
        except (OSError, ValueError) as e:
            raise InputError(f"unreadable reference file: {e}", js) from None
        png = js.with_suffix(".png")
        ids = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        if ids is None:
            raise InputError("reference instance map missing or unreadable", png)
        inst = meta.get("instances", [])
        boxes = np.array([o["box"] for o in inst], np.float64).reshape(-1, 4)
        out.append(ReferenceFrame(index, ids, [str(o["class"]) for o in inst], boxes))
    if not out:
        raise InputError("no NNNNNN.json reference files", d)
    return out


@dataclass
class RecallScore:
    """Totals over a sequence (see the module docstring for each figure)."""

    frames: int = 0
    vehicles: int = 0
    vehicles_found: int = 0
    riders: int = 0
    riders_found: int = 0
    output_boxes: int = 0
    false_boxes: int = 0
    ious: list[float] = field(default_factory=list)

    @property
    def recall_vehicles(self) -> float:
        return self.vehicles_found / max(self.vehicles, 1)

    @property
    def recall_riders(self) -> float:
        return self.riders_found / max(self.riders, 1)

    @property
    def mask_iou_vehicles(self) -> float:
        return float(np.mean(self.ious)) if self.ious else 0.0

    @property
    def false_boxes_per_frame(self) -> float:
        return self.false_boxes / max(self.frames, 1)

    def to_dict(self) -> dict:
        d = asdict(self)
        del d["ious"]
        d.update(recall_vehicles=round(self.recall_vehicles, 4), recall_riders=round(self.recall_riders, 4),
                 mask_iou_vehicles=round(self.mask_iou_vehicles, 4),
                 false_boxes_per_frame=round(self.false_boxes_per_frame, 3))
        return d


def score_frame(
    ref: ReferenceFrame,
    boxes: np.ndarray,
    mask: np.ndarray | None = None,
    score: RecallScore | None = None,
    min_area: float = NEAR_AREA,
) -> RecallScore:
    """Add one frame's output ``boxes`` (N, 4) and left ``mask`` (uint8/bool, the frame's
    shape; None: recall only) to ``score`` (a new one when None)."""
    s = score if score is not None else RecallScore()
    s.frames += 1
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    s.output_boxes += len(boxes)
    classes = np.array(ref.classes, dtype=object)
    dyn = np.isin(classes, list(VEHICLES | RIDERS)) if len(classes) else np.zeros(0, bool)
    if len(boxes):
        if dyn.any():
            best = box_iou(boxes, ref.boxes[dyn]).max(axis=1)
            s.false_boxes += int(np.count_nonzero(best < FALSE_BOX_IOU))
        else:
            s.false_boxes += len(boxes)
    if mask is not None:
        if mask.shape[:2] != ref.shape:
            raise InputError(f"output mask shape {mask.shape[:2]} differs from the reference's {ref.shape} "
                             f"(frame {ref.index})")
        pred = np.asarray(mask) > (127 if mask.dtype == np.uint8 else 0)
    H, W = ref.shape
    iou = box_iou(ref.boxes, boxes) if len(boxes) and len(ref.boxes) else np.zeros((len(ref.boxes), 0))
    for k, cls in enumerate(ref.classes):  # a handful of reference objects per frame
        x0, y0, x1, y1 = ref.boxes[k]
        near = (x1 - x0) * (y1 - y0) >= min_area
        found = bool(iou.shape[1] and iou[k].max() >= MATCH_IOU)
        if cls in VEHICLES and near:
            s.vehicles += 1
            s.vehicles_found += found
            if mask is not None:
                dx, dy = 0.10 * (x1 - x0), 0.10 * (y1 - y0)
                X0, Y0 = max(int(x0 - dx), 0), max(int(y0 - dy), 0)
                X1, Y1 = min(int(x1 + dx) + 1, W), min(int(y1 + dy) + 1, H)
                r, p = ref.ids[Y0:Y1, X0:X1] > 0, pred[Y0:Y1, X0:X1]
                union = np.count_nonzero(r | p)
                s.ious.append(np.count_nonzero(r & p) / union if union else 0.0)
        elif cls in RIDERS:
            s.riders += 1
            s.riders_found += found
    return s
