"""``dynastereo`` command line: a thin shell over the Python API."""

from __future__ import annotations

import logging
import os
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Optional

import typer
from rich.console import Console
from rich.table import Table

from ..errors import DynastereoError, Interrupted
from .signals import STOP

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Stereo visual SLAM in dynamic scenes: mask moving objects in both stereo images, fast, on a CPU.",
)
# Piped output (CI logs, files) gets wide tables instead of rich's 80-column default.
console = Console(stderr=True, width=None if sys.stderr.isatty() else 160, soft_wrap=True)
out_console = Console(width=None if sys.stdout.isatty() else 160, soft_wrap=True)

def _print_version(value: bool) -> None:
    if value:
        from .. import __version__

        out_console.print(f"dynastereo {__version__}", highlight=False)
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    pass


models_app = typer.Typer(help="List, download and verify detector models.", invoke_without_command=True)
app.add_typer(models_app, name="models")


_RATE_HELP = ("Frame rate (Hz) for the timestamps of a folder with no times.txt and no timestamp file names "
              "(default: 10 Hz, with a warning), or of a video instead of its container's stamps.")


def _fail(e: Exception) -> None:
    console.print(f"[bold red]error:[/] {e}", soft_wrap=True, highlight=False, markup=True)
    raise typer.Exit(2)


def _check_option(flag: str, value, ok: bool, want: str) -> None:
    """One line naming the option, what it must be (with its unit) and what it got."""
    if not ok:
        _fail(DynastereoError(f"{flag} must be {want}, got {value:g}" if isinstance(value, float)
                              else f"{flag} must be {want}, got {value}"))


def _kept_files(out: Path, names: tuple[str, ...], what: str, extra: tuple[Path, ...] = ()) -> Callable[[], str]:
    """The closing line's account of an interrupted job, made when it is printed: only
    the files that exist are named."""

    def kept() -> str:
        have = [n for n in names if (out / n).exists()]
        more = [str(p) for p in extra if p.exists()]
        if not have and not more:
            return f"nothing was written to {out}"
        text = f"{', '.join(have)} ({what}) are in {out}" if have else ""
        return "; ".join([t for t in (text, *(f"{p} was written" for p in more)) if t])

    return kept


class _Job:
    """Frames done so far of the running job, for the message when a signal stops it."""

    def __init__(self, kept: "str | Callable[[], str]") -> None:
        self._kept = kept
        self.done = 0
        self.total: int | None = None

    @property
    def kept(self) -> str:
        """What the interrupted job left (a callable looks at the files that exist)."""
        return self._kept() if callable(self._kept) else self._kept

    def tick(self, done: int, total: int | None) -> None:
        """Call after each frame: records it, and stops the job there if a signal came."""
        self.done, self.total = done, total
        STOP.check()


@contextmanager
def _job(kept: str):
    """A job run from the CLI: bad input -> one line, exit 2; SIGINT / SIGTERM -> the job
    stops after the frame in progress, one line saying what is kept, exit 130 / 143."""
    job = _Job(kept)
    try:
        with STOP.job():
            yield job
    except DynastereoError as e:
        _fail(e)
    except Interrupted as e:
        of = f" of {job.total}" if job.total else ""
        console.print(f"[bold yellow]interrupted[/] by {e.name} after {job.done}{of} frames; {job.kept}",
                      soft_wrap=True, highlight=False)
        raise typer.Exit(e.exit_code)


def _progress():
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[info]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=False,
        disable=not console.is_terminal and os.environ.get("DYNASTEREO_PROGRESS", "") != "1",
    )


def timing_table(summary: dict[str, dict[str, float]], title: str = "timing (ms per stereo pair)") -> Table:
    table = Table(title=title)
    table.add_column("stage")
    table.add_column("median", justify="right")
    table.add_column("p90", justify="right")
    table.add_column("mean", justify="right")
    table.add_column("frames", justify="right")
    for name, s in summary.items():
        table.add_row(name, f"{s['median']:.1f}", f"{s['p90']:.1f}", f"{s['mean']:.1f}", str(s["n"]))
    return table


def _build_config(config: Optional[Path], overrides: dict):
    from ..config import load_config

    return load_config(config).with_overrides(overrides)


@app.command()
def mask(
    sequence: Path = typer.Argument(..., help="Sequence folder: KITTI odometry, KITTI raw drive, EuRoC mav0, or left/right folders + YAML calibration; or a stereo video (side by side: stereo.mkv; two files: left.mkv,right.mkv) or a camera (cam:0), with --calib."),
    out: Path = typer.Option(..., "--out", "-o", help="Output directory."),
    detector: Optional[str] = typer.Option(None, help="yolov3, yolov3-tiny, yolox-nano, fastestdet, yolo11n-int8, oracle, or a .cfg/.onnx path."),
    stereo: Optional[str] = typer.Option(None, help="Stereo matcher: bm | sgbm | sgbm3way."),
    wls: Optional[bool] = typer.Option(None, "--wls/--no-wls", help="WLS-filter the disparity."),
    masker: Optional[str] = typer.Option(None, help="outline | box | seg | none."),
    canvas: Optional[str] = typer.Option(None, help="How the frame meets the detector: frame (its own scale, default) | tiles | model (the model's square canvas)."),
    schedule: Optional[str] = typer.Option(None, help="When the detector runs: interval (every detector.interval-th frame, default 2) | every | rotate (one tile per frame); boxes are carried between runs."),
    frames: Optional[str] = typer.Option(None, help="A count N, or inclusive index ranges a-b,c-d (a- = a to the end)."),
    save_disparity: bool = typer.Option(False, "--save-disparity", help="Write DIR/disparity/NNNNNN.png (uint16, disparity*256)."),
    overlays: bool = typer.Option(False, "--overlays", help="Write DIR/overlays/NNNNNN.png."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML configuration."),
    calib: Optional[Path] = typer.Option(None, "--calib", help="YAML calibration for a generic folder pair."),
    rate: Optional[float] = typer.Option(None, "--rate", help=_RATE_HELP),
    models_dir: Optional[Path] = typer.Option(None, "--models-dir", help="Model directory (default: $DYNASTEREO_MODELS or the cache)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an earlier run in DIR (its outputs are deleted first)."),
    no_stereo_check: bool = typer.Option(False, "--no-stereo-check", help="Skip the check that the pair is rectified left/right (not identical, swapped or unrectified)."),
    viewer: bool = typer.Option(False, "--viewer", help="Show the frames live in the rerun viewer (spawns it; needs `pip install dynastereo[viz]`)."),
    rrd: Optional[Path] = typer.Option(None, "--rrd", help="Record the frames for the rerun viewer into FILE.rrd (headless; `rerun FILE.rrd` opens it)."),
) -> None:
    """Mask the dynamic objects of a stereo sequence in BOTH images."""
    from ..runtime import JobKind, JobSpec, OutputSpec, SourceSpec, run as run_job

    with _job(_kept_files(out, ("masks", "objects.jsonl", "timing.json"), "the frames done; timing.json with the signal")) as job:
        overrides = {"detector.name": detector, "stereo.algorithm": stereo, "stereo.wls": wls, "masker.kind": masker,
                     "detector.canvas": canvas, "detector.schedule": schedule}
        spec = JobSpec(JobKind.MASK, SourceSpec(path=sequence, calib=calib, rate=rate),
                       OutputSpec(out, overwrite=overwrite, save_disparity=save_disparity, overlays=overlays,
                                  viewer=viewer, rrd=rrd),
                       _build_config(config, overrides), frames=frames, models_dir=models_dir,
                       stereo_check=not no_stereo_check)
        with _progress() as prog:
            task = prog.add_task("masking", total=None, info="")

            def on_frame(done: int, total: int, rec: dict) -> None:
                total = total if total < sys.maxsize else None  # a camera (io.video.UNBOUNDED): no end
                ms = rec["ms"]
                prog.update(task, completed=done, total=total,
                            info=f"detect {ms.get('detect', 0):.0f} ms  mask {ms.get('mask', 0):.0f} ms")
                job.tick(done, total)

            result = run_job(spec, progress=on_frame)
    out_console.print(timing_table(result.summary))
    out_console.print(f"{len(result.frames_done)} frames -> {out}  ({result.wall_s:.1f} s)")
    for line in [ln for ln in _run_summary_lines(out, None) if ln.startswith("calibration:")]:  # a mask job: no GT
        out_console.print(line, highlight=False)


def _run_source(sequence, bag, calib, rate, config, left_topic, right_topic, left_info, right_info,
                sync_tolerance, rectify, bag_outputs):
    """The run's :class:`~dynastereo.runtime.SourceSpec`: a folder / video / camera, or a bag
    (its CameraInfo topics ``auto`` / ``none`` / a topic; an ORB-SLAM2 settings file given as
    ``--config`` is its calibration when it has no CameraInfo)."""
    from ..runtime import SourceSpec
    from ..runtime.spec import settings_calibration

    if bag is None:
        return SourceSpec(path=sequence, calib=calib, rate=rate)
    from ..ros.bagrun import BagSource

    if sequence is not None:
        return SourceSpec(path=sequence, opener=BagSource(bag), calib=calib, rate=rate)  # refused: both given
    info = {"auto": "auto", "none": None}
    source = BagSource(bag, left_topic, right_topic, info.get(left_info.lower(), left_info),
                       info.get(right_info.lower(), right_info), sync_tolerance / 1000.0, rectify,
                       settings_calibration(config), bag_outputs)
    return SourceSpec(opener=source, calib=calib, rate=rate)


@app.command()
def run(
    sequence: Optional[Path] = typer.Argument(None, help="Sequence folder: KITTI odometry, KITTI raw drive, EuRoC mav0, or left/right folders + YAML calibration; or a stereo video (side by side: stereo.mkv; two files: left.mkv,right.mkv) or a side-by-side camera (cam:0, until --frames N or Ctrl-C), with --calib (or --bag)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output directory."),
    masker: Optional[str] = typer.Option(None, help="none | box | outline | seg."),
    detector: Optional[str] = typer.Option(None, help="yolov3, yolov3-tiny, yolox-nano, fastestdet, yolo11n-int8, oracle, or a .cfg/.onnx path."),
    stereo: Optional[str] = typer.Option(None, help="Stereo matcher for the masks: bm | sgbm | sgbm3way."),
    canvas: Optional[str] = typer.Option(None, help="How the frame meets the detector: frame (its own scale, default) | tiles | model (the model's square canvas)."),
    schedule: Optional[str] = typer.Option(None, help="When the detector runs: interval (every detector.interval-th frame, default 2) | every | rotate (one tile per frame); boxes are carried between runs."),
    frames: Optional[str] = typer.Option(None, help="A count N, or inclusive index ranges a-b,c-d (a- = a to the end), fed in that order (revisits allowed)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML configuration, or an ORB-SLAM2 stereo settings file."),
    calib: Optional[Path] = typer.Option(None, "--calib", help="YAML calibration for a generic folder pair (with --bag: wins over CameraInfo)."),
    rate: Optional[float] = typer.Option(None, "--rate", help=_RATE_HELP),
    models_dir: Optional[Path] = typer.Option(None, "--models-dir", help="Model directory (default: $DYNASTEREO_MODELS or the cache)."),
    save_masks: bool = typer.Option(False, "--save-masks", help="Also write DIR/masks/{left,right}/NNNNNN.png."),
    mask_all: bool = typer.Option(False, "--mask-all", help="Mask every detection, moving or not (the thesis; motion.mode: all). Default: only objects judged moving or not yet judged."),
    object_block: Optional[int] = typer.Option(None, "--object-block", help="The block the objects' outlines are matched again with for their world positions (objects.block_size; default 11; 0: the masker's disparity)."),
    bag: Optional[Path] = typer.Option(None, "--bag", help="Read a ROS bag instead of a folder: ROS 1 .bag, ROS 2 .db3 (or bag directory), .mcap. Writes DIR/output.<same format> too."),
    left_topic: str = typer.Option("/camera/left/image_raw", "--left-topic", help="[--bag] Left sensor_msgs/Image or CompressedImage topic."),
    right_topic: str = typer.Option("/camera/right/image_raw", "--right-topic", help="[--bag] Right image topic."),
    left_info: str = typer.Option("auto", "--left-info", help="[--bag] Left CameraInfo topic; auto = camera_info beside the image topic; none = ignore."),
    right_info: str = typer.Option("auto", "--right-info", help="[--bag] Right CameraInfo topic (auto / none / a topic)."),
    sync_tolerance: float = typer.Option(5.0, "--sync-tolerance", help="[--bag] Largest left/right stamp difference of a pair, ms."),
    rectify: str = typer.Option("auto", "--rectify", help="[--bag] Rectify with CameraInfo: auto (unless already rectified) | yes | no."),
    bag_outputs: str = typer.Option("all", "--bag-outputs", help="[--bag] Output bag content: all, or a comma list of odometry,tf,masked,masks,disparity,path,map_points,objects."),
    save_map: Optional[Path] = typer.Option(None, "--save-map", help="Write the final map to FILE (docs/reference/map-format.md)."),
    load_map: Optional[Path] = typer.Option(None, "--load-map", help="Start from the map in FILE (from --save-map)."),
    save_cloud: Optional[Path] = typer.Option(None, "--save-cloud", help="Write the final map's points as a PLY point cloud (none on a moving object)."),
    save_mesh: Optional[Path] = typer.Option(None, "--save-mesh", help="Write the static world as a dense PLY triangle mesh (the keyframes' disparity fused at the final poses, movers left out; settings mesh.*)."),
    save_dense_cloud: Optional[Path] = typer.Option(None, "--save-dense-cloud", help="Write the same fused surface's points as a PLY point cloud (no triangles)."),
    localize_only: bool = typer.Option(False, "--localize-only", help="With --load-map: localize in the map, add no keyframes."),
    no_loop_closing: bool = typer.Option(False, "--no-loop-closing", help="Turn loop closing off (slam.loop_closing: false)."),
    vocabulary: Optional[Path] = typer.Option(None, "--vocabulary", help="ORB vocabulary file from `dynastereo vocab` (default: the built-in one)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an earlier run in DIR (its outputs are deleted first)."),
    no_stereo_check: bool = typer.Option(False, "--no-stereo-check", help="Skip the check that the pair is rectified left/right (not identical, swapped or unrectified)."),
    report: bool = typer.Option(False, "--report", help="Also write DIR/report.html (as `dynastereo report DIR`)."),
    gt: Optional[Path] = typer.Option(None, "--gt", help="Ground-truth trajectory (KITTI or TUM) for --report and the viewer (default: poses/NN.txt of a KITTI layout, when present)."),
    viewer: bool = typer.Option(False, "--viewer", help="Show the frames live in the rerun viewer (spawns it; needs `pip install dynastereo[viz]`)."),
    rrd: Optional[Path] = typer.Option(None, "--rrd", help="Record the frames for the rerun viewer into FILE.rrd (headless; `rerun FILE.rrd` opens it)."),
) -> None:
    """Mask and track a stereo sequence (a folder or a ROS bag): trajectory, timing and run summary out."""
    from ..runtime import JobKind, JobSpec, OutputSpec, run as run_job

    _check_option("--sync-tolerance", sync_tolerance, 0 <= sync_tolerance <= 10_000,
                  "a time in 0..10000 ms (milliseconds)")
    kept = _kept_files(out, ("run.json", "timing.json", "trajectory.kitti.txt", "trajectory.tum.txt"),
                       "with the signal; the frames done", (save_map,) if save_map else ())
    with _job(kept) as job:
        overrides = {"detector.name": detector, "stereo.algorithm": stereo, "masker.kind": masker,
                     "detector.canvas": canvas, "detector.schedule": schedule,
                     "slam.loop_closing": False if no_loop_closing else None,
                     "slam.vocabulary": str(vocabulary) if vocabulary else None,
                     "motion.mode": "all" if mask_all else None, "objects.block_size": object_block}
        spec = JobSpec(JobKind.RUN, _run_source(sequence, bag, calib, rate, config, left_topic, right_topic,
                                                left_info, right_info, sync_tolerance, rectify, bag_outputs),
                       OutputSpec(out, overwrite=overwrite, save_masks=save_masks, save_map=save_map,
                                  save_cloud=save_cloud, save_mesh=save_mesh, save_dense_cloud=save_dense_cloud,
                                  report=report, viewer=viewer, rrd=rrd),
                       _build_config(config, overrides), frames=frames, models_dir=models_dir, load_map=load_map,
                       localize_only=localize_only, stereo_check=not no_stereo_check, gt=gt, settings=config)
        with _progress() as prog:
            task = prog.add_task("tracking", total=None, info="")

            def on_frame(done: int, total: int, rec: dict) -> None:
                total = total if total < sys.maxsize else None  # a camera (io.video.UNBOUNDED): no end
                prog.update(task, completed=done, total=total, info=f"{rec['fps']:.1f} FPS  {rec['status']}")
                job.tick(done, total)

            result = run_job(spec, progress=on_frame)
    _print_run(result, out, save_map=save_map, save_cloud=save_cloud, mesh_file=save_mesh or save_dense_cloud, rrd=rrd)


def _print_run(result, out: Path, *, save_map: Optional[Path], save_cloud: Optional[Path],
               mesh_file: Optional[Path], rrd: Optional[Path]) -> None:
    """What ``run`` prints once the run is done: the timing table, the run's figures, the
    files it wrote, its accuracy, the report; exit 1 when every frame was lost."""
    bag_report = result.bag
    out_console.print(timing_table(result.summary, "timing (ms per frame)"))
    if "masking" in result.summary and "total" in result.summary:
        out_console.print("note: masking runs on its own thread beside tracking (the next frame's, while this one "
                          "is tracked): its time overlaps the others' and can exceed the total", highlight=False)
    st = result.stats
    out_console.print(
        f"{len(result.frames)} frames, {result.fps:.1f} FPS end to end; lost {len(result.lost)}, "
        f"keyframes {st.get('keyframes')}, map points {st.get('map_points')} -> {out}"
    )
    if st.get("loops") or st.get("recoveries"):
        out_console.print(f"loops closed {st.get('loops', 0)}; frames tracked again after a loss: "
                          f"{st.get('recoveries', 0)} (details in run.json)")
    if save_map:
        out_console.print(f"map saved to {save_map}")
    if save_cloud:
        out_console.print(f"static map points saved to {save_cloud}")
    if result.mesh and "vertices" in result.mesh:
        m = result.mesh
        out_console.print(f"static world: {m['vertices']} vertices, {m['triangles']} triangles from {m['keyframes']} "
                          f"keyframes -> {mesh_file}")
    if bag_report is not None:
        r = bag_report
        out_console.print(
            f"bag: {r['pairs']} stereo pairs from {r['left_topic']} + {r['right_topic']} "
            f"(unpaired: {r['unpaired_left']} left, {r['unpaired_right']} right, "
            f"tolerance {r['tolerance_s'] * 1000:g} ms); calibration: {r['calibration_source']}"
            f"{', rectified on read' if r['rectified_on_read'] else ''}; output bag {r['output_bag']}",
            highlight=False)
    for line in _run_summary_lines(out, result.report):
        out_console.print(line, highlight=False)
    if result.report is not None:
        out_console.print(f"report: {result.report}", highlight=False)
    if rrd is not None:
        out_console.print(f"recording: {rrd} (open it with `rerun {rrd}`)", highlight=False)
    if result.frames and len(result.lost) == len(result.frames):  # done, but nothing to show for it
        console.print(f"[bold red]error:[/] every one of the {len(result.frames)} frames was lost: no pose was tracked "
                      f"({out / 'run.json'}); check the calibration, the images and --load-map", highlight=False)
        raise typer.Exit(1)


def _run_summary_lines(out: Path, report: Optional[Path]) -> list[str]:
    """What a finished run used and how well it did: the calibration and ground truth it
    recorded in run.json, and -- with a ground truth -- one line of accuracy (ATE, drift,
    path length) and where the report is (or how to make one)."""
    import json

    try:
        run = json.loads((out / ("run.json" if (out / "run.json").is_file() else "timing.json")).read_text())
    except (OSError, ValueError):
        return []
    if not isinstance(run, dict):
        return []
    lines = []
    if run.get("calibration"):
        lines.append(f"calibration: {run['calibration']}")
    gt = run.get("ground_truth")
    if not gt:
        return lines + ["ground truth: none found (eval/report take one: `dynastereo eval TRAJ GT`)"]
    try:
        from ..eval import evaluate_files

        r = evaluate_files(out / "trajectory.kitti.txt", Path(gt))
    except DynastereoError as e:
        return lines + [f"ground truth: {gt} (not evaluated: {e})"]
    where = f"report: {report}" if report is not None else f"`dynastereo report {out}` makes the report"
    drift = f"{r.drift_percent:.2f} %" if r.drift_percent is not None else "n/a"
    lines.append(f"accuracy: ATE {r.ape['rmse']:.3f} m (RMSE), drift {drift}, path {r.path_length_m:.1f} m, "
                 f"against {gt}; {where}")
    return lines


def _run_inputs(run_dir: Path) -> list[Path]:
    """The sequence, calibration and ground truth a run's ``run.json`` records (absolute
    paths), the sequence first; [] when there is no readable record."""
    import json

    try:
        rec = json.loads((run_dir / "run.json").read_text())
    except (OSError, ValueError):
        return []
    if not isinstance(rec, dict) or not isinstance(rec.get("sequence"), str):
        return []
    return [Path(rec["sequence"])] + [Path(rec[k]) for k in ("calibration", "ground_truth") if isinstance(rec.get(k), str)]


@app.command("report")
def report_cmd(
    run_dir: Path = typer.Argument(..., help="Output folder of `dynastereo run` (or `mask`)."),
    gt: Optional[Path] = typer.Option(None, "--gt", help="Ground-truth trajectory, KITTI or TUM (default: poses/NN.txt beside a KITTI-layout sequence, or a KITTI raw drive's oxts/, when present)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="HTML file to write (default: RUN_DIR/report.html)."),
    overlays: int = typer.Option(6, "--overlays", help="Mask overlays at most (first, worst, evenly spaced; needs --save-masks in the run)."),
    no_auto_gt: bool = typer.Option(False, "--no-auto-gt", help="Do not look for the ground truth beside the sequence."),
) -> None:
    """One self-contained HTML page of a run: summary, trajectory vs ground truth, APE/RPE/drift, timing, masks, objects."""
    from ..api import make_report

    from ..io.outputs import RUN_OUTPUTS, check_output_file, refuse_input_as_output

    _check_option("--overlays", overlays, 0 <= overlays <= 1000, "a count of images in 0..1000")
    try:
        if out is not None:
            recorded = _run_inputs(run_dir)  # the sequence first
            refuse_input_as_output(out, [gt, run_dir, *(run_dir / n for n in RUN_OUTPUTS), *recorded],
                                   what="report file", flag="--out", folders=recorded[:1], own=run_dir)
            check_output_file(out, what="report file")
        path = make_report(run_dir, gt, out, overlays=overlays, auto_gt=not no_auto_gt)
    except DynastereoError as e:
        _fail(e)
    from ..eval.html_report import partial_reason

    why = partial_reason(run_dir)
    out_console.print(f"report: {path}" + (f" (partial: {why})" if why else ""), highlight=False)


@app.command("gt")
def gt_cmd(
    sequence: Path = typer.Argument(..., help="Sequence folder: a KITTI raw drive (its oxts/ GPS/IMU) or a KITTI odometry sequences/NN."),
    out: Path = typer.Option(..., "--out", "-o", help="Poses file: KITTI rows (with --format both, the TUM file goes beside it as STEM.tum.txt)."),
    fmt: str = typer.Option("both", "--format", help="kitti | tum | both."),
    at: str = typer.Option("images", "--at", help="KITTI raw: images (each OXTS pose moved to its image's stamp with the packet's own motion) | packets (the devkit's poses, at the packets' stamps)."),
) -> None:
    """Write a sequence's ground truth as camera-0 (rectified) poses in the first frame, KITTI and TUM."""
    from ..api import ground_truth, write_ground_truth
    from ..eval.trajectory import find_ground_truth
    from ..io.outputs import refuse_input_as_output

    try:
        refuse_input_as_output(out, [sequence, find_ground_truth(sequence) if sequence.is_dir() else None],
                               what="poses file", flag="--out", folders=[sequence])
        paths = write_ground_truth(sequence, out, fmt, at=at)
        traj = ground_truth(sequence, at=at)
    except DynastereoError as e:
        _fail(e)
    span = f", {traj.timestamps[-1] - traj.timestamps[0]:.2f} s" if traj.timestamps is not None else ""
    out_console.print(f"{len(traj)} poses, path {traj.path_length:.2f} m{span}: " + ", ".join(map(str, paths)),
                      highlight=False)


@app.command("export-bag")
def export_bag_cmd(
    sequence: Path = typer.Argument(..., help="Sequence folder (KITTI layout; EuRoC and generic folders too)."),
    out: Path = typer.Argument(..., help="Output bag file: .bag (ros1), .db3 (ros2), .mcap."),
    fmt: Optional[str] = typer.Option(None, "--format", "-f", help="ros1 | ros2 | mcap (default: from OUT's suffix)."),
    frames: Optional[str] = typer.Option(None, help="A count N, or inclusive index ranges a-b,c-d (a- = a to the end)."),
    encoding: str = typer.Option("auto", "--encoding", help="auto (mono8/bgr8) | mono8 | mono16 | bgr8 | rgb8 | png | jpeg (CompressedImage on <topic>/compressed)."),
    color: bool = typer.Option(False, "--color", help="KITTI: the colour pair image_2/image_3."),
    raw: bool = typer.Option(False, "--raw", help="Raw images + raw CameraInfo (K, D, R, P) for sequences rectified on read (EuRoC)."),
    calib: Optional[Path] = typer.Option(None, "--calib", help="YAML calibration for a generic folder pair."),
    rate: Optional[float] = typer.Option(None, "--rate", help=_RATE_HELP),
    time_offset: float = typer.Option(0.0, "--time-offset", help="Seconds added to every stamp (KITTI's times.txt starts at 0 s = 1970; e.g. 1.7e9 for a 2023 date)."),
    force: bool = typer.Option(False, "--overwrite", "--force", help="Replace OUT if it exists."),
) -> None:
    """Write a stereo sequence as a ROS bag: /camera/{left,right}/image_raw + camera_info, with the sequence's stamps."""
    from ..api import export_bag
    from ..io.outputs import check_output_file, refuse_input_as_output
    from ..io.times import UNIX_DATE_MIN_S
    from ..ros.bags import BAG_SUFFIX, check_format

    _check_option("--time-offset", time_offset, abs(time_offset) <= 1e10, "a time in seconds within +-1e10")
    kept = (f"{out} is the earlier bag, unchanged" if out.exists() and force
            else f"{out} holds the frames written so far (closed, readable)")
    with _job(kept) as job:
        if fmt is None:
            suffix = out.suffix.lower()
            fmt = next((k for k, v in BAG_SUFFIX.items() if v == suffix), None)
            if fmt is None:
                raise DynastereoError(f"--format not given and {out.name!r} has no .bag/.db3/.mcap suffix")
        fmt = check_format(fmt)
        if out.suffix.lower() != BAG_SUFFIX[fmt]:
            raise DynastereoError(f"a {fmt} bag must be named *{BAG_SUFFIX[fmt]}, got {out.name!r}")
        refuse_input_as_output(out, [sequence, calib], what="output bag", folders=[sequence])
        check_output_file(out, what="output bag", overwrite=force)
        with _progress() as prog:
            task = prog.add_task(f"export {fmt}", total=None, info="")

            def on_frame(i: int, n: int) -> None:
                prog.update(task, completed=i, total=n)
                job.tick(i, n)

            try:
                r = export_bag(sequence, out, fmt, frames=frames, calib=calib, color=color, encoding=encoding,
                               raw=raw, time_offset_s=time_offset, overwrite=force, progress=on_frame, rate=rate)
            except OSError as e:  # disk full, no permission, EIO: the bag is named
                raise DynastereoError(f"{out}: cannot write the bag ({e.strerror or e})") from None
            except Exception as e:  # sqlite3 (ROS 2 .db3): "database or disk is full"
                if type(e).__module__.split(".")[0] not in ("sqlite3", "_sqlite3"):
                    raise
                raise DynastereoError(f"{out}: cannot write the bag (sqlite: {e})") from None
    out_console.print(f"wrote {r.path} ({r.format}, {r.frames} frames): "
                      + ", ".join(f"{t} {n}" for t, n in r.topics.items()), highlight=False)
    if r.first_stamp_ns is not None and r.first_stamp_ns < UNIX_DATE_MIN_S * 1_000_000_000:
        out_console.print(f"note: the stamps start at {r.first_stamp_ns * 1e-9:g} s (1970); some ROS tools show "
                          "that oddly: --time-offset S shifts them (e.g. --time-offset 1.7e9)", highlight=False)


@app.command(context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def node(
    ctx: typer.Context,
    launch: bool = typer.Option(False, "--launch", help="Run `roslaunch dynastereo dynastereo.launch ARGS` (arg:=value ...)."),
    package_path: bool = typer.Option(False, "--package-path", help="Print the ROS package folder (for ROS_PACKAGE_PATH) and exit."),
    ros2: bool = typer.Option(False, "--ros2", help="The live ROS 2 node over DDS (no rclpy; needs the ros2 extra: pip install 'dynastereo[ros2]')."),
    params: Optional[Path] = typer.Option(None, "--params", help="ROS 2 parameters file (with --ros2): '/**: ros__parameters:' or 'dynastereo: ros__parameters:'."),
) -> None:
    """The live ROS 1 node (needs Debian's python3-rospy etc.; extra arguments go to ROS: remaps, _param:=value), or with --ros2 the ROS 2 node."""
    if ros2:
        from ..ros.ros2 import main as ros2_main

        if ctx.args:
            _fail(DynastereoError(f"unexpected arguments for the ROS 2 node: {' '.join(ctx.args)} "
                                  "(its parameters come from --params FILE)"))
        STOP.uninstall()  # the node handles SIGINT / SIGTERM itself (final BA, save)
        raise typer.Exit(ros2_main(str(params) if params is not None else None))
    if params is not None:
        _fail(DynastereoError("--params is for the ROS 2 node (--ros2); the ROS 1 node reads _param:=value"))
    from importlib.resources import files

    pkg = str(files("dynastereo.ros") / "ros_package")
    if package_path:
        print(pkg)
        return
    os.environ["DYNASTEREO_PYTHON"] = sys.executable
    paths = [p for p in os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep) if p]
    os.environ["ROS_PACKAGE_PATH"] = os.pathsep.join([pkg] + [p for p in paths if p != pkg])
    if launch:
        import shutil

        exe = shutil.which("roslaunch")
        if exe is None:
            _fail(DynastereoError("roslaunch not found (Debian: apt-get install python3-roslaunch rosout)"))
        os.execv(exe, [exe, "dynastereo", "dynastereo.launch", *ctx.args])
    from ..ros.ros1 import main as node_main

    STOP.uninstall()  # the node handles its signals itself (rospy)
    raise typer.Exit(node_main(["dynastereo_node", *ctx.args]))


@app.command("play")
def play_cmd(
    source: str = typer.Argument(..., help="A ROS 2 bag (.db3, .mcap) or a sequence folder."),
    ros2: bool = typer.Option(False, "--ros2", help="Publish over ROS 2 (DDS, no rclpy; the ros2 extra)."),
    rate: Optional[float] = typer.Option(None, "--rate", help="Frames per second (default: the stamps' own pace)."),
    lockstep: bool = typer.Option(False, "--lockstep", help="Each frame once the node's odometry of the previous one came back."),
    frames: Optional[str] = typer.Option(None, "--frames", help="Frames to play, e.g. 0-49."),
    stamp: str = typer.Option("sequence", "--stamp", help="Header stamps: 'sequence' (the source's) or 'now' (wall clock, for latency)."),
    wait: float = typer.Option(20.0, "--wait", help="Seconds to wait for the node's subscriptions."),
) -> None:
    """Publish a bag or a sequence folder as live camera topics (images + CameraInfo)."""
    if not ros2:
        _fail(DynastereoError("play needs --ros2 (the ROS 1 player: python -m dynastereo.ros.player SEQUENCE)"))
    _check_option("--rate", rate, rate is None or rate > 0, "a frame rate > 0 Hz")
    _check_option("--stamp", stamp, stamp in ("sequence", "now"), "sequence or now")
    from ..ros.dds import import_cyclonedds
    from ..ros.ros2_player import Ros2Player, open_source

    try:
        import_cyclonedds()
        seq, idx = open_source(source, frames)
        player = Ros2Player(seq, idx)
    except DynastereoError as e:
        _fail(e)
    if not player.wait_for_subscribers(wait):
        console.print(f"no subscriber after {wait:g} s; publishing anyway", highlight=False)
    log = player.play(rate, stamp=stamp, lockstep=lockstep)
    s = log.summary()
    out_console.print(f"published {s['published']} frames"
                      + (f", {s['answered']} answered, {s['timeouts']} timed out" if lockstep else
                         f" (late median {s['late_ms_median']:.1f} ms)"), highlight=False)
    import time

    time.sleep(0.5)  # reliable samples still in flight
    player.close()


@models_app.callback()
def models_main(
    ctx: typer.Context,
    models_dir: Optional[Path] = typer.Option(None, "--models-dir", help="Model directory (default: $DYNASTEREO_MODELS or the cache)."),
) -> None:
    """Without a subcommand: list the known models and whether they are present."""
    if ctx.invoked_subcommand is not None:
        return
    from ..models import list_models, resolve_models_dir

    d = resolve_models_dir(models_dir)
    print(f"models directory: {d}  (--models-dir, $DYNASTEREO_MODELS, or the cache)")
    for m in list_models(d):
        state = "ok" if m["verified"] else ("present, NOT verified" if m["present"] else "not downloaded")
        flag = "  [baseline only, AGPL: never a default]" if m["baseline_only"] else ""
        print(f"\n{m['name']:14s} {m['kind']:8s} {m['licence']}  -- {state}{flag}")
        print(f"  {m['description']}")
        for f in m["files"]:
            sha = f["sha256"] or "(unknown: format-checked only)"
            print(f"  {f['status']:8s} {f['filename']:24s} sha256 {sha}")
            print(f"           {f['url'] or '(no official download: ' + m['source'] + ')'}")


@models_app.command("download")
def models_download(
    names: list[str] = typer.Argument(..., help="Model names (see `dynastereo models`)."),
    dest: Optional[Path] = typer.Option(None, "--dest", help="Directory (default: $DYNASTEREO_MODELS or the cache)."),
    mirror: Optional[str] = typer.Option(None, "--mirror", help="Base URL serving <name>/<file> instead of the official addresses."),
) -> None:
    """Download models with checksum verification."""
    from ..models import download_models, resolve_models_dir

    try:
        d = resolve_models_dir(dest)
        paths = download_models(names, d, mirror=mirror)
    except DynastereoError as e:
        _fail(e)
    for p in paths:
        out_console.print(f"ok  {p}")


@models_app.command("verify")
def models_verify(
    names: Optional[list[str]] = typer.Argument(None, help="Model names (default: all present)."),
    models_dir: Optional[Path] = typer.Option(None, "--models-dir"),
) -> None:
    """Check the sha256 of the model files present."""
    from ..models import KNOWN_MODELS, resolve_models_dir, verify

    d = resolve_models_dir(models_dir)
    bad = 0
    for name in names or list(KNOWN_MODELS):
        problems = verify(name, d)
        if problems and not names and all("missing" in p for p in problems):
            continue
        bad += bool(problems)
        out_console.print(f"{'FAIL' if problems else 'ok  '} {name}" + ("".join(f"\n     {p}" for p in problems)))
    if bad:
        raise typer.Exit(1)


@app.command()
def synth(
    out: Optional[Path] = typer.Argument(None, help="Output root (KITTI odometry layout: OUT/sequences/00, OUT/poses/00.txt)."),
    scenario: str = typer.Option("mixed", help="Scenario name (see --list)."),
    list_: bool = typer.Option(False, "--list", help="List the scenarios and exit (no OUT needed; also `--scenario list`)."),
    frames: Optional[int] = typer.Option(None, help="Number of frames (default: the scenario's)."),
    seed: int = typer.Option(0, help="Random seed."),
    size: str = typer.Option("640x192", help="Image size WxH."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a sequence generated earlier in OUT."),
) -> None:
    """Generate a synthetic dynamic stereo street sequence with exact ground truth."""
    from ..io.outputs import SYNTH_OUTPUTS, OutputLock, prepare_output_dir
    from ..synth import SCENARIOS, generate
    from ..synth.writer import check_options

    if list_ or scenario == "list":
        for name, sc in SCENARIOS.items():
            out_console.print(f"{name:10s} {getattr(sc, 'description', '')}")
        return
    if out is None:
        _fail(DynastereoError("synth needs an output folder OUT (or --list)"))
    with _job(f"{out} holds the frames rendered so far (an incomplete sequence)") as job:
        w, h = check_options(scenario, frames, size)  # before an earlier sequence is cleared
        job_lock = OutputLock(out)
        job_lock.acquire()
        prepare_output_dir(out, overwrite=overwrite, names=SYNTH_OUTPUTS)
        with _progress() as prog:
            task = prog.add_task(f"synth {scenario}", total=None, info="")

            def on_frame(i: int, n: int) -> None:
                prog.update(task, completed=i, total=n)
                job.tick(i, n)

            seq = generate(out, scenario, frames=frames, seed=seed, size=(w, h), progress=on_frame)
    out_console.print(f"wrote {seq}")


@app.command()
def demo(
    out: Optional[Path] = typer.Option(None, "--out", help="Where to write (default: a new temporary directory)."),
    scenario: str = typer.Option("convoy", help="Synthetic scenario (see `dynastereo synth --list`)."),
    frames: int = typer.Option(60, help="Frames to generate."),
    detector: Optional[str] = typer.Option(None, help="Detector (default: yolox-nano if its weights are present, else the oracle)."),
    models_dir: Optional[Path] = typer.Option(None, "--models-dir", help="Model directory (default: $DYNASTEREO_MODELS or the cache)."),
    viewer: bool = typer.Option(False, "--viewer", help="Show the outline-masked run live in the rerun viewer (needs `pip install dynastereo[viz]`)."),
    rrd: Optional[Path] = typer.Option(None, "--rrd", help="Record the outline-masked run into FILE.rrd for the rerun viewer."),
) -> None:
    """Embedded default, offline: synthetic dynamic scene -> SLAM unmasked vs masked, evaluated against GT; an HTML report per run."""
    from ..demo import run_demo

    _check_option("--frames", frames, 2 <= frames <= 100_000, "a number of frames in 2..100000 (the runs are scored against the ground truth: 2 poses at least)")
    try:
        run_demo(out, scenario=scenario, frames=frames, detector=detector, models_dir=models_dir,
                 console=out_console, progress=_progress, viewer=viewer, rrd=rrd)
    except DynastereoError as e:
        _fail(e)


@app.command("config")
def config_cmd(
    config: Optional[Path] = typer.Argument(None, help="A YAML (or ORB-SLAM2 settings) file to check and print merged with the defaults."),
) -> None:
    """Print the configuration (defaults, or FILE merged over them) as YAML."""
    from ..config import dump_config

    try:
        cfg = _build_config(config, {})
    except DynastereoError as e:
        _fail(e)
    print(dump_config(cfg), end="")


def _run_ground_truth(estimate: Path) -> Path:
    """The ground truth of the sequence a run's ``run.json`` (beside ``estimate``) names."""
    import json

    from ..errors import InputError
    from ..eval.trajectory import recorded_ground_truth

    run = estimate.parent / "run.json"
    try:
        record = json.loads(run.read_text()) if run.is_file() else {}
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read it ({e})", run) from None
    if not isinstance(record, dict):
        raise InputError("not a JSON object", run)
    gt = recorded_ground_truth(record, run)
    if gt is None:
        raise InputError("no ground truth given, and none found for the run's sequence (run.json beside the "
                         "estimate: KITTI poses/NN.txt, a KITTI raw drive's oxts/)", estimate)
    return gt


@app.command("eval")
def eval_cmd(
    estimate: Path = typer.Argument(..., help="Estimated trajectory (KITTI 3x4 rows or TUM)."),
    ground_truth: Optional[Path] = typer.Argument(None, help="Ground truth (KITTI or TUM, or a KITTI raw drive folder: its oxts/); a longer one is cut to the estimate. Default: the run's sequence's own (run.json beside the estimate: KITTI poses/NN.txt, a raw drive's oxts/)."),
    as_json: bool = typer.Option(False, "--json", help="Print the numbers as JSON (keys ape.rmse, ape.mean, ..., drift_percent)."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Trajectory plot PNG (default: beside the estimate)."),
    no_align: bool = typer.Option(False, "--no-align", help="Do not SE(3)-align before APE."),
    rpe_delta: int = typer.Option(1, "--rpe-delta", help="RPE step in frames."),
    match: str = typer.Option("auto", "--match", help="How rows are paired: auto (stamps when both have them, else frame index) | index (frame index whatever the stamps say: a video's run against KITTI poses)."),
) -> None:
    """APE (thesis table), RPE, drift and the KITTI odometry metric, with evo; writes a top-view plot."""
    import json

    from ..eval import evaluate_files, format_table, plot_trajectories, to_json_dict
    from ..io.outputs import check_output_file, refuse_input_as_output

    _check_option("--rpe-delta", rpe_delta, 1 <= rpe_delta <= 100_000, "a step of 1..100000 frames")
    implicit = ground_truth is None
    try:
        if ground_truth is None:
            ground_truth = _run_ground_truth(estimate)
        png = plot or estimate.with_name(estimate.name.split(".")[0] + "_vs_gt.png")
        refuse_input_as_output(png, [estimate, ground_truth], what="plot file", flag="--plot")
        if plot is not None or estimate.is_file():
            check_output_file(png, what="plot file")
        r = evaluate_files(estimate, ground_truth, align=not no_align, rpe_delta=rpe_delta, match=match)
        try:
            plot_trajectories(r.estimate, r.ground_truth, png, title=f"{estimate.name} vs {ground_truth.name}")
        except OSError as e:  # disk full, no permission: the plot is named
            raise DynastereoError(f"{png}: cannot write the plot ({e.strerror or e})") from None
    except DynastereoError as e:
        _fail(e)
    if as_json:
        d = to_json_dict(r)
        d["plot"] = str(png)
        print(json.dumps(d, indent=1))
    else:
        print(format_table(r))
        if implicit:
            print(f"ground truth: {ground_truth} (the run's sequence's, from run.json)")
        print(f"plot: {png}")


@app.command("bench")
def bench_cmd(
    root: Path = typer.Argument(..., help="Dataset root: KITTI odometry (sequences/NN + poses/NN.txt), KITTI raw drives, EuRoC folders, or a folder of `dynastereo synth` outputs."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder: results.json, tables.md, plots/, runs/<sequence>/<masker>/r<k>/."),
    sequences: Optional[str] = typer.Option(None, "--sequences", help="Which sequences: ranges and names, e.g. 00-10 or 03,07 or 'convoy/*' (default: all found)."),
    maskers: str = typer.Option("none,box,outline,seg", "--maskers", help="Comma list of none, box, outline, seg."),
    repeats: int = typer.Option(1, "--repeats", help="Runs per sequence and masker (seed = config seed + repeat); runs are deterministic: more than 1 only to measure timing."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML configuration (or ORB-SLAM2 settings) for every job."),
    detector: Optional[str] = typer.Option(None, "--detector", help="Detector for every job (overrides the configuration), e.g. oracle for synthetic sequences."),
    frames: Optional[str] = typer.Option(None, "--frames", help="Frames of every sequence: a count N or ranges a-b (default: all)."),
    engine: str = typer.Option("local", "--engine", help="local (process pool) | ray."),
    address: Optional[str] = typer.Option(None, "--address", help="[ray] Join this Ray cluster (host:6379, ray://host:10001, auto) instead of starting a local instance."),
    workers: Optional[int] = typer.Option(None, "--workers", "-j", help="Jobs at a time (local processes / local Ray CPUs); default: the CPU cores."),
    threads: int = typer.Option(1, "--threads", help="Threads per job (detector.threads, slam.threads)."),
    models_dir: Optional[Path] = typer.Option(None, "--models-dir", help="Model directory (default: $DYNASTEREO_MODELS or the cache)."),
    no_plots: bool = typer.Option(False, "--no-plots", help="Do not draw plots/ate.png and plots/trajectories_*.png."),
) -> None:
    """Benchmark a whole dataset: every (sequence, masker, repeat) as a job, in parallel, resumable, with the thesis' tables."""
    from ..api import bench

    _check_option("--repeats", repeats, 1 <= repeats <= 100, "a number of runs in 1..100")
    _check_option("--workers", workers, workers is None or 1 <= workers <= 1024, "a number of jobs at a time in 1..1024")
    _check_option("--threads", threads, 0 <= threads <= 256, "a number of threads in 0..256 (0: the library's default)")
    bar = _progress()
    task = bar.add_task("bench frames", total=None, info="")

    def on_progress(p: dict) -> None:
        running = ", ".join(p["running"][:3]) + (" ..." if len(p["running"]) > 3 else "")
        failed = f", {p['jobs_failed']} failed" if p["jobs_failed"] else ""
        bar.update(task, completed=p["frames_done"], total=p["frames_total"] or None,
                   info=f"jobs {p['jobs_done']}/{p['jobs_total']}{failed}" + (f", running {running}" if running else ""))
        ev = p.get("event")
        if ev and ev[0] == "failed":
            bar.console.print(f"[yellow]job {ev[1]} failed[/] (retried once; errors in results.json)", highlight=False)

    try:
        with bar:
            result = bench(root, out, sequences=sequences, maskers=maskers, repeats=repeats, config=config,
                           overrides={"detector.name": detector}, frames=frames, engine=engine, address=address,
                           workers=workers, threads=threads, models_dir=models_dir, plots=not no_plots,
                           progress=on_progress)
    except KeyboardInterrupt:
        console.print(f"[bold yellow]interrupted[/]: {out / 'results.json'} and tables.md hold the finished runs; "
                      "run the same command again to continue", highlight=False)
        raise typer.Exit(130)
    except DynastereoError as e:
        _fail(e)
    print(result.tables_path.read_text())
    reused = sum(bool(r.get("reused")) for r in result.runs)
    out_console.print(
        f"{result.count('done')} of {len(result.runs)} runs done ({reused} reused), {result.count('failed')} failed, "
        f"in {result.wall_s:.1f} s -> {result.results_path}, {result.tables_path}", highlight=False)
    if result.count("failed"):
        raise typer.Exit(1)


@app.command("vocab")
def vocab_cmd(
    images: list[str] = typer.Argument(..., help="Image files, folders (the images directly inside) or glob patterns ('**' recurses)."),
    out: Path = typer.Option(..., "--out", "-o", help="Vocabulary file to write (.npz; use it with slam.vocabulary in the config)."),
    k: int = typer.Option(12, "--k", help="Branching factor of the vocabulary tree."),
    levels: int = typer.Option(4, "--levels", help="Depth of the tree: at most k**levels words."),
    features: int = typer.Option(2000, "--features", help="ORB features per image."),
    seed: int = typer.Option(0, "--seed", help="Random seed (k-means++ seeding); the same seed and images give the same vocabulary."),
) -> None:
    """Train an ORB bag-of-words vocabulary (place recognition, loop closing) on images."""
    import time

    from ..slam.vocabulary import collect_images, train_from_images

    _check_option("--k", k, 2 <= k <= 64, "a branching factor in 2..64")
    _check_option("--levels", levels, 1 <= levels <= 8, "a tree depth in 1..8")
    _check_option("--k / --levels", k**levels, k**levels <= 10_000_000, "at most 10^7 words (k**levels)")
    _check_option("--features", features, 1 <= features <= 100_000, "a number of ORB features per image in 1..100000")

    from ..io.outputs import check_output_file

    try:
        check_output_file(out, what="vocabulary file")
        paths = collect_images(images)
        t0 = time.perf_counter()
        with _progress() as prog:
            tasks = {"features": prog.add_task("ORB features", total=len(paths), info=""),
                     "train": prog.add_task("k-medians", total=levels, info=f"k={k}, {levels} levels")}

            def on_progress(stage: str, done: int, total: int) -> None:
                prog.update(tasks[stage], completed=done, total=total)

            vocab = train_from_images(paths, k=k, levels=levels, n_features=features, seed=seed, progress=on_progress)
        out.parent.mkdir(parents=True, exist_ok=True)
        vocab.save(out)
    except DynastereoError as e:
        _fail(e)
    except OSError as e:
        _fail(DynastereoError(f"{out}: {e.strerror or e}"))
    out_console.print(
        f"{len(paths)} images, {vocab.meta['descriptors']} descriptors -> {vocab.n_words} words (k={k}, {levels} levels) "
        f"in {time.perf_counter() - t0:.1f} s; wrote {out} ({out.stat().st_size / 1024:.0f} KiB)", highlight=False)


def main() -> None:
    """The ``dynastereo`` entry point.  Whatever a command leaves uncaught ends in one line:
    a :class:`DynastereoError` (bad input) or an OS error (a file system failure no
    check foresaw) exits 2, SIGINT / SIGTERM exit 130 / 143 (module ``signals``)."""
    logging.basicConfig(level=os.environ.get("DYNASTEREO_LOG", "WARNING").upper(),
                        format="%(levelname)s %(name)s: %(message)s")
    STOP.install()
    try:
        app()
    except Interrupted as e:
        console.print(f"[bold yellow]interrupted[/] by {e.name}", highlight=False)
        sys.exit(e.exit_code)
    except DynastereoError as e:
        console.print(f"[bold red]error:[/] {e}", soft_wrap=True, highlight=False)
        sys.exit(2)
    except OSError as e:
        where = f"{e.filename}: " if e.filename else ""
        text = str(e.strerror or e).strip().splitlines()[0] if str(e.strerror or e).strip() else type(e).__name__
        if "shared object" in text or "shared library" in text:  # a library that could not be mapped
            text = text.split(". ")[0] + " (a memory limit (`ulimit -v`) too tight to load it, or a broken install?)"
        console.print(f"[bold red]error:[/] {where}{text}", soft_wrap=True, highlight=False)
        sys.exit(2)
    except MemoryError as e:
        console.print(f"[bold red]error:[/] {memory_error_line(e)}", soft_wrap=True, highlight=False, markup=True)
        sys.exit(2)
    except ImportError as e:
        console.print(f"[bold red]error:[/] {import_error_line(e)}", soft_wrap=True, highlight=False, markup=True)
        sys.exit(2)
    finally:
        STOP.uninstall()


def memory_error_line(e: MemoryError) -> str:
    """One line for a failed allocation: what could not be allocated, and the way out."""
    what = str(e).strip().splitlines()[0] if str(e).strip() else "an allocation failed"
    return (f"out of memory: {what} (the input needs more memory than this process may use: free memory, "
            "`ulimit -v`; try fewer frames or smaller images)")


def import_error_line(e: ImportError) -> str:
    """One line for a package that failed to load (missing, or no memory to map it)."""
    name = e.name or (str(e).split("'")[1] if "'" in str(e) else "a package")
    why = str(e).strip().splitlines()[0] if str(e).strip() else "import failed"
    low = why.lower()
    hint = ("a memory limit (`ulimit -v`) too tight to load it?" if any(w in low for w in ("memory", "map", "shared object"))
            else "is it installed in this environment? (`make install`, or `pip install dynastereo`)")
    return f"cannot load {name}: {why} ({hint})"


if __name__ == "__main__":
    main()
