"""Trajectory evaluation: KITTI/TUM files, APE/RPE (evo), drift, KITTI devkit metric, plots.

``evaluate_files(estimate, ground_truth)`` -> :class:`EvalResult`; ``format_table`` /
``to_json_dict`` print it; ``plot_trajectories`` draws the top view.
"""

from .metrics import (
    STAT_KEYS,
    EvalResult,
    KittiMetric,
    drift,
    evaluate,
    evaluate_files,
    kitti_odometry_error,
    match_trajectories,
)
from .plot import plot_ape_over_time, plot_trajectories
from .report import format_table, to_json_dict
from .trajectory import (
    FRAMES_NAME,
    KITTI_NAME,
    TUM_NAME,
    Trajectory,
    TrajectoryWriter,
    frame_indices_beside,
    read_frame_indices,
    read_trajectory,
    write_kitti,
    write_trajectory,
    write_tum,
)

__all__ = [
    "STAT_KEYS",
    "EvalResult",
    "KittiMetric",
    "drift",
    "evaluate",
    "evaluate_files",
    "kitti_odometry_error",
    "match_trajectories",
    "plot_ape_over_time",
    "plot_trajectories",
    "format_table",
    "to_json_dict",
    "FRAMES_NAME",
    "KITTI_NAME",
    "TUM_NAME",
    "Trajectory",
    "TrajectoryWriter",
    "frame_indices_beside",
    "read_frame_indices",
    "read_trajectory",
    "write_kitti",
    "write_trajectory",
    "write_tum",
]
