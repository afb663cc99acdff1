"""``dynastereo demo``: the embedded default, offline, in about a minute.

1. generate a synthetic dynamic street sequence (``convoy``: a truck ahead at the
   camera's speed fills a big part of the view -- the case that breaks SLAM without
   masking) with exact ground truth;
2. run the stereo SLAM on it unmasked, with ``box`` masks and with ``outline`` masks;
3. evaluate each trajectory against the ground truth (ATE RMSE, drift), score the masks
   against the ground-truth instance masks (IoU), report FPS, and plot the trajectories;
4. write an HTML report of each run (``run_<masker>/report.html``) and print their paths.

``viewer`` / ``rrd``: the ``outline`` run (the last masked one) goes to the rerun viewer /
into an ``.rrd`` recording.

The detector is YOLOX-nano when its weights are found (``--models-dir``,
``$DYNASTEREO_MODELS`` or the cache); otherwise the ground-truth **oracle** boxes, and
the output says so.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from rich.console import Console
from rich.table import Table

from .config import Config


@dataclass
class DemoRow:
    masker: str
    ate_rmse: float
    drift_percent: float
    iou_left: float | None
    iou_right: float | None
    fps: float
    lost: int


def pick_detector(models_dir: str | Path | None) -> tuple[str, str]:
    """("yolox-nano", why) when its weights verify, else ("oracle", why)."""
    from .models import resolve_models_dir, verify

    d = resolve_models_dir(models_dir)
    problems = verify("yolox-nano", d)
    if not problems:
        return "yolox-nano", f"detector: yolox-nano from {d}"
    return "oracle", (
        f"detector: ORACLE (ground-truth boxes) -- no verified yolox-nano weights in {d}; "
        "`dynastereo models download yolox-nano` fetches them"
    )


def run_demo(
    out: str | Path | None = None,
    *,
    scenario: str = "convoy",
    frames: int = 60,
    size: tuple[int, int] = (640, 192),
    seed: int = 0,
    detector: str | None = None,
    models_dir: str | Path | None = None,
    maskers: tuple[str, ...] = ("none", "box", "outline"),
    console: Console | None = None,
    progress: Callable | None = None,
    viewer: bool = False,
    rrd: str | Path | None = None,
) -> list[DemoRow]:
    from .eval import plot_trajectories
    from .synth import generate

    console = console or Console()
    root = Path(out) if out is not None else Path(tempfile.mkdtemp(prefix="dynastereo-demo-"))
    root.mkdir(parents=True, exist_ok=True)
    for sub in ["synth", *(f"run_{k}" for k in maskers)]:  # the demo's own folders: start clean
        shutil.rmtree(root / sub, ignore_errors=True)
    detector, real, why = _choose_detector(detector, models_dir)
    console.print(f"[bold]dynastereo demo[/] -> {root}")
    console.print(why)

    def bar():
        return None if progress is None else progress()

    seq = root / "synth" / "sequences" / "00"
    prog = bar()
    if prog is not None:
        with prog:
            task = prog.add_task(f"synth {scenario}", total=frames, info="")
            generate(root / "synth", scenario, frames=frames, seed=seed, size=size,
                     progress=lambda i, n: prog.update(task, completed=i, total=n))
    else:
        generate(root / "synth", scenario, frames=frames, seed=seed, size=size)
    gt = root / "synth" / "poses" / "00.txt"

    rows: list[DemoRow] = []
    trajectories = {}
    cfg = Config().with_overrides({"detector.name": detector, "seed": seed})
    runs = [(kind, detector) for kind in maskers]
    if real is not None and "outline" in maskers:
        runs.append(("outline", real))
    shown = next((r for r in reversed(runs) if r[0] != "none" and r[1] == detector), runs[-1])
    reports = []
    for kind, det in runs:
        label = kind if det == detector else f"{kind} ({det})"
        run_dir = root / f"run_{kind}" if det == detector else root / f"run_{kind}_{det}"
        view = dict(viewer=viewer, rrd=rrd) if (kind, det) == shown else {}
        c = cfg.with_overrides({"masker.kind": kind, "detector.name": det})
        row, ev, report = _demo_run(seq, gt, run_dir, label, c, frames, models_dir, view, bar())
        reports.append((label, report))
        ev.estimate.name = ""
        trajectories[f"masker {label}"] = ev.estimate
        rows.append(row)
        gt_traj = ev.ground_truth

    plot = plot_trajectories(trajectories, gt_traj, root / "trajectories.png",
                             title=f"synthetic '{scenario}', {frames} frames: masking vs none")
    _print_table(console, rows, f"synthetic '{scenario}' ({frames} frames, {size[0]}x{size[1]}), {detector} boxes")
    console.print(f"plot: {plot}")
    for label, path in reports:
        console.print(f"report ({label}): {path}", highlight=False)
    (root / "demo.json").write_text(json.dumps(
        {"scenario": scenario, "frames": frames, "size": list(size), "detector": detector,
         "rows": [r.__dict__ for r in rows], "plot": str(plot),
         "reports": {label: str(path) for label, path in reports}}, indent=1))
    return rows


def _choose_detector(detector: str | None, models_dir: str | Path | None) -> tuple[str, str | None, str]:
    """``(detector of the masked runs, a real detector for one more row or None, what to
    print)``: the oracle by default, plus a real detector's row when one is found."""
    real = None
    if detector is None:
        real, why = pick_detector(models_dir)
        detector = "oracle"
        if real == "oracle":
            real = None
        else:
            why = (f"{why}; the masks below use the ORACLE (ground-truth) boxes, plus one row with "
                   f"{real}'s boxes (detectors trained on photos find few of the stylized synthetic objects)")
    else:
        why = f"detector: {detector}" + (" (ground-truth boxes)" if detector == "oracle" else "")
    return detector, real, why


def _demo_run(seq: Path, gt: Path, run_dir: Path, label: str, c: Config, frames: int,
              models_dir: str | Path | None, view: dict, prog) -> tuple[DemoRow, object, Path | None]:
    """One row of the demo: ``dynastereo run`` of the sequence with configuration ``c``
    into ``run_dir``, scored against the ground truth.  Returns ``(row, evaluation,
    report path)``."""
    from .eval import evaluate_files
    from .eval.masks import score_mask_dir
    from .runtime import JobKind, JobSpec, OutputSpec, SourceSpec, run

    kind = c.masker.kind
    shutil.rmtree(run_dir, ignore_errors=True)
    spec = JobSpec(JobKind.RUN, SourceSpec(path=seq),
                   OutputSpec(run_dir, save_masks=kind != "none", report=True, **view), c,
                   models_dir=models_dir, gt=gt)
    with prog if prog is not None else nullcontext():
        on_frame = None
        if prog is not None:
            task = prog.add_task(f"SLAM, masker {label}", total=frames, info="")
            on_frame = lambda k, n, rec: prog.update(task, completed=k, total=n,  # noqa: E731
                                                     info=f"{rec['fps']:.1f} FPS")
        res = run(spec, progress=on_frame)
    ev = evaluate_files(run_dir / "trajectory.kitti.txt", gt)
    iou_l = iou_r = None
    if kind != "none":
        # the masks SLAM got: with the motion test (the default) only the moving objects'
        agree = score_mask_dir(run_dir, seq, frames=list(range(frames)),
                               moving_only=c.motion.mode == "moving").summary()
        iou_l, iou_r = agree["iou_left"], agree["iou_right"]
    row = DemoRow(label, ev.ape["rmse"], ev.drift_percent or 0.0, iou_l, iou_r, res.fps, len(res.lost))
    return row, ev, res.report


def _print_table(console: Console, rows: list[DemoRow], title: str) -> None:
    """The demo's table: one row per run."""
    table = Table(title=title)
    for col in ("masker", "ATE RMSE (m)", "drift (%)", "mask IoU left", "mask IoU right", "FPS", "lost"):
        table.add_column(col, justify="right" if col != "masker" else "left")
    for r in rows:
        table.add_row(r.masker, f"{r.ate_rmse:.3f}", f"{r.drift_percent:.2f}",
                      "-" if r.iou_left is None else f"{r.iou_left:.3f}",
                      "-" if r.iou_right is None else f"{r.iou_right:.3f}", f"{r.fps:.1f}", str(r.lost))
    console.print(table)
