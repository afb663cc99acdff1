"""masking.boxes: the one box IoU (tracker, stereo box matching, motion, reference masks)."""

from __future__ import annotations

import numpy as np

from dynastereo.masking.boxes import box_iou, box_iou_pairs


def _random_boxes(rng, n):
    xy = rng.uniform(0, 1200, (n, 2))
    wh = rng.uniform(1, 300, (n, 2))
    return np.hstack([xy, xy + wh]).astype(np.float32)


def test_known_values_and_empty_and_degenerate() -> None:
    iou = box_iou([[0, 0, 10, 10]], [[0, 0, 10, 10], [5, 0, 15, 10], [20, 20, 30, 30], [0, 0, 5, 10]])
    assert np.allclose(iou, [[1.0, 50 / 150, 0.0, 0.5]])
    assert box_iou(np.zeros((0, 4)), [[0, 0, 1, 1]]).shape == (0, 1)
    assert box_iou([[1, 1, 1, 1]], [[1, 1, 1, 1], [5, 5, 3, 3]]).tolist() == [[0.0, 0.0]]  # no area, inverted
    assert box_iou([[0, 0, 10, 10]], [[10, 10, 0, 0]]).tolist() == [[0.0]]


def test_pairs_broadcast_equals_the_matrix_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    a, b = _random_boxes(rng, 7), _random_boxes(rng, 9)
    m = box_iou(a, b)
    assert m.shape == (7, 9) and m.max() > 0
    assert np.array_equal(box_iou_pairs(a[:, None, :], b[None, :, :]), m)
    assert np.array_equal(box_iou_pairs(a[2], b[4]), m[2, 4])


def test_same_bits_as_the_two_former_copies_on_valid_boxes() -> None:
    def old_maskers(a, b):  # maskers._box_iou_matrix
        a = np.asarray(a, np.float64).reshape(-1, 1, 4)
        b = np.asarray(b, np.float64).reshape(1, -1, 4)
        iw = np.clip(np.minimum(a[..., 2], b[..., 2]) - np.maximum(a[..., 0], b[..., 0]), 0, None)
        ih = np.clip(np.minimum(a[..., 3], b[..., 3]) - np.maximum(a[..., 1], b[..., 1]), 0, None)
        inter = iw * ih
        area_a = (a[..., 2] - a[..., 0]) * (a[..., 3] - a[..., 1])
        area_b = (b[..., 2] - b[..., 0]) * (b[..., 3] - b[..., 1])
        return inter / np.maximum(area_a + area_b - inter, 1e-9)

    rng = np.random.default_rng(5)
    a, b = _random_boxes(rng, 20), _random_boxes(rng, 30)
    b[:5] = a[:5] + rng.normal(0, 3, (5, 4)).astype(np.float32)  # close pairs too
    assert np.array_equal(box_iou(a, b), old_maskers(a, b))
    # the stereo matcher's form: left box i against every right box shifted by its own disparity
    shifted = np.repeat(b[None].astype(np.float64), len(a), axis=0) + rng.uniform(-50, 50, (len(a), len(b), 1)) * [1, 0, 1, 0]
    loop = np.stack([old_maskers(a[i:i + 1], shifted[i])[0] for i in range(len(a))])
    assert np.array_equal(box_iou_pairs(a.astype(np.float64)[:, None, :], shifted), loop)


def test_one_class_group_definition_gives_the_former_partitions() -> None:
    from dynastereo.masking.detection.classes import CLASS_GROUPS, COCO_CLASSES, class_group_index
    from dynastereo.masking.detection.scale import GROUPS
    from dynastereo.masking.detection.box_tracker import TrackerParams

    assert TrackerParams().class_groups is CLASS_GROUPS
    assert class_group_index() == {"car": 0, "bus": 0, "truck": 0, "train": 0, "bicycle": 1, "motorcycle": 1}
    assert class_group_index((("Motorbike", "bicycle"),)) == {"motorcycle": 0, "bicycle": 0}
    # the seam merger's former table: the same classes share a group (person alone)
    former = {"car": 0, "truck": 0, "bus": 0, "train": 0, "person": 1, "bicycle": 2, "motorcycle": 2}
    old = [former.get(n, 100 + k) for k, n in enumerate(COCO_CLASSES)]
    new = [GROUPS.get(n, 100 + k) for k, n in enumerate(COCO_CLASSES)]
    assert np.array_equal(np.equal.outer(old, old), np.equal.outer(new, new))
