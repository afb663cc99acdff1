"""The objects' own block matching (objects/disparity.py, ``objects.block_size``):
StereoBM's matching with its checks inside each outline, in a window around the masker's
disparities; what it gives the objects' positions; where it is configured."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dynastereo.config import Config, ObjectsConfig, StereoConfig
from dynastereo.datatypes import MaskMethod, ObjectMask, StereoCalibration, StereoFrame, StereoMasks
from dynastereo.errors import ConfigError
from dynastereo.masking.disparity import StereoMatcher, params_at_scale
from dynastereo.objects.disparity import ObjectStereo
from dynastereo.objects.world import WorldObjects

H, W = 192, 480
BOX = (200, 70, 270, 130)  # x0, y0, x1, y1 of the object (a plane facing the camera; 4,200 px)
D_OBJ, D_BG = 14.3, 6.0


def _texture(seed: int, flat_from: int | None = None) -> np.ndarray:
    """Band-limited random texture (bilinear interpolation of it is faithful), wider than
    the image; columns from ``flat_from`` on are one grey."""
    t = np.random.default_rng(seed).random((H, W + 64)).astype(np.float32) * 255.0
    t = cv2.GaussianBlur(t, (0, 0), 1.2)
    t = (t - t.mean()) * (60.0 / t.std()) + 128.0
    if flat_from is not None:
        t[:, flat_from:] = 128.0
    return t


def _pair(flat_from: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(left, right, labels): a textured background at D_BG and a plane at D_OBJ in BOX
    (without texture from column ``flat_from`` on)."""
    x0, y0, x1, y1 = BOX
    bg = _texture(1)
    obj = _texture(2, flat_from=flat_from)
    xs = np.arange(W, dtype=np.float32)[None, :].repeat(H, 0)
    ys = np.arange(H, dtype=np.float32)[:, None].repeat(W, 1)
    inside = (ys >= y0) & (ys < y1)
    left = np.where(inside & (xs >= x0) & (xs < x1), obj[:, :W], bg[:, :W])
    # the right image: the object's pixels moved by its disparity, in front of the background's
    xl_obj, xl_bg = xs + D_OBJ, xs + D_BG
    on_obj = inside & (xl_obj >= x0) & (xl_obj < x1)
    r_obj = cv2.remap(obj, xl_obj, ys, cv2.INTER_LINEAR)
    r_bg = cv2.remap(bg, xl_bg, ys, cv2.INTER_LINEAR)
    right = np.where(on_obj, r_obj, r_bg)
    labels = np.zeros((H, W), np.int32)
    labels[y0:y1, x0:x1] = 1
    return np.clip(left, 0, 255).astype(np.uint8), np.clip(right, 0, 255).astype(np.uint8), labels


def _boxes() -> np.ndarray:
    return np.array([BOX], np.int64)


@pytest.fixture(scope="module")
def scene():
    left, right, labels = _pair()
    disp = StereoMatcher(StereoConfig()).compute(left, right)  # the masker's 15-px disparity
    return left, right, labels, disp


def test_the_outline_is_matched_again_to_a_tenth_of_a_pixel(scene):
    left, right, labels, disp = scene
    out, matched = ObjectStereo(11)(left, right, labels, disp, _boxes())
    inside = labels == 1
    v = out[inside]
    assert matched[0] == np.count_nonzero(v > 0) > 0.7 * inside.sum()
    assert abs(float(np.median(v[v > 0])) - D_OBJ) < 0.1
    # outside the outline the masker's values are kept as they were
    assert np.array_equal(out[~inside], disp[~inside])
    # into a buffer kept between frames: the outline alone is written (the objects' stage
    # reads it there where it was matched), the same values; the rest keeps what it held
    kept = np.full(disp.shape, -7.0, np.float32)
    again, _ = ObjectStereo(11)(left, right, labels, disp, _boxes(), kept)
    assert again is kept and np.array_equal(kept[inside], out[inside]) and np.all(kept[~inside] == -7.0)


def test_it_is_stereo_bm_inside_the_window(scene):
    """Where OpenCV's StereoBM with the same block and checks over the whole frame gives a
    disparity, this matcher gives the same one, to the bit (its window and box change only
    which pixels pass the checks, and few)."""
    left, right, labels, disp = scene
    ours, _ = ObjectStereo(11, samples=0)(left, right, labels, disp, _boxes())  # every pixel matched
    bm = StereoMatcher(StereoConfig(block_size=11)).compute(left, right)
    inside = labels == 1
    both = inside & (ours > 0) & (bm > 0)
    assert both.sum() > 0.8 * inside.sum()
    assert (ours[both] == bm[both]).mean() > 0.99
    assert np.count_nonzero(inside & ((ours > 0) != (bm > 0))) < 0.1 * inside.sum()


def test_a_pixel_failing_bm_checks_gets_no_disparity():
    """The object's right half has no texture: its pixels fail the uniqueness test (and
    the speckle filter) there, as in BM -- none of them keeps a disparity -- while the
    textured half is matched."""
    left, right, labels = _pair(flat_from=(BOX[0] + BOX[2]) // 2)
    disp = StereoMatcher(StereoConfig()).compute(left, right)
    out, _ = ObjectStereo(11)(left, right, labels, disp, _boxes())
    x0, y0, x1, y1 = BOX
    mid = (x0 + x1) // 2
    textured = out[y0:y1, x0:mid - 8]
    flat = out[y0 + 6:y1 - 6, mid + 8:x1]
    assert np.count_nonzero(textured > 0) > 0.6 * textured.size
    assert np.count_nonzero(flat > 0) < 0.05 * flat.size
    # with every check off (no uniqueness, no left-right check, no speckle filter) the flat half is "matched"
    loose = ObjectStereo(11, checks=params_at_scale(StereoConfig(uniqueness_ratio=0, disp12_max_diff=-1,
                                                                 speckle_window_size=0), 1))
    out2, _ = loose(left, right, labels, disp, _boxes())
    assert np.count_nonzero(out2[y0 + 6:y1 - 6, mid + 8:x1] > 0) > 0.5 * flat.size


def test_an_outline_mostly_failing_the_checks_keeps_the_maskers():
    """An object textured only on its first 10 of 70 columns: fewer than 30 % of its pixels
    pass the checks -- too few for the objects' stage to measure (``MIN_VALID_FRACTION``) --
    so the masker's disparity stays, which it may measure."""
    left, right, labels = _pair(flat_from=BOX[0] + 10)
    disp = np.where(labels == 1, np.float32(D_OBJ), StereoMatcher(StereoConfig()).compute(left, right))
    out, matched = ObjectStereo(11, samples=0)(left, right, labels, disp, _boxes())
    assert matched.tolist() == [-1] and np.array_equal(out, disp)
    # the same object textured on half its columns is matched again
    left, right, labels = _pair(flat_from=BOX[0] + 35)
    assert ObjectStereo(11, samples=0)(left, right, labels, disp, _boxes())[1][0] > 0


def test_an_outline_without_disparities_keeps_the_maskers(scene):
    left, right, labels, _ = scene
    disp = np.zeros((H, W), np.float32)
    disp[100, 250] = 14.0  # one pixel: too few to set a window
    out, matched = ObjectStereo(11)(left, right, labels, disp, _boxes())
    assert matched.tolist() == [-1]
    assert np.array_equal(out, disp)


def test_a_stride_matches_every_other_row_and_column(scene):
    """``stride: 2`` matches a quarter of the pixels, each pixel taking its 2x2 cell's
    sample; a box larger than ``samples`` pixels gets the stride that keeps about that many."""
    left, right, labels, disp = scene
    inside = labels == 1
    full, n_full = ObjectStereo(11, samples=0)(left, right, labels, disp, _boxes())
    out, n = ObjectStereo(11, stride=2, samples=0)(left, right, labels, disp, _boxes())
    v = out[inside]
    assert abs(float(np.median(v[v > 0])) - D_OBJ) < 0.1
    assert 0.8 * n_full[0] < n[0] < 1.2 * n_full[0]  # pixels with a disparity: about as many
    x0, y0 = BOX[:2]
    row = out[y0 + 10, x0:x0 + 40]
    assert np.array_equal(row[0::2], row[1::2]) and not np.array_equal(full[y0 + 10, x0:x0 + 40:2],
                                                                      full[y0 + 10, x0 + 1:x0 + 41:2])
    assert np.array_equal(out[y0 + 10, x0:x0 + 40], out[y0 + 11, x0:x0 + 40])
    # the box has 4,200 pixels: with samples 2,000 it is matched at stride 2, as above
    auto, _ = ObjectStereo(11, samples=2000)(left, right, labels, disp, _boxes())
    assert np.array_equal(auto, out)


def test_a_box_larger_than_max_area_keeps_the_maskers(scene):
    """Objects much larger than the masker's block gain nothing from a smaller one: a box
    beyond ``max_area`` pixels (the configuration's: 20 of the masker's blocks) is left as
    the masker matched it."""
    left, right, labels, disp = scene
    out, matched = ObjectStereo(11, max_area=4199)(left, right, labels, disp, _boxes())
    assert matched.tolist() == [-1] and np.array_equal(out, disp)
    assert ObjectStereo(11, max_area=4200)(left, right, labels, disp, _boxes())[1][0] > 0
    cfg = Config().with_overrides({"objects.block_size": 11, "stereo.block_size": 13})
    assert ObjectStereo.from_config(cfg.objects, cfg.stereo).max_area == 20 * 13 * 13


def test_the_frames_budget_matches_the_smaller_boxes_first(scene):
    """Within a frame's budget (the boxes' areas with the block's margin), the smaller
    boxes are matched first; those beyond it keep the masker's disparity."""
    left, right, labels, disp = scene
    x0, y0, x1, y1 = BOX
    two = labels.copy()
    two[y0:y1, x0:x0 + 20] = np.where(labels[y0:y1, x0:x0 + 20] == 1, 2, 0)  # a second, narrower object
    boxes = np.array([[x0 + 20, y0, x1, y1], [x0, y0, x0 + 20, y1]], np.int64)
    small, big = (20 + 11) * (y1 - y0 + 11), (x1 - x0 - 20 + 11) * (y1 - y0 + 11)
    _, both = ObjectStereo(11, budget=small + big)(left, right, two, disp, boxes)
    out, one = ObjectStereo(11, budget=small + big - 1)(left, right, two, disp, boxes)
    assert both.min() > 0 and one[1] > 0 and one[0] == -1
    assert np.array_equal(out[two == 1], disp[two == 1])  # the larger one: the masker's


def test_bad_inputs_are_one_line_errors(scene):
    left, right, labels, disp = scene
    with pytest.raises(ValueError, match="one shape"):
        ObjectStereo(11)(left[:, :100], right, labels, disp, _boxes())


def test_the_configuration_sets_it():
    assert ObjectStereo.from_config(ObjectsConfig(), StereoConfig()).block == 11  # the default
    assert ObjectStereo.from_config(ObjectsConfig(block_size=0), StereoConfig()) is None  # the masker's
    s = ObjectStereo.from_config(ObjectsConfig(block_size=11, stride=2), StereoConfig(uniqueness_ratio=15))
    assert (s.block, s.stride, s.checks.uniqueness_ratio, s.checks.speckle_window_size, s.max_area) == (11, 2, 15, 100,
                                                                                                        4500)
    for bad in ({"objects.block_size": 4}, {"objects.block_size": 3}, {"objects.stride": 0}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            Config().with_overrides(bad)


def test_positions_come_from_the_objects_own_matching(scene):
    """A car's plane at D_OBJ whose masker disparity inside the outline reads 0.6 px too
    high: from the masker's disparity its range is that much short; matched again from the
    images (``objects.block_size: 11``) it is right to within the matching's error."""
    left, right, labels, disp = scene
    fx, b = 400.0, 0.5
    calib = StereoCalibration(np.array([[fx, 0, W / 2], [0, fx, H / 2], [0, 0, 1]]), b, W, H)
    biased = disp.copy()
    biased[(labels == 1) & (disp > 0)] += 0.6
    z_true = fx * b / D_OBJ  # the face's range (0.56 m beyond the biased one's)

    def depth(world: WorldObjects) -> float:
        o = ObjectMask(tuple(float(v) for v in BOX), "person", 0.9, MaskMethod.OUTLINE, D_OBJ + 0.6,
                       int((labels == 1).sum()), 0, track_id=1)
        m = StereoMasks(labels.astype(np.uint8), labels.astype(np.uint8), [o], labels_left=labels,
                        labels_right=labels, box_disparity=biased)
        s = world.update(m, np.eye(4), True, 0.0, StereoFrame(0, 0.0, left, right))[0]
        return float(s.camera[2])

    own = depth(WorldObjects.from_config(calib, Config()))  # the default: block 11
    masker = depth(WorldObjects.from_config(calib, Config().with_overrides({"objects.block_size": 0})))
    # the centre lies behind the face by the same amount either way: the difference is the bias's
    assert own - masker == pytest.approx(z_true - fx * b / (D_OBJ + 0.6), abs=0.08)
