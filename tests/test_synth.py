"""Synthetic stereo sequences (dynastereo.synth): layout, exact geometry, ground truth, oracle.

All sequences are generated here at small sizes (the file runs in well under a minute);
the photometric stereo check and the ORB check use the real default size 640x192.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynastereo.errors import InputError
from dynastereo.synth import (
    SCENARIOS,
    OracleDetector,
    generate,
    intrinsics,
    make_plan,
    read_gt_disparity,
    read_gt_masks,
    read_objects,
)
from dynastereo.synth.render import Renderer
from dynastereo.synth.world import build_world
from dynastereo.datatypes import Detections

REQUIRED = ("static", "crossing", "convoy", "oncoming", "loop", "mixed")


@pytest.fixture(scope="module")
def mixed_small(tmp_path_factory) -> Path:
    return generate(tmp_path_factory.mktemp("mixed"), "mixed", frames=12, seed=3, size=(320, 96), noise=0.0)


@pytest.fixture(scope="module")
def full_size(tmp_path_factory) -> Path:
    """Default size, noise off: frames of three scenarios for the photometric + ORB checks."""
    root = tmp_path_factory.mktemp("full")
    for sc, n in (("mixed", 31), ("convoy", 16), ("static", 41)):
        generate(root / sc, sc, frames=n, seed=0, noise=0.0)
    return root


def _png(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img


# ---------------------------------------------------------------------------------------------
# layout and formats


def test_scenarios_registry():
    for name in REQUIRED:
        assert name in SCENARIOS, name
        assert len(SCENARIOS[name].description) > 20


def test_unknown_scenario_lists_names(tmp_path):
    with pytest.raises(InputError) as e:
        generate(tmp_path, "nope", frames=1)
    for name in REQUIRED:
        assert name in str(e.value)
    with pytest.raises(InputError):
        generate(tmp_path, "mixed", frames=1, size="640by192")
    with pytest.raises(InputError):
        generate(tmp_path, "mixed", frames=0)


def test_layout_and_formats(mixed_small: Path):
    seq = mixed_small
    root = seq.parent.parent
    assert seq == root / "sequences" / "00"
    n = 12
    W, H = 320, 96
    for sub, dtype in (
        ("image_0", np.uint8),
        ("image_1", np.uint8),
        ("gt/disparity", np.uint16),
        ("gt/masks/left", np.uint8),
        ("gt/masks/right", np.uint8),
    ):
        files = sorted((seq / sub).glob("*.png"))
        assert [f.name for f in files] == [f"{i:06d}.png" for i in range(n)], sub
        img = _png(files[0])
        assert img.shape == (H, W) and img.dtype == dtype, (sub, img.shape, img.dtype)
    # calib.txt: P0..P3, KITTI's focal length scaled to the width, 0.54 m baseline
    rows = {}
    for line in (seq / "calib.txt").read_text().splitlines():
        key, vals = line.split(":")
        rows[key] = np.array(vals.split(), float).reshape(3, 4)
    assert set(rows) == {"P0", "P1", "P2", "P3"}
    fx = rows["P0"][0, 0]
    assert fx == pytest.approx(718.856 * W / 1241, rel=1e-9)
    assert -rows["P1"][0, 3] / fx == pytest.approx(0.54)
    assert np.allclose(rows["P2"], rows["P0"]) and np.allclose(rows["P3"], rows["P1"])
    # times at 10 Hz; poses: n rows of 12 numbers, identity first
    t = np.loadtxt(seq / "times.txt")
    assert np.allclose(t, np.arange(n) * 0.1)
    P = np.loadtxt(root / "poses" / "00.txt")
    assert P.shape == (n, 12)
    assert np.allclose(P[0].reshape(3, 4), np.eye(4)[:3], atol=1e-9)
    R = P[:, :12].reshape(n, 3, 4)[:, :, :3]
    assert np.allclose(R @ np.transpose(R, (0, 2, 1)), np.eye(3), atol=1e-6)
    # the rig drives forward (+z of the first camera) at city speed
    speed = np.linalg.norm(np.diff(P.reshape(n, 3, 4)[:, :, 3], axis=0), axis=1) / 0.1
    assert 3.0 < speed.mean() < 14.0


def test_project_reader_opens_it(mixed_small: Path):
    from dynastereo.io import open_sequence

    s = open_sequence(mixed_small)
    assert len(s) == 12
    fx, fy, cx, cy = intrinsics((320, 96))
    assert s.calibration.fx == pytest.approx(fx) and s.calibration.baseline == pytest.approx(0.54)
    f = s.frame(3)
    assert f.left.shape[:2] == (96, 320)
    assert np.array_equal(f.left_gray, _png(mixed_small / "image_0" / "000003.png"))


# ---------------------------------------------------------------------------------------------
# ground truth consistency


def test_boxes_and_counts_match_masks(mixed_small: Path):
    gt = read_objects(mixed_small)
    assert len(gt) == 12 and gt.scenario == "mixed" and gt.size == (320, 96)
    seen = 0
    for i in range(len(gt)):
        left, right = read_gt_masks(mixed_small, i)
        recs = {o.id: o for o in gt.frame(i)}
        present = (set(np.unique(left)) | set(np.unique(right))) - {0}
        assert present == set(recs), i  # every object in a mask is listed, and only those
        for oid, o in recs.items():
            for mask, box, count in ((left, o.box_left, o.pixels_left), (right, o.box_right, o.pixels_right)):
                ys, xs = np.nonzero(mask == oid)
                assert count == len(ys)
                if count:
                    assert box == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
                else:
                    assert box is None
            assert gt.objects[oid]["label"] == o.label
            seen += 1
    assert seen > 20


def test_mask_pixels_have_object_depth(mixed_small: Path):
    """Object pixels' GT depth lies inside the object's 3-D extent; its box centre projects into the box."""
    gt = read_objects(mixed_small)
    fx, fy, cx, cy = intrinsics((320, 96))
    checked = 0
    for i in range(len(gt)):
        disp = read_gt_disparity(mixed_small, i)
        left, _ = read_gt_masks(mixed_small, i)
        for o in gt.frame(i):
            if o.pixels_left < 15:
                continue
            d = disp[left == o.id]
            assert (d > 0).all()
            z = fx * 0.54 / d
            w, h, length = gt.objects[o.id]["size"]
            r = 0.5 * math.sqrt(w * w + h * h + length * length) + 0.6  # half diagonal + swinging limbs
            zc = o.position_cam[2]
            assert z.min() > zc - r - 0.05 and z.max() < zc + r + 0.05, (i, o.id, z.min(), z.max(), zc)
            assert o.distance == pytest.approx(float(np.linalg.norm(o.position_cam)), abs=2e-3)
            checked += 1
    assert checked > 10


def _stereo_errors(seq: Path, i: int) -> tuple[float, float, float]:
    """(bilinear MAE, near-integer-disparity MAE, fraction of pixels checked) of right vs warped left."""
    L = _png(seq / "image_0" / f"{i:06d}.png").astype(np.float32)
    R = _png(seq / "image_1" / f"{i:06d}.png").astype(np.float32)
    d = read_gt_disparity(seq, i)
    ml, mr = read_gt_masks(seq, i)
    H, W = L.shape
    xr = np.arange(W, dtype=np.float32)[None, :] - d
    # non-occluded in the right view: nothing further right maps at or left of x_r ...
    after = np.minimum.accumulate(xr[:, ::-1], axis=1)[:, ::-1]
    after = np.concatenate([after[:, 1:], np.full((H, 1), np.inf, np.float32)], 1)
    ok = xr < after - 0.5
    # ... and no occluder beyond the right border (could hide behind it), not at a depth edge
    ok &= (xr >= 1) & (xr + d.max() + 8 < W - 1)
    jump = np.zeros((H, W), np.uint8)
    e = np.abs(np.diff(d, axis=1)) > 0.3
    jump[:, 1:] |= e
    jump[:, :-1] |= e
    ok &= cv2.dilate(jump, np.ones((1, 7), np.uint8)) == 0
    # same object (or none) at the matching right pixels
    rows = np.repeat(np.arange(H)[:, None], W, 1)
    x0 = np.clip(np.floor(xr).astype(int), 0, W - 1)
    x1 = np.clip(x0 + 1, 0, W - 1)
    ok &= (mr[rows, x0] == ml) & (mr[rows, x1] == ml)
    ys = rows.astype(np.float32)
    warped = cv2.remap(R, xr, ys, cv2.INTER_LINEAR)
    err = np.abs(warped - L)
    near = ok & (np.abs(d - np.round(d)) < 0.005)
    nearest = cv2.remap(R, np.round(xr), ys, cv2.INTER_NEAREST)
    return float(err[ok].mean()), float(np.abs(nearest - L)[near].mean()), float(ok.mean())


@pytest.mark.parametrize("sc,frames", [("mixed", (0, 15, 30)), ("convoy", (0, 15)), ("static", (20, 40))])
def test_right_equals_left_warped_by_gt_disparity(full_size: Path, sc: str, frames):
    seq = full_size / sc / "sequences" / "00"
    for i in frames:
        mae, mae_int, frac = _stereo_errors(seq, i)
        assert frac > 0.6, (sc, i, frac)
        # where the disparity is an integer the warp needs no interpolation: exact up to rounding
        assert mae_int < 0.3, (sc, i, mae_int)
        # everywhere else bilinear interpolation of the textures adds a little
        assert mae < 1.0, (sc, i, mae)


def test_exact_geometry_in_memory():
    """Right depth at the pixel the left disparity points to is the left depth (no file rounding)."""
    world = build_world(1)
    plan = make_plan(world, "crossing", 20, 1)
    W, H = 320, 96
    fx, fy, cx, cy = intrinsics((W, H))
    r = Renderer(world, W, H, fx, fy, cx, cy)
    r.prepare([o.shape for o in plan.objects])
    x, z, th = plan.camera(19)
    objs = []
    from dynastereo.synth.writer import _posed

    objs = _posed(plan, 1.9, world.params.cam_height)
    rx, rz = math.cos(th), -math.sin(th)
    left = r.render(x, z, th, objs)
    right = r.render(x + 0.54 * rx, z + 0.54 * rz, th, objs)
    assert (left.ids > 0).any()
    zl = left.depth
    fin = np.isfinite(zl)
    d = np.where(fin, fx * 0.54 / np.where(fin, zl, 1.0), 0.0)
    xr = np.arange(W)[None, :] - d
    rows = np.repeat(np.arange(H)[:, None], W, 1)
    xi = np.round(xr).astype(int)
    near = fin & (np.abs(xr - xi) < 0.02) & (xi >= 0) & (xi < W)
    zr = right.depth[rows[near], xi[near]]
    rel = np.abs(zr - zl[near]) / zl[near]
    # visible in both views -> same depth; the few others are occluded in the right view
    assert np.mean(rel < 1e-3) > 0.9
    assert np.all(zr[rel >= 1e-3] < zl[near][rel >= 1e-3])  # a mismatch is always an occluder
    # the sky (no surface) is the same in both views
    sky = ~np.isfinite(left.depth) & ~np.isfinite(right.depth)
    assert np.abs(left.image[sky] - right.image[sky]).max() < 1e-3


def test_orb_finds_many_features_everywhere(full_size: Path):
    orb = cv2.ORB_create(2000)
    frames = [("mixed", i) for i in (0, 10, 20, 30)] + [("convoy", i) for i in (0, 15)] + [("static", i) for i in (0, 20, 40)]
    thirds_ok = 0
    for sc, i in frames:
        img = _png(full_size / sc / "sequences" / "00" / "image_0" / f"{i:06d}.png")
        assert img.shape == (192, 640)
        kp = orb.detect(img, None)
        assert len(kp) > 1000, (sc, i, len(kp))
        pts = np.array([k.pt for k in kp])
        # spread: every quarter of the width has corners ...
        assert np.all(np.histogram(pts[:, 0], bins=4, range=(0, 640))[0] > 40), (sc, i)
        # ... and so has every third of the height, except in a frame or two that look
        # across an empty intersection (bare asphalt in the lower third)
        thirds_ok += bool(np.all(np.histogram(pts[:, 1], bins=3, range=(0, 192))[0] > 40))
    assert thirds_ok >= len(frames) - 2


# ---------------------------------------------------------------------------------------------
# scenario shapes


def test_static_scenario_has_no_motion(tmp_path):
    seq = generate(tmp_path, "static", frames=6, size=(160, 48), seed=2)
    gt = read_objects(seq)
    assert gt.objects and not any(o["moves"] for o in gt.objects.values())
    assert sum(len(f) for f in gt.frames) > 5
    assert not any(o.moving for f in gt.frames for o in f)


def test_convoy_lead_vehicle_keeps_distance_and_fills_the_view(tmp_path):
    n = 25
    seq = generate(tmp_path, "convoy", frames=n, size=(320, 96), seed=0)
    gt = read_objects(seq)
    lead = [o for f in gt.frames for o in f if o.label == "truck" and o.moving]
    assert len(lead) == n  # one moving truck, in every frame
    assert len({o.id for o in lead}) == 1
    z = np.array([o.position_cam[2] for o in lead])
    x = np.array([o.position_cam[0] for o in lead])
    assert 6.0 < z.mean() < 14.0 and z.std() < 0.05 * z.mean()
    assert np.all(np.abs(x) < 1.0)  # straight ahead, in the rig's lane
    share = np.array([o.pixels_left for o in lead]) / (320 * 96)
    assert share.min() > 0.2, share.min()
    P = np.loadtxt(seq.parent.parent / "poses" / "00.txt").reshape(n, 3, 4)
    assert np.linalg.norm(P[-1][:, 3]) > 10.0  # while the rig itself moves on


def test_crossing_people_cross_in_front(tmp_path):
    n = 45
    seq = generate(tmp_path, "crossing", frames=n, size=(160, 48), seed=0)
    gt = read_objects(seq)
    tracks: dict[int, list] = {}
    for f in gt.frames:
        for o in f:
            if o.label == "person" and o.moving:
                tracks.setdefault(o.id, []).append(o.position_cam)
    crossing = [
        t for t in tracks.values() if len(t) > 5 and min(p[2] for p in t) > 2.0 and (max(p[0] for p in t) - min(p[0] for p in t)) > 2.0
    ]
    assert crossing, "no person crosses the road ahead of the rig"


def test_oncoming_cars_approach(tmp_path):
    seq = generate(tmp_path, "oncoming", frames=30, size=(160, 48), seed=0)
    gt = read_objects(seq)
    closing = {}
    for f in gt.frames:
        for o in f:
            if o.moving and o.label in ("car", "truck"):
                closing.setdefault(o.id, []).append(o.position_cam)
    fast = [t for t in closing.values() if len(t) >= 5 and (t[0][2] - t[-1][2]) / (0.1 * (len(t) - 1)) > 12.0]
    assert fast  # closing speed = rig + oncoming speed
    assert all(p[0] < -1.5 for t in fast for p in t if p[2] < 60.0)  # on the left (oncoming lane)


def test_loop_returns_to_its_start(tmp_path):
    seq = generate(tmp_path, "loop", size=(64, 24), seed=0)
    P = np.loadtxt(seq.parent.parent / "poses" / "00.txt").reshape(-1, 3, 4)
    t = P[:, :, 3]
    length = np.linalg.norm(np.diff(t, axis=0), axis=1).sum()
    assert 350.0 < length < 650.0, length
    half = len(t) // 2
    k = half + int(np.argmin(np.linalg.norm(t[half:], axis=1)))
    assert np.linalg.norm(t[k]) < 1.0  # back at the start ...
    cosang = (np.trace(P[k][:, :3]) - 1) / 2
    assert cosang > math.cos(math.radians(5))  # ... facing the same way
    overlap = np.linalg.norm(np.diff(t[k:], axis=0), axis=1).sum()
    assert 40.0 < overlap < 80.0, overlap  # and on over the first stretch again
    assert np.linalg.norm(t[-1] - t[int(np.argmin(np.linalg.norm(t[: half] - t[-1], axis=1)))]) < 1.0
    assert np.max(np.linalg.norm(t, axis=1)) > 80.0  # after going round the block
    yaw = np.unwrap(np.arctan2(P[:, 0, 2], P[:, 2, 2]))
    assert abs(abs(yaw[k] - yaw[0]) - 2 * math.pi) < 0.2  # one full turn
    gt = read_objects(seq)
    assert sum(o["moves"] for o in gt.objects.values()) >= 5


def test_deterministic_for_a_seed(tmp_path, mixed_small: Path):
    a = generate(tmp_path / "a", "mixed", frames=3, seed=3, size=(320, 96), noise=0.0)
    for sub in ("image_0", "image_1", "gt/disparity", "gt/masks/left", "gt/masks/right"):
        for i in range(3):
            f = f"{sub}/{i:06d}.png"
            assert np.array_equal(_png(a / f), _png(mixed_small / f)), f  # prefix of the 12-frame run
    ja = json.loads((a / "gt" / "objects.json").read_text())
    jb = json.loads((mixed_small / "gt" / "objects.json").read_text())
    assert ja["frames_gt"] == jb["frames_gt"][:3]
    b = generate(tmp_path / "b", "mixed", frames=1, seed=4, size=(320, 96), noise=0.0)
    assert not np.array_equal(_png(b / "image_0/000000.png"), _png(a / "image_0/000000.png"))
    # noise is seeded too
    c1 = generate(tmp_path / "c1", "mixed", frames=1, seed=3, size=(320, 96), noise=2.0)
    c2 = generate(tmp_path / "c2", "mixed", frames=1, seed=3, size=(320, 96), noise=2.0)
    n1, n2 = _png(c1 / "image_0/000000.png"), _png(c2 / "image_0/000000.png")
    assert np.array_equal(n1, n2)
    diff = n1.astype(float) - _png(a / "image_0/000000.png")
    assert 1.0 < diff.std() < 3.0


# ---------------------------------------------------------------------------------------------
# oracle detector


def test_oracle_returns_gt_boxes(mixed_small: Path):
    oracle = OracleDetector(mixed_small)
    gt = read_objects(mixed_small)
    assert oracle.name == "oracle" and "car" in oracle.class_names and "person" in oracle.class_names
    for i in range(len(gt)):
        det = oracle.detect_frame(i)
        assert isinstance(det, Detections)
        want = sorted(o.box_left for o in gt.frame(i) if o.box_left is not None)
        got = sorted(tuple(int(v) for v in b) for b in det.boxes)
        assert got == want
        assert np.all(det.scores == 1.0)
        assert sorted(det.labels()) == sorted(o.label for o in gt.frame(i) if o.box_left is not None)


def test_oracle_masker_keeps_only_the_configured_classes(mixed_small: Path):
    # detector.dynamic_classes limits the oracle as it limits a network: a hidden class is
    # a mover the detector does not know
    from dynastereo.config import Config
    from dynastereo.io import open_sequence
    from dynastereo.masking import build_masker

    seq = open_sequence(mixed_small)
    gt = read_objects(mixed_small)
    i = max(range(len(gt)), key=lambda k: len({o.label for o in gt.frame(k) if o.box_left is not None}))
    assert {"car", "person"} <= {o.label for o in gt.frame(i) if o.box_left is not None}
    for classes, want in ((["person"], {"person"}), (None, {"car", "person"})):
        cfg = Config().with_overrides({"detector.name": "oracle", **({"detector.dynamic_classes": classes}
                                                                   if classes else {})})
        masks = build_masker(cfg, seq.calibration, ground_truth=mixed_small).mask(seq.frame(i))
        labels = {o.label for o in masks.objects}
        assert want <= labels if classes is None else labels == want


def test_oracle_frame_binding(mixed_small: Path):
    oracle = OracleDetector(mixed_small, with_masks=True)
    img5 = _png(mixed_small / "image_0" / "000005.png")
    # unbound: found by the image itself (grey or BGR)
    by_image = oracle.detect(cv2.cvtColor(img5, cv2.COLOR_GRAY2BGR))
    ref = oracle.detect_frame(5)
    assert np.array_equal(by_image.boxes, ref.boxes)
    left, right = oracle.gt_masks(5)
    assert by_image.masks is not None and by_image.masks.shape == (len(ref), 96, 320)
    for m, b in zip(by_image.masks, by_image.boxes):
        ys, xs = np.nonzero(m)
        assert (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1) == tuple(int(v) for v in b)
    # bound: answers for the bound frame whatever the image
    assert np.array_equal(oracle.for_frame(7).detect(img5).boxes, oracle.detect_frame(7).boxes)
    oracle.frame_index = None
    with pytest.raises(InputError):
        oracle.detect(np.zeros((96, 320), np.uint8))
    with pytest.raises(InputError):
        oracle.for_frame(99)
    # filters
    moving = OracleDetector(mixed_small, moving_only=True)
    for i in range(12):
        assert len(moving.detect_frame(i)) == sum(1 for o in read_objects(mixed_small).frame(i) if o.moving and o.box_left)


def test_oracle_is_a_detector_for_the_masker(full_size: Path):
    """The oracle plugs into the real outline masker (unbound: frames found by image)."""
    from dynastereo.io import open_sequence
    from dynastereo.masking.base import Detector
    from dynastereo.masking.maskers import OutlineMasker

    seq = full_size / "mixed" / "sequences" / "00"
    oracle = OracleDetector(seq, min_pixels=100)
    assert isinstance(oracle, Detector)
    masker = OutlineMasker(oracle)
    s = open_sequence(seq)
    ious = []
    for i in (0, 10, 20, 30):
        masks = masker.mask(s.frame(i))
        left, right = oracle.gt_masks(i)
        ids = [o.id for o in oracle.objects(i)]
        for pred, gt in ((masks.left > 0, np.isin(left, ids)), (masks.right > 0, np.isin(right, ids))):
            if gt.any():
                ious.append((pred & gt).sum() / (pred | gt).sum())
    assert ious and float(np.mean(ious)) > 0.4, ious
