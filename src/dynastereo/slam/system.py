"""System: the SLAM back-end's public API.

    system = System(config, calibration)
    for frame, masks in ...:
        T_wc = system.track(frame, masks)      # 3x4 camera-to-world of the left camera
    poses = system.trajectory()                # (N, 3, 4), one per frame fed, in order
    system.shutdown()

World = the first frame's left camera (KITTI ground-truth convention).  Every frame fed
gets exactly one trajectory row.  Poses of tracked frames are kept relative to their
reference keyframe (as ORB-SLAM2 does), so later local BA refines them too.

A pose is accepted only with enough support: after local-map tracking at least
``min_inliers`` inliers and at least ``min_inlier_fraction`` (25 %) of the median of the
last tracked frames.  A jump the motion model cannot follow (a revisit fed as
``--frames 0-98,40-60``, a gap) leaves a wrong prediction with a few chance inliers on far
points: such a pose is refused, and a prior-free search over the map's keyframes runs
instead (``Tracker.relocalise``: descriptor votes pick candidate keyframes, PnP-RANSAC,
motion-only BA, local map; ``reloc_min_inliers`` needed).  A frame placed that way is
``tracked`` with method ``reloc`` (or ``reference`` when the reference keyframe's
descriptors already placed it); the velocity is not taken across such a jump.

When no pose is supported the frame is *lost*: a WARNING log line names the frame and
the reason, ``frame_states()`` flags it ``lost``, and its trajectory row is the
*constant-velocity prediction* (last pose times last velocity; the last pose if no
velocity yet) -- over a run of lost frames the prediction continues at that velocity.
Then:

* the frame has at least ``min_init_points`` stereo points (a new place): a new map is
  initialised from them, anchored to that predicted pose, and tracking continues on it
  (``map_id`` increments; the frame is the new map's first keyframe);
* it has fewer (a black or blank frame, a lens cover): the map is kept, and the next
  frames are tracked / relocalised in it again -- after ten black frames KITTI 06 is
  found again at its true place, no new map needed.

Nothing raises on bad frames.

Stereo self-calibration (``slam.self_calibrate``, on by default): rectified pairs often
carry a small constant disparity offset (a right principal-point error; KITTI's is about
0.15-0.25 px), which biases every depth by ``delta / bf`` in inverse depth -- on KITTI a
0.7 % too long path.  When the map has ``selfcal_keyframes`` keyframes, a BA over the
whole map is solved at three offsets in the local-BA worker; the parabola of its cost
gives the offset (``optimizer.self_calibrating_ba``), which is then applied to every
keyframe's and every later frame's stereo observations (``stats()["disparity_offset"]``).
It is refined the same way at 1.5x, 2.25x... that many keyframes (``selfcal_rounds``
estimates in all): on KITTI 03 the first estimate is +0.13 +- 0.05 px, one over the 34
keyframes of the clip +0.21 +- 0.03 px.  No offset is applied until an estimate is
``selfcal_min_sigmas`` from 0; the later rounds then refine it.

Loop closing (``loop_closing.LoopCloser``, after each new keyframe), relocalisation with
the bag-of-words keyframe database and map files (``save_map`` / ``load_map``, with
``localize_only``) are described in the README and in those modules.
"""

from __future__ import annotations

import logging
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config import Config, SlamConfig
from ..errors import ConfigError
from ..timing import StageTimer
from ..types import StereoCalibration, StereoFrame, StereoMasks
from .frame import Frame
from .geometry import inv_T, orthonormalize
from .keyframe import KeyFrame
from .local_mapping import BARunner, LocalMapper, MappingParams
from .keyframe_database import KeyFrameDatabase
from .loop_closing import LoopCloser, LoopEvent, LoopParams, LoopStats
from .map import Map
from .matcher import stereo_match
from .orb import ORBExtractor
from .tracking import TrackParams, Tracker
from .vocabulary import BowVector, Vocabulary

log = logging.getLogger("dynastereo.slam")


def _shift_stereo(uv: np.ndarray, u_right: np.ndarray, depth: np.ndarray, delta: float, bf: float) -> None:
    """Add ``delta`` px to the disparity of the stereo keypoints (in place; >= 0.01 px)."""
    st = u_right >= 0
    if not st.any():
        return
    disp = np.maximum(uv[st, 0] - u_right[st] + delta, 0.01)
    u_right[st] = uv[st, 0] - disp
    depth[st] = bf / disp


@dataclass
class FrameState:
    """What happened to one frame (``System.frame_states()``)."""

    index: int  # position in the order fed
    frame_index: int  # StereoFrame.index
    status: str  # "init", "tracked", "lost"
    method: str  # "init", "motion", "reference", "reloc", "" (lost)
    keyframe: bool  # a lost frame that starts a new map is its first keyframe
    inliers: int  # after local-map tracking (lost: of the best refused pose, 0 if none)
    n_features: int
    n_stereo: int
    map_id: int  # increments at each re-initialisation


@dataclass
class FrameView:
    """What the last tracked frame looks like to a viewer (``System.frame_view()``)."""

    uv: np.ndarray  # (N, 2) left keypoints, pixels
    inlier: np.ndarray  # (N,) bool: matched to a map point and kept by the pose optimisation
    outlier: np.ndarray  # (N,) bool: matched, rejected as an outlier
    local_points: np.ndarray  # (M, 3) world positions of the local map's points


@dataclass
class Recovery:
    """A frame tracked again after lost frames (``System.recoveries()``)."""

    frame: int  # position in the order fed
    frame_index: int
    lost_frames: int  # lost frames just before it
    method: str  # "reloc" / "reference" / "motion" (found in the same map) or "init" (a new map)
    map_id: int


@dataclass
class _Record:
    ref_kf: int | None
    T: np.ndarray  # T_c_ref if ref_kf is not None, else absolute T_cw


def _validate(cfg: SlamConfig) -> None:
    if cfg.n_features < 50:
        raise ConfigError(f"slam.n_features must be >= 50, got {cfg.n_features}")
    if not cfg.scale_factor > 1.0:
        raise ConfigError(f"slam.scale_factor must be > 1, got {cfg.scale_factor}")
    if not 1 <= cfg.n_levels <= 32:
        raise ConfigError(f"slam.n_levels must be in 1..32, got {cfg.n_levels}")
    if cfg.local_ba not in ("process", "inline", "off"):
        raise ConfigError(f"slam.local_ba must be process, inline or off, got {cfg.local_ba!r}")
    if cfg.th_depth <= 0:
        raise ConfigError(f"slam.th_depth must be positive, got {cfg.th_depth}")
    if not 0.0 <= cfg.min_inlier_fraction < 1.0:
        raise ConfigError(f"slam.min_inlier_fraction must be in [0, 1), got {cfg.min_inlier_fraction}")
    if cfg.reloc_candidates < 0 or cfg.reloc_min_inliers < 0:
        raise ConfigError("slam.reloc_candidates and slam.reloc_min_inliers must be >= 0")
    if cfg.loop_consistency < 0 or cfg.loop_min_inliers < 10 or cfg.loop_ba_lag_frames < 0:
        raise ConfigError(
            "slam.loop_consistency must be >= 0, slam.loop_min_inliers >= 10 and slam.loop_ba_lag_frames >= 0"
        )
    if cfg.selfcal_rounds < 1:
        raise ConfigError(f"slam.selfcal_rounds must be >= 1, got {cfg.selfcal_rounds}")
    if cfg.selfcal_keyframes < 3:
        raise ConfigError(f"slam.selfcal_keyframes must be >= 3, got {cfg.selfcal_keyframes}")
    if not np.isfinite(cfg.disparity_offset) or abs(cfg.disparity_offset) > 5.0:
        raise ConfigError(f"slam.disparity_offset must be a few pixels at most, got {cfg.disparity_offset}")


class System:
    def __init__(
        self,
        config: Config | SlamConfig | None = None,
        calibration: StereoCalibration | None = None,
        *,
        seed: int | None = None,
    ) -> None:
        if isinstance(config, Config):
            cfg = config.slam
            seed = config.seed if seed is None else seed
        else:
            cfg = config or SlamConfig()
        if calibration is None:
            raise ConfigError("System needs the rectified StereoCalibration of the sequence")
        _validate(cfg)
        self.cfg = cfg
        self.seed = int(seed or 0)
        self.calib = calibration
        self.extractor = ORBExtractor(
            cfg.n_features, cfg.scale_factor, cfg.n_levels, cfg.ini_th_fast, cfg.min_th_fast, cfg.oversample, cfg.mask_margin
        )
        ex = self.extractor
        self.th_depth_m = cfg.th_depth * calibration.baseline
        self._track_params = TrackParams(
            scales=ex.scales,
            inv_sigma2=ex.inv_sigma2,
            th_depth_m=self.th_depth_m,
            min_inliers=cfg.min_inliers,
            max_frames=cfg.max_frames,
            min_frames=cfg.min_frames,
            seed=self.seed,
        )
        self._map_params = MappingParams(
            scales=ex.scales,
            sigma2=ex.sigma2,
            inv_sigma2=ex.inv_sigma2,
            th_depth_m=self.th_depth_m,
            local_ba=cfg.local_ba,
            ba_iterations=cfg.ba_iterations,
            ba_max_keyframes=cfg.ba_max_keyframes,
            ba_max_fixed=cfg.ba_max_fixed,
            ba_lag_frames=cfg.ba_lag_frames,
            triangulation_neighbours=cfg.triangulation_neighbours,
            fuse_neighbours=cfg.fuse_neighbours,
            keyframe_culling=cfg.keyframe_culling,
            self_calibrate=cfg.self_calibrate and cfg.local_ba != "off",
            selfcal_keyframes=cfg.selfcal_keyframes,
            selfcal_rounds=cfg.selfcal_rounds,
            selfcal_min_sigmas=cfg.selfcal_min_sigmas,
        )
        # disparity offset (px) added to every measured disparity; self-calibrated once
        # when slam.self_calibrate (see optimizer.self_calibrating_ba)
        self.disparity_offset = float(cfg.disparity_offset)
        self.disparity_offset_sigma: float | None = None
        self._selfcal_due = self._map_params.self_calibrate
        self._threads = ThreadPoolExecutor(max_workers=2) if cfg.threads > 1 else None
        self.runner = BARunner(cfg.local_ba)
        self.timer = StageTimer()
        self._records: list[_Record] = []
        self._states: list[FrameState] = []
        self._n = 0
        self._map_id = -1
        self._anchor = np.eye(4)
        self._velocity: np.ndarray | None = None
        self._last_T: np.ndarray | None = None
        self._last_ok = False  # the last frame was tracked (not lost)
        self._last_method = ""
        self._recent_inliers: deque[int] = deque(maxlen=5)
        self._kf_total = 0
        self._kf_loaded = 0
        self._closed = False
        # place recognition and loop closing
        self.vocab = Vocabulary.load(cfg.vocabulary) if cfg.vocabulary else Vocabulary.default()
        self._loop_params = LoopParams(
            consistency=cfg.loop_consistency,
            min_inliers=cfg.loop_min_inliers,
            full_ba=cfg.loop_full_ba and cfg.local_ba != "off",
            full_ba_lag_frames=cfg.loop_ba_lag_frames,
            close_depth_m=self.th_depth_m,
            seed=self.seed,
        )
        self._loop_events: list[LoopEvent] = []
        self._loop_stats = LoopStats()
        self._reloc_ms: list[float] = []
        self.closer: LoopCloser | None = None
        self.localize_only = False
        self._recoveries: list[Recovery] = []
        self._lost_run = 0
        self._new_map()

    @classmethod
    def from_orbslam_settings(cls, path: str, base: Config | None = None) -> "System":
        """A System configured from an ORB-SLAM2 stereo settings file (camera included)."""
        from .settings import load_orbslam_settings

        base_cfg = base or Config()
        slam, calib = load_orbslam_settings(path, base_cfg.slam)
        return cls(slam, calib, seed=base_cfg.seed)

    # ------------------------------------------------------------------ state
    def _new_map(self, mp: Map | None = None) -> None:
        """Start a new map (empty, or ``mp``: a loaded one); the old one's frame poses are
        made absolute first."""
        if self.closer is not None:
            self.closer.shutdown()
        if getattr(self, "mapper", None) is not None:
            self.mapper.shutdown()
            self._bake_records()
        self._map_id += 1
        self.map = mp if mp is not None else Map(self.extractor.scales)
        self.tracker = Tracker(self._track_params)
        self.tracker.velocity = self._velocity
        self.mapper = LocalMapper(self.map, self._map_params, self.runner)
        self.mapper.selfcal_due = self._selfcal_due
        self.mapper.offset_now = self.disparity_offset
        self.mapper.on_offset = self._set_disparity_offset
        self.kfdb = KeyFrameDatabase(self.vocab)
        self.closer = None
        if self.cfg.loop_closing and not self.localize_only:
            ex = self.extractor
            self.closer = LoopCloser(
                self.map, self.kfdb, self.vocab, self.mapper, self._loop_params, ex.inv_sigma2, ex.scales,
                events=self._loop_events, stats=self._loop_stats,
            )
        self._initialised = False
        self._recent_inliers = deque(maxlen=5)

    def _set_disparity_offset(self, offset: float, sigma: float | None = None) -> None:
        """Move every keyframe's and the last frame's stereo observations to ``offset``
        (called by local mapping with the self-calibrated value, before it applies the
        BA that was solved with it); later frames are matched with it."""
        delta = float(offset) - self.disparity_offset
        self._selfcal_due = False  # a new map (re-initialisation) does not start over
        self.disparity_offset_sigma = sigma
        self.mapper.offset_now = float(offset)
        if delta == 0.0:
            return
        self.disparity_offset = float(offset)
        done: set[int] = set()
        holders = list(self.map.keyframes.values())
        if self.tracker.last is not None:
            holders.append(self.tracker.last)
        for h in holders:  # a keyframe shares its arrays with its frame: shift once
            if id(h.u_right) in done:
                continue
            done.add(id(h.u_right))
            _shift_stereo(h.uv, h.u_right, h.depth, delta, self.calib.bf)
        # points seen by a single keyframe (not in the BA): from that keyframe's new depth
        mp = self.map
        for kf in self.map.keyframes.values():
            kp = np.flatnonzero((kf.point_ids >= 0) & (kf.u_right >= 0))
            pts = kf.point_ids[kp]
            one = (mp.ref_kf[pts] == kf.id) & (mp.nobs[pts] <= 2) & ~mp.bad[pts]
            if one.any():
                mp.pos[pts[one]] = kf.unproject(kp[one])

    def _sync_offset(self, f: Frame, offset_used: float) -> float:
        """Move ``f``'s stereo observations to the disparity offset if a self-calibration
        result was applied since ``f`` was matched with ``offset_used``."""
        if self.disparity_offset != offset_used:
            _shift_stereo(f.uv, f.u_right, f.depth, self.disparity_offset - offset_used, self.calib.bf)
        return self.disparity_offset

    def _bake_records(self) -> None:
        """Make the poses of all frames so far absolute (before the map is dropped)."""
        for r in self._records:
            if r.ref_kf is not None:
                T_ref = self.map.keyframe_pose(r.ref_kf)
                r.T = r.T @ T_ref if T_ref is not None else r.T
                r.ref_kf = None

    # --------------------------------------------------------------- features
    def _features(self, frame: StereoFrame, masks: StereoMasks | None):
        left = frame.left_gray
        right = frame.right_gray
        ml = masks.left if masks is not None else None
        mr = masks.right if masks is not None else None
        ex = self.extractor
        if self._threads is not None:
            fr = self._threads.submit(ex.extract, right, mr)
            fl = ex.extract(left, ml)
            return fl, fr.result(), left, right
        return ex.extract(left, ml), ex.extract(right, mr), left, right

    # ------------------------------------------------------------------ track
    def track(
        self, frame: StereoFrame, masks: StereoMasks | None = None, timer: StageTimer | None = None
    ) -> np.ndarray:
        """Track one rectified stereo frame; returns its 3x4 camera-to-world pose.

        ``masks`` (255 = dynamic) keep the detector off dynamic objects in each image.
        Stage times go to ``timer`` (the caller's frame) or to ``self.timer``.
        """
        if self._closed:
            raise RuntimeError("System.track called after shutdown()")
        own = timer is None
        tm = self.timer if own else timer
        if own:
            tm.start_frame(frame.index)
        n = self._n
        c = self.calib
        if frame.left.shape[:2] != (c.height, c.width):
            raise ValueError(
                f"frame {frame.index}: image size {frame.left.shape[1]}x{frame.left.shape[0]} differs from the "
                f"calibration's {c.width}x{c.height}"
            )
        with tm.stage("features"):
            fl, fr, pl, pr = self._features(frame, masks)
        with tm.stage("stereo"):
            st = stereo_match(
                fl.uv, fl.octave, fl.desc, fr.uv, fr.octave, fr.desc, pl, pr, self.extractor.scales, c.fx, c.bf
            )
            if self.disparity_offset != 0.0:
                _shift_stereo(fl.uv, st.u_right, st.depth, self.disparity_offset, c.bf)
            f = Frame.from_features(n, fl, st.u_right, st.depth, c)
            offset_used = self.disparity_offset
        self._refresh_last_pose()
        n_stereo = int(np.count_nonzero(f.depth > 0))
        status, method, is_kf = "tracked", "", False
        reason = ""
        with tm.stage("track"):
            if not self._initialised:
                ok = False
            else:
                ok, method, reason = self._track_frame(f, frame.index)
                f.T_cw = orthonormalize(f.T_cw)
        track_inliers = int(self.tracker.n_inliers) if self._initialised else 0
        with tm.stage("local_mapping"):
            # the local BA submitted ba_lag_frames ago is applied now (waiting for it if
            # needed): it ran while this frame's features, stereo and tracking were computed
            self.mapper.collect(n)
            if self.closer is not None:
                self.closer.collect(n)
            offset_used = self._sync_offset(f, offset_used)
        if not self._initialised:
            T_pred = self._predict()
            f.T_cw = T_pred
            f.clear_matches(np.arange(len(f)))
            with tm.stage("local_mapping"):
                is_kf = self._initialise(f, first=(n == 0))
            status, method = ("init", "init") if is_kf else ("lost", "")
            if not is_kf:
                log.warning(
                    "frame %d: cannot initialise the map (%d stereo points < %d); "
                    "pose from the constant-velocity prediction",
                    frame.index,
                    n_stereo,
                    self.cfg.min_init_points,
                )
        elif ok:
            self._recent_inliers.append(int(self.tracker.n_inliers))
            if not self.localize_only:
                with tm.stage("local_mapping"):
                    if self.tracker.need_new_keyframe(self.map, f):
                        self._create_keyframe(f)
                        is_kf = True
        else:
            T_pred = self._predict()
            status, method = "lost", ""
            f.T_cw = T_pred
            f.clear_matches(np.arange(len(f)))
            if self.localize_only:
                log.warning(
                    "frame %d: tracking lost (%s); pose from the constant-velocity prediction; "
                    "localisation only: the map is kept",
                    frame.index,
                    reason,
                )
            elif n_stereo >= self.cfg.min_init_points:
                log.warning(
                    "frame %d: tracking lost (%s); pose from the constant-velocity prediction; "
                    "re-initialising the map at that pose",
                    frame.index,
                    reason,
                )
                with tm.stage("local_mapping"):
                    self._new_map()
                    offset_used = self._sync_offset(f, offset_used)
                    is_kf = self._initialise(f, first=False)
            else:
                log.warning(
                    "frame %d: tracking lost (%s); pose from the constant-velocity prediction; "
                    "%d stereo points are too few to re-initialise (< %d): the map is kept to "
                    "relocalise the next frames in",
                    frame.index,
                    reason,
                    n_stereo,
                    self.cfg.min_init_points,
                )
        T_cw = orthonormalize(f.T_cw)
        f.T_cw = T_cw
        # velocity (the last frame's motion, in the camera frame), only between two frames
        # tracked in a row.  A frame the motion model could not place (its pose from the
        # reference keyframe or a relocalisation) may follow a jump (a revisit): it keeps
        # the old velocity, unless the frame before it was placed that way too.
        continuous = self._last_ok and status == "tracked" and (
            method == "motion" or self._velocity is None or self._last_method in ("reference", "reloc", "init")
        )
        if self._last_T is not None and continuous:
            self._velocity = orthonormalize(T_cw @ inv_T(self._last_T))
            self.tracker.velocity = self._velocity
        self._last_T = T_cw
        self._last_ok = status != "lost"
        self._last_method = method
        # drop temporary VO matches; the frame becomes the tracker's last frame
        temp = f.matched & (f.point_ids < 0)
        f.clear_matches(np.flatnonzero(temp))
        self.tracker.last = f
        # trajectory record, relative to the reference keyframe when there is one
        ref = self.tracker.ref_kf
        if status != "lost" and ref is not None and ref.id in self.map.keyframes:
            # a keyframe's own frame follows the keyframe exactly (an inline local BA may
            # already have moved it)
            T_rel = np.eye(4) if (is_kf and ref.frame_index == n) else T_cw @ inv_T(ref.T_cw)
            self._records.append(_Record(ref.id, T_rel))
        else:
            self._records.append(_Record(None, T_cw.copy()))
        if status == "lost":
            self._lost_run += 1
        elif self._lost_run:
            self._recoveries.append(Recovery(n, frame.index, self._lost_run, method, self._map_id))
            log.info("frame %d: tracked again (%s) after %d lost frames", frame.index, method, self._lost_run)
            self._lost_run = 0
        inliers = track_inliers if status == "lost" else int(self.tracker.n_inliers)
        self._states.append(
            FrameState(n, frame.index, status, method, is_kf, inliers, len(f), n_stereo, self._map_id)
        )
        self._n += 1
        if own:
            tm.end_frame(status=status)
        return inv_T(T_cw)[:3].copy()

    def _refresh_last_pose(self) -> None:
        """The last frame's pose from its reference keyframe, which local BA may have
        moved since (ORB-SLAM2's ``UpdateLastFrame``): prediction and velocity use it."""
        if not self._records or self.tracker.last is None:
            return
        r = self._records[-1]
        if r.ref_kf is None:
            return
        T_ref = self.map.keyframe_pose(r.ref_kf)
        if T_ref is None:
            return
        T = orthonormalize(r.T @ T_ref)
        self._last_T = T
        self.tracker.last.T_cw = T

    def _predict(self) -> np.ndarray:
        if self._last_T is None:
            return self._anchor.copy()
        if self._velocity is None:
            return self._last_T.copy()
        return self._velocity @ self._last_T

    def _support_reference(self) -> float | None:
        """Median inliers of the last tracked frames of this map (None: too few yet)."""
        r = self._recent_inliers
        return float(np.median(r)) if len(r) >= 3 else None

    def _track_frame(self, f: Frame, frame_index: int) -> tuple[bool, str, str]:
        """Motion model, else reference keyframe; then the local map.  A pose is accepted
        only with enough support: at least ``min_inliers`` inliers after local-map
        tracking and at least ``min_inlier_fraction`` of the recent frames' median.
        Otherwise a prior-free search over the map's keyframes (relocalisation) is tried;
        its best hypothesis needs ``reloc_min_inliers``.  Returns ``(ok, method, reason
        for a failure)``."""
        tr, mp, cfg = self.tracker, self.map, self.cfg
        tr.n_inliers = 0
        f.T_cw = self._predict()
        if tr.ref_kf is not None and tr.ref_kf.id not in mp.keyframes:
            tr.ref_kf = mp.keyframes[max(mp.keyframes)] if mp.keyframes else None
        if len(f) < 10:
            return False, "", f"{len(f)} features"
        ok, method = False, ""
        if tr.velocity is not None and tr.last is not None and self._last_ok:
            ok = tr.track_motion_model(mp, f)
            method = "motion"
        if not ok:
            ok = tr.track_reference_keyframe(mp, f, self._predict())
            method = "reference"
        if ok:
            tr.track_local_map(mp, f)
        n = tr.n_inliers if ok else 0
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
            found, kid = self._relocalise(f)
            if found and tr.n_inliers >= max(cfg.reloc_min_inliers, cfg.min_inliers):
                log.info(
                    "frame %d: %s; relocalised against keyframe %d (%d inliers)", frame_index, why, kid, tr.n_inliers
                )
                return True, "reloc", ""
            why += (
                f"; relocalisation found {tr.n_inliers} inliers < {cfg.reloc_min_inliers}"
                if found
                else "; relocalisation found no keyframe"
            )
        return False, method, why

    def _relocalise(self, f: Frame) -> tuple[bool, int]:
        """``Tracker.relocalise`` on the bag-of-words candidates (ORB-SLAM2's
        ``DetectRelocalizationCandidates``); when none of them holds, on the keyframes
        that see most of a sample of the frame's descriptors (brute force)."""
        import time

        t0 = time.perf_counter()
        tr, mp, n = self.tracker, self.map, self.cfg.reloc_candidates
        bow, _ = self.vocab.transform(f.desc)
        cands = [k for k in self.kfdb.detect_relocalisation_candidates(bow, mp.best_covisibles) if k in mp.keyframes]
        found, kid = tr.relocalise(mp, f, cands[:n])
        if not found or tr.n_inliers < max(self.cfg.reloc_min_inliers, self.cfg.min_inliers):
            more = [k for k in tr.candidate_keyframes(mp, f, n) if k not in cands[:n]]
            if more:
                found, kid = tr.relocalise(mp, f, more)
        self._reloc_ms.append((time.perf_counter() - t0) * 1e3)
        return found, kid

    def _place_keyframe(self, kf: KeyFrame, frame_pos: int) -> None:
        """The new keyframe goes to loop closing (detection + correction) and to the
        keyframe database."""
        if self.closer is not None:
            self.closer.process(kf, frame_pos)
        else:
            self.kfdb.add(kf.id, self.vocab.transform(kf.desc)[0])

    # ------------------------------------------------------------ keyframes
    def _initialise(self, f: Frame, first: bool) -> bool:
        idx = np.flatnonzero(f.depth > 0)
        if len(idx) < self.cfg.min_init_points:
            return False
        if first:
            f.T_cw = self._anchor.copy()
        kf = self._make_keyframe(f)
        ids = self.map.new_points(kf.unproject(idx), kf.desc[idx], kf.id)
        self.map.add_observations(kf, idx, ids)
        f.point_ids[idx] = ids
        f.match_xyz[idx] = self.map.pos[ids]
        self.map.update_points(ids)
        self.tracker.ref_kf = kf
        self.tracker.last_kf_frame = f.index
        self.tracker.n_inliers = len(idx)
        self.mapper.process(kf, np.zeros(0, np.int64), f.index)
        self._place_keyframe(kf, f.index)
        self._initialised = True
        return True

    def _make_keyframe(self, f: Frame) -> KeyFrame:
        kf = KeyFrame(
            id=self.map.new_kf_id(),
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
        self.map.add_keyframe(kf)
        self._kf_total += 1
        return kf

    def _create_keyframe(self, f: Frame) -> None:
        """``Tracking::CreateNewKeyFrame`` + local mapping of the new keyframe."""
        mp = self.map
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
            f.match_xyz[cand[keep]] = mp.pos[ids[keep]]
            ids = ids[keep]
        self.tracker.ref_kf = kf
        self.tracker.last_kf_frame = f.index
        self.mapper.process(kf, ids, f.index)
        self._place_keyframe(kf, f.index)

    # ---------------------------------------------------------------- results
    def trajectory(self) -> np.ndarray:
        """(N, 3, 4) camera-to-world poses of the left camera, one per frame fed."""
        out = np.zeros((len(self._records), 3, 4))
        for i, r in enumerate(self._records):
            T_cw = r.T
            if r.ref_kf is not None:
                T_ref = self.map.keyframe_pose(r.ref_kf)
                if T_ref is not None:
                    T_cw = orthonormalize(r.T @ T_ref)
            out[i] = inv_T(T_cw)[:3]
        return out

    def frame_view(self) -> FrameView | None:
        """Keypoints (inliers / outliers) of the last frame tracked and the local map's
        points (copies; None before the first frame)."""
        f = self.tracker.last
        if f is None:
            return None
        matched = f.point_ids >= 0
        local = [k for k in self.tracker.local_kfs if k in self.map.keyframes]
        pts = self.map.points_of(local) if local else np.zeros(0, np.int64)
        return FrameView(f.uv.copy(), matched & ~f.outlier, matched & f.outlier, self.map.pos[pts].copy())

    def map_points(self) -> np.ndarray:
        """(M, 3) world positions of all good map points (a copy)."""
        n = self.map.n
        return self.map.pos[:n][~self.map.bad[:n]].copy()

    def frame_states(self) -> list[FrameState]:
        return list(self._states)

    def lost_frames(self) -> list[int]:
        """Positions (in the order fed) of the frames marked lost."""
        return [s.index for s in self._states if s.status == "lost"]

    def stats(self) -> dict[str, Any]:
        ms = self.mapper.stats
        st = self._states
        return {
            "frames": len(st),
            "tracked": sum(s.status in ("tracked", "init") for s in st),
            "lost": sum(s.status == "lost" for s in st),
            "reinitialisations": max(0, self._map_id),
            "keyframes": len(self.map.keyframes),
            "keyframes_created": self._kf_total,
            "keyframes_loaded": self._kf_loaded,
            "map_points": self.map.stats()["map_points"],
            "local_ba_runs": ms.ba_runs,
            "local_ba_ms_median": float(np.median(ms.ba_ms)) if ms.ba_ms else 0.0,
            "local_ba_wait_ms_median": float(np.median(ms.ba_wait_ms)) if ms.ba_wait_ms else 0.0,
            "points_triangulated": ms.points_triangulated,
            "points_fused": ms.points_fused,
            "points_culled": ms.points_culled,
            "keyframes_culled": ms.keyframes_culled,
            "disparity_offset": self.disparity_offset,
            "disparity_offset_sigma": self.disparity_offset_sigma,
            "relocalisations": sum(s.method == "reloc" for s in st),
            "relocalisation_ms_median": float(np.median(self._reloc_ms)) if self._reloc_ms else 0.0,
            "recoveries": len(self._recoveries),
            "loops": len(self._loop_events),
            "loop_candidates_rejected": self._loop_stats.rejected,
            "loop_query_ms_median": float(np.median(self._loop_stats.query_ms)) if self._loop_stats.query_ms else 0.0,
            "pose_graph_ms_median": (
                float(np.median([e.pose_graph_ms for e in self._loop_events])) if self._loop_events else 0.0
            ),
            "localize_only": self.localize_only,
        }

    # -------------------------------------------------------------- map files
    def _orb_settings(self) -> dict[str, Any]:
        c = self.cfg
        return {"n_features": c.n_features, "scale_factor": c.scale_factor, "n_levels": c.n_levels}

    def save_map(self, path, meta: dict[str, Any] | None = None, optimize: bool = True) -> None:
        """Write the current map (keyframes, map points, covisibility, bag of words, the
        vocabulary and the disparity offset) to ``path`` (``docs/map_format.md``).  The
        local and full BAs in flight are applied first; with ``optimize`` (and mapping on)
        a final bundle adjustment over the whole map -- self-calibrating, so the disparity
        offset is refined over all keyframes -- makes the map the best it can be for reuse
        (the frame poses, ``trajectory()``, follow it)."""
        from .map_io import MapFile, save_map

        if not self.localize_only:
            if self.closer is not None:
                self.closer.collect(self._n, force=True)
            self.mapper.collect(self._n, force=True)
            if optimize and self.cfg.local_ba != "off":
                self.mapper.optimize_whole_map()
        bows = {}
        for k in self.map.keyframes:
            if k in self.kfdb:
                b = self.kfdb.bow(k)
                bows[k] = (b.words, b.weights)
        info = {"frames": self._n, "map_id": self._map_id, "loops": len(self._loop_events)}
        info.update(meta or {})
        save_map(
            path,
            MapFile(
                map=self.map,
                calibration=self.calib,
                disparity_offset=self.disparity_offset,
                orb=self._orb_settings(),
                vocabulary=self.vocab,
                bow=bows,
                meta=info,
            ),
        )
        log.info("map saved: %s (%d keyframes, %d points)", path, len(self.map.keyframes), self.map.stats()["map_points"])

    def load_map(self, path, localize_only: bool = False) -> None:
        """Start from the map in ``path`` (written by ``save_map``), before the first
        frame.  ``localize_only``: track in it without adding keyframes or points (no
        local mapping, no loop closing); the first frame is placed by relocalisation.
        Otherwise mapping (and loop closing) go on in the loaded map."""
        from .map_io import check_compatible, load_map

        if self._n:
            raise RuntimeError("System.load_map must be called before the first frame")
        mf = load_map(path)
        check_compatible(mf, self.calib, self._orb_settings(), path)
        if mf.vocabulary is not None:
            self.vocab = mf.vocabulary
        self.localize_only = bool(localize_only)
        self.disparity_offset = float(mf.disparity_offset)
        self._selfcal_due = False
        self._map_id = -1
        self._new_map(mf.map)
        self.mapper.selfcal_due = False
        saved = mf.bow or {}
        for k, kf in self.map.keyframes.items():
            if k in saved:
                bow = BowVector(np.asarray(saved[k][0]), np.asarray(saved[k][1]))
            else:
                bow = self.vocab.transform(kf.desc)[0]
            self.kfdb.add(k, bow)
        self._initialised = bool(self.map.keyframes)
        self._kf_total = 0  # keyframes created by this run
        self._kf_loaded = len(self.map.keyframes)
        log.info(
            "map loaded: %s (%d keyframes, %d points)%s",
            path,
            len(self.map.keyframes),
            self.map.stats()["map_points"],
            "; localisation only" if self.localize_only else "",
        )

    def loops(self) -> list[LoopEvent]:
        """The loops closed so far (all maps)."""
        return list(self._loop_events)

    def recoveries(self) -> list[Recovery]:
        """Frames tracked again after lost frames."""
        return list(self._recoveries)

    def shutdown(self) -> None:
        """Finish the pending local BA and stop the worker process and threads."""
        if self._closed:
            return
        if self.closer is not None:
            self.closer.shutdown()
        self.mapper.shutdown()
        self.runner.shutdown()
        if self._threads is not None:
            self._threads.shutdown(wait=True)
        self._closed = True

    def __enter__(self) -> "System":
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def __del__(self) -> None:  # best effort: never leave a worker process behind
        try:
            if not self._closed:
                self.shutdown()
        except Exception:  # noqa: BLE001
            pass
