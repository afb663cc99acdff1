"""Detection at the frame's own scale: tiles and seams, exact graph rewrites, the stage's
schedule and carried boxes, and recall against the reference masks of real frames."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import require
from dynastereo.config import Config, DetectorConfig
from dynastereo.errors import ConfigError, ModelError
from dynastereo.masking.detection import (
    DetectionStage,
    ScaledDetector,
    Tile,
    create_detector,
    merge_tile_boxes,
    tile_windows,
)
from dynastereo.masking.detection.rewrite import rewrite
from dynastereo.datatypes import Detections, StereoFrame

NAMES = ("person", "bicycle", "car", "motorcycle", "bus", "truck")
CAR = NAMES.index("car")


def iou(a, b) -> float:
    x0, y0 = max(a[0], b[0]), max(a[1], b[1])
    x1, y1 = min(a[2], b[2]), min(a[3], b[3])
    inter = max(x1 - x0, 0) * max(y1 - y0, 0)
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


class PartsDetector:
    """A test double of a YOLO detector: in each image (a tile) it 'detects' the visible part
    of known objects (frame coordinates), found from the tile's position in the frame."""

    name = "parts"
    class_names = NAMES
    nms_threshold = 0.45

    def __init__(self, frame: np.ndarray, objects: list[tuple[list[float], int]]):
        self.frame, self.objects = frame, objects
        self.calls = 0  # images seen
        self.batches: list[int] = []  # sizes of detect_batch calls

    def _origin(self, img: np.ndarray) -> tuple[int, int]:
        # a tile is a view into the frame: its offset from the frame's buffer
        off = img.__array_interface__["data"][0] - self.frame.__array_interface__["data"][0]
        return (off % self.frame.strides[0]) // self.frame.strides[1], off // self.frame.strides[0]

    def detect(self, img: np.ndarray) -> Detections:
        self.calls += 1
        ox, oy = self._origin(img)
        h, w = img.shape[:2]
        boxes, cls = [], []
        for (x0, y0, x1, y1), c in self.objects:
            bx0, bx1 = max(x0, ox), min(x1, ox + w)
            if bx1 - bx0 >= 8:
                boxes.append([bx0 - ox, y0 - oy, bx1 - ox, y1 - oy])
                cls.append(c)
        return Detections(np.array(boxes).reshape(-1, 4), np.full(len(boxes), 0.9), cls, NAMES)

    def detect_batch(self, images):
        self.batches.append(len(images))
        return [self.detect(im) for im in images]


def test_tile_windows_cover_the_frame_with_overlap():
    tiles = tile_windows(1241, 376, 3, 0.2)
    assert len(tiles) == 3
    assert tiles[0].x0 == 0 and tiles[-1].x1 == 1241
    assert all(t.y0 == 0 and t.y1 == 376 for t in tiles)
    widths = {t.width for t in tiles}
    assert max(widths) - min(widths) <= 1
    for a, b in zip(tiles, tiles[1:]):
        shared = a.x1 - b.x0
        assert abs(shared - 0.2 * a.width) <= 2
    assert tile_windows(640, 192, 1, 0.2) == [Tile(0, 0, 640, 192)]
    with pytest.raises(ConfigError, match="tile_overlap"):
        tile_windows(640, 192, 2, 1.0)


@pytest.mark.parametrize("box", [[300.0, 150.0, 600.0, 300.0],  # cut by both seams' sides of tiles 0/1
                                 [420.0, 100.0, 470.0, 200.0],  # inside the overlap: whole in both tiles
                                 [350.0, 120.0, 900.0, 330.0]])  # over three tiles
def test_object_cut_by_a_tile_seam_comes_out_whole(box):
    frame = np.zeros((376, 1241), np.uint8)
    other = [20.0, 200.0, 120.0, 260.0]  # a car away from any seam
    det = ScaledDetector(PartsDetector(frame, [(box, CAR), (other, CAR)]), "tiles", 1.0, 3, 0.2)
    out = det.detect(frame)
    assert det.base.batches == [3] and det.base.calls == 3  # one batched call for the three tiles
    assert len(out) == 2, out.boxes
    best = max(iou(b, box) for b in out.boxes)
    assert best > 0.99, out.boxes
    assert max(iou(b, other) for b in out.boxes) > 0.99


def test_merge_keeps_two_cars_side_by_side_at_a_seam_apart_vertically():
    tiles = tile_windows(1241, 376, 3, 0.2)
    seam = tiles[0].x1
    # a car ending at the seam (cut) and a person starting there: different groups stay apart
    boxes = np.array([[seam - 80, 150, seam, 250], [seam - 1, 150, seam + 40, 250]], np.float32)
    groups = np.array([0, 1])
    b, s, c = merge_tile_boxes(boxes, np.array([0.9, 0.8], np.float32), np.array([CAR, 0]), np.array([0, 1]),
                               tiles, groups, 0.45)
    assert len(b) == 2
    # same group but no vertical overlap: apart too
    boxes = np.array([[seam - 80, 50, seam, 120], [seam - 1, 200, seam + 40, 300]], np.float32)
    b, s, c = merge_tile_boxes(boxes, np.array([0.9, 0.8], np.float32), np.array([CAR, CAR]), np.array([0, 1]),
                               tiles, np.array([0, 0]), 0.45)
    assert len(b) == 2


def _models(models_dir: Path, name: str) -> Path:
    return require(models_dir / name, f"model {name}")


@pytest.mark.realdata
@pytest.mark.parametrize("name,file,layout", [("yolox-nano", "yolox_nano.onnx", "yolox"),
                                              ("fastestdet", "FastestDet.onnx", "fastestdet")])
def test_rewrite_is_exact_at_the_native_size_and_batches(models_dir, name, file, layout):
    import onnxruntime as ort

    path = _models(models_dir, name) / file
    base = create_detector(DetectorConfig(name=name), models_dir)
    w, h = base.input_w, base.input_h
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    a = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    b = ort.InferenceSession(rewrite(path, layout, w, h, 1), so, providers=["CPUExecutionProvider"])
    c = ort.InferenceSession(rewrite(path, layout, w, h, 3), so, providers=["CPUExecutionProvider"])
    x = np.random.default_rng(0).random((3, 3, h, w), dtype=np.float32) * 255
    name_in = a.get_inputs()[0].name
    for k in range(3):
        ra, rb = a.run(None, {name_in: x[k : k + 1]}), b.run(None, {name_in: x[k : k + 1]})
        assert all(np.array_equal(u, v) for u, v in zip(ra, rb))
    rc = c.run(None, {name_in: x})[0]
    single = np.concatenate([a.run(None, {name_in: x[k : k + 1]})[0] for k in range(3)])
    assert rc.shape == single.shape
    np.testing.assert_allclose(rc, single, rtol=1e-4, atol=1e-3)
    with pytest.raises(ModelError, match="multiples of 32"):
        rewrite(path, layout, 1241, 376)


@pytest.mark.realdata
@pytest.mark.parametrize("name,gain", [("yolox-nano", 0.15), ("yolov3-tiny", 0.15), ("fastestdet", 0.0)])
def test_frame_canvas_finds_more_near_cars_than_the_square_canvas(models_dir, data_dir, name, gain):
    """On KITTI 06 frames (reference masks), the frame at its own scale finds clearly more
    of the near vehicles than the frame letterboxed into the model's square canvas
    (FastestDet, a weaker network, at least as many: its gain shows on raw 0001)."""
    from dynastereo.eval.refmasks import load_references, score_frame

    ref_dir = require(data_dir.parent / "reference/refmasks/seq06", "reference masks seq06")
    refs = load_references(ref_dir)[:51:5]
    seq = require(data_dir / "kitti_odometry/dataset/sequences/06/image_0", "KITTI 06")
    base = create_detector(DetectorConfig(name=name, score_threshold=0.25), models_dir)
    model, frame = ScaledDetector(base, "model"), ScaledDetector(base, "frame")
    s_model = s_frame = None
    for r in refs:
        img = cv2.imread(str(seq / f"{r.index:06d}.png"), cv2.IMREAD_GRAYSCALE)
        s_model = score_frame(r, model.detect(img).boxes, None, s_model)
        s_frame = score_frame(r, frame.detect(img).boxes, None, s_frame)
    assert frame.canvas_size == (1248, 384) if name != "yolov3-tiny" else frame.canvas_size[0] == 1248
    assert s_frame.vehicles >= 15
    assert s_frame.recall_vehicles >= s_model.recall_vehicles + gain, (s_model.to_dict(), s_frame.to_dict())


def _frame(k: int, img: np.ndarray) -> StereoFrame:
    return StereoFrame(k, 0.1 * k, img, img)


def test_stage_interval_schedule_carries_boxes_between_runs():
    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur(rng.integers(0, 255, (192, 640), dtype=np.uint8), (3, 3), 0)
    det = PartsDetector(img, [([100.0, 60.0, 180.0, 120.0], CAR)])
    cfg = DetectorConfig(canvas="frame", schedule="interval", interval=3, contrast="none")
    stage = DetectionStage(det, cfg)
    outs = [stage.detect_frame(_frame(k, img)) for k in range(7)]
    assert det.calls == 3  # frames 0, 3, 6
    assert [bool(o.carried[0]) for o in outs] == [False, True, True, False, True, True, False]
    assert all(o.track_id(0) == 0 for o in outs)  # one object, one track
    assert all(iou(o.boxes[0], [100, 60, 180, 120]) > 0.95 for o in outs)
    stage.reset()
    assert stage.detect_frame(_frame(0, img)).carried.tolist() == [False]
    assert det.calls == 4


def test_stage_warm_up_runs_the_network_once_and_changes_nothing():
    """The detector's first (slow) call made before the frame loop: one inference on a
    black frame of the frame's size; the schedule and the carried boxes as if it never ran."""
    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur(rng.integers(0, 255, (192, 640), dtype=np.uint8), (3, 3), 0)
    cfg = DetectorConfig(canvas="frame", schedule="interval", interval=3, contrast="none")
    runs = []
    for warm in (False, True):
        det = PartsDetector(img, [([100.0, 60.0, 180.0, 120.0], CAR)])
        stage = DetectionStage(det, cfg)
        if warm:
            stage.warm_up(192, 640)
            assert det.calls == 1
        runs.append(([stage.detect_frame(_frame(k, img)) for k in range(4)], det.calls - warm))
    (a, ca), (b, cb) = runs
    assert ca == cb == 2  # frames 0 and 3, either way
    assert all(np.array_equal(x.boxes, y.boxes) and np.array_equal(x.carried, y.carried) for x, y in zip(a, b))


def test_stage_rotate_searches_one_tile_per_frame():
    img = np.random.default_rng(2).integers(0, 255, (376, 1241), dtype=np.uint8)
    det = PartsDetector(img, [([30.0, 100.0, 150.0, 200.0], CAR), ([1000.0, 100.0, 1150.0, 220.0], CAR)])
    cfg = DetectorConfig(canvas="tiles", tiles=3, schedule="rotate", contrast="none")
    stage = DetectionStage(det, cfg)
    o0 = stage.detect_frame(_frame(0, img))  # tile 0: the left car only
    assert len(o0) == 1 and o0.boxes[0][0] < 200
    o2 = [stage.detect_frame(_frame(k, img)) for k in (1, 2)][-1]  # tile 2 found the right car
    assert len(o2) == 2
    assert sorted(o2.carried.tolist()) == [False, True]


def test_stage_leaves_an_oracle_alone():
    class Oracle:
        name, class_names = "oracle", NAMES

        def detect_frame(self, index):
            return Detections(np.array([[index, 0, index + 10, 10]]), [1.0], [CAR], NAMES)

    stage = DetectionStage(Oracle(), DetectorConfig())
    d = stage.detect_frame(_frame(5, np.zeros((20, 40), np.uint8)))
    assert d.boxes[0][0] == 5 and d.carried is None and stage.tracker is None


@pytest.mark.parametrize("key,value,match", [
    ("canvas", "square", "detector.canvas"),
    ("schedule", "sometimes", "detector.schedule"),
    ("contrast", "hdr", "detector.contrast"),
    ("scale", 0.0, "detector.scale"),
    ("interval", 0, "detector.interval"),
    ("tile_overlap", 1.5, "detector.tile_overlap"),
    ("score_threshold", 1.5, "detector.score_threshold"),
])
def test_detector_options_are_checked_where_the_configuration_is_made(key, value, match):
    with pytest.raises(ConfigError, match=match):
        Config().with_overrides({f"detector.{key}": value})


def test_rotate_needs_tiles_and_skipping_needs_tracking(tmp_path):
    from dynastereo.config import load_config

    p = tmp_path / "c.yaml"
    p.write_text("detector:\n  schedule: rotate\n")
    with pytest.raises(ConfigError, match="c.yaml.*canvas 'tiles'|canvas 'tiles'.*c.yaml"):
        load_config(p)
    with pytest.raises(ConfigError, match="track: true"):
        DetectorConfig(schedule="interval", track=False)


@pytest.mark.parametrize("canvas", ["frame", "tiles"])
def test_band_top_leaves_the_sky_out_and_keeps_frame_coordinates(canvas):
    """``detector.band_top``: the network sees the frame below its top quarter only (a
    smaller canvas), and the boxes come back in frame coordinates."""
    frame = np.zeros((376, 1241), np.uint8)
    box = [300.0, 150.0, 600.0, 300.0]
    base = PartsDetector(frame, [(box, CAR)])
    seen = []
    detect = base.detect

    def spy(img):
        seen.append((base._origin(img), img.shape))
        return detect(img)

    base.detect = spy
    det = ScaledDetector(base, canvas, 1.0, 3, 0.2, band_top=0.25)
    out = det.detect(frame)
    assert seen and all(o[1] == 94 and s[0] == 376 - 94 for o, s in seen)  # rows 94.. only
    assert max(iou(b, box) for b in out.boxes) > 0.99
    with pytest.raises(ConfigError, match="band_top"):
        DetectorConfig(band_top=0.95)
