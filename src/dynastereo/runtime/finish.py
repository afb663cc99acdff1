"""A job's last files, written whatever happened to it (a failure, a signal, a full disk).

A run (``dynastereo run``) ends in steps that each run whatever happens before them:
the SLAM finishes its pending local BA, the map and cloud are saved, the trajectory files
are rewritten with the final, bundle-adjusted poses (when the run went well), then
``timing.json`` and ``run.json`` (room for it reserved at the start, so the folder says how
the run ended even on a full disk: ``io.outputs.write_json_reserved``).  A mask job ends
with ``timing.json``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import DynastereoError, OutputError
from ..io.outputs import atomic_write_text, reserve_json, write_failed, write_json_reserved, write_ply
from .results import JobResult
from .spec import JobSpec

if TYPE_CHECKING:  # pragma: no cover
    from .job import Job
    from .loop import FrameLoop

log = logging.getLogger("dynastereo.mesh")


def resolve_ground_truth(gt: str | Path | None, sequence: Any) -> Path | None:
    """``gt``, else the sequence's own ground truth when it has one (KITTI odometry
    ``poses/NN.txt``, a KITTI raw drive's ``oxts/``)."""
    from ..eval.trajectory import find_ground_truth

    if gt is not None:
        return Path(gt)
    path = getattr(sequence, "path", sequence)
    return find_ground_truth(path) if isinstance(path, (str, Path)) else None


def checked_ground_truth(gt: Path, *, explicit: bool) -> Path | None:
    """``gt`` made absolute once it reads as a trajectory: a bad ``--gt`` (``explicit``) is
    an :class:`~dynastereo.errors.InputError` before anything is written; a bad one found
    beside the sequence is left out with a warning."""
    import logging

    from ..errors import InputError
    from ..eval.trajectory import read_trajectory

    try:
        read_trajectory(gt)
    except InputError as e:
        if explicit:
            raise InputError(f"--gt: {e}") from None
        logging.getLogger(__name__).warning("the ground truth found beside the sequence is not used: %s", e)
        return None
    return Path(gt).absolute()


def versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("dynastereo", "numpy", "opencv-contrib-python-headless", "gtsam", "onnxruntime", "evo"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def status(error: str | None) -> str:
    """run.json's ``status``: ``done``, ``interrupted: SIGINT`` or ``failed: <reason>``."""
    if error is None:
        return "done"
    if error.startswith("Interrupted: "):
        return "interrupted: " + error.split(": ", 1)[1].split()[0]
    return f"failed: {error}"


def reserve_run_json(out: Path, spec: JobSpec, n_frames: int) -> None:
    """run.json first, with room for the final record: a run killed outright (SIGKILL) is
    known as one (``"status": "running"``, no end)."""
    reserve_json(out / "run.json", json.dumps({"status": "running", "frames_requested": n_frames,
                                               "sequence": absolute(spec.source.name) or ""}))


def absolute(path: Any) -> str | None:
    """``path`` as an absolute path string (a camera ``cam:N`` and two videos ``a,b`` as
    they are given, each video made absolute); None for None / ""."""
    if path is None or str(path) == "":
        return None
    text = str(path)
    if text.startswith("cam:"):
        return text
    return ",".join(str(Path(p).absolute()) for p in text.split(","))


def calibration_file(seq: Any) -> str | None:
    """The calibration file a sequence was read with (absolute), when it says."""
    return absolute(getattr(seq, "calibration_file", None))


# --------------------------------------------------------------------------- mask job


def finish_mask(job: "Job", loop: "FrameLoop", error: str | None) -> JobResult:
    """``timing.json`` of a mask job (with ``error`` when it failed)."""
    st, timer = loop.state, loop.timer
    loop.close()
    out = job.spec.outputs.dir
    wall = time.perf_counter() - st.t0
    masker = job.processor.masker
    extra = {"masker": getattr(masker, "name", type(masker).__name__),
             "sequence": absolute(getattr(job.sequence, "path", None)) or "",
             "calibration": calibration_file(job.sequence),
             "frames_done": st.n_done, "frames_requested": len(job.frames), "wall_s": round(wall, 3)}
    if error:
        extra["error"] = error
    try:
        timer.write(out / "timing.json", **extra)
    except OSError as e:
        if error is None:  # else the first error is the one to report
            raise write_failed(e, out / "timing.json") from None
    return JobResult(out, list(job.frames[:st.n_done]), timer, wall, error=error)


# --------------------------------------------------------------------------- SLAM run


def _save_map_and_cloud(job: "Job", n_done: int) -> dict:
    """The final map (``--save-map``) and cloud (``--save-cloud``: none on a box an object
    judged moving or undecided had); run.json's ``map`` entry (``save_error`` when saving failed)."""
    o, system, world = job.spec.outputs, job.processor.system, job.processor.world
    map_out = dict(job.map_info)
    if o.save_map is not None and n_done:
        try:
            system.save_map(o.save_map, meta={"sequence": str(getattr(job.sequence, "path", "")),
                                              "frames": [int(i) for i in job.frames[:n_done]]})
            map_out["saved"] = str(o.save_map)
        except Exception as e:  # noqa: BLE001 -- reported, and raised when the run itself went well
            map_out["save_error"] = f"{type(e).__name__}: {e}"
    if o.save_cloud is not None and n_done:
        pts = system.map_points()
        write_ply(o.save_cloud, pts[world.outside_movers(pts)] if world is not None else pts)
    return map_out


def save_mesh(job: "Job") -> dict:
    """The static world's mesh (``--save-mesh``) and dense cloud (``--save-dense-cloud``),
    fused at the final poses (the SLAM shut down: its last BA done) from the keyframes the
    run kept (:mod:`dynastereo.mesh`); run.json's ``mesh`` entry.  Built after the frame
    loop: tracking never waits for it."""
    from ..mesh import fuse_system, write_cloud_ply, write_mesh_ply

    o, rec = job.spec.outputs, job.mesh_recorder
    res = fuse_system(rec, job.processor.system, job.sequence.calibration, job.spec.config)
    info = res.stats.to_dict()
    c = job.sequence.calibration
    info["camera"] = {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width, "height": c.height}
    if o.save_mesh is not None:
        write_mesh_ply(o.save_mesh, res.mesh)
        info["file"] = str(o.save_mesh)
    if o.save_dense_cloud is not None:
        write_cloud_ply(o.save_dense_cloud, res.mesh)
        info["dense_cloud"] = str(o.save_dense_cloud)
    if res.unmasked is not None:
        first = Path(o.save_mesh or o.save_dense_cloud)
        other = first.with_name(first.stem + "_unmasked.ply")
        (write_mesh_ply if o.save_mesh is not None else write_cloud_ply)(other, res.unmasked)
        info["unmasked_file"], info["unmasked_vertices"] = str(other), len(res.unmasked.vertices)
    for ob in job.observers:  # the viewers: the rerun viewer shows it (viz.rerun.RerunObserver.on_mesh)
        if hasattr(ob, "on_mesh"):
            ob.on_mesh(res.mesh)
    s = res.stats
    log.info("mesh: %d vertices, %d triangles from %d keyframes (%.1f MB of voxels, %.2f s CPU) -> %s",
             s.vertices, s.triangles, s.keyframes, s.voxel_bytes / 1e6, s.disparity_s + s.fusion_s + s.marching_s,
             o.save_mesh or o.save_dense_cloud)
    return info


def _write_final_trajectory(out: Path, poses: np.ndarray, stamps: np.ndarray, done: list[int]) -> None:
    """The trajectory files again, with the final (bundle-adjusted) poses of the frames done."""
    from ..eval.trajectory import FRAMES_NAME, write_kitti, write_tum

    for path, write in ((out / "trajectory.kitti.txt", lambda p: write_kitti(p, poses)),
                        (out / "trajectory.tum.txt", lambda p: write_tum(p, poses, stamps[done])),
                        (out / FRAMES_NAME, lambda p: atomic_write_text(p, "".join(f"{i}\n" for i in done)))):
        try:
            write(path)
        except OSError as e:  # the live rows stay (atomic writes): the files still agree
            raise write_failed(e, path) from None


def run_record(job: "Job", n_done: int, stats: dict, map_out: dict, fps: float, wall: float) -> dict:
    """``run.json``: what ran (sequence, masker, motion test, configuration, versions) and
    what came of it (frames tracked / lost, keyframes, map points, loops, recoveries, map)."""
    from ..config import to_dict

    seq, proc, frames = job.sequence, job.processor, job.frames
    system, masker, motion = proc.system, proc.masker, proc.motion
    states = system.results() if n_done else []
    lost = [k for k, s in enumerate(states) if s.status == "lost"]
    return {
        "sequence": absolute(getattr(seq, "path", None)) or "",
        "calibration": calibration_file(seq),
        "ground_truth": absolute(job.ground_truth),
        "timestamps": getattr(seq, "timestamp_source", None),
        "masker": getattr(masker, "name", "none") if masker is not None else "none",
        "motion": ({"mode": "moving", "map_points_forgotten": motion.forgotten} if motion is not None
                   else {"mode": "all" if masker is not None else "none"}),
        "frames_requested": len(frames),
        "frames_done": n_done,
        **(seq.run_info() if hasattr(seq, "run_info") else {}),  # a camera: frames dropped
        **({"frame_gaps": gaps} if (gaps := list(getattr(seq, "missing_frames", []) or [])) else {}),
        "frames_tracked": sum(s.status in ("tracked", "init") for s in states),
        "frames_lost": len(lost),
        "lost": [{"position": k, "frame": frames[k], "map_id": states[k].map_id} for k in lost],
        "keyframes": stats.get("keyframes"),
        "map_points": stats.get("map_points"),
        "stats": stats,
        "loops": [e.to_dict() for e in system.loops()] if n_done else [],
        "recoveries": [dataclasses.asdict(r) for r in system.recoveries()] if n_done else [],
        "map": map_out,
        **({"mesh": job.mesh_info} if job.mesh_info else {}),
        "fps": round(fps, 3),
        "wall_s": round(wall, 3),
        "config": to_dict(job.spec.config),
        "versions": versions(),
    }


def finish_run(job: "Job", loop: "FrameLoop", error: str | None) -> JobResult:
    """The run's last files (module doc); raises the first late error when the run itself went well."""
    st, timer, system, out = loop.state, loop.timer, job.processor.system, job.spec.outputs.dir
    n_done, first_error, late = st.n_done, error, None
    map_out = dict(job.map_info)
    try:
        system.shutdown()  # finishes the pending local BA
        map_out = _save_map_and_cloud(job, n_done)
    except BaseException as e:  # noqa: BLE001 -- a signal breaking a wait: the files below are still written
        late, error = e, error or f"{type(e).__name__}: {e}"
    loop.close()
    outputs, late = _close_output_observers(job, late)  # a bag's final map: after the last BA
    error = error or (f"{type(late).__name__}: {late}" if late is not None else None)
    wall = time.perf_counter() - st.t0
    fps = n_done / wall if wall > 0 else 0.0
    poses = system.trajectory() if n_done else np.zeros((0, 3, 4))
    if error is None and n_done:
        try:
            stamps = loop.processor.source.stamps_of(st.stamps)
            _write_final_trajectory(out, poses, stamps, job.frames[:n_done])
        except OutputError as e:
            late, error = e, f"{type(e).__name__}: {e}"
    if job.mesh_recorder is not None and n_done and error is not None:
        job.mesh_info = {"skipped": "the run did not finish: no mesh built"}
    elif job.mesh_recorder is not None and n_done:
        try:
            job.mesh_info = save_mesh(job)
        except (DynastereoError, MemoryError) as e:  # the grid's budget, an unwritable file: the run's files stay
            job.mesh_info = {"error": str(e)}
            late, error = late or e, error or f"{type(e).__name__}: {e}"
    stats = system.stats().to_dict() if n_done else {}
    try:
        timer.write(out / "timing.json", summary_extra={"fps": round(fps, 3)}, wall_s=round(wall, 3),
                    frames_done=n_done, local_mapping={k: v for k, v in stats.items() if k.startswith("local_ba")},
                    **({"error": error} if error else {}))
    except OSError as e:
        late = late or write_failed(e, out / "timing.json")
        error = error or f"{type(late).__name__}: {late}"
    late = _write_run_json(job, loop, error, stats, map_out, fps, wall) or late
    if late is not None and first_error is None:
        raise late
    if "save_error" in map_out and first_error is None:  # else the run's own error is the one raised
        raise DynastereoError(f"{job.spec.outputs.save_map}: saving the map failed ({map_out['save_error']})")
    lost = system.lost_frames() if n_done else []
    return JobResult(out, list(job.frames[:n_done]), timer, wall, fps=fps, poses=poses, stats=stats, lost=lost,
                     outputs=outputs, mesh=job.mesh_info or None)


def _close_output_observers(job: "Job", late: BaseException | None) -> tuple[dict, BaseException | None]:
    """Every :class:`~dynastereo.observers.OutputObserver` of the job closed (each even when
    one before it failed): ``({name: what it wrote}, the first failure)``."""
    from ..observers import OutputObserver

    outputs: dict = {}
    for ob in job.observers:
        if isinstance(ob, OutputObserver):
            try:
                outputs[ob.name] = ob.close()
            except BaseException as e:  # noqa: BLE001 -- the run's own files are still written
                late = late or e
    return outputs, late


def _write_run_json(job: "Job", loop: "FrameLoop", error: str | None, stats: dict, map_out: dict, fps: float,
                    wall: float) -> OutputError | None:
    run = run_record(job, loop.state.n_done, stats, map_out, fps, wall)
    run["status"] = status(error)
    if loop.fallbacks:
        run["fallbacks"] = loop.fallbacks
    if error:
        run["error"] = error
    try:
        write_json_reserved(job.spec.outputs.dir / "run.json", json.dumps(run, indent=1, default=float))
    except OutputError as e:
        return e
    return None
