"""Pieces shared by the detectors: input conversion, letterbox, box mapping, base class."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import cv2
import numpy as np

from ...config import DetectorConfig
from ...errors import InputError
from ...datatypes import Detections
from .classes import dynamic_class_mask
from .postprocess import PostResult, RowLayout, postprocess, postprocess_loop


def to_bgr(image: np.ndarray) -> np.ndarray:
    """A uint8 3-channel BGR view/copy of ``image`` (gray, gray HxWx1, BGR or BGRA)."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise InputError(f"detector input must be a uint8 image, got dtype {img.dtype}")
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.ndim == 3 and img.shape[2] == 1:
        return cv2.cvtColor(img[:, :, 0], cv2.COLOR_GRAY2BGR)
    if img.ndim == 3 and img.shape[2] == 3:
        return img
    if img.ndim == 3 and img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    raise InputError(f"detector input must be HxW or HxWx{{1,3,4}}, got shape {img.shape}")


@dataclass(frozen=True)
class BoxTransform:
    """Maps boxes from the network frame to image pixels: ``x_img = (x - pad_x) * scale_x``."""

    scale_x: float
    scale_y: float
    pad_x: float
    pad_y: float
    width: int  # image size, for clipping
    height: int

    def apply(self, boxes: np.ndarray) -> np.ndarray:
        """Boxes (x1, y1, x2, y2) in image pixels, clipped to the image."""
        out = np.empty_like(boxes, dtype=np.float32)
        out[:, 0::2] = (boxes[:, 0::2] - self.pad_x) * self.scale_x
        out[:, 1::2] = (boxes[:, 1::2] - self.pad_y) * self.scale_y
        np.clip(out[:, 0::2], 0, self.width, out=out[:, 0::2])
        np.clip(out[:, 1::2], 0, self.height, out=out[:, 1::2])
        return out


def letterbox(
    image: np.ndarray, size: tuple[int, int], pad_value: int = 114, center: bool = False
) -> tuple[np.ndarray, float, tuple[int, int]]:
    """Resize keeping the aspect ratio into ``size`` = (width, height), pad the rest.

    ``center=False`` pads at the right/bottom (YOLOX: image at the top-left);
    ``center=True`` splits the padding evenly (Ultralytics).
    Returns ``(padded, ratio, (pad_x, pad_y))``.
    """
    h, w = image.shape[:2]
    tw, th = size
    r = min(tw / w, th / h)
    nw, nh = min(tw, int(round(w * r))), min(th, int(round(h * r)))
    if center:
        px, py = int(round((tw - nw) / 2 - 0.1)), int(round((th - nh) / 2 - 0.1))
    else:
        px = py = 0
    out = np.full((th, tw, image.shape[2]), pad_value, np.uint8)
    out[py : py + nh, px : px + nw] = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_LINEAR)
    return out, r, (px, py)


@dataclass
class RawOutput:
    """What the network returned for one image, with what is needed to finish it."""

    outputs: list[np.ndarray]
    transform: BoxTransform
    image_shape: tuple[int, int]  # (H, W)
    extra: dict = field(default_factory=dict)


class YoloDetectorBase:
    """Shared ``detect`` = ``raw_outputs`` (pre-process + network) then ``postprocess``.

    Subclasses set ``name``, ``class_names``, ``num_classes``, ``layout`` and implement
    :meth:`raw_outputs` (and :meth:`rows` when the raw output needs decoding).
    """

    name: str
    class_names: tuple[str, ...]
    num_classes: int
    layout: RowLayout

    def _init_common(self, name: str, class_names: Sequence[str], config: DetectorConfig | None) -> None:
        self.config = config or DetectorConfig()
        self.name = name
        self.class_names = tuple(class_names)
        self.num_classes = len(self.class_names)
        self.dynamic = dynamic_class_mask(self.class_names, self.config.dynamic_classes)
        self.score_threshold = float(self.config.score_threshold)
        self.nms_threshold = float(self.config.nms_threshold)
        self.min_box_size = float(self.config.min_box_size)

    # -- to implement ---------------------------------------------------------
    def raw_outputs(self, image: np.ndarray) -> RawOutput:
        raise NotImplementedError

    def rows(self, raw: RawOutput) -> np.ndarray | list[np.ndarray]:
        """The prediction rows in the network frame (decoded where the model needs it)."""
        return raw.outputs

    # -- shared ---------------------------------------------------------------
    def select(self, raw: RawOutput, loop: bool = False) -> PostResult:
        """Threshold + dynamic-class filter + NMS; ``loop=True``: the per-row baseline."""
        fn = postprocess_loop if loop else postprocess
        return fn(self.rows(raw), self.num_classes, self.layout, self.score_threshold, self.nms_threshold, self.dynamic)

    def postprocess(self, raw: RawOutput, loop: bool = False) -> Detections:
        """Raw network output -> :class:`Detections` in image pixels (clipped)."""
        res = self.select(raw, loop=loop)
        return self._to_detections(res, raw)

    def _to_detections(self, res: PostResult, raw: RawOutput) -> Detections:
        if len(res) == 0:
            return Detections.empty(self.class_names)
        boxes = raw.transform.apply(res.boxes)
        wh = boxes[:, 2:] - boxes[:, :2]
        keep = (wh[:, 0] >= self.min_box_size) & (wh[:, 1] >= self.min_box_size)
        return Detections(boxes[keep], res.scores[keep], res.class_ids[keep], self.class_names)

    def detect(self, image: np.ndarray) -> Detections:
        """Dynamic-class detections in ``image`` pixel coordinates (BGR or gray input)."""
        return self.postprocess(self.raw_outputs(image))

    def raw_outputs_batch(self, images: list[np.ndarray]) -> list[RawOutput]:
        """:meth:`raw_outputs` of several images (one network call where the model allows)."""
        return [self.raw_outputs(im) for im in images]

    def detect_batch(self, images: list[np.ndarray]) -> list[Detections]:
        """:meth:`detect` of several images, e.g. the tiles of one frame."""
        return [self.postprocess(r) for r in self.raw_outputs_batch(images)]

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"
