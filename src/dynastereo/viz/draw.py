"""Drawing of masks, objects and their motion verdicts on images: the overlays of
``dynastereo mask --overlays``, the report's frames and the ROS node's overlay topic."""

from __future__ import annotations

import cv2
import numpy as np

from ..datatypes import VERDICT_COLOURS, StereoFrame, StereoMasks




def _tint(bgr: np.ndarray, sel: np.ndarray, colour: tuple[int, int, int], alpha: float = 0.5) -> None:
    bgr[sel] = ((1 - alpha) * bgr[sel] + alpha * np.array(colour, np.float32)).astype(np.uint8)


def draw_objects(image: np.ndarray, mask: np.ndarray, objects, labels: np.ndarray | None = None,
                 boxes: bool = True) -> np.ndarray:
    """``image`` (grey or BGR) with the masked pixels ``mask`` tinted and outlined in the
    colour of their object's verdict (:data:`VERDICT_COLOURS`; without instance
    ``labels``: red), static objects' pixels lightly tinted green, and, with ``boxes``, each
    object's box in its verdict's colour with its label, verdict and speed (a box-fallback
    mask's box is drawn thinner)."""
    bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    sel = mask > 0
    if labels is None or not objects:
        _tint(bgr, sel, VERDICT_COLOURS[True])
    else:
        verdict = np.array([0] + [{True: 1, None: 2, False: 3}[o.moving] for o in objects], np.uint8)[labels]
        _tint(bgr, sel & (verdict <= 1), VERDICT_COLOURS[True])
        _tint(bgr, sel & (verdict == 2), VERDICT_COLOURS[None])
        _tint(bgr, ~sel & (verdict == 3), VERDICT_COLOURS[False], 0.3)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(bgr, contours, -1, (0, 0, 255), 1)
    if not boxes:
        return bgr
    for ob in objects:
        x1, y1, x2, y2 = (int(round(v)) for v in ob.box)
        colour = VERDICT_COLOURS[ob.moving]
        state = {True: "moving", False: "static", None: "?"}[ob.moving]
        speed = f" {ob.speed_mps:.1f}m/s" if ob.speed_mps is not None else ""
        cv2.rectangle(bgr, (x1, y1), (x2 - 1, y2 - 1), colour, 1 if ob.method.is_fallback else 2)
        cv2.putText(bgr, f"{ob.label} {state}{speed}", (x1, max(10, y1 - 3)), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    colour, 1, cv2.LINE_AA)
    return bgr


def draw_overlay(frame: StereoFrame, masks: StereoMasks) -> np.ndarray:
    """Left|right side by side, masked pixels tinted by their object's verdict (moving red,
    not yet judged orange; static objects, left to SLAM, green: :data:`VERDICT_COLOURS`),
    boxes (left) in the verdict's colour (thin: box fallback); below, when the masker
    computed a full-frame disparity, its normalized, contrast-enhanced 8-bit view (thesis
    3.3.3) in false colour beside the left mask."""
    left = draw_objects(frame.left, masks.left, masks.objects, masks.labels_left)
    right = draw_objects(frame.right, masks.right, masks.objects, masks.labels_right, boxes=False)
    top = np.hstack([left, right])
    if masks.disparity is None:
        return top
    from ..masking.disparity import normalize_disparity

    view = cv2.applyColorMap(normalize_disparity(masks.disparity, enhance=True), cv2.COLORMAP_JET)
    view[masks.disparity <= 0] = 0
    return np.vstack([top, np.hstack([view, cv2.cvtColor(masks.left, cv2.COLOR_GRAY2BGR)])])
