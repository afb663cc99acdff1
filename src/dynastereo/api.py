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


def load_sequence(sequence: str | Path | Sequence, calib: str | Path | None = None, color: bool = False) -> Sequence:
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
    return create_masker(cfg, models_dir=Path(models_dir) if models_dir else None, detector=detector)


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
    seq = load_sequence(sequence, calib)
    indices = parse_frame_spec(frames, len(seq))
    masker = build_masker(cfg, seq, models_dir)
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
) -> SlamJobResult:
    """Mask and track ``sequence`` with the stereo SLAM; see ``pipeline.run_slam_job``.

    ``frames`` may revisit (``"0-98,40-60"``): frames are fed in the order given.
    """
    from .config import to_dict
    from .slam import System

    cfg = cfg or Config()
    seq = load_sequence(sequence, calib)
    indices = parse_frame_spec(frames, len(seq))
    masker = build_masker(cfg, seq, models_dir)
    system = System(cfg, seq.calibration)
    return run_slam_job(seq, masker, system, out, indices, config_dict=to_dict(cfg),
                        save_masks=save_masks, progress=progress)
