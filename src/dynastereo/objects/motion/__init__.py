"""Mask only what moves: each tracked object judged moving or static from stereo scene flow.

Masking every detected car costs SLAM its best texture when the cars are parked.  This
module decides per object, against the camera's motion that SLAM measured from the
static background (world frame, not the image: a truck that fills the view and drives
with the camera is moving).  Two halves, because masking runs one frame ahead of
tracking on a prefetch thread:

* :class:`SceneFlow` (masking thread, ``measure(frame, masks)`` after the masker):
  for every object seen in frames k-1 and k under the same track id, the points followed
  into k-1 topped up to ``motion.max_points`` with new corners on its outline at k-1
  (``goodFeaturesToTrack`` on the instance label, where the masker's disparity is
  valid, 3 px from the points it has) are followed to k by pyramidal Lucas-Kanade, ONE
  forward and one backward call for all objects' points, on the union of their boxes
  (forward-backward checked, error < 1 px); a point is kept when
  it lands on the same object's outline at k with a valid disparity there.  Each point
  keeps where it was first seen (pixel, disparity, frame), up to ``window_frames`` back.
  Result: a :class:`FrameFlow` of ``(u, v, d)`` at k-1, k and first sight per object.
* :class:`MotionJudge` (main thread): ``select(masks)`` just before ``System.track``
  gives the masks SLAM gets -- only objects judged moving or not yet judged (the safe
  default) are masked, static ones are left to tracking and mapping; ``update(masks,
  pose, ok)`` after tracking weighs the frame's flow against the camera motion:

  - frame to frame (:func:`static_chi2`): a static point's ``(u, v, d)`` at k-1, moved by
    ``T_{k,k-1}`` and projected, must land on its measurement at k.  The residual's
    covariance holds the measurement noise at k (``sigma_px``, ``sigma_disparity``) and
    the noise at k-1 propagated through the prediction (its Jacobian, by finite
    differences): the stereo depth uncertainty ``sigma_Z = Z^2 sigma_d / bf`` and the
    lateral ``Z sigma_px / f`` enter that way; the fraction of points over ``chi2``;
  - over the window (:func:`world_velocity`): the object's world velocity, the median of
    ``(X_k - X_first) / age`` of its points in the world frame, against its covariance
    (stereo at both ends, at most ``object_points`` independent points, SLAM's pose
    error as a random walk): chi-square against ``object_chi2``.  The long baseline sees
    a car ahead at the camera's speed far away, which one frame cannot.

  The velocity's noise is that of a median of points of unequal ages
  (``velocity_noise: median``): the points first seen a frame ago, whose displacement is
  noisy, barely move a median, so they must not set its covariance.

  Evidence of motion / rest per frame, hysteresis over frames (``confirm_frames``; a
  mover released after as many frames of rest as it gave of motion, at most
  ``release_frames``; one frame failing both tests decides an undecided object moving,
  ``strong_confirm``) gives the verdict ``moving`` True / False / None (undecided); a
  frame where most objects judged static seem to move gives none (a bad pose), and no
  window displacement is measured across it afterwards (``suspect_restarts_window``).  Speed =
  the velocity's norm / dt (median of the last 3 frames).  ``update`` returns the objects
  that turned moving from static, whose map points :class:`ObjectMotion` removes
  (the frame processor applies them: ``System.forget_region``).  An undecided object whose box overlaps a judged one of
  its class group by IoU >= ``duplicate_iou`` is a second detection of it (a detector
  names one car ``car`` and ``truck``) and takes its verdict (:meth:`MotionJudge.verdicts`).

The package: :mod:`.flow` (``SceneFlow``), :mod:`.stats` (``static_chi2``, ``world_velocity``),
:mod:`.verdicts` (``MotionJudge``: evidence and hysteresis), :mod:`.map_edits` (the points of an
object turned moving removed); here ``ObjectMotion`` and ``build_motion``.

Everything is vectorized over all objects' points at once (grouped medians and sums);
per object there is only the hysteresis.
Maskers without instance labels (``seg``) get verdicts but keep every object masked;
objects without a track id (``detector.track: false``) stay undecided (masked).
"""

from __future__ import annotations

from dataclasses import dataclass

from ...config import MotionConfig
from ...datatypes import StereoCalibration, StereoFrame, StereoMasks
from .flow import FrameFlow, ObjectFlow, SceneFlow
from .map_edits import MapEdit, moving_edits, object_region
from .stats import static_chi2, static_residuals, world_velocity
from .verdicts import MotionJudge

__all__ = [
    "FrameFlow",
    "MapEdit",
    "MotionJudge",
    "ObjectFlow",
    "ObjectMotion",
    "SceneFlow",
    "build_motion",
    "moving_edits",
    "object_region",
    "static_chi2",
    "static_residuals",
    "world_velocity",
]


class ObjectMotion:
    """Both halves for one stream of frames: ``measure`` on the masking thread, ``select``
    before and ``update`` after ``System.track`` on the tracking thread.  ``update`` returns
    the map edits of the objects that turned moving (``motion.forget_points``); the caller
    applies them to the SLAM's map and counts what went (:meth:`forgot`)."""

    def __init__(self, cfg: MotionConfig, calibration: StereoCalibration):
        self.cfg = cfg
        self.calib = calibration
        self.flow = SceneFlow(cfg)
        self.judge = MotionJudge(cfg, calibration)
        self.forgotten = 0  # map points removed so far

    def measure(self, frame: StereoFrame, masks: StereoMasks | None) -> None:
        if masks is not None:
            masks.flow = self.flow.measure(frame, masks)

    def select(self, masks: StereoMasks | None) -> StereoMasks | None:
        return self.judge.select(masks)

    def update(self, masks: StereoMasks | None, tracked) -> MotionUpdate:
        """``tracked``: the frame's ``TrackResult``.  Returns the objects that turned moving
        from static and the map edits that remove their points (none when
        ``motion.forget_points`` is off)."""
        ok = str(tracked.status) in ("tracked", "init")
        turned = self.judge.update(masks, tracked.pose, ok)
        edits: list[MapEdit] = []
        if turned and self.cfg.forget_points and masks is not None:
            edits = moving_edits(masks, turned, self.calib)
        return MotionUpdate(turned, edits)

    def forgot(self, n: int) -> None:
        """Count ``n`` map points removed by applying this test's map edits."""
        self.forgotten += int(n)


@dataclass(frozen=True)
class MotionUpdate:
    """What :meth:`ObjectMotion.update` found on a frame."""

    turned: list[int]  # objects (indices into masks.objects) that turned moving from static
    edits: list[MapEdit]  # their map points to remove (System.forget_region)


def build_motion(cfg, calibration: StereoCalibration | None, masker=None) -> ObjectMotion | None:
    """The motion test for a job (``cfg``: the whole Config), or None when every detection
    is masked (``motion.mode: all``), nothing is masked, or there is no calibration."""
    if masker is None or getattr(masker, "name", "") == "none" or calibration is None:
        return None
    if str(cfg.motion.mode).lower() == "all":
        return None
    return ObjectMotion(cfg.motion, calibration)
