"""``dynastereo run --bag``: what a bag run writes into its output bag.

The bag is read as a :class:`~dynastereo.ros.bags.BagStereoSequence` and fed to the same
job as a sequence folder (:func:`dynastereo.runtime.run`: trajectory files,
``timing.json``, ``run.json``), with a :class:`BagOutput` observer that writes every
tracked frame to ``DIR/output.{bag,db3,mcap}`` (the input's format): odometry, TF, the
masked images, the masks, the disparity, the path so far and (every ``MAP_EVERY``-th frame
and once more after the final bundle adjustment) the map points (topics in
:mod:`dynastereo.ros.messages`).
``DIR/bag.json`` records the pairing (pairs, unpaired left/right messages, tolerance),
the calibration source and what was written.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..config import Config
from ..datatypes import StereoFrame, StereoMasks
from ..observers import FrameEvent
from ..runtime.spec import BAG_OUTPUTS
from .bags import BAG_SUFFIX, BagStereoSequence, BagWriter
from .convert import masked_image, twist_between
from .core import disparity_data
from .messages import MAP_EVERY, ODOM_FRAME, OUTPUT_TOPICS, OUTPUT_TYPES, OdometryData

class BagOutput:
    """Writes the per-frame results into the output bag."""

    def __init__(self, path: Path, fmt: str, cfg: Config, calibration, camera_frame: str,
                 outputs: tuple[str, ...] = BAG_OUTPUTS, stamps_ns: np.ndarray | None = None) -> None:
        self.path = Path(path)
        self.stamps_ns = stamps_ns  # per sequence index, for on_frame
        self.writer = BagWriter(path, fmt, overwrite=True)
        self.b = self.writer.builder
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
        keys = [k for k in OUTPUT_TOPICS if self._key_on(k)]
        for k in keys:
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

    def close(self) -> None:
        """The final map (after the run's last bundle adjustment), then the bag closed."""
        if self._system is not None and self._last[1]:
            self.write_map(self._system.map_points(), *self._last)
        self.writer.close()


def open_bag_output(spec, seq: BagStereoSequence) -> BagOutput:
    """The writer of a bag run's ``DIR/output.<the input's format>`` (``spec``: its
    :class:`~dynastereo.runtime.spec.JobSpec`), opened once the output folder is ready."""
    path = spec.outputs.dir / ("output" + BAG_SUFFIX[seq.format])
    return BagOutput(path, seq.format, spec.config, seq.calibration, seq.frame_id, spec.source.bag.outputs,
                     stamps_ns=seq.stamps_ns)
