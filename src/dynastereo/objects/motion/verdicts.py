"""The deciding half of the motion test (main thread): :class:`MotionJudge` weighs each
frame's flow against the camera motion and keeps, per track, the hysteresis that gives the
verdict moving / static / undecided (the package doc of :mod:`dynastereo.objects.motion`)."""

from __future__ import annotations

import functools
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ...config import MotionConfig
from ...datatypes import StereoCalibration, StereoMasks
from ...masking.boxes import box_iou
from ...masking.detection.classes import canonical_name, class_group_index
from .flow import FrameFlow, ObjectFlow
from .stats import _group_median, _mahalanobis, _object_velocities, _point_velocities, static_residuals

# class groups whose names a detector swaps on one object (the box tracker's)
_GROUP_OF = class_group_index()


@functools.lru_cache(maxsize=256)
def _group(label: str):
    """The class group of a detector label (its own name outside the groups)."""
    return _GROUP_OF.get(canonical_name(label), label)


# the speed's reported sigma: the velocity covariance's along the velocity, times this.  The
# covariance is the rest test's, conservative by design (shared biases, pose noise); on the
# development seeds (10-12, 7,011 object-frames) |speed error| / its sigma had a median of
# 0.19 at every range (0-15, 15-30, 30-60 m: the shape right, the scale not), so scaled
# for a normal's median of 0.674
SPEED_SIGMA_SCALE = 0.28
# the slow road users, whose rest the test must tell from a walking or cycling pace
SLOW_GROUPS = frozenset({_group("person"), _group("bicycle")})


def _median3(v) -> float:
    """``np.median`` of a few numbers (the last speeds), without numpy's overhead."""
    v = sorted(v)
    m = len(v) // 2
    return float(v[m]) if len(v) % 2 else 0.5 * (v[m - 1] + v[m])


@dataclass
class _TrackState:
    moving: bool | None = None
    run: int = 0  # > 0: frames of motion evidence in a row; < 0: of rest
    moves: int = 0  # frames of motion evidence since the track was last static (or new)
    quick: bool = True  # every frame of the current run of rest told from rest_resolution
    speeds: deque = field(default_factory=lambda: deque(maxlen=3))
    speed_sigmas: deque = field(default_factory=lambda: deque(maxlen=3))  # each speed's sigma along its velocity
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
        self._restart = -1  # seq of the last suspect frame: the window's anchors start at it
        self._strong = np.zeros(0, bool)  # per object of the frame weighed: both tests failed (_evidence)
        # with a list here, one row per object and frame tested:
        # (seq, track, points, fraction over chi2 (-1: frame skipped), window chi2, evidence)
        self.log: list | None = None

    def reset(self) -> None:
        self.tracks.clear()
        self._last = None
        self._poses.clear()
        self._restart = -1

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

    def _evidence(self, n: np.ndarray, frac: np.ndarray, chi_velocity: np.ndarray,
                  resolved: np.ndarray) -> list[bool | None]:
        """Per object, this frame's evidence from its points tested (``n``), the fraction
        of them over ``chi2``, its velocity's chi-square and whether rest can be told at all
        (``resolved``, :meth:`_resolvable`): True motion, False rest, None
        neither (too few points, or too far; half of ``min_points`` suffice to keep an
        object masked)."""
        c = self.cfg
        enough = n >= max(3, c.min_points // 2)
        moving = enough & ((frac >= c.moving_fraction) | (chi_velocity > c.object_chi2))
        rest = (enough & ~moving & (n >= c.min_points) & (frac <= c.static_fraction)
                & (chi_velocity <= c.object_chi2_static) & resolved)
        # both tests failed by min_points points or more: decisive for an undecided object
        self._strong = (n >= c.min_points) & (frac >= c.moving_fraction) & (chi_velocity > c.object_chi2)
        return [True if m else (False if r else None) for m, r in zip(moving, rest)]

    def _step(self, t: _TrackState, e: bool | None, strong: bool = False, told: bool = True) -> bool:
        """Hysteresis; True when the track turned moving from static.  ``strong``: both
        tests failed at once (:meth:`_evidence`), which decides an undecided track moving
        on its own with ``motion.strong_confirm``; ``told``: the object is near enough for
        the window test to tell its rest from ``rest_resolution`` (:meth:`_resolvable`, any
        class): a proportional release needs every frame of the run of rest told, else a
        mover waits the full ``release_frames`` (a tram 80 m away: its rest is no evidence)."""
        c = self.cfg
        if e is None:
            return False
        t.run = (max(t.run, 0) + 1) if e else (min(t.run, 0) - 1)
        t.moves += bool(e)
        was = t.moving
        # a mover is released after as many frames of rest as it gave of motion, at least
        # confirm_frames and at most release_frames ("proportional"; "fixed": release_frames)
        if not told:
            t.quick = False
        elif t.run == -1:
            t.quick = True  # a new run of rest: quick while every frame of it is told
        quick = e is False and t.quick and c.release == "proportional"
        release = min(c.release_frames, max(c.confirm_frames, t.moves)) if quick else c.release_frames
        if t.run >= c.confirm_frames or (strong and was is None and c.strong_confirm):
            t.moving = True
        elif (was is None and t.run <= -c.confirm_frames) or (was is True and t.run <= -release):
            t.moving = False
        if t.moving is False:
            t.moves = 0
        return was is False and t.moving is True

    def _measured_sigma(self, Cv: np.ndarray, age: np.ndarray, group: np.ndarray, counts: np.ndarray,
                        T1: np.ndarray, X1: np.ndarray) -> np.ndarray:
        """Per object with points (``group`` non-decreasing, ``counts`` its points): the
        standard deviation (m a frame) of its median velocity along its worst direction,
        from its points' own covariances (``Cv``: stereo at both ends over their ages):
        the median point's largest variance * (pi / 2) / n (n at most ``object_points``),
        plus the camera's pose error over the median age -- the median, not the mean, as
        the velocity is a median: a few points first seen a frame ago do not make it noisy."""
        c = self.cfg
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        lam = np.linalg.eigvalsh(Cv)[:, -1]
        med = _group_median(np.column_stack([lam, age]), group, starts, counts)
        n = np.minimum(counts, c.object_points).astype(np.float64)
        X = np.add.reduceat(X1, starts) / counts[:, None]
        pose = np.radians(c.sigma_pose_deg) ** 2 * np.einsum("gi,gi->g", X, X) + c.sigma_pose_m ** 2
        return np.sqrt(med[:, 0] * (0.5 * np.pi) / n + pose / med[:, 1])

    def _rest_limits(self, slow: np.ndarray) -> np.ndarray:
        """(G,) m/s: per object, the speed its rest must be told from (``rest_resolution``
        for the slow road users, ``rest_resolution_vehicle`` for the others; inf: none)."""
        c = self.cfg
        return np.where(slow, c.rest_resolution,
                        np.inf if c.rest_resolution_vehicle is None else c.rest_resolution_vehicle)

    def _resolvable(self, d: np.ndarray, owner: np.ndarray, slow: np.ndarray, dt: float,
                    limit: np.ndarray | None = None) -> np.ndarray:
        """(G,) bool: whether the window test can tell each object at rest at all.  For the
        slow road users (``slow``: persons, bicycles -- a walker at 1.4 m/s, a cyclist at 4):
        whether, at its distance (the median disparity ``d`` of its points, ``owner`` their
        objects), the stereo noise of a velocity over the whole window (``window_frames``
        frames of ``dt`` s, ``object_points`` points) resolves ``rest_resolution`` m/s:
        ``2 sigma <= rest_resolution`` with ``sigma = sqrt(2) sigma_Z / (window dt)
        sqrt(pi / 2 / object_points)``, ``sigma_Z = Z^2 sigma_d / bf``.  Vehicles: the same
        with ``rest_resolution_vehicle`` where it is set, else True (judged at any range).
        An object without points: True.  ``limit``: (G,) m/s to resolve instead (any class)."""
        c = self.cfg
        G = len(slow)
        out = np.ones(G, bool)
        limit = self._rest_limits(slow) if limit is None else limit
        judged = np.isfinite(limit)
        if not len(d) or not judged.any():
            return out
        mine = judged[owner]  # the judged objects' points only (owner non-decreasing: so is owner[mine])
        counts = np.bincount(owner[mine], minlength=G)
        has = counts > 0
        if not has.any():
            return out
        starts = np.concatenate([[0], np.cumsum(counts[has])[:-1]])
        dm = _group_median(d[mine][:, None], owner[mine], starts, counts[has])[:, 0]
        z = self.calib.bf / np.maximum(dm, 1e-6)
        sigma = np.sqrt(2.0) * z * z * c.sigma_disparity / self.calib.bf / (c.window_frames * dt)
        out[has] = 2.0 * sigma * np.sqrt(0.5 * np.pi / c.object_points) <= limit[has]
        return out

    def _weigh(self, flow: FrameFlow, T0: np.ndarray, T1: np.ndarray, labels: list[str]) -> list[int]:
        """The evidence of one frame's flow under the camera motion ``T0`` -> ``T1``: every
        object's points tested at once, per object only the hysteresis; ``labels``: the
        frame's objects' labels (``ObjectFlow.index`` into them)."""
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
        cov = np.zeros((G, 3, 3))  # its covariance
        nvel = np.zeros(G, np.int64)
        chi_v = np.zeros(G)
        slow = np.array([_group(labels[of.index]) in SLOW_GROUPS for of in objs], bool)
        measured = c.rest_sigma == "measured"
        resolved = np.ones(G, bool) if measured else self._resolvable(cat.d1, owner, slow, flow.dt)
        sig_v = np.full(G, np.inf)  # m/s: the velocity's largest standard deviation ("measured")
        if flow.seq in self._poses:
            S = np.array([c.sigma_px**2, c.sigma_px**2, c.sigma_disparity**2])
            win = cat
            if c.suspect_restarts_window and self._restart >= 0:
                # a suspect frame's pose may have jumped: no displacement is measured across
                # it, the points first seen before it are anchored at k-1 instead
                early = (cat.seqa >= 0) & (cat.seqa < self._restart)
                if early.any():
                    win = ObjectFlow(-1, -1, cat.uv0, cat.d0, cat.uv1, cat.d1, np.where(early[:, None], cat.uv0, cat.uva),
                                     np.where(early, cat.d0, cat.da), np.where(early, -1, cat.seqa))
            use, V, Cv, age, X1 = _point_velocities(win, flow.seq, self._poses, self.calib, S)
            if use.any():
                median = c.velocity_noise == "median"
                res = _object_velocities(V, Cv, age, X1, owner[use], G, T1[:3, :3], c.object_points,
                                         np.radians(c.sigma_pose_deg), c.sigma_pose_m, median_cov=median)
                has, vel[has], Cm, nvel[has] = res[:4]
                cov[has] = res[4] if median else Cm  # the speed's sigma: the mean's (SPEED_SIGMA_SCALE)
                chi_v[has] = np.einsum("gi,gi->g", vel[has], np.linalg.solve(Cm, vel[has][:, :, None])[:, :, 0])
                if measured:
                    sig_v[has] = self._measured_sigma(Cv, age, owner[use], nvel[has], T1, X1) / flow.dt
        if measured:
            resolved = 2.0 * sig_v <= self._rest_limits(slow)
        # a quick (proportional) release needs an object near enough for the window test to
        # tell its rest from rest_resolution (the far-walker rule, any class)
        told = self._resolvable(cat.d1, owner, slow, flow.dt, np.full(G, c.rest_resolution))
        evidence = self._evidence(n, frac, chi_v, resolved)
        states = [self.tracks[of.track] for of in objs]
        # the camera's motion itself is suspect when most objects judged static seem to move
        # at once (a bad pose): no evidence from this frame
        judged = [e for t, e in zip(states, evidence) if t.moving is False and e is not None]
        suspect = len(judged) >= 2 and sum(judged) >= c.suspect_fraction * len(judged)
        if self.log is not None:
            self.log.extend((flow.seq, of.track, int(n[k]), -1.0 if suspect else float(frac[k]), float(chi_v[k]),
                             None if suspect else evidence[k]) for k, of in enumerate(objs))
        if suspect:
            self._restart = flow.seq
            return []
        turned = []
        for k, (of, t) in enumerate(zip(objs, states)):
            if self._step(t, evidence[k], bool(self._strong[k]), bool(told[k])):
                turned.append(of.index)
            if nvel[k] >= c.min_points:
                sp = float(np.linalg.norm(vel[k]))
                u = vel[k] / sp if sp > 0 else None  # the sigma along the velocity (at rest: the mean axis')
                var = float(u @ cov[k] @ u) if u is not None else float(np.trace(cov[k])) / 3.0
                t.speeds.append(sp / flow.dt)
                t.speed_sigmas.append(SPEED_SIGMA_SCALE * np.sqrt(max(var, 0.0)) / flow.dt)
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
            turned = self._weigh(flow, last[1], T_wc, [o.label for o in masks.objects])
        for o, v in zip(masks.objects, self.verdicts(masks.objects)):
            t = self.tracks.get(int(o.track_id)) if o.track_id >= 0 else None
            o.moving = v
            o.speed_mps = _median3(t.speeds) if t is not None and t.speeds else None
            o.speed_sigma_mps = _median3(t.speed_sigmas) if t is not None and t.speed_sigmas else None
        stale = [k for k, t in self.tracks.items() if self._n - t.last_seen > 50]
        for k in stale:
            del self.tracks[k]
        return turned
