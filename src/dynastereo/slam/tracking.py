"""Tracking (ORB-SLAM2 ``Tracking``): pose of every frame against the map.

Order per frame: constant-velocity prediction + projection matching of the last
frame's points (map points and temporary stereo "visual odometry" points), or, when
that fails, descriptor matching against the reference keyframe with PnP-RANSAC; then
local-map tracking (projection of the points of the covisible keyframes) and
motion-only BA after each matching step; finally the keyframe decision.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from .frame import Frame
from .geometry import desc_u64, inv_T, rotation_consistent, unique_best
from .keyframe import KeyFrame
from .map import Map
from .matcher import TH_HIGH, TH_LOW, keyframe_point_matches, search_by_projection
from .optimizer import optimize_pose, project

log = logging.getLogger("dynastereo.slam")


@dataclass
class TrackParams:
    scales: np.ndarray
    inv_sigma2: np.ndarray
    th_depth_m: float
    min_inliers: int = 20
    max_frames: int = 10
    min_frames: int = 0
    seed: int = 0


def pnp_ransac(
    X: np.ndarray, uv: np.ndarray, K: np.ndarray, seed: int, iterations: int = 200, min_inliers: int = 10
) -> tuple[np.ndarray | None, int]:
    """Prior-free PnP-RANSAC (EPnP, 3 px, fixed seed): ``(T_cw or None, inliers)``; None
    with fewer than ``min_inliers`` inliers."""
    cv2.setRNGSeed(seed)
    okp, rvec, tvec, inl = cv2.solvePnPRansac(
        X.astype(np.float64),
        uv.astype(np.float64),
        K,
        None,
        iterationsCount=iterations,
        reprojectionError=3.0,
        confidence=0.999,
        flags=cv2.SOLVEPNP_EPNP,
    )
    if not okp or inl is None or len(inl) < min_inliers:
        return None, 0 if inl is None else len(inl)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T, len(inl)


class Tracker:
    def __init__(self, params: TrackParams) -> None:
        self.p = params
        self.last: Frame | None = None
        self.velocity: np.ndarray | None = None
        self.ref_kf: KeyFrame | None = None
        self.last_kf_frame = -(10**9)
        self.n_inliers = 0
        self.local_kfs: list[int] = []
        self.method = ""

    # ----------------------------------------------------------------- helpers
    def _optimize(self, mp: Map, frame: Frame) -> int:
        """Motion-only BA on the frame's matches; outliers are unmatched.  Returns the
        number of inlier matches to real map points."""
        idx = np.flatnonzero(frame.matched)
        if len(idx) < 3:
            return 0
        calib = frame.calib
        T, inl = optimize_pose(
            frame.T_cw,
            frame.match_xyz[idx],
            frame.uv[idx],
            frame.u_right[idx],
            self.p.inv_sigma2[frame.octave[idx]],
            calib.K,
            calib.bf,
        )
        frame.T_cw = T
        frame.clear_matches(idx[~inl])
        return int(np.count_nonzero(frame.point_ids[idx[inl]] >= 0))

    def _last_frame_points(self, mp: Map, last: Frame):
        """Points to project from the last frame: its map points (current positions)
        plus temporary points from its close stereo keypoints (``UpdateLastFrame``)."""
        pid = mp.resolve(last.point_ids)
        has_mp = pid >= 0
        # temporary stereo points: closest first, all closer than th_depth, at least 100
        cand = np.flatnonzero((last.depth > 0) & ~has_mp)
        cand = cand[np.argsort(last.depth[cand], kind="stable")]
        close = last.depth[cand] < self.p.th_depth_m
        n_take = max(int(close.sum()), min(100, len(cand)))
        tmp = cand[:n_take]
        idx_mp = np.flatnonzero(has_mp)
        kp_idx = np.concatenate([idx_mp, tmp])
        X = np.concatenate([mp.pos[pid[idx_mp]], last.unproject(tmp)])
        d64 = np.concatenate([desc_u64(mp.desc[pid[idx_mp]]), last.desc64[tmp]])
        pts = np.concatenate([pid[idx_mp], np.full(len(tmp), -1, np.int64)])
        return kp_idx, X, d64, pts

    def _assign(self, frame: Frame, kp: np.ndarray, pts: np.ndarray, X: np.ndarray) -> None:
        frame.point_ids[kp] = pts
        frame.match_xyz[kp] = X
        frame.outlier[kp] = False

    # ------------------------------------------------------- tracking methods
    def track_motion_model(self, mp: Map, frame: Frame) -> bool:
        last = self.last
        if last is None or self.velocity is None:
            return False
        frame.T_cw = self.velocity @ last.T_cw
        kp_last, X, d64, pts = self._last_frame_points(mp, last)
        if len(X) == 0:
            return False
        c = frame.calib
        K = c.K
        Xc, u, v, ur = project(frame.T_cw, X, K[0, 0], K[1, 1], K[0, 2], K[1, 2], c.bf)
        inside = (Xc[:, 2] > 0) & (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
        # forward / backward motion restricts the search levels
        T_lc = last.T_cw @ inv_T(frame.T_cw)
        tz = T_lc[2, 3]
        oct_last = last.octave[kp_last].astype(np.int64)
        if tz > c.baseline:
            lo, hi = oct_last, np.full(len(oct_last), 99)
        elif -tz > c.baseline:
            lo, hi = np.zeros(len(oct_last), np.int64), oct_last
        else:
            lo, hi = oct_last - 1, oct_last + 1
        sel = np.flatnonzero(inside)
        matches = None
        for th in (7.0, 14.0):
            radius = th * self.p.scales[oct_last[sel]]
            m = search_by_projection(
                frame.grid,
                frame.octave,
                frame.desc64,
                frame.u_right,
                None,
                u[sel],
                v[sel],
                radius,
                d64[sel],
                min_level=lo[sel],
                max_level=hi[sel],
                u_right=ur[sel],
                th_dist=TH_HIGH,
                angle_check=(last.angle[kp_last[sel]], frame.angle),
            )
            matches = m
            if len(m.query) >= 20:
                break
        if matches is None or len(matches.query) < 20:
            return False
        q = sel[matches.query]
        frame.clear_matches(np.arange(len(frame)))
        self._assign(frame, matches.kp, pts[q], X[q])
        n = self._optimize(mp, frame)
        n_all = int(frame.matched.sum())
        return n_all >= 10 if n < 10 else True

    def _pnp(self, X: np.ndarray, uv: np.ndarray, frame: Frame) -> tuple[np.ndarray | None, int]:
        return pnp_ransac(X, uv, frame.calib.K, self.p.seed)

    def track_reference_keyframe(self, mp: Map, frame: Frame, T_guess: np.ndarray | None) -> bool:
        """Descriptor matching against the reference keyframe's map points, pose from
        PnP-RANSAC (else ``T_guess``), then motion-only BA."""
        kf = self.ref_kf
        if kf is None:
            return False
        ki, pts = keyframe_point_matches(mp, kf, frame)
        if len(ki) < 15:
            return False
        X = mp.pos[pts]
        T, _ = self._pnp(X, frame.uv[ki], frame)
        if T is None:
            if T_guess is None:
                return False
            T = T_guess.copy()
        frame.T_cw = T
        frame.clear_matches(np.arange(len(frame)))
        self._assign(frame, ki, pts, X)
        n = self._optimize(mp, frame)
        return n >= 10

    # --------------------------------------------------------------- relocalisation
    def candidate_keyframes(self, mp: Map, frame: Frame, n: int = 3, max_points: int = 20000) -> list[int]:
        """Keyframes of the map most likely to see the frame's place: a sample of the
        frame's descriptors is matched to the map's points (nearest, <= TH_LOW) and every
        keyframe gets a vote per matched point it observes (a brute-force stand-in for
        ORB-SLAM2's bag-of-words keyframe database, cheap on maps of a few dozen keyframes)."""
        if len(frame) < 10 or not mp.keyframes:
            return []
        pts = np.flatnonzero(~mp.bad[: mp.n] & (mp.nobs[: mp.n] > 0))
        if len(pts) == 0:
            return []
        if len(pts) > max_points:  # newest points (deterministic)
            pts = pts[-max_points:]
        step = max(1, len(frame) // 400)
        sample = np.arange(0, len(frame), step)
        dnn, inn = cv2.batchDistance(frame.desc[sample], mp.desc[pts], cv2.CV_32S, normType=cv2.NORM_HAMMING, K=1)
        good = (inn[:, 0] >= 0) & (dnn[:, 0] <= TH_LOW)
        matched = np.unique(pts[inn[good, 0]])
        counts = mp.covisible_counts(matched)
        ranked = sorted(
            ((c, k) for k, c in counts.items() if k in mp.keyframes and c >= 5), key=lambda t: (-t[0], -t[1])
        )
        return [k for _, k in ranked[:n]]

    def relocalise(self, mp: Map, frame: Frame, candidates: list[int]) -> tuple[bool, int]:
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
            self.ref_kf,
            list(self.local_kfs),
            self.n_inliers,
        )
        best: tuple | None = None
        for kid in candidates:
            kf = mp.keyframes.get(kid)
            if kf is None:
                continue
            ki, pts = keyframe_point_matches(mp, kf, frame)
            if len(ki) < 15:
                continue
            X = mp.pos[pts]
            T, _ = self._pnp(X, frame.uv[ki], frame)
            if T is None:
                continue
            frame.T_cw = T
            frame.clear_matches(np.arange(len(frame)))
            self._assign(frame, ki, pts, X)
            if self._optimize(mp, frame) < 10:
                continue
            self.ref_kf = kf
            self.track_local_map(mp, frame, count=False)
            if best is None or self.n_inliers > best[0]:
                best = (
                    self.n_inliers,
                    kid,
                    frame.T_cw.copy(),
                    frame.point_ids.copy(),
                    frame.match_xyz.copy(),
                    frame.outlier.copy(),
                    self.ref_kf,
                    list(self.local_kfs),
                )
        if best is None:
            (frame.T_cw, frame.point_ids, frame.match_xyz, frame.outlier, self.ref_kf, self.local_kfs,
             self.n_inliers) = saved
            return False, -1
        n, kid, frame.T_cw, frame.point_ids, frame.match_xyz, frame.outlier, self.ref_kf, self.local_kfs = best
        self.n_inliers = n
        inl = frame.point_ids[frame.point_ids >= 0]
        mp.found[inl] += 1
        mp.visible[inl] += 1
        return True, kid

    def update_local_keyframes(self, mp: Map, frame: Frame) -> list[int]:
        pid = frame.point_ids
        pts = mp.resolve(pid[pid >= 0])
        counts = mp.covisible_counts(pts[pts >= 0])
        counts = {k: c for k, c in counts.items() if k in mp.keyframes}
        if not counts:
            if self.ref_kf is not None and self.ref_kf.id in mp.keyframes:
                counts = {self.ref_kf.id: 1}
            else:
                return []
        best = max(counts.items(), key=lambda t: (t[1], t[0]))[0]
        self.ref_kf = mp.keyframes[best]
        local = sorted(counts, key=lambda k: (-counts[k], k))[:80]
        seen = set(local)
        for k in list(local):
            if len(local) >= 80:
                break
            for n in mp.keyframes[k].best_covisibles(10):
                if n not in seen and n in mp.keyframes:
                    seen.add(n)
                    local.append(n)
                    break
        self.local_kfs = local
        return local

    def track_local_map(self, mp: Map, frame: Frame, count: bool = True) -> bool:
        """Project the local map's points, match, motion-only BA.  ``count``: update the
        points' visible / found counters (off for relocalisation hypotheses)."""
        local = self.update_local_keyframes(mp, frame)
        if not local:
            return False
        ids = mp.points_of(local)
        # points already matched in this frame: counted visible, not searched again
        has = np.flatnonzero(frame.point_ids >= 0)
        res = mp.resolve(frame.point_ids[has])
        frame.clear_matches(has[res < 0])
        frame.point_ids[has[res >= 0]] = res[res >= 0]
        already = frame.point_ids[frame.point_ids >= 0]
        if count:
            mp.visible[already] += 1
        ids = ids[~np.isin(ids, already)]
        if len(ids):
            f = mp.in_frustum(ids, frame.T_cw, frame.T_wc[:3, 3], frame.calib)
            sel, u, v, ur, dist, cosv, Xw = f.sel, f.u, f.v, f.ur, f.dist, f.cosv, f.Xw
            if count:
                mp.visible[ids[sel]] += 1
            if len(sel):
                lev = mp.predict_level(ids[sel], dist[sel])
                r = np.where(cosv[sel] > 0.998, 2.5, 4.0) * self.p.scales[lev]
                m = search_by_projection(
                    frame.grid,
                    frame.octave,
                    frame.desc64,
                    frame.u_right,
                    frame.point_ids < 0,
                    u[sel],
                    v[sel],
                    r,
                    desc_u64(mp.desc[ids[sel]]),
                    min_level=lev - 1,
                    max_level=lev,
                    u_right=ur[sel],
                    th_dist=TH_HIGH,
                    ratio=0.8,
                )
                q = sel[m.query]
                self._assign(frame, m.kp, ids[q], Xw[q])
        # refresh the positions of all map-point matches (the map may have moved)
        has = frame.point_ids >= 0
        frame.match_xyz[has] = mp.pos[frame.point_ids[has]]
        n = self._optimize(mp, frame)
        if count:
            mp.found[frame.point_ids[frame.point_ids >= 0]] += 1
        self.n_inliers = n
        return n >= self.p.min_inliers

    # ---------------------------------------------------------- keyframe policy
    def need_new_keyframe(self, mp: Map, frame: Frame) -> bool:
        if self.ref_kf is None:
            return True
        n_kfs = len(mp.keyframes)
        min_obs = 3 if n_kfs > 2 else 2
        ref_pts = self.ref_kf.point_ids[self.ref_kf.point_ids >= 0]
        n_ref = int(np.count_nonzero(mp.nobs[ref_pts] >= min_obs))
        close = (frame.depth > 0) & (frame.depth < self.p.th_depth_m)
        tracked = frame.point_ids >= 0
        n_tracked_close = int(np.count_nonzero(close & tracked))
        n_non_tracked_close = int(np.count_nonzero(close & ~tracked))
        need_close = n_tracked_close < 100 and n_non_tracked_close > 70
        th_ref = 0.4 if n_kfs < 2 else 0.75
        since = frame.index - self.last_kf_frame
        c1a = since >= self.p.max_frames
        c1b = since >= self.p.min_frames  # local mapping is never busy from tracking's view
        c1c = self.n_inliers < n_ref * 0.25 or need_close
        c2 = (self.n_inliers < n_ref * th_ref or need_close) and self.n_inliers > 15
        return bool((c1a or c1b or c1c) and c2)
