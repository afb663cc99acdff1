"""One runtime for every job: a :class:`JobSpec` in, one frame loop, sinks out.

* :mod:`.spec` -- :class:`JobSpec` (source, configuration, outputs, options), validated once;
* :mod:`.sources` -- where frames come from: any sequence (folders, videos, cameras, bags)
  and the live node's input queue;
* :mod:`.processor` -- :class:`FrameProcessor`: read -> mask -> motion -> track, one frame;
* :mod:`.pipelining` -- the masking stage beside the tracking stage, on two threads;
* :mod:`.loop` -- :class:`FrameLoop`: **the frame loop**, the one every job runs;
* :mod:`.sinks` -- what is written per frame; :mod:`.finish` -- the job's last files;
* :mod:`.job` -- :func:`run`: the one place a job is assembled.

``dynastereo mask`` / ``run`` (folder, video, camera, bag), the Python API, ``bench`` and
``demo`` call :func:`run`; the live ROS node runs the same :class:`FrameLoop` over a
:class:`~dynastereo.runtime.sources.LiveSource`.
"""

from __future__ import annotations

from .job import run
from .results import BagRunResult, MaskJobResult, SlamJobResult
from .spec import BagSpec, JobKind, JobSpec, OutputSpec, SourceSpec

__all__ = ["BagRunResult", "BagSpec", "JobKind", "JobSpec", "MaskJobResult", "OutputSpec", "SlamJobResult",
           "SourceSpec", "run"]
