"""Disparity estimation: OpenCV BM / SGBM (+ WLS), band and half-resolution fast paths,
parameter validation, the normalized view.  Synthetic known-answer pairs + KITTI 2015 GT."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import require
from dynastereo.config import StereoConfig
from dynastereo.errors import ConfigError
from dynastereo.masking.disparity import StereoMatcher, normalize_disparity, params_at_scale


# ---------------------------------------------------------------------------------------
# synthetic stereo: textured fronto-parallel layers at known integer disparities
# ---------------------------------------------------------------------------------------
def texture(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 1.0)
    t = (t - t.min()) * (255.0 / (t.max() - t.min()))
    return t.astype(np.uint8)


def layered_pair(h: int, w: int, d_bg: int, layers: list[tuple[np.ndarray, int]], seed: int = 0):
    """Left/right images + GT left disparity; each layer = (left mask, disparity), far to near."""
    bg = texture(h, w + d_bg, seed)
    left = bg[:, :w].copy()
    right = bg[:, d_bg:d_bg + w].copy()
    gt = np.full((h, w), float(d_bg), np.float32)
    for k, (m, d) in enumerate(layers):
        tex = texture(h, w + d, seed + 1 + k)
        left[m] = tex[:, :w][m]
        mr = np.zeros_like(m)
        mr[:, :w - d] = m[:, d:]
        right[mr] = tex[:, d:d + w][mr]
        gt[m] = d
    return left, right, gt


def rect_mask(h, w, x0, y0, x1, y1):
    m = np.zeros((h, w), bool)
    m[y0:y1, x0:x1] = True
    return m


@pytest.fixture(scope="module")
def planes():
    h, w = 200, 400
    return layered_pair(h, w, 12, [(rect_mask(h, w, 200, 50, 330, 150), 37)])


# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "alg,block", [("bm", 15), ("bm", 9), ("sgbm", 5), ("sgbm3way", 5), ("hh", 5)]
)
def test_planes_recovered_within_one_pixel(planes, alg, block):
    left, right, gt = planes
    m = StereoMatcher(StereoConfig(algorithm=alg, block_size=block, num_disparities=64))
    d = m.compute(left, right)
    assert d.dtype == np.float32 and d.shape == left.shape
    # interior of each plane, away from the image border, the matcher's invalid left band
    # and the depth edges
    interior = np.zeros_like(gt, bool)
    interior[15:-15, 64 + 15:-15] = True
    edge = cv2.dilate((np.abs(cv2.Laplacian(gt, cv2.CV_32F)) > 0).astype(np.uint8), np.ones((21, 45), np.uint8)) > 0
    region = interior & ~edge
    valid = region & (d > 0)
    assert valid.sum() > 0.9 * region.sum(), f"{alg}: density {valid.sum() / region.sum():.2f}"
    err = np.abs(d - gt)[valid]
    assert np.mean(err <= 1.0) > 0.98, f"{alg}: {np.mean(err <= 1.0):.3f} within 1 px"
    # both planes are found
    for level in (12, 37):
        sel = valid & (gt == level)
        assert abs(float(np.median(d[sel])) - level) < 0.5


def test_left_border_columns_matched_and_no_negative(planes):
    """Both images are padded on the left before matching, so the leftmost numDisparities
    columns (which OpenCV leaves invalid) get disparities wherever the match is inside the
    right image (d <= x); never a match into the padding (d > x).  (Before the padding
    the first 63 columns were all invalid: this test asserted that.)"""
    left, right, gt = planes
    d = StereoMatcher(StereoConfig(num_disparities=64)).compute(left, right)
    assert (d >= 0).all()  # invalid is reported as 0, never as OpenCV's (minD-1)
    xs = np.arange(d.shape[1])[None, :]
    assert not (d > xs).any()  # x - d < 0: outside the right image
    border = np.s_[15:-15, 12 + 8:60]  # background d = 12, matchable for x >= 12
    assert (d[border] > 0).mean() > 0.9
    assert np.median(np.abs(d[border] - 12)) < 0.5


def test_left_border_object_recovered():
    """A textured object at the image's left border (d = 20, columns 0..69) in front of a
    background (d = 5): its pixels x >= 20 are matched at 20 -- OpenCV alone gives none
    of them (it leaves columns < numDisparities - 1 invalid)."""
    h, w = 160, 320
    left, right, gt = layered_pair(h, w, 5, [(rect_mask(h, w, 0, 30, 70, 130), 20)], seed=3)
    for alg, block in (("bm", 15), ("sgbm3way", 5)):
        d = StereoMatcher(StereoConfig(algorithm=alg, block_size=block, num_disparities=64)).compute(left, right)
        obj = np.s_[40:120, 20 + block:60]
        assert (d[obj] > 0).mean() > 0.9, alg
        assert np.median(np.abs(d[obj] - 20)) < 0.5, alg
        assert not (d > np.arange(w)[None, :]).any()


def test_bm_unchanged_away_from_the_borders(planes):
    """The padding changes nothing where OpenCV already had every candidate disparity and
    the whole block: away from the left border and half a block from the other three."""
    left, right, _ = planes
    m = StereoMatcher(StereoConfig(num_disparities=64, block_size=15))
    ours = m.compute(left, right)
    raw = m._matcher(1).left.compute(left, right)
    ref = m._matcher(1).to_float(raw, 1)
    inner = np.s_[8:-8, 64 + 15:-8]
    np.testing.assert_array_equal(ours[inner], ref[inner])
    # OpenCV alone leaves the outer half block invalid; with the padding it is matched
    for edge in (np.s_[:7, 64 + 15:], np.s_[-7:, 64 + 15:], np.s_[8:-8, -7:]):
        assert (ref[edge] <= 0).all()
        assert (ours[edge] > 0).mean() > 0.9


def test_object_on_the_bottom_edge_keeps_its_bottom_rows():
    """A textured object standing on the image's bottom edge (a truck close ahead): its
    bottom rows get its disparity, in the full frame, in a band and at half resolution."""
    h, w = 120, 320
    obj = rect_mask(h, w, 120, 40, 260, h)
    left, right, gt = layered_pair(h, w, 4, [(obj, 30)], seed=5)
    m = StereoMatcher(StereoConfig(num_disparities=64, block_size=15))
    full = m.compute(left, right)[h - 7:, 140:240]
    band = m.compute_band(left, right, 60, h, 100, 280)[-7:, 40:140]  # band rows 60..h, cols 100..280
    half = m.compute(left, right, scale=2)[h - 7:, 140:240]
    for sub in (full, band, half):
        assert (sub > 0).mean() > 0.9
        assert np.median(np.abs(sub[sub > 0] - 30)) < 1.0
    np.testing.assert_array_equal(full, band)


def test_sgbm_band_at_left_border_narrower_than_num_disparities(planes):
    """A band touching the left border and narrower than numDisparities (a small box near
    the border): SGBM used to fail inside OpenCV (negative allocation); it is padded now."""
    left, right, _ = planes
    m = StereoMatcher(StereoConfig(algorithm="sgbm3way", block_size=5, num_disparities=64))
    b = m.compute_band(left, right, 60, 100, 0, 20)
    assert b.shape == (40, 20)
    assert (b <= np.arange(20)[None, :]).all()
    assert np.median(b[b > 0]) == pytest.approx(12, abs=0.5)  # the background, where x >= 12


def test_compute_coarse(planes):
    left, right, gt = planes
    m = StereoMatcher(StereoConfig(num_disparities=64))
    for scale in (2, 4):
        c = m.compute_coarse(left, right, y0=41, scale=scale)
        y0 = 41 - 41 % scale
        assert c.shape == ((200 - y0) // scale, 400 // scale)
        # cell (r, k) covers rows y0 + r*scale.., columns k*scale..: the background (d = 12)
        # right of the near plane (columns 200..330)
        bg = c[3:-3, 340 // scale:-3]
        assert (bg > 0).mean() > 0.8
        assert np.median(np.abs(bg[bg > 0] - 12)) < 1.0
        plane = c[(60 - y0) // scale:(140 - y0) // scale, 215 // scale:315 // scale]
        assert np.median(plane[plane > 0]) == pytest.approx(37, abs=1.0)


def test_min_disparity_invalid_maps_to_zero(planes):
    left, right, gt = planes
    m = StereoMatcher(StereoConfig(min_disparity=8, num_disparities=48))
    d = m.compute(left, right)
    # OpenCV marks invalid as (minD - 1) * 16 = 7 px here; it must come back as 0
    assert not np.any(np.isclose(d, 7.0))
    v = d > 0
    assert v.mean() > 0.4
    assert np.median(np.abs(d - gt)[v]) < 0.5


def test_wls_dense_and_accurate(planes):
    left, right, gt = planes
    d = StereoMatcher(StereoConfig(num_disparities=64, wls=True)).compute(left, right)
    inner = np.s_[20:-20, 90:-20]
    assert (d[inner] > 0).mean() > 0.99  # WLS fills the invalid pixels
    assert np.median(np.abs(d - gt)[inner]) < 0.5


def test_every_parameter_reaches_opencv():
    cfg = StereoConfig(
        algorithm="bm", min_disparity=2, num_disparities=64, block_size=11, disp12_max_diff=3,
        pre_filter_cap=25, uniqueness_ratio=7, speckle_window_size=55, speckle_range=4,
        texture_threshold=17,
    )
    bm = StereoMatcher(cfg)._matcher(1).left
    assert (bm.getMinDisparity(), bm.getNumDisparities(), bm.getBlockSize(), bm.getDisp12MaxDiff(),
            bm.getPreFilterCap(), bm.getUniquenessRatio(), bm.getSpeckleWindowSize(),
            bm.getSpeckleRange(), bm.getTextureThreshold()) == (2, 64, 11, 3, 25, 7, 55, 4, 17)
    for alg, mode in (("sgbm", cv2.STEREO_SGBM_MODE_SGBM), ("sgbm3way", cv2.STEREO_SGBM_MODE_SGBM_3WAY),
                      ("hh", cv2.STEREO_SGBM_MODE_HH)):
        cfg = StereoConfig(algorithm=alg, min_disparity=-4, num_disparities=32, block_size=7, p1=100,
                           p2=900, disp12_max_diff=2, pre_filter_cap=40, uniqueness_ratio=3,
                           speckle_window_size=80, speckle_range=1)
        sg = StereoMatcher(cfg)._matcher(1).left
        assert (sg.getMode(), sg.getMinDisparity(), sg.getNumDisparities(), sg.getBlockSize(), sg.getP1(),
                sg.getP2(), sg.getDisp12MaxDiff(), sg.getPreFilterCap(), sg.getUniquenessRatio(),
                sg.getSpeckleWindowSize(), sg.getSpeckleRange()) == (mode, -4, 32, 7, 100, 900, 2, 40, 3, 80, 1)
    # defaults for P1/P2: 8 and 32 * block^2
    sg = StereoMatcher(StereoConfig(algorithm="sgbm", block_size=5))._matcher(1).left
    assert (sg.getP1(), sg.getP2()) == (200, 800)
    wls = StereoMatcher(StereoConfig(wls=True, wls_lambda=5000, wls_sigma=1.2))._matcher(1).wls
    assert wls.getLambda() == pytest.approx(5000) and wls.getSigmaColor() == pytest.approx(1.2)


@pytest.mark.parametrize(
    "kw,what",
    [
        ({"num_disparities": 100}, "num_disparities"),
        ({"num_disparities": 0}, "num_disparities"),
        ({"block_size": 16}, "block_size"),
        ({"block_size": 3}, "block_size"),  # BM needs >= 5
        ({"block_size": 257, "algorithm": "sgbm"}, "block_size"),
        ({"algorithm": "census"}, "algorithm"),
        ({"algorithm": "sgbm", "p1": 500, "p2": 400}, "p2"),
        ({"pre_filter_cap": 64}, "pre_filter_cap"),
        ({"uniqueness_ratio": -1}, "uniqueness_ratio"),
        ({"speckle_range": -2}, "speckle"),
        ({"region": "roi"}, "region"),
        ({"scale": 3}, "scale"),
        ({"wls": True, "wls_sigma": 0.0}, "wls"),
    ],
)
def test_invalid_config_raises(kw, what):
    with pytest.raises(ConfigError, match=what):
        StereoMatcher(StereoConfig(**kw))


def test_sgbm_accepts_small_block():
    StereoMatcher(StereoConfig(algorithm="sgbm", block_size=1))
    StereoMatcher(StereoConfig(algorithm="sgbm3way", block_size=3))


def test_params_at_half_scale():
    p = params_at_scale(StereoConfig(num_disparities=96, block_size=15, speckle_window_size=100), 2)
    assert (p.num_disparities, p.block_size, p.speckle_window_size) == (48, 7, 25)
    p = params_at_scale(StereoConfig(num_disparities=80, block_size=7), 2)
    assert p.num_disparities == 48 and p.block_size == 5  # rounded up to 16; BM block >= 5


@pytest.mark.parametrize("alg", ["bm", "sgbm3way"])
def test_band_equals_full_frame_inside_region(planes, alg):
    left, right, _ = planes
    m = StereoMatcher(StereoConfig(algorithm=alg, block_size=15 if alg == "bm" else 5, num_disparities=64))
    full = m.compute(left, right)
    for y0, y1, x0, x1 in ((40, 160, 190, 340), (0, 80, 0, 120), (120, 200, 300, 400)):
        band = m.compute_band(left, right, y0, y1, x0, x1)
        assert band.shape == (y1 - y0, x1 - x0)
        same = np.abs(band - full[y0:y1, x0:x1]) <= 0.25
        assert same.mean() > 0.97, (alg, (y0, y1, x0, x1), same.mean())


def test_half_scale_close_to_full(planes):
    left, right, gt = planes
    m = StereoMatcher(StereoConfig(num_disparities=64))
    half = m.compute(left, right, scale=2)
    assert half.shape == left.shape
    band = m.compute_band(left, right, 41, 163, 187, 351, scale=2)  # odd offsets: grid alignment
    assert band.shape == (122, 164)
    assert (np.abs(band - half[41:163, 187:351]) <= 0.5).mean() > 0.97  # same coarse grid
    inner = np.s_[20:-20, 90:-20]
    v = half[inner] > 0
    assert v.mean() > 0.8
    err = np.abs(half[inner] - gt[inner])[v]
    assert np.mean(err <= 2.0) > 0.9  # half resolution: within 2 px (one coarse pixel)


def test_band_region_clipped_to_image(planes):
    left, right, _ = planes
    m = StereoMatcher(StereoConfig(num_disparities=64))
    b = m.compute_band(left, right, -20, 50, 350, 900)
    assert b.shape == (50, 50)
    assert m.compute_band(left, right, 10, 10, 0, 50).shape == (0, 50)


def test_colour_input_and_size_mismatch(planes):
    left, right, _ = planes
    m = StereoMatcher()
    a = m.compute(cv2.cvtColor(left, cv2.COLOR_GRAY2BGR), cv2.cvtColor(right, cv2.COLOR_GRAY2BGR))
    np.testing.assert_array_equal(a, m.compute(left, right))
    with pytest.raises(ValueError, match="differ"):
        m.compute(left, right[:, :-2])


def test_normalize_disparity():
    rng = np.random.default_rng(1)
    # poor-disparity scene: almost everything at ~10 px, a faint object at 10.8 px
    d = np.full((120, 160), 10.0, np.float32) + rng.normal(0, 0.05, (120, 160)).astype(np.float32)
    d[40:80, 60:100] += 0.8
    d[:, :20] = 0.0  # invalid
    for enhance in (False, True):
        v = normalize_disparity(d, enhance=enhance)
        assert v.dtype == np.uint8 and v.shape == d.shape
        assert (v[:, :20] == 0).all() and (v[:, 20:] >= 1).all()
    plain = normalize_disparity(d, enhance=False)
    enh = normalize_disparity(d, enhance=True)
    # object vs background separation in grey levels grows with enhancement
    sep_plain = float(plain[45:75, 65:95].mean()) - float(plain[45:75, 25:55].mean())
    sep_enh = float(enh[45:75, 65:95].mean()) - float(enh[45:75, 25:55].mean())
    assert sep_enh > 0 and sep_plain > 0
    assert normalize_disparity(np.zeros((4, 4), np.float32)).max() == 0
    # monotone without enhancement
    ramp = np.tile(np.linspace(1, 50, 64, dtype=np.float32), (4, 1))
    r = normalize_disparity(ramp, enhance=False)
    assert (np.diff(r[0].astype(int)) >= 0).all() and r[0, 0] == 1 and r[0, -1] == 255


# ---------------------------------------------------------------------------------------
# real data: KITTI 2015 with ground truth
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def kitti2015(data_dir):
    root = require(data_dir / "kitti_stereo2015/training", "KITTI stereo 2015")
    name = "000046_10.png"
    left = cv2.imread(str(require(root / "image_2" / name)), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(require(root / "image_3" / name)), cv2.IMREAD_GRAYSCALE)
    gt = cv2.imread(str(require(root / "disp_occ_0" / name)), cv2.IMREAD_UNCHANGED).astype(np.float32) / 256.0
    return left, right, gt


def _rates(d: np.ndarray, gt: np.ndarray) -> tuple[float, float, float]:
    v = gt > 0
    est = v & (d > 0)
    bad_est = np.abs(d - gt) > 3
    return (
        float((v & (bad_est | (d <= 0))).sum() / v.sum()),  # bad incl. missing
        float((est & bad_est).sum() / est.sum()),  # bad among estimates
        float(est.sum() / v.sum()),  # density
    )


@pytest.mark.realdata
@pytest.mark.parametrize(
    "cfg,max_bad_all,max_bad_est,min_density",
    [
        (StereoConfig(algorithm="bm", block_size=15, num_disparities=128), 0.70, 0.06, 0.35),
        (StereoConfig(algorithm="bm", block_size=15, num_disparities=128, wls=True), 0.35, 0.25, 0.85),
        (StereoConfig(algorithm="sgbm3way", block_size=5, num_disparities=128), 0.18, 0.05, 0.85),
        (StereoConfig(algorithm="sgbm", block_size=5, num_disparities=128), 0.18, 0.05, 0.85),
    ],
)
def test_kitti2015_bad_pixel_rate(kitti2015, cfg, max_bad_all, max_bad_est, min_density):
    left, right, gt = kitti2015
    d = StereoMatcher(cfg).compute(left, right)
    bad_all, bad_est, density = _rates(d, gt)
    assert bad_all < max_bad_all and bad_est < max_bad_est and density > min_density, (
        cfg.algorithm, cfg.wls, bad_all, bad_est, density)


@pytest.mark.realdata
def test_kitti2015_half_scale_not_much_worse(kitti2015):
    left, right, gt = kitti2015
    m = StereoMatcher(StereoConfig(algorithm="sgbm3way", block_size=5, num_disparities=128))
    full = _rates(m.compute(left, right), gt)
    half = _rates(m.compute(left, right, scale=2), gt)
    assert half[0] < full[0] + 0.05 and half[2] > full[2] - 0.05, (full, half)


@pytest.mark.realdata
def test_kitti_band_matches_full(kitti06):
    left = cv2.imread(str(require(kitti06 / "image_0/000010.png")), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(require(kitti06 / "image_1/000010.png")), cv2.IMREAD_GRAYSCALE)
    m = StereoMatcher(StereoConfig())
    full = m.compute(left, right)
    for y0, y1, x0, x1 in ((150, 260, 500, 700), (100, 300, 0, 300), (150, 250, 900, left.shape[1])):
        band = m.compute_band(left, right, y0, y1, x0, x1)
        assert (np.abs(band - full[y0:y1, x0:x1]) <= 0.25).mean() > 0.98
