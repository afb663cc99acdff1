"""Mask quality against ground-truth instance masks (synthetic sequences).

Per object and per view, the IoU of the predicted binary mask with the object's GT
mask, measured inside the object's GT box and ignoring pixels of *other* GT objects
(masking a neighbouring object is right, not a false positive). Objects farther than
``max_distance`` metres, or with fewer than ``min_pixels`` visible pixels, are left out.
:class:`LossBudget` splits an outline masker's left-image errors by cause.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import ImageReadError
from ..datatypes import MaskMethod


@dataclass
class ObjectScore:
    frame: int
    object_id: int
    label: str
    view: str  # "left" | "right"
    distance: float
    iou: float
    precision: float
    recall: float


@dataclass
class MaskAgreement:
    scores: list[ObjectScore] = field(default_factory=list)

    def mean(self, view: str | None = None, field_name: str = "iou") -> float:
        v = [getattr(s, field_name) for s in self.scores if view is None or s.view == view]
        return float(np.mean(v)) if v else float("nan")

    def summary(self) -> dict[str, float]:
        return {
            "iou_left": round(self.mean("left"), 4),
            "iou_right": round(self.mean("right"), 4),
            "iou": round(self.mean(), 4),
            "precision": round(self.mean(field_name="precision"), 4),
            "recall": round(self.mean(field_name="recall"), 4),
            "objects_left": sum(s.view == "left" for s in self.scores),
            "objects_right": sum(s.view == "right" for s in self.scores),
        }


def score_frame(
    frame: int,
    pred: dict[str, np.ndarray],
    gt_ids: dict[str, np.ndarray],
    objects: list,
    max_distance: float = 30.0,
    min_pixels: int = 50,
) -> list[ObjectScore]:
    """Scores of one frame; ``pred``/``gt_ids`` map "left"/"right" to the images,
    ``objects`` are the frame's ``GTObject`` records."""
    out: list[ObjectScore] = []
    for view in ("left", "right"):
        p, g = pred[view] > 0, gt_ids[view]
        for ob in objects:
            box = ob.box_left if view == "left" else ob.box_right
            npx = ob.pixels_left if view == "left" else ob.pixels_right
            if box is None or ob.distance > max_distance or npx < min_pixels:
                continue
            x1, y1, x2, y2 = box
            gid = g[y1:y2, x1:x2]
            mine = gid == ob.id
            counted = mine | (gid == 0)
            pp = p[y1:y2, x1:x2] & counted
            inter = np.count_nonzero(pp & mine)
            union = np.count_nonzero(pp | mine)
            npred = np.count_nonzero(pp)
            nmine = np.count_nonzero(mine)
            out.append(ObjectScore(
                frame, ob.id, ob.label, view, float(ob.distance),
                inter / union if union else 0.0,
                inter / npred if npred else 0.0,
                inter / nmine if nmine else 0.0,
            ))
    return out


class LossBudget:
    """Where an outline masker's left-image pixels go wrong, over the objects scored by
    ``score_frame`` (nearer than 30 m, >= 50 px): inside each object's GT box, false
    positives of its own outline (and those in the box's bottom quarter: the road at its
    base), false positives of *other* boxes' masks, and object pixels no mask covers -- each as a
    share of the object pixels; plus how many objects were outlined or masked whole."""

    def __init__(self, max_distance: float = 30.0, min_pixels: int = 50):
        self.max_distance, self.min_pixels = max_distance, min_pixels
        self.px = {"object": 0, "fp_own": 0, "fp_own_base": 0, "fp_other": 0, "missed": 0}
        self.methods: dict[str, int] = {}

    def add(self, gt_objects: list, detected: list, masks: list, labels: np.ndarray, gt_left: np.ndarray) -> None:
        """One frame: its ``GTObject`` records, the objects the oracle detected (detection
        order), the masker's ``ObjectMask`` records, its left label image (``k + 1`` =
        detection ``k``) and the GT left instance mask."""
        index = {o.id: k for k, o in enumerate(detected)}
        for ob in gt_objects:
            if ob.box_left is None or ob.distance > self.max_distance or ob.pixels_left < self.min_pixels:
                continue
            k = index.get(ob.id)
            if k is None:
                continue
            x1, y1, x2, y2 = ob.box_left
            g, lab = gt_left[y1:y2, x1:x2], labels[y1:y2, x1:x2]
            mine = g == ob.id
            counted = mine | (g == 0)  # other objects' pixels are masked rightly
            own = lab == k + 1
            fp_own = own & counted & ~mine
            self.px["object"] += int(np.count_nonzero(mine))
            self.px["fp_own"] += int(np.count_nonzero(fp_own))
            self.px["fp_own_base"] += int(np.count_nonzero(fp_own[(3 * fp_own.shape[0]) // 4:]))
            self.px["fp_other"] += int(np.count_nonzero((lab > 0) & ~own & counted & ~mine))
            self.px["missed"] += int(np.count_nonzero(mine & (lab == 0)))
            method = masks[k].method
            self.methods[method] = self.methods.get(method, 0) + 1

    def summary(self) -> dict:
        n = max(self.px["object"], 1)
        outlined = self.methods.get(MaskMethod.OUTLINE, 0)
        return {
            "objects": sum(self.methods.values()),
            "outlined": outlined,
            "fallbacks": sum(self.methods.values()) - outlined,
            "methods": dict(sorted(self.methods.items())),
            "object_pixels": self.px["object"],
            **{key: round(self.px[key] / n, 4) for key in ("fp_own", "fp_own_base", "fp_other", "missed")},
        }


def _read_mask(path: Path) -> np.ndarray:
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise ImageReadError("missing or unreadable mask", path)
    return m


def score_mask_dir(
    out_dir: str | Path,
    sequence: str | Path,
    frames: list[int] | None = None,
    max_distance: float = 30.0,
    moving_only: bool = False,
) -> MaskAgreement:
    """Score the masks ``dynastereo mask`` wrote under ``out_dir/masks`` against the GT of
    the synthetic ``sequence`` (frames: those given, else every mask present);
    ``moving_only``: against the objects moving in each frame (the masks of a ``run``
    that masks only what moves, ``motion.mode: moving``)."""
    from ..synth import read_gt_masks, read_objects

    out_dir, seq = Path(out_dir), Path(sequence)
    gt = read_objects(seq)
    if frames is None:
        frames = sorted(int(p.stem) for p in (out_dir / "masks" / "left").glob("*.png"))
    result = MaskAgreement()
    for i in frames:
        name = f"{i:06d}.png"
        pred = {v: _read_mask(out_dir / "masks" / v / name) for v in ("left", "right")}
        gl, gr = read_gt_masks(seq, i)
        objects = [o for o in gt.frames[i] if o.moving or not moving_only]
        result.scores += score_frame(i, pred, {"left": gl, "right": gr}, objects, max_distance)
    return result
