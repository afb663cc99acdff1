"""Relocalization (ORB-SLAM2 ``Tracking::Relocalization``): a prior-free pose of a frame in
the map, when neither the motion model nor the reference keyframe gives a supported one.

Candidate keyframes come from the bag-of-words keyframe database
(``KeyFrameDatabase.detect_relocalization_candidates``, ORB-SLAM2's
``DetectRelocalizationCandidates``), then, when none of them holds, from
:func:`candidate_keyframes` (a vote of a sample of the frame's descriptors matched
brute force to the map's points).  For each candidate: descriptor matches, PnP-RANSAC,
motion-only BA and local-map tracking; the hypothesis with most inliers wins
(:func:`relocalize`).  The tracker's state (reference keyframe, local keyframes,
inliers) is left as the winning hypothesis made it.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .frame import Frame
from .geometry import pnp_ransac
from .map import Map
from .matcher import TH_LOW, keyframe_point_matches

if TYPE_CHECKING:  # for annotations only: the Tracker imports this module
    from .tracking import Tracker


def relocalize_frame(tracker: Tracker, f: Frame) -> tuple[bool, int]:
    """:func:`relocalize` on the bag-of-words candidates (ORB-SLAM2's
    ``DetectRelocalizationCandidates``); when none of them holds, on the keyframes
    that see most of a sample of the frame's descriptors (brute force)."""
    t0 = time.perf_counter()
    active, cfg = tracker.active, tracker.cfg
    mp, n = active.map, cfg.reloc_candidates
    bow, _ = tracker.vocab.transform(f.desc)
    cands = [k for k in active.kfdb.detect_relocalization_candidates(bow, mp.best_covisibles)
             if k in mp.keyframes]
    found, kid = relocalize(tracker, mp, f, cands[:n])
    if not found or tracker.n_inliers < max(cfg.reloc_min_inliers, cfg.min_inliers):
        more = [k for k in candidate_keyframes(mp, f, n) if k not in cands[:n]]
        if more:
            found, kid = relocalize(tracker, mp, f, more)
    tracker.reloc_ms.append((time.perf_counter() - t0) * 1e3)
    return found, kid


def relocalize(tracker: Tracker, mp: Map, frame: Frame, candidates: list[int]) -> tuple[bool, int]:
    """Prior-free pose of the frame in the map (ORB-SLAM2 ``Relocalization``): for each
    candidate keyframe (from the bag-of-words database, or ``candidate_keyframes``),
    descriptor matches + PnP-RANSAC + motion-only BA + local-map tracking; the
    hypothesis with most inliers wins.  Returns ``(found, keyframe id)``; the frame /
    tracker hold the best hypothesis (or are left as they were when none is found)."""
    saved = (
        frame.T_cw.copy() if frame.T_cw is not None else None,
        frame.point_ids.copy(),
        frame.match_xyz.copy(),
        frame.outlier.copy(),
        tracker.ref_kf,
        list(tracker.local_kfs),
        tracker.n_inliers,
    )
    best: tuple | None = None
    for kid in candidates:
        kf = mp.keyframes.get(kid)
        if kf is None:
            continue
        ki, pts = keyframe_point_matches(mp, kf, frame)
        if len(ki) < 15:
            continue
        X = mp.points.pos[pts]
        T, _ = pnp_ransac(X, frame.uv[ki], frame.calib.K, tracker.seed)
        if T is None:
            continue
        frame.T_cw = T
        frame.clear_matches(np.arange(len(frame)))
        tracker.assign_matches(frame, ki, pts, X)
        if tracker.optimize_frame(mp, frame) < 10:
            continue
        tracker.ref_kf = kf
        tracker.track_local_map(mp, frame, count=False)
        if best is None or tracker.n_inliers > best[0]:
            best = (
                tracker.n_inliers,
                kid,
                frame.T_cw.copy(),
                frame.point_ids.copy(),
                frame.match_xyz.copy(),
                frame.outlier.copy(),
                tracker.ref_kf,
                list(tracker.local_kfs),
            )
    if best is None:
        (frame.T_cw, frame.point_ids, frame.match_xyz, frame.outlier, tracker.ref_kf, tracker.local_kfs,
         tracker.n_inliers) = saved
        return False, -1
    n, kid, frame.T_cw, frame.point_ids, frame.match_xyz, frame.outlier, tracker.ref_kf, tracker.local_kfs = best
    tracker.n_inliers = n
    inl = frame.point_ids[frame.point_ids >= 0]
    mp.points.mark_found(inl)
    mp.points.mark_visible(inl)
    return True, kid


def candidate_keyframes(mp: Map, frame: Frame, n: int = 3, max_points: int = 20000) -> list[int]:
    """Keyframes of the map most likely to see the frame's place: a sample of the
    frame's descriptors is matched to the map's points (nearest, <= TH_LOW) and every
    keyframe gets a vote per matched point it observes (a brute-force stand-in for
    ORB-SLAM2's bag-of-words keyframe database, cheap on maps of a few dozen keyframes)."""
    if len(frame) < 10 or not mp.keyframes:
        return []
    pts = np.flatnonzero(~mp.points.bad[: mp.points.n] & (mp.points.nobs[: mp.points.n] > 0))
    if len(pts) == 0:
        return []
    if len(pts) > max_points:  # newest points (deterministic)
        pts = pts[-max_points:]
    step = max(1, len(frame) // 400)
    sample = np.arange(0, len(frame), step)
    dnn, inn = cv2.batchDistance(frame.desc[sample], mp.points.desc[pts], cv2.CV_32S, normType=cv2.NORM_HAMMING, K=1)
    good = (inn[:, 0] >= 0) & (dnn[:, 0] <= TH_LOW)
    matched = np.unique(pts[inn[good, 0]])
    counts = mp.covisible_counts(matched)
    ranked = sorted(
        ((c, k) for k, c in counts.items() if k in mp.keyframes and c >= 5), key=lambda t: (-t[0], -t[1])
    )
    return [k for _, k in ranked[:n]]
