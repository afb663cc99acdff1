"""``dynastereo run --bag``: a bag as an ordinary source, and what a bag run writes into its output bag.

:class:`BagSource` (``SourceSpec(opener=BagSource(...))``) is the one place a bag run is
made: it opens the bag as a :class:`~dynastereo.ros.bags.BagStereoSequence`, fed to the same
job as a sequence folder (:func:`dynastereo.runtime.run`: trajectory files,
``timing.json``, ``run.json``), and gives the job a :class:`BagOutput` observer that writes every
tracked frame to ``DIR/output.{bag,db3,mcap}`` (the input's format): odometry, TF, the
masked images, the masks, the disparity, the path so far and (every ``MAP_EVERY``-th frame
and once more after the final bundle adjustment) the map points (topics in
:mod:`dynastereo.ros.messages`).
``DIR/bag.json`` records the pairing (pairs, unpaired left/right messages, tolerance),
the calibration source and what was written.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..config import Config
from ..datatypes import StereoFrame, StereoMasks
from ..errors import ConfigError, InputError
from ..io.outputs import atomic_write_text
from ..observers import FrameEvent
from ..runtime.spec import JobKind, JobSpec, SourceSpec
from .bags import BAG_SUFFIX, BagStereoSequence, BagWriter
from .convert import masked_image, twist_between
from .core import disparity_data
from .messages import DEFAULT_LEFT_TOPIC, DEFAULT_RIGHT_TOPIC, MAP_EVERY, ODOM_FRAME, OUTPUT_TOPICS, OUTPUT_TYPES, \
    OdometryData

#: What a bag run can write into its output bag (``--bag-outputs``).
BAG_OUTPUTS = ("odometry", "tf", "masked", "masks", "disparity", "path", "map_points", "objects")


def parse_bag_outputs(spec: str | list[str] | tuple[str, ...] | None) -> tuple[str, ...]:
    """``"all"`` / None -> every output; else a comma list of :data:`BAG_OUTPUTS`."""
    if spec is None:
        return BAG_OUTPUTS
    items = [s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec) if s.strip()]
    if items == ["all"]:
        return BAG_OUTPUTS
    bad = [s for s in items if s not in BAG_OUTPUTS]
    if bad:
        raise InputError(f"unknown bag output(s) {', '.join(bad)}; choose from {', '.join(BAG_OUTPUTS)} or 'all'")
    return tuple(items)


@dataclass(frozen=True)
class BagSource:
    """A stereo ROS bag as input (``run --bag``): topics, CameraInfo, pairing, rectification,
    and what goes into the output bag (``DIR/output.<same format>``).  A
    :class:`~dynastereo.runtime.spec.OpenableSource`: ``SourceSpec(opener=BagSource(path))``."""

    path: Path
    left_topic: str = DEFAULT_LEFT_TOPIC
    right_topic: str = DEFAULT_RIGHT_TOPIC
    left_info: str | None = "auto"  # auto: camera_info beside the image topic; None: ignore
    right_info: str | None = "auto"
    tolerance_s: float = 0.005  # largest left/right stamp difference of a pair
    rectify: str = "auto"  # auto | yes | no
    fallback_calib: Path | None = None  # used only without CameraInfo (an ORB-SLAM2 settings file)
    outputs: tuple[str, ...] = BAG_OUTPUTS
    kind = "bag"

    def __post_init__(self) -> None:
        if not self.tolerance_s >= 0:
            raise ConfigError(f"--sync-tolerance must be a time >= 0 ms (milliseconds), got {self.tolerance_s * 1e3:g}")
        if self.rectify not in ("auto", "yes", "no"):
            raise ConfigError(f"--rectify must be auto, yes or no, got {self.rectify!r}")
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "outputs", parse_bag_outputs(self.outputs))

    def check(self, source: SourceSpec) -> None:
        if source.rate is not None:
            raise ConfigError("--rate is for sequence folders; a bag's images carry their stamps")

    def check_job(self, job: JobSpec) -> None:
        if job.kind is JobKind.MASK:
            raise ConfigError("a mask job tracks nothing: bag needs a run")
        if job.outputs.save_map or job.load_map:
            raise ConfigError("--save-map / --load-map work on sequence folders, not with --bag")

    def open(self, calib: Path | None) -> BagStereoSequence:
        return BagStereoSequence(self.path, self.left_topic, self.right_topic, self.left_info, self.right_info, calib,
                                 self.tolerance_s, self.rectify, fallback_calib=self.fallback_calib)

    def job_observers(self, job: JobSpec, sequence: BagStereoSequence) -> tuple["BagOutput"]:
        """The writer of the run's ``DIR/output.<the input's format>`` and ``DIR/bag.json``."""
        return (BagOutput(None, sequence.format, job.config, sequence.calibration, sequence.frame_id, self.outputs,
                          stamps_ns=sequence.stamps_ns, source=sequence),)

class BagOutput:
    """Writes the per-frame results into the output bag.  ``path`` None: a bag run's
    observer (:class:`~dynastereo.observers.OutputObserver`), whose bag
    ``DIR/output.<fmt>`` is created when the run's output folder is ready (``open``) and
    which writes ``DIR/bag.json`` when closed (``source``: the bag read, for its pairing)."""

    name = "bag"

    def __init__(self, path: Path | None, fmt: str, cfg: Config, calibration, camera_frame: str,
                 outputs: tuple[str, ...] = BAG_OUTPUTS, stamps_ns: np.ndarray | None = None,
                 source: BagStereoSequence | None = None) -> None:
        self.fmt, self.source = fmt, source
        self.stamps_ns = stamps_ns  # per sequence index, for on_frame
        self.out_dir: Path | None = None
        self.n_frames = 0
        self.path = None if path is None else Path(path)
        self.writer: Any = None
        self.cfg = cfg
        self.calibration = calibration
        self.camera_frame = camera_frame
        self.outputs = outputs
        self._matcher = None
        self._prev: tuple[np.ndarray, int] | None = None
        self._path: tuple[list[np.ndarray], list[int]] = ([], [])
        from ..objects.world import ObjectPaths

        self._object_paths = ObjectPaths()
        self._system: Any = None  # the SLAM system of the frames written (for the final map)
        self._last: tuple[int, int] = (0, 0)  # stamp and count of the frames written
        if self.path is not None:
            self._create()

    def open(self, out_dir: Path, n_frames: int) -> None:
        """:class:`~dynastereo.observers.OutputObserver`: the bag created in the run's ready
        output folder."""
        self.out_dir, self.n_frames = Path(out_dir), int(n_frames)
        self.path = self.out_dir / ("output" + BAG_SUFFIX[self.fmt])
        self._create()

    def _create(self) -> None:
        self.writer = BagWriter(self.path, self.fmt, overwrite=True)
        self.b = self.writer.builder
        for k in (k for k in OUTPUT_TOPICS if self._key_on(k)):
            self.writer.add(OUTPUT_TOPICS[k], OUTPUT_TYPES[k])

    def _key_on(self, key: str) -> bool:
        group = {"left_masked": "masked", "right_masked": "masked", "left_mask": "masks", "right_mask": "masks"}
        return group.get(key, key) in self.outputs

    def on_frame(self, event: FrameEvent) -> None:
        """:class:`~dynastereo.observers.FrameObserver`: the tracked frame into the bag, at its
        stamp (the map points from ``event.system``)."""
        stamp = int(self.stamps_ns[event.frame.index])
        self._system, self._last = event.system, (stamp, event.position + 1)
        self.write(event.position, event.frame, event.masks, event.pose, stamp,
                   event.system.map_points if event.system is not None else None)

    def write(self, seq_pos: int, frame: StereoFrame, masks: StereoMasks | None, pose: np.ndarray,
              stamp_ns: int, map_points: Callable[[], np.ndarray] | None = None) -> None:
        """One frame's messages; ``map_points`` (``System.map_points``) gives the cloud
        on every ``MAP_EVERY``-th frame."""
        w, b, cf = self.writer, self.b, self.camera_frame
        T = np.vstack([np.asarray(pose, np.float64)[:3], [0.0, 0.0, 0.0, 1.0]])
        self._path[0].append(T)
        self._path[1].append(int(stamp_ns))
        if "path" in self.outputs:
            w.write(OUTPUT_TOPICS["path"], stamp_ns, b.path(*self._path, ODOM_FRAME, seq=seq_pos))
        if map_points is not None and seq_pos % MAP_EVERY == 0:
            self.write_map(map_points(), stamp_ns, seq_pos)
        prev = self._prev
        lin, ang = twist_between(prev[0] if prev else None, T, (stamp_ns - prev[1]) * 1e-9 if prev else 0.0)
        self._prev = (T, stamp_ns)
        odo = OdometryData(stamp_ns=stamp_ns, pose=T, frame_id=ODOM_FRAME, child_frame_id=cf, linear=lin,
                           angular=ang, seq=seq_pos)
        if "odometry" in self.outputs:
            w.write(OUTPUT_TOPICS["odometry"], stamp_ns, b.odometry(odo))
        if "tf" in self.outputs:
            w.write(OUTPUT_TOPICS["tf"], stamp_ns, b.tf(odo))
        shape = frame.left.shape[:2]
        ml = masks.left if masks is not None else np.zeros(shape, np.uint8)
        mr = masks.right if masks is not None else np.zeros(shape, np.uint8)
        if "masked" in self.outputs:
            w.write(OUTPUT_TOPICS["left_masked"], stamp_ns, b.image(masked_image(frame.left, ml), stamp_ns, cf,
                                                                    seq=seq_pos))
            w.write(OUTPUT_TOPICS["right_masked"], stamp_ns, b.image(masked_image(frame.right, mr), stamp_ns, cf,
                                                                     seq=seq_pos))
        if "masks" in self.outputs:
            w.write(OUTPUT_TOPICS["left_mask"], stamp_ns, b.image(ml, stamp_ns, cf, "mono8", seq=seq_pos))
            w.write(OUTPUT_TOPICS["right_mask"], stamp_ns, b.image(mr, stamp_ns, cf, "mono8", seq=seq_pos))
        if "objects" in self.outputs:
            objs = masks.objects if masks is not None else []
            self._object_paths.add(objs)
            w.write(OUTPUT_TOPICS["objects"], stamp_ns,
                    b.object_markers(objs, stamp_ns, ODOM_FRAME, seq_pos, self._object_paths.paths()))
        if "disparity" in self.outputs:
            if masks is not None and masks.disparity is not None:
                d = masks.disparity
            else:
                from ..masking import StereoMatcher

                if self._matcher is None:
                    self._matcher = StereoMatcher(self.cfg.stereo)
                d = self._matcher.compute(frame.left_gray, frame.right_gray, scale=int(self.cfg.stereo.scale))
            w.write(OUTPUT_TOPICS["disparity"], stamp_ns,
                    b.disparity(disparity_data(d, self.calibration, self.cfg), stamp_ns, cf, seq=seq_pos))

    def write_map(self, points: np.ndarray, stamp_ns: int, seq_pos: int = 0) -> None:
        if "map_points" in self.outputs:
            self.writer.write(OUTPUT_TOPICS["map_points"], stamp_ns, self.b.point_cloud(points, stamp_ns, ODOM_FRAME,
                                                                                        seq=seq_pos))

    def close(self) -> dict:
        """The final map (after the run's last bundle adjustment), then the bag closed; a
        bag run's ``DIR/bag.json`` (the pairing -- pairs, unpaired messages, tolerance --, the
        calibration source and what went into the output bag), which is returned."""
        if self.writer is None:
            return {}
        if self._system is not None and self._last[1]:
            self.write_map(self._system.map_points(), *self._last)
        self.writer.close()
        if self.source is None or self.out_dir is None:
            return {"output_bag": str(self.path), "output_topics": self.writer.counts}
        seq = self.source
        report = {"bag": str(seq.path), "format": seq.format, **seq.report.to_dict(),
                  "frames_requested": self.n_frames, "output_bag": str(self.path),
                  "output_topics": self.writer.counts}
        atomic_write_text(self.out_dir / "bag.json", json.dumps(report, indent=1))
        return report
