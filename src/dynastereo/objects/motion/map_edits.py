"""The map edits of the motion test: the map points of an object that turned moving from
static are to be removed (``motion.forget_points``).  The motion test only says which
(:class:`MapEdit`); the frame processor applies them through the SLAM's public API
(``System.forget_region``), so the objects never call into the SLAM."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...datatypes import StereoCalibration, StereoMasks
from .flow import FrameFlow


@dataclass(frozen=True)
class MapEdit:
    """The map points to forget: those seen in the left-image pixels ``region`` (bool, H x W)
    at depths in ``[z_min, z_max]`` metres, from the frame just tracked."""

    region: np.ndarray
    z_min: float
    z_max: float


def object_region(masks: StereoMasks, index: int, flow: FrameFlow | None, calib: StereoCalibration
                  ) -> MapEdit | None:
    """The map edit of object ``index``, which turned moving: its left-image pixels and its
    nearest and farthest depth (metres, one metre of margin); None when unknown."""
    if masks.labels_left is None:
        return None
    region = masks.labels_left == index + 1
    d = [of.d1 for of in (flow.objects if flow is not None else []) if of.index == index]
    if not d or not len(d[0]):
        return None
    z = calib.bf / d[0]
    return MapEdit(region, float(z.min()) - 1.0, float(z.max()) + 1.0)


def moving_edits(masks: StereoMasks, turned: list[int], calib: StereoCalibration) -> list[MapEdit]:
    """The map edits of the objects ``turned`` (indices into ``masks.objects``) moving from
    static, in that order (the objects whose region is unknown are left out)."""
    edits = (object_region(masks, i, masks.flow, calib) for i in turned)
    return [e for e in edits if e is not None]
