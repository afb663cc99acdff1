"""High-level Python API: the same jobs the CLI runs.

```python
from dynastereo.api import mask_sequence
result = mask_sequence("KITTI/sequences/06", "out/", frames="0-9")
result.summary["mask"]["median"]
```

Each function builds a :class:`~dynastereo.runtime.JobSpec` and runs it with
:func:`dynastereo.runtime.run`, the one place a job is assembled (the CLI does the same).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from .config import Config
from .io import open_sequence
from .io.base import Sequence
from .io.frames import select_frames
from .io.outputs import check_output_file
from .observers import FrameObserver
from .runtime import JobKind, JobResult, JobSpec, OutputSpec, SourceSpec
from .runtime import run as run_job
from .runtime.finish import resolve_ground_truth  # noqa: F401 -- part of the API (re-exported)
from .runtime.spec import settings_calibration
from .viz.viewers import viewers  # noqa: F401 -- part of the API


def load_sequence(sequence: str | Path | Sequence, calib: str | Path | None = None,
                  color: bool | None = None, rate: float | None = None) -> Sequence:
    """``sequence`` opened with :func:`~dynastereo.io.open_sequence` (a path), or as it is."""
    if isinstance(sequence, (str, Path)):
        return open_sequence(Path(sequence), calib=Path(calib) if calib else None, color=color, rate=rate)
    return sequence


def source_spec(sequence: str | Path | Sequence, calib: str | Path | None = None,
                rate: float | None = None) -> SourceSpec:
    """The :class:`~dynastereo.runtime.SourceSpec` of a path or an opened sequence."""
    if isinstance(sequence, (str, Path)):
        return SourceSpec(path=sequence, calib=Path(calib) if calib else None, rate=rate)
    return SourceSpec(sequence=sequence)


def make_report(run_dir: str | Path, gt: str | Path | None = None, out: str | Path | None = None, *,
                overlays: int = 6, auto_gt: bool = True) -> Path:
    """Write the self-contained HTML page of a run folder (default ``RUN_DIR/report.html``)
    and return its path; see :func:`dynastereo.eval.html_report.build_report`."""
    from .eval.html_report import build_report

    return build_report(run_dir, gt, out, overlays=overlays, auto_gt=auto_gt)


def ground_truth(sequence: str | Path, at: str = "images"):
    """The ground truth of a sequence folder as a :class:`~dynastereo.eval.Trajectory`: a
    KITTI raw drive's OXTS converted to rectified camera-0 poses, or KITTI odometry's
    ``poses/NN.txt`` (:func:`~dynastereo.eval.trajectory.find_ground_truth`); InputError if none.
    ``at`` (KITTI raw only): ``"images"`` -- the poses at the images' stamps -- or
    ``"packets"`` -- the devkit's, at the OXTS packets' (:mod:`dynastereo.io.kitti_raw`)."""
    from .errors import InputError
    from .eval.trajectory import find_ground_truth, read_trajectory
    from .io.kitti_raw import GT_AT

    if at not in GT_AT:
        raise InputError(f"--at: {at!r} is not one of {', '.join(GT_AT)}")
    path = find_ground_truth(sequence)
    if path is None:
        raise InputError("no ground truth found (KITTI odometry poses/NN.txt beside sequences/NN, or a KITTI raw "
                         "drive's oxts/)", sequence)
    return read_trajectory(path, name="ground truth", at=at)


def write_ground_truth(sequence: str | Path, out: str | Path, fmt: str = "both", at: str = "images") -> list[Path]:
    """Write :func:`ground_truth` to ``out``: ``fmt`` ``"kitti"`` (12 numbers a row), ``"tum"``
    (``t x y z qx qy qz qw``) or ``"both"`` (KITTI to ``out``, TUM beside it as
    ``<stem>.tum.txt``); ``at`` as :func:`ground_truth`'s.  Returns the files written."""
    from .errors import InputError
    from .eval.trajectory import write_kitti, write_tum

    if fmt not in ("kitti", "tum", "both"):
        raise InputError(f"--format: {fmt!r} is not one of kitti, tum, both")
    traj = ground_truth(sequence, at=at)
    out = Path(out)
    check_output_file(out, what="ground-truth file")
    written = []
    if fmt in ("kitti", "both"):
        written.append(write_kitti(out, traj.poses))
    if fmt == "tum":
        written.append(write_tum(out, traj.poses, traj.timestamps))
    elif fmt == "both":
        tum = out.with_name(out.name.split(".")[0] + ".tum.txt")
        check_output_file(tum, what="ground-truth file")
        written.append(write_tum(tum, traj.poses, traj.timestamps))
    return written


def mask_sequence(
    sequence: str | Path | Sequence,
    out: str | Path,
    cfg: Config | None = None,
    *,
    frames: str | int | None = None,
    calib: str | Path | None = None,
    rate: float | None = None,
    models_dir: str | Path | None = None,
    save_disparity: bool = False,
    overlays: bool = False,
    progress: Callable[[int, int, dict], None] | None = None,
    overwrite: bool = False,
    stereo_check: bool = True,
    observers: tuple[FrameObserver, ...] = (),
    viewer: bool = False,
    rrd: str | Path | None = None,
) -> JobResult:
    """Mask the dynamic objects of ``sequence`` in both images (a :class:`~dynastereo.runtime.JobSpec` of kind ``mask``, run by
    :func:`dynastereo.runtime.run`).

    ``overwrite``: the outputs of an earlier run in ``out`` are deleted first (default False:
    an :class:`~dynastereo.errors.OutputError`, as the CLI without ``--overwrite``);
    ``stereo_check``: refuse pairs that are identical, swapped or not rectified
    (:class:`~dynastereo.errors.StereoCheckError`; ``io.stereo_check``).  ``viewer`` /
    ``rrd``: show the frames in the rerun viewer / record them (see :func:`viewers`).
    ``rate``: frame rate (Hz) for a folder without timestamps (see :func:`~dynastereo.io.open_sequence`)."""
    spec = JobSpec(JobKind.MASK, source_spec(sequence, calib, rate),
                   OutputSpec(Path(out), overwrite=overwrite, save_disparity=save_disparity, overlays=overlays,
                              viewer=viewer, rrd=rrd),
                   cfg or Config(), frames=frames, models_dir=models_dir, stereo_check=stereo_check)
    return run_job(spec, progress=progress, observers=observers)


def run_sequence(
    sequence: str | Path | Sequence,
    out: str | Path,
    cfg: Config | None = None,
    *,
    frames: str | int | None = None,
    calib: str | Path | None = None,
    rate: float | None = None,
    models_dir: str | Path | None = None,
    save_masks: bool = False,
    progress: Callable[[int, int, dict], None] | None = None,
    save_map: str | Path | None = None,
    load_map: str | Path | None = None,
    localize_only: bool = False,
    overwrite: bool = False,
    stereo_check: bool = True,
    report: bool = False,
    gt: str | Path | None = None,
    observers: tuple[FrameObserver, ...] = (),
    viewer: bool = False,
    rrd: str | Path | None = None,
    save_cloud: str | Path | None = None,
) -> JobResult:
    """Mask and track ``sequence`` with the stereo SLAM (a :class:`~dynastereo.runtime.JobSpec` of kind ``run``;
    the outputs are listed in :mod:`dynastereo.runtime.sinks` and :mod:`dynastereo.runtime.finish`).

    ``frames`` may revisit (``"0-98,40-60"``): frames are fed in the order given.
    ``load_map``: start from a map file (``save_map`` of an earlier run); with
    ``localize_only`` the map is only localized in (no new keyframes).  ``save_map``:
    write the final map there (its path is checked before the first frame).
    ``overwrite`` / ``stereo_check``: as for :func:`mask_sequence`.  ``report``: also write
    ``out/report.html`` (:func:`make_report`; its path in ``result.report``).  ``viewer`` /
    ``rrd``: show the run in the rerun viewer / record it to an ``.rrd`` file
    (:func:`viewers`).  ``gt``: ground truth for both (default: ``poses/NN.txt`` of a KITTI
    layout, when present).  ``rate``: as for :func:`mask_sequence`; where the stamps came
    from is ``run.json``'s ``timestamps``.  ``save_cloud``: write the final map's points as
    PLY, none on an object judged moving or undecided.
    """
    spec = JobSpec(JobKind.RUN, source_spec(sequence, calib, rate),
                   OutputSpec(Path(out), overwrite=overwrite, save_masks=save_masks, save_map=save_map,
                              save_cloud=save_cloud, report=report, viewer=viewer, rrd=rrd),
                   cfg or Config(), frames=frames, models_dir=models_dir, load_map=load_map,
                   localize_only=localize_only, stereo_check=stereo_check, gt=gt)
    return run_job(spec, progress=progress, observers=observers)


# --------------------------------------------------------------------------- benchmarks


def bench(
    root: str | Path,
    out: str | Path,
    *,
    sequences: str | None = None,
    maskers: str | list[str] = "none,box,outline,seg",
    repeats: int = 1,
    config: str | Path | None = None,
    overrides: dict | None = None,
    frames: str | None = None,
    engine: str = "local",
    address: str | None = None,
    workers: int | None = None,
    threads: int = 1,
    models_dir: str | Path | None = None,
    plots: bool = True,
    progress: Callable[[dict], None] | None = None,
):
    """Run every (sequence, masker, repeat) of the sequences under ``root`` as its own job,
    evaluate each against its ground truth, write ``out/results.json``, ``out/tables.md``
    and ``out/plots/``; finished jobs are reused.  ``engine``: ``local`` (process pool) or
    ``ray`` (local instance, or the cluster at ``address``).  See
    :func:`dynastereo.bench.runner.run_bench`."""
    from .bench import run_bench

    return run_bench(root, out, sequences=sequences, maskers=maskers, repeats=repeats, config=config,
                     overrides=overrides, frames=frames, engine=engine, address=address, workers=workers,
                     threads=threads, models_dir=models_dir, plots=plots, progress=progress)


# --------------------------------------------------------------------------- ROS bags


def run_bag(
    bag: str | Path,
    out: str | Path,
    cfg: Config | None = None,
    *,
    left_topic: str | None = None,
    right_topic: str | None = None,
    left_info: str | None = "auto",
    right_info: str | None = "auto",
    calib: str | Path | None = None,
    config_path: str | Path | None = None,
    tolerance_s: float = 0.005,
    rectify: str = "auto",
    frames: str | int | None = None,
    models_dir: str | Path | None = None,
    save_masks: bool = False,
    outputs: str | None = None,
    progress: Callable[[int, int, dict], None] | None = None,
    overwrite: bool = False,
    stereo_check: bool = True,
    report: bool = False,
    gt: str | Path | None = None,
    observers: tuple[FrameObserver, ...] = (),
    viewer: bool = False,
    rrd: str | Path | None = None,
    save_cloud: str | Path | None = None,
) -> JobResult:
    """Mask and track a stereo bag (ROS 1 .bag, ROS 2 .db3, .mcap); results as for
    :func:`run_sequence` plus ``out/output.<fmt>`` and ``out/bag.json``.  Calibration:
    ``calib`` (YAML) > the bag's CameraInfo > ``config_path`` when it is an ORB-SLAM2
    settings file.  ``overwrite`` / ``stereo_check`` / ``report`` / ``viewer`` / ``rrd`` /
    ``gt`` as for :func:`run_sequence`.  The output bag's content: :class:`dynastereo.ros.bagrun.BagOutput`."""
    from .ros.bagrun import BagSource
    from .ros.messages import DEFAULT_LEFT_TOPIC, DEFAULT_RIGHT_TOPIC

    source = BagSource(Path(bag), left_topic or DEFAULT_LEFT_TOPIC, right_topic or DEFAULT_RIGHT_TOPIC, left_info,
                       right_info, tolerance_s, rectify, settings_calibration(config_path), outputs)
    spec = JobSpec(JobKind.RUN, SourceSpec(opener=source, calib=Path(calib) if calib else None),
                   OutputSpec(Path(out), overwrite=overwrite, save_masks=save_masks, save_cloud=save_cloud,
                              report=report, viewer=viewer, rrd=rrd),
                   cfg or Config(), frames=frames, models_dir=models_dir, stereo_check=stereo_check, gt=gt)
    return run_job(spec, progress=progress, observers=observers)


def export_bag(
    sequence: str | Path | Sequence,
    out: str | Path,
    fmt: str = "ros1",
    *,
    frames: str | int | None = None,
    calib: str | Path | None = None,
    color: bool = False,
    encoding: str = "auto",
    raw: bool = False,
    time_offset_s: float = 0.0,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    rate: float | None = None,
):
    """Write a stereo sequence folder as a bag (``ros1`` .bag, ``ros2`` .db3, ``mcap``) on
    ``/camera/{left,right}/image_raw`` + ``camera_info``; see :func:`dynastereo.ros.bags.export_bag`.
    The stamps are the sequence's plus ``time_offset_s`` (KITTI's ``times.txt`` starts at
    0 s, i.e. 1970); ``rate`` as for :func:`mask_sequence`."""
    from .ros.bags import export_bag as _export

    seq = load_sequence(sequence, calib, color=color, rate=rate)
    indices = select_frames(frames, seq)
    return _export(seq, out, fmt, frames=indices, encoding=encoding, raw=raw, time_offset_s=time_offset_s,
                   overwrite=overwrite, progress=progress)
