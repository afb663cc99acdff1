"""Where objects/world.py puts an object's centre: the top view for static
vehicles, the far end of a vehicle cut by the image's side, the top row of a box cut by
the image's bottom, no measurement from an outline mostly without disparity, and the
measurement (not the filter's position) as the position of an object in full view."""

from __future__ import annotations

import numpy as np
import pytest

from dynastereo.datatypes import MaskMethod, ObjectMask, StereoCalibration, StereoMasks
from dynastereo.objects.world import CLASS_SIZE, WorldObjects

W, H = 640, 240
FX = 400.0
B = 0.5
CALIB = StereoCalibration(np.array([[FX, 0, W / 2], [0, FX, H / 2], [0, 0, 1]]), B, W, H)


def _frame(objs: list[dict]) -> StereoMasks:
    """One frame of flat objects: per object a dict with ``label``, ``track``, ``moving``
    and either ``face`` (camera-frame centre of a face square to the view, ``w``, ``h``)
    or ``side`` (a face along the view: ``x``, ``z0``, ``z1``, centre height ``y``, ``h``);
    ``holes``: the share of its pixels without a disparity."""
    labels = np.zeros((H, W), np.int32)
    disp = np.zeros((H, W), np.float32)
    out = []
    for k, o in enumerate(objs):
        if "face" in o:
            X, w, h = o["face"], o["w"], o["h"]
            u0, u1 = FX * (X[0] - w / 2) / X[2] + W / 2, FX * (X[0] + w / 2) / X[2] + W / 2
            v0, v1 = FX * (X[1] - h / 2) / X[2] + H / 2, FX * (X[1] + h / 2) / X[2] + H / 2
            x0, x1 = max(int(round(u0)), 0), min(int(round(u1)), W)
            y0, y1 = max(int(round(v0)), 0), min(int(round(v1)), H)
            labels[y0:y1, x0:x1] = k + 1
            disp[y0:y1, x0:x1] = FX * B / X[2]
        else:  # a plane x = const from z0 to z1, column by column
            x, z0, z1, y, h = o["x"], o["z0"], o["z1"], o["y"], o["h"]
            us = np.arange(W)
            with np.errstate(divide="ignore"):
                z = FX * x / (us + 0.5 - W / 2)
            cols = np.flatnonzero((z >= z0) & (z <= z1))
            x0, x1 = int(cols.min()), int(cols.max()) + 1
            y0, y1 = H, 0
            for u in cols:
                a = max(int(round(FX * (y - h / 2) / z[u] + H / 2)), 0)
                b = min(int(round(FX * (y + h / 2) / z[u] + H / 2)), H)
                labels[a:b, u] = k + 1
                disp[a:b, u] = FX * B / z[u]
                y0, y1 = min(y0, a), max(y1, b)
        if o.get("holes"):
            ys, xs = np.nonzero(labels == k + 1)
            drop = np.random.default_rng(0).random(len(ys)) < o["holes"]
            disp[ys[drop], xs[drop]] = 0.0
        d = float(np.median(disp[(labels == k + 1) & (disp > 0)])) if ((labels == k + 1) & (disp > 0)).any() else 0.0
        m = ObjectMask((x0, y0, x1, y1), o["label"], 0.9, MaskMethod.OUTLINE, d, int((labels == k + 1).sum()), 0,
                       track_id=o.get("track", -1))
        m.moving = o.get("moving")
        out.append(m)
    return StereoMasks(labels.astype(np.uint8), labels.astype(np.uint8), out, labels_left=labels,
                       labels_right=labels, box_disparity=disp)


def test_static_vehicle_centre_from_the_top_view():
    """A parked car judged static, its rear face seen: the centre is half the class
    length behind the face along the heading (the camera's axis) and half its width
    beyond the face's near edge; the box's row at the face's depth gives its height."""
    L = CLASS_SIZE["car"][2]
    s = WorldObjects(CALIB).update(_frame([dict(label="car", track=2, moving=False, face=np.array([3.5, 0.5, 15.0]),
                                                w=1.8, h=1.5)]), np.eye(4), True, 0.0)[0]
    assert s.camera[2] == pytest.approx(15.0 + L / 2, abs=0.1)
    assert s.camera[0] == pytest.approx(3.5, abs=0.25)  # the face's 10th percentile + w / 2
    assert s.camera[1] == pytest.approx(0.5, abs=0.02)


def test_vehicle_cut_by_the_image_side_from_its_far_end():
    """A static car alongside, its near end out of the image's left side: along the
    heading its centre is the far end seen minus half the class length; across, the
    side seen plus half the class width (the 95th percentile of the pixels' depths falls
    short of the far end by a few cm here: their density falls as 1 / z^3)."""
    Wc, _, L = CLASS_SIZE["car"]
    x, z1 = -6.0, 9.4
    f = _frame([dict(label="car", track=4, moving=False, side=True, x=x, z0=z1 - L, z1=z1, y=0.9, h=1.5)])
    assert f.objects[0].box[0] == 0  # cut
    s = WorldObjects(CALIB).update(f, np.eye(4), True, 0.0)[0]
    assert s.camera[2] == pytest.approx(z1 - L / 2, abs=0.2)
    assert s.camera[0] == pytest.approx(x - Wc / 2, abs=0.1)


def test_box_cut_by_the_image_bottom_hangs_from_its_top_row():
    """A person 4 m ahead: feet below the image's bottom; the centre is half the class
    height below the head, not at the box's (cut) centre row."""
    Hc = CLASS_SIZE["person"][1]
    f = _frame([dict(label="person", track=5, moving=True, face=np.array([0.3, 0.5, 4.0]), w=0.5, h=Hc)])
    assert f.objects[0].box[3] == H
    s = WorldObjects(CALIB).update(f, np.eye(4), True, 0.0)[0]
    assert s.camera[1] == pytest.approx(0.5, abs=0.05)
    assert s.camera[2] == pytest.approx(4.0 + CLASS_SIZE["person"][2] / 2, abs=0.1)


def test_outline_mostly_without_disparity_gives_no_measurement():
    face = dict(label="car", track=1, face=np.array([0.0, 0.5, 12.0]), w=1.8, h=1.5)
    wo = WorldObjects(CALIB)
    assert wo.update(_frame([dict(face, holes=0.85)]), np.eye(4), True, 0.0) == [None]
    assert wo.update(_frame([dict(face, holes=0.5)]), np.eye(4), True, 0.1)[0] is not None


def test_full_view_position_is_the_measurement_a_cut_one_the_filters():
    """A parked car seen 10 frames at the same place, then 1 m farther (within the gate):
    in full view the position jumps with the measurement (the filter would move a
    fraction); cut by the image's side, the filter's position moves less."""
    L = CLASS_SIZE["car"][2]
    full = dict(label="car", track=1, moving=False, w=1.8, h=1.5)
    side = dict(label="car", track=2, moving=False, side=True, x=-6.0, y=0.9, h=1.5)
    wo = WorldObjects(CALIB)
    for f in range(10):
        wo.update(_frame([dict(full, face=np.array([0.0, 0.5, 12.0])), dict(side, z0=9.4 - L, z1=9.4)]),
                  np.eye(4), True, 0.1 * f)
    s_full, s_cut = wo.update(_frame([dict(full, face=np.array([0.0, 0.5, 13.0])), dict(side, z0=10.4 - L, z1=10.4)]),
                              np.eye(4), True, 1.0)
    assert s_full.camera[2] == pytest.approx(13.0 + L / 2, abs=0.1)
    assert s_full.speed < 0.3 and s_full.updates == 11  # the filter still runs (velocity)
    assert s_cut.camera[2] < 9.4 - L / 2 + 0.8


def test_crossing_vehicle_heading_from_its_points():
    """A truck crossing 12 m ahead, its side in view and its velocity not yet known: the
    heading comes from its points (they spread 8 m across the view), so its centre is
    half its width behind the side -- not half its length behind, as the camera's axis
    for a heading would have it.  A car seen from behind (points spread over its width
    only) keeps the heading it had."""
    Wt = CLASS_SIZE["truck"][0]
    f = _frame([dict(label="truck", track=3, moving=True, face=np.array([0.0, 0.2, 12.0]), w=8.0, h=3.0),
                dict(label="car", track=4, moving=True, face=np.array([-4.5, 0.5, 9.0]), w=1.8, h=1.5)])
    truck, car = WorldObjects(CALIB).update(f, np.eye(4), True, 0.0)
    assert abs(truck.heading[0]) == pytest.approx(1.0, abs=0.01)
    assert truck.camera[2] == pytest.approx(12.0 + Wt / 2, abs=0.15)
    assert truck.camera[0] == pytest.approx(0.0, abs=0.15)
    assert car.heading[2] == pytest.approx(1.0, abs=1e-6)


def test_cut_vehicle_background_in_its_outline_stays_bounded():
    """An outline that takes in background past the end seen (a real detector's): the far
    end's percentile runs off, but the centre stays within half the length of the other
    visible end (here the car's true centre is 7.2 m ahead; unbounded, 20 m)."""
    L = CLASS_SIZE["car"][2]
    f = _frame([dict(label="car", track=4, moving=False, side=True, x=-6.0, z0=9.4 - L, z1=9.4, y=0.9, h=1.5)])
    ys, xs = np.nonzero(f.labels_left == 1)
    far = xs >= np.percentile(xs, 85)  # the columns next to the far end: background 25 m away
    f.box_disparity[ys[far], xs[far]] = FX * B / 25.0
    s = WorldObjects(CALIB).update(f, np.eye(4), True, 0.0)[0]
    assert 7.0 < s.camera[2] < 8.0 + L / 2  # the near visible end (7.5 m) + L / 2 at most


def test_an_object_without_a_measurement_coasts_on_its_filter():
    """A car driving away at 5 m/s, measured for 12 frames; then its outline has almost
    no disparity: its filter's prediction (flagged ``predicted``), still moving on at its
    speed; once more than ``COAST_S`` has passed since its last measurement: no position."""
    from dynastereo.objects.world import COAST_S

    car = dict(label="car", track=3, moving=True, w=1.8, h=1.5)
    wo = WorldObjects(CALIB)
    for f in range(12):
        s = wo.update(_frame([dict(car, face=np.array([0.0, 0.5, 10.0 + 0.5 * f]))]), np.eye(4), True, 0.1 * f)[0]
    assert s is not None and not s.predicted and s.speed == pytest.approx(5.0, abs=0.5)
    z_last = s.camera[2]
    p = wo.update(_frame([dict(car, face=np.array([0.0, 0.5, 16.0]), holes=0.9)]), np.eye(4), True, 1.2)[0]
    assert p is not None and p.predicted and p.to_dict()["predicted"] is True
    assert p.camera[2] == pytest.approx(z_last + 0.5, abs=0.15)  # one frame on at 5 m/s
    late = 1.1 + COAST_S + 0.1
    assert wo.update(_frame([dict(car, face=np.array([0.0, 0.5, 16.0]), holes=0.9)]), np.eye(4), True, late) == [None]
    assert "predicted" not in s.to_dict()


def test_a_static_object_cut_by_the_side_keeps_its_last_full_view():
    """A parked car measured in full view, then -- the camera 9 m on -- cut by the image's
    side, with a far end 1 m off (a measurement biased by the end it cannot see), then
    without a measurement: both times it stays where its last full view put it in the
    world.  Judged moving once, it forgets that view."""
    car = dict(label="car", track=7, moving=False, w=1.8, h=1.5)
    wo = WorldObjects(CALIB)
    for f in range(5):
        s = wo.update(_frame([dict(car, face=np.array([-5.0, 0.9, 14.0]))]), np.eye(4), True, 0.1 * f)[0]
    seen = s.world.copy()
    pose = np.eye(4)
    pose[2, 3] = 9.0
    cut = _frame([dict(car, side=True, x=-5.1, z0=5.0, z1=10.4, y=0.9, h=1.5)])
    assert cut.objects[0].box[0] == 0
    alone = WorldObjects(CALIB).update(cut, pose, True, 0.5)[0]  # what the cut view alone gives
    assert np.linalg.norm(alone.world - seen) > 0.5
    s = wo.update(cut, pose, True, 0.5)[0]
    assert s.world == pytest.approx(seen, abs=1e-9)
    assert s.camera == pytest.approx(seen - pose[:3, 3], abs=1e-9)
    p = wo.update(_frame([dict(car, face=np.array([-5.0, 0.9, 5.0]), holes=0.9)]), pose, True, 0.6)[0]
    assert p.predicted and p.world == pytest.approx(seen, abs=1e-9)
    wo.update(_frame([dict(car, moving=None, face=np.array([-5.0, 0.9, 5.5]))]), pose, True, 0.7)
    m = wo.update(cut, pose, True, 0.8)[0]
    assert np.linalg.norm(m.world - seen) > 1e-3  # the filter's position now


def test_a_sliver_with_a_nearer_objects_disparity_gives_no_measurement():
    """A box a few pixels across beside a truck 4.5 m away, its pixels carrying the
    truck's disparity (stereo matching fattens a near object's edges): at that depth a
    car would be 133 px tall, the box is 12 -- no measurement, where it would have put a
    car 20 m away at 4.5 m.  A whole car 20 m away, and a person whose box is cut by the
    image's bottom, are measured."""
    sliver = _frame([dict(label="car", track=1, face=np.array([-2.0, 0.2, 20.0]), w=0.15, h=0.55)])
    sliver.box_disparity[sliver.labels_left == 1] = FX * B / 4.5
    assert sliver.objects[0].box[3] - sliver.objects[0].box[1] == 12
    assert WorldObjects(CALIB).update(sliver, np.eye(4), True, 0.0) == [None]
    whole = _frame([dict(label="car", track=2, face=np.array([-2.0, 0.5, 20.0]), w=1.8, h=1.5)])
    assert WorldObjects(CALIB).update(whole, np.eye(4), True, 0.0)[0].camera[2] == pytest.approx(20.0 + 2.2, abs=0.3)
    low = _frame([dict(label="person", track=3, face=np.array([0.3, 1.0, 3.0]), w=0.5, h=0.4)])  # feet and legs only
    assert low.objects[0].box[3] == H
    assert WorldObjects(CALIB).update(low, np.eye(4), True, 0.0)[0] is not None
