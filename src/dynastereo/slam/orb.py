"""ORB extraction: scale pyramid, grid-bucketed corners, dynamic mask given to the detector.

OpenCV's ORB detects FAST corners on every pyramid level (ranked by FAST score) with
the *static* region as detection mask -- the image itself is never painted, so mask
edges create no false corners.  We ask for ``oversample`` times more corners than wanted
and then spread them over the image with a per-level grid (like ORB-SLAM2's quadtree:
the strongest corner of every cell first, then the second strongest, ... until the
level's quota is met).  Descriptors are computed for the kept corners only.

The per-level quotas follow ORB-SLAM2: ``n * (1 - 1/s) / (1 - (1/s)^L)`` for level 0,
shrinking by ``1/s`` per level.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .kernels.bucketing import bucket_corners

EDGE_THRESHOLD = 19
PATCH_SIZE = 31


@dataclass
class Features:
    """Keypoints of one image, array-wise (level-0 pixel coordinates)."""

    uv: np.ndarray  # (N, 2) float64
    octave: np.ndarray  # (N,) int32 pyramid level
    angle: np.ndarray  # (N,) float32 degrees
    response: np.ndarray  # (N,) float32
    desc: np.ndarray  # (N, 32) uint8

    def __len__(self) -> int:
        return len(self.uv)

    @classmethod
    def empty(cls) -> "Features":
        return cls(
            np.zeros((0, 2)),
            np.zeros(0, np.int32),
            np.zeros(0, np.float32),
            np.zeros(0, np.float32),
            np.zeros((0, 32), np.uint8),
        )


class ORBExtractor:
    def __init__(
        self,
        n_features: int = 2000,
        scale_factor: float = 1.2,
        n_levels: int = 8,
        ini_th_fast: int = 20,
        min_th_fast: int = 7,
        oversample: float = 2.0,
        mask_margin: int = 0,
    ) -> None:
        if n_features < 1 or n_levels < 1 or scale_factor <= 1.0:
            raise ValueError(
                f"ORB extractor: invalid n_features={n_features}, n_levels={n_levels}, scale_factor={scale_factor}"
            )
        self.n_features = int(n_features)
        self.scale_factor = float(scale_factor)
        self.n_levels = int(n_levels)
        self.ini_th_fast = int(ini_th_fast)
        self.min_th_fast = int(min_th_fast)
        self.oversample = max(1.0, float(oversample))
        self.mask_margin = int(mask_margin)
        self.center_offset = True
        self.scales = self.scale_factor ** np.arange(self.n_levels)
        self.inv_scales = 1.0 / self.scales
        self.sigma2 = self.scales**2
        self.inv_sigma2 = 1.0 / self.sigma2
        f = 1.0 / self.scale_factor
        n0 = self.n_features * (1 - f) / (1 - f**self.n_levels)
        quota = np.round(n0 * f ** np.arange(self.n_levels)).astype(np.int64)
        quota[-1] = max(0, self.n_features - int(quota[:-1].sum()))
        self.quota = quota
        # the detector: FAST corners ranked by FAST score, at ini_th_fast; a pyramid level
        # where that finds too few corners is detected again at min_th_fast (ORB-SLAM2
        # retries the *cells* where ini_th_fast finds nothing; ranking by score within grid
        # cells gives the same preference for strong corners where there are some).  On
        # KITTI every level has enough at 20: FAST at 7 costs twice as much (35k corners
        # per image instead of 14k) for the same accuracy.
        self._det = self._orb(self.ini_th_fast)
        self._det_min = self._orb(self.min_th_fast) if self.min_th_fast < self.ini_th_fast else None
        self.fallbacks = 0  # images that needed the min_th_fast pass

    def _orb(self, threshold: int):
        return cv2.ORB_create(
            nfeatures=int(round(self.n_features * self.oversample)),
            scaleFactor=self.scale_factor,
            nlevels=self.n_levels,
            edgeThreshold=EDGE_THRESHOLD,
            firstLevel=0,
            WTA_K=2,
            scoreType=cv2.ORB_FAST_SCORE,
            patchSize=PATCH_SIZE,
            fastThreshold=int(threshold),
        )

    def detect_mask(self, dynamic: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray | None:
        """Detection mask (255 = may detect) from a dynamic mask (255 = dynamic)."""
        if dynamic is None:
            return None
        if dynamic.shape[:2] != shape:
            raise ValueError(f"mask shape {dynamic.shape[:2]} differs from image shape {shape}")
        dyn = dynamic
        if self.mask_margin > 0:
            k = 2 * self.mask_margin + 1
            dyn = cv2.dilate(dyn, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
        if not dyn.any():
            return None
        return np.where(dyn > 0, 0, 255).astype(np.uint8)

    def extract(self, gray: np.ndarray, dynamic: np.ndarray | None = None) -> Features:
        """ORB features of a grayscale image; no corner is detected where ``dynamic`` is set."""
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise ValueError("ORBExtractor.extract expects a uint8 grayscale image")
        mask = self.detect_mask(dynamic, gray.shape)
        kps, uv, resp, lev = self._detect(self._det, gray, mask)
        if self._det_min is not None:
            # levels with fewer corners than 3/4 of what bucketing wants: again at min_th_fast
            short = np.bincount(lev, minlength=self.n_levels)[: self.n_levels] < 0.75 * self.oversample * self.quota
            if short.any():
                self.fallbacks += 1
                kps2, uv2, resp2, lev2 = self._detect(self._det_min, gray, mask)
                a = np.flatnonzero(~short[np.clip(lev, 0, self.n_levels - 1)])
                b = np.flatnonzero(short[np.clip(lev2, 0, self.n_levels - 1)])
                kps = [kps[i] for i in a] + [kps2[i] for i in b]
                uv, resp, lev = np.concatenate([uv[a], uv2[b]]), np.concatenate([resp[a], resp2[b]]), np.concatenate([lev[a], lev2[b]])
        if not len(kps):
            return Features.empty()
        n = len(kps)
        cand = np.arange(n)
        if mask is not None:
            # OpenCV checks the mask on each pyramid level (resized): at coarse levels a
            # corner near the edge can still land on a dynamic pixel in full resolution
            H, W = gray.shape
            c = self.centre(uv, lev, gray.shape)
            x = np.clip(np.rint(c[:, 0]).astype(np.int64), 0, W - 1)
            y = np.clip(np.rint(c[:, 1]).astype(np.int64), 0, H - 1)
            cand = np.flatnonzero(mask[y, x] > 0)
        keep = cand[self._bucket(uv[cand, 0], uv[cand, 1], resp[cand], lev[cand], gray.shape)]
        sel = [kps[i] for i in keep]
        sel, desc = self._det.compute(gray, sel)
        if desc is None or not sel:
            return Features.empty()
        m = len(sel)
        if m != len(keep):  # compute() may drop points at the border; re-read them
            uv = cv2.KeyPoint_convert(sel).astype(np.float64).reshape(-1, 2)
            resp = np.fromiter((k.response for k in sel), np.float32, m)
            lev = np.fromiter((k.octave for k in sel), np.int32, m)
        else:
            uv, resp, lev = uv[keep], resp[keep], lev[keep]
        angle = np.fromiter((k.angle for k in sel), np.float32, m)
        return Features(uv=self.centre(uv, lev, gray.shape), octave=lev, angle=angle, response=resp, desc=np.ascontiguousarray(desc))

    @staticmethod
    def _detect(det, gray: np.ndarray, mask: np.ndarray | None):
        """Keypoints and, as arrays, their points, scores and levels.  cv2.KeyPoint ->
        arrays at the OpenCV boundary: points in C++ (KeyPoint_convert), score and level
        through np.fromiter (about 0.05 us per keypoint)."""
        kps = det.detect(gray, mask)
        n = len(kps)
        if n == 0:
            return kps, np.zeros((0, 2)), np.zeros(0, np.float32), np.zeros(0, np.int32)
        uv = cv2.KeyPoint_convert(kps).astype(np.float64).reshape(-1, 2)
        resp = np.fromiter((k.response for k in kps), np.float32, n)
        lev = np.fromiter((k.octave for k in kps), np.int32, n)
        return kps, uv, resp, lev

    def centre(self, uv: np.ndarray, lev: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Full-resolution position of corners that OpenCV reports as ``(x_l * s_l, y_l * s_l)``.

        OpenCV's ORB resizes each level from the previous one (linear interpolation) to
        ``round(W / s_l) x round(H / s_l)``, so level pixel ``x_l`` is centred at
        ``(x_l + 0.5) * W / W_l - 0.5`` of the full image (per axis; the size rounding
        matters: 370 rows / 103 at level 7 is 3.592, not 1.2^7 = 3.583).
        """
        if not self.center_offset:
            return uv
        H, W = shape
        lv = np.clip(lev, 0, self.n_levels - 1)
        s = self.scales[lv]
        Wl = np.round(W / self.scales)[lv]
        Hl = np.round(H / self.scales)[lv]
        out = np.empty_like(uv)
        out[:, 0] = (np.rint(uv[:, 0] / s) + 0.5) * (W / Wl) - 0.5
        out[:, 1] = (np.rint(uv[:, 1] / s) + 0.5) * (H / Hl) - 0.5
        return out

    def _bucket(self, u: np.ndarray, v: np.ndarray, resp: np.ndarray, lev: np.ndarray, shape) -> np.ndarray:
        """Indices of the kept corners: per level, grid cells of about one quota-th of
        the image; rank corners within their cell by response; take rank 0 of every cell,
        then rank 1, ..., strongest first, until the level's quota is met (one compiled
        call, :func:`.kernels.bucketing.bucket_corners`)."""
        H, W = shape
        return bucket_corners(np.ascontiguousarray(u, np.float64), np.ascontiguousarray(v, np.float64),
                              np.ascontiguousarray(resp, np.float32), np.ascontiguousarray(lev, np.int32),
                              self.quota, int(W), int(H))
