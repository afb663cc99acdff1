"""Detectors and their post-processing: synthetic known answers + real photos / KITTI frames.

Real models via DYNASTEREO_MODELS, real photos in ``$DYNASTEREO_DATA/../images``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import require, skip_or_fail
from dynastereo.config import DetectorConfig
from dynastereo.errors import ConfigError, InputError, ModelError
from dynastereo.masking.base import Detector
from dynastereo.masking.detection import (
    COCO_CLASSES,
    DARKNET_LAYOUT,
    ULTRALYTICS_LAYOUT,
    YOLOX_LAYOUT,
    DarknetDetector,
    FastestDetDetector,
    UltralyticsDetector,
    UltralyticsSegModel,
    YoloxDetector,
    create_detector,
    create_seg_model,
    dynamic_class_mask,
    letterbox,
    nms,
    postprocess,
    postprocess_loop,
)
from dynastereo.masking.detection.common import BoxTransform

DETECTORS = ["yolov3-tiny", "yolox-nano", "fastestdet", "yolo11n-int8"]
# Hand-checked regions in street.jpg (1330x1330): the walking man at the left, the white car.
STREET_PERSON = np.array([70, 550, 260, 945], np.float32)
STREET_CAR = np.array([668, 590, 965, 768], np.float32)


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of boxes ``a`` (N, 4) with one box ``b`` (4,)."""
    a = np.atleast_2d(a)
    x1, y1 = np.maximum(a[:, 0], b[0]), np.maximum(a[:, 1], b[1])
    x2, y2 = np.minimum(a[:, 2], b[2]), np.minimum(a[:, 3], b[3])
    inter = np.clip(x2 - x1, 0, None) * np.clip(y2 - y1, 0, None)
    area = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / np.maximum(area, 1e-9)


# --------------------------------------------------------------------------- synthetic


def _row(box_cxcywh, cls_id, score, nc=80, obj=None, noise=0.0):
    """A raw row [cx, cy, w, h, (obj), scores...]."""
    scores = np.full(nc, noise, np.float32)
    scores[cls_id] = score
    head = list(box_cxcywh) + ([] if obj is None else [obj])
    return np.concatenate([np.asarray(head, np.float32), scores])


def _synthetic_darknet(rng: np.random.Generator) -> tuple[list[np.ndarray], dict]:
    """Two 'layers' of Darknet-style rows with a known answer hidden among noise rows."""
    nc = 80
    car, person, dog = COCO_CLASSES.index("car"), COCO_CLASSES.index("person"), COCO_CLASSES.index("dog")
    special = [
        _row((100, 100, 40, 20), car, 0.90, obj=0.95),  # kept
        _row((102, 101, 40, 20), car, 0.80, obj=0.85),  # same car, suppressed by NMS
        _row((101, 100, 40, 20), person, 0.70, obj=0.75),  # overlaps the car but another class: kept
        _row((300, 50, 10, 30), dog, 0.99, obj=0.99),  # not a dynamic class: dropped
        _row((200, 200, 50, 50), car, 0.30, obj=0.90),  # below threshold: dropped
        _row((400, 300, 30, 30), car, 0.50, obj=0.60),  # far away: kept
    ]
    # noise rows: objectness and scores below the threshold (0.35)
    noise = np.zeros((500, 5 + nc), np.float32)
    noise[:, :2] = rng.uniform(0, 500, (500, 2))
    noise[:, 2:4] = rng.uniform(5, 50, (500, 2))
    noise[:, 4] = rng.uniform(0, 0.34, 500)
    noise[:, 5:] = rng.uniform(0, 0.3, (500, nc)) * noise[:, 4:5]
    layer1 = np.vstack([noise[:300], np.array(special[:3])])
    layer2 = np.vstack([noise[300:], np.array(special[3:])])
    expected = {
        "boxes": np.array([[80, 90, 120, 110], [81, 90, 121, 110], [385, 285, 415, 315]], np.float32),
        "scores": np.array([0.90, 0.70, 0.50], np.float32),
        "class_ids": np.array([car, person, car]),
        "rows": np.array([300, 302, 303 + 200 + 2]),
    }
    return [layer1, layer2], expected


@pytest.mark.parametrize("fn", [postprocess, postprocess_loop], ids=["array", "loop"])
def test_postprocess_known_answer_darknet(fn):
    layers, exp = _synthetic_darknet(np.random.default_rng(0))
    dyn = dynamic_class_mask(COCO_CLASSES, ["person", "car"])
    res = fn(layers, 80, DARKNET_LAYOUT, 0.35, 0.45, dyn)
    np.testing.assert_allclose(res.boxes, exp["boxes"], atol=1e-4)
    np.testing.assert_allclose(res.scores, exp["scores"], atol=1e-6)
    np.testing.assert_array_equal(res.class_ids, exp["class_ids"])
    np.testing.assert_array_equal(res.rows, exp["rows"])


def test_postprocess_without_class_filter_keeps_the_dog():
    layers, _ = _synthetic_darknet(np.random.default_rng(1))
    res = postprocess(layers, 80, DARKNET_LAYOUT, 0.35, 0.45, None)
    assert COCO_CLASSES.index("dog") in res.class_ids
    assert len(res) == 4


@pytest.mark.parametrize("fn", [postprocess, postprocess_loop], ids=["array", "loop"])
def test_postprocess_yolox_multiplies_objectness(fn):
    car = COCO_CLASSES.index("car")
    rows = np.array(
        [
            _row((50, 50, 20, 20), car, 0.8, obj=0.5),  # 0.40 > 0.35: kept
            _row((150, 50, 20, 20), car, 0.3, obj=0.9),  # 0.27: dropped
            _row((250, 50, 20, 20), car, 0.39, obj=0.95),  # 0.3705: kept
            _row((350, 50, 20, 20), car, 0.99, obj=0.3),  # 0.297: dropped although the class score is high
        ]
    )
    res = fn(rows, 80, YOLOX_LAYOUT, 0.35, 0.45, None)
    np.testing.assert_array_equal(np.sort(res.rows), [0, 2])
    np.testing.assert_allclose(sorted(res.scores), sorted([0.4, 0.39 * 0.95]), rtol=1e-6)


@pytest.mark.parametrize("fn", [postprocess, postprocess_loop], ids=["array", "loop"])
def test_postprocess_ultralytics_layout_and_extra_columns(fn):
    person = COCO_CLASSES.index("person")
    rows = np.array(
        [
            np.concatenate([_row((10, 20, 4, 8), person, 0.6), np.full(32, 7.0, np.float32)]),
            np.concatenate([_row((60, 20, 4, 8), person, 0.2), np.full(32, 7.0, np.float32)]),
        ]
    )
    res = fn(rows, 80, ULTRALYTICS_LAYOUT, 0.35, 0.45, None)
    assert res.rows.tolist() == [0]
    np.testing.assert_allclose(res.boxes, [[8, 16, 12, 24]])


def test_postprocess_empty_and_nothing_above_threshold():
    rows = np.zeros((10, 85), np.float32)
    for fn in (postprocess, postprocess_loop):
        r = fn(rows, 80, YOLOX_LAYOUT, 0.35, 0.45, None)
        assert len(r) == 0 and r.boxes.shape == (0, 4)


def test_nms_is_class_aware():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [0, 0, 10, 10], [50, 50, 60, 60]], np.float32)
    scores = np.array([0.9, 0.8, 0.7, 0.6], np.float32)
    classes = np.array([0, 0, 1, 0])
    assert nms(boxes, scores, classes, 0.45).tolist() == [0, 2, 3]
    assert nms(boxes, scores, np.zeros(4, int), 0.45).tolist() == [0, 3]


def test_dynamic_class_mask_aliases_and_errors():
    darknet_names = ["person", "bicycle", "car", "motorbike", "aeroplane", "dog"]
    m = dynamic_class_mask(darknet_names, ["motorcycle", "Car", "airplane"])
    assert m.tolist() == [False, False, True, True, True, False]
    with pytest.raises(ConfigError, match="unicorn"):
        dynamic_class_mask(COCO_CLASSES, ["person", "unicorn"])


def test_letterbox_and_box_transform_round_trip():
    img = np.zeros((100, 300, 3), np.uint8)
    out, r, (px, py) = letterbox(img, (320, 320), center=True)
    assert out.shape == (320, 320, 3) and r == pytest.approx(320 / 300)
    assert px == 0 and py == (320 - round(100 * r)) // 2
    assert (out[:py] == 114).all() and (out[py : py + round(100 * r)] == 0).all()
    t = BoxTransform(1 / r, 1 / r, px, py, 300, 100)
    box_img = np.array([[30, 20, 90, 80]], np.float32)
    box_net = box_img * r + np.array([px, py, px, py])
    np.testing.assert_allclose(t.apply(box_net), box_img, atol=1e-4)
    # clipping to the image
    np.testing.assert_allclose(t.apply(np.array([[-50, -50, 1000, 1000]], np.float32)), [[0, 0, 300, 100]])


# --------------------------------------------------------------------------- real models


@pytest.fixture(scope="module")
def images_dir(data_dir: Path) -> Path:
    return require(data_dir.parent / "images", "detector test photos (shared/images)")


@pytest.fixture(scope="module")
def street(images_dir: Path) -> np.ndarray:
    img = cv2.imread(str(require(images_dir / "street.jpg", "street.jpg")))
    assert img is not None
    return img


@pytest.fixture(scope="module")
def detectors(models_dir: Path) -> dict:
    return {}


def get_detector(cache: dict, models_dir: Path, name: str, **kw):
    key = (name, tuple(sorted(kw.items())))
    if key not in cache:
        require(models_dir / name, f"model {name}")
        cache[key] = create_detector(DetectorConfig(name=name, **kw), models_dir)
    return cache[key]


@pytest.mark.realdata
@pytest.mark.parametrize("name", DETECTORS)
def test_detector_finds_person_and_car_on_street(name, detectors, models_dir, street):
    det = get_detector(detectors, models_dir, name)
    assert isinstance(det, Detector)
    assert len(det.class_names) == 80 and det.class_names[3] == "motorcycle"
    d = det.detect(street)
    h, w = street.shape[:2]
    labels = np.array(d.labels())
    assert "person" in labels and "car" in labels
    assert set(labels) <= {"person", "bicycle", "car", "motorcycle", "bus", "truck", "train"}
    assert (d.boxes[:, 0] >= 0).all() and (d.boxes[:, 2] <= w).all()
    assert (d.boxes[:, 1] >= 0).all() and (d.boxes[:, 3] <= h).all()
    assert (d.boxes[:, 2] > d.boxes[:, 0]).all() and (d.boxes[:, 3] > d.boxes[:, 1]).all()
    assert (d.scores > DetectorConfig().score_threshold).all() and (d.scores <= 1).all()
    assert iou(d.boxes[labels == "person"], STREET_PERSON).max() > 0.8
    assert iou(d.boxes[labels == "car"], STREET_CAR).max() > 0.8
    # everything found is in the lower street half where the people and cars are
    cy = (d.boxes[:, 1] + d.boxes[:, 3]) / 2
    assert ((cy > 0.35 * h) & (cy < 0.85 * h)).all()


@pytest.mark.realdata
@pytest.mark.parametrize("name", DETECTORS)
def test_grayscale_input(name, detectors, models_dir, street):
    det = get_detector(detectors, models_dir, name)
    gray = cv2.cvtColor(street, cv2.COLOR_BGR2GRAY)
    d2 = det.detect(gray)
    d3 = det.detect(gray[:, :, None])
    np.testing.assert_array_equal(d2.boxes, d3.boxes)
    bgr = det.detect(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)).boxes
    if name == "yolox-nano":  # grey frames run its one-channel graph: the same boxes up to rounding
        np.testing.assert_allclose(d2.boxes, bgr, atol=0.05)
        three = get_detector(detectors, models_dir, name, grey_input=False)
        np.testing.assert_array_equal(three.detect(gray).boxes, bgr)  # the three-channel path, bit for bit
    else:
        np.testing.assert_array_equal(d2.boxes, bgr)
    labels = np.array(d2.labels())
    assert "person" in labels
    assert iou(d2.boxes[labels == "person"], STREET_PERSON).max() > 0.5
    with pytest.raises(InputError):
        det.detect(gray.astype(np.float32))


@pytest.mark.realdata
@pytest.mark.parametrize("name", DETECTORS)
def test_dynamic_class_filter_removes_the_dog(name, detectors, models_dir, images_dir):
    img = cv2.imread(str(require(images_dir / "dog.jpg", "dog.jpg")))
    default = get_detector(detectors, models_dir, name).detect(img)
    with_dog = get_detector(
        detectors, models_dir, name, dynamic_classes=("person", "bicycle", "car", "truck", "dog")
    ).detect(img)
    assert "dog" in with_dog.labels()
    assert "dog" not in default.labels()
    assert {"bicycle", "car"} & set(default.labels())
    # the dog sits in the lower-left; the default detector keeps nothing centred there alone
    dog_box = with_dog.boxes[np.array(with_dog.labels()) == "dog"][0]
    assert dog_box[0] < 0.3 * img.shape[1] and dog_box[3] > 0.8 * img.shape[0]


@pytest.mark.realdata
def test_kitti_grayscale_frame_near_car(detectors, models_dir, kitti06):
    """KITTI 06 frame 10: a parked car fills the lower-right corner."""
    img = cv2.imread(str(require(kitti06 / "image_0/000010.png")), cv2.IMREAD_UNCHANGED)
    assert img.ndim == 2
    for name in ("yolox-nano", "yolov3-tiny", "yolo11n-int8"):
        d = get_detector(detectors, models_dir, name).detect(img)
        labels = np.array(d.labels())
        near = d.boxes[labels == "car"]
        assert iou(near, np.array([990, 210, 1226, 370], np.float32)).max() > 0.6, name


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["yolov3-tiny", "yolox-nano", "fastestdet", "yolo11n-int8"])
def test_array_wise_equals_loop_on_real_raw_output(name, detectors, models_dir, street, kitti06):
    det = get_detector(detectors, models_dir, name)
    kitti = cv2.imread(str(require(kitti06 / "image_0/000010.png")), cv2.IMREAD_GRAYSCALE)
    for img in (street, kitti):
        raw = det.raw_outputs(img)
        rows = det.rows(raw)
        n_rows = sum(len(r) for r in rows) if isinstance(rows, list) else len(rows)
        assert n_rows >= 484
        for thr, dyn in ((det.score_threshold, det.dynamic), (0.05, None)):
            a = postprocess(rows, det.num_classes, det.layout, thr, 0.45, dyn)
            b = postprocess_loop(rows, det.num_classes, det.layout, thr, 0.45, dyn)
            assert len(a) > 0
            np.testing.assert_array_equal(a.rows, b.rows)
            np.testing.assert_array_equal(a.class_ids, b.class_ids)
            np.testing.assert_allclose(a.boxes, b.boxes, rtol=1e-6, atol=1e-4)
            np.testing.assert_allclose(a.scores, b.scores, rtol=1e-6)
        # detect == postprocess(raw_outputs) (and the loop path gives the same Detections)
        d1, d2 = det.postprocess(raw), det.postprocess(raw, loop=True)
        np.testing.assert_allclose(d1.boxes, d2.boxes, atol=1e-3)
        np.testing.assert_allclose(d1.boxes, det.detect(img).boxes, atol=1e-3)


@pytest.mark.realdata
def test_darknet_outputs_are_three_scales_stackable(detectors, models_dir, street):
    det = get_detector(detectors, models_dir, "yolov3-tiny")
    assert isinstance(det, DarknetDetector) and (det.input_w, det.input_h) == (416, 416)
    raw = det.raw_outputs(street)
    assert [o.shape for o in raw.outputs] == [(507, 85), (2028, 85)]
    # class scores include objectness (the DARKNET layout relies on it)
    o = np.concatenate(raw.outputs)
    assert (o[:, 5:].max(1) <= o[:, 4] + 1e-6).all()


@pytest.mark.realdata
def test_darknet_input_size_override(models_dir, street):
    require(models_dir / "yolov3-tiny")
    det = create_detector(DetectorConfig(name="yolov3-tiny", input_size=320), models_dir)
    assert (det.input_w, det.input_h) == (320, 320)
    d = det.detect(street)
    labels = np.array(d.labels())
    assert iou(d.boxes[labels == "person"], STREET_PERSON).max() > 0.5
    with pytest.raises(ConfigError, match="multiple of 32"):
        create_detector(DetectorConfig(name="yolov3-tiny", input_size=300), models_dir)
    with pytest.raises(ConfigError, match="fixed"):
        create_detector(DetectorConfig(name="yolox-nano", input_size=320), models_dir)


@pytest.mark.realdata
def test_model_paths_and_layout_autodetection(models_dir, street):
    cases = {
        models_dir / "yolov3-tiny/yolov3-tiny.cfg": DarknetDetector,
        models_dir / "yolox-nano/yolox_nano.onnx": YoloxDetector,
        models_dir / "fastestdet/FastestDet.onnx": FastestDetDetector,
        models_dir / "yolo11n-int8/yolo11n_int8.onnx": UltralyticsDetector,
        models_dir / "yolov8n-seg-int8/yolov8n-seg_int8.onnx": UltralyticsSegModel,
    }
    for path, cls in cases.items():
        det = create_detector(DetectorConfig(name=str(require(path))))
        assert type(det) is cls, path
        assert len(det.class_names) == 80


@pytest.mark.realdata
def test_seg_model_instance_masks(models_dir, street, kitti06):
    require(models_dir / "yolov8n-seg-int8")
    seg = create_seg_model("yolov8n-seg-int8", DetectorConfig(), models_dir)
    assert isinstance(seg, Detector)
    d = seg.detect(street)
    h, w = street.shape[:2]
    assert d.masks is not None and d.masks.shape == (len(d), h, w) and d.masks.dtype == bool
    labels = np.array(d.labels())
    assert "person" in labels and "car" in labels
    for m, b in zip(d.masks, d.boxes):
        x1, y1, x2, y2 = np.floor(b[:2]).astype(int).tolist() + np.ceil(b[2:]).astype(int).tolist()
        inside = m[y1:y2, x1:x2].sum()
        assert inside == m.sum()  # cropped to its box
        fill = inside / max((x2 - x1) * (y2 - y1), 1)
        assert 0.2 < fill < 0.99  # an outline, neither empty nor the whole box
    # the man on the left: his mask covers his torso, not the street beside him
    i = int(np.argmax(iou(d.boxes, STREET_PERSON) * (labels == "person")))
    assert iou(d.boxes[i : i + 1], STREET_PERSON)[0] > 0.6
    m = d.masks[i]
    assert m[680:720, 150:180].mean() > 0.9
    assert m[560:600, 75:95].mean() < 0.5  # upper-left corner of his box is background
    # a tall crop (letterbox padding left and right this time)
    tall = np.ascontiguousarray(street[:, :600])
    dt = seg.detect(tall)
    lt = np.array(dt.labels())
    j = int(np.argmax(iou(dt.boxes, STREET_PERSON) * (lt == "person")))
    assert iou(dt.boxes[j : j + 1], STREET_PERSON)[0] > 0.6
    assert dt.masks[j][680:720, 150:180].mean() > 0.9
    assert dt.masks[j][560:600, 75:95].mean() < 0.5
    # grayscale KITTI frame (the seg masker runs it on both images)
    k = cv2.imread(str(require(kitti06 / "image_0/000010.png")), cv2.IMREAD_GRAYSCALE)
    dk = seg.detect(k)
    assert dk.masks.shape == (len(dk), *k.shape)
    assert len(dk) >= 1 and dk.masks.any(axis=(1, 2)).all()


@pytest.mark.realdata
def test_seg_model_rejects_detection_models(models_dir):
    with pytest.raises(ModelError, match="not a segmentation model"):
        create_seg_model("yolox-nano", DetectorConfig(), models_dir)
    with pytest.raises(ModelError, match="expected a 'ultralytics-seg'"):
        create_seg_model(str(require(models_dir / "fastestdet/FastestDet.onnx")), DetectorConfig())


# --------------------------------------------------------------------------- errors


def test_unknown_detector_name_lists_known_models(tmp_path):
    with pytest.raises(ModelError) as e:
        create_detector(DetectorConfig(name="yolo-nonexistent"), tmp_path)
    msg = str(e.value)
    for n in ("yolov3", "yolov3-tiny", "yolox-nano", "fastestdet", "yolo11n-int8"):
        assert n in msg


def test_missing_model_files_name_path_and_download_command(tmp_path):
    with pytest.raises(ModelError) as e:
        create_detector(DetectorConfig(name="yolox-nano"), tmp_path)
    assert str(tmp_path / "yolox-nano" / "yolox_nano.onnx") in str(e.value)
    assert "dynastereo models download yolox-nano" in str(e.value)
    with pytest.raises(ModelError, match="yolov3.weights|yolov3.cfg"):
        create_detector(DetectorConfig(name="yolov3"), tmp_path)
    with pytest.raises(ModelError, match="no official download"):
        create_detector(DetectorConfig(name="yolo11n-int8"), tmp_path)


def test_path_errors(tmp_path):
    with pytest.raises(ModelError, match="not found") as e:
        create_detector(DetectorConfig(name=str(tmp_path / "nope.onnx")))
    assert "nope.onnx" in str(e.value)
    cfg = tmp_path / "mynet.cfg"
    cfg.write_text("[net]\nwidth=416\nheight=416\n[yolo]\nclasses=80\n")
    with pytest.raises(ModelError, match="mynet.weights"):
        create_detector(DetectorConfig(name=str(cfg)))
    bad = tmp_path / "broken.onnx"
    bad.write_bytes(b"this is not an onnx model")
    with pytest.raises(ModelError, match="broken.onnx"):
        create_detector(DetectorConfig(name=str(bad)))


@pytest.mark.realdata
def test_unknown_dynamic_class_is_a_config_error(models_dir):
    require(models_dir / "fastestdet")
    with pytest.raises(ConfigError, match="unicorn"):
        create_detector(DetectorConfig(name="fastestdet", dynamic_classes=["car", "unicorn"]), models_dir)


@pytest.mark.realdata
def test_class_names_file_mismatch(models_dir, tmp_path):
    src = require(models_dir / "fastestdet/FastestDet.onnx")
    (tmp_path / "FastestDet.onnx").symlink_to(src)
    (tmp_path / "coco.names").write_text("person\ncar\n")
    with pytest.raises(ModelError, match="80 class scores"):
        create_detector(DetectorConfig(name=str(tmp_path / "FastestDet.onnx")))


# ---------------------------------------------------------------- runtime


def test_runtime_resolution_and_fallback_line(caplog, monkeypatch):
    from dynastereo.masking.detection import runtime as rt

    monkeypatch.setattr(rt, "_NOTED", set())
    caplog.set_level("WARNING", logger="dynastereo.detector")
    # auto: OpenVINO where installed, bf16 only where the CPU computes in bf16
    assert rt.resolve_runtime("auto", "auto", have_openvino=True, caps=("FP32", "BF16")).label == "openvino/bf16"
    # ... and onnxruntime elsewhere (OpenVINO's f32 costs more CPU than onnxruntime's)
    assert rt.resolve_runtime("auto", "auto", have_openvino=True, caps=("FP32",)).label == "onnxruntime/f32"
    assert rt.resolve_runtime("auto", "f32", have_openvino=True, caps=("BF16",)).label == "onnxruntime/f32"
    assert rt.resolve_runtime("openvino", "auto", have_openvino=True, caps=("FP32",)).label == "openvino/f32"
    assert rt.resolve_runtime("onnxruntime", "auto", have_openvino=True, caps=("BF16",)).label == "onnxruntime/f32"
    assert not caplog.records  # nothing asked for that could not be had
    # openvino asked for but absent: onnxruntime, with ONE line (once per process)
    for _ in range(3):
        c = rt.resolve_runtime("openvino", "auto", have_openvino=False)
        assert c.label == "onnxruntime/f32"
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "OpenVINO is not installed" in lines[0] and "onnxruntime" in lines[0]
    # the default (auto) without the extra: onnxruntime, and one line says so too
    assert rt.resolve_runtime("auto", "auto", have_openvino=False).label == "onnxruntime/f32"
    assert rt.resolve_runtime("auto", "auto", have_openvino=False).label == "onnxruntime/f32"
    assert len(caplog.records) == 2 and "pip install 'dynastereo[openvino]'" in caplog.records[-1].getMessage()
    # bf16 on a CPU without it: f32, said once
    c = rt.resolve_runtime("openvino", "bf16", have_openvino=True, caps=("FP32", "INT8"))
    assert c.label == "openvino/f32" and "no bf16" in c.note
    assert len(caplog.records) == 3


def test_runtime_config_keys_validate():
    assert DetectorConfig().runtime == "onnxruntime" and DetectorConfig().precision == "auto"
    assert DetectorConfig(runtime="auto").runtime == "auto"
    with pytest.raises(ConfigError, match="detector.runtime"):
        DetectorConfig(runtime="tensorrt")
    with pytest.raises(ConfigError, match="detector.precision"):
        DetectorConfig(precision="fp8")


def _near_boxes(d, min_area: float = 2000.0) -> np.ndarray:
    wh = d.boxes[:, 2:] - d.boxes[:, :2]
    return d.boxes[wh[:, 0] * wh[:, 1] >= min_area]


@pytest.mark.realdata
@pytest.mark.parametrize("grey_input", [False, True])
def test_openvino_matches_onnxruntime_on_kitti_frames(models_dir, kitti06, grey_input):
    """OpenVINO f32 and bf16 find the same near vehicles as onnxruntime on real frames
    (the sequences' recall and IoU move by <= 0.01: docs/guide/masking.md, "Detectors and models"), with
    the grey frames as three equal channels and into the one-channel graph."""
    from dynastereo.masking.detection import ScaledDetector, openvino_available
    from dynastereo.masking.boxes import box_iou

    if not openvino_available():
        skip_or_fail("OpenVINO is not installed (pip install 'dynastereo[openvino]')")
    require(models_dir / "yolox-nano", "model yolox-nano")
    runs = {}
    for label, kw in {"ort": {"runtime": "onnxruntime"}, "f32": {"runtime": "openvino", "precision": "f32"},
                      "bf16": {"runtime": "openvino", "precision": "bf16"}}.items():
        det = create_detector(DetectorConfig(threads=1, grey_input=grey_input, **kw), models_dir)
        want = "onnxruntime/f32" if label == "ort" else f"openvino/{kw['precision']}"
        if label == "bf16" and det.runtime.precision != "bf16":
            want = "openvino/f32"  # a CPU without bf16: f32 (resolve_runtime says so)
        assert det.runtime.label == want
        runs[label] = ScaledDetector(det, "frame", 1.0)
    best: dict[str, list[float]] = {"f32": [], "bf16": []}
    for k in range(0, 51, 10):
        img = cv2.imread(str(require(kitti06 / f"image_0/{k:06d}.png")), cv2.IMREAD_UNCHANGED)
        ref = _near_boxes(runs["ort"].detect(img))
        for label in best:
            got = runs[label].detect(img)
            if len(ref):
                iou = box_iou(ref, got.boxes) if len(got) else np.zeros((len(ref), 1))
                best[label] += iou.max(axis=1).tolist()
    f32, bf16 = np.array(best["f32"]), np.array(best["bf16"])
    assert len(f32) >= 10  # the frames hold near vehicles to compare
    assert (f32 >= 0.98).all(), f32  # f32: the same network, the same boxes
    # bf16: a box near the score threshold may come or go (2 of 18 here with three channels,
    # 4 of 18 into the one-channel graph: the sequences' near-vehicle recall is unchanged
    # either way, bench_recall.py rows "ov bf16 1t band .25 carry/2 [3 channels]"); the rest agree
    assert (bf16 >= 0.5).mean() >= (0.75 if grey_input else 0.85) and np.median(bf16) >= 0.95, bf16


@pytest.mark.realdata
def test_yolox_grey_input_blob_equals_the_bgr_one(models_dir, kitti06):
    """A grey frame is letterboxed once and copied to the 3 channels: the same network
    input, bit for bit, as the colour path (grey -> BGR, letterbox, blobFromImage) --
    or, with ``grey_input`` (the default), that blob's one channel for the grey graph."""
    require(models_dir / "yolox-nano", "model yolox-nano")
    img = cv2.imread(str(require(kitti06 / "image_0/000010.png")), cv2.IMREAD_GRAYSCALE)
    for grey_input in (False, True):
        det = create_detector(DetectorConfig(name="yolox-nano", runtime="onnxruntime", grey_input=grey_input),
                              models_dir)
        for d in (det, det.with_canvas(1248, 384)):
            grey, (tg, sg, _) = d._prepare(img)
            bgr, (tb, sb, _) = d._prepare(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
            assert sg == sb and tg == tb
            # three equal channels, or the one channel of the grey-input graph
            assert np.array_equal(grey, bgr) if not grey_input else np.array_equal(grey[:, 0], bgr[:, 0])
            assert grey.shape[1] == (1 if grey_input else 3)
            grey1, _ = d._prepare(img[:, :, None])
            assert np.array_equal(grey1, grey)


@pytest.mark.realdata
def test_yolox_grey_input_graph_finds_the_same_boxes(models_dir, kitti06):
    """The one-channel YOLOX graph (its first convolution's weights summed over the three
    equal channels: rewrite.py "Grey input") computes the three-channel network's function:
    on KITTI frames at the frame's canvas its raw outputs agree to float rounding and its
    detections are the same boxes (within 0.05 px), classes and scores; a colour frame still
    runs the three-channel graph, and a grey frame the one-channel one."""
    from dynastereo.masking.detection import ScaledDetector

    require(models_dir / "yolox-nano", "model yolox-nano")
    base = create_detector(DetectorConfig(name="yolox-nano", runtime="onnxruntime"), models_dir)
    one = base.with_canvas(1248, 384)
    three = create_detector(DetectorConfig(name="yolox-nano", runtime="onnxruntime", grey_input=False),
                            models_dir).with_canvas(1248, 384)
    assert one._grey and not three._grey and one._grey_session is None
    n_boxes = 0
    for k in range(0, 51, 10):
        img = cv2.imread(str(require(kitti06 / f"image_0/{k:06d}.png")), cv2.IMREAD_GRAYSCALE)
        r1, r3 = one.raw_outputs(img), three.raw_outputs(img)
        assert r1.outputs[0].shape == r3.outputs[0].shape
        np.testing.assert_allclose(r1.outputs[0], r3.outputs[0], atol=2e-3, rtol=1e-3)
        d1 = ScaledDetector(one, "frame", 1.0).detect(img)
        d3 = ScaledDetector(three, "frame", 1.0).detect(img)
        assert len(d1) == len(d3) and list(d1.labels()) == list(d3.labels())
        np.testing.assert_allclose(d1.boxes, d3.boxes, atol=0.05)
        np.testing.assert_allclose(d1.scores, d3.scores, atol=1e-3)
        n_boxes += len(d1)
    assert n_boxes >= 10 and one._grey_session is not None
    colour = create_detector(DetectorConfig(name="yolox-nano", runtime="onnxruntime"), models_dir)
    colour.detect(np.zeros((96, 128, 3), np.uint8) + np.uint8([0, 60, 120]))
    assert colour._grey_session is None  # a colour frame: the three-channel graph


@pytest.mark.realdata
@pytest.mark.parametrize("canvas", ["tiles", "model"])
def test_grey_input_graph_on_tiles_and_the_model_canvas(models_dir, kitti06, canvas):
    """The one-channel graph also runs batched (three tiles in one call) and at the model's
    own square canvas: the same boxes as three equal channels, within 0.05 px."""
    from dynastereo.masking.detection import ScaledDetector

    require(models_dir / "yolox-nano", "model yolox-nano")
    img = cv2.imread(str(require(kitti06 / "image_0/000020.png")), cv2.IMREAD_GRAYSCALE)
    got = {}
    for grey in (True, False):
        base = create_detector(DetectorConfig(name="yolox-nano", runtime="onnxruntime", grey_input=grey), models_dir)
        got[grey] = ScaledDetector(base, canvas, 1.0, tiles=3).detect(img)
    assert len(got[True]) == len(got[False]) >= 1
    assert list(got[True].labels()) == list(got[False].labels())
    np.testing.assert_allclose(got[True].boxes, got[False].boxes, atol=0.05)


@pytest.mark.realdata
def test_warm_up_makes_the_grey_graph_before_the_first_frame(models_dir, kitti06):
    """The detection stage's warm-up runs YOLOX on a colour and a grey black frame, so the
    frame loop's first grey frame finds its one-channel session made (its creation is not
    paid inside the loop), and the first detections are those without a warm-up."""
    from dynastereo.masking.detection.stage import DetectionStage

    require(models_dir / "yolox-nano", "model yolox-nano")
    img = cv2.imread(str(require(kitti06 / "image_0/000010.png")), cv2.IMREAD_GRAYSCALE)
    cfg = DetectorConfig(name="yolox-nano", runtime="onnxruntime")
    stage = DetectionStage(create_detector(cfg, models_dir), cfg)
    stage.warm_up(*img.shape)
    _, planned = stage.detector.plan(img.shape[1], img.shape[0])
    assert planned.grey_graph and planned._grey_session is not None
    cold = DetectionStage(create_detector(cfg, models_dir), cfg)
    np.testing.assert_array_equal(stage.detect(img).boxes, cold.detect(img).boxes)


@pytest.mark.realdata
def test_grey_input_falls_back_to_three_channels(models_dir, kitti06, monkeypatch, caplog):
    """A YOLOX export whose stem cannot be folded runs grey frames as three equal channels
    (the same boxes as grey_input false, bit for bit), with one line saying so."""
    import logging

    from dynastereo.masking.detection import onnx as onnx_mod

    require(models_dir / "yolox-nano", "model yolox-nano")
    img = cv2.imread(str(require(kitti06 / "image_0/000010.png")), cv2.IMREAD_GRAYSCALE)
    three = create_detector(DetectorConfig(name="yolox-nano", runtime="onnxruntime", grey_input=False), models_dir)
    want = three.detect(img).boxes

    def refuse(path, layout, w, h, batch=1, grey=False):
        raise ModelError("not the expected YOLOX export: no Focus concat", path)

    det = create_detector(DetectorConfig(name="yolox-nano", runtime="onnxruntime"), models_dir)
    monkeypatch.setattr(onnx_mod, "rewrite", refuse)
    with caplog.at_level(logging.INFO, logger="dynastereo"):
        got = det.detect(img).boxes
        again = det.detect(img).boxes
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(again, want)
    assert not det._grey and "three equal channels" in caplog.text


def test_grey_input_only_for_yolox_and_a_boolean(tmp_path):
    """Only YOLOX has a grey-input form; ``detector.grey_input`` is true or false."""
    from dynastereo.masking.detection.rewrite import rewrite

    with pytest.raises(ModelError, match="no grey-input form"):
        rewrite(tmp_path / "m.onnx", "fastestdet", 352, 352, grey=True)
    with pytest.raises(ConfigError, match="detector.grey_input"):
        DetectorConfig(grey_input="yes")
    assert DetectorConfig().grey_input is True


@pytest.mark.realdata
def test_grey_input_rewrite_refuses_other_graphs(models_dir):
    """A graph not built as YOLOX's stem (Focus slices, a 4 x 3-channel concat, then the
    first convolution) is an error naming the file."""
    from dynastereo.masking.detection.rewrite import rewrite

    fastest = require(models_dir / "fastestdet" / "FastestDet.onnx", "FastestDet model")
    with pytest.raises(ModelError, match="FastestDet.onnx"):
        rewrite(fastest, "yolox", 352, 352, grey=True)


@pytest.mark.realdata
def test_openvino_session_threads_and_streams(models_dir):
    """OpenVINO is set up like onnxruntime (tests/test_realtime.py): a fixed thread count,
    one stream, no pinning -- the detector leaves the tracking its core."""
    from dynastereo.masking.detection import OpenVinoSession, openvino_available

    if not openvino_available():
        skip_or_fail("OpenVINO is not installed (pip install 'dynastereo[openvino]')")
    model = require(models_dir / "yolox-nano" / "yolox_nano.onnx", "YOLOX-nano model")
    s = OpenVinoSession(model, 1, "f32")
    assert int(s.compiled.get_property("INFERENCE_NUM_THREADS")) == 1
    assert int(s.compiled.get_property("NUM_STREAMS")) == 1
    assert str(s.compiled.get_property("ENABLE_CPU_PINNING")).lower() in ("false", "no")
    assert [o.name for o in s.get_inputs()] and len(s.get_outputs()) == 1


@pytest.mark.realdata
def test_quantize_writes_a_qdq_graph_with_an_f32_head(models_dir, kitti03, tmp_path):
    """masking/detection/quantize.py (the INT8 measurement, docs/guide/masking.md, "Runtime and precision"): a QDQ
    copy calibrated on unscored frames, its head left in f32, readable by onnxruntime."""
    import onnx
    import onnxruntime as ort

    from dynastereo.masking.detection.quantize import quantize_detector

    require(models_dir / "yolox-nano", "model yolox-nano")
    images = sorted((kitti03 / "image_0").glob("*.png"))[:2]
    out = quantize_detector(str(models_dir / "yolox-nano/yolox_nano.onnx"), images, tmp_path / "q.onnx",
                            canvas=(320, 96))
    g = onnx.load(str(out)).graph
    ops = [n.op_type for n in g.node]
    assert "QuantizeLinear" in ops and "DequantizeLinear" in ops
    dims = [d.dim_value for d in g.input[0].type.tensor_type.shape.dim]
    assert dims == [1, 3, 96, 320]
    # the head's last convolutions take f32 weights (no DequantizeLinear in front)
    deq = {o for n in g.node if n.op_type == "DequantizeLinear" for o in n.output}
    preds = [n for n in g.node if n.op_type == "Conv" and "_preds" in "".join(n.input)]
    assert len(preds) == 9 and not any(n.input[1] in deq for n in preds)
    s = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    y = s.run(None, {s.get_inputs()[0].name: np.zeros((1, 3, 96, 320), np.float32)})[0]
    assert y.shape[-1] == 85


def test_two_inference_threads_give_the_same_boxes_bit_for_bit(models_dir, kitti06):
    """``detector.threads: 2`` (the default) halves the network's wall time; the boxes and
    scores must be those of one thread exactly, so a live node and an offline run agree."""
    from dynastereo.masking.detection.stage import DetectionStage

    require(models_dir / "yolox-nano", "model yolox-nano")
    stages = {t: DetectionStage(create_detector(DetectorConfig(threads=t), models_dir), DetectorConfig(threads=t))
              for t in (1, 2)}
    n = 0
    for k in range(0, 51, 5):
        img = cv2.imread(str(require(kitti06 / f"image_0/{k:06d}.png")), cv2.IMREAD_UNCHANGED)
        one, two = (stages[t].detect(img) for t in (1, 2))
        np.testing.assert_array_equal(one.boxes, two.boxes)
        np.testing.assert_array_equal(one.scores, two.scores)
        np.testing.assert_array_equal(one.class_ids, two.class_ids)
        n += len(one)
    assert n >= 20  # the frames hold boxes to compare
