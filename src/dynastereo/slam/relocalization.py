"""Relocalization (ORB-SLAM2 ``Tracking::Relocalization``): a prior-free pose of a frame in
the map, when neither the motion model nor the reference keyframe gives a supported one.

Candidate keyframes come from the bag-of-words keyframe database, the one shared with loop
closing (``KeyFrameDatabase.detect_relocalization_candidates``, ORB-SLAM2's
``DetectRelocalizationCandidates``).  For each candidate: descriptor matches, PnP-RANSAC,
motion-only BA and local-map tracking; the hypothesis with most inliers wins
(:func:`relocalize`).  The tracker's state (reference keyframe, local keyframes,
inliers) is left as the winning hypothesis made it.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from .frame import Frame
from .geometry import pnp_ransac
from .keyframe_database import KeyFrameDatabase
from .map import Map
from .matcher import keyframe_point_matches
from .vocabulary import Vocabulary

if TYPE_CHECKING:  # for annotations only: the Tracker imports this module
    from .tracking import Tracker


def relocalize_frame(tracker: Tracker, f: Frame) -> tuple[bool, int]:
    """:func:`relocalize` on the best ``slam.reloc_candidates`` keyframes of the
    bag-of-words database (ORB-SLAM2's ``DetectRelocalizationCandidates``)."""
    t0 = time.perf_counter()
    active, cfg = tracker.active, tracker.cfg
    mp, n = active.map, cfg.reloc_candidates
    found, kid = relocalize(tracker, mp, f, database_candidates(tracker.vocab, active.kfdb, mp, f, n))
    tracker.reloc_ms.append((time.perf_counter() - t0) * 1e3)
    return found, kid


def database_candidates(vocab: Vocabulary, kfdb: KeyFrameDatabase, mp: Map, f: Frame, n: int) -> list[int]:
    """The ``n`` best relocalization candidates of the frame in the keyframe database
    ``kfdb`` (the keyframes of ``mp`` only), best first."""
    bow, _ = vocab.transform(f.desc)
    return [k for k in kfdb.detect_relocalization_candidates(bow, mp.best_covisibles) if k in mp.keyframes][:n]


def relocalize(tracker: Tracker, mp: Map, frame: Frame, candidates: list[int]) -> tuple[bool, int]:
    """Prior-free pose of the frame in the map (ORB-SLAM2 ``Relocalization``): for each
    candidate keyframe (:func:`database_candidates`),
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
