"""Procedural textures and their mip-mapped sampling.

Every surface of the synthetic world is textured in *its own* coordinates (world
ground coordinates, facade coordinates, object-local coordinates), so a point looks
the same from both cameras and from every frame -- what stereo matching and SLAM need.

Textures are pre-rendered once per world into float32 images (values in 0..1) and
sampled with :class:`MipTexture`: a mip pyramid packed into one image, sampled with
two bilinear ``cv2.remap`` taps and a blend between mip levels (trilinear
filtering), which keeps distant surfaces band-limited (no aliasing between the two
views, so the right image really equals the warped left one).
"""

from __future__ import annotations

import cv2
import numpy as np

_PAD = 2  # texels of padding around each packed level (bilinear needs 1)
_REMAP_COLS = 1024
_INTERP = cv2.INTER_LINEAR  # remap wants 2-D maps below 32767 per side: flat points go in rows of this


def remap_points(src: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``src`` at float32 points ``(mx, my)`` of any shape."""
    shape = mx.shape
    n = mx.size
    if n == 0:
        return np.zeros(shape, np.float32)
    if mx.ndim == 2 and shape[0] < 32767 and shape[1] < 32767:
        return cv2.remap(src, mx, my, _INTERP, borderMode=cv2.BORDER_REPLICATE)
    rows = -(-n // _REMAP_COLS)
    total = rows * _REMAP_COLS
    fx = np.zeros(total, np.float32)
    fy = np.zeros(total, np.float32)
    fx[:n] = mx.ravel()
    fy[:n] = my.ravel()
    out = cv2.remap(
        src,
        fx.reshape(rows, _REMAP_COLS),
        fy.reshape(rows, _REMAP_COLS),
        _INTERP,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out.ravel()[:n].reshape(shape)


class MipTexture:
    """A float32 texture with its mip pyramid packed into one image.

    ``wrap=True`` tiles the texture (sizes must be divisible by ``2**(levels-1)``);
    otherwise coordinates are clamped to the edge.  ``texel`` is the size of one
    level-0 texel in metres (informative; callers convert metres to texels).
    """

    def __init__(self, image: np.ndarray, *, wrap: bool, texel: float = 1.0, levels: int | None = None):
        img = np.ascontiguousarray(image, dtype=np.float32)
        if img.ndim != 2:
            raise ValueError("MipTexture expects a single-channel image")
        h, w = img.shape
        if levels is None:
            levels = 1
            while min(h, w) >> levels >= 4 and levels < 12:
                levels += 1
        if wrap and (h % (1 << (levels - 1)) or w % (1 << (levels - 1))):
            raise ValueError(f"wrapped texture size {w}x{h} not divisible by 2**{levels - 1}")
        self.wrap = wrap
        self.texel = float(texel)
        self.levels = levels
        mode = "wrap" if wrap else "edge"
        pyr = [img]
        for _ in range(1, levels):
            prev = pyr[-1]
            ph, pw = prev.shape
            padded = np.pad(prev, 2, mode=mode)
            down = cv2.pyrDown(padded, borderType=cv2.BORDER_REPLICATE)
            nh, nw = (ph + 1) // 2, (pw + 1) // 2
            pyr.append(np.ascontiguousarray(down[1 : 1 + nh, 1 : 1 + nw]))
        # pack: level 0 at the left, the others stacked in a column to its right
        w0 = pyr[0].shape[1] + 2 * _PAD
        h0 = pyr[0].shape[0] + 2 * _PAD
        col_h = sum(p.shape[0] + 2 * _PAD for p in pyr[1:])
        col_w = max((p.shape[1] + 2 * _PAD for p in pyr[1:]), default=0)
        atlas = np.zeros((max(h0, col_h), w0 + col_w), np.float32)
        ox = np.zeros(levels, np.float32)
        oy = np.zeros(levels, np.float32)
        y = 0
        for i, p in enumerate(pyr):
            x0, y0 = (0, 0) if i == 0 else (w0, y)
            ph, pw = p.shape
            atlas[y0 : y0 + ph + 2 * _PAD, x0 : x0 + pw + 2 * _PAD] = np.pad(p, _PAD, mode=mode)
            ox[i] = x0 + _PAD
            oy[i] = y0 + _PAD
            if i > 0:
                y += ph + 2 * _PAD
        if atlas.shape[0] >= 32767 or atlas.shape[1] >= 32767:
            raise ValueError(f"texture too large for cv2.remap: {atlas.shape}")
        self.atlas = atlas
        self.ox = ox
        self.oy = oy
        self.lw = np.array([p.shape[1] for p in pyr], np.float32)
        self.lh = np.array([p.shape[0] for p in pyr], np.float32)
        self.scale = np.array([0.5**i for i in range(levels)], np.float32)
        self.width = w
        self.height = h

    def _tap(self, u: np.ndarray, v: np.ndarray, lev: np.ndarray) -> np.ndarray:
        s = np.ldexp(np.float32(1.0), -lev).astype(np.float32)  # 2**-lev
        ul = (u + 0.5) * s - 0.5
        vl = (v + 0.5) * s - 0.5
        # level sizes: exact for wrapped textures (sizes divisible by 2**levels); for clamped
        # ones w * 2**-lev <= the real ceil(w / 2**lev), so the clamp stays inside the level
        lw = np.float32(self.width) * s
        lh = np.float32(self.height) * s
        if self.wrap:
            ul = ul - np.floor(ul / lw) * lw
            vl = vl - np.floor(vl / lh) * lh
        else:
            ul = np.minimum(np.maximum(ul, 0.0), lw - 1.0)
            vl = np.minimum(np.maximum(vl, 0.0), lh - 1.0)
        mx = (ul + self.ox[lev]).astype(np.float32, copy=False)
        my = (vl + self.oy[lev]).astype(np.float32, copy=False)
        mx, my = np.broadcast_arrays(mx, my)
        return remap_points(self.atlas, np.ascontiguousarray(mx), np.ascontiguousarray(my))

    def sample(self, u: np.ndarray, v: np.ndarray, lod: np.ndarray | float) -> np.ndarray:
        """Trilinear samples at level-0 texel coordinates ``(u, v)`` (texel centres at integers).

        ``lod`` (broadcastable to ``u``) is log2 of the pixel footprint in texels.
        """
        lod = np.clip(np.asarray(lod, np.float32), 0.0, self.levels - 1)
        l0 = lod.astype(np.int32)  # floor, lod >= 0
        frac = lod - l0
        a = self._tap(u, v, l0)
        if self.levels == 1 or not np.any(frac > 1e-3):
            return a
        l1 = np.minimum(l0 + 1, self.levels - 1)
        b = self._tap(u, v, l1)
        return a + frac * (b - a)


# ---------------------------------------------------------------------------------------------
# procedural generators (run once per world; vectorized over the texture, never per pixel)


def periodic_noise(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[int, int]) -> np.ndarray:
    """Smooth periodic value noise in [-1, 1]: a random ``cells`` grid upsampled (bicubic)."""
    h, w = shape
    ch, cw = max(1, cells[0]), max(1, cells[1])
    g = rng.uniform(-1.0, 1.0, (ch, cw)).astype(np.float32)
    big = np.tile(g, (3, 3))
    up = cv2.resize(big, (3 * w, 3 * h), interpolation=cv2.INTER_CUBIC)
    return np.ascontiguousarray(up[h : 2 * h, w : 2 * w])


def fractal_noise(
    rng: np.random.Generator,
    shape: tuple[int, int],
    base_cells: int,
    octaves: int,
    persistence: float = 0.5,
) -> np.ndarray:
    """Sum of periodic noise octaves, roughly in [-1, 1]."""
    h, w = shape
    out = np.zeros(shape, np.float32)
    amp, total = 1.0, 0.0
    cells = base_cells
    for _ in range(octaves):
        ch = max(1, int(round(cells * h / max(h, w))))
        cw = max(1, int(round(cells * w / max(h, w))))
        out += amp * periodic_noise(rng, shape, (min(ch, h), min(cw, w)))
        total += amp
        amp *= persistence
        cells *= 2
    return out / total


def speckle(rng: np.random.Generator, shape: tuple[int, int], density: float, sigma: float = 0.7) -> np.ndarray:
    """Sparse blurred dots (+/-1 random sign) -- small high-contrast blobs, ORB corner food."""
    dots = np.zeros(shape, np.float32)
    n = int(density * shape[0] * shape[1])
    ys = rng.integers(0, shape[0], n)
    xs = rng.integers(0, shape[1], n)
    dots[ys, xs] = rng.choice(np.array([-1.0, 1.0], np.float32), n)
    blurred = cv2.GaussianBlur(np.tile(dots, (3, 3)), (0, 0), sigma)
    h, w = shape
    out = blurred[h : 2 * h, w : 2 * w]
    m = float(np.abs(out).max()) or 1.0
    return np.ascontiguousarray(out / m)


def asphalt_detail(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Tileable asphalt: grain, bright and dark stones of a few sizes; mean ~0.5."""
    n = fractal_noise(rng, (size, size), 32, 3, 0.6)
    fine = speckle(rng, (size, size), 0.05, 0.9)
    stones = speckle(rng, (size, size), 0.006, 2.2)
    img = 0.5 + 0.12 * n + 0.45 * fine + 0.35 * stones
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def facade_detail(rng: np.random.Generator, size: int = 512, texel: float = 0.02) -> np.ndarray:
    """Tileable brick/plaster pattern, mean ~0.5 (bricks 24 x 7.5 cm, mortar joints)."""
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float32)
    bh = 0.08 / texel  # brick course in texels
    bw = 0.24 / texel
    course = np.floor(ys / bh)
    xo = xs + (course % 2) * bw / 2
    fy = ys / bh - course
    fx = xo / bw - np.floor(xo / bw)
    mortar = ((fy < 0.12) | (fx < 0.05)).astype(np.float32)
    brick_id = np.floor(xo / bw) * 131 + course * 71
    table = rng.uniform(-1, 1, 4096).astype(np.float32)
    brick_tone = table[(brick_id.astype(np.int64) % 4096)]
    grain = fractal_noise(rng, (size, size), 32, 3, 0.6)
    img = 0.55 + 0.12 * brick_tone + 0.12 * grain - 0.35 * mortar
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def material_texture(
    rng: np.random.Generator,
    base: float,
    kind: str,
    size: int = 128,
) -> np.ndarray:
    """Small tileable object texture (albedo 0..1) of a given kind.

    ``paint``: car paint with stripes, dirt, decals; ``glass``: dark with reflections;
    ``tire``: very dark rubber; ``cloth``: fabric with pattern; ``skin``; ``cargo``:
    truck panels with logos (many corners).
    """
    shape = (size, size)
    n = fractal_noise(rng, shape, 8, 4, 0.6)
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float32)
    if kind == "paint":
        img = base + 0.07 * n
        # stripes and decals
        if rng.random() < 0.7:
            y0 = rng.integers(0, size)
            img = np.where(np.abs(((ys - y0) % size) - size / 2) < rng.uniform(2, 6), img * 0.55 + 0.3, img)
        img += 0.25 * speckle(rng, shape, 0.01, 1.0)
        for _ in range(rng.integers(2, 6)):
            x0, y0 = rng.integers(0, size, 2)
            rw, rh = rng.integers(4, 24, 2)
            tone = rng.uniform(0.05, 0.95)
            m = (((xs - x0) % size) < rw) & (((ys - y0) % size) < rh)
            img = np.where(m, tone + 0.05 * n, img)
    elif kind == "glass":
        img = 0.12 + 0.06 * n + 0.25 * np.clip(np.sin((xs + ys) * 2 * np.pi / size * 2), 0, 1) ** 4
    elif kind == "tire":
        img = 0.08 + 0.04 * n + 0.05 * speckle(rng, shape, 0.02, 0.8)
    elif kind == "skin":
        img = base + 0.05 * n
    elif kind == "cloth":
        period = int(rng.choice([8, 16, 32]))
        pat = rng.integers(0, 3)
        if pat == 0:
            stripe = ((xs // (period // 2)) % 2).astype(np.float32)
        elif pat == 1:
            stripe = (((xs // (period // 2)) + (ys // (period // 2))) % 2).astype(np.float32)
        else:
            stripe = np.zeros(shape, np.float32)
        img = base + 0.18 * (stripe - 0.5) + 0.08 * n + 0.15 * speckle(rng, shape, 0.01, 0.8)
    elif kind == "cargo":
        img = base + 0.06 * n
        # panel seams
        img = np.where((xs % 32) < 1.5, img * 0.6, img)
        for _ in range(rng.integers(10, 20)):  # logos, letters, stickers
            x0, y0 = rng.integers(0, size, 2)
            rw, rh = rng.integers(3, 20, 2)
            tone = rng.uniform(0.0, 1.0)
            m = (((xs - x0) % size) < rw) & (((ys - y0) % size) < rh)
            img = np.where(m, tone, img)
        img += 0.3 * speckle(rng, shape, 0.02, 0.9)
    elif kind == "poster":
        img = _poster(rng, base, size) + 0.04 * n
    elif kind == "plate":  # number plate: dark characters on a light strip (the top 1/5 of the tile)
        canvas = np.full(shape, int(base * 255), np.uint8)
        text = "".join(rng.choice(list(_LETTERS), 2)) + "-" + "".join(rng.choice(list("0123456789"), 4))
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.7 * size / 128, 2)
        cv2.putText(canvas, text, (max(1, (size - tw) // 2), min(size // 5 - 3, th + 5)), cv2.FONT_HERSHEY_SIMPLEX,
                    0.7 * size / 128, 20, 2, cv2.LINE_AA)
        img = canvas.astype(np.float32) / 255.0 + 0.02 * n
    else:  # pragma: no cover - programming error
        raise ValueError(f"unknown material kind {kind!r}")
    return np.clip(img, 0.02, 0.98).astype(np.float32)


_LETTERS = "ABCDEFGHKLMNOPRSTUVWXYZ"


def _poster(rng: np.random.Generator, base: float, size: int) -> np.ndarray:
    """Advertising livery (a truck's rear door, a bus's back): a logo of a few bold
    shapes, a company name in large letters, a slogan and a phone number in small ones,
    a frame.  Drawn with OpenCV primitives (no per-pixel Python), high contrast against
    ``base``: the kind of surface ORB finds hundreds of corners on."""
    canvas = np.full((size, size), int(round(base * 255)), np.uint8)
    dark = base > 0.5

    def tone() -> int:  # contrasting ink
        return int(rng.uniform(0.02, 0.3) * 255) if dark else int(rng.uniform(0.7, 0.98) * 255)

    s = size / 128.0
    # logo: circles / rectangles / a triangle in the upper part
    for _ in range(int(rng.integers(3, 6))):
        cx, cy = int(rng.uniform(0.15, 0.85) * size), int(rng.uniform(0.1, 0.45) * size)
        r = int(rng.uniform(5, 16) * s)
        kind = int(rng.integers(0, 3))
        ink = tone() if rng.random() < 0.7 else int(rng.uniform(0.3, 0.7) * 255)
        if kind == 0:
            cv2.circle(canvas, (cx, cy), r, ink, -1 if rng.random() < 0.6 else max(1, int(2 * s)), cv2.LINE_AA)
        elif kind == 1:
            cv2.rectangle(canvas, (cx - r, cy - r // 2), (cx + r, cy + r // 2), ink, -1)
        else:
            pts = np.array([[cx, cy - r], [cx - r, cy + r], [cx + r, cy + r]], np.int32)
            cv2.fillConvexPoly(canvas, pts, ink, cv2.LINE_AA)
    # lettering: a name in large letters, then smaller lines
    fonts = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_TRIPLEX)
    y = int(0.55 * size)
    for scale, thick, chars in ((0.62, 2, (4, 7)), (0.36, 1, (8, 12)), (0.36, 1, (8, 12)), (0.3, 1, (9, 13))):
        word = "".join(rng.choice(list(_LETTERS + "   "), int(rng.integers(*chars))))
        if scale == 0.3:
            word = "".join(rng.choice(list("0123456789 -"), int(rng.integers(*chars))))
        font = fonts[int(rng.integers(0, len(fonts)))]
        (tw, th), _ = cv2.getTextSize(word, font, scale * s, thick)
        x = int(max(2, (size - tw) / 2 + rng.uniform(-0.1, 0.1) * size))
        cv2.putText(canvas, word, (x, y), font, scale * s, tone(), thick, cv2.LINE_AA)
        y += int(th + 6 * s)
        if y > size - 6:
            break
    cv2.rectangle(canvas, (1, 1), (size - 2, size - 2), tone(), max(1, int(2 * s)))
    return canvas.astype(np.float32) / 255.0


class TileAtlas:
    """Many small square tileable textures (materials) with their mip pyramids in one image.

    Every material wraps inside its own tile at every level, so one ``sample`` call (two
    ``cv2.remap`` taps) textures the pixels of all objects of a view at once.
    """

    def __init__(self, tiles: list[np.ndarray]):
        if not tiles:
            tiles = [np.full((8, 8), 0.5, np.float32)]
        S = tiles[0].shape[0]
        if any(t.shape != (S, S) for t in tiles) or S & (S - 1):
            raise ValueError("tiles must be equal squares with a power-of-two side")
        levels = 1
        while (S >> levels) >= 2:
            levels += 1
        M = len(tiles)
        cols = max(1, min(M, 32))
        rows = -(-M // cols)
        sizes = [S >> lev for lev in range(levels)]
        slot = [s + 2 * _PAD for s in sizes]
        heights = [rows * sl for sl in slot]
        atlas = np.zeros((sum(heights), cols * slot[0]), np.float32)
        ox = np.zeros((M, levels), np.float32)
        oy = np.zeros((M, levels), np.float32)
        y_base = 0
        pyrs = []
        for t in tiles:
            pyr = [np.ascontiguousarray(t, dtype=np.float32)]
            for _ in range(1, levels):
                prev = pyr[-1]
                down = cv2.pyrDown(np.pad(prev, 2, mode="wrap"), borderType=cv2.BORDER_REPLICATE)
                n = prev.shape[0] // 2
                pyr.append(np.ascontiguousarray(down[1 : 1 + n, 1 : 1 + n]))
            pyrs.append(pyr)
        for lev in range(levels):
            for m, pyr in enumerate(pyrs):
                r, c = divmod(m, cols)
                y0 = y_base + r * slot[lev]
                x0 = c * slot[lev]
                atlas[y0 : y0 + slot[lev], x0 : x0 + slot[lev]] = np.pad(pyr[lev], _PAD, mode="wrap")
                ox[m, lev] = x0 + _PAD
                oy[m, lev] = y0 + _PAD
            y_base += heights[lev]
        if atlas.shape[0] >= 32767 or atlas.shape[1] >= 32767:
            raise ValueError(f"too many materials for one atlas: {M}")
        self.atlas = atlas
        self.ox = ox
        self.oy = oy
        self.levels = levels
        self.size = np.array(sizes, np.float32)
        self.scale = np.array([0.5**lev for lev in range(levels)], np.float32)

    def _tap(self, mat: np.ndarray, u: np.ndarray, v: np.ndarray, lev: np.ndarray) -> np.ndarray:
        s = self.scale[lev]
        n = self.size[lev]
        ul = (u + 0.5) * s - 0.5
        vl = (v + 0.5) * s - 0.5
        ul = ul - np.floor(ul / n) * n
        vl = vl - np.floor(vl / n) * n
        mx = (ul + self.ox[mat, lev]).astype(np.float32)
        my = (vl + self.oy[mat, lev]).astype(np.float32)
        return remap_points(self.atlas, mx, my)

    def sample(self, mat: np.ndarray, u: np.ndarray, v: np.ndarray, lod: np.ndarray) -> np.ndarray:
        """Trilinear samples of material ``mat`` (per point) at level-0 texel coordinates."""
        lod = np.clip(np.asarray(lod, np.float32), 0.0, self.levels - 1)
        l0 = lod.astype(np.int32)
        frac = lod - l0
        a = self._tap(mat, u, v, l0)
        l1 = np.minimum(l0 + 1, self.levels - 1)
        b = self._tap(mat, u, v, l1)
        return a + frac * (b - a)
