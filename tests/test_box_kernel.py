"""masking.boxkernel: all of a frame's boxes outlined and transferred in one compiled call
give the per-box numpy / OpenCV path's results (``tests/reference/masking_numpy.py``)
bit for bit -- label images, disparities, methods, ranges, pixel counts -- on synthetic
boxes (edge cases included) and on real KITTI frames."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import require
from dynastereo.config import OutlineConfig
from dynastereo.datatypes import MaskMethod
from dynastereo.masking.boxkernel import TABLE_STEPS, _pairwise, bin_table, to_bins_numpy
from dynastereo.masking.ground import GroundLine
from dynastereo.masking.outline import outline_objects
from dynastereo.masking.transfer import transfer_labels
from reference.masking_numpy import outline_objects_numpy, transfer_labels_numpy

ROAD = GroundLine(slope=0.3, offset=-12.0, ok=True, reason="ok")
CONFIGS = [
    OutlineConfig(),
    OutlineConfig(ground_removal=True),
    OutlineConfig(fill_holes=False, keep_largest_component=False, dilate=0),
    OutlineConfig(near_peak_ratio=1.0, peak_extend_ratio=1.0, overlap_weight=1.0, claim_fraction=1.0,
                  min_outline_fraction=0.0),
    OutlineConfig(dilate=5, bin_width=0.5, peak_tolerance_rel=0.0),
]


def assert_same_outlines(disp, boxes, shape, cfg, ground=None, max_disparity=None, origin=(0, 0)):
    a = outline_objects(disp, boxes, shape, cfg, origin=origin, ground=ground, max_disparity=max_disparity)
    b = outline_objects_numpy(disp, boxes, shape, cfg, origin=origin, ground=ground, max_disparity=max_disparity)
    assert a.methods == b.methods
    assert a.ranges == b.ranges
    np.testing.assert_array_equal(a.disparity, b.disparity)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.pixels, b.pixels)
    np.testing.assert_array_equal(a.rois, b.rois)
    np.testing.assert_array_equal(a.mask, np.where(b.labels > 0, 255, 0).astype(np.uint8))
    return b


def assert_same_transfer(o, disp, origin=(0, 0), **kw):
    for mode in ("rigid", "affine"):
        for occluded in (False, True):
            args = dict(mode=mode, disp=disp, origin=origin, ranges=o.ranges, occluded=occluded, **kw)
            a = transfer_labels(o.labels, o.disparity, o.rois, **args)
            b = transfer_labels_numpy(o.labels, o.disparity, o.rois, **args)
            np.testing.assert_array_equal(a.labels, b.labels)
            np.testing.assert_array_equal(a.pixels, b.pixels)
            np.testing.assert_array_equal(a.mask, np.where(b.labels > 0, 255, 0).astype(np.uint8))
            np.testing.assert_allclose(np.reshape(a.models, (-1, 3)), np.reshape(b.models, (-1, 3)),
                                       rtol=1e-9, atol=1e-9)


def scene(rng, h=120, w=200):
    """A disparity image (a road ramp, elliptic objects, some slanted; noise on the 1/16 px
    grid; holes) and boxes around the objects, some past the image's edges, some overlapping,
    some outside it."""
    d = np.maximum(0, (np.arange(h, dtype=np.float32)[:, None] - 40) * 0.3) * np.ones((1, w), np.float32)
    yy, xx = np.mgrid[:h, :w]
    boxes = []
    for _ in range(int(rng.integers(0, 7))):
        x0, y0 = int(rng.integers(-20, w)), int(rng.integers(-10, h))
        bw, bh = int(rng.integers(1, 90)), int(rng.integers(1, 70))
        dd = float(rng.uniform(2, 100))
        cx, cy = x0 + bw / 2, y0 + bh / 2
        blob = ((xx - cx) / max(bw / 2.2, 1)) ** 2 + ((yy - cy) / max(bh / 2.2, 1)) ** 2 < 1
        slope = float(rng.uniform(-0.1, 0.1)) if rng.random() < 0.5 else 0.0
        d[blob] = (dd + slope * (xx - cx))[blob]
        boxes.append([x0 + rng.normal(0, 3), y0 + rng.normal(0, 3), x0 + bw + rng.normal(0, 3),
                      y0 + bh + rng.normal(0, 3)])
    d = d + rng.normal(0, rng.uniform(0, 1.0), d.shape)
    d = np.round(d * 16) / 16
    d[rng.random(d.shape) < rng.uniform(0, 0.6)] = 0
    if rng.random() < 0.2:
        d[:, : w // 2] = 0
    if rng.random() < 0.2:
        d = d + rng.uniform(0, 0.05, d.shape)  # off the 1/16 px grid
    d[d < 0] = 0
    if rng.random() < 0.3 and boxes:
        b = list(boxes[0])
        b[0] += 10
        b[2] += 10
        boxes.append(b)
    if rng.random() < 0.2:
        boxes.append([w + 5, 10, w + 20, 30])
    return d.astype(np.float32), np.array(boxes, np.float64).reshape(-1, 4)


def test_pairwise_sum_is_numpys():
    """The kernels' float32 sums are numpy's pairwise sums, to the last bit (the object's
    disparity is the mean of its peak's values)."""
    rng = np.random.default_rng(0)
    for _ in range(300):
        n = int(rng.integers(1, 30000))
        a = (rng.random(n) * 60).astype(np.float32)
        lo = int(rng.integers(0, 5))
        assert _pairwise(a, lo, max(n - lo, 0)) == a[lo:].sum()


def test_the_bin_table_is_numpys_bin_coordinate():
    """On the 1/16 px grid the bin coordinate is numpy's own (its SIMD log); off it, within
    a float32 ulp or two."""
    for bw, rel in ((1.0, 0.08), (0.5, 0.0), (1.0, 0.2)):
        t = bin_table(bw, rel)
        v = (np.arange(t.size, dtype=np.float32) / np.float32(TABLE_STEPS)).astype(np.float32)
        np.testing.assert_array_equal(t, to_bins_numpy(v, bw, rel))


@pytest.mark.parametrize("seed", range(4))
def test_the_kernels_agree_with_the_per_box_path_on_synthetic_boxes(seed):
    """Random scenes over the outline settings (the road removed, no holes filled, no
    dilation, the near peak, claims and small outlines off, a wider dilation and no
    relative bins), with and without a largest disparity: the same outlines and the same
    right-image labels (rigid and affine, occluded bands or not) as the per-box path."""
    rng = np.random.default_rng(seed)
    for t in range(60):
        d, boxes = scene(rng)
        cfg = CONFIGS[t % len(CONFIGS)]
        o = assert_same_outlines(d, boxes, d.shape, cfg, ground=ROAD if cfg.ground_removal else None,
                                 max_disparity=None if t % 3 else 95.0)
        assert_same_transfer(o, d)


def test_edge_cases_agree():
    """A box past every edge of the image, an empty one (outside, and of no width), one
    without a valid disparity, overlapping boxes at different disparities, a tiny one, one
    whose peak reaches the matcher's range, one cut by the right border (its right mask
    continued to the border), and a region array smaller than the image (``origin``)."""
    h, w = 90, 160
    d = np.zeros((h, w), np.float32)
    d[10:60, 0:40] = 20.0  # at the left border
    d[30:90, 120:160] = 30.0  # at the bottom-right corner
    d[20:70, 60:110] = 12.0  # behind ...
    d[35:80, 80:100] = 25.0  # ... a nearer one, overlapping
    d[0:15, 45:60] = 93.5  # near the matcher's limit
    d[::3, ::5] = 0.0  # holes
    boxes = np.array([
        [-10.0, 5.0, 45.0, 65.0],  # past the left edge
        [115.0, 25.0, 175.0, 100.0],  # past the right and bottom edges (cut by the right border)
        [58.0, 18.0, 112.0, 72.0],  # overlapping the next
        [78.0, 33.0, 102.0, 82.0],
        [200.0, 10.0, 220.0, 30.0],  # outside the image
        [50.0, 50.0, 50.0, 60.0],  # no width
        [5.0, 70.0, 30.0, 88.0],  # no valid disparity
        [140.0, 2.0, 145.0, 6.0],  # tiny
        [44.0, 0.0, 61.0, 16.0],  # the peak reaches the matcher's range
    ])
    for cfg in CONFIGS:
        o = assert_same_outlines(d, boxes, (h, w), cfg, max_disparity=95.0)
        assert_same_transfer(o, d)
    o = assert_same_outlines(d, boxes, (h, w), OutlineConfig(), max_disparity=95.0)
    assert o.methods[4] == MaskMethod.EMPTY and o.methods[5] == MaskMethod.EMPTY
    assert o.methods[6] == MaskMethod.FALLBACK_NO_DISPARITY and o.methods[7] == MaskMethod.FALLBACK_TINY
    assert o.methods[8] == MaskMethod.FALLBACK_RANGE
    # a region array: the disparity of rows 10.. and columns 30.. only
    sub = np.ascontiguousarray(d[10:, 30:])
    o = assert_same_outlines(sub, boxes, (h, w), OutlineConfig(), origin=(30, 10))
    assert_same_transfer(o, sub, origin=(30, 10))
    # unknown disparities are swept over the range; no boxes at all
    z = np.zeros((h, w), np.float32)
    o = assert_same_outlines(z, boxes, (h, w), OutlineConfig())
    assert_same_transfer(o, z, sweep=(2.0, 40.0))
    assert_same_outlines(d, np.zeros((0, 4)), (h, w), OutlineConfig())


def test_ranges_as_numpy_floats_compare_in_float64():
    """Ranges given as numpy float64 (not python floats) select the fitted pixels in
    float64, as numpy compares them."""
    rng = np.random.default_rng(3)
    d, boxes = scene(rng)
    while len(boxes) == 0:
        d, boxes = scene(rng)
    o = outline_objects_numpy(d, boxes, d.shape, OutlineConfig())
    ranges = [(np.float64(lo + 1 / 32), np.float64(hi - 1 / 32)) for lo, hi in o.ranges]
    a = transfer_labels(o.labels, o.disparity, o.rois, mode="affine", disp=d, ranges=ranges)
    b = transfer_labels_numpy(o.labels, o.disparity, o.rois, mode="affine", disp=d, ranges=ranges)
    np.testing.assert_array_equal(a.labels, b.labels)


CLIPS = {
    "06": "kitti_odometry/dataset/sequences/06",
    "03": "kitti_odometry/dataset/sequences/03",
    "raw0001": "kitti_raw/2011_09_26/2011_09_26_drive_0001_sync",
}


@pytest.mark.parametrize("clip", sorted(CLIPS))
def test_the_kernels_agree_with_the_per_box_path_on_real_frames(clip, data_dir, models_dir):
    """Real frames of KITTI 06, 03 and raw 0001 with the default masker (detector, boxes
    carried, disparity where the boxes need it): the masker's left and right labels are
    the per-box path's from the same disparity and boxes, bit for bit."""
    from dynastereo.config import Config
    from dynastereo.io import open_sequence
    from dynastereo.masking import build_masker

    seq = open_sequence(require(data_dir / CLIPS[clip], clip))
    cfg = Config()
    masker = build_masker(cfg, seq.calibration, models_dir=models_dir)
    oc = cfg.masker.outline
    n_objects = 0
    for i in range(0, min(len(seq), 24), 3):
        f = seq.frame(i)
        m = masker.mask(f)
        dets, disp = m.detections, m.box_disparity
        if len(dets) == 0:
            continue
        n_objects += len(dets)
        o = outline_objects_numpy(disp, dets.boxes, f.shape, oc, max_disparity=masker.matcher.max_disparity)
        t = transfer_labels_numpy(o.labels, o.disparity, o.rois, mode=oc.transfer, disp=disp, ranges=o.ranges,
                                  sweep=masker._sweep(), occluded=oc.transfer_occluded)
        np.testing.assert_array_equal(m.labels_left, o.labels)
        np.testing.assert_array_equal(m.labels_right, t.labels)
        np.testing.assert_array_equal(m.left, np.where(o.labels > 0, 255, 0).astype(np.uint8))
        np.testing.assert_array_equal(m.right, np.where(t.labels > 0, 255, 0).astype(np.uint8))
        assert [ob.method for ob in m.objects] == o.methods
    assert n_objects > 0


@pytest.mark.parametrize("case", ["row", "column", "flat"])
def test_degenerate_affine_fits_agree(case):
    """An object on one row, on one column (lstsq's minimum-norm solution) or of one
    disparity: the same model (to 1e-9) and the same right labels as numpy's lstsq."""
    h, w = 40, 120
    lab = np.zeros((h, w), np.int32)
    d = np.zeros((h, w), np.float32)
    if case == "row":
        lab[20, 10:90] = 1
        d[20, 10:90] = 10 + 0.005 * np.arange(80)
    elif case == "column":
        lab[2:38, 50] = 1
        d[2:38, 50] = 10 + 0.05 * np.arange(36)
    else:
        lab[5:30, 20:60] = 1
        d[5:30, 20:60] = 12.0
    d = (np.round(d * 16) / 16).astype(np.float32)
    rois = np.array([[10, 2, 91, 39]])
    args = dict(mode="affine", disp=d, ranges=[(5.0, 30.0)], max_slope=10.0)
    a = transfer_labels(lab, np.array([12.0], np.float32), rois, **args)
    b = transfer_labels_numpy(lab, np.array([12.0], np.float32), rois, **args)
    np.testing.assert_allclose(a.models, b.models, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(a.labels, b.labels)


def test_shape_steps_agree_with_opencv():
    """The largest 8-connected component (ties to the one OpenCV labels first), the holes'
    filling and the elliptic dilation give OpenCV's masks on random masks, speckled and
    blocky, with ties of equal components."""
    from dynastereo.masking.boxkernel import _dilate, _fill_holes, _largest_component
    from dynastereo.masking.outline import dilation_rows
    from reference.masking_numpy import _dilate as dilate_cv
    from reference.masking_numpy import _fill_holes as fill_cv
    from reference.masking_numpy import _largest_component as largest_cv

    rng = np.random.default_rng(0)
    for t in range(400):
        h, w = int(rng.integers(1, 40)), int(rng.integers(1, 60))
        if t % 3 == 0:
            m = (rng.random((h, w)) < rng.uniform(0.05, 0.7)).astype(np.uint8)
        elif t % 3 == 1:
            m = np.kron(rng.random((h // 4 + 1, w // 4 + 1)) < 0.4, np.ones((4, 4), np.uint8))[:h, :w].astype(np.uint8)
        else:  # equal squares: ties
            m = np.zeros((h, w), np.uint8)
            for _ in range(int(rng.integers(1, 5))):
                y, x = int(rng.integers(0, h)), int(rng.integers(0, w))
                m[y:y + 2, x:x + 2] = 1
        lab = np.zeros((h, w), np.int32)
        stack = np.zeros(h * w, np.int64)
        a = m.copy()
        _largest_component(a, lab, stack)
        np.testing.assert_array_equal(a, largest_cv(m))
        a = m.copy()
        _fill_holes(a, lab, stack)
        np.testing.assert_array_equal(a, fill_cv(m))
        r = int(rng.integers(1, 6))
        lo, hi = dilation_rows(r)
        out = np.zeros_like(m)
        _dilate(m, out, np.zeros((h, w), np.int32), lo, hi)
        np.testing.assert_array_equal(out, dilate_cv(m, r))
