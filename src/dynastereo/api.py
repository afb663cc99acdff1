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
from .io.outputs import check_output_file, prepare_output_dir
from .io.stereo_check import check_sequence
from .pipeline import MaskJobResult, SlamJobResult, run_mask_job, run_slam_job


def load_sequence(sequence: str | Path | Sequence, calib: str | Path | None = None,
                  color: bool | None = None) -> Sequence:
    if isinstance(sequence, (str, Path)):
        return open_sequence(Path(sequence), calib=Path(calib) if calib else None, color=color)
    return sequence


def _checked_inputs(seq: Sequence, cfg: Config, frames, models_dir, ground_truth, *, out, overwrite: bool,
                    stereo_check: bool):
    """(frame indices, masker) for a job, after the checks made before its first frame: the
    frames, the stereo pair (``io.stereo_check``), the model (the masker factory verifies
    it), and last the output folder (``io.outputs.prepare_output_dir``: an earlier run there
    is cleared only once the inputs proved good)."""
    from .masking import build_masker

    indices = parse_frame_spec(frames, len(seq))
    if stereo_check:
        check_sequence(seq, indices)
    masker = build_masker(cfg, seq.calibration, models_dir=models_dir, ground_truth=ground_truth)
    prepare_output_dir(out, overwrite=overwrite)
    return indices, masker


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
    overwrite: bool = True,
    stereo_check: bool = True,
) -> MaskJobResult:
    """Mask the dynamic objects of ``sequence`` in both images; see ``pipeline.run_mask_job``.

    ``overwrite``: the outputs of an earlier run in ``out`` are deleted first (False: an
    :class:`~dynastereo.errors.OutputError`, as the CLI without ``--overwrite``);
    ``stereo_check``: refuse pairs that are identical, swapped or not rectified
    (:class:`~dynastereo.errors.StereoCheckError`; ``io.stereo_check``)."""
    cfg = cfg or Config()
    if save_disparity and cfg.stereo.region != "full":
        cfg = cfg.with_overrides({"stereo.region": "full"})
    seq = load_sequence(sequence, calib)
    indices, masker = _checked_inputs(seq, cfg, frames, models_dir, getattr(seq, "path", None), out=out,
                                      overwrite=overwrite, stereo_check=stereo_check)
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
    overwrite: bool = True,
    stereo_check: bool = True,
) -> SlamJobResult:
    """Mask and track ``sequence`` with the stereo SLAM; see ``pipeline.run_slam_job``.

    ``frames`` may revisit (``"0-98,40-60"``): frames are fed in the order given.
    ``load_map``: start from a map file (``save_map`` of an earlier run); with
    ``localize_only`` the map is only localised in (no new keyframes).  ``save_map``:
    write the final map there (its path is checked before the first frame).
    ``overwrite`` / ``stereo_check``: as for :func:`mask_sequence`.
    """
    cfg = cfg or Config()
    seq = load_sequence(sequence, calib)
    return slam_job(seq, out, cfg, frames=frames, models_dir=models_dir, ground_truth=getattr(seq, "path", None),
                    save_masks=save_masks, progress=progress, save_map=save_map, load_map=load_map,
                    localize_only=localize_only, overwrite=overwrite, stereo_check=stereo_check)


def slam_job(
    seq: Sequence,
    out: str | Path,
    cfg: Config,
    *,
    frames: str | int | None = None,
    models_dir: str | Path | None = None,
    ground_truth: str | Path | None = None,
    open_sinks: Callable[[], tuple] | None = None,
    save_masks: bool = False,
    progress: Callable[[int, int, dict], None] | None = None,
    save_map: str | Path | None = None,
    load_map: str | Path | None = None,
    localize_only: bool = False,
    overwrite: bool = True,
    stereo_check: bool = True,
) -> SlamJobResult:
    """The one place that assembles reader -> masker -> SLAM -> writers, for a folder, a
    bag or anything else that is a :class:`~dynastereo.io.base.Sequence`: the inputs checked
    (:func:`_checked_inputs`: frames, stereo pair, model, then the output folder), the
    masker from :func:`dynastereo.masking.build_masker` (the sequence's calibration), the
    SLAM system (optionally from ``load_map``), then :func:`~dynastereo.pipeline.run_slam_job`
    with the per-frame writers ``open_sinks()`` returns (a bag's; opened once the output
    folder is ready; :class:`~dynastereo.pipeline.FrameSink`)."""
    from .config import to_dict
    from .errors import ConfigError
    from .slam import System

    if localize_only and load_map is None:
        raise ConfigError("localisation only needs a map: give load_map (--load-map FILE)")
    if save_map is not None:
        check_output_file(save_map, what="map file")
    indices, masker = _checked_inputs(seq, cfg, frames, models_dir, ground_truth, out=out, overwrite=overwrite,
                                      stereo_check=stereo_check)
    sinks = open_sinks() if open_sinks is not None else ()
    system = System(cfg, seq.calibration)
    info = {}
    if load_map is not None:
        try:
            system.load_map(load_map, localize_only=localize_only)
        except BaseException:
            system.shutdown()
            raise
        info = {"loaded": str(load_map), "localize_only": bool(localize_only)}
    return run_slam_job(seq, masker, system, out, indices, config_dict=to_dict(cfg), sinks=sinks,
                        save_masks=save_masks, progress=progress, save_map=save_map, map_info=info)


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
    overwrite: bool = True,
    stereo_check: bool = True,
):
    """Mask and track a stereo bag (ROS 1 .bag, ROS 2 .db3, .mcap); results as for
    :func:`run_sequence` plus ``out/output.<fmt>`` and ``out/bag.json``.  Calibration:
    ``calib`` (YAML) > the bag's CameraInfo > ``config_path`` when it is an ORB-SLAM2
    settings file.  ``overwrite`` / ``stereo_check``: as for :func:`mask_sequence`.
    See :func:`dynastereo.ros.bagrun.run_bag`."""
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
                    models_dir=models_dir, save_masks=save_masks, outputs=outputs, progress=progress,
                    overwrite=overwrite, stereo_check=stereo_check)


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
