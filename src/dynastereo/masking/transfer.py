"""Move each left-image object mask into the right image by its own disparity.

A left pixel ``(x, y)`` with disparity ``d`` is seen at ``(x - d, y)`` in the right image
(thesis 3.3.3).  Forward-warping every pixel by its own noisy disparity leaves gaps and
ragged edges, so each object is moved by a *model* of its disparity and the right mask is
built by *backward* sampling (every right pixel asks which left pixel it comes from), which
leaves no gaps by construction:

* ``rigid``: the object's peak disparity, rounded to whole pixels -- a pure shift, exact
  for a fronto-parallel object (a car seen from behind) and for whole-box fallbacks;
* ``affine``: ``d(x, y) = a + b x + c y`` least-squares fitted to the object's valid
  disparities within its peak range (a car seen from the side: its disparity changes
  along it); the right pixel ``x_r`` then comes from ``x_l = (x_r + a + c y) / (1 - b)``.
  A poor fit (few pixels, implausible slope) falls back to ``rigid``.

Objects with unknown disparity (no valid pixel in the box) are swept over the matcher's
whole disparity range: the right mask is the union of all the shifts, wide but safe.
Objects partly leaving the right image (``x - d < 0``) are clipped there; objects cut by
the *left* image's right border continue in the right image (which sees ``d`` more
columns there), so their rows touching that border are extended to the right border.  Where objects
overlap in the right image the nearer one (larger disparity) wins, as in the left.  With
``occluded`` an object hidden in part behind a nearer one in the left image also covers
the band the right camera sees past the nearer object's right edge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..config import TRANSFER_MODES
from .boxkernel import affine_paint, transfer_frame

MODES = TRANSFER_MODES  # masker.outline.transfer (config)
# A box ending this close to the right border is taken as cut by it.
BORDER_TOUCH = 3


@dataclass
class TransferResult:
    labels: np.ndarray  # int32 (H, W) right image: 0 = none, i = object i
    pixels: np.ndarray  # (N,) pixels of each object in ``labels``
    models: list[tuple[float, float, float]] = field(default_factory=list)  # (a, b, c) per object
    painted: np.ndarray | None = None  # uint8 (H, W), 255 = any object, when the kernel made it

    @property
    def mask(self) -> np.ndarray:
        """uint8 mask, 255 = any object."""
        if self.painted is not None:
            return self.painted
        return np.where(self.labels > 0, np.uint8(255), np.uint8(0))


def transfer_labels(
    left_labels: np.ndarray,
    disparities: np.ndarray,
    rois: np.ndarray,
    *,
    mode: str = "rigid",
    disp: np.ndarray | None = None,
    origin: tuple[int, int] = (0, 0),
    ranges: list[tuple[float, float]] | None = None,
    sweep: tuple[float, float] = (0.0, 95.0),
    max_slope: float = 0.25,
    occluded: bool = False,
    occluded_margin: float = 1.0,
) -> TransferResult:
    """Right-image label image from the left one, all the objects in one compiled call
    (:func:`.boxkernel.transfer_frame`).

    ``disparities[i]`` is object ``i+1``'s disparity (pixels; ``<= 0`` unknown -> swept
    over ``sweep = (dmin, dmax)``).  ``rois[i]`` is its left box ROI (x0, y0, x1, y1), within
    which its label pixels lie.  ``mode="affine"`` needs the disparity ``disp`` (region
    array with top-left ``origin``) and optionally each object's accepted disparity range
    ``ranges[i] = (lo, hi)`` used to select the pixels to fit.

    ``occluded``: an object partly hidden in the left image behind a nearer object (larger
    disparity, by more than ``occluded_margin`` px) is seen further in the right image --
    the right camera looks past the nearer object's right edge.  Its box's pixels the
    nearer object covers are moved with it, so that band, ``d_near - d`` pixels wide, is
    masked too (the nearer object, painted later, keeps its own pixels): a car behind a
    truck, a pedestrian behind another.
    """
    if mode not in MODES:
        raise ValueError(f"transfer mode must be one of {MODES}, got {mode!r}")
    h, w = left_labels.shape
    rois = np.ascontiguousarray(np.asarray(rois).reshape(-1, 4), np.int64)
    n = len(rois)
    d = np.ascontiguousarray(np.asarray(disparities, np.float64).reshape(-1)[:n])
    affine = mode == "affine" and disp is not None
    rng = np.zeros((n, 2), np.float64)
    # a python float is compared with the float32 disparities in float32 (numpy's weak
    # scalars), a numpy float64 in float64
    weak = np.ones(n, np.bool_)
    if ranges is not None:
        for i, (lo, hi) in enumerate(ranges[:n]):
            rng[i] = lo, hi
            weak[i] = type(lo) is not np.float64 and type(hi) is not np.float64
    right = np.zeros((h, w), np.int32)
    mask = np.zeros((h, w), np.uint8)
    pixels = np.zeros(n, np.int64)
    models = np.zeros((n, 3), np.float64)
    dmin, dmax = int(np.floor(max(sweep[0], 0.0))), int(np.ceil(sweep[1]))
    transfer_frame(np.ascontiguousarray(left_labels, np.int32), d, rois, affine,
                   np.ascontiguousarray(disp if affine else _NO_DISP, np.float32), int(origin[0]), int(origin[1]),
                   rng, ranges is not None, weak, dmin, dmax, float(max_slope), bool(occluded),
                   float(occluded_margin), right, mask, pixels, models)
    return TransferResult(right, pixels, [tuple(float(v) for v in m) for m in models], mask)


_NO_DISP = np.zeros((1, 1), np.float32)


def warm_up_kernels() -> None:
    """Load (or compile) the transfer's compiled kernel now, not in the first frames."""
    labels = np.zeros((24, 32), np.int32)
    labels[4:20, 4:12] = 1
    labels[4:20, 14:31] = 2
    disp = np.full((24, 32), 3.0, np.float32)
    rois = np.array([[4, 4, 12, 20], [14, 4, 32, 20]])
    transfer_labels(labels, np.array([3.0, 0.0], np.float32), rois, mode="affine", disp=disp,
                    ranges=[(2.0, 4.0), (0.0, 0.0)], occluded=True)


_affine_paint = affine_paint  # (the tests' name)
