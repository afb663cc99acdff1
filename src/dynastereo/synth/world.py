"""The static synthetic city: a ring road around one block, side streets, facades, ground, sky.

Map frame (internal): x right, y DOWN, z "north"; the ground is the plane ``y = cam_height``
and the camera centre moves in the plane ``y = 0`` (upright camera, yaw only).  The
ring road runs around the inner block ``|x| <= A, |z| <= B``; a point of the road is
addressed by ``(side, sigma, d)``: side 0..3 of the block, ``sigma`` metres along it in
the driving direction, ``d`` metres away from the block facade.  Driving direction is
clockwise seen from above with the block on the RIGHT (right-hand traffic, right turns
at the corners); the contour at offset ``d`` is a rounded rectangle (corner radius ``d``)
parametrized by arc length ``s`` (:meth:`RingRoad.contour`).

Cross section (distance from the inner facade): sidewalk 0-4 m, parking 4-6.5, the
camera's lane 6.5-10 (centre 8.25), oncoming lane 10-13.5 (centre 11.75), parking
13.5-16, sidewalk 16-20, outer facades at 20 m.  In the middle of every side a side
street (12 m between facades) leaves outwards (40 m, closed by a facade) and a dead end
street (25 m) goes into the block: four 4-way intersections with zebra crossings.

Facades are one-sided vertical rectangles (visible from the street side) with a
per-building roofline; everything above them is sky at infinity.  The world is fully
determined by the seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .textures import MipTexture, asphalt_detail, facade_detail, fractal_noise

TAU = 2.0 * np.pi


def fwd(theta: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Forward unit vector (x, z) of a camera with heading ``theta`` (0 = +z, pi/2 = +x)."""
    return np.sin(theta), np.cos(theta)


def right(theta: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Right unit vector (x, z) of a camera with heading ``theta``."""
    return np.cos(theta), -np.sin(theta)


@dataclass(frozen=True)
class WorldParams:
    A: float = 55.0  # inner block half extent along x
    B: float = 30.0  # inner block half extent along z
    sidewalk: float = 4.0
    parking: float = 2.5
    lane: float = 3.5
    gap: float = 12.0  # side street width between facades
    street_road: float = 8.0  # side street carriageway width
    inner_depth: float = 25.0  # dead-end streets into the block
    outer_depth: float = 40.0  # side streets leaving the ring
    cam_height: float = 1.65
    ground_texel: float = 0.10
    facade_texel: float = 0.08
    facade_detail_texel: float = 0.02
    ground_detail_texel: float = 0.015
    hmin: float = 8.0
    hmax: float = 22.0

    # cross section offsets (distance from the inner facade)
    @property
    def d_inner_curb(self) -> float:
        return self.sidewalk

    @property
    def d_park_in(self) -> float:
        return self.sidewalk + self.parking / 2

    @property
    def d_lane_in(self) -> float:
        return self.sidewalk + self.parking + self.lane / 2

    @property
    def d_centre(self) -> float:
        return self.sidewalk + self.parking + self.lane

    @property
    def d_lane_out(self) -> float:
        return self.sidewalk + self.parking + 1.5 * self.lane

    @property
    def d_park_out(self) -> float:
        return self.sidewalk + 1.5 * self.parking + 2 * self.lane

    @property
    def d_outer_curb(self) -> float:
        return self.sidewalk + 2 * self.parking + 2 * self.lane

    @property
    def d_outer_wall(self) -> float:
        return 2 * self.sidewalk + 2 * self.parking + 2 * self.lane


class RingRoad:
    """Geometry of the ring road around the inner block (vectorized)."""

    def __init__(self, A: float, B: float):
        self.A = float(A)
        self.B = float(B)
        self.side_len = np.array([2 * B, 2 * A, 2 * B, 2 * A])
        self.heading = np.array([0.0, 0.5 * np.pi, np.pi, 1.5 * np.pi])
        self.start = np.array([(-A, -B), (-A, B), (A, B), (A, -B)], dtype=np.float64)

    def length(self, d: float) -> float:
        return float(self.side_len.sum() + TAU * d)

    def side_point(self, side: int | np.ndarray, sigma, d) -> tuple[np.ndarray, np.ndarray]:
        """World (x, z) of side coordinates; ``sigma`` along the side, ``d`` away from the block."""
        side = np.asarray(side) % 4
        th = self.heading[side]
        fx, fz = fwd(th)
        rx, rz = right(th)
        sx = self.start[side, 0]
        sz = self.start[side, 1]
        return sx + sigma * fx - d * rx, sz + sigma * fz - d * rz

    def contour(self, s, d: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, z, heading) at arc length ``s`` (wraps) of the contour at offset ``d``."""
        s = np.asarray(s, dtype=np.float64)
        arc = 0.5 * np.pi * d
        seg_len = np.array([self.side_len[0], arc, self.side_len[1], arc, self.side_len[2], arc, self.side_len[3], arc])
        bounds = np.concatenate([[0.0], np.cumsum(seg_len)])
        L = bounds[-1]
        sm = np.mod(s, L)
        seg = np.clip(np.searchsorted(bounds, sm, side="right") - 1, 0, 7)
        local = sm - bounds[seg]
        side = seg // 2
        is_arc = (seg % 2) == 1
        th0 = self.heading[side]
        # straight part
        xs, zs = self.side_point(side, local, d)
        # arc part: centre = end corner of the side = start of the next side
        alpha = np.where(is_arc, local / max(d, 1e-9), 0.0)
        th = th0 + alpha
        cx = self.start[(side + 1) % 4, 0]
        cz = self.start[(side + 1) % 4, 1]
        rx, rz = right(th)
        xa = cx - d * rx
        za = cz - d * rz
        x = np.where(is_arc, xa, xs)
        z = np.where(is_arc, za, zs)
        return x, z, np.where(is_arc, th, th0)

    def segment_of(self, s, d: float) -> tuple[np.ndarray, np.ndarray]:
        """(segment index 0..7 -- even = straight side, odd = corner arc, local arc length)."""
        s = np.asarray(s, dtype=np.float64)
        arc = 0.5 * np.pi * d
        seg_len = np.array([self.side_len[0], arc, self.side_len[1], arc, self.side_len[2], arc, self.side_len[3], arc])
        bounds = np.concatenate([[0.0], np.cumsum(seg_len)])
        sm = np.mod(s, bounds[-1])
        seg = np.clip(np.searchsorted(bounds, sm, side="right") - 1, 0, 7)
        return seg, sm - bounds[seg]

    def _bounds(self, d: float) -> np.ndarray:
        arc = 0.5 * np.pi * d
        seg_len = np.array([self.side_len[0], arc, self.side_len[1], arc, self.side_len[2], arc, self.side_len[3], arc])
        return np.concatenate([[0.0], np.cumsum(seg_len)])

    def phi(self, s, d: float) -> np.ndarray:
        """Contour-independent position: segment index + fraction (0..8, unwrapped with s)."""
        s = np.asarray(s, dtype=np.float64)
        b = self._bounds(d)
        L = b[-1]
        turns = np.floor(s / L)
        sm = s - turns * L
        seg = np.clip(np.searchsorted(b, sm, side="right") - 1, 0, 7)
        frac = (sm - b[seg]) / np.maximum(b[seg + 1] - b[seg], 1e-9)
        return turns * 8 + seg + frac

    def s_of_phi(self, phi, d: float) -> np.ndarray:
        """Inverse of :meth:`phi` on the contour at offset ``d``."""
        phi = np.asarray(phi, dtype=np.float64)
        b = self._bounds(d)
        turns = np.floor(phi / 8)
        pm = phi - turns * 8
        seg = np.clip(np.floor(pm).astype(int), 0, 7)
        return turns * b[-1] + b[seg] + (pm - seg) * (b[seg + 1] - b[seg])

    def s_of_side(self, side: int, sigma: float, d: float) -> float:
        """Arc length on the contour at offset ``d`` of side coordinates (side, sigma)."""
        arc = 0.5 * np.pi * d
        return float(sum(self.side_len[i] + arc for i in range(side)) + sigma)


@dataclass
class Segment:
    """One-sided vertical facade rectangle between p0 and p1 (x, z) on the ground."""

    p0: np.ndarray
    p1: np.ndarray
    normal: np.ndarray  # unit (x, z), pointing to the visible side
    length: float = 0.0
    offset: float = 0.0  # start in the global facade coordinate U (metres)
    band: int = 0
    x_texel: float = 0.0  # atlas column of u = 0


@dataclass
class Building:
    u0: float  # global facade coordinate U of its left edge
    u1: float
    height: float
    detail: float  # strength of the brick/plaster detail texture


@dataclass
class World:
    params: WorldParams
    ring: RingRoad
    segments: list[Segment]
    buildings: list[Building]
    facade: MipTexture
    facade_detail: MipTexture
    ground: MipTexture
    ground_detail: MipTexture
    sky: MipTexture
    ground_origin: tuple[float, float]  # world (x, z) of ground texel (0, 0)
    facade_height: float  # metres covered by one atlas band (above the ground)
    band_stride: int  # atlas rows between bands
    # packed per-segment / per-building arrays for the renderer
    seg_p0: np.ndarray = field(default=None)  # type: ignore[assignment]
    seg_e: np.ndarray = field(default=None)  # type: ignore[assignment]
    seg_n: np.ndarray = field(default=None)  # type: ignore[assignment]
    seg_len: np.ndarray = field(default=None)  # type: ignore[assignment]
    seg_off: np.ndarray = field(default=None)  # type: ignore[assignment]
    seg_band_y: np.ndarray = field(default=None)  # type: ignore[assignment]
    seg_xt: np.ndarray = field(default=None)  # type: ignore[assignment]
    bld_u0: np.ndarray = field(default=None)  # type: ignore[assignment]
    bld_height: np.ndarray = field(default=None)  # type: ignore[assignment]
    bld_detail: np.ndarray = field(default=None)  # type: ignore[assignment]
    intersections: list[tuple[int, float]] = field(default_factory=list)  # (side, sigma of centre)

    def pack(self) -> None:
        S = self.segments
        self.seg_p0 = np.array([s.p0 for s in S], np.float64)
        self.seg_e = np.array([(s.p1 - s.p0) / max(s.length, 1e-9) for s in S], np.float64)
        self.seg_n = np.array([s.normal for s in S], np.float64)
        self.seg_len = np.array([s.length for s in S], np.float64)
        self.seg_off = np.array([s.offset for s in S], np.float64)
        self.seg_band_y = np.array([s.band * self.band_stride for s in S], np.float32)
        self.seg_xt = np.array([s.x_texel for s in S], np.float64)
        self.bld_u0 = np.array([b.u0 for b in self.buildings], np.float64)
        self.bld_height = np.array([b.height for b in self.buildings], np.float64)
        self.bld_detail = np.array([b.detail for b in self.buildings], np.float32)

    def building_at(self, U: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.bld_u0, U, side="right") - 1, 0, len(self.buildings) - 1)


# ---------------------------------------------------------------------------------------------


def _wall_segments(p: WorldParams, ring: RingRoad) -> tuple[list[Segment], list[tuple[int, float]]]:
    segs: list[Segment] = []
    inters: list[tuple[int, float]] = []
    g = p.gap / 2
    D = p.d_outer_wall

    def add(side: int, s0: float, d0: float, s1: float, d1: float, normal_kind: str) -> None:
        x0, z0 = ring.side_point(side, s0, d0)
        x1, z1 = ring.side_point(side, s1, d1)
        th = ring.heading[side]
        fx, fz = fwd(th)
        rx, rz = right(th)
        n = {"-r": (-rx, -rz), "+r": (rx, rz), "+f": (fx, fz), "-f": (-fx, -fz)}[normal_kind]
        p0 = np.array([float(x0), float(z0)])
        p1 = np.array([float(x1), float(z1)])
        segs.append(Segment(p0, p1, np.array(n, float), float(np.hypot(*(p1 - p0)))))

    for side in range(4):
        L = float(ring.side_len[side])
        mid = L / 2
        inters.append((side, mid))
        # inner block facades (d = 0) facing the road, with the dead-end street gap
        add(side, 0.0, 0.0, mid - g, 0.0, "-r")
        add(side, mid + g, 0.0, L, 0.0, "-r")
        # dead-end street into the block
        add(side, mid - g, 0.0, mid - g, -p.inner_depth, "+f")
        add(side, mid + g, -p.inner_depth, mid + g, 0.0, "-f")
        add(side, mid - g, -p.inner_depth, mid + g, -p.inner_depth, "-r")
        # outer facades (d = D) facing the block, with the side street gap
        add(side, -D, D, mid - g, D, "+r")
        add(side, mid + g, D, L + D, D, "+r")
        # side street leaving the ring
        add(side, mid - g, D, mid - g, D + p.outer_depth, "+f")
        add(side, mid + g, D + p.outer_depth, mid + g, D, "-f")
        add(side, mid - g, D + p.outer_depth, mid + g, D + p.outer_depth, "+r")
    return segs, inters


def _layout_buildings(rng: np.random.Generator, p: WorldParams, segs: list[Segment]) -> list[Building]:
    """Split every segment into buildings; assign global U offsets and atlas bands."""
    margin = 2.0  # metres of atlas between segments (mip bleeding)
    band_w = 4096
    band_m = band_w * p.facade_texel
    buildings: list[Building] = []
    band, x_m = 0, margin
    U = 0.0
    for s in segs:
        need = s.length + 2 * margin
        if x_m + need > band_m:
            band += 1
            x_m = margin
        s.band = band
        s.x_texel = (x_m + margin) / p.facade_texel
        s.offset = U + margin
        x_m += need
        # buildings along the segment
        u = 0.0
        while u < s.length - 1e-6:
            w = float(rng.uniform(8.0, 22.0))
            if s.length - (u + w) < 5.0:
                w = s.length - u
            h = float(rng.uniform(p.hmin, p.hmax))
            buildings.append(Building(s.offset + u, s.offset + u + w, h, float(rng.uniform(0.5, 1.0))))
            u += w
        U += need
    return buildings


def _facade_atlas(rng: np.random.Generator, p: WorldParams, segs: list[Segment], blds: list[Building]):
    tx = p.facade_texel
    H_m = p.hmax + 2.0
    rows = int(np.ceil(H_m / tx))
    band_rows = rows + 32
    nb = max(s.band for s in segs) + 1
    width = 4096
    atlas = np.full((nb * band_rows, width), 0.5, np.float32)
    noise = cv2.resize(
        rng.uniform(-1, 1, (nb * band_rows // 16 + 1, width // 16 + 1)).astype(np.float32),
        (width, nb * band_rows),
        interpolation=cv2.INTER_CUBIC,
    )
    noise += 0.5 * cv2.resize(
        rng.uniform(-1, 1, (nb * band_rows // 4 + 1, width // 4 + 1)).astype(np.float32),
        (width, nb * band_rows),
        interpolation=cv2.INTER_LINEAR,
    )
    hts_all = (H_m - np.arange(rows) * tx).astype(np.float32)  # height above ground of each atlas row
    seg_by_off = sorted(segs, key=lambda s: s.offset)
    for b in blds:
        s = next(sg for sg in reversed(seg_by_off) if sg.offset <= b.u0 + 1e-9)
        y0 = s.band * band_rows
        c0 = int(np.floor(s.x_texel + (b.u0 - s.offset) / tx))
        c1 = int(np.ceil(s.x_texel + (b.u1 - s.offset) / tx)) + 1
        c0, c1 = max(c0, 0), min(c1, width)
        if c1 <= c0:
            continue
        ub = ((np.arange(c0, c1) - s.x_texel) * tx + s.offset - b.u0).astype(np.float32)  # metres in building
        img = _building_facade(rng, b, ub, hts_all[:, None], noise[y0 : y0 + rows, c0:c1])
        atlas[y0 : y0 + rows, c0:c1] = img
        # below ground (only reached by bilinear taps): replicate the plinth
        atlas[y0 + rows : y0 + band_rows, c0:c1] = img[-1:, :]
    # margins between segments replicate the segment ends (mip levels bleed into them)
    m_t = int(2.0 / tx)
    for s in segs:
        y0 = s.band * band_rows
        a = int(np.floor(s.x_texel))
        b = min(int(np.ceil(s.x_texel + s.length / tx)), width - 1)
        atlas[y0 : y0 + band_rows, max(a - m_t, 0) : a] = atlas[y0 : y0 + band_rows, a : a + 1]
        atlas[y0 : y0 + band_rows, b + 1 : min(b + 1 + m_t, width)] = atlas[y0 : y0 + band_rows, b : b + 1]
    # soften the 1-texel steps of window frames (magnified close up they would be hard ramps)
    atlas = cv2.GaussianBlur(atlas, (0, 0), 0.5)
    return np.clip(atlas, 0.02, 0.98), H_m, band_rows


def _building_facade(rng: np.random.Generator, b: Building, ub: np.ndarray, hg: np.ndarray,
                     noise: np.ndarray) -> np.ndarray:
    """One building's facade texels: ``ub`` metres along the building (columns), ``hg``
    height above ground (rows, a column vector), ``noise`` the atlas noise there.  The
    steps draw from ``rng`` in a fixed order (the world is a function of the seed)."""
    bw = b.u1 - b.u0
    tone = rng.uniform(0.35, 0.8)
    img = tone + 0.06 * noise
    img, gf = _upper_floors(rng, img, tone, b, bw, ub, hg)
    img, shop = _shop_fronts(rng, img, b, gf, ub, hg, noise)
    img = _posters(rng, img, bw, gf, shop, ub, hg)
    # plinth and cornice; above the roof: cornice colour (never seen, avoids mip bleeding)
    img = np.where(hg < 0.35, tone * 0.6, img)
    corn = hg > b.height - 0.6
    img = np.where(corn, tone * 0.8, img)
    img = np.where(np.abs(hg - (b.height - 0.6)) < 0.1, tone * 0.5, img)
    return img


def _upper_floors(rng: np.random.Generator, img: np.ndarray, tone: float, b: Building, bw: float,
                  ub: np.ndarray, hg: np.ndarray) -> tuple[np.ndarray, float]:
    """Floors and windows (frames, glass, curtains, mullions, string courses); returns
    the texels and the ground floor's height."""
    fh = rng.uniform(2.9, 3.6)
    gf = rng.uniform(3.6, 4.6)  # ground floor height
    sp = rng.uniform(2.4, 3.6)
    ww = rng.uniform(0.9, min(1.6, sp - 0.6))
    wh = rng.uniform(1.2, min(1.9, fh - 1.0))
    n_cols = max(1, int((bw - 1.0) // sp))
    m0 = (bw - n_cols * sp) / 2
    fxw = (ub - m0) / sp
    kx = np.floor(fxw)
    dxw = np.abs(fxw - kx - 0.5) * sp
    col_in = (kx >= 0) & (kx < n_cols)
    fz = (hg - gf) / fh
    fi = np.floor(fz)
    z = (fz - fi) * fh
    row_ok = (fi >= 0) & (hg < b.height - 1.0)
    win_r = row_ok & (z > 0.9) & (z < 0.9 + wh)
    frm_r = row_ok & (z > 0.82) & (z < 0.98 + wh)
    win = win_r & (col_in & (dxw < ww / 2))[None, :]
    frm = frm_r & (col_in & (dxw < ww / 2 + 0.09))[None, :]
    frame_tone = float(np.clip(tone + rng.choice([-0.3, 0.25]), 0.05, 0.95))
    img = np.where(frm, frame_tone, img)
    gtab = rng.uniform(0.05, 0.35, 4096).astype(np.float32)
    gid = ((kx.astype(np.int64)[None, :] * 37 + fi.astype(np.int64) * 101) % 4096).astype(np.int64)
    glass = gtab[gid] + 0.1 * np.clip(1.0 - (z - 0.9) / wh, 0, 1)
    # curtains in some windows
    curtain = (gtab[(gid + 7) % 4096] > 0.25) & ((fxw - kx) < 0.5)
    glass = np.where(curtain, glass + 0.35, glass)
    img = np.where(win, glass, img)
    # mullion
    mull = win & (np.abs(fxw - kx - 0.5) * sp < 0.04)[None, :]
    img = np.where(mull, frame_tone, img)
    # string courses between floors
    if rng.random() < 0.6:
        sc = row_ok & (np.abs(z - 0.0) < 0.12)
        img = np.where(sc, tone * 0.75, img)
    return img, gf


def _shop_fronts(rng: np.random.Generator, img: np.ndarray, b: Building, gf: float, ub: np.ndarray,
                 hg: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ground floor: shop windows with goods, doors, signs with lettering; returns
    the texels and where the shop windows are."""
    shop_sp = rng.uniform(3.0, 4.5)
    fx2 = ub / shop_sp
    k2 = np.floor(fx2)
    d2 = np.abs(fx2 - k2 - 0.5) * shop_sp
    shop_w = rng.uniform(1.8, shop_sp - 0.6)
    is_door = (((k2.astype(np.int64) * 13 + int(b.u0)) % 5) == 0)[None, :]
    shop = (hg > 0.45) & (hg < gf - 1.0) & (d2 < shop_w / 2)[None, :]
    door = (hg > 0.0) & (hg < 2.3) & (d2 < 0.6)[None, :] & is_door
    # shop windows with goods on display: a random block pattern (per 15 cm cell)
    cell_x = np.floor(ub / 0.15).astype(np.int64)
    cell_y = np.floor(hg / 0.15).astype(np.int64)
    goods_tab = rng.uniform(0.05, 0.75, 4093).astype(np.float32)
    goods = goods_tab[(cell_x[None, :] * 31 + cell_y * 17 + int(b.u0 * 7)) % 4093]
    goods = np.where(goods_tab[(cell_x[None, :] * 7 + cell_y * 3 + 11) % 4093] > 0.45, goods, 0.12)
    img = np.where(shop & ~is_door, goods + 0.06 * noise, img)
    img = np.where(door, 0.18, img)
    # shop signs with "lettering"
    sign_tone = rng.uniform(0.0, 1.0)
    sign = (hg > gf - 0.85) & (hg < gf - 0.25) & (d2 < shop_w / 2)[None, :]
    letter_tab = rng.random(4093) < 0.5
    letters = letter_tab[(np.floor(ub / 0.12).astype(np.int64)[None, :] * 13 + np.floor(hg / 0.2).astype(np.int64) * 5) % 4093]
    letters &= (hg > gf - 0.72) & (hg < gf - 0.38)
    img = np.where(sign, np.where(letters, 1.0 - sign_tone, sign_tone), img)
    return img, shop


def _posters(rng: np.random.Generator, img: np.ndarray, bw: float, gf: float, shop: np.ndarray,
             ub: np.ndarray, hg: np.ndarray) -> np.ndarray:
    """Posters and graffiti on the ground floor between the shops."""
    for _ in range(int(rng.integers(0, 4))):
        px0 = rng.uniform(0, max(bw - 1.0, 0.1))
        pw_, ph_ = rng.uniform(0.4, 1.2), rng.uniform(0.5, 1.2)
        py0 = rng.uniform(0.4, max(gf - 1.2 - ph_, 0.5))
        poster = (hg > py0) & (hg < py0 + ph_) & ((ub > px0) & (ub < px0 + pw_))[None, :] & ~shop
        ptab = rng.uniform(0, 1, 4093).astype(np.float32)
        pat = ptab[(np.floor(ub / 0.1).astype(np.int64)[None, :] * 19 + np.floor(hg / 0.1).astype(np.int64) * 23) % 4093]
        img = np.where(poster, pat, img)
    return img

def _poly(points_xz: np.ndarray, origin: tuple[float, float], texel: float, shift: int = 2) -> np.ndarray:
    scale = (1 << shift) / texel
    pts = np.stack([(points_xz[:, 0] - origin[0]) * scale, (points_xz[:, 1] - origin[1]) * scale], 1)
    return np.round(pts).astype(np.int32).reshape(-1, 1, 2)


def _ground_atlas(rng: np.random.Generator, p: WorldParams, ring: RingRoad, inters):
    tx = p.ground_texel
    ext_x = p.A + p.d_outer_wall + p.outer_depth + 5.0
    ext_z = p.B + p.d_outer_wall + p.outer_depth + 5.0
    W = int(np.ceil(2 * ext_x / tx))
    H = int(np.ceil(2 * ext_z / tx))
    origin = (-ext_x, -ext_z)
    SH = 2
    road = np.zeros((H, W), np.uint8)
    marks = np.zeros((H, W), np.uint8)

    def contour_pts(d: float, step: float = 0.25) -> np.ndarray:
        L = ring.length(d)
        s = np.arange(0.0, L, step)
        x, z, _ = ring.contour(s, d)
        return np.stack([x, z], 1)

    cv2.fillPoly(road, [_poly(contour_pts(p.d_outer_curb), origin, tx, SH)], 255, cv2.LINE_AA, SH)
    cv2.fillPoly(road, [_poly(contour_pts(p.d_inner_curb), origin, tx, SH)], 0, cv2.LINE_AA, SH)
    hw = p.street_road / 2
    for side, mid in inters:
        for d0, d1 in ((-(p.inner_depth - 4.0), p.d_inner_curb + 0.5), (p.d_outer_curb - 0.5, p.d_outer_wall + p.outer_depth - 4.0)):
            corners = [ring.side_point(side, mid + a, d) for a, d in ((-hw, d0), (hw, d0), (hw, d1), (-hw, d1))]
            cv2.fillPoly(road, [_poly(np.array(corners, float), origin, tx, SH)], 255, cv2.LINE_AA, SH)

    def near_intersection(x: np.ndarray, z: np.ndarray, along: float, across: float) -> np.ndarray:
        out = np.zeros(x.shape, bool)
        for side, mid in inters:
            cx, cz = ring.side_point(side, mid, p.d_centre)
            th = ring.heading[side]
            fx, fz = fwd(th)
            out |= (np.abs((x - cx) * fx + (z - cz) * fz) < along) & (np.abs((x - cx) * fz - (z - cz) * fx) < across)
        return out

    def lines_along(d: float, on: float, off: float, width: float, img: np.ndarray, along_excl: float) -> None:
        L = ring.length(d)
        period = on + off
        starts = np.arange(0.0, L, period)
        polys = []
        for s0 in starts:
            s = np.linspace(s0, s0 + on, max(2, int(on / 0.5) + 1))
            x, z, _ = ring.contour(s, d)
            keep = ~near_intersection(x, z, along_excl, 14.0)
            if keep.all():
                polys.append(_poly(np.stack([x, z], 1), origin, tx, SH))
        cv2.polylines(img, polys, False, 255, max(1, int(round(width / tx))), cv2.LINE_AA, SH)

    # centre line dashed, lane edges solid (split into long dashes so intersections can break them)
    lines_along(p.d_centre, 3.0, 6.0, 0.15, marks, p.gap / 2 + 3.0)
    lines_along(p.d_inner_curb + p.parking, 5.0, 0.01, 0.12, marks, p.gap / 2 + 1.0)
    lines_along(p.d_outer_curb - p.parking, 5.0, 0.01, 0.12, marks, p.gap / 2 + 1.0)
    # parking bays and zebra crossings on the straights
    for side in range(4):
        L = float(ring.side_len[side])
        mid = L / 2
        for d0, d1 in ((p.d_inner_curb, p.d_inner_curb + p.parking), (p.d_outer_curb - p.parking, p.d_outer_curb)):
            for sg in np.arange(6.0, L - 6.0, 5.5):
                if abs(sg - mid) < p.gap / 2 + 6.0:
                    continue
                a = ring.side_point(side, sg, d0)
                b = ring.side_point(side, sg, d1)
                cv2.polylines(marks, [_poly(np.array([a, b], float), origin, tx, SH)], False, 255, 1, cv2.LINE_AA, SH)
        for zc in (mid - p.gap / 2 - 2.2, mid + p.gap / 2 + 2.2):
            for k in range(int((p.d_outer_curb - p.d_inner_curb - 0.6) / 1.0) + 1):
                d0 = p.d_inner_curb + 0.3 + k * 1.0
                d1 = min(d0 + 0.5, p.d_outer_curb - 0.2)
                corners = [ring.side_point(side, zc + a, d) for a, d in ((-1.5, d0), (1.5, d0), (1.5, d1), (-1.5, d1))]
                cv2.fillPoly(marks, [_poly(np.array(corners, float), origin, tx, SH)], 255, cv2.LINE_AA, SH)
    dark, spots = _ground_wear(rng, W, H, tx)
    img = _ground_shading(rng, road, marks, dark, spots, tx)
    return np.clip(img, 0.02, 0.98).astype(np.float32), origin


def _ground_wear(rng: np.random.Generator, W: int, H: int, tx: float) -> tuple[np.ndarray, np.ndarray]:
    """Wear of the ground atlas (H, W texels of ``tx`` m): ``dark`` (uint8: patches,
    manholes, cracks) and ``spots`` (float32: small dark and light stains and gravel)."""
    dark = np.zeros((H, W), np.uint8)
    # patches, manholes, cracks, stains
    n_patch = int(W * H * tx * tx / 60.0)
    for _ in range(n_patch):
        cx, cz = rng.uniform(0, W), rng.uniform(0, H)
        a = rng.uniform(0.5, 3.0) / tx
        bb = rng.uniform(0.5, 2.0) / tx
        ang = rng.uniform(0, 180)
        if rng.random() < 0.15:
            cv2.circle(dark, (int(cx), int(cz)), int(0.35 / tx), 200, -1, cv2.LINE_AA)
            cv2.circle(dark, (int(cx), int(cz)), int(0.35 / tx), 60, 1, cv2.LINE_AA)
        else:
            cv2.ellipse(dark, ((cx, cz), (a, bb), ang), int(rng.integers(40, 120)), -1, cv2.LINE_AA)
    for _ in range(n_patch * 2):
        pts = np.cumsum(rng.normal(0, 0.6 / tx, (int(rng.integers(3, 8)), 2)), 0) + rng.uniform(0, [W, H])
        cv2.polylines(dark, [pts.astype(np.int32).reshape(-1, 1, 2)], False, 255, 1, cv2.LINE_AA)
    # small stains and gravel spots (10-40 cm), dark and light: corners at any distance
    spots = np.zeros((H, W), np.float32)
    n_spot = int(W * H * tx * tx / 2.0)
    sx = rng.integers(0, W, n_spot)
    sy = rng.integers(0, H, n_spot)
    spots[sy, sx] = rng.choice(np.array([-1.0, 1.0], np.float32), n_spot) * rng.uniform(0.4, 1.0, n_spot).astype(np.float32)
    spots = cv2.GaussianBlur(spots, (0, 0), 1.0) * 2 * np.pi  # unit peak for an isolated spot
    return dark, spots


def _ground_shading(rng: np.random.Generator, road: np.ndarray, marks: np.ndarray, dark: np.ndarray,
                    spots: np.ndarray, tx: float) -> np.ndarray:
    """Grey levels of the ground atlas: asphalt on the ``road``, paving tiles elsewhere,
    curbs at the road's edge, worn ``marks`` painted on top."""
    H, W = road.shape
    roadf = road.astype(np.float32) / 255.0
    # worn paint: markings lose patches of paint
    wear = cv2.resize(rng.uniform(0, 1, (H // 3 + 2, W // 3 + 2)).astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
    marksf = (marks.astype(np.float32) / 255.0) * roadf * np.clip((wear - 0.2) * 3.0, 0.25, 1.0)
    darkf = dark.astype(np.float32) / 255.0
    big = cv2.resize(rng.uniform(-1, 1, (H // 40 + 2, W // 40 + 2)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC)
    mid_n = cv2.resize(rng.uniform(-1, 1, (H // 6 + 2, W // 6 + 2)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC)
    asphalt = 0.33 + 0.05 * big + 0.05 * mid_n - 0.2 * darkf + 0.12 * spots
    # sidewalk: paving tiles 0.6 m
    ys, xs = np.mgrid[0:H, 0:W]
    wx = xs * tx
    wz = ys * tx
    tile = 0.6
    ti = np.floor(wx / tile).astype(np.int64) * 7919 + np.floor(wz / tile).astype(np.int64) * 104729
    ttab = rng.uniform(-1, 1, 8192).astype(np.float32)
    joint = ((wx / tile) % 1.0 < 0.12) | ((wz / tile) % 1.0 < 0.12)
    pave = 0.58 + 0.08 * ttab[ti % 8192] + 0.04 * big - 0.15 * joint - 0.1 * darkf + 0.08 * spots
    img = roadf * asphalt + (1 - roadf) * pave
    # curb: bright band outside the road edge, dark gutter inside
    edge_out = cv2.dilate(road, np.ones((3, 3), np.uint8)).astype(np.float32) / 255.0 - roadf
    edge_in = roadf - cv2.erode(road, np.ones((3, 3), np.uint8)).astype(np.float32) / 255.0
    img = img + 0.3 * np.clip(edge_out, 0, 1) - 0.12 * np.clip(edge_in, 0, 1)
    img = img * (1 - marksf) + 0.88 * marksf
    return img


def _sky(rng: np.random.Generator) -> np.ndarray:
    h, w = 128, 2048
    clouds = fractal_noise(rng, (h, w), 12, 5, 0.55)
    clouds = np.clip(clouds * 1.6 + 0.1, 0, 1)
    grad = np.linspace(0.88, 0.72, h, dtype=np.float32)[:, None]
    return np.clip(grad + 0.08 * clouds, 0, 1).astype(np.float32)


def build_world(seed: int, params: WorldParams | None = None) -> World:
    """The city for ``seed`` (same for every scenario)."""
    p = params or WorldParams()
    rng = np.random.default_rng([seed, 1])
    ring = RingRoad(p.A, p.B)
    segs, inters = _wall_segments(p, ring)
    blds = _layout_buildings(rng, p, segs)
    fac, fac_h, band_rows = _facade_atlas(rng, p, segs, blds)
    ground, origin = _ground_atlas(rng, p, ring, inters)
    world = World(
        params=p,
        ring=ring,
        segments=segs,
        buildings=blds,
        facade=MipTexture(fac, wrap=False, texel=p.facade_texel),
        facade_detail=MipTexture(facade_detail(rng, 512, p.facade_detail_texel), wrap=True, texel=p.facade_detail_texel),
        ground=MipTexture(ground, wrap=False, texel=p.ground_texel),
        ground_detail=MipTexture(asphalt_detail(rng, 512), wrap=True, texel=p.ground_detail_texel),
        sky=MipTexture(_sky(rng), wrap=True, texel=1.0),
        ground_origin=origin,
        facade_height=fac_h,
        band_stride=band_rows,
        intersections=inters,
    )
    world.pack()
    return world


__all__ = ["World", "WorldParams", "RingRoad", "build_world", "fwd", "right"]
