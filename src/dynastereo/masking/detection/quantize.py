"""INT8 (static, QDQ) copies of the ONNX detectors, calibrated on real frames.

``quantize_detector(model, images, out)`` rewrites the detector's graph to the canvas it
runs on (a KITTI frame at scale 1: 1248x384, :mod:`..masking.detection.rewrite`), feeds it
the calibration images exactly as the detector prepares them (CLAHE, letterbox), and
writes a QDQ graph (onnxruntime's ``quantize_static``: int8 weights per channel,
int8 activations from min/max ranges).  Both runtimes read that file: onnxruntime runs
it with its int8 kernels, OpenVINO as int8 (VNNI / AMX where the CPU has them).

The calibration frames must not be the frames the result is scored on: the benchmark
(``benchmarks/bench_recall.py``) calibrates on KITTI 03 and scores on KITTI 06 and raw
0001.  Use: ``python -m dynastereo.masking.detection.quantize --images DIR/*.png --out FILE.onnx``.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Iterable

import cv2
import numpy as np

from ...config import DetectorConfig
from ...errors import ModelError


def calibration_blobs(detector, images: Iterable[Path | str], contrast: bool = True) -> list[np.ndarray]:
    """The network inputs of ``images`` as ``detector`` (a YOLOX/FastestDet ONNX detector
    at its canvas) prepares them, after the stage's CLAHE."""
    from .stage import Contrast

    clahe = Contrast() if contrast else None
    blobs = []
    for p in images:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ModelError("cannot read the calibration image", Path(p))
        if clahe is not None:
            img = clahe(img)
        blob, _ = detector._prepare(img)
        blobs.append(blob)
    return blobs


def _opset13(data: bytes) -> bytes:
    """The graph at ONNX opset >= 13 (per-channel DequantizeLinear needs its ``axis``)."""
    import onnx
    from onnx import version_converter

    m = onnx.load_from_string(data)
    op = max((o.version for o in m.opset_import if o.domain in ("", "ai.onnx")), default=13)
    if op >= 13:
        return data
    return version_converter.convert_version(m, 13).SerializeToString()


def quantize_detector(model: str | Path, images: list[Path | str], out: str | Path,
                      canvas: tuple[int, int] | None = None, f32_tail: int = 36) -> Path:
    """A QDQ int8 copy of ``model`` at ``canvas`` (width, height; default: the first
    image's size rounded up to multiples of 32), calibrated on ``images``; returns ``out``.
    ``f32_tail``: the last convolutions left in f32 (36: YOLOX-nano's decoupled head, 12
    convolutions at each of 3 levels -- quantized, its objectness falls from 0.97 to 0.30
    on a KITTI frame and nothing is detected)."""
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

    from . import create_detector
    from .scale import round32

    if not images:
        raise ModelError("no calibration images given")
    # the three-channel graph is the one quantized (not the grey-input copy)
    cfg = DetectorConfig(name=str(model), runtime="onnxruntime", threads=2, grey_input=False)
    det = create_detector(cfg)
    if canvas is None:
        im = cv2.imread(str(images[0]), cv2.IMREAD_UNCHANGED)
        canvas = (round32(im.shape[1]), round32(im.shape[0]))
    det = det.with_canvas(*canvas)
    blobs = calibration_blobs(det, images)
    name = det.input_name

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.it = iter(blobs)

        def get_next(self):
            b = next(self.it, None)
            return None if b is None else {name: b}

    from ..masking.detection.rewrite import rewrite

    with tempfile.TemporaryDirectory() as tmp:
        f32 = Path(tmp) / "f32.onnx"
        f32.write_bytes(_opset13(rewrite(det.onnx_path, det.onnx_layout, canvas[0], canvas[1])))
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        import onnx

        g = onnx.load(str(f32)).graph
        # the convolutions, but not the head's last ones (box regression, objectness and
        # class logits stay f32: one int8 range for all would flatten the scores)
        convs = [n.name for n in g.node if n.op_type == "Conv"]
        keep_f32 = [n.name for n in g.node if n.op_type == "Conv" and "_preds" in "".join(n.input)]
        keep_f32 += convs[len(convs) - f32_tail:] if f32_tail else []
        quantize_static(str(f32), str(out), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        op_types_to_quantize=["Conv"], nodes_to_exclude=keep_f32)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="yolox-nano", help="registry name or .onnx path")
    ap.add_argument("--images", nargs="+", required=True, help="calibration images (not the scored frames)")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--f32-tail", type=int, default=36, help="last convolutions kept in f32 (the head)")
    ap.add_argument("--canvas", default="", help="WxH (default: the first image's size, multiples of 32)")
    a = ap.parse_args(argv)
    canvas = tuple(int(v) for v in a.canvas.lower().split("x")) if a.canvas else None
    print(quantize_detector(a.model, a.images, a.out, canvas, a.f32_tail))  # type: ignore[arg-type]


if __name__ == "__main__":
    main()
