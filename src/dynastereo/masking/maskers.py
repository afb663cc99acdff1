"""Maskers: detections + disparity -> masks of the dynamic objects in BOTH stereo images.

* :class:`OutlineMasker` -- the project's method (thesis 3.3): detect on the LEFT image
  only; disparity only where the boxes need it (``stereo.region = "boxes"``, optionally at
  ``stereo.scale`` = 2); per box the dominant disparity peak is the object's outline
  (:mod:`.outline`); each mask is moved to the right image by its disparity
  (:mod:`.transfer`).
* :class:`BoxMasker` -- the cheap baseline: the boxes themselves; the right mask is each
  box shifted by the box's dominant disparity (from the same band disparity).
* :class:`SegMasker` -- pixel masks from an instance-segmentation network run on both
  images (stand-in for DynaSLAM's Mask R-CNN; the shipped model is AGPL: never default).
* :class:`NoneMasker` -- nothing is masked.

Stage times go to the :class:`StageTimer`: ``detect`` (the network alone) and then
``disparity``, ``outline`` / ``boxes``, ``transfer`` (seg: ``segment``), which the pipeline
sums into ``mask``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import cv2
import numpy as np

from ..compiled import jit
from ..config import OutlineConfig, StereoConfig
from ..timing import StageTimer, timed
from ..datatypes import Detections, MaskMethod, ObjectMask, StereoFrame, StereoMasks
from .boxes import box_iou_pairs
from .base import Detector
from .disparity import StereoMatcher
from .ground import DEFAULT_BASELINE, GroundLine, fit_ground_line, road_samples, slope_range
from .outline import (
    LEFT_CONTEXT,
    OutlineResult,
    clip_boxes,
    dominant_disparity,
    outline_objects,
    roi_disparity,
    tolerance,
    warm_up_kernels as outline_kernels,
)
from .transfer import transfer_labels, warm_up_kernels as transfer_kernels

#: Stages that make up ``mask``: everything in masking but the detector network
#: (``detect``); ``contrast`` and ``carry`` are the detection stage's own work.
MASK_STAGES = ("contrast", "carry", "disparity", "outline", "transfer", "segment", "boxes")


_stage = timed  # the maskers' stages, timed when a timer is given


def _to_mask(labels: np.ndarray) -> np.ndarray:
    return (labels > 0).view(np.uint8) * np.uint8(255)


# --------------------------------------------------------------------------------------
# Where to compute disparity
# --------------------------------------------------------------------------------------
def plan_regions(
    matcher: StereoMatcher,
    rois: np.ndarray,
    shape: tuple[int, int],
    scale: int,
    margin: int = 0,
    left_margin: int = 0,
) -> list[tuple[int, int, int, int]]:
    """Image regions ``(y0, y1, x0, x1)`` whose disparity covers all ``rois`` (grown by
    ``margin`` on every side and ``left_margin`` more on the left).

    Block matching costs about (crop area) x numDisparities, and each crop is padded by
    numDisparities columns on the left; so boxes far apart are matched separately and
    boxes whose padded crops overlap are merged into one region when that is cheaper
    (greedy, over the handful of boxes).
    """
    h, w = shape
    rects: list[tuple[int, int, int, int]] = []
    for r in np.asarray(rois).reshape(-1, 4):
        x0, y0, x1, y1 = (int(v) for v in r)
        x0, y0 = max(0, x0 - margin - left_margin), max(0, y0 - margin)
        x1, y1 = min(w, x1 + margin), min(h, y1 + margin)
        if x1 > x0 and y1 > y0:
            rects.append((y0, y1, x0, x1))
    if not rects:
        return []

    left_pad, pad = matcher.crop_padding(scale)  # a region's crop, as StereoMatcher.band_crop makes it
    out = _greedy_regions(np.array(rects, np.int64), h, w, left_pad, pad, scale)
    return [(int(r[0]), int(r[1]), int(r[2]), int(r[3])) for r in out]


@jit
def _greedy_regions(rects, h, w, left_pad, pad, scale):  # pragma: no cover - compiled
    """:func:`plan_regions`' greedy merge over ``rects`` (n, 4) = (y0, y1, x0, x1): while
    some pair's union costs no more than the two apart, merge the pair that saves most
    (the first such pair in (i, j) order on a tie).  A region's cost: its padded crop's
    area (columns from ``x0 - left_pad`` to ``pad`` beyond ``x1``, rows ``pad`` beyond both
    ends, clipped to the image; aligned to ``scale``) plus ``4000 scale^2`` a call."""
    regions = rects.copy()
    n = regions.shape[0]
    cost = np.empty(n, np.int64)
    for i in range(n):
        cost[i] = _crop_cost(regions[i, 0], regions[i, 1], regions[i, 2], regions[i, 3], h, w, left_pad, pad, scale)
    while n > 1:
        best_gain, bi, bj = -1, -1, -1
        by0, by1, bx0, bx1, bcost = 0, 0, 0, 0, 0
        for i in range(n):
            for j in range(i + 1, n):
                y0, y1 = min(regions[i, 0], regions[j, 0]), max(regions[i, 1], regions[j, 1])
                x0, x1 = min(regions[i, 2], regions[j, 2]), max(regions[i, 3], regions[j, 3])
                cu = _crop_cost(y0, y1, x0, x1, h, w, left_pad, pad, scale)
                gain = cost[i] + cost[j] - cu
                if gain >= 0 and (bi < 0 or gain > best_gain):
                    best_gain, bi, bj = gain, i, j
                    by0, by1, bx0, bx1, bcost = y0, y1, x0, x1, cu
        if bi < 0:
            break
        regions[bi, 0], regions[bi, 1], regions[bi, 2], regions[bi, 3] = by0, by1, bx0, bx1
        cost[bi] = bcost
        for k in range(bj, n - 1):  # delete region bj, keeping the order
            regions[k] = regions[k + 1]
            cost[k] = cost[k + 1]
        n -= 1
    return regions[:n]


@jit(inline="always")
def _crop_cost(y0, y1, x0, x1, h, w, left_pad, pad, scale):  # pragma: no cover - compiled
    cx0 = max(0, x0 - left_pad)
    cx1 = min(w, x1 + pad)
    cy0 = max(0, y0 - pad)
    cy1 = min(h, y1 + pad)
    if scale > 1:
        cx0 -= cx0 % scale
        cy0 -= cy0 % scale
    return (cy1 - cy0) * (cx1 - cx0) + 4000 * scale * scale


def region_disparity(
    matcher: StereoMatcher,
    left_gray: np.ndarray,
    right_gray: np.ndarray,
    regions: list[tuple[int, int, int, int]],
    scale: int,
) -> np.ndarray:
    """Full-frame-sized float32 disparity, computed only inside ``regions`` (0 elsewhere)."""
    disp = np.zeros(left_gray.shape[:2], np.float32)
    for y0, y1, x0, x1 in regions:
        disp[y0:y1, x0:x1] = matcher.compute_band(left_gray, right_gray, y0, y1, x0, x1, scale=scale)
    return disp


def _objects(
    dets: Detections,
    method: list[MaskMethod],
    disparity: np.ndarray,
    pixels_left: np.ndarray,
    pixels_right: np.ndarray,
) -> list[ObjectMask]:
    labels = dets.labels()
    return [
        ObjectMask(
            box=tuple(float(v) for v in dets.boxes[i]),  # type: ignore[arg-type]
            label=labels[i],
            score=float(dets.scores[i]),
            method=method[i],
            disparity=float(disparity[i]),
            pixels_left=int(pixels_left[i]),
            pixels_right=int(pixels_right[i]),
            track_id=dets.track_id(i),
            source=dets.source(i),
        )
        for i in range(len(dets))
    ]


class _DisparityMasker:
    """Shared: detector on the left image + disparity where the boxes need it."""

    name = "disparity-base"

    def __init__(
        self,
        detector: Detector,
        matcher: StereoMatcher | None = None,
        stereo: StereoConfig | None = None,
        full_disparity: bool = False,
    ):
        self.detector = detector
        self.matcher = matcher or StereoMatcher(stereo or StereoConfig())
        self.stereo = self.matcher.cfg
        self.full_disparity = bool(full_disparity) or self.stereo.region == "full"
        self.scale = int(self.stereo.scale)

    def warm_up(self, height: int, width: int) -> None:
        """The detector's first (slow) call on a black frame of this size, before the frame
        loop (:meth:`DetectionStage.warm_up`), and the outlines' (row fill, disparity peak),
        the region plan's and the right-image transfer's compiled kernels loaded; no state
        changes."""
        outline_kernels()
        transfer_kernels()
        plan_regions(self.matcher, np.array([[0, 0, 1, 1], [2, 2, 3, 3]]), (max(height, 4), max(width, 4)), self.scale)
        warm = getattr(self.detector, "warm_up", None)
        if warm is not None:
            warm(height, width)

    def mask_detections(
        self, frame: StereoFrame, dets: Detections, timer: StageTimer | None = None
    ) -> StereoMasks:
        """Masks for given detections (the detector is not run), with their instance
        labels and the disparity computed (``labels_left`` / ``labels_right`` /
        ``box_disparity``)."""
        masks, left, right = self.mask_labels(frame, dets, timer)
        masks.labels_left, masks.labels_right = left, right
        return masks

    def mask(self, frame: StereoFrame, timer: StageTimer | None = None) -> StereoMasks:
        return self.mask_detections(frame, self._detect(frame, timer), timer)

    def _no_objects(self, shape: tuple[int, int], dets: Detections,
                    disp: np.ndarray | None) -> tuple[StereoMasks, np.ndarray, np.ndarray]:
        """``mask_labels``'s result for a frame without detections."""
        m = StereoMasks.empty(shape)
        m.detections = dets
        m.disparity = disp if self.full_disparity else None
        m.box_disparity = disp
        z = np.zeros(shape, np.int32)
        return m, z, z

    def _detect(self, frame: StereoFrame, timer: StageTimer | None) -> Detections:
        from .detection.stage import DetectionStage

        if isinstance(self.detector, DetectionStage):
            return self.detector.detect_frame(frame, timer)  # it times its own stages
        with _stage(timer, "detect"):
            return self.detector.detect(frame.left)

    def _disparity(
        self, frame: StereoFrame, rois: np.ndarray, timer: StageTimer | None, left_margin: int = 0
    ) -> np.ndarray | None:
        """Full-frame-sized disparity (0 where not computed); None when nothing is needed.

        The ``disparity`` stage is recorded even then (about 0 ms), so every frame has a
        ``mask`` time and its median is over all frames, not only those with objects.
        """
        with _stage(timer, "disparity"):
            if not self.full_disparity and len(rois) == 0:
                return None
            gl, gr = frame.left_gray, frame.right_gray
            if self.full_disparity:
                return self.matcher.compute(gl, gr, scale=self.scale)
            regions = plan_regions(self.matcher, rois, gl.shape[:2], self.scale, left_margin=left_margin)
            return region_disparity(self.matcher, gl, gr, regions, self.scale)

    def _sweep(self) -> tuple[float, float]:
        return (float(max(self.stereo.min_disparity, 0)), self.matcher.max_disparity)


def _compose_outlines(sub: OutlineResult, fresh: list[int], reuse: dict, rois: np.ndarray,
                      shape: tuple[int, int], ground: GroundLine | None) -> OutlineResult:
    """All objects' outline result: ``sub`` (the outlines of the boxes ``fresh``) and the
    carried outlines ``reuse`` painted far to near (nearer objects win shared pixels)."""
    n = len(fresh) + len(reuse)
    disparity = np.zeros(n, np.float32)
    methods: list[MaskMethod] = [MaskMethod.OUTLINE] * n
    ranges: list[tuple[float, float]] = [(0.0, 0.0)] * n
    for j, k in enumerate(fresh):
        disparity[k], methods[k], ranges[k] = sub.disparity[j], sub.methods[j], sub.ranges[j]
    for k, (_, d, r, m) in reuse.items():
        disparity[k], methods[k], ranges[k] = d, m, r
    rois = np.asarray(rois, np.int32).reshape(-1, 4)
    labels = np.zeros(shape, np.int32)
    sub_of = {k: j + 1 for j, k in enumerate(fresh)}
    for k in sorted(range(n), key=lambda i: (float(disparity[i]), i)):  # a handful of boxes
        x0, y0, x1, y1 = (int(v) for v in rois[k])
        sel = reuse[k][0] if k in reuse else sub.labels[y0:y1, x0:x1] == sub_of[k]
        labels[y0:y1, x0:x1][sel] = k + 1
    pixels = np.array([np.count_nonzero(labels[r[1]:r[3], r[0]:r[2]] == k + 1) for k, r in enumerate(rois)],
                      np.int64)
    return OutlineResult(labels, disparity, methods, rois, pixels, ranges, ground)


class OutlineMasker(_DisparityMasker):
    """Outlines from the dominant disparity peak per box, moved to the right image.

    With ``cfg.ground_removal`` the road's disparity line is fitted per frame (in the
    ``disparity`` stage: a coarse disparity of the image's lower part, :mod:`.ground`)
    and road pixels leave the outlines; the fit (``ok``, ``reason``) is returned in
    ``StereoMasks.ground``.  ``baseline`` (metres, the rig's) sets the plausible road slopes; without
    it ``cfg.ground_baseline`` or KITTI's 0.54 m.
    """

    name = "outline"

    def __init__(
        self,
        detector: Detector,
        matcher: StereoMatcher | None = None,
        cfg: OutlineConfig | None = None,
        stereo: StereoConfig | None = None,
        full_disparity: bool = False,
        baseline: float | None = None,
    ):
        super().__init__(detector, matcher, stereo, full_disparity)
        self.cfg = cfg or OutlineConfig()
        self.cfg.validate()  # (a configuration changed after it was made)
        self.baseline = float(baseline) if baseline else None
        self._kept: dict = {}  # track id -> its outline of the previous frame (cfg.carry_outline)
        self._kept_index = -2

    def ground_baseline(self) -> float:
        """The rig's baseline (m) for the road line: the configuration's, the rig's, else KITTI's."""
        return self.cfg.ground_baseline or self.baseline or DEFAULT_BASELINE

    def ground_slopes(self) -> tuple[float, float]:
        """Plausible road slopes (disparity px per image row) for this rig."""
        return slope_range(self.ground_baseline(), self.cfg.ground_min_height, self.cfg.ground_max_height)

    def fit_ground(self, frame: StereoFrame) -> GroundLine:
        """The road's disparity line in ``frame``, from a coarse disparity of the image's
        lower part (the same whatever ``stereo.region``/``scale``: masks do not depend on
        where the objects' disparity was computed)."""
        c = self.cfg
        rows, vals = road_samples(self.matcher, frame.left_gray, frame.right_gray, c.ground_rows_from)
        line = fit_ground_line(rows, vals, self.ground_slopes(), frame.shape[0], tolerance=c.ground_fit_tolerance,
                               min_inliers=c.ground_min_inliers)
        return replace(line, baseline=self.ground_baseline())

    # -- carried boxes keep their outline (cfg.carry_outline) ------------------------
    def _carried_outlines(self, frame: StereoFrame, dets: Detections, disp: np.ndarray,
                          rois: np.ndarray) -> dict[int, tuple[np.ndarray, float, tuple[float, float], MaskMethod]]:
        """Per detection index that keeps its outline: (its mask in its ROI, disparity,
        range, method) -- the previous frame's outline of its track moved by the box's
        scale and shift, when the box moved little and the disparity under the moved mask
        is still its peak's."""
        kept = self._kept
        if (not kept or dets.track_ids is None or dets.carried is None
                or frame.index != self._kept_index + 1):
            return {}
        c = self.cfg
        out = {}
        for k in np.flatnonzero(dets.carried):
            st = kept.get(int(dets.track_ids[k]))
            if st is None:
                continue
            b0, b1 = st[0], dets.boxes[k].astype(np.float64)
            w0, h0, w1, h1 = b0[2] - b0[0], b0[3] - b0[1], b1[2] - b1[0], b1[3] - b1[1]
            if min(w0, h0, w1, h1) <= 0:
                continue
            s = 0.5 * (w1 / w0 + h1 / h0)
            shift = float(np.hypot(*((b1[:2] + b1[2:]) / 2 - (b0[:2] + b0[2:]) / 2)))
            if abs(s - 1.0) > c.carry_max_scale or shift > c.carry_max_shift * max(w0, h0):
                continue
            x0, y0, x1, y1 = (int(v) for v in rois[k])
            if x1 - x0 < c.min_box_side or y1 - y0 < c.min_box_side:
                continue
            patch, (px0, py0) = st[1], st[2]
            tx, ty = b1[0] - s * b0[0], b1[1] - s * b0[1]
            M = np.array([[s, 0.0, s * px0 + tx - x0], [0.0, s, s * py0 + ty - y0]])
            moved = cv2.warpAffine(patch.view(np.uint8), M, (x1 - x0, y1 - y0), flags=cv2.INTER_NEAREST) > 0
            if np.count_nonzero(moved) < c.min_box_pixels:
                continue
            d = disp[y0:y1, x0:x1][moved]
            d = d[d > 0]
            want = st[3] * s
            if d.size < max(c.min_valid_fraction * moved.size, 20) or abs(float(np.median(d)) - want) > tolerance(want, c):
                continue  # its disparity peak changed: outlined again
            out[int(k)] = (moved, want, (st[4][0] * s, st[4][1] * s), st[5])
        return out

    def _keep_outlines(self, frame: StereoFrame, dets: Detections, o: OutlineResult) -> None:
        """Each tracked object's outline of this frame, for the next one (true outlines only)."""
        self._kept = {}
        self._kept_index = frame.index
        if dets.track_ids is None:
            return
        for k, tid in enumerate(dets.track_ids):
            if tid < 0 or o.methods[k] != MaskMethod.OUTLINE:
                continue
            x0, y0, x1, y1 = (int(v) for v in o.rois[k])
            self._kept[int(tid)] = (dets.boxes[k].astype(np.float64), o.labels[y0:y1, x0:x1] == k + 1, (x0, y0),
                                    float(o.disparity[k]), tuple(o.ranges[k]), o.methods[k])

    def mask_labels(
        self, frame: StereoFrame, dets: Detections, timer: StageTimer | None = None
    ) -> tuple[StereoMasks, np.ndarray, np.ndarray]:
        """Masks plus the left and right instance label images (int32, ``k + 1`` = detection ``k``)."""
        shape = frame.shape
        rois = clip_boxes(dets.boxes, shape)
        disp = self._disparity(frame, rois, timer, left_margin=LEFT_CONTEXT)
        if len(dets) == 0:
            return self._no_objects(shape, dets, disp)
        assert disp is not None
        ground = None
        if self.cfg.ground_removal:
            with _stage(timer, "disparity"):  # the road's disparity is disparity work too
                ground = self.fit_ground(frame)
        with _stage(timer, "outline"):
            reuse = self._carried_outlines(frame, dets, disp, rois) if self.cfg.carry_outline else {}
            if reuse:
                fresh = [k for k in range(len(dets)) if k not in reuse]
                sub = outline_objects(disp, dets.boxes[fresh], shape, self.cfg, ground=ground,
                                      max_disparity=self.matcher.max_disparity)
                o = _compose_outlines(sub, fresh, reuse, rois, shape, ground)
            else:
                o = outline_objects(disp, dets.boxes, shape, self.cfg, ground=ground,
                                    max_disparity=self.matcher.max_disparity)
            if self.cfg.carry_outline:
                self._keep_outlines(frame, dets, o)
            left = o.mask
        with _stage(timer, "transfer"):
            t = transfer_labels(
                o.labels, o.disparity, o.rois,
                mode=self.cfg.transfer, disp=disp, ranges=o.ranges, sweep=self._sweep(),
                occluded=self.cfg.transfer_occluded,
            )
            right = t.mask
        objects = _objects(dets, o.methods, o.disparity, o.pixels, t.pixels)
        masks = StereoMasks(left, right, objects, dets, disp if self.full_disparity else None, ground=ground,
                            box_disparity=disp)
        return masks, o.labels, t.labels


class BoxMasker(_DisparityMasker):
    """The boxes as masks; right mask = each box shifted by its dominant disparity.

    The box's disparity is the same dominant (nearest-preferring) histogram peak the
    outline uses, from the same band disparity; a box without valid disparity is swept
    over the whole disparity range in the right image (method ``box-fallback:no-disparity``).
    """

    name = "box"

    def __init__(
        self,
        detector: Detector,
        matcher: StereoMatcher | None = None,
        cfg: OutlineConfig | None = None,
        stereo: StereoConfig | None = None,
        full_disparity: bool = False,
        margin: int = 0,
    ):
        super().__init__(detector, matcher, stereo, full_disparity)
        self.cfg = cfg or OutlineConfig()
        self.margin = int(margin)

    def mask_labels(
        self, frame: StereoFrame, dets: Detections, timer: StageTimer | None = None
    ) -> tuple[StereoMasks, np.ndarray, np.ndarray]:
        """Masks plus the left and right instance label images (int32, ``k + 1`` = detection ``k``)."""
        shape = frame.shape
        rois = clip_boxes(dets.boxes, shape, self.margin)
        disp = self._disparity(frame, rois, timer)
        if len(dets) == 0:
            return self._no_objects(shape, dets, disp)
        assert disp is not None
        n = len(dets)
        with _stage(timer, "boxes"):
            disparity = np.zeros(n, np.float32)
            methods = [MaskMethod.BOX] * n
            for i in range(n):
                x0, y0, x1, y1 = (int(v) for v in rois[i])
                droi = roi_disparity(disp, (0, 0), (x0, y0, x1, y1))
                v = droi[droi > 0]
                area = max((x1 - x0) * (y1 - y0), 1)
                if v.size < max(self.cfg.min_valid_fraction * area, 8):
                    disparity[i] = float(np.median(v)) if v.size else 0.0
                    methods[i] = MaskMethod.FALLBACK_NO_DISPARITY
                    continue
                p = dominant_disparity(v, self.cfg.bin_width, rel=self.cfg.peak_tolerance_rel,
                                       near_ratio=self.cfg.near_peak_ratio)
                disparity[i] = p.disparity if p is not None else 0.0
            labels = np.zeros(shape, np.int32)
            for i in sorted(range(n), key=lambda k: float(disparity[k])):  # nearer wins
                x0, y0, x1, y1 = (int(v) for v in rois[i])
                labels[y0:y1, x0:x1] = i + 1
            pixels = np.array([np.count_nonzero(labels[r[1]:r[3], r[0]:r[2]] == i + 1)
                               for i, r in enumerate(rois)], np.int64)
            left = _to_mask(labels)
        with _stage(timer, "transfer"):
            t = transfer_labels(labels, disparity, rois, mode="rigid", sweep=self._sweep())
            right = t.mask
        objects = _objects(dets, methods, disparity, pixels, t.pixels)
        masks = StereoMasks(left, right, objects, dets, disp if self.full_disparity else None, box_disparity=disp)
        return masks, labels, t.labels


def match_stereo_detections(left: Detections, right: Detections, max_disparity: float) -> np.ndarray:
    """For each left detection, the index of its right-image detection (-1 if none).

    Same class; the right box is the left one moved left by some disparity in
    ``[0, max_disparity]``: the right box is shifted back by the centre difference and the
    pair with the best resulting box IoU (>= 0.3) is taken, greedily.
    """
    n, m = len(left), len(right)
    out = np.full(n, -1, np.int64)
    if n == 0 or m == 0:
        return out
    lb, rb = left.boxes.astype(np.float64), right.boxes.astype(np.float64)
    lc = (lb[:, 0] + lb[:, 2]) / 2
    rc = (rb[:, 0] + rb[:, 2]) / 2
    shift = lc[:, None] - rc[None, :]  # (n, m) candidate disparities
    shifted = np.repeat(rb[None, :, :], n, axis=0)
    shifted[..., 0] += shift
    shifted[..., 2] += shift
    iou = box_iou_pairs(lb[:, None, :], shifted)  # (n, m): left box i with right box j moved by shift[i, j]
    ok = (left.class_ids[:, None] == right.class_ids[None, :]) & (shift >= -2) & (shift <= max_disparity + 2)
    iou = np.where(ok, iou, 0.0)
    while True:
        i, j = np.unravel_index(int(np.argmax(iou)), iou.shape)
        if iou[i, j] < 0.3:
            break
        out[i] = j
        iou[i, :] = 0
        iou[:, j] = 0
    return out


class SegMasker:
    """Pixel masks from an instance-segmentation network run on BOTH images.

    Stages: ``detect`` = the network on the two images, ``segment`` = post-processing
    (thresholds, NMS, mask decoding and resizing) and the union of the instance masks.
    Models exposing ``raw_outputs`` / ``postprocess`` are timed that way; others run
    ``detect`` whole (timed as ``detect``).
    """

    name = "seg"

    def __init__(self, seg_model: Any, max_disparity: float = 192.0):
        self.model = seg_model
        self.max_disparity = float(max_disparity)
        self._split = hasattr(seg_model, "raw_outputs") and hasattr(seg_model, "postprocess")

    def _run(self, frame: StereoFrame, timer: StageTimer | None) -> tuple[Detections, Detections]:
        if self._split:
            with _stage(timer, "detect"):
                rl = self.model.raw_outputs(frame.left)
                rr = self.model.raw_outputs(frame.right)
            with _stage(timer, "segment"):
                return self.model.postprocess(rl), self.model.postprocess(rr)
        with _stage(timer, "detect"):
            return self.model.detect(frame.left), self.model.detect(frame.right)

    @staticmethod
    def _union(d: Detections, shape: tuple[int, int]) -> np.ndarray:
        if d.masks is None or len(d) == 0:
            return np.zeros(shape, np.uint8)
        return np.any(d.masks, axis=0).view(np.uint8) * np.uint8(255)

    def mask(self, frame: StereoFrame, timer: StageTimer | None = None) -> StereoMasks:
        return self.segment_both(frame, timer)[0]

    def segment_both(
        self, frame: StereoFrame, timer: StageTimer | None = None
    ) -> tuple[StereoMasks, Detections, Detections, np.ndarray]:
        """Masks, the left and right instance detections (with ``masks``) and, per left
        instance, the index of its right instance (-1 if none)."""
        dl, dr = self._run(frame, timer)
        shape = frame.shape
        with _stage(timer, "segment"):
            left = self._union(dl, shape)
            right = self._union(dr, shape)
            match = match_stereo_detections(dl, dr, self.max_disparity)
            n = len(dl)
            pl = np.zeros(n, np.int64)
            pr = np.zeros(n, np.int64)
            disp = np.zeros(n, np.float32)
            if dl.masks is not None and n:
                pl[:] = dl.masks.reshape(n, -1).sum(axis=1)
            for i in range(n):
                j = int(match[i])
                if j >= 0:
                    if dr.masks is not None:
                        pr[i] = int(np.count_nonzero(dr.masks[j]))
                    disp[i] = float((dl.boxes[i, 0] + dl.boxes[i, 2] - dr.boxes[j, 0] - dr.boxes[j, 2]) / 2)
        objects = _objects(dl, [MaskMethod.SEG] * n, disp, pl, pr)
        return StereoMasks(left, right, objects, dl, None), dl, dr, match


class NoneMasker:
    """Masks nothing (plain stereo SLAM)."""

    name = "none"

    def mask(self, frame: StereoFrame, timer: StageTimer | None = None) -> StereoMasks:
        return StereoMasks.empty(frame.shape)
