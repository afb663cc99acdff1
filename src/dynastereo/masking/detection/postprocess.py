"""Post-processing of raw YOLO-style predictions (thesis 3.2.2, Algorithms 1 and 2).

A one-stage detector outputs one *row* per candidate box (10,647 for YOLOv3 at 416x416,
2,535 for YOLOv3-tiny, 3,549 for YOLOX-nano, 2,100 for YOLO11n at 320):

    [cx, cy, w, h, (objectness), score_0 .. score_{C-1}, (extra columns, e.g. mask coefficients)]

:class:`RowLayout` says whether an objectness column is present and whether the final
score is ``objectness * class score`` (YOLOX, FastestDet) or the class score alone
(OpenCV's Darknet output, whose class scores already include objectness; Ultralytics,
which has no objectness).

:func:`postprocess` is the array-wise method (thesis Algorithm 2): stack all rows, keep
the candidates above the score threshold and of a dynamic class with boolean masks over
the whole array, convert only the survivors' boxes, then class-aware NMS
(``cv2.dnn.NMSBoxesBatched``).  There is no Python loop over raw predictions.

:func:`postprocess_loop` is the thesis' first, slow method (Algorithm 1): a Python loop
over every raw prediction.  It is kept ONLY as a benchmark baseline
(``benchmarks/bench_detect.py``) and as a cross-check in the tests; it gives the same
boxes as :func:`postprocess`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np


@dataclass(frozen=True)
class RowLayout:
    """Column layout of the raw prediction rows (see module docstring)."""

    name: str
    objectness: bool  # column 4 is an objectness score; class scores start at 5 (else 4)
    multiply_objectness: bool  # final score = objectness * class score (else class score alone)

    @property
    def class_start(self) -> int:
        return 5 if self.objectness else 4


#: OpenCV's Darknet YOLO output: [cx, cy, w, h] in 0..1, objectness, class scores that
#: already include the objectness (and are zeroed below the layer's threshold).
DARKNET_LAYOUT = RowLayout("darknet", objectness=True, multiply_objectness=False)
#: YOLOX / FastestDet (after grid decoding): objectness and class scores separate.
YOLOX_LAYOUT = RowLayout("yolox", objectness=True, multiply_objectness=True)
#: Ultralytics YOLOv8/YOLO11 (rows = the transposed 1x(4+C)xN output): no objectness.
ULTRALYTICS_LAYOUT = RowLayout("ultralytics", objectness=False, multiply_objectness=False)


@dataclass
class PostResult:
    """Boxes kept after thresholding, class filter and NMS, in the rows' own frame."""

    boxes: np.ndarray  # (K, 4) float32 x1, y1, x2, y2
    scores: np.ndarray  # (K,) float32
    class_ids: np.ndarray  # (K,) int32
    rows: np.ndarray  # (K,) int64 index of each kept box in the stacked rows

    def __len__(self) -> int:
        return len(self.boxes)

    @classmethod
    def empty(cls) -> "PostResult":
        return cls(
            np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32), np.zeros(0, np.int64)
        )


def stack_rows(outputs: np.ndarray | Sequence[np.ndarray]) -> np.ndarray:
    """All prediction rows as one 2-D float32 array (thesis Algorithm 2, lines 1-2)."""
    if isinstance(outputs, np.ndarray):
        arr = outputs
    else:
        parts = [np.asarray(o).reshape(-1, np.asarray(o).shape[-1]) for o in outputs]
        arr = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=0)
    arr = arr.reshape(-1, arr.shape[-1])
    return arr if arr.dtype == np.float32 else arr.astype(np.float32)


def nms(boxes: np.ndarray, scores: np.ndarray, class_ids: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Class-aware non-maximum suppression; indices kept, best score first.

    ``boxes`` are ``x1, y1, x2, y2``.  Boxes of different classes never suppress each other.
    """
    n = len(boxes)
    if n == 0:
        return np.zeros(0, np.int64)
    xywh = np.empty((n, 4), np.float64)
    xywh[:, :2] = boxes[:, :2]
    xywh[:, 2:] = boxes[:, 2:] - boxes[:, :2]
    idx = cv2.dnn.NMSBoxesBatched(
        xywh, np.asarray(scores, np.float32), np.asarray(class_ids, np.int32), -1.0, float(iou_threshold)
    )
    return np.asarray(idx, np.int64).reshape(-1)


def _finish(
    boxes: np.ndarray, scores: np.ndarray, class_ids: np.ndarray, rows: np.ndarray, nms_threshold: float
) -> PostResult:
    keep = nms(boxes, scores, class_ids, nms_threshold)
    return PostResult(
        boxes[keep].astype(np.float32, copy=False),
        scores[keep].astype(np.float32, copy=False),
        class_ids[keep].astype(np.int32, copy=False),
        rows[keep].astype(np.int64, copy=False),
    )


def postprocess(
    outputs: np.ndarray | Sequence[np.ndarray],
    num_classes: int,
    layout: RowLayout,
    score_threshold: float,
    nms_threshold: float,
    dynamic: np.ndarray | None = None,
) -> PostResult:
    """Array-wise post-processing (thesis Algorithm 2).

    ``outputs``: the raw rows, one array or a list of per-layer arrays (stacked here).
    ``dynamic``: boolean per class id (:func:`~.classes.dynamic_class_mask`); ``None`` keeps
    every class.  A box's class is the arg-max over *all* classes; it is then kept only if
    that class is dynamic (so a dog is dropped, not relabelled as a car).
    A box is kept when its score is strictly above ``score_threshold``.
    """
    pred = stack_rows(outputs)
    s = layout.class_start
    cls = pred[:, s : s + num_classes]
    thr = np.float32(score_threshold)
    # Candidate rows: a cheap 1-D test first.  With objectness, score <= objectness
    # (class scores are probabilities <= 1), so objectness > thr is necessary.
    if layout.objectness:
        cand = np.flatnonzero(pred[:, 4] > thr)
    else:
        cand = np.flatnonzero(cls.max(axis=1) > thr)
    if cand.size == 0:
        return PostResult.empty()
    sub = cls[cand]
    class_ids = sub.argmax(axis=1)
    scores = sub[np.arange(cand.size), class_ids]
    if layout.multiply_objectness:
        scores = scores * pred[cand, 4]
    keep = scores > thr
    if dynamic is not None:
        keep &= dynamic[class_ids]
    rows = cand[keep]
    if rows.size == 0:
        return PostResult.empty()
    cxcy = pred[rows, 0:2]
    half = pred[rows, 2:4] / 2
    boxes = np.concatenate([cxcy - half, cxcy + half], axis=1)
    return _finish(boxes, scores[keep], class_ids[keep], rows, nms_threshold)


def postprocess_loop(
    outputs: np.ndarray | Sequence[np.ndarray],
    num_classes: int,
    layout: RowLayout,
    score_threshold: float,
    nms_threshold: float,
    dynamic: np.ndarray | None = None,
) -> PostResult:
    """BASELINE ONLY: the thesis' Algorithm 1, a Python loop over every raw detection.

    Same inputs and result as :func:`postprocess`, kept to measure what the array-wise
    method saves (thesis 4.2: 27.9 ms vs 4 ms).  Do not use it in the pipeline.
    """
    layers = [outputs] if isinstance(outputs, np.ndarray) else list(outputs)
    s = layout.class_start
    thr = np.float32(score_threshold)
    boxes, scores, class_ids, rows = [], [], [], []
    offset = 0
    for layer in layers:  # for layers outputs do
        layer = np.asarray(layer, np.float32).reshape(-1, np.asarray(layer).shape[-1])
        for i, row in enumerate(layer):  # for each detection in layer outputs do
            class_scores = row[s : s + num_classes]
            class_id = int(np.argmax(class_scores))
            score = class_scores[class_id]
            if layout.multiply_objectness:
                score = score * row[4]
            if score > thr and (dynamic is None or dynamic[class_id]):
                cx, cy, w, h = row[0], row[1], row[2], row[3]
                boxes.append([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2])
                scores.append(score)
                class_ids.append(class_id)
                rows.append(offset + i)
        offset += len(layer)
    if not boxes:
        return PostResult.empty()
    return _finish(
        np.array(boxes, np.float32),
        np.array(scores, np.float32),
        np.array(class_ids, np.int32),
        np.array(rows, np.int64),
        nms_threshold,
    )
