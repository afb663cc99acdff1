"""Image and disparity-map files.

* ``read_image(path, color)``: ``uint8`` gray ``(H, W)`` or BGR ``(H, W, 3)``.
* ``image_size(path)``: ``(width, height)`` without decoding the pixels for PNG
  (the IHDR header); other formats are decoded.
* ``write_disparity_png`` / ``read_disparity_png``: the KITTI convention -- ``uint16``
  PNG holding ``disparity * 256``, 0 = invalid.
* ``read_pfm`` / ``write_pfm``: Portable Float Map (Middlebury ground truth); ``inf`` and
  NaN (Middlebury's "unknown") become 0 = invalid, our disparity convention.

Every failure raises :class:`~dynastereo.errors.ImageReadError` naming the file.
"""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np

from ..errors import ImageReadError, InputError
from .outputs import write_bytes

IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _check_file(path: Path) -> None:
    if not path.exists():
        raise ImageReadError("image file not found", path)
    if not path.is_file():
        raise ImageReadError("not a file", path)


def read_image(path: str | Path, color: bool = False, bits: int | None = None) -> np.ndarray:
    """Read an image as 8 bits: gray ``(H, W)`` if ``color`` is false, else BGR ``(H, W, 3)``.

    A gray file read with ``color=True`` gives three equal channels; a colour file read
    with ``color=False`` is converted to gray by the decoder.  A 16-bit file is scaled from
    ``bits`` significant bits (default: 16; 12-bit camera data in 16-bit PNGs wants 12,
    :func:`significant_bits` finds it) to 8.
    """
    path = Path(path)
    _check_file(path)
    img = cv2.imread(str(path), (cv2.IMREAD_COLOR if color else cv2.IMREAD_GRAYSCALE) | cv2.IMREAD_ANYDEPTH)
    if img is None or img.size == 0:
        raise ImageReadError("cannot decode image (corrupt or unsupported format)", path)
    if img.dtype == np.uint16:
        shift = max(0, int(bits or 16) - 8)
        img = np.minimum(img >> shift, 255).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return img


def significant_bits(path: str | Path) -> int | None:
    """The bits a 16-bit image's values use (its largest value's bit length, at least 8);
    None for an 8-bit image."""
    path = Path(path)
    _check_file(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype != np.uint16:
        return None
    return max(8, int(img.max()).bit_length())


def image_size(path: str | Path) -> tuple[int, int]:
    """``(width, height)`` of an image; PNG sizes come from the header without decoding."""
    path = Path(path)
    _check_file(path)
    if path.suffix.lower() == ".png":
        try:
            with open(path, "rb") as f:
                head = f.read(24)
        except OSError as e:
            raise ImageReadError(f"cannot read file: {e.strerror}", path) from None
        if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
            raise ImageReadError("not a valid PNG file (bad header)", path)
        w, h = struct.unpack(">II", head[16:24])
        return int(w), int(h)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ImageReadError("cannot decode image (corrupt or unsupported format)", path)
    return int(img.shape[1]), int(img.shape[0])


def list_images(folder: str | Path) -> list[Path]:
    """Image files directly inside ``folder``, sorted by name (case-insensitive suffix match)."""
    folder = Path(folder)
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


# --------------------------------------------------------------------------- disparity


def write_disparity_png(path: str | Path, disparity: np.ndarray) -> None:
    """Write float disparity (pixels) as a KITTI ``uint16`` PNG: ``round(d * 256)``, 0 = invalid.

    Values ``<= 0`` or non-finite are written as 0; valid values are clamped to
    ``[1/256, 65535/256]`` so a tiny valid disparity stays valid.
    """
    path = Path(path)
    d = np.asarray(disparity, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"disparity must be 2-D, got shape {d.shape}")
    valid = np.isfinite(d) & (d > 0)
    q = np.zeros(d.shape, np.uint16)
    q[valid] = np.clip(np.rint(d[valid] * 256.0), 1, 65535).astype(np.uint16)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", q)
    if not ok:
        raise InputError("cannot encode the disparity PNG", path)
    write_bytes(path, buf.tobytes())  # a failed write: OutputError naming the file


def read_disparity_png(path: str | Path) -> np.ndarray:
    """Read a KITTI disparity PNG (``uint16``, disparity*256, 0 = invalid) as float32 pixels."""
    path = Path(path)
    _check_file(path)
    q = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if q is None:
        raise ImageReadError("cannot decode disparity PNG", path)
    if q.dtype != np.uint16 or q.ndim != 2:
        raise ImageReadError(
            f"not a KITTI disparity map: expected a 16-bit single-channel PNG, got {q.dtype} with shape {q.shape}",
            path,
        )
    return q.astype(np.float32) / np.float32(256.0)


def read_pfm(path: str | Path) -> np.ndarray:
    """Read a PFM file (``Pf`` gray -> ``(H, W)``, ``PF`` colour -> ``(H, W, 3)``), float32, top row first.

    ``inf`` / NaN values (Middlebury: unknown disparity) become 0 (= invalid).
    """
    path = Path(path)
    _check_file(path)
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as e:
        raise ImageReadError(f"cannot read file: {e.strerror}", path) from None
    # Header: three whitespace-separated tokens lines: type, "W H", scale.
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4 and pos < len(data):
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        start = pos
        while pos < len(data) and not data[pos : pos + 1].isspace():
            pos += 1
        tokens.append(data[start:pos])
    pos += 1  # the single whitespace byte after the scale
    if len(tokens) < 4 or tokens[0] not in (b"Pf", b"PF"):
        raise ImageReadError("not a PFM file (header must start with 'Pf' or 'PF')", path)
    try:
        width, height, scale = int(tokens[1]), int(tokens[2]), float(tokens[3])
    except ValueError:
        raise ImageReadError(f"malformed PFM header {b' '.join(tokens[1:4])!r}", path) from None
    channels = 3 if tokens[0] == b"PF" else 1
    if width <= 0 or height <= 0 or scale == 0:
        raise ImageReadError(f"malformed PFM header: size {width}x{height}, scale {scale}", path)
    count = width * height * channels
    if len(data) - pos < 4 * count:
        raise ImageReadError(
            f"truncated PFM: {width}x{height}x{channels} needs {4 * count} bytes, file has {len(data) - pos}", path
        )
    dtype = "<f4" if scale < 0 else ">f4"
    arr = np.frombuffer(data, dtype=dtype, count=count, offset=pos).astype(np.float32)
    shape = (height, width) if channels == 1 else (height, width, 3)
    arr = np.flipud(arr.reshape(shape))  # PFM stores the bottom row first
    arr = np.where(np.isfinite(arr), arr, np.float32(0.0)).astype(np.float32)
    return np.ascontiguousarray(arr)


def write_pfm(path: str | Path, image: np.ndarray) -> None:
    """Write a float32 ``(H, W)`` or ``(H, W, 3)`` array as little-endian PFM."""
    path = Path(path)
    a = np.asarray(image, dtype="<f4")
    if a.ndim == 2:
        kind = b"Pf"
    elif a.ndim == 3 and a.shape[2] == 3:
        kind = b"PF"
    else:
        raise ValueError(f"PFM needs (H, W) or (H, W, 3), got {a.shape}")
    h, w = a.shape[:2]
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(kind + b"\n" + f"{w} {h}\n".encode() + b"-1.0\n")
        f.write(np.ascontiguousarray(np.flipud(a)).tobytes())
