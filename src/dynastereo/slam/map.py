"""The map: keyframes, covisibility and culled keyframes over two tables.

``Map.points`` (:class:`~.map_points.MapPoints`): one row per point id (position,
descriptor, viewing normal, scale-invariance distance range, observation count,
visible/found counters, ...), never reused.  ``Map.obs``
(:class:`~.observations.Observations`): one row per ``(keyframe id, keypoint index,
point id)`` with an alive flag and per-point lists; each keyframe keeps, per keypoint,
its point id and its observation row.  The map keeps what links keyframes and points
(adding / erasing observations, culling, fusing, normals and descriptors, frustum
tests) and works on the tables' arrays at once.  ``to_arrays()`` / ``from_arrays()``
are the map-file entries (``docs/reference/map-format.md``; ``map_io`` writes the container).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import MapFileError
from .geometry import desc_u64
from .kernels.bookkeeping import by_keyframe, new_observations, unique_good
from .kernels.bookkeeping import update_points as _update_points
from .keyframe import KeyFrame
from .map_points import MapPoints
from .observations import Observations
from .optimizer import project
from .table import check_entry


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


class Map:
    """Keyframes, their covisibility graph and culled keyframes, over two tables: the
    map points (``points``, :class:`~.map_points.MapPoints`) and the observations that
    link keyframe keypoints to them (``obs``, :class:`~.observations.Observations`)."""

    def __init__(self, scales: np.ndarray, capacity: int = 4096) -> None:
        self.scales = np.asarray(scales, np.float64)
        self.n_levels = len(self.scales)
        self.log_scale = float(np.log(self.scales[1])) if self.n_levels > 1 else 1.0
        self.points = MapPoints(capacity)
        self.obs = Observations(capacity * 4, capacity)
        self.keyframes: dict[int, KeyFrame] = {}
        # culled keyframes: id -> (parent id, T_c_parent), to keep frame poses that refer to them
        self.culled: dict[int, tuple[int, np.ndarray]] = {}
        self.next_kf_id = 0

    # ------------------------------------------------------------------ points
    def new_points(self, pos: np.ndarray, desc: np.ndarray, kf_id: int) -> np.ndarray:
        ids = self.points.add(pos, desc, kf_id)
        self.obs.add_points(self.points.n)
        return ids

    # ------------------------------------------------------------ observations
    def add_observations(self, kf: KeyFrame, kp: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """Add observations (kf, kp[i]) -> pts[i]; skips keypoints already used, points
        already observed by ``kf``, duplicates and bad points.  Returns the kept mask."""
        kp = np.ascontiguousarray(kp, np.int64)
        pts = np.ascontiguousarray(pts, np.int64)
        keep = new_observations(kf.point_ids, kp, pts, self.points.bad)
        kp_k, pt_k = kp[keep], pts[keep]
        if len(kp_k) == 0:
            return keep
        kf.point_ids[kp_k] = pt_k
        kf.obs_row[kp_k] = self.obs.add(kf.id, kp_k, pt_k)  # pt_k has no duplicates
        self.points.nobs[pt_k] += 1 + (kf.u_right[kp_k] >= 0)  # (as np.add.at: pt_k is unique)
        return keep

    def erase_observations(self, kf: KeyFrame, kp: np.ndarray, cull: bool = True) -> None:
        """Remove keyframe observations; points left with <= 2 observations become bad."""
        kp = np.asarray(kp, np.int64)
        kp = kp[kf.point_ids[kp] >= 0]
        if len(kp) == 0:
            return
        P = self.points
        pts = kf.point_ids[kp]
        self.obs.erase(kf.obs_row[kp])
        np.add.at(P.nobs, pts, -(1 + (kf.u_right[kp] >= 0)))
        kf.point_ids[kp] = -1
        kf.obs_row[kp] = -1
        if cull:
            weak = np.unique(pts[P.nobs[pts] <= 2])
            if len(weak):
                self.set_bad(weak)
            # points whose reference keyframe lost them: pick another observer
            fix = np.unique(pts[(P.ref_kf[pts] == kf.id) & ~P.bad[pts]])
            if len(fix):
                self._reassign_ref(fix)

    def _by_keyframe(self, rows: np.ndarray):
        """(keyframe, its keypoints) of the observation rows, per keyframe still in the
        map (a loop over keyframes, not rows)."""
        kps = self.obs.kp[rows]
        for kf, sel in self.keyframe_groups(rows):
            if kf is not None:
                yield kf, kps[sel]

    def keyframe_groups(self, rows: np.ndarray):
        """(keyframe or None, the positions in ``rows`` of its rows) per keyframe id of
        the observation rows ``rows``, ascending, each group in ``rows``' order (one
        compiled grouping, then a loop over keyframes, not rows)."""
        order, ids, starts = by_keyframe(self.obs.kf[rows])
        for g, kid in enumerate(ids.tolist()):
            yield self.keyframes.get(kid), order[starts[g]:starts[g + 1]]

    def set_bad(self, pts: np.ndarray) -> None:
        P = self.points
        pts = np.unique(np.asarray(pts, np.int64))
        pts = pts[~P.bad[pts]]
        if len(pts) == 0:
            return
        rows = self.obs.rows_of(pts)
        P.bad[pts] = True
        self.obs.erase(rows)
        P.nobs[pts] = 0
        for kf, sel in self._by_keyframe(rows):
            kf.point_ids[sel] = -1
            kf.obs_row[sel] = -1

    def _reassign_ref(self, pts: np.ndarray) -> None:
        p, kf_ids = self.obs.first_observers(pts)
        self.points.ref_kf[p] = kf_ids

    def replace(self, old: np.ndarray, new: np.ndarray) -> None:
        """Fuse points: observations of ``old[i]`` move to ``new[i]``; ``old`` become bad."""
        P = self.points
        old = np.asarray(old, np.int64)
        new = np.asarray(new, np.int64)
        ok = (old != new) & P.good(old) & P.good(new)
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
        mapping = np.full(P.n, -1, np.int64)
        mapping[old] = new
        # erase the old observations (without culling), then add them for the new points
        rows = self.obs.rows_of(old)
        self.obs.erase(rows)
        for kf, sel in self._by_keyframe(rows):
            pts_old = kf.point_ids[sel]
            np.add.at(P.nobs, pts_old, -(1 + (kf.u_right[sel] >= 0)))
            kf.point_ids[sel] = -1
            kf.obs_row[sel] = -1
            self.add_observations(kf, sel, mapping[pts_old])
        P.visible[new] += P.visible[old]
        P.found[new] += P.found[old]
        P.bad[old] = True
        P.nobs[old] = 0
        P.replaced[old] = new

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
        return unique_good(np.concatenate([self.keyframes[k].point_ids for k in kf_ids]), self.points.bad)

    def best_covisibles(self, kf_id: int, n: int = 10) -> list[int]:
        """The ``n`` strongest covisible keyframes of keyframe ``kf_id`` still in the map
        (none for an unknown one); the ``covisibles`` callback of the keyframe database."""
        kf = self.keyframes.get(kf_id)
        return [] if kf is None else [k for k in kf.best_covisibles(n) if k in self.keyframes]

    def covisible_counts(self, pts: np.ndarray, exclude: int | None = None) -> dict[int, int]:
        """Number of the given points each keyframe observes."""
        rows = self.obs.rows_of(pts)
        kfs = self.obs.kf[rows]
        if exclude is not None:
            kfs = kfs[kfs != exclude]
        if len(kfs) == 0:
            return {}
        _, ids, starts = by_keyframe(kfs)
        return dict(zip(ids.tolist(), np.diff(starts).tolist()))

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
        pts = unique_good(np.ascontiguousarray(pts, np.int64), self.points.bad)
        if len(pts) == 0:
            return
        rows = self.obs.rows_of(pts)
        if len(rows) == 0:
            return
        kf_ids = self.obs.kf[rows]
        kps = self.obs.kp[rows]
        # gather per-row camera centres, levels and descriptors (a loop over keyframes)
        centers = np.empty((len(rows), 3))
        levels = np.empty(len(rows), np.int64)
        descs = np.empty((len(rows), 32), np.uint8)
        for kf, sel in self.keyframe_groups(rows):
            k = kps[sel]
            centers[sel] = kf.center
            levels[sel] = kf.octave[k]
            descs[sel] = kf.desc[k]
        # normals, distances (reference keyframes fixed first), descriptors: one kernel
        P = self.points
        _update_points(pts, rows, self.obs.pt[rows], kf_ids, centers, levels, descs, desc_u64(descs), P.pos,
                       P.ref_kf, P.normal, P.max_dist, P.min_dist, P.desc, self.scales, int(max_obs))

    def in_frustum(self, pts: np.ndarray, T_cw: np.ndarray, center: np.ndarray, calib) -> "Frustum":
        """ORB-SLAM2's ``isInFrustum`` for points ``pts`` seen from a camera at ``T_cw``
        (optical centre ``center`` in world): in front, inside the image, within the
        scale-invariance distances, viewing angle under 60 degrees; vectorized."""
        K = calib.K
        Xw = self.points.pos[pts]
        Xc, u, v, ur = project(T_cw, Xw, K[0, 0], K[1, 1], K[0, 2], K[1, 2], calib.bf)
        PO = Xw - center
        dist = np.linalg.norm(PO, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cosv = (PO * self.points.normal[pts]).sum(axis=1) / np.maximum(dist, 1e-12)
        vis = (
            (Xc[:, 2] > 0)
            & (u >= 0)
            & (u < calib.width)
            & (v >= 0)
            & (v < calib.height)
            & (dist >= 0.8 * self.points.min_dist[pts])
            & (dist <= 1.2 * self.points.max_dist[pts])
            & (cosv >= 0.5)
        )
        return Frustum(np.flatnonzero(vis), Xw, u, v, ur, dist, cosv)

    def predict_level(self, pts: np.ndarray, dist: np.ndarray) -> np.ndarray:
        """Pyramid level at which a point at ``dist`` should be seen (``PredictScale``)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = self.points.max_dist[pts] / np.maximum(dist, 1e-9)
            lev = np.ceil(np.log(np.maximum(ratio, 1e-9)) / self.log_scale)
        return np.clip(np.nan_to_num(lev, nan=0.0), 0, self.n_levels - 1).astype(np.int64)

    def stats(self) -> dict[str, int]:
        return {
            "keyframes": len(self.keyframes),
            "map_points": len(self.points.good_ids()),
            "observations": self.obs.n_alive(),
        }

    # --------------------------------------------------------------- map files
    @staticmethod
    def entries() -> dict[str, tuple[np.dtype, tuple]]:
        """Map-file entry -> (dtype, shape with the header's count names), in file order
        (``docs/reference/map-format.md``)."""
        return {"map/scales": _OWN_ENTRIES["map/scales"], **MapPoints.entries(), **Observations.entries(),
                **_OWN_ENTRIES}

    @staticmethod
    def counts_of(arrays: dict[str, np.ndarray]) -> dict[str, int]:
        """The header's counts (``COUNTS``) of the arrays of :meth:`to_arrays`."""
        found: dict[str, int] = {}
        for name, (_dt, shape) in Map.entries().items():
            found.setdefault(shape[0], len(arrays[name]))
        return {c: found[c] for c in COUNTS}

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The map as named plain arrays (the entries of a map file): the two tables,
        keyframes packed into concatenated per-keypoint arrays with offsets, the
        covisibility graph as an edge list, the culled keyframes.  ``ValueError`` for a
        map that disagrees with itself."""
        arrays: dict[str, np.ndarray] = {"map/scales": self.scales, **self.points.to_arrays(), **self.obs.to_arrays()}
        # keyframes (a loop over keyframes, the per-keypoint data is concatenated at once)
        kfs = list(self.keyframes.values())
        for key, kf in self.keyframes.items():
            if kf.id != key:
                raise ValueError(f"keyframe stored under id {key} has id {kf.id}")
        counts = np.array([len(kf.uv) for kf in kfs], np.int64)
        offsets = np.zeros(len(kfs) + 1, np.int64)
        np.cumsum(counts, out=offsets[1:])
        arrays["keyframes/id"] = np.array([kf.id for kf in kfs], np.int64)
        arrays["keyframes/frame_index"] = np.array([kf.frame_index for kf in kfs], np.int64)
        arrays["keyframes/T_cw"] = np.array([kf.T_cw for kf in kfs], np.float64).reshape(len(kfs), 4, 4)
        arrays["keyframes/bad"] = np.array([kf.bad for kf in kfs], bool)
        arrays["keyframes/offsets"] = offsets
        for name in KEYPOINT_FIELDS:
            dt, shape = _OWN_ENTRIES[f"keypoints/{name}"]
            parts = [getattr(kf, name) for kf in kfs]
            for kf, p, c in zip(kfs, parts, counts):
                if len(p) != c:
                    raise ValueError(f"keyframe {kf.id}: {name} has {len(p)} rows, uv has {c}")
            arrays[f"keypoints/{name}"] = (
                np.concatenate(parts, axis=0, dtype=dt, casting="same_kind") if parts
                else np.zeros((0,) + shape[1:], dt)
            )
        src: list[int] = []
        dst: list[int] = []
        wts: list[int] = []
        for kf in kfs:
            src.extend([kf.id] * len(kf.covis))
            dst.extend(kf.covis.keys())
            wts.extend(kf.covis.values())
        arrays["covis/src"] = np.array(src, np.int64)
        arrays["covis/dst"] = np.array(dst, np.int64)
        arrays["covis/weight"] = np.array(wts, np.int64)
        arrays["culled/id"] = np.array(list(self.culled.keys()), np.int64)
        arrays["culled/parent"] = np.array([p for p, _ in self.culled.values()], np.int64)
        arrays["culled/T_c_parent"] = np.array([T for _, T in self.culled.values()], np.float64).reshape(-1, 4, 4)
        return {name: _as(arrays[name], dt, name) for name, (dt, _shape) in self.entries().items()}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], calib, next_kf_id: int,
                    counts: dict[str, int] | None = None) -> "Map":
        """The working map of :meth:`to_arrays`' arrays; every keyframe gets ``calib``.
        ``counts``: the header's counts the arrays must match (default: theirs).  Every
        entry's dtype and shape and the cross references between the tables are checked
        first: :class:`MapFileError` naming the entry or the problem."""
        counts = dict(counts) if counts is not None else cls.counts_of(arrays)
        points = MapPoints.from_arrays(arrays, counts)
        obs = Observations.from_arrays(arrays, counts)
        a = {**points.to_arrays(), **obs.to_arrays()}
        for name, (dt, shape) in _OWN_ENTRIES.items():
            if name not in arrays:
                raise MapFileError(f"corrupt or incomplete map file: entry '{name}' is missing")
            a[name] = check_entry(name, np.asarray(arrays[name]), dt, shape, counts)
        _check_arrays(a, counts, next_kf_id)
        mp = cls(a["map/scales"], capacity=0)
        mp.points, mp.obs = points, obs
        off = a["keyframes/offsets"].tolist()
        kp = {name: a[f"keypoints/{name}"] for name in KEYPOINT_FIELDS}
        fidx = a["keyframes/frame_index"].tolist()
        kbad = a["keyframes/bad"].tolist()
        T = a["keyframes/T_cw"]
        for i, kid in enumerate(a["keyframes/id"].tolist()):
            s = slice(off[i], off[i + 1])
            # each keyframe owns its arrays (as in a live map), no views into one buffer
            mp.keyframes[kid] = KeyFrame(
                id=kid, frame_index=fidx[i], calib=calib, T_cw=T[i].copy(), bad=kbad[i],
                **{name: arr[s].copy() for name, arr in kp.items()},
            )
        kfs = mp.keyframes
        for s_, d_, w_ in zip(a["covis/src"].tolist(), a["covis/dst"].tolist(), a["covis/weight"].tolist()):
            kfs[s_].covis[d_] = w_
        for cid, par, Tc in zip(a["culled/id"].tolist(), a["culled/parent"].tolist(), a["culled/T_c_parent"]):
            mp.culled[cid] = (par, Tc.copy())
        mp.next_kf_id = int(next_kf_id)
        return mp


# ---------------------------------------------------------------- map files
_F8, _F4, _I8, _I4, _U1, _B = (np.dtype(t) for t in ("<f8", "<f4", "<i8", "<i4", "u1", "?"))
COUNTS = ("points", "observations", "keyframes", "keypoints", "covis_edges", "culled", "levels")
KEYPOINT_FIELDS = ("uv", "octave", "angle", "desc", "u_right", "depth", "point_ids", "obs_row")
# the entries of the map itself (the tables have theirs)
_OWN_ENTRIES: dict[str, tuple[np.dtype, tuple]] = {
    "map/scales": (_F8, ("levels",)),
    "keyframes/id": (_I8, ("keyframes",)),
    "keyframes/frame_index": (_I8, ("keyframes",)),
    "keyframes/T_cw": (_F8, ("keyframes", 4, 4)),
    "keyframes/bad": (_B, ("keyframes",)),
    "keyframes/offsets": (_I8, ("keyframes+1",)),
    # keypoints of all keyframes, concatenated in keyframe order
    "keypoints/uv": (_F8, ("keypoints", 2)),
    "keypoints/octave": (_I4, ("keypoints",)),
    "keypoints/angle": (_F4, ("keypoints",)),
    "keypoints/desc": (_U1, ("keypoints", 32)),
    "keypoints/u_right": (_F8, ("keypoints",)),
    "keypoints/depth": (_F8, ("keypoints",)),
    "keypoints/point_ids": (_I8, ("keypoints",)),
    "keypoints/obs_row": (_I8, ("keypoints",)),
    # covisibility graph, one row per (keyframe, neighbour) entry of KeyFrame.covis
    "covis/src": (_I8, ("covis_edges",)),
    "covis/dst": (_I8, ("covis_edges",)),
    "covis/weight": (_I8, ("covis_edges",)),
    # culled keyframes: id -> (parent id, T_c_parent)
    "culled/id": (_I8, ("culled",)),
    "culled/parent": (_I8, ("culled",)),
    "culled/T_c_parent": (_F8, ("culled", 4, 4)),
}


def _as(a, dtype: np.dtype, what: str) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype == dtype:
        return np.ascontiguousarray(a)
    if not np.can_cast(a.dtype, dtype, "same_kind"):
        raise ValueError(f"{what}: dtype {a.dtype} cannot be stored as {dtype}")
    return np.ascontiguousarray(a.astype(dtype))


def _check_arrays(a: dict[str, np.ndarray], c: dict[str, int], next_kf_id: int) -> None:
    """Cross references between the tables (vectorized): anything that would make the
    map index out of range, or disagree with itself, is an error naming the problem."""
    n, m, nk = c["points"], c["observations"], c["keyframes"]

    def bad(msg: str) -> MapFileError:
        return MapFileError(f"inconsistent map: {msg}")

    sc = a["map/scales"]
    if len(sc) == 0 or not np.isfinite(sc).all() or sc[0] != 1.0 or (np.diff(sc) <= 0).any():
        raise bad("map/scales must start at 1 and increase")
    ids = a["keyframes/id"]
    if len(np.unique(ids)) != nk or (nk and (ids.min() < 0 or ids.max() >= next_kf_id)):
        raise bad(f"keyframe ids must be unique and in 0..next_kf_id-1 ({next_kf_id - 1})")
    off = a["keyframes/offsets"]
    if off[0] != 0 or off[-1] != c["keypoints"] or (np.diff(off) < 0).any():
        raise bad("keyframes/offsets must rise from 0 to the number of keypoints")
    T = a["keyframes/T_cw"]
    if not np.isfinite(T).all() or not np.allclose(T[:, 3], [0.0, 0.0, 0.0, 1.0]):
        raise bad("keyframe poses must be finite 4x4 rigid transforms")

    def out_of(x: np.ndarray, lo: int, hi: int) -> int:
        return int(np.count_nonzero((x < lo) | (x >= hi)))

    for name, lo, hi, what in (
        ("obs/pt", 0, n, f"the {n} map points"),
        ("obs/next_row", -1, m, f"the {m} observation rows"),
        ("points/head", -1, m, f"the {m} observation rows"),
        ("points/replaced", -1, n, f"the {n} map points"),
        ("keypoints/point_ids", -1, n, f"the {n} map points"),
        ("keypoints/obs_row", -1, m, f"the {m} observation rows"),
    ):
        k = out_of(a[name], lo, hi)
        if k:
            raise bad(f"{k} values of {name} point beyond {what}")
    if (a["obs/kp"] < 0).any():
        raise bad("negative keypoint indices in obs/kp")
    # each point's observation list runs newest first (a row links to an older, lower row),
    # through rows of that point only: no list can loop (a loop would never end)
    nxt, opt, head = a["obs/next_row"], a["obs/pt"], a["points/head"]
    linked = nxt >= 0
    if (nxt[linked] >= np.flatnonzero(linked)).any():
        raise bad("obs/next_row must link each row to an older (lower) row: the observation lists form a cycle")
    if not (np.array_equal(opt[nxt[linked]], opt[linked])
            and np.array_equal(opt[head[head >= 0]], np.flatnonzero(head >= 0))):
        raise bad("the observation lists (points/head, obs/next_row) mix rows of different points")
    for name in ("points/pos", "points/normal", "points/min_dist", "points/max_dist"):
        k = int(np.count_nonzero(~np.isfinite(a[name])))
        if k:
            raise bad(f"{k} non-finite values (nan/inf) in {name}")
    pid, orow = a["keypoints/point_ids"], a["keypoints/obs_row"]
    has = pid >= 0
    if not np.array_equal(has, orow >= 0):
        raise bad("keypoints/point_ids and keypoints/obs_row disagree on which keypoints have a point")
    rows = orow[has]
    kp_kf = np.repeat(ids, np.diff(off))
    kp_idx = np.arange(len(pid)) - np.repeat(off[:-1], np.diff(off))
    if not (a["obs/alive"][rows].all() and np.array_equal(a["obs/pt"][rows], pid[has])
            and np.array_equal(a["obs/kf"][rows], kp_kf[has]) and np.array_equal(a["obs/kp"][rows], kp_idx[has])):
        raise bad("keyframe keypoints and the observation rows they name disagree")
    if int(np.count_nonzero(a["obs/alive"])) != len(rows) or len(np.unique(rows)) != len(rows):
        raise bad("alive observation rows are not exactly the rows the keyframes name")
    for name in ("covis/src", "covis/dst"):
        if not np.isin(a[name], ids).all():
            raise bad(f"{name} names keyframes that are not in the map")
    if (a["covis/weight"] <= 0).any():
        raise bad("covisibility weights must be positive")
    cid = a["culled/id"]
    if len(np.unique(cid)) != len(cid) or np.isin(cid, ids).any() or not np.isfinite(a["culled/T_c_parent"]).all():
        raise bad("culled keyframes must be unique, not in the map, with finite poses")
