"""Model files checked for size before the first frame: a truncated download must fail
with one line naming the file, the expected and the actual size -- never load.

* Darknet: the ``.weights`` size follows from the ``.cfg`` (a header of 3 int32 + the
  ``seen`` counter, then float32 biases, batch-norm scales/means/variances and kernels of
  every ``[convolutional]`` layer, in order; the channels flow through ``[maxpool]``,
  ``[upsample]``, ``[route]``, ``[shortcut]`` and ``[yolo]``).  OpenCV reads what is there
  and leaves the rest of the weights uninitialised: a 1 MB piece of the 35 MB
  yolov3-tiny.weights "detects" hundreds of boxes a frame.
* ONNX: the file is a protobuf ``ModelProto``; each top-level field declares its length,
  so a file cut short is found by walking the top-level fields (no parsing of the graph).
"""

from __future__ import annotations

from pathlib import Path

from ..errors import ModelError


def darknet_cfg_sections(cfg_path: Path) -> list[tuple[str, dict[str, str]]]:
    """A Darknet ``.cfg`` as ``[(section name, {key: value})]`` in file order (names and keys
    lower-case, ``#`` comments and lines before the first section left out)."""
    try:
        text = Path(cfg_path).read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise ModelError(f"cannot read Darknet cfg: {e.strerror or e}", cfg_path) from None
    out: list[tuple[str, dict[str, str]]] = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith("["):
            out.append((line.strip("[]").strip().lower(), {}))
        elif "=" in line and out:
            k, v = line.split("=", 1)
            out[-1][1][k.strip().lower()] = v.strip()
    return out


def darknet_weights_floats(cfg_path: str | Path) -> int:
    """The number of float32 values a ``.weights`` file for ``cfg_path`` holds (after its
    header).  ModelError naming the cfg when a layer cannot be followed."""
    cfg_path = Path(cfg_path)
    secs = darknet_cfg_sections(cfg_path)
    if not secs or secs[0][0] not in ("net", "network"):
        raise ModelError("not a Darknet cfg: it does not start with [net]", cfg_path)
    try:
        channels = int(secs[0][1].get("channels", 3))
        outs: list[int] = []  # output channels of each layer
        n_floats = 0
        for kind, kv in secs[1:]:
            prev = outs[-1] if outs else channels
            if kind in ("convolutional", "conv"):
                filters, size = int(kv.get("filters", 1)), int(kv.get("size", 1))
                groups = int(kv.get("groups", 1))
                bn = int(kv.get("batch_normalize", 0))
                n_floats += filters * (4 if bn else 1) + filters * (prev // groups) * size * size
                outs.append(filters)
            elif kind == "route":
                layers = [int(v) for v in kv["layers"].split(",") if v.strip()]
                here = len(outs)
                c = sum(outs[i if i >= 0 else here + i] for i in layers)
                groups = int(kv.get("groups", 1))
                outs.append(c // groups)
            elif kind == "connected":
                raise ModelError("[connected] layers are not supported by the size check", cfg_path)
            else:  # maxpool, upsample, shortcut, yolo, region, dropout, ...: channels unchanged
                outs.append(prev)
    except (ValueError, KeyError, IndexError) as e:
        raise ModelError(f"cannot follow the layers to size the weights ({type(e).__name__}: {e})", cfg_path) from None
    return n_floats


def check_darknet_weights(cfg_path: str | Path, weights_path: str | Path) -> None:
    """ModelError naming ``weights_path`` with the expected and the actual size when the
    file is not as large as ``cfg_path`` implies."""
    cfg_path, weights_path = Path(cfg_path), Path(weights_path)
    floats = darknet_weights_floats(cfg_path)
    actual = weights_path.stat().st_size
    with open(weights_path, "rb") as f:
        head = f.read(12)
    if len(head) < 12:
        raise ModelError(f"Darknet weights file too small for its header: {actual} bytes", weights_path)
    major, minor = int.from_bytes(head[:4], "little"), int.from_bytes(head[4:8], "little")
    seen = 8 if major * 10 + minor >= 2 and major < 1000 and minor < 1000 else 4
    expected = 12 + seen + 4 * floats
    if actual != expected:
        what = "truncated" if actual < expected else "larger than its cfg implies"
        raise ModelError(f"Darknet weights file is {what}: {cfg_path.name} implies {expected} bytes, "
                         f"the file has {actual}", weights_path)


def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        if pos >= len(buf):
            raise EOFError
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, pos
        shift += 7
        if shift > 63:
            raise ValueError("varint too long")


def check_onnx_size(path: str | Path) -> None:
    """ModelError naming ``path`` when its top-level protobuf fields run past the end of
    the file (a truncated download), with the size they declare and the actual size."""
    path = Path(path)
    try:
        buf = path.read_bytes()
    except OSError:
        return  # the loader reports a missing or unreadable file
    pos, n = 0, len(buf)
    try:
        while pos < n:
            tag, pos = _varint(buf, pos)
            wire = tag & 7
            if wire == 0:
                _, pos = _varint(buf, pos)
            elif wire == 1:
                pos += 8
            elif wire == 5:
                pos += 4
            elif wire == 2:
                length, pos = _varint(buf, pos)
                pos += length
            else:
                return  # not a protobuf we can walk: left to onnxruntime's own message
            if pos > n:
                raise ModelError(f"ONNX model file is truncated: its fields need at least {pos} bytes, "
                                 f"the file has {n}", path)
    except EOFError:
        raise ModelError(f"ONNX model file is truncated: it ends inside a field header at {n} bytes", path) from None
    except ValueError:
        return
