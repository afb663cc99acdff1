"""The one place a job is assembled and run: :func:`run` (a :class:`~dynastereo.runtime.spec.JobSpec` in, a result out).

Assembly, in this order (each check before the first frame, the output folder last, so
an earlier run there is cleared only once the inputs proved good):

1. the source (:func:`~dynastereo.runtime.sources.open_sequence_source`);
2. the map and cloud files writable; the frames; the stereo pair (``io.stereo_check``);
3. the masker (:func:`dynastereo.masking.build_masker`, which verifies the model), its
   detector's first (slow, lazily initialized) inference made on a black frame;
4. the output folder (``io.outputs.prepare_output_dir``);
5. the SLAM system (optionally from a saved map), the motion test, the objects' world tracker;
6. the sinks and observers (a bag's writer, the viewer, the periodic stereo check).

Then the frame loop (:class:`~dynastereo.runtime.loop.FrameLoop`) and the job's last files
(:mod:`dynastereo.runtime.finish`): whatever happens, they say how the job ended.

The masking and SLAM packages (onnxruntime, numba: about a second to load), the rerun viewer,
the report (matplotlib) and the bag writer (rosbags) are imported where a job needs them:
``import dynastereo.api`` and ``dynastereo --help`` do not pay for them.  No import here is
inside a function to dodge a cycle (``tests/test_imports.py``).
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import as_interrupt
from ..io.base import Sequence
from ..io.frames import select_frames
from ..io.outputs import check_output_file, prepare_output_dir
from ..io.stereo_check import PeriodicStereoCheck, check_sequence
from ..observers import FrameObserver
from . import finish
from .loop import FrameLoop, Progress
from .processor import FrameProcessor
from .results import BagRunResult, MaskJobResult, SlamJobResult, new_mask_timer, new_run_timer
from .sinks import (DisparitySink, MaskSink, MeshSink, ObjectsLogSink, ObserverSink, OverlaySink, Sink, TracksSink,
                    TrajectorySink)
from .sources import SequenceSource, open_sequence_source
from .spec import JobKind, JobSpec

if TYPE_CHECKING:
    from ..config import Config


@dataclass
class Job:
    """A job's parts, once assembled (:func:`assemble`)."""

    spec: JobSpec
    sequence: Sequence
    frames: list[int]
    processor: FrameProcessor
    sinks: list[Sink] = field(default_factory=list)
    observers: tuple[FrameObserver, ...] = ()
    bag_output: Any = None  # ros.bagrun.BagOutput
    map_info: dict = field(default_factory=dict)
    mesh_recorder: Any = None  # mesh.KeyframeRecorder (--save-mesh / --save-dense-cloud)
    mesh_info: dict = field(default_factory=dict)  # run.json's "mesh"


def run(spec: JobSpec, *, progress: Progress | None = None, observers: tuple[FrameObserver, ...] = (),
        masker: Any = None) -> MaskJobResult | SlamJobResult | BagRunResult:
    """Run the job ``spec`` describes (module doc).  ``progress(done, total, record)`` after
    each frame; ``observers`` get a :class:`~dynastereo.observers.FrameEvent` per frame;
    ``masker``: a ready :class:`~dynastereo.masking.base.Masker` instead of the one the
    configuration builds (e.g. ground-truth masks in a benchmark)."""
    seq = open_sequence_source(spec.source)
    try:
        gt = _ground_truth(spec, seq)
        with ExitStack() as stack:
            obs = stack.enter_context(_viewers(spec, observers, gt))
            job = assemble(spec, seq, obs, masker)
            stack.callback(_close_sinks, job)
            result = execute(job, progress)
        return _after(spec, job, result, gt)
    finally:
        if spec.source.bag is not None:
            seq.close()


def _ground_truth(spec: JobSpec, seq: Sequence) -> Path | None:
    """A run's ground truth for the viewer and the report: ``--gt``, else the sequence's own
    (a bag: ``--gt`` only); None for a mask job."""
    if spec.kind is not JobKind.RUN:
        return None
    return spec.gt if spec.source.bag is not None else finish.resolve_ground_truth(spec.gt, seq)


def _viewers(spec: JobSpec, observers: tuple[FrameObserver, ...], gt: Path | None):
    from ..viz.viewers import viewers

    name = {JobKind.MASK: "dynastereo mask", JobKind.RUN: "dynastereo run"}[spec.kind]
    name += " --bag" if spec.source.bag is not None else ""
    return viewers(observers, viewer=spec.outputs.viewer, rrd=spec.outputs.rrd, gt=gt, name=name)


def _checked_frames(spec: JobSpec, seq: Sequence, masker: Any = None) -> tuple[list[int], Any]:
    """(frame indices, masker), after the checks made before the first frame (module doc)."""
    from ..masking import build_masker

    o = spec.outputs
    if o.save_map is not None:
        check_output_file(o.save_map, what="map file")
    if o.save_cloud is not None:
        check_output_file(o.save_cloud, what="point cloud file")
    if o.save_mesh is not None:
        check_output_file(o.save_mesh, what="mesh file")
    if o.save_dense_cloud is not None:
        check_output_file(o.save_dense_cloud, what="dense cloud file")
    indices = select_frames(spec.frames, seq)
    if spec.stereo_check:
        check_sequence(seq, indices)
    # a bag has no synthetic ground truth: detector 'oracle' is refused by the masker factory
    truth = None if spec.source.bag is not None else getattr(seq, "path", None)
    if masker is None:
        masker = build_masker(spec.config, seq.calibration, models_dir=spec.models_dir, ground_truth=truth)
    c = getattr(seq, "calibration", None)
    if hasattr(masker, "warm_up") and c is not None:  # not in the frame loop: its FPS, a camera's first frames
        masker.warm_up(c.height, c.width)
    prepare_output_dir(o.dir, overwrite=o.overwrite)
    return indices, masker


def assemble(spec: JobSpec, seq: Sequence, observers: tuple[FrameObserver, ...], masker: Any = None) -> Job:
    """The job's parts (module doc: steps 2-6)."""
    indices, masker = _checked_frames(spec, seq, masker)
    source = SequenceSource(seq, indices)
    if spec.stereo_check:
        observers = (*observers, PeriodicStereoCheck(getattr(seq, "path", None)))
    if spec.kind is JobKind.MASK:
        return Job(spec, seq, indices, FrameProcessor(source, masker), observers=observers)
    system, info = _slam_system(spec, seq)
    from ..masking.motion import build_motion

    motion = build_motion(spec.config, seq.calibration, masker)
    world = _world_objects(seq, masker, spec.config)
    return Job(spec, seq, indices, FrameProcessor(source, masker, system=system, motion=motion, world=world),
               observers=observers, map_info=info)


def open_outputs(job: Job) -> None:
    """A run's first files: run.json (room reserved), then the sinks' files and a bag's
    output bag.  A failure here (a file that cannot be written) ends the job like any
    other: its run.json says so."""
    spec, proc = job.spec, job.processor
    finish.reserve_run_json(spec.outputs.dir, spec, len(job.frames))
    _open_run_sinks(job.sinks, spec, proc.masker, proc.world)
    if spec.outputs.mesh_wanted:
        from ..mesh import KeyframeRecorder

        job.mesh_recorder = KeyframeRecorder()
        job.sinks.append(MeshSink(job.mesh_recorder))
    if spec.source.bag is not None:
        from ..ros.bagrun import open_bag_output

        job.bag_output = open_bag_output(spec, job.sequence)
        job.observers = (*job.observers, job.bag_output)


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


def _slam_system(spec: JobSpec, seq: Sequence) -> tuple[Any, dict]:
    """The SLAM system for ``seq`` (from ``spec.load_map`` when given) and run.json's ``map`` entry."""
    from ..slam import System

    system = System(spec.config, seq.calibration)
    if spec.load_map is None:
        return system, {}
    try:
        system.load_map(spec.load_map, localize_only=spec.localize_only)
    except BaseException:
        system.shutdown()
        raise
    return system, {"loaded": str(spec.load_map), "localize_only": bool(spec.localize_only)}


def _world_objects(seq: Sequence, masker: Any, cfg: Config) -> Any:
    """The objects' world tracker of a masked run (slam.objects), or None."""
    if masker is None or getattr(seq, "calibration", None) is None:
        return None
    from ..slam.objects import WorldObjects

    return WorldObjects.from_config(seq.calibration, cfg)


def _close_sinks(job: Job) -> None:
    for s in job.sinks:
        s.close()
    job.sinks = []


def execute(job: Job, progress: Progress | None) -> MaskJobResult | SlamJobResult:
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


def _after(spec: JobSpec, job: Job, result: Any, gt: Path | None) -> Any:
    """The report and a bag run's bag.json, once the job's files are written."""
    if spec.outputs.report:
        from ..eval.html_report import build_report

        result.report = build_report(spec.outputs.dir, gt, None)
    if job.bag_output is None:
        return result
    report = finish.write_bag_json(spec, job)
    result.bag = report
    return BagRunResult(spec.outputs.dir, job.bag_output.path, result, report)
