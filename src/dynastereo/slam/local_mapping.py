"""Local mapping (ORB-SLAM2 ``LocalMapping``), run for every new keyframe.

1. ``process``: observations of the keyframe -> point normals / descriptors,
   covisibility edges;
2. culling of recently added points (found/visible ratio, observation count);
3. new points by triangulation against the best covisible keyframes (descriptor
   match under the epipolar constraint, parallax / reprojection / scale checks);
4. fusion of duplicated points with the neighbours (``SearchInNeighbors``);
5. local bundle adjustment (``optimizer.local_ba``: one compiled kernel, GIL released)
   in a thread beside tracking (``BARunner``), or inline.  The result of a job submitted
   at frame ``k`` is applied right before frame ``k + lag`` is tracked (waiting for it,
   at most ``slam.ba_wait_s``, if needed), which keeps a run deterministic whatever the
   machine's speed;
6. keyframe culling (90% of the close points seen at the same or finer scale by at
   least 3 other keyframes).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from ..config import SlamConfig
from .geometry import (
    orthonormalize,
    CHI2_MONO,
    CHI2_STEREO,
    desc_u64,
    inv_T,
    rotation_consistent,
    skew,
    triangulate_dlt,
    unique_best,
)
from .keyframe import KeyFrame
from .map import Map
from .kernels.bookkeeping import redundant_points, unique_good, unseen_good
from .kernels.epipolar import epipolar_best
from .matcher import TH_LOW, search_by_projection
from .optimizer import LocalBAProblem, LocalBAResult, reprojection_chi2, run_ba
from .orb import ORBExtractor
from .selfcal import MAX_POINTS, SelfCalibration
from .warmup import warm_up_kernels

log = logging.getLogger("dynastereo.slam")

@dataclass
class MappingStats:
    ba_runs: int = 0
    ba_ms: list[float] = field(default_factory=list)
    ba_wait_ms: list[float] = field(default_factory=list)
    points_triangulated: int = 0
    points_culled: int = 0
    points_fused: int = 0
    keyframes_culled: int = 0


class BAJob:
    """One bundle adjustment solved in its own daemon thread: the compiled kernel
    releases the GIL, so tracking runs beside it.  ``abort`` (read by the kernel between
    iterations) stops it; a daemon thread never keeps the process alive."""

    def __init__(self, problem: LocalBAProblem, ready: threading.Event | None) -> None:
        self.problem = problem
        self.abort = np.zeros(1, np.int64)
        self.error: BaseException | None = None
        self._ready = ready
        self._res: LocalBAResult | None = None
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="local-ba", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            if self._ready is not None:  # the kernel's compile / cache load at start-up
                self._ready.wait()
            if not self.abort[0]:
                self._res = run_ba(self.problem, self.abort)
        except BaseException as e:  # noqa: BLE001 -- reported by the thread that collects it
            self.error = e
        finally:
            self._done.set()

    def done(self) -> bool:
        return self._done.is_set()

    def result(self, timeout: float) -> LocalBAResult | None:
        """The result, or None when it is not done within ``timeout`` s (the job is then
        aborted) or failed (``error``)."""
        if not self._done.wait(timeout):
            self.abort[0] = 1
            return None
        return self._res


class BARunner:
    """Runs bundle adjustments in threads (``thread``) or inline, for every map of a
    System (local BAs, self-calibrating BAs, the loops' full BAs).

    Every wait is bounded: ``wait`` gives a job ``wait_s`` seconds (after the kernel's
    start-up compile / cache load, bounded by ``COMPILE_WAIT_S``); a job not done by then
    is aborted and its result skipped, and a failed one is skipped too.  Each such
    fallback is logged and kept in ``fallbacks`` (``run.json``: ``stats.local_ba_fallbacks``)
    with the frame it happened at."""

    COMPILE_WAIT_S = 600.0

    def __init__(self, mode: str, wait_s: float = 5.0) -> None:
        if mode == "process":  # the former worker process: now a thread
            mode = "thread"
        if mode not in ("thread", "inline", "off"):
            raise ValueError(f"slam.local_ba must be thread, inline or off, got {mode!r}")
        self.mode = mode
        self.wait_s = float(wait_s)
        self.fallbacks: list[dict] = []
        self._jobs: list[BAJob] = []
        self._ready: threading.Event | None = None
        self._warmup: threading.Thread | None = None

    def warm_up(self) -> None:
        """Compile (first run) or load from numba's cache the SLAM's kernels, the BA's
        included (:mod:`.warmup`), in a daemon thread, so that neither the first frames
        nor the first local BA stall on it."""
        if self._ready is not None:
            return
        ready = self._ready = threading.Event()
        ba = self.mode != "off"

        def run() -> None:
            try:
                warm_up_kernels(ba=ba)
            except Exception as e:  # noqa: BLE001 -- the first call reports it again
                log.warning("SLAM kernel warm-up failed: %s", e)
            finally:
                ready.set()

        self._warmup = threading.Thread(target=run, name="slam-warmup", daemon=True)
        self._warmup.start()

    def wait_warm_up(self) -> float:
        """Wait for :meth:`warm_up` to end (at once when it has, or never started);
        returns the seconds waited."""
        t0 = time.perf_counter()
        if self._ready is not None and not self._ready.is_set():
            if not self._ready.wait(2.0):
                log.info("loading the SLAM kernels (the first run after an install compiles them: ~15 s)")
                self._ready.wait()
        return time.perf_counter() - t0

    def submit(self, problem: LocalBAProblem) -> BAJob | LocalBAResult:
        if self.mode == "thread":
            self._jobs = [j for j in self._jobs if not j.done()]
            job = BAJob(problem, self._ready)
            self._jobs.append(job)
            return job
        return run_ba(problem)

    def wait(self, job: BAJob | LocalBAResult, frame: int, what: str = "local",
             wait_s: float | None = None) -> LocalBAResult | None:
        """The job's result, waiting at most ``wait_s`` (default ``self.wait_s``) once the
        kernel is ready; None (recorded in ``fallbacks``) when it is skipped."""
        if isinstance(job, LocalBAResult):
            return job
        t0 = time.perf_counter()
        if self._ready is not None and not self._ready.wait(self.COMPILE_WAIT_S):
            log.warning("local BA kernel still compiling after %.0f s", self.COMPILE_WAIT_S)
        bound = self.wait_s if wait_s is None else float(wait_s)
        res = job.result(bound)
        if res is not None:
            return res
        if job.error is not None:
            reason = f"failed: {type(job.error).__name__}: {job.error}"
        else:
            reason = f"not done within {bound:g} s: aborted"
        waited = time.perf_counter() - t0
        self.fallbacks.append({"frame": int(frame), "ba": what, "reason": reason, "action": "result skipped",
                               "waited_s": round(waited, 3)})
        log.warning("frame %d: %s bundle adjustment %s; its result is skipped", frame, what, reason)
        return None

    def abort(self, job: BAJob | LocalBAResult | None) -> None:
        """Stop a job whose answer will not be read."""
        if isinstance(job, BAJob):
            job.abort[0] = 1

    #: how long shutdown waits for the kernel's threads to end (bounded: a stalled one is left)
    JOIN_S = 10.0

    def shutdown(self) -> None:
        """Abort the jobs still running and wait (at most ``JOIN_S`` s) for their threads
        and for the kernel's start-up load to end: a thread still inside numba/LLVM while
        the interpreter exits aborts the process ("terminate called without an active
        exception") after the outputs were written."""
        for j in self._jobs:
            j.abort[0] = 1
        deadline = time.monotonic() + self.JOIN_S
        threads = [j._thread for j in self._jobs] + ([self._warmup] if self._warmup is not None else [])
        for t in threads:
            t.join(max(0.0, deadline - time.monotonic()))
        self._jobs = []


class LocalMapper:
    """Local mapping of one map.  ``cfg``: the ``slam`` section as loaded; ``orb``: the
    pyramid the keypoints come from (scales, sigma^2); ``selfcal``: the disparity offset
    (:mod:`.selfcal`), whose self-calibrating BA is one of this mapper's BAs."""

    def __init__(self, mp: Map, cfg: SlamConfig, orb: ORBExtractor, th_depth_m: float, runner: BARunner,
                 selfcal: SelfCalibration) -> None:
        self.mp = mp
        self.cfg = cfg
        self.orb = orb
        self.th_depth_m = float(th_depth_m)
        self.runner = runner
        self.selfcal = selfcal
        self.recent = np.zeros(0, np.int64)
        self.stats = MappingStats()
        self._job: BAJob | LocalBAResult | None = None
        self._job_due = 0
        self._job_map = None
        self._job_since: tuple[int, int] | None = None
        self._pending_kf: KeyFrame | None = None
        self._last_frame = 0  # the latest frame position collect saw (fallback records)

    # ---------------------------------------------------------------- pipeline
    def process(self, kf: KeyFrame, new_points: np.ndarray, frame_index: int) -> None:
        mp = self.mp
        pts = kf.point_ids[kf.point_ids >= 0]
        mp.update_points(pts)
        mp.update_connections(kf)
        self.recent = np.concatenate([self.recent, new_points])
        self.cull_points(kf)
        created = self.create_new_points(kf)
        self.recent = np.concatenate([self.recent, created])
        self.fuse(kf)
        mp.update_connections(kf)
        if self.cfg.local_ba != "off":
            if self._job is None:
                self._submit(kf, frame_index)
            else:
                self._pending_kf = kf
        if self.cfg.keyframe_culling:
            self.cull_keyframes(kf)

    def cull_points(self, kf: KeyFrame) -> None:
        mp = self.mp
        r = self.recent
        r = r[~mp.points.bad[r]]
        ratio = mp.points.found_ratio(r)
        age = kf.id - mp.points.first_kf[r]
        bad = (ratio < 0.25) | ((age >= 2) & (mp.points.nobs[r] <= 3))
        if bad.any():
            mp.set_bad(r[bad])
            self.stats.points_culled += int(bad.sum())
        self.recent = r[~bad & (age < 3)]

    # ----------------------------------------------------------- triangulation
    def create_new_points(self, kf1: KeyFrame) -> np.ndarray:
        mp = self.mp
        c = kf1.calib
        K = c.K
        Kinv = np.linalg.inv(K)
        bf, b = c.bf, c.baseline
        created: list[np.ndarray] = []
        C1 = kf1.center
        R1w, t1w = kf1.T_cw[:3, :3], kf1.T_cw[:3, 3]
        ratio_factor = 1.5 * float(self.orb.scales[1] if len(self.orb.scales) > 1 else 1.2)
        for nid in kf1.best_covisibles(self.cfg.triangulation_neighbours):
            kf2 = mp.keyframes.get(nid)
            if kf2 is None:
                continue
            C2 = kf2.center
            if np.linalg.norm(C2 - C1) < b:
                continue
            i1 = np.flatnonzero(kf1.point_ids < 0)
            i2 = np.flatnonzero(kf2.point_ids < 0)
            if len(i1) == 0 or len(i2) == 0:
                continue
            R2w, t2w = kf2.T_cw[:3, :3], kf2.T_cw[:3, 3]
            R21 = R2w @ R1w.T
            t21 = -R21 @ t1w + t2w
            F21 = Kinv.T @ skew(t21) @ R21 @ Kinv
            # a keypoint of kf2 too close to the epipole is ambiguous (both monocular)
            ep = K @ (R2w @ C1 + t2w)
            epipole = (ep[0] / ep[2], ep[1] / ep[2]) if abs(ep[2]) > 1e-9 else None
            # per kf1 keypoint the best descriptor on its epipolar line among its 4 nearest
            # in kf2 (one compiled call a pair)
            o2 = kf2.octave[i2]
            best, bdist = epipolar_best(kf1.desc[i1], kf1.uv[i1], kf1.u_right[i1] < 0, kf2.desc[i2], kf2.uv[i2],
                                        kf2.u_right[i2] < 0, 3.84 * self.orb.sigma2[o2], 100 * self.orb.scales[o2],
                                        F21, epipole, TH_LOW, k_nn=4)
            has = best >= 0
            if not has.any():
                continue
            k1, k2, dist = i1[has], i2[best[has]], bdist[has]
            # then one per kf2 keypoint, rotation consistency
            sel = unique_best(k2, dist)
            k1, k2, dist = k1[sel], k2[sel], dist[sel]
            rot = rotation_consistent(kf1.angle[k1] - kf2.angle[k2])
            k1, k2 = k1[rot], k2[rot]
            if len(k1) == 0:
                continue
            X = self._triangulate(kf1, kf2, k1, k2, Kinv)
            ok = np.isfinite(X[:, 0])
            # in front of both cameras, reprojection error, scale consistency
            for kf, kk in ((kf1, k1), (kf2, k2)):
                chi2, front = reprojection_chi2(
                    kf.T_cw, np.nan_to_num(X), kf.uv[kk], kf.u_right[kk], self.orb.inv_sigma2[kf.octave[kk]], K, bf
                )
                th = np.where(kf.u_right[kk] >= 0, CHI2_STEREO, CHI2_MONO)
                ok &= front & (chi2 <= th)
            Xs = np.nan_to_num(X)
            dist1 = np.linalg.norm(Xs - C1, axis=1)
            dist2 = np.linalg.norm(Xs - C2, axis=1)
            ok &= (dist1 > 0) & (dist2 > 0)
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio_dist = dist2 / dist1
            ratio_oct = self.orb.scales[kf1.octave[k1]] / self.orb.scales[kf2.octave[k2]]
            ok &= ~((ratio_dist * ratio_factor < ratio_oct) | (ratio_dist > ratio_oct * ratio_factor))
            k1, k2, X = k1[ok], k2[ok], X[ok]
            if len(k1) == 0:
                continue
            ids = mp.new_points(X, kf1.desc[k1], kf1.id)
            mp.add_observations(kf1, k1, ids)
            mp.add_observations(kf2, k2, ids)
            created.append(ids)
        out = np.concatenate(created) if created else np.zeros(0, np.int64)
        # normals, distances, descriptors of the new points at once (each depends only on
        # its own two observations, which later pairs cannot touch)
        mp.update_points(out)
        self.stats.points_triangulated += len(out)
        return out

    def _triangulate(self, kf1: KeyFrame, kf2: KeyFrame, k1: np.ndarray, k2: np.ndarray, Kinv: np.ndarray):
        """ORB-SLAM2's choice: linear triangulation when the rays' parallax beats the
        stereo parallax, else the stereo point of the keyframe with more parallax."""
        c = kf1.calib
        b = c.baseline
        xn1 = np.c_[kf1.uv[k1], np.ones(len(k1))] @ Kinv.T
        xn2 = np.c_[kf2.uv[k2], np.ones(len(k2))] @ Kinv.T
        ray1 = xn1 @ kf1.T_cw[:3, :3]  # R_wc @ xn
        ray2 = xn2 @ kf2.T_cw[:3, :3]
        cos_rays = (ray1 * ray2).sum(axis=1) / (np.linalg.norm(ray1, axis=1) * np.linalg.norm(ray2, axis=1))
        st1 = kf1.u_right[k1] >= 0
        st2 = kf2.u_right[k2] >= 0
        with np.errstate(divide="ignore", invalid="ignore"):
            cos_st1 = np.where(st1, np.cos(2 * np.arctan2(b / 2, kf1.depth[k1])), 2.0)
            cos_st2 = np.where(st2, np.cos(2 * np.arctan2(b / 2, kf2.depth[k2])), 2.0)
        cos_st = np.minimum(cos_st1, cos_st2)
        X = np.full((len(k1), 3), np.nan)
        use_tri = (cos_rays < cos_st) & (cos_rays > 0) & (st1 | st2 | (cos_rays < 0.9998))
        if use_tri.any():
            X[use_tri] = triangulate_dlt(
                kf1.T_cw[:3], kf2.T_cw[:3], xn1[use_tri, :2], xn2[use_tri, :2]
            )
        use1 = ~use_tri & st1 & (cos_st1 < cos_st2)
        if use1.any():
            X[use1] = kf1.unproject(k1[use1])
        use2 = ~use_tri & ~use1 & st2 & (cos_st2 < cos_st1)
        if use2.any():
            X[use2] = kf2.unproject(k2[use2])
        return X

    # ------------------------------------------------------------------ fusion
    def _fuse_into(self, target: KeyFrame, pts: np.ndarray) -> int:
        """Project ``pts`` into ``target``; merge with / attach to the matched keypoints."""
        mp = self.mp
        pts = pts[unseen_good(pts, mp.points.bad, target.point_ids)]
        if len(pts) == 0:
            return 0
        f = mp.in_frustum(pts, target.T_cw, target.center, target.calib)
        sel, u, v, ur, dist = f.sel, f.u, f.v, f.ur, f.dist
        if len(sel) == 0:
            return 0
        lev = mp.predict_level(pts[sel], dist[sel])
        r = 3.0 * self.orb.scales[lev]
        m = search_by_projection(
            target.grid,
            target.octave,
            target.desc64,
            target.u_right,
            None,
            u[sel],
            v[sel],
            r,
            desc_u64(mp.points.desc[pts[sel]]),
            min_level=lev - 1,
            max_level=lev,
            u_right=ur[sel],
            th_dist=TH_LOW,
            reproj_check=(target.uv, self.orb.inv_sigma2[target.octave]),
        )
        if len(m.query) == 0:
            return 0
        src = pts[sel[m.query]]
        kp = m.kp
        existing = target.point_ids[kp]
        has = existing >= 0
        # existing point: the one with more observations survives
        e, s_ = existing[has], src[has]
        keep_src = mp.points.nobs[s_] > mp.points.nobs[e]
        mp.replace(np.where(keep_src, e, s_), np.where(keep_src, s_, e))
        mp.add_observations(target, kp[~has], src[~has])
        return len(kp)

    def fuse(self, kf: KeyFrame) -> None:
        mp = self.mp
        n = self.cfg.fuse_neighbours
        if n <= 0:
            return
        targets: list[int] = []
        for k in kf.best_covisibles(n):
            if k in mp.keyframes and k not in targets:
                targets.append(k)
        for k in list(targets):
            for k2 in mp.keyframes[k].best_covisibles(5):
                if k2 != kf.id and k2 in mp.keyframes and k2 not in targets:
                    targets.append(k2)
        fused = 0
        for k in targets:
            fused += self._fuse_into(mp.keyframes[k], kf.point_ids[kf.point_ids >= 0])
        cand = [mp.keyframes[k].point_ids for k in targets if k in mp.keyframes]
        if cand:
            # (bad points would be dropped by _fuse_into as well)
            fused += self._fuse_into(kf, unique_good(np.concatenate(cand), mp.points.bad))
        self.stats.points_fused += fused
        mp.update_points(kf.point_ids[kf.point_ids >= 0])
        for k in targets:
            if k in mp.keyframes:
                mp.update_connections(mp.keyframes[k])

    # -------------------------------------------------------------- local BA
    def build_problem(self, kf: KeyFrame) -> LocalBAProblem | None:
        mp = self.mp
        p = self.cfg
        local = [kf.id] + [k for k in kf.best_covisibles() if k in mp.keyframes][: p.ba_max_keyframes - 1]
        pts = mp.points_of(local)
        if len(pts) == 0:
            return None
        rows = mp.obs.rows_of(pts)
        okf = mp.obs.kf[rows]
        is_local = np.isin(okf, local)
        others, counts = np.unique(okf[~is_local], return_counts=True)
        order = np.lexsort((others, -counts))
        fixed_ids = [int(k) for k in others[order][: p.ba_max_fixed] if int(k) in mp.keyframes]
        origin = min(mp.keyframes)
        if not fixed_ids or origin in local:
            # gauge: the map's first keyframe stays fixed (ORB-SLAM2 fixes keyframe 0)
            if origin in local:
                local.remove(origin)
                fixed_ids = [origin] + fixed_ids
            elif not fixed_ids:
                oldest = min(local)
                local.remove(oldest)
                fixed_ids = [oldest]
        return self._problem(kf, local, fixed_ids, pts, rows)

    def build_selfcal_problem(self, kf: KeyFrame) -> LocalBAProblem | None:
        """BA over all keyframes of the map (the first one fixed) with the disparity
        offset as an extra unknown (``optimizer.self_calibrating_ba``)."""
        mp = self.mp
        ids = sorted(mp.keyframes)
        if len(ids) < 3:
            return None
        pts = mp.points_of(ids)
        if len(pts) == 0:
            return None
        # the offset shows in points seen from several keyframes: the most observed
        # ones, at most selfcal.MAX_POINTS (the three solves stay cheap)
        rows = mp.obs.rows_of(pts)
        n_kf = np.bincount(np.searchsorted(pts, mp.obs.pt[rows]), minlength=len(pts))
        order = np.lexsort((pts, -n_kf))
        keep = np.sort(order[: MAX_POINTS][n_kf[order[:MAX_POINTS]] >= 2])
        pts = pts[keep]
        prob = self._problem(kf, ids[1:], ids[:1], pts, mp.obs.rows_of(pts))
        if prob is not None:
            self.selfcal.prepare(prob)
            # robust iterations only: the three solves' costs stay over the same observations
            prob.iterations, prob.refine_iterations = max(prob.iterations, 5), 0
        return prob

    def build_global_problem(self, kf: KeyFrame) -> LocalBAProblem | None:
        """BA over all keyframes and their points, the map's first keyframe fixed (the
        full BA after a loop; the final BA of a saved map without self-calibration)."""
        mp = self.mp
        ids = sorted(mp.keyframes)
        if len(ids) < 3:
            return None
        pts = mp.points_of(ids)
        prob = self._problem(kf, ids[1:], ids[:1], pts, mp.obs.rows_of(pts)) if len(pts) else None
        if prob is not None:
            prob.refine_iterations = 0  # robust iterations only (ORB-SLAM2's global BA)
        return prob

    def _problem(
        self, kf: KeyFrame, local: list[int], fixed_ids: list[int], pts: np.ndarray, rows: np.ndarray
    ) -> LocalBAProblem | None:
        mp = self.mp
        okf = mp.obs.kf[rows]
        all_kf = np.array(local + fixed_ids, np.int64)
        rows = rows[np.isin(okf, all_kf)]
        okf = mp.obs.kf[rows]
        okp = mp.obs.kp[rows]
        opt = mp.obs.pt[rows]
        sorted_ids = np.sort(all_kf)
        pos_sorted = np.argsort(all_kf)
        obs_kf = pos_sorted[np.searchsorted(sorted_ids, okf)]
        uv = np.zeros((len(rows), 2))
        ur = np.zeros(len(rows))
        lev = np.zeros(len(rows), np.int64)
        for kfo, s in mp.keyframe_groups(rows):  # gather per keyframe
            k = okp[s]
            uv[s] = kfo.uv[k]
            ur[s] = kfo.u_right[k]
            lev[s] = kfo.octave[k]
        # keep points seen by at least two of these keyframes: a point with a single
        # observation puts no constraint on any pose (and a monocular one has no depth)
        cnt = np.bincount(np.searchsorted(pts, opt), minlength=len(pts))
        keep_pt = cnt >= 2
        keep_row = keep_pt[np.searchsorted(pts, opt)]
        pts = pts[keep_pt]
        rows, obs_kf, opt, uv, ur, lev = rows[keep_row], obs_kf[keep_row], opt[keep_row], uv[keep_row], ur[keep_row], lev[keep_row]
        if len(pts) == 0:
            return None
        obs_pt = np.searchsorted(pts, opt)
        fixed = np.zeros(len(all_kf), bool)
        fixed[len(local) :] = True
        T_wc = np.stack([inv_T(mp.keyframes[int(k)].T_cw) for k in all_kf])
        prob = LocalBAProblem(
            kf_ids=all_kf,
            T_wc=T_wc,
            fixed=fixed,
            pt_ids=pts,
            X=mp.points.pos[pts].copy(),
            obs_kf=obs_kf,
            obs_pt=obs_pt,
            uv=uv,
            ur=ur,
            sigma=self.orb.scales[lev],
            K=kf.calib.K,
            baseline=kf.calib.baseline,
            iterations=self.cfg.ba_iterations,
            refine_iterations=self.cfg.ba_refine_iterations,
        )
        return prob

    def _submit(self, kf: KeyFrame, frame_index: int) -> None:
        prob = None
        if self.selfcal.round_due(len(self.mp.keyframes)):
            prob = self.build_selfcal_problem(kf)
            if prob is not None:
                self.selfcal.start_round()
        if prob is None:
            prob = self.build_problem(kf)
        if prob is None:
            return
        res = self.runner.submit(prob)
        self._job = res
        lag = self.selfcal.lag_frames(prob, self.cfg.ba_lag_frames)
        self._job_due = frame_index + max(0, lag)
        self._job_map = id(self.mp)
        self._job_since = (max(self.mp.keyframes), self.mp.points.n)
        if isinstance(res, LocalBAResult):
            self._apply(res)
            self._job = None

    def optimize_whole_map(self) -> LocalBAResult | None:
        """A final bundle adjustment over every keyframe (inline; the pending local BA is
        applied first): with ``self_calibrate`` the self-calibrating one, which also refines
        the disparity offset over the whole map.  Used before a map is saved."""
        self.collect(0, force=True)
        mp = self.mp
        if len(mp.keyframes) < 3:
            return None
        kf = mp.keyframes[max(mp.keyframes)]
        if self.selfcal.enabled:
            prob = self.build_selfcal_problem(kf)
        else:
            prob = self.build_global_problem(kf)
        if prob is None:
            return None
        prob.iterations, prob.rel_tol = max(prob.iterations, 10), 1e-5
        res = run_ba(prob)
        self._apply(res)
        return res

    def collect(self, frame_index: int, force: bool = False) -> None:
        """Apply the running BA's result if it is due (waits for it)."""
        self._last_frame = max(self._last_frame, frame_index)
        if self._job is None:
            return
        if not force and frame_index < self._job_due:
            return
        t0 = time.perf_counter()
        job = self._job
        res = self.runner.wait(job, self._last_frame, "self-calibrating" if job.problem.offset_grid else "local") \
            if isinstance(job, BAJob) else job
        self.stats.ba_wait_ms.append((time.perf_counter() - t0) * 1e3)
        self._job = None
        if res is not None and self._job_map == id(self.mp):
            self._apply(res, since=self._job_since)
        pending = self._pending_kf
        self._pending_kf = None
        if pending is not None and pending.id in self.mp.keyframes and not force:
            self._submit(pending, frame_index)

    def _apply(self, res: LocalBAResult, since: tuple[int, int] | None = None) -> None:
        """Apply a BA's keyframe poses and points; ``since``: (the newest keyframe id, the
        point count) when it was submitted -- what the map gained while it ran follows
        (:meth:`_carry_newer`)."""
        mp = self.mp
        anchor = since[0] if since is not None and since[0] in mp.keyframes else None
        T_anchor = mp.keyframes[anchor].T_cw.copy() if anchor is not None else None
        self.stats.ba_runs += 1
        self.stats.ba_ms.append(res.ms)
        if res.offset_costs is not None:
            log.info(
                "disparity offset self-calibration: %s (costs %s; %.0f ms)",
                "none" if res.offset is None else f"{res.offset:+.3f} +- {res.offset_sigma:.3f} px",
                ", ".join(f"{x:.0f}" for x in res.offset_costs),
                res.ms,
            )
            if res.offset is not None:
                # the keyframes' stereo observations move to the offset the BA used
                self.selfcal.apply(res.offset, res.offset_sigma, mp)
        for i, k in enumerate(res.kf_ids):
            kf = mp.keyframes.get(int(k))
            if kf is not None:
                kf.T_cw = orthonormalize(inv_T(orthonormalize(res.T_wc[i])))
        ok = mp.points.good(res.pt_ids)
        mp.points.pos[res.pt_ids[ok]] = res.X[ok]
        if T_anchor is not None:
            self._carry_newer(anchor, T_anchor, since[1], res.pt_ids)
        # outlier observations: chi2 above the 95% bound or behind the camera
        pts = res.pt_ids[ok]
        rows = mp.obs.rows_of(pts)
        okp = mp.obs.kp[rows]
        bad_rows: list[tuple[KeyFrame, np.ndarray]] = []
        for kf, s in mp.keyframe_groups(rows):
            if kf is None:
                continue
            kp = okp[s]
            ptk = mp.obs.pt[rows[s]]
            chi2, front = reprojection_chi2(
                kf.T_cw, mp.points.pos[ptk], kf.uv[kp], kf.u_right[kp], self.orb.inv_sigma2[kf.octave[kp]], kf.calib.K, kf.calib.bf
            )
            th = np.where(kf.u_right[kp] >= 0, CHI2_STEREO, CHI2_MONO)
            out = (chi2 > th) | ~front
            if out.any():
                bad_rows.append((kf, kp[out]))
        for kf, kp in bad_rows:
            mp.erase_observations(kf, kp)
        mp.update_points(pts)

    def _carry_newer(self, anchor: int, T_anchor: np.ndarray, n_points: int, ba_points: np.ndarray) -> None:
        """A BA applied frames after it was submitted (on its thread): the keyframes made
        since (ids above ``anchor``, the keyframe it was submitted for) were tracked against
        the map before it, and the points made since (ids from ``n_points`` on, not in the
        BA) from them.  They follow the anchor's correction rigidly (``T_anchor``: its pose
        before), as the frames follow their reference keyframe; left where they were, the
        newest keyframes and the BA's disagreed by the correction (KITTI 06, ``--masker
        none``: one-frame jumps of 0.2-0.4 m where a self-calibrating BA submitted six
        keyframes earlier was applied)."""
        mp = self.mp
        T_new = mp.keyframes[anchor].T_cw
        if np.array_equal(T_new, T_anchor):
            return
        W = inv_T(T_new) @ T_anchor  # old world -> new world, for what hangs on the anchor
        W_inv = inv_T(W)
        for k, kf in mp.keyframes.items():
            if k > anchor:
                kf.T_cw = orthonormalize(kf.T_cw @ W_inv)
        new = np.arange(n_points, mp.points.n, dtype=np.int64)
        new = new[~np.isin(new, ba_points) & mp.points.good(new)]
        if len(new):
            mp.points.transform(new, W)

    # ------------------------------------------------------- keyframe culling
    def cull_keyframes(self, kf: KeyFrame) -> None:
        mp = self.mp
        origin = min(mp.keyframes)
        th_obs = 3
        for k in kf.best_covisibles():
            if k == origin or k == kf.id or k not in mp.keyframes:
                continue
            kf2 = mp.keyframes[k]
            idx = np.flatnonzero(kf2.point_ids >= 0)
            close = (kf2.depth[idx] >= 0) & (kf2.depth[idx] <= self.th_depth_m)
            idx = idx[close]
            n_mps = len(idx)
            if n_mps == 0:
                continue
            pts = kf2.point_ids[idx]
            strong = mp.points.nobs[pts] > th_obs
            idx, pts = idx[strong], pts[strong]
            if len(pts) <= 0.9 * n_mps:
                continue
            rows = mp.obs.rows_of(pts)
            rows = rows[mp.obs.kf[rows] != k]
            lev_other = np.zeros(len(rows), np.int64)
            okp = mp.obs.kp[rows]
            for kf3, s in mp.keyframe_groups(rows):
                if kf3 is not None:
                    lev_other[s] = kf3.octave[okp[s]]
            n_red = redundant_points(pts, kf2.octave[idx].astype(np.int64), mp.obs.pt[rows], lev_other, th_obs)
            if n_red > 0.9 * n_mps:
                self._cull_keyframe(kf2)

    def _cull_keyframe(self, kf: KeyFrame) -> None:
        mp = self.mp
        parents = [k for k in kf.best_covisibles() if k in mp.keyframes and k != kf.id]
        if not parents:
            return
        parent = mp.keyframes[parents[0]]
        mp.culled[kf.id] = (parent.id, kf.T_cw @ inv_T(parent.T_cw))
        mp.set_bad_keyframe(kf)
        self.stats.keyframes_culled += 1

    def shutdown(self) -> None:
        if self._job is not None:
            self.collect(0, force=True)
