"""Relocalization (ORB-SLAM2 ``Tracking::Relocalization``): a prior-free pose of a frame in
the map, when neither the motion model nor the reference keyframe gives a supported one.

Candidate keyframes come from the bag-of-words keyframe database, the one shared with loop
closing (``KeyFrameDatabase.detect_relocalization_candidates``, ORB-SLAM2's
``DetectRelocalizationCandidates``).  For each candidate: descriptor matches, PnP-RANSAC,
motion-only BA and local-map tracking; the hypothesis with most inliers wins
(``Tracker.relocalize``).  The tracking state (reference keyframe, local keyframes,
inliers) stays the tracker's own: the search is its method, as in ORB-SLAM2, and this
module only ranks the candidates.
"""

from __future__ import annotations

from .frame import Frame
from .keyframe_database import KeyFrameDatabase
from .map import Map
from .vocabulary import Vocabulary


def database_candidates(vocab: Vocabulary, kfdb: KeyFrameDatabase, mp: Map, f: Frame, n: int) -> list[int]:
    """The ``n`` best relocalization candidates of the frame in the keyframe database
    ``kfdb`` (the keyframes of ``mp`` only), best first."""
    bow, _ = vocab.transform(f.desc)
    return [k for k in kfdb.detect_relocalization_candidates(bow, mp.best_covisibles) if k in mp.keyframes][:n]
