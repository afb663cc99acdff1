"""Vectorized ray casting of one view of the synthetic world.

Every pixel's ray is intersected analytically with the scene; the nearest hit wins
(z-buffer).  Rays are ``(u, v, 1)`` in camera coordinates, so the ray parameter IS the
depth ``z`` and the disparity is exactly ``f * b / z``.

The camera is upright (yaw only), which makes the static scene separable: a vertical
facade plane is hit at the same depth by every ray of an image column, and the ground
at the same depth by every ray of an image row.  The facades are therefore
intersected per column (K nearest candidates), the ground per row, and only the
"which surface, where in its texture" step is per pixel.  Objects are intersected per
pixel inside the projected box of each primitive.  No Python loop runs over pixels;
the loops are over the few facade candidates, objects and primitives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .objects import Shape
from .textures import TileAtlas
from .world import World

SKY_ID = 0
_NEAR = 0.05
_ANISO = 0.3  # vertical footprint weight in the mip level (horizontal is exact: 1.0)
# the 12 edges of a box whose 8 corners are ordered x-major: index = 4*ix + 2*iy + iz
_BIG_SLAB = 1e29  # padded (absent) slabs are at +-1e30
_EDGES = np.array([(i, i | b) for b in (1, 2, 4) for i in range(8) if not i & b])


@dataclass
class PosedObject:
    id: int
    shape: Shape
    R: np.ndarray  # object -> map rotation
    origin: np.ndarray  # map coordinates of the object origin (on the ground)
    phase: float


@dataclass
class View:
    image: np.ndarray  # float32 (H, W) grey levels 0..255 (not clipped)
    depth: np.ndarray  # float32 (H, W) depth z in metres, inf = sky
    ids: np.ndarray  # uint8 (H, W) object instance id, 0 = none


@dataclass(frozen=True)
class Lighting:
    sun: tuple[float, float, float] = (-0.35, -0.8, 0.5)  # towards the sun, map frame (y down)
    ambient: float = 0.5
    diffuse: float = 0.55
    exposure: float = 1.15


@dataclass(frozen=True)
class _Rays:
    """One view's camera: map position, heading (cos, sin), the texture-filtering
    origin, the per-column ray directions and the map -> camera rotation."""

    cam_x: float
    cam_z: float
    cth: float
    sth: float
    lx: float
    lz: float
    dx: np.ndarray  # (W,) horizontal ray direction, map frame
    dz: np.ndarray
    cam: np.ndarray  # (3,) map position
    Rc: np.ndarray  # (3, 3) map -> camera rotation (rows)


@dataclass(frozen=True)
class _Facades:
    """The ``kk`` nearest facade candidates per column, nearest first, each (kk, W)."""

    kk: int
    uk: np.ndarray  # position along the segment
    segk: np.ndarray  # global segment index
    valid: np.ndarray  # a hit at all
    Uk: np.ndarray  # position along the street's facade line
    bld: np.ndarray  # building index
    topk: np.ndarray  # y of the roof (y down); inf without a hit
    tk_f: np.ndarray  # depth; 1e9 without a hit


@dataclass(frozen=True)
class _Hits:
    """Winning (primitive, pixel) pairs in float64: entry depth ``t``, the constraint
    entered through ``wc``, the rays ``Dw`` / origins ``ow`` in the primitive frames (3
    arrays each) and the primitives' quadric coefficients and centres."""

    t: np.ndarray
    wc: np.ndarray
    Dw: list
    ow: list
    qk2: np.ndarray
    qc: np.ndarray


class Renderer:
    """Renders views of ``world`` with a pinhole camera (fx, fy, cx, cy) of size width x height."""

    def __init__(
        self,
        world: World,
        width: int,
        height: int,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        lighting: Lighting | None = None,
        candidates: int = 3,
    ):
        self.world = world
        self.W = int(width)
        self.H = int(height)
        self.fx, self.fy, self.cx, self.cy = float(fx), float(fy), float(cx), float(cy)
        self.uc = ((np.arange(self.W) - cx) / fx).astype(np.float64)
        self.vc = ((np.arange(self.H) - cy) / fy).astype(np.float64)
        self.uc32 = self.uc.astype(np.float32)
        self.vc32 = self.vc.astype(np.float32)
        self.light = lighting or Lighting()
        L = np.asarray(self.light.sun, float)
        self.L = L / np.linalg.norm(L)
        self.K = candidates
        h = world.params.cam_height
        with np.errstate(divide="ignore"):
            self.t_ground = np.where(self.vc > 1e-9, h / np.maximum(self.vc, 1e-12), np.inf)
        # ground mip level per row: max(column footprint, ANISO * row footprint)
        t = np.where(np.isfinite(self.t_ground), self.t_ground, 1e9)
        fp = np.maximum(t / self.fx, _ANISO * t * t / (h * self.fy))
        with np.errstate(divide="ignore"):
            self.ground_lod = np.log2(fp / world.params.ground_texel).astype(np.float32)
            self.ground_dlod = np.log2(fp / world.params.ground_detail_texel).astype(np.float32)
        self.sky_lod = float(np.log2((1.0 / self.fx) / (2 * np.pi / world.sky.width)))

    # -----------------------------------------------------------------------------------------
    def render(
        self,
        cam_x: float,
        cam_z: float,
        heading: float,
        objects: list[PosedObject],
        lod_origin: tuple[float, float] | None = None,
    ) -> View:
        """One view from the camera at map (cam_x, 0, cam_z) with ``heading``.

        Texture filtering (mip levels) is computed as seen from ``lod_origin`` (default:
        this camera); the stereo writer passes the rig centre, so both views filter every
        surface point identically and differ only by geometry.

        The steps: the facade candidates per column, the surface each pixel sees (a
        candidate, the ground or the sky) and its shading; then the objects that survive
        culling: their soft contact shadows on the ground, then the objects themselves.
        """
        H, W = self.H, self.W
        ray = self._rays(cam_x, cam_z, heading, lod_origin)
        fac = self._facade_candidates(ray)
        sel = self._surfaces(fac)
        flat = sel.ravel()
        img = np.empty(H * W, np.float32)
        depth = np.empty(H * W, np.float32)
        ids = np.zeros((H, W), np.uint8)
        idx = np.flatnonzero(flat < fac.kk)
        if idx.size:
            self._shade_facades(ray, fac, idx, flat[idx], img, depth)
        idx = np.flatnonzero(flat == fac.kk)
        ground_xz = self._shade_ground(ray, idx, img, depth) if idx.size else None
        idx = np.flatnonzero(flat == fac.kk + 1)
        if idx.size:
            self._shade_sky(ray, idx, img, depth)
        img = img.reshape(H, W)
        depth = depth.reshape(H, W)
        img *= np.float32(255.0 * self.light.exposure)

        shown = self._shown_objects(objects, ray, depth)
        if ground_xz is not None and shown:
            gmask = sel == fac.kk
            gx2 = ground_xz[0].reshape(H, W)
            gz2 = ground_xz[1].reshape(H, W)
            for ob in shown:
                self._shadow(ob, img, gmask, gx2, gz2, ray.Rc, ray.cam)
        if shown:
            self._objects(shown, img, depth, ids, ray.Rc, ray.cam, np.array([ray.lx, 0.0, ray.lz]))
        return View(img, depth, ids)

    def _rays(self, cam_x: float, cam_z: float, heading: float, lod_origin: tuple[float, float] | None) -> _Rays:
        lx, lz = (cam_x, cam_z) if lod_origin is None else lod_origin
        cth, sth = np.cos(heading), np.sin(heading)
        fwd3 = np.array([sth, 0.0, cth])
        rgt3 = np.array([cth, 0.0, -sth])
        down3 = np.array([0.0, 1.0, 0.0])
        return _Rays(
            cam_x, cam_z, cth, sth, lx, lz,
            dx=self.uc * cth + sth,  # (W,) horizontal ray direction, map frame
            dz=-self.uc * sth + cth,
            cam=np.array([cam_x, 0.0, cam_z]),
            Rc=np.stack([rgt3, down3, fwd3]),  # map -> camera rotation (rows)
        )

    def _facade_candidates(self, ray: _Rays) -> _Facades:
        """Per column, the K nearest front-facing facade hits, nearest first."""
        w = self.world
        W, K = self.W, self.K
        dx, dz = ray.dx, ray.dz
        rel = w.seg_p0 - np.array([ray.cam_x, ray.cam_z])  # (S, 2)
        num = (w.seg_n * rel).sum(1)
        front = np.flatnonzero(num < -1e-6)
        n = w.seg_n[front]
        e = w.seg_e[front]
        denom = n[:, :1] * dx[None, :] + n[:, 1:] * dz[None, :]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num[front, None] / denom
            u = -(rel[front] * e).sum(1)[:, None] + t * (e[:, :1] * dx[None, :] + e[:, 1:] * dz[None, :])
        ok = (denom < -1e-9) & (t > _NEAR) & (u >= 0) & (u <= w.seg_len[front, None])
        t = np.where(ok, t, np.inf)
        kk = min(K, len(front))
        if len(front) > kk:
            part = np.argpartition(t, kk - 1, axis=0)[:kk]
        else:
            part = np.broadcast_to(np.arange(len(front))[:, None], (len(front), W))
        tk = np.take_along_axis(t, part, 0)
        order = np.argsort(tk, axis=0)
        part = np.take_along_axis(part, order, 0)
        tk = np.take_along_axis(tk, order, 0)
        uk = np.take_along_axis(np.where(ok, u, 0.0), part, 0)
        segk = front[part]  # (kk, W) global segment index
        valid = np.isfinite(tk)
        Uk = w.seg_off[segk] + uk
        bld = w.building_at(Uk)
        topk = np.where(valid, w.params.cam_height - w.bld_height[bld], np.inf)  # y of the roof (y down)
        tk_f = np.where(valid, tk, 1e9)
        return _Facades(kk, uk, segk, valid, Uk, bld, topk, tk_f)

    def _surfaces(self, fac: _Facades) -> np.ndarray:
        """Per pixel the first candidate ``k`` whose vertical extent contains the ray, else
        ``kk`` = ground (below the horizon) or ``kk + 1`` = sky; int8 (H, W)."""
        vc, h, kk = self.vc, self.world.params.cam_height, fac.kk
        sel = np.full((self.H, self.W), kk + 1, np.int8)  # kk+1 = sky
        sel[vc > 0, :] = kk  # kk = ground
        for k in range(kk - 1, -1, -1):
            y = vc[:, None] * fac.tk_f[k][None, :]
            hit = (y >= fac.topk[k][None, :]) & (y <= h)
            sel[hit] = k
        return sel

    def _shade_facades(self, ray: _Rays, fac: _Facades, idx: np.ndarray, cand: np.ndarray,
                       img: np.ndarray, depth: np.ndarray) -> None:
        """Facade pixels ``idx`` (flat), which see candidate ``cand``: texture, detail, shade."""
        w = self.world
        p = w.params
        W, h = self.W, p.cam_height
        dx, dz, cth, sth = ray.dx, ray.dz, ray.cth, ray.sth
        segk, valid, uk, tk_f, bld, Uk = fac.segk, fac.valid, fac.uk, fac.tk_f, fac.bld, fac.Uk
        r = idx // W
        c = idx - r * W
        kc = cand.astype(np.int64) * W + c
        nk = w.seg_n[segk]  # (kk, W, 2)
        er = np.array([cth, -sth])
        # footprint along the facade of a pixel looking at the hit point from lod_origin
        hx = ray.cam_x + tk_f * dx[None, :] - ray.lx
        hz = ray.cam_z + tk_f * dz[None, :] - ray.lz
        zc = hx * sth + hz * cth  # depth of the hit point seen from lod_origin
        with np.errstate(divide="ignore", invalid="ignore"):
            cdx = hx / zc
            cdz = hz / zc
            nd = nk[..., 0] * cdx + nk[..., 1] * cdz
            ne = nk[..., 0] * er[0] + nk[..., 1] * er[1]
            ratio = np.where(valid, ne / nd, 0.0)
        fpx = np.where(valid, zc, 1e9) / self.fx * np.hypot(er[0] - cdx * ratio, er[1] - cdz * ratio)
        fp = np.maximum(fpx, _ANISO * tk_f / self.fy)
        lod = np.log2(np.maximum(fp, 1e-6) / p.facade_texel).astype(np.float32)
        dlod = (lod + np.float32(np.log2(p.facade_texel / p.facade_detail_texel))).astype(np.float32)
        shade = (self.light.ambient + self.light.diffuse * np.maximum(0.0, nk[..., 0] * self.L[0] + nk[..., 1] * self.L[2])).astype(np.float32)
        ax = (w.seg_xt[segk] + uk / p.facade_texel).astype(np.float32)
        ay0 = (w.seg_band_y[segk] + w.facade_height / p.facade_texel).astype(np.float32)
        tpix = tk_f.ravel()[kc].astype(np.float32)
        hgt = np.float32(h) - self.vc32[r] * tpix
        col = w.facade.sample(ax.ravel()[kc], ay0.ravel()[kc] - hgt / np.float32(p.facade_texel), lod.ravel()[kc])
        ud = (Uk.ravel()[kc] / p.facade_detail_texel).astype(np.float32)
        det = w.facade_detail.sample(ud, hgt / np.float32(p.facade_detail_texel), dlod.ravel()[kc])
        strength = w.bld_detail[bld].ravel()[kc]
        img[idx] = col * (1.0 + strength * (det - 0.5) * 2.0) * shade.ravel()[kc]
        depth[idx] = tpix

    def _shade_ground(self, ray: _Rays, idx: np.ndarray, img: np.ndarray,
                      depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ground pixels ``idx`` (flat); returns the map x, z of every ground pixel (flat,
        0 elsewhere) for the contact shadows."""
        w = self.world
        p = w.params
        r = idx // self.W
        c = idx - r * self.W
        tg = self.t_ground[r]
        gx = ray.cam_x + tg * ray.dx[c]
        gz = ray.cam_z + tg * ray.dz[c]
        ox, oz = w.ground_origin
        gt = p.ground_texel
        col = w.ground.sample(((gx - ox) / gt).astype(np.float32), ((gz - oz) / gt).astype(np.float32), self.ground_lod[r])
        dt = p.ground_detail_texel
        det = w.ground_detail.sample((gx / dt).astype(np.float32), (gz / dt).astype(np.float32), self.ground_dlod[r])
        g_shade = np.float32(self.light.ambient + self.light.diffuse * max(0.0, -self.L[1]))
        img[idx] = col * (1.0 + (det - 0.5) * 1.3) * g_shade
        depth[idx] = tg.astype(np.float32)
        gxf = np.zeros(self.H * self.W, np.float64)
        gzf = np.zeros(self.H * self.W, np.float64)
        gxf[idx] = gx
        gzf[idx] = gz
        return gxf, gzf

    def _shade_sky(self, ray: _Rays, idx: np.ndarray, img: np.ndarray, depth: np.ndarray) -> None:
        """Sky pixels ``idx`` (flat): a function of the ray direction only, identical in both views."""
        sky = self.world.sky
        r = idx // self.W
        c = idx - r * self.W
        az = np.arctan2(ray.dx, ray.dz)
        hn = np.hypot(ray.dx, ray.dz)
        su = ((az / (2 * np.pi)) % 1.0 * sky.width).astype(np.float32)[c]
        tan_el = (-self.vc[r] / hn[c])
        sv = np.clip(tan_el / 0.5 * (sky.height - 1), 0, sky.height - 2).astype(np.float32)
        img[idx] = sky.sample(su, sv, self.sky_lod)
        depth[idx] = np.inf

    def _shown_objects(self, objects: list[PosedObject], ray: _Rays, depth: np.ndarray) -> list[PosedObject]:
        """The objects in the view frustum (within 250 m) and not hidden by the static
        scene: objects behind the facades of other streets (most of them) cost one box
        projection."""
        W, Rc, cam = self.W, ray.Rc, ray.cam
        visible = []
        for ob in objects:
            wdt, hgt_o, lng = ob.shape.size
            centre = ob.origin + ob.R @ np.array([0.0, -hgt_o / 2, 0.0])
            pc = Rc @ (centre - cam)
            rad = ob.shape.radius
            if pc[2] < -rad or np.linalg.norm(pc) > 250.0:
                continue
            if pc[2] > rad and abs(pc[0]) - rad > pc[2] * (W / 2 + 2) / self.fx:
                continue
            visible.append(ob)
        shown = []
        for ob in visible:
            wdt, hgt_o, lng = ob.shape.size
            loc = np.array([[x, y, z] for x in (-wdt / 2 - 0.4, wdt / 2 + 0.4) for y in (-hgt_o - 0.2, 0.0) for z in (-lng / 2 - 0.4, lng / 2 + 0.4)])
            corners = ob.origin + loc @ ob.R.T
            rect = self._rect(corners, Rc, cam)
            if rect is None:
                continue
            zmin = float(((corners - cam) @ Rc[2]).min())
            r0, r1, c0, c1 = rect
            if zmin > 0 and float(depth[r0:r1, c0:c1].max()) < zmin:
                continue
            shown.append(ob)
        return shown

    # -----------------------------------------------------------------------------------------
    def _rect(self, corners_map: np.ndarray, Rc: np.ndarray, cam: np.ndarray, margin: int = 2):
        pc = (corners_map - cam) @ Rc.T
        z = pc[:, 2]
        if np.all(z < _NEAR):
            return None
        if np.any(z < _NEAR):
            # the part of the box in front of the near plane is the hull of the corners in
            # front of it and of the points where the box edges cross it
            a = pc[_EDGES[:, 0]]
            b = pc[_EDGES[:, 1]]
            cross = (a[:, 2] - _NEAR) * (b[:, 2] - _NEAR) < 0
            a, b = a[cross], b[cross]
            f = (_NEAR - a[:, 2]) / (b[:, 2] - a[:, 2])
            pc = np.concatenate([pc[z >= _NEAR], a + f[:, None] * (b - a)])
            z = np.maximum(pc[:, 2], _NEAR)
        cols = self.fx * pc[:, 0] / z + self.cx
        rows = self.fy * pc[:, 1] / z + self.cy
        c0 = max(int(np.floor(cols.min())) - margin, 0)
        c1 = min(int(np.ceil(cols.max())) + margin + 1, self.W)
        r0 = max(int(np.floor(rows.min())) - margin, 0)
        r1 = min(int(np.ceil(rows.max())) + margin + 1, self.H)
        if c1 <= c0 or r1 <= r0:
            return None
        return r0, r1, c0, c1

    def _shadow(self, ob: PosedObject, img, ground_mask, gx, gz, Rc, cam) -> None:
        wdt, _, lng = ob.shape.size
        a, b = wdt / 2 + 0.35, lng / 2 + 0.35
        loc = np.array([[x, y, z] for x in (-a, a) for y in (-0.01, 0.0) for z in (-b, b)])
        corners = ob.origin + loc @ ob.R.T
        rect = self._rect(corners, Rc, cam)
        if rect is None:
            return
        r0, r1, c0, c1 = rect
        m = ground_mask[r0:r1, c0:c1]
        if not m.any():
            return
        qx = gx[r0:r1, c0:c1] - ob.origin[0]
        qz = gz[r0:r1, c0:c1] - ob.origin[2]
        lx = qx * ob.R[0, 0] + qz * ob.R[2, 0]  # R^T (q): object x
        lz = qx * ob.R[0, 2] + qz * ob.R[2, 2]  # object z
        s = (lx / (wdt / 2 + 0.1)) ** 2 + (lz / (lng / 2 + 0.1)) ** 2
        f = (1.0 - 0.55 * np.exp(-s * s)).astype(np.float32)
        sub = img[r0:r1, c0:c1]
        sub[m] *= f[m]

    def prepare(self, shapes: list[Shape]) -> None:
        """Pack the materials of ``shapes`` (all objects of a sequence) into one texture atlas."""
        index: dict[int, int] = {}
        tiles: list[np.ndarray] = []
        texels: list[float] = []
        self._mat_ids = {}
        for sh in shapes:
            ids_ = []
            for m in sh.materials:
                if id(m) not in index:
                    index[id(m)] = len(tiles)
                    tiles.append(m.image)
                    texels.append(m.texel)
                ids_.append(index[id(m)])
            self._mat_ids[id(sh)] = np.array(ids_, np.int64)
        self.materials = TileAtlas(tiles)
        self.mat_texel = np.array(texels or [1.0], np.float64)

    def _objects(self, shown: list[PosedObject], img, depth, ids, Rc, cam, lod_origin) -> None:
        """Ray casts all primitives of all shown objects in one vectorized pass.

        Every primitive contributes the pixels of its projected box as (primitive, pixel)
        pairs; the pairs are intersected together, the z-buffer keeps the nearest hit per
        pixel, and the winners are textured in one call on the material atlas.
        """
        H, W = self.H, self.W
        Rs, cs, objid, const = [], [], [], []
        for ob in shown:
            k = ob.shape.const()
            Rp, cp = ob.shape.pose_arrays(ob.phase)
            Rs.append(ob.R[None] @ Rp)  # primitive -> map
            cs.append(ob.origin[None] + cp @ ob.R.T)
            objid.append(np.full(len(Rp), ob.id, np.uint8))
            const.append((k, self._mat_ids[id(ob.shape)][k["mat"]]))
        Rw = np.concatenate(Rs)  # (P, 3, 3)
        cw = np.concatenate(cs)  # (P, 3)
        oid = np.concatenate(objid)
        slo = np.concatenate([k["slo"] for k, _ in const])
        shi = np.concatenate([k["shi"] for k, _ in const])
        qc = np.concatenate([k["qc"] for k, _ in const])
        qk2 = np.concatenate([k["qk2"] for k, _ in const])
        qv = np.concatenate([k["qv"] for k, _ in const])
        corners = np.concatenate([k["corners"] for k, _ in const])  # (P, 8, 3) primitive frame
        mat = np.concatenate([m for _, m in const])
        gain = np.concatenate([k["gain"] for k, _ in const])
        # projected boxes
        cmap = cw[:, None, :] + np.einsum("pij,pkj->pki", Rw, corners)
        pc = (cmap - cam) @ Rc.T  # (P, 8, 3) camera frame
        z = pc[..., 2]
        P = len(Rw)
        rect = np.zeros((P, 4), np.int64)
        front = np.all(z >= _NEAR, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            cols = self.fx * pc[..., 0] / z + self.cx
            rows = self.fy * pc[..., 1] / z + self.cy
        rect[:, 0] = np.floor(rows.min(1)) - 2
        rect[:, 1] = np.ceil(rows.max(1)) + 3
        rect[:, 2] = np.floor(cols.min(1)) - 2
        rect[:, 3] = np.ceil(cols.max(1)) + 3
        for j in np.flatnonzero(~front):  # boxes crossing the near plane (rare)
            rr = self._rect(cmap[j], Rc, cam, margin=2)
            rect[j] = rr if rr is not None else (0, 0, 0, 0)
        rect[:, 0:2] = np.clip(rect[:, 0:2], 0, H)
        rect[:, 2:4] = np.clip(rect[:, 2:4], 0, W)
        area = np.maximum(rect[:, 1] - rect[:, 0], 0) * np.maximum(rect[:, 3] - rect[:, 2], 0)
        zmin = z.min(1)
        # rays in the primitive frames
        Rt = np.transpose(Rw, (0, 2, 1))
        o = np.einsum("pij,pj->pi", Rt, cam[None] - cw)  # (P, 3)
        M = Rt @ Rc.T[None]  # (P, 3, 3): camera ray (u, v, 1) -> primitive frame
        o_lod = np.einsum("pij,pj->pi", Rt, lod_origin[None] - cw)  # lod_origin in primitive frames
        prm = dict(rect=rect, zmin=zmin, o=o, o_lod=o_lod, M=M, slo=slo, shi=shi, qc=qc, qk2=qk2, qv=qv, mat=mat, gain=gain, oid=oid, Rw=Rw)
        # big primitives one by one, nearest first, each skipped when what is already drawn
        # hides its whole box; then all the small ones together, minus the hidden ones
        def hidden(j: int) -> bool:
            return bool(zmin[j] > float(depth[rect[j, 0] : rect[j, 1], rect[j, 2] : rect[j, 3]].max()))

        big = np.flatnonzero(area >= 3000)
        for j in big[np.argsort(zmin[big])]:
            if not hidden(j):
                self._cast(np.array([j]), prm, img, depth, ids)
        rest = np.flatnonzero((area < 3000) & (area > 0))
        if big.size and rest.size:
            rest = np.array([j for j in rest if not hidden(j)], np.int64)
        if rest.size:
            self._cast(rest, prm, img, depth, ids)

    def _cast(self, sel: np.ndarray, prm: dict, img, depth, ids) -> None:
        """Intersect primitives ``sel`` with the rays of their projected boxes: all
        (primitive, pixel) pairs in float32, the z-buffer keeps one nearest winner per
        pixel, the winners are intersected again in float64 and shaded."""
        pairs = self._pairs(sel, prm, depth)
        if pairs is None:
            return
        row, col, pix, counts, rep = pairs
        tin, tout = self._intersect_pairs(sel, prm, row, col, rep)
        dflat = depth.reshape(-1)
        won = self._z_winners(tin, tout, pix, dflat)
        if won is None:
            return
        h_idx, ph = won
        # winners in float64: exact depth and the constraint the ray enters through
        P = len(sel)
        if P == 1:
            pw = np.zeros(len(h_idx), np.int64)
        else:  # sorted: winners grouped by primitive
            pw = np.searchsorted(np.cumsum(counts), h_idx, side="right")
        wcount = np.bincount(pw, minlength=P)

        def repw(a: np.ndarray) -> np.ndarray:  # per-primitive value -> per winner
            return np.repeat(a, wcount, axis=0)

        hits = self._entry_hits(sel, prm, repw, self.uc[col[h_idx]], self.vc[row[h_idx]])
        dflat[ph] = hits.t.astype(np.float32)
        g = sel[pw]
        img.reshape(-1)[ph] = self._shade_hits(sel, prm, repw, hits, g)
        ids.reshape(-1)[ph] = prm["oid"][g]

    def _pairs(self, sel: np.ndarray, prm: dict, depth: np.ndarray):
        """The (primitive, pixel) pairs of the boxes of ``sel``: row, col, flat pixel,
        pairs per primitive and ``rep`` (per-primitive value -> per pair); None when a
        single primitive's pixels are all nearer than it already (early z)."""
        W = self.W
        f32 = np.float32
        rect = prm["rect"][sel]
        hh = rect[:, 1] - rect[:, 0]
        ww = rect[:, 3] - rect[:, 2]
        counts = hh * ww
        N = int(counts.sum())

        def rep(a: np.ndarray) -> np.ndarray:  # per-primitive value -> per pair
            return np.repeat(a, counts)

        # float32 here; the winners are redone in float64
        local = (np.arange(N) - rep(np.cumsum(counts) - counts)).astype(f32)
        wf = rep(ww.astype(f32))
        rl = np.floor((local + f32(0.5)) / wf)
        row = (rep(rect[:, 0].astype(f32)) + rl).astype(np.int64)
        col = (rep(rect[:, 2].astype(f32)) + local - rl * wf).astype(np.int64)
        pix = row * W + col
        if len(sel) == 1:
            # a single (big) primitive: its parameters are scalars, and pixels already
            # nearer than its nearest point (early z) need no intersection at all
            idx = np.flatnonzero(depth.reshape(-1)[pix] > prm["zmin"][sel[0]])
            if idx.size == 0:
                return None
            row, col, pix = row[idx], col[idx], pix[idx]

            def rep(a: np.ndarray) -> np.ndarray:  # noqa: F811 - scalar broadcast
                return a[0]

        return row, col, pix, counts, rep

    def _intersect_pairs(self, sel: np.ndarray, prm: dict, row: np.ndarray, col: np.ndarray,
                         rep) -> tuple[np.ndarray, np.ndarray]:
        """Entry and exit ray parameters (float32) of every pair: the primitive is the
        intersection of up to three slabs and two quadrics."""
        f32 = np.float32
        N = len(row)
        M = prm["M"][sel].astype(f32)
        o = prm["o"][sel].astype(f32)
        slo = prm["slo"][sel].astype(f32)
        shi = prm["shi"][sel].astype(f32)
        # absent quadrics: k = 0, c = 0 gives t in (-1e10, 1e10): always satisfied
        qc = np.where(prm["qv"][sel][..., None], prm["qc"][sel], 0.0).astype(f32)
        qk2 = np.where(prm["qv"][sel][..., None], prm["qk2"][sel], 0.0).astype(f32)
        u = self.uc32[col]
        v = self.vc32[row]
        D = [rep(M[:, i, 0]) * u + rep(M[:, i, 1]) * v + rep(M[:, i, 2]) for i in range(3)]
        O = [rep(o[:, i]) for i in range(3)]
        tin = np.full(N, _NEAR, f32)
        tout = np.full(N, np.inf, f32)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for i in range(3):
                if not (slo[:, i] > -_BIG_SLAB).any():
                    continue
                inv = f32(1.0) / D[i]
                t1 = (rep(slo[:, i]) - O[i]) * inv
                t2 = (rep(shi[:, i]) - O[i]) * inv
                np.maximum(tin, np.minimum(t1, t2), out=tin)
                np.minimum(tout, np.maximum(t1, t2), out=tout)
            for q in range(2):
                if not prm["qv"][sel][:, q].any():
                    continue
                k = [rep(qk2[:, q, i]) for i in range(3)]
                oc = [O[i] - rep(qc[:, q, i]) for i in range(3)]
                kd = [k[i] * D[i] for i in range(3)]
                qa = np.maximum(kd[0] * D[0] + kd[1] * D[1] + kd[2] * D[2], f32(1e-20))
                qb = kd[0] * oc[0] + kd[1] * oc[1] + kd[2] * oc[2]
                qcc = k[0] * oc[0] * oc[0] + k[1] * oc[1] * oc[1] + k[2] * oc[2] * oc[2] - f32(1.0)
                # a miss (disc < 0) gives tn = tf: an empty interval, no hit
                sq = np.sqrt(np.maximum(qb * qb - qa * qcc, f32(0.0)))
                np.maximum(tin, (-qb - sq) / qa, out=tin)
                np.minimum(tout, (-qb + sq) / qa, out=tout)
        return tin, tout

    @staticmethod
    def _z_winners(tin: np.ndarray, tout: np.ndarray, pix: np.ndarray,
                   dflat: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The pairs that hit nearer than the z-buffer ``dflat`` (updated in place), one
        winner per pixel (exact ties: one of them); (pair index, pixel) or None."""
        hit = (tin > _NEAR) & (tin < tout)
        hit &= tin < dflat[pix]
        h_idx = np.flatnonzero(hit)
        if h_idx.size == 0:
            return None
        th = tin[h_idx]
        ph = pix[h_idx]
        np.minimum.at(dflat, ph, th)
        win = np.flatnonzero(th == dflat[ph])
        h_idx = h_idx[win]
        ph = ph[win]
        claim = np.full(dflat.size, -1, np.int64)  # exact ties: one winner per pixel
        claim[ph] = np.arange(len(ph))
        keep = np.flatnonzero(claim[ph] == np.arange(len(ph)))
        return h_idx[keep], ph[keep]

    @staticmethod
    def _entry_hits(sel: np.ndarray, prm: dict, repw, uu: np.ndarray, vv: np.ndarray) -> _Hits:
        """The winners' rays again in float64: entry depth and the constraint entered
        through (0..2: slab axis, 3..4: quadric)."""
        Ms = prm["M"][sel]
        Dw = [repw(Ms[:, i, 0]) * uu + repw(Ms[:, i, 1]) * vv + repw(Ms[:, i, 2]) for i in range(3)]
        os_ = prm["o"][sel]
        ow = [repw(os_[:, i]) for i in range(3)]
        n = len(uu)
        t = np.full(n, -np.inf)
        wc = np.zeros(n, np.int8)
        slo_g = repw(prm["slo"][sel])
        shi_g = repw(prm["shi"][sel])
        qv_g = repw(prm["qv"][sel])
        qk2_g = repw(prm["qk2"][sel])
        qc_g = repw(prm["qc"][sel])
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for i in range(3):
                lo_i = slo_g[:, i]
                if not (lo_i > -_BIG_SLAB).any():
                    continue
                inv = 1.0 / Dw[i]
                tn = np.minimum((lo_i - ow[i]) * inv, (shi_g[:, i] - ow[i]) * inv)
                upd = (tn > t) & (lo_i > -_BIG_SLAB)
                t = np.where(upd, tn, t)
                wc = np.where(upd, i, wc)
            for q in range(2):
                if not qv_g[:, q].any():
                    continue
                k = [qk2_g[:, q, i] for i in range(3)]
                oc = [ow[i] - qc_g[:, q, i] for i in range(3)]
                qa = np.maximum(k[0] * Dw[0] * Dw[0] + k[1] * Dw[1] * Dw[1] + k[2] * Dw[2] * Dw[2], 1e-20)
                qb = k[0] * oc[0] * Dw[0] + k[1] * oc[1] * Dw[1] + k[2] * oc[2] * Dw[2]
                qcc = k[0] * oc[0] * oc[0] + k[1] * oc[1] * oc[1] + k[2] * oc[2] * oc[2] - 1.0
                tn = (-qb - np.sqrt(np.maximum(qb * qb - qa * qcc, 0.0))) / qa
                upd = (tn > t) & qv_g[:, q]
                t = np.where(upd, tn, t)
                wc = np.where(upd, 3 + q, wc)
        return _Hits(t, wc, Dw, ow, qk2_g, qc_g)

    def _shade_hits(self, sel: np.ndarray, prm: dict, repw, hits: _Hits, g: np.ndarray) -> np.ndarray:
        """Grey levels of the winners (primitives ``g``): normal of the entering
        constraint, texture by the dominant normal axis, mip level from lod_origin."""
        t, wc, Dw, ow, qk2_g, qc_g = hits.t, hits.wc, hits.Dw, hits.ow, hits.qk2, hits.qc
        n = len(t)
        Pp = [ow[i] + t * Dw[i] for i in range(3)]
        nrm = [np.zeros(n) for _ in range(3)]
        for i in range(3):
            m_ = wc == i
            nrm[i] = np.where(m_, -np.sign(Dw[i]), nrm[i])
        for q in range(2):
            m_ = wc == 3 + q
            if m_.any():
                for i in range(3):
                    nrm[i] = np.where(m_, qk2_g[:, q, i] * (Pp[i] - qc_g[:, q, i]), nrm[i])
        nl = np.sqrt(nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2]) + 1e-12
        nrm = [x / nl for x in nrm]
        an = [np.abs(x) for x in nrm]
        use_x = (an[0] >= an[1]) & (an[0] >= an[2])
        use_z = ~use_x & (an[2] >= an[1])
        tu = np.where(use_x, Pp[2], Pp[0])
        tv = np.where(use_x | use_z, Pp[1], Pp[2])
        ol = repw(prm["o_lod"][sel])  # incidence seen from lod_origin: same in both views
        vl = [Pp[i] - ol[:, i] for i in range(3)]
        dl = np.sqrt(vl[0] * vl[0] + vl[1] * vl[1] + vl[2] * vl[2])
        cos = np.abs(nrm[0] * vl[0] + nrm[1] * vl[1] + nrm[2] * vl[2]) / dl
        m = prm["mat"][g]
        tx = self.mat_texel[m]
        lod = np.log2(np.maximum(t / (self.fx * tx) / np.maximum(cos, 0.25), 1e-6)).astype(np.float32)
        alb = self.materials.sample(m, (tu / tx).astype(np.float32), (tv / tx).astype(np.float32), lod)
        Lp = repw(self.L @ prm["Rw"][sel])  # light direction in each primitive frame
        ndl = Lp[:, 0] * nrm[0] + Lp[:, 1] * nrm[1] + Lp[:, 2] * nrm[2]
        shade = self.light.ambient + self.light.diffuse * np.maximum(0.0, ndl)
        return (alb * prm["gain"][g] * shade * (255.0 * self.light.exposure)).astype(np.float32)
