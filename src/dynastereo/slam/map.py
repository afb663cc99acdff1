"""The map: keyframes and map points, map points stored array-wise.

Map points are rows of growable numpy arrays (position, descriptor, viewing normal,
scale-invariance distance range, observation count, visible/found counters, ...);
a point's id is its row and is never reused.  Observations are rows of a table
``(keyframe id, keypoint index, point id)`` with an alive flag; each keyframe keeps,
per keypoint, its point id and its observation row.  Everything that touches many
points (projection, normals, descriptors, culling) works on these arrays at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import desc_u64
from .keyframe import KeyFrame


@dataclass
class Frustum:
    """Result of :meth:`Map.in_frustum`: ``sel`` indexes the visible points; the other
    arrays are per queried point (world position, projection, right u, distance, cos)."""

    sel: np.ndarray
    Xw: np.ndarray
    u: np.ndarray
    v: np.ndarray
    ur: np.ndarray
    dist: np.ndarray
    cosv: np.ndarray

COVIS_MIN_WEIGHT = 15  # ORB-SLAM2: covisibility edge when >= 15 shared points


def _grow(a: np.ndarray, n: int, fill=0) -> np.ndarray:
    cap = len(a)
    if n <= cap:
        return a
    new_cap = max(n, 2 * cap)
    out = np.full((new_cap,) + a.shape[1:], fill, dtype=a.dtype)
    out[:cap] = a
    return out


class Map:
    def __init__(self, scales: np.ndarray, capacity: int = 4096) -> None:
        self.scales = np.asarray(scales, np.float64)
        self.n_levels = len(self.scales)
        self.log_scale = float(np.log(self.scales[1])) if self.n_levels > 1 else 1.0
        c = capacity
        self.n = 0
        self.pos = np.zeros((c, 3))
        self.desc = np.zeros((c, 32), np.uint8)
        self.normal = np.zeros((c, 3))
        self.min_dist = np.zeros(c)
        self.max_dist = np.zeros(c)
        self.nobs = np.zeros(c, np.int32)  # ORB-SLAM2 count: stereo observation = 2
        self.visible = np.zeros(c, np.int32)
        self.found = np.zeros(c, np.int32)
        self.first_kf = np.zeros(c, np.int64)
        self.ref_kf = np.zeros(c, np.int64)
        self.bad = np.zeros(c, bool)
        self.replaced = np.full(c, -1, np.int64)
        # observation table
        self.m = 0
        self.obs_kf = np.zeros(c * 4, np.int64)
        self.obs_kp = np.zeros(c * 4, np.int64)
        self.obs_pt = np.zeros(c * 4, np.int64)
        self.obs_alive = np.zeros(c * 4, bool)
        # per-point linked lists of observation rows (newest first): head[pt], next_row[row]
        self.head = np.full(c, -1, np.int64)
        self.next_row = np.full(c * 4, -1, np.int64)
        self.keyframes: dict[int, KeyFrame] = {}
        # culled keyframes: id -> (parent id, T_c_parent), to keep frame poses that refer to them
        self.culled: dict[int, tuple[int, np.ndarray]] = {}
        self.next_kf_id = 0

    # ------------------------------------------------------------------ points
    @property
    def desc64(self) -> np.ndarray:
        return desc_u64(self.desc[: self.n])

    def good(self, ids: np.ndarray) -> np.ndarray:
        ids = np.asarray(ids, np.int64)
        return (ids >= 0) & ~self.bad[np.maximum(ids, 0)]

    def resolve(self, ids: np.ndarray) -> np.ndarray:
        """Follow ``replaced`` links (fused points); -1 for bad points."""
        ids = np.asarray(ids, np.int64).copy()
        for _ in range(8):
            ok = ids >= 0
            r = np.where(ok, self.replaced[np.maximum(ids, 0)], -1)
            mv = ok & (r >= 0)
            if not mv.any():
                break
            ids[mv] = r[mv]
        ok = ids >= 0
        ids[ok & self.bad[np.maximum(ids, 0)]] = -1
        return ids

    def new_points(self, pos: np.ndarray, desc: np.ndarray, kf_id: int) -> np.ndarray:
        k = len(pos)
        n0, n1 = self.n, self.n + k
        for name, fill in (
            ("pos", 0),
            ("desc", 0),
            ("normal", 0),
            ("min_dist", 0),
            ("max_dist", 0),
            ("nobs", 0),
            ("visible", 0),
            ("found", 0),
            ("first_kf", 0),
            ("ref_kf", 0),
            ("bad", False),
            ("replaced", -1),
            ("head", -1),
        ):
            setattr(self, name, _grow(getattr(self, name), n1, fill))
        self.pos[n0:n1] = pos
        self.desc[n0:n1] = desc
        self.nobs[n0:n1] = 0
        self.visible[n0:n1] = 1
        self.found[n0:n1] = 1
        self.first_kf[n0:n1] = kf_id
        self.ref_kf[n0:n1] = kf_id
        self.bad[n0:n1] = False
        self.replaced[n0:n1] = -1
        self.head[n0:n1] = -1
        self.n = n1
        return np.arange(n0, n1, dtype=np.int64)

    # ------------------------------------------------------------ observations
    def add_observations(self, kf: KeyFrame, kp: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """Add observations (kf, kp[i]) -> pts[i]; skips keypoints already used, points
        already observed by ``kf``, duplicates and bad points.  Returns the kept mask."""
        kp = np.asarray(kp, np.int64)
        pts = np.asarray(pts, np.int64)
        keep = (kf.point_ids[kp] < 0) & self.good(pts)
        keep &= ~np.isin(pts, kf.point_ids[kf.point_ids >= 0])
        if keep.any():
            # one keypoint per point and one point per keypoint
            idx = np.flatnonzero(keep)
            _, first = np.unique(pts[idx], return_index=True)
            idx = idx[first]
            _, first = np.unique(kp[idx], return_index=True)
            idx = idx[first]
            keep[:] = False
            keep[idx] = True
        kp_k, pt_k = kp[keep], pts[keep]
        k = len(kp_k)
        if k == 0:
            return keep
        r0, r1 = self.m, self.m + k
        self.obs_kf = _grow(self.obs_kf, r1)
        self.obs_kp = _grow(self.obs_kp, r1)
        self.obs_pt = _grow(self.obs_pt, r1)
        self.obs_alive = _grow(self.obs_alive, r1, False)
        self.next_row = _grow(self.next_row, r1, -1)
        self.next_row[r0:r1] = self.head[pt_k]  # pt_k has no duplicates
        self.head[pt_k] = np.arange(r0, r1)
        self.obs_kf[r0:r1] = kf.id
        self.obs_kp[r0:r1] = kp_k
        self.obs_pt[r0:r1] = pt_k
        self.obs_alive[r0:r1] = True
        self.m = r1
        kf.point_ids[kp_k] = pt_k
        kf.obs_row[kp_k] = np.arange(r0, r1)
        np.add.at(self.nobs, pt_k, 1 + (kf.u_right[kp_k] >= 0))
        return keep

    def erase_observations(self, kf: KeyFrame, kp: np.ndarray, cull: bool = True) -> None:
        """Remove keyframe observations; points left with <= 2 observations become bad."""
        kp = np.asarray(kp, np.int64)
        kp = kp[kf.point_ids[kp] >= 0]
        if len(kp) == 0:
            return
        rows = kf.obs_row[kp]
        pts = kf.point_ids[kp]
        self.obs_alive[rows] = False
        np.add.at(self.nobs, pts, -(1 + (kf.u_right[kp] >= 0)))
        kf.point_ids[kp] = -1
        kf.obs_row[kp] = -1
        if cull:
            weak = np.unique(pts[self.nobs[pts] <= 2])
            if len(weak):
                self.set_bad(weak)
            # points whose reference keyframe lost them: pick another observer
            fix = np.unique(pts[(self.ref_kf[pts] == kf.id) & ~self.bad[pts]])
            if len(fix):
                self._reassign_ref(fix)

    def rows_of(self, pts: np.ndarray) -> np.ndarray:
        """Alive observation rows of the given points (sorted), walking the per-point
        lists: cost proportional to those points' observations, not to the map size."""
        pts = np.asarray(pts, np.int64)
        cur = self.head[np.unique(pts[pts >= 0])]
        out = []
        while len(cur):
            cur = cur[cur >= 0]
            if not len(cur):
                break
            out.append(cur)
            cur = self.next_row[cur]
        if not out:
            return np.zeros(0, np.int64)
        r = np.concatenate(out)
        return np.sort(r[self.obs_alive[r]])

    def set_bad(self, pts: np.ndarray) -> None:
        pts = np.unique(np.asarray(pts, np.int64))
        pts = pts[~self.bad[pts]]
        if len(pts) == 0:
            return
        rows = self.rows_of(pts)
        self.bad[pts] = True
        self.obs_alive[rows] = False
        self.nobs[pts] = 0
        kfs = self.obs_kf[rows]
        kps = self.obs_kp[rows]
        for kid in np.unique(kfs):  # loop over keyframes, not points
            kf = self.keyframes.get(int(kid))
            if kf is None:
                continue
            sel = kps[kfs == kid]
            kf.point_ids[sel] = -1
            kf.obs_row[sel] = -1

    def _reassign_ref(self, pts: np.ndarray) -> None:
        rows = self.rows_of(pts)
        # first alive observer of each point
        order = np.argsort(self.obs_pt[rows], kind="stable")
        r = rows[order]
        p = self.obs_pt[r]
        first = np.ones(len(p), bool)
        first[1:] = p[1:] != p[:-1]
        self.ref_kf[p[first]] = self.obs_kf[r[first]]

    def replace(self, old: np.ndarray, new: np.ndarray) -> None:
        """Fuse points: observations of ``old[i]`` move to ``new[i]``; ``old`` become bad."""
        old = np.asarray(old, np.int64)
        new = np.asarray(new, np.int64)
        ok = (old != new) & self.good(old) & self.good(new)
        old, new = old[ok], new[ok]
        if len(old) == 0:
            return
        _, first = np.unique(old, return_index=True)
        old, new = old[first], new[first]
        # a point cannot be both replaced and a replacement target in one call
        tgt = ~np.isin(new, old)
        old, new = old[tgt], new[tgt]
        if len(old) == 0:
            return
        mapping = np.full(self.n, -1, np.int64)
        mapping[old] = new
        rows = self.rows_of(old)
        kfs = self.obs_kf[rows]
        kps = self.obs_kp[rows]
        # erase the old observations (without culling), then add them for the new points
        self.obs_alive[rows] = False
        for kid in np.unique(kfs):
            kf = self.keyframes.get(int(kid))
            if kf is None:
                continue
            sel = kps[kfs == kid]
            pts_old = kf.point_ids[sel]
            np.add.at(self.nobs, pts_old, -(1 + (kf.u_right[sel] >= 0)))
            kf.point_ids[sel] = -1
            kf.obs_row[sel] = -1
            self.add_observations(kf, sel, mapping[pts_old])
        self.visible[new] += self.visible[old]
        self.found[new] += self.found[old]
        self.bad[old] = True
        self.nobs[old] = 0
        self.replaced[old] = new

    # --------------------------------------------------------------- keyframes
    def add_keyframe(self, kf: KeyFrame) -> None:
        self.keyframes[kf.id] = kf

    def keyframe_pose(self, kf_id: int) -> np.ndarray | None:
        """T_cw of a keyframe, through the parents of culled ones; None if unknown."""
        T = np.eye(4)
        k = kf_id
        for _ in range(10000):
            kf = self.keyframes.get(k)
            if kf is not None:
                return T @ kf.T_cw
            if k not in self.culled:
                return None
            parent, T_cp = self.culled[k]
            T = T @ T_cp
            k = parent
        return None

    def new_kf_id(self) -> int:
        i = self.next_kf_id
        self.next_kf_id += 1
        return i

    def points_of(self, kf_ids) -> np.ndarray:
        """The good map points observed by the keyframes ``kf_ids`` (sorted, unique)."""
        pts = np.unique(np.concatenate([self.keyframes[k].point_ids for k in kf_ids]))
        return pts[self.good(pts)]

    def best_covisibles(self, kf_id: int, n: int = 10) -> list[int]:
        """The ``n`` strongest covisible keyframes of keyframe ``kf_id`` still in the map
        (none for an unknown one); the ``covisibles`` callback of the keyframe database."""
        kf = self.keyframes.get(kf_id)
        return [] if kf is None else [k for k in kf.best_covisibles(n) if k in self.keyframes]

    def covisible_counts(self, pts: np.ndarray, exclude: int | None = None) -> dict[int, int]:
        """Number of the given points each keyframe observes."""
        rows = self.rows_of(pts)
        kfs = self.obs_kf[rows]
        if exclude is not None:
            kfs = kfs[kfs != exclude]
        if len(kfs) == 0:
            return {}
        ids, counts = np.unique(kfs, return_counts=True)
        return {int(i): int(c) for i, c in zip(ids, counts)}

    def update_connections(self, kf: KeyFrame) -> None:
        """Covisibility edges of ``kf`` (>= 15 shared points, else the best one)."""
        counts = self.covisible_counts(kf.point_ids[kf.point_ids >= 0], exclude=kf.id)
        counts = {k: c for k, c in counts.items() if k in self.keyframes and not self.keyframes[k].bad}
        old = set(kf.covis)
        if not counts:
            kf.covis = {}
        else:
            edges = {k: c for k, c in counts.items() if c >= COVIS_MIN_WEIGHT}
            if not edges:
                best = max(counts.items(), key=lambda t: (t[1], -t[0]))
                edges = {best[0]: best[1]}
            kf.covis = edges
        for k in old - set(kf.covis):
            other = self.keyframes.get(k)
            if other is not None:
                other.covis.pop(kf.id, None)
        for k, w in kf.covis.items():
            self.keyframes[k].covis[kf.id] = w

    def set_bad_keyframe(self, kf: KeyFrame) -> None:
        kf.bad = True
        self.erase_observations(kf, np.flatnonzero(kf.point_ids >= 0))
        for k in list(kf.covis):
            other = self.keyframes.get(k)
            if other is not None:
                other.covis.pop(kf.id, None)
        kf.covis = {}
        del self.keyframes[kf.id]

    # ------------------------------------------------------------ point updates
    def update_points(self, pts: np.ndarray, max_obs: int = 12) -> None:
        """Viewing normal, scale-invariance distances and distinctive descriptor of points
        (``MapPoint::UpdateNormalAndDepth`` / ``ComputeDistinctiveDescriptors``), at once."""
        pts = np.unique(np.asarray(pts, np.int64))
        pts = pts[(pts >= 0) & ~self.bad[pts]]
        if len(pts) == 0:
            return
        rows = self.rows_of(pts)
        if len(rows) == 0:
            return
        kf_ids = self.obs_kf[rows]
        kps = self.obs_kp[rows]
        ptr = self.obs_pt[rows]
        # gather per-row camera centres, levels and descriptors (loop over keyframes)
        centers = np.zeros((len(rows), 3))
        levels = np.zeros(len(rows), np.int64)
        descs = np.zeros((len(rows), 32), np.uint8)
        for kid in np.unique(kf_ids):
            kf = self.keyframes[int(kid)]
            sel = kf_ids == kid
            centers[sel] = kf.center
            levels[sel] = kf.octave[kps[sel]]
            descs[sel] = kf.desc[kps[sel]]
        # normals
        v = self.pos[ptr] - centers
        nv = np.linalg.norm(v, axis=1, keepdims=True)
        v /= np.maximum(nv, 1e-12)
        loc = np.searchsorted(pts, ptr)
        acc = np.zeros((len(pts), 3))
        np.add.at(acc, loc, v)
        cnt = np.bincount(loc, minlength=len(pts))
        acc /= np.maximum(cnt, 1)[:, None]
        nrm = np.linalg.norm(acc, axis=1, keepdims=True)
        has = cnt > 0
        self.normal[pts[has]] = acc[has] / np.maximum(nrm[has], 1e-12)
        # depth range from the reference keyframe's observation
        is_ref = self.ref_kf[ptr] == kf_ids
        missing = np.setdiff1d(pts, ptr[is_ref])
        if len(missing):
            self._reassign_ref(missing)
            is_ref = self.ref_kf[ptr] == kf_ids
        r_idx = np.flatnonzero(is_ref)
        dist = nv[r_idx, 0]
        max_d = dist * self.scales[levels[r_idx]]
        self.max_dist[ptr[r_idx]] = max_d
        self.min_dist[ptr[r_idx]] = max_d / self.scales[-1]
        # distinctive descriptor: the observation with least median distance to the others
        order = np.lexsort((-rows, loc))  # newest observations first within each point
        loc_s = loc[order]
        start = np.searchsorted(loc_s, np.arange(len(pts)))
        rank = np.arange(len(order)) - start[loc_s]
        keep = rank < max_obs
        order, loc_s, rank = order[keep], loc_s[keep], rank[keep]
        K = int(rank.max()) + 1
        P = len(pts)
        D = np.zeros((P, K, 4), np.uint64)
        valid = np.zeros((P, K), bool)
        D[loc_s, rank] = desc_u64(descs[order])
        valid[loc_s, rank] = True
        dd = np.zeros((P, K, K), np.int32)
        for w in range(4):
            dd += np.bitwise_count(np.bitwise_xor(D[:, :, None, w], D[:, None, :, w])).astype(np.int32)
        big = 1 << 20
        dd = np.where(valid[:, None, :], dd, big)
        dd.sort(axis=2)
        nv_ = valid.sum(axis=1)
        med_idx = np.maximum((nv_ - 1) // 2, 0)
        med = np.take_along_axis(dd, np.broadcast_to(med_idx[:, None, None], (P, K, 1)), axis=2)[:, :, 0]
        med = np.where(valid, med, big)
        best = np.argmin(med, axis=1)
        sel_desc = np.zeros((P, 32), np.uint8)
        src = np.full((P, K), -1, np.int64)
        src[loc_s, rank] = order
        bi = src[np.arange(P), best]
        okp = bi >= 0
        sel_desc[okp] = descs[bi[okp]]
        self.desc[pts[okp]] = sel_desc[okp]

    def in_frustum(self, pts: np.ndarray, T_cw: np.ndarray, center: np.ndarray, calib) -> "Frustum":
        """ORB-SLAM2's ``isInFrustum`` for points ``pts`` seen from a camera at ``T_cw``
        (optical centre ``center`` in world): in front, inside the image, within the
        scale-invariance distances, viewing angle under 60 degrees; vectorised."""
        from .optimizer import project

        K = calib.K
        Xw = self.pos[pts]
        Xc, u, v, ur = project(T_cw, Xw, K[0, 0], K[1, 1], K[0, 2], K[1, 2], calib.bf)
        PO = Xw - center
        dist = np.linalg.norm(PO, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cosv = (PO * self.normal[pts]).sum(axis=1) / np.maximum(dist, 1e-12)
        vis = (
            (Xc[:, 2] > 0)
            & (u >= 0)
            & (u < calib.width)
            & (v >= 0)
            & (v < calib.height)
            & (dist >= 0.8 * self.min_dist[pts])
            & (dist <= 1.2 * self.max_dist[pts])
            & (cosv >= 0.5)
        )
        return Frustum(np.flatnonzero(vis), Xw, u, v, ur, dist, cosv)

    def predict_level(self, pts: np.ndarray, dist: np.ndarray) -> np.ndarray:
        """Pyramid level at which a point at ``dist`` should be seen (``PredictScale``)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = self.max_dist[pts] / np.maximum(dist, 1e-9)
            lev = np.ceil(np.log(np.maximum(ratio, 1e-9)) / self.log_scale)
        return np.clip(np.nan_to_num(lev, nan=0.0), 0, self.n_levels - 1).astype(np.int64)

    def stats(self) -> dict[str, int]:
        return {
            "keyframes": len(self.keyframes),
            "map_points": int((~self.bad[: self.n]).sum()),
            "observations": int(self.obs_alive[: self.m].sum()),
        }
