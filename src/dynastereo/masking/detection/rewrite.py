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

**Grey input** (``grey=True``, YOLOX only): a grey camera's frame reaches the network as
three equal channels.  YOLOX's stem (Focus) slices the input into its four pixel phases
and concatenates them (4 x 3 channels) before the first convolution, so with equal
channels that convolution's weights can be summed over each phase's three colours: the
graph then takes one channel (``batch x 1 x H x W``) and computes the same function up to
float rounding (outputs within ~1e-4; the first convolution does a third of its work and
the input blob is a third of the size: ~10 % of the network's CPU on a KITTI canvas).
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


def _fold_grey_yolox(m, path: Path) -> None:
    """The YOLOX graph ``m`` made to take one grey channel (module doc): its first
    convolution, fed by the Focus concat of four 3-channel phase slices of the input, gets
    its weights summed over each phase's three channels.  A ModelError when the graph is
    not so built."""
    import onnx.numpy_helper as nph

    g = m.graph
    name = g.input[0].name
    users = [n for n in g.node if name in n.input]
    if not users or any(n.op_type != "Slice" for n in users):
        raise ModelError("not the expected YOLOX export: its input does not feed the Focus slices alone", path)
    conv = next((n for n in g.node if n.op_type == "Conv"), None)
    cat = next((n for n in g.node if conv is not None and n.op_type == "Concat" and conv.input[0] in n.output), None)
    init = {t.name: t for t in g.initializer}
    w = nph.to_array(init[conv.input[1]]) if conv is not None and conv.input[1] in init else None
    if cat is None or len(cat.input) != 4 or w is None or w.ndim != 4 or w.shape[1] != 12:
        raise ModelError("not the expected YOLOX export: no Focus concat of 4 x 3 channels before the first "
                         "convolution", path)
    folded = w.reshape(w.shape[0], 4, 3, *w.shape[2:]).sum(axis=2, dtype=np.float64).astype(w.dtype)
    init[conv.input[1]].CopyFrom(nph.from_array(folded, conv.input[1]))
    g.input[0].type.tensor_type.shape.dim[1].dim_value = 1


def rewrite_yolox(path: Path, width: int, height: int, batch: int = 1, grey: bool = False) -> bytes:
    import onnx.numpy_helper as nph

    _check_canvas(path, width, height, batch)
    m = _load(path)
    if grey:
        _fold_grey_yolox(m, path)
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


def rewrite(path: str | Path, layout: str, width: int, height: int, batch: int = 1, grey: bool = False) -> bytes:
    """Serialized ONNX of ``path`` (a ``layout`` model) with input ``batch`` x 3 x ``height`` x ``width``
    (``grey``: ``batch`` x 1 x ``height`` x ``width``, YOLOX only; module doc)."""
    p = Path(path)
    if grey:
        if layout != "yolox":
            raise ModelError(f"a '{layout}' model has no grey-input form (only yolox)", p)
        return rewrite_yolox(p, int(width), int(height), int(batch), grey=True)
    fn = {"yolox": rewrite_yolox, "fastestdet": rewrite_fastestdet,
          "ultralytics": rewrite_ultralytics, "ultralytics-seg": rewrite_ultralytics}.get(layout)
    if fn is None:
        raise ModelError(f"a '{layout}' model cannot be rewritten to another canvas (known: {', '.join(REWRITABLE)})", p)
    return fn(p, int(width), int(height), int(batch))
