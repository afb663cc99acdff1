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
class MaskJobResult:
    out: Path
    frames_done: list[int] = field(default_factory=list)
    timer: StageTimer = field(default_factory=new_mask_timer)
    error: str | None = None
    wall_s: float = 0.0

    @property
    def summary(self) -> dict[str, dict[str, float]]:
        return self.timer.summary()


@dataclass
class SlamJobResult:
    out: Path
    poses: np.ndarray  # (N, 3, 4) camera-to-world, one per frame fed
    frames: list[int]
    stats: dict
    timer: StageTimer
    wall_s: float
    fps: float
    lost: list[int] = field(default_factory=list)  # positions (in the order fed) of lost frames
    report: Path | None = None  # the HTML report, when one was asked for
    bag: dict[str, Any] | None = None  # a bag run: pairing and output counts (bag.json)
    mesh: dict[str, Any] | None = None  # --save-mesh / --save-dense-cloud: run.json's "mesh"

    @property
    def summary(self) -> dict[str, dict[str, float]]:
        return self.timer.summary()


@dataclass
class BagRunResult:
    out: Path
    output_bag: Path
    slam: SlamJobResult
    report: dict[str, Any]  # pairing + output counts (bag.json)
