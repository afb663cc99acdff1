"""One runtime for every job: a :class:`JobSpec` in, one frame loop, sinks out.

* :mod:`.spec` -- :class:`JobSpec` (source, configuration, outputs, options), validated once;
* :mod:`.sources` -- where frames come from: any sequence (folders, videos, cameras, and
  sources that open themselves, as a ROS bag: :class:`~dynastereo.runtime.spec.OpenableSource`)
  and the live node's input queue;
* :mod:`.processor` -- :class:`FrameProcessor`: read -> mask -> motion -> track, one frame;
* :mod:`.pipelining` -- the masking stage beside the tracking stage, on two threads;
* :mod:`.loop` -- :class:`FrameLoop`: **the frame loop**, the one every job runs;
* :mod:`.sinks` -- what is written per frame; :mod:`.finish` -- the job's last files;
* :mod:`.assembly` -- the one assembly of masker, SLAM, motion test and world objects;
* :mod:`.job` -- :func:`run`: the one place a job is assembled; a :class:`JobResult` out.

The runtime imports nothing of ``ros``: a bag run's source and its output-bag observer
come from :class:`dynastereo.ros.bagrun.BagSource`, handed in like any other source.

``dynastereo mask`` / ``run`` (folder, video, camera, bag), the Python API, ``bench`` and
``demo`` call :func:`run`; the live ROS node runs the same :class:`FrameLoop` over a
:class:`~dynastereo.runtime.sources.LiveSource`.
"""

from __future__ import annotations

from .job import run
from .results import JobResult, MaskJobResult, SlamJobResult
from .spec import JobKind, JobSpec, OpenableSource, OutputSpec, SourceSpec

__all__ = ["JobKind", "JobResult", "JobSpec", "MaskJobResult", "OpenableSource", "OutputSpec", "SlamJobResult",
           "SourceSpec", "run"]
