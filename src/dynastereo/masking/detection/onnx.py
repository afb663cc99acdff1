"""ONNX detectors on onnxruntime (CPU): YOLOX, FastestDet, Ultralytics YOLOv8/YOLO11 (+ seg).

Each class documents its model's input and output; all share the array-wise
post-processing of :mod:`.postprocess`.  The two Ultralytics models are AGPL-3.0 and are
used only as measured baselines (never a default).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ...config import DetectorConfig
from ...errors import ConfigError, ModelError
from ...datatypes import Detections
from ...models.sizecheck import check_onnx_size
from .classes import resolve_class_names
from .common import BoxTransform, RawOutput, YoloDetectorBase, letterbox, to_bgr
from .postprocess import ULTRALYTICS_LAYOUT, YOLOX_LAYOUT, PostResult
from .rewrite import rewrite
from .runtime import OpenVinoSession, RuntimeChoice, _note_once, resolve_runtime

STRIDES = (8, 16, 32)


def make_session(path: Path, threads: int, model_bytes: bytes | None = None,
                 choice: RuntimeChoice | None = None) -> Any:
    """A CPU inference session of ``choice``'s runtime (:mod:`.runtime`; default
    onnxruntime f32).  OpenVINO: :class:`~.runtime.OpenVinoSession`; a graph it cannot
    read or compile (the dynamic-int8 Ultralytics models) runs on onnxruntime, with one
    line saying so.

    An onnxruntime CPU session with ``threads`` intra-op threads (1 inter-op thread)
    that do not spin: onnxruntime's workers busy-wait between ops by default, and on two
    cores that spinning takes the core the tracking needs (KITTI 03 with the default
    settings: 7.9 FPS spinning, 9.9 FPS not; ~30 ms of CPU a frame).
    ``model_bytes``: a rewritten graph of ``path`` (:mod:`.rewrite`) instead of the file."""
    if model_bytes is None and not Path(path).is_file():
        raise ModelError("ONNX model file not found", path)
    if model_bytes is None:
        check_onnx_size(path)  # a truncated file: expected and actual size named
    if choice is not None and choice.runtime == "openvino":
        try:
            return OpenVinoSession(Path(path), threads, choice.precision, model_bytes)
        except ModelError as e:
            _note_once(f"{Path(path).name}: {e.args[0] if e.args else e}; running it on onnxruntime")
    import onnxruntime as ort

    so = ort.SessionOptions()
    if threads and threads > 0:
        so.intra_op_num_threads = int(threads)
    so.inter_op_num_threads = 1
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.add_session_config_entry("session.inter_op.allow_spinning", "0")
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.log_severity_level = 3
    try:
        src = model_bytes if model_bytes is not None else str(path)
        return ort.InferenceSession(src, sess_options=so, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types (InvalidProtobuf, Fail, ...)
        raise ModelError(f"onnxruntime cannot load the model: {e}", path) from None


def _grey_view(image: np.ndarray) -> np.ndarray | None:
    """The (H, W) uint8 image of a grey input (H x W or H x W x 1), else None."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        return None
    if img.ndim == 2:
        return img
    if img.ndim == 3 and img.shape[2] == 1:
        return img[:, :, 0]
    return None


def runtime_of(config: DetectorConfig) -> RuntimeChoice:
    """The runtime ``config`` asks for, resolved on this machine (:func:`.runtime.resolve_runtime`)."""
    return resolve_runtime(config.runtime, config.precision)


def _dims(shape: list[Any]) -> list[int | None]:
    return [d if isinstance(d, int) and d > 0 else None for d in shape]


def num_anchors(size: int) -> int:
    """Rows of a 3-level (strides 8/16/32) anchor-free head for a square input."""
    return sum((size // s) ** 2 for s in STRIDES)


def detect_onnx_layout(session: Any, path: Path | str = "") -> str:
    """``yolox`` | ``fastestdet`` | ``ultralytics`` | ``ultralytics-seg`` from the output shapes."""
    ins = session.get_inputs()
    outs = [_dims(o.shape) for o in session.get_outputs()]
    in_shape = _dims(ins[0].shape) if ins else []
    size = in_shape[2] if len(in_shape) == 4 else None
    if len(outs) == 2 and sorted(len(o) for o in outs) == [3, 4]:
        return "ultralytics-seg"
    if len(outs) == 1 and len(outs[0]) == 4 and (outs[0][1] or 0) > 5:
        return "fastestdet"
    if len(outs) == 1 and len(outs[0]) == 3:
        _, a, b = outs[0]
        if size is not None:
            n = num_anchors(size)
            if b == n and (a or 0) > 4:
                return "ultralytics"
            if a == n and (b or 0) > 5:
                return "yolox"
        if a is not None and b is not None:
            return "ultralytics" if a < b else "yolox"
    raise ModelError(
        f"cannot recognize the detector layout from input {in_shape} and outputs {outs} "
        "(expected YOLOX 1xNx(5+C), FastestDet 1x(5+C)xHxW, Ultralytics 1x(4+C)xN [+ 1x32xHxW prototypes])",
        path,
    )


class OnnxDetectorBase(YoloDetectorBase):
    default_size = 416
    onnx_layout = ""  # the rewrite layout (.rewrite), "" = cannot be rewritten

    def __init__(
        self,
        onnx_path: str | Path,
        config: DetectorConfig | None = None,
        *,
        name: str | None = None,
        session: Any = None,
    ) -> None:
        self.onnx_path = Path(onnx_path)
        config = config or DetectorConfig()
        self.session = (session if session is not None
                        else make_session(self.onnx_path, config.threads, choice=runtime_of(config)))
        inp = self.session.get_inputs()[0]
        self.input_name = inp.name
        shape = _dims(inp.shape)
        if len(shape) != 4:
            raise ModelError(f"expected a 1x3xHxW input, got {inp.shape}", self.onnx_path)
        h, w = shape[2], shape[3]
        if h is not None and w is not None:
            if config.input_size is not None and (config.input_size != h or config.input_size != w):
                raise ConfigError(
                    f"detector.input_size={config.input_size} but {self.onnx_path.name} has a fixed {w}x{h} input; "
                    "leave input_size unset (null) for this model"
                )
            self.input_w, self.input_h = w, h
        else:
            self.input_w = self.input_h = int(config.input_size or self.default_size)
        self.output_shapes = [_dims(o.shape) for o in self.session.get_outputs()]
        self.batch = shape[0] or 1
        meta = self.session.get_modelmeta().custom_metadata_map or {}
        nc = self._num_classes()
        self._init_common(name or self.onnx_path.stem, resolve_class_names(self.onnx_path, nc, meta), config)

    def _num_classes(self) -> int:
        raise NotImplementedError

    @property
    def runtime(self) -> RuntimeChoice:
        """What runs this detector's graph (runtime, precision)."""
        if isinstance(self.session, OpenVinoSession):
            return RuntimeChoice("openvino", self.session.precision)
        return RuntimeChoice("onnxruntime", "f32")

    def _run(self, blob: np.ndarray) -> list[np.ndarray]:
        return self.session.run(None, {self.input_name: blob})

    @property
    def can_rewrite(self) -> bool:
        return bool(self.onnx_layout) and self.onnx_path.is_file()

    def with_canvas(self, width: int, height: int, batch: int = 1) -> "OnnxDetectorBase":
        """The same weights on a ``width`` x ``height`` canvas, ``batch`` images per call
        (the graph rewritten exactly, :mod:`.rewrite`); ``self`` when that is its canvas."""
        if (width, height, batch) == (self.input_w, self.input_h, self.batch):
            return self
        if not self.can_rewrite:
            raise ModelError(f"{type(self).__name__} cannot run at another canvas", self.onnx_path)
        data = rewrite(self.onnx_path, self.onnx_layout, width, height, batch)
        session = make_session(self.onnx_path, self.config.threads, data, choice=self.runtime)
        cfg = replace(self.config, input_size=None)
        return type(self)(self.onnx_path, cfg, name=self.name, session=session, **self._native_kw())

    def _native_kw(self) -> dict:
        return {}

    def raw_outputs_batch(self, images: list[np.ndarray]) -> list[RawOutput]:
        """:meth:`raw_outputs` of several images in one network call when the session's
        batch matches (a rewritten graph), else one call each."""
        if self.batch != len(images) or len(images) < 2:
            return [self.raw_outputs(im) for im in images]
        prepared = [self._prepare(im) for im in images]
        outs = self._run(np.concatenate([b for b, _ in prepared], axis=0))
        return [RawOutput([o[k : k + 1] for o in outs], t, t_shape, extra)
                for k, (_, (t, t_shape, extra)) in enumerate(prepared)]

    def _prepare(self, image: np.ndarray) -> tuple[np.ndarray, tuple[BoxTransform, tuple[int, int], dict]]:
        """(1x3xHxW blob, (transform, image shape, extra)) for one image."""
        raise NotImplementedError

    def raw_outputs(self, image: np.ndarray) -> RawOutput:
        blob, (t, shape, extra) = self._prepare(image)
        return RawOutput(list(self._run(blob)), t, shape, extra)


class YoloxDetector(OnnxDetectorBase):
    """YOLOX (nano/tiny/s...) ONNX export without in-model decoding.

    Input 1x3xSxS, BGR 0..255 float, letterboxed at the top-left, padded with 114.
    Output 1xNx(5+C), N = (S/8)^2 + (S/16)^2 + (S/32)^2: ``[dx, dy, log w, log h]`` per grid
    cell (decoded here: ``xy = (d + grid) * stride``, ``wh = exp(log) * stride``), objectness
    and class scores already sigmoided; score = objectness * class score.
    """

    layout = YOLOX_LAYOUT
    default_size = 416
    onnx_layout = "yolox"

    def __init__(
        self, onnx_path: str | Path, config: DetectorConfig | None = None, *, name: str | None = None, session: Any = None
    ) -> None:
        super().__init__(onnx_path, config, name=name, session=session)
        grids, strides = [], []
        for s in STRIDES:
            gh, gw = self.input_h // s, self.input_w // s
            yv, xv = np.meshgrid(np.arange(gh), np.arange(gw), indexing="ij")
            grids.append(np.stack([xv, yv], -1).reshape(-1, 2))
            strides.append(np.full((gh * gw, 1), s))
        self._grid = np.concatenate(grids).astype(np.float32)
        self._stride = np.concatenate(strides).astype(np.float32)
        # a grey frame runs a one-channel copy of the graph (rewrite.py, "Grey input"),
        # made on its first use (or the stage's warm-up) at this detector's canvas and batch
        self._grey_session: Any = None
        self._grey = bool(self.config.grey_input) and self.can_rewrite
        n = self.output_shapes[0][1]
        if n is not None and n != len(self._grid):
            raise ModelError(f"output has {n} rows, expected {len(self._grid)} for a {self.input_w}x{self.input_h} input", self.onnx_path)

    def _num_classes(self) -> int:
        c = self.output_shapes[0][-1]
        if c is None or c <= 5:
            raise ModelError(f"unexpected YOLOX output shape {self.output_shapes[0]}", self.onnx_path)
        return c - 5

    def _prepare(self, image: np.ndarray) -> tuple[np.ndarray, tuple[BoxTransform, tuple[int, int], dict]]:
        grey = _grey_view(image)
        if grey is not None:  # a grey frame: letterboxed once, not three times (the same blob)
            h, w = grey.shape
            tw, th = self.input_w, self.input_h
            r = min(tw / w, th / h)  # as letterbox()
            nw, nh = min(tw, int(round(w * r))), min(th, int(round(h * r)))
            blob = np.full((1, 1 if self._grey else 3, th, tw), 114.0, np.float32)
            blob[0, 0, :nh, :nw] = cv2.resize(grey, (nw, nh), interpolation=cv2.INTER_LINEAR)
            if not self._grey:
                blob[0, 1] = blob[0, 0]
                blob[0, 2] = blob[0, 0]
            return blob, (BoxTransform(1.0 / r, 1.0 / r, 0.0, 0.0, w, h), (h, w), {})
        img = to_bgr(image)
        h, w = img.shape[:2]
        padded, r, _ = letterbox(img, (self.input_w, self.input_h), 114, center=False)
        blob = cv2.dnn.blobFromImage(padded)  # 1x3xHxW float32, BGR, 0..255
        return blob, (BoxTransform(1.0 / r, 1.0 / r, 0.0, 0.0, w, h), (h, w), {})

    @property
    def grey_graph(self) -> bool:
        """Whether grey frames run a graph of their own (the one-channel copy)."""
        return self._grey

    def _run(self, blob: np.ndarray) -> list[np.ndarray]:
        if blob.shape[1] != 1:
            return super()._run(blob)
        if self._grey_session is None:
            try:
                data = rewrite(self.onnx_path, self.onnx_layout, self.input_w, self.input_h, self.batch, grey=True)
            except ModelError as e:  # an export whose stem is not YOLOX's Focus: three channels, as before
                _note_once(f"{self.onnx_path.name}: {e.args[0] if e.args else e}; grey frames run as three "
                           "equal channels")
                self._grey = False
                return super()._run(np.repeat(blob, 3, axis=1))
            self._grey_session = make_session(self.onnx_path, self.config.threads, data, choice=self.runtime)
        return self._grey_session.run(None, {self.input_name: blob})

    def rows(self, raw: RawOutput) -> np.ndarray:
        p = raw.outputs[0].reshape(-1, raw.outputs[0].shape[-1])
        dec = p.copy()
        dec[:, 0:2] = (p[:, 0:2] + self._grid) * self._stride
        dec[:, 2:4] = np.exp(p[:, 2:4]) * self._stride
        return dec


class FastestDetDetector(OnnxDetectorBase):
    """FastestDet (dog-qiuqiu) ONNX, as its official onnx-runtime example runs it.

    Input 1x3x352x352, plain resize (no letterbox), BGR, 0..1.  Output 1x(5+C)xHxW
    (22x22): channel 0 objectness (sigmoided in the model), 1-4 box regression, 5.. class
    scores (softmax in the model).  Decoding: ``cx = (tanh(r1) + gx) / W``,
    ``cy = (tanh(r2) + gy) / H``, ``w = sigmoid(r3)``, ``h = sigmoid(r4)`` (0..1 of the image);
    score = objectness * class score.
    """

    layout = YOLOX_LAYOUT
    default_size = 352
    onnx_layout = "fastestdet"

    def __init__(
        self, onnx_path: str | Path, config: DetectorConfig | None = None, *, name: str | None = None, session: Any = None,
        native: tuple[int, int] | None = None,
    ) -> None:
        super().__init__(onnx_path, config, name=name, session=session)
        # box sizes are sigmoids in units of the canvas the model was trained at: on a
        # rewritten canvas they are rescaled from that (native) canvas to this one
        self.native_w, self.native_h = native or (self.input_w, self.input_h)
        shp = self.output_shapes[0]
        gh = shp[2] or self.input_h // 16
        gw = shp[3] or self.input_w // 16
        self._grid_shape = (gh, gw)
        yv, xv = np.meshgrid(np.arange(gh), np.arange(gw), indexing="ij")
        self._gx = xv.reshape(-1).astype(np.float32)
        self._gy = yv.reshape(-1).astype(np.float32)

    def _native_kw(self) -> dict:
        return {"native": (self.native_w, self.native_h)}

    def _num_classes(self) -> int:
        c = self.output_shapes[0][1]
        if c is None or c <= 5:
            raise ModelError(f"unexpected FastestDet output shape {self.output_shapes[0]}", self.onnx_path)
        return c - 5

    def _prepare(self, image: np.ndarray) -> tuple[np.ndarray, tuple[BoxTransform, tuple[int, int], dict]]:
        img = to_bgr(image)
        h, w = img.shape[:2]
        blob = cv2.dnn.blobFromImage(img, 1 / 255.0, (self.input_w, self.input_h), swapRB=False, crop=False)
        return blob, (BoxTransform(float(w), float(h), 0.0, 0.0, w, h), (h, w), {})

    def rows(self, raw: RawOutput) -> np.ndarray:
        f = raw.outputs[0]
        c, gh, gw = f.shape[1], f.shape[2], f.shape[3]
        p = f.reshape(c, gh * gw).T  # (cells, 5+C)
        if (gh, gw) != self._grid_shape:
            yv, xv = np.meshgrid(np.arange(gh), np.arange(gw), indexing="ij")
            gx, gy = xv.reshape(-1).astype(np.float32), yv.reshape(-1).astype(np.float32)
        else:
            gx, gy = self._gx, self._gy
        # rows in the layout's order: [cx, cy, w, h] (0..1 of the image), objectness, classes
        out = np.empty((gh * gw, c), np.float32)
        out[:, 0] = (np.tanh(p[:, 1]) + gx) / gw
        out[:, 1] = (np.tanh(p[:, 2]) + gy) / gh
        out[:, 2:4] = 1.0 / (1.0 + np.exp(-p[:, 3:5]))
        if (self.native_w, self.native_h) != (self.input_w, self.input_h):
            out[:, 2] *= self.native_w / self.input_w
            out[:, 3] *= self.native_h / self.input_h
        out[:, 4] = p[:, 0]
        out[:, 5:] = p[:, 5:]
        return out


class UltralyticsDetector(OnnxDetectorBase):
    """Ultralytics YOLOv8 / YOLO11 detection export (AGPL-3.0: baseline only).

    Input 1x3xSxS (320 here), RGB 0..1, letterboxed in the centre with 114.
    Output 1x(4+C)xN: ``cx, cy, w, h`` in input pixels, then C class scores (no objectness).
    """

    layout = ULTRALYTICS_LAYOUT
    default_size = 640
    onnx_layout = "ultralytics"
    _extra_channels = 0  # mask coefficients (seg)

    def _det_output_index(self) -> int:
        return next(i for i, s in enumerate(self.output_shapes) if len(s) == 3)

    def _num_classes(self) -> int:
        c = self.output_shapes[self._det_output_index()][1]
        if c is None or c <= 4 + self._extra_channels:
            raise ModelError(f"unexpected Ultralytics output shape {self.output_shapes}", self.onnx_path)
        return c - 4 - self._extra_channels

    def _prepare(self, image: np.ndarray) -> tuple[np.ndarray, tuple[BoxTransform, tuple[int, int], dict]]:
        img = to_bgr(image)
        h, w = img.shape[:2]
        padded, r, (px, py) = letterbox(img, (self.input_w, self.input_h), 114, center=True)
        blob = cv2.dnn.blobFromImage(padded, 1 / 255.0, swapRB=True)
        return blob, (BoxTransform(1.0 / r, 1.0 / r, float(px), float(py), w, h), (h, w), {"ratio": r})

    def rows(self, raw: RawOutput) -> np.ndarray:
        o = raw.outputs[self._det_output_index()]
        return np.ascontiguousarray(o.reshape(o.shape[-2], o.shape[-1]).T)


class UltralyticsSegModel(UltralyticsDetector):
    """Ultralytics YOLOv8-seg export (AGPL-3.0: baseline only), e.g. yolov8n-seg.

    Outputs 1x(4+C+32)xN (box, C scores, 32 mask coefficients) and 1x32xMHxMW prototypes.
    (Rewritten canvases: box decoding only; the mask resampling assumes square prototypes.)
    :meth:`detect` returns :class:`Detections` with ``masks``: (K, H, W) bool instance masks
    at full image resolution, each ``sigmoid(coef @ prototypes) > 0.5`` bilinearly
    resampled from the prototype grid and cropped to its box.
    """

    def _num_classes(self) -> int:
        proto = next((s for s in self.output_shapes if len(s) == 4), None)
        if proto is None or proto[1] is None:
            raise ModelError(f"expected a 1xKxHxW prototype output, got {self.output_shapes}", self.onnx_path)
        self._extra_channels = proto[1]
        return super()._num_classes()

    def postprocess(self, raw: RawOutput, loop: bool = False) -> Detections:
        res = self.select(raw, loop=loop)
        h, w = raw.image_shape
        if len(res) == 0:
            d = Detections.empty(self.class_names)
            d.masks = np.zeros((0, h, w), bool)
            return d
        boxes = raw.transform.apply(res.boxes)
        wh = boxes[:, 2:] - boxes[:, :2]
        keep = (wh[:, 0] >= self.min_box_size) & (wh[:, 1] >= self.min_box_size)
        res = PostResult(res.boxes[keep], res.scores[keep], res.class_ids[keep], res.rows[keep])
        boxes = boxes[keep]
        masks = self._masks(raw, res, boxes)
        return Detections(boxes, res.scores, res.class_ids, self.class_names, masks)

    def _masks(self, raw: RawOutput, res: PostResult, boxes: np.ndarray) -> np.ndarray:
        h, w = raw.image_shape
        out = np.zeros((len(boxes), h, w), bool)
        if len(boxes) == 0:
            return out
        proto = next(o for o in raw.outputs if o.ndim == 4)[0]  # (32, MH, MW)
        nm, mh, mw = proto.shape
        rows = self.rows(raw)
        c0 = 4 + self.num_classes
        coef = rows[res.rows, c0 : c0 + nm]  # (K, 32)
        logits = (coef @ proto.reshape(nm, -1)).reshape(-1, mh, mw)  # sigmoid > 0.5 <=> logit > 0
        r = raw.extra["ratio"]
        px, py = raw.transform.pad_x, raw.transform.pad_y
        kx, ky = mw / self.input_w, mh / self.input_h
        for i, (x1, y1, x2, y2) in enumerate(boxes):  # a handful of detected boxes
            x1i, y1i = int(np.floor(x1)), int(np.floor(y1))
            x2i, y2i = int(np.ceil(x2)), int(np.ceil(y2))
            bw, bh = x2i - x1i, y2i - y1i
            if bw <= 0 or bh <= 0:
                continue
            # dst pixel (j, i) = image pixel (x1i + j, y1i + i); its centre in prototype pixels
            M = np.array(
                [
                    [r * kx, 0.0, ((x1i + 0.5) * r + px) * kx - 0.5],
                    [0.0, r * ky, ((y1i + 0.5) * r + py) * ky - 0.5],
                ],
                np.float64,
            )
            patch = cv2.warpAffine(
                logits[i], M, (bw, bh), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE
            )
            out[i, y1i:y2i, x1i:x2i] = patch > 0
        return out
