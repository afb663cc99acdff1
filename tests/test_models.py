"""Model registry and download: the real download code against a local HTTP mirror."""

from __future__ import annotations

import functools
import hashlib
import http.server
import threading
from pathlib import Path

import pytest

from conftest import require
from dynastereo.config import DetectorConfig
from dynastereo.errors import ModelError
from dynastereo.models import (
    KNOWN_MODELS,
    ModelFile,
    check_file,
    download,
    download_models,
    list_models,
    model_path,
    resolve_models_dir,
    verify,
)
from dynastereo.models import registry


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format, *args):  # noqa: A002 - keep the test output clean
        pass


def _serve(directory: Path):
    handler = functools.partial(_QuietHandler, directory=str(directory))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    return server, f"http://127.0.0.1:{server.server_address[1]}"


@pytest.fixture()
def mirror(models_dir: Path):
    """A local HTTP server serving the real model folder (<name>/<file>)."""
    server, url = _serve(models_dir)
    yield url
    server.shutdown()
    server.server_close()


@pytest.fixture()
def bad_mirror(tmp_path: Path, models_dir: Path):
    """A mirror whose FastestDet.onnx has the right size but the wrong bytes."""
    root = tmp_path / "badmirror"
    (root / "fastestdet").mkdir(parents=True)
    real = require(models_dir / "fastestdet/FastestDet.onnx")
    data = bytearray(real.read_bytes())
    data[1000:1010] = b"0123456789"
    (root / "fastestdet/FastestDet.onnx").write_bytes(bytes(data))
    (root / "fastestdet/coco.names").write_bytes((models_dir / "fastestdet/coco.names").read_bytes())
    (root / "yolox-nano").mkdir()
    (root / "yolox-nano/yolox_nano.onnx").write_bytes(b"short")
    server, url = _serve(root)
    yield url
    server.shutdown()
    server.server_close()


def _leftovers(d: Path) -> list[str]:
    return sorted(p.name for p in d.rglob("*") if p.is_file()) if d.exists() else []


@pytest.mark.realdata
def test_registry_checksums_match_the_reference_models(models_dir):
    """Every model present in DYNASTEREO_MODELS verifies against the registry."""
    checked = 0
    for name in KNOWN_MODELS:
        if not (models_dir / name).is_dir():
            assert name == "yolov3", f"reference model folder {name} missing"
            continue
        assert verify(name, models_dir) == [], name
        checked += 1
    assert checked == 5


@pytest.mark.realdata
def test_download_through_mirror(tmp_path, mirror, models_dir):
    dest = tmp_path / "models"
    paths = download_models(["fastestdet", "yolox-nano"], dest, mirror=mirror, progress=False)
    assert sorted(p.relative_to(dest).as_posix() for p in paths) == [
        "fastestdet/FastestDet.onnx",
        "fastestdet/coco.names",
        "yolox-nano/coco.names",
        "yolox-nano/yolox_nano.onnx",
    ]
    for p in paths:
        assert hashlib.sha256(p.read_bytes()).hexdigest() == hashlib.sha256(
            (models_dir / p.relative_to(dest)).read_bytes()
        ).hexdigest()
    assert verify("fastestdet", dest) == [] and verify("yolox-nano", dest) == []
    assert not [n for n in _leftovers(dest) if n.endswith(".part")]
    # the downloaded models work
    from dynastereo.masking.detection import create_detector

    det = create_detector(DetectorConfig(name="fastestdet"), dest)
    assert det.name == "fastestdet"


@pytest.mark.realdata
def test_download_skips_files_already_verified(tmp_path, mirror, monkeypatch):
    dest = tmp_path / "m"
    download("fastestdet", dest, mirror=mirror, progress=True)  # also exercises the progress bar

    def boom(*a, **k):
        raise AssertionError("should not download again")

    monkeypatch.setattr(registry, "_fetch", boom)
    assert len(download("fastestdet", dest, mirror=mirror, progress=False)) == 2
    # a corrupted local file is fetched again
    monkeypatch.undo()
    (dest / "fastestdet/FastestDet.onnx").write_bytes(b"corrupt")
    assert verify("fastestdet", dest)
    download("fastestdet", dest, mirror=mirror, progress=False)
    assert verify("fastestdet", dest) == []


@pytest.mark.realdata
def test_mirror_from_environment(tmp_path, mirror, monkeypatch):
    monkeypatch.setenv("DYNASTEREO_MODEL_MIRROR", mirror)
    paths = download("yolo11n-int8", tmp_path, progress=False)  # AGPL: only via a mirror
    assert [p.name for p in paths] == ["yolo11n_int8.onnx"]
    assert verify("yolo11n-int8", tmp_path) == []


@pytest.mark.realdata
def test_wrong_content_raises_and_leaves_nothing(tmp_path, bad_mirror):
    dest = tmp_path / "dest"
    with pytest.raises(ModelError) as e:
        download("fastestdet", dest, mirror=bad_mirror, progress=False)
    msg = str(e.value)
    spec = KNOWN_MODELS["fastestdet"].files[0]
    assert "FastestDet.onnx" in msg and spec.sha256 in msg and "actual" in msg
    actual = msg.split("actual ")[1].split(";")[0].strip()
    assert len(actual) == 64 and actual != spec.sha256
    assert not (dest / "fastestdet/FastestDet.onnx").exists()
    assert "FastestDet.onnx" not in " ".join(_leftovers(dest))  # no temporary file either
    with pytest.raises(ModelError, match="expected 3678356"):
        download("yolox-nano", dest, mirror=bad_mirror, progress=False)
    assert not [n for n in _leftovers(dest) if "yolox" in n]


@pytest.mark.realdata
def test_missing_file_on_server(tmp_path, bad_mirror):
    # the bad mirror has no yolov3-tiny folder: HTTP 404
    with pytest.raises(ModelError, match="download of .*yolov3-tiny.cfg failed"):
        download("yolov3-tiny", tmp_path / "dest", mirror=bad_mirror, progress=False)
    assert _leftovers(tmp_path / "dest") == []


def test_agpl_models_have_no_official_download(tmp_path, monkeypatch):
    monkeypatch.delenv("DYNASTEREO_MODEL_MIRROR", raising=False)
    for name in ("yolo11n-int8", "yolov8n-seg-int8"):
        spec = KNOWN_MODELS[name]
        assert spec.baseline_only and "AGPL" in spec.licence
        assert all(f.url is None for f in spec.files)
        with pytest.raises(ModelError, match="no official download"):
            download(name, tmp_path, progress=False)
    assert not KNOWN_MODELS[DetectorConfig().name].baseline_only


def test_registry_official_addresses():
    urls = {f.filename: f.url for s in KNOWN_MODELS.values() for f in s.files}
    assert urls["yolov3.weights"] == "https://pjreddie.com/media/files/yolov3.weights"
    assert urls["yolov3-tiny.weights"] == "https://pjreddie.com/media/files/yolov3-tiny.weights"
    assert "Megvii-BaseDetection/YOLOX/releases/download/0.1.1rc0/yolox_nano.onnx" in urls["yolox_nano.onnx"]
    assert "dog-qiuqiu/FastestDet" in urls["FastestDet.onnx"]
    assert urls["coco.names"].endswith("darknet/master/data/coco.names")
    y3 = {f.filename: f for f in KNOWN_MODELS["yolov3"].files}
    assert y3["yolov3.weights"].size == 248_007_048
    assert y3["yolov3.weights"].sha256 == "523e4e69e1d015393a1b0a441cef1d9c7659e3eb2d7e15f793f060a21b32f297"
    for s in KNOWN_MODELS.values():
        assert s.kind in ("darknet", "onnx", "seg")
        for f in s.files:
            assert f.sha256 is None or len(f.sha256) == 64
            assert f.sha256 is not None or f.filename == "yolov3.cfg"


def test_check_file_without_sha_checks_size_and_structure(tmp_path):
    good = tmp_path / "net.cfg"
    good.write_text("[net]\nwidth=416\n[yolo]\nclasses=80\n")
    spec = ModelFile("net.cfg", None, None, good.stat().st_size)
    assert check_file(good, spec) is None
    assert "size" in check_file(good, ModelFile("net.cfg", None, None, 1))
    bad = tmp_path / "bad.cfg"
    bad.write_text("<html>not found</html>" + " " * (good.stat().st_size - 22))
    assert "not a Darknet" in check_file(bad, ModelFile("bad.cfg", None, None, bad.stat().st_size))
    assert "missing" in check_file(tmp_path / "absent.cfg", spec)


def test_resolve_models_dir_precedence(tmp_path, monkeypatch):
    from dynastereo.models import registry

    monkeypatch.setattr(registry, "checkout_shared_models", lambda: None)
    monkeypatch.setenv("DYNASTEREO_MODELS", str(tmp_path / "env"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert resolve_models_dir(tmp_path / "explicit") == tmp_path / "explicit"
    assert resolve_models_dir() == tmp_path / "env"
    monkeypatch.delenv("DYNASTEREO_MODELS")
    assert resolve_models_dir() == tmp_path / "xdg/dynastereo/models"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert resolve_models_dir() == tmp_path / "home/.cache/dynastereo/models"


def test_models_dir_found_beside_a_checkout_when_nothing_else_is_set(tmp_path, monkeypatch):
    """Neither --models-dir nor $DYNASTEREO_MODELS, an empty cache: ../shared/models beside the
    checkout (where .ci/run finds it); a cache that holds models still wins."""
    from dynastereo.models import registry

    shared = tmp_path / "shared" / "models"
    shared.mkdir(parents=True)
    monkeypatch.setattr(registry, "checkout_shared_models", lambda: shared)
    monkeypatch.delenv("DYNASTEREO_MODELS", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert resolve_models_dir() == shared
    (tmp_path / "xdg/dynastereo/models/yolox-nano").mkdir(parents=True)
    assert resolve_models_dir() == tmp_path / "xdg/dynastereo/models"


def test_download_failure_is_one_short_line() -> None:
    from dynastereo.models.registry import download_reason

    e = ConnectionError("HTTPSConnectionPool(host='github.com', port=443): Max retries exceeded with url: /x "
                        "(Caused by NameResolutionError(\"<urllib3.connection.HTTPSConnection object at 0x7f>: "
                        "Failed to resolve 'github.com' ([Errno -3] Temporary failure in name resolution)\"))")
    assert download_reason(e) == "the host name cannot be resolved (no network or no DNS)"
    assert len(download_reason(ValueError("x" * 500))) <= 160


def test_model_path_layout_and_unknown_name(tmp_path):
    assert model_path("yolox-nano", tmp_path) == tmp_path / "yolox-nano/yolox_nano.onnx"
    assert model_path("yolov3-tiny", tmp_path) == tmp_path / "yolov3-tiny/yolov3-tiny.cfg"
    with pytest.raises(ModelError, match="known models: yolov3, yolov3-tiny"):
        model_path("nope", tmp_path)
    with pytest.raises(ModelError, match="unknown model 'nope'"):
        download_models(["nope"], tmp_path, progress=False)
    with pytest.raises(ModelError, match="unknown model"):
        verify("nope", tmp_path)


def test_verify_reports_missing_files(tmp_path):
    problems = verify("yolov3", tmp_path)
    assert len(problems) == 3 and all("missing" in p for p in problems)
    assert str(tmp_path / "yolov3/yolov3.weights") in " ".join(problems)


@pytest.mark.realdata
def test_list_models(models_dir, tmp_path):
    rows = {m["name"]: m for m in list_models(models_dir)}
    assert list(rows) == list(KNOWN_MODELS)
    for key in ("name", "kind", "licence", "files", "url", "sha256", "present", "verified"):
        assert key in rows["yolox-nano"]
    assert rows["yolox-nano"]["present"] and rows["yolox-nano"]["verified"]
    assert rows["yolo11n-int8"]["verified"] and rows["yolo11n-int8"]["url"] is None
    assert not rows["yolov3"]["present"]
    statuses = {f["filename"]: f["status"] for f in rows["yolov3-tiny"]["files"]}
    assert statuses == {"yolov3-tiny.cfg": "ok", "yolov3-tiny.weights": "ok", "coco.names": "ok"}
    empty = list_models(tmp_path)
    assert all(f["status"] == "missing" for m in empty for f in m["files"])
    (tmp_path / "fastestdet").mkdir()
    (tmp_path / "fastestdet/FastestDet.onnx").write_bytes(b"x")
    bad = {m["name"]: m for m in list_models(tmp_path)}["fastestdet"]["files"][0]
    assert bad["present"] and not bad["verified"] and bad["status"].startswith("bad:")
