"""Self-calibration of the stereo disparity offset (``slam.self_calibrate``).

Rectified pairs often carry a small constant disparity offset (a right principal-point
error; KITTI's is about 0.15-0.25 px), which biases every depth by ``delta / bf`` in
inverse depth -- on KITTI a 0.7 % too long path.  :class:`SelfCalibration` owns all of it:

* **the schedule**: when the map has ``selfcal_keyframes`` keyframes, local mapping
  solves a BA over the whole map at three offsets (:data:`GRID`) in its BA thread; the
  parabola of its cost gives the offset (``optimizer.self_calibrating_ba``).  It is refined
  the same way at 1.5x, 2.25x... that many keyframes (``selfcal_rounds`` estimates in
  all).  A new map (re-initialization) starts the schedule again only while no estimate
  has been applied; a loaded map keeps its offset;
* **the estimate** ``offset`` +- ``sigma`` (px).  No offset is applied until an estimate is
  ``selfcal_min_sigmas`` from 0; the later rounds then refine it whatever its size;
* **applying it**, in one place: new frames' stereo matches get the offset
  (:meth:`on_frame`); an estimate moves every keyframe's and the frame in flight's
  stereo observations, and the points seen by a single keyframe (:meth:`apply`).
"""

from __future__ import annotations

import math

import numpy as np

from ..config import SlamConfig
from .map import Map

# disparity offsets (px) at which the self-calibrating BA is solved
GRID = (-0.3, 0.0, 0.3)
# frames tracked while the self-calibrating BA runs in the BA thread
LAG_FRAMES = 8
# points in the self-calibrating BA
MAX_POINTS = 6000


def shift_disparity(uv: np.ndarray, u_right: np.ndarray, depth: np.ndarray, delta: float, bf: float) -> None:
    """Add ``delta`` px to the disparity of the stereo keypoints (in place; >= 0.01 px)."""
    st = u_right >= 0
    if not st.any():
        return
    disp = np.maximum(uv[st, 0] - u_right[st] + delta, 0.01)
    u_right[st] = uv[st, 0] - disp
    depth[st] = bf / disp


class SelfCalibration:
    """The disparity offset of one :class:`~dynastereo.slam.System` (module doc)."""

    def __init__(self, cfg: SlamConfig, bf: float) -> None:
        self.cfg = cfg
        self.bf = float(bf)
        self.enabled = bool(cfg.self_calibrate and cfg.mapping_on)
        self.offset = float(cfg.disparity_offset)  # px, carried by every stereo observation now
        self.sigma: float | None = None
        self.follow = None  # the frame the next one is tracked against: it follows an estimate too
        self._restart = self.enabled  # a new map starts a schedule until an estimate was applied
        self._base = 0.0  # the offset the running self-calibrating BA's observations carry
        self.due = False
        self.at = cfg.selfcal_keyframes
        self.rounds_left = cfg.selfcal_rounds
        self.new_map()

    # ------------------------------------------------------------- schedule
    def new_map(self) -> None:
        """A new map starts: the schedule again (unless an estimate was applied already)."""
        self.due = self._restart
        self.at = self.cfg.selfcal_keyframes
        self.rounds_left = self.cfg.selfcal_rounds

    def loaded(self, offset: float) -> None:
        """A map file's offset: used as it is, no schedule."""
        self.offset = float(offset)
        self._restart = self.due = False

    def round_due(self, n_keyframes: int) -> bool:
        """Whether the next local BA is a self-calibrating one."""
        return self.due and self.rounds_left > 0 and n_keyframes >= self.at

    def start_round(self) -> None:
        """A self-calibrating BA (made with :meth:`prepare`) was submitted: the next round
        comes at 1.5 times as many keyframes."""
        self.rounds_left -= 1
        self.at = int(math.ceil(self.at * 1.5))
        self.due = self.rounds_left > 0

    def prepare(self, problem) -> None:
        """Make ``problem`` estimate the offset, relative to the one its observations carry."""
        problem.offset_grid = GRID
        # an offset must first be told apart from 0; once one is applied, the later
        # rounds refine it whatever the size of the change
        problem.offset_min_sigmas = self.cfg.selfcal_min_sigmas if self.offset == 0.0 else 0.0
        self._base = self.offset

    @staticmethod
    def lag_frames(problem, lag: int) -> int:
        """Frames to track before a BA's result is applied: a self-calibrating BA solves the
        map several times, so it gets at least :data:`LAG_FRAMES`."""
        return max(lag, LAG_FRAMES) if problem.offset_grid else lag

    # -------------------------------------------------------------- applying
    def on_frame(self, uv: np.ndarray, u_right: np.ndarray, depth: np.ndarray) -> float:
        """A new frame's stereo matches get the offset; returns the offset they carry."""
        if self.offset != 0.0:
            shift_disparity(uv, u_right, depth, self.offset, self.bf)
        return self.offset

    def sync(self, frame, offset_used: float) -> float:
        """Move ``frame``'s stereo observations to the current offset if an estimate was
        applied since it was matched with ``offset_used``; returns the current offset."""
        if self.offset != offset_used:
            shift_disparity(frame.uv, frame.u_right, frame.depth, self.offset - offset_used, self.bf)
        return self.offset

    def apply(self, estimate: float, sigma: float | None, mp: Map) -> None:
        """A self-calibrating BA's estimate (relative to the offset its observations
        carried): every keyframe's and the followed frame's stereo observations move to
        the new offset, before the BA solved with it is applied; points seen by a single
        keyframe (not in the BA) are placed again from that keyframe's new depth."""
        offset = self._base + float(estimate)
        delta = offset - self.offset
        self._restart = False  # a new map (re-initialization) does not start over
        self.sigma = sigma
        if delta == 0.0:
            return
        self.offset = offset
        done: set[int] = set()
        holders = list(mp.keyframes.values())
        if self.follow is not None:
            holders.append(self.follow)
        for h in holders:  # a keyframe shares its arrays with its frame: shift once
            if id(h.u_right) in done:
                continue
            done.add(id(h.u_right))
            shift_disparity(h.uv, h.u_right, h.depth, delta, self.bf)
        for kf in mp.keyframes.values():
            kp = np.flatnonzero((kf.point_ids >= 0) & (kf.u_right >= 0))
            pts = kf.point_ids[kp]
            one = (mp.points.ref_kf[pts] == kf.id) & (mp.points.nobs[pts] <= 2) & ~mp.points.bad[pts]
            if one.any():
                mp.points.pos[pts[one]] = kf.unproject(kp[one])
