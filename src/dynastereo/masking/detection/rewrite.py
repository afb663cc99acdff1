"""Fixed-shape ONNX detectors rewritten to another canvas (and batch) where that is exact.

A detector exported with a fixed square input (YOLOX-nano 416x416, FastestDet 352x352,
YOLO11n 320x320) is a fully convolutional network: its weights do not depend on the
canvas, only a few shape constants do.  Rewriting those constants lets the same weights
run on a rectangular canvas that matches the frame's aspect (a KITTI frame 1241x376 at
scale 1 in 1248x384 instead of shrunk to a third in 416x416) or on a batch of tiles in one
call.  Per layout, the constants that depend on the input size are:

* ``yolox`` -- the three head reshapes ``[1, 85, -1]`` (only the batch dimension is fixed);
  every other op (Focus slices, convs, nearest x2 upsampling, SPP max pools, concat on
  channels) is size-agnostic.
* ``fastestdet`` -- the ShuffleNetV2 channel-shuffle reshapes ``[B*C/2, 2, H*W]`` and
  ``[2, -1, C/2, H, W]`` at strides 8, 16 and 32 (26 constants).
* ``ultralytics`` / ``ultralytics-seg`` -- the anchor points (1, 2, A) and strides (1, A)
  of ``dist2bbox`` and the two DFL reshape shapes ``[.., A]`` (the five constants that
  ``shared/tools/refmasks.py`` rewrites); batch 1 only.

Exactness: at the model's own size the rewritten graph gives bit-identical outputs
(tests check it); at another canvas it computes exactly what the network's architecture
computes there (no interpolation of weights or outputs).  Canvas sides must be multiples
of 32 (the coarsest stride).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import ModelError

STRIDES = (8, 16, 32)
REWRITABLE = ("yolox", "fastestdet", "ultralytics", "ultralytics-seg")


def _load(path: Path):
    try:
        import onnx
    except ImportError:  # pragma: no cover - onnx is a dependency
        raise ModelError("the 'onnx' package is needed to run a detector at another canvas", path) from None
    try:
        return onnx.load(str(path))
    except Exception as e:  # protobuf errors
        raise ModelError(f"cannot read the ONNX graph: {e}", path) from None


def _finish(m, width: int, height: int, batch: int) -> bytes:
    dims = m.graph.input[0].type.tensor_type.shape.dim
    dims[0].dim_value, dims[2].dim_value, dims[3].dim_value = batch, height, width
    del m.graph.value_info[:]  # stale intermediate shapes
    for o in m.graph.output:
        for d in o.type.tensor_type.shape.dim:
            d.Clear()
            d.dim_param = "d"
    return m.SerializeToString()


def _check_canvas(path: Path, width: int, height: int, batch: int) -> None:
    if width <= 0 or height <= 0 or width % 32 or height % 32:
        raise ModelError(f"detector canvas must have sides that are positive multiples of 32, got {width}x{height}",
                         path)
    if batch < 1:
        raise ModelError(f"batch must be >= 1, got {batch}", path)


def input_size(path: Path) -> tuple[int, int]:
    """(width, height) of a model's fixed input."""
    m = _load(path)
    dims = m.graph.input[0].type.tensor_type.shape.dim
    return int(dims[3].dim_value), int(dims[2].dim_value)


def rewrite_yolox(path: Path, width: int, height: int, batch: int = 1) -> bytes:
    import onnx.numpy_helper as nph

    _check_canvas(path, width, height, batch)
    m = _load(path)
    n = 0
    for t in m.graph.initializer:
        a = nph.to_array(t)
        if a.dtype == np.int64 and a.ndim == 1 and a.size == 3 and a[0] == 1 and a[2] == -1:
            t.CopyFrom(nph.from_array(np.array([batch, a[1], -1], np.int64), t.name))
            n += 1
    if n != 3:
        raise ModelError(f"not the expected YOLOX export: {n} head reshapes [1, C, -1] found, expected 3", path)
    return _finish(m, width, height, batch)


def rewrite_fastestdet(path: Path, width: int, height: int, batch: int = 1) -> bytes:
    import onnx.numpy_helper as nph

    _check_canvas(path, width, height, batch)
    m = _load(path)
    w0, h0 = input_size(path)
    n = 0
    for t in m.graph.initializer:
        a = nph.to_array(t)
        if a.dtype != np.int64 or a.ndim != 1:
            continue
        for s in STRIDES:
            gh0, gw0, gh, gw = h0 // s, w0 // s, height // s, width // s
            if a.size == 3 and a[1] == 2 and a[2] == gh0 * gw0:  # [C/2, 2, H*W]
                t.CopyFrom(nph.from_array(np.array([a[0] * batch, 2, gh * gw], np.int64), t.name))
                n += 1
                break
            if a.size == 5 and a[0] == 2 and a[1] == -1 and a[3] == gh0 and a[4] == gw0:  # [2, -1, C/2, H, W]
                t.CopyFrom(nph.from_array(np.array([2, -1, a[2], gh, gw], np.int64), t.name))
                n += 1
                break
    if n == 0 or n % 2:
        raise ModelError(f"not the expected FastestDet export: {n} channel-shuffle shapes found", path)
    return _finish(m, width, height, batch)


def _anchors(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Anchor centres (1, 2, A) and strides (1, A) in Ultralytics' order."""
    pts, st = [], []
    for s in STRIDES:
        gh, gw = height // s, width // s
        gy, gx = np.meshgrid(np.arange(gh) + 0.5, np.arange(gw) + 0.5, indexing="ij")
        pts.append(np.stack([gx.ravel(), gy.ravel()], 0))
        st.append(np.full(gh * gw, float(s)))
    return np.concatenate(pts, 1)[None].astype(np.float32), np.concatenate(st)[None].astype(np.float32)


def rewrite_ultralytics(path: Path, width: int, height: int, batch: int = 1) -> bytes:
    import onnx.numpy_helper as nph

    _check_canvas(path, width, height, batch)
    if batch != 1:
        raise ModelError("Ultralytics exports run with batch 1 only", path)
    m = _load(path)
    w0, h0 = input_size(path)
    a0 = sum((h0 // s) * (w0 // s) for s in STRIDES)
    A = sum((height // s) * (width // s) for s in STRIDES)
    anchors, strides = _anchors(width, height)
    counts = [0, 0, 0]
    for t in m.graph.initializer:
        a = nph.to_array(t)
        if a.shape == (1, 2, a0) and a.dtype == np.float32:
            t.CopyFrom(nph.from_array(anchors, t.name))
            counts[0] += 1
        elif a.shape == (1, a0) and a.dtype == np.float32:
            t.CopyFrom(nph.from_array(strides, t.name))
            counts[1] += 1
        elif a.dtype == np.int64 and a.ndim == 1 and a.size in (3, 4) and a[-1] == a0:
            b = a.copy()
            b[-1] = A
            t.CopyFrom(nph.from_array(b, t.name))
            counts[2] += 1
    if counts[0] < 1 or counts[1] < 1 or counts[2] < 1:
        raise ModelError(f"not the expected Ultralytics export: anchors/strides/DFL shapes found {counts}", path)
    return _finish(m, width, height, batch)


def rewrite(path: str | Path, layout: str, width: int, height: int, batch: int = 1) -> bytes:
    """Serialized ONNX of ``path`` (a ``layout`` model) with input ``batch`` x 3 x ``height`` x ``width``."""
    p = Path(path)
    fn = {"yolox": rewrite_yolox, "fastestdet": rewrite_fastestdet,
          "ultralytics": rewrite_ultralytics, "ultralytics-seg": rewrite_ultralytics}.get(layout)
    if fn is None:
        raise ModelError(f"a '{layout}' model cannot be rewritten to another canvas (known: {', '.join(REWRITABLE)})", p)
    return fn(p, int(width), int(height), int(batch))
