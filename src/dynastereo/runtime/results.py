"""What a job returns (:func:`dynastereo.runtime.run`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..masking.maskers import MASK_STAGES
from ..timing import StageTimer


def new_mask_timer() -> StageTimer:
    """The timer of a mask job: ``mask`` = every masking stage but the detector."""
    t = StageTimer()
    t.add_derived("mask", MASK_STAGES)
    return t


def new_run_timer() -> StageTimer:
    """The timer of a SLAM run: ``masking`` = the detector and every masking stage."""
    t = StageTimer()
    t.add_derived("masking", ("detect",) + MASK_STAGES)
    return t


@dataclass
class JobResult:
    """What every job returns (:func:`dynastereo.runtime.run`): a mask job, a run, a bag run.

    ``frames``: the frames done, in the order fed.  A run (SLAM) also has ``poses`` (N, 3, 4)
    camera-to-world, the final ones, one per frame done), ``stats``, ``fps``, ``lost``
    (positions of the lost frames), ``report`` (the HTML report, when asked for) and
    ``outputs``: what the source's own observers wrote (a bag run: ``outputs["bag"]``, the
    pairing and the output bag's counts, as in ``bag.json``)."""

    out: Path
    frames: list[int]
    timer: StageTimer
    wall_s: float = 0.0
    fps: float = 0.0
    error: str | None = None
    poses: np.ndarray | None = None
    stats: dict = field(default_factory=dict)
    lost: list[int] = field(default_factory=list)
    report: Path | None = None
    outputs: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def summary(self) -> dict[str, dict[str, float]]:
        return self.timer.summary()

    @property
    def frames_done(self) -> list[int]:
        """The frames done (``frames``)."""
        return self.frames

    @property
    def bag(self) -> dict[str, Any] | None:
        """A bag run's ``bag.json`` (``outputs["bag"]``); None for other sources."""
        return self.outputs.get("bag")

    @property
    def output_bag(self) -> Path | None:
        """A bag run's output bag (``DIR/output.<fmt>``); None for other sources."""
        b = self.bag
        return Path(b["output_bag"]) if b and "output_bag" in b else None

    @property
    def moving_objects(self) -> list[int]:
        """The track ids of the objects judged moving (``objects_tracks.csv``;
        :func:`dynastereo.objects.world.moving_tracks`, the report's count); [] without tracks."""
        from ..objects.world import TRACKS_NAME, moving_tracks, read_tracks

        path = Path(self.out) / TRACKS_NAME
        if not path.is_file():
            return []
        return sorted(moving_tracks(read_tracks(path)))


#: The names a mask job's and a run's result had before they were one type.
MaskJobResult = SlamJobResult = JobResult
