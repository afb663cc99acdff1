"""Masking of dynamic objects in both stereo images (thesis 3.3).

``build_masker(cfg, calibration)`` builds the masker ``cfg.masker.kind`` names:

* ``outline`` (default): detector on the left image, disparity where the boxes need it,
  outline from the dominant disparity peak, mask moved to the right image by disparity;
* ``box``: the boxes, moved to the right image by their disparity;
* ``seg``: an instance-segmentation network on both images (AGPL model: a baseline only);
* ``none``: nothing masked.
"""

from __future__ import annotations

from pathlib import Path

from ..config import Config
from ..errors import ConfigError
from ..datatypes import StereoCalibration
from .base import Detector, DisparityEstimator, Masker
from .disparity import StereoMatcher, normalize_disparity
from .maskers import MASK_STAGES, BoxMasker, NoneMasker, OutlineMasker, SegMasker
from .outline import OutlineResult, outline_objects
from .transfer import TransferResult, transfer_labels


def build_masker(
    cfg: Config,
    calibration: StereoCalibration | None = None,
    *,
    models_dir: str | Path | None = None,
    detector: Detector | None = None,
    ground_truth: str | Path | None = None,
    full_disparity: bool = False,
) -> Masker:
    """The masker for ``cfg.masker.kind`` -- the one factory ``mask``, ``run``, ``run --bag``
    and the live node build their maskers with.

    ``calibration``: the rig's (its baseline sets the road line's plausible slopes; without
    it ``masker.outline.ground_baseline`` or KITTI's).  ``detector`` replaces the one
    ``cfg.detector`` names (tests, or a node that keeps its network across parameter
    changes); ``detector.name: oracle`` uses the ground-truth boxes of the synthetic
    sequence at ``ground_truth`` (``dynastereo synth``).  ``full_disparity=True`` makes the
    disparity-based maskers compute the whole frame and return it in
    ``StereoMasks.disparity`` (to save it), as ``stereo.region: full`` does.
    """
    cfg.masker.validate()  # (a configuration changed after it was made)
    kind = str(cfg.masker.kind).lower()
    if kind == "none":
        return NoneMasker()
    if kind == "seg":
        from .detection import create_seg_model

        model = create_seg_model(cfg.masker.seg_model, cfg.detector, models_dir)
        return SegMasker(model, max_disparity=float(cfg.stereo.min_disparity + cfg.stereo.num_disparities))
    matcher = StereoMatcher(cfg.stereo)  # validates the stereo section first
    from .detection import DetectionStage, create_detector

    if detector is None:
        detector = _oracle(ground_truth, cfg.detector.dynamic_classes) if str(cfg.detector.name) == "oracle" else \
            create_detector(cfg.detector, models_dir)
    if not isinstance(detector, DetectionStage):
        detector = DetectionStage(detector, cfg.detector)
    baseline = calibration.baseline if calibration is not None else None
    if kind == "box":
        return BoxMasker(detector, matcher, cfg.masker.outline, full_disparity=full_disparity,
                         margin=cfg.masker.box_margin)
    return OutlineMasker(detector, matcher, cfg.masker.outline, full_disparity=full_disparity, baseline=baseline)


def _oracle(ground_truth: str | Path | None, classes) -> Detector:
    """The ground-truth boxes of a synthetic sequence, of the labels ``classes`` only
    (``detector.dynamic_classes``: hiding a class makes a mover the detector does not know)."""
    if ground_truth is None:
        raise ConfigError("detector 'oracle' needs a synthetic sequence's ground truth (dynastereo synth); "
                          "not available for bags or live topics")
    from ..synth import OracleDetector

    return OracleDetector(ground_truth, classes=tuple(classes))


__all__ = [
    "BoxMasker",
    "MASK_STAGES",
    "Detector",
    "DisparityEstimator",
    "Masker",
    "NoneMasker",
    "OutlineMasker",
    "OutlineResult",
    "SegMasker",
    "StereoMatcher",
    "TransferResult",
    "build_masker",
    "normalize_disparity",
    "outline_objects",
    "transfer_labels",
]
