"""The one place a job is assembled and run: :func:`run` (a :class:`~dynastereo.runtime.spec.JobSpec` in, a result out).

Assembly, in this order (each check before the first frame, the output folder last, so
an earlier run there is cleared only once every input and option proved good):

1. the source (:func:`~dynastereo.runtime.sources.open_sequence_source`), the ground
   truth (read once: a bad ``--gt`` fails here), the map, cloud and recording files writable
   and none of them an input;
2. the frames; the stereo pair (``io.stereo_check``);
3. the masker (:func:`~dynastereo.runtime.assembly.assemble_stages`, which verifies the model), its
   detector's first (slow, lazily initialized) inference made on a black frame;
4. the SLAM system (its vocabulary, optionally a saved map: both read and checked here), the
   motion test and the objects' world tracker (:func:`~dynastereo.runtime.assembly.assemble_stages`,
   the one assembly jobs and nodes share);
5. the output folder: locked against a second job (``io.outputs.OutputLock``), then
   prepared (``io.outputs.prepare_output_dir``: an earlier run's files cleared);
6. the sinks and observers (a bag's writer, the viewer, the periodic stereo check).

Then the frame loop (:class:`~dynastereo.runtime.loop.FrameLoop`) and the job's last files
(:mod:`dynastereo.runtime.finish`): whatever happens, they say how the job ended.

The masking and SLAM packages (onnxruntime, numba: about a second to load), the rerun viewer,
the report (matplotlib) and the bag writer (rosbags) are imported where a job needs them:
``import dynastereo.api`` and ``dynastereo --help`` do not pay for them.  No import here is
inside a function to dodge a cycle (``tests/test_imports.py``).
"""

from __future__ import annotations

import logging
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import as_interrupt
from ..io.base import Sequence
from ..io.frames import select_frames
from ..io.outputs import OutputLock, check_output_file, prepare_output_dir, refuse_input_as_output
from ..io.stereo_check import PeriodicStereoCheck, check_sequence
from ..observers import FrameObserver, OutputObserver
from . import finish
from .assembly import assemble_stages
from .loop import FrameLoop, Progress
from .processor import FrameProcessor
from .results import JobResult, new_mask_timer, new_run_timer
from .sinks import (DisparitySink, MaskSink, MeshSink, ObjectsLogSink, ObserverSink, OverlaySink, Sink, TracksSink,
                    TrajectorySink)
from .sources import SequenceSource, open_sequence_source
from .spec import JobKind, JobSpec


@dataclass
class Job:
    """A job's parts, once assembled (:func:`assemble`)."""

    spec: JobSpec
    sequence: Sequence
    frames: list[int]
    processor: FrameProcessor
    sinks: list[Sink] = field(default_factory=list)
    observers: tuple[FrameObserver, ...] = ()
    map_info: dict = field(default_factory=dict)
    ground_truth: Path | None = None  # what the report and run.json name
    lock: OutputLock | None = None  # the output folder's, held until the job ends
    mesh_recorder: Any = None  # mesh.KeyframeRecorder (--save-mesh / --save-dense-cloud)
    mesh_info: dict = field(default_factory=dict)  # run.json's "mesh"


def run(spec: JobSpec, *, progress: Progress | None = None, observers: tuple[FrameObserver, ...] = (),
        masker: Any = None) -> JobResult:
    """Run the job ``spec`` describes (module doc).  ``progress(done, total, record)`` after
    each frame; ``observers`` get a :class:`~dynastereo.observers.FrameEvent` per frame;
    ``masker``: a ready :class:`~dynastereo.masking.base.Masker` instead of the one the
    configuration builds (e.g. ground-truth masks in a benchmark)."""
    seq = open_sequence_source(spec.source)
    from .spec import settings_disagreement

    warning = settings_disagreement(spec.settings, getattr(seq, "calibration", None),
                                    getattr(seq, "calibration_file", None))
    if warning:
        logging.getLogger("dynastereo.runtime").warning("%s", warning)
    job: Job | None = None
    try:
        gt = _ground_truth(spec, seq)
        _check_output_files(spec, gt)
        with ExitStack() as stack:
            obs = stack.enter_context(_viewers(spec, observers, gt))
            job = assemble(spec, seq, obs, masker)
            job.ground_truth = gt
            stack.callback(_close_sinks, job)
            result = execute(job, progress)
        return _after(spec, job, result, gt)
    finally:
        if job is not None and job.lock is not None:  # held to the end: the report is written under it too
            job.lock.release()
        if spec.source.sequence is None and hasattr(seq, "close"):  # what the runtime opened, it closes
            seq.close()


def _ground_truth(spec: JobSpec, seq: Sequence) -> Path | None:
    """A run's ground truth for the viewer and the report: ``--gt``, else the sequence's own
    (a bag has none: ``--gt`` only); None for a mask job."""
    if spec.kind is not JobKind.RUN:
        return None
    gt = finish.resolve_ground_truth(spec.gt, seq)
    if gt is not None:
        gt = finish.checked_ground_truth(gt, explicit=spec.gt is not None)
    return gt


def _check_output_files(spec: JobSpec, gt: Path | None) -> None:
    """The single output files (map, cloud, recording) writable, and none of them an input."""
    o = spec.outputs
    inputs = (spec.source.name, spec.source.calib, spec.load_map, gt, spec.config.slam.vocabulary or None)
    for path, what, flag in ((o.save_map, "map file", "--save-map"), (o.save_cloud, "point cloud file", "--save-cloud"),
                             (o.save_mesh, "mesh file", "--save-mesh"),
                             (o.save_dense_cloud, "dense cloud file", "--save-dense-cloud"), (o.rrd, "recording", "--rrd")):
        if path is not None:
            refuse_input_as_output(path, [i for i in inputs if i != spec.load_map or flag != "--save-map"],
                                   what=what, flag=flag, folders=[spec.source.name], own=o.dir)
            check_output_file(path, what=f"{what} ({flag})")
    if spec.source.name is not None and Path(spec.source.name).is_dir():
        refuse_input_as_output(o.dir, [spec.source.name], what="output folder", flag="--out")


def _viewers(spec: JobSpec, observers: tuple[FrameObserver, ...], gt: Path | None):
    from ..viz.viewers import viewers

    name = {JobKind.MASK: "dynastereo mask", JobKind.RUN: "dynastereo run"}[spec.kind]
    name += f" --{spec.source.opener.kind}" if spec.source.opener is not None else ""
    positions = None
    if gt is not None and (spec.outputs.viewer or spec.outputs.rrd is not None):
        from ..eval.trajectory import read_trajectory

        positions = read_trajectory(gt, name="ground truth").positions
    return viewers(observers, viewer=spec.outputs.viewer, rrd=spec.outputs.rrd, gt=positions, name=name)


def _checked_frames(spec: JobSpec, seq: Sequence, masker: Any = None) -> tuple[list[int], Any]:
    """(frame indices, masker), after the checks made before the first frame (module doc)."""
    indices = select_frames(spec.frames, seq)
    if spec.stereo_check:
        check_sequence(seq, indices)
    # synthetic ground truth (detector 'oracle') is a sequence folder's; a file (a bag, a
    # video) has none: the oracle is refused by the masker factory
    path = getattr(seq, "path", None)
    truth = path if path is not None and Path(path).is_dir() else None
    if masker is None:
        masker = assemble_stages(spec.config, seq.calibration, slam=False, models_dir=spec.models_dir,
                                 ground_truth=truth).masker
    c = getattr(seq, "calibration", None)
    if hasattr(masker, "warm_up") and c is not None:  # not in the frame loop: its FPS, a camera's first frames
        masker.warm_up(c.height, c.width)
    return indices, masker


def _prepare_output(spec: JobSpec, system: Any) -> OutputLock:
    """The output folder locked and prepared (module doc: step 5); the SLAM system shut
    down (and the lock let go) when that fails."""
    lock = OutputLock(spec.outputs.dir)
    try:
        lock.acquire()
        prepare_output_dir(spec.outputs.dir, overwrite=spec.outputs.overwrite)
    except BaseException:
        lock.release()
        if system is not None:
            system.shutdown()
        raise
    return lock


def assemble(spec: JobSpec, seq: Sequence, observers: tuple[FrameObserver, ...], masker: Any = None) -> Job:
    """The job's parts (module doc: steps 2-6)."""
    indices, masker = _checked_frames(spec, seq, masker)
    source = SequenceSource(seq, indices)
    if spec.stereo_check:
        observers = (*observers, PeriodicStereoCheck(getattr(seq, "path", None)))
    if spec.kind is JobKind.MASK:
        lock = _prepare_output(spec, None)
        return Job(spec, seq, indices, FrameProcessor(source, masker), observers=observers, lock=lock)
    st = assemble_stages(spec.config, getattr(seq, "calibration", None), masker=masker, load_map=spec.load_map,
                         localize_only=spec.localize_only)
    lock = _prepare_output(spec, st.system)
    proc = FrameProcessor(source, st.masker, system=st.system, motion=st.motion, world=st.world)
    return Job(spec, seq, indices, proc, observers=observers, map_info=st.map_info, lock=lock)


def open_outputs(job: Job) -> None:
    """A run's first files: run.json (room reserved), then the sinks' files and the files of
    the source's own observers (a bag's output bag: ``OpenableSource.job_observers``),
    and every :class:`~dynastereo.observers.OutputObserver` opened.  A failure here (a file
    that cannot be written) ends the job like any other: its run.json says so."""
    spec, proc = job.spec, job.processor
    finish.reserve_run_json(spec.outputs.dir, spec, len(job.frames))
    _open_run_sinks(job.sinks, spec, proc.masker, proc.world)
    if spec.outputs.mesh_wanted:
        from ..mesh import KeyframeRecorder

        job.mesh_recorder = KeyframeRecorder()
        job.sinks.append(MeshSink(job.mesh_recorder))
    if spec.source.opener is not None:
        job.observers = (*job.observers, *spec.source.opener.job_observers(spec, job.sequence))
    for ob in job.observers:
        if isinstance(ob, OutputObserver):
            ob.open(spec.outputs.dir, len(job.frames))


def _mask_sinks(spec: JobSpec, masker: Any) -> list[Sink]:
    o, out = spec.outputs, spec.outputs.dir
    sinks: list[Sink] = [MaskSink(out)]
    if o.save_disparity:
        sinks.append(DisparitySink(out, getattr(masker, "name", type(masker).__name__)))
    if o.overlays:
        sinks.append(OverlaySink(out))
    sinks.append(ObjectsLogSink(out))
    return sinks


def _open_run_sinks(sinks: list[Sink], spec: JobSpec, masker: Any, world: Any) -> None:
    """Into ``sinks`` one by one (those opened are closed if a later one fails)."""
    out = spec.outputs.dir
    if world is not None:
        sinks.append(TracksSink(out))
    sinks.append(TrajectorySink(out))
    if spec.outputs.save_masks:
        sinks.append(MaskSink(out))
    if masker is not None:
        sinks.append(ObjectsLogSink(out))


def _close_sinks(job: Job) -> None:
    for s in job.sinks:
        s.close()
    job.sinks = []


def execute(job: Job, progress: Progress | None) -> JobResult:
    """The frame loop over the job, then its last files (whatever happened)."""
    spec = job.spec
    run_job = spec.kind is JobKind.RUN
    timer = new_run_timer() if run_job else new_mask_timer()
    if job.processor.system is not None:  # start-up, not the frame loop (its FPS, a camera's first frames)
        job.processor.system.wait_ready()
    observers = ObserverSink(job.observers, job.processor.system, job.sequence.calibration)
    loop = FrameLoop(job.processor, timer, observers=observers, pipelined=run_job and spec.prefetch,
                     progress=progress, total=len(job.frames))
    error: str | None = None
    try:
        if run_job:
            open_outputs(job)
        else:
            job.sinks = _mask_sinks(spec, job.processor.masker)
        loop.sinks, observers.observers = job.sinks, job.observers  # the same list: sinks opened so far
        loop.run()
    except BaseException as exc:
        e = as_interrupt(exc)
        error = f"{type(e).__name__}: {e}"
        if e is not exc:
            raise e from None
        raise
    finally:
        for s in job.sinks:  # every row file holds the frames done, no more
            s.truncate(loop.state.n_done)
        _close_sinks(job)
        if run_job:
            result = finish.finish_run(job, loop, error)
        else:
            result = finish.finish_mask(job, loop, error)
    return result


def _after(spec: JobSpec, job: Job, result: JobResult, gt: Path | None) -> JobResult:
    """The report, once the job's files are written."""
    if spec.outputs.report:
        from ..eval.html_report import build_report

        result.report = build_report(spec.outputs.dir, gt, None)
    return result
