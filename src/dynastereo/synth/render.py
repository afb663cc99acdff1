"""Vectorised ray casting of one view of the synthetic world.

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

from .objects import Prim, Shape
from .world import World

SKY_ID = 0
_NEAR = 0.05
_ANISO = 0.3  # vertical footprint weight in the mip level (horizontal is exact: 1.0)


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
    def render(self, cam_x: float, cam_z: float, heading: float, objects: list[PosedObject]) -> View:
        w = self.world
        p = w.params
        H, W, K = self.H, self.W, self.K
        h = p.cam_height
        cth, sth = np.cos(heading), np.sin(heading)
        dx = self.uc * cth + sth  # (W,) horizontal ray direction, map frame
        dz = -self.uc * sth + cth

        # ---- facades, per column: K nearest front-facing hits
        rel = w.seg_p0 - np.array([cam_x, cam_z])  # (S, 2)
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
        topk = np.where(valid, h - w.bld_height[bld], np.inf)  # y of the roof (y down)
        tk_f = np.where(valid, tk, 1e9)

        # ---- per pixel: first candidate whose vertical extent contains the ray
        vc = self.vc
        sel = np.full((H, W), kk + 1, np.int8)  # kk+1 = sky
        sel[vc > 0, :] = kk  # kk = ground
        for k in range(kk - 1, -1, -1):
            y = vc[:, None] * tk_f[k][None, :]
            hit = (y >= topk[k][None, :]) & (y <= h)
            sel[hit] = k
        self_flat = sel.ravel()
        img = np.empty(H * W, np.float32)
        depth = np.empty(H * W, np.float32)
        ids = np.zeros((H, W), np.uint8)

        # ---- facade shading
        idx = np.flatnonzero(self_flat < kk)
        if idx.size:
            r = idx // W
            c = idx - r * W
            kc = self_flat[idx].astype(np.int64) * W + c
            nk = w.seg_n[segk]  # (kk, W, 2)
            er = np.array([cth, -sth])
            nd = nk[..., 0] * dx[None, :] + nk[..., 1] * dz[None, :]
            ne = nk[..., 0] * er[0] + nk[..., 1] * er[1]
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(valid, ne / nd, 0.0)
            fpx = tk_f / self.fx * np.hypot(er[0] - dx[None, :] * ratio, er[1] - dz[None, :] * ratio)
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
            img[idx] = col * (1.0 + strength * (det - 0.5) * 1.2) * shade.ravel()[kc]
            depth[idx] = tpix

        # ---- ground
        idx = np.flatnonzero(self_flat == kk)
        if idx.size:
            r = idx // W
            c = idx - r * W
            tg = self.t_ground[r]
            gx = cam_x + tg * dx[c]
            gz = cam_z + tg * dz[c]
            ox, oz = w.ground_origin
            gt = p.ground_texel
            col = w.ground.sample(((gx - ox) / gt).astype(np.float32), ((gz - oz) / gt).astype(np.float32), self.ground_lod[r])
            dt = p.ground_detail_texel
            det = w.ground_detail.sample(
                np.mod(gx / dt, 4096.0).astype(np.float32), np.mod(gz / dt, 4096.0).astype(np.float32), self.ground_dlod[r]
            )
            g_shade = np.float32(self.light.ambient + self.light.diffuse * max(0.0, -self.L[1]))
            img[idx] = col * (1.0 + (det - 0.5) * 1.1) * g_shade
            depth[idx] = tg.astype(np.float32)
            gxf = np.empty(H * W, np.float64)
            gzf = np.empty(H * W, np.float64)
            gxf[idx] = gx
            gzf[idx] = gz
        else:
            gxf = gzf = None

        # ---- sky (a function of the ray direction only: identical in both views)
        idx = np.flatnonzero(self_flat == kk + 1)
        if idx.size:
            r = idx // W
            c = idx - r * W
            az = np.arctan2(dx, dz)
            hn = np.hypot(dx, dz)
            su = ((az / (2 * np.pi)) % 1.0 * w.sky.width).astype(np.float32)[c]
            tan_el = (-self.vc[r] / hn[c])
            sv = np.clip(tan_el / 0.5 * (w.sky.height - 1), 0, w.sky.height - 2).astype(np.float32)
            img[idx] = w.sky.sample(su, sv, self.sky_lod)
            depth[idx] = np.inf

        img = img.reshape(H, W)
        depth = depth.reshape(H, W)
        img *= np.float32(255.0 * self.light.exposure)

        # ---- objects: soft contact shadows on the ground, then the objects themselves
        fwd3 = np.array([sth, 0.0, cth])
        rgt3 = np.array([cth, 0.0, -sth])
        down3 = np.array([0.0, 1.0, 0.0])
        cam = np.array([cam_x, 0.0, cam_z])
        Rc = np.stack([rgt3, down3, fwd3])  # map -> camera rotation (rows)
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
        if gxf is not None:
            sel2 = sel
            for ob in visible:
                self._shadow(ob, img, sel2 == kk, gxf.reshape(H, W), gzf.reshape(H, W), Rc, cam)
        for ob in visible:
            for prim in ob.shape.prims(ob.phase):
                self._prim(ob, prim, img, depth, ids, Rc, cam)
        return View(img, depth, ids)

    # -----------------------------------------------------------------------------------------
    def _rect(self, corners_map: np.ndarray, Rc: np.ndarray, cam: np.ndarray, margin: int = 2):
        pc = (corners_map - cam) @ Rc.T
        z = pc[:, 2]
        if np.all(z < _NEAR):
            return None
        if np.any(z < _NEAR):
            return 0, self.H, 0, self.W
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
        loc = np.array([[-a, 0, -b], [a, 0, -b], [a, 0, b], [-a, 0, b]])
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

    def _prim(self, ob: PosedObject, prim: Prim, img, depth, ids, Rc, cam) -> None:
        Rw = ob.R @ prim.R  # primitive -> map
        cw = ob.origin + ob.R @ prim.c
        lo, hi = prim.lo, prim.hi
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        rect = self._rect(cw + corners @ Rw.T, Rc, cam)
        if rect is None:
            return
        r0, r1, c0, c1 = rect
        # rays in the primitive frame: origin o, direction D = U*a + V*b + c
        Rt = Rw.T
        o = Rt @ (cam - cw)
        A = Rt @ Rc[0]
        Bv = Rt @ Rc[1]
        C = Rt @ Rc[2]
        U = self.uc[c0:c1][None, :]
        V = self.vc[r0:r1][:, None]
        D = [U * A[i] + V * Bv[i] + C[i] for i in range(3)]
        shape = (r1 - r0, c1 - c0)
        tin = np.full(shape, _NEAR)
        tout = np.full(shape, np.inf)
        which = np.full(shape, -1, np.int8)
        j = 0
        with np.errstate(divide="ignore", invalid="ignore"):
            for ax, l, hgh in prim.slabs:
                inv = 1.0 / D[ax]
                t1 = (l - o[ax]) * inv
                t2 = (hgh - o[ax]) * inv
                tn = np.minimum(t1, t2)
                tf = np.maximum(t1, t2)
                upd = tn > tin
                tin = np.where(upd, tn, tin)
                which[upd] = j
                np.minimum(tout, tf, out=tout)
                j += 1
            for cq, kq in prim.quads:
                oc = o - cq
                qa = sum((kq[i] * kq[i]) * D[i] * D[i] for i in range(3) if kq[i] != 0.0)
                qb = sum((kq[i] * kq[i] * oc[i]) * D[i] for i in range(3) if kq[i] != 0.0)
                qc = float(sum((kq[i] * oc[i]) ** 2 for i in range(3))) - 1.0
                qa = np.maximum(qa, 1e-20)
                disc = qb * qb - qa * qc
                sq = np.sqrt(np.maximum(disc, 0.0))
                tn = np.where(disc >= 0, (-qb - sq) / qa, np.inf)
                tf = np.where(disc >= 0, (-qb + sq) / qa, -np.inf)
                upd = tn > tin
                tin = np.where(upd, tn, tin)
                which[upd] = j
                np.minimum(tout, tf, out=tout)
                j += 1
        dsub = depth[r0:r1, c0:c1]
        win = (which >= 0) & (tin < tout) & (tin < dsub)
        if not win.any():
            return
        t = tin[win]
        Dw = [d[win] for d in D]
        P = [o[i] + t * Dw[i] for i in range(3)]
        wsel = which[win]
        nrm = [np.zeros_like(t) for _ in range(3)]
        j = 0
        for ax, _, _ in prim.slabs:
            m = wsel == j
            nrm[ax] = np.where(m, -np.sign(Dw[ax]), nrm[ax])
            j += 1
        for cq, kq in prim.quads:
            m = wsel == j
            for i in range(3):
                nrm[i] = np.where(m, kq[i] * kq[i] * (P[i] - cq[i]), nrm[i])
            j += 1
        nl = np.sqrt(nrm[0] ** 2 + nrm[1] ** 2 + nrm[2] ** 2) + 1e-12
        nrm = [x / nl for x in nrm]
        an = [np.abs(x) for x in nrm]
        use_x = (an[0] >= an[1]) & (an[0] >= an[2])
        use_z = ~use_x & (an[2] >= an[1])
        tu = np.where(use_x, P[2], P[0])
        tv = np.where(use_x | use_z, P[1], P[2])
        dl = np.sqrt(Dw[0] ** 2 + Dw[1] ** 2 + Dw[2] ** 2)
        cos = np.abs(nrm[0] * Dw[0] + nrm[1] * Dw[1] + nrm[2] * Dw[2]) / dl
        mat = ob.shape.materials[prim.material]
        fp = t / self.fx / np.maximum(cos, 0.25)
        lod = np.log2(np.maximum(fp, 1e-6) / mat.texel).astype(np.float32)
        alb = mat.sample((tu / mat.texel).astype(np.float32), (tv / mat.texel).astype(np.float32), lod)
        nw = Rw @ np.stack(nrm)  # map-frame normals (3, n)
        shade = self.light.ambient + self.light.diffuse * np.maximum(0.0, self.L @ nw)
        val = (alb * (prim.gain * shade) * (255.0 * self.light.exposure)).astype(np.float32)
        img[r0:r1, c0:c1][win] = val
        dsub[win] = t.astype(np.float32)
        ids[r0:r1, c0:c1][win] = ob.id
