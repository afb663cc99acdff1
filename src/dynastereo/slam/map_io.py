"""Saving and loading a SLAM map (``--save-map`` / ``--load-map``): the ``dynastereo-map`` file.

    mf = map_file_from_system(system, meta={"sequence": str(seq_path)})
    save_map("run/map.dsmap", mf)                      # atomic: temp file + os.replace
    mf = load_map("run/map.dsmap")                     # MapFileError on any problem
    check_compatible(mf, sequence.calibration, orb_settings(config), "run/map.dsmap")

One file, a zip archive: ``header.json`` (format name, version, counts, calibration,
ORB settings, disparity offset, free-form meta) and one ``.npy`` entry per array
(``points/pos``, ``obs/kf``, ``keypoints/uv``, ...), arrays trimmed to their used
length; keyframes are packed into concatenated per-keypoint arrays with offsets, the
covisibility graph is an edge list.  No pickle anywhere: every entry is read with
``allow_pickle=False``.  The layout, dtypes, units, frames and the versioning policy
are documented in ``docs/reference/map-format.md``.

This module is the container only: the header (format, version, counts, calibration,
ORB settings, disparity offset, vocabulary / bag-of-words descriptors, meta), the zip
archive (atomic save, per-entry compression, no pickle) and the checks that need the
header (counts, version, ORB levels, another camera).  The arrays are the map's own:
``Map.to_arrays()`` / ``Map.from_arrays()``, which take the point and observation
tables' (``MapPoints``, ``Observations``) and pack the keyframes; a stored vocabulary
is ``Vocabulary.to_arrays()`` / ``from_arrays()``.  Every entry's dtype and shape and
the cross references between the tables are checked on load, so a corrupt or
inconsistent file is a :class:`~dynastereo.errors.MapFileError` naming the file and
the problem, never an ``IndexError`` later in tracking.
"""

from __future__ import annotations

import datetime as _dt
import io
import json
import math
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from .. import __version__
from ..errors import MapFileError
from ..io.outputs import atomic_open
from ..datatypes import StereoCalibration
from .map import COUNTS, Map
from .table import check_entry

FORMAT = "dynastereo-map"
VERSION = 1
HEADER = "header.json"

# check_compatible tolerances: relative for fx, fy and the baseline, pixels for cx, cy
REL_TOL = 1e-3
PX_TOL = 0.5


class ArrayVocabulary(Protocol):
    """What a vocabulary stored in a map file must offer (duck typing)."""

    def to_arrays(self) -> dict[str, np.ndarray]: ...

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> "ArrayVocabulary": ...


@dataclass
class MapFile:
    """Everything a map file holds.

    ``calibration`` is the rectified rig every keyframe was made with; ``disparity_offset``
    the offset (px) already applied to the keyframes' stereo observations (``u_right``,
    ``depth``), which a system tracking in the map must apply to its frames too; ``orb``
    the extractor settings (``n_features``, ``scale_factor``, ``n_levels``); ``bow`` the
    optional per-keyframe bag of words ``{keyframe id: (word ids, weights)}``;
    ``meta`` free-form JSON data (``save_map`` adds ``created`` and
    ``dynastereo_version`` when absent)."""

    map: Map
    calibration: StereoCalibration
    disparity_offset: float
    orb: dict
    vocabulary: ArrayVocabulary | None = None
    bow: dict[int, tuple[np.ndarray, np.ndarray]] | None = None
    meta: dict = field(default_factory=dict)


# ---------------------------------------------------------------------- layout
# the map's entries (``Map.entries()``: its tables' and its own) and, optionally, these
BOW_ENTRIES: dict[str, tuple[np.dtype | str, tuple]] = {
    "bow/kf": (np.dtype("<i8"), ("bow_keyframes",)),
    "bow/offsets": (np.dtype("<i8"), ("bow_keyframes+1",)),
    "bow/words": ("i", ("bow_entries",)),  # integer kind, dtype as the vocabulary made it
    "bow/weights": ("f", ("bow_entries",)),  # floating kind, likewise
}
# entries that deflate gains < 10 % on (descriptors, point positions / normals / distances,
# keypoint angles: measured on KITTI maps) are stored; everything else (ids, rows, levels,
# flags, uv, stereo) is deflated at level 1: 2-10x smaller, fast.  uint8 vocabulary
# arrays (word centres: descriptors) are stored too
_STORED = {"points/desc", "keypoints/desc", "points/pos", "points/normal", "points/min_dist", "points/max_dist",
           "keypoints/angle"}


# ------------------------------------------------------------------- helpers
def orb_settings(cfg: Any) -> dict:
    """The ``orb`` dict of a map file from a ``Config`` / ``SlamConfig`` (or a dict)."""
    if isinstance(cfg, dict):
        return {"n_features": int(cfg["n_features"]), "scale_factor": float(cfg["scale_factor"]),
                "n_levels": int(cfg["n_levels"])}
    slam = getattr(cfg, "slam", cfg)
    return {"n_features": int(slam.n_features), "scale_factor": float(slam.scale_factor),
            "n_levels": int(slam.n_levels)}


def map_file_from_system(system: Any, meta: dict | None = None, vocabulary: Any = None,
                         bow: dict | None = None) -> MapFile:
    """A :class:`MapFile` of ``system``'s current map (call it after ``shutdown()`` or
    once the pending local BA is applied, so the saved map is the final one)."""
    return MapFile(system.map, system.calib, float(system.disparity_offset), orb_settings(system.cfg),
                   vocabulary, bow, dict(meta or {}))


def _calib_dict(c: StereoCalibration) -> dict:
    return {"K": np.asarray(c.K, float).tolist(), "baseline": float(c.baseline), "width": int(c.width),
            "height": int(c.height)}


def _same_calib(a: StereoCalibration, b: StereoCalibration) -> bool:
    return a is b or (a.width == b.width and a.height == b.height and a.baseline == b.baseline
                      and np.array_equal(a.K, b.K))


def _json_default(o: Any) -> Any:
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (_dt.datetime, _dt.date)):
        return o.isoformat()
    if isinstance(o, (set, tuple)):
        return list(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    # (not np.ascontiguousarray: it turns 0-d arrays into 1-d ones; write_array writes C order)
    np.lib.format.write_array(buf, np.asarray(a), allow_pickle=False)
    return buf.getvalue()


# ----------------------------------------------------------------------- save
def _collect(mf: MapFile) -> tuple[dict, dict[str, np.ndarray]]:
    """(header, arrays) of a map file; raises ValueError / TypeError for a bad MapFile."""
    off, orb = _check_map_file(mf)
    mp, calib = mf.map, mf.calibration
    arrays = mp.to_arrays()
    header_counts = Map.counts_of(arrays)
    bow_hdr = _bow_arrays(mf, arrays, header_counts)  # optional: bag of words per keyframe
    vocab_hdr = _vocabulary_arrays(mf, arrays)  # optional: the vocabulary's arrays
    meta = dict(mf.meta or {})
    meta.setdefault("created", _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
    meta.setdefault("dynastereo_version", __version__)
    header = {
        "format": FORMAT,
        "version": VERSION,
        "counts": header_counts,
        "next_kf_id": int(mp.next_kf_id),
        "calibration": _calib_dict(calib),
        "disparity_offset": off,
        "orb": orb,
        "vocabulary": vocab_hdr,
        "bow": bow_hdr,
        "meta": meta,
    }
    try:
        json.dumps(header, default=_json_default, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(f"map file header (meta / orb) is not JSON data: {e}") from None
    return header, arrays


def _check_map_file(mf: MapFile) -> tuple[float, dict]:
    """``(disparity offset, ORB settings)`` of a map file whose map, calibration, offset and
    ORB settings agree; raises ValueError / TypeError otherwise."""
    mp, calib = mf.map, mf.calibration
    if not isinstance(mp, Map):
        raise TypeError(f"MapFile.map must be a dynastereo.slam.map.Map, got {type(mp).__name__}")
    if not isinstance(calib, StereoCalibration):
        raise TypeError(f"MapFile.calibration must be a StereoCalibration, got {type(calib).__name__}")
    off = float(mf.disparity_offset)
    if not math.isfinite(off):
        raise ValueError(f"disparity_offset must be finite, got {off}")
    orb = dict(mf.orb)
    for k in ("n_features", "scale_factor", "n_levels"):
        if k not in orb:
            raise ValueError(f"MapFile.orb lacks {k!r} (use map_io.orb_settings(config))")
    if int(orb["n_levels"]) != mp.n_levels or (
        mp.n_levels > 1 and not math.isclose(float(orb["scale_factor"]), float(mp.scales[1]), rel_tol=1e-6)
    ):
        raise ValueError(
            f"MapFile.orb (scale_factor {orb['scale_factor']}, n_levels {orb['n_levels']}) disagrees with the "
            f"map's scale pyramid ({mp.n_levels} levels, factor {mp.scales[1] if mp.n_levels > 1 else 1.0:g})"
        )
    for kf in mp.keyframes.values():
        if not _same_calib(kf.calib, calib):
            raise ValueError(f"keyframe {kf.id} has another calibration than MapFile.calibration")
    return off, orb


def _bow_arrays(mf: MapFile, arrays: dict[str, np.ndarray], header_counts: dict) -> dict | None:
    """The keyframes' bags of words (``mf.bow``) added to ``arrays`` and their counts to
    ``header_counts``; returns the header's ``bow`` entry (None without them)."""
    mp = mf.map
    bow_hdr = None
    if mf.bow is not None:
        ids = [int(k) for k in mf.bow]
        missing = [k for k in ids if k not in mp.keyframes]
        if missing:
            raise ValueError(f"bow given for keyframes not in the map: {missing[:5]}")
        words = [np.asarray(mf.bow[k][0]).reshape(-1) for k in mf.bow]
        weights = [np.asarray(mf.bow[k][1]).reshape(-1) for k in mf.bow]
        for k, w, g in zip(ids, words, weights):
            if len(w) != len(g):
                raise ValueError(f"bow of keyframe {k}: {len(w)} words but {len(g)} weights")
            if w.dtype.kind not in "iu" or g.dtype.kind != "f":
                raise ValueError(f"bow of keyframe {k}: words must be integers, weights floats "
                                 f"(got {w.dtype}, {g.dtype})")
        boff = np.zeros(len(ids) + 1, np.int64)
        np.cumsum([len(w) for w in words], out=boff[1:])
        arrays["bow/kf"] = np.array(ids, np.int64)
        arrays["bow/offsets"] = boff
        arrays["bow/words"] = np.concatenate(words) if words else np.zeros(0, np.int64)
        arrays["bow/weights"] = np.concatenate(weights) if weights else np.zeros(0, np.float64)
        if arrays["bow/words"].dtype.kind == "u":
            arrays["bow/words"] = arrays["bow/words"].astype(np.int64)
        header_counts["bow_keyframes"] = len(ids)
        header_counts["bow_entries"] = int(boff[-1])
        bow_hdr = {"words_dtype": str(arrays["bow/words"].dtype), "weights_dtype": str(arrays["bow/weights"].dtype)}
    return bow_hdr


def _vocabulary_arrays(mf: MapFile, arrays: dict[str, np.ndarray]) -> dict | None:
    """The vocabulary's arrays (``mf.vocabulary``) added to ``arrays``; returns the header's
    ``vocabulary`` entry (None without one)."""
    vocab_hdr = None
    if mf.vocabulary is not None:
        va = mf.vocabulary.to_arrays()
        if not isinstance(va, dict):
            raise TypeError(f"{type(mf.vocabulary).__name__}.to_arrays() must return a dict of arrays")
        for key, a in va.items():
            if not isinstance(key, str) or not key or key.startswith("/") or ".." in key:
                raise ValueError(f"vocabulary array name {key!r} is not a plain name")
            a = np.asarray(a)
            if a.dtype.hasobject:
                raise ValueError(f"vocabulary array {key!r} has object dtype (not storable without pickle)")
            arrays[f"vocab/{key}"] = a
        t = type(mf.vocabulary)
        vocab_hdr = {"class": f"{t.__module__}.{t.__qualname__}", "entries": list(va)}
    return vocab_hdr


def save_map(path: str | os.PathLike, mf: MapFile) -> None:
    """Write ``mf`` to ``path`` atomically: a temporary file in the same folder, fsynced,
    then ``os.replace`` -- a crash or an error never leaves a partial file under the name
    (an existing file there stays as it was).  ``MapFileError`` when the file cannot be
    written; ``ValueError`` / ``TypeError`` for an inconsistent ``MapFile``."""
    path = Path(path)
    header, arrays = _collect(mf)  # everything that can fail on the data, before any file exists
    hbytes = json.dumps(header, default=_json_default, allow_nan=False, indent=1).encode("utf-8")
    try:
        if path.is_dir():
            raise IsADirectoryError(21, "is a folder")
        with atomic_open(path, "wb", fsync=True, mkdir=False) as fh:
            with zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
                zf.writestr(HEADER, hbytes, compress_type=zipfile.ZIP_DEFLATED, compresslevel=6)
                for name, a in arrays.items():
                    if name in _STORED or (name.startswith("vocab/") and a.dtype == np.uint8):
                        zf.writestr(name + ".npy", _npy_bytes(a), compress_type=zipfile.ZIP_STORED)
                    else:
                        zf.writestr(name + ".npy", _npy_bytes(a), compress_type=zipfile.ZIP_DEFLATED,
                                    compresslevel=1)
    except OSError as e:
        raise MapFileError(f"cannot write the map file: {e.strerror or e}", path) from e
    try:  # make the rename durable (best effort; not possible on every platform)
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass


# ----------------------------------------------------------------------- load
class _Reader:
    """The zip archive of a map file, with every failure turned into MapFileError."""

    def __init__(self, path: Path) -> None:
        self.path = path
        if not path.exists():
            raise MapFileError("map file not found", path)
        if path.is_dir():
            raise MapFileError("is a folder, not a map file", path)
        try:
            self.zf = zipfile.ZipFile(path, "r")
        except zipfile.BadZipFile:
            raise MapFileError(
                f"not a {FORMAT} file (not a zip archive, or a truncated / corrupt one)", path
            ) from None
        except OSError as e:
            raise MapFileError(f"cannot read the map file: {e.strerror or e}", path) from None
        self.names = set(self.zf.namelist())

    def close(self) -> None:
        self.zf.close()

    def err(self, msg: str) -> MapFileError:
        return MapFileError(msg, self.path)

    def raw(self, name: str, limit: int | None = None) -> bytes:
        """Entry ``name``'s bytes; an entry that would inflate past ``limit`` bytes (default:
        half the memory this process may still use) is refused before it is inflated."""
        if name not in self.names:
            raise self.err(f"corrupt or incomplete map file: entry '{name}' is missing")
        size = self.zf.getinfo(name).file_size
        cap = memory_budget() if limit is None else limit
        if size > cap:
            why = (f"the header's counts allow {cap} bytes" if limit is not None
                   else f"more than half the memory available ({cap / 2**30:.1f} GiB)")
            raise self.err(f"corrupt map file: entry '{name}' would inflate to {size / 2**30:.2f} GiB; {why}")
        try:
            return self.zf.read(name)
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, NotImplementedError, ValueError) as e:
            raise self.err(f"corrupt map file: entry '{name}' cannot be read ({e})") from None

    def array(self, name: str, limit: int | None = None) -> np.ndarray:
        if name + ".npy" not in self.names:
            raise self.err(f"corrupt or incomplete map file: entry '{name}' is missing")
        data = self.raw(name + ".npy", limit)
        try:
            return np.lib.format.read_array(io.BytesIO(data), allow_pickle=False)
        except (ValueError, EOFError, OSError) as e:
            raise self.err(f"corrupt map file: entry '{name}' is not a valid array ({e})") from None

    def checked(self, name: str, dtype: np.dtype | str, shape: tuple, counts: dict[str, int]) -> np.ndarray:
        try:
            return check_entry(name, self.array(name, entry_limit(dtype, shape, counts)), dtype, shape, counts)
        except MapFileError as e:
            raise self.named(e) from None

    def named(self, e: MapFileError) -> MapFileError:
        """``e`` naming this file (the tables' errors name the entry only)."""
        return e if e.path is not None else self.err(str(e))


def memory_budget() -> int:
    """Half the memory this process may still take (free memory, and an address-space
    limit such as ``ulimit -v``): no single map entry may inflate beyond it."""
    avail = 1 << 62
    try:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        pass
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            avail = min(avail, soft)
    except (ImportError, ValueError, OSError):
        pass
    return max(avail // 2, 1 << 20)


def entry_limit(dtype: np.dtype | str, shape: tuple, counts: dict[str, int]) -> int | None:
    """The largest size an array entry of ``shape`` (count names) may have: its data at the
    header's counts plus the .npy header; None when a count is unknown."""
    try:
        n = 1
        for s in shape:
            n *= (counts[s[:-2]] + 1 if s.endswith("+1") else counts[s]) if isinstance(s, str) else int(s)
    except (KeyError, TypeError):
        return None
    item = np.dtype(dtype).itemsize if not isinstance(dtype, str) else 8
    return n * item + 4096


def _check_counts_fit(r: "_Reader", counts: dict[str, int]) -> None:
    """The arrays the header's counts announce must fit in memory (a forged header)."""
    total = sum(entry_limit(dt, shape, counts) or 0 for dt, shape in Map.entries().values())
    if total > memory_budget():
        raise r.err(f"corrupt map file: the header's counts need {total / 2**30:.1f} GiB of arrays, more than "
                    f"half the memory available ({memory_budget() / 2**30:.1f} GiB)")


def read_header(path: str | os.PathLike) -> dict:
    """The checked JSON header of a map file (format, version, counts, calibration, orb,
    meta, ...) without reading its arrays."""
    r = _Reader(Path(path))
    try:
        return _header(r)
    finally:
        r.close()


def _header(r: _Reader) -> dict:
    if HEADER not in r.names:
        raise r.err(f"not a {FORMAT} file: the archive has no '{HEADER}' entry")
    try:
        h = json.loads(r.raw(HEADER, 16 << 20).decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise r.err(f"corrupt map file: '{HEADER}' is not valid JSON ({e})") from None
    if not isinstance(h, dict):
        raise r.err(f"corrupt map file: '{HEADER}' is not a JSON object")
    if h.get("format") != FORMAT:
        raise r.err(f"not a {FORMAT} file: the header's format is {h.get('format')!r}")
    v = h.get("version")
    if not isinstance(v, int) or isinstance(v, bool) or v < 1:
        raise r.err(f"unknown {FORMAT} version {v!r}; this dynastereo reads version {VERSION}")
    if v > VERSION:
        raise r.err(f"written by a newer dynastereo: version {v}, this one reads {VERSION}")
    for key in ("counts", "next_kf_id", "calibration", "disparity_offset", "orb", "meta"):
        if key not in h:
            raise r.err(f"corrupt map file: the header lacks '{key}'")
    c = h["counts"]
    if not isinstance(c, dict):
        raise r.err("corrupt map file: the header's 'counts' is not an object")
    for key in COUNTS:
        x = c.get(key)
        if not isinstance(x, int) or isinstance(x, bool) or x < 0:
            raise r.err(f"corrupt map file: the header's counts.{key} is {x!r}, expected a count")
    if not isinstance(h["next_kf_id"], int) or h["next_kf_id"] < 0:
        raise r.err(f"corrupt map file: next_kf_id is {h['next_kf_id']!r}")
    off = h["disparity_offset"]
    if not isinstance(off, (int, float)) or not math.isfinite(off):
        raise r.err(f"corrupt map file: disparity_offset is {off!r}")
    orb = h["orb"]
    if not isinstance(orb, dict) or not all(k in orb for k in ("n_features", "scale_factor", "n_levels")):
        raise r.err("corrupt map file: the header's 'orb' lacks n_features / scale_factor / n_levels")
    if not (isinstance(orb["n_features"], int) and isinstance(orb["n_levels"], int)
            and isinstance(orb["scale_factor"], (int, float)) and orb["scale_factor"] >= 1.0):
        raise r.err(f"corrupt map file: the header's 'orb' is {orb!r}")
    if not isinstance(h["meta"], dict):
        raise r.err("corrupt map file: the header's 'meta' is not an object")
    return h


def _calibration(r: _Reader, d: Any) -> StereoCalibration:
    try:
        c = StereoCalibration(
            K=np.array(d["K"], np.float64).reshape(3, 3), baseline=float(d["baseline"]), width=int(d["width"]),
            height=int(d["height"]),
        )
    except (KeyError, TypeError, ValueError) as e:
        raise r.err(f"corrupt map file: invalid calibration in the header ({e})") from None
    if c.width <= 0 or c.height <= 0 or not np.isfinite(c.K).all():
        raise r.err(f"corrupt map file: invalid calibration in the header ({c.width}x{c.height})")
    return c


def _check_file(r: _Reader, h: dict, a: dict[str, np.ndarray]) -> None:
    """What the map's own checks (``Map.from_arrays``) cannot see: the header's ORB
    levels against the scales, the bag of words against the keyframes."""

    def bad(msg: str) -> MapFileError:
        return r.err(f"inconsistent map: {msg}")

    if int(h["orb"]["n_levels"]) != len(a["map/scales"]):
        raise bad(f"orb.n_levels {h['orb']['n_levels']} but {len(a['map/scales'])} scales")
    if "bow/kf" in a:
        ids = a["keyframes/id"]
        bk, bo = a["bow/kf"], a["bow/offsets"]
        if not np.isin(bk, ids).all() or len(np.unique(bk)) != len(bk):
            raise bad("bow/kf names keyframes that are not in the map (or twice)")
        if bo[0] != 0 or bo[-1] != h["counts"]["bow_entries"] or (np.diff(bo) < 0).any():
            raise bad("bow/offsets must rise from 0 to the number of bow entries")


def _vocabulary_class() -> type:
    from .vocabulary import Vocabulary  # only when a file holds a vocabulary

    return Vocabulary


def load_map(path: str | os.PathLike, vocabulary_cls: type | None = None) -> MapFile:
    """Read a map file written by :func:`save_map`; raises :class:`MapFileError` naming
    the file and the problem (missing, not a map file, truncated or corrupt, newer
    version, missing entries, inconsistent tables).  A stored vocabulary is rebuilt with
    ``vocabulary_cls.from_arrays`` (default: ``dynastereo.slam.vocabulary.Vocabulary``,
    imported only when the file holds one)."""
    p = Path(path)
    r = _Reader(p)
    try:
        h = _header(r)
        calib = _calibration(r, h["calibration"])
        counts = dict(h["counts"])
        _check_counts_fit(r, counts)
        a = {name: r.array(name, entry_limit(dt, shape, counts)) for name, (dt, shape) in Map.entries().items()}
        bow_present = any(name + ".npy" in r.names for name in BOW_ENTRIES) or "bow_keyframes" in counts
        if bow_present:
            for key in ("bow_keyframes", "bow_entries"):
                x = counts.get(key)
                if not isinstance(x, int) or isinstance(x, bool) or x < 0:
                    raise r.err(f"corrupt map file: the header's counts.{key} is {x!r}, expected a count")
            for name, (dt, shape) in BOW_ENTRIES.items():
                a[name] = r.checked(name, dt, shape, counts)
        try:
            mp = Map.from_arrays(a, calib, h["next_kf_id"], counts)
        except MapFileError as e:
            raise r.named(e) from None
        _check_file(r, h, a)
        vocab_arrays = None
        if h.get("vocabulary") is not None:
            vh = h["vocabulary"]
            entries = vh.get("entries") if isinstance(vh, dict) else None
            if not isinstance(entries, list) or not all(isinstance(e, str) for e in entries):
                raise r.err("corrupt map file: the header's 'vocabulary' lacks its list of entries")
            vocab_arrays = {e: r.array(f"vocab/{e}") for e in entries}
    finally:
        r.close()
    bow = None
    if "bow/kf" in a:
        bo = a["bow/offsets"].tolist()
        bow = {
            k: (a["bow/words"][bo[i]:bo[i + 1]].copy(), a["bow/weights"][bo[i]:bo[i + 1]].copy())
            for i, k in enumerate(a["bow/kf"].tolist())
        }
    vocab = None
    if vocab_arrays is not None:
        cls = vocabulary_cls
        if cls is None:
            try:
                cls = _vocabulary_class()
            except ImportError as e:
                raise MapFileError(
                    f"the map file holds a vocabulary, but dynastereo.slam.vocabulary.Vocabulary cannot be "
                    f"imported ({e})", p
                ) from None
        try:
            vocab = cls.from_arrays(vocab_arrays)
        except (KeyError, ValueError, TypeError, IndexError) as e:
            raise MapFileError(f"corrupt map file: the stored vocabulary cannot be rebuilt ({e})", p) from None
    return MapFile(mp, calib, float(h["disparity_offset"]), dict(h["orb"]), vocab, bow, dict(h["meta"]))


# -------------------------------------------------------------- compatibility
def check_compatible(mf: MapFile, calibration: StereoCalibration, orb: Any, path: str | os.PathLike,
                     rel_tol: float = REL_TOL, px_tol: float = PX_TOL) -> None:
    """Raise :class:`MapFileError` (naming ``path`` and every mismatch) when the map in
    ``mf`` was built for another camera or ORB setting than ``calibration`` / ``orb``
    (a dict or a ``Config`` / ``SlamConfig``): image size (exact), fx, fy and baseline
    (relative ``rel_tol``, 0.1 %), cx, cy (``px_tol`` pixels), ORB scale factor and
    number of levels (exact).  ``n_features`` may differ."""
    orb = orb_settings(orb)
    a, b = mf.calibration, calibration
    bad: list[str] = []
    if (a.width, a.height) != (b.width, b.height):
        bad.append(f"image size {a.width}x{a.height} in the map, {b.width}x{b.height} here")
    for what, x, y in (("fx", a.fx, b.fx), ("fy", a.fy, b.fy), ("baseline", a.baseline, b.baseline)):
        if not math.isclose(x, y, rel_tol=rel_tol):
            bad.append(f"{what} {x:.6g} in the map, {y:.6g} here ({100 * abs(x - y) / abs(y):.2f}% > "
                       f"{100 * rel_tol:.2f}%)")
    for what, x, y in (("cx", a.cx, b.cx), ("cy", a.cy, b.cy)):
        if abs(x - y) > px_tol:
            bad.append(f"{what} {x:.6g} in the map, {y:.6g} here (> {px_tol:g} px)")
    mo = mf.orb
    if not math.isclose(float(mo["scale_factor"]), orb["scale_factor"], rel_tol=1e-9):
        bad.append(f"ORB scale factor {float(mo['scale_factor']):g} in the map, {orb['scale_factor']:g} here")
    if int(mo["n_levels"]) != orb["n_levels"]:
        bad.append(f"ORB levels {int(mo['n_levels'])} in the map, {orb['n_levels']} here")
    if bad:
        raise MapFileError("the map was built for another camera / ORB setting: " + "; ".join(bad), path)
