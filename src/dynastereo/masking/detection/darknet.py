"""YOLOv3 / YOLOv3-tiny through OpenCV's dnn Darknet importer (thesis 3.2.1).

OpenCV 4.x only (OpenCV 5 dropped ``readNetFromDarknet``).  Input: plain resize to the
network size (no letterbox, as OpenCV's samples and the thesis do), RGB, 0..1.  Output:
one array per YOLO layer, rows ``[cx, cy, w, h]`` (0..1 of the image) + objectness + 80
class scores that already include the objectness (:data:`DARKNET_LAYOUT`).  OpenCV's YOLO
layer zeroes class scores <= 0.2, so a ``score_threshold`` below 0.2 changes nothing here.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from ...config import DetectorConfig
from ...errors import ConfigError, ModelError
from ...models.sizecheck import check_darknet_weights
from .classes import COCO_CLASSES, read_names_file
from .common import BoxTransform, RawOutput, YoloDetectorBase, to_bgr
from .postprocess import DARKNET_LAYOUT


def read_cfg_net(cfg_path: Path) -> dict[str, str]:
    """The ``[net]`` section of a Darknet .cfg as a dict (keys lower-case)."""
    out: dict[str, str] = {}
    section = None
    try:
        text = Path(cfg_path).read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise ModelError(f"cannot read Darknet cfg: {e}", cfg_path) from None
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith("["):
            section = line.strip("[]").strip().lower()
            continue
        if section == "net" and "=" in line:
            k, v = line.split("=", 1)
            out[k.strip().lower()] = v.strip()
    return out


def count_yolo_classes(cfg_path: Path) -> int | None:
    """``classes=`` of the first ``[yolo]``/``[region]`` section, if any."""
    section = None
    for line in Path(cfg_path).read_text(encoding="utf-8", errors="replace").splitlines():
        line = line.split("#", 1)[0].strip()
        if line.startswith("["):
            section = line.strip("[]").strip().lower()
        elif section in ("yolo", "region") and line.replace(" ", "").startswith("classes="):
            try:
                return int(line.split("=", 1)[1])
            except ValueError:
                return None
    return None


class DarknetDetector(YoloDetectorBase):
    """YOLOv3 / YOLOv3-tiny (.cfg + .weights) on OpenCV dnn, CPU.

    ``names``: a class-name file, a sequence of names, or ``None`` (``coco.names`` beside
    the cfg, else the built-in COCO list).  Input size: ``config.input_size`` if set, else
    ``input_size`` (the registry's default), else the cfg's ``[net] width/height``.

    ``config.threads`` is applied with ``cv2.setNumThreads`` -- a process-wide OpenCV setting
    (it also governs the stereo matchers); the default 2 matches OpenCV's own default on a
    2-core machine.  One instance is not thread-safe (``cv2.dnn.Net`` holds its input);
    the ONNX detectors are.
    """

    layout = DARKNET_LAYOUT

    def __init__(
        self,
        cfg_path: str | Path,
        weights_path: str | Path,
        names: str | Path | Sequence[str] | None = None,
        config: DetectorConfig | None = None,
        *,
        name: str | None = None,
        input_size: int | None = None,
    ) -> None:
        cfg_path, weights_path = Path(cfg_path), Path(weights_path)
        for p, what in ((cfg_path, "Darknet cfg"), (weights_path, "Darknet weights")):
            if not p.is_file():
                raise ModelError(f"{what} file not found", p)
        config = config or DetectorConfig()
        if names is None:
            nf = cfg_path.parent / "coco.names"
            class_names = read_names_file(nf) if nf.is_file() else COCO_CLASSES
        elif isinstance(names, (str, Path)):
            class_names = read_names_file(Path(names))
        else:
            class_names = tuple(names)
        n_cfg = count_yolo_classes(cfg_path)
        if n_cfg is not None and n_cfg != len(class_names):
            raise ModelError(f"cfg declares classes={n_cfg} but {len(class_names)} class names were given", cfg_path)
        self._init_common(name or cfg_path.stem, class_names, config)

        net_section = read_cfg_net(cfg_path)
        size = config.input_size or input_size
        if size is not None:
            self.input_w = self.input_h = int(size)
        else:
            try:
                self.input_w = int(net_section.get("width", 416))
                self.input_h = int(net_section.get("height", 416))
            except ValueError:
                raise ModelError("[net] width/height are not integers", cfg_path) from None
        if self.input_w % 32 or self.input_h % 32 or self.input_w <= 0 or self.input_h <= 0:
            raise ConfigError(
                f"detector.input_size must be a positive multiple of 32 for Darknet YOLO, got {self.input_w}x{self.input_h}"
            )

        check_darknet_weights(cfg_path, weights_path)  # a truncated file: one line, before the first frame
        if config.threads and config.threads > 0:
            cv2.setNumThreads(int(config.threads))
        try:
            self.net = cv2.dnn.readNetFromDarknet(str(cfg_path), str(weights_path))
        except (cv2.error, AttributeError) as e:
            raise ModelError(f"OpenCV cannot load the Darknet model (with weights {weights_path}): {e}", cfg_path) from None
        if self.net.empty():
            raise ModelError(f"OpenCV loaded an empty network (weights {weights_path})", cfg_path)
        self.net.setPreferableBackend(cv2.dnn.DNN_BACKEND_OPENCV)
        self.net.setPreferableTarget(cv2.dnn.DNN_TARGET_CPU)
        self.out_names = tuple(self.net.getUnconnectedOutLayersNames())
        self.cfg_path, self.weights_path = cfg_path, weights_path

    can_rewrite = True
    batch = 1

    def with_canvas(self, width: int, height: int, batch: int = 1) -> "DarknetDetector":
        """The same network at a ``width`` x ``height`` blob (Darknet's YOLO layers take
        any multiple of 32); shares the loaded network, so not for another thread."""
        if width % 32 or height % 32 or width <= 0 or height <= 0:
            raise ConfigError(f"Darknet YOLO canvas sides must be positive multiples of 32, got {width}x{height}")
        if (width, height) == (self.input_w, self.input_h):
            return self
        other = copy.copy(self)
        other.input_w, other.input_h = int(width), int(height)
        return other

    def raw_outputs_batch(self, images: list[np.ndarray]) -> list[RawOutput]:
        return [self.raw_outputs(im) for im in images]

    def raw_outputs(self, image: np.ndarray) -> RawOutput:
        """Network outputs (one (N_l, 85) array per YOLO layer) for ``image``."""
        img = to_bgr(image)
        h, w = img.shape[:2]
        blob = cv2.dnn.blobFromImage(img, 1 / 255.0, (self.input_w, self.input_h), swapRB=True, crop=False)
        self.net.setInput(blob)
        outs = [np.asarray(o, np.float32) for o in self.net.forward(self.out_names)]
        # rows are 0..1 of the (resized) image -> pixels: scale by the image size
        return RawOutput(outs, BoxTransform(float(w), float(h), 0.0, 0.0, w, h), (h, w))
