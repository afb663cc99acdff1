"""Trajectory accuracy: APE, RPE (both with evo), start-anchored drift, KITTI devkit metric.

Definitions (all translations in metres, poses camera-to-world):

* **Matching.**  Estimate row ``k`` is compared with ground-truth row
  ``frame_indices[k]`` when frame indices are given (frames lost by tracking, revisits);
  otherwise, when both trajectories have timestamps (TUM), with the ground-truth pose
  nearest in time (``evo.core.sync.matching_time_indices``, within ``max_time_diff``);
  otherwise row ``k`` with row ``k`` (KITTI).  A ground truth longer than the estimate
  is cut to the estimate's frames, with a warning.
* **APE**: ``evo.core.metrics.APE`` w.r.t. the translation part, after an SE(3) Umeyama
  alignment of the estimate onto the ground truth (``PosePath3D.align(...,
  correct_scale=False)``) -- the thesis' evaluation.  ``align=False`` compares raw poses.
* **RPE**: ``evo.core.metrics.RPE`` w.r.t. the translation part (and, in
  ``rpe_rot_deg``, the rotation angle in degrees) between poses ``delta`` frames apart.
* **Drift**: both trajectories are re-anchored at their first matched pose
  (``T0^-1 T_i``, so both start at the identity); ``drift_m`` is the distance between
  their final positions, ``drift_percent = 100 * drift_m / path_length_m`` with
  ``path_length_m`` the length of the matched ground-truth path.  Independent of the
  Umeyama alignment (which would hide drift by spreading it over the path).
* **KITTI**: the odometry devkit's ``calcSequenceErrors`` (evaluate_odometry.cpp),
  vectorized: every 10th frame starts segments of 100, 200, ..., 800 m of ground-truth
  path; the relative pose error over each segment gives a translation error / length
  and a rotation angle / length; their means over all segments are reported as
  ``t_err_percent`` and ``r_err_deg_per_100m``.  ``None`` when no segment fits (path
  shorter than 100 m).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from evo.core import metrics as evo_metrics
from evo.core import sync as evo_sync
from evo.core.geometry import GeometryException
from evo.core.trajectory import PosePath3D
from evo.core.units import Unit

from ..errors import InputError
from .trajectory import Trajectory, frame_indices_beside, read_frame_indices, read_trajectory

log = logging.getLogger(__name__)

STAT_KEYS: tuple[str, ...] = ("max", "mean", "median", "min", "rmse", "sse", "std")  # the thesis' column order
KITTI_LENGTHS: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
KITTI_STEP = 10  # devkit: a segment starts every 10th frame ("every second" at 10 Hz)


@dataclass(frozen=True)
class KittiMetric:
    """KITTI odometry devkit averages over all segments (and per segment length)."""

    t_err_percent: float
    r_err_deg_per_100m: float
    n_segments: int
    per_length: dict[float, tuple[float, float, int]] = field(default_factory=dict)
    """segment length (m) -> (t_err %, r_err deg/100 m, number of segments)."""


@dataclass
class EvalResult:
    ape: dict[str, float]
    """APE translation statistics (m): max, mean, median, min, rmse, sse (m^2), std."""
    rpe: dict[str, float]
    """RPE translation statistics (m) over ``rpe_delta`` frames; empty if too few poses."""
    rpe_rot_deg: dict[str, float]
    """RPE rotation-angle statistics (deg) over ``rpe_delta`` frames."""
    rpe_delta: int
    drift_m: float
    drift_percent: float | None
    """``None`` when the ground-truth path has zero length."""
    path_length_m: float
    kitti: KittiMetric | None
    n_frames: int
    aligned: bool
    alignment: np.ndarray
    """4x4 SE(3) transform applied to the estimate (identity when ``aligned`` is False)."""
    ape_errors: np.ndarray
    """per-frame APE translation error (m), ``(n_frames,)``."""
    estimate: Trajectory
    """matched estimate rows, after alignment (what APE compares; plot this)."""
    ground_truth: Trajectory
    """ground-truth rows matched to the estimate."""
    matching: str
    warnings: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------- matching


def match_trajectories(
    estimate: Trajectory,
    ground_truth: Trajectory,
    *,
    frame_indices: np.ndarray | list[int] | None = None,
    max_time_diff: float = 0.01,
) -> tuple[Trajectory, Trajectory, list[str], str]:
    """Pair estimate and ground-truth rows (see module doc).

    Returns ``(estimate_rows, ground_truth_rows, warnings, how)``; both trajectories
    have the same length.  Raises :class:`InputError` when they cannot be paired.
    """
    n_est, n_gt = len(estimate), len(ground_truth)
    warns: list[str] = []
    gt_label = f"ground truth {ground_truth.path or ground_truth.name}"

    if frame_indices is not None:
        fi = np.asarray(frame_indices, dtype=np.int64).reshape(-1)
        if fi.shape[0] != n_est:
            raise InputError(
                f"{fi.shape[0]} frame indices for {n_est} estimated poses", estimate.path or estimate.name
            )
        if fi.size and (fi.min() < 0 or fi.max() >= n_gt):
            raise InputError(
                f"estimate refers to frames {fi.min()}..{fi.max()} but the ground truth has {n_gt} poses "
                f"(frames 0..{n_gt - 1})",
                ground_truth.path or ground_truth.name,
            )
        n_used = int(np.unique(fi).size)
        if n_used < n_gt:
            warns.append(
                f"{gt_label} has {n_gt} poses; cut to the estimate's {n_used} frames "
                f"({fi.min()}..{fi.max()}, {n_gt - n_used} ground-truth poses unused)"
            )
        return estimate, ground_truth.subset(fi), warns, "frame index"

    if estimate.timestamps is not None and ground_truth.timestamps is not None:
        idx_est, idx_gt = evo_sync.matching_time_indices(
            estimate.timestamps, ground_truth.timestamps, max_diff=max_time_diff
        )
        if len(idx_est) < max(1, (n_est + 1) // 2):  # the stamps do not align: no guess by index
            raise InputError(
                "the stamps do not align: "
                + ("no estimated pose has" if not idx_est else f"only {len(idx_est)} of {n_est} estimated poses have")
                + f" a ground-truth pose within {max_time_diff} s (estimate {estimate.timestamps[0]:.3f}..{estimate.timestamps[-1]:.3f} s, "
                f"{gt_label} {ground_truth.timestamps[0]:.3f}..{ground_truth.timestamps[-1]:.3f} s); "
                "`dynastereo eval --match index` pairs the rows by frame index instead",
                estimate.path or estimate.name,
            )
        if len(idx_est) < n_est:
            warns.append(
                f"{n_est - len(idx_est)} of {n_est} estimated poses have no ground-truth pose within "
                f"{max_time_diff} s and are not evaluated"
            )
        n_used = len(set(idx_gt))
        if n_used < n_gt:
            warns.append(
                f"{gt_label} has {n_gt} poses; cut to the {n_used} matching the estimate's timestamps"
            )
        return estimate.subset(idx_est), ground_truth.subset(idx_gt), warns, "timestamp"

    if estimate.timestamps is not None and not _rows_are_frames(estimate.timestamps):
        # A TUM estimate (say of --frames 20-29: its stamps start at 2.08 s) against a
        # ground truth without stamps: row k is not frame k, and nothing says which it is.
        raise InputError(
            f"the estimate has stamps ({estimate.timestamps[0]:.3f}..{estimate.timestamps[-1]:.3f} s, "
            f"{n_est} poses) but {gt_label} has none ({n_gt} poses) and no times.txt was found for it "
            "(KITTI layout: sequences/NN/times.txt beside poses/NN.txt): the rows cannot be matched by stamp, "
            "and matching them by row would guess; give a ground truth with stamps (TUM), or keep the run's "
            "trajectory.frames.txt beside the estimate",
            estimate.path or estimate.name,
        )
    if n_est > n_gt:
        raise InputError(
            f"estimate has {n_est} poses but the ground truth only {n_gt} (row i is frame i)",
            ground_truth.path or ground_truth.name,
        )
    if n_gt > n_est:
        warns.append(f"{gt_label} has {n_gt} poses; cut to the estimate's {n_est} frames (0..{n_est - 1})")
    return estimate, ground_truth.subset(np.arange(n_est)), warns, "frame index"


# --------------------------------------------------------------------------- pieces


def _rows_are_frames(t: np.ndarray) -> bool:
    """Whether stamps say that row k is frame k: they start at 0 and step evenly (within
    10 %), as a run from the first frame without gaps writes them."""
    if len(t) < 2:
        return len(t) == 0 or abs(float(t[0])) < 1e-9
    d = np.diff(t)
    dt = float(np.median(d))
    return dt > 0 and abs(float(t[0])) <= 0.1 * dt and float(np.max(np.abs(d - dt))) <= 0.1 * dt


def umeyama_se3(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """4x4 SE(3) ``T`` minimizing ``sum |T x_i - y_i|^2`` for ``(N, 3)`` point sets.

    Same equations as ``evo.core.geometry.umeyama_alignment`` without its rank check: for
    collinear or identical points the rotation about the degenerate directions is
    arbitrary (any choice gives the same, minimal, residual).
    """
    mx, my = x.mean(axis=0), y.mean(axis=0)
    cov = (y - my).T @ (x - mx) / x.shape[0]
    u, _, vt = np.linalg.svd(cov)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        s[2, 2] = -1.0
    T = np.eye(4)
    T[:3, :3] = u @ s @ vt
    T[:3, 3] = my - T[:3, :3] @ mx
    return T


def _stats(metric: evo_metrics.PE) -> dict[str, float]:
    s = metric.get_all_statistics()
    return {k: float(s[k]) for k in STAT_KEYS}


def _array_stats(e: np.ndarray) -> dict[str, float]:
    """The statistics of ``evo.core.metrics.PE.get_all_statistics`` for an error array."""
    sq = np.square(e)
    return {
        "max": float(e.max()),
        "mean": float(e.mean()),
        "median": float(np.median(e)),
        "min": float(e.min()),
        "rmse": float(np.sqrt(sq.mean())),
        "sse": float(sq.sum()),
        "std": float(e.std()),
    }


def rotation_angle_deg(T: np.ndarray) -> np.ndarray:
    """Rotation angle (deg) of ``(..., 4, 4)`` or ``(..., 3, 3)`` matrices; accurate near 0 and pi."""
    R = T[..., :3, :3]
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    return np.degrees(np.arctan2(0.5 * np.linalg.norm(w, axis=-1), c))


def _relative(poses: np.ndarray) -> np.ndarray:
    """Poses re-anchored at the first one: ``T0^-1 T_i``."""
    return np.linalg.inv(poses[0]) @ poses


def drift(estimate_poses: np.ndarray, gt_poses: np.ndarray) -> tuple[float, float, float | None]:
    """Start-anchored final position error: ``(drift_m, gt_path_length_m, drift_percent)``."""
    e = _relative(np.asarray(estimate_poses, dtype=np.float64))
    g = _relative(np.asarray(gt_poses, dtype=np.float64))
    drift_m = float(np.linalg.norm(e[-1, :3, 3] - g[-1, :3, 3]))
    length = float(np.linalg.norm(np.diff(g[:, :3, 3], axis=0), axis=1).sum())
    return drift_m, length, (100.0 * drift_m / length if length > 0 else None)


def kitti_odometry_error(
    estimate_poses: np.ndarray,
    gt_poses: np.ndarray,
    *,
    lengths: tuple[float, ...] = KITTI_LENGTHS,
    step: int = KITTI_STEP,
) -> KittiMetric | None:
    """The KITTI odometry devkit metric over frame-matched ``(N, 4, 4)`` poses.

    ``None`` when no segment of the given lengths fits in the ground-truth path.
    """
    est = np.asarray(estimate_poses, dtype=np.float64)
    gt = np.asarray(gt_poses, dtype=np.float64)
    n = gt.shape[0]
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))])
    first = np.arange(0, n, step)
    lens = np.asarray(lengths, dtype=np.float64)
    F = np.repeat(first, lens.size)
    L = np.tile(lens, first.size)
    # devkit lastFrameFromSegmentLength: first i with dist[i] > dist[first] + len
    last = np.searchsorted(dist, dist[F] + L, side="right")
    ok = last < n
    if not ok.any():
        return None
    F, L, last = F[ok], L[ok], last[ok]
    d_gt = np.linalg.inv(gt[F]) @ gt[last]
    d_est = np.linalg.inv(est[F]) @ est[last]
    err = np.linalg.inv(d_est) @ d_gt
    cos = np.clip(0.5 * (np.trace(err[:, :3, :3], axis1=1, axis2=2) - 1.0), -1.0, 1.0)
    r_err = np.arccos(cos) / L  # rad / m
    t_err = np.linalg.norm(err[:, :3, 3], axis=1) / L  # m / m
    to_pct, to_deg100 = 100.0, 100.0 * 180.0 / np.pi
    per_length = {
        float(length): (
            float(t_err[L == length].mean() * to_pct),
            float(r_err[L == length].mean() * to_deg100),
            int((L == length).sum()),
        )
        for length in np.unique(L)
    }
    return KittiMetric(
        t_err_percent=float(t_err.mean() * to_pct),
        r_err_deg_per_100m=float(r_err.mean() * to_deg100),
        n_segments=int(L.size),
        per_length=per_length,
    )


# --------------------------------------------------------------------------- evaluate


def evaluate(
    estimate: Trajectory,
    ground_truth: Trajectory,
    *,
    align: bool = True,
    rpe_delta: int = 1,
    frame_indices: np.ndarray | list[int] | None = None,
    max_time_diff: float = 0.01,
) -> EvalResult:
    """Compare ``estimate`` with ``ground_truth`` (see the module doc for definitions)."""
    if rpe_delta < 1:
        raise ValueError(f"rpe_delta must be >= 1, got {rpe_delta}")
    est, gt, warns, how = match_trajectories(
        estimate, ground_truth, frame_indices=frame_indices, max_time_diff=max_time_diff
    )
    n = len(est)
    if n < 2:
        raise InputError(f"need at least 2 matched poses to evaluate, got {n}", estimate.path or estimate.name)

    gt_path = PosePath3D(poses_se3=list(gt.poses))
    est_path = PosePath3D(poses_se3=list(est.poses))
    T = np.eye(4)
    if align:
        try:
            r, t, _ = est_path.align(gt_path, correct_scale=False)
            T[:3, :3], T[:3, 3] = r, t
        except GeometryException:
            # evo refuses collinear / static paths; the least-squares solution still exists.
            T = umeyama_se3(est.positions, gt.positions)
            est_path.transform(T)
            warns.append(
                "positions are collinear or static: the SE(3) alignment's rotation about the path is arbitrary"
            )

    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((gt_path, est_path))

    rpe: dict[str, float] = {}
    rpe_rot: dict[str, float] = {}
    if n > rpe_delta:
        m = evo_metrics.RPE(
            evo_metrics.PoseRelation.translation_part, delta=rpe_delta, delta_unit=Unit.frames, all_pairs=False
        )
        m.process_data((gt_path, est_path))
        rpe = _stats(m)
        # Rotation part from the same relative error poses, vectorized (evo's per-pair so3_log
        # is 4x slower than all the rest and rejects rotations off SO(3) by > 1e-6).
        rpe_rot = _array_stats(rotation_angle_deg(np.asarray(m.E)))
    else:
        warns.append(f"RPE not computed: {n} poses, delta {rpe_delta} frames")

    drift_m, length, drift_pct = drift(est.poses, gt.poses)
    if drift_pct is None:
        warns.append("ground-truth path has zero length: drift % undefined")
    kitti = kitti_odometry_error(est.poses, gt.poses)

    for w in warns:
        log.info(w)  # the caller prints result.warnings (format_table includes them)
    aligned_est = Trajectory(np.array(est_path.poses_se3), est.timestamps, est.name, est.path)
    return EvalResult(
        ape=_stats(ape),
        rpe=rpe,
        rpe_rot_deg=rpe_rot,
        rpe_delta=int(rpe_delta),
        drift_m=drift_m,
        drift_percent=drift_pct,
        path_length_m=length,
        kitti=kitti,
        n_frames=n,
        aligned=align,
        alignment=T,
        ape_errors=np.asarray(ape.error, dtype=np.float64),
        estimate=aligned_est,
        ground_truth=gt,
        matching=how,
        warnings=warns,
    )


def kitti_times_for(gt_path: Path) -> Path | None:
    """``sequences/NN/times.txt`` for a ground truth ``poses/NN.txt`` in KITTI's layout."""
    p = Path(gt_path).resolve()
    if p.parent.name != "poses":
        return None
    t = p.parent.parent / "sequences" / p.stem / "times.txt"
    return t if t.is_file() else None


def _with_kitti_times(gt: Trajectory, gt_path: Path) -> Trajectory:
    """``gt`` with the stamps of its sequence's ``times.txt`` (KITTI layout); a times.txt
    shorter than the poses (a copy of the first frames) stamps those rows only."""
    from ..io.times import read_times

    times_path = kitti_times_for(gt_path)
    if times_path is None:
        return gt
    try:
        t = read_times(times_path)
    except Exception:  # noqa: BLE001 -- an unreadable times.txt: matched as before, without stamps
        return gt
    n = min(len(t), len(gt))
    if n < 2:
        return gt
    rows = gt.subset(np.arange(n)) if n < len(gt) else gt
    return Trajectory(rows.poses, t[:n].astype(np.float64), gt.name, gt.path)


def _with_stamps_beside(est: Trajectory, est_path: Path) -> Trajectory:
    """A run's ``<stem>.kitti.txt`` with the stamps of ``<stem>.tum.txt`` beside it (same rows)."""
    twin = est_path.with_name(est_path.name.split(".")[0] + ".tum.txt")
    if twin == est_path or not twin.is_file():
        return est
    try:
        tum = read_trajectory(twin)
    except InputError:
        return est
    if tum.timestamps is None or len(tum) != len(est):
        return est
    return Trajectory(est.poses, tum.timestamps, est.name, est.path)


def evaluate_files(
    estimate_path,
    ground_truth_path,
    *,
    align: bool = True,
    rpe_delta: int = 1,
    frame_indices: np.ndarray | list[int] | None = None,
    use_frames_file: bool = True,
    max_time_diff: float = 0.01,
    match: str = "auto",
) -> EvalResult:
    """Read both files and :func:`evaluate`.

    With ``use_frames_file`` (default) and no explicit ``frame_indices``, a
    ``<stem>.frames.txt`` beside the estimate (written by :class:`TrajectoryWriter`) maps
    its rows to ground-truth frames -- unless both files carry timestamps, which then
    decide.  ``match="index"``: the rows are paired by frame index whatever the stamps say
    (that frames file, else row i with ground-truth row i): a video's container stamps
    against KITTI's poses.
    """
    if match not in ("auto", "index"):
        raise InputError(f"--match must be auto or index, got {match!r}")
    est = read_trajectory(estimate_path)
    gt = read_trajectory(ground_truth_path, name="ground truth")
    if match == "index" and frame_indices is None:
        side = frame_indices_beside(estimate_path) if use_frames_file else None
        frame_indices = read_frame_indices(side) if side is not None else np.arange(len(est))
        if len(frame_indices) != len(est):
            raise InputError(f"{len(frame_indices)} frame indices but the estimate has {len(est)} poses", side)
    how_extra = ""
    if frame_indices is None and gt.timestamps is None:  # KITTI poses: the sequence's times.txt ...
        stamped = _with_kitti_times(gt, Path(ground_truth_path))
        if stamped.timestamps is not None:
            if est.timestamps is None:  # ... for a run's KITTI file: its TUM twin has the stamps
                est = _with_stamps_beside(est, Path(estimate_path))
            if est.timestamps is not None:
                gt = stamped
                how_extra = f" ({kitti_times_for(Path(ground_truth_path)).name} of the ground truth)"
    if frame_indices is None and use_frames_file and (est.timestamps is None or gt.timestamps is None):
        side = frame_indices_beside(estimate_path)
        if side is not None:
            frame_indices = read_frame_indices(side)
            if len(frame_indices) != len(est):
                raise InputError(
                    f"{len(frame_indices)} frame indices but the estimate {estimate_path} has {len(est)} poses", side
                )
            how_extra += f" ({side.name})"
    result = evaluate(
        est, gt, align=align, rpe_delta=rpe_delta, frame_indices=frame_indices, max_time_diff=max_time_diff
    )
    result.matching += how_extra
    return result
