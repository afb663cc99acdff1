"""System: the SLAM back-end's public API.

    system = System(config, calibration)
    for frame, masks in ...:
        res = system.track(frame, masks)       # TrackResult: res.pose 3x4 camera-to-world
    poses = system.trajectory()                # (N, 3, 4), one per frame fed, in order
    system.shutdown()

``System`` is a thin facade (ORB-SLAM2's ``System``): it builds the ORB extractor, the
self-calibration, the BA runner (bundle adjustments in a thread; its kernel is compiled or
loaded from cache in the background at start) and the :class:`~.tracking.Tracker`, and wires each new
map's local mapper, keyframe database and loop closer (:class:`~.active_map.ActiveMap`)
to it.  The tracking state lives in the tracker, the policy below in ``tracking``.

World = the first frame's left camera (KITTI ground-truth convention).  Every frame fed
gets exactly one trajectory row.  Poses of tracked frames are kept relative to their
reference keyframe (as ORB-SLAM2 does), so later local BA refines them too.

A pose is accepted only with enough support: after local-map tracking at least
``min_inliers`` inliers and at least ``min_inlier_fraction`` (25 %) of the median of the
last tracked frames.  A jump the motion model cannot follow (a revisit fed as
``--frames 0-98,40-60``, a gap) leaves a wrong prediction with a few chance inliers on far
points: such a pose is refused, and a prior-free search over the map's keyframes runs
instead (``Tracker.relocalize``: bag-of-words candidate keyframes, PnP-RANSAC,
motion-only BA, local map; ``reloc_min_inliers`` needed).  A frame placed that way is
``tracked`` with method ``reloc`` (or ``reference`` when the reference keyframe's
descriptors already placed it); the velocity is not taken across such a jump.

When no pose is supported the frame is *lost*: a WARNING log line names the frame and
the reason, ``results()`` flags it ``lost``, and its trajectory row is the
*constant-velocity prediction* (last pose times last velocity; the last pose if no
velocity yet) -- over a run of lost frames the prediction continues at that velocity.
Then:

* the frame has at least ``min_init_points`` stereo points (a new place): a new map is
  initialized from them, anchored to that predicted pose, and tracking continues on it
  (``map_id`` increments; the frame is the new map's first keyframe);
* it has fewer (a black or blank frame, a lens cover): the map is kept, and the next
  frames are tracked / relocalized in it again -- after ten black frames KITTI 06 is
  found again at its true place, no new map needed.

Nothing raises on bad frames.

Stereo self-calibration (``slam.self_calibrate``, on by default) of the rig's disparity
offset: :mod:`.selfcal` (``stats().disparity_offset``).

Loop closing (``loop_closing.LoopCloser``, after each new keyframe), relocalization with
the bag-of-words keyframe database and map files (``save_map`` / ``load_map``, with
``localize_only``) are described in docs/guide/slam.md and in those modules.
"""

from __future__ import annotations

import dataclasses
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config import Config, SlamConfig
from ..errors import ConfigError
from ..timing import StageTimer
from ..datatypes import StereoCalibration, StereoFrame, StereoMasks
from .active_map import ActiveMap
from .dynamic import forget_region
from .keyframe_database import KeyFrameDatabase
from .local_mapping import BARunner, LocalMapper
from .loop_closing import LoopCloser, LoopEvent, LoopStats
from .map import Map
from .map_io import check_compatible, load_map, map_file_from_system, orb_settings, save_map
from .orb import ORBExtractor
from .selfcal import SelfCalibration
from .settings import load_orbslam_settings
from .tracking import FrameFeatures, Recovery, Tracker, TrackingMethod, TrackingState, TrackResult
from .vocabulary import BowVector, Vocabulary

log = logging.getLogger("dynastereo.slam")


@dataclass
class SystemStats:
    """What a run did (``System.stats()``; ``run.json`` ``stats``)."""

    frames: int
    tracked: int
    lost: int
    reinitializations: int
    keyframes: int
    keyframes_created: int
    keyframes_loaded: int
    map_points: int
    # a keyframe's local mapping + loop closing (wall ms, on the mapping thread or inline),
    # and how long tracking waited for it (slam.local_mapping "thread")
    local_mapping_ms_median: float
    local_mapping_wait_ms_median: float
    local_ba_runs: int
    local_ba_ms_median: float
    local_ba_wait_ms_median: float
    # BA results skipped (not done within slam.ba_wait_s / loop_ba_wait_s, or failed):
    # {"frame", "ba", "reason", "action", "waited_s"} each
    local_ba_fallbacks: list[dict]
    points_triangulated: int
    points_fused: int
    points_culled: int
    keyframes_culled: int
    disparity_offset: float
    disparity_offset_sigma: float | None
    relocalizations: int
    relocalization_ms_median: float
    recoveries: int
    loops: int
    loop_candidates_rejected: int
    loop_query_ms_median: float
    pose_graph_ms_median: float
    localize_only: bool

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class FrameView:
    """What the last tracked frame looks like to a viewer (``System.frame_view()``)."""

    uv: np.ndarray  # (N, 2) left keypoints, pixels
    inlier: np.ndarray  # (N,) bool: matched to a map point and kept by the pose optimization
    outlier: np.ndarray  # (N,) bool: matched, rejected by the pose optimization
    local_points: np.ndarray  # (M, 3) world positions of the local map's points


def _median(v: list[float]) -> float:
    return float(np.median(v)) if v else 0.0


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
        cfg.validate()  # (a configuration changed after it was made)
        self.cfg = cfg
        self.seed = int(seed or 0)
        self.calib = calibration
        self.extractor = ORBExtractor(
            cfg.n_features, cfg.scale_factor, cfg.n_levels, cfg.ini_th_fast, cfg.min_th_fast, cfg.oversample, cfg.mask_margin
        )
        self.selfcal = SelfCalibration(cfg, calibration.bf)
        self._threads = ThreadPoolExecutor(max_workers=2, thread_name_prefix="features") if cfg.threads > 1 else None
        self._mapping = (ThreadPoolExecutor(max_workers=1, thread_name_prefix="local-mapping")
                         if cfg.local_mapping == "thread" else None)
        self.runner = BARunner(cfg.local_ba, cfg.ba_wait_s)
        self.runner.warm_up()
        self.timer = StageTimer()
        self.vocab = Vocabulary.load(cfg.vocabulary) if cfg.vocabulary else Vocabulary.default()
        self.tracker = Tracker(cfg, calibration, self.extractor, self.selfcal, self.vocab, seed=self.seed,
                               reset_map=self._new_map, threads=self._threads, mapping=self._mapping)
        self.th_depth_m = self.tracker.th_depth_m  # "close" stereo points: th_depth baselines
        self._loop_events: list[LoopEvent] = []
        self._loop_stats = LoopStats()
        self._kf_loaded = 0
        self._closed = False
        self.active: ActiveMap | None = None
        self._new_map()

    @classmethod
    def from_orbslam_settings(cls, path: str, base: Config | None = None) -> "System":
        """A System configured from an ORB-SLAM2 stereo settings file (camera included)."""
        base_cfg = base or Config()
        slam, calib = load_orbslam_settings(path, base_cfg.slam)
        return cls(slam, calib, seed=base_cfg.seed)

    # ------------------------------------------------------------------ maps
    @property
    def map(self) -> Map:
        """The map being built (or localized in); the keyframe being mapped is waited for."""
        self.tracker.join_mapping()
        return self.active.map

    @property
    def localize_only(self) -> bool:
        return self.tracker.localize_only

    @property
    def disparity_offset(self) -> float:
        """The disparity offset (px) every stereo observation carries now."""
        return self.selfcal.offset

    def _new_map(self, mp: Map | None = None, initialized: bool = False) -> None:
        """Start a new map (empty, or ``mp``: a loaded one) and track in it; the old
        map's frame poses are made absolute first."""
        old = self.active
        if old is not None:
            self.tracker.join_mapping()
            old.shutdown()
        mp = mp if mp is not None else Map(self.extractor.scales)
        self.selfcal.new_map()
        mapper = LocalMapper(mp, self.cfg, self.extractor, self.th_depth_m, self.runner, self.selfcal)
        kfdb = KeyFrameDatabase(self.vocab)
        closer = None
        if self.cfg.loop_closing and not self.localize_only:
            ex = self.extractor
            closer = LoopCloser(mp, kfdb, self.vocab, mapper, self.cfg, self.th_depth_m, self.seed, ex.inv_sigma2,
                                ex.scales, events=self._loop_events, stats=self._loop_stats)
        self.active = ActiveMap(old.id + 1 if old is not None else 0, mp, mapper, kfdb, closer)
        self.tracker.attach(self.active, initialized=initialized)

    # ------------------------------------------------------------------ track
    def wait_ready(self) -> float:
        """Wait until the SLAM's compiled kernels are loaded (started in the background
        when the System is made; compiled on the first run after an install), so that the
        first frames do not share the CPU with their loading; returns the seconds waited.
        Optional: a frame tracked before waits for the kernels it calls."""
        return self.runner.wait_warm_up()

    def features(self, frame: StereoFrame, masks: StereoMasks | None = None,
                 timer: StageTimer | None = None) -> FrameFeatures:
        """ORB features and stereo matches of ``frame`` (masked by ``masks``), computed
        ahead of :meth:`track` -- on another thread if wanted: they read no map and no
        tracking state.  Give them to ``track(frame, masks, features=...)`` with the same
        masks; the result is the same as without."""
        if self._closed:
            raise RuntimeError("System.features called after shutdown()")
        return self.tracker.features(frame, masks, timer)

    def track(
        self, frame: StereoFrame, masks: StereoMasks | None = None, timer: StageTimer | None = None,
        features: FrameFeatures | None = None,
    ) -> TrackResult:
        """Track one rectified stereo frame: its :class:`~.tracking.TrackResult` (``pose``:
        3x4 camera-to-world of the left camera).

        ``masks`` (255 = dynamic) keep the detector off dynamic objects in each image.
        Stage times go to ``timer`` (the caller's frame) or to ``self.timer``.
        ``features``: the frame's :meth:`features`, if computed ahead.
        """
        if self._closed:
            raise RuntimeError("System.track called after shutdown()")
        own = timer is None
        tm = self.timer if own else timer
        if own:
            tm.start_frame(frame.index)
        res = self.tracker.track(frame, masks, tm, features)
        if own:
            tm.end_frame(status=res.status)
        return res

    def forget_region(self, region: np.ndarray, z_min: float, z_max: float) -> int:
        """Remove from the map the points that project, from the last tracked frame, into
        the left-image pixels ``region`` (bool) at depths ``[z_min, z_max]`` m -- an
        object that turned out to move (``slam.dynamic``); returns how many."""
        return forget_region(self.map, self.tracker.last, region, z_min, z_max)

    # ---------------------------------------------------------------- results
    def trajectory(self) -> np.ndarray:
        """(N, 3, 4) camera-to-world poses of the left camera, one per frame fed."""
        return self.tracker.trajectory.poses(self.map)

    def frame_view(self) -> FrameView | None:
        """Keypoints (inliers / outliers) of the last frame tracked and the local map's
        points (copies; None before the first frame)."""
        f = self.tracker.last
        if f is None:
            return None
        matched = f.point_ids >= 0
        local = [k for k in self.tracker.local_kfs if k in self.map.keyframes]
        pts = self.map.points_of(local) if local else np.zeros(0, np.int64)
        rejected = np.zeros(len(f.uv), bool)
        rejected[f.rejected] = True
        return FrameView(f.uv.copy(), matched, rejected, self.map.points.pos[pts].copy())

    def map_points(self) -> np.ndarray:
        """(M, 3) world positions of all good map points (a copy)."""
        P = self.map.points
        return P.pos[P.good_ids()]

    def results(self) -> list[TrackResult]:
        """Every frame fed, as tracked."""
        return list(self.tracker.results)

    def lost_frames(self) -> list[int]:
        """Positions (in the order fed) of the frames marked lost."""
        return [s.index for s in self.tracker.results if s.status == TrackingState.LOST]

    def stats(self) -> SystemStats:
        self.tracker.join_mapping()
        ms = self.active.mapper.stats
        tr = self.tracker
        st = tr.results
        return SystemStats(
            frames=len(st),
            tracked=sum(s.status != TrackingState.LOST for s in st),
            lost=sum(s.status == TrackingState.LOST for s in st),
            reinitializations=self.active.id,
            keyframes=len(self.map.keyframes),
            keyframes_created=tr.keyframes_created,
            keyframes_loaded=self._kf_loaded,
            map_points=self.map.stats()["map_points"],
            local_mapping_ms_median=_median(tr.mapping_ms),
            local_mapping_wait_ms_median=_median(tr.mapping_wait_ms),
            local_ba_runs=ms.ba_runs,
            local_ba_ms_median=_median(ms.ba_ms),
            local_ba_wait_ms_median=_median(ms.ba_wait_ms),
            local_ba_fallbacks=list(self.runner.fallbacks),
            points_triangulated=ms.points_triangulated,
            points_fused=ms.points_fused,
            points_culled=ms.points_culled,
            keyframes_culled=ms.keyframes_culled,
            disparity_offset=self.selfcal.offset,
            disparity_offset_sigma=self.selfcal.sigma,
            relocalizations=sum(s.method == TrackingMethod.RELOC for s in st),
            relocalization_ms_median=_median(tr.reloc_ms),
            recoveries=len(tr.recoveries),
            loops=len(self._loop_events),
            loop_candidates_rejected=self._loop_stats.rejected,
            loop_query_ms_median=_median(self._loop_stats.query_ms),
            pose_graph_ms_median=_median([e.pose_graph_ms for e in self._loop_events]),
            localize_only=self.localize_only,
        )

    def loops(self) -> list[LoopEvent]:
        """The loops closed so far (all maps)."""
        self.tracker.join_mapping()
        return list(self._loop_events)

    def recoveries(self) -> list[Recovery]:
        """Frames tracked again after lost frames."""
        return list(self.tracker.recoveries)

    # -------------------------------------------------------------- map files
    def save_map(self, path, meta: dict[str, Any] | None = None, optimize: bool = True) -> None:
        """Write the current map (keyframes, map points, covisibility, bag of words, the
        vocabulary and the disparity offset) to ``path`` (``docs/reference/map-format.md``).  The
        local and full BAs in flight are applied first; with ``optimize`` (and mapping on)
        a final bundle adjustment over the whole map -- self-calibrating, so the disparity
        offset is refined over all keyframes -- makes the map the best it can be for reuse
        (the frame poses, ``trajectory()``, follow it)."""
        active, n = self.active, self.tracker.n
        if not self.localize_only:
            if active.closer is not None:
                active.closer.collect(n, force=True)
            active.mapper.collect(n, force=True)
            if optimize and self.cfg.mapping_on:
                active.mapper.optimize_whole_map()
        bows = {}
        for k in self.map.keyframes:
            if k in active.kfdb:
                b = active.kfdb.bow(k)
                bows[k] = (b.words, b.weights)
        info = {"frames": n, "map_id": active.id, "loops": len(self._loop_events)}
        info.update(meta or {})
        save_map(path, map_file_from_system(self, meta=info, vocabulary=self.vocab, bow=bows))
        log.info("map saved: %s (%d keyframes, %d points)", path, len(self.map.keyframes), self.map.stats()["map_points"])

    def load_map(self, path, localize_only: bool = False) -> None:
        """Start from the map in ``path`` (written by ``save_map``), before the first
        frame.  ``localize_only``: track in it without adding keyframes or points (no
        local mapping, no loop closing); the first frame is placed by relocalization.
        Otherwise mapping (and loop closing) go on in the loaded map."""
        if self.tracker.n:
            raise RuntimeError("System.load_map must be called before the first frame")
        mf = load_map(path)
        check_compatible(mf, self.calib, orb_settings(self.cfg), path)
        if mf.vocabulary is not None:
            self.vocab = self.tracker.vocab = mf.vocabulary
        self.tracker.localize_only = bool(localize_only)
        self.selfcal.loaded(mf.disparity_offset)
        self.active.shutdown()
        self.active = None  # the loaded map is map 0
        self._new_map(mf.map, initialized=bool(mf.map.keyframes))
        saved = mf.bow or {}
        for k, kf in self.map.keyframes.items():
            if k in saved:
                bow = BowVector(np.asarray(saved[k][0]), np.asarray(saved[k][1]))
            else:
                bow = self.vocab.transform(kf.desc)[0]
            self.active.kfdb.add(k, bow)
        self._kf_loaded = len(self.map.keyframes)
        log.info(
            "map loaded: %s (%d keyframes, %d points)%s",
            path,
            len(self.map.keyframes),
            self.map.stats()["map_points"],
            "; localization only" if self.localize_only else "",
        )

    def shutdown(self) -> None:
        """Apply the pending BAs (each wait bounded) and stop the threads."""
        if self._closed:
            return
        try:
            self.tracker.join_mapping()
        finally:
            self.active.shutdown()
            self.runner.shutdown()
            for pool in (self._threads, self._mapping):
                if pool is not None:
                    pool.shutdown(wait=True)
            self._closed = True  # also when the mapping thread's error is raised here: once

    def __enter__(self) -> "System":
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def __del__(self) -> None:  # best effort: never leave a BA running
        try:
            if not self._closed:
                self.shutdown()
        except Exception:  # noqa: BLE001
            pass
