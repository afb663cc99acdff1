"""Loop closing (ORB-SLAM2 ``LoopClosing``) for a stereo rig: SE(3), no scale drift.

For every new keyframe (after its local mapping):

1. **Detection** (``DetectLoop``): the keyframe's bag of words is scored against the
   keyframe database; candidates must beat the keyframe's lowest score against its own
   covisible keyframes and lie outside its covisibility neighbourhood
   (``KeyFrameDatabase.detect_loop_candidates``).  A candidate is accepted once its
   covisibility group was a candidate for ``consistency`` consecutive keyframes.
2. **Geometric verification** (``ComputeSim3``; stereo: SE(3)): descriptor matches of
   the candidate's map points to the keyframe's keypoints, PnP-RANSAC, motion-only BA
   (stereo observations), then the map points of the candidate and its covisible
   keyframes projected with that pose for more matches and a second BA; at least
   ``min_inliers`` inliers.
3. **Correction** (``CorrectLoop``): the keyframe and its covisible keyframes move by the
   loop correction, their map points with them; duplicated map points are fused
   (the loop side's points projected into the corrected keyframes); covisibility is
   updated, and the new links across the loop become loop edges.
4. **Essential-graph optimization** with gtsam (``optimizer.optimize_pose_graph``):
   spanning-tree edges (each keyframe to its strongest earlier covisible keyframe),
   covisibility edges of weight >= ``covis_edge_weight``, all loop edges; the loop
   keyframe and the map's first keyframe fixed.  Every map point then follows its
   reference keyframe.
5. **Full bundle adjustment** over the whole map, in the BA thread (the compiled kernel,
   GIL released), applied ``loop_ba_lag_frames`` frames later (waiting at most
   ``loop_ba_wait_s``); keyframes and points made in the
   meantime follow the correction of their neighbours.  A second loop before it is
   applied discards it (ORB-SLAM2 aborts it).

Frame poses are stored relative to their reference keyframes (``System``), so the whole
trajectory, past frames included, follows the corrected keyframes.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from ..config import SlamConfig
from .geometry import desc_u64, inv_T, orthonormalize, pnp_ransac
from .keyframe import KeyFrame
from .local_mapping import LocalMapper
from .map import Map
from .keyframe_database import KeyFrameDatabase
from .matcher import TH_HIGH, keyframe_point_matches, search_by_projection
from .optimizer import LocalBAProblem, LocalBAResult, optimize_pose, optimize_pose_graph
from .vocabulary import BowVector, Vocabulary

log = logging.getLogger("dynastereo.slam")


@dataclass
class LoopEvent:
    """One closed loop (``System.loops()``, ``run.json`` ``loops``)."""

    frame: int  # position (in the order fed) of the frame whose keyframe closed it
    frame_index: int  # that frame's StereoFrame.index
    keyframe: int
    loop_keyframe: int
    loop_frame_index: int  # StereoFrame.index of the loop keyframe's frame
    score: float  # bag-of-words score keyframe / loop keyframe
    matches: int  # descriptor matches to the loop keyframe
    inliers: int  # after projection matching and pose optimization
    correction_m: float  # translation of the keyframe's correction
    correction_deg: float  # rotation of the keyframe's correction
    points_fused: int
    loop_edges: int  # new covisibility links across the loop
    pose_graph_keyframes: int
    pose_graph_edges: int
    pose_graph_ms: float
    correct_ms: float  # whole correction: fusion + pose graph + point update
    full_ba_ms: float | None = None  # set when the full BA is applied
    full_ba_applied: bool = False
    full_ba_iterations: int = 0
    full_ba_cost: tuple[float, float] | None = None  # before / after

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class LoopStats:
    query_ms: list[float] = field(default_factory=list)  # BoW transform + detection per keyframe
    rejected: int = 0  # consistent candidates that failed geometric verification
    full_ba_discarded: int = 0


def _rot_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


class LoopCloser:
    """Loop detection and correction on one map; owns nothing but its loop state.  The
    keyframe database (shared with relocalization) is kept by ``System``."""

    def __init__(
        self,
        mp: Map,
        db: KeyFrameDatabase,
        vocab: Vocabulary,
        mapper: LocalMapper,
        cfg: SlamConfig,
        close_depth_m: float,
        seed: int,
        inv_sigma2: np.ndarray,
        scales: np.ndarray,
        events: list[LoopEvent] | None = None,
        stats: LoopStats | None = None,
    ) -> None:
        self.mp = mp
        self.db = db
        self.vocab = vocab
        self.mapper = mapper
        self.cfg = cfg
        self.close_depth_m = float(close_depth_m)  # "close" stereo points (th_depth baselines)
        self.seed = int(seed)
        self.inv_sigma2 = inv_sigma2
        self.scales = scales
        # shared by the closers of a System's successive maps
        self.events: list[LoopEvent] = [] if events is None else events
        self.stats = LoopStats() if stats is None else stats
        self.loop_edges: list[tuple[int, int]] = []
        self._groups: list[tuple[set[int], int]] = []
        self._last_loop_kf = -(10**9)
        self._ba_job = None  # (job, problem, due frame, loop count)
        self._last_frame = 0  # the latest frame position collect saw (fallback records)

    # ------------------------------------------------------------- detection
    def detect(self, kf: KeyFrame, bow: BowVector) -> list[int]:
        """Consistent loop candidates for ``kf`` (ORB-SLAM2 ``DetectLoop``)."""
        mp = self.mp
        if kf.id < self._last_loop_kf + self.cfg.loop_min_kf_gap or len(mp.keyframes) <= self.cfg.loop_min_kf_gap:
            return []
        connected = [k for k in kf.covis if k in mp.keyframes]
        if not connected:
            return []
        in_db = [k for k in connected if k in self.db]
        min_score = min(self.vocab.score(bow, self.db.bow(k)) for k in in_db) if in_db else 1.0
        # not a loop: the keyframe's covisible keyframes and theirs (the place it is in)
        near = set(connected) | {kf.id}
        for k in connected:
            near.update(mp.keyframes[k].covis)
        cands = self.db.detect_loop_candidates(kf.id, bow, near, min_score, mp.best_covisibles)
        # the last keyframes are the same stretch of road, not a loop
        cands = [c for c in cands if kf.id - c >= 2 * self.cfg.loop_min_kf_gap]
        if not cands:
            self._groups = []
            return []
        new_groups: list[tuple[set[int], int]] = []
        extended = [False] * len(self._groups)
        enough: list[int] = []
        for c in cands:
            group = {c, *mp.best_covisibles(c)}
            consistent = False
            for gi, (g, count) in enumerate(self._groups):
                if group & g:
                    consistent = True
                    cur = count + 1
                    if not extended[gi]:
                        new_groups.append((group, cur))
                        extended[gi] = True
                    if cur >= self.cfg.loop_consistency and c not in enough:
                        enough.append(c)
            if not consistent:
                new_groups.append((group, 0))
        self._groups = new_groups
        return enough

    # ---------------------------------------------------------- verification
    def verify(self, kf: KeyFrame, cand: KeyFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray, int] | None:
        """Corrected ``T_cw`` of ``kf`` from the loop keyframe ``cand``: returns
        ``(T_cw, kf keypoints, loop map points, descriptor matches)`` for the inlier matches,
        or None."""
        mp = self.mp
        ki, pts = keyframe_point_matches(mp, cand, kf)
        n_desc = len(ki)
        if n_desc < self.cfg.loop_min_matches:
            return None
        calib = kf.calib
        T, _ = pnp_ransac(mp.points.pos[pts], kf.uv[ki], calib.K, self.seed, 300, self.cfg.loop_min_matches // 2)
        if T is None:
            return None
        T, ok = self._optimize(T, ki, mp.points.pos[pts], kf)
        ki, pts = ki[ok], pts[ok]
        if len(ki) < self.cfg.loop_min_matches:
            return None
        # more matches: the loop keyframe's neighbourhood projected with the new pose
        cand_pts = mp.points_of([cand.id] + [k for k in cand.covis if k in mp.keyframes])
        cand_pts = cand_pts[~np.isin(cand_pts, pts)]
        if len(cand_pts):
            center = inv_T(T)[:3, 3]
            f = mp.in_frustum(cand_pts, T, center, calib)
            sel = f.sel
            if len(sel):
                lev = mp.predict_level(cand_pts[sel], f.dist[sel])
                free = np.ones(len(kf), bool)
                free[ki] = False
                m = search_by_projection(
                    kf.grid, kf.octave, kf.desc64, kf.u_right, free,
                    f.u[sel], f.v[sel], 10.0 * self.scales[lev], desc_u64(mp.points.desc[cand_pts[sel]]),
                    min_level=lev - 1, max_level=lev + 1, u_right=f.ur[sel], th_dist=TH_HIGH, ratio=None,
                )
                ki = np.concatenate([ki, m.kp])
                pts = np.concatenate([pts, cand_pts[sel[m.query]]])
        T, ok = self._optimize(T, ki, mp.points.pos[pts], kf)
        ki, pts = ki[ok], pts[ok]
        n_close = int(np.count_nonzero((kf.depth[ki] > 0) & (kf.depth[ki] < self.close_depth_m)))
        if len(ki) < self.cfg.loop_min_inliers or n_close < self.cfg.loop_min_close_inliers:
            return None
        return T, ki, pts, n_desc

    def _optimize(self, T: np.ndarray, ki: np.ndarray, X: np.ndarray, kf: KeyFrame):
        return optimize_pose(
            T, X, kf.uv[ki], kf.u_right[ki], self.inv_sigma2[kf.octave[ki]], kf.calib.K, kf.calib.bf
        )

    # ------------------------------------------------------------ the pipeline
    def process(self, kf: KeyFrame, frame_pos: int) -> LoopEvent | None:
        """Detect, verify and correct a loop for the new keyframe ``kf`` (its BoW is
        added to the database in any case).  Returns the loop closed, if any."""
        t0 = time.perf_counter()
        bow, _ = self.vocab.transform(kf.desc)
        self._sync_db()
        cands = self.detect(kf, bow)
        self.stats.query_ms.append((time.perf_counter() - t0) * 1e3)
        event = None
        for cid in cands[: self.cfg.loop_max_verify]:
            cand = self.mp.keyframes.get(cid)
            if cand is None:
                continue
            found = self.verify(kf, cand)
            if found is None:
                self.stats.rejected += 1
                continue
            T_new, ki, pts, n_desc = found
            event = self.correct(kf, cand, T_new, ki, pts, frame_pos, self.vocab.score(bow, self.db.bow(cid)), n_desc)
            break
        self.db.add(kf.id, bow)
        return event

    def _sync_db(self) -> None:
        """Culled keyframes leave the database."""
        for k in [k for k in self.db.ids() if k not in self.mp.keyframes]:
            self.db.erase(k)

    # -------------------------------------------------------------- correction
    def correct(
        self,
        kf: KeyFrame,
        loop: KeyFrame,
        T_new: np.ndarray,
        ki: np.ndarray,
        loop_pts: np.ndarray,
        frame_pos: int,
        score: float,
        n_desc: int,
    ) -> LoopEvent:
        mp = self.mp
        t0 = time.perf_counter()
        self._settle_bundle_adjustments(frame_pos)
        # 1. the keyframe and its neighbours move by the correction, their points with them
        T_old_all = {k: k_.T_cw.copy() for k, k_ in mp.keyframes.items()}
        D = inv_T(kf.T_cw) @ T_new  # T_i_new = T_i_old @ D for every connected keyframe
        connected = [kf.id] + [k for k in kf.covis if k in mp.keyframes]
        for k in connected:
            mp.keyframes[k].T_cw = orthonormalize(mp.keyframes[k].T_cw @ D)
        pts = mp.points_of(connected)
        mp.points.transform(pts, inv_T(D))
        fused = self._fuse_loop(kf, loop, ki, loop_pts, connected)
        new_links = self._new_links(kf, loop, connected)
        # 4. essential graph
        t_pg = time.perf_counter()
        n_kf, n_edges = self._optimize_essential_graph(kf, loop, T_old_all, new_links)
        pg_ms = (time.perf_counter() - t_pg) * 1e3
        self.loop_edges.extend(new_links)
        self._last_loop_kf = kf.id
        self._groups = []
        dT = T_new @ inv_T(T_old_all[kf.id])
        event = LoopEvent(
            frame=frame_pos,
            frame_index=kf.frame_index,
            keyframe=kf.id,
            loop_keyframe=loop.id,
            loop_frame_index=loop.frame_index,
            score=float(score),
            matches=int(n_desc),
            inliers=int(len(ki)),
            correction_m=float(np.linalg.norm(inv_T(T_new)[:3, 3] - inv_T(T_old_all[kf.id])[:3, 3])),
            correction_deg=_rot_deg(dT[:3, :3]),
            points_fused=fused,
            loop_edges=len(new_links),
            pose_graph_keyframes=n_kf,
            pose_graph_edges=n_edges,
            pose_graph_ms=pg_ms,
            correct_ms=(time.perf_counter() - t0) * 1e3,
        )
        self.events.append(event)
        log.info(
            "loop closed: keyframe %d (frame %d) with keyframe %d (frame %d): %d inliers, correction %.2f m / %.2f deg; "
            "%d points fused; essential graph of %d keyframes / %d edges in %.0f ms",
            kf.id, kf.frame_index, loop.id, loop.frame_index, event.inliers, event.correction_m,
            event.correction_deg, fused, n_kf, n_edges, pg_ms,
        )
        if self.cfg.loop_full_ba and self.cfg.mapping_on:
            self._submit_full_ba(kf, frame_pos)
        return event

    def _settle_bundle_adjustments(self, frame_pos: int) -> None:
        """Before a correction: the local BA in flight (solved on the poses before the loop)
        is applied; a full BA still running belongs to the map before this loop: dropped."""
        self.mapper.collect(frame_pos, force=True)
        if self._ba_job is not None:
            job = self._ba_job[0]
            self._ba_job = None
            self.stats.full_ba_discarded += 1
            self.mapper.runner.abort(job)  # its answer is never read: stop it now

    def _fuse_loop(self, kf: KeyFrame, loop: KeyFrame, ki: np.ndarray, loop_pts: np.ndarray,
                   connected: list[int]) -> int:
        """2. Fusion: the verified matches, then the loop side's points in every connected
        keyframe.  Returns the points fused."""
        mp = self.mp
        cur = kf.point_ids[ki]
        has = cur >= 0
        mp.replace(cur[has], loop_pts[has])
        fused = int(has.sum())
        mp.add_observations(kf, ki[~has], loop_pts[~has])
        loop_side = [loop.id] + [k for k in loop.covis if k in mp.keyframes and k not in connected]
        side_pts = mp.points_of(loop_side)
        for k in connected:
            if k in mp.keyframes:
                fused += self.mapper._fuse_into(mp.keyframes[k], side_pts)
        return fused

    def _new_links(self, kf: KeyFrame, loop: KeyFrame, connected: list[int]) -> list[tuple[int, int]]:
        """3. Covisibility of the connected keyframes again, and the new links across the
        loop (at least keyframe -- loop keyframe)."""
        mp = self.mp
        before = {k: set(mp.keyframes[k].covis) for k in connected if k in mp.keyframes}
        for k in before:
            mp.update_connections(mp.keyframes[k])
        new_links: list[tuple[int, int]] = []
        conn = set(connected)
        for k in before:
            for j in mp.keyframes[k].covis:
                if j not in before[k] and j not in conn:
                    new_links.append((k, j))
        if not any(j == loop.id or k == loop.id for k, j in new_links):
            new_links.append((kf.id, loop.id))
        return new_links

    def _optimize_essential_graph(
        self, kf: KeyFrame, loop: KeyFrame, T_old: dict[int, np.ndarray], new_links: list[tuple[int, int]]
    ) -> tuple[int, int]:
        mp = self.mp
        ids = sorted(mp.keyframes)
        pos = {k: i for i, k in enumerate(ids)}
        T_init = np.stack([mp.keyframes[k].T_cw for k in ids])  # corrected for the connected ones
        T_wc = np.stack([inv_T(T) for T in T_init])
        T_wc_old = {k: inv_T(T_old[k]) for k in ids if k in T_old}
        edges: dict[tuple[int, int], np.ndarray] = {}

        def rel(a: int, b: int, source: dict[int, np.ndarray] | None) -> np.ndarray:
            if source is not None and a in source and b in source:
                return inv_T(source[a]) @ source[b]
            return inv_T(T_wc[pos[a]]) @ T_wc[pos[b]]

        for k in ids:
            kfo = mp.keyframes[k]
            earlier = [(w, j) for j, w in kfo.covis.items() if j < k and j in pos]
            if earlier:  # spanning tree: strongest earlier covisible keyframe
                parent = max(earlier)[1]
            else:
                i = pos[k]
                parent = ids[i - 1] if i > 0 else None
            if parent is not None:
                edges[(parent, k)] = rel(parent, k, T_wc_old)
            for j, w in kfo.covis.items():
                if j < k and j in pos and w >= self.cfg.loop_covis_edge_weight and (j, k) not in edges:
                    edges[(j, k)] = rel(j, k, T_wc_old)
        for a, b in self.loop_edges:  # earlier loops, as they stand now
            if a in pos and b in pos:
                edges[(min(a, b), max(a, b))] = rel(min(a, b), max(a, b), T_wc_old)
        for a, b in new_links:  # this loop: from the corrected poses
            if a in pos and b in pos:
                edges[(min(a, b), max(a, b))] = rel(min(a, b), max(a, b), None)
        keys = list(edges)
        e = np.array([(pos[a], pos[b]) for a, b in keys], np.int64).reshape(-1, 2)
        meas = np.stack([edges[k] for k in keys]) if keys else np.zeros((0, 4, 4))
        fixed = np.array(sorted({pos[loop.id], 0}), np.int64)
        T_opt, _, _, _ = optimize_pose_graph(T_wc, e, meas, fixed)
        # keyframes, then every point with its reference keyframe's correction
        T_cw_new = np.stack([orthonormalize(inv_T(T)) for T in T_opt])
        M = np.einsum("kij,kjl->kil", T_opt, T_init)  # world(init) -> world(new) per keyframe
        for i, k in enumerate(ids):
            mp.keyframes[k].T_cw = T_cw_new[i]
        self._move_points(ids, M)
        return len(ids), len(keys)

    def _move_points(self, ids: list[int], M: np.ndarray, pts: np.ndarray | None = None) -> None:
        """Points ``pts`` (default: all good ones) follow the correction ``M[i]`` (4x4, old
        world -> new world) of their reference keyframe ``ids[i]`` (sorted ids; points
        whose reference is unknown stay)."""
        mp = self.mp
        if pts is None:
            pts = mp.points.good_ids()
        ref = mp.points.ref_kf[pts]
        sorted_ids = np.asarray(ids, np.int64)
        loc = np.searchsorted(sorted_ids, ref)
        ok = (loc < len(sorted_ids)) & (sorted_ids[np.minimum(loc, len(sorted_ids) - 1)] == ref)
        mp.points.transform(pts[ok], M[loc[ok]])

    # ----------------------------------------------------------------- full BA
    def _submit_full_ba(self, kf: KeyFrame, frame_pos: int) -> None:
        prob = self.mapper.build_global_problem(kf)
        if prob is None:
            return
        prob.iterations = self.cfg.loop_full_ba_iterations
        prob.rel_tol = 1e-5
        job = self.mapper.runner.submit(prob)
        self._ba_job = (job, prob, frame_pos + max(0, self.cfg.loop_ba_lag_frames), len(self.events))

    def collect(self, frame_pos: int, force: bool = False) -> None:
        """Apply the full BA when it is due (waits for it, at most ``loop_ba_wait_s``)."""
        self._last_frame = max(self._last_frame, frame_pos)
        if self._ba_job is None:
            return
        job, prob, due, n_loops = self._ba_job
        if not force and frame_pos < due:
            return
        self._ba_job = None
        res = self.mapper.runner.wait(job, self._last_frame, "full (loop)", self.cfg.loop_ba_wait_s)
        if res is None:
            return
        if n_loops != len(self.events):
            self.stats.full_ba_discarded += 1
            return
        # a local BA in flight was solved on the poses before this result: apply it first
        self.mapper.collect(frame_pos, force=True)
        self._apply_full_ba(prob, res)
        ev = self.events[-1]
        ev.full_ba_ms, ev.full_ba_applied, ev.full_ba_iterations = res.ms, True, res.iterations
        ev.full_ba_cost = (res.error_before, res.error_after)
        log.info("full BA after the loop applied: %d keyframes, %d points, %.0f ms", len(res.kf_ids), len(res.pt_ids), res.ms)

    def _apply_full_ba(self, prob: LocalBAProblem, res: LocalBAResult) -> None:
        mp = self.mp
        ids = sorted(mp.keyframes)
        in_res = {int(k): i for i, k in enumerate(res.kf_ids)}
        T_in = {int(k): inv_T(prob.T_wc[i]) for i, k in enumerate(prob.kf_ids)}
        T_before = {k: mp.keyframes[k].T_cw.copy() for k in ids}
        for k in ids:
            kfo = mp.keyframes[k]
            if k in in_res:
                kfo.T_cw = orthonormalize(inv_T(res.T_wc[in_res[k]]))
                continue
            # made since the BA was submitted: follows its strongest neighbour in the result
            nbs = [j for j in kfo.best_covisibles() if j in in_res]
            if not nbs:
                continue
            j = nbs[0]
            D = inv_T(T_in[j]) @ inv_T(res.T_wc[in_res[j]])
            kfo.T_cw = orthonormalize(kfo.T_cw @ D)
        # points of the result take its positions; the others follow their reference keyframe
        ok = mp.points.good(res.pt_ids)
        M = np.stack([inv_T(mp.keyframes[k].T_cw) @ T_before[k] for k in ids])
        in_prob = np.zeros(mp.points.n, bool)
        in_prob[res.pt_ids[ok]] = True
        self._move_points(ids, M, np.flatnonzero(~mp.points.bad[: mp.points.n] & ~in_prob))
        mp.points.pos[res.pt_ids[ok]] = res.X[ok]

    def shutdown(self) -> None:
        if self._ba_job is not None:
            self.collect(0, force=True)
