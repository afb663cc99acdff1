"""Jobs that chain the stages over a sequence and write the results.

``run_mask_job`` is what ``dynastereo mask`` runs: for each requested frame it masks
both images and writes, as it goes (so a failure never loses earlier frames)::

    DIR/masks/left/NNNNNN.png    uint8, 255 = dynamic
    DIR/masks/right/NNNNNN.png   uint8, 255 = dynamic
    DIR/disparity/NNNNNN.png     uint16, disparity*256 (KITTI), with save_disparity
    DIR/overlays/NNNNNN.png      left|right with masks and boxes drawn, with overlays
    DIR/objects.jsonl            one JSON line per frame: what was masked and how
    DIR/timing.json              per frame and per stage ms + summary (median, p90)

These names are a contract that later tools read.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import queue
import threading
import time
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from .errors import OutputError, as_interrupt
from .io.base import Sequence
from .io.images import write_disparity_png
from .io.outputs import RowFile, atomic_write_text, reserve_json, write_bytes, write_failed, write_json_reserved, write_ply
from .masking.base import Masker
from .masking.maskers import MASK_STAGES
from .viz.draw import draw_overlay
from .observers import FrameEvent, FrameObserver, notify
from .timing import StageTimer
from .datatypes import StereoFrame, StereoMasks

log = logging.getLogger(__name__)



def frame_name(index: int) -> str:
    return f"{index:06d}.png"


@dataclass
class MaskJobResult:
    out: Path
    frames_done: list[int] = field(default_factory=list)
    timer: StageTimer = field(default_factory=StageTimer)
    error: str | None = None
    wall_s: float = 0.0

    @property
    def summary(self) -> dict[str, dict[str, float]]:
        return self.timer.summary()


def new_mask_timer() -> StageTimer:
    t = StageTimer()
    t.add_derived("mask", MASK_STAGES)
    return t


def objects_record(idx: int, masks: StereoMasks) -> dict:
    """The ``objects.jsonl`` line of a frame: what was masked and how."""
    record = {
        "frame": idx,
        "objects": [o.to_dict() for o in masks.objects],
        "fallbacks": sum(o.method.is_fallback for o in masks.objects),
    }
    if masks.ground is not None:  # the road line the outlines left out (ok=False: not removed)
        record["road"] = masks.ground.to_dict()
    return record


def _write_png(path: Path, img: np.ndarray) -> None:
    """PNG-encode ``img`` and write it; a failed write (disk full, no permission, EIO)
    removes the partial file and raises an OutputError naming it."""
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        from .errors import OutputError, as_interrupt

        raise OutputError("cannot encode the image as PNG", path)
    write_bytes(path, buf.tobytes())


def _unlink_quietly(paths: list[Path]) -> None:
    for p in paths:
        try:
            p.unlink(missing_ok=True)
        except OSError:
            pass


def run_mask_job(
    sequence: Sequence,
    masker: Masker,
    out: str | Path,
    frames: list[int],
    *,
    save_disparity: bool = False,
    overlays: bool = False,
    progress: Callable[[int, int, dict], None] | None = None,
    observers: tuple[FrameObserver, ...] = (),
) -> MaskJobResult:
    """Mask ``frames`` of ``sequence`` with ``masker`` and write the results under ``out``.

    On an exception the frames already done stay on disk, ``timing.json`` is written
    with an ``error`` entry, and the exception propagates.
    """
    out = Path(out)
    dirs = {"left": out / "masks" / "left", "right": out / "masks" / "right"}
    if save_disparity:
        dirs["disparity"] = out / "disparity"
    if overlays:
        dirs["overlays"] = out / "overlays"
    for d in dirs.values():
        d.mkdir(parents=True, exist_ok=True)

    result = MaskJobResult(out=out, timer=new_mask_timer())
    timer = result.timer
    t0 = time.perf_counter()
    meta = {"masker": getattr(masker, "name", type(masker).__name__), "sequence": str(sequence.path)}
    try:
        with RowFile(out / "objects.jsonl") as objects_log:
            for k, idx in enumerate(frames):
                t_read = time.perf_counter()
                frame = sequence.frame(idx)
                read_ms = (time.perf_counter() - t_read) * 1000.0
                timer.start_frame(idx)
                timer.add("read", read_ms)
                masks = masker.mask(frame, timer)
                rec = timer.end_frame()
                name = frame_name(idx)
                if save_disparity and masks.disparity is None:
                    raise RuntimeError(f"masker {meta['masker']} produced no full-frame disparity")
                written: list[Path] = []
                before = len(result.frames_done)
                try:  # a failed write (or a signal) takes this frame's files back out: every output agrees
                    for d, img in (("left", masks.left), ("right", masks.right)):
                        written.append(dirs[d] / name)
                        _write_png(dirs[d] / name, img)
                    if save_disparity:
                        written.append(dirs["disparity"] / name)
                        write_disparity_png(dirs["disparity"] / name, masks.disparity)
                    if overlays:
                        written.append(dirs["overlays"] / name)
                        _write_png(dirs["overlays"] / name, draw_overlay(frame, masks))
                    objects_log.append(json.dumps(objects_record(idx, masks)) + "\n")
                    result.frames_done.append(idx)
                except BaseException:
                    if len(result.frames_done) == before:  # not done: none of its files stay
                        objects_log.truncate(before)
                        _unlink_quietly(written)
                    raise
                notify(observers, FrameEvent(k, frame, masks, rec["ms"], calibration=sequence.calibration))
                if progress is not None:
                    progress(k + 1, len(frames), rec)
    except BaseException as exc:
        e = as_interrupt(exc)
        result.error = f"{type(e).__name__}: {e}"
        if e is not exc:
            raise e from None
        raise
    finally:
        result.wall_s = time.perf_counter() - t0
        del timer.frames[len(result.frames_done):]  # a frame whose outputs failed is not done
        extra = dict(meta, frames_done=len(result.frames_done), frames_requested=len(frames),
                     wall_s=round(result.wall_s, 3))
        if result.error:
            extra["error"] = result.error
        try:
            timer.write(out / "timing.json", **extra)
        except OSError as e:
            if result.error is None:  # else the first error is the one to report
                raise write_failed(e, out / "timing.json") from None
    return result


# --------------------------------------------------------------------------- SLAM job

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
    report: Path | None = None  # the HTML report, when one was asked for (api.run_sequence(report=True))

    @property
    def summary(self) -> dict[str, dict[str, float]]:
        return self.timer.summary()


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("dynastereo", "numpy", "opencv-contrib-python-headless", "gtsam", "onnxruntime", "evo"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def _masking_step(sequence: Sequence, masker: Masker | None, idx: int,
                  motion=None) -> tuple[StereoFrame, StereoMasks | None, dict]:
    """Read and mask one frame, and measure its objects' flow for the motion test
    (``motion_flow``); its own timer (this runs on the prefetch thread)."""
    t = new_mask_timer()
    t.start_frame(idx)
    with t.stage("read"):
        frame = sequence.frame(idx)
    masks = masker.mask(frame, t) if masker is not None else None
    if motion is not None:
        with t.stage("motion_flow"):
            motion.measure(frame, masks)
    return frame, masks, t.end_frame()["ms"]


#: The longest wait for the prefetch thread's masks of a frame (the first frame's include
#: loading the detector and compiling kernels): past it the frame is masked inline and
#: the run goes on without prefetch, recorded in run.json's ``fallbacks``.
PREFETCH_TIMEOUT_S = 120.0


class _Prefetcher:
    """One daemon thread that reads and masks frame k+1 while frame k is tracked.  The
    hand-over (:meth:`result`) waits on the frame's future with a bound, never a polling
    loop; a daemon thread, so a stuck detector cannot keep the process from exiting."""

    def __init__(self, timeout_s: float | None) -> None:
        self.timeout_s = PREFETCH_TIMEOUT_S if timeout_s is None else float(timeout_s)
        self.inline = False
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._loop, name="prefetch", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while True:
            item = self._jobs.get()
            if item is None:
                return
            fut, fn, args = item
            if fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(fn(*args))
                except BaseException as e:  # noqa: BLE001 -- handed over to the main thread
                    fut.set_exception(e)

    def submit(self, fn, *args) -> Future:
        fut: Future = Future()
        fut.call = (fn, args)  # type: ignore[attr-defined]
        if not self.inline:
            self._jobs.put((fut, fn, args))
        return fut

    def result(self, fut: Future, k: int, idx: int, fallbacks: list[dict]):
        fn, args = fut.call  # type: ignore[attr-defined]
        if self.inline:
            return fn(*args)
        try:
            return fut.result(timeout=self.timeout_s)
        except FutureTimeout:
            fut.cancel()
            self.inline = True
            fallbacks.append({"frame": int(idx), "position": int(k), "what": "prefetch",
                              "action": "masked inline from here on",
                              "reason": f"no masks from the prefetch thread within {self.timeout_s:g} s"})
            log.warning("frame %d: no masks from the prefetch thread within %g s; masking inline from here on",
                        idx, self.timeout_s)
            return fn(*args)

    #: how long close() waits for a frame being masked to finish (bounded: a stuck one is left)
    JOIN_S = 10.0

    def close(self) -> None:
        """Stop the thread, waiting (at most ``JOIN_S`` s) for the frame it is masking: a
        thread still inside onnxruntime while the interpreter exits aborts the process
        ("terminate called without an active exception") after the outputs were written."""
        self._jobs.put(None)
        self._thread.join(self.JOIN_S)


def _status(error: str | None) -> str:
    """run.json's ``status``: ``done``, ``interrupted: SIGINT`` or ``failed: <reason>``."""
    if error is None:
        return "done"
    if error.startswith("Interrupted: "):
        return "interrupted: " + error.split(": ", 1)[1].split()[0]
    return f"failed: {error}"


def _save_map(system, save_map: str | Path | None, sequence: Sequence, done: list[int],
              map_info: dict | None) -> dict:
    """The final map into ``save_map`` (when frames were done); the run.json ``map`` entry
    (``save_error`` when it failed: raised once the run's files are written)."""
    map_out = dict(map_info or {})
    if save_map is not None and done:
        try:
            system.save_map(save_map, meta={"sequence": str(getattr(sequence, "path", "")),
                                            "frames": [int(i) for i in done]})
            map_out["saved"] = str(save_map)
        except Exception as e:  # noqa: BLE001 -- reported, and raised when the run itself went well
            map_out["save_error"] = f"{type(e).__name__}: {e}"
    return map_out


def _write_final_trajectory(out: Path, poses: np.ndarray, stamps: np.ndarray, done: list[int]) -> None:
    """The trajectory files again, with the final (bundle-adjusted) poses of the frames done."""
    from .eval.trajectory import FRAMES_NAME, write_kitti, write_tum

    for path, write in ((out / "trajectory.kitti.txt", lambda p: write_kitti(p, poses)),
                        (out / "trajectory.tum.txt", lambda p: write_tum(p, poses, stamps[done])),
                        (out / FRAMES_NAME, lambda p: atomic_write_text(p, "".join(f"{i}\n" for i in done)))):
        try:
            write(path)
        except OSError as e:  # the live rows stay (atomic writes): the files still agree
            raise write_failed(e, path) from None


def _run_record(sequence: Sequence, masker: Masker | None, motion, frames: list[int], n_done: int, system,
                stats: dict, map_out: dict, fps: float, wall: float, config_dict: dict | None) -> dict:
    """``run.json``: what ran (sequence, masker, motion test, configuration, versions) and
    what came of it (frames tracked / lost, keyframes, map points, loops, recoveries, map)."""
    states = system.results() if n_done else []
    lost = [k for k, s in enumerate(states) if s.status == "lost"]
    return {
        "sequence": str(getattr(sequence, "path", "")),
        "timestamps": getattr(sequence, "timestamp_source", None),
        "masker": getattr(masker, "name", "none") if masker is not None else "none",
        "motion": ({"mode": "moving", "map_points_forgotten": motion.forgotten} if motion is not None
                   else {"mode": "all" if masker is not None else "none"}),
        "frames_requested": len(frames),
        "frames_done": n_done,
        **(sequence.run_info() if hasattr(sequence, "run_info") else {}),  # a camera: frames dropped
        **({"frame_gaps": gaps} if (gaps := list(getattr(sequence, "missing_frames", []) or [])) else {}),
        "frames_tracked": sum(s.status in ("tracked", "init") for s in states),
        "frames_lost": len(lost),
        "lost": [{"position": k, "frame": frames[k], "map_id": states[k].map_id} for k in lost],
        "keyframes": stats.get("keyframes"),
        "map_points": stats.get("map_points"),
        "stats": stats,
        "loops": [e.to_dict() for e in system.loops()] if n_done else [],
        "recoveries": [dataclasses.asdict(r) for r in system.recoveries()] if n_done else [],
        "map": map_out,
        "fps": round(fps, 3),
        "wall_s": round(wall, 3),
        "config": config_dict or {},
        "versions": _versions(),
    }


def _world_objects(sequence: Sequence, masker: Masker | None, motion, out: Path):
    """The objects' world tracker and its ``objects_tracks.csv`` for a masked run (slam.objects)."""
    if masker is None or getattr(sequence, "calibration", None) is None:
        return None, None
    from .slam.objects import TRACKS_NAME, TrackWriter, WorldObjects

    mc = getattr(motion, "cfg", None)
    kw = {"sigma_disparity": mc.sigma_disparity, "sigma_px": mc.sigma_px} if mc is not None else {}
    return WorldObjects(sequence.calibration, **kw), TrackWriter(out / TRACKS_NAME)


def run_slam_job(
    sequence: Sequence,
    masker: Masker | None,
    system,
    out: str | Path,
    frames: list[int],
    *,
    config_dict: dict | None = None,
    save_masks: bool = False,
    prefetch: bool = True,
    progress: Callable[[int, int, dict], None] | None = None,
    save_map: str | Path | None = None,
    map_info: dict | None = None,
    observers: tuple[FrameObserver, ...] = (),
    motion=None,
    prefetch_timeout_s: float | None = None,
    save_cloud: str | Path | None = None,
) -> SlamJobResult:
    """Feed ``frames`` of ``sequence`` (masked by ``masker``, None = unmasked) to the SLAM
    ``system`` and write, under ``out``:

    * ``trajectory.kitti.txt`` / ``trajectory.tum.txt`` / ``trajectory.frames.txt``: one
      row per frame fed, in order; appended live (a crash keeps every row written), then
      rewritten at the end with the final, bundle-adjusted poses;
    * ``objects.jsonl`` (masked runs): one line per frame, as from ``run_mask_job``, each
      object with its place in the world (``world``, ``velocity``, ``speed``, ``extent``:
      :mod:`dynastereo.slam.objects`), and ``objects_tracks.csv`` (one row per object and frame);
    * ``timing.json``: per frame ms for ``masking`` (= ``detect`` + ``mask``), ``features``,
      ``stereo``, ``track``; ``local_mapping`` separately; ``summary.fps`` end to end;
    * ``run.json``: configuration, versions, frames tracked / lost, keyframes, map points,
      ``loops`` (every loop closed), ``recoveries`` (frames tracked again after lost ones),
      ``map`` (the map file loaded / saved);
    * ``save_map``: the final map (``System.save_map``), also after an error mid-sequence
      (the map of the frames done);
    * ``save_cloud``: the final map's points as PLY, less any inside a box an object judged
      moving or undecided had (``slam.objects.WorldObjects.outside_movers``);
    * and whatever the ``observers`` write (a bag's writer, a viewer): each gets a
      :class:`~dynastereo.observers.FrameEvent` per frame once it is tracked.

    Masking of frame k+1 runs on a prefetch thread while frame k is tracked (OpenCV and
    onnxruntime release the GIL).

    ``motion`` (a :class:`~dynastereo.masking.motion.ObjectMotion`, None = every
    detection masked): its flow is measured on the prefetch thread; SLAM gets the masks of
    the objects judged moving or not yet judged (``select``, from the verdicts up to the
    previous frame), and after tracking the verdicts are updated with this frame's
    camera motion (``motion`` stage) -- ``objects.jsonl`` and ``masks/`` show them.
    """
    from .eval.trajectory import TrajectoryWriter

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if save_masks:
        for side in ("left", "right"):
            (out / "masks" / side).mkdir(parents=True, exist_ok=True)
    timer = StageTimer()
    timer.add_derived("masking", ("detect",) + MASK_STAGES)
    # a live source (a camera) has no stamps before its frames: each frame carries its own
    stamps = None if getattr(sequence, "live", False) else np.asarray(sequence.timestamps(), dtype=np.float64)
    frame_stamps: list[float] = []
    prefetcher = _Prefetcher(prefetch_timeout_s) if prefetch else None
    error: str | None = None
    t0 = time.perf_counter()
    n_done = 0

    def submit(k: int):
        if k >= len(frames):
            return None
        if prefetcher is None:
            return _masking_step(sequence, masker, frames[k], motion)
        return prefetcher.submit(_masking_step, sequence, masker, frames[k], motion)

    fallbacks: list[dict] = []
    writer = objects_log = world = tracks = None
    try:
        # run.json first, with room for the final record: the folder says how the run ended
        # even when the disk fills up (io.outputs.write_json_reserved), and a run killed
        # outright (SIGKILL) is known as one ("status": "running", no end).
        reserve_json(out / "run.json", json.dumps({"status": "running", "frames_requested": len(frames),
                                                   "sequence": str(getattr(sequence, "path", ""))}))
        objects_log = RowFile(out / "objects.jsonl") if masker is not None else None
        world, tracks = _world_objects(sequence, masker, motion, out)
        writer = TrajectoryWriter(out)
        pending = submit(0)
        for k, idx in enumerate(frames):
            if prefetcher is None:
                frame, masks, mask_ms = pending
            else:
                frame, masks, mask_ms = prefetcher.result(pending, k, idx, fallbacks)
            pending = submit(k + 1)
            timer.start_frame(idx)
            for name, ms in mask_ms.items():
                if name not in ("total", "mask"):
                    timer.add(name, ms)
            slam_masks = motion.select(masks) if motion is not None else masks
            stamp = frame.timestamp if stamps is None else float(stamps[idx])
            frame_stamps.append(stamp)
            tracked = system.track(frame, slam_masks, timer)
            pose = tracked.pose
            if motion is not None:
                with timer.stage("motion"):
                    motion.update(masks, tracked, system)
            if world is not None:
                with timer.stage("objects"):
                    world.update(masks, pose, str(tracked.status) in ("tracked", "init"), stamp)
                    tracks.write(idx, stamp, masks)
            rec = timer.end_frame(status=tracked.status)
            writer.append(pose, frame_index=idx, timestamp=stamp)
            written: list[Path] = []
            try:  # a failed write takes the frame back out of every output: they agree
                if save_masks and slam_masks is not None:
                    for side, img in (("left", slam_masks.left), ("right", slam_masks.right)):
                        written.append(out / "masks" / side / frame_name(idx))
                        _write_png(written[-1], img)
                if objects_log is not None:
                    objects_log.append(json.dumps(objects_record(idx, masks)) + "\n")
                n_done = k + 1  # its outputs are written: what follows (an observer too) may fail, they stay
            except BaseException:
                if n_done == k:  # not done: none of its outputs stay
                    writer.truncate(k)
                    if objects_log is not None:
                        objects_log.truncate(k)
                    _unlink_quietly(written)
                raise
            notify(observers, FrameEvent(k, frame, slam_masks, rec["ms"], pose, tracked.status, system,
                                         sequence.calibration))
            if progress is not None:
                progress(k + 1, len(frames), dict(rec, fps=n_done / (time.perf_counter() - t0)))
    except BaseException as exc:
        e = as_interrupt(exc)
        error = f"{type(e).__name__}: {e}"
        if e is not exc:
            raise e from None
        raise
    finally:
        # Clean-up in steps that each run whatever happens before them (a signal while the
        # BA finishes, a full disk): timing.json and run.json are always written last.
        late: BaseException | None = None
        first_error = error
        for rows in (writer, objects_log):  # every row file holds the frames done, no more
            if rows is not None:
                rows.truncate(n_done)
                rows.close()
        if tracks is not None:
            tracks.close()
        map_out = dict(map_info or {})
        try:
            system.shutdown()  # finishes the pending local BA; also stops the worker on an error
            map_out = _save_map(system, save_map, sequence, frames[:n_done], map_info)
            if save_cloud is not None and n_done:
                pts = system.map_points()
                write_ply(save_cloud, pts[world.outside_movers(pts)] if world is not None else pts)
        except BaseException as e:  # noqa: BLE001 -- a signal breaking a wait: the files below are still written
            late = e
            error = error or f"{type(e).__name__}: {e}"
        if prefetcher is not None:
            prefetcher.close()
        wall = time.perf_counter() - t0
        fps = n_done / wall if wall > 0 else 0.0
        poses = system.trajectory() if n_done else np.zeros((0, 3, 4))
        del timer.frames[n_done:]  # a frame whose outputs failed is not done
        if error is None and n_done:
            try:
                _write_final_trajectory(out, poses, np.asarray(frame_stamps) if stamps is None else stamps,
                                        frames[:n_done])
            except OutputError as e:
                late, error = e, f"{type(e).__name__}: {e}"
        stats = system.stats().to_dict() if n_done else {}
        lost = system.lost_frames() if n_done else []
        try:
            timer.write(out / "timing.json", summary_extra={"fps": round(fps, 3)}, wall_s=round(wall, 3),
                        frames_done=n_done, local_mapping={k: v for k, v in stats.items() if k.startswith("local_ba")},
                        **({"error": error} if error else {}))
        except OSError as e:
            late = late or write_failed(e, out / "timing.json")
            error = error or f"{type(late).__name__}: {late}"
            (out / "timing.json.tmp").unlink(missing_ok=True)
        run = _run_record(sequence, masker, motion, frames, n_done, system, stats, map_out, fps, wall, config_dict)
        run["status"] = _status(error)
        if fallbacks:
            run["fallbacks"] = fallbacks
        if error:
            run["error"] = error
        try:
            write_json_reserved(out / "run.json", json.dumps(run, indent=1, default=float))
        except OutputError as e:
            late = late or e
        if late is not None and first_error is None:
            raise late
    if "save_error" in map_out:
        from .errors import DynastereoError

        raise DynastereoError(f"{save_map}: saving the map failed ({map_out['save_error']})")
    return SlamJobResult(out, poses, frames[:n_done], stats, timer, wall, fps, lost)
