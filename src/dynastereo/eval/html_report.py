"""One self-contained HTML page of a run (``dynastereo report RUN_DIR``).

Reads what ``run_slam_job`` / ``run_mask_job`` wrote (``run.json``, ``timing.json``,
``trajectory.kitti.txt`` + ``trajectory.frames.txt``, ``objects.jsonl``,
``masks/{left,right}/``) and, with a ground truth, evaluates the trajectory with
:func:`dynastereo.eval.evaluate_files`.  Every plot is a matplotlib PNG (the mask overlays
JPEG) inlined as a ``data:`` URI; the page needs no network and no other file.

Sections (each only when its input exists): summary, trajectory (top and side view),
accuracy (APE over time, the thesis' APE table, RPE, drift, KITTI metric), time per
stage (stacked per frame, medians), mask overlays (first, worst, evenly spaced),
objects per frame (by class; by ``moving`` decision when the records carry one).

Every key number is also in the page as ``<td data-key="KEY">`` (``frames_tracked``,
``ape.rmse``, ``timing.track.median``...) so that a test or a script can read it back.
"""

from __future__ import annotations

import base64
import html
import io
import json
import logging
import math
from collections import Counter
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from matplotlib.figure import Figure

from ..dotted import flatten_dotted
from ..errors import InputError
from .metrics import STAT_KEYS, EvalResult, evaluate_files
from .plot import _new_figure, plot_ape_over_time, plot_trajectories
from .report import format_table
from .trajectory import FRAMES_NAME, KITTI_NAME, read_frame_indices, read_trajectory, recorded_ground_truth

REPORT_NAME = "report.html"
SUMMARY_KEYS = ("frames_requested", "frames_done", "frames_tracked", "frames_lost", "keyframes", "map_points",
                "fps", "wall_s")
log = logging.getLogger(__name__)
LEGACY_DERIVED = {"mask", "masking"}  # timing.json written before it listed its derived stages
OVERLAY_WIDTH = 960  # px, the overlays are scaled down to this width
OVERLAY_JPEG_QUALITY = 85  # camera images: JPEG is ~10x smaller than PNG; the plots stay PNG


@dataclass
class RunFiles:
    """What a run folder holds (None / empty when a file is absent)."""

    root: Path
    run: dict[str, Any]
    timing: dict[str, Any] | None
    objects: list[dict[str, Any]]
    frames: np.ndarray | None  # trajectory row -> frame index
    partial: str | None = None  # why the run's files are incomplete (an interrupted run), None when whole


def _read_json(path: Path) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise InputError(f"not valid JSON ({e.msg}, line {e.lineno})", path) from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read it ({e})", path) from None
    if not isinstance(data, dict):
        raise InputError(f"not a JSON object (a {type(data).__name__}): not written by dynastereo", path)
    return data


def read_run(run_dir: str | Path) -> RunFiles:
    """The files of a run folder; :class:`InputError` when it has neither ``run.json``
    nor ``timing.json``."""
    root = Path(run_dir)
    if not root.is_dir():
        raise InputError("no such run folder", root)
    run = _read_json(root / "run.json")
    timing = _read_json(root / "timing.json")
    rows = _row_count(root)
    partial = None
    if run is None and timing is None:
        if rows is None and not (root / "objects.jsonl").is_file():
            raise InputError("neither run.json nor timing.json: not the output of `dynastereo run` or `mask`", root)
        partial = ("the run was interrupted before it wrote run.json and timing.json (killed?): this report is "
                   f"made from the {rows or 0} trajectory rows and the objects.jsonl lines written")
        run = {"status": "interrupted", "frames_done": rows or 0}
    elif run is not None and run.get("status") == "running":
        partial = ("the run was interrupted before it finished (killed?: run.json still says \"running\"): this "
                   f"report is made from the {rows or 0} trajectory rows written")
        run = dict(run, status="interrupted", frames_done=rows or 0)
    if partial is None and run is not None and "frames_done" in run:
        # a finished run's files: name those that are gone rather than show an empty page
        wanted = ["timing.json", KITTI_NAME, "trajectory.tum.txt", FRAMES_NAME] if run.get("frames_done") else []
        missing = [n for n in wanted if not (root / n).is_file()]
        if missing:
            partial = (f"{', '.join(missing)} {'is' if len(missing) == 1 else 'are'} missing from the run folder "
                       "(deleted or moved?): this report shows only what is left")
    objects = []
    obj_path = root / "objects.jsonl"
    if obj_path.is_file():
        for n, line in enumerate(obj_path.read_text().splitlines(), 1):
            if line.strip():
                try:
                    rec = json.loads(line)
                except json.JSONDecodeError as e:
                    raise InputError(f"line {n}: not valid JSON ({e.msg})", obj_path) from None
                if not isinstance(rec, dict) or not isinstance(rec.get("objects", []), list):
                    raise InputError(f"line {n}: not a frame's record (a JSON object with a list of objects)",
                                     obj_path)
                objects.append(rec)
    frames = read_frame_indices(root / FRAMES_NAME) if (root / FRAMES_NAME).is_file() else None
    if partial is not None and frames is not None and rows is not None:
        frames = frames[:rows]  # a row cut by the kill: the files agree on the rows they all hold
    return RunFiles(root, run or {}, timing, objects, frames, partial)


def _row_count(root: Path) -> int | None:
    """Whole rows in all of the run's trajectory files (the least of them), None without any."""
    counts = []
    for name in (KITTI_NAME, "trajectory.tum.txt", FRAMES_NAME):
        p = root / name
        if p.is_file():
            text = p.read_text(errors="replace")
            counts.append(text.count("\n"))  # a last row without its newline was cut by the kill
    return min(counts) if counts else None


def partial_reason(run_dir: str | Path) -> str | None:
    """Why a run folder's report is partial (an interrupted run), or None."""
    try:
        return read_run(run_dir).partial
    except InputError:
        return None


# --------------------------------------------------------------------------- HTML pieces


def _esc(v: Any) -> str:
    return html.escape(str(v))


def _fmt(v: Any) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        if not math.isfinite(v):
            return "n/a"
        return f"{v:.4g}" if abs(v) < 1000 else f"{v:.1f}"
    return str(v)


def _table(rows: list[list[Any]], head: list[str] | None = None, keys: list[list[str | None]] | None = None) -> str:
    """An HTML table; ``keys[r][c]`` puts ``data-key`` on a cell."""
    out = ["<table>"]
    if head:
        out.append("<tr>" + "".join(f"<th>{_esc(h)}</th>" for h in head) + "</tr>")
    for r, row in enumerate(rows):
        cells = []
        for c, v in enumerate(row):
            key = keys[r][c] if keys else None
            attr = f' data-key="{_esc(key)}"' if key else ""
            cells.append(f"<td{attr}>{_esc(_fmt(v))}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</table>")
    return "".join(out)


def _kv_table(items: list[tuple[str, Any, str | None]]) -> str:
    """Two-column table of (label, value, data-key)."""
    return _table([[k, v] for k, v, _ in items], keys=[[None, key] for _, _, key in items])


def _img(data: bytes, alt: str, mime: str = "image/png") -> str:
    return f'<img alt="{_esc(alt)}" src="data:{mime};base64,{base64.b64encode(data).decode()}">'


def _figure(size: tuple[float, float]) -> Figure:
    return _new_figure(size, dpi=90)


def _png_of(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _plot_png(fn, *args, **kwargs) -> bytes:
    """PNG bytes of one of ``eval.plot``'s functions (they write to a file object)."""
    buf = io.BytesIO()
    fn(*args, buf, **kwargs)
    return buf.getvalue()


# --------------------------------------------------------------------------- sections


def _summary_section(rf: RunFiles) -> str:
    run = rf.run
    cfg = run.get("config", {})
    items: list[tuple[str, Any, str | None]] = [("sequence", run.get("sequence") or (rf.timing or {}).get("sequence"),
                                                 "sequence")]
    items.append(("masker", run.get("masker") or (rf.timing or {}).get("masker"), "masker"))
    if cfg.get("detector"):
        items.append(("detector", cfg["detector"].get("name"), "detector"))
    items += [(k.replace("_", " "), run.get(k), k) for k in SUMMARY_KEYS if k in run]
    items.append(("loops closed", len(run.get("loops", [])), "loops"))
    items.append(("relocalizations / recoveries", len(run.get("recoveries", [])), "recoveries"))
    if run.get("map"):
        items += [(f"map {k}", v, f"map.{k}") for k, v in run["map"].items()]
    if rf.timing and not run:
        items += [("frames done", rf.timing.get("frames_done"), "frames_done"),
                  ("wall s", rf.timing.get("wall_s"), "wall_s")]
    parts = ["<h2>Summary</h2>", _kv_table(items)]
    if rf.partial:
        parts.insert(0, f'<p class="error" data-key="partial">partial report: {_esc(rf.partial)}</p>')
    if run.get("error") or (rf.timing or {}).get("error"):
        parts.append(f'<p class="error">run failed: {_esc(run.get("error") or rf.timing["error"])}</p>')
    if run.get("loops"):
        heads = ["frame", "loop frame", "score", "inliers", "correction m", "correction deg", "points fused"]
        rows = [[e.get("frame_index"), e.get("loop_frame_index"), e.get("score"), e.get("inliers"),
                 e.get("correction_m"), e.get("correction_deg"), e.get("points_fused")] for e in run["loops"]]
        parts += ["<h3>Loops closed</h3>", _table(rows, heads)]
    if run.get("recoveries"):
        heads = ["frame", "lost frames before", "method", "map"]
        rows = [[r.get("frame_index"), r.get("lost_frames"), r.get("method"), r.get("map_id")]
                for r in run["recoveries"]]
        parts += ["<h3>Tracked again after lost frames</h3>", _table(rows, heads)]
    if run.get("lost"):
        parts.append("<p>lost frames: " + _esc(", ".join(str(x["frame"]) for x in run["lost"])) + "</p>")
    if cfg:
        parts.append("<details><summary>settings (configuration of the run)</summary>"
                     + _table([[k, json.dumps(v) if isinstance(v, (list, tuple)) else v]
                                              for k, v in flatten_dotted(cfg).items()], ["key", "value"]) + "</details>")
    if run.get("versions"):
        parts.append("<details><summary>versions</summary>"
                     + _table([[k, v] for k, v in run["versions"].items()], ["package", "version"]) + "</details>")
    return "\n".join(parts)


def _trajectory_section(rf: RunFiles, ev: EvalResult | None, gt_path: Path | None) -> str:
    kitti = rf.root / KITTI_NAME
    if not kitti.is_file():
        return ""
    if ev is not None:
        est, gt = ev.estimate, ev.ground_truth
        note = f"estimate SE(3)-aligned to the ground truth {gt_path}" if ev.aligned else "not aligned"
    else:
        est, gt = read_trajectory(kitti), None
        note = "no ground truth (give --gt FILE)"
    est.name = ""
    plots = [_img(_plot_png(plot_trajectories, {"estimate": est}, gt, title=f"{view} view", plane=plane),
                  f"trajectory {view} view") for view, plane in (("top", "auto"), ("side", "side"))]
    return f'<h2>Trajectory</h2><p>{_esc(note)}</p><div class="row">{"".join(plots)}</div>'


def _accuracy_section(ev: EvalResult | None) -> str:
    if ev is None:
        return ""
    heads = ["", *(f"{k} (m²)" if k == "sse" else f"{k} (m)" for k in STAT_KEYS)]
    rows = [["APE", *(ev.ape[k] for k in STAT_KEYS)]]
    keys = [[None, *(f"ape.{k}" for k in STAT_KEYS)]]
    if ev.rpe:
        rows.append([f"RPE d={ev.rpe_delta}", *(ev.rpe[k] for k in STAT_KEYS)])
        keys.append([None, *(f"rpe.{k}" for k in STAT_KEYS)])
    if ev.rpe_rot_deg:
        rows.append([f"RPE rot (deg) d={ev.rpe_delta}", *(ev.rpe_rot_deg.get(k) for k in STAT_KEYS)])
        keys.append([None, *(f"rpe_rot_deg.{k}" for k in STAT_KEYS)])
    drift_items = [("drift %", ev.drift_percent, "drift_percent"), ("drift m (final position error)", ev.drift_m,
                                                                     "drift_m"),
                   ("ground-truth path m", ev.path_length_m, "path_length_m"), ("frames matched", ev.n_frames,
                                                                              "n_frames"),
                   ("KITTI t_err %", ev.kitti.t_err_percent if ev.kitti else None, "kitti.t_err_percent"),
                   ("KITTI r_err deg/100 m", ev.kitti.r_err_deg_per_100m if ev.kitti else None,
                    "kitti.r_err_deg_per_100m")]
    return ("<h2>Accuracy</h2>" + _img(_plot_png(plot_ape_over_time, ev), "APE over time")
            + "<h3>APE and RPE (translation part)</h3>" + _table(rows, heads, keys)
            + "<h3>Drift</h3>" + _kv_table(drift_items)
            + f"<details><summary>as printed by <code>dynastereo eval</code></summary><pre>{_esc(format_table(ev))}"
            "</pre></details>")


def leaf_stages(timing: dict[str, Any]) -> list[str]:
    """The stages that do not sum others (``derived`` ones and ``total`` left out), in order."""
    derived = set(timing.get("derived", {})) if "derived" in timing else LEGACY_DERIVED
    names: list[str] = []
    for f in timing.get("frames", []):
        names += [k for k in f["ms"] if k not in names and k not in derived and k != "total"]
    return names


def _timing_section(timing: dict[str, Any] | None) -> str:
    if not timing or not timing.get("frames"):
        return ""
    frames = timing["frames"]
    leaves = leaf_stages(timing)
    x = np.arange(len(frames))
    stack = np.array([[f["ms"].get(s, 0.0) for f in frames] for s in leaves])
    fig = _figure((9.0, 3.6))
    ax = fig.add_subplot()
    ax.stackplot(x, stack, labels=leaves, alpha=0.85)
    ax.plot(x, [f["ms"].get("total", np.nan) for f in frames], color="k", lw=1, label="total (end to end)")
    ax.set_xlabel("frame (in the order fed)")
    ax.set_ylabel("ms")
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=8, ncols=4)
    ax.set_title("time per stage, stacked (masking runs on a prefetch thread beside tracking)")
    summary = timing.get("summary", {})
    names = [k for k, v in summary.items() if isinstance(v, dict)]
    rows = [[k, summary[k].get("median"), summary[k].get("p90"), summary[k].get("mean"), summary[k].get("n")]
            for k in names]
    keys = [[None, f"timing.{k}.median", f"timing.{k}.p90", f"timing.{k}.mean", None] for k in names]
    extra = [(k, v, f"timing.{k}") for k, v in summary.items() if not isinstance(v, dict)]
    return ("<h2>Time per stage</h2>" + _img(_png_of(fig), "time per stage")
            + _table(rows, ["stage", "median ms", "p90 ms", "mean ms", "frames"], keys)
            + (_kv_table(extra) if extra else ""))


def _mask_frames(rf: RunFiles) -> list[int]:
    d = rf.root / "masks" / "left"
    if not d.is_dir():
        return []
    return sorted(int(p.stem) for p in d.glob("*.png") if p.stem.isdigit())


def pick_sample_frames(available: list[int], worst: int | None, n: int = 6) -> list[tuple[int, str]]:
    """(frame, why): the first, the worst (when known), then evenly spaced ones; no repeats."""
    if not available:
        return []
    picks = [(available[0], "first")]
    if worst is not None and worst in available and worst != available[0]:
        picks.append((worst, "worst"))
    for i in np.linspace(0, len(available) - 1, max(n - len(picks), 0) + 2).round().astype(int)[1:]:
        f = available[int(i)]
        if all(f != p for p, _ in picks) and len(picks) < n:
            picks.append((f, "evenly spaced"))
    return picks


def _objects_by_frame(rf: RunFiles) -> dict[int, list]:
    from ..datatypes import ObjectMask

    fields = set(ObjectMask.__dataclass_fields__)
    out = {}
    for rec in rf.objects:
        out[int(rec["frame"])] = [ObjectMask(**{k: (tuple(v) if k == "box" else v) for k, v in o.items()
                                                if k in fields}) for o in rec.get("objects", [])]
    return out


def _overlay_section(rf: RunFiles, ev: EvalResult | None, n: int) -> str:
    available = _mask_frames(rf)
    if not available or n <= 0:
        return ""
    from ..viz.draw import draw_overlay
    from ..datatypes import StereoFrame, StereoMasks

    worst, why_worst = None, ""
    if ev is not None and rf.frames is not None and len(rf.frames) == len(ev.ape_errors):
        worst, why_worst = int(rf.frames[int(np.argmax(ev.ape_errors))]), "largest APE"
    else:  # the largest masked fraction of the left image
        frac = {f: float(np.count_nonzero(cv2.imread(str(rf.root / "masks/left" / f"{f:06d}.png"), 0)))
                for f in available}
        worst, why_worst = max(frac, key=frac.get), "largest masked area"
    seq = None
    if rf.run.get("sequence") and Path(str(rf.run["sequence"])).is_absolute():  # a relative one: not known where
        try:
            from ..io import open_sequence

            seq = open_sequence(Path(rf.run["sequence"]))
        except Exception:  # noqa: BLE001 -- the overlays then show the masks alone
            seq = None
    objects = _objects_by_frame(rf)
    figs = []
    for f, why in pick_sample_frames(available, worst, n):
        left = cv2.imread(str(rf.root / "masks/left" / f"{f:06d}.png"), cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(str(rf.root / "masks/right" / f"{f:06d}.png"), cv2.IMREAD_GRAYSCALE)
        if left is None or right is None:
            continue
        frame = seq.frame(f) if seq is not None and f < len(seq) else None
        if frame is None:
            frame = StereoFrame(f, 0.0, np.full_like(left, 96), np.full_like(right, 96))
        img = draw_overlay(frame, StereoMasks(left, right, objects.get(f, [])))
        scale = OVERLAY_WIDTH / img.shape[1]
        if scale < 1:
            img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, OVERLAY_JPEG_QUALITY])
        label = f"frame {f} ({why}{': ' + why_worst if why == 'worst' else ''})"
        figs.append(f"<figure>{_img(jpg.tobytes(), label, 'image/jpeg')}<figcaption>{_esc(label)}</figcaption></figure>")
    note = "" if seq is not None else "<p>(sequence images not found: masks on grey)</p>"
    return ("<h2>Masks</h2><p>left | right, masked pixels tinted; boxes by the motion test's verdict: "
            "red moving, orange not yet judged (both masked), green static (left to SLAM); thin: box fallback</p>"
            + note + "".join(figs))


def _objects_section(rf: RunFiles) -> str:
    if not rf.objects:
        return ""
    frames = [int(r["frame"]) for r in rf.objects]
    x = np.arange(len(frames))
    by_class = [Counter(o.get("label", "?") for o in r.get("objects", [])) for r in rf.objects]
    classes = sorted(set().union(*by_class))
    has_decision = any("moving" in o for r in rf.objects for o in r.get("objects", []))
    fig = _figure((9.0, 3.4 * (2 if has_decision else 1)))
    axes = fig.subplots(2 if has_decision else 1, 1, squeeze=False)[:, 0]
    if classes:
        axes[0].stackplot(x, [[c[k] for c in by_class] for k in classes], labels=classes, alpha=0.85)
    axes[0].set_title("objects per frame by class")
    if has_decision:
        name = {True: "moving", False: "static", None: "undecided"}
        by_dec = [Counter(name.get(o.get("moving"), "undecided") for o in r.get("objects", [])) for r in rf.objects]
        decs = ["moving", "static", "undecided"]
        axes[1].stackplot(x, [[c[k] for c in by_dec] for k in decs], labels=decs,
                          colors=["tab:red", "tab:green", "tab:gray"], alpha=0.85)
        axes[1].set_title("objects per frame by decision")
    for ax in axes:
        ax.set_xlabel("frame (in the order fed)")
        ax.set_ylabel("objects")
        ax.grid(True, alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="upper left", fontsize=8, ncols=4)
    total = Counter(o.get("label", "?") for r in rf.objects for o in r.get("objects", []))
    methods = Counter(o.get("method", "?").split(":")[0] for r in rf.objects for o in r.get("objects", []))
    rows = [[k, v] for k, v in total.most_common()]
    return ("<h2>Objects</h2>" + _img(_png_of(fig), "objects per frame")
            + "<h3>detections over the run</h3>" + _table(rows, ["class", "objects (sum over frames)"])
            + _table([[k, v] for k, v in methods.most_common()], ["mask method", "objects"]))


VIEW_MARGIN = 40.0  # m around the camera path in the objects' top view


def _object_paths_section(rf: RunFiles) -> str:
    """Top view of the camera path with every object's path (``objects_tracks.csv``,
    coloured by the track's verdict: moving when the motion test said so in most of its
    frames), and speed over time per moving object."""
    from ..objects.world import MOVING_MIN_FRAMES, TRACKS_NAME, moving_tracks, read_tracks, track_verdict, verdict_rgb

    path = rf.root / TRACKS_NAME
    if not path.is_file():
        return ""
    tracks = read_tracks(path)
    if not tracks:
        return ""
    cam = read_trajectory(rf.root / KITTI_NAME).positions if (rf.root / KITTI_NAME).is_file() else None

    verdict = track_verdict
    movers = moving_tracks(tracks)
    fig = _figure((9.0, 6.0))
    ax = fig.subplots()
    for k, t in tracks.items():
        if len(t["frame"]) < 2:
            continue
        c = np.array(verdict_rgb(verdict(t))) / 255.0
        ax.plot(t["xyz"][:, 0], t["xyz"][:, 2], "-", color=c, lw=1.6 if k in movers else 0.9,
                alpha=0.9 if k in movers else 0.6)
        if k in movers:
            ax.annotate(f"#{k} {t['label']}", t["xyz"][-1, [0, 2]], fontsize=7, color=c)
    if cam is not None:
        ax.plot(cam[:, 0], cam[:, 2], "-", color="tab:blue", lw=2.2, label="camera")
        ax.plot(cam[:1, 0], cam[:1, 2], "o", color="tab:blue")
    ax.plot([], [], color=np.array(verdict_rgb(True)) / 255, label="object, moving")
    ax.plot([], [], color=np.array(verdict_rgb(False)) / 255, label="object, static")
    ax.plot([], [], color=np.array(verdict_rgb(None)) / 255, label="object, undecided")
    if cam is not None:  # the camera's surroundings: far objects' paths would shrink the view
        lo, hi = cam[:, [0, 2]].min(axis=0) - VIEW_MARGIN, cam[:, [0, 2]].max(axis=0) + VIEW_MARGIN
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m), forward at the start")
    ax.set_title("top view: the camera and the objects' paths (the trajectory's frame)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    html = ["<h2>Objects in the world</h2>",
            f"<p>{len(tracks)} tracked objects, {len(movers)} judged moving (moving in most of the frames the "
            f"motion test decided, seen in at least {MOVING_MIN_FRAMES} frames: "
            "<code>dynastereo.objects.world.moving_tracks</code>, <code>result.moving_objects</code>); "
            "positions and velocities from "
            f"<code>{TRACKS_NAME}</code> (<code>objects.jsonl</code>: <code>world</code>, <code>velocity</code>, "
            "<code>speed</code>)</p>", _img(_png_of(fig), "objects' paths, top view")]
    if movers:
        fig = _figure((9.0, 3.6))
        ax = fig.subplots()
        for k, t in movers.items():  # where the filter has settled (speed sigma <= 1.5 m/s)
            sp = np.where(t["speed_sigma"] <= 1.5, t["speed"], np.nan)
            ax.plot(t["stamp"], sp, ".-", lw=1.4, ms=3, label=f"#{k} {t['label']}")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("speed (m/s)")
        ax.set_title("speed over time, moving objects (where its sigma <= 1.5 m/s)")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize=7, ncols=3)
        rows = [[f"#{k}", t["label"], len(t["frame"]), f"{t['frame'][0]}-{t['frame'][-1]}",
                 _fmt(float(np.nanmedian(t["speed"]))) if np.isfinite(t["speed"]).any() else "-",
                 _fmt(float(np.linalg.norm(t["xyz"][-1] - t["xyz"][0])))] for k, t in movers.items()]
        html += [_img(_png_of(fig), "speed over time"),
                 _table(rows, ["track", "class", "frames", "frame range", "median speed (m/s)", "moved (m)"])]
    return "".join(html)


STYLE = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:1.5em auto;max-width:1100px;
color:#222;background:#fff;padding:0 1em}
h1{font-size:1.6em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0}td,th{border:1px solid #ddd;padding:.2em .6em;text-align:right}
td:first-child,th:first-child{text-align:left}th{background:#f3f3f3}
img{max-width:100%;height:auto}.row{display:flex;flex-wrap:wrap;gap:1em}.row img{max-width:48%}
figure{margin:.6em 0}figcaption{font-size:.9em;color:#555}.error{color:#b00;font-weight:bold}
pre{background:#f7f7f7;padding:.6em;overflow-x:auto}
"""


def build_report(
    run_dir: str | Path,
    gt: str | Path | None = None,
    out: str | Path | None = None,
    *,
    overlays: int = 6,
    auto_gt: bool = True,
) -> Path:
    """Write the HTML page of the run in ``run_dir`` (default ``RUN_DIR/report.html``).

    ``gt``: ground-truth trajectory (KITTI or TUM); without it, with ``auto_gt``, the
    KITTI layout's ``poses/NN.txt`` beside the run's sequence when it exists.
    ``overlays``: how many mask overlays at most (needs ``masks/``, from ``--save-masks``).
    Returns the path written.
    """
    rf = read_run(run_dir)
    try:
        return _build_report(rf, gt, out, overlays, auto_gt)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as e:
        # a run file edited or from elsewhere (fields of the wrong type): one line, not a traceback
        raise InputError(f"a run file is malformed ({type(e).__name__}: {e}); was it written by dynastereo?",
                         rf.root) from None


def _build_report(rf: RunFiles, gt: str | Path | None, out: str | Path | None, overlays: int, auto_gt: bool) -> Path:
    gt_path = Path(gt) if gt is not None else None
    if gt_path is None and auto_gt and rf.run:
        try:
            gt_path = recorded_ground_truth(rf.run, rf.root / "run.json")
        except InputError as e:
            log.warning("no ground truth for the report: %s", e)
    if gt_path is not None and not gt_path.exists():
        raise InputError("ground truth file not found", gt_path)
    ev = None
    if gt_path is not None and (rf.root / KITTI_NAME).is_file():
        if rf.partial is not None and rf.frames is not None:  # the rows all files hold
            from .metrics import evaluate

            est = read_trajectory(rf.root / KITTI_NAME)
            n = min(len(est), len(rf.frames))
            ev = evaluate(est.subset(np.arange(n)), read_trajectory(gt_path, name="ground truth"),
                          frame_indices=rf.frames[:n])
        else:
            ev = evaluate_files(rf.root / KITTI_NAME, gt_path)
    title = f"dynastereo run: {Path(rf.run.get('sequence') or rf.root).name}"
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    body = [f"<h1>{_esc(title)}</h1>", f"<p>run folder {_esc(rf.root.resolve())}; report made {stamp}</p>",
            _summary_section(rf), _trajectory_section(rf, ev, gt_path), _accuracy_section(ev),
            _timing_section(rf.timing), _overlay_section(rf, ev, overlays), _objects_section(rf),
            _object_paths_section(rf)]
    page = (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{_esc(title)}</title>'
            f'<meta name="viewport" content="width=device-width,initial-scale=1"><link rel="icon" href="data:,"><style>{STYLE}</style></head>'
            f'<body>{"".join(b for b in body if b)}</body></html>\n')
    path = Path(out) if out is not None else rf.root / REPORT_NAME
    from ..io.outputs import atomic_write_text

    atomic_write_text(path, page, fsync=False)  # an earlier report stays whole until the new one is
    return path
