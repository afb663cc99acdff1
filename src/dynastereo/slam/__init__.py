"""Stereo visual SLAM back-end (ORB-SLAM2-style tracking and local mapping) in Python.

    from dynastereo.slam import System
    system = System(config, sequence.calibration)     # Config or SlamConfig
    res = system.track(stereo_frame, masks, timer)    # TrackResult; res.pose 3x4 camera-to-world
    poses = system.trajectory()                       # (N, 3, 4), one row per frame fed
    system.stats(); system.results(); system.lost_frames()
    system.loops(); system.recoveries()               # loops closed, frames found again
    system.save_map("m.dsmap"); other.load_map("m.dsmap", localize_only=True)
    system.shutdown()                                 # applies the pending local BA, stops its thread

Modules follow ORB-SLAM2: ``orb`` (ORBExtractor: masked, grid-bucketed pyramid ORB),
``matcher`` (stereo row matching, projection search), ``frame`` / ``keyframe`` / ``map``
(array-wise map points and observations, covisibility), ``tracking`` (the tracking state
and its policy), ``trajectory`` (the per-frame rows), ``selfcal`` (the disparity offset),
``active_map`` (the map with its mapper, database and loop closer), ``local_mapping``
(point creation / culling / fusion, local BA, keyframe culling), ``optimizer`` (numpy
motion-only BA, bundle adjustment), ``kernels`` (the compiled kernels: BA, pose, matching), ``settings``
(ORB-SLAM2 settings files), ``vocabulary`` / ``keyframe_database`` (bag of words, place
recognition), ``loop_closing`` (detection, SE(3) verification, fusion, essential graph,
full BA), ``map_io`` (map files), ``system``.  Stage times: ``features``, ``stereo``,
``track``, ``local_mapping``.

Beyond ORB-SLAM2's tracking: a pose needs support (inliers against the recent frames'
median) or it is replaced by a prior-free search over the map's keyframes
(``Tracker.relocalize`` on bag-of-words candidates) -- revisits and gaps are found again
or marked lost, never mis-tracked; and the stereo rig's disparity offset is
self-calibrated by BAs over the whole map (``optimizer.self_calibrating_ba``).  See ``system`` for the lost-frame
policy.
"""

from .settings import load_orbslam_settings
from .loop_closing import LoopEvent
from .system import System, SystemStats
from .tracking import FrameFeatures, Recovery, TrackingMethod, TrackingState, TrackResult

__all__ = ["System", "SystemStats", "TrackResult", "FrameFeatures", "TrackingState", "TrackingMethod", "Recovery", "LoopEvent",
           "load_orbslam_settings"]
