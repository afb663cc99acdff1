"""Object detectors (left image only) and their array-wise post-processing.

``create_detector(cfg)`` builds a :class:`~dynastereo.masking.base.Detector` from a
:class:`~dynastereo.config.DetectorConfig`: ``cfg.name`` is a registry name
(``yolov3``, ``yolov3-tiny``, ``yolox-nano``, ``fastestdet``, ``yolo11n-int8``) found in
``<models_dir>/<name>/``, or a path to a Darknet ``.cfg`` (weights beside it, same stem)
or an ``.onnx`` file (layout recognized from its output shapes).
``create_seg_model`` builds the instance-segmentation baseline (``yolov8n-seg-int8``).
"""

from __future__ import annotations

from pathlib import Path

from ...config import DetectorConfig
from ...errors import ModelError
from ...models.registry import KNOWN_MODELS, ModelSpec, note_unregistered, resolve_models_dir, verify_at_load
from ...models.sizecheck import check_darknet_weights, check_onnx_size
from ..base import Detector
from .classes import COCO_CLASSES, canonical_name, dynamic_class_mask
from .common import BoxTransform, RawOutput, YoloDetectorBase, letterbox, to_bgr
from .darknet import DarknetDetector
from .onnx import (
    FastestDetDetector,
    UltralyticsDetector,
    UltralyticsSegModel,
    YoloxDetector,
    detect_onnx_layout,
    make_session,
    runtime_of,
)
from .runtime import PRECISIONS, RUNTIMES, OpenVinoSession, RuntimeChoice, openvino_available, resolve_runtime
from .scale import CANVAS_MODES, ScaledDetector, Tile, merge_tile_boxes, tile_windows
from .stage import Contrast, DetectionStage
from .box_tracker import BoxTracker, TrackerParams
from .postprocess import (
    DARKNET_LAYOUT,
    ULTRALYTICS_LAYOUT,
    YOLOX_LAYOUT,
    PostResult,
    RowLayout,
    nms,
    postprocess,
    postprocess_loop,
)

_ONNX_CLASSES = {
    "yolox": YoloxDetector,
    "fastestdet": FastestDetDetector,
    "ultralytics": UltralyticsDetector,
    "ultralytics-seg": UltralyticsSegModel,
}


def _known_list() -> str:
    return ", ".join(KNOWN_MODELS)


def _installed_files(spec: ModelSpec, models_dir: Path | str | None) -> Path:
    """The model's folder, after checking its required files are there."""
    root = resolve_models_dir(models_dir)
    d = root / spec.name
    for f in spec.files:
        if f.filename == "coco.names":
            continue  # optional: falls back to the model's metadata / the built-in COCO list
        p = d / f.filename
        if not p.is_file():
            hint = (
                f"run `dynastereo models download {spec.name}`"
                if all(x.url for x in spec.files)
                else f"{spec.licence}: no official download; place the file there (or `dynastereo models download {spec.name} --mirror URL`)"
            )
            raise ModelError(f"model '{spec.name}' file missing (models dir {root}); {hint}; or point --models-dir "
                             f"DIR / $DYNASTEREO_MODELS at a folder holding {spec.name}/", p)
    verify_at_load(spec, d)
    return d


def _onnx_detector(path: Path, cfg: DetectorConfig, name: str | None, want_layout: str | None = None) -> YoloDetectorBase:
    session = make_session(path, cfg.threads, choice=runtime_of(cfg))
    layout = detect_onnx_layout(session, path)
    if want_layout is not None and layout != want_layout:
        raise ModelError(f"expected a '{want_layout}' model, but the outputs look like '{layout}'", path)
    return _ONNX_CLASSES[layout](path, cfg, name=name, session=session)


def create_detector(cfg: DetectorConfig | None = None, models_dir: Path | str | None = None) -> Detector:
    """A detector for ``cfg.name`` (registry name or .cfg/.onnx path); see the module docstring.

    Raises :class:`ModelError` for an unknown name (listing the known ones) or a missing
    file (naming it and the download command), :class:`ConfigError` for unknown
    ``dynamic_classes``.
    """
    cfg = cfg or DetectorConfig()
    name = str(cfg.name)
    spec = KNOWN_MODELS.get(name)
    if spec is not None:
        d = _installed_files(spec, models_dir)
        main = d / spec.main_file.filename
        if spec.kind == "darknet":
            weights = d / spec.weights_file.filename  # type: ignore[union-attr]
            return DarknetDetector(main, weights, None, cfg, name=name, input_size=spec.input_size)
        return _onnx_detector(main, cfg, name, spec.layout)
    p = Path(name).expanduser()
    suffix = p.suffix.lower()
    if suffix in (".cfg", ".onnx"):
        if not p.is_file():
            raise ModelError("detector model file not found", p)
        if suffix == ".cfg":
            weights = p.with_suffix(".weights")
            if not weights.is_file():
                raise ModelError(f"Darknet weights not found beside the cfg (expected {weights.name})", weights)
            check_darknet_weights(p, weights)  # a truncated file: refused before any warning
            note_unregistered(p, weights)
            return DarknetDetector(p, weights, None, cfg, name=p.stem)
        check_onnx_size(p)
        note_unregistered(p)
        return _onnx_detector(p, cfg, p.stem)
    raise ModelError(f"unknown detector '{name}'; known models: {_known_list()}, or a path to a .cfg or .onnx file")


def create_seg_model(
    name_or_path: str | Path, cfg: DetectorConfig | None = None, models_dir: Path | str | None = None
) -> UltralyticsSegModel:
    """The instance-segmentation baseline (``yolov8n-seg-int8`` or a YOLOv8-seg .onnx path).

    Thresholds, dynamic classes and threads come from ``cfg`` (a DetectorConfig).
    """
    cfg = cfg or DetectorConfig()
    name = str(name_or_path)
    spec = KNOWN_MODELS.get(name)
    if spec is not None:
        if spec.kind != "seg":
            seg = [s.name for s in KNOWN_MODELS.values() if s.kind == "seg"]
            raise ModelError(f"'{name}' is not a segmentation model; segmentation models: {', '.join(seg)}")
        d = _installed_files(spec, models_dir)
        return _onnx_detector(d / spec.main_file.filename, cfg, name, "ultralytics-seg")  # type: ignore[return-value]
    p = Path(name).expanduser()
    if p.suffix.lower() == ".onnx":
        if not p.is_file():
            raise ModelError("segmentation model file not found", p)
        note_unregistered(p)
        return _onnx_detector(p, cfg, p.stem, "ultralytics-seg")  # type: ignore[return-value]
    seg = [s.name for s in KNOWN_MODELS.values() if s.kind == "seg"]
    raise ModelError(f"unknown segmentation model '{name}'; known: {', '.join(seg)}, or a path to an .onnx file")


__all__ = [
    "BoxTracker",
    "OpenVinoSession",
    "PRECISIONS",
    "RUNTIMES",
    "RuntimeChoice",
    "openvino_available",
    "resolve_runtime",
    "runtime_of",
    "BoxTransform",
    "CANVAS_MODES",
    "Contrast",
    "DetectionStage",
    "ScaledDetector",
    "Tile",
    "TrackerParams",
    "merge_tile_boxes",
    "tile_windows",
    "COCO_CLASSES",
    "DARKNET_LAYOUT",
    "DarknetDetector",
    "FastestDetDetector",
    "PostResult",
    "RawOutput",
    "RowLayout",
    "ULTRALYTICS_LAYOUT",
    "UltralyticsDetector",
    "UltralyticsSegModel",
    "YOLOX_LAYOUT",
    "YoloDetectorBase",
    "YoloxDetector",
    "canonical_name",
    "create_detector",
    "create_seg_model",
    "detect_onnx_layout",
    "dynamic_class_mask",
    "letterbox",
    "make_session",
    "nms",
    "postprocess",
    "postprocess_loop",
    "to_bgr",
]
