"""Class-name lists of the detectors and the dynamic-class filter.

Models name the 80 COCO classes slightly differently: Darknet's ``coco.names`` says
``motorbike``, ``aeroplane``, ``sofa``, ``tvmonitor``...; Ultralytics says ``motorcycle``,
``airplane``, ``couch``, ``tv``.  Every name is normalized to one canonical spelling (the
Ultralytics/COCO-API one, :data:`COCO_CLASSES`), so ``dynamic_classes`` means the same for
every model and ``Detections.class_names`` can be compared across models.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ...errors import ConfigError, ModelError

#: The 80 COCO classes in the order every COCO-trained YOLO uses (canonical spelling).
COCO_CLASSES: tuple[str, ...] = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat",
    "traffic light", "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog",
    "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella",
    "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard", "sports ball", "kite",
    "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket", "bottle",
    "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich",
    "orange", "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch",
    "potted plant", "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote",
    "keyboard", "cell phone", "microwave", "oven", "toaster", "sink", "refrigerator", "book",
    "clock", "vase", "scissors", "teddy bear", "hair drier", "toothbrush",
)  # fmt: skip

#: Other spellings of the same classes (Darknet / PASCAL VOC style) -> canonical.
ALIASES: dict[str, str] = {
    "motorbike": "motorcycle",
    "aeroplane": "airplane",
    "sofa": "couch",
    "pottedplant": "potted plant",
    "diningtable": "dining table",
    "tvmonitor": "tv",
    "hair dryer": "hair drier",
    "cellphone": "cell phone",
}


#: Classes a detector swaps on one object (a car called "truck" in one frame or tile and
#: "car" in the next): each tuple is one group for matching boxes over frames and merging
#: them across tile seams; every other class (``person`` too) is a group of its own.
CLASS_GROUPS: tuple[tuple[str, ...], ...] = (("car", "bus", "truck", "train"), ("bicycle", "motorcycle"))


def class_group_index(groups: tuple[tuple[str, ...], ...] = CLASS_GROUPS) -> dict[str, int]:
    """``{canonical class name: index of its group in groups}`` (classes in no group absent)."""
    return {canonical_name(n): gi for gi, g in enumerate(groups) for n in g}


def canonical_name(name: str) -> str:
    """Lower-case, ``_``/``-`` -> space, collapse spaces, then map aliases."""
    n = " ".join(str(name).strip().lower().replace("_", " ").replace("-", " ").split())
    return ALIASES.get(n, n)


def read_names_file(path: Path) -> tuple[str, ...]:
    """One class name per line (blank lines ignored), canonicalized."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise ModelError(f"cannot read class names: {e}", path) from None
    names = tuple(canonical_name(s) for s in lines if s.strip())
    if not names:
        raise ModelError("class-name file is empty", path)
    return names


def names_from_onnx_metadata(meta: dict[str, str]) -> tuple[str, ...] | None:
    """Ultralytics exports store ``names`` as a Python dict literal ``{0: 'person', ...}``."""
    text = meta.get("names")
    if not text:
        return None
    try:
        d = ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return None
    if isinstance(d, dict):
        try:
            return tuple(canonical_name(d[i]) for i in range(len(d)))
        except KeyError:
            return None
    if isinstance(d, (list, tuple)):
        return tuple(canonical_name(v) for v in d)
    return None


def resolve_class_names(
    model_file: Path, num_classes: int, onnx_meta: dict[str, str] | None = None
) -> tuple[str, ...]:
    """Class names for a model: ``coco.names`` beside it, else ONNX metadata, else COCO.

    The list must have exactly ``num_classes`` entries (what the network outputs).
    """
    names_file = Path(model_file).parent / "coco.names"
    source: str | Path
    if names_file.is_file():
        names, source = read_names_file(names_file), names_file
    elif onnx_meta is not None and (meta_names := names_from_onnx_metadata(onnx_meta)):
        names, source = meta_names, model_file
    else:
        names, source = COCO_CLASSES, "built-in COCO list"
    if len(names) != num_classes:
        raise ModelError(
            f"model outputs {num_classes} class scores but the class names ({source}) list {len(names)}",
            model_file,
        )
    return names


def dynamic_class_mask(class_names: Sequence[str], dynamic_classes: Iterable[str]) -> np.ndarray:
    """Boolean per class id: True where the class is one of ``dynamic_classes``.

    Built once per detector; the post-processing indexes it with the class ids of all
    candidate boxes at once.  An unknown class name raises :class:`ConfigError`.
    """
    canon = [canonical_name(n) for n in class_names]
    index = {n: i for i, n in enumerate(canon)}
    mask = np.zeros(len(canon), dtype=bool)
    unknown = []
    for want in dynamic_classes:
        c = canonical_name(want)
        if c in index:
            mask[index[c]] = True
        else:
            unknown.append(str(want))
    if unknown:
        raise ConfigError(
            f"unknown class name(s) in detector.dynamic_classes: {', '.join(unknown)}; "
            f"the model's classes are: {', '.join(canon)}"
        )
    return mask
