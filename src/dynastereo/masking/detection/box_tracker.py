"""Box tracker: carry detector boxes between frames so masks cover objects between detections.

The detector need not run on every frame, and it misses objects now and then; a
:class:`BoxTracker` keeps each object's box alive on the frames in between and gives
every box a track id.  Call :meth:`BoxTracker.update` once per frame, in order, with the
frame's grey left image and the detector's :class:`~dynastereo.datatypes.Detections` for
that frame, or ``None`` when the detector did not run on it.

Method
------
*Propagation* (every frame that has a previous frame of the same size; with
``lk_downscale`` 2 the flow is measured on both images shrunk to half by ``cv2.pyrDown``,
the forward-backward bound counted in the small image's pixels).  Each track's
box is moved from the previous image to this one by sparse optical flow, median-flow
style: ``cv2.goodFeaturesToTrack`` picks up to ``max_points`` corners in the *inner*
part of the box on the previous image (a margin of ``inner_margin`` of the box size on
each side is left out, as a box's rim is mostly background); when a box gives fewer than
``min_points`` corners a regular grid over the inner part is added.  The points of all
boxes go through ONE pyramidal Lucas-Kanade call forward and one backward (on the
union of the boxes grown by ``search_margin`` px, not the whole image); a point is
kept when both calls found it and the forward-backward error is below ``fb_max_error``
px.  Per box, a scale ``s`` is
the median ratio of the pairwise distances of its kept points (this frame / previous,
pairs at least ``min_pair_dist`` px apart), clamped to
``[1 / max_scale_change, max_scale_change]``, and the translation is
``t = median(p1 - s * p0)``; the box's corners are mapped by ``x -> s * x + t`` (no
rotation).  A box with fewer than ``min_points`` kept points cannot be propagated: it is
dropped unless a detection of this frame confirms it (matched against its
previous-frame box).  Propagated boxes are clipped to the image; a box narrower or
lower than ``min_box_size`` px (after clipping: it shrank, or it left the image) is
dropped.

*Matching* (frames where the detector ran).  Propagated tracks are matched one-to-one to
the frame's detections by ``scipy.optimize.linear_sum_assignment`` on IoU, allowing only
pairs of the same *class group* with IoU >= ``match_iou``.  Class groups
(``class_groups``): the vehicles ``car``/``bus``/``truck``/``train`` are one group (a
detector flips between them on the same object), ``bicycle``/``motorcycle`` another,
every other class (``person`` included) is its own group.  A matched track takes the
detection's box, score and class (the class is corrected) and is not carried; an
unmatched detection starts a new track (ids count up from 0 per tracker, and
:meth:`BoxTracker.reset` restarts them).  Detections are never dropped by the tracker.

*Carrying*.  A track that is not confirmed by a detection in this frame is returned with
``carried=True``.  Its ``misses`` count only frames where the detector RAN and did not
confirm it (frames with ``None`` are not misses); it is dropped when ``misses >
max_carry`` -- or at its first miss when fewer than ``min_hits`` detector runs have
seen it (a single low-score detection is often a false one).  Independently, it is dropped when it has been carried for more than
``max_age_frames`` frames in a row (any frames).  A carried box's score is its last
detected score times ``score_decay`` per carried frame.  A carried box that overlaps a
box of the same class group kept before it (this frame's detections first, then older
tracks) by IoU >= ``dup_iou`` is dropped as a duplicate.

*Instance masks* (seg models): when detections come with ``masks``, each track keeps its
mask and a carried track's mask is warped with the same ``x -> s * x + t``; the output
has ``masks`` only when every returned box has one.

Output order: the first ``len(detections)`` boxes are this frame's detections in their
order (boxes clipped to the image), then the carried boxes by increasing track id.  The
tracker is deterministic: the same frames and detections give the same output.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from ...compiled import jit
from ...datatypes import Detections
from ..boxes import box_iou
from .classes import CLASS_GROUPS, canonical_name, class_group_index

__all__ = ["BoxTracker", "TrackerParams"]


@dataclass(frozen=True)
class TrackerParams:
    """Parameters of :class:`BoxTracker` (see the module docstring for the rules)."""

    # a detection confirms/corrects a track at this IoU with the track's propagated box
    # (same class group only, see class_groups)
    match_iou: float = 0.3
    # detector frames a track may go unconfirmed (frames with no detector run don't count);
    # one more and it is dropped
    max_carry: int = 3
    # frames in a row (any frames) a track may be carried without a confirming detection
    max_age_frames: int = 12
    # a track seen by fewer detector runs than this is not carried past a run that misses
    # it (one low-score detection is often a false one); frames without a run still carry it
    min_hits: int = 1
    # fewer points surviving the forward-backward check -> the box cannot be propagated
    min_points: int = 6
    # forward-backward LK error (px) to keep a point
    fb_max_error: float = 1.0
    # corners sampled per box (goodFeaturesToTrack's maxCorners)
    max_points: int = 40
    # points are sampled in the box minus this fraction of its width/height on each side
    inner_margin: float = 0.15
    # side of the fallback point grid (added when a box gives fewer than min_points corners)
    grid_side: int = 6
    # LK window (px, square) and pyramid levels above the image (3: motions up to ~60 px)
    lk_win: int = 15
    lk_levels: int = 3
    # LK runs on the union of the boxes grown by this many px, not the whole image (its
    # pyramids are most of the cost); larger motions are beyond a 3-level pyramid anyway
    search_margin: int = 64
    # LK on the image shrunk by this factor (1 or 2; cv2.pyrDown once per frame): a box's
    # motion needs no sub-pixel accuracy, and LK's pyramids -- most of the carrying's CPU --
    # have a quarter of the pixels at 2 (lk_win and lk_levels then apply to the small image)
    lk_downscale: int = 1
    # pairs of points closer than this (px, previous frame) are not used for the scale
    min_pair_dist: float = 4.0
    # the per-frame scale is clamped to [1 / max_scale_change, max_scale_change]
    max_scale_change: float = 1.25
    # a box narrower or lower than this (px) after clipping to the image is dropped
    min_box_size: float = 4.0
    # a carried box's score: last detected score * score_decay ** (frames carried)
    score_decay: float = 0.9
    # a carried box overlapping an earlier-kept box of its class group this much is dropped
    dup_iou: float = 0.7
    # classes that are one group for matching (canonical COCO names); others: own group
    class_groups: tuple[tuple[str, ...], ...] = CLASS_GROUPS

    def __post_init__(self) -> None:
        if not 0.0 < self.match_iou <= 1.0:
            raise ValueError(f"match_iou must be in (0, 1], got {self.match_iou}")
        if self.max_carry < 0 or self.max_age_frames < 0:
            raise ValueError("max_carry and max_age_frames must be >= 0")
        if self.min_points < 2 or self.max_points < self.min_points:
            raise ValueError("need 2 <= min_points <= max_points")
        if not 0.0 <= self.inner_margin < 0.5:
            raise ValueError(f"inner_margin must be in [0, 0.5), got {self.inner_margin}")
        if self.max_scale_change < 1.0:
            raise ValueError(f"max_scale_change must be >= 1, got {self.max_scale_change}")
        if self.lk_win < 3 or self.lk_levels < 0:
            raise ValueError("lk_win must be >= 3 and lk_levels >= 0")
        if self.lk_downscale not in (1, 2):
            raise ValueError(f"lk_downscale must be 1 or 2, got {self.lk_downscale}")


@dataclass
class _Track:
    id: int
    box: np.ndarray  # float64 (4,) x1, y1, x2, y2 in the last processed frame
    score: float  # last detected score
    class_id: int
    misses: int = 0  # detector frames without a confirming detection
    hits: int = 1  # detector frames that detected it
    vel: np.ndarray | None = None  # float64 (4,) box change over the last frame, if known
    age: int = 0  # frames carried since the last confirming detection
    mask: np.ndarray | None = field(default=None, repr=False)  # bool (H, W)


class BoxTracker:
    """Carries detector boxes from frame to frame by sparse optical flow (module docstring)."""

    def __init__(self, params: TrackerParams | None = None):
        self.params = params or TrackerParams()
        p = self.params
        self._group_of = class_group_index(p.class_groups)
        self._lk_kw = dict(
            winSize=(p.lk_win, p.lk_win),
            maxLevel=p.lk_levels,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03),
        )
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget all tracks and the previous frame; track ids start again from 0."""
        self._tracks: list[_Track] = []
        self._next_id = 0
        self._prev: np.ndarray | None = None
        self._prev_small: np.ndarray | None = None  # _prev shrunk by lk_downscale (None: not made)
        self._class_names: tuple[str, ...] = ()

    @property
    def num_tracks(self) -> int:
        return len(self._tracks)

    # ------------------------------------------------------------------ helpers
    def _group(self, class_id: int, names: tuple[str, ...]) -> object:
        if 0 <= class_id < len(names):
            n = canonical_name(names[class_id])
            return ("g", self._group_of[n]) if n in self._group_of else ("c", n)
        return ("i", int(class_id))

    def _sample_points(self, prev: np.ndarray, box: np.ndarray) -> np.ndarray:
        """Points (n, 2) float32 (cv2 pixel-centre coordinates) in the inner part of ``box``."""
        p = self.params
        h, w = prev.shape
        mx = p.inner_margin * (box[2] - box[0])
        my = p.inner_margin * (box[3] - box[1])
        x1, y1 = int(np.floor(max(box[0] + mx, 0))), int(np.floor(max(box[1] + my, 0)))
        x2, y2 = int(np.ceil(min(box[2] - mx, w))), int(np.ceil(min(box[3] - my, h)))
        if x2 - x1 < 3 or y2 - y1 < 3:
            return np.zeros((0, 2), np.float32)
        roi = prev[y1:y2, x1:x2]
        min_dist = max(2.0, min(x2 - x1, y2 - y1) / 10.0)
        c = cv2.goodFeaturesToTrack(roi, p.max_points, 0.01, min_dist, blockSize=3)
        pts = np.zeros((0, 2), np.float32) if c is None else c.reshape(-1, 2) + np.float32([x1, y1])
        if len(pts) < p.min_points:
            g = (np.arange(p.grid_side, dtype=np.float32) + 0.5) / p.grid_side
            gx, gy = np.meshgrid(x1 + g * (x2 - x1) - 0.5, y1 + g * (y2 - y1) - 0.5)
            pts = np.concatenate([pts, np.stack([gx.ravel(), gy.ravel()], 1)]).astype(np.float32)
        return pts

    def _small(self, gray: np.ndarray) -> np.ndarray:
        """The image LK runs on (``lk_downscale``)."""
        return gray if self.params.lk_downscale == 1 else cv2.pyrDown(gray)

    def _propagate(self, gray: np.ndarray, small: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Propagated boxes (T, 4), ok flags (T,), affine (T, 3) = (s, tx, ty) per track."""
        p = self.params
        T = len(self._tracks)
        boxes = np.array([t.box for t in self._tracks], np.float64).reshape(-1, 4)
        ok = np.zeros(T, bool)
        aff = np.tile(np.array([1.0, 0.0, 0.0]), (T, 1))
        pts_list = [self._sample_points(self._prev, t.box) for t in self._tracks]
        owner = np.concatenate([np.full(len(q), i) for i, q in enumerate(pts_list)]) if T else np.zeros(0, int)
        if len(owner) == 0:
            return boxes, ok, aff
        k = p.lk_downscale
        h, w = small.shape
        m = p.search_margin // k
        cx0, cy0 = (max(0, int(np.floor(v / k)) - m) for v in boxes[:, :2].min(axis=0))
        cx1 = min(w, int(np.ceil(boxes[:, 2].max() / k)) + m)
        cy1 = min(h, int(np.ceil(boxes[:, 3].max() / k)) + m)
        prev_small = self._prev_small if self._prev_small is not None else self._small(self._prev)
        prev_c, cur_c = prev_small[cy0:cy1, cx0:cx1], small[cy0:cy1, cx0:cx1]
        off = np.float32([cx0, cy0])
        # pixel centres: x_small = (x + 0.5) / k - 0.5
        p0 = ((np.concatenate(pts_list) + 0.5) / k - 0.5 - off).astype(np.float32).reshape(-1, 1, 2)
        # (the Python binding takes images only, not prebuilt pyramids: 2 builds per call)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev_c, cur_c, p0, None, **self._lk_kw)
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(cur_c, prev_c, p1, None, **self._lk_kw)
        p0, p1, p0b = ((q.reshape(-1, 2) + off + 0.5) * k - 0.5 for q in (p0, p1, p0b))
        fb = np.linalg.norm(p0 - p0b, axis=1)
        good = (st1.ravel() == 1) & (st2.ravel() == 1) & np.isfinite(fb) & (fb < p.fb_max_error * k)
        lo, hi = 1.0 / p.max_scale_change, p.max_scale_change
        _median_flow(p0.astype(np.float64), p1.astype(np.float64), owner.astype(np.int64), good, T, p.min_points,
                     float(p.min_pair_dist), lo, hi, aff, ok)
        # A box whose own points are lost (too dark, too fast, too much scale change) is
        # moved by its velocity of the last frame when it has one, else by the motion of
        # all surviving points together (one scale + translation: the ego-motion's
        # expansion, right for parked cars); only with neither is it lost.
        fallback = np.zeros(T, bool)
        if not ok.all():
            glob = None
            if np.count_nonzero(good) >= 2 * p.min_points:
                a, b = p0[good].astype(np.float64), p1[good].astype(np.float64)
                ac, bc = a - a.mean(0), b - b.mean(0)
                sg = float(np.clip(np.sqrt((bc**2).sum() / max((ac**2).sum(), 1e-9)), lo, hi))
                tg = b.mean(0) - sg * a.mean(0)
                glob = (sg, tg[0], tg[1])
            for i in np.flatnonzero(~ok):
                if self._tracks[i].vel is not None:
                    fallback[i] = True
                elif glob is not None:
                    aff[i] = glob
                    ok[i] = True
        # box corners (x2/y2 exclusive) -> pixel-centre coordinates, map, and back
        s, tx, ty = aff[:, 0:1], aff[:, 1:2], aff[:, 2:3]
        moved = s * (boxes - 0.5) + np.concatenate([tx, ty, tx, ty], axis=1) + 0.5
        boxes = np.where(ok[:, None], moved, boxes)
        for i in np.flatnonzero(fallback):
            boxes[i] = boxes[i] + self._tracks[i].vel
        ok |= fallback
        return boxes, ok, aff

    def _remap_classes(self, names: tuple[str, ...]) -> None:
        """Detections with other class names than before: re-index the tracks' classes by name."""
        if not names or names == self._class_names:
            return
        if self._class_names:
            index = {canonical_name(n): i for i, n in enumerate(names)}
            kept = []
            for t in self._tracks:
                old = self._class_names[t.class_id] if 0 <= t.class_id < len(self._class_names) else None
                new = index.get(canonical_name(old)) if old is not None else None
                if new is not None:
                    t.class_id = new
                    kept.append(t)
            self._tracks = kept
        self._class_names = tuple(names)

    # ------------------------------------------------------------------ main
    def update(
        self, gray: np.ndarray, detections: Detections | None, region: tuple[float, ...] | None = None
    ) -> Detections:
        """Boxes to mask on this frame (see the module docstring for the rules).

        ``gray``: the frame's grey left image, ``uint8 (H, W)`` (a BGR image is converted).
        ``detections``: the detector's output for this frame, or ``None`` if it did not run.
        ``region``: ``(x0, y0, x1, y1)`` when the detector searched only that part of the
        frame (one tile): only tracks whose box centre lies in it count a miss.
        """
        gray = self._prepare(gray, detections)
        h, w = gray.shape
        bounds = np.array([w, h, w, h], np.float64)
        # 1. propagate every track into this frame
        small = None
        if self._tracks and self._prev is not None:
            small = self._small(gray)
            boxes, ok, aff = self._propagate(gray, small)
        else:
            boxes = np.array([t.box for t in self._tracks], np.float64).reshape(-1, 4)
            ok = np.zeros(len(self._tracks), bool)
            aff = np.tile(np.array([1.0, 0.0, 0.0]), (len(self._tracks), 1))
        boxes = np.clip(boxes, 0.0, bounds)
        # 2. match to this frame's detections
        det_boxes = np.zeros((0, 4))
        if detections is not None and len(detections):
            det_boxes = np.clip(detections.boxes.astype(np.float64), 0.0, bounds)
        matched_det = self._match(boxes, det_boxes, detections)
        # 3. tracks of the detections (confirmed or new), in detection order
        out_tracks = self._detection_tracks(det_boxes, detections, matched_det)
        # 4. carried tracks: propagated, not confirmed, within the limits
        carried_tracks = self._carried_tracks(boxes, ok, aff, matched_det, det_boxes, out_tracks,
                                              detections is not None, region, (h, w))
        self._tracks = out_tracks + carried_tracks
        self._prev = gray
        self._prev_small = small  # None: made from _prev when the next frame needs it
        # 5. output
        return self._output(len(out_tracks), detections, (h, w))

    def _prepare(self, gray: np.ndarray, detections: Detections | None) -> np.ndarray:
        """The frame's grey image, checked; tracks dropped across a change of image size;
        the classes remapped to the detector's names."""
        gray = np.asarray(gray)
        if gray.ndim == 3:
            gray = cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
        if gray.dtype != np.uint8 or gray.ndim != 2:
            raise ValueError(f"gray must be a uint8 (H, W) image, got {gray.dtype} {gray.shape}")
        gray = np.ascontiguousarray(gray)
        if self._prev is not None and self._prev.shape != gray.shape:
            self._tracks = []  # cannot propagate across a change of image size
            self._prev = self._prev_small = None
        if detections is not None:
            self._remap_classes(tuple(detections.class_names))
        return gray

    def _match(self, boxes: np.ndarray, det_boxes: np.ndarray, detections: Detections | None) -> np.ndarray:
        """For each track, the index of the detection it matches (-1: none): the same class
        group, IoU of the propagated box at least ``match_iou``, one to one (Hungarian)."""
        p, names = self.params, self._class_names
        T, n_det = len(self._tracks), len(det_boxes)
        matched_det = np.full(T, -1)
        if T and n_det:
            iou = box_iou(boxes, det_boxes)
            tg = [self._group(t.class_id, names) for t in self._tracks]
            dg = [self._group(int(c), names) for c in detections.class_ids]  # type: ignore[union-attr]
            same = np.array([[a == b for b in dg] for a in tg], bool).reshape(T, n_det)
            valid = same & (iou >= p.match_iou)
            if valid.any():
                rows, cols = linear_sum_assignment(np.where(valid, -iou, 1.0))
                keep = valid[rows, cols]
                matched_det[rows[keep]] = cols[keep]
        return matched_det

    def _detection_tracks(
        self, det_boxes: np.ndarray, detections: Detections | None, matched_det: np.ndarray
    ) -> list[_Track]:
        """One track per detection, in detection order: the matched track confirmed, or a
        new one."""
        n_det = len(det_boxes)
        by_id = {t.id: t for t in self._tracks}
        det_track = np.full(n_det, -1, np.int64)
        for ti in np.flatnonzero(matched_det >= 0):
            det_track[matched_det[ti]] = self._tracks[ti].id
        out_tracks: list[_Track] = []
        for j in range(n_det):
            cid = int(detections.class_ids[j])  # type: ignore[union-attr]
            mask = None if detections.masks is None else np.asarray(detections.masks[j], bool)  # type: ignore[union-attr]
            score = float(detections.scores[j])  # type: ignore[union-attr]
            if det_track[j] >= 0:
                t = by_id[int(det_track[j])]
                t.vel = det_boxes[j] - t.box if self._prev is not None else None
                t.box, t.score, t.class_id, t.misses, t.age, t.mask = det_boxes[j], score, cid, 0, 0, mask
                t.hits += 1
            else:
                t = _Track(self._next_id, det_boxes[j], score, cid, mask=mask)
                self._next_id += 1
            out_tracks.append(t)
        return out_tracks

    def _carried_tracks(
        self,
        boxes: np.ndarray,
        ok: np.ndarray,
        aff: np.ndarray,
        matched_det: np.ndarray,
        det_boxes: np.ndarray,
        out_tracks: list[_Track],
        ran: bool,
        region: tuple[float, ...] | None,
        shape: tuple[int, int],
    ) -> list[_Track]:
        """The tracks carried without a detection: propagated, unmatched, within the miss
        and age limits, not too small, and not a duplicate of a kept box of their group."""
        p, names = self.params, self._class_names
        h, w = shape
        kept_boxes = [det_boxes[j] for j in range(len(det_boxes))]
        kept_groups = [self._group(t.class_id, names) for t in out_tracks]
        carried_tracks: list[_Track] = []
        for ti in sorted(range(len(self._tracks)), key=lambda k: self._tracks[k].id):
            if matched_det[ti] >= 0 or not ok[ti]:
                continue
            t = self._tracks[ti]
            b = boxes[ti]
            searched = region is None or (
                region[0] <= (b[0] + b[2]) / 2 < region[2] and region[1] <= (b[1] + b[3]) / 2 < region[3]
            )
            t.misses += int(ran and searched)
            t.age += 1
            if t.misses > (p.max_carry if t.hits >= p.min_hits else 0) or t.age > p.max_age_frames:
                continue
            if b[2] - b[0] < p.min_box_size or b[3] - b[1] < p.min_box_size:
                continue
            g = self._group(t.class_id, names)
            if kept_boxes:
                iou = box_iou(b[None], np.array(kept_boxes))[0]
                if any(iou[k] >= p.dup_iou and kept_groups[k] == g for k in range(len(kept_boxes))):
                    continue
            t.vel = b - t.box
            t.box = b
            if t.mask is not None:
                s, tx, ty = aff[ti]
                M = np.array([[s, 0.0, tx], [0.0, s, ty]])
                t.mask = cv2.warpAffine(t.mask.astype(np.uint8), M, (w, h), flags=cv2.INTER_NEAREST) > 0
            kept_boxes.append(b)
            kept_groups.append(g)
            carried_tracks.append(t)
        return carried_tracks

    def _output(self, n_detected: int, detections: Detections | None, shape: tuple[int, int]) -> Detections:
        """The current tracks as ``Detections``: the detected ones first, then the carried
        ones (``carried`` True), scores decayed by the frames carried."""
        p = self.params
        h, w = shape
        n = len(self._tracks)
        boxes_out = np.array([t.box for t in self._tracks], np.float32).reshape(n, 4)
        scores = np.array(
            [t.score * p.score_decay**t.age for t in self._tracks], np.float32
        ).reshape(n)
        masks = None
        if n and all(t.mask is not None for t in self._tracks):
            masks = np.stack([t.mask for t in self._tracks])  # type: ignore[misc]
        elif n == 0 and detections is not None and detections.masks is not None:
            masks = np.zeros((0, h, w), bool)
        return Detections(
            boxes_out,
            scores,
            np.array([t.class_id for t in self._tracks], np.int32).reshape(n),
            self._class_names,
            masks,
            np.array([t.id for t in self._tracks], np.int64).reshape(n),
            np.array([False] * n_detected + [True] * (n - n_detected), bool).reshape(n),
        )

def warm_up_kernels() -> None:
    """Load (or compile) the tracker's compiled kernel now, not in the first frames."""
    _median_flow(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0, np.bool_), 0, 1, 1.0, 0.5,
                 2.0, np.zeros((0, 3)), np.zeros(0, np.bool_))


@jit
def _median_flow(p0, p1, owner, good, T, min_points, min_pair_dist, lo, hi, aff, ok):  # pragma: no cover - compiled
    """Per track i with at least ``min_points`` good points (``owner`` == i, in order): the
    scale ``s`` -- the median ratio of its points' pairwise distances (this frame over the
    previous, pairs at least ``min_pair_dist`` apart), clamped to [lo, hi], 1 without such
    pairs -- and the translation ``t = median(p1 - s p0)`` per axis, into ``aff[i]`` (s,
    tx, ty), ``ok[i]`` set (median flow, one call a frame)."""
    n = p0.shape[0]
    for i in range(T):
        m = 0
        for j in range(n):
            if good[j] and owner[j] == i:
                m += 1
        if m < min_points:
            continue
        a = np.empty((m, 2))
        b = np.empty((m, 2))
        q = 0
        for j in range(n):
            if good[j] and owner[j] == i:
                a[q, 0], a[q, 1] = p0[j, 0], p0[j, 1]
                b[q, 0], b[q, 1] = p1[j, 0], p1[j, 1]
                q += 1
        ratios = np.empty(m * (m - 1) // 2)
        r = 0
        for u in range(m):
            for v in range(u + 1, m):
                dx0, dy0 = a[u, 0] - a[v, 0], a[u, 1] - a[v, 1]
                d0 = np.sqrt(dx0 * dx0 + dy0 * dy0)
                if d0 >= min_pair_dist:
                    dx1, dy1 = b[u, 0] - b[v, 0], b[u, 1] - b[v, 1]
                    ratios[r] = np.sqrt(dx1 * dx1 + dy1 * dy1) / d0
                    r += 1
        s = min(max(np.median(ratios[:r]), lo), hi) if r > 0 else 1.0
        tx = np.empty(m)
        ty = np.empty(m)
        for u in range(m):
            tx[u] = b[u, 0] - s * a[u, 0]
            ty[u] = b[u, 1] - s * a[u, 1]
        aff[i, 0], aff[i, 1], aff[i, 2] = s, np.median(tx), np.median(ty)
        ok[i] = True
