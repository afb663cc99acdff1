"""The sequence protocol every input format implements."""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, Protocol, runtime_checkable

import numpy as np

from ..datatypes import StereoCalibration, StereoFrame


@runtime_checkable
class Sequence(Protocol):
    """A rectified stereo sequence.

    ``frame(i)`` returns the i-th *rectified* pair (raw formats rectify on read, with
    maps computed once); images keep their colour if the source has it.
    """

    name: str
    path: Path
    calibration: StereoCalibration

    def __len__(self) -> int: ...

    def timestamps(self) -> np.ndarray: ...

    def frame(self, index: int) -> StereoFrame: ...

    def __iter__(self) -> Iterator[StereoFrame]: ...
