"""The measuring half of the motion test (masking thread): :class:`SceneFlow` follows each
tracked object's points from frame k-1 to k (the package doc of :mod:`dynastereo.objects.motion`)
into a :class:`FrameFlow` of :class:`ObjectFlow`."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ...config import MotionConfig
from ...datatypes import StereoFrame, StereoMasks

_LK = dict(winSize=(11, 11), maxLevel=3, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03))
_FB_MAX = 1.0  # px, forward-backward error to keep a point
_MARGIN = 48  # px around the boxes' union that LK works on
_NEAR = tuple(a.ravel() for a in np.meshgrid(np.arange(-3, 4), np.arange(-3, 4)))  # (dx, dy) offsets
_MIN_PIXELS = 150  # objects with fewer outline pixels are not followed (they stay undecided: masked)
_NONE2 = np.zeros((0, 2), np.float32)
_NO_POINTS = (np.zeros((0, 2)), (np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64)))  # a track's points: none


@dataclass
class ObjectFlow:
    """One object's points from frame k-1 to k: pixels ``(n, 2)`` and disparities ``(n,)``."""

    track: int
    index: int  # the object's index in masks.objects at k
    uv0: np.ndarray
    d0: np.ndarray
    uv1: np.ndarray
    d1: np.ndarray
    # each point where it was first seen (followed since): pixel, disparity, frame (seq)
    uva: np.ndarray | None = None
    da: np.ndarray | None = None
    seqa: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.uva is None:  # first seen at k-1
            self.uva, self.da = self.uv0, self.d0
            self.seqa = np.full(len(self.d0), -1, np.int64)

    def __len__(self) -> int:
        return len(self.d0)


@dataclass
class FrameFlow:
    """The objects' scene flow into one frame (``StereoMasks.flow``)."""

    seq: int  # the frame's number in the order measured (0, 1, ...)
    dt: float  # seconds since the previous frame
    objects: list[ObjectFlow] = field(default_factory=list)
    epoch: int = 0  # SceneFlow.reset() counts up: the track ids start again (a new masker)


@dataclass
class _Prev:
    seq: int
    index: int
    stamp: float
    gray: np.ndarray
    labels: np.ndarray
    disparity: np.ndarray
    tracks: np.ndarray  # (N,) track id per object
    boxes: np.ndarray  # (N, 4)
    # per track id, the points followed into this frame: (uv (n, 2), their anchors (uv, d, seq))
    points: dict = field(default_factory=dict)


def _lookup(img: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(values at the nearest pixels, inside-the-image flags)."""
    h, w = img.shape[:2]
    x = np.rint(uv[:, 0]).astype(np.int64)
    y = np.rint(uv[:, 1]).astype(np.int64)
    inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    return img[np.minimum(np.maximum(y, 0), h - 1), np.minimum(np.maximum(x, 0), w - 1)], inside


class SceneFlow:
    """The measuring half (masking thread): module docstring."""

    def __init__(self, cfg: MotionConfig | None = None):
        self.cfg = cfg or MotionConfig()
        self._prev: _Prev | None = None
        self._seq = 0
        self.epoch = 0

    def reset(self) -> None:
        """Forget the previous frame; the verdicts are forgotten too (a new masker's track
        ids start again): the judge sees the new ``epoch``."""
        self._prev = None
        self.epoch += 1

    def _corners(self, prev: _Prev, i: int, have: np.ndarray) -> np.ndarray:
        """Up to ``max_points`` points (n, 2) float32 on object ``i``'s outline at k-1, at
        least 3 px from the points it ``have`` already (and no more than make up the number)."""
        n = self.cfg.max_points - len(have)
        if n < max(3, self.cfg.max_points // 4):
            return _NONE2
        h, w = prev.gray.shape
        x0, y0, x1, y1 = prev.boxes[i]
        x0, y0 = max(int(np.floor(x0)), 0), max(int(np.floor(y0)), 0)
        x1, y1 = min(int(np.ceil(x1)), w), min(int(np.ceil(y1)), h)
        if x1 - x0 < 4 or y1 - y0 < 4:
            return _NONE2
        sel = (prev.labels[y0:y1, x0:x1] == i + 1) & (prev.disparity[y0:y1, x0:x1] > 0)
        if np.count_nonzero(sel) < max(self.cfg.min_points, _MIN_PIXELS):
            return _NONE2
        if len(have):  # not within 3 px of a point followed already
            hx = (np.rint(have[:, 0]).astype(np.int64) - x0)[:, None] + _NEAR[0]
            hy = (np.rint(have[:, 1]).astype(np.int64) - y0)[:, None] + _NEAR[1]
            sel[np.minimum(np.maximum(hy, 0), y1 - y0 - 1), np.minimum(np.maximum(hx, 0), x1 - x0 - 1)] = False
        min_dist = max(2.0, min(x1 - x0, y1 - y0) / 12.0)
        c = cv2.goodFeaturesToTrack(prev.gray[y0:y1, x0:x1], n, 0.001, min_dist,
                                    mask=sel.view(np.uint8), blockSize=3)
        if c is None:
            return _NONE2
        return c.reshape(-1, 2) + np.float32([x0, y0])

    def measure(self, frame: StereoFrame, masks: StereoMasks | None) -> FrameFlow:
        """The objects' flow from the previous frame measured into this one (empty on the
        first frame, after a jump in the frame indices, or without labels/disparity)."""
        seq = self._seq
        self._seq += 1
        prev = self._prev
        self._prev = None
        stamp = float(frame.timestamp)
        dt = stamp - prev.stamp if prev is not None else 0.0
        out = FrameFlow(seq, dt if dt > 0 else 0.1, epoch=self.epoch)
        if masks is None or masks.labels_left is None or masks.box_disparity is None:
            return out
        gray = frame.left_gray
        objs = masks.objects
        tracks = np.array([o.track_id for o in objs], np.int64)
        boxes = np.array([o.box for o in objs], np.float64).reshape(-1, 4)
        self._prev = _Prev(seq, frame.index, stamp, gray, masks.labels_left, masks.box_disparity, tracks, boxes)
        if prev is None or prev.gray.shape != gray.shape or (frame.index >= 0 and frame.index != prev.index + 1):
            return out
        cur_of = {int(t): j for j, t in enumerate(tracks) if t >= 0}
        pairs = [(i, cur_of[int(t)]) for i, t in enumerate(prev.tracks) if t >= 0 and int(t) in cur_of]
        if not pairs:
            return out
        # the points followed into k-1 (anchors kept up to window_frames back), topped up
        # with new corners on the outline at k-1 (anchored there: their disparity at k-1)
        W = self.cfg.window_frames
        p0s, uas, das, sas = [], [], [], []
        for i, _ in pairs:
            uv, (ua, da, sa) = prev.points.get(int(prev.tracks[i]), _NO_POINTS)
            young = seq - sa <= W
            uv, ua, da, sa = uv[young], ua[young], da[young], sa[young]
            new = self._corners(prev, i, uv)
            p0s += (uv, new)
            uas += (ua, new)
            das += (da, np.full(len(new), np.nan))
            sas += (sa, np.full(len(new), seq - 1))
        counts = np.add.reduceat(np.array([len(p) for p in p0s]), np.arange(0, len(p0s), 2))
        if counts.sum() == 0:
            return out
        owner = np.repeat(np.arange(len(pairs)), counts)
        p0 = np.concatenate(p0s).astype(np.float32)
        ua, da, sa = np.concatenate(uas).astype(np.float64), np.concatenate(das), np.concatenate(sas)
        d0, _ = _lookup(prev.disparity, p0)
        fresh = np.isnan(da)
        da[fresh] = d0[fresh]
        # one forward-backward LK call for every object's points, on the union of their
        # boxes (k-1 and k) grown by a margin; the crop starts on the coarsest pyramid
        # level's grid, so its pyramid is the whole image's (a crop origin moving from frame
        # to frame would move LK's coarse start points, and its result by up to the
        # convergence bound 0.03 px: much of a far object's 0.15 px of motion a frame)
        h, w = gray.shape
        bx = np.concatenate([prev.boxes[[i for i, _ in pairs]], boxes[[j for _, j in pairs]]])
        grid = 1 << _LK["maxLevel"]
        cx0 = max(0, int(bx[:, 0].min()) - _MARGIN) // grid * grid
        cy0 = max(0, int(bx[:, 1].min()) - _MARGIN) // grid * grid
        cx1, cy1 = min(w, int(bx[:, 2].max()) + _MARGIN), min(h, int(bx[:, 3].max()) + _MARGIN)
        off = np.float32([cx0, cy0])
        a, b = prev.gray[cy0:cy1, cx0:cx1], gray[cy0:cy1, cx0:cx1]
        q0 = (p0 - off).reshape(-1, 1, 2)
        q1, st1, _ = cv2.calcOpticalFlowPyrLK(a, b, q0, None, **_LK)
        q0b, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, q1, None, **_LK)
        p1 = q1.reshape(-1, 2) + off
        fb = np.linalg.norm(q0.reshape(-1, 2) - q0b.reshape(-1, 2), axis=1)
        good = (st1.ravel() == 1) & (st2.ravel() == 1) & np.isfinite(fb) & (fb < _FB_MAX)
        d1, in1 = _lookup(masks.box_disparity, p1)
        lab1, _ = _lookup(masks.labels_left, p1)
        cur_label = np.array([j + 1 for _, j in pairs], np.int64)[owner]
        good &= in1 & (d0 > 0) & (d1 > 0) & (da > 0) & (lab1 == cur_label)
        keep = np.flatnonzero(good)
        p0, p1 = p0[keep].astype(np.float64), p1[keep].astype(np.float64)
        d0, d1 = d0[keep].astype(np.float64), d1[keep].astype(np.float64)
        ua, da, sa = ua[keep], da[keep], sa[keep]
        ends = np.searchsorted(owner[keep], np.arange(len(pairs) + 1))
        for k, (_, j) in enumerate(pairs):
            s = slice(ends[k], ends[k + 1])
            if s.stop > s.start:
                out.objects.append(ObjectFlow(int(tracks[j]), j, p0[s], d0[s], p1[s], d1[s], ua[s], da[s], sa[s]))
                self._prev.points[int(tracks[j])] = (p1[s], (ua[s], da[s], sa[s]))
        return out
