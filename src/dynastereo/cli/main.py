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


def _run_source(sequence, bag, calib, rate, config, left_topic, right_topic, left_info, right_info,
                sync_tolerance, rectify, bag_outputs):
    """The run's :class:`~dynastereo.runtime.SourceSpec`: a folder / video / camera, or a bag
    (its CameraInfo topics ``auto`` / ``none`` / a topic; an ORB-SLAM2 settings file given as
    ``--config`` is its calibration when it has no CameraInfo)."""
    from ..runtime import BagSpec, SourceSpec
    from ..runtime.spec import settings_calibration

    if bag is None or sequence is not None:
        return SourceSpec(path=sequence, bag=None if bag is None else BagSpec(bag), calib=calib, rate=rate)
    info = {"auto": "auto", "none": None}
    spec = BagSpec(bag, left_topic, right_topic, info.get(left_info.lower(), left_info),
                   info.get(right_info.lower(), right_info), sync_tolerance / 1000.0, rectify,
                   settings_calibration(config), bag_outputs)
    return SourceSpec(bag=spec, calib=calib, rate=rate)


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
    save_map: Optional[Path] = typer.Option(None, "--save-map", help="Write the final map to FILE (docs/map_format.md)."),
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
                       localize_only=localize_only, stereo_check=not no_stereo_check, gt=gt)
        with _progress() as prog:
            task = prog.add_task("tracking", total=None, info="")

            def on_frame(done: int, total: int, rec: dict) -> None:
                total = total if total < sys.maxsize else None  # a camera (io.video.UNBOUNDED): no end
                prog.update(task, completed=done, total=total, info=f"{rec['fps']:.1f} FPS  {rec['status']}")
                job.tick(done, total)

            result = run_job(spec, progress=on_frame)
            if bag is not None:
                result = result.slam
    bag_report = result.bag
    out_console.print(timing_table(result.summary, "timing (ms per frame)"))
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
                          f"keyframes -> {save_mesh or save_dense_cloud}")
    if bag_report is not None:
        r = bag_report
        out_console.print(
            f"bag: {r['pairs']} stereo pairs from {r['left_topic']} + {r['right_topic']} "
            f"(unpaired: {r['unpaired_left']} left, {r['unpaired_right']} right, "
            f"tolerance {r['tolerance_s'] * 1000:g} ms); calibration: {r['calibration_source']}"
            f"{', rectified on read' if r['rectified_on_read'] else ''}; output bag {r['output_bag']}",
            highlight=False)
    if result.report is not None:
        out_console.print(f"report: {result.report}", highlight=False)
    if rrd is not None:
        out_console.print(f"recording: {rrd} (open it with `rerun {rrd}`)", highlight=False)


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

    _check_option("--overlays", overlays, overlays >= 0, "a count of images >= 0")
    try:
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

    try:
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
    from ..io.outputs import check_output_file
    from ..io.times import UNIX_DATE_MIN_S
    from ..ros.bags import BAG_SUFFIX, check_format

    with _job(f"{out} holds the frames written so far (closed, readable)") as job:
        if fmt is None:
            suffix = out.suffix.lower()
            fmt = next((k for k, v in BAG_SUFFIX.items() if v == suffix), None)
            if fmt is None:
                raise DynastereoError(f"--format not given and {out.name!r} has no .bag/.db3/.mcap suffix")
        fmt = check_format(fmt)
        if out.suffix.lower() != BAG_SUFFIX[fmt]:
            raise DynastereoError(f"a {fmt} bag must be named *{BAG_SUFFIX[fmt]}, got {out.name!r}")
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
) -> None:
    """The live ROS 1 node (needs Debian's python3-rospy etc.; extra arguments go to ROS: remaps, _param:=value)."""
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
    from ..io.outputs import SYNTH_OUTPUTS, prepare_output_dir
    from ..synth import SCENARIOS, generate

    if list_ or scenario == "list":
        for name, sc in SCENARIOS.items():
            out_console.print(f"{name:10s} {getattr(sc, 'description', '')}")
        return
    if out is None:
        _fail(DynastereoError("synth needs an output folder OUT (or --list)"))
    try:
        w, h = (int(v) for v in size.lower().split("x"))
    except ValueError:
        _fail(DynastereoError(f"--size must be WxH, got {size!r}"))
    with _job(f"{out} holds the frames rendered so far (an incomplete sequence)") as job:
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
    from ..eval.trajectory import find_ground_truth

    run = estimate.parent / "run.json"
    seq = json.loads(run.read_text()).get("sequence") if run.is_file() else None
    gt = find_ground_truth(seq) if seq else None
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
) -> None:
    """APE (thesis table), RPE, drift and the KITTI odometry metric, with evo; writes a top-view plot."""
    import json

    from ..eval import evaluate_files, format_table, plot_trajectories, to_json_dict
    from ..io.outputs import check_output_file

    _check_option("--rpe-delta", rpe_delta, rpe_delta >= 1, "a step of >= 1 frames")
    try:
        if ground_truth is None:
            ground_truth = _run_ground_truth(estimate)
        png = plot or estimate.with_name(estimate.name.split(".")[0] + "_vs_gt.png")
        if plot is not None or estimate.is_file():
            check_output_file(png, what="plot file")
        r = evaluate_files(estimate, ground_truth, align=not no_align, rpe_delta=rpe_delta)
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
        print(f"plot: {png}")


@app.command("bench")
def bench_cmd(
    root: Path = typer.Argument(..., help="Dataset root: KITTI odometry (sequences/NN + poses/NN.txt), KITTI raw drives, EuRoC folders, or a folder of `dynastereo synth` outputs."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder: results.json, tables.md, plots/, runs/<sequence>/<masker>/r<k>/."),
    sequences: Optional[str] = typer.Option(None, "--sequences", help="Which sequences: ranges and names, e.g. 00-10 or 03,07 or 'convoy/*' (default: all found)."),
    maskers: str = typer.Option("none,box,outline,seg", "--maskers", help="Comma list of none, box, outline, seg."),
    repeats: int = typer.Option(3, "--repeats", help="Runs per sequence and masker (seed = config seed + repeat)."),
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

    _check_option("--repeats", repeats, repeats >= 1, "a number of runs >= 1")
    _check_option("--workers", workers, workers is None or workers >= 1, "a number of jobs at a time >= 1")
    _check_option("--threads", threads, threads >= 0, "a number of threads >= 0 (0: the library's default)")
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

    _check_option("--k", k, k >= 2, "a branching factor >= 2")
    _check_option("--levels", levels, levels >= 1, "a tree depth >= 1")
    _check_option("--features", features, features >= 1, "a number of ORB features per image >= 1")

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
        console.print(f"[bold red]error:[/] {where}{e.strerror or e}", soft_wrap=True, highlight=False)
        sys.exit(2)
    finally:
        STOP.uninstall()


if __name__ == "__main__":
    main()
