"""Disparity estimation with OpenCV StereoBM / StereoSGBM (+ optional WLS filter).

Thesis 3.3.1 (block matching and its parameters), 3.3.2 (WLS post-filter) and 3.3.3
(normalized, contrast-enhanced view of the disparity).

``StereoMatcher(cfg).compute(left_gray, right_gray)`` gives the full-frame disparity
(float32 pixels, ``<= 0`` invalid).  The masking fast path is
``compute_band(left, right, y0, y1, x0, x1, scale)``: the disparity of one image region
only (the band the detected boxes cover), optionally at half resolution.  Block
matching for a left pixel ``x`` looks at right pixels ``x - minD - numD + 1 .. x - minD``,
so the crop handed to OpenCV is padded on the left by ``minD + numD`` columns (plus half a
block on every side); the padding columns are the ones OpenCV leaves invalid, so inside
the requested region the band result is the full-frame result (up to the speckle filter
and, for SGBM/WLS, the slightly shorter aggregation paths; tests bound the difference).

Left image border: OpenCV leaves the leftmost ``minD + numD - 1`` columns invalid (not
every candidate disparity fits there) -- 15 % of a 640-pixel image with numDisparities 96,
where a pedestrian at the border would get no disparity at all.  When a crop reaches the
left image border, both images are padded there (border replicate, featureless) by the
missing columns before matching; a left pixel ``x`` whose true disparity ``d <= x`` is then
matched, and any result ``d > x`` (a match into the padding, i.e. outside the right image)
is invalid.  Away from the border the result is unchanged.  The other three borders lose
half a block (OpenCV leaves it invalid); crops reaching them are padded by that much, so
objects on the image's bottom edge keep their bottom rows (:meth:`StereoMatcher.border_padding`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..config import STEREO_SCALES as SCALES, StereoConfig
from ..errors import ConfigError

_SGBM_MODES = {
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "sgbm3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "hh": cv2.STEREO_SGBM_MODE_HH,
    "hh4": cv2.STEREO_SGBM_MODE_HH4,
}


@dataclass(frozen=True)
class MatcherParams:
    """The OpenCV parameters actually used at one scale (after defaults and scaling)."""

    algorithm: str
    min_disparity: int
    num_disparities: int
    block_size: int
    p1: int
    p2: int
    disp12_max_diff: int
    pre_filter_cap: int
    uniqueness_ratio: int
    speckle_window_size: int
    speckle_range: int
    texture_threshold: int


def params_at_scale(cfg: StereoConfig, scale: int) -> MatcherParams:
    """OpenCV parameters for images downscaled by ``scale`` (1 = as configured).

    Disparities shrink by ``scale`` (numDisparities rounded up to a multiple of 16), the
    block keeps its footprint (odd, >= 5 for BM), P1/P2 and the texture threshold follow
    the block area, the speckle window the image area.
    """
    alg = str(cfg.algorithm).lower()
    p1, p2 = cfg.default_p()
    if scale == 1:
        return MatcherParams(alg, cfg.min_disparity, cfg.num_disparities, cfg.block_size, p1, p2,
                             cfg.disp12_max_diff, cfg.pre_filter_cap, cfg.uniqueness_ratio,
                             cfg.speckle_window_size, cfg.speckle_range, cfg.texture_threshold)
    nd = max(16, int(math.ceil(cfg.num_disparities / scale / 16.0)) * 16)
    md = int(math.floor(cfg.min_disparity / scale))
    bs = max(5 if alg == "bm" else 3, (cfg.block_size // scale) | 1)
    if bs > cfg.block_size:
        bs = cfg.block_size
    area_ratio = (bs * bs) / float(cfg.block_size * cfg.block_size)
    return MatcherParams(
        alg, md, nd, bs,
        int(round(p1 * area_ratio)), max(int(round(p2 * area_ratio)), int(round(p1 * area_ratio)) + 1),
        cfg.disp12_max_diff, cfg.pre_filter_cap, cfg.uniqueness_ratio,
        int(round(cfg.speckle_window_size / (scale * scale))), cfg.speckle_range,
        int(round(cfg.texture_threshold * area_ratio)),
    )


def _create_cv_matcher(p: MatcherParams):
    if p.algorithm == "bm":
        m = cv2.StereoBM_create(numDisparities=p.num_disparities, blockSize=p.block_size)
        m.setMinDisparity(p.min_disparity)
        m.setPreFilterCap(p.pre_filter_cap)
        m.setTextureThreshold(p.texture_threshold)
        m.setUniquenessRatio(p.uniqueness_ratio)
        m.setSpeckleWindowSize(p.speckle_window_size)
        m.setSpeckleRange(p.speckle_range)
        m.setDisp12MaxDiff(p.disp12_max_diff)
        return m
    return cv2.StereoSGBM_create(
        minDisparity=p.min_disparity,
        numDisparities=p.num_disparities,
        blockSize=p.block_size,
        P1=p.p1,
        P2=p.p2,
        disp12MaxDiff=p.disp12_max_diff,
        preFilterCap=p.pre_filter_cap,
        uniquenessRatio=p.uniqueness_ratio,
        speckleWindowSize=p.speckle_window_size,
        speckleRange=p.speckle_range,
        mode=_SGBM_MODES[p.algorithm],
    )


class _ScaledMatcher:
    """OpenCV matcher(s) for one scale: left, and right + WLS filter when enabled."""

    def __init__(self, cfg: StereoConfig, scale: int):
        self.params = params_at_scale(cfg, scale)
        self.left = _create_cv_matcher(self.params)
        self.right = None
        self.wls = None
        if cfg.wls:
            self.right = cv2.ximgproc.createRightMatcher(self.left)
            self.wls = cv2.ximgproc.createDisparityWLSFilter(self.left)
            self.wls.setLambda(float(cfg.wls_lambda))
            self.wls.setSigmaColor(float(cfg.wls_sigma))

    def raw(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """int16 disparity * 16 (OpenCV's fixed point)."""
        dl = self.left.compute(left, right)
        if self.wls is None:
            return dl
        dr = self.right.compute(right, left)
        return self.wls.filter(dl, left, disparity_map_right=dr)

    def to_float(self, raw: np.ndarray, scale: int) -> np.ndarray:
        """float32 pixels at full resolution units, 0 where invalid."""
        d = raw.astype(np.float32)
        d *= scale / 16.0
        # OpenCV marks invalid as (minD - 1) * 16, which is > 0 when minD > 1.
        d[raw < self.params.min_disparity * 16] = 0.0
        np.maximum(d, 0.0, out=d)
        return d


def _gray(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        raise ValueError(f"disparity needs uint8 images, got {img.dtype}")
    return img


class StereoMatcher:
    """DisparityEstimator over OpenCV StereoBM / StereoSGBM (modes SGBM, 3-way, HH, HH4).

    All the thesis parameters come from :class:`StereoConfig`; invalid values raise
    :class:`ConfigError` naming the option.  With ``cfg.wls`` the left disparity is
    post-filtered with the WLS filter (``cv2.ximgproc``) using a right matcher for the
    left-right confidence.
    """

    def __init__(self, cfg: StereoConfig | None = None):
        cfg = cfg or StereoConfig()
        cfg.validate()  # (a configuration changed after it was made)
        self.cfg = cfg
        self.algorithm = str(cfg.algorithm).lower()
        self.name = self.algorithm + ("+wls" if cfg.wls else "")
        self._by_scale: dict[int, _ScaledMatcher] = {}

    def _matcher(self, scale: int) -> _ScaledMatcher:
        m = self._by_scale.get(scale)
        if m is None:
            if scale not in SCALES:
                raise ConfigError(f"disparity scale must be one of {SCALES}, got {scale}")
            m = self._by_scale[scale] = _ScaledMatcher(self.cfg, scale)
        return m

    def params(self, scale: int = 1) -> MatcherParams:
        return self._matcher(scale).params

    @property
    def max_disparity(self) -> float:
        """Largest disparity the matcher can report (pixels)."""
        return float(self.cfg.min_disparity + self.cfg.num_disparities - 1)

    # -- full frame ---------------------------------------------------------------
    def compute(self, left_gray: np.ndarray, right_gray: np.ndarray, scale: int = 1) -> np.ndarray:
        """Full-frame disparity of the left image: float32 pixels, ``<= 0`` invalid."""
        h, w = left_gray.shape[:2]
        return self.compute_band(left_gray, right_gray, 0, h, 0, w, scale=scale)

    # -- region -------------------------------------------------------------------
    def crop_padding(self, scale: int = 1) -> tuple[int, int]:
        """(left, other): the columns a region's crop takes left of it (the disparity
        range, half a block and a margin), and the rows or columns on every other side."""
        p = self.params(scale)
        half = (p.block_size // 2) * scale
        extra = (16 if self.algorithm == "bm" and not self.cfg.wls else 32) * scale
        return (max(p.min_disparity, 0) + p.num_disparities) * scale + half + extra, half + extra

    def band_crop(self, shape: tuple[int, int], y0: int, y1: int, x0: int, x1: int,
                  scale: int = 1) -> tuple[int, int, int, int]:
        """The padded crop ``(cy0, cy1, cx0, cx1)`` handed to OpenCV for a region."""
        h, w = shape
        left_pad, pad = self.crop_padding(scale)
        cx0 = max(0, x0 - left_pad)
        cx1 = min(w, x1 + pad)
        cy0 = max(0, y0 - pad)
        cy1 = min(h, y1 + pad)
        if scale > 1:  # align the crop to the coarse grid
            cx0 -= cx0 % scale
            cy0 -= cy0 % scale
        return cy0, cy1, cx0, cx1

    def compute_band(
        self,
        left: np.ndarray,
        right: np.ndarray,
        y0: int,
        y1: int,
        x0: int,
        x1: int,
        scale: int = 1,
    ) -> np.ndarray:
        """Disparity of rows ``y0:y1``, columns ``x0:x1`` only: float32 ``(y1-y0, x1-x0)``.

        Values are full-resolution pixels (``<= 0`` invalid) whatever ``scale``: with
        ``scale=2`` both crops are halved (INTER_AREA), matched with halved
        numDisparities / block, and the result is expanded back (nearest) and doubled.
        """
        left = _gray(left)
        right = _gray(right)
        if left.shape != right.shape:
            raise ValueError(f"left and right images differ in size: {left.shape} vs {right.shape}")
        h, w = left.shape
        y0, y1 = max(0, int(y0)), min(h, int(y1))
        x0, x1 = max(0, int(x0)), min(w, int(x1))
        if y1 <= y0 or x1 <= x0:
            return np.zeros((max(0, y1 - y0), max(0, x1 - x0)), np.float32)
        m = self._matcher(scale)
        cy0, cy1, cx0, cx1 = self.band_crop((h, w), y0, y1, x0, x1, scale)
        lc = left[cy0:cy1, cx0:cx1]
        rc = right[cy0:cy1, cx0:cx1]
        # columns missing left of the crop (it reaches the image border): padded, so the
        # pixels near x = 0 get every candidate disparity; crop coords = image coords + pad
        pad = self.left_padding(x0, scale)
        # rows / columns the block needs beyond the top, bottom and right image borders
        pt, pb, pr = self.border_padding((cy0, cy1, cx0, cx1), (h, w), scale)
        if pad or pt or pb or pr:
            lc = cv2.copyMakeBorder(lc, pt, pb, pad, pr, cv2.BORDER_REPLICATE)
            rc = cv2.copyMakeBorder(rc, pt, pb, pad, pr, cv2.BORDER_REPLICATE)
            cx0 -= pad
            cy0 -= pt
        if scale > 1:
            ch, cw = lc.shape
            ph, pw = (-ch) % scale, (-cw) % scale
            if ph or pw:
                lc = cv2.copyMakeBorder(lc, 0, ph, 0, pw, cv2.BORDER_REPLICATE)
                rc = cv2.copyMakeBorder(rc, 0, ph, 0, pw, cv2.BORDER_REPLICATE)
            size = (lc.shape[1] // scale, lc.shape[0] // scale)
            lc = cv2.resize(lc, size, interpolation=cv2.INTER_AREA)
            rc = cv2.resize(rc, size, interpolation=cv2.INTER_AREA)
        else:
            lc = np.ascontiguousarray(lc)
            rc = np.ascontiguousarray(rc)
        raw = m.raw(lc, rc)
        if scale > 1:
            # Only the coarse cells covering the region, expanded by repetition.
            oy, ox = y0 - cy0, x0 - cx0
            ry0, rx0 = oy // scale, ox // scale
            ry1 = -(-(oy + y1 - y0) // scale)
            rx1 = -(-(ox + x1 - x0) // scale)
            sub = m.to_float(raw[ry0:ry1, rx0:rx1], scale)
            big = np.repeat(np.repeat(sub, scale, axis=0), scale, axis=1)
            sy, sx = oy - ry0 * scale, ox - rx0 * scale
            out = np.ascontiguousarray(big[sy:sy + (y1 - y0), sx:sx + (x1 - x0)])
        else:
            out = m.to_float(raw[y0 - cy0:y1 - cy0, x0 - cx0:x1 - cx0], 1)
        if pad:
            _drop_matches_into_padding(out, x0)
        return out

    def compute_coarse(self, left: np.ndarray, right: np.ndarray, y0: int = 0, scale: int = 4) -> np.ndarray:
        """Quick coarse disparity of rows ``y0:`` at full width, for large smooth
        surfaces (the road): both images' rows from ``y0`` (rounded down to the
        ``scale`` grid) shrunk by ``scale`` (INTER_AREA) and matched, no padding and no
        WLS filter.

        Returns the coarse map (cell ``(r, k)`` covers image rows
        ``y0 - y0 % scale + r * scale ..`` and columns ``k * scale ..``), values in
        full-resolution pixels, ``<= 0`` invalid (the leftmost ``numDisparities`` cells
        included).
        """
        left = _gray(left)
        right = _gray(right)
        if left.shape != right.shape:
            raise ValueError(f"left and right images differ in size: {left.shape} vs {right.shape}")
        m = self._matcher(scale)
        h, w = left.shape
        y0 = max(0, min(int(y0), h - 1))
        y0 -= y0 % scale
        hh, ww = (h - y0) // scale, w // scale
        if hh < 1 or ww < 1:
            return np.zeros((0, 0), np.float32)
        lc, rc = left[y0:y0 + hh * scale, :ww * scale], right[y0:y0 + hh * scale, :ww * scale]
        if scale > 1:
            lc = cv2.resize(lc, (ww, hh), interpolation=cv2.INTER_AREA)
            rc = cv2.resize(rc, (ww, hh), interpolation=cv2.INTER_AREA)
        else:
            lc, rc = np.ascontiguousarray(lc), np.ascontiguousarray(rc)
        # the left matcher alone: a WLS filter would smear the road into everything
        return m.to_float(m.left.compute(lc, rc), scale)

    def border_padding(self, crop: tuple[int, int, int, int], shape: tuple[int, int],
                       scale: int = 1) -> tuple[int, int, int]:
        """``(top, bottom, right)``: rows above / below and columns right of the image that
        :meth:`compute_band` adds (border replicate) to a crop ``(cy0, cy1, cx0, cx1)``
        reaching those image borders -- half a block and one more, a multiple of ``scale``.

        OpenCV leaves the outer half block of its input invalid: without the padding the
        bottom 7 rows of the image (block 15) have no disparity, and an object standing
        on the image's bottom edge (a truck 4 m ahead, a pedestrian close by) loses them
        -- the rows with its bumper and wheels.  Any crop reaching a border gets the same
        padding, so a band equals the full frame there too."""
        h, w = shape
        cy0, cy1, _, cx1 = crop
        half = (self.params(scale).block_size // 2 + 1) * scale
        return (half if cy0 <= 0 else 0, half if cy1 >= h else 0, half if cx1 >= w else 0)

    def left_padding(self, x0: int, scale: int = 1) -> int:
        """Columns :meth:`compute_band` adds left of the image for a region starting at
        column ``x0`` (0 when the image has them): a multiple of ``scale``."""
        p = self.params(scale)
        need = (max(p.min_disparity, 0) + p.num_disparities) * scale + (p.block_size // 2) * scale
        pad = max(0, need - int(x0))
        return -(-pad // scale) * scale


def _drop_matches_into_padding(d: np.ndarray, x0: int) -> None:
    """Invalidate (in place) disparities ``d > x`` of the columns ``x = x0 + k``: the
    matched right pixel ``x - d`` lies left of the right image, in the padding."""
    n = min(d.shape[1], int(d.max(initial=0.0)) + 1 - int(x0))  # only these columns can
    if n > 0:
        xs = (int(x0) + np.arange(n)).astype(np.float32)
        sub = d[:, :n]
        sub[sub > xs[None, :]] = 0.0


def normalize_disparity(disp: np.ndarray, enhance: bool = True) -> np.ndarray:
    """uint8 view of a disparity map (0 = invalid), thesis 3.3.3.

    Valid disparities are stretched linearly to 1..255 -- between the 2nd and 98th
    percentile with ``enhance`` (robust to a few outliers), else between min and max --
    and with ``enhance`` the contrast is then equalized locally (CLAHE), which brings out
    objects in scenes with poor disparity (much sky or plain ground).
    """
    d = np.asarray(disp, dtype=np.float32)
    out = np.zeros(d.shape, np.uint8)
    valid = d > 0
    if not valid.any():
        return out
    vals = d[valid]
    if enhance:
        lo, hi = (float(v) for v in np.percentile(vals, (2.0, 98.0)))
    else:
        lo, hi = float(vals.min()), float(vals.max())
    if hi <= lo:
        out[valid] = 255
        return out
    scaled = (d - lo) * (254.0 / (hi - lo)) + 1.0
    np.clip(scaled, 1.0, 255.0, out=scaled)
    out[valid] = scaled[valid].astype(np.uint8)
    if enhance:
        clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8))
        out = clahe.apply(out)
        out[~valid] = 0
        # CLAHE may map a valid pixel to 0; keep 0 reserved for invalid.
        out[valid & (out == 0)] = 1
    return out
