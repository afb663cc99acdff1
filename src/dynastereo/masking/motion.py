"""Mask only what moves: each tracked object judged moving or static from stereo scene flow.

Masking every detected car costs SLAM its best texture when the cars are parked.  This
module decides per object, against the camera's motion that SLAM measured from the
static background (world frame, not the image: a truck that fills the view and drives
with the camera is moving).  Two halves, because masking runs one frame ahead of
tracking on a prefetch thread:

* :class:`SceneFlow` (masking thread, ``measure(frame, masks)`` after the masker):
  for every object seen in frames k-1 and k under the same track id, the points followed
  into k-1 topped up to ``motion.max_points`` with new corners on its outline at k-1
  (``goodFeaturesToTrack`` on the instance label, where the masker's disparity is
  valid, 3 px from the points it has) are followed to k by pyramidal Lucas-Kanade, ONE
  forward and one backward call for all objects' points, on the union of their boxes
  (forward-backward checked, error < 1 px); a point is kept when
  it lands on the same object's outline at k with a valid disparity there.  Each point
  keeps where it was first seen (pixel, disparity, frame), up to ``window_frames`` back.
  Result: a :class:`FrameFlow` of ``(u, v, d)`` at k-1, k and first sight per object.
* :class:`MotionJudge` (main thread): ``select(masks)`` just before ``System.track``
  gives the masks SLAM gets -- only objects judged moving or not yet judged (the safe
  default) are masked, static ones are left to tracking and mapping; ``update(masks,
  pose, ok)`` after tracking weighs the frame's flow against the camera motion:

  - frame to frame (:func:`static_chi2`): a static point's ``(u, v, d)`` at k-1, moved by
    ``T_{k,k-1}`` and projected, must land on its measurement at k.  The residual's
    covariance holds the measurement noise at k (``sigma_px``, ``sigma_disparity``) and
    the noise at k-1 propagated through the prediction (its Jacobian, by finite
    differences): the stereo depth uncertainty ``sigma_Z = Z^2 sigma_d / bf`` and the
    lateral ``Z sigma_px / f`` enter that way; the fraction of points over ``chi2``;
  - over the window (:func:`world_velocity`): the object's world velocity, the median of
    ``(X_k - X_first) / age`` of its points in the world frame, against its covariance
    (stereo at both ends, at most ``object_points`` independent points, SLAM's pose
    error as a random walk): chi-square against ``object_chi2``.  The long baseline sees
    a car ahead at the camera's speed far away, which one frame cannot.

  Evidence of motion / rest per frame, hysteresis over frames (``confirm_frames``,
  ``release_frames``) gives the verdict ``moving`` True / False / None (undecided); a
  frame where most objects judged static seem to move gives none (a bad pose).  Speed =
  the velocity's norm / dt (median of the last 3 frames).  ``update`` returns the objects
  that turned moving from static, whose map points :class:`ObjectMotion` removes
  (``System.forget_region``).  An undecided object whose box overlaps a judged one of
  its class group by IoU >= ``duplicate_iou`` is a second detection of it (a detector
  names one car ``car`` and ``truck``) and takes its verdict (:meth:`MotionJudge.verdicts`).

Everything is vectorized over all objects' points at once (grouped medians and sums);
per object there is only the hysteresis.
Maskers without instance labels (``seg``) get verdicts but keep every object masked;
objects without a track id (``detector.track: false``) stay undecided (masked).
"""

from __future__ import annotations

import functools
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..config import MotionConfig
from ..datatypes import StereoCalibration, StereoFrame, StereoMasks
from .detection.classes import canonical_name, class_group_index
from .boxes import box_iou

__all__ = ["FrameFlow", "ObjectFlow", "SceneFlow", "MotionJudge", "ObjectMotion", "static_chi2", "world_velocity"]

_LK = dict(winSize=(11, 11), maxLevel=3, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03))
_FB_MAX = 1.0  # px, forward-backward error to keep a point
_MARGIN = 48  # px around the boxes' union that LK works on
_NEAR = tuple(a.ravel() for a in np.meshgrid(np.arange(-3, 4), np.arange(-3, 4)))  # (dx, dy) offsets
_MIN_PIXELS = 150  # objects with fewer outline pixels are not followed (they stay undecided: masked)
# class groups whose names a detector swaps on one object (detection.classes.CLASS_GROUPS)
_GROUP_OF = class_group_index()
_NONE2 = np.zeros((0, 2), np.float32)
_NO_POINTS = (np.zeros((0, 2)), (np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64)))  # a track's points: none


@functools.lru_cache(maxsize=256)
def _group(label: str):
    """The class group of a detector label (its own name outside the groups)."""
    return _GROUP_OF.get(canonical_name(label), label)


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


# ----------------------------------------------------------------------------- the test


def _project(uv: np.ndarray, d: np.ndarray, T: np.ndarray, K: np.ndarray, bf: float) -> np.ndarray:
    """``(u, v, d)`` (n, 3) of the stereo points ``(uv, d)`` moved by the 4x4 ``T`` (NaN behind)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Z = bf / d
    X = np.stack([(uv[:, 0] - cx) * Z / fx, (uv[:, 1] - cy) * Z / fy, Z], axis=1)
    Y = X @ T[:3, :3].T + T[:3, 3]
    z = np.where(Y[:, 2] > 1e-6, Y[:, 2], np.nan)
    return np.stack([fx * Y[:, 0] / z + cx, fy * Y[:, 1] / z + cy, bf / z], axis=1)


def _points(uv: np.ndarray, d: np.ndarray, K: np.ndarray, bf: float) -> np.ndarray:
    Z = bf / d
    return np.stack([(uv[:, 0] - K[0, 2]) * Z / K[0, 0], (uv[:, 1] - K[1, 2]) * Z / K[1, 1], Z], axis=1)


def static_residuals(flow: ObjectFlow, T_10: np.ndarray, calib: StereoCalibration, sigma_px: float,
                     sigma_d: float, keep: bool = False):
    """Per point, the residual ``(n, 3)`` of ``(u, v, d)`` at k against a static object's
    prediction from k-1 under the camera motion ``T_10`` (k-1 camera -> k camera, 4x4) and
    its covariance ``(n, 3, 3)``; rows with a prediction behind the camera are dropped
    (``keep``: kept, and their flags returned third)."""
    K, bf = calib.K, calib.bf
    # the prediction and its Jacobian w.r.t. (u0, v0, d0) by forward differences: one
    # projection of the points and of their 3 nudged copies
    n = len(flow.d0)
    steps = np.array([0.5, 0.5, 0.05])
    uvd = np.tile(np.column_stack([flow.uv0, flow.d0]), (4, 1))
    uvd[n:] += np.repeat(np.eye(3) * steps, n, axis=0)
    q = _project(uvd[:, :2], uvd[:, 2], T_10, K, bf).reshape(4, n, 3)
    p = q[0]
    J = ((q[1:] - p) / steps[:, None, None]).transpose(1, 2, 0)  # (n, 3 outputs, 3 inputs)
    S = np.array([sigma_px**2, sigma_px**2, sigma_d**2])
    C = np.einsum("nij,j,nkj->nik", J, S, J) + np.diag(S)
    r = np.stack([flow.uv1[:, 0], flow.uv1[:, 1], flow.d1], axis=1) - p
    ok = np.isfinite(r).all(axis=1) & np.isfinite(C).all(axis=(1, 2))
    return (r, C, ok) if keep else (r[ok], C[ok])


def _mahalanobis(r: np.ndarray, C: np.ndarray) -> np.ndarray:
    return np.einsum("ni,ni->n", r, np.linalg.solve(C, r[:, :, None])[:, :, 0])


def static_chi2(flow: ObjectFlow, T_10: np.ndarray, calib: StereoCalibration, sigma_px: float,
                sigma_d: float) -> np.ndarray:
    """Per point, the chi-square (3 dof) of the static hypothesis (:func:`static_residuals`)."""
    r, C = static_residuals(flow, T_10, calib, sigma_px, sigma_d)
    return _mahalanobis(r, C) if len(r) else np.zeros(0)


def _point_cov(uv: np.ndarray, d: np.ndarray, calib: StereoCalibration, S: np.ndarray) -> np.ndarray:
    """Covariances ``(n, 3, 3)`` of the stereo points ``(uv, d)`` (camera frame) for pixel /
    disparity variances ``S`` = (su^2, sv^2, sd^2): sigma_Z = Z^2 sigma_d / bf, lateral Z
    sigma_px / f, and their correlation."""
    fx, fy, cx, cy = calib.fx, calib.fy, calib.cx, calib.cy
    Z = calib.bf / d
    J = np.zeros((len(d), 3, 3))
    J[:, 0, 0] = Z / fx
    J[:, 1, 1] = Z / fy
    J[:, 0, 2] = -(uv[:, 0] - cx) * Z / (fx * d)
    J[:, 1, 2] = -(uv[:, 1] - cy) * Z / (fy * d)
    J[:, 2, 2] = -Z / d
    return np.einsum("nij,j,nkj->nik", J, S, J)


def _point_velocities(flow: ObjectFlow, seq: int, poses: dict[int, np.ndarray], calib: StereoCalibration,
                      S: np.ndarray):
    """Per point with a known anchor pose: (which points (n,) bool, world displacement per
    frame since the anchor (m, 3), its covariance (m, 3, 3), age in frames (m,), the
    point at k in the camera frame (m, 3))."""
    anchor = flow.seqa.copy()
    anchor[anchor < 0] = seq - 1
    known = np.array(sorted(poses), np.int64)
    use = np.isin(anchor, known)
    K, bf = calib.K, calib.bf
    T1 = poses[seq]
    R1 = T1[:3, :3]
    stack = np.stack([poses[int(k)] for k in known]) if len(known) else np.zeros((0, 4, 4))
    Ta = stack[np.searchsorted(known, anchor[use])]
    Ra = Ta[:, :3, :3]
    age = (seq - anchor[use]).astype(np.float64)
    uva, da, uv1, d1 = flow.uva[use], flow.da[use], flow.uv1[use], flow.d1[use]
    Xa = np.einsum("nij,nj->ni", Ra, _points(uva, da, K, bf)) + Ta[:, :3, 3]
    X1 = _points(uv1, d1, K, bf)
    V = ((X1 @ R1.T + T1[:3, 3]) - Xa) / age[:, None]
    Ca = np.einsum("nij,njk,nlk->nil", Ra, _point_cov(uva, da, calib, S), Ra)
    C = (Ca + R1 @ _point_cov(uv1, d1, calib, S) @ R1.T) / (age**2)[:, None, None]
    return use, V, C, age, X1


def _group_median(v: np.ndarray, group: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Per group, the median of the rows ``v`` (m, c) (``np.median``'s value: the mean of
    the two middle ones for an even count); ``group`` (m,) non-decreasing, ``starts`` /
    ``counts`` its groups' first rows and sizes (all > 0)."""
    lo, hi = starts + (counts - 1) // 2, starts + counts // 2
    out = np.empty((len(counts), v.shape[1]))
    for c in range(v.shape[1]):
        sv = v[np.lexsort((v[:, c], group)), c]
        out[:, c] = 0.5 * (sv[lo] + sv[hi])
    return out


def _object_velocities(V, C, age, X1, group, n_groups, R1, max_points, sigma_rot, sigma_t):
    """Per object (``group`` (m,) non-decreasing in ``range(n_groups)``: each point's
    object) with points: (which objects (G,) bool, median velocity (g, 3), its covariance
    (g, 3, 3), points used (g,)) -- :func:`world_velocity`'s model, for all objects at once."""
    counts_all = np.bincount(group, minlength=n_groups)
    has = counts_all > 0
    counts = counts_all[has]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    f = counts.astype(np.float64)
    n = np.minimum(counts, max_points).astype(np.float64)
    X = np.add.reduceat(X1, starts) / f[:, None]
    I3 = np.eye(3)
    pose = (sigma_rot**2 * (np.einsum("gi,gi->g", X, X)[:, None, None] * I3 - X[:, :, None] * X[:, None, :])
            + sigma_t**2 * I3)  # camera frame
    mean_age = np.add.reduceat(age, starts) / f
    Cm = (np.add.reduceat(C, starts) / f[:, None, None] * ((np.pi / 2) / n)[:, None, None]
          + R1 @ pose @ R1.T / mean_age[:, None, None])
    return has, _group_median(V, group, starts, counts), Cm, counts


def world_velocity(flow: ObjectFlow, seq: int, poses: dict[int, np.ndarray], calib: StereoCalibration,
                   sigma_px: float, sigma_d: float, max_points: int, sigma_rot: float = 0.0,
                   sigma_t: float = 0.0) -> tuple[np.ndarray, np.ndarray, int] | None:
    """(the object's world displacement per frame (3,), its covariance (3, 3), points used)
    from its points' displacements since they were first seen (``flow.uva`` / ``da`` at
    frame ``seqa``; ``poses``: seq -> 4x4 camera-to-world of the frames tracked, ``seq``
    this frame's): the median of ``(X_k - X_a) / age`` over the points; the covariance is
    the mean point covariance (stereo at both ends, / age^2) * (pi / 2) / n with n at
    most ``max_points`` (the points' errors are not independent: the pose's and the
    disparity's biases are shared), plus the camera motion's own error per frame:
    ``sigma_rot`` (rad) about any axis moves the object's median point X by ``dw x X``,
    ``sigma_t`` (m) shifts it, both as a random walk over the age.  None: no point has
    a known anchor pose."""
    if seq not in poses:
        return None
    S = np.array([sigma_px**2, sigma_px**2, sigma_d**2])
    use, V, C, age, X1 = _point_velocities(flow, seq, poses, calib, S)
    if not use.any():
        return None
    _, v, Cm, n = _object_velocities(V, C, age, X1, np.zeros(len(V), np.int64), 1, poses[seq][:3, :3],
                                     max_points, sigma_rot, sigma_t)
    return v[0], Cm[0], int(n[0])


def _median3(v) -> float:
    """``np.median`` of a few numbers (the last speeds), without numpy's overhead."""
    v = sorted(v)
    m = len(v) // 2
    return float(v[m]) if len(v) % 2 else 0.5 * (v[m - 1] + v[m])


@dataclass
class _TrackState:
    moving: bool | None = None
    run: int = 0  # > 0: frames of motion evidence in a row; < 0: of rest
    speeds: deque = field(default_factory=lambda: deque(maxlen=3))
    last_seen: int = 0


class MotionJudge:
    """The deciding half (main thread): module docstring."""

    def __init__(self, cfg: MotionConfig | None, calibration: StereoCalibration):
        self.cfg = cfg or MotionConfig()
        self.cfg.validate()
        self.calib = calibration
        self.tracks: dict[int, _TrackState] = {}
        self._last: tuple[int, np.ndarray] | None = None  # (seq, T_wc 4x4) of the last tracked frame
        self._poses: dict[int, np.ndarray] = {}  # seq -> T_wc of the recent frames tracked
        self._n = 0
        self._epoch = 0
        # with a list here, one row per object and frame tested:
        # (seq, track, points, fraction over chi2 (-1: frame skipped), window chi2, evidence)
        self.log: list | None = None

    def reset(self) -> None:
        self.tracks.clear()
        self._last = None
        self._poses.clear()

    def _sync(self, masks: StereoMasks) -> None:
        flow = masks.flow
        if flow is not None and flow.epoch != self._epoch:
            self.reset()
            self._epoch = flow.epoch

    def state(self, track: int) -> bool | None:
        t = self.tracks.get(int(track))
        return None if t is None else t.moving

    def verdicts(self, objects: list) -> list[bool | None]:
        """Per object (``ObjectMask``), its track's verdict; an undecided object that
        overlaps a judged one of its class group (``detection.classes.CLASS_GROUPS``) by
        IoU >= ``duplicate_iou`` is a second detection of that object (a detector names
        one car ``car`` and ``truck``; the tracker keeps both boxes, the second under a new
        id every run) and takes its verdict."""
        v = [self.state(o.track_id) if o.track_id >= 0 else None for o in objects]
        undecided = [k for k, x in enumerate(v) if x is None]
        judged = [k for k, x in enumerate(v) if x is not None]
        if not undecided or not judged:
            return v
        iou = box_iou([objects[k].box for k in undecided], [objects[k].box for k in judged])
        group = [_group(o.label) for o in objects]
        for a, k in enumerate(undecided):
            same = [b for b, j in enumerate(judged) if group[j] == group[k] and iou[a, b] >= self.cfg.duplicate_iou]
            if same:
                v[k] = v[judged[max(same, key=lambda b: iou[a, b])]]
        return v

    def select(self, masks: StereoMasks | None) -> StereoMasks | None:
        """The masks SLAM gets for this frame: only objects judged moving or not yet judged
        (``ObjectMask.masked`` / ``moving`` set on ``masks.objects``; :meth:`verdicts`);
        ``masks`` itself when every object stays masked."""
        if masks is None:
            return None
        self._sync(masks)
        keep = []
        for i, (o, v) in enumerate(zip(masks.objects, self.verdicts(masks.objects))):
            o.moving = v
            o.masked = o.moving is not False or masks.labels_left is None
            if o.masked:
                keep.append(i + 1)
        if len(keep) == len(masks.objects):
            return masks
        left, right = masks.left.copy(), masks.right.copy()
        h, w = left.shape
        for i, o in enumerate(masks.objects):
            if o.masked:
                continue
            # the object's pixels: in its box on the left, in its rows on the right
            x0, y0 = max(int(o.box[0]), 0), max(int(o.box[1]), 0)
            x1, y1 = min(int(np.ceil(o.box[2])), w), min(int(np.ceil(o.box[3])), h)
            crop = left[y0:y1, x0:x1]
            crop[masks.labels_left[y0:y1, x0:x1] == i + 1] = 0
            band = right[y0:y1]
            band[masks.labels_right[y0:y1] == i + 1] = 0
        return StereoMasks(left, right, masks.objects, masks.detections, masks.disparity, masks.ground,
                           masks.labels_left, masks.labels_right, masks.box_disparity, masks.flow)

    def _evidence(self, n: np.ndarray, frac: np.ndarray, chi_velocity: np.ndarray) -> list[bool | None]:
        """Per object, this frame's evidence from its points tested (``n``), the fraction
        of them over ``chi2`` and its velocity's chi-square: True motion, False rest, None
        neither (too few points; half of ``min_points`` suffice to keep an object masked)."""
        c = self.cfg
        enough = n >= max(3, c.min_points // 2)
        moving = enough & ((frac >= c.moving_fraction) | (chi_velocity > c.object_chi2))
        rest = (enough & ~moving & (n >= c.min_points) & (frac <= c.static_fraction)
                & (chi_velocity <= c.object_chi2_static))
        return [True if m else (False if r else None) for m, r in zip(moving, rest)]

    def _step(self, t: _TrackState, e: bool | None) -> bool:
        """Hysteresis; True when the track turned moving from static."""
        c = self.cfg
        if e is None:
            return False
        t.run = (max(t.run, 0) + 1) if e else (min(t.run, 0) - 1)
        was = t.moving
        if t.run >= c.confirm_frames:
            t.moving = True
        elif (was is None and t.run <= -c.confirm_frames) or (was is True and t.run <= -c.release_frames):
            t.moving = False
        return was is False and t.moving is True

    def _weigh(self, flow: FrameFlow, T0: np.ndarray, T1: np.ndarray) -> list[int]:
        """The evidence of one frame's flow under the camera motion ``T0`` -> ``T1``: every
        object's points tested at once, per object only the hysteresis."""
        c = self.cfg
        objs = flow.objects
        if not objs:
            return []
        T_10 = np.linalg.inv(T1) @ T0
        G = len(objs)
        owner = np.repeat(np.arange(G), [len(of) for of in objs])
        cat = ObjectFlow(-1, -1, *(np.concatenate([getattr(of, a) for of in objs])
                                   for a in ("uv0", "d0", "uv1", "d1", "uva", "da", "seqa")))
        # frame to frame: per object, the points tested and the fraction over chi2
        r, C, ok = static_residuals(cat, T_10, self.calib, c.sigma_px, c.sigma_disparity, keep=True)
        over = np.zeros(len(owner), bool)
        if ok.any():
            over[ok] = _mahalanobis(r[ok], C[ok]) > c.chi2
        n = np.bincount(owner[ok], minlength=G)
        frac = np.bincount(owner[over], minlength=G) / np.maximum(n, 1)
        # over the window: per object, its world velocity and the chi-square of rest
        vel = np.zeros((G, 3))
        nvel = np.zeros(G, np.int64)
        chi_v = np.zeros(G)
        if flow.seq in self._poses:
            S = np.array([c.sigma_px**2, c.sigma_px**2, c.sigma_disparity**2])
            use, V, Cv, age, X1 = _point_velocities(cat, flow.seq, self._poses, self.calib, S)
            if use.any():
                has, vel[has], Cm, nvel[has] = _object_velocities(
                    V, Cv, age, X1, owner[use], G, T1[:3, :3], c.object_points, np.radians(c.sigma_pose_deg),
                    c.sigma_pose_m)
                chi_v[has] = np.einsum("gi,gi->g", vel[has], np.linalg.solve(Cm, vel[has][:, :, None])[:, :, 0])
        evidence = self._evidence(n, frac, chi_v)
        states = [self.tracks[of.track] for of in objs]
        # the camera's motion itself is suspect when most objects judged static seem to move
        # at once (a bad pose): no evidence from this frame
        judged = [e for t, e in zip(states, evidence) if t.moving is False and e is not None]
        suspect = len(judged) >= 2 and sum(judged) >= c.suspect_fraction * len(judged)
        if self.log is not None:
            self.log.extend((flow.seq, of.track, int(n[k]), -1.0 if suspect else float(frac[k]), float(chi_v[k]),
                             None if suspect else evidence[k]) for k, of in enumerate(objs))
        if suspect:
            return []
        turned = []
        for k, (of, t) in enumerate(zip(objs, states)):
            if self._step(t, evidence[k]):
                turned.append(of.index)
            if nvel[k] >= c.min_points:
                t.speeds.append(float(np.linalg.norm(vel[k])) / flow.dt)
        return turned

    def update(self, masks: StereoMasks | None, pose: np.ndarray, ok: bool) -> list[int]:
        """Weigh the frame's flow (``masks.flow``) against the camera motion since the last
        frame (``pose``: 3x4 camera-to-world of this frame; ``ok``: tracked, not lost) and
        update the verdicts (``moving`` / ``speed_mps`` of ``masks.objects``).  Returns the
        indices (into ``masks.objects``) of the objects that turned moving from static."""
        self._n += 1
        if masks is not None:
            self._sync(masks)
        flow = masks.flow if masks is not None else None
        T_wc = np.vstack([np.asarray(pose, np.float64)[:3, :4], [0.0, 0.0, 0.0, 1.0]])
        last = self._last
        self._last = ((flow.seq if flow is not None else -1), T_wc) if ok else None
        turned: list[int] = []
        if masks is None:
            return turned
        for o in masks.objects:
            if o.track_id >= 0:
                self.tracks.setdefault(int(o.track_id), _TrackState()).last_seen = self._n
        if flow is not None and ok:
            self._poses[flow.seq] = T_wc
            for k in [k for k in self._poses if k < flow.seq - self.cfg.window_frames - 1]:
                del self._poses[k]
        if flow is not None and last is not None and ok and last[0] == flow.seq - 1:
            turned = self._weigh(flow, last[1], T_wc)
        for o, v in zip(masks.objects, self.verdicts(masks.objects)):
            t = self.tracks.get(int(o.track_id)) if o.track_id >= 0 else None
            o.moving = v
            o.speed_mps = _median3(t.speeds) if t is not None and t.speeds else None
        stale = [k for k, t in self.tracks.items() if self._n - t.last_seen > 50]
        for k in stale:
            del self.tracks[k]
        return turned


def object_region(masks: StereoMasks, index: int, flow: FrameFlow | None, calib: StereoCalibration
                  ) -> tuple[np.ndarray, float, float] | None:
    """(left-image pixels of object ``index``, nearest and farthest depth in metres) of an
    object that turned moving, for removing its map points; None when unknown."""
    if masks.labels_left is None:
        return None
    region = masks.labels_left == index + 1
    d = [of.d1 for of in (flow.objects if flow is not None else []) if of.index == index]
    if not d or not len(d[0]):
        return None
    z = calib.bf / d[0]
    return region, float(z.min()) - 1.0, float(z.max()) + 1.0


class ObjectMotion:
    """Both halves for one stream of frames: ``measure`` on the masking thread, ``select``
    before and ``update`` after ``System.track`` on the tracking thread; ``update`` also
    removes the map points of objects that turned moving (``motion.forget_points``)."""

    def __init__(self, cfg: MotionConfig, calibration: StereoCalibration):
        self.cfg = cfg
        self.calib = calibration
        self.flow = SceneFlow(cfg)
        self.judge = MotionJudge(cfg, calibration)
        self.forgotten = 0  # map points removed so far

    def measure(self, frame: StereoFrame, masks: StereoMasks | None) -> None:
        if masks is not None:
            masks.flow = self.flow.measure(frame, masks)

    def select(self, masks: StereoMasks | None) -> StereoMasks | None:
        return self.judge.select(masks)

    def update(self, masks: StereoMasks | None, tracked, system=None) -> list[int]:
        """``tracked``: the frame's ``TrackResult``; ``system``: the SLAM ``System`` whose map
        loses the points of objects that turned moving (None: the map is left alone)."""
        ok = str(tracked.status) in ("tracked", "init")
        turned = self.judge.update(masks, tracked.pose, ok)
        if turned and system is not None and self.cfg.forget_points and masks is not None:
            for i in turned:
                reg = object_region(masks, i, masks.flow, self.calib)
                if reg is not None:
                    self.forgotten += system.forget_region(*reg)
        return turned


def build_motion(cfg, calibration: StereoCalibration | None, masker=None) -> ObjectMotion | None:
    """The motion test for a job (``cfg``: the whole Config), or None when every detection
    is masked (``motion.mode: all``), nothing is masked, or there is no calibration."""
    if masker is None or getattr(masker, "name", "") == "none" or calibration is None:
        return None
    if str(cfg.motion.mode).lower() == "all":
        return None
    return ObjectMotion(cfg.motion, calibration)
