"""Every object's track in the world (objects/world.py), its outputs (objects.jsonl,
objects_tracks.csv, rerun, HTML report, ROS MarkerArray), the static map export
(--save-cloud) and the raw 0001 reference labels of the motion test."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from dynastereo.objects.world import TRACKS_NAME, ObjectPaths, WorldObjects, read_tracks
from dynastereo.datatypes import MaskMethod, ObjectMask, StereoCalibration, StereoMasks

W, H = 640, 240
FX = 400.0
B = 0.5
CALIB = StereoCalibration(np.array([[FX, 0, W / 2], [0, FX, H / 2], [0, 0, 1]]), B, W, H)
LABELS = Path(__file__).parent / "data" / "raw0001_motion_labels.json"
runner = CliRunner()


def _masks(objs: list[tuple[str, int, np.ndarray, float, float]]) -> StereoMasks:
    """One frame: per object (label, track, camera-frame centre of its rear face, width,
    height), a flat rectangle at the face's disparity (labels, box disparity)."""
    labels = np.zeros((H, W), np.int32)
    disp = np.zeros((H, W), np.float32)
    out = []
    for k, (label, track, X, w, h) in enumerate(objs):
        u0, u1 = FX * (X[0] - w / 2) / X[2] + W / 2, FX * (X[0] + w / 2) / X[2] + W / 2
        v0, v1 = FX * (X[1] - h / 2) / X[2] + H / 2, FX * (X[1] + h / 2) / X[2] + H / 2
        x0, x1, y0, y1 = (int(round(v)) for v in (u0, u1, v0, v1))
        labels[y0:y1, x0:x1] = k + 1
        d = FX * B / X[2]
        disp[y0:y1, x0:x1] = d
        out.append(ObjectMask((x0, y0, x1, y1), label, 0.9, MaskMethod.OUTLINE, d, (x1 - x0) * (y1 - y0), 0,
                              track_id=track))
    return StereoMasks(labels.astype(np.uint8), labels.astype(np.uint8), out, labels_left=labels,
                       labels_right=labels, box_disparity=disp)


def test_positions_speed_and_uncertainty_on_exact_disparity():
    """A car driving ahead at 5 m/s (we stand still), a parked car to the right: the centre
    is half a car length behind the face seen; the speed converges; the parked car keeps
    still; positions come back in the world frame through the pose."""
    wo = WorldObjects(CALIB)
    pose = np.eye(4)
    pose[:3, 3] = (10.0, 0.0, 5.0)  # the camera stands at (10, 0, 5) in the world
    states = None
    for f in range(25):
        t = 0.1 * f
        front = np.array([0.0, 0.5, 12.0 + 5.0 * t])  # rear face centre (camera frame)
        parked = np.array([3.5, 0.5, 15.0])
        states = wo.update(_masks([("car", 1, front, 1.8, 1.5), ("car", 2, parked, 1.8, 1.5)]), pose, True, t)
    mover, still = states
    # the car's centre: its rear face + 4.4 / 2 (the class length) along the view, in the world
    want = pose[:3, 3] + np.array([0.0, 0.5, 12.0 + 5.0 * 2.4 + 2.2])
    assert np.linalg.norm(mover.world - want) < 0.35
    assert mover.speed == pytest.approx(5.0, abs=0.3)
    assert abs(mover.velocity[2] - 5.0) < 0.3 and abs(mover.velocity[0]) < 0.3 and abs(mover.velocity[1]) < 0.1
    assert 0.0 < mover.speed_sigma < 2.0 and mover.updates == 25  # 31 m away: sigma_r ~ Z^2 sigma_d / bf = 2.4 m
    assert still.speed < 0.3
    # off-axis, the half length is added along the view ray: 0.5 m sideways of the box centre here
    assert np.linalg.norm(still.camera - np.array([3.5, 0.5, 15.0 + 2.2])) < 0.6
    # the uncertainty grows with the distance (depth noise ~ Z^2)
    assert mover.distance > still.distance and mover.world_sigma[2] > 0
    # on the objects themselves, and in objects.jsonl's record
    d = mover.to_dict()
    assert set(d) >= {"world", "world_sigma", "velocity", "velocity_sigma", "speed", "speed_sigma", "extent", "camera"}
    # a frame without a pose: no states, the filter keeps its state
    m = _masks([("car", 1, np.array([0.0, 0.5, 25.0]), 1.8, 1.5)])
    assert wo.update(m, pose, ok=False, stamp=2.5) == [None] and m.objects[0].world is None
    assert m.objects[0].to_dict().get("world") is None


def test_the_motion_tests_speed_counts_by_its_own_sigma():
    """A walker crossing at 1 m/s whose motion-test speed reads 15 m/s (the flow of a far
    object is mostly depth noise): with the motion test's sigma of it (10 m/s) the filter's
    speed stays with the positions; given as exact (no sigma: 0.3 m/s) it follows the 15."""

    def speed(sigma: float | None) -> float:  # the filter's, median over frames 5-19
        wo = WorldObjects(CALIB)
        out = []
        for f in range(20):
            m = _masks([("person", 4, np.array([-2.0 + 0.1 * f, 0.2, 12.0]), 0.6, 1.7)])
            m.objects[0].moving, m.objects[0].speed_mps, m.objects[0].speed_sigma_mps = True, 15.0, sigma
            out.append(wo.update(m, np.eye(4), True, 0.1 * f)[0].speed)
        return float(np.median(out[5:]))

    assert speed(10.0) == pytest.approx(1.0, abs=0.5) and speed(None) > 8.0


def test_forty_tracks_and_forgotten_ones():
    """More tracks than the filters' table starts with (32): each its own filter; a track
    unseen for longer than ``max_gap`` (2 s) is forgotten -- its id seen again starts anew."""
    grid = [(x, y) for y in (-1.2, -0.4, 0.4, 1.2, 2.0) for x in np.arange(-2.8, 3.0, 0.8)]  # 8 x 5, apart
    objs = [("person", 100 + i, np.array([x, y, 10.0]), 0.6, 0.6) for i, (x, y) in enumerate(grid)]
    wo = WorldObjects(CALIB)
    for f in range(3):
        s = wo.update(_masks(objs), np.eye(4), True, 0.1 * f)
    assert len(s) == 40 and all(x is not None and x.updates == 3 and x.speed < 0.5 for x in s)
    assert sorted(x.track for x in s) == list(range(100, 140))
    # a frame 2.5 s on with five new ids only: the forty are forgotten after it; then five
    # of them again beside the new five: those start anew, the new ones go on
    new = [(lb, t + 1000, X, w, h) for lb, t, X, w, h in objs[5:10]]
    wo.update(_masks(new), np.eye(4), True, 2.5)
    s = wo.update(_masks(objs[:5] + new), np.eye(4), True, 2.6)
    assert [x.updates for x in s] == [1] * 5 + [2] * 5


def test_no_disparity_no_track_and_restart():
    wo = WorldObjects(CALIB)
    m = _masks([("person", -1, np.array([1.0, 0.2, 8.0]), 0.6, 1.7), ("car", 3, np.array([-2.0, 0.5, 10.0]), 1.8, 1.5)])
    m.box_disparity[m.labels_left == 2] = 0.0  # the car has no disparity
    s = wo.update(m, np.eye(4), True, 0.0)
    assert s[0] is not None and s[0].velocity is None and s[1] is None  # untracked: position only
    # a track id that jumps to another object far away restarts its filter (no huge speed)
    wo.update(_masks([("car", 7, np.array([0.0, 0.5, 10.0]), 1.8, 1.5)]), np.eye(4), True, 0.1)
    wo.update(_masks([("car", 7, np.array([0.0, 0.5, 10.0]), 1.8, 1.5)]), np.eye(4), True, 0.2)
    s = wo.update(_masks([("car", 7, np.array([8.0, 0.5, 30.0]), 1.8, 1.5)]), np.eye(4), True, 0.3)
    assert wo.restarts == 1 and s[0].updates == 1 and s[0].speed < 1e-6


def test_outside_movers_and_paths():
    wo = WorldObjects(CALIB)
    m = _masks([("car", 1, np.array([0.0, 0.5, 12.0]), 1.8, 1.5)])
    m.objects[0].moving = True
    wo.update(m, np.eye(4), True, 0.0)
    c = m.objects[0].world.world
    pts = np.array([c, c + (0.5, 0.2, 1.0), c + (5.0, 0.0, 0.0), c + (0.0, 0.0, 10.0)])
    assert wo.outside_movers(pts).tolist() == [False, False, True, True]
    paths = ObjectPaths()
    paths.add(m.objects)
    paths.add(m.objects)
    (t, p, moving), = paths.paths()
    assert t == 1 and p.shape == (2, 3) and moving is True


def _read_ply(path: Path) -> np.ndarray:
    """A plain PLY reader (binary little endian, float x y z), independent of the writer."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    head = data[:end].decode("ascii").splitlines()
    assert head[0] == "ply" and head[1] == "format binary_little_endian 1.0"
    n = next(int(h.split()[2]) for h in head if h.startswith("element vertex"))
    props = [h.split()[2] for h in head if h.startswith("property")]
    assert props == ["x", "y", "z"]
    body = data[end:]
    assert len(body) == 12 * n
    return np.array(struct.unpack(f"<{3 * n}f", body), np.float64).reshape(n, 3)


@pytest.fixture(scope="module")
def convoy_run(tmp_path_factory):
    from dynastereo.synth import generate

    seq = generate(tmp_path_factory.mktemp("convoy"), "convoy", frames=14, seed=3, size=(480, 144))
    out = tmp_path_factory.mktemp("run") / "run"
    r = runner.invoke(__import__("dynastereo.cli.main", fromlist=["app"]).app,
                      ["run", str(seq), "--out", str(out), "--detector", "oracle", "--save-cloud",
                       str(out / "static.ply"), "--report"])
    assert r.exit_code == 0, r.output
    return seq, out


def test_run_writes_objects_in_the_world(convoy_run):
    from dynastereo.synth import read_objects

    seq, out = convoy_run
    recs = [json.loads(line) for line in (out / "objects.jsonl").read_text().splitlines()]
    with_world = [o for r in recs for o in r["objects"] if "world" in o]
    assert len(with_world) >= 10
    assert all(len(o["world"]) == 3 and len(o["extent"]) == 3 for o in with_world)
    assert sum("velocity" in o for o in with_world) >= 10
    # the track file: one row per object-frame with a world position
    tracks = read_tracks(out / TRACKS_NAME)
    assert sum(len(t["frame"]) for t in tracks.values()) == len(with_world)
    # accuracy against the exact object centres, in the frame's camera (oracle boxes)
    gt = read_objects(seq)
    err = []
    for r in recs:
        g = {o.id: o for o in gt.frame(r["frame"])}
        for o in r["objects"]:
            go = g.get(o["track"])
            if go is not None and "camera" in o and go.distance < 30:
                err.append(np.linalg.norm(np.subtract(o["camera"], go.position_cam)))
    assert len(err) >= 10 and np.median(err) < 1.0
    # the HTML report shows their paths
    page = (out / "report.html").read_text()
    assert "<h2>Objects in the world</h2>" in page and 'alt="objects&#x27; paths, top view"' in page


def test_run_with_the_objects_own_matching(convoy_run, tmp_path):
    """``--object-block 0`` (objects.block_size; default 11: the outlines matched again)
    moves the positions, not the masks: the same objects masked in every frame, their
    positions from the masker's disparity, near the default's own matching."""
    from dynastereo.synth import read_objects

    seq, base = convoy_run
    app = __import__("dynastereo.cli.main", fromlist=["app"]).app
    out = tmp_path / "masker"
    r = runner.invoke(app, ["run", str(seq), "--out", str(out), "--detector", "oracle", "--object-block", "0"])
    assert r.exit_code == 0, r.output
    read = lambda d: [json.loads(line) for line in (d / "objects.jsonl").read_text().splitlines()]  # noqa: E731
    a, b = read(base), read(out)
    assert [[o["masked"] for o in r["objects"]] for r in a] == [[o["masked"] for o in r["objects"]] for r in b]
    moved = [np.linalg.norm(np.subtract(p["camera"], q["camera"])) for ra, rb in zip(a, b)
             for p, q in zip(ra["objects"], rb["objects"]) if "camera" in p and "camera" in q]
    assert len(moved) >= 10 and max(moved) > 0.01
    gt = read_objects(seq)
    err = [np.linalg.norm(np.subtract(o["camera"], g.position_cam)) for r in b
           for o in r["objects"] for g in gt.frame(r["frame"]) if g.id == o["track"] and "camera" in o and g.distance < 30]
    assert len(err) >= 10 and np.median(err) < 1.0
    bad = runner.invoke(app, ["run", str(seq), "--out", str(tmp_path / "bad"), "--object-block", "4"])
    assert bad.exit_code != 0 and "objects.block_size must be 0" in bad.output


def test_save_cloud_loads_back_without_movers(convoy_run):
    _, out = convoy_run
    pts = _read_ply(out / "static.ply")
    run = json.loads((out / "run.json").read_text())
    assert 100 < len(pts) <= run["map_points"]
    assert np.isfinite(pts).all()


def test_object_markers_serialize_for_ros1_and_ros2():
    from dynastereo.ros.messages import OUTPUT_TOPICS, OUTPUT_TYPES, RosbagsBuilder

    assert OUTPUT_TYPES["objects"] == "visualization_msgs/MarkerArray" and OUTPUT_TOPICS["objects"]
    wo = WorldObjects(CALIB)
    m = _masks([("car", 4, np.array([0.0, 0.5, 12.0]), 1.8, 1.5), ("person", 9, np.array([2.0, 0.2, 8.0]), 0.6, 1.7)])
    m.objects[0].moving, m.objects[1].moving = True, False
    paths = ObjectPaths()
    for t in range(3):
        wo.update(m, np.eye(4), True, 0.1 * t)
        paths.add(m.objects)
    for ros1 in (True, False):
        b = RosbagsBuilder(ros1)
        msg = b.object_markers(m.objects, 123_000_000, "odom", 2, paths.paths())
        raw = b.serialize(msg)
        back = (b.typestore.deserialize_ros1 if ros1 else b.typestore.deserialize_cdr)(
            raw, "visualization_msgs/msg/MarkerArray")
        kinds = [(mk.ns, mk.type, mk.action) for mk in back.markers]
        assert kinds[0][2] == 3  # DELETEALL first
        assert ("objects", 1, 0) in kinds and ("labels", 9, 0) in kinds and ("paths", 4, 0) in kinds
        cube = next(mk for mk in back.markers if mk.ns == "objects" and mk.id == 4)
        assert cube.color.r > 0.8 and cube.color.g < 0.3  # moving: red
        assert cube.pose.position.z == pytest.approx(m.objects[0].world.world[2], abs=1e-6)
        label = next(mk for mk in back.markers if mk.ns == "labels" and mk.id == 9)
        assert label.text.startswith("person #9")


def test_raw0001_reference_labels():
    """The committed labels (bench_objects.py --make-labels; checked by eye on overlays):
    the tram, the cyclists and the passing car move, the parked rows on the left stand."""
    lab = json.loads(LABELS.read_text())
    by_id = {o["id"]: o for o in lab["objects"]}
    assert all(len(o["frames"]) == len(o["boxes"]) == len(o["pixels"]) for o in lab["objects"])
    tram = [o for o in lab["objects"] if o["label"] == "bus" and o["moving"]]
    assert tram and max(o["moved_m"] for o in tram) > 20
    assert any(o["label"] == "bicycle" and o["moving"] for o in lab["objects"])
    assert sum(o["label"] == "person" and o["moving"] is True for o in lab["objects"]) >= 5  # the cyclists
    assert any(o["label"] == "car" and o["moving"] and o["frames"][0] >= 60 for o in lab["objects"])  # passing car
    parked = [o for o in lab["objects"] if o["label"] == "car" and o["frames"][0] < 20 and max(o["pixels"]) > 5000]
    assert len(parked) >= 6 and all(o["moving"] is False for o in parked)
    # no object labelled static goes faster than the moving threshold
    th = lab["thresholds"]["moving_mps"]
    assert all(o["speed"] < th for o in lab["objects"] if o["moving"] is False)
    assert all(o["speed"] > th for o in lab["objects"] if o["moving"] is True)
    assert by_id  # ids unique
    assert len(by_id) == len(lab["objects"])


def test_verdict_scoring(tmp_path):
    """The scoring of a run's verdicts against the labels (benchmarks/bench_objects.py)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
    from bench_objects import score_verdicts

    lab = {"objects": [
        {"id": 1, "label": "car", "moving": True, "frames": [0, 1, 2], "boxes": [[0, 0, 40, 40]] * 3,
         "pixels": [900] * 3},
        {"id": 2, "label": "car", "moving": False, "frames": [0, 1, 2], "boxes": [[100, 0, 140, 40]] * 3,
         "pixels": [900] * 3}]}
    (tmp_path / "labels.json").write_text(json.dumps(lab))
    run = tmp_path / "run"
    run.mkdir()
    rows = []
    for f, (v1, v2) in enumerate([(None, None), (True, False), (True, True)]):
        rows.append({"frame": f, "objects": [
            {"box": [1, 1, 40, 40], "moving": v1, "masked": v1 is not False},
            {"box": [100, 0, 139, 41], "moving": v2, "masked": v2 is not False}]})
    (run / "objects.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    s = score_verdicts(run, tmp_path / "labels.json")
    assert (s["right"], s["undecided"], s["wrong"]) == (3, 2, 1)
    assert s["right_of_decided"] == pytest.approx(0.75)
    assert s["movers"] == 1 and s["movers_masked_within_3"] == 1
    assert (s["static_frames"], s["static_unmasked"]) == (3, 1)


def test_bag_run_writes_object_markers(convoy_run, models_dir, tmp_path):
    """``run --bag``: ``/dynastereo/objects`` (MarkerArray) once a frame, boxes in ``odom``."""
    from dynastereo.api import run_bag
    from dynastereo.config import Config
    from dynastereo.io import KittiSequence
    from dynastereo.ros import export_bag
    from dynastereo.ros.bags import bag_topics, read_messages

    seq, _ = convoy_run
    src = export_bag(KittiSequence(seq), tmp_path / "s.mcap", "mcap", frames=list(range(8)))
    res = run_bag(src.path, tmp_path / "out", Config(), outputs="odometry,objects", models_dir=models_dir)
    topics = bag_topics(res.output_bag)
    assert topics["/dynastereo/objects"] == ("visualization_msgs/msg/MarkerArray", 8)
    arrays = [m for _, _, m in read_messages(res.output_bag, ["/dynastereo/objects"])]
    cubes = [mk for a in arrays for mk in a.markers if mk.ns == "objects"]
    assert len(cubes) >= 8 and all(mk.header.frame_id == "odom" and mk.scale.z > 0 for mk in cubes)
    recs = [json.loads(line) for line in (tmp_path / "out" / "objects.jsonl").read_text().splitlines()]
    assert len(cubes) == sum("world" in o for r in recs for o in r["objects"])
