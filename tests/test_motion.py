"""The per-object motion test (``objects/motion``): known answers.

* geometry alone (no images): a parked object, one crossing at 1 m/s 15 m ahead and
  one driving 6 m ahead at the camera's 10 m/s, seen by a camera driving forward; their
  stereo points with pixel noise -> parked static, the other two moving, speeds right;
* the whole pipeline on a short synthetic ``convoy`` (oracle boxes): the truck that
  fills the view and drives with the camera is judged moving and stays masked, parked
  cars are judged static and left to SLAM; ``objects.jsonl`` carries the contract;
* ``motion.mode: all`` (the thesis: every detection masked) gives exactly the
  trajectory of the masker's masks fed straight to the SLAM;
* map points on an object that turns moving leave the map (``System.forget_region``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dynastereo.api import mask_sequence, run_sequence
from dynastereo.config import Config, MotionConfig
from dynastereo.errors import ConfigError
from dynastereo.objects.motion import FrameFlow, MotionJudge, ObjectFlow
from dynastereo.synth import generate, read_objects
from dynastereo.datatypes import MaskMethod, ObjectMask, StereoCalibration, StereoMasks

pytestmark = pytest.mark.usefixtures("quiet_slam")

CALIB = StereoCalibration(np.array([[370.0, 0, 320.0], [0, 370.0, 96.0], [0, 0, 1]]), 0.54, 640, 192)
DT = 0.1


def _uvd(X: np.ndarray, T_wc: np.ndarray, rng, sigma_px=0.3, sigma_d=0.2):
    """(uv, d) with noise of world points ``X`` (n, 3) seen from camera ``T_wc``."""
    Xc = (X - T_wc[:3, 3]) @ T_wc[:3, :3]
    K = CALIB.K
    uv = np.stack([K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 2], K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]], axis=1)
    d = CALIB.bf / Xc[:, 2]
    return uv + rng.normal(0, sigma_px, uv.shape), d + rng.normal(0, sigma_d, d.shape)


def _camera(k: int, speed: float = 10.0) -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = speed * DT * k  # driving forward along the optical axis
    return T


def _objects() -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """track -> (points on the object at time 0 (n, 3), velocity m/s) in the world."""
    rng = np.random.default_rng(0)

    def blob(centre, size):
        return np.asarray(centre) + rng.uniform(-0.5, 0.5, (30, 3)) * np.asarray(size)

    return {
        1: (blob([-3.0, 0.5, 12.0], [1.8, 1.4, 4.0]), np.zeros(3)),  # parked on the left
        2: (blob([2.0, 0.5, 15.0], [0.6, 1.7, 0.5]), np.array([1.0, 0.0, 0.0])),  # crossing at 1 m/s
        3: (blob([0.0, 0.2, 6.0], [2.0, 2.0, 0.3]), np.array([0.0, 0.0, 10.0])),  # ahead, at the camera's speed
    }


def _masks(k: int, flows: list[ObjectFlow]) -> StereoMasks:
    """Masks of 3 objects: object i (track i + 1) owns the image's i-th column band."""
    labels = np.zeros((192, 640), np.int32)
    for i in range(3):
        labels[:, i * 200:(i + 1) * 200] = i + 1
    objs = [ObjectMask((i * 200.0, 0.0, (i + 1) * 200.0, 192.0), "car", 1.0, MaskMethod.OUTLINE, 10.0, 1, 1, i + 1)
            for i in range(3)]
    m = (labels > 0).astype(np.uint8) * 255
    return StereoMasks(m, m.copy(), objs, labels_left=labels, labels_right=labels, flow=FrameFlow(k, DT, flows))


def _judge_known_motions(frames: int = 6) -> tuple[MotionJudge, StereoMasks]:
    """A judge fed ``frames`` frames of the three objects of :func:`_objects` (noisy)."""
    rng = np.random.default_rng(1)
    judge = MotionJudge(MotionConfig(), CALIB)
    objects = _objects()
    for k in range(frames):
        flows = []
        if k > 0:
            for tr, (X, v) in objects.items():
                uv0, d0 = _uvd(X + v * DT * (k - 1), _camera(k - 1), rng)
                uv1, d1 = _uvd(X + v * DT * k, _camera(k), rng)
                flows.append(ObjectFlow(tr, tr - 1, uv0, d0, uv1, d1))
        masks = _masks(k, flows)
        slam_masks = judge.select(masks)
        if k == 0:  # nothing judged yet: everything masked (the safe default)
            assert slam_masks is masks and all(o.masked and o.moving is None for o in masks.objects)
        judge.update(masks, _camera(k)[:3], ok=True)
    return judge, masks


def test_known_motions_are_judged_from_geometry() -> None:
    judge, masks = _judge_known_motions()
    assert [o.moving for o in masks.objects] == [False, True, True]
    speeds = [o.speed_mps for o in masks.objects]
    assert speeds[0] < 0.3 and abs(speeds[1] - 1.0) < 0.3 and abs(speeds[2] - 10.0) < 1.0
    # each with its sigma along the velocity (stereo and pose noise), the truth within 2 of them
    sig = [o.speed_sigma_mps for o in masks.objects]
    assert all(0.0 < v < 2.0 for v in sig)
    assert all(abs(sp - true) <= 2.0 * v for sp, true, v in zip(speeds, (0.0, 1.0, 10.0), sig))
    # the parked car's pixels are left to SLAM in both images, the movers stay masked
    out = judge.select(masks)
    assert [o.masked for o in masks.objects] == [False, True, True]
    assert not out.left[:, :200].any() and not out.right[:, :200].any()
    assert out.left[:, 200:600].all() and out.right[:, 200:600].all()


def test_a_second_detection_of_a_judged_object_takes_its_verdict() -> None:
    """The detector names the parked car 'car' and 'truck' (two boxes, the second under a
    new track id): the duplicate is left to SLAM with it; a person in the same box, or a
    vehicle box overlapping less than ``duplicate_iou``, stays undecided (masked)."""
    judge, masks = _judge_known_motions()
    assert [o.moving for o in masks.objects] == [False, True, True]
    labels = masks.labels_left.copy()
    extra = [  # (box, label, its pixels (rows, cols))
        ((2.0, 0.0, 200.0, 190.0), "truck", (slice(0, 60), slice(2, 200))),  # the parked car again
        ((200.0, 4.0, 398.0, 192.0), "bus", (slice(0, 60), slice(200, 400))),  # the crosser again
        ((0.0, 0.0, 200.0, 192.0), "person", (slice(60, 120), slice(0, 200))),  # another class group
        ((0.0, 0.0, 120.0, 192.0), "car", (slice(120, 192), slice(0, 100))),  # IoU 0.6 with the parked car
    ]
    objs = list(masks.objects)
    for t, (box, label, (rows, cols)) in enumerate(extra):
        labels[rows, cols] = len(objs) + 1
        objs.append(ObjectMask(box, label, 1.0, MaskMethod.OUTLINE, 10.0, 1, 1, 90 + t))
    m = (labels > 0).astype(np.uint8) * 255
    dup = StereoMasks(m, m.copy(), objs, labels_left=labels, labels_right=labels, flow=FrameFlow(6, DT, []))
    out = judge.select(dup)
    assert [o.moving for o in objs] == [False, True, True, False, True, None, None]
    assert [o.masked for o in objs] == [False, True, True, False, True, True, True]
    assert not out.left[:60, 2:200].any()  # the parked car's second box: left to SLAM
    assert out.left[:60, 200:400].all() and out.left[60:120, :200].all() and out.left[120:, :100].all()
    judge.update(dup, _camera(6)[:3], ok=True)  # the verdicts reported after the frame agree
    assert [o.moving for o in objs] == [False, True, True, False, True, None, None]


def test_a_parked_object_that_starts_to_move_is_caught_and_reported() -> None:
    rng = np.random.default_rng(2)
    judge = MotionJudge(MotionConfig(), CALIB)
    X, _ = _objects()[1]
    turned_at = None
    pos = X.copy()
    for k in range(10):
        v = np.zeros(3) if k < 5 else np.array([0.0, 0.0, 3.0])  # pulls away at frame 5
        flows = []
        if k > 0:
            uv0, d0 = _uvd(pos, _camera(k - 1), rng)
            pos = pos + v * DT
            uv1, d1 = _uvd(pos, _camera(k), rng)
            flows.append(ObjectFlow(1, 0, uv0, d0, uv1, d1))
        masks = _masks(k, flows)
        judge.select(masks)
        if judge.update(masks, _camera(k)[:3], ok=True) and turned_at is None:
            turned_at = k
        if k == 4:
            assert masks.objects[0].moving is False
    assert masks.objects[0].moving is True and turned_at is not None and 5 <= turned_at <= 7


def test_lost_frames_give_no_evidence() -> None:
    judge = MotionJudge(MotionConfig(), CALIB)
    rng = np.random.default_rng(3)
    X, v = _objects()[2]
    for k in range(5):
        flows = []
        if k > 0:
            uv0, d0 = _uvd(X + v * DT * (k - 1), _camera(k - 1), rng)
            uv1, d1 = _uvd(X + v * DT * k, _camera(k), rng)
            flows.append(ObjectFlow(2, 1, uv0, d0, uv1, d1))
        masks = _masks(k, flows)
        judge.update(masks, _camera(k)[:3], ok=False)
    assert masks.objects[1].moving is None and masks.objects[1].masked


def _far_scene(cfg: MotionConfig, anchored: bool = False) -> tuple[MotionJudge, StereoMasks]:
    """Three objects at rest, seen by the camera driving forward for 10 frames: a car and a
    person 45 m ahead and a person 12 m ahead; the judge and the last frame's masks.
    ``anchored``: the points followed since frame 0 (else first seen a frame before)."""
    rng = np.random.default_rng(3)
    judge = MotionJudge(cfg, CALIB)
    pts = {1: np.array([-4.0, 0.5, 45.0]), 2: np.array([4.0, 0.5, 45.0]), 3: np.array([2.0, 0.5, 12.0])}
    labels = {1: "car", 2: "person", 3: "person"}
    X = {t: c + rng.uniform(-0.5, 0.5, (30, 3)) * [0.6, 1.6, 0.4] for t, c in pts.items()}
    lab = np.zeros((192, 640), np.int32)
    for i in range(3):
        lab[:, i * 200:(i + 1) * 200] = i + 1
    m = (lab > 0).astype(np.uint8) * 255
    first = {t: _uvd(X[t], _camera(0, 5.0), rng) for t in pts}
    for k in range(10):
        flows = []
        if k > 0:
            for t in pts:
                uv0, d0 = _uvd(X[t], _camera(k - 1, 5.0), rng)
                uv1, d1 = _uvd(X[t], _camera(k, 5.0), rng)
                seen = (first[t][0], first[t][1], np.zeros(len(d0), np.int64)) if anchored else (None, None, None)
                flows.append(ObjectFlow(t, t - 1, uv0, d0, uv1, d1, *seen))
        objs = [ObjectMask((i * 200.0, 0.0, (i + 1) * 200.0, 192.0), labels[i + 1], 1.0, MaskMethod.OUTLINE, 10.0, 1,
                           1, i + 1) for i in range(3)]
        masks = StereoMasks(m, m.copy(), objs, labels_left=lab, labels_right=lab, flow=FrameFlow(k, DT, flows))
        judge.select(masks)
        judge.update(masks, _camera(k, 5.0)[:3], ok=True)
    return judge, masks


def test_a_walker_too_far_to_tell_from_rest_stays_undecided() -> None:
    """At 45 m (fx 370 px, baseline 0.54 m) the stereo noise of a velocity over the whole
    window is ~1.4 m/s: the test cannot tell a standing person from a walking one
    (``rest_resolution`` 2 m/s, twice the noise), so the far person stays undecided --
    masked -- while the far car (vehicles are told at any range) and the near person are
    judged static."""
    judge, masks = _far_scene(MotionConfig())
    assert [o.moving for o in masks.objects] == [False, None, False]
    judge.select(masks)
    assert [o.masked for o in masks.objects] == [False, True, False]
    # with a coarser resolution asked for, the far person is told static too
    loose = MotionJudge(MotionConfig(rest_resolution=4.0), CALIB)
    assert loose._resolvable(np.full(30, CALIB.bf / 45.0), np.zeros(30, np.int64), np.array([True]), DT)[0]
    assert not judge._resolvable(np.full(30, CALIB.bf / 45.0), np.zeros(30, np.int64), np.array([True]), DT)[0]


def test_the_rest_rule_for_vehicles_and_from_the_measured_velocity_noise() -> None:
    """``rest_resolution_vehicle`` puts the far car under the walker's rule (undecided at
    45 m at 2 m/s, judged at 4 m/s); ``rest_sigma: measured`` weighs the object's own
    velocity covariance (its points' actual ages) instead of a whole window's: with every
    point first seen a frame before (0.1 s of baseline) not even the near person is told
    from a walker; with the points followed since frame 0 the near one is, the far ones
    still are not."""
    assert [o.moving for o in _far_scene(MotionConfig(rest_resolution_vehicle=2.0))[1].objects] == [None, None, False]
    assert [o.moving for o in _far_scene(MotionConfig(rest_resolution_vehicle=4.0))[1].objects] == [False, None, False]
    assert [o.moving for o in _far_scene(MotionConfig(rest_sigma="measured"))[1].objects] == [False, None, None]
    for anchored in (False, True):  # the default: the same verdicts either way
        assert [o.moving for o in _far_scene(MotionConfig(), anchored)[1].objects] == [False, None, False]
    measured = _far_scene(MotionConfig(rest_sigma="measured"), anchored=True)[1].objects
    assert [o.moving for o in measured] == [False, None, False]  # vehicles: still at any range
    measured = _far_scene(MotionConfig(rest_sigma="measured", rest_resolution_vehicle=2.0), anchored=True)[1].objects
    assert [o.moving for o in measured] == [None, None, False]
    judge = MotionJudge(MotionConfig(), CALIB)
    assert list(judge._rest_limits(np.array([True, False]))) == [2.0, np.inf]


def test_motion_config_is_validated() -> None:
    with pytest.raises(ConfigError, match="motion.mode"):
        Config().with_overrides({"motion.mode": "some"})
    with pytest.raises(ConfigError, match="static_fraction"):
        MotionConfig(static_fraction=0.6, moving_fraction=0.5)
    with pytest.raises(ConfigError, match="motion.confirm_frames"):
        MotionConfig(confirm_frames=0)
    with pytest.raises(ConfigError, match="motion.duplicate_iou"):
        MotionConfig(duplicate_iou=0.0)
    with pytest.raises(ConfigError, match="motion.rest_resolution"):
        MotionConfig(rest_resolution=0.0)
    with pytest.raises(ConfigError, match="motion.rest_resolution_vehicle"):
        MotionConfig(rest_resolution_vehicle=0.0)
    with pytest.raises(ConfigError, match="motion.rest_sigma"):
        MotionConfig(rest_sigma="nominal")
    with pytest.raises(ConfigError, match="motion.velocity_noise"):
        MotionConfig(velocity_noise="max")
    with pytest.raises(ConfigError, match="motion.release"):
        MotionConfig(release="never")
    with pytest.raises(ConfigError, match="motion.strong_confirm"):
        Config().with_overrides({"motion.strong_confirm": "yes"})


# ----------------------------------------------------------------------------- pipeline

FRAMES = 10


@pytest.fixture(scope="module")
def convoy(tmp_path_factory) -> Path:
    return generate(tmp_path_factory.mktemp("convoy"), "convoy", frames=FRAMES, seed=0, size=(640, 192))


def _lines(path: Path) -> list[dict]:
    return [json.loads(s) for s in path.read_text().splitlines()]


def test_convoy_truck_is_moving_and_parked_cars_are_used(convoy: Path, tmp_path: Path) -> None:
    cfg = Config().with_overrides({"detector.name": "oracle"})
    res = run_sequence(convoy, tmp_path / "run", cfg, save_masks=True)
    gt = read_objects(convoy)
    lines = _lines(tmp_path / "run" / "objects.jsonl")
    assert [r["frame"] for r in lines] == list(range(FRAMES)) and len(res.frames) == FRAMES
    for o in lines[0]["objects"]:  # the contract; nothing judged on the first frame
        assert {"track", "label", "box", "moving", "masked", "speed_mps"} <= set(o)
        assert o["moving"] is None and o["masked"] is True
    truck = {o.id for f in gt.frames for o in f if o.label == "truck" and o.moving}
    assert len(truck) == 1
    last = {o["track"]: o for o in lines[-1]["objects"]}
    (tid,) = truck
    assert last[tid]["moving"] is True and last[tid]["masked"] is True
    assert 4.0 < last[tid]["speed_mps"] < 8.5  # 22 km/h = 6.1 m/s
    parked = [o for o in last.values() if not {g.id: g for g in gt.frame(FRAMES - 1)}[o["track"]].moving
              and o["moving"] is not None]
    assert parked and all(o["moving"] is False and o["masked"] is False for o in parked)
    # a static car's pixels are not in the mask SLAM got, the truck's are
    import cv2

    m = cv2.imread(str(tmp_path / "run" / "masks" / "left" / f"{FRAMES - 1:06d}.png"), cv2.IMREAD_GRAYSCALE)
    x1, y1, x2, y2 = (int(v) for v in last[tid]["box"])
    assert m[y1:y2, x1:x2].mean() > 0.5 * 255
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["motion"]["mode"] == "moving"


def test_mask_all_reproduces_the_masker_fed_straight_to_slam(convoy: Path, tmp_path: Path) -> None:
    from dynastereo.io import open_sequence
    from dynastereo.masking import build_masker
    from dynastereo.slam import System

    cfg = Config().with_overrides({"detector.name": "oracle", "motion.mode": "all", "slam.local_ba": "inline"})
    res = run_sequence(convoy, tmp_path / "all", cfg)
    seq = open_sequence(convoy)
    masker = build_masker(cfg, seq.calibration, ground_truth=convoy)
    with System(cfg, seq.calibration) as system:
        for i in range(FRAMES):
            frame = seq.frame(i)
            system.track(frame, masker.mask(frame))
        ref = system.trajectory()
    np.testing.assert_array_equal(res.poses, ref)
    for r in _lines(tmp_path / "all" / "objects.jsonl"):
        assert all(o["masked"] is True and o["moving"] is None for o in r["objects"])


def test_mask_job_writes_the_fields_undecided(convoy: Path, tmp_path: Path) -> None:
    cfg = Config().with_overrides({"detector.name": "oracle"})
    mask_sequence(convoy, tmp_path / "m", cfg, frames="0-2")
    gt_ids = {o.id for o in read_objects(convoy).frame(1)}
    for r in _lines(tmp_path / "m" / "objects.jsonl"):
        for o in r["objects"]:
            assert o["moving"] is None and o["masked"] is True and o["speed_mps"] is None
    assert {o["track"] for o in _lines(tmp_path / "m" / "objects.jsonl")[1]["objects"]} <= gt_ids  # oracle: GT ids


def test_forget_region_removes_the_points_of_an_object(convoy: Path) -> None:
    from dynastereo.io import open_sequence
    from dynastereo.slam import System

    seq = open_sequence(convoy)
    cfg = Config().with_overrides({"slam.local_ba": "inline"})
    with System(cfg, seq.calibration) as system:
        for i in range(3):
            system.track(seq.frame(i))
        before = len(system.map_points())
        gt = read_objects(convoy).frame(2)
        truck = next(o for o in gt if o.label == "truck")
        region = np.zeros((seq.calibration.height, seq.calibration.width), bool)
        x1, y1, x2, y2 = truck.box_left
        region[y1:y2, x1:x2] = True
        n = system.forget_region(region, 0.5, truck.distance + 3.0)
        assert n > 20 and len(system.map_points()) == before - n
        assert system.forget_region(region, 0.5, truck.distance + 3.0) == 0  # already gone
        assert system.track(seq.frame(3)).status == "tracked"


def test_overlay_colours_follow_the_verdicts() -> None:
    from dynastereo.viz.draw import VERDICT_COLOURS, draw_overlay
    from dynastereo.datatypes import StereoFrame

    masks = _masks(0, [])
    for o, v in zip(masks.objects, (False, True, None)):
        o.moving = v
    masks.left[:, :200] = 0  # the static object is not masked
    frame = StereoFrame(0, 0.0, np.full((192, 640), 128, np.uint8), np.full((192, 640), 128, np.uint8))
    img = draw_overlay(frame, masks)[:, :640].astype(int)
    px = [img[100, x] for x in (100, 300, 500)]  # BGR inside each object
    assert px[0][1] > px[0][2] and px[0][1] > px[0][0]  # static: green
    assert px[1][2] > px[1][1] and px[1][2] > px[1][0]  # moving: red
    assert px[2][2] > px[2][0] and px[2][1] > px[2][0] and px[2][1] < px[2][2]  # undecided: orange
    assert VERDICT_COLOURS[True] != VERDICT_COLOURS[False] != VERDICT_COLOURS[None]


def test_live_node_masks_only_what_moves(convoy: Path) -> None:
    from dynastereo.io import open_sequence
    from dynastereo.masking import build_masker
    from dynastereo.ros.core import StereoInput, StereoNodeCore
    from dynastereo.ros.convert import objects_view
    from dynastereo.synth import OracleDetector

    class ByImage:  # the oracle finds the frame from the image itself (the node numbers frames itself)
        def __init__(self, oracle):
            self.oracle, self.name, self.class_names = oracle, "oracle", oracle.class_names

        def detect(self, image):
            return self.oracle.detect(image)

    seq = open_sequence(convoy)
    cfg = Config().with_overrides({"slam.local_ba": "inline"})
    masker = build_masker(cfg, seq.calibration, detector=ByImage(OracleDetector(convoy)))
    core = StereoNodeCore(cfg, calibration=seq.calibration, masker=masker)
    try:
        for i in range(FRAMES):
            f = seq.frame(i)
            res = core.process(StereoInput(f.left, f.right, int(round(f.timestamp * 1e9)) + 1))
    finally:
        core.shutdown()
    gt = {o.id: o for o in read_objects(convoy).frame(FRAMES - 1)}
    objs = res.masks.objects
    truck = next(o for o in objs if gt[o.track_id].label == "truck")
    assert truck.moving is True and truck.masked
    static = [o for o in objs if o.moving is False]
    assert static and all(not o.masked and not gt[o.track_id].moving for o in static)
    for o in static:  # left to SLAM: not in the published mask
        lab = res.masks.labels_left == objs.index(o) + 1
        assert not res.masks.left[lab].any()
    view = objects_view(res.frame.left, res.masks.left, res.masks)
    assert view.shape == res.frame.left.shape[:2] + (3,)


def test_cli_mask_all_and_default(convoy: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from dynastereo.cli.main import app

    runner = CliRunner()
    for flag, mode in ((["--mask-all"], "all"), ([], "moving")):
        out = tmp_path / mode
        r = runner.invoke(app, ["run", str(convoy), "-o", str(out), "--detector", "oracle", "--frames", "0-5", *flag])
        assert r.exit_code == 0, r.output
        assert json.loads((out / "run.json").read_text())["motion"]["mode"] == mode
        last = _lines(out / "objects.jsonl")[-1]["objects"]
        assert any(o["moving"] is not None for o in last) == (mode == "moving")


def _car_driving_away(cfg: MotionConfig, frames: int = 20) -> bool | None:
    """A car 30 m ahead driving away at 10 m/s, the camera following at 9 m/s; its 11
    points followed for unequal times (1 to 14 frames, as on a small far outline whose
    points keep being lost and replaced).  Its verdict after ``frames`` frames."""
    rng = np.random.default_rng(3)
    X = np.array([0.0, 0.5, 30.0]) + rng.uniform(-0.5, 0.5, (11, 3)) * np.array([1.8, 1.4, 0.2])
    v = np.array([0.0, 0.0, 10.0])
    ages = np.array([1, 1, 2, 5, 7, 9, 11, 11, 11, 12, 14])
    judge = MotionJudge(cfg, CALIB)
    objs = [ObjectMask((300.0, 80.0, 340.0, 110.0), "car", 1.0, MaskMethod.OUTLINE, 6.7, 1, 1, 1)]
    for k in range(frames):
        flows = []
        if k > 0:
            anchor = np.maximum(k - ages, 0)
            uva, da = zip(*(_uvd(X[i:i + 1] + v * DT * a, _camera(a, 9.0), rng) for i, a in enumerate(anchor)))
            uv0, d0 = _uvd(X + v * DT * (k - 1), _camera(k - 1, 9.0), rng)
            uv1, d1 = _uvd(X + v * DT * k, _camera(k, 9.0), rng)
            flows.append(ObjectFlow(1, 0, uv0, d0, uv1, d1, np.concatenate(uva), np.concatenate(da), anchor))
        masks = StereoMasks(np.zeros((192, 640), np.uint8), np.zeros((192, 640), np.uint8), objs,
                            flow=FrameFlow(k, DT, flows))
        judge.update(masks, _camera(k, 9.0)[:3], ok=True)
    return masks.objects[0].moving


def test_a_far_car_driving_away_with_young_points_is_moving() -> None:
    """The window velocity is a median over the points: its noise is that of a median of
    points of unequal noise (``velocity_noise: median``), which the few points first seen
    a frame ago barely change.  Weighed by the mean point covariance (``mean``, before) the
    youngest points' noise hid 1 m a frame at 30 m, and the car was judged at rest."""
    assert _car_driving_away(MotionConfig()) is True
    assert _car_driving_away(MotionConfig(velocity_noise="mean")) is False
