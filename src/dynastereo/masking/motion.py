"""Mask only what moves: each tracked object judged moving or static from stereo scene flow.

Masking every detected car costs SLAM its best texture when the cars are parked.  This
module decides per object, against the camera's motion that SLAM measured from the
static background (world frame, not the image: a truck that fills the view and drives
with the camera is moving).  Two halves, because masking runs one frame ahead of
tracking on a prefetch thread:

* :class:`SceneFlow` (masking thread, ``measure(frame, masks)`` after the masker):
  for every object seen in frames k-1 and k under the same track id, up to
  ``motion.max_points`` corners on its outline at k-1 (``goodFeaturesToTrack`` on the
  instance label, where the masker's disparity is valid) are followed to k by one
  pyramidal Lucas-Kanade call for all objects (forward-backward checked, error < 1 px);
  a point is kept when it lands on the same object's outline at k with a valid
  disparity there.  Result: a :class:`FrameFlow` of ``(u, v, d)`` at k-1 and k per object.
* :class:`MotionJudge` (main thread): ``select(masks)`` just before ``System.track``
  gives the masks SLAM gets -- only objects judged moving or not yet judged (the safe
  default) are masked, static ones are left to tracking and mapping; ``update(masks,
  pose, ok)`` after tracking weighs the frame's flow against the camera motion
  ``T_{k,k-1}``: a static point's ``(u, v, d)`` at k-1, moved by the camera motion and
  projected, must land on its measurement at k.  The residual's covariance holds the
  measurement noise at k (``sigma_px``, ``sigma_disparity``) and the noise at k-1
  propagated through the prediction (its Jacobian, by finite differences): the stereo
  depth uncertainty ``sigma_Z = Z^2 sigma_d / bf`` and the lateral ``Z sigma_px / f``
  enter that way.  Per object the fraction of points whose chi-square exceeds
  ``motion.chi2`` is evidence of motion (>= ``moving_fraction``) or of rest
  (<= ``static_fraction``); hysteresis over frames (``confirm_frames``,
  ``release_frames``) gives the verdict ``moving`` True / False / None (undecided).
  Speed = the median world-frame displacement of the points / dt (median of the last 3
  frames).  ``update`` returns the tracks that turned moving from static, whose map
  points the caller removes (``System.forget_region``).

Everything is vectorised over the points; the per-object work is a few array slices.
Maskers without instance labels (``seg``) get verdicts but keep every object masked;
objects without a track id (``detector.track: false``) stay undecided (masked).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..config import MotionConfig
from ..types import StereoCalibration, StereoFrame, StereoMasks

__all__ = ["FrameFlow", "ObjectFlow", "SceneFlow", "MotionJudge", "ObjectMotion", "static_chi2"]

_LK = dict(winSize=(15, 15), maxLevel=3, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03))
_FB_MAX = 1.0  # px, forward-backward error to keep a point
_MARGIN = 48  # px around the boxes' union that LK works on


@dataclass
class ObjectFlow:
    """One object's points from frame k-1 to k: pixels ``(n, 2)`` and disparities ``(n,)``."""

    track: int
    index: int  # the object's index in masks.objects at k
    uv0: np.ndarray
    d0: np.ndarray
    uv1: np.ndarray
    d1: np.ndarray

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


def _lookup(img: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(values at the nearest pixels, inside-the-image flags)."""
    h, w = img.shape[:2]
    x = np.rint(uv[:, 0]).astype(np.int64)
    y = np.rint(uv[:, 1]).astype(np.int64)
    inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    return img[np.clip(y, 0, h - 1), np.clip(x, 0, w - 1)], inside


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

    def _corners(self, prev: _Prev, i: int) -> np.ndarray:
        """Up to ``max_points`` points (n, 2) float32 on object ``i``'s outline at k-1."""
        h, w = prev.gray.shape
        x0, y0, x1, y1 = prev.boxes[i]
        x0, y0 = max(int(np.floor(x0)), 0), max(int(np.floor(y0)), 0)
        x1, y1 = min(int(np.ceil(x1)), w), min(int(np.ceil(y1)), h)
        if x1 - x0 < 4 or y1 - y0 < 4:
            return np.zeros((0, 2), np.float32)
        sel = (prev.labels[y0:y1, x0:x1] == i + 1) & (prev.disparity[y0:y1, x0:x1] > 0)
        if np.count_nonzero(sel) < self.cfg.min_points:
            return np.zeros((0, 2), np.float32)
        min_dist = max(2.0, min(x1 - x0, y1 - y0) / 12.0)
        c = cv2.goodFeaturesToTrack(prev.gray[y0:y1, x0:x1], self.cfg.max_points, 0.001, min_dist,
                                    mask=sel.view(np.uint8), blockSize=3)
        if c is None:
            return np.zeros((0, 2), np.float32)
        return (c.reshape(-1, 2) + np.float32([x0, y0])).astype(np.float32)

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
        pts = [self._corners(prev, i) for i, _ in pairs]
        owner = np.concatenate([np.full(len(p), k) for k, p in enumerate(pts)]) if pts else np.zeros(0, int)
        if len(owner) == 0:
            return out
        p0 = np.concatenate(pts)
        # LK on the union of both frames' boxes grown by a margin, not the whole image
        h, w = gray.shape
        sel_boxes = np.concatenate([prev.boxes[[i for i, _ in pairs]], boxes[[j for _, j in pairs]]])
        cx0, cy0 = (max(0, int(v) - _MARGIN) for v in sel_boxes[:, :2].min(axis=0))
        cx1, cy1 = min(w, int(sel_boxes[:, 2].max()) + _MARGIN), min(h, int(sel_boxes[:, 3].max()) + _MARGIN)
        off = np.float32([cx0, cy0])
        a, b = prev.gray[cy0:cy1, cx0:cx1], gray[cy0:cy1, cx0:cx1]
        q0 = (p0 - off).reshape(-1, 1, 2)
        q1, st1, _ = cv2.calcOpticalFlowPyrLK(a, b, q0, None, **_LK)
        q0b, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, q1, None, **_LK)
        p1 = q1.reshape(-1, 2) + off
        fb = np.linalg.norm(q0.reshape(-1, 2) - q0b.reshape(-1, 2), axis=1)
        good = (st1.ravel() == 1) & (st2.ravel() == 1) & np.isfinite(fb) & (fb < _FB_MAX)
        d0, _ = _lookup(prev.disparity, p0)
        d1, in1 = _lookup(masks.box_disparity, p1)
        lab1, _ = _lookup(masks.labels_left, p1)
        cur_label = np.array([j + 1 for _, j in pairs], np.int64)[owner]
        good &= in1 & (d0 > 0) & (d1 > 0) & (lab1 == cur_label)
        for k, (_, j) in enumerate(pairs):
            s = good & (owner == k)
            if np.any(s):
                out.objects.append(ObjectFlow(int(tracks[j]), j, p0[s].astype(np.float64), d0[s].astype(np.float64),
                                              p1[s].astype(np.float64), d1[s].astype(np.float64)))
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
                     sigma_d: float) -> tuple[np.ndarray, np.ndarray]:
    """Per point, the residual ``(n, 3)`` of ``(u, v, d)`` at k against a static object's
    prediction from k-1 under the camera motion ``T_10`` (k-1 camera -> k camera, 4x4) and
    its covariance ``(n, 3, 3)``; rows with a prediction behind the camera are dropped."""
    K, bf = calib.K, calib.bf
    p = _project(flow.uv0, flow.d0, T_10, K, bf)
    # Jacobian of the prediction w.r.t. (u0, v0, d0), by forward differences
    steps = (0.5, 0.5, 0.05)
    J = np.empty((len(p), 3, 3))
    for c, h in enumerate(steps):
        uv, d = flow.uv0.copy(), flow.d0.copy()
        if c < 2:
            uv[:, c] += h
        else:
            d = d + h
        J[:, :, c] = (_project(uv, d, T_10, K, bf) - p) / h
    S = np.array([sigma_px**2, sigma_px**2, sigma_d**2])
    C = np.einsum("nij,j,nkj->nik", J, S, J) + np.diag(S)
    r = np.stack([flow.uv1[:, 0], flow.uv1[:, 1], flow.d1], axis=1) - p
    ok = np.isfinite(r).all(axis=1) & np.isfinite(C).all(axis=(1, 2))
    return r[ok], C[ok]


def _mahalanobis(r: np.ndarray, C: np.ndarray) -> np.ndarray:
    return np.einsum("ni,ni->n", r, np.linalg.solve(C, r[:, :, None])[:, :, 0])


def static_chi2(flow: ObjectFlow, T_10: np.ndarray, calib: StereoCalibration, sigma_px: float,
                sigma_d: float, max_points: int) -> tuple[np.ndarray, float]:
    """(per point chi-square of the static hypothesis, the object's chi-square): the
    object's is that of its median residual, whose covariance is the median point
    covariance * (pi / 2) / n with n at most ``max_points`` (the points' errors are not
    independent: the pose's and the disparity's biases are shared)."""
    r, C = static_residuals(flow, T_10, calib, sigma_px, sigma_d)
    if len(r) == 0:
        return np.zeros(0), 0.0
    chi = _mahalanobis(r, C)
    n = min(len(r), max_points)
    Cm = np.median(C, axis=0) * (np.pi / 2) / n
    return chi, float(_mahalanobis(np.median(r, axis=0)[None], Cm[None])[0])


@dataclass
class _TrackState:
    moving: bool | None = None
    run: int = 0  # > 0: frames of motion evidence in a row; < 0: of rest
    speeds: deque = field(default_factory=lambda: deque(maxlen=3))
    last_seen: int = 0
    evidence: int = 0  # frames that gave evidence either way


class MotionJudge:
    """The deciding half (main thread): module docstring."""

    def __init__(self, cfg: MotionConfig | None, calibration: StereoCalibration):
        self.cfg = cfg or MotionConfig()
        self.cfg.validate()
        self.calib = calibration
        self.tracks: dict[int, _TrackState] = {}
        self._last: tuple[int, np.ndarray] | None = None  # (seq, T_wc 4x4) of the last tracked frame
        self._n = 0
        self._epoch = 0
        # with a list here, one row per object and frame tested:
        # (seq, track, points, fraction over chi2, object chi2, evidence)
        self.log: list | None = None

    def reset(self) -> None:
        self.tracks.clear()
        self._last = None

    def _sync(self, masks: StereoMasks) -> None:
        flow = masks.flow
        if flow is not None and flow.epoch != self._epoch:
            self.reset()
            self._epoch = flow.epoch

    def state(self, track: int) -> bool | None:
        t = self.tracks.get(int(track))
        return None if t is None else t.moving

    def select(self, masks: StereoMasks | None) -> StereoMasks | None:
        """The masks SLAM gets for this frame: only objects judged moving or not yet judged
        (``ObjectMask.masked`` / ``moving`` set on ``masks.objects``); ``masks`` itself
        when every object stays masked."""
        if masks is None:
            return None
        self._sync(masks)
        keep = []
        for i, o in enumerate(masks.objects):
            o.moving = self.state(o.track_id) if o.track_id >= 0 else None
            o.masked = o.moving is not False or masks.labels_left is None
            if o.masked:
                keep.append(i + 1)
        if len(keep) == len(masks.objects):
            return masks
        lut = np.zeros(len(masks.objects) + 1, np.uint8)
        lut[keep] = 255
        out = StereoMasks(lut[masks.labels_left], lut[masks.labels_right], masks.objects, masks.detections,
                          masks.disparity, masks.ground, masks.labels_left, masks.labels_right,
                          masks.box_disparity, masks.flow)
        return out

    def _evidence(self, chi: np.ndarray, chi_obj: float) -> bool | None:
        c = self.cfg
        if len(chi) < max(3, c.min_points // 2):
            return None
        frac = float(np.mean(chi > c.chi2))
        if frac >= c.moving_fraction or chi_obj > c.object_chi2:
            return True  # (half of min_points suffice to keep an object masked)
        if len(chi) >= c.min_points and frac <= c.static_fraction and chi_obj <= c.object_chi2_static:
            return False
        return None

    def _step(self, t: _TrackState, e: bool | None) -> bool:
        """Hysteresis; True when the track turned moving from static."""
        c = self.cfg
        if e is None:
            return False
        t.evidence += 1
        t.run = (max(t.run, 0) + 1) if e else (min(t.run, 0) - 1)
        was = t.moving
        if t.run >= c.confirm_frames:
            t.moving = True
        elif (was is None and t.run <= -c.confirm_frames) or (was is True and t.run <= -c.release_frames):
            t.moving = False
        return was is False and t.moving is True

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
        if flow is not None and last is not None and ok and last[0] == flow.seq - 1:
            T_10 = np.linalg.inv(T_wc) @ last[1]
            c = self.cfg
            for of in flow.objects:
                t = self.tracks[of.track]
                chi, chi_obj = static_chi2(of, T_10, self.calib, c.sigma_px, c.sigma_disparity, c.object_points)
                e = self._evidence(chi, chi_obj)
                if self.log is not None:
                    self.log.append((flow.seq, of.track, len(chi), float(np.mean(chi > c.chi2)) if len(chi) else 0.0,
                                     chi_obj, e))
                if self._step(t, e):
                    turned.append(of.index)
                X0 = _points(of.uv0, of.d0, self.calib.K, self.calib.bf) @ last[1][:3, :3].T + last[1][:3, 3]
                X1 = _points(of.uv1, of.d1, self.calib.K, self.calib.bf) @ T_wc[:3, :3].T + T_wc[:3, 3]
                t.speeds.append(float(np.linalg.norm(np.median(X1 - X0, axis=0))) / flow.dt)
        for o in masks.objects:
            t = self.tracks.get(int(o.track_id)) if o.track_id >= 0 else None
            o.moving = None if t is None else t.moving
            o.speed_mps = float(np.median(t.speeds)) if t is not None and t.speeds else None
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
