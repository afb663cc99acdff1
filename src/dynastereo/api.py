"""High-level Python API: the same jobs the CLI runs.

>>> from dynastereo.api import mask_sequence
>>> result = mask_sequence("KITTI/sequences/06", "out/", frames="0-9")
>>> result.summary["mask"]["median"]

Every job is assembled in one place each: :func:`mask_sequence` and :func:`slam_job`
(``run``, ``run --bag``) check their inputs with :func:`_checked_inputs` and build the
masker with :func:`dynastereo.masking.build_masker`; the live node uses the same factory.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

from .config import Config
from .io import open_sequence
from .io.base import Sequence
from .io.frames import select_frames
from .io.outputs import check_output_file, prepare_output_dir
from .io.stereo_check import check_sequence
from .observers import FrameObserver
from .pipeline import MaskJobResult, SlamJobResult, run_mask_job, run_slam_job


def load_sequence(sequence: str | Path | Sequence, calib: str | Path | None = None,
                  color: bool | None = None, rate: float | None = None) -> Sequence:
    """``sequence`` opened with :func:`~dynastereo.io.open_sequence` (a path), or as it is."""
    if isinstance(sequence, (str, Path)):
        return open_sequence(Path(sequence), calib=Path(calib) if calib else None, color=color, rate=rate)
    return sequence


def _checked_inputs(seq: Sequence, cfg: Config, frames, models_dir, ground_truth, *, out, overwrite: bool,
                    stereo_check: bool):
    """(frame indices, masker) for a job, after the checks made before its first frame: the
    frames, the stereo pair (``io.stereo_check``), the model (the masker factory verifies
    it), and last the output folder (``io.outputs.prepare_output_dir``: an earlier run there
    is cleared only once the inputs proved good)."""
    from .masking import build_masker

    indices = select_frames(frames, seq)
    if stereo_check:
        check_sequence(seq, indices)
    masker = build_masker(cfg, seq.calibration, models_dir=models_dir, ground_truth=ground_truth)
    prepare_output_dir(out, overwrite=overwrite)
    return indices, masker


def _stereo_watch(seq: Sequence, stereo_check: bool) -> tuple[FrameObserver, ...]:
    """The stereo check again every ``CHECK_EVERY`` frames of the job (``io.stereo_check``)."""
    from .io.stereo_check import PeriodicStereoCheck

    return (PeriodicStereoCheck(getattr(seq, "path", None)),) if stereo_check else ()


def make_report(run_dir: str | Path, gt: str | Path | None = None, out: str | Path | None = None, *,
                overlays: int = 6, auto_gt: bool = True) -> Path:
    """Write the self-contained HTML page of a run folder (default ``RUN_DIR/report.html``)
    and return its path; see :func:`dynastereo.eval.html_report.build_report`."""
    from .eval.html_report import build_report

    return build_report(run_dir, gt, out, overlays=overlays, auto_gt=auto_gt)


def ground_truth(sequence: str | Path):
    """The ground truth of a sequence folder as a :class:`~dynastereo.eval.Trajectory`: a
    KITTI raw drive's OXTS converted to rectified camera-0 poses, or KITTI odometry's
    ``poses/NN.txt`` (:func:`~dynastereo.eval.trajectory.find_ground_truth`); InputError if none."""
    from .errors import InputError
    from .eval.trajectory import find_ground_truth, read_trajectory

    path = find_ground_truth(sequence)
    if path is None:
        raise InputError("no ground truth found (KITTI odometry poses/NN.txt beside sequences/NN, or a KITTI raw "
                         "drive's oxts/)", sequence)
    return read_trajectory(path, name="ground truth")


def write_ground_truth(sequence: str | Path, out: str | Path, fmt: str = "both") -> list[Path]:
    """Write :func:`ground_truth` to ``out``: ``fmt`` ``"kitti"`` (12 numbers a row), ``"tum"``
    (``t x y z qx qy qz qw``) or ``"both"`` (KITTI to ``out``, TUM beside it as
    ``<stem>.tum.txt``).  Returns the files written."""
    from .errors import InputError
    from .eval.trajectory import write_kitti, write_tum

    if fmt not in ("kitti", "tum", "both"):
        raise InputError(f"--format: {fmt!r} is not one of kitti, tum, both")
    traj = ground_truth(sequence)
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


def resolve_ground_truth(gt: str | Path | None, sequence) -> Path | None:
    """``gt``, else the sequence's own ground truth when it has one (KITTI odometry
    ``poses/NN.txt``, a KITTI raw drive's ``oxts/``)."""
    from .eval.html_report import default_ground_truth

    if gt is not None:
        return Path(gt)
    path = getattr(sequence, "path", sequence)
    return default_ground_truth(path) if isinstance(path, (str, Path)) else None


@contextmanager
def viewers(observers: tuple[FrameObserver, ...] = (), *, viewer: bool = False, rrd: str | Path | None = None,
            gt: str | Path | None = None, name: str = "dynastereo") -> Iterator[tuple[FrameObserver, ...]]:
    """``observers`` plus, with ``viewer`` (spawn the rerun viewer) or ``rrd`` (record to a
    file), a :class:`dynastereo.viz.rerun.RerunObserver` (needs ``pip install
    dynastereo[viz]``), flushed and closed on exit.  Neither: rerun is not imported."""
    if not viewer and rrd is None:
        yield tuple(observers)
        return
    from .viz.rerun import RerunObserver

    rec = RerunObserver(spawn=viewer, rrd=rrd, gt=gt, name=name)
    try:
        yield (*observers, rec)
    finally:
        rec.close()


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
    overwrite: bool = True,
    stereo_check: bool = True,
    observers: tuple[FrameObserver, ...] = (),
    viewer: bool = False,
    rrd: str | Path | None = None,
) -> MaskJobResult:
    """Mask the dynamic objects of ``sequence`` in both images; see ``pipeline.run_mask_job``.

    ``overwrite``: the outputs of an earlier run in ``out`` are deleted first (False: an
    :class:`~dynastereo.errors.OutputError`, as the CLI without ``--overwrite``);
    ``stereo_check``: refuse pairs that are identical, swapped or not rectified
    (:class:`~dynastereo.errors.StereoCheckError`; ``io.stereo_check``).  ``viewer`` /
    ``rrd``: show the frames in the rerun viewer / record them (see :func:`viewers`).
    ``rate``: frame rate (Hz) for a folder without timestamps (see :func:`~dynastereo.io.open_sequence`)."""
    cfg = cfg or Config()
    if save_disparity and cfg.stereo.region != "full":
        cfg = cfg.with_overrides({"stereo.region": "full"})
    seq = load_sequence(sequence, calib, rate=rate)
    indices, masker = _checked_inputs(seq, cfg, frames, models_dir, getattr(seq, "path", None), out=out,
                                      overwrite=overwrite, stereo_check=stereo_check)
    watch = _stereo_watch(seq, stereo_check)
    with viewers((*observers, *watch), viewer=viewer, rrd=rrd, name="dynastereo mask") as obs:
        return run_mask_job(seq, masker, out, indices, save_disparity=save_disparity, overlays=overlays,
                            progress=progress, observers=obs)


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
    overwrite: bool = True,
    stereo_check: bool = True,
    report: bool = False,
    gt: str | Path | None = None,
    observers: tuple[FrameObserver, ...] = (),
    viewer: bool = False,
    rrd: str | Path | None = None,
    save_cloud: str | Path | None = None,
) -> SlamJobResult:
    """Mask and track ``sequence`` with the stereo SLAM; see ``pipeline.run_slam_job``.

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
    cfg = cfg or Config()
    seq = load_sequence(sequence, calib, rate=rate)
    gt = resolve_ground_truth(gt, seq)
    with viewers(observers, viewer=viewer, rrd=rrd, gt=gt, name="dynastereo run") as obs:
        res = slam_job(seq, out, cfg, frames=frames, models_dir=models_dir, ground_truth=getattr(seq, "path", None),
                       observers=obs, save_masks=save_masks, progress=progress, save_map=save_map,
                       load_map=load_map, localize_only=localize_only, overwrite=overwrite, stereo_check=stereo_check,
                       save_cloud=save_cloud)
    if report:
        res.report = make_report(out, gt)
    return res


def slam_job(
    seq: Sequence,
    out: str | Path,
    cfg: Config,
    *,
    frames: str | int | None = None,
    models_dir: str | Path | None = None,
    ground_truth: str | Path | None = None,
    observers: tuple[FrameObserver, ...] = (),
    open_observers: Callable[[], tuple[FrameObserver, ...]] | None = None,
    save_masks: bool = False,
    progress: Callable[[int, int, dict], None] | None = None,
    save_map: str | Path | None = None,
    load_map: str | Path | None = None,
    localize_only: bool = False,
    overwrite: bool = True,
    stereo_check: bool = True,
    save_cloud: str | Path | None = None,
) -> SlamJobResult:
    """The one place that assembles reader -> masker -> SLAM -> writers, for a folder, a
    bag or anything else that is a :class:`~dynastereo.io.base.Sequence`: the inputs checked
    (:func:`_checked_inputs`: frames, stereo pair, model, then the output folder), the
    masker from :func:`dynastereo.masking.build_masker` (the sequence's calibration), the
    SLAM system (optionally from ``load_map``), the motion test (``cfg.motion``:
    :func:`dynastereo.masking.motion.build_motion`), then
    :func:`~dynastereo.pipeline.run_slam_job` with ``observers`` and those
    ``open_observers()`` returns once the output folder is ready (a bag's writer)."""
    from .config import to_dict
    from .errors import ConfigError
    from .slam import System

    if localize_only and load_map is None:
        raise ConfigError("localization only needs a map: give load_map (--load-map FILE)")
    if save_map is not None:
        check_output_file(save_map, what="map file")
    if save_cloud is not None:
        check_output_file(save_cloud, what="point cloud file")
    indices, masker = _checked_inputs(seq, cfg, frames, models_dir, ground_truth, out=out, overwrite=overwrite,
                                      stereo_check=stereo_check)
    observers = (*observers, *_stereo_watch(seq, stereo_check))
    if open_observers is not None:
        observers = (*observers, *open_observers())
    system = System(cfg, seq.calibration)
    info = {}
    if load_map is not None:
        try:
            system.load_map(load_map, localize_only=localize_only)
        except BaseException:
            system.shutdown()
            raise
        info = {"loaded": str(load_map), "localize_only": bool(localize_only)}
    from .masking.motion import build_motion

    return run_slam_job(seq, masker, system, out, indices, config_dict=to_dict(cfg), save_masks=save_masks,
                        progress=progress, save_map=save_map, map_info=info, observers=observers,
                        motion=build_motion(cfg, seq.calibration, masker), save_cloud=save_cloud)


# --------------------------------------------------------------------------- benchmarks


def bench(
    root: str | Path,
    out: str | Path,
    *,
    sequences: str | None = None,
    maskers: str | list[str] = "none,box,outline,seg",
    repeats: int = 3,
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
    overwrite: bool = True,
    stereo_check: bool = True,
    report: bool = False,
    gt: str | Path | None = None,
    observers: tuple[FrameObserver, ...] = (),
    viewer: bool = False,
    rrd: str | Path | None = None,
    save_cloud: str | Path | None = None,
):
    """Mask and track a stereo bag (ROS 1 .bag, ROS 2 .db3, .mcap); results as for
    :func:`run_sequence` plus ``out/output.<fmt>`` and ``out/bag.json``.  Calibration:
    ``calib`` (YAML) > the bag's CameraInfo > ``config_path`` when it is an ORB-SLAM2
    settings file.  ``overwrite`` / ``stereo_check`` / ``report`` / ``viewer`` / ``rrd`` /
    ``gt`` as for :func:`run_sequence`.  See :func:`dynastereo.ros.bagrun.run_bag`."""
    from .ros.bagrun import run_bag as _run_bag
    from .ros.messages import DEFAULT_LEFT_TOPIC, DEFAULT_RIGHT_TOPIC

    fallback = None
    if config_path is not None:
        from .io.calib import is_orbslam2_settings, read_yaml_file

        if is_orbslam2_settings(read_yaml_file(config_path)):
            fallback = config_path
    with viewers(observers, viewer=viewer, rrd=rrd, gt=gt, name="dynastereo run --bag") as obs:
        res = _run_bag(bag, out, cfg, left_topic=left_topic or DEFAULT_LEFT_TOPIC,
                       right_topic=right_topic or DEFAULT_RIGHT_TOPIC, left_info=left_info, right_info=right_info,
                       calib=calib, fallback_calib=fallback, tolerance_s=tolerance_s, rectify=rectify,
                       frames=frames, models_dir=models_dir, save_masks=save_masks, outputs=outputs,
                       progress=progress, overwrite=overwrite, stereo_check=stereo_check, observers=obs,
                       save_cloud=save_cloud)
    if report:
        res.slam.report = make_report(out, gt)
    return res


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
