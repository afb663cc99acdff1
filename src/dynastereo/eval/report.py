"""Text table (the thesis' APE layout) and flat JSON dict of an :class:`EvalResult`."""

from __future__ import annotations

import math
from typing import Any

from .metrics import STAT_KEYS, EvalResult


def _num(v: float) -> str:
    """Thesis-like: 2 decimals, 3 significant digits for small values, integers when large."""
    if v is None or not math.isfinite(v):
        return "n/a"
    a = abs(v)
    if a >= 1000:
        return f"{v:.0f}"
    if a >= 1 or a == 0:
        return f"{v:.2f}"
    return f"{v:.3g}" if a >= 0.001 else f"{v:.2e}"


def format_table(result: EvalResult, label: str | None = None) -> str:
    """The APE table in the thesis' layout (max mean median min rmse sse std, metres),
    then RPE, the start-anchored drift and the KITTI devkit metric."""
    label = label or result.estimate.name or "estimate"
    heads = ["", *(f"{k}(m^2)" if k == "sse" else f"{k}(m)" for k in STAT_KEYS)]
    rows = [[f"APE {label}", *(_num(result.ape[k]) for k in STAT_KEYS)]]
    if result.rpe:
        rows.append([f"RPE d={result.rpe_delta}", *(_num(result.rpe[k]) for k in STAT_KEYS)])
    widths = [max(len(r[c]) for r in [heads, *rows]) for c in range(len(heads))]
    fmt_row = lambda r: "  ".join(  # noqa: E731
        (cell.ljust(w) if c == 0 else cell.rjust(w)) for c, (cell, w) in enumerate(zip(r, widths))
    )
    align = "SE(3) Umeyama alignment, no scale" if result.aligned else "no alignment"
    lines = [f"APE w.r.t. translation part, {align}; {result.n_frames} frames matched by {result.matching}"]
    lines += [fmt_row(heads), *map(fmt_row, rows)]
    if result.rpe_rot_deg:
        lines.append(
            f"RPE rotation (d={result.rpe_delta}): rmse {_num(result.rpe_rot_deg['rmse'])} deg, "
            f"max {_num(result.rpe_rot_deg['max'])} deg"
        )
    drift = "n/a" if result.drift_percent is None else f"{result.drift_percent:.2f} %"
    lines.append(
        f"drift: {drift} of {result.path_length_m:.1f} m path "
        f"(final position error {result.drift_m:.3f} m, both trajectories anchored at the first frame)"
    )
    if result.kitti is None:
        lines.append(f"KITTI devkit: n/a (path {result.path_length_m:.1f} m: no 100..800 m segment fits)")
    else:
        k = result.kitti
        lines.append(
            f"KITTI devkit: t_err {k.t_err_percent:.2f} %, r_err {k.r_err_deg_per_100m:.3f} deg/100 m "
            f"({k.n_segments} segments of 100..800 m)"
        )
    lines += [f"warning: {w}" for w in result.warnings]
    return "\n".join(lines)


def _clean(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def to_json_dict(result: EvalResult) -> dict[str, Any]:
    """Flat, JSON-serialisable keys: ``ape.<stat>``, ``rpe.<stat>``, ``rpe_rot_deg.<stat>``,
    ``drift_percent``, ``drift_m``, ``path_length_m``, ``kitti.t_err_percent``,
    ``kitti.r_err_deg_per_100m``, ``kitti.n_segments``, ``n_frames``, ``rpe_delta``,
    ``aligned``, ``matching``, ``warnings``.  Missing values are ``None`` (JSON null)."""
    d: dict[str, Any] = {f"ape.{k}": result.ape[k] for k in STAT_KEYS}
    d.update({f"rpe.{k}": result.rpe.get(k) for k in STAT_KEYS})
    d.update({f"rpe_rot_deg.{k}": result.rpe_rot_deg.get(k) for k in STAT_KEYS})
    d.update(
        {
            "rpe_delta": result.rpe_delta,
            "drift_percent": result.drift_percent,
            "drift_m": result.drift_m,
            "path_length_m": result.path_length_m,
            "kitti.t_err_percent": result.kitti.t_err_percent if result.kitti else None,
            "kitti.r_err_deg_per_100m": result.kitti.r_err_deg_per_100m if result.kitti else None,
            "kitti.n_segments": result.kitti.n_segments if result.kitti else 0,
            "n_frames": result.n_frames,
            "aligned": result.aligned,
            "matching": result.matching,
            "warnings": list(result.warnings),
        }
    )
    return {k: _clean(v) for k, v in d.items()}
