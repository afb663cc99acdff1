"""Trajectory plots (PNG), drawn with matplotlib's object API on the Agg canvas (no pyplot state)."""

from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .metrics import EvalResult
from .trajectory import Trajectory

_AXES = {"x": 0, "y": 1, "z": 2}


def top_view_plane(gt: Trajectory) -> str:
    """The plane to look at from above: drop the axis along which ``gt`` moves least.

    KITTI camera coordinates (y down) give ``"xz"``; z-up worlds (TUM, EuRoC) ``"xy"``.
    When y barely moves (under 5% of the largest extent) it is the one dropped, so a
    straight drive in KITTI coordinates is shown as x-z too.
    """
    spread = np.ptp(gt.positions, axis=0)
    drop = int(np.argmin(spread))
    if spread[1] <= 0.05 * spread.max():
        drop = 1  # a (near) tie with the camera's y (down) axis: a straight drive in KITTI coordinates
    keep = sorted(set(range(3)) - {drop})
    return "".join("xyz"[i] for i in keep)


def _new_figure(size: tuple[float, float], dpi: int = 100) -> Figure:
    """A matplotlib figure on its own Agg canvas (no pyplot, no global state)."""
    fig = Figure(figsize=size, dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path_png: str | Path | BinaryIO) -> Path | BinaryIO:
    """Write the PNG to a path (its folder made) or to a binary file object (returned as is)."""
    if hasattr(path_png, "write"):
        fig.savefig(path_png, format="png")
        return path_png
    from ..io.outputs import atomic_open

    path = Path(path_png)
    with atomic_open(path, "wb", fsync=False) as fh:  # an earlier plot stays whole until the new one is
        fig.savefig(fh, format="png")
    return path


def side_view_plane(ref: Trajectory) -> str:
    """The side view: the axis of the top view (:func:`top_view_plane`) along which
    ``ref`` travels furthest, against the axis the top view drops (the height)."""
    top = top_view_plane(ref)
    spread = np.ptp(ref.positions, axis=0)
    along = max(top, key=lambda c: spread[_AXES[c]])
    return along + next(c for c in "xyz" if c not in top)


def plot_trajectories(
    est: Trajectory | dict[str, Trajectory],
    gt: Trajectory | None,
    path_png: str | Path | BinaryIO,
    title: str | None = None,
    *,
    plane: str = "auto",
) -> Path | BinaryIO:
    """Top view of ``est`` (pass the aligned one, ``EvalResult.estimate``) over ``gt``.

    ``est`` may be a dict ``{label: trajectory}`` to compare several estimates; ``gt``
    may be None (the estimate alone).

    ``plane``: ``"auto"`` (see :func:`top_view_plane`), ``"side"`` (see
    :func:`side_view_plane`), or two of x/y/z, e.g. ``"xz"``.  Equal aspect, circle =
    start, square = end.  Returns the PNG path (or the file object written to).
    """
    ests = est if isinstance(est, dict) else {"estimate": est}
    ref = gt if gt is not None else next(iter(ests.values()))
    if plane == "auto":
        plane = top_view_plane(ref)
    elif plane == "side":
        plane = side_view_plane(ref)
    if len(plane) != 2 or any(c not in _AXES for c in plane):
        raise ValueError(f"plane must be two of x, y, z (e.g. 'xz'), got {plane!r}")
    i, j = _AXES[plane[0]], _AXES[plane[1]]
    fig = _new_figure((7.0, 6.0))
    ax = fig.add_subplot()
    curves = [] if gt is None else [(gt, "ground truth", dict(color="0.2", ls="--"))]
    curves += [(t, label, dict(color=f"C{k}")) for k, (label, t) in enumerate(ests.items())]
    for traj, label, style in curves:
        p = traj.positions
        name = label if traj.name in ("", label) else f"{label} ({traj.name})"
        (line,) = ax.plot(p[:, i], p[:, j], lw=1.5, label=name, **style)
        ax.plot(p[0, i], p[0, j], "o", color=line.get_color(), ms=7, mfc="none", mew=2)
        ax.plot(p[-1, i], p[-1, j], "s", color=line.get_color(), ms=6)
    ax.set_xlabel(f"{plane[0]} [m]")
    ax.set_ylabel(f"{plane[1]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", title="○ start  ■ end", fontsize=9)
    if title:
        ax.set_title(title)
    return _save(fig, path_png)


def plot_ape_over_time(result: EvalResult, path_png: str | Path | BinaryIO, title: str | None = None) -> Path | BinaryIO:
    """APE translation error per frame (against time when the estimate has timestamps)."""
    ts = result.estimate.timestamps
    x = ts - ts[0] if ts is not None else np.arange(result.n_frames)
    fig = _new_figure((8.0, 4.0))
    ax = fig.add_subplot()
    ax.plot(x, result.ape_errors, color="C0", lw=1.2, label="APE")
    for key, color in (("rmse", "C3"), ("mean", "C1"), ("median", "C2")):
        ax.axhline(result.ape[key], color=color, lw=1, ls=":", label=f"{key} {result.ape[key]:.3f} m")
    ax.set_xlabel("time [s]" if ts is not None else "frame")
    ax.set_ylabel("APE (translation) [m]")
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=9)
    ax.set_title(title or ("APE, SE(3)-aligned" if result.aligned else "APE, not aligned"))
    return _save(fig, path_png)
