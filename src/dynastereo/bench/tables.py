"""``tables.md`` and the plots of a sweep, from the records of ``results.json``.

Tables (the thesis' layout, Tables 4 and 5): ATE RMSE per sequence and masker, mean ± std
over the repeats; KITTI devkit t_err / r_err; start-anchored drift; time per stage and FPS
per masker; failed runs with their errors.  Numbers are printed with :func:`fmt` (4
significant decimals) from the records as they are, so each cell can be found again in
results.json.  ``std`` is the sample standard deviation (n - 1), shown when n > 1.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from .discover import BenchSequence

from ..masking.maskers import MASK_STAGES

# columns of the timing table: masking's parts, masking (= detect + parts), then the SLAM
STAGE_ORDER = ("read", "detect", *MASK_STAGES, "masking", "features", "stereo", "track", "local_mapping", "total")


def fmt(v: float | None, digits: int = 4) -> str:
    if v is None or not math.isfinite(v):
        return "n/a"
    return f"{v:.{digits}f}"


def mean_std(values: list[float]) -> tuple[float, float | None]:
    a = np.asarray(values, dtype=np.float64)
    return float(a.mean()), (float(a.std(ddof=1)) if a.size > 1 else None)


def cell(values: list[float | None], digits: int = 4) -> str:
    """``mean ± std (n)``; ``n/a`` without values; the count of repeats when it is not all."""
    vals = [v for v in values if v is not None and math.isfinite(v)]
    if not vals:
        return "n/a"
    m, s = mean_std(vals)
    text = fmt(m, digits) if s is None else f"{fmt(m, digits)} ± {fmt(s, digits)}"
    return text if len(vals) == len(values) else f"{text} ({len(vals)}/{len(values)})"


def _groups(runs: list[dict[str, Any]]) -> tuple[list[str], list[str], dict[tuple[str, str], list[dict]]]:
    seqs = list(dict.fromkeys(r["sequence"] for r in runs))
    maskers = list(dict.fromkeys(r["masker"] for r in runs))
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in runs:
        if r["status"] == "done":
            groups.setdefault((r["sequence"], r["masker"]), []).append(r)
    return seqs, maskers, groups


def _metric_table(title: str, key: str, seqs, maskers, groups, digits: int = 4) -> list[str]:
    lines = [f"### {title}", "", "| sequence | " + " | ".join(maskers) + " |",
             "|---|" + "---:|" * len(maskers)]
    for s in seqs:
        row = [cell([g["metrics"].get(key) for g in groups.get((s, m), [])], digits) if groups.get((s, m))
               else "—" for m in maskers]
        lines.append(f"| {s} | " + " | ".join(row) + " |")
    return lines + [""]


def stage_medians(runs: list[dict[str, Any]], masker: str) -> dict[str, float]:
    """Per stage: the median over the masker's runs of each run's median ms per frame."""
    per: dict[str, list[float]] = {}
    for r in runs:
        if r["status"] == "done" and r["masker"] == masker:
            for k, v in r.get("timing_ms", {}).items():
                per.setdefault(k, []).append(float(v))
    return {k: float(np.median(v)) for k, v in per.items()}


def _timing_table(runs, maskers) -> list[str]:
    meds = {m: stage_medians(runs, m) for m in maskers}
    names = [s for s in STAGE_ORDER if any(s in d for d in meds.values())]
    names += sorted({k for d in meds.values() for k in d} - set(names))
    lines = ["### Time per stage (ms per frame; median over the runs of each run's median) and FPS", "",
             "| masker | " + " | ".join(names) + " | FPS | overhead s/job |",
             "|---|" + "---:|" * (len(names) + 2)]
    for m in maskers:
        done = [r for r in runs if r["status"] == "done" and r["masker"] == m]
        fps = fmt(float(np.median([r["fps"] for r in done])), 2) if done else "n/a"
        over = fmt(float(np.median([r["overhead_s"] for r in done])), 2) if done else "n/a"
        lines.append(f"| {m} | " + " | ".join(fmt(meds[m].get(k), 1) for k in names) + f" | {fps} | {over} |")
    return lines + [""]


def render_tables(runs: list[dict[str, Any]], meta: dict[str, Any] | None = None) -> str:
    seqs, maskers, groups = _groups(runs)
    meta = meta or {}
    n_done = sum(r["status"] == "done" for r in runs)
    failed = [r for r in runs if r["status"] not in ("done",)]
    head = [
        "# dynastereo bench",
        "",
        f"{n_done} of {len(runs)} runs finished; {meta.get('repeats', '?')} repeat(s) per sequence and masker "
        f"(seed + repeat); engine: {meta.get('engine_description', meta.get('engine', '?'))}; "
        f"root: `{meta.get('root', '?')}`" + (f"; frames {meta['frames']}" if meta.get("frames") else "") + ".",
        "Cells: mean ± sample std over the repeats (n/m: only n of m runs had the number).",
        "",
    ]
    body = _metric_table("ATE RMSE (m), SE(3)-aligned (thesis Table 5)", "ape.rmse", seqs, maskers, groups)
    body += _metric_table("KITTI t_err (%)", "kitti.t_err_percent", seqs, maskers, groups, 3)
    body += _metric_table("KITTI r_err (deg / 100 m)", "kitti.r_err_deg_per_100m", seqs, maskers, groups, 3)
    body += _metric_table("Drift (% of the path, start-anchored)", "drift_percent", seqs, maskers, groups, 3)
    body += _timing_table(runs, maskers)
    if failed:
        body += ["### Runs not finished", "", "| run | status | attempts | error |", "|---|---|---:|---|"]
        for r in failed:
            err = (r.get("error") or "").replace("|", "\\|")
            body.append(f"| {r['key']} | {r['status']} | {r.get('attempts', 0)} | {err} |")
        body.append("")
    retried = [r for r in runs if r["status"] == "done" and r.get("errors")]
    if retried:
        body += ["### Runs that failed once and finished on retry", ""]
        body += [f"- {r['key']}: {r['errors'][0].splitlines()[0]}" for r in retried] + [""]
    return "\n".join(head + body)


def write_tables(runs: list[dict[str, Any]], path: Path, meta: dict[str, Any] | None = None) -> Path:
    path.write_text(render_tables(runs, meta))
    return path


# --------------------------------------------------------------------------- plots


def plot_ate_bars(runs: list[dict[str, Any]], path: Path) -> Path | None:
    from ..eval.plot import _new_figure, _save

    seqs, maskers, groups = _groups(runs)
    if not groups:
        return None
    fig = _new_figure((max(5.0, 1.2 * len(seqs) * max(1, len(maskers)) / 2 + 2), 4.0))
    ax = fig.add_subplot()
    width = 0.8 / max(1, len(maskers))
    x = np.arange(len(seqs))
    for k, m in enumerate(maskers):
        stats = [[g["metrics"].get("ape.rmse") for g in groups.get((s, m), [])] for s in seqs]
        stats = [[v for v in vals if v is not None] for vals in stats]
        means = [mean_std(v)[0] if v else np.nan for v in stats]
        errs = [(mean_std(v)[1] or 0.0) if v else 0.0 for v in stats]
        ax.bar(x + (k - (len(maskers) - 1) / 2) * width, means, width, yerr=errs, capsize=3, label=m, color=f"C{k}")
    ax.set_xticks(x, seqs, rotation=30 if len(seqs) > 6 else 0, ha="right" if len(seqs) > 6 else "center")
    ax.set_ylabel("ATE RMSE [m]")
    ax.set_title("ATE RMSE per sequence (mean ± std over repeats)")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(title="masker", fontsize=9)
    return _save(fig, path)


def plot_sequence_trajectories(runs: list[dict[str, Any]], seq: BenchSequence, path: Path) -> Path | None:
    """Ground truth and, per masker, the aligned estimate of its first finished repeat."""
    from ..eval import Trajectory, evaluate_files, plot_trajectories

    ests: dict[str, Trajectory] = {}
    gt = None
    for r in sorted((r for r in runs if r["status"] == "done" and r["sequence"] == seq.name and r.get("metrics")),
                    key=lambda r: r["repeat"]):
        if r["masker"] in ests or not r.get("ground_truth"):
            continue
        res = evaluate_files(Path(r["dir"]) / r["metrics"].get("estimate", "trajectory.kitti.txt"), r["ground_truth"])
        ests[r["masker"]] = dataclasses.replace(res.estimate, name=r["masker"])  # legend: the masker alone
        if gt is None or len(res.ground_truth) > len(gt):
            gt = res.ground_truth
    if gt is None:
        return None
    return plot_trajectories(ests, gt, path, title=f"{seq.name}: estimates (SE(3)-aligned) vs ground truth")


def write_plots(runs: list[dict[str, Any]], sequences: list[BenchSequence], folder: Path) -> list[Path]:
    out = [plot_ate_bars(runs, folder / "ate.png")]
    for s in sequences:
        out.append(plot_sequence_trajectories(runs, s, folder / f"trajectories_{s.name.replace('/', '_')}.png"))
    return [p for p in out if p is not None]
