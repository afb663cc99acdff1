"""High-level Python API: the same jobs the CLI runs.

>>> from dynastereo.api import mask_sequence
>>> result = mask_sequence("KITTI/sequences/06", "out/", frames="0-9")
>>> result.summary["mask"]["median"]
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from .config import Config
from .io import open_sequence
from .io.base import Sequence
from .io.frames import parse_frame_spec
from .pipeline import MaskJobResult, SlamJobResult, run_mask_job, run_slam_job


def load_sequence(sequence: str | Path | Sequence, calib: str | Path | None = None,
                  color: bool | None = None) -> Sequence:
    if isinstance(sequence, (str, Path)):
        return open_sequence(Path(sequence), calib=Path(calib) if calib else None, color=color)
    return sequence


def build_masker(cfg: Config, sequence: Sequence, models_dir: str | Path | None = None):
    """The masker the configuration asks for; ``detector.name == "oracle"`` uses the
    ground truth boxes of a synthetic sequence (``dynastereo synth``)."""
    from .masking import create_masker

    detector = None
    if cfg.detector.name == "oracle" and cfg.masker.kind in ("outline", "box"):
        from .synth import OracleDetector

        detector = OracleDetector(sequence.path)
    masker = create_masker(cfg, models_dir=Path(models_dir) if models_dir else None, detector=detector)
    if hasattr(masker, "set_baseline"):  # the road line's slope is baseline / camera height
        masker.set_baseline(sequence.calibration.baseline)
    return masker


def _prepare(sequence, cfg: Config, frames, calib, models_dir):
    """(sequence, frame indices, masker) for a job."""
    seq = load_sequence(sequence, calib)
    return seq, parse_frame_spec(frames, len(seq)), build_masker(cfg, seq, models_dir)


def mask_sequence(
    sequence: str | Path | Sequence,
    out: str | Path,
    cfg: Config | None = None,
    *,
    frames: str | int | None = None,
    calib: str | Path | None = None,
    models_dir: str | Path | None = None,
    save_disparity: bool = False,
    overlays: bool = False,
    progress: Callable[[int, int, dict], None] | None = None,
) -> MaskJobResult:
    """Mask the dynamic objects of ``sequence`` in both images; see ``pipeline.run_mask_job``."""
    cfg = cfg or Config()
    if save_disparity and cfg.stereo.region != "full":
        cfg = cfg.with_overrides({"stereo.region": "full"})
    seq, indices, masker = _prepare(sequence, cfg, frames, calib, models_dir)
    return run_mask_job(seq, masker, out, indices, save_disparity=save_disparity, overlays=overlays, progress=progress)


def run_sequence(
    sequence: str | Path | Sequence,
    out: str | Path,
    cfg: Config | None = None,
    *,
    frames: str | int | None = None,
    calib: str | Path | None = None,
    models_dir: str | Path | None = None,
    save_masks: bool = False,
    progress: Callable[[int, int, dict], None] | None = None,
    save_map: str | Path | None = None,
    load_map: str | Path | None = None,
    localize_only: bool = False,
) -> SlamJobResult:
    """Mask and track ``sequence`` with the stereo SLAM; see ``pipeline.run_slam_job``.

    ``frames`` may revisit (``"0-98,40-60"``): frames are fed in the order given.
    ``load_map``: start from a map file (``save_map`` of an earlier run); with
    ``localize_only`` the map is only localised in (no new keyframes).  ``save_map``:
    write the final map there.
    """
    from .config import to_dict
    from .errors import ConfigError
    from .slam import System

    if localize_only and load_map is None:
        raise ConfigError("localisation only needs a map: give load_map (--load-map FILE)")
    cfg = cfg or Config()
    seq, indices, masker = _prepare(sequence, cfg, frames, calib, models_dir)
    system = System(cfg, seq.calibration)
    info = {}
    if load_map is not None:
        try:
            system.load_map(load_map, localize_only=localize_only)
        except BaseException:
            system.shutdown()
            raise
        info = {"loaded": str(load_map), "localize_only": bool(localize_only)}
    return run_slam_job(seq, masker, system, out, indices, config_dict=to_dict(cfg),
                        save_masks=save_masks, progress=progress, save_map=save_map, map_info=info)


# --------------------------------------------------------------------------- benchmarks


def bench(
    root: str | Path,
    out: str | Path,
    *,
    sequences: str | None = None,
    maskers: str | list[str] = "none,box,outline,seg",
    repeats: int = 3,
    config: str | Path | None = None,
    overrides: dict | None = None,
    frames: str | None = None,
    engine: str = "local",
    address: str | None = None,
    workers: int | None = None,
    threads: int = 1,
    models_dir: str | Path | None = None,
    plots: bool = True,
    progress: Callable[[dict], None] | None = None,
):
    """Run every (sequence, masker, repeat) of the sequences under ``root`` as its own job,
    evaluate each against its ground truth, write ``out/results.json``, ``out/tables.md``
    and ``out/plots/``; finished jobs are reused.  ``engine``: ``local`` (process pool) or
    ``ray`` (local instance, or the cluster at ``address``).  See
    :func:`dynastereo.bench.runner.run_bench`."""
    from .bench import run_bench

    return run_bench(root, out, sequences=sequences, maskers=maskers, repeats=repeats, config=config,
                     overrides=overrides, frames=frames, engine=engine, address=address, workers=workers,
                     threads=threads, models_dir=models_dir, plots=plots, progress=progress)


# --------------------------------------------------------------------------- ROS bags


def run_bag(
    bag: str | Path,
    out: str | Path,
    cfg: Config | None = None,
    *,
    left_topic: str | None = None,
    right_topic: str | None = None,
    left_info: str | None = "auto",
    right_info: str | None = "auto",
    calib: str | Path | None = None,
    config_path: str | Path | None = None,
    tolerance_s: float = 0.005,
    rectify: str = "auto",
    frames: str | int | None = None,
    models_dir: str | Path | None = None,
    save_masks: bool = False,
    outputs: str | None = None,
    progress: Callable[[int, int, dict], None] | None = None,
):
    """Mask and track a stereo bag (ROS 1 .bag, ROS 2 .db3, .mcap); results as for
    :func:`run_sequence` plus ``out/output.<fmt>`` and ``out/bag.json``.  Calibration:
    ``calib`` (YAML) > the bag's CameraInfo > ``config_path`` when it is an ORB-SLAM2
    settings file.  See :func:`dynastereo.ros.bagrun.run_bag`."""
    from .ros.bagrun import run_bag as _run_bag
    from .ros.messages import DEFAULT_LEFT_TOPIC, DEFAULT_RIGHT_TOPIC

    fallback = None
    if config_path is not None:
        from .io.calib import is_orbslam2_settings, read_yaml_file

        if is_orbslam2_settings(read_yaml_file(config_path)):
            fallback = config_path
    return _run_bag(bag, out, cfg, left_topic=left_topic or DEFAULT_LEFT_TOPIC,
                    right_topic=right_topic or DEFAULT_RIGHT_TOPIC, left_info=left_info, right_info=right_info,
                    calib=calib, fallback_calib=fallback, tolerance_s=tolerance_s, rectify=rectify, frames=frames,
                    models_dir=models_dir, save_masks=save_masks, outputs=outputs, progress=progress)


def export_bag(
    sequence: str | Path | Sequence,
    out: str | Path,
    fmt: str = "ros1",
    *,
    frames: str | int | None = None,
    calib: str | Path | None = None,
    color: bool = False,
    encoding: str = "auto",
    raw: bool = False,
    time_offset_s: float = 0.0,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
):
    """Write a stereo sequence folder as a bag (``ros1`` .bag, ``ros2`` .db3, ``mcap``) on
    ``/camera/{left,right}/image_raw`` + ``camera_info``; see :func:`dynastereo.ros.bags.export_bag`."""
    from .ros.bags import export_bag as _export

    seq = load_sequence(sequence, calib, color=color)
    indices = parse_frame_spec(frames, len(seq))
    return _export(seq, out, fmt, frames=indices, encoding=encoding, raw=raw, time_offset_s=time_offset_s,
                   overwrite=overwrite, progress=progress)
