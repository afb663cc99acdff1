"""Jobs that chain the stages over a sequence and write the results.

``run_mask_job`` is what ``dynastereo mask`` runs: for each requested frame it masks
both images and writes, as it goes (so a failure never loses earlier frames)::

    DIR/masks/left/NNNNNN.png    uint8, 255 = dynamic
    DIR/masks/right/NNNNNN.png   uint8, 255 = dynamic
    DIR/disparity/NNNNNN.png     uint16, disparity*256 (KITTI), with save_disparity
    DIR/overlays/NNNNNN.png      left|right with masks and boxes drawn, with overlays
    DIR/objects.jsonl            one JSON line per frame: what was masked and how
    DIR/timing.json              per frame and per stage ms + summary (median, p90)

These names are a contract that later tools read.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from .io.base import Sequence
from .io.images import write_disparity_png
from .masking.base import Masker
from .timing import StageTimer
from .types import StereoFrame, StereoMasks

# Stages that make up "mask": everything in masking but the detector network.
MASK_STAGES = ("disparity", "outline", "transfer", "segment", "boxes")


def frame_name(index: int) -> str:
    return f"{index:06d}.png"


@dataclass
class MaskJobResult:
    out: Path
    frames_done: list[int] = field(default_factory=list)
    timer: StageTimer = field(default_factory=StageTimer)
    error: str | None = None
    wall_s: float = 0.0

    @property
    def summary(self) -> dict[str, dict[str, float]]:
        return self.timer.summary()


def new_mask_timer() -> StageTimer:
    t = StageTimer()
    t.add_derived("mask", MASK_STAGES)
    return t


def draw_overlay(frame: StereoFrame, masks: StereoMasks) -> np.ndarray:
    """Left|right side by side, dynamic pixels tinted red, boxes (left) in green (orange:
    box fallback); below, when the masker computed a full-frame disparity, its normalised,
    contrast-enhanced 8-bit view (thesis 3.3.3) in false colour beside the left mask."""
    views = []
    for img, m in ((frame.left, masks.left), (frame.right, masks.right)):
        bgr = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
        sel = m > 0
        tint = np.array([0, 0, 255], np.float32)
        bgr[sel] = (0.5 * bgr[sel] + 0.5 * tint).astype(np.uint8)
        contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(bgr, contours, -1, (0, 0, 255), 1)
        views.append(bgr)
    left = views[0]
    for ob in masks.objects:
        x1, y1, x2, y2 = (int(round(v)) for v in ob.box)
        color = (0, 200, 0) if ob.method in ("outline", "seg", "box") else (0, 200, 255)
        cv2.rectangle(left, (x1, y1), (x2 - 1, y2 - 1), color, 1)
        cv2.putText(left, f"{ob.label} {ob.method}", (x1, max(10, y1 - 3)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.4, color, 1, cv2.LINE_AA)
    top = np.hstack(views)
    if masks.disparity is None:
        return top
    from .masking.disparity import normalize_disparity

    view = cv2.applyColorMap(normalize_disparity(masks.disparity, enhance=True), cv2.COLORMAP_JET)
    view[masks.disparity <= 0] = 0
    return np.vstack([top, np.hstack([view, cv2.cvtColor(masks.left, cv2.COLOR_GRAY2BGR)])])


def _write_png(path: Path, img: np.ndarray) -> None:
    if not cv2.imwrite(str(path), img):
        from .errors import InputError

        raise InputError("cannot write image (disk full or no permission?)", path)


def run_mask_job(
    sequence: Sequence,
    masker: Masker,
    out: str | Path,
    frames: list[int],
    *,
    save_disparity: bool = False,
    overlays: bool = False,
    progress: Callable[[int, int, dict], None] | None = None,
) -> MaskJobResult:
    """Mask ``frames`` of ``sequence`` with ``masker`` and write the results under ``out``.

    On an exception the frames already done stay on disk, ``timing.json`` is written
    with an ``error`` entry, and the exception propagates.
    """
    out = Path(out)
    dirs = {"left": out / "masks" / "left", "right": out / "masks" / "right"}
    if save_disparity:
        dirs["disparity"] = out / "disparity"
    if overlays:
        dirs["overlays"] = out / "overlays"
    for d in dirs.values():
        d.mkdir(parents=True, exist_ok=True)

    result = MaskJobResult(out=out, timer=new_mask_timer())
    timer = result.timer
    t0 = time.perf_counter()
    meta = {"masker": getattr(masker, "name", type(masker).__name__), "sequence": str(sequence.path)}
    try:
        with open(out / "objects.jsonl", "w") as objects_log:
            for k, idx in enumerate(frames):
                with_read = time.perf_counter()
                frame = sequence.frame(idx)
                read_ms = (time.perf_counter() - with_read) * 1000.0
                timer.start_frame(idx)
                timer.add("read", read_ms)
                masks = masker.mask(frame, timer)
                rec = timer.end_frame()
                name = frame_name(idx)
                _write_png(dirs["left"] / name, masks.left)
                _write_png(dirs["right"] / name, masks.right)
                if save_disparity:
                    if masks.disparity is None:
                        raise RuntimeError(f"masker {meta['masker']} produced no full-frame disparity")
                    write_disparity_png(dirs["disparity"] / name, masks.disparity)
                if overlays:
                    _write_png(dirs["overlays"] / name, draw_overlay(frame, masks))
                objects_log.write(json.dumps({
                    "frame": idx,
                    "objects": [o.to_dict() for o in masks.objects],
                    "fallbacks": sum(o.method.startswith("box-fallback") for o in masks.objects),
                }) + "\n")
                objects_log.flush()
                result.frames_done.append(idx)
                if progress is not None:
                    progress(k + 1, len(frames), rec)
    except BaseException as e:
        result.error = f"{type(e).__name__}: {e}"
        raise
    finally:
        result.wall_s = time.perf_counter() - t0
        extra = dict(meta, frames_done=len(result.frames_done), frames_requested=len(frames),
                     wall_s=round(result.wall_s, 3))
        if result.error:
            extra["error"] = result.error
        timer.write(out / "timing.json", **extra)
    return result
