"""The one assembly of a job's stages: :func:`assemble_stages`.

A configuration and a calibration in; the masker, the SLAM system, the motion test and the
objects' world tracker out.  Every job (:func:`dynastereo.runtime.job.assemble`) and every
live node (ROS 1's and ROS 2's :class:`~dynastereo.ros.core.StereoNodeCore`) builds its
stages here, so that a run and a node given the same frames make the same poses and
objects; ``System(...)`` is constructed nowhere else in ``src/``
(``tests/test_architecture.py`` checks it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..config import Config
    from ..datatypes import StereoCalibration


@dataclass
class Stages:
    """A job's stages (:class:`~dynastereo.runtime.processor.FrameProcessor` takes them)."""

    masker: Any
    system: Any = None  # slam.System; None: no SLAM (a mask job, or slam=False)
    motion: Any = None  # objects.motion.ObjectMotion; None: every detection masked
    world: Any = None  # objects.world.WorldObjects; None without a masker or a calibration
    map_info: dict = field(default_factory=dict)  # run.json's "map" entry (a loaded map)


def assemble_stages(cfg: Config, calibration: StereoCalibration | None, *, masker: Any = None, slam: bool = True,
                    models_dir: str | Path | None = None, detector: Any = None, ground_truth: str | Path | None = None,
                    load_map: str | Path | None = None, localize_only: bool = False) -> Stages:
    """The stages for ``cfg`` and the rectified rig ``calibration`` (module doc).

    ``masker``: a ready masker to use (else built by :func:`dynastereo.masking.build_masker`
    with ``models_dir``, ``detector`` -- a ready network -- and ``ground_truth`` -- a synthetic
    sequence's folder for detector ``oracle``).  ``slam=False``: the masker only (a mask job,
    the checks before a job's first frame, a node's live parameter change).  ``load_map``: the
    SLAM starts from a saved map (``localize_only``: it is not extended); the system is shut
    down if loading fails.
    """
    if masker is None:
        from ..masking import build_masker

        masker = build_masker(cfg, calibration, models_dir=models_dir, detector=detector, ground_truth=ground_truth)
    if not slam:
        return Stages(masker)
    from ..objects.motion import build_motion
    from ..slam import System

    system = System(cfg, calibration)
    info: dict = {}
    if load_map is not None:
        try:
            system.load_map(load_map, localize_only=localize_only)
        except BaseException:
            system.shutdown()
            raise
        info = {"loaded": str(load_map), "localize_only": bool(localize_only)}
    motion = build_motion(cfg, calibration, masker)
    world = None
    if masker is not None and calibration is not None:
        from ..objects.world import WorldObjects

        world = WorldObjects.from_config(calibration, cfg)
    return Stages(masker, system, motion, world, info)
