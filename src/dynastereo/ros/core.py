"""The node's logic, transport-agnostic: :class:`StereoNodeCore`.

A ROS adapter (ROS 1: :mod:`dynastereo.ros.ros1`; ROS 2 over DDS: :mod:`dynastereo.ros.ros2`)
only converts messages to :class:`StereoInput` (numpy images + stamp), calls
:meth:`StereoNodeCore.submit`, and implements :class:`NodeSink` to publish what the core
hands back.  Everything else is here: rectification, masking, tracking, odometry and
disparity, live parameter changes, the bounded queue and the statistics.

Keeping up
----------
``submit`` never blocks and never queues without bound: the input queue holds at most
``queue_size`` pairs (default 1) and, when a new pair arrives while it is full, the
*oldest* waiting pair is dropped and counted (``stats.dropped``).  The pairs go through
the frame loop every job runs (:class:`dynastereo.runtime.loop.FrameLoop` over a
:class:`dynastereo.runtime.sources.LiveSource`), on one thread by default;
``pipelined=True`` uses two: masking of pair k+1 overlaps tracking of pair k, and the
masking thread takes the next pair only once the tracker has taken the previous one
(:mod:`dynastereo.runtime.pipelining`), so at most ``queue_size + 2`` pairs are in flight
and a busy tracker never makes masked pairs queue up.  A pair that fails is counted
(``stats.errors``) and the node goes on.  Pipelining
raises the frame rate a machine can sustain when it has cores to spare; on two shared
cores the two stages slow each other down and latency rises (benchmarks/bench_ros_latency.py),
hence serial is the default.  Poses are published as soon as tracking returns
(:meth:`NodeSink.publish_pose`), images and disparity after that.

Determinism
-----------
Frames that are not dropped are processed in arrival order with the same configuration,
so the poses equal those of an offline run (``System.track`` on the same frames, same
seed) -- the live test checks this.

Parameters
----------
``update_params({"stereo.block_size": 21, ...})`` validates the change (the Config
dataclasses and :func:`~dynastereo.masking.build_masker` raise ConfigError on a bad
value, the old configuration stays), builds the new masker off the processing threads
(the detector network is reloaded only when a ``detector.*`` key changed) and swaps it
in before the next frame.  ``stereo.*``, ``masker.*`` and ``detector.*`` are live;
``slam.*`` and ``seed`` are fixed at start-up (the map would not survive a change).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Protocol

import numpy as np

from ..config import Config, to_dict
from ..datatypes import StereoCalibration, StereoFrame, StereoMasks
from ..dotted import flatten_dotted
from ..errors import ConfigError
from ..io.calib import RawStereoCalibration
from ..io.queues import DropOldestQueue  # noqa: F401 -- re-exported (tests, adapters)
from ..io.rectify import Rectifier
from ..io.stereo_check import StereoWatch
from ..runtime.assembly import assemble_stages
from ..runtime.loop import FrameLoop
from ..runtime.pipelining import block_sigint
from ..runtime.processor import FrameItem, FrameProcessor, Processed
from ..runtime.results import new_run_timer
from ..runtime.sources import LiveSource, StereoInput
from ..timing import StageTimer
from .convert import twist_between
from .messages import DEFAULT_LEFT_FRAME, ODOM_FRAME, DisparityData, OdometryData

log = logging.getLogger("dynastereo.ros")

LIVE_SECTIONS = ("stereo", "masker", "detector")


@dataclass
class NodeResult:
    """What processing one pair produced (handed to the :class:`NodeSink`)."""

    position: int  # 0, 1, ... in the order tracked
    stamp_ns: int
    frame: StereoFrame  # rectified
    masks: StereoMasks | None
    pose: np.ndarray  # 3x4 camera-to-world (odom = first frame's left camera)
    odometry: OdometryData
    status: str  # init | tracked | lost
    ms: dict[str, float]  # per stage
    received: float  # wall clock s
    pose_time: float  # wall clock s when tracking returned


class NodeSink(Protocol):
    """The publishing side of an adapter."""

    def publish_pose(self, result: NodeResult) -> None: ...

    def publish_images(self, result: NodeResult, disparity: DisparityData | None) -> None: ...

    def wants_disparity(self) -> bool: ...


#: The longest wait for the SLAM held by the tracker thread (stop, save): past it the step
#: is skipped and recorded as a fallback.
SLAM_LOCK_TIMEOUT_S = 60.0
@dataclass
class NodeStats:
    received: int = 0  # pairs submitted
    processed: int = 0  # pairs tracked and published
    dropped: int = 0  # pairs evicted from the full queue (never processed)
    errors: int = 0  # pairs that raised while processing
    discarded_at_stop: int = 0
    lost: int = 0
    param_updates: int = 0
    param_rejections: int = 0
    latency_stamp_ms: list[float] = field(default_factory=list)  # stamp -> odometry published
    latency_receipt_ms: list[float] = field(default_factory=list)  # pair complete -> odometry published
    last_error: str = ""

    def summary(self) -> dict[str, Any]:
        def q(v: list[float]) -> dict[str, float]:
            if not v:
                return {}
            a = np.asarray(v, dtype=np.float64)
            return {"median": round(float(np.median(a)), 3), "p95": round(float(np.percentile(a, 95)), 3),
                    "max": round(float(a.max()), 3), "n": int(a.size)}

        d = {k: getattr(self, k) for k in ("received", "processed", "dropped", "errors", "discarded_at_stop", "lost",
                                            "param_updates", "param_rejections", "last_error")}
        d["latency_stamp_ms"] = q(self.latency_stamp_ms)
        d["latency_receipt_ms"] = q(self.latency_receipt_ms)
        return d


def flatten_live(cfg: Config) -> dict[str, Any]:
    """``{"stereo.block_size": 15, ...}`` for the live sections (None values left out)."""
    d = to_dict(cfg)
    out: dict[str, Any] = {}
    for s in LIVE_SECTIONS:
        out.update(flatten_dotted(d[s], s, skip_none=True))
    return out


def disparity_data(disp: np.ndarray, calib: StereoCalibration, cfg: Config) -> DisparityData:
    s = cfg.stereo
    lo = float(max(s.min_disparity, 0))
    return DisparityData(image=disp, f=calib.fx, T=calib.baseline, min_disparity=lo,
                         max_disparity=lo + float(s.num_disparities), delta_d=1.0 / 16.0)


def node_detector(cfg: Config, models_dir: Path | None = None, detector: Any = None,
                  detector_cfg: dict | None = None) -> tuple[Any, dict | None]:
    """``(detector, its configuration)`` for ``cfg``: ``detector`` is kept when its
    configuration equals ``detector_cfg`` (or when it was given and ``detector_cfg`` is None),
    else the network is loaded anew (a live change of a ``detector.*`` key); None when the
    masker needs no detector.  The masker itself is built by
    :func:`dynastereo.masking.build_masker`, as for every other job."""
    if str(cfg.masker.kind).lower() not in ("outline", "box"):
        return None, detector_cfg
    if str(cfg.detector.name) == "oracle":
        raise ConfigError("detector 'oracle' needs a synthetic sequence's ground truth; not available for bags "
                          "or live topics")
    if detector is None or (detector_cfg is not None and detector_cfg != to_dict(cfg.detector)):
        from ..masking.detection import create_detector

        detector, detector_cfg = create_detector(cfg.detector, models_dir), to_dict(cfg.detector)
    return detector, detector_cfg


class StereoNodeCore:
    """Stereo pairs in; masks, poses and disparity out (module doc).

    ``calibration``: known at start (a calibration file) or set later from the first
    CameraInfo pair with :meth:`set_calibration` (raw calibrations are rectified with a
    :class:`~dynastereo.io.rectify.Rectifier`).  ``detector``: a ready detector instead of the
    one ``cfg.detector`` names; ``masker``: a ready masker instead of the one ``cfg``
    builds (tests; a live parameter change replaces it with one built from ``cfg``).
    ``sink``: where results go (may be None: then use :meth:`process` and its return value).
    """

    def __init__(
        self,
        cfg: Config | None = None,
        *,
        calibration: StereoCalibration | RawStereoCalibration | None = None,
        models_dir: str | Path | None = None,
        detector: Any = None,
        masker: Any = None,
        queue_size: int = 1,
        pipelined: bool = False,
        sink: NodeSink | None = None,
        odom_frame: str = ODOM_FRAME,
        camera_frame: str = "",
        mesh: bool = False,
    ) -> None:
        self.cfg = cfg or Config()
        self.models_dir = Path(models_dir) if models_dir else None
        self.sink = sink
        self.pipelined = bool(pipelined)
        self.odom_frame = odom_frame
        self.camera_frame = camera_frame
        self.stats = NodeStats()
        self.timer = new_run_timer()
        self._detector = detector
        self._detector_cfg = to_dict(self.cfg.detector) if detector is None else None
        self.calibration: StereoCalibration | None = None
        self._own_masker = masker is None  # built here: (re)built for the rig once its calibration is known
        self.source = LiveSource(self._prepare, queue_size)
        # with the calibration given, set_calibration (below) builds it once; without it, a
        # masker for no rig now (the configuration checked), rebuilt when CameraInfo comes
        self.processor = FrameProcessor(self.source, masker if masker is not None or calibration is not None
                                        else self._build_masker(self.cfg))
        self._slam_lock = self.processor.lock
        self._masker_cfg = self.cfg
        self._pending: tuple[Any, Config] | None = None
        self._param_lock = threading.Lock()
        self.fallbacks: list[dict[str, Any]] = []  # bounded waits that ran out (node.json)
        self._matcher = None  # for published disparity when the masker computed none
        self._matcher_cfg: Any = None
        self._calib_in: StereoCalibration | RawStereoCalibration | None = None
        self.rectifier: Rectifier | None = None
        self._stamps: list[int] = []
        self._prev: tuple[np.ndarray, int] | None = None
        self._last: NodeResult | None = None
        self.loop = FrameLoop(self.processor, self.timer, pipelined=self.pipelined, on_error=self._error,
                              after=self._publish)
        self.mesh_recorder = None  # mesh: the keyframes kept for build_mesh (their images: memory grows with them)
        if mesh:
            from ..mesh import KeyframeRecorder
            from ..runtime.sinks import MeshSink

            self.mesh_recorder = KeyframeRecorder()
            self.loop.sinks.append(MeshSink(self.mesh_recorder))
        self._thread: threading.Thread | None = None
        self._running = False
        self.stereo_watch = StereoWatch("stereo input")  # warns once if the pairs look wrong
        if calibration is not None:
            self.set_calibration(calibration)

    # ------------------------------------------------------------------ setup
    @property
    def _masker(self) -> Any:
        return self.processor.masker

    @property
    def _system(self) -> Any:
        return self.processor.system

    def _build_masker(self, cfg: Config) -> Any:
        detector, self._detector_cfg = node_detector(cfg, self.models_dir, self._detector, self._detector_cfg)
        if detector is not None:
            self._detector = detector
        return assemble_stages(cfg, self.calibration, slam=False, models_dir=self.models_dir,
                               detector=detector).masker

    def set_calibration(self, calibration: StereoCalibration | RawStereoCalibration) -> bool:
        """Set the camera once (creates the SLAM system); True if it was new.  A different
        calibration later raises ConfigError (the map is in the first camera's units).  The
        stages come from :func:`~dynastereo.runtime.assembly.assemble_stages`, as every job's."""
        with self._slam_lock:
            if self._calib_in is not None:
                if _same_calibration(self._calib_in, calibration):
                    return False
                raise ConfigError("the stereo calibration changed while running; restart the node to use it")
            if isinstance(calibration, RawStereoCalibration):
                self.rectifier = Rectifier(calibration)
                self.calibration = self.rectifier.calibration
            else:
                self.rectifier = None
                self.calibration = calibration
            p = self.processor
            masker = p.masker
            if self._own_masker:  # the road line's slopes follow the rig's baseline
                with self._param_lock:
                    masker = p.masker = self._build_masker(self._masker_cfg)
            with _sigint_blocked():  # threads started meanwhile (the BA's) inherit it: Ctrl-C is the main thread's
                st = assemble_stages(self.cfg, self.calibration, masker=masker)
            p.system, p.motion, p.world = st.system, st.motion, st.world
            self.source.calibration = self.calibration
            self._calib_in = calibration
            return True

    def warm_up(self) -> None:
        """Run the detector once on a black image (its first call is slow: lazy
        initialization), so the first real frame does not pay for it.  No state changes.
        Through the masker's detection stage (``warm_up`` of the outline and box maskers, the
        ones with a detector), so that the frames' own canvas, tiles and batch are what is
        initialized; before the calibration is known, on a 640x480 image (the slowest part,
        the runtime's start in the process, does not depend on the size)."""
        h, w = (self.calibration.height, self.calibration.width) if self.calibration is not None else (480, 640)
        warm = getattr(self._masker, "warm_up", None)
        if warm is not None:
            warm(h, w)

    @property
    def ready(self) -> bool:
        return self._system is not None

    @property
    def queue_size(self) -> int:
        return self.source.queue.maxsize

    def set_queue_size(self, n: int) -> None:
        self.stats.dropped += self.source.resize(n)

    # ------------------------------------------------------------------ params
    def update_params(self, changes: dict[str, Any]) -> dict[str, Any]:
        """Apply dotted-key changes of the live sections (module doc); returns those that
        differ from the current values.  Raises ConfigError (nothing applied) on a bad
        key or value."""
        bad = [k for k in changes if k.split(".", 1)[0] not in LIVE_SECTIONS]
        if bad:
            self.stats.param_rejections += 1
            raise ConfigError(f"not changeable at run time: {', '.join(sorted(bad))} (only "
                              f"{', '.join(s + '.*' for s in LIVE_SECTIONS)}; slam.* and seed need a restart)")
        current = flatten_live(self.cfg)
        diff = {k: v for k, v in changes.items() if current.get(k, None) != v}
        if not diff:
            return {}
        try:
            new_cfg = self.cfg.with_overrides(diff)
            if flatten_live(new_cfg) == current:
                return {}
            masker = self._build_masker(new_cfg)
        except Exception as e:
            self.stats.param_rejections += 1
            if isinstance(e, ConfigError):
                raise
            raise ConfigError(f"parameters rejected: {type(e).__name__}: {e}") from None
        with self._param_lock:
            self._pending = (masker, new_cfg)
            self.cfg = new_cfg
        self.stats.param_updates += 1
        log.info("parameters changed: %s", ", ".join(f"{k}={v!r}" for k, v in diff.items()))
        return diff

    def _take_pending(self) -> None:
        with self._param_lock:
            if self._pending is not None:
                self.processor.masker, self._masker_cfg = self._pending
                self._own_masker = True
                self._pending = None
                if self.processor.motion is not None:  # the new masker's track ids start again
                    self.processor.motion.flow.reset()

    # ------------------------------------------------------------------ input
    def submit(self, inp: StereoInput) -> int:
        """Queue a pair for processing (never blocks); returns how many older waiting
        pairs were dropped to make room."""
        self.stats.received += 1
        n = self.source.submit(inp)
        self.stats.dropped += n
        return n

    def start(self) -> None:
        """The frame loop on its own thread (and, pipelined, the masking thread beside it)."""
        if self._running:
            return
        self._running = True
        self._thread = threading.Thread(target=self._run_loop, name="dynastereo-process", daemon=True)
        self._thread.start()

    def _run_loop(self) -> None:
        block_sigint()
        try:
            self.loop.run()  # frames that fail are counted (``_error``) and the loop goes on
        except BaseException as e:  # noqa: BLE001 -- never silently: the node would stop tracking
            self.stats.last_error = f"the frame loop stopped: {type(e).__name__}: {e}"
            log.critical("%s", self.stats.last_error, exc_info=True)
            raise

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Wait until every submitted pair is processed or dropped; False on timeout."""
        return self.source.wait_idle(timeout)

    def stop(self, timeout: float = 10.0) -> None:
        """Stop the threads (the pair being processed is finished, waiting ones discarded).
        A thread still busy after ``timeout`` s is left behind (a daemon), recorded in
        ``fallbacks`` (node.json)."""
        if not self._running:
            return
        self._running = False
        self.stats.discarded_at_stop += self.source.close()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                self._fallback("stop", f"thread {self._thread.name} still busy after {timeout:g} s",
                               "left behind (daemon)")
        if not self.loop.close():
            self._fallback("stop", f"thread dynastereo-mask still busy after {timeout:g} s", "left behind (daemon)")
        self._thread = None

    def shutdown(self) -> None:
        """Stop and finish the SLAM (pending local BA)."""
        self.stop()
        with self._slam_locked("shutdown", "the SLAM's final local BA skipped") as ok:
            if ok and self._system is not None:
                self._system.shutdown()

    def _fallback(self, what: str, reason: str, action: str) -> None:
        self.fallbacks.append({"what": what, "frame": self.loop.state.n_done, "reason": reason, "action": action})
        log.warning("%s: %s; %s", what, reason, action)

    @contextmanager
    def _slam_locked(self, what: str, action: str) -> Iterator[bool]:
        """The SLAM lock, waited for at most :data:`SLAM_LOCK_TIMEOUT_S`: yields False (and
        records the fallback) when the tracker thread holds it longer (stuck)."""
        ok = self._slam_lock.acquire(timeout=SLAM_LOCK_TIMEOUT_S)
        if not ok:
            self._fallback(what, f"the tracker thread held the SLAM for over {SLAM_LOCK_TIMEOUT_S:g} s", action)
        try:
            yield ok
        finally:
            if ok:
                self._slam_lock.release()

    # ------------------------------------------------------------------ processing
    def _error(self, e: BaseException) -> None:
        self.stats.errors += 1
        self.stats.last_error = f"{type(e).__name__}: {e}"
        log.error("frame failed: %s", self.stats.last_error, exc_info=log.isEnabledFor(logging.DEBUG))

    def process(self, inp: StereoInput) -> NodeResult:
        """Mask, track and publish one pair on the calling thread."""
        self.loop.process(FrameItem(self.loop.state.n_done, None, inp))
        return self._last

    def _prepare(self, inp: StereoInput, t: StageTimer) -> StereoFrame:
        """The pair as a rectified frame (the masking stage's read; the live source's ``prepare``)."""
        if self._system is None:
            raise ConfigError("no calibration yet (waiting for CameraInfo, or give a calibration file)")
        self._take_pending()
        left, right = inp.left, inp.right
        if self.rectifier is not None:
            with t.stage("rectify"):
                left, right = self.rectifier.rectify(left, right)
        c = self.calibration
        if (left.shape[1], left.shape[0]) != c.size or left.shape[:2] != right.shape[:2]:
            raise ValueError(f"images are {left.shape[1]}x{left.shape[0]} / {right.shape[1]}x{right.shape[0]}, "
                             f"the calibration is for {c.width}x{c.height}")
        frame = StereoFrame(index=-1, timestamp=inp.stamp_ns * 1e-9, left=left, right=right)
        if not self.stereo_watch.done:
            self.stereo_watch.observe(frame)
        return frame

    def _publish(self, p: Processed) -> None:
        """The tracked pair out: the pose at once, then the images and disparity."""
        inp: StereoInput = p.payload
        pose_time = time.time()
        self._stamps.append(int(inp.stamp_ns))
        T = np.vstack([p.pose, [0.0, 0.0, 0.0, 1.0]])
        prev = self._prev
        lin, ang = twist_between(prev[0] if prev else None, T, (inp.stamp_ns - prev[1]) * 1e-9 if prev else 0.0)
        self._prev = (T, int(inp.stamp_ns))
        odo = OdometryData(stamp_ns=int(inp.stamp_ns), pose=T, frame_id=self.odom_frame,
                           child_frame_id=self.camera_frame or inp.frame_id or DEFAULT_LEFT_FRAME,
                           linear=lin, angular=ang, seq=p.position)
        res = NodeResult(p.position, int(inp.stamp_ns), p.frame, p.slam_masks, p.pose, odo, p.status, p.ms,
                         inp.received, pose_time)
        self._last = res
        if self.sink is not None:
            self.sink.publish_pose(res)
        published = time.time()
        self.stats.processed += 1
        self.stats.lost += p.status == "lost"
        self.stats.latency_stamp_ms.append((published - inp.stamp_ns * 1e-9) * 1000.0)
        self.stats.latency_receipt_ms.append((published - inp.received) * 1000.0)
        if self.sink is not None:
            disp = self.compute_disparity(p.frame, p.slam_masks) if self.sink.wants_disparity() else None
            self.sink.publish_images(res, disp)

    def map_points(self) -> np.ndarray:
        """(M, 3) positions of the map points, in ``odom`` (empty before the calibration)."""
        with self._slam_lock:
            return self._system.map_points() if self._system is not None else np.zeros((0, 3))

    def compute_disparity(self, frame: StereoFrame, masks: StereoMasks | None) -> DisparityData:
        """The full-frame disparity to publish (the masker's when it made one)."""
        cfg = self._masker_cfg
        if masks is not None and masks.disparity is not None:
            d = masks.disparity
        else:
            from ..masking import StereoMatcher

            if self._matcher is None or self._matcher_cfg != cfg.stereo:
                self._matcher, self._matcher_cfg = StereoMatcher(cfg.stereo), cfg.stereo
            d = self._matcher.compute(frame.left_gray, frame.right_gray, scale=int(cfg.stereo.scale))
        return disparity_data(d, self.calibration, cfg)

    # ------------------------------------------------------------------ results
    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """``(poses (N, 3, 4), stamps ns (N,))``: the current (locally bundle-adjusted) poses
        (none when the tracker thread is stuck holding the SLAM: a recorded fallback)."""
        with self._slam_locked("trajectory", "no poses returned") as ok:
            if not ok or self._system is None or not self._stamps:
                return np.zeros((0, 3, 4)), np.zeros(0, np.int64)
            return self._system.trajectory(), np.asarray(self._stamps, np.int64)

    def build_mesh(self) -> Any:
        """The static world's mesh so far (:mod:`dynastereo.mesh`, a
        :class:`~dynastereo.mesh.DenseResult`; None before the first keyframe or without
        ``mesh``): the keyframes kept, at the current (bundle-adjusted) poses.  The SLAM is
        held only to copy the poses; the fusion runs on the calling thread meanwhile."""
        rec = self.mesh_recorder
        if rec is None or not rec.views or self._system is None:
            return None
        from ..mesh import KeyframeRecorder, fuse

        with self._slam_locked("mesh", "no mesh built") as ok:
            if not ok:
                return None
            sysm = self._system
            poses = sysm.trajectory()
            done = np.array([str(s.status) in ("tracked", "init") for s in sysm.results()], bool)
            offset = float(sysm.disparity_offset)
            snap = KeyframeRecorder()
            snap.views, snap.moving_tracks = list(rec.views), set(rec.moving_tracks)
        return fuse(snap, poses, self.calibration, self._masker_cfg, disparity_offset=offset, ok=done)

    def mesh_service(self, builder: Any, save_dir: Path, pub_mesh: Any, pub_dense: Any) -> tuple[bool, str]:
        """The ``build_mesh`` service of both nodes: :meth:`build_mesh`, written to
        ``save_dir/mesh.ply``, published as a Marker TRIANGLE_LIST (``pub_mesh``) and its
        vertices as a PointCloud2 (``pub_dense``) with the transport's ``builder``, stamped
        with the last published pair's stamp; ``(success, message)`` -- the counts as JSON,
        or why not (the node goes on)."""
        stamp_ns = self._stamps[-1] if self._stamps else 0
        try:
            from ..mesh import write_mesh_ply

            res = self.build_mesh()
            if res is None:
                return False, "no keyframe yet" if self.mesh_recorder is not None else "started without mesh: true"
            path = write_mesh_ply(Path(save_dir) / "mesh.ply", res.mesh)
            if pub_dense is not None:
                pub_dense.publish(builder.point_cloud(res.mesh.vertices, stamp_ns, self.odom_frame))
            if pub_mesh is not None:
                pub_mesh.publish(builder.mesh_marker(res.mesh, stamp_ns, self.odom_frame))
            return True, json.dumps({**res.stats.to_dict(), "file": str(path)})
        except Exception as e:  # noqa: BLE001 -- the node goes on; the caller is told
            return False, f"{type(e).__name__}: {e}"

    def status(self) -> dict[str, Any]:
        d = self.stats.summary()
        d.update(queue_size=self.queue_size, queue_high_water=self.source.queue.high_water, ready=self.ready,
                 pipelined=self.pipelined, config=to_dict(self.cfg), fallbacks=list(self.fallbacks))
        if self.stereo_watch.verdict is not None:
            d["stereo_check"] = self.stereo_watch.verdict.to_dict()
        if self.calibration is not None:
            c = self.calibration
            d["calibration"] = {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "baseline": c.baseline,
                                "width": c.width, "height": c.height, "rectified_on_receipt": self.rectifier is not None}
        return d

    def save(self, out_dir: str | Path) -> dict[str, str]:
        """Write ``trajectory.{kitti,tum,frames}.txt``, ``timing.json`` and ``node.json``
        (statistics, latency, configuration) into ``out_dir``; returns the paths."""
        from ..eval.trajectory import FRAMES_NAME, KITTI_NAME, TUM_NAME, write_kitti, write_tum
        from ..io.outputs import atomic_write_text

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        poses, stamps = self.trajectory()
        paths = {"kitti": out / KITTI_NAME, "tum": out / TUM_NAME, "frames": out / FRAMES_NAME,
                 "timing": out / "timing.json", "node": out / "node.json"}
        write_kitti(paths["kitti"], poses)
        write_tum(paths["tum"], poses, stamps.astype(np.float64) * 1e-9)
        atomic_write_text(paths["frames"], "".join(f"{i}\n" for i in range(len(stamps))))
        with self._slam_locked("save", "timing.json not written") as ok:
            if ok:
                self.timer.write(paths["timing"], frames_done=len(stamps))
        st = self.status()
        if self._system is not None:
            st["slam"] = self._system.stats().to_dict()
        atomic_write_text(paths["node"], json.dumps(st, indent=1, default=float))
        return {k: str(v) for k, v in paths.items()}


class _sigint_blocked:
    """Block SIGINT in this thread (child processes started meanwhile inherit the mask and
    so ignore a SIGINT sent to the whole process group: the node shuts them down itself,
    after the final local BA).  Python runs signal handlers in the main thread only, so
    blocking it in other threads changes nothing else."""

    def __enter__(self) -> None:
        import signal

        self._old = None
        if hasattr(signal, "pthread_sigmask"):
            self._old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})

    def __exit__(self, *exc: object) -> None:
        import signal

        if self._old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, self._old)


def _same_calibration(a: Any, b: Any) -> bool:
    if type(a) is not type(b):
        return False
    if isinstance(a, StereoCalibration):
        return np.array_equal(a.K, b.K) and a.baseline == b.baseline and a.size == b.size
    fa = {k: getattr(a, k) for k in ("K1", "D1", "K2", "D2", "R1", "R2", "P1", "P2", "R", "T")}
    fb = {k: getattr(b, k) for k in fa}
    return a.size == b.size and all(
        (x is None and y is None) or (x is not None and y is not None and np.array_equal(x, y))
        for x, y in ((fa[k], fb[k]) for k in fa))
