"""Box tracker (masking.detection.box_tracker): boxes carried between detections.

Synthetic sequences with known answers: a random-texture object moving (and scaling,
as an approaching car) by a known sub-pixel motion over a textured background that moves
differently (camera motion); the tracker sees a detection on some frames only."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dynastereo.masking.detection.classes import COCO_CLASSES
from dynastereo.masking.boxes import box_iou
from dynastereo.masking.detection.box_tracker import BoxTracker, TrackerParams
from dynastereo.datatypes import Detections

H, W = 240, 480
CAR, BUS, PERSON = COCO_CLASSES.index("car"), COCO_CLASSES.index("bus"), COCO_CLASSES.index("person")


def texture(h: int, w: int, seed: int, sigma: float = 1.2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), sigma)
    return ((t - t.min()) * (255.0 / (t.max() - t.min()))).astype(np.float32)


class Scene:
    """Objects (texture, centre0, velocity, scale per frame) over a background moving by bg_v."""

    def __init__(self, objects, bg_v=(-0.6, 0.2), seed=0, h=H, w=W):
        self.h, self.w = h, w
        self.bg = texture(h + 40, w + 40, seed)
        self.bg_v = np.asarray(bg_v, float)
        self.objects = [(texture(*sz, seed + 1 + i), np.asarray(c, float), np.asarray(v, float), s)
                        for i, (sz, c, v, s) in enumerate(objects)]  # fmt: skip

    def _pose(self, o, k):
        tex, c0, v, s = o
        return tex, c0 + k * v, s**k

    def box(self, k: int, i: int = 0) -> np.ndarray:
        """True box (x1, y1, x2, y2, x2/y2 exclusive) of object i on frame k."""
        tex, c, s = self._pose(self.objects[i], k)
        th, tw = tex.shape
        half = np.array([tw, th]) * s / 2
        return np.concatenate([c - half, c + half]) + 0.5

    def frame(self, k: int) -> np.ndarray:
        M = np.float32([[1, 0, -20 + k * self.bg_v[0]], [0, 1, -20 + k * self.bg_v[1]]])
        img = cv2.warpAffine(self.bg, M, (self.w, self.h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        for o in self.objects:
            tex, c, s = self._pose(o, k)
            th, tw = tex.shape
            # texture pixel q (centre coords) -> s * (q - centre_tex) + c
            M = np.float32([[s, 0, c[0] - s * (tw - 1) / 2], [0, s, c[1] - s * (th - 1) / 2]])
            obj = cv2.warpAffine(tex, M, (self.w, self.h), flags=cv2.INTER_LINEAR)
            alpha = cv2.warpAffine(np.ones_like(tex), M, (self.w, self.h), flags=cv2.INTER_LINEAR)
            img = img * (1 - alpha) + obj * alpha
        return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def dets(boxes, classes=None, scores=None) -> Detections:
    boxes = np.asarray(boxes, np.float32).reshape(-1, 4)
    n = len(boxes)
    classes = [CAR] * n if classes is None else classes
    scores = [0.9] * n if scores is None else scores
    return Detections(boxes, scores, classes, COCO_CLASSES)


def corner_error(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a, float) - np.asarray(b, float))))


# ---------------------------------------------------------------------------------------
# following the object between detections
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "velocity, scale",
    [((2.3, 0.7), 1.0), ((-1.4, -3.6), 1.0), ((0.8, 1.5), 1.05)],  # last: an approaching car
    ids=["subpixel", "pixel", "scaling"],
)
@pytest.mark.parametrize("downscale", [1, 2], ids=["full", "half-size flow"])
def test_carried_box_follows_the_object(velocity, scale, downscale):
    sc = Scene([((60, 100), (200, 120), velocity, scale)])
    tr = BoxTracker(TrackerParams(lk_downscale=downscale, lk_win=15 if downscale == 1 else 11,
                                  lk_levels=3 if downscale == 1 else 2))
    out = tr.update(sc.frame(0), dets(sc.box(0)))
    assert len(out) == 1 and out.track_ids.tolist() == [0] and out.carried.tolist() == [False]
    errs = []
    for k in range(1, 6):
        out = tr.update(sc.frame(k), None)
        assert len(out) == 1
        assert out.track_ids.tolist() == [0]
        assert out.carried.tolist() == [True]
        assert out.scores[0] == pytest.approx(0.9 * 0.9**k, rel=1e-5)
        assert out.labels() == ["car"]
        errs.append(corner_error(out.boxes[0], sc.box(k)))
    assert max(errs) < 1.0, errs  # (measured: < 0.2 px full size; the issue asks for 2 px)
    # and it really moved: standing still would be far off
    assert corner_error(sc.box(0), sc.box(5)) > 6.0
    if scale != 1.0:
        b = out.boxes[0]
        assert (b[2] - b[0]) / 100 == pytest.approx(scale**5, abs=0.03)


def test_detection_confirms_carried_track_and_corrects_class():
    sc = Scene([((60, 100), (200, 120), (2.0, 0.5), 1.0)])
    tr = BoxTracker()
    tr.update(sc.frame(0), dets(sc.box(0), [CAR]))
    for k in range(1, 4):
        tr.update(sc.frame(k), None)
    det_box = sc.box(4) + np.array([1.5, -1.0, 2.0, 0.5])  # a detector's box is a bit off
    out = tr.update(sc.frame(4), dets(det_box, [BUS], [0.7]))  # same group: vehicles
    assert out.track_ids.tolist() == [0]
    assert out.carried.tolist() == [False]
    assert out.labels() == ["bus"]
    assert out.scores[0] == pytest.approx(0.7)
    np.testing.assert_allclose(out.boxes[0], det_box, atol=1e-4)
    # carried again from the confirmed box, score decays from the new one
    out = tr.update(sc.frame(5), None)
    assert out.track_ids.tolist() == [0] and out.carried.tolist() == [True]
    assert out.scores[0] == pytest.approx(0.7 * 0.9)
    assert corner_error(out.boxes[0], sc.box(5)) < 3.0  # the detection's offset is carried along


def test_new_far_detection_gets_new_id_and_other_group_does_not_match():
    sc = Scene([((60, 100), (150, 120), (1.0, 0.0), 1.0), ((50, 40), (380, 90), (-1.0, 0.5), 1.0)])
    tr = BoxTracker()
    tr.update(sc.frame(0), dets(sc.box(0, 0)))
    tr.update(sc.frame(1), None)
    out = tr.update(sc.frame(2), dets([sc.box(2, 1), sc.box(2, 0)], [PERSON, CAR]))
    assert out.track_ids.tolist() == [1, 0]  # detection order: the new one first
    assert out.carried.tolist() == [False, False]
    # a person detection on the carried car does not confirm it: a new track, car carried
    out = tr.update(sc.frame(3), dets(sc.box(3, 0), [PERSON]))
    assert out.track_ids.tolist() == [2, 0, 1]
    assert out.carried.tolist() == [False, True, True]
    assert out.labels() == ["person", "car", "person"]
    assert corner_error(out.boxes[1], sc.box(3, 0)) < 2.0
    assert corner_error(out.boxes[2], sc.box(3, 1)) < 2.0


def test_track_dropped_after_max_carry_detector_frames():
    sc = Scene([((60, 100), (200, 120), (1.5, 0.5), 1.0)])
    tr = BoxTracker(TrackerParams(max_carry=3))
    tr.update(sc.frame(0), dets(sc.box(0)))
    k = 1
    for misses in (1, 2, 3):
        # frames without a detector run in between do not count as misses
        out = tr.update(sc.frame(k), None)
        assert out.carried.tolist() == [True]
        out = tr.update(sc.frame(k + 1), Detections.empty(COCO_CLASSES))
        assert out.track_ids.tolist() == [0] and out.carried.tolist() == [True], misses
        k += 2
    out = tr.update(sc.frame(k), Detections.empty(COCO_CLASSES))  # 4th miss > max_carry
    assert len(out) == 0 and tr.num_tracks == 0
    out = tr.update(sc.frame(k + 1), None)
    assert len(out) == 0


def test_a_track_seen_once_is_not_carried_past_a_miss_with_min_hits():
    sc = Scene([((60, 100), (200, 120), (1.5, 0.5), 1.0)])
    tr = BoxTracker(TrackerParams(max_carry=3, min_hits=2))
    tr.update(sc.frame(0), dets(sc.box(0)))
    assert tr.update(sc.frame(1), None).carried.tolist() == [True]  # no run: carried
    assert len(tr.update(sc.frame(2), Detections.empty(COCO_CLASSES))) == 0  # one hit, one miss: gone
    tr = BoxTracker(TrackerParams(max_carry=3, min_hits=2))
    tr.update(sc.frame(0), dets(sc.box(0)))
    tr.update(sc.frame(1), dets(sc.box(1)))  # confirmed: two hits
    out = tr.update(sc.frame(2), Detections.empty(COCO_CLASSES))
    assert out.track_ids.tolist() == [0] and out.carried.tolist() == [True]


def test_max_age_frames_caps_carrying_without_detector_runs():
    sc = Scene([((60, 100), (200, 120), (1.5, 0.5), 1.0)])
    tr = BoxTracker(TrackerParams(max_age_frames=2))
    tr.update(sc.frame(0), dets(sc.box(0)))
    assert len(tr.update(sc.frame(1), None)) == 1
    assert len(tr.update(sc.frame(2), None)) == 1
    assert len(tr.update(sc.frame(3), None)) == 0


def test_lost_points_drop_the_box_unless_detected():
    flat = np.full((H, W), 128, np.uint8)  # nothing to track
    box = [100, 80, 200, 150]
    tr = BoxTracker()
    tr.update(flat, dets(box))
    assert len(tr.update(flat, None)) == 0
    # a detection of this frame keeps the track (matched on its previous box)
    tr.reset()
    tr.update(flat, dets(box))
    out = tr.update(flat, dets(np.add(box, 2)))
    assert out.track_ids.tolist() == [0] and out.carried.tolist() == [False]


def test_a_box_whose_points_are_lost_moves_on_by_its_velocity():
    """Detected on two frames (a known velocity), then its texture is gone (points lost):
    carried on by that velocity instead of dropped."""
    flat = np.full((H, W), 128, np.uint8)
    tr = BoxTracker()
    tr.update(flat, dets([100, 80, 200, 150]))
    tr.update(flat, dets([106, 81, 208, 152]))  # moved (+6, +1), grew by 2 / 1 px
    out = tr.update(flat, None)
    assert out.track_ids.tolist() == [0] and out.carried.tolist() == [True]
    np.testing.assert_allclose(out.boxes[0], [112, 82, 216, 154], atol=1e-3)


def test_a_new_box_without_points_follows_the_other_boxes_motion():
    """Its own points lost and no velocity yet: the motion of the other boxes' points
    (here all moving by the same known shift) carries it, within 2 px."""
    sc = Scene([((60, 100), (80, 90), (4.0, 1.5), 1.0), ((300, 60), (90, 80), (4.0, 1.5), 1.0)], bg_v=(4.0, 1.5))
    f0, f1 = sc.frame(0), sc.frame(1).copy()
    blank = [150, 150, 230, 210]
    f0 = f0.copy()
    f0[150:210, 150:230] = 128  # a flat patch: no points of its own
    f1[150:210, 150:230] = 128
    tr = BoxTracker()
    tr.update(f0, Detections(np.array([sc.box(0, 0), sc.box(0, 1), blank], np.float32), [0.9] * 3, [2, 2, 2],
                             COCO_CLASSES))
    out = tr.update(f1, None)
    assert len(out) == 3 and out.carried.all()
    np.testing.assert_allclose(out.boxes[2], np.add(blank, [4.0, 1.5, 4.0, 1.5]), atol=2.0)


def test_box_leaving_the_image_is_clipped_then_dropped():
    sc = Scene([((60, 80), (60, 120), (-9.0, 0.0), 1.0)], bg_v=(0.0, 0.0))
    tr = BoxTracker(TrackerParams(max_age_frames=50))
    tr.update(sc.frame(0), dets(sc.box(0)))
    seen = []
    for k in range(1, 15):
        out = tr.update(sc.frame(k), None)
        if len(out):
            b = out.boxes[0]
            assert b[0] >= 0 and b[1] >= 0 and b[2] <= W and b[3] <= H
            truth = np.clip(sc.box(k), 0, [W, H, W, H])
            assert abs(b[2] - truth[2]) < 2.5, k  # the right edge still follows the object
        seen.append(len(out))
    # the object is gone after frame ~11 (right edge 60 + 40 - 9k < 0); the box too
    assert seen[0] == 1 and seen[-1] == 0
    assert seen.index(0) <= 11


def test_empty_detections_and_empty_tracker():
    img = Scene([]).frame(0)
    tr = BoxTracker()
    for d in (None, Detections.empty(COCO_CLASSES), Detections.empty()):
        out = tr.update(img, d)
        assert len(out) == 0
        assert out.track_ids.dtype == np.int64 and out.track_ids.shape == (0,)
        assert out.carried.dtype == bool and out.carried.shape == (0,)
        assert out.boxes.shape == (0, 4)
    out = tr.update(img, dets([[10, 10, 60, 50], [100, 100, 180, 170], [300, 40, 350, 90]]))
    assert out.track_ids.tolist() == [0, 1, 2]
    assert out.carried.tolist() == [False] * 3
    assert out.class_names == COCO_CLASSES


def test_select_keeps_track_ids_and_carried():
    sc = Scene([((60, 100), (150, 120), (1.0, 0.0), 1.0), ((50, 40), (380, 90), (-1.0, 0.5), 1.0)])
    tr = BoxTracker()
    tr.update(sc.frame(0), dets([sc.box(0, 0)]))
    out = tr.update(sc.frame(1), dets([sc.box(1, 1)], [PERSON]))
    assert out.track_ids.tolist() == [1, 0] and out.carried.tolist() == [False, True]
    sub = out.select(np.array([False, True]))
    assert sub.track_ids.tolist() == [0] and sub.carried.tolist() == [True]
    assert sub.track_id(0) == 0 and sub.source(0) == "carried"
    sub = out.select(np.array([0]))
    assert sub.track_ids.tolist() == [1] and sub.source(0) == "detected"


def test_reset_restarts_ids_and_boxes_clipped():
    img = Scene([]).frame(0)
    tr = BoxTracker()
    tr.update(img, dets([[10, 10, 60, 50]]))
    tr.update(img, dets([[300, 100, 360, 150]]))
    assert tr.num_tracks == 2
    tr.reset()
    assert tr.num_tracks == 0
    out = tr.update(img, dets([[-20, -5, 60, 50]]))
    assert out.track_ids.tolist() == [0]
    np.testing.assert_allclose(out.boxes[0], [0, 0, 60, 50])


def test_deterministic():
    sc = Scene([((60, 100), (200, 120), (2.3, 0.7), 1.03), ((50, 40), (380, 90), (-1.0, 0.5), 1.0)])
    runs = []
    for _ in range(2):
        tr = BoxTracker()
        res = [tr.update(sc.frame(0), dets([sc.box(0, 0), sc.box(0, 1)], [CAR, PERSON]))]
        res += [tr.update(sc.frame(k), None) for k in range(1, 4)]
        runs.append(res)
    for a, b in zip(*runs):
        np.testing.assert_array_equal(a.boxes, b.boxes)
        np.testing.assert_array_equal(a.track_ids, b.track_ids)


def test_instance_masks_are_carried_with_the_box():
    sc = Scene([((60, 100), (200, 120), (3.0, 1.0), 1.0)])
    box = sc.box(0)
    m = np.zeros((1, H, W), bool)
    m[0, int(box[1]) + 5 : int(box[3]) - 5, int(box[0]) + 5 : int(box[2]) - 5] = True
    tr = BoxTracker()
    d = dets(box)
    d.masks = m
    out = tr.update(sc.frame(0), d)
    assert out.masks is not None and out.masks.shape == (1, H, W)
    for k in range(1, 4):
        out = tr.update(sc.frame(k), None)
    assert out.masks is not None
    ys, xs = np.nonzero(out.masks[0])
    ys0, xs0 = np.nonzero(m[0])
    assert xs.mean() - xs0.mean() == pytest.approx(9.0, abs=1.0)
    assert ys.mean() - ys0.mean() == pytest.approx(3.0, abs=1.0)


def test_box_iou_and_params_validation():
    iou = box_iou([[0, 0, 10, 10]], [[0, 0, 10, 10], [5, 0, 15, 10], [20, 20, 30, 30]])
    np.testing.assert_allclose(iou, [[1.0, 1 / 3, 0.0]])
    assert box_iou(np.zeros((0, 4)), [[0, 0, 1, 1]]).shape == (0, 1)
    with pytest.raises(ValueError):
        TrackerParams(match_iou=0.0)
    with pytest.raises(ValueError):
        TrackerParams(min_points=10, max_points=5)


def _median_flow_reference(p0, p1, owner, good, T, min_points, min_pair_dist, lo, hi):
    """The per-track median flow as plain numpy (the form it had before its kernel)."""
    aff = np.tile(np.array([1.0, 0.0, 0.0]), (T, 1))
    ok = np.zeros(T, bool)
    for i in range(T):
        sel = good & (owner == i)
        if np.count_nonzero(sel) < min_points:
            continue
        a, b = p0[sel], p1[sel]
        iu, ju = np.triu_indices(len(a), 1)
        d0 = np.linalg.norm(a[iu] - a[ju], axis=1)
        d1 = np.linalg.norm(b[iu] - b[ju], axis=1)
        use = d0 >= min_pair_dist
        s = float(np.clip(np.median(d1[use] / d0[use]), lo, hi)) if np.any(use) else 1.0
        t = np.median(b - s * a, axis=0)
        aff[i] = (s, t[0], t[1])
        ok[i] = True
    return aff, ok


def test_median_flow_kernel_agrees_with_the_reference():
    """The compiled median flow (scale from pairwise distances, translation) gives the
    plain numpy version's boxes bit for bit on random point sets: tracks with too few
    good points, points too close for a pair, odd and even counts, clamped scales."""
    from dynastereo.masking.detection.box_tracker import _median_flow

    rng = np.random.default_rng(1)
    for _ in range(300):
        T = int(rng.integers(1, 6))
        n = int(rng.integers(0, 60))
        p0 = rng.uniform(0, 100, (n, 2)).astype(np.float32).astype(np.float64)
        if rng.random() < 0.2:
            p0 = np.round(p0 / 20) * 20  # coincident points: pairs below the distance
        s = rng.uniform(0.5, 1.8)
        p1 = (s * p0 + rng.uniform(-5, 5, 2) + rng.normal(0, 0.5, (n, 2))).astype(np.float32).astype(np.float64)
        owner = np.sort(rng.integers(0, T, n)).astype(np.int64)
        good = rng.random(n) < 0.8
        aff = np.tile(np.array([1.0, 0.0, 0.0]), (T, 1))
        ok = np.zeros(T, bool)
        _median_flow(p0, p1, owner, good, T, 4, 3.0, 1 / 1.5, 1.5, aff, ok)
        ref_aff, ref_ok = _median_flow_reference(p0, p1, owner, good, T, 4, 3.0, 1 / 1.5, 1.5)
        assert np.array_equal(ok, ref_ok) and np.array_equal(aff, ref_aff)
