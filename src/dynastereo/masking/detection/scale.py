"""Detection at the frame's own scale: a rectangular canvas or overlapping tiles.

A detector letterboxed into its own square canvas shrinks a wide frame: a 1241x376 KITTI
frame in 416x416 is shown at a third of its size, and most cars are missed.
:class:`ScaledDetector` runs a detector so that objects keep about their native size
(``detector.canvas`` in the configuration):

* ``frame`` -- one rectangular canvas of the frame's own aspect at ``detector.scale``
  (sides rounded up to multiples of 32): the ONNX graph rewritten exactly
  (:mod:`.rewrite`), Darknet at a rectangular blob.
* ``tiles`` -- ``detector.tiles`` overlapping tiles across the frame (full height;
  ``detector.tile_overlap`` of a tile's width shared with each neighbour), each at
  ``detector.scale``, batched into one network call where the graph allows; the boxes of
  all tiles are pooled (:func:`merge_tile_boxes`): duplicates suppressed, and an object
  cut by a seam, seen in part by two tiles, comes out whole.
* ``model`` -- the model's own canvas (the frame letterboxed; the old behavior).

``detector.band_top`` (``frame`` and ``tiles``): the top fraction of the frame (sky,
tree tops, far facades) is left out of the canvas; a smaller canvas, less CPU.

A model that cannot be rewritten runs its tiles at its own canvas instead (each tile
letterboxed: still about native scale for tiles near the canvas' size).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...config import DETECTOR_CANVASES
from ...errors import ConfigError
from ...datatypes import Detections
from .classes import class_group_index
from .postprocess import nms

CANVAS_MODES = DETECTOR_CANVASES
#: class name -> group when merging across seams (a car seen as "truck" in one tile and
#: "car" in the other is one vehicle): :data:`~.classes.CLASS_GROUPS`
GROUPS = class_group_index()


def round32(v: float) -> int:
    return max(32, int(math.ceil(v / 32.0 - 1e-9)) * 32)


@dataclass(frozen=True)
class Tile:
    """A window ``x0 <= x < x1``, ``y0 <= y < y1`` of the frame."""

    x0: int
    y0: int
    x1: int
    y1: int

    @property
    def width(self) -> int:
        return self.x1 - self.x0

    @property
    def height(self) -> int:
        return self.y1 - self.y0


def tile_windows(width: int, height: int, tiles: int, overlap: float) -> list[Tile]:
    """``tiles`` windows of equal width across the frame (full height), neighbours sharing
    ``overlap`` of a tile's width; the first starts at 0, the last ends at ``width``."""
    if tiles < 1:
        raise ConfigError(f"detector.tiles must be >= 1, got {tiles}")
    if not (0.0 <= overlap < 1.0):
        raise ConfigError(f"detector.tile_overlap must be in [0, 1), got {overlap}")
    if tiles == 1:
        return [Tile(0, 0, width, height)]
    tw = int(math.ceil(width / (tiles - (tiles - 1) * overlap)))
    step = (width - tw) / (tiles - 1)
    out = []
    for k in range(tiles):
        x0 = int(round(k * step))
        out.append(Tile(x0, 0, min(width, x0 + tw), height))
    return out


def merge_tile_boxes(
    boxes: np.ndarray,
    scores: np.ndarray,
    class_ids: np.ndarray,
    tile_index: np.ndarray,
    tiles: list[Tile],
    groups: np.ndarray,
    nms_threshold: float,
    edge: float = 4.0,
    min_overlap_y: float = 0.5,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pool the boxes of all tiles (frame coordinates) into one set of objects.

    1. Class-aware NMS over all tiles (an object whole in two overlapping tiles).
    2. Seams: a box that ends within ``edge`` px of an inner tile border (not the frame's)
       is *cut*.  A cut box and a box of another tile of the same group that overlap or
       touch across that border, and share at least ``min_overlap_y`` of the shorter one's
       height, are one object: replaced by their union (the higher score and its class).
       Repeated until nothing merges (an object over three tiles).
    3. A cut box lying for >= 70 % of its area inside another box of its group is
       dropped (the part of an object another tile saw whole).
    Returns ``(boxes, scores, class_ids)``, best score first.
    """
    if len(boxes) == 0:
        return boxes.reshape(0, 4).astype(np.float32), scores[:0], class_ids[:0]
    keep = nms(boxes, scores, class_ids, nms_threshold)
    b = boxes[keep].astype(np.float64)
    s = scores[keep].astype(np.float64)
    c = class_ids[keep].copy()
    g = groups[keep].copy()
    t = tile_index[keep]
    tx0 = np.array([tl.x0 for tl in tiles], np.float64)
    tx1 = np.array([tl.x1 for tl in tiles], np.float64)
    fx0, fx1 = tx0.min(), tx1.max()
    # per box: the borders of the tile(s) that saw its left and right edges, and the
    # set of tiles it comes from (bit mask)
    bl, br = tx0[t], tx1[t]
    seen = np.left_shift(1, t.astype(np.int64))
    b, s, c, g, bl, br = _merge_seams(b, s, c, g, bl, br, seen, (fx0, fx1), edge, min_overlap_y)
    if len(b) > 1:
        drop = _cut_parts_inside(b, g, _cut_flags(b, bl, br, (fx0, fx1), edge))
        b, s, c = b[~drop], s[~drop], c[~drop]
    order = np.argsort(-s, kind="stable")
    return b[order].astype(np.float32), s[order].astype(np.float32), c[order].astype(np.int32)


def _cut_flags(
    b: np.ndarray, bl: np.ndarray, br: np.ndarray, frame_x: tuple[float, float], edge: float
) -> np.ndarray:
    """Boxes that end within ``edge`` px of an inner tile border (left or right), not the
    frame's."""
    cl = (b[:, 0] - bl <= edge) & (bl > frame_x[0])
    cr = (br - b[:, 2] <= edge) & (br < frame_x[1])
    return np.stack([cl, cr])


def _merge_seams(b, s, c, g, bl, br, seen, frame_x: tuple[float, float], edge: float, min_overlap_y: float):
    """Step 2 of :func:`merge_tile_boxes`: cut boxes joined across tile seams, the
    best-scoring pair first, until nothing merges.  The arrays are per box: box, score,
    class, group, the left / right borders of the tiles that saw its edges, and the tiles
    it comes from (bit mask).  Returns ``(b, s, c, g, bl, br)`` of the boxes left."""
    while len(b) > 1:
        cl, cr = _cut_flags(b, bl, br, frame_x, edge)
        iy = np.minimum(b[:, None, 3], b[None, :, 3]) - np.maximum(b[:, None, 1], b[None, :, 1])
        hmin = np.minimum(b[:, None, 3] - b[:, None, 1], b[None, :, 3] - b[None, :, 1])
        ix = np.minimum(b[:, None, 2], b[None, :, 2]) - np.maximum(b[:, None, 0], b[None, :, 0])
        ok = (g[:, None] == g[None, :]) & ((seen[:, None] & seen[None, :]) == 0)
        ok &= iy >= min_overlap_y * np.maximum(hmin, 1e-9)
        ok &= ix >= -edge  # overlapping or touching
        # i is cut at its right border and j reaches past it (j further right), or i is
        # cut at its left border and j reaches past that to the left
        seam_r = cr[:, None] & (b[None, :, 2] > br[:, None] + edge) & (b[None, :, 0] < b[:, None, 2] + edge)
        seam_l = cl[:, None] & (b[None, :, 0] < bl[:, None] - edge) & (b[None, :, 2] > b[:, None, 0] - edge)
        ok &= seam_r | seam_l
        ok |= ok.T
        np.fill_diagonal(ok, False)
        if not ok.any():
            break
        pair = np.where(ok, s[:, None] + s[None, :], -np.inf)  # the best-scoring pair first
        i, j = np.unravel_index(int(np.argmax(pair)), pair.shape)
        hi, lo = (i, j) if s[i] >= s[j] else (j, i)
        li = i if b[i, 0] <= b[j, 0] else j  # the part giving the union's left edge
        ri = i if b[i, 2] >= b[j, 2] else j
        b[hi] = [b[li, 0], min(b[i, 1], b[j, 1]), b[ri, 2], max(b[i, 3], b[j, 3])]
        bl[hi], br[hi] = bl[li], br[ri]
        seen[hi] |= seen[lo]
        s[hi] = max(s[i], s[j])
        sel = np.arange(len(b)) != lo
        b, s, c, g, bl, br, seen = b[sel], s[sel], c[sel], g[sel], bl[sel], br[sel], seen[sel]
    return b, s, c, g, bl, br


def _cut_parts_inside(b: np.ndarray, g: np.ndarray, cut: np.ndarray) -> np.ndarray:
    """Step 3 of :func:`merge_tile_boxes`: the cut boxes lying for >= 70 % of their area
    inside a larger box of their group (the part of an object another tile saw whole)."""
    x0 = np.maximum(b[:, None, 0], b[None, :, 0])
    y0 = np.maximum(b[:, None, 1], b[None, :, 1])
    x1 = np.minimum(b[:, None, 2], b[None, :, 2])
    y1 = np.minimum(b[:, None, 3], b[None, :, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    inside = (inter >= 0.7 * np.maximum(area[:, None], 1e-9)) & (g[:, None] == g[None, :])
    inside &= area[None, :] > area[:, None]  # inside a larger box
    np.fill_diagonal(inside, False)
    return (cut[0] | cut[1]) & inside.any(axis=1)


class ScaledDetector:
    """A detector run at the frame's own scale (module docstring); ``detect(image)`` like
    any detector.  ``base`` is a YOLO detector of :mod:`.onnx` / :mod:`.darknet`."""

    def __init__(self, base, canvas: str = "frame", scale: float = 1.0, tiles: int = 3,
                 tile_overlap: float = 0.2, band_top: float = 0.0):
        canvas = str(canvas).lower()
        if canvas not in CANVAS_MODES:
            raise ConfigError(f"detector.canvas must be one of {', '.join(CANVAS_MODES)}, got {canvas!r}")
        if not (0.1 <= float(scale) <= 4.0):
            raise ConfigError(f"detector.scale must be in [0.1, 4], got {scale}")
        tile_windows(100, 100, int(tiles), float(tile_overlap))  # validates
        if not (0.0 <= float(band_top) < 0.9):
            raise ConfigError(f"detector.band_top must be in [0, 0.9), got {band_top}")
        self.band_top = float(band_top)
        self.base = base
        self.canvas = canvas
        self.scale = float(scale)
        self.tiles = int(tiles)
        self.tile_overlap = float(tile_overlap)
        self.name = base.name
        self.class_names = base.class_names
        self._groups = np.array([GROUPS.get(n, 100 + k) for k, n in enumerate(self.class_names)], np.int64)
        self._plans: dict[tuple[int, int], tuple[list[Tile], object]] = {}
        self._single: dict[tuple[int, int], object] = {}  # batch-1 canvas for one tile

    def plan(self, width: int, height: int) -> tuple[list[Tile], object]:
        """(windows, detector at the right canvas) for a frame size (cached)."""
        key = (int(width), int(height))
        if key not in self._plans:
            base = self.base
            if self.canvas == "model":
                windows = [Tile(0, 0, width, height)]
                det = base
            else:
                n = self.tiles if self.canvas == "tiles" else 1
                # the band below the sky: the top band_top of the frame is not searched
                y0 = min(int(round(self.band_top * height)), height - 32) if self.band_top > 0 else 0
                windows = [Tile(t.x0, y0, t.x1, t.y1) for t in tile_windows(width, height, n, self.tile_overlap)]
                tw = max(t.width for t in windows)
                th = max(t.height for t in windows)
                det = base
                if getattr(base, "can_rewrite", False):
                    det = base.with_canvas(round32(tw * self.scale), round32(th * self.scale), len(windows))
            self._plans[key] = (windows, det)
        return self._plans[key]

    @property
    def grey_graph(self) -> bool:
        """Whether the network runs grey frames through a graph of its own (YOLOX's
        one-channel copy): the stage's warm-up then runs a grey frame too."""
        return bool(getattr(self.base, "grey_graph", False))

    @property
    def canvas_size(self) -> tuple[int, int] | None:
        """(width, height) of the network canvas of the last planned frame size."""
        if not self._plans:
            return None
        det = next(reversed(self._plans.values()))[1]
        return int(det.input_w), int(det.input_h)

    def detect_window(self, image: np.ndarray, k: int) -> Detections:
        """Detections in window ``k`` of the frame's plan only (frame coordinates)."""
        h, w = image.shape[:2]
        windows, det = self.plan(w, h)
        t = windows[k]
        if len(windows) == 1:
            return self._detect_one(det, image, t)
        if getattr(det, "batch", 1) != 1 and hasattr(self.base, "with_canvas"):
            det = self._single.get((w, h)) or self._single.setdefault(
                (w, h), self.base.with_canvas(det.input_w, det.input_h, 1))
        return self._detect_in(det, image, t)

    @staticmethod
    def _detect_in(det, image: np.ndarray, t: Tile) -> Detections:
        """``det`` on window ``t`` of ``image``, boxes in frame coordinates."""
        d = det.detect(image[t.y0 : t.y1, t.x0 : t.x1])
        if len(d):
            d.boxes[:, 0::2] += t.x0
            d.boxes[:, 1::2] += t.y0
        return d

    @staticmethod
    def _detect_one(det, image: np.ndarray, t: Tile) -> Detections:
        """One window: the whole image, or its band below ``t.y0`` (boxes in frame coordinates)."""
        if t.y0 == 0:
            return det.detect(image)
        return ScaledDetector._detect_in(det, image, t)

    def detect(self, image: np.ndarray) -> Detections:
        h, w = image.shape[:2]
        windows, det = self.plan(w, h)
        if len(windows) == 1:
            return self._detect_one(det, image, windows[0])
        crops = [image[t.y0 : t.y1, t.x0 : t.x1] for t in windows]  # views, no copies
        per_tile = det.detect_batch(crops)
        boxes, scores, cls, idx = [], [], [], []
        for k, (t, d) in enumerate(zip(windows, per_tile)):
            if len(d) == 0:
                continue
            bb = d.boxes.copy()
            bb[:, 0::2] += t.x0
            bb[:, 1::2] += t.y0
            boxes.append(bb)
            scores.append(d.scores)
            cls.append(d.class_ids)
            idx.append(np.full(len(d), k, np.int64))
        if not boxes:
            return Detections.empty(self.class_names)
        B, S, C, T = (np.concatenate(x) for x in (boxes, scores, cls, idx))
        b, s, c = merge_tile_boxes(B, S, C, T, windows, self._groups[C], float(self.base.nms_threshold))
        return Detections(b, s, c, self.class_names)

    def __repr__(self) -> str:
        return f"ScaledDetector({self.base!r}, canvas={self.canvas!r}, scale={self.scale}, tiles={self.tiles})"
