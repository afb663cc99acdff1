"""Masking: outline from the dominant disparity peak, transfer to the right image, maskers.

Synthetic stereo pairs with known answers (textured layers shifted by known integer
disparities) + KITTI odometry frames with the real detector."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import require
from dynastereo.config import Config, OutlineConfig, StereoConfig
from dynastereo.errors import ConfigError
from dynastereo.masking import (
    BoxMasker,
    NoneMasker,
    OutlineMasker,
    SegMasker,
    StereoMatcher,
    build_masker,
    outline_objects,
    transfer_labels,
)
from dynastereo.masking.ground import GroundLine, fit_ground_line, road_samples, sample_valid, slope_range
from dynastereo.masking.maskers import match_stereo_detections, plan_regions, region_disparity
from dynastereo.masking.outline import (
    clip_boxes,
    dominant_disparity,
    fill_invalid_rows,
)
from dynastereo.timing import StageTimer
from dynastereo.datatypes import Detections, MaskMethod, StereoFrame

H, W = 240, 480


# ---------------------------------------------------------------------------------------
# synthetic scenes
# ---------------------------------------------------------------------------------------
def texture(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 1.0)
    t = (t - t.min()) * (255.0 / (t.max() - t.min()))
    return t.astype(np.uint8)


def shift_left(m: np.ndarray, d: int) -> np.ndarray:
    """Where a left-image mask lands in the right image for disparity d (x_r = x_l - d)."""
    out = np.zeros_like(m)
    out[:, : m.shape[1] - d] = m[:, d:]
    return out


def layered_pair(d_bg: int, layers: list[tuple[np.ndarray, int]], seed: int = 0, h: int = H, w: int = W):
    """Textured background at d_bg plus textured layers (left mask, disparity), far to near.

    Returns left, right, and per layer its GT right mask (the visible part, occlusion by
    nearer layers included)."""
    bg = texture(h, w + d_bg, seed)
    left = bg[:, :w].copy()
    right = bg[:, d_bg:d_bg + w].copy()
    rights = []
    for k, (m, d) in enumerate(layers):
        tex = texture(h, w + d, seed + 1 + k)
        left[m] = tex[:, :w][m]
        mr = shift_left(m, d)
        right[mr] = tex[:, d:d + w][mr]
        rights = [r & ~mr for r in rights] + [mr]
    return left, right, rights


def ellipse_mask(cx, cy, ax, ay, h=H, w=W) -> np.ndarray:
    m = np.zeros((h, w), np.uint8)
    cv2.ellipse(m, (cx, cy), (ax, ay), 0, 0, 360, 1, -1)
    return m.astype(bool)


def rect_mask(x0, y0, x1, y1, h=H, w=W) -> np.ndarray:
    m = np.zeros((h, w), bool)
    m[y0:y1, x0:x1] = True
    return m


def box_of(m: np.ndarray) -> list[float]:
    ys, xs = np.nonzero(m)
    return [float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1)]


def dets(*boxes, labels=None) -> Detections:
    n = len(boxes)
    return Detections(np.array(boxes, np.float32).reshape(-1, 4), np.full(n, 0.9), np.full(n, 2), ("person", "bicycle", "car"))


class FakeDetector:
    name = "fake"
    class_names = ("person", "bicycle", "car")

    def __init__(self, detections: Detections):
        self.detections = detections
        self.calls = 0

    def detect(self, image):
        self.calls += 1
        return self.detections


def iou(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a > 0, b > 0
    return float((a & b).sum() / max((a | b).sum(), 1))


def frame(left, right) -> StereoFrame:
    return StereoFrame(index=0, timestamp=0.0, left=left, right=right)


STEREO = StereoConfig(num_disparities=64, block_size=15)


@pytest.fixture(scope="module")
def blob_scene():
    """A 'car' (ellipse, d=30) in front of a textured background (d=8)."""
    blob = ellipse_mask(260, 130, 70, 45)
    left, right, (blob_r,) = layered_pair(8, [(blob, 30)])
    return left, right, blob, blob_r


# ---------------------------------------------------------------------------------------
# building blocks
# ---------------------------------------------------------------------------------------
def test_dominant_disparity_peak_refined():
    rng = np.random.default_rng(0)
    v = np.r_[rng.normal(20.3, 0.3, 600), rng.normal(7.0, 0.3, 300), rng.uniform(1, 60, 100)]
    p = dominant_disparity(v.astype(np.float32), 1.0)
    assert abs(p.disparity - 20.3) < 0.2
    # the nearer peak wins when nearly as high
    v2 = np.r_[rng.normal(10, 0.3, 500), rng.normal(30, 0.3, 400)].astype(np.float32)
    assert abs(dominant_disparity(v2, 1.0).disparity - 10) < 0.3
    assert abs(dominant_disparity(v2, 1.0, near_ratio=0.5).disparity - 30) < 0.3
    # a slanted surface (uniform 40..60) plus background: the extended range covers it
    v3 = np.r_[rng.uniform(40, 60, 2000), rng.normal(10, 0.3, 300)].astype(np.float32)
    p3 = dominant_disparity(v3, 1.0, rel=0.08, extend_ratio=0.1)
    assert p3.lo < 42 and p3.hi > 58 and 40 <= p3.disparity <= 60
    assert dominant_disparity(np.zeros(0, np.float32), 1.0) is None


def test_fill_invalid_rows_takes_farther_neighbour():
    d = np.array([[0, 5, 0, 0, 9, 0], [0, 0, 0, 0, 0, 0], [3, 0, 3, 0, 0, 7]], np.float32)
    f = fill_invalid_rows(d)
    np.testing.assert_array_equal(f[0], [5, 5, 5, 5, 9, 9])
    np.testing.assert_array_equal(f[1], 0)
    np.testing.assert_array_equal(f[2], [3, 3, 3, 3, 3, 7])
    # runs at either end take their only neighbour
    f = fill_invalid_rows(np.array([[0, 0, 8, 0, 0]], np.float32))
    np.testing.assert_array_equal(f, [[8, 8, 8, 8, 8]])



def _fill_rows_reference(d: np.ndarray) -> np.ndarray:
    """fill_invalid_rows as plain numpy (the form it had before its kernel)."""
    h, w = d.shape
    valid = d > 0
    if valid.all() or not valid.any():
        return d.copy()
    idx = np.arange(w, dtype=np.int32)[None, :]
    li = np.maximum.accumulate(np.where(valid, idx, np.int32(-1)), axis=1)
    ri = np.minimum.accumulate(np.where(valid, idx, np.int32(w))[:, ::-1], axis=1)[:, ::-1]
    dpad = np.zeros((h, w + 1), np.float32)
    dpad[:, :w] = d
    lv = np.take_along_axis(dpad, np.where(li >= 0, li, np.int32(w)), axis=1)
    rv = np.take_along_axis(dpad, ri, axis=1)
    two_sided = np.where((rv > lv) & ~((idx - li) <= (rv - lv)), rv, np.minimum(lv, rv))
    filled = np.where((lv > 0) & (rv > 0), two_sided, np.maximum(lv, rv))
    return np.where(valid, d, filled).astype(np.float32)


def test_fill_invalid_rows_kernel_agrees_with_the_reference():
    """The compiled row fill gives the plain numpy version's result bit for bit on random
    rows: holes, invalid (negative) values, ties, all valid and none."""
    rng = np.random.default_rng(0)
    for _ in range(500):
        h, w = int(rng.integers(1, 10)), int(rng.integers(1, 40))
        d = (rng.uniform(0, 60, (h, w)) * (rng.random((h, w)) < rng.uniform(0, 1))).astype(np.float32)
        d[rng.random((h, w)) < 0.1] = -1.0
        if rng.random() < 0.3:
            d = np.round(d)
        out = fill_invalid_rows(d)
        assert out.dtype == np.float32 and np.array_equal(out, _fill_rows_reference(d))

def _dominant_reference(v, bw, rel, near_ratio, weights, extend_ratio):
    """dominant_disparity as plain numpy (the form it had before its kernel): (d, n, lo, hi)."""
    from dynastereo.masking.outline import _to_bins

    u = _to_bins(v, bw, rel)
    idx = (u - float(u.min())).astype(np.int64)
    counts = np.bincount(idx, weights=weights).astype(np.float64)
    sm = counts * 2.0
    if counts.size >= 3:
        sm[1:] += counts[:-1]
        sm[:-1] += counts[1:]
    else:
        sm = counts
    k = int(np.argmax(sm))
    if near_ratio < 1.0 and sm.size >= 3:
        cand = np.flatnonzero((sm >= np.r_[-1.0, sm[:-1]]) & (sm >= np.r_[sm[1:], -1.0]) & (sm >= near_ratio * sm[k]))
        k = int(cand.max())
    sel = (idx >= k - 1) & (idx <= k + 1)
    d = float(np.average(v[sel], weights=weights[sel] + 1e-12)) if weights is not None else float(v[sel].mean())
    lo = hi = d
    if extend_ratio < 1.0:
        below = np.flatnonzero(sm < extend_ratio * sm[k])
        kl = int(below[below < k].max()) + 1 if np.any(below < k) else 0
        kh = int(below[below > k].min()) - 1 if np.any(below > k) else sm.size - 1
        if kl < k and np.any(idx == kl):
            lo = float(v[idx == kl].min())
        if kh > k and np.any(idx == kh):
            hi = float(v[idx == kh].max())
    return d, int(np.count_nonzero(sel)), min(lo, d), max(hi, d)


def test_dominant_disparity_kernel_agrees_with_the_reference():
    """The compiled histogram peak gives the plain numpy version's peak bit for bit on
    random disparities: flat, peaked over background, on the 1/16 px grid; weighted or
    not; the near-peak rule and the range extension on and off."""
    rng = np.random.default_rng(0)
    for _ in range(600):
        n = int(rng.integers(1, 300))
        kind = int(rng.integers(0, 3))
        if kind == 0:
            v = rng.uniform(0.5, 90, n)
        elif kind == 1:
            v = np.r_[rng.normal(rng.uniform(5, 60), rng.uniform(0.1, 3), n), rng.uniform(1, 90, n // 3)]
        else:
            v = np.round(rng.uniform(1, 40, n) * 16) / 16
        v = np.abs(v).astype(np.float32) + np.float32(0.01)
        w = None if rng.random() < 0.5 else np.where(rng.random(v.size) < 0.3, np.float32(0.25), np.float32(1.0))
        args = (float(rng.choice([0.5, 1.0])), float(rng.choice([0.0, 0.08])), float(rng.choice([1.0, 0.4])))
        er = float(rng.choice([1.0, 0.1]))
        p = dominant_disparity(v, args[0], rel=args[1], near_ratio=args[2], weights=w, extend_ratio=er)
        assert (p.disparity, p.count, p.lo, p.hi) == _dominant_reference(v, *args, w, er)


def test_affine_paint_kernel_agrees_with_the_reference():
    """The compiled affine transfer paints the right image as the plain numpy version
    (sample every right pixel of the corners' span back at ``rint((x + a + c y) / (1 -
    b))``, then paint the block clipped to the image) on random masks and models, boxes at
    the image's edges included."""
    from reference.masking_numpy import _paint, _paint_affine

    def reference(right, m, roi, model, value):
        x0, y0, x1, y1 = roi
        a, b, c = model
        cx = np.array([x0, x1 - 1, x0, x1 - 1], np.float64)
        cy = np.array([y0, y0, y1 - 1, y1 - 1], np.float64)
        xr = cx - (a + b * cx + c * cy)
        rx0, rx1 = int(np.floor(xr.min())) - 1, int(np.ceil(xr.max())) + 2
        xs, ys = np.arange(rx0, rx1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64)
        xl = np.rint((xs[None, :] + a + c * ys[:, None]) / (1.0 - b)).astype(np.int64) - x0
        inside = (xl >= 0) & (xl < x1 - x0)
        vals = np.zeros(xl.shape, bool)
        vals[inside] = m[np.broadcast_to(np.arange(y1 - y0)[:, None], xl.shape)[inside], xl[inside]]
        return _paint(right, vals, rx0, y0, value)

    rng = np.random.default_rng(0)
    H_, W_ = 60, 120
    for _ in range(300):
        x0, y0 = int(rng.integers(0, W_ - 5)), int(rng.integers(0, H_ - 5))
        x1, y1 = min(W_, x0 + int(rng.integers(2, 50))), min(H_, y0 + int(rng.integers(2, 30)))
        m = rng.random((y1 - y0, x1 - x0)) < 0.6
        model = (float(rng.uniform(-5, 80)), float(rng.uniform(-0.25, 0.25)), float(rng.uniform(-0.25, 0.25)))
        if rng.random() < 0.3:
            model = (float(np.round(model[0]) + 0.5), 0.0, 0.0)  # halves: rint's ties
        a_, b_ = np.zeros((H_, W_), np.int32), np.zeros((H_, W_), np.int32)
        x1_ = min(x1, W_ - 4)  # away from the border extension (it is the same code on both sides)
        if x1_ <= x0 + 1:
            continue
        m = m[:, : x1_ - x0]
        r1 = _paint_affine(a_, m, m, (x0, y0, x1_, y1), model, 3)
        r2 = reference(b_, m, (x0, y0, x1_, y1), model, 3)
        assert r1 == r2 and np.array_equal(a_, b_)


def test_plan_regions_kernel_agrees_with_the_reference():
    """The compiled greedy merge plans the same regions as the plain Python one (each
    pair's union costed with ``StereoMatcher.band_crop``) on random boxes, at both scales."""
    def reference(matcher, rois, shape, scale, left_margin):
        h, w = shape
        regions = []
        for x0, y0, x1, y1 in np.asarray(rois, int).reshape(-1, 4).tolist():
            x0, y0, x1, y1 = max(0, x0 - left_margin), max(0, y0), min(w, x1), min(h, y1)
            if x1 > x0 and y1 > y0:
                regions.append((y0, y1, x0, x1))

        def cost(rc):
            cy0, cy1, cx0, cx1 = matcher.band_crop(shape, *rc, scale=scale)
            return (cy1 - cy0) * (cx1 - cx0) + 4000 * scale * scale

        while len(regions) > 1:
            best = None
            for i in range(len(regions)):
                for j in range(i + 1, len(regions)):
                    a, b = regions[i], regions[j]
                    u = (min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3]))
                    gain = cost(a) + cost(b) - cost(u)
                    if gain >= 0 and (best is None or gain > best[0]):
                        best = (gain, i, j, u)
            if best is None:
                break
            regions[best[1]] = best[3]
            del regions[best[2]]
        return regions

    rng = np.random.default_rng(0)
    for scale in (1, 2):
        matcher = StereoMatcher(StereoConfig())
        for _ in range(150):
            n = int(rng.integers(0, 14))
            x0, y0 = rng.integers(-20, 1242, n), rng.integers(-20, 375, n)
            rois = np.stack([x0, y0, x0 + rng.integers(1, 300, n), y0 + rng.integers(1, 200, n)], 1)
            lm = int(rng.integers(0, 50))
            assert plan_regions(matcher, rois, (375, 1242), scale, left_margin=lm) == reference(
                matcher, rois, (375, 1242), scale, lm)


def test_clip_boxes():
    r = clip_boxes(np.array([[-10.5, 5.2, 30.1, 500.0], [470.0, -3.0, 490.0, 9.9]]), (H, W))
    np.testing.assert_array_equal(r, [[0, 5, 31, H], [470, 0, W, 10]])


# ---------------------------------------------------------------------------------------
# outline
# ---------------------------------------------------------------------------------------
def test_outline_beats_box_on_blob(blob_scene):
    left, right, blob, _ = blob_scene
    disp = StereoMatcher(STEREO).compute(left, right)
    box = box_of(blob)
    o = outline_objects(disp, np.array([box]), (H, W), OutlineConfig())
    assert o.methods == ["outline"]
    assert abs(o.disparity[0] - 30) < 0.5
    out = o.labels == 1
    box_iou = iou(rect_mask(*(int(v) for v in box)), blob)
    assert box_iou < 0.8
    assert iou(out, blob) > 0.9 > box_iou + 0.1
    # inside the box, never outside
    x0, y0, x1, y1 = (int(v) for v in box)
    assert not out[:, :x0].any() and not out[:, x1:].any() and not out[:y0].any() and not out[y1:].any()
    assert o.pixels[0] == out.sum()


def test_outline_fills_textureless_hole():
    """A textureless patch inside the object (no valid disparity) is filled."""
    blob = ellipse_mask(240, 120, 80, 60)
    left, right, _ = layered_pair(6, [(blob, 28)])
    hole = rect_mask(195, 95, 285, 155)
    for img, sh in ((left, 0), (right, 28)):  # flat grey on the object in both views
        img[shift_left(hole, sh) if sh else hole] = 128
    disp = StereoMatcher(STEREO).compute(left, right)
    assert (disp[hole] <= 0).mean() > 0.5  # BM finds no disparity there
    o = outline_objects(disp, np.array([box_of(blob)]), (H, W), OutlineConfig())
    assert (o.labels[hole] == 1).all()
    assert iou(o.labels == 1, blob) > 0.9


@pytest.mark.parametrize("fill", [True, False])
def test_outline_flood_fills_enclosed_window(fill):
    """A window through the object showing the background (valid, far disparity) is an
    enclosed hole of the outline: filled with fill_holes, left open without."""
    blob = ellipse_mask(240, 120, 90, 70)
    window = rect_mask(210, 95, 270, 140)
    left, right, _ = layered_pair(6, [(blob & ~window, 28)])
    disp = StereoMatcher(STEREO).compute(left, right)
    inner = rect_mask(222, 105, 258, 130)
    assert np.median(disp[inner]) == pytest.approx(6, abs=0.5)  # the background shows through
    o = outline_objects(disp, np.array([box_of(blob)]), (H, W), OutlineConfig(fill_holes=fill))
    assert o.methods == ["outline"]
    assert (o.labels[inner] == 1).all() == fill
    if not fill:
        assert not (o.labels[inner] == 1).any()


def test_no_valid_disparity_falls_back_to_box():
    left, right, _ = layered_pair(8, [])
    flat = rect_mask(150, 60, 330, 200)
    left[flat] = 90
    right[shift_left(flat, 8)] = 90
    box = [200.0, 100.0, 280.0, 160.0]  # well inside the flat area
    m = OutlineMasker(FakeDetector(dets(box)), StereoMatcher(STEREO))
    res = m.mask(frame(left, right))
    ob = res.objects[0]
    assert ob.method == MaskMethod.FALLBACK_NO_DISPARITY == "box-fallback:no-disparity"
    assert ob.disparity == 0.0
    assert iou(res.left, rect_mask(200, 100, 280, 160)) == 1.0
    # unknown disparity: the right mask covers every possible shift 0..63
    assert iou(res.right, rect_mask(200 - 63, 100, 280, 160)) == 1.0
    assert ob.pixels_left == 80 * 60 and ob.pixels_right == (80 + 63) * 60


def test_sparse_object_disparity_falls_back_to_box_moved_by_peak():
    """A textureless object with valid disparity on a few small spots only, each at its
    own disparity (a dark, shiny car showing reflections): no peak holds enough of the
    box, so it is masked whole -- and still moved to the right image by its peak."""
    left, right, _ = layered_pair(3, [])
    flat = rect_mask(150, 50, 340, 190)
    left[flat] = 100
    right[shift_left(flat, 30)] = 100
    disparities = (30, 8, 16, 22, 12)
    for k, d in enumerate(disparities):
        spot = rect_mask(165 + 34 * k, 70 + 18 * k, 175 + 34 * k, 80 + 18 * k)
        tex = texture(H, W + d, 50 + k)
        left[spot] = tex[:, :W][spot]
        right[shift_left(spot, d)] = tex[:, d:d + W][shift_left(spot, d)]
    disp = StereoMatcher(STEREO).compute(left, right)
    roi = disp[60:180, 160:330]  # the box: inside the flat area (BM fattens the edges)
    assert (roi > 0).mean() > 0.05  # enough valid pixels overall ...
    box = [160.0, 60.0, 330.0, 180.0]
    res = OutlineMasker(FakeDetector(dets(box)), StereoMatcher(STEREO)).mask(frame(left, right))
    ob = res.objects[0]
    assert ob.method == "box-fallback:sparse-disparity", ob  # ... but on no single peak
    assert abs(ob.disparity - 30) < 1.0  # the highest (and nearest-enough) spot
    inner = rect_mask(160, 60, 330, 180)
    assert (res.left[inner] == 255).all() and not res.left[~inner].any()
    assert iou(res.right, shift_left(inner, 30)) > 0.95


def test_tiny_box_masked_whole(blob_scene):
    left, right, _, _ = blob_scene
    disp = StereoMatcher(STEREO).compute(left, right)
    o = outline_objects(disp, np.array([[100.0, 30.0, 106.0, 38.0]]), (H, W), OutlineConfig(min_box_pixels=64))
    assert o.methods == [MaskMethod.FALLBACK_TINY]
    assert (o.labels[30:38, 100:106] == 1).all() and o.pixels[0] == 48


def test_overlapping_boxes_nearer_wins():
    far = rect_mask(150, 60, 300, 200)
    near = ellipse_mask(300, 150, 50, 50)
    left, right, (far_r, near_r) = layered_pair(5, [(far, 15), (near, 40)])
    disp = StereoMatcher(STEREO).compute(left, right)
    boxes = np.array([box_of(near), box_of(far)])  # near first: order must not matter
    o = outline_objects(disp, boxes, (H, W), OutlineConfig())
    assert o.methods == ["outline", "outline"]
    assert abs(o.disparity[0] - 40) < 0.5 and abs(o.disparity[1] - 15) < 0.5
    overlap = near & far
    assert overlap.sum() > 1000
    core = cv2.erode(overlap.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    assert (o.labels[core] == 1).all()  # the nearer object owns the shared pixels
    assert iou(o.labels == 1, near) > 0.9
    visible_far = far & ~near
    assert iou(o.labels == 2, visible_far) > 0.85
    # right image: the near object occludes the far one there too
    t = transfer_labels(o.labels, o.disparity, o.rois, mode="rigid")
    assert iou(t.labels == 1, near_r) > 0.9
    assert iou(t.labels == 2, far_r) > 0.85


def test_border_boxes_clipped(blob_scene):
    left, right, _, _ = blob_scene
    m = OutlineMasker(FakeDetector(dets([-40.0, -10.0, 60.0, 90.0], [420.0, 150.0, 560.0, 300.0])), StereoMatcher(STEREO))
    res = m.mask(frame(left, right))
    assert res.left.shape == (H, W) and res.right.shape == (H, W)
    assert [o.method for o in res.objects] != []
    assert not res.left[90:, 60:420].any() and res.left.any()
    for ob in res.objects:
        assert ob.pixels_left > 0


# ---------------------------------------------------------------------------------------
# ground (road) removal
# ---------------------------------------------------------------------------------------
ROAD_A, ROAD_VH = 0.54 / 1.65, 96.0  # KITTI-like rig: baseline / camera height, horizon row
RH, RW = 192, 640


def _contact(d: float) -> int:
    """Image row where an object at disparity d touches the road."""
    return int(ROAD_VH + d / ROAD_A)


@pytest.fixture(scope="module")
def road_scene():
    """A 640x192 street: textured road (d = A (v - VH), A = 0.54 / 1.65 px per row), a wall
    (d = 2) above it, a pedestrian (d = 20, two legs with the road between them) and a
    car (d = 30, body 0.3 m above the road, two wheels) standing on it.  Returns the
    exact disparity, the left/right images (road warped row by row, objects as layers)
    and the left masks."""
    rows = np.arange(RH, dtype=np.float32)[:, None]
    bg = np.maximum(ROAD_A * (rows - ROAD_VH), 2.0) * np.ones((1, RW), np.float32)
    ped = np.zeros((RH, RW), bool)
    vc = _contact(20)
    ped[vc - 63:vc - 30, 150:168] = True  # torso, 18 px (0.5 m) wide
    ped[vc - 30:vc + 1, 150:156] = True  # legs, 8 px apart
    ped[vc - 30:vc + 1, 162:168] = True
    car = np.zeros((RH, RW), bool)
    vc = _contact(30)
    car[vc - 83:vc - 17, 380:480] = True  # body
    car[vc - 17:vc + 1, 385:400] = True  # wheels
    car[vc - 17:vc + 1, 460:475] = True
    disp = bg.copy()
    disp[ped], disp[car] = 20.0, 30.0
    tex = texture(RH, RW + 64, 0).astype(np.float32)
    xs = np.arange(RW, dtype=np.float32)[None, :]
    left = tex[:, :RW].copy()
    right = cv2.remap(tex, xs + bg, np.repeat(rows, RW, 1), cv2.INTER_LINEAR)  # right(x) = left(x + d)
    for k, (m, d) in enumerate(((ped, 20), (car, 30))):
        t = texture(RH, RW + d, 1 + k).astype(np.float32)
        left[m] = t[:, :RW][m]
        mr = shift_left(m, d)
        right[mr] = t[:, d:d + RW][mr]
    return disp, left.astype(np.uint8), right.astype(np.uint8), ped, car


def _road_line() -> GroundLine:
    return GroundLine(ROAD_A, -ROAD_A * ROAD_VH, True, "ok", baseline=0.54)


def test_ground_fit_recovers_known_line():
    """v-disparity samples of a road (a = 0.327 px/row, horizon 96, noise 0.3 px) among
    clutter -- walls and cars (constant disparity over many rows), mismatches -- and a
    denser cluster of far structure near the horizon: the fit finds the road."""
    rng = np.random.default_rng(0)
    v_road = rng.uniform(100, 192, 1500)
    d_road = ROAD_A * (v_road - ROAD_VH) + rng.normal(0, 0.3, v_road.size)
    walls = [(rng.uniform(70, 140, 300), np.full(300, float(dd))) for dd in (3.0, 6.0, 9.0, 14.0, 25.0)]
    v_far = rng.uniform(80, 110, 1500)
    d_far = rng.uniform(1, 6, v_far.size)
    v_out = rng.uniform(0, 192, 300)
    d_out = rng.uniform(1, 60, 300)
    v = np.concatenate([v_road, v_far, v_out] + [w[0] for w in walls])
    d = np.concatenate([d_road, d_far, d_out] + [w[1] for w in walls])
    g = fit_ground_line(v, d, slope_range(0.54, 0.8, 3.0), RH)
    assert g.ok and g.reason == "ok", g
    assert g.slope == pytest.approx(ROAD_A, abs=0.005)
    assert g.horizon == pytest.approx(ROAD_VH, abs=1.0)
    assert g.inliers >= 1300
    np.testing.assert_allclose(g.at(np.array([150.0])), [ROAD_A * 54], atol=0.2)
    assert _road_line().camera_height == pytest.approx(1.65)


def test_ground_fit_unreliable_cases():
    rng = np.random.default_rng(1)
    # a truck filling the view: one disparity over all rows -- no slope in range fits it
    v = rng.uniform(0, 192, 3000)
    g = fit_ground_line(v, 30 + rng.normal(0, 0.3, v.size), slope_range(0.54, 0.8, 3.0), RH)
    assert not g.ok and g.reason in ("few-rows", "few-inliers", "weak-support"), g
    # a road seen by a camera 6 m high: slope outside 0.8 .. 3 m
    v = rng.uniform(100, 192, 2000)
    g = fit_ground_line(v, 0.09 * (v - 96), slope_range(0.54, 0.8, 3.0), RH)
    assert not g.ok, g
    # too few points
    g = fit_ground_line(v[:50], ROAD_A * (v[:50] - 96), slope_range(0.54, 0.8, 3.0), RH)
    assert not g.ok and g.reason == "few-points"
    # the unreliable line is not used: same outline as without one
    disp = np.full((60, 80), 10.0, np.float32)
    box = np.array([[10.0, 10.0, 50.0, 50.0]])
    bad = GroundLine(1.0, 0.0, False, "few-inliers")
    a = outline_objects(disp, box, disp.shape, OutlineConfig(), ground=bad)
    b = outline_objects(disp, box, disp.shape, OutlineConfig(ground_removal=False))
    np.testing.assert_array_equal(a.labels, b.labels)
    assert a.ground is bad


def test_sample_valid_subsamples_regularly():
    d = np.zeros((100, 200), np.float32)
    d[40:, :] = 5.0
    rows, vals = sample_valid(d, max_points=1000, row0=10)
    assert 500 <= rows.size <= 1300 and (vals == 5.0).all()
    assert rows.min() >= 50 and rows.max() <= 109  # image rows of the valid part


def test_outline_removes_road_exact_disparity(road_scene):
    """Exact disparity: the road between the pedestrian's legs, beside its feet and under
    the car's body has the disparity of the object's bottom rows, so a disparity-peak
    outline keeps it; the road line removes it -- and nothing of the objects."""
    disp, _, _, ped, car = road_scene
    boxes = np.array([box_of(ped), box_of(car)])
    road = ~(ped | car)
    cfg = OutlineConfig(dilate=0, ground_removal=True, min_outline_fraction=0.4)
    plain = outline_objects(disp, boxes, disp.shape, cfg)
    o = outline_objects(disp, boxes, disp.shape, cfg, ground=_road_line())
    assert ((plain.labels > 0) & road).sum() > 500  # the bug: road kept
    assert not ((o.labels > 0) & road).any()
    assert iou(o.labels == 1, ped) > 0.95 and iou(o.labels == 2, car) > 0.97
    assert iou(o.labels == 1, ped) > iou(plain.labels == 1, ped) + 0.08
    assert iou(o.labels == 2, car) > iou(plain.labels == 2, car) + 0.08
    # with the default dilation, it does not grow back into the road either
    od = outline_objects(disp, boxes, disp.shape, OutlineConfig(dilate=3, ground_removal=True, min_outline_fraction=0.4), ground=_road_line())
    assert not ((od.labels > 0) & road).any()
    # noisy disparity (0.3 px): still almost no road
    rng = np.random.default_rng(2)
    noisy = disp + rng.normal(0, 0.3, disp.shape).astype(np.float32)
    on = outline_objects(noisy, boxes, disp.shape, cfg, ground=_road_line())
    assert ((on.labels > 0) & road).sum() < 0.15 * ((plain.labels > 0) & road).sum()
    assert iou(on.labels == 2, car) > 0.9


def test_road_filled_from_object_is_removed(road_scene):
    """Invalid road pixels (a shadow) right of the car's wheel are filled along the row
    from the wheel; below the wheel's footprint they are still road (a value below the
    road's), and the hole filling does not bring them back."""
    disp, _, _, _, car = road_scene
    d = disp.copy()
    vc = _contact(30)
    d[vc - 3:, 475:500] = 0.0  # no texture in the shadow: no disparity
    d[vc + 1:vc + 4, 380:500] = 0.0
    o = outline_objects(d, np.array([[370.0, vc - 83.0, 500.0, vc + 4.0]]), d.shape, OutlineConfig(dilate=0, ground_removal=True, min_outline_fraction=0.4),
                        ground=_road_line())
    m = o.labels == 1
    assert not m[vc + 1:, :].any()  # nothing below the contact row
    assert iou(m, car) > 0.95


def test_ground_max_fraction_protects_object():
    """A line that would take most of an object's pixels (a wrong fit, a slope) is not
    applied to that object."""
    disp = np.full((192, 200), 2.0, np.float32)
    disp[100:160, 60:140] = 20.0  # a wall-like object
    wrong = GroundLine(0.2, -6.0, True, "ok")  # says d = 20 .. 26 is road in rows 130..160
    o = outline_objects(disp, np.array([[60.0, 100.0, 140.0, 160.0]]), disp.shape, OutlineConfig(dilate=0),
                        ground=wrong)
    assert (o.labels[100:160, 60:140] == 1).mean() > 0.99


def test_ground_fit_on_rendered_stereo_pair(road_scene):
    """The masker's road line from the images (coarse disparity of the lower part)."""
    _, left, right, _, _ = road_scene
    m = StereoMatcher(StereoConfig())
    rows, vals = road_samples(m, left, right)
    g = fit_ground_line(rows, vals, slope_range(0.54, 0.8, 3.0), RH)
    assert g.ok, g
    assert g.slope == pytest.approx(ROAD_A, abs=0.015)
    assert g.horizon == pytest.approx(ROAD_VH, abs=3.0)
    masker = OutlineMasker(FakeDetector(Detections.empty()), m)
    g2 = masker.fit_ground(frame(left, right))
    assert g2.ok and g2.slope == pytest.approx(g.slope) and g2.camera_height == pytest.approx(1.65, abs=0.1)
    # a taller camera (another rig) is outside the default heights only if told so
    narrow = OutlineMasker(FakeDetector(Detections.empty()), m, OutlineConfig(ground_min_height=2.0))
    assert not narrow.fit_ground(frame(left, right)).ok


@pytest.mark.parametrize("alg,block", [("bm", 15), ("sgbm3way", 5)])
def test_outline_masker_removes_road_on_rendered_pair(road_scene, alg, block):
    """End to end from the images.  SGBM measures the road under the car's body and
    between the wheels: the car's outline loses it (IoU 0.85 -> 0.96).  BM with its
    15-px block cannot match this fine-textured road at all near the objects (the road's
    disparity changes by 5 px over a block's height): those pixels are invalid, filled
    from the wheels, and mostly stay -- less road, no loss."""
    disp, left, right, ped, car = road_scene
    boxes = dets(box_of(ped), box_of(car))
    road = ~(ped | car)
    res = {}
    for on in (False, True):
        masker = OutlineMasker(FakeDetector(boxes), StereoMatcher(StereoConfig(algorithm=alg, block_size=block)),
                               OutlineConfig(ground_removal=on))
        m, lab, _ = masker.mask_labels(frame(left, right), boxes)
        res[on] = lab
        assert (m.ground is not None and m.ground.ok) == on
    kept = {on: int(((res[on] > 0) & road).sum()) for on in res}
    car_iou = {on: iou(res[on] == 2, car) for on in res}
    assert car_iou[True] >= car_iou[False] - 0.005
    if alg == "sgbm3way":
        assert kept[True] < 0.3 * kept[False], kept
        assert car_iou[True] > 0.95 and car_iou[True] > car_iou[False] + 0.08, car_iou
    else:
        assert kept[True] < 0.95 * kept[False], kept


def test_left_border_object_outlined():
    """An object at the image's left border: matched now (padding), outlined, not the box."""
    patch = rect_mask(0, 40, 90, 160)
    left, right, (gt_right,) = layered_pair(4, [(patch, 24)])
    res = OutlineMasker(FakeDetector(dets(box_of(patch))), StereoMatcher(STEREO)).mask(frame(left, right))
    ob = res.objects[0]
    assert ob.method == "outline" and abs(ob.disparity - 24) < 0.5
    assert iou(res.left, patch) > 0.9


# ---------------------------------------------------------------------------------------
# one peak, one object
# ---------------------------------------------------------------------------------------
def test_box_over_a_nearer_box_keeps_its_own_peak():
    """A car's box reaches 30 columns over the truck in front of it: the truck's
    disparity (nearer, high enough for the near-peak rule) must not become the car's."""
    disp = np.full((120, 320), 3.0, np.float32)
    disp[10:110, 100:250] = 40.0  # truck
    disp[50:100, 250:300] = 14.0  # car, visible right of it
    boxes = np.array([[100.0, 10.0, 250.0, 110.0], [220.0, 50.0, 300.0, 100.0]])
    both_off = OutlineConfig(overlap_weight=1.0, claim_fraction=1.0, dilate=0)
    assert abs(outline_objects(disp, boxes, disp.shape, both_off).disparity[1] - 40) < 0.5  # the old failure
    for cfg in (OutlineConfig(dilate=0), OutlineConfig(claim_fraction=1.0, dilate=0),
                OutlineConfig(overlap_weight=1.0, dilate=0)):
        o = outline_objects(disp, boxes, disp.shape, cfg)
        assert abs(o.disparity[0] - 40) < 0.5 and abs(o.disparity[1] - 14) < 0.5, cfg
        assert iou(o.labels == 2, disp == 14.0) > 0.95


def test_box_in_occlusion_shadow_gives_up_spilled_peak():
    """A far car left of a near truck: the matcher left it invalid (occlusion shadow)
    except for the truck's disparity spilled a few columns past the truck's edge.  That
    peak is the truck's: the car is masked whole, not as the truck's sliver."""
    disp = np.zeros((120, 320), np.float32)
    disp[:, :100] = 3.0
    disp[10:110, 150:300] = 40.0  # truck
    disp[40:90, 144:150] = 40.0  # spilled past its left edge
    boxes = np.array([[150.0, 10.0, 300.0, 110.0], [110.0, 40.0, 150.0, 90.0]])
    old = outline_objects(disp, boxes, disp.shape, OutlineConfig(claim_fraction=1.0, min_outline_fraction=0.0))
    assert old.methods[1] == "outline" and abs(old.disparity[1] - 40) < 0.5  # the sliver
    o = outline_objects(disp, boxes, disp.shape, OutlineConfig())
    assert o.methods[0] == "outline" and abs(o.disparity[0] - 40) < 0.5
    assert o.methods[1] == MaskMethod.FALLBACK_NO_DISPARITY
    assert (o.labels[40:90, 110:144] == 2).all()


def test_small_outline_becomes_the_box():
    """Inside a box the matcher measured only the background at its sides and a small
    patch nearer (a near object with little texture, its plate): the outline is that patch
    -- under min_outline_fraction of the box, so the box is masked whole."""
    disp = np.zeros((120, 320), np.float32)
    disp[20:100, 100:105] = 3.0  # background at the box's sides
    disp[20:100, 135:140] = 3.0
    disp[30:90, 115:125] = 20.0  # the patch measured on the object
    box = np.array([[100.0, 20.0, 140.0, 100.0]])
    off = outline_objects(disp, box, disp.shape, OutlineConfig(min_outline_fraction=0.0))
    assert off.methods == ["outline"] and abs(off.disparity[0] - 20) < 0.5
    assert 0.2 < (off.labels == 1).sum() / (40 * 80) < 0.4
    o = outline_objects(disp, box, disp.shape, OutlineConfig(min_outline_fraction=0.4))
    assert o.methods == [MaskMethod.FALLBACK_SMALL] and abs(o.disparity[0] - 20) < 0.5
    assert (o.labels[20:100, 100:140] == 1).all()


def test_small_outline_counts_only_the_part_no_nearer_object_takes():
    """A car mostly hidden behind a nearer truck inside its box: its visible part is small
    against its box but not against the part the truck leaves -- it keeps its outline."""
    disp = np.full((120, 320), 3.0, np.float32)
    disp[10:110, 100:250] = 40.0  # truck
    disp[50:100, 250:270] = 14.0  # car, visible right of it
    boxes = np.array([[100.0, 10.0, 250.0, 110.0], [180.0, 50.0, 270.0, 100.0]])
    o = outline_objects(disp, boxes, disp.shape, OutlineConfig(dilate=0))
    assert o.methods == ["outline", "outline"]
    assert iou(o.labels == 2, disp == 14.0) > 0.9


def test_object_beyond_the_matchers_range_is_masked_whole():
    """An object whose nearer part is beyond numDisparities (a car right beside the rig):
    only its farther part has a disparity, at the top of the range -- the box is masked."""
    disp = np.full((120, 320), 3.0, np.float32)
    disp[40:120, 200:320] = 0.0  # too near to match
    disp[40:120, 200:240] = 94.0  # the farther end, just within the range
    box = np.array([[200.0, 40.0, 320.0, 120.0]])
    o = outline_objects(disp, box, disp.shape, OutlineConfig(), max_disparity=95.0)
    assert o.methods == [MaskMethod.FALLBACK_RANGE] and (o.labels[40:120, 200:320] == 1).all()
    assert outline_objects(disp, box, disp.shape, OutlineConfig()).methods == ["outline"]  # range unknown


def test_side_by_side_objects_keep_the_same_peak():
    """Two pedestrians side by side at the same distance, boxes overlapping a little:
    both keep the (same) peak."""
    disp = np.full((120, 200), 3.0, np.float32)
    disp[20:100, 50:80] = 15.0
    disp[20:100, 84:114] = 15.0
    boxes = np.array([[50.0, 20.0, 86.0, 100.0], [78.0, 20.0, 114.0, 100.0]])
    o = outline_objects(disp, boxes, disp.shape, OutlineConfig(dilate=0))
    assert o.methods == ["outline", "outline"]
    assert iou(o.labels == 1, rect_mask(50, 20, 80, 100, 120, 200)) > 0.9
    assert iou(o.labels == 2, rect_mask(84, 20, 114, 100, 120, 200)) > 0.9


def test_narrow_box_masked_whole():
    disp = np.full((100, 100), 10.0, np.float32)
    o = outline_objects(disp, np.array([[10.0, 10.0, 16.0, 90.0]]), disp.shape, OutlineConfig(min_box_side=8))
    assert o.methods == [MaskMethod.FALLBACK_TINY] and o.pixels[0] == 6 * 80


# ---------------------------------------------------------------------------------------
# synthetic street with exact ground truth (dynastereo.synth)
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def synth_crossing(tmp_path_factory):
    from dynastereo.synth import generate

    return generate(tmp_path_factory.mktemp("synth") / "crossing", "crossing", frames=12)


def _synth_scores(seq, disp_of, cfg: OutlineConfig, ground_of) -> dict[str, float]:
    """Mean left-view IoU of the outline (and of the boxes) against the GT instance masks,
    objects nearer than 30 m, oracle boxes."""
    from dynastereo.eval.masks import score_frame
    from dynastereo.synth import OracleDetector, read_gt_masks, read_objects

    gt, oracle = read_objects(seq), OracleDetector(seq)
    out: dict[str, list[float]] = {"outline": [], "box": []}
    for i in range(len(gt)):
        det = oracle.detect_frame(i)
        d = disp_of(i)
        o = outline_objects(d, det.boxes, d.shape, cfg, ground=ground_of(i))
        rois = clip_boxes(det.boxes, d.shape)
        boxes = np.zeros(d.shape, np.uint8)
        for x0, y0, x1, y1 in rois:
            boxes[y0:y1, x0:x1] = 255
        gl, gr = read_gt_masks(seq, i)
        for name, m in (("outline", (o.labels > 0).astype(np.uint8) * 255), ("box", boxes)):
            out[name] += [sc.iou for sc in score_frame(i, {"left": m, "right": m}, {"left": gl, "right": gr},
                                                       gt.frames[i]) if sc.view == "left"]
    return {k: float(np.mean(v)) for k, v in out.items()}


def test_synth_exact_disparity_road_removal_beats_box(synth_crossing):
    """With the exact disparity of the synthetic street and its exact road line (baseline
    0.54 m over camera height 1.65 m, horizon at cy), the road removal is what makes the
    outline beat the boxes: left IoU outline 0.87 vs box 0.76 on these 12 frames of the
    current crossing scene (0.90 vs 0.72 on the earlier one)."""
    from dynastereo.synth import read_gt_disparity, read_objects

    meta = read_objects(synth_crossing)
    a = meta.calibration["baseline"] / meta.meta["camera_height"]
    line = GroundLine(a, -a * meta.calibration["cy"], True, "ok", baseline=meta.calibration["baseline"])
    cfg = OutlineConfig(dilate=0, min_outline_fraction=0.0, ground_removal=True)  # the road alone (no fallback guard)
    disp = lambda i: read_gt_disparity(synth_crossing, i)  # noqa: E731
    with_road = _synth_scores(synth_crossing, disp, cfg, lambda i: line)
    without = _synth_scores(synth_crossing, disp, cfg, lambda i: None)
    assert with_road["outline"] > with_road["box"] + 0.10, with_road  # the synthetic-scenes target
    assert with_road["outline"] > without["outline"] + 0.08, (with_road, without)


def test_synth_convoy_truck_masked_to_the_image_bottom(tmp_path):
    """The convoy's truck 4.5 m ahead stands on the image's bottom edge: its bumper and
    plate rows there get a disparity (the matcher's border padding), so the outline covers
    the truck in both views (IoU 0.89-0.91 without the padding, 0.93-0.95 with it)."""
    from dynastereo.api import load_sequence
    from dynastereo.config import Config
    from dynastereo.eval.masks import score_frame
    from dynastereo.synth import generate, read_gt_masks, read_objects

    seq_dir = generate(tmp_path / "convoy", "convoy", frames=4, seed=0)
    gt, seq = read_objects(seq_dir), load_sequence(seq_dir)
    masker = build_masker(Config().with_overrides({"detector.name": "oracle"}), seq.calibration, ground_truth=seq_dir)
    ious = []
    for i in range(len(seq)):
        m = masker.mask_detections(seq.frame(i), masker.detector.detector.detect_frame(i))
        gl, gr = read_gt_masks(seq_dir, i)
        ious += [s.iou for s in score_frame(i, {"left": m.left, "right": m.right}, {"left": gl, "right": gr},
                                            gt.frames[i]) if s.label == "truck"]
    assert len(ious) == 2 * len(seq)
    assert min(ious) > 0.92, ious


def test_synth_road_line_fitted_from_images(synth_crossing):
    """The road line fitted from the rendered images matches the synthetic rig's: slope
    baseline / camera height = 0.327 px per row, horizon at cy = 96."""
    from dynastereo.io import open_sequence

    seq = open_sequence(synth_crossing)
    masker = OutlineMasker(FakeDetector(Detections.empty()), StereoMatcher(StereoConfig()))
    fits = [masker.fit_ground(seq.frame(i)) for i in range(len(seq))]
    ok = [g for g in fits if g.ok]
    assert len(ok) >= 0.9 * len(fits), [g.reason for g in fits]
    for g in ok:
        assert g.slope == pytest.approx(0.54 / 1.65, abs=0.015), g
        assert g.horizon == pytest.approx(96.0, abs=4.0), g
        assert g.camera_height == pytest.approx(1.65, abs=0.1)


# ---------------------------------------------------------------------------------------
# transfer
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("d", [1, 7, 23, 50])
@pytest.mark.parametrize("mode", ["rigid", "affine"])
def test_transfer_exact_for_integer_disparity(d, mode):
    patch = ellipse_mask(300, 120, 60, 40) | rect_mask(250, 150, 290, 200)
    left, right, (gt_right,) = layered_pair(3, [(patch, d)], seed=d)
    disp = StereoMatcher(STEREO).compute(left, right)
    labels = patch.astype(np.int32)
    rois = clip_boxes(np.array([box_of(patch)]), (H, W))
    v = disp[patch & (disp > 0)]
    dd = float(np.median(v))  # the object's measured disparity, not the GT
    t = transfer_labels(labels, np.array([dd]), rois, mode=mode, disp=disp, ranges=[(d - 2, d + 2)])
    np.testing.assert_array_equal(t.labels == 1, gt_right)
    assert t.pixels[0] == gt_right.sum()


def test_transfer_object_leaving_right_image():
    patch = rect_mask(10, 50, 90, 150)  # x - d < 0 for the first 30 columns
    left, right, (gt_right,) = layered_pair(4, [(patch, 40)])
    masker = OutlineMasker(FakeDetector(dets(box_of(patch))), StereoMatcher(STEREO), OutlineConfig(dilate=0))
    res = masker.mask(frame(left, right))
    ob = res.objects[0]
    assert abs(ob.disparity - 40) < 0.5
    # the left outline: BM has no disparity in its leftmost 63 columns -> only the part
    # right of that is found; what was found lands exactly where GT says
    found = res.left > 0
    assert found.any()
    np.testing.assert_array_equal(res.right > 0, shift_left(found, 40))
    assert (res.right[gt_right == 0] == 0).all()
    assert ob.pixels_right < ob.pixels_left


def test_transfer_extends_object_cut_by_right_border():
    """An object cut by the left image's right border is seen further in the right image."""
    patch = rect_mask(400, 60, W, 160)
    left, right, (gt_right,) = layered_pair(5, [(patch, 30)])
    # the right image sees 30 more columns of the object: extend the texture there
    ext = texture(H, W + 30, 99)[:, W:W + 30]
    right[60:160, W - 30:] = ext[60:160]
    gt_right = rect_mask(370, 60, W, 160)
    res = OutlineMasker(FakeDetector(dets([400.0, 60.0, float(W), 160.0])), StereoMatcher(STEREO),
                        OutlineConfig(dilate=0)).mask(frame(left, right))
    assert iou(res.right, gt_right) > 0.97
    assert res.right[60:160, W - 5:].all()


def test_transfer_uncovers_object_behind_nearer_one():
    """A car (d = 10) behind the right edge of a truck (d = 40), its box reaching over the
    truck: the right camera sees 30 more columns of it past the truck's edge.  With
    ``transfer_occluded`` its right mask covers them; the truck's is unchanged."""
    car = rect_mask(200, 100, 330, 180)
    truck = rect_mask(120, 40, 280, 200)
    left, right, (car_r, truck_r) = layered_pair(4, [(car, 10), (truck, 40)])
    assert car_r[100:180, 240:270].all()  # the band seen only from the right
    boxes = dets(box_of(truck), [250.0, 100.0, 330.0, 180.0])
    out = {}
    for occ in (False, True):
        masker = OutlineMasker(FakeDetector(boxes), StereoMatcher(STEREO), OutlineConfig(dilate=0, transfer_occluded=occ))
        _, _, lab_r = masker.mask_labels(frame(left, right), boxes)
        out[occ] = lab_r
    assert iou(out[True] == 2, car_r) > 0.9
    assert iou(out[True] == 2, car_r) > iou(out[False] == 2, car_r) + 0.2
    np.testing.assert_array_equal(out[True] == 1, out[False] == 1)


def test_transfer_affine_follows_slanted_object():
    """A plane whose disparity grows along x (a car seen from the side)."""
    h, w = H, W
    xs = np.arange(w, dtype=np.float64)
    x0, x1, y0, y1 = 180, 380, 60, 180
    dx = 10.0 + 0.1 * (xs - x0)  # 10 .. 30 px
    tex_bg = texture(h, w + 8, 5)
    left = tex_bg[:, :w].copy()
    right = tex_bg[:, 8:8 + w].copy()
    obj_tex = texture(h, 2 * w, 6).astype(np.float32)
    # left: object texture in object coordinates u = x; right pixel xr shows u with xr = u - d(u)
    left[y0:y1, x0:x1] = obj_tex[y0:y1, x0:x1].astype(np.uint8)
    u = xs[x0:x1]
    xr = u - dx[x0:x1]
    ur = np.interp(np.arange(int(np.ceil(xr[0])), int(np.floor(xr[-1])) + 1), xr, u)
    cols = np.arange(int(np.ceil(xr[0])), int(np.floor(xr[-1])) + 1)
    mapx = np.tile(ur.astype(np.float32), (y1 - y0, 1))
    mapy = np.repeat(np.arange(y0, y1, dtype=np.float32)[:, None], len(cols), axis=1)
    right[y0:y1, cols] = cv2.remap(obj_tex, mapx, mapy, cv2.INTER_LINEAR).astype(np.uint8)
    gt_right = rect_mask(int(cols[0]), y0, int(cols[-1]) + 1, y1)
    disp = StereoMatcher(StereoConfig(num_disparities=64, block_size=9)).compute(left, right)
    box = np.array([[x0, y0, x1, y1]], np.float32)
    cfg = OutlineConfig(dilate=0)
    o = outline_objects(disp, box, (h, w), cfg)
    assert iou(o.labels == 1, rect_mask(x0, y0, x1, y1)) > 0.85  # the extended peak covers the slant
    rigid = transfer_labels(o.labels, o.disparity, o.rois, mode="rigid")
    affine = transfer_labels(o.labels, o.disparity, o.rois, mode="affine", disp=disp, ranges=o.ranges)
    a, b, c = affine.models[0]
    assert abs(b - 0.1) < 0.02 and abs(c) < 0.02
    assert iou(affine.labels == 1, gt_right) > 0.85
    assert iou(affine.labels == 1, gt_right) > iou(rigid.labels == 1, gt_right) + 0.05


# ---------------------------------------------------------------------------------------
# maskers
# ---------------------------------------------------------------------------------------
def test_outline_masker_end_to_end(blob_scene):
    left, right, blob, blob_r = blob_scene
    det = FakeDetector(dets(box_of(blob)))
    m = OutlineMasker(det, StereoMatcher(STEREO))
    timer = StageTimer()
    timer.start_frame(0)
    res = m.mask(frame(left, right), timer)
    rec = timer.end_frame()
    assert {"detect", "disparity", "outline", "transfer"} <= set(rec["ms"])
    assert det.calls == 1  # left image only
    assert res.left.dtype == np.uint8 and set(np.unique(res.left)) <= {0, 255}
    assert iou(res.left, blob) > 0.9 and iou(res.right, blob_r) > 0.9
    ob = res.objects[0]
    assert ob.method == "outline" and abs(ob.disparity - 30) < 0.5 and ob.label == "car"
    assert ob.pixels_left == np.count_nonzero(res.left) and ob.pixels_right == np.count_nonzero(res.right)
    assert res.detections is det.detections
    assert res.disparity is None  # band only
    _, lab_l, lab_r = m.mask_labels(frame(left, right), det.detections)
    np.testing.assert_array_equal(lab_l > 0, res.left > 0)
    np.testing.assert_array_equal(lab_r > 0, res.right > 0)
    assert set(np.unique(lab_l)) == {0, 1}
    full = OutlineMasker(det, StereoMatcher(StereoConfig(num_disparities=64, region="full"))).mask(frame(left, right))
    assert full.disparity is not None and full.disparity.shape == (H, W)
    np.testing.assert_array_equal(full.left, res.left)


def test_band_and_half_scale_masks_match_full(blob_scene):
    left, right, blob, blob_r = blob_scene
    det = FakeDetector(dets(box_of(blob)))
    full = OutlineMasker(det, StereoMatcher(StereoConfig(num_disparities=64, region="full"))).mask(frame(left, right))
    band = OutlineMasker(det, StereoMatcher(StereoConfig(num_disparities=64))).mask(frame(left, right))
    half = OutlineMasker(det, StereoMatcher(StereoConfig(num_disparities=64, scale=2))).mask(frame(left, right))
    assert iou(band.left, full.left) > 0.99 and iou(band.right, full.right) > 0.99
    assert iou(half.left, full.left) > 0.9 and iou(half.right, full.right) > 0.9
    assert iou(half.left, blob) > 0.85 and iou(half.right, blob_r) > 0.85


def test_plan_regions_merges_near_boxes_and_splits_far_ones():
    m = StereoMatcher(StereoConfig(num_disparities=64))
    near = plan_regions(m, np.array([[200, 50, 260, 120], [250, 60, 300, 130]]), (H, W), 1)
    assert near == [(50, 130, 200, 300)]
    far = plan_regions(m, np.array([[100, 10, 140, 40], [400, 190, 450, 230]]), (H, W), 1)
    assert sorted(far) == [(10, 40, 100, 140), (190, 230, 400, 450)]
    left, right, _ = layered_pair(8, [])
    d = region_disparity(m, left, right, far, 1)
    assert (d[10:40, 100:140] > 0).mean() > 0.8 and not d[100:180, 200:300].any()


def test_box_masker(blob_scene):
    left, right, blob, blob_r = blob_scene
    box = box_of(blob)
    res = BoxMasker(FakeDetector(dets(box)), StereoMatcher(STEREO)).mask(frame(left, right))
    x0, y0, x1, y1 = (int(v) for v in box)
    np.testing.assert_array_equal(res.left > 0, rect_mask(x0, y0, x1, y1))
    np.testing.assert_array_equal(res.right > 0, rect_mask(x0 - 30, y0, x1 - 30, y1))
    assert res.objects[0].method == "box" and abs(res.objects[0].disparity - 30) < 0.5


def test_no_detections_gives_empty_masks(blob_scene):
    left, right, _, _ = blob_scene
    timer = StageTimer()
    timer.start_frame(0)
    res = OutlineMasker(FakeDetector(Detections.empty()), StereoMatcher(STEREO)).mask(frame(left, right), timer)
    rec = timer.end_frame()
    assert not res.left.any() and not res.right.any() and res.objects == []
    assert "disparity" in rec["ms"]  # nothing computed, but the stage is recorded (mask exists)
    res = NoneMasker().mask(frame(left, right))
    assert not res.left.any() and res.left.shape == (H, W)


class FakeSeg:
    """Seg model on the blob scene: the GT masks, right box shifted by 30."""

    name = "fake-seg"
    class_names = ("person", "bicycle", "car")

    def __init__(self, blob, blob_r):
        self.masks = {True: blob, False: blob_r}

    def detect(self, image):
        is_left = image is self.left_img
        m = self.masks[is_left]
        d = dets(box_of(m))
        d.masks = m[None]
        return d


def test_seg_masker(blob_scene):
    left, right, blob, blob_r = blob_scene
    seg = FakeSeg(blob, blob_r)
    seg.left_img = left
    timer = StageTimer()
    timer.start_frame(0)
    res = SegMasker(seg).mask(frame(left, right), timer)
    timer.end_frame()
    np.testing.assert_array_equal(res.left > 0, blob)
    np.testing.assert_array_equal(res.right > 0, blob_r)
    ob = res.objects[0]
    assert ob.method == "seg" and ob.pixels_right == blob_r.sum() and abs(ob.disparity - 30) <= 1
    assert "detect" in timer.frames[0]["ms"]


def test_match_stereo_detections():
    left = dets([100, 50, 200, 150], [300, 60, 340, 140])
    right = dets([280, 62, 318, 141], [80, 50, 180, 150], [10, 10, 20, 20])
    np.testing.assert_array_equal(match_stereo_detections(left, right, 64), [1, 0])
    # a right box to the RIGHT of the left one is not a match (negative disparity)
    np.testing.assert_array_equal(match_stereo_detections(dets([100, 50, 200, 150]), dets([140, 50, 240, 150]), 64), [-1])


def test_build_masker_kinds():
    cfg = Config()
    det = FakeDetector(Detections.empty())
    assert isinstance(build_masker(cfg.with_overrides({"masker.kind": "none"})), NoneMasker)
    assert isinstance(build_masker(cfg, detector=det), OutlineMasker)
    assert isinstance(build_masker(cfg.with_overrides({"masker.kind": "box"}), detector=det), BoxMasker)
    m = build_masker(cfg, detector=det, full_disparity=True)
    assert m.full_disparity
    with pytest.raises(ConfigError, match="masker.kind"):
        build_masker(cfg.with_overrides({"masker.kind": "magic"}), detector=det)
    with pytest.raises(ConfigError, match="num_disparities"):
        build_masker(cfg.with_overrides({"stereo.num_disparities": 90}), detector=det)
    with pytest.raises(ConfigError, match="transfer"):
        build_masker(cfg.with_overrides({"masker.outline.transfer": "warp"}), detector=det)


# ---------------------------------------------------------------------------------------
# real data: KITTI odometry with the real detector
# ---------------------------------------------------------------------------------------
def _kitti_frame(seq_dir, i: int) -> StereoFrame:
    left = cv2.imread(str(require(seq_dir / f"image_0/{i:06d}.png")), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(require(seq_dir / f"image_1/{i:06d}.png")), cv2.IMREAD_GRAYSCALE)
    return StereoFrame(index=i, timestamp=0.0, left=left, right=right)


@pytest.fixture(scope="module")
def kitti_detector(models_dir):
    from dynastereo.config import DetectorConfig
    from dynastereo.masking.detection import create_detector

    require(models_dir / "yolox-nano", "yolox-nano model")
    return create_detector(DetectorConfig(name="yolox-nano", score_threshold=0.25), models_dir)  # the 0.1 threshold


@pytest.mark.realdata
def test_kitti06_outline_masks(kitti06, kitti_detector):
    masker = OutlineMasker(kitti_detector, StereoMatcher(StereoConfig()))
    n_objects = 0
    for i in (0, 5, 10):
        f = _kitti_frame(kitti06, i)
        dets = kitti_detector.detect(f.left)
        dets = dets.select(dets.scores >= 0.4)  # clear detections; weak ones may be false positives
        res, left_labels, right_labels = masker.mask_labels(f, dets)
        d = res.detections
        assert d is not None and len(d) == len(res.objects)
        rois = clip_boxes(d.boxes, f.shape)
        in_boxes = np.zeros(f.shape, bool)
        for x0, y0, x1, y1 in rois:
            in_boxes[y0:y1, x0:x1] = True
        assert not res.left[~in_boxes].any()  # left masks lie inside the boxes
        for k, ob in enumerate(res.objects):
            if ob.method != "outline":
                continue
            n_objects += 1
            x0, y0, x1, y1 = rois[k]
            assert ob.pixels_left > 0.2 * (x1 - x0) * (y1 - y0)
            if x1 >= f.shape[1] - 3:
                # cut by the left image's right border: the right image sees more of it
                rows = np.nonzero(res.left[y0:y1, x1 - 1])[0] + y0
                assert rows.size and res.right[rows, -1].all()
                continue
            # right mask shifted left by about the object's disparity: column centroids
            # (per-object label images, so a neighbour's mask cannot leak into the measure)
            left_cols = np.nonzero((left_labels == k + 1).any(axis=0))[0]
            right_cols = np.nonzero((right_labels == k + 1).any(axis=0))[0]
            assert right_cols.size
            shift = left_cols.mean() - right_cols.mean()
            assert abs(shift - ob.disparity) < max(3.0, 0.1 * ob.disparity), (i, ob, shift)
    assert n_objects >= 2


@pytest.mark.realdata
def test_kitti06_band_and_half_scale_masks_close_to_full(kitti06, kitti_detector):
    frames = [_kitti_frame(kitti06, i) for i in (0, 5, 10, 15)]
    detections = [kitti_detector.detect(f.left) for f in frames]
    assert sum(len(d) for d in detections) >= 3
    # the configuration of 0.1 (road line removed, box fallback under 0.4 of the box): the
    # masks match almost exactly; the defaults (no road line, fallback under 0.6): an
    # outline near the fallback threshold may flip between outline and box
    for ground in (True, False):
        oc = OutlineConfig(ground_removal=True, min_outline_fraction=0.4) if ground else OutlineConfig()
        mk = {
            name: OutlineMasker(FakeDetector(Detections.empty()), StereoMatcher(StereoConfig(**kw)), oc)
            for name, kw in (("full", {"region": "full"}), ("band", {}), ("half", {"scale": 2}))
        }
        ious = {"band": [], "half": []}
        for f, d in zip(frames, detections):
            ref = mk["full"].mask_detections(f, d)
            for name in ious:
                r = mk[name].mask_detections(f, d)
                ious[name].append((iou(r.left, ref.left), iou(r.right, ref.right)))
        band, half = np.array(ious["band"]), np.array(ious["half"])
        if ground:
            assert band.min() > 0.99, band
        else:
            assert band.mean() > 0.97 and band.min() > 0.8, band
        assert half.mean() > 0.8, half


@pytest.mark.realdata
def test_kitti_road_line(kitti06, kitti03):
    """KITTI's rig: baseline 0.54 m, camera 1.65 m above the road -> the road's disparity
    grows by 0.54 / 1.65 = 0.33 px per image row; horizon near cy = 185 (pitch varies)."""
    masker = OutlineMasker(FakeDetector(Detections.empty()), StereoMatcher(StereoConfig()))
    fits = []
    for seq, frames in ((kitti06, (0, 10, 20, 30, 40, 50)), (kitti03, (0, 20, 60, 80))):
        for i in frames:
            fits.append(masker.fit_ground(_kitti_frame(seq, i)))
    ok = [g for g in fits if g.ok]
    assert len(ok) >= len(fits) - 1, [g.reason for g in fits]
    for g in ok:
        assert 0.29 < g.slope < 0.37, g
        assert 150 < g.horizon < 205, g
        assert 1.45 < g.camera_height < 1.9, g


@pytest.mark.realdata
def test_kitti_seg_masker_both_images(kitti06, models_dir):
    from dynastereo.config import DetectorConfig
    from dynastereo.masking.detection import create_seg_model

    require(models_dir / "yolov8n-seg-int8", "yolov8n-seg-int8 model")
    seg = create_seg_model("yolov8n-seg-int8", DetectorConfig(), models_dir)
    f = _kitti_frame(kitti06, 10)
    timer = StageTimer()
    timer.start_frame(10)
    res = SegMasker(seg).mask(f, timer)
    rec = timer.end_frame()
    assert {"detect", "segment"} <= set(rec["ms"])
    assert res.left.any() and res.right.any()
    assert any(o.pixels_right > 0 and o.disparity > 0 for o in res.objects)


def test_object_method_and_source_are_enums_written_as_their_strings() -> None:
    import json

    from dynastereo.datatypes import DetectionSource, ObjectMask

    ob = ObjectMask((1.0, 2.0, 3.0, 4.0), "car", 0.9, "box-fallback:tiny", 5.0, 6, 7, source="carried")
    assert ob.method is MaskMethod.FALLBACK_TINY and ob.method.is_fallback and ob.source is DetectionSource.CARRIED
    assert not MaskMethod.OUTLINE.is_fallback and not MaskMethod.EMPTY.is_fallback
    assert f"{ob.label} {ob.method}" == "car box-fallback:tiny"  # the pictures' captions
    d = ob.to_dict()
    assert type(d["method"]) is str and type(d["source"]) is str
    assert json.dumps(d) == json.dumps({"box": [1.0, 2.0, 3.0, 4.0], "label": "car", "score": 0.9,
                                        "method": "box-fallback:tiny", "disparity": 5.0, "pixels_left": 6,
                                        "pixels_right": 7, "track_id": -1, "source": "carried", "track": -1,
                                        "moving": None, "masked": True, "speed_mps": None,
                                        "speed_sigma_mps": None})
    with pytest.raises(ValueError):
        ObjectMask((0.0, 0.0, 1.0, 1.0), "car", 0.5, "bogus", 0.0, 0, 0)


@pytest.mark.realdata
def test_mask_runs_are_byte_identical(kitti06, models_dir, tmp_path):
    """Two `dynastereo mask` runs of the same frames with the defaults (the runtime
    `auto` picks: OpenVINO bf16 here when installed; the schedule and the carried boxes
    included) write the same masks, byte for byte, and the same objects."""
    from dynastereo.api import mask_sequence
    from dynastereo.config import Config

    outs = []
    for k in range(2):
        out = tmp_path / f"run{k}"
        mask_sequence(kitti06, out, Config(), frames="0-5", models_dir=models_dir)
        outs.append(out)
    files = sorted(p.relative_to(outs[0]) for p in (outs[0] / "masks").rglob("*.png"))
    assert len(files) >= 12  # 6 frames, left and right
    for f in files:
        assert (outs[0] / f).read_bytes() == (outs[1] / f).read_bytes(), f
    assert (outs[0] / "objects.jsonl").read_text() == (outs[1] / "objects.jsonl").read_text()


def _tracked(box, carried: bool) -> Detections:
    d = dets(box)
    d.track_ids = np.array([0], np.int64)
    d.carried = np.array([carried])
    return d


@pytest.mark.parametrize("d1, kept", [(30, True), (18, False)], ids=["same depth", "disparity peak changed"])
def test_carried_box_keeps_its_outline(d1, kept):
    """masker.outline.carry_outline: a carried box that moved little keeps its previous
    outline moved by the box's shift (no new outline) -- unless the disparity under it is no
    longer its peak's; the result matches a fresh outline either way."""
    from dynastereo.config import OutlineConfig

    blob0 = ellipse_mask(260, 130, 70, 45)
    blob1 = ellipse_mask(264, 131, 70, 45)  # the car moved 4 px right, 1 px down
    l0, r0, _ = layered_pair(8, [(blob0, 30)])
    l1, r1, (blob1_r,) = layered_pair(8, [(blob1, d1)])
    f0 = StereoFrame(index=0, timestamp=0.0, left=l0, right=r0)
    f1 = StereoFrame(index=1, timestamp=0.1, left=l1, right=r1)
    carry = OutlineMasker(FakeDetector(dets(box_of(blob0))), StereoMatcher(STEREO), OutlineConfig(carry_outline=True))
    fresh = OutlineMasker(FakeDetector(dets(box_of(blob0))), StereoMatcher(STEREO))
    m0, lab0, _ = carry.mask_labels(f0, _tracked(box_of(blob0), False))
    calls = []
    orig = carry._carried_outlines
    carry._carried_outlines = lambda *a: calls.append(r := orig(*a)) or r
    m1, lab1, _ = carry.mask_labels(f1, _tracked(box_of(blob1), True))
    ref = fresh.mask_detections(f1, _tracked(box_of(blob1), True))
    assert bool(calls[0]) == kept
    if kept:  # exactly the previous outline, moved by the box's shift
        np.testing.assert_array_equal(lab1[:, 4:] > 0, np.roll(lab0 > 0, 1, axis=0)[:, :-4])
        assert abs(m1.objects[0].disparity - 30) < 0.5
    assert iou(m1.left, ref.left) > 0.95 and iou(m1.right, ref.right) > 0.9
    assert iou(m1.left, blob1) > 0.9 and iou(m1.right, blob1_r) > 0.85
    # a frame that does not follow the kept one (a jump): outlined anew
    f3 = StereoFrame(index=3, timestamp=0.3, left=l1, right=r1)
    calls.clear()
    carry.mask_labels(f3, _tracked(box_of(blob1), True))
    assert calls == [{}]
