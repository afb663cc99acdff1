"""``dynastereo run --bag``: a stereo bag through masking + SLAM, results into a bag.

The bag is read as a :class:`~dynastereo.ros.bags.BagStereoSequence` and fed to the same
job as a sequence folder (:func:`dynastereo.api.slam_job`: trajectory files,
``timing.json``, ``run.json``), with a :class:`BagOutput` observer that writes every
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
from ..errors import InputError
from ..observers import FrameEvent
from ..datatypes import StereoFrame, StereoMasks
from .bags import BAG_SUFFIX, BagStereoSequence, BagWriter
from .convert import masked_image, twist_between
from .core import disparity_data
from .messages import (DEFAULT_LEFT_TOPIC, DEFAULT_RIGHT_TOPIC, MAP_EVERY, ODOM_FRAME, OUTPUT_TOPICS, OUTPUT_TYPES,
                       OdometryData)

ALL_OUTPUTS = ("odometry", "tf", "masked", "masks", "disparity", "path", "map_points", "objects")


def parse_outputs(spec: str | list[str] | tuple[str, ...] | None) -> tuple[str, ...]:
    """``"all"`` / None -> every output; else a comma list of odometry, tf, masked, masks, disparity,
    path, map_points, objects."""
    if spec is None:
        return ALL_OUTPUTS
    items = [s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec) if s.strip()]
    if items == ["all"]:
        return ALL_OUTPUTS
    bad = [s for s in items if s not in ALL_OUTPUTS]
    if bad:
        raise InputError(f"unknown bag output(s) {', '.join(bad)}; choose from {', '.join(ALL_OUTPUTS)} or 'all'")
    return tuple(items)


class BagOutput:
    """Writes the per-frame results into the output bag."""

    def __init__(self, path: Path, fmt: str, cfg: Config, calibration, camera_frame: str,
                 outputs: tuple[str, ...] = ALL_OUTPUTS, stamps_ns: np.ndarray | None = None) -> None:
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
        from ..slam.objects import ObjectPaths

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


@dataclass
class BagRunResult:
    out: Path
    output_bag: Path
    slam: Any  # pipeline.SlamJobResult
    report: dict[str, Any]  # pairing + output counts (bag.json)


def run_bag(
    bag: str | Path,
    out: str | Path,
    cfg: Config | None = None,
    *,
    left_topic: str = DEFAULT_LEFT_TOPIC,
    right_topic: str = DEFAULT_RIGHT_TOPIC,
    left_info: str | None = "auto",
    right_info: str | None = "auto",
    calib: str | Path | None = None,
    fallback_calib: str | Path | None = None,
    tolerance_s: float = 0.005,
    rectify: str = "auto",
    frames: str | int | None = None,
    models_dir: str | Path | None = None,
    save_masks: bool = False,
    outputs: str | tuple[str, ...] | None = None,
    progress: Callable[[int, int, dict], None] | None = None,
    overwrite: bool = True,
    stereo_check: bool = True,
    observers: tuple = (),
    save_cloud: str | Path | None = None,
) -> BagRunResult:
    """Run masking + SLAM on a stereo bag (module doc); see :class:`BagStereoSequence` for
    the topic, calibration and pairing arguments (``fallback_calib``: used only when the bag
    has no CameraInfo, e.g. the ORB-SLAM2 settings file given as ``--config``); ``stereo_check``:
    refuse identical / swapped / unrectified pairs (``io.stereo_check``); ``overwrite``: clear
    an earlier run in ``out`` (False: refuse it; ``io.outputs.prepare_output_dir``)."""
    from ..api import slam_job
    from ..io.frames import parse_frame_spec

    cfg = cfg or Config()
    outs = parse_outputs(outputs)
    out = Path(out)
    seq = BagStereoSequence(bag, left_topic, right_topic, left_info, right_info, calib, tolerance_s, rectify,
                            fallback_calib=fallback_calib)
    try:
        indices = parse_frame_spec(frames, len(seq))
        out_bag = out / ("output" + BAG_SUFFIX[seq.format])
        writers: list[BagOutput] = []

        def open_writer() -> tuple[BagOutput]:  # once the output folder is checked and ready
            writers.append(BagOutput(out_bag, seq.format, cfg, seq.calibration, seq.frame_id, outs,
                                     stamps_ns=seq.stamps_ns))
            return (writers[0],)

        try:  # a bag has no synthetic ground truth: detector 'oracle' is refused by the masker factory
            res = slam_job(seq, out, cfg, frames=frames, models_dir=models_dir, observers=observers,
                           open_observers=open_writer, save_masks=save_masks, progress=progress,
                           overwrite=overwrite, stereo_check=stereo_check, save_cloud=save_cloud)
        finally:
            for w in writers:
                w.close()
        writer = writers[0]
        report = {"bag": str(Path(bag)), "format": seq.format, **seq.report.to_dict(),
                  "frames_requested": len(indices), "output_bag": str(out_bag), "output_topics": writer.writer.counts}
        (out / "bag.json").write_text(json.dumps(report, indent=1))
        return BagRunResult(out, out_bag, res, report)
    finally:
        seq.close()
