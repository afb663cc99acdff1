"""The map edits of the motion test: the map points of an object that turned moving from
static are removed (``motion.forget_points``; ``System.forget_region``)."""

from __future__ import annotations

import numpy as np

from ...datatypes import StereoCalibration, StereoMasks
from .flow import FrameFlow


def object_region(masks: StereoMasks, index: int, flow: FrameFlow | None, calib: StereoCalibration
                  ) -> tuple[np.ndarray, float, float] | None:
    """(left-image pixels of object ``index``, nearest and farthest depth in metres) of an
    object that turned moving, for removing its map points; None when unknown."""
    if masks.labels_left is None:
        return None
    region = masks.labels_left == index + 1
    d = [of.d1 for of in (flow.objects if flow is not None else []) if of.index == index]
    if not d or not len(d[0]):
        return None
    z = calib.bf / d[0]
    return region, float(z.min()) - 1.0, float(z.max()) + 1.0


def forget_moving(system, masks: StereoMasks, turned: list[int], calib: StereoCalibration) -> int:
    """Remove from ``system``'s map (``System.forget_region``) the points of the objects
    ``turned`` (indices into ``masks.objects``) moving from static; returns how many went."""
    n = 0
    for i in turned:
        reg = object_region(masks, i, masks.flow, calib)
        if reg is not None:
            n += system.forget_region(*reg)
    return n
