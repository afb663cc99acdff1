"""Every object's track in the world: position, velocity, speed and extent from stereo.

The masker outlines each detected object (``StereoMasks.labels_left``) and computes the
disparity in its box (``StereoMasks.box_disparity``; with ``objects.block_size`` the
outlines are matched again with that block first, ``objects.disparity``); SLAM gives
the frame's camera pose.  :class:`WorldObjects` turns them, per frame and object, into an :class:`ObjectState` in
the trajectory's frame (the first camera's: x right, y down, z forward):

* **Measurement** (one compiled pass over the objects' boxes, :func:`_object_stats`, then
  one over the objects for the geometry below, :func:`_centres`): the
  disparities of the object's own outline pixels (with a box masker: the box's pixels
  within 15 % of the object's peak disparity; a box of more than 2 ``FIRST_PASS_PIXELS``
  (16,000) pixels on every few rows) go into a histogram of 1/16 px bins, giving
  the median and the 10th / 90th percentiles.  An outline with a disparity on fewer than
  ``MIN_VALID_FRACTION`` (30 %) of its pixels gives no measurement: it is mostly occluded,
  and what disparity it has is often its occluder's leaking in (a car behind the truck
  ahead got the truck's range).  Nor does a box shorter than ``MIN_VISIBLE_HEIGHT`` (30 %)
  of its class height at the depth measured (unless cut by the image's top or bottom):
  a sliver of a car beside a truck 4.5 m away whose pixels carry the truck's disparity
  (block matching fattens a near object's edges) put the car 14-20 m nearer than it was,
  and the filter coasted on it (docs/design/objects-motion.md has the measurements).
* **Centre, not surface.**  Stereo sees the near surface; the object's centre lies behind
  it.  With a class footprint (``CLASS_SIZE``: width, height, length) and a heading (the
  track's velocity when it moves faster than 1 m/s, else the camera's forward axis: parked
  cars line the road), the centre comes from one of two models.  A vehicle the motion test
  judged moving takes its heading from its points where they show it (a pass over them
  between the two others): the principal axis of their top-view coordinates (those within
  the 5th-95th percentile disparities), when they spread along it over ``AXIS_EXTENT``
  (1.5) class widths and their variance along it is ``AXIS_RATIO`` (4) times that across,
  and, once the track has a velocity, within ``AXIS_AGREE`` (40 degrees) of its heading
  (the velocity's is 15-25 degrees off for a crossing truck); then the top view places it
  (crossing trucks 0.25 m, cut ones 0.31 m, development seeds).  A vehicle seen
  from behind or ahead shows only its width: it keeps the velocity's heading and the ray.

  - *top view* (objects the motion test judged static, persons, and objects cut by the
    image's left / right side): a second pass over the pixels gives the percentiles of
    their top-view coordinates along the heading (a) and across it (b); per axis the face
    toward the camera (the 10th / 90th percentile) plus half the footprint, or both ends'
    middle (5th / 95th percentiles) when the camera is within the object's span.  For a
    vehicle cut by the image's side one end is out of view: along the heading, the end
    seen (the 95th / 5th percentile, the one away from the cut side: a parked car's far
    end, a crossing car's front as it comes in) minus half the class length, but no
    farther from the other visible end than half the length (a detector's outline that
    takes in background past the end seen put cut cars 10 m off on KITTI raw 0001).
  - *view ray* (the other moving or undecided vehicles in full view, whose heading is the
    filter's velocity's; seen from behind or ahead, the ray is insensitive to its error):
    the box's extent along the ray through the box centre is ``e = l|cos φ| + w|sin φ|``,
    and the centre is at the nearest point (the 90th percentile disparity's range) plus
    ``e / 2``.

  The top-view and heading passes visit every ``st``-th row and column of a box, ``st =
  1 + sqrt(n / SAMPLE_PIXELS)`` for an outline of n pixels (``SAMPLE_PIXELS`` 1000; 2000
  cost more for the same positions).

  Vertically: the box centre's row at the median disparity's depth (the box spans the
  surface seen, nearer than the centre); a box cut by the image's bottom (a person close
  by; the synthetic scenes' 192 rows cut most) hangs half the class height below its top
  row.  On the synthetic dev scenes (seeds 10-12) with ground-truth disparity this model
  errs 0.23 m (median, objects within 30 m), with the stereo's 0.26 m.
* **Uncertainty.**  Along the ray ``σ_r = r σ_d / d`` (the disparity's noise,
  ``motion.sigma_disparity``, shared by the pixels: not divided by their number) plus a
  tenth of the class length; across it ``r σ_px / f`` with ``σ_px`` a twentieth of the box
  width (at least 1 px) plus a tenth of the class width.  The 3x3 covariance is rotated into
  the world with the pose.
* **Velocity** (:func:`_track_frame`, one compiled call a frame over a table of the
  tracks' states, with the uncertainty, the position out and the coasting below): a
  constant-velocity Kalman filter per track id in the world frame (state ``[p, v]``, white
  acceleration noise ``accel_noise`` m²/s³, a thousandth of it vertically: objects keep to
  the ground).  After the position, the motion test's own speed
  (``ObjectMask.speed_mps``, from its points' flow) updates the speed along the filter's
  direction, with the motion test's own sigma of it (``speed_sigma_mps``: its stereo and
  pose noise along the velocity, growing with the range squared; at least ``SPEED_SIGMA``,
  0.3 m/s, plus 10 % of the speed: a walker 50 m ahead on KITTI raw 0001, whose 15-26 m/s
  from the flow was taken at +-1.6 m/s and set the filter's speed, now counts at +-4 m/s),
  and an object the motion test judged static gets ``v = 0`` (σ 0.1 m/s).  An
  innovation over chi-square ``GATE`` (the tracker gave the id to another object) restarts
  the track.  Speed = ``|v|`` with ``σ = sqrt(vᵀ P_v v) / |v|``.
* **Position out**: an object in full view gets this frame's measurement, not the
  filter's position: its errors are systematic (range- and view-dependent: the class
  footprint, the face's percentile) rather than white, and the world-frame filter adds
  those of earlier, farther frames and SLAM's drift to it (dev seeds: 0.26 m so, 0.27 m
  all measured, 0.30-0.33 m all filtered with ``accel_noise`` 50-2; static cars in the
  convoy 0.27 m measured, 0.71 m filtered).  An object cut by the image's side gets the
  filter's position, which keeps what the full view gave (cut static cars 0.37 m, 0.59 m
  measured).  An object judged static keeps the world position of its last full view
  when it is cut by the image's side or has no measurement: a parked car does not move,
  and the cut view's measurement is biased by the end it cannot see (dev seeds 10-12,
  replayed: static cars cut by the side 0.19-0.23 m instead of 0.30-0.49 m; all objects
  within 30 m, misses counted, 0.273 m instead of 0.327 m, the median over the runs).  ``world_sigma`` is the
  measurement's, the filter's or the kept view's accordingly.
* **No measurement** (an outline mostly without disparity): a track whose filter took a
  measurement within ``COAST_S`` (1 s) gets the filter's prediction, ``p + v dt`` with
  covariance ``P_p + dt^2 P_v``, flagged ``predicted`` -- as a tracker coasts; without one,
  no position (dev seeds 10-12: 95 % of the object-frames within 30 m placed instead of
  79 %, and the median with the rest counted as misses 0.32 m instead of 0.35).
* **Extent**: the box's width and height at the centre's depth, and the class length.

Frames whose pose was lost are skipped (the filter only predicts over the gap).  Objects
without a track id get a position but no velocity.  :class:`TrackWriter` appends one CSV
row per object and frame (``objects_tracks.csv``).
"""

from __future__ import annotations

import csv
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, NamedTuple

import numpy as np

from ..compiled import jit
from ..datatypes import VERDICT_COLOURS, StereoCalibration, StereoFrame, StereoMasks
from .disparity import ObjectStereo

if TYPE_CHECKING:
    from ..config import Config

__all__ = ["ObjectState", "WorldObjects", "TrackWriter", "CLASS_SIZE", "TRACKS_NAME", "read_tracks", "verdict_rgb",
           "box_corners", "ObjectPaths"]

TRACKS_NAME = "objects_tracks.csv"
TRACK_COLUMNS = ("track_id", "frame", "stamp", "label", "x", "y", "z", "vx", "vy", "vz", "speed", "speed_sigma",
                 "moving")
# typical footprints (width, height, length) in metres, by detector label
CLASS_SIZE = {
    "car": (1.8, 1.5, 4.4), "truck": (2.5, 3.0, 8.0), "bus": (2.6, 3.2, 12.0), "train": (2.6, 3.5, 20.0),
    "person": (0.6, 1.7, 0.5), "bicycle": (0.6, 1.7, 1.8), "motorcycle": (0.8, 1.5, 2.1),
}
DEFAULT_SIZE = (1.0, 1.5, 1.0)
BIN = 1.0 / 16.0  # px, disparity histogram bin
N_BINS = 4096  # disparities up to 256 px
AB_STEP = 0.02  # m, top-view histogram bin
AB_BINS = 2500  # +-25 m around the median point
#: :func:`_object_stats`' output, one record per object: named fields, not columns
STATS = np.dtype([
    ("n_disparity", np.float64), ("d_median", np.float64), ("d_p10", np.float64), ("d_p90", np.float64),
    ("a_median", np.float64), ("a_p10", np.float64), ("a_p90", np.float64), ("a_p5", np.float64),
    ("a_p95", np.float64), ("b_p10", np.float64), ("b_p90", np.float64), ("b_p5", np.float64),
    ("b_p95", np.float64), ("n_outline", np.float64), ("axis_from_points", np.float64), ("d_p5", np.float64),
    ("d_p95", np.float64),
])
SAMPLE_PIXELS = 1000.0  # the top-view and heading passes visit every st-th row and column: ~ this many pixels
FIRST_PASS_PIXELS = 8000  # the disparity histogram of a box of A pixels: every (A // this)-th row
AXIS_EXTENT = 1.5  # the heading from the points: their spread along it, class widths (at least)
AXIS_RATIO = 4.0  # ... over their spread across it (variances, at least)
AXIS_AGREE = np.radians(40.0)  # ... within this of the velocity's heading, where known
MIN_VALID_FRACTION = 0.3  # of an outline's pixels with a disparity: fewer, no measurement
MIN_VISIBLE_HEIGHT = 0.3  # of the class height at the depth measured: a shorter box (not cut), no measurement
COAST_S = 1.0  # s: an object without a measurement gets its filter's prediction this long after its last update
GATE = 40.0  # chi-square (3 dof) of an innovation that restarts the track
VERTICAL = np.diag([1.0, 1e-3, 1.0])  # the filter's acceleration noise per world axis (y: down)
MOVING_HEADING_SPEED = 1.0  # m/s: above it, the velocity gives the heading
#: :func:`_track_frame`'s output, one record per object (the fields of :class:`ObjectState`)
STATE = np.dtype([
    ("world", np.float64, (3,)), ("world_sigma", np.float64, (3,)), ("extent", np.float64, (3,)),
    ("heading", np.float64, (3,)), ("distance", np.float64), ("camera", np.float64, (3,)),
    ("velocity", np.float64, (3,)), ("velocity_sigma", np.float64, (3,)), ("speed", np.float64),
    ("speed_sigma", np.float64),
])


class Camera(NamedTuple):
    """The rectified left camera, as the kernels take it (pixels; ``bf`` px·m)."""

    fx: float
    fy: float
    cx: float
    cy: float
    bf: float
    height: float  # the image's rows

    @classmethod
    def of(cls, c: StereoCalibration, height: float | None = None) -> "Camera":
        return cls(float(c.fx), float(c.fy), float(c.cx), float(c.cy), float(c.bf),
                   float(c.height if height is None else height))


class Images(NamedTuple):
    """A frame's images for :func:`_object_stats`: instance labels (``use_labels``: whether
    they are the outlines), the masker's disparity and the objects' own (``own``)."""

    labels: np.ndarray
    disp: np.ndarray
    own: np.ndarray
    use_labels: bool


class StatsInputs(NamedTuple):
    """Per object, for :func:`_object_stats` (docstring there)."""

    own_k: np.ndarray
    boxes: np.ndarray
    peak: np.ndarray
    head: np.ndarray
    need_ab: np.ndarray
    axis: np.ndarray
    width: np.ndarray
    v_known: np.ndarray


class Histograms(NamedTuple):
    """The kernel's histogram buffers (zeroed when they come in and when they leave)."""

    d: np.ndarray  # (N, N_BINS) disparities
    a: np.ndarray  # (N, AB_BINS) top view, along the heading
    b: np.ndarray  # (N, AB_BINS) top view, across it


class CentreInputs(NamedTuple):
    """Per object, for :func:`_centres`: boxes (N, 4) float, sizes (N, 3), heading (N, 2),
    cut by the image's left / right side, small (no length), measured in the top view."""

    boxes: np.ndarray
    sizes: np.ndarray
    head: np.ndarray
    left: np.ndarray
    right: np.ndarray
    small: np.ndarray
    top_view: np.ndarray


class Measurements(NamedTuple):
    """Per object, :func:`_centres`' output and :func:`_track_frame`'s input: whether it
    gives a measurement, its centre in the camera, the range sigma of its median disparity,
    its box's width / height at unit depth, cut by the image's side, its heading (x, z) in
    the camera's top view, its class size (w, h, l)."""

    valid: np.ndarray
    X: np.ndarray
    sigma_r: np.ndarray
    size_unit: np.ndarray
    cut: np.ndarray
    head: np.ndarray
    sizes: np.ndarray


class Verdicts(NamedTuple):
    """Per object, for :func:`_track_frame`: its track's slot (-1: none), the motion test's
    verdict static, its speed (NaN: none) and that speed's sigma (NaN: unknown)."""

    slots: np.ndarray
    still: np.ndarray
    speed: np.ndarray
    speed_sigma: np.ndarray


class Filter(NamedTuple):
    """The filter's settings: acceleration noise per world axis, the innovation gate, how
    long a track coasts on its prediction."""

    qa: np.ndarray
    gate: float
    coast_s: float


class TrackArrays(NamedTuple):
    """The track table's arrays (:class:`_TrackTable`), updated in place by the kernels."""

    x: np.ndarray
    P: np.ndarray
    t: np.ndarray
    n: np.ndarray
    full: np.ndarray
    has_full: np.ndarray
SPEED_DIRECTION = 0.3  # m/s: the filter's velocity gives a direction for the motion test's speed above it
SPEED_SIGMA = 0.3  # m/s, the motion test's speed at least (its own sigma where larger; plus 10 %)
STILL_SIGMA = 0.1  # m/s, the velocity of an object the motion test judged static


@jit
def _quantiles(hist, n, lo, hi, origin, step, b0=0, b1=-1):  # pragma: no cover - compiled
    """The ``lo`` and ``hi`` quantiles of a histogram whose counts (``n`` of them) all lie in
    bins ``b0 .. b1`` (default: all); 0.0 for one not reached."""
    c = 0
    got = False
    q_lo = 0.0
    tl = lo * n
    th = hi * n
    if b1 < 0:
        b1 = hist.shape[0] - 1
    for b in range(b0, b1 + 1):
        c += hist[b]
        if not got and c >= tl:
            q_lo = origin + (b + 0.5) * step
            got = True
        if c >= th:
            return q_lo, origin + (b + 0.5) * step
    return q_lo, 0.0


@jit(inline="always")
def _median_point(boxes, out, k, cam):  # pragma: no cover - compiled
    """(x, z) in the camera's top view of object k's median disparity on its box centre's column."""
    zm = cam.bf / max(out[k].d_median, 1e-3)
    return (0.5 * (boxes[k, 0] + boxes[k, 2]) - cam.cx) * zm / cam.fx, zm


@jit
def _object_stats(images, objs, cam, hists, out):  # pragma: no cover - compiled
    """Per object k (boxes int (N, 4) clipped x0, y0, x1, y1; ``head`` (N, 2) its heading
    (x, z) in the camera's top view; ``need_ab``: whether it needs the top-view pass;
    ``axis``: whether to try the heading from its points, ``width`` its class width,
    ``v_known`` whether ``head`` is its velocity's): ``out[k]``, a :data:`STATS` record =
    ``n_disparity`` (pixels with a disparity), ``d_median`` / ``d_p10`` / ``d_p90`` / ``d_p5`` /
    ``d_p95`` (its disparities' quantiles), then its pixels' top-view coordinates along the
    heading (``a_median``, ``a_p10``, ``a_p90``, ``a_p5``, ``a_p95``) and across it (``b_p10``,
    ``b_p90``, ``b_p5``, ``b_p95``), metres; ``n_outline`` its outline's pixels, with a
    disparity or not; ``axis_from_points`` 1 where the heading came from its points (then
    ``head[k]`` is that heading and ``need_ab[k]`` set, in place); ``out`` comes in zeroed.
    The heading from the points (module doc): the principal axis of their
    top-view coordinates (those within the p5-p95 disparities), taken when they spread
    along it over ``AXIS_EXTENT`` class widths (a uniform spread's ``sqrt(12 λ1)``) and
    ``AXIS_RATIO`` times their spread across it (variances), and when within
    ``AXIS_AGREE`` of the velocity's heading (where known); signed like ``head``.  From histograms
    ``hist`` (N, bins), ``hist_a`` / ``hist_b`` (N, AB bins) (module doc), which must come
    in zeroed and are left zeroed (the bins used are cleared: buffers reused frame to frame).
    With instance labels each box's own outline (its label's pixels); without, each box's
    pixels within 15 % of the object's peak disparity.  Object k's disparities are ``own``'s
    where ``own_k[k]`` (its outline matched again: ``objects.disparity``), else
    ``disp``'s.  ``images`` / ``objs`` / ``cam`` / ``hists``: :class:`Images`,
    :class:`StatsInputs`, :class:`Camera`, :class:`Histograms`."""
    labels, disp, own, use_labels = images.labels, images.disp, images.own, images.use_labels
    own_k, boxes, peak, head, need_ab, axis, width, v_known = objs
    bf, fx, cx = cam.bf, cam.fx, cam.cx
    hist, hist_a, hist_b = hists.d, hists.a, hists.b
    n_obj = boxes.shape[0]
    nb = hist.shape[1]
    na = hist_a.shape[1]
    half = 0.5 * na * AB_STEP
    if n_obj == 0:
        return
    # first pass: the disparity histograms (and the range of bins each one uses)
    bmin = np.full(n_obj, nb, np.int64)
    bmax = np.zeros(n_obj, np.int64)
    n_hist = np.zeros(n_obj, np.int64)  # the disparities in each histogram
    if use_labels:
        # per box, its own outline's pixels (label k + 1: only inside box k), the counts
        # kept in registers (added into out[k] per pixel, each add waited on the one before)
        for k in range(n_obj):
            x0, y0, x1, y1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
            kk = k + 1
            c_all = 0
            c_d = 0
            lo_b = nb
            hi_b = 0
            sy = max(1, (x1 - x0) * (y1 - y0) // FIRST_PASS_PIXELS)  # a large box: every sy-th row
            for y in range(y0, y1, sy):
                lab = labels[y, x0:x1]  # row slices: indices from 0, no negative-index wrap test
                dis = (own if own_k[k] else disp)[y, x0:x1]
                for i in range(x1 - x0):
                    if lab[i] != kk:
                        continue
                    c_all += 1
                    d = dis[i]
                    if d <= 0.0:
                        continue
                    b = min(int(d * 16.0), nb - 1)
                    hist[k, b] += 1
                    c_d += 1
                    lo_b = min(lo_b, b)
                    hi_b = max(hi_b, b)
            n_hist[k] = c_d
            out[k].n_disparity = c_d * sy  # the outline's pixels (with a disparity), estimated
            out[k].n_outline = c_all * sy
            bmin[k] = lo_b
            bmax[k] = hi_b
    else:
        for k in range(n_obj):
            lo = 0.85 * peak[k] - 1.0
            hi = 1.15 * peak[k] + 1.0
            for y in range(boxes[k, 1], boxes[k, 3]):
                for x in range(boxes[k, 0], boxes[k, 2]):
                    d = disp[y, x]
                    if d <= 0.0 or (peak[k] > 0.0 and (d < lo or d > hi)):
                        continue
                    b = min(int(d * 16.0), nb - 1)
                    hist[k, b] += 1
                    out[k].n_disparity += 1
                    out[k].n_outline += 1
                    bmin[k] = min(bmin[k], b)
                    bmax[k] = max(bmax[k], b)
    am = np.zeros(n_obj)
    bm = np.zeros(n_obj)
    any_ab = False
    for k in range(n_obj):
        n = n_hist[k] if use_labels else int(out[k].n_disparity)
        if n == 0:
            continue
        out[k].d_median, _ = _quantiles(hist[k], n, 0.5, 0.5, 0.0, BIN, bmin[k], bmax[k])
        out[k].d_p10, out[k].d_p90 = _quantiles(hist[k], n, 0.1, 0.9, 0.0, BIN, bmin[k], bmax[k])
        out[k].d_p5, out[k].d_p95 = _quantiles(hist[k], n, 0.05, 0.95, 0.0, BIN, bmin[k], bmax[k])
        hist[k, bmin[k]:bmax[k] + 1] = 0  # left zeroed for the next frame
    # the heading from the points: their top-view second moments (about the median
    # point), in a pass over the objects that try it
    for k in range(n_obj):
        if not axis[k] or out[k].n_disparity < 30:
            continue
        xm, zm = _median_point(boxes, out, k, cam)
        lo = out[k].d_p5 - 0.5 * BIN
        hi = out[k].d_p95 + 0.5 * BIN
        m0 = 0.0
        sx = 0.0
        sz = 0.0
        sxx = 0.0
        sxz = 0.0
        szz = 0.0
        st = 1 + int(np.sqrt(out[k].n_disparity / SAMPLE_PIXELS))
        src = own if own_k[k] else disp
        for y in range(boxes[k, 1], boxes[k, 3], st):
            for x in range(boxes[k, 0], boxes[k, 2], st):
                d = src[y, x]
                if d < lo or d > hi or d <= 0.0:
                    continue
                if use_labels and labels[y, x] != k + 1:
                    continue
                z = bf / d
                xx = (x + 0.5 - cx) * z / fx - xm
                z -= zm
                m0 += 1.0
                sx += xx
                sz += z
                sxx += xx * xx
                sxz += xx * z
                szz += z * z
        if m0 < 30:
            continue
        cxx = sxx / m0 - (sx / m0) ** 2
        cxz = sxz / m0 - (sx / m0) * (sz / m0)
        czz = szz / m0 - (sz / m0) ** 2
        tr = 0.5 * (cxx + czz)
        disc = np.sqrt(max(0.25 * (cxx - czz) ** 2 + cxz * cxz, 0.0))
        l1 = tr + disc
        l2 = max(tr - disc, 1e-9)
        if np.sqrt(12.0 * l1) < AXIS_EXTENT * width[k] or l1 < AXIS_RATIO * l2:
            continue
        # the major axis: (cxz, l1 - cxx), or (l1 - czz, cxz) when that one is degenerate
        ex, ez = cxz, l1 - cxx
        if abs(ex) + abs(ez) < 1e-12:
            ex, ez = l1 - czz, cxz
        nrm = np.sqrt(ex * ex + ez * ez)
        if nrm < 1e-12:
            continue
        ex /= nrm
        ez /= nrm
        c = ex * head[k, 0] + ez * head[k, 1]
        if c < 0.0:
            ex, ez, c = -ex, -ez, -c
        if v_known[k] and c < np.cos(AXIS_AGREE):
            continue
        head[k, 0] = ex
        head[k, 1] = ez
        need_ab[k] = True
        out[k].axis_from_points = 1.0
    for k in range(n_obj):
        if need_ab[k] and out[k].n_disparity > 0:
            any_ab = True
            xm, zm = _median_point(boxes, out, k, cam)
            am[k] = xm * head[k, 0] + zm * head[k, 1]
            bm[k] = xm * head[k, 1] - zm * head[k, 0]
    if not any_ab:
        return
    # second pass, for the objects that need it: the pixels' top-view coordinates along /
    # across the heading, around the median point of the box centre's column
    for k in range(n_obj):
        if not need_ab[k] or out[k].n_disparity == 0:
            continue
        hx, hz = head[k, 0], head[k, 1]
        lo = 0.85 * peak[k] - 1.0
        hi = 1.15 * peak[k] + 1.0
        a0, a1, c0, c1 = na, 0, na, 0
        st = 1 + int(np.sqrt(out[k].n_disparity / SAMPLE_PIXELS))  # every st-th row and column
        src = own if own_k[k] else disp
        cnt = 0
        for y in range(boxes[k, 1], boxes[k, 3], st):
            for x in range(boxes[k, 0], boxes[k, 2], st):
                d = src[y, x]
                if d <= 0.0:
                    continue
                if use_labels:
                    if labels[y, x] != k + 1:
                        continue
                elif peak[k] > 0.0 and (d < lo or d > hi):
                    continue
                z = bf / d
                xx = (x + 0.5 - cx) * z / fx
                ia = int((xx * hx + z * hz - am[k] + half) / AB_STEP)
                ib = int((xx * hz - z * hx - bm[k] + half) / AB_STEP)
                ia = min(max(ia, 0), na - 1)
                ib = min(max(ib, 0), na - 1)
                hist_a[k, ia] += 1
                hist_b[k, ib] += 1
                cnt += 1
                a0, a1, c0, c1 = min(a0, ia), max(a1, ia), min(c0, ib), max(c1, ib)
        if cnt == 0:
            continue
        n = cnt
        out[k].a_median, _ = _quantiles(hist_a[k], n, 0.5, 0.5, am[k] - half, AB_STEP, a0, a1)
        out[k].a_p10, out[k].a_p90 = _quantiles(hist_a[k], n, 0.1, 0.9, am[k] - half, AB_STEP, a0, a1)
        out[k].a_p5, out[k].a_p95 = _quantiles(hist_a[k], n, 0.05, 0.95, am[k] - half, AB_STEP, a0, a1)
        out[k].b_p10, out[k].b_p90 = _quantiles(hist_b[k], n, 0.1, 0.9, bm[k] - half, AB_STEP, c0, c1)
        out[k].b_p5, out[k].b_p95 = _quantiles(hist_b[k], n, 0.05, 0.95, bm[k] - half, AB_STEP, c0, c1)
        hist_a[k, a0:a1 + 1] = 0
        hist_b[k, c0:c1 + 1] = 0


@jit(inline="always")
def _axis_centre(mid, lo, hi, extent):  # pragma: no cover - compiled
    """The centre along one top-view axis: both ends' middle ``mid`` when the camera is
    within the object's span, else the face toward the camera (``lo`` beyond it, ``hi``
    before it) plus half the ``extent``."""
    if abs(mid) < 0.5 * extent:
        return mid
    return lo + 0.5 * extent if mid > 0 else hi - 0.5 * extent


@jit
def _centres(out, objs, cam, sigma_d, meas):  # pragma: no cover - compiled
    """Per object k, from :func:`_object_stats`' ``out[k]`` (module doc, "Centre, not
    surface"): whether it gives a measurement (``valid[k]``: a disparity on at least
    ``MIN_VALID_FRACTION`` of its outline, and a box not shorter than ``MIN_VISIBLE_HEIGHT``
    of its class height at that depth unless cut by the image's top or bottom), its centre
    in the camera ``X[k]`` (the top view -- per axis the face toward the camera plus half
    the footprint, both ends' middle when the camera is within the object's span, the end
    seen for a vehicle cut by the image's side, bounded by the other visible end -- or, for
    the others (``top_view[k]`` False), the box centre's ray at the nearest point plus half
    the box's extent along it; vertically the box centre's row at the surface's depth, or
    half the class height below the top row of a box cut by the image's bottom), the range
    sigma of the median disparity ``sigma_r[k]`` and the box's width / height at unit
    depth ``size_unit[k]``.  ``sizes`` (N, 3) width, height, length; ``head`` (N, 2) the
    heading (x, z) in the camera's top view; ``boxes`` (N, 4) float (``objs``:
    :class:`CentreInputs`; ``cam``: :class:`Camera`; the results into ``meas``, a
    :class:`Measurements`)."""
    boxes, sizes, head, left, right, small, top_view = objs
    cx, cy, fx, fy, bf, h_img = cam.cx, cam.cy, cam.fx, cam.fy, cam.bf, cam.height
    X, valid, sigma_r, size_unit = meas.X, meas.valid, meas.sigma_r, meas.size_unit
    for k in range(boxes.shape[0]):
        x0, y0, x1, y1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
        w_, h_, l_ = sizes[k, 0], sizes[k, 1], sizes[k, 2]
        n, dmed = out[k].n_disparity, out[k].d_median
        # an outline mostly without disparity (occluded, or another object's disparity
        # leaking in): no measurement; nor from a box too short for its class at the depth
        # measured, not cut by the image's top or bottom: a sliver beside a nearer object
        # whose disparity leaked in (stereo matching fattens a near object's edges)
        ok = n >= 10 and dmed > 0.5 and n >= MIN_VALID_FRACTION * out[k].n_outline
        v_cut = y0 <= 1.0 or y1 >= h_img - 1.0
        tall = (y1 - y0) >= MIN_VISIBLE_HEIGHT * h_ * fy * max(dmed, 0.0) / bf
        ok = ok and (v_cut or tall)
        # top view: per axis (along the heading, extent l; across it, extent w) the face
        # toward the camera (at 0) plus half the extent; a camera within the object's span
        # (5th / 95th percentiles' middle) sees both ends: their middle
        a_lo, a_hi, a_5, a_95 = out[k].a_p10, out[k].a_p90, out[k].a_p5, out[k].a_p95
        b_lo, b_hi, b_5, b_95 = out[k].b_p10, out[k].b_p90, out[k].b_p5, out[k].b_p95
        a_mid = 0.5 * (a_5 + a_95)
        b_mid = 0.5 * (b_5 + b_95)
        a_c = _axis_centre(a_mid, a_lo, a_hi, l_)
        b_c = _axis_centre(b_mid, b_lo, b_hi, w_)
        # cut by the image's side, one end is out of view: along the heading, the end seen
        # (the one away from the cut side) minus half the length.  Along the heading the
        # image column grows with a where the object lies at b < 0 (u ~ x / z: d(x/z)/da =
        # -b / z^2), so the end seen is the high one (the 95th percentile) for a box cut
        # by the left side at b < 0 or by the right side at b > 0 (a parked car's far end,
        # a crossing car's front as it comes in), else the low one (the 5th).  The object
        # holds its visible points: its centre no farther from the cut side's visible end
        # than half the length (a real detector's outline takes in background past the
        # end seen: up to 10 m on KITTI raw 0001)
        if (left[k] or right[k]) and not small[k] and not (left[k] and right[k]):
            high = b_mid < 0 if left[k] else b_mid > 0
            if high:
                a_c = min(a_95 - 0.5 * l_, a_5 + 0.5 * l_)
            else:
                a_c = max(a_5 + 0.5 * l_, a_95 - 0.5 * l_)
        hx, hz = head[k, 0], head[k, 1]
        dm = dmed if ok else 1.0
        if top_view[k]:
            X[k, 0] = a_c * hx + b_c * hz
            X[k, 2] = a_c * hz - b_c * hx
        else:
            # whole in view and not known static: the box centre's ray, at the nearest
            # point (p90 disparity) plus half the box's extent along the ray
            rx = (0.5 * (x0 + x1) - cx) / fx
            nr = np.sqrt(rx * rx + 1.0)
            rx /= nr
            rz = 1.0 / nr
            cos_phi = abs(rx * hx + rz * hz)
            e = l_ * cos_phi + w_ * np.sqrt(max(1.0 - cos_phi * cos_phi, 0.0))
            r_near = bf / (max(out[k].d_p90, 0.5) if ok else 1.0) / rz
            r = max(r_near + 0.5 * e, bf / dm / rz)
            X[k, 0] = rx * r
            X[k, 2] = rz * r
        # vertical: the box centre's row at the depth of the surface seen (the median
        # disparity's: the box spans the near surface, not the centre's depth); a box cut by
        # the image's bottom (a person close by) hangs half the class height below its top row
        if y1 >= h_img - 1.0 and y0 > 1.0:
            X[k, 1] = (y0 - cy) / fy * X[k, 2] + 0.5 * h_
        else:
            X[k, 1] = (0.5 * (y0 + y1) - cy) / fy * (bf / dm)
        valid[k] = ok and X[k, 2] > 0
        sigma_r[k] = (bf / dm) * sigma_d / dm
        size_unit[k, 0] = (x1 - x0) / fx
        size_unit[k, 1] = (y1 - y0) / fy


@jit
def _inv3(S, out):  # pragma: no cover - compiled
    a, b, c = S[0, 0], S[0, 1], S[0, 2]
    d, e, f = S[1, 0], S[1, 1], S[1, 2]
    g, h, i = S[2, 0], S[2, 1], S[2, 2]
    A, B, C = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * A + b * B + c * C
    out[0, 0], out[1, 0], out[2, 0] = A / det, B / det, C / det
    out[0, 1], out[1, 1], out[2, 1] = -(b * i - c * h) / det, (a * i - c * g) / det, -(a * h - b * g) / det
    out[0, 2], out[1, 2], out[2, 2] = (b * f - c * e) / det, -(a * f - c * d) / det, (a * e - b * d) / det


@jit
def _update3(x, g, Pn, y, Si, o, K, KP):  # pragma: no cover - compiled
    """Kalman update of state ``x[g]`` (6) and covariance ``Pn`` by a 3-vector measurement
    of the state's entries ``o..o+2`` (H = [I 0] for o = 0, [0 I] for o = 3): innovation
    ``y``, inverse innovation covariance ``Si``; ``K`` (6, 3), ``KP`` (6, 6) scratch."""
    for i in range(6):
        for j in range(3):
            K[i, j] = Pn[i, o] * Si[0, j] + Pn[i, o + 1] * Si[1, j] + Pn[i, o + 2] * Si[2, j]
    for i in range(6):
        x[g, i] += K[i, 0] * y[0] + K[i, 1] * y[1] + K[i, 2] * y[2]
        for j in range(6):
            KP[i, j] = K[i, 0] * Pn[o, j] + K[i, 1] * Pn[o + 1, j] + K[i, 2] * Pn[o + 2, j]
    for i in range(6):
        for j in range(6):
            Pn[i, j] -= KP[i, j]


@jit
def _kalman(x, P, z, Rz, dt, qa, speed, speed_sigma, still, speed_dir, still_sigma, chi):  # pragma: no cover
    """Per track g, in place: predict ``x`` (G, 6), ``P`` (G, 6, 6) over ``dt`` with white
    acceleration noise ``qa`` (3,) per axis; update with the position ``z`` (G, 3),
    covariance ``Rz`` (G, 3, 3) (``chi``: the innovation's chi-square); then with the
    motion test's ``speed`` along the velocity (NaN: none; sigma ``speed_sigma`` plus 10 %),
    or ``v = 0`` where ``still``."""
    Pn = np.empty((6, 6))
    S = np.empty((3, 3))
    Si = np.empty((3, 3))
    K = np.empty((6, 3))
    KP = np.empty((6, 6))
    y = np.empty(3)
    h = np.empty(6)
    for g in range(x.shape[0]):
        t = dt[g]
        # predict: F = [[I, t I], [0, I]], Q = [[t^3/3, t^2/2], [t^2/2, t]] qa
        for i in range(3):
            x[g, i] += t * x[g, i + 3]
        for i in range(3):
            for j in range(3):
                p11, p12, p21, p22 = P[g, i, j], P[g, i, j + 3], P[g, i + 3, j], P[g, i + 3, j + 3]
                Pn[i, j] = p11 + t * (p12 + p21) + t * t * p22
                Pn[i, j + 3] = p12 + t * p22
                Pn[i + 3, j] = p21 + t * p22
                Pn[i + 3, j + 3] = p22
            Pn[i, i] += t ** 3 / 3.0 * qa[i]
            Pn[i, i + 3] += t * t / 2.0 * qa[i]
            Pn[i + 3, i] += t * t / 2.0 * qa[i]
            Pn[i + 3, i + 3] += t * qa[i]
        # position update, H = [I 0]
        for i in range(3):
            y[i] = z[g, i] - x[g, i]
            for j in range(3):
                S[i, j] = Pn[i, j] + Rz[g, i, j]
        _inv3(S, Si)
        c = 0.0
        for i in range(3):
            for j in range(3):
                c += y[i] * Si[i, j] * y[j]
        chi[g] = c
        _update3(x, g, Pn, y, Si, 0, K, KP)
        sp = np.sqrt(x[g, 3] ** 2 + x[g, 4] ** 2 + x[g, 5] ** 2)
        if still[g]:  # v = 0, H = [0 I]
            for i in range(3):
                y[i] = -x[g, i + 3]
                for j in range(3):
                    S[i, j] = Pn[i + 3, j + 3] + (still_sigma ** 2 if i == j else 0.0)
            _inv3(S, Si)
            _update3(x, g, Pn, y, Si, 3, K, KP)
        elif not np.isnan(speed[g]) and sp > speed_dir:  # |v| = speed, H = [0, v / |v|]
            for i in range(6):
                h[i] = 0.0
            for i in range(3):
                h[i + 3] = x[g, i + 3] / sp
            s = speed_sigma[g] ** 2 + (0.1 * speed[g]) ** 2
            for i in range(3, 6):
                for j in range(3, 6):
                    s += h[i] * Pn[i, j] * h[j]
            for i in range(6):
                k = 0.0
                for j in range(3, 6):
                    k += Pn[i, j] * h[j]
                K[i, 0] = k / s
            for j in range(6):
                hp = 0.0
                for i in range(3, 6):
                    hp += h[i] * Pn[i, j]
                y[0] = hp
                for i in range(6):
                    KP[i, j] = K[i, 0] * hp
            r = speed[g] - sp
            for i in range(6):
                x[g, i] += K[i, 0] * r
            for i in range(6):
                for j in range(6):
                    Pn[i, j] -= KP[i, j]
        for i in range(6):
            for j in range(6):
                P[g, i, j] = Pn[i, j]


@jit
def _headings(R, slots, tx, tn, head, moves):  # pragma: no cover - compiled
    """Per object k, in place: ``head[k]`` its heading (x, z) in the camera's top view --
    its track's velocity when faster than ``MOVING_HEADING_SPEED`` (``moves[k]``), else the
    camera's forward axis -- from the track table's states ``tx`` / counts ``tn`` at
    ``slots[k]`` (-1: no track); ``R`` the camera's rotation into the world."""
    for k in range(slots.shape[0]):
        hw0, hw1, hw2 = R[0, 2], R[1, 2], R[2, 2]
        moves[k] = False
        s = slots[k]
        if s >= 0 and tn[s] > 0:
            v0, v1, v2 = tx[s, 3], tx[s, 4], tx[s, 5]
            if v0 * v0 + v1 * v1 + v2 * v2 > MOVING_HEADING_SPEED ** 2:
                hw0, hw1, hw2 = v0, v1, v2
                moves[k] = True
        hx = R[0, 0] * hw0 + R[1, 0] * hw1 + R[2, 0] * hw2  # into the camera: R^T h, in the top view
        hz = R[0, 2] * hw0 + R[1, 2] * hw1 + R[2, 2] * hw2
        nrm = max(np.sqrt(hx * hx + hz * hz), 1e-9)
        head[k, 0] = hx / nrm
        head[k, 1] = hz / nrm


@jit(inline="always")
def _speed_into(v, Pv, out, k):  # pragma: no cover - compiled
    """``out[k]``'s velocity fields from a filter's velocity ``v`` (3,) and its covariance
    ``Pv`` (3, 3): velocity, its sigmas per axis, speed ``|v|`` and its sigma
    ``sqrt(vᵀ P_v v) / |v|`` (at rest: the mean axis sigma)."""
    sp = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    vpv = 0.0
    for i in range(3):
        out[k].velocity[i] = v[i]
        out[k].velocity_sigma[i] = np.sqrt(Pv[i, i])
        for j in range(3):
            vpv += v[i] * Pv[i, j] * v[j]
    out[k].speed = sp
    out[k].speed_sigma = (np.sqrt(vpv) / max(sp, 1e-6) if sp > 1e-6
                           else np.sqrt((Pv[0, 0] + Pv[1, 1] + Pv[2, 2]) / 3.0))


@jit(inline="always")
def _to_camera(R, t_c, out, k):  # pragma: no cover - compiled
    """``out[k]``'s camera centre from its world one: ``R^T (world - t_c)``."""
    for j in range(3):
        out[k].camera[j] = (R[0, j] * (out[k].world[0] - t_c[0]) + R[1, j] * (out[k].world[1] - t_c[1])
                             + R[2, j] * (out[k].world[2] - t_c[2]))


@jit
def _track_frame(meas, verdicts, R, t_c, stamp, fx, filt, tracks, out, flags):  # pragma: no cover - compiled
    """The frame's states from the measurements (module doc: uncertainty, velocity,
    position out, no measurement), one call a frame.

    Per object k: ``X_c`` / ``valid`` / ``sigma_r`` / ``size_unit`` / ``cut`` / ``head`` (x, z)
    as :meth:`WorldObjects.measure` gives them, ``sizes`` (N, 3), its track's slot in the
    table (``slots``, -1: no track), the motion test's verdict static (``still``), speed
    (``speed``, NaN: none) and its sigma (``speed_sigma``, NaN: unknown); ``R`` / ``t_c``
    the camera's pose; ``qa`` the filter's acceleration noise per world axis.  The track
    table (``tx`` (S, 6) states, ``tP`` (S, 6, 6) covariances, ``tt`` stamps of the last
    update, ``tn`` updates, 0: no state yet; ``tfull`` (S, 6) / ``thas`` a static track's
    last full view, world and sigma) is updated in place.  Writes ``out`` (N :data:`STATE`
    records, zeroed when they come in: world, world sigma, extent, heading in the world,
    distance, camera centre, velocity, its sigmas, speed, its sigma) and ``flags``
    (N, 3: 0 none / 1 measured / 2 the filter's prediction, 1 where it has a velocity, the
    track's updates); returns the number of tracks restarted (an innovation over ``gate``).
    ``meas``: :class:`Measurements`; ``verdicts``: :class:`Verdicts`; ``filt``:
    :class:`Filter`; ``tracks``: :class:`TrackArrays`."""
    valid, X_c, sigma_r, size_unit, cut, head, sizes = meas
    slots, still, speed, speed_sigma = verdicts
    qa, gate, coast_s = filt
    tx, tP, tt, tn, tfull, thas = tracks
    N = X_c.shape[0]
    Cw = np.empty((N, 3, 3))
    for k in range(N):
        flags[k, 0] = 0
        flags[k, 1] = 0
        flags[k, 2] = 1
        x0, x1, x2 = X_c[k, 0], X_c[k, 1], X_c[k, 2]
        r = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        out[k].distance = r
        # covariance: sig_along^2 r r^T + sig_lat^2 (I - r r^T), into the world (R r)
        sa = np.sqrt(sigma_r[k] ** 2 + (0.1 * sizes[k, 2]) ** 2)
        sl = np.sqrt((r * max(0.05 * size_unit[k, 0] * fx, 1.0) / fx) ** 2 + (0.1 * sizes[k, 0]) ** 2)
        a = sa * sa - sl * sl
        b = sl * sl
        inv = 1.0 / max(r, 1e-9)
        hx, hz = head[k, 0], head[k, 1]
        for i in range(3):
            out[k].world[i] = R[i, 0] * x0 + R[i, 1] * x1 + R[i, 2] * x2 + t_c[i]
            out[k].heading[i] = R[i, 0] * hx + R[i, 2] * hz
            out[k].camera[i] = X_c[k, i]
        u0 = (R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2) * inv
        u1 = (R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2) * inv
        u2 = (R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2) * inv
        Cw[k, 0, 0], Cw[k, 0, 1], Cw[k, 0, 2] = a * u0 * u0 + b, a * u0 * u1, a * u0 * u2
        Cw[k, 1, 0], Cw[k, 1, 1], Cw[k, 1, 2] = a * u1 * u0, a * u1 * u1 + b, a * u1 * u2
        Cw[k, 2, 0], Cw[k, 2, 1], Cw[k, 2, 2] = a * u2 * u0, a * u2 * u1, a * u2 * u2 + b
        for i in range(3):
            out[k].world_sigma[i] = np.sqrt(Cw[k, i, i])
        depth = max(x2, 0.0)
        out[k].extent[0] = size_unit[k, 0] * depth
        out[k].extent[1] = size_unit[k, 1] * depth
        out[k].extent[2] = sizes[k, 2]
    # the filter: one row per track with a measurement (its first object; a second
    # detection under the same id shares it)
    row = np.full(tn.shape[0], -1, np.int64)
    rows = np.empty(N, np.int64)
    G = 0
    for k in range(N):
        s = slots[k]
        if valid[k] and s >= 0 and row[s] < 0:
            row[s] = G
            rows[G] = k
            G += 1
    xg = np.zeros((G, 6))
    Pg = np.zeros((G, 6, 6))
    dt = np.zeros(G)
    z = np.empty((G, 3))
    Rz = np.empty((G, 3, 3))
    spd = np.empty(G)
    ssg = np.empty(G)
    stl = np.empty(G, np.bool_)
    for g in range(G):
        k = rows[g]
        s = slots[k]
        if tn[s] > 0:
            xg[g] = tx[s]
            Pg[g] = tP[s]
            dt[g] = max(stamp - tt[s], 1e-3)
        for i in range(3):
            z[g, i] = out[k].world[i]
        Rz[g] = Cw[k]
        spd[g] = speed[k]
        # the motion test's speed sigma, at least SPEED_SIGMA (unknown: SPEED_SIGMA)
        ssg[g] = SPEED_SIGMA if np.isnan(speed_sigma[k]) else max(SPEED_SIGMA, speed_sigma[k])
        stl[g] = still[k]
    chi = np.zeros(G)
    _kalman(xg, Pg, z, Rz, dt, qa, spd, ssg, stl, SPEED_DIRECTION, STILL_SIGMA, chi)
    restarts = 0
    for g in range(G):
        s = slots[rows[g]]
        known = tn[s] > 0
        fresh = not known or chi[g] > gate
        if known and chi[g] > gate:
            restarts += 1
        if fresh:  # a new track, or a restarted one (the id went to another object): the measurement, v = 0 +- 10 m/s
            for i in range(6):
                xg[g, i] = z[g, i] if i < 3 else 0.0
                for j in range(6):
                    Pg[g, i, j] = Rz[g, i, j] if i < 3 and j < 3 else 0.0
            for i in range(3):
                Pg[g, 3 + i, 3 + i] = 100.0 * VERTICAL[i, i]
        tx[s] = xg[g]
        tP[s] = Pg[g]
        tt[s] = stamp
        tn[s] = 1 if fresh else tn[s] + 1
    # each static object's last full view (measured, not cut by the image's side), kept
    # per track; a track judged moving or undecided forgets it
    for k in range(N):
        s = slots[k]
        if s >= 0 and valid[k] and not cut[k] and still[k]:
            for i in range(3):
                tfull[s, i] = out[k].world[i]
                tfull[s, 3 + i] = out[k].world_sigma[i]
            thas[s] = True
    for k in range(N):
        if slots[k] >= 0 and not still[k]:
            thas[slots[k]] = False
    for k in range(N):
        s = slots[k]
        if not valid[k]:
            continue
        flags[k, 0] = 1
        if s < 0:
            continue
        g = row[s]
        if cut[k] and rows[g] == k:  # cut by the image's side: the filter's position
            for i in range(3):
                out[k].world[i] = xg[g, i]
                out[k].world_sigma[i] = np.sqrt(Pg[g, i, i])
            _to_camera(R, t_c, out, k)
        if cut[k] and still[k] and thas[s]:  # judged static: where its last full view put it
            for i in range(3):
                out[k].world[i] = tfull[s, i]
                out[k].world_sigma[i] = tfull[s, 3 + i]
            _to_camera(R, t_c, out, k)
        _speed_into(xg[g, 3:], Pg[g, 3:, 3:], out, k)
        flags[k, 1] = 1
        flags[k, 2] = tn[s]
    # no measurement: the filter's prediction within coast_s of its last update (or, judged
    # static, its last full view)
    for k in range(N):
        s = slots[k]
        if valid[k] or s < 0 or tn[s] == 0 or stamp - tt[s] > coast_s:
            continue
        d = stamp - tt[s]
        for i in range(3):
            out[k].world[i] = tx[s, i] + d * tx[s, 3 + i]
            out[k].world_sigma[i] = np.sqrt(tP[s, i, i] + d * d * tP[s, 3 + i, 3 + i])
        _to_camera(R, t_c, out, k)
        if still[k] and thas[s]:
            for i in range(3):
                out[k].world[i] = tfull[s, i]
                out[k].world_sigma[i] = tfull[s, 3 + i]
            _to_camera(R, t_c, out, k)
        c0, c1, c2 = out[k].camera[0], out[k].camera[1], out[k].camera[2]
        out[k].distance = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        out[k].extent[0] = size_unit[k, 0] * max(c2, 0.0)
        out[k].extent[1] = size_unit[k, 1] * max(c2, 0.0)
        _speed_into(tx[s, 3:], tP[s, 3:, 3:], out, k)
        flags[k, 0] = 2
        flags[k, 1] = 1
        flags[k, 2] = tn[s]
    return restarts


class _TrackTable:
    """The filters' state per track id, in slots of arrays (the compiled kernels' form):
    ``x`` (S, 6), ``P`` (S, 6, 6), ``t`` the stamp of its last update, ``n`` its updates
    (0: none yet), ``full`` / ``has_full`` a static track's last full view (world, sigma)."""

    def __init__(self, capacity: int = 32):
        self.slot: dict[int, int] = {}
        self.ids = np.zeros(0, np.int64)  # each slot's track id, -1: free
        self.x, self.P = np.zeros((0, 6)), np.zeros((0, 6, 6))
        self.t, self.n = np.zeros(0), np.zeros(0, np.int64)
        self.full, self.has_full = np.zeros((0, 6)), np.zeros(0, np.bool_)
        self._free: list[int] = []
        self._grow(capacity)

    def _grow(self, cap: int) -> None:
        old = len(self.ids)
        pad = lambda a, shape, fill=0: np.concatenate([a, np.full((cap - old, *shape), fill, a.dtype)])  # noqa: E731
        self.x, self.P, self.t, self.n = pad(self.x, (6,)), pad(self.P, (6, 6)), pad(self.t, ()), pad(self.n, ())
        self.full, self.has_full, self.ids = pad(self.full, (6,)), pad(self.has_full, ()), pad(self.ids, (), -1)
        self._free = list(range(cap - 1, old - 1, -1)) + self._free

    def slots(self, tracks: list[int]) -> np.ndarray:
        """(N,) the slots of the track ids (-1 for an object without one); a new id gets a
        free slot without a state."""
        out = np.full(len(tracks), -1, np.int64)
        for i, t in enumerate(tracks):
            if t < 0:
                continue
            s = self.slot.get(t)
            if s is None:
                if not self._free:
                    self._grow(2 * len(self.ids))
                s = self._free.pop()
                self.slot[t], self.ids[s], self.n[s], self.has_full[s] = s, t, 0, False
            out[i] = s
        return out

    def arrays(self) -> TrackArrays:
        """The table's arrays, as the kernels take them (updated in place)."""
        return TrackArrays(self.x, self.P, self.t, self.n, self.full, self.has_full)

    def last_stamp(self, default: float) -> float:
        used = (self.ids >= 0) & (self.n > 0)
        return float(self.t[used].max()) if used.any() else default

    def drop(self, stamp: float, max_gap: float) -> None:
        """Forget the tracks not updated within ``max_gap`` s and the slots never updated."""
        gone = np.flatnonzero((self.ids >= 0) & ((self.n == 0) | (stamp - self.t > max_gap)))
        for s in gone.tolist():
            del self.slot[int(self.ids[s])]
            self.ids[s] = -1
            self._free.append(s)

    def clear(self) -> None:
        self.drop(np.inf, -1.0)


@dataclass
class ObjectState:
    """One object in one frame, in the trajectory's (world) frame; metres, m/s."""

    track: int
    world: np.ndarray  # (3,) centre
    world_sigma: np.ndarray  # (3,) standard deviations
    extent: np.ndarray  # (3,) width, height, length
    heading: np.ndarray  # (3,) unit vector, world: the length axis
    distance: float  # from the camera, metres
    camera: np.ndarray | None = None  # (3,) centre in this frame's camera (x right, y down, z forward)
    velocity: np.ndarray | None = None  # (3,)
    velocity_sigma: np.ndarray | None = None
    speed: float | None = None
    speed_sigma: float | None = None
    updates: int = 1  # measurements the track's filter has taken
    predicted: bool = False  # no measurement this frame: the filter's prediction

    def to_dict(self) -> dict[str, Any]:
        r = lambda a, n=3: [round(float(v), n) for v in a]  # noqa: E731
        d = {"world": r(self.world), "world_sigma": r(self.world_sigma), "extent": r(self.extent, 2),
             "distance": round(float(self.distance), 2)}
        if self.camera is not None:
            d["camera"] = r(self.camera)
        if self.velocity is not None:
            d.update(velocity=r(self.velocity), velocity_sigma=r(self.velocity_sigma),
                     speed=round(float(self.speed), 3), speed_sigma=round(float(self.speed_sigma), 3))
        if self.predicted:
            d["predicted"] = True
        return d


def verdict_rgb(moving: bool | None) -> tuple[int, int, int]:
    """The motion test's verdict colour as RGB (``datatypes.VERDICT_COLOURS``, which is BGR):
    moving red, static green, undecided orange."""
    b, g, r = VERDICT_COLOURS[None if moving is None else bool(moving)]
    return (r, g, b)


def box_corners(centre: np.ndarray, extent: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """(8, 3) corners of an object's box: ``extent`` (width, height, length), the length
    along ``heading`` (world, y down), upright."""
    h = np.array([heading[0], 0.0, heading[2]])
    h /= max(np.linalg.norm(h), 1e-9)
    across = np.array([h[2], 0.0, -h[0]])
    up = np.array([0.0, 1.0, 0.0])
    w, hh, l = 0.5 * np.asarray(extent, float)
    sx, sy, sz = np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")
    return centre + (sx.reshape(-1, 1) * w * across + sy.reshape(-1, 1) * hh * up + sz.reshape(-1, 1) * l * h)


def _class_size(label: str) -> tuple[float, float, float]:
    return CLASS_SIZE.get(str(label).lower(), DEFAULT_SIZE)


class WorldObjects:
    """Per stream of frames: ``update(masks, pose, ok, stamp, frame)`` after each tracked
    frame (module doc).  ``accel_noise``: the filter's white acceleration noise (m²/s³);
    ``sigma_disparity`` / ``sigma_px``: stereo noise (px); ``max_gap``: seconds after
    which an unseen track is forgotten; ``stereo``: the objects' own block matching
    (``objects.block_size``; None: the masker's disparity)."""

    def __init__(self, calibration: StereoCalibration, *, accel_noise: float = 2.0, sigma_disparity: float = 0.5,
                 sigma_px: float = 0.5, max_gap: float = 2.0, stereo: ObjectStereo | None = None):
        self.gate = GATE
        self.restarts = 0
        self.calib = calibration
        self.q = float(accel_noise)
        self.sigma_d = float(sigma_disparity)
        self.sigma_px = float(sigma_px)
        self.max_gap = float(max_gap)
        self.stereo = stereo
        self._own_disp: np.ndarray | None = None  # its result's buffer, kept between frames
        if stereo is not None:
            stereo.warm_up()
        self._tracks = _TrackTable()  # the filters' states per track id
        self._qa = self.q * np.diag(VERTICAL)  # the filter's acceleration noise per world axis
        self._filter = Filter(self._qa, float(self.gate), float(COAST_S))
        self._hist = np.zeros((0, N_BINS), np.int32)  # the kernel's histograms (module doc)
        self._hist_ab = np.zeros((2, 0, AB_BINS), np.int32)
        self.last: list[ObjectState | None] = []
        self._mover_boxes: deque = deque(maxlen=20000)  # (centre, extent, heading) of movers, every frame
        # the compiled kernels loaded (or compiled) now, not in the first frames
        b0, f0, i0, z2 = np.zeros(0, np.bool_), np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 2))
        cam = Camera(1.0, 1.0, 0.0, 0.0, 1.0, 1.0)
        _object_stats(Images(np.zeros((1, 1), np.int32), np.zeros((1, 1), np.float32), np.zeros((1, 1), np.float32),
                             True),
                      StatsInputs(b0, np.zeros((0, 4), np.int64), f0, z2, b0, b0, f0, b0), cam,
                      Histograms(np.zeros((0, N_BINS), np.int32), np.zeros((0, AB_BINS), np.int32),
                                 np.zeros((0, AB_BINS), np.int32)), np.zeros(0, STATS))
        meas = Measurements(b0, np.zeros((0, 3)), f0, z2, b0, z2, np.zeros((0, 3)))
        _centres(np.zeros(0, STATS), CentreInputs(np.zeros((0, 4)), np.zeros((0, 3)), z2, b0, b0, b0, b0), cam, 1.0,
                 meas)
        tb = self._tracks
        _headings(np.eye(3), i0, tb.x, tb.n, z2, b0)
        _track_frame(meas, Verdicts(i0, b0, f0, f0), np.eye(3), np.zeros(3), 0.0, 1.0, self._filter, tb.arrays(),
                     np.zeros(0, STATE), np.zeros((0, 3), np.int64))

    @classmethod
    def from_config(cls, calibration: StereoCalibration, cfg: Config) -> "WorldObjects":
        """The tracker a run of ``cfg`` uses: the motion test's stereo noise, the objects'
        own matching (``objects.*``)."""
        return cls(calibration, sigma_disparity=cfg.motion.sigma_disparity, sigma_px=cfg.motion.sigma_px,
                   stereo=ObjectStereo.from_config(cfg.objects, cfg.stereo))

    def outside_movers(self, points: np.ndarray, margin: float = 0.5) -> np.ndarray:
        """(M,) bool: the world ``points`` (M, 3) outside every box (grown by ``margin`` m)
        an object judged moving had in any frame -- what a static map export keeps."""
        P = np.asarray(points, np.float64).reshape(-1, 3)
        keep = np.ones(len(P), bool)
        for c, ext, h in self._mover_boxes:  # per mover box (hundreds), vectorised over the points
            along = np.array([h[0], 0.0, h[2]])
            along /= max(np.linalg.norm(along), 1e-9)
            across = np.array([along[2], 0.0, -along[0]])
            d = P - c
            half = 0.5 * np.asarray(ext) + margin
            inside = ((np.abs(d @ across) <= half[0]) & (np.abs(d[:, 1]) <= half[1])
                      & (np.abs(d @ along) <= half[2]))
            keep &= ~inside
        return keep

    def reset(self) -> None:
        self._tracks.clear()

    # ------------------------------------------------------------------ measurement
    def measure(self, masks: StereoMasks, head_c: np.ndarray, sizes: np.ndarray,
                v_known: np.ndarray | None = None, frame: StereoFrame | None = None) -> Measurements:
        """Per object (``head_c`` (N, 2): heading (x, z) in the camera's top view; ``sizes``
        (N, 3) width, height, length; ``v_known`` (N,): whether the heading is the track's
        velocity's), a :class:`Measurements`: valid (N,), centre in the camera (N, 3), range
        sigma of the median disparity (N,), box width / height at unit depth (N, 2), cut by
        the image's left / right side (N,), the heading used (N, 2: a moving vehicle's from
        its points where they show it), the sizes (module doc).  With ``frame`` and the objects' own matching
        (``stereo``), the outlines' disparity is matched again first."""
        c = self.calib
        objs = masks.objects
        N = len(objs)
        disp = masks.box_disparity if masks.box_disparity is not None else masks.disparity
        boxes = np.array([o.box for o in objs], np.float64).reshape(N, 4)
        h_img, w_img = (disp.shape[:2] if disp is not None else (c.height, c.width))
        left, right = boxes[:, 0] <= 1.0, boxes[:, 2] >= w_img - 1.0  # cut by the image's left / right side
        cut = left | right
        small = sizes[:, 2] < 1.0  # a person: no length to speak of
        static = np.array([o.moving is False for o in objs], bool)
        top_view = cut | small | static  # the rest (moving or undecided vehicles in full view): the ray
        moving = np.array([o.moving is True for o in objs], bool)
        head_c = np.array(head_c, np.float64, order="C").reshape(N, 2)  # a copy: the kernel may replace a heading
        v_known = np.zeros(N, np.bool_) if v_known is None else np.asarray(v_known, np.bool_)
        out = np.zeros(N, STATS)
        use = False
        if disp is not None and N:
            bi = np.empty((N, 4), np.int64)
            bi[:, 0] = np.clip(np.floor(boxes[:, 0]), 0, w_img)
            bi[:, 1] = np.clip(np.floor(boxes[:, 1]), 0, h_img)
            bi[:, 2] = np.clip(np.ceil(boxes[:, 2]), 0, w_img)
            bi[:, 3] = np.clip(np.ceil(boxes[:, 3]), 0, h_img)
            labels = masks.labels_left
            use = labels is not None and labels.shape == disp.shape
            disp = np.ascontiguousarray(disp, np.float32)
            own, own_k = disp, np.zeros(N, np.bool_)
            if use and frame is not None and self.stereo is not None:
                # the outlines matched again: read from its buffer where it matched them
                own, matched = self.stereo(frame.left_gray, frame.right_gray, labels, disp, bi, self._own_disp)
                self._own_disp, own_k = own, matched >= 0
            peak = np.array([o.disparity for o in objs], np.float64)
            if self._hist.shape[0] < N:  # the kernel leaves them zeroed: allocated once
                self._hist = np.zeros((N, N_BINS), np.int32)
                self._hist_ab = np.zeros((2, N, AB_BINS), np.int32)
            _object_stats(Images(labels if use else np.zeros((1, 1), np.int32), disp, own, use),
                          StatsInputs(own_k, bi, peak, head_c, top_view, moving & ~small,
                                      np.ascontiguousarray(sizes[:, 0]), v_known),
                          Camera.of(c, h_img), Histograms(self._hist[:N], self._hist_ab[0, :N], self._hist_ab[1, :N]),
                          out)
        sizes = np.ascontiguousarray(sizes, np.float64)
        meas = Measurements(np.empty(N, np.bool_), np.empty((N, 3)), np.empty(N), np.empty((N, 2)), cut, head_c, sizes)
        _centres(out, CentreInputs(boxes, sizes, head_c, left, right, small, top_view), Camera.of(c, h_img),
                 self.sigma_d, meas)
        return meas

    # ------------------------------------------------------------------ the frame
    def update(self, masks: StereoMasks | None, pose: np.ndarray, ok: bool = True,
               stamp: float | None = None, frame: StereoFrame | None = None) -> list[ObjectState | None]:
        """The states of ``masks.objects`` in this frame (None: no disparity, or the pose
        was lost), also set as each object's ``world``; ``pose``: 3x4 / 4x4 camera-to-world;
        ``stamp``: seconds (default: 0.1 s a frame); ``frame``: the stereo pair, for the
        objects' own matching (``stereo``; without it, the masker's disparity).  Three
        compiled calls (the headings, the measurement, the tracks) over the frame's objects."""
        if masks is None or not masks.objects:
            self.last = []
            return []
        objs = masks.objects
        N = len(objs)
        states: list[ObjectState | None] = [None] * N
        if not ok:
            for o in objs:
                o.world = None
            self.last = states
            return states
        pose = np.asarray(pose, np.float64)
        R, t_c = np.ascontiguousarray(pose[:3, :3]), np.ascontiguousarray(pose[:3, 3])
        tb = self._tracks
        stamp = float(stamp) if stamp is not None else tb.last_stamp(-0.1) + 0.1
        sizes = np.array([_class_size(o.label) for o in objs]).reshape(N, 3)  # w, h, l
        tracks = [int(o.track_id) for o in objs]
        slots = tb.slots(tracks)
        still = np.array([o.moving is False for o in objs], np.bool_)
        speed = np.array([np.nan if o.speed_mps is None else o.speed_mps for o in objs], np.float64)
        speed_sigma = np.array([np.nan if o.speed_sigma_mps is None else o.speed_sigma_mps for o in objs], np.float64)
        head = np.empty((N, 2))
        moves = np.empty(N, np.bool_)
        _headings(R, slots, tb.x, tb.n, head, moves)
        meas = self.measure(masks, head, sizes, moves, frame)
        out = np.zeros(N, STATE)
        flags = np.empty((N, 3), np.int64)
        self.restarts += _track_frame(meas, Verdicts(slots, still, speed, speed_sigma), R, t_c, stamp,
                                      float(self.calib.fx), self._filter, tb.arrays(), out, flags)
        for k in np.flatnonzero(flags[:, 0]).tolist():
            o = out[k]
            st = ObjectState(tracks[k], o["world"].copy(), o["world_sigma"].copy(), o["extent"].copy(),
                             o["heading"].copy(), float(o["distance"]), o["camera"].copy(), updates=int(flags[k, 2]),
                             predicted=bool(flags[k, 0] == 2))
            if flags[k, 1]:
                st.velocity, st.velocity_sigma = o["velocity"].copy(), o["velocity_sigma"].copy()
                st.speed, st.speed_sigma = float(o["speed"]), float(o["speed_sigma"])
            states[k] = st
            if objs[k].moving is not False:  # moving, or undecided (masked): never in the map
                # copies: views would keep every frame's whole output alive in the deque
                self._mover_boxes.append((st.world.copy(), st.extent.copy(), st.heading.copy()))
        for o, st in zip(objs, states):
            o.world = st
        tb.drop(stamp, self.max_gap)
        self.last = states
        return states


class ObjectPaths:
    """Each track's recent world positions and last verdict, for drawing paths (rerun, ROS):
    ``add(objects)`` once a frame with its ``ObjectMask`` list; ``paths()`` -> ``[(track,
    (n, 3) positions, moving)]`` of the tracks with two positions or more."""

    def __init__(self, max_len: int = 300):
        self.max_len = max_len
        self._p: dict[int, deque] = {}
        self._v: dict[int, bool | None] = {}

    def add(self, objects: list) -> None:
        for o in objects:
            if getattr(o, "world", None) is not None and o.track_id >= 0:
                self._p.setdefault(int(o.track_id), deque(maxlen=self.max_len)).append(np.asarray(o.world.world, float))
                self._v[int(o.track_id)] = o.moving

    def paths(self) -> list[tuple[int, np.ndarray, bool | None]]:
        return [(t, np.array(p), self._v[t]) for t, p in self._p.items() if len(p) > 1]


class TrackWriter:
    """``objects_tracks.csv``: one row per object and frame with a world position
    (``TRACK_COLUMNS``), flushed after every frame."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._fh: IO[str] | None = open(self.path, "w", newline="")
        self._w = csv.writer(self._fh)
        self._w.writerow(TRACK_COLUMNS)

    def write(self, frame: int, stamp: float, masks: StereoMasks | None) -> None:
        if self._fh is None or masks is None:
            return
        f = lambda v: "" if v is None else f"{float(v):.3f}"  # noqa: E731
        for o in masks.objects:
            s = getattr(o, "world", None)
            if s is None:
                continue
            v = s.velocity if s.velocity is not None else (None, None, None)
            mv = "" if o.moving is None else int(bool(o.moving))
            self._w.writerow([s.track, frame, f"{stamp:.6f}", o.label, *map(f, s.world), *map(f, v), f(s.speed),
                              f(s.speed_sigma), mv])
        self._fh.flush()

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def __enter__(self) -> "TrackWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_tracks(path: str | Path) -> dict[int, dict[str, np.ndarray]]:
    """``objects_tracks.csv`` as ``{track: {"frame", "stamp", "xyz" (n, 3), "speed", "speed_sigma", "moving"
    (1, 0, -1 undecided), "label"}}``."""
    out: dict[int, dict[str, list]] = {}
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            t = out.setdefault(int(row["track_id"]), {"frame": [], "stamp": [], "xyz": [], "speed": [],
                                                       "speed_sigma": [], "moving": [], "label": row["label"]})
            t["frame"].append(int(row["frame"]))
            t["stamp"].append(float(row["stamp"]))
            t["xyz"].append([float(row["x"]), float(row["y"]), float(row["z"])])
            t["speed"].append(float(row["speed"]) if row["speed"] else np.nan)
            t["speed_sigma"].append(float(row["speed_sigma"]) if row["speed_sigma"] else np.nan)
            t["moving"].append({"": -1, "0": 0, "1": 1}[row["moving"]])
    return {k: {kk: (np.asarray(vv) if kk != "label" else vv) for kk, vv in v.items()} for k, v in out.items()}


#: A track counts as an object judged moving (:func:`moving_tracks`) when the motion test
#: said "moving" in most of the frames it decided, over at least this many frames.
MOVING_MIN_FRAMES = 3


def track_verdict(track: dict[str, np.ndarray]) -> bool | None:
    """A track's verdict from its rows' ``moving`` column (1, 0, -1 undecided): moving when
    most of its decided frames say so; None when none decided."""
    m = np.asarray(track["moving"])
    dec = m[m >= 0]
    return None if not len(dec) else bool((dec == 1).mean() > 0.5)


def moving_tracks(tracks: dict[int, dict[str, np.ndarray]]) -> dict[int, dict[str, np.ndarray]]:
    """The objects judged moving -- the one definition the report, ``run``'s summary and
    :attr:`~dynastereo.runtime.results.JobResult.moving_objects` share: tracks whose
    verdict (:func:`track_verdict`) is moving, seen in at least :data:`MOVING_MIN_FRAMES`
    frames.  (Counting the tracks with any row ``moving == 1`` counts more: a track can be
    judged moving in a frame or two and static in most.)"""
    return {k: t for k, t in tracks.items() if track_verdict(t) is True and len(t["frame"]) >= MOVING_MIN_FRAMES}
