"""Tracking (ORB-SLAM2 ``Tracking``): the pose of every frame against the map, and the
tracking state -- last frame, velocity, reference keyframe -- held once, here.

``Tracker.track(frame, masks) -> TrackResult`` per frame:

1. **features** (left and right ORB outside the masks) and **stereo** row matching
   (``Tracker.features``: no map, so they may be computed ahead on another thread), with
   the disparity offset of :mod:`.selfcal` applied; then the last keyframe's local
   mapping, if it runs on its thread, is waited for (``join_mapping``);
2. **pose**: constant-velocity prediction + projection matching of the last frame's
   points (map points and temporary stereo "visual odometry" points), or, when that
   fails, descriptor matching against the reference keyframe with PnP-RANSAC; then
   local-map tracking (projection of the points of the covisible keyframes) and
   motion-only BA after each matching step.  A pose is accepted only with enough
   support: at least ``min_inliers`` inliers after local-map tracking and at least
   ``min_inlier_fraction`` of the median of the last tracked frames.  Otherwise a
   prior-free search over the map's keyframes runs (:mod:`.relocalization`: bag-of-words
   candidates, PnP-RANSAC, motion-only BA, local map; ``reloc_min_inliers`` needed);
3. **keyframe decision** (``need_new_keyframe``) and the keyframe handed to local
   mapping and loop closing (:class:`~.active_map.ActiveMap`): inline, or on the
   ``local-mapping`` thread once the frame is done (``slam.local_mapping``);
4. **lost**: when no pose is supported the frame's pose is the constant-velocity
   prediction; with ``min_init_points`` stereo points a new map is started there
   (``reset_map``, the System's), else the map is kept to relocalize the next frames in.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from enum import StrEnum
from typing import Callable

import numpy as np

from ..config import SlamConfig
from ..timing import StageTimer, timed
from ..datatypes import StereoCalibration, StereoFrame, StereoMasks
from .active_map import ActiveMap
from .frame import Frame
from .geometry import desc_u64, inv_T, orthonormalize, pnp_ransac
from .keyframe import KeyFrame
from .map import Map
from .matcher import TH_HIGH, keyframe_point_matches, search_by_projection, stereo_match
from .optimizer import optimize_pose, project
from .orb import Features, ORBExtractor
from .relocalization import database_candidates
from .selfcal import SelfCalibration
from .frame_trajectory import FrameTrajectory
from .vocabulary import Vocabulary

log = logging.getLogger("dynastereo.slam")


class TrackingState(StrEnum):
    """What became of a frame."""

    INIT = "init"  # it started a map (the first frame, or a re-initialization)
    TRACKED = "tracked"
    LOST = "lost"  # no supported pose: the constant-velocity prediction


class TrackingMethod(StrEnum):
    """How a frame's pose was found."""

    INIT = "init"
    MOTION = "motion"  # constant-velocity model + the last frame's points
    REFERENCE = "reference"  # the reference keyframe's descriptors + PnP-RANSAC
    RELOC = "reloc"  # prior-free search over the map's keyframes
    NONE = ""  # lost


def _numbered(index: int | None) -> bool:
    """A frame index that is set (a live frame is numbered when it is tracked: None or -1 before)."""
    return index is not None and index >= 0


@dataclass
class FrameFeatures:
    """A frame's ORB features (left image) and their stereo matches (``Tracker.features``):
    what needs no map, so it may be computed ahead of tracking, on another thread."""

    index: int | None  # the frame's index (None or -1: a live frame not numbered yet)
    left: Features
    u_right: np.ndarray  # (N,) right-image u of each left keypoint, -1 none
    depth: np.ndarray  # (N,) metres, -1 none


@dataclass
class TrackResult:
    """One frame as tracked (``System.track``, ``System.results()``)."""

    index: int  # position in the order fed
    frame_index: int  # StereoFrame.index
    status: TrackingState
    method: TrackingMethod
    keyframe: bool  # a lost frame that starts a new map is its first keyframe
    inliers: int  # after local-map tracking (lost: of the best refused pose, 0 if none)
    n_features: int
    n_stereo: int
    map_id: int  # increments at each re-initialization
    pose: np.ndarray  # 3x4 camera-to-world as tracked (trajectory() has the refined one)

    @property
    def ok(self) -> bool:
        return self.status != TrackingState.LOST


@dataclass
class Recovery:
    """A frame tracked again after lost frames (``System.recoveries()``)."""

    frame: int  # position in the order fed
    frame_index: int
    lost_frames: int  # lost frames just before it
    method: TrackingMethod  # found in the same map (reloc / reference / motion) or INIT (a new map)
    map_id: int


class Tracker:
    """The tracking thread of ORB-SLAM2 (module doc).  ``cfg``: the ``slam`` section;
    ``selfcal``: the disparity offset applied to every new frame; ``reset_map``: starts a
    new map (``System``'s), which then calls :meth:`attach`."""

    def __init__(
        self,
        cfg: SlamConfig,
        calib: StereoCalibration,
        orb: ORBExtractor,
        selfcal: SelfCalibration,
        vocab: Vocabulary,
        *,
        seed: int = 0,
        reset_map: Callable[[], None] | None = None,
        threads: ThreadPoolExecutor | None = None,
        mapping: ThreadPoolExecutor | None = None,
    ) -> None:
        self.cfg = cfg
        self.calib = calib
        self.orb = orb
        self.selfcal = selfcal
        self.vocab = vocab
        self.seed = int(seed)
        self.th_depth_m = cfg.th_depth * calib.baseline
        self._reset_map = reset_map
        self._threads = threads
        # local mapping of a new keyframe: on this one-thread pool (slam.local_mapping
        # "thread") while the next frame's features and stereo matches are computed, or
        # inline (None); joined before anything reads the map again (join_mapping)
        self._mapping = mapping
        self._mapping_due: tuple[ActiveMap, KeyFrame, np.ndarray, int] | None = None
        self._mapping_job: Future | None = None
        self._mapping_lock = threading.Lock()
        self.mapping_ms: list[float] = []  # each keyframe's local mapping + loop closing, wall ms
        self.mapping_wait_ms: list[float] = []  # tracking's wait for it (thread mode)
        self.localize_only = False
        self.active: ActiveMap | None = None
        # tracking state: kept across maps
        self.velocity: np.ndarray | None = None  # the last frame's motion, camera frame
        self.last_T: np.ndarray | None = None  # the last frame's T_cw
        self.last_ok = False  # the last frame was tracked (not lost)
        self.last_method = TrackingMethod.NONE
        self.anchor = np.eye(4)  # the first frame's pose
        # the frames fed
        self.n = 0
        self.trajectory = FrameTrajectory()
        self.results: list[TrackResult] = []
        self.recoveries: list[Recovery] = []
        self.reloc_ms: list[float] = []
        self.keyframes_created = 0
        self._lost_run = 0
        self._forget_map()

    def _forget_map(self) -> None:
        """Tracking state that belongs to one map."""
        self.last: Frame | None = None
        self.ref_kf: KeyFrame | None = None
        self.last_kf_frame = -(10**9)
        self.n_inliers = 0
        self.local_kfs: list[int] = []
        self.initialized = False
        self.recent_inliers: deque[int] = deque(maxlen=5)

    def attach(self, active: ActiveMap, initialized: bool = False) -> None:
        """Track in ``active`` from now on (a new map; ``initialized``: a loaded one); the
        caller (``System._new_map``) has waited for the old map's mapping first."""
        if self.active is not None:
            self.trajectory.bake(self.active.map)  # the old map's frame poses made absolute
        self.active = active
        self._forget_map()
        self.initialized = bool(initialized)

    # --------------------------------------------------------------- features
    def _features(self, frame: StereoFrame, masks: StereoMasks | None):
        left = frame.left_gray
        right = frame.right_gray
        ml = masks.left if masks is not None else None
        mr = masks.right if masks is not None else None
        ex = self.orb
        if self._threads is not None:
            fr = self._threads.submit(ex.extract, right, mr)
            fl = ex.extract(left, ml)
            return fl, fr.result(), left, right
        return ex.extract(left, ml), ex.extract(right, mr), left, right

    def features(self, frame: StereoFrame, masks: StereoMasks | None, tm: StageTimer | None = None) -> FrameFeatures:
        """ORB features of both images and their stereo matches (``features`` / ``stereo``
        stages of ``tm``, if given).  Reads no map and no tracking state: it may run ahead,
        on another thread."""
        c = self.calib
        if frame.left.shape[:2] != (c.height, c.width):
            raise ValueError(
                f"frame {frame.index}: image size {frame.left.shape[1]}x{frame.left.shape[0]} differs from the "
                f"calibration's {c.width}x{c.height}"
            )
        with timed(tm, "features"):
            fl, fr, pl, pr = self._features(frame, masks)
        with timed(tm, "stereo"):
            st = stereo_match(
                fl.uv, fl.octave, fl.desc, fr.uv, fr.octave, fr.desc, pl, pr, self.orb.scales, c.fx, c.bf
            )
        return FrameFeatures(frame.index, fl, st.u_right, st.depth)

    def make_frame(self, frame: StereoFrame, masks: StereoMasks | None, tm: StageTimer,
                   feats: FrameFeatures | None = None) -> tuple[Frame, float]:
        """``(Frame, the disparity offset its matches carry)`` from ``feats`` (computed
        now when None), with the disparity offset applied."""
        if feats is None:
            feats = self.features(frame, masks, tm)
        elif _numbered(feats.index) and _numbered(frame.index) and feats.index != frame.index:
            raise ValueError(f"features of frame {feats.index} given with frame {frame.index}")
        with tm.stage("stereo"):
            offset_used = self.selfcal.on_frame(feats.left.uv, feats.u_right, feats.depth)
            f = Frame.from_features(self.n, feats.left, feats.u_right, feats.depth, self.calib)
        return f, offset_used

    # ------------------------------------------------------------------ track
    def track(self, frame: StereoFrame, masks: StereoMasks | None, tm: StageTimer,
              feats: FrameFeatures | None = None) -> TrackResult:
        """Track one rectified stereo frame (module doc); stage times go to ``tm``.
        ``feats``: its :meth:`features`, if computed ahead (with the same ``masks``).
        A keyframe it made is mapped afterwards (on the mapping thread), even if the
        frame failed after making it."""
        try:
            return self._track(frame, masks, tm, feats)
        finally:
            self._start_mapping()

    def _track(self, frame: StereoFrame, masks: StereoMasks | None, tm: StageTimer,
               feats: FrameFeatures | None) -> TrackResult:
        assert self.active is not None, "Tracker.attach(map) first"
        n = self.n
        f, offset_used = self.make_frame(frame, masks, tm, feats)
        with tm.stage("local_mapping"):
            self.join_mapping()  # the last keyframe's local mapping ran beside make_frame
        self._refresh_last_pose()
        n_stereo = int(np.count_nonzero(f.depth > 0))
        status, method, is_kf = TrackingState.TRACKED, TrackingMethod.NONE, False
        reason = ""
        with tm.stage("track"):
            if not self.initialized:
                ok = False
            else:
                ok, method, reason = self._track_frame(f, frame.index)
                f.T_cw = orthonormalize(f.T_cw)
        track_inliers = int(self.n_inliers) if self.initialized else 0
        with tm.stage("local_mapping"):
            # the local BA submitted ba_lag_frames ago is applied now (waiting for it if
            # needed): it ran while this frame's features, stereo and tracking were computed
            ref = self.ref_kf if ok else None
            T_ref = ref.T_cw.copy() if ref is not None else None
            self.active.collect(n)
            offset_used = self.selfcal.sync(f, offset_used)
            if T_ref is not None:
                self._follow_reference(f, ref, T_ref)
        if not self.initialized:
            f.T_cw = self._predict()
            f.clear_matches(np.arange(len(f)))
            with tm.stage("local_mapping"):
                is_kf = self._initialize(f, first=(n == 0))
            status, method = (TrackingState.INIT, TrackingMethod.INIT) if is_kf else \
                (TrackingState.LOST, TrackingMethod.NONE)
            if not is_kf:
                log.warning(
                    "frame %d: cannot initialize the map (%d stereo points < %d); "
                    "pose from the constant-velocity prediction",
                    frame.index, n_stereo, self.cfg.min_init_points,
                )
        elif ok:
            self.recent_inliers.append(int(self.n_inliers))
            if not self.localize_only:
                with tm.stage("local_mapping"):
                    if self.need_new_keyframe(self.active.map, f):
                        self._create_keyframe(f)
                        is_kf = True
        else:
            status, method = TrackingState.LOST, TrackingMethod.NONE
            f.T_cw = self._predict()
            f.clear_matches(np.arange(len(f)))
            is_kf = self._lost(f, frame.index, reason, n_stereo, tm, offset_used)
        T_cw = orthonormalize(f.T_cw)
        f.T_cw = T_cw
        self._update_motion(T_cw, status, method)
        # drop temporary VO matches; the frame becomes the last frame
        temp = f.matched & (f.point_ids < 0)
        f.clear_matches(np.flatnonzero(temp))
        self.last = f
        self.selfcal.follow = f
        self._record(T_cw, status, is_kf, n)
        if status == TrackingState.LOST:
            self._lost_run += 1
        elif self._lost_run:
            self.recoveries.append(Recovery(n, frame.index, self._lost_run, method, self.active.id))
            log.info("frame %d: tracked again (%s) after %d lost frames", frame.index, method, self._lost_run)
            self._lost_run = 0
        inliers = track_inliers if status == TrackingState.LOST else int(self.n_inliers)
        res = TrackResult(n, frame.index, status, method, is_kf, inliers, len(f), n_stereo, self.active.id,
                          inv_T(T_cw)[:3].copy())
        self.results.append(res)
        self.n += 1
        return res

    def _lost(self, f: Frame, frame_index: int, reason: str, n_stereo: int, tm: StageTimer,
              offset_used: float) -> bool:
        """No supported pose: keep the map (localization only, or too few stereo points),
        else start a new map at the predicted pose.  True when ``f`` became a keyframe."""
        if self.localize_only:
            log.warning(
                "frame %d: tracking lost (%s); pose from the constant-velocity prediction; "
                "localization only: the map is kept",
                frame_index, reason,
            )
            return False
        if n_stereo >= self.cfg.min_init_points:
            log.warning(
                "frame %d: tracking lost (%s); pose from the constant-velocity prediction; "
                "re-initializing the map at that pose",
                frame_index, reason,
            )
            with tm.stage("local_mapping"):
                self._reset_map()
                self.selfcal.sync(f, offset_used)
                return self._initialize(f, first=False)
        log.warning(
            "frame %d: tracking lost (%s); pose from the constant-velocity prediction; "
            "%d stereo points are too few to re-initialize (< %d): the map is kept to "
            "relocalize the next frames in",
            frame_index, reason, n_stereo, self.cfg.min_init_points,
        )
        return False

    def _update_motion(self, T_cw: np.ndarray, status: TrackingState, method: TrackingMethod) -> None:
        """The velocity (the last frame's motion, in the camera frame), only between two
        frames tracked in a row.  A frame the motion model could not place (its pose from
        the reference keyframe or a relocalization) may follow a jump (a revisit): it keeps
        the old velocity, unless the frame before it was placed that way too."""
        continuous = self.last_ok and status == TrackingState.TRACKED and (
            method == TrackingMethod.MOTION or self.velocity is None
            or self.last_method in (TrackingMethod.REFERENCE, TrackingMethod.RELOC, TrackingMethod.INIT)
        )
        if self.last_T is not None and continuous:
            self.velocity = orthonormalize(T_cw @ inv_T(self.last_T))
        self.last_T = T_cw
        self.last_ok = status != TrackingState.LOST
        self.last_method = method

    def _record(self, T_cw: np.ndarray, status: TrackingState, is_kf: bool, n: int) -> None:
        """The frame's trajectory row, relative to its reference keyframe when it has one."""
        ref = self.ref_kf
        if status != TrackingState.LOST and ref is not None and ref.id in self.active.map.keyframes:
            # a keyframe's own frame follows the keyframe exactly (its local BA or a loop
            # may move it)
            T_rel = np.eye(4) if is_kf else T_cw @ inv_T(ref.T_cw)
            self.trajectory.add(T_rel, ref.id)
        else:
            self.trajectory.add(T_cw.copy())

    def _follow_reference(self, f: Frame, ref: KeyFrame, T_ref: np.ndarray) -> None:
        """After a local BA applied between this frame's tracking and its record: the frame
        was tracked against the map before the BA, so it keeps its pose relative to its
        reference keyframe (``T_ref``: that keyframe's pose it was tracked against) and
        moves with it, as if the BA had been applied first; the last frame follows its own
        reference keyframe too (the velocity compares the two).  Without this the frame's
        row (relative to the moved keyframe) and the keyframe it may become took the BA's
        correction as an error: KITTI 06, ``--masker none``, twelve ``slam.n_features``
        variants, ATE median 0.052 m with the BA on its thread against 0.042 inline; 0.032
        with this and :meth:`LocalMapper._carry_newer` (``benchmarks/bench_then_now.py``)."""
        if ref.id not in self.active.map.keyframes or np.array_equal(ref.T_cw, T_ref):
            return
        f.T_cw = orthonormalize(f.T_cw @ inv_T(T_ref) @ ref.T_cw)
        self._refresh_last_pose()

    def _refresh_last_pose(self) -> None:
        """The last frame's pose from its reference keyframe, which local BA may have
        moved since (ORB-SLAM2's ``UpdateLastFrame``): prediction and velocity use it."""
        if self.last is None:
            return
        T = self.trajectory.last_pose(self.active.map)
        if T is None:
            return
        self.last_T = T
        self.last.T_cw = T

    def _predict(self) -> np.ndarray:
        if self.last_T is None:
            return self.anchor.copy()
        if self.velocity is None:
            return self.last_T.copy()
        return self.velocity @ self.last_T

    def _support_reference(self) -> float | None:
        """Median inliers of the last tracked frames of this map (None: too few yet)."""
        r = self.recent_inliers
        return float(np.median(r)) if len(r) >= 3 else None

    def _track_frame(self, f: Frame, frame_index: int) -> tuple[bool, TrackingMethod, str]:
        """Motion model, else reference keyframe; then the local map; a supported pose,
        else relocalization (module doc).  Returns ``(ok, method, reason for a failure)``."""
        mp, cfg = self.active.map, self.cfg
        self.n_inliers = 0
        f.T_cw = self._predict()
        if self.ref_kf is not None and self.ref_kf.id not in mp.keyframes:
            self.ref_kf = mp.keyframes[max(mp.keyframes)] if mp.keyframes else None
        if len(f) < 10:
            return False, TrackingMethod.NONE, f"{len(f)} features"
        ok, method = False, TrackingMethod.NONE
        if self.velocity is not None and self.last is not None and self.last_ok:
            ok = self.track_motion_model(mp, f)
            method = TrackingMethod.MOTION
        if not ok:
            ok = self.track_reference_keyframe(mp, f, self._predict())
            method = TrackingMethod.REFERENCE
        if ok:
            self.track_local_map(mp, f)
        n = self.n_inliers if ok else 0
        ref = self._support_reference()
        if ok and n >= cfg.min_inliers and (ref is None or n >= cfg.min_inlier_fraction * ref):
            return True, method, ""
        if not ok:
            why = "no pose from the motion model nor from the reference keyframe"
        elif n < cfg.min_inliers:
            why = f"{n} inliers after local-map tracking < {cfg.min_inliers}"
        else:
            why = (
                f"{n} inliers after local-map tracking, {100.0 * n / ref:.0f}% of the recent median "
                f"{ref:.0f} (< {100.0 * cfg.min_inlier_fraction:.0f}%)"
            )
        if cfg.reloc_candidates > 0:
            found, kid = self.relocalize(f)
            if found and self.n_inliers >= max(cfg.reloc_min_inliers, cfg.min_inliers):
                log.info(
                    "frame %d: %s; relocalized against keyframe %d (%d inliers)", frame_index, why, kid, self.n_inliers
                )
                return True, TrackingMethod.RELOC, ""
            why += (
                f"; relocalization found {self.n_inliers} inliers < {cfg.reloc_min_inliers}"
                if found
                else "; relocalization found no keyframe"
            )
        return False, method, why

    # ------------------------------------------------------------ relocalization
    def relocalize(self, f: Frame) -> tuple[bool, int]:
        """ORB-SLAM2's ``Tracking::Relocalization``: :meth:`relocalize_against` the best
        ``slam.reloc_candidates`` keyframes of the bag-of-words database
        (:func:`.relocalization.database_candidates`)."""
        t0 = time.perf_counter()
        mp = self.active.map
        candidates = database_candidates(self.vocab, self.active.kfdb, mp, f, self.cfg.reloc_candidates)
        found, kid = self.relocalize_against(mp, f, candidates)
        self.reloc_ms.append((time.perf_counter() - t0) * 1e3)
        return found, kid

    def relocalize_against(self, mp: Map, frame: Frame, candidates: list[int]) -> tuple[bool, int]:
        """Prior-free pose of the frame in the map: for each candidate keyframe,
        descriptor matches + PnP-RANSAC + motion-only BA + local-map tracking; the
        hypothesis with most inliers wins.  Returns ``(found, keyframe id)``; the frame and
        the tracking state hold the best hypothesis (or are left as they were when none is
        found)."""
        saved = (
            frame.T_cw.copy() if frame.T_cw is not None else None,
            frame.point_ids.copy(),
            frame.match_xyz.copy(),
            frame.outlier.copy(),
            self.ref_kf,
            list(self.local_kfs),
            self.n_inliers,
        )
        best: tuple | None = None
        for kid in candidates:
            kf = mp.keyframes.get(kid)
            if kf is None:
                continue
            ki, pts = keyframe_point_matches(mp, kf, frame)
            if len(ki) < 15:
                continue
            X = mp.points.pos[pts]
            T, _ = pnp_ransac(X, frame.uv[ki], frame.calib.K, self.seed)
            if T is None:
                continue
            frame.T_cw = T
            frame.clear_matches(np.arange(len(frame)))
            self.assign_matches(frame, ki, pts, X)
            if self.optimize_frame(mp, frame) < 10:
                continue
            self.ref_kf = kf
            self.track_local_map(mp, frame, count=False)
            if best is None or self.n_inliers > best[0]:
                best = (
                    self.n_inliers,
                    kid,
                    frame.T_cw.copy(),
                    frame.point_ids.copy(),
                    frame.match_xyz.copy(),
                    frame.outlier.copy(),
                    self.ref_kf,
                    list(self.local_kfs),
                )
        if best is None:
            (frame.T_cw, frame.point_ids, frame.match_xyz, frame.outlier, self.ref_kf, self.local_kfs,
             self.n_inliers) = saved
            return False, -1
        n, kid, frame.T_cw, frame.point_ids, frame.match_xyz, frame.outlier, self.ref_kf, self.local_kfs = best
        self.n_inliers = n
        inl = frame.point_ids[frame.point_ids >= 0]
        mp.points.mark_found(inl)
        mp.points.mark_visible(inl)
        return True, kid

    # ------------------------------------------------------------ keyframes
    def _initialize(self, f: Frame, first: bool) -> bool:
        """A map from the frame's stereo points (at least ``min_init_points``)."""
        idx = np.flatnonzero(f.depth > 0)
        if len(idx) < self.cfg.min_init_points:
            return False
        if first:
            f.T_cw = self.anchor.copy()
        mp = self.active.map
        kf = self._make_keyframe(f)
        ids = mp.new_points(kf.unproject(idx), kf.desc[idx], kf.id)
        mp.add_observations(kf, idx, ids)
        f.point_ids[idx] = ids
        f.match_xyz[idx] = mp.points.pos[ids]
        mp.update_points(ids)
        self.ref_kf = kf
        self.last_kf_frame = f.index
        self.n_inliers = len(idx)
        self.active.mapper.process(kf, np.zeros(0, np.int64), f.index)
        self.active.place_keyframe(kf, f.index, self.vocab)
        self.initialized = True
        return True

    def _make_keyframe(self, f: Frame) -> KeyFrame:
        mp = self.active.map
        kf = KeyFrame(
            id=mp.new_kf_id(),
            frame_index=f.index,
            uv=f.uv,
            octave=f.octave,
            angle=f.angle,
            desc=f.desc,
            u_right=f.u_right,
            depth=f.depth,
            calib=f.calib,
            T_cw=f.T_cw.copy(),
        )
        mp.add_keyframe(kf)
        self.keyframes_created += 1
        return kf

    def _create_keyframe(self, f: Frame) -> None:
        """``Tracking::CreateNewKeyFrame`` + local mapping of the new keyframe."""
        mp = self.active.map
        kf = self._make_keyframe(f)
        has = np.flatnonzero(f.point_ids >= 0)
        mp.add_observations(kf, has, f.point_ids[has])
        # new points from close stereo keypoints (all closer than th_depth, at least 100)
        cand = np.flatnonzero((f.depth > 0) & (kf.point_ids < 0))
        cand = cand[np.argsort(f.depth[cand], kind="stable")]
        n_close = int(np.count_nonzero(f.depth[cand] < self.th_depth_m))
        cand = cand[: max(n_close, min(100, len(cand)))]
        ids = np.zeros(0, np.int64)
        if len(cand):
            ids = mp.new_points(kf.unproject(cand), kf.desc[cand], kf.id)
            keep = mp.add_observations(kf, cand, ids)
            f.point_ids[cand[keep]] = ids[keep]
            f.match_xyz[cand[keep]] = mp.points.pos[ids[keep]]
            ids = ids[keep]
        self.ref_kf = kf
        self.last_kf_frame = f.index
        self._mapping_due = (self.active, kf, ids, f.index)
        if self._mapping is None:
            self._start_mapping()

    # ----------------------------------------------------------- local mapping
    def _map_keyframe(self, active: ActiveMap, kf: KeyFrame, ids: np.ndarray, frame_index: int) -> None:
        """Local mapping of a new keyframe, then loop closing (or the keyframe database)."""
        t0 = time.perf_counter()
        active.mapper.process(kf, ids, frame_index)
        active.place_keyframe(kf, frame_index, self.vocab)
        self.mapping_ms.append((time.perf_counter() - t0) * 1e3)

    def _start_mapping(self) -> None:
        """Map the keyframe this frame made: inline, or on the mapping thread once the frame
        is done (the frame's own bookkeeping reads nothing local mapping writes)."""
        due, self._mapping_due = self._mapping_due, None
        if due is None:
            return
        if self._mapping is None:
            self._map_keyframe(*due)
        else:
            self._mapping_job = self._mapping.submit(self._map_keyframe, *due)

    def join_mapping(self) -> None:
        """Wait for the keyframe being mapped (its error, if any, is raised here).  Every
        reader of the map calls it first, so a run is the same as with inline mapping."""
        with self._mapping_lock:  # a second reader (another thread) waits here until it is done
            job = self._mapping_job
            if job is None:
                return
            t0 = time.perf_counter()
            try:
                job.result()
            except BaseException:
                if job.done():  # the mapping's own error: raised once
                    self._mapping_job = None
                raise  # else the wait was interrupted (a signal): the next reader waits again
            finally:
                self.mapping_wait_ms.append((time.perf_counter() - t0) * 1e3)
            self._mapping_job = None

    # ----------------------------------------------------------------- helpers
    def optimize_frame(self, mp: Map, frame: Frame) -> int:
        """Motion-only BA on the frame's matches; outliers are unmatched.  Returns the
        number of inlier matches to real map points."""
        idx = np.flatnonzero(frame.matched)
        if len(idx) < 3:
            return 0
        calib = frame.calib
        T, inl = optimize_pose(
            frame.T_cw,
            frame.match_xyz[idx],
            frame.uv[idx],
            frame.u_right[idx],
            self.orb.inv_sigma2[frame.octave[idx]],
            calib.K,
            calib.bf,
        )
        frame.T_cw = T
        frame.rejected = idx[~inl]
        frame.clear_matches(frame.rejected)
        return int(np.count_nonzero(frame.point_ids[idx[inl]] >= 0))

    def _last_frame_points(self, mp: Map, last: Frame):
        """Points to project from the last frame: its map points (current positions)
        plus temporary points from its close stereo keypoints (``UpdateLastFrame``)."""
        pid = mp.points.resolve(last.point_ids)
        has_mp = pid >= 0
        # temporary stereo points: closest first, all closer than th_depth, at least 100
        cand = np.flatnonzero((last.depth > 0) & ~has_mp)
        cand = cand[np.argsort(last.depth[cand], kind="stable")]
        close = last.depth[cand] < self.th_depth_m
        n_take = max(int(close.sum()), min(100, len(cand)))
        tmp = cand[:n_take]
        idx_mp = np.flatnonzero(has_mp)
        kp_idx = np.concatenate([idx_mp, tmp])
        X = np.concatenate([mp.points.pos[pid[idx_mp]], last.unproject(tmp)])
        d64 = np.concatenate([desc_u64(mp.points.desc[pid[idx_mp]]), last.desc64[tmp]])
        pts = np.concatenate([pid[idx_mp], np.full(len(tmp), -1, np.int64)])
        return kp_idx, X, d64, pts

    def assign_matches(self, frame: Frame, kp: np.ndarray, pts: np.ndarray, X: np.ndarray) -> None:
        frame.point_ids[kp] = pts
        frame.match_xyz[kp] = X
        frame.outlier[kp] = False

    # ------------------------------------------------------- tracking methods
    def track_motion_model(self, mp: Map, frame: Frame) -> bool:
        last = self.last
        if last is None or self.velocity is None:
            return False
        frame.T_cw = self.velocity @ last.T_cw
        kp_last, X, d64, pts = self._last_frame_points(mp, last)
        if len(X) == 0:
            return False
        c = frame.calib
        K = c.K
        Xc, u, v, ur = project(frame.T_cw, X, K[0, 0], K[1, 1], K[0, 2], K[1, 2], c.bf)
        inside = (Xc[:, 2] > 0) & (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
        # forward / backward motion restricts the search levels
        T_lc = last.T_cw @ inv_T(frame.T_cw)
        tz = T_lc[2, 3]
        oct_last = last.octave[kp_last].astype(np.int64)
        if tz > c.baseline:
            lo, hi = oct_last, np.full(len(oct_last), 99)
        elif -tz > c.baseline:
            lo, hi = np.zeros(len(oct_last), np.int64), oct_last
        else:
            lo, hi = oct_last - 1, oct_last + 1
        sel = np.flatnonzero(inside)
        matches = None
        for th in (7.0, 14.0):
            radius = th * self.orb.scales[oct_last[sel]]
            m = search_by_projection(
                frame.grid,
                frame.octave,
                frame.desc64,
                frame.u_right,
                None,
                u[sel],
                v[sel],
                radius,
                d64[sel],
                min_level=lo[sel],
                max_level=hi[sel],
                u_right=ur[sel],
                th_dist=TH_HIGH,
                angle_check=(last.angle[kp_last[sel]], frame.angle),
            )
            matches = m
            if len(m.query) >= 20:
                break
        if matches is None or len(matches.query) < 20:
            return False
        q = sel[matches.query]
        frame.clear_matches(np.arange(len(frame)))
        self.assign_matches(frame, matches.kp, pts[q], X[q])
        n = self.optimize_frame(mp, frame)
        n_all = int(frame.matched.sum())
        return n_all >= 10 if n < 10 else True

    def track_reference_keyframe(self, mp: Map, frame: Frame, T_guess: np.ndarray | None) -> bool:
        """Descriptor matching against the reference keyframe's map points, pose from
        PnP-RANSAC (else ``T_guess``), then motion-only BA."""
        kf = self.ref_kf
        if kf is None:
            return False
        ki, pts = keyframe_point_matches(mp, kf, frame)
        if len(ki) < 15:
            return False
        X = mp.points.pos[pts]
        T, _ = pnp_ransac(X, frame.uv[ki], frame.calib.K, self.seed)
        if T is None:
            if T_guess is None:
                return False
            T = T_guess.copy()
        frame.T_cw = T
        frame.clear_matches(np.arange(len(frame)))
        self.assign_matches(frame, ki, pts, X)
        n = self.optimize_frame(mp, frame)
        return n >= 10

    def update_local_keyframes(self, mp: Map, frame: Frame) -> list[int]:
        pid = frame.point_ids
        pts = mp.points.resolve(pid[pid >= 0])
        counts = mp.covisible_counts(pts[pts >= 0])
        counts = {k: c for k, c in counts.items() if k in mp.keyframes}
        if not counts:
            if self.ref_kf is not None and self.ref_kf.id in mp.keyframes:
                counts = {self.ref_kf.id: 1}
            else:
                return []
        best = max(counts.items(), key=lambda t: (t[1], t[0]))[0]
        self.ref_kf = mp.keyframes[best]
        local = sorted(counts, key=lambda k: (-counts[k], k))[:80]
        seen = set(local)
        for k in list(local):
            if len(local) >= 80:
                break
            for n in mp.keyframes[k].best_covisibles(10):
                if n not in seen and n in mp.keyframes:
                    seen.add(n)
                    local.append(n)
                    break
        self.local_kfs = local
        return local

    def track_local_map(self, mp: Map, frame: Frame, count: bool = True) -> bool:
        """Project the local map's points, match, motion-only BA.  ``count``: update the
        points' visible / found counters (off for relocalization hypotheses)."""
        local = self.update_local_keyframes(mp, frame)
        if not local:
            return False
        ids = mp.points_of(local)
        # points already matched in this frame: counted visible, not searched again
        has = np.flatnonzero(frame.point_ids >= 0)
        res = mp.points.resolve(frame.point_ids[has])
        frame.clear_matches(has[res < 0])
        frame.point_ids[has[res >= 0]] = res[res >= 0]
        already = frame.point_ids[frame.point_ids >= 0]
        if count:
            mp.points.mark_visible(already)
        ids = ids[~np.isin(ids, already)]
        if len(ids):
            f = mp.in_frustum(ids, frame.T_cw, frame.T_wc[:3, 3], frame.calib)
            sel, u, v, ur, dist, cosv, Xw = f.sel, f.u, f.v, f.ur, f.dist, f.cosv, f.Xw
            if count:
                mp.points.mark_visible(ids[sel])
            if len(sel):
                lev = mp.predict_level(ids[sel], dist[sel])
                r = np.where(cosv[sel] > 0.998, 2.5, 4.0) * self.orb.scales[lev]
                m = search_by_projection(
                    frame.grid,
                    frame.octave,
                    frame.desc64,
                    frame.u_right,
                    frame.point_ids < 0,
                    u[sel],
                    v[sel],
                    r,
                    desc_u64(mp.points.desc[ids[sel]]),
                    min_level=lev - 1,
                    max_level=lev,
                    u_right=ur[sel],
                    th_dist=TH_HIGH,
                    ratio=0.8,
                )
                q = sel[m.query]
                self.assign_matches(frame, m.kp, ids[q], Xw[q])
        # refresh the positions of all map-point matches (the map may have moved)
        has = frame.point_ids >= 0
        frame.match_xyz[has] = mp.points.pos[frame.point_ids[has]]
        n = self.optimize_frame(mp, frame)
        if count:
            mp.points.mark_found(frame.point_ids[frame.point_ids >= 0])
        self.n_inliers = n
        return n >= self.cfg.min_inliers

    # ---------------------------------------------------------- keyframe policy
    def need_new_keyframe(self, mp: Map, frame: Frame) -> bool:
        if self.ref_kf is None:
            return True
        n_kfs = len(mp.keyframes)
        min_obs = 3 if n_kfs > 2 else 2
        ref_pts = self.ref_kf.point_ids[self.ref_kf.point_ids >= 0]
        n_ref = int(np.count_nonzero(mp.points.nobs[ref_pts] >= min_obs))
        close = (frame.depth > 0) & (frame.depth < self.th_depth_m)
        tracked = frame.point_ids >= 0
        n_tracked_close = int(np.count_nonzero(close & tracked))
        n_non_tracked_close = int(np.count_nonzero(close & ~tracked))
        need_close = n_tracked_close < 100 and n_non_tracked_close > 70
        th_ref = 0.4 if n_kfs < 2 else 0.75
        since = frame.index - self.last_kf_frame
        c1a = since >= self.cfg.max_frames
        c1b = since >= self.cfg.min_frames  # local mapping is never busy from tracking's view
        c1c = self.n_inliers < n_ref * 0.25 or need_close
        c2 = (self.n_inliers < n_ref * th_ref or need_close) and self.n_inliers > 15
        return bool((c1a or c1b or c1c) and c2)
