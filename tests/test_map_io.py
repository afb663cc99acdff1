"""Map files (``dynastereo.slam.map_io``): a map built by the SLAM on a synthetic sequence
is saved and loaded back exactly, the loaded map works (frustum, covisibility, point
resolution, relocalization of a frame gives the same pose as in the original map), and
every kind of bad file -- missing, truncated, random bytes, a flipped byte, another
format, a newer version, a missing entry, a wrong dtype, a pickled entry, inconsistent
tables, another camera -- is a MapFileError naming the file and the problem.  A failing
save leaves no partial file.  Real data: a KITTI 06 map, and a seq 03 camera refused.
"""

from __future__ import annotations

import copy
import io
import json
import os
import sys
import types
import zipfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from dynastereo.config import Config, SlamConfig
from dynastereo.errors import InputError, MapFileError
from dynastereo.io import open_sequence
from dynastereo.slam import System
from dynastereo.slam import map_io
from dynastereo.slam.frame import Frame
from dynastereo.slam.geometry import inv_T
from dynastereo.slam.map import Map
from dynastereo.slam.map_io import (
    FORMAT,
    VERSION,
    MapFile,
    check_compatible,
    load_map,
    map_file_from_system,
    orb_settings,
    read_header,
    save_map,
)
from dynastereo.slam.keyframe_database import KeyFrameDatabase
from dynastereo.slam.matcher import stereo_match
from dynastereo.slam.relocalization import database_candidates
from dynastereo.slam.selfcal import shift_disparity
from dynastereo.slam.tracking import Tracker
from dynastereo.synth import generate
from dynastereo.datatypes import StereoCalibration

SIZE = (480, 144)
N_FRAMES = 12
POINT_ARRAYS = ("pos", "desc", "normal", "min_dist", "max_dist", "nobs", "visible", "found", "first_kf", "ref_kf",
                "bad", "replaced")
OBS_ARRAYS = ("kf", "kp", "pt", "alive", "next_row")
KP_ARRAYS = ("uv", "octave", "angle", "desc", "u_right", "depth", "point_ids", "obs_row")

pytestmark = pytest.mark.usefixtures("quiet_slam")


class FakeVocabulary:
    """Stands in for dynastereo.slam.vocabulary.Vocabulary: only the two methods used."""

    def __init__(self, words: np.ndarray, idf: np.ndarray, name: str = "fake") -> None:
        self.words, self.idf, self.name = words, idf, name

    def to_arrays(self) -> dict[str, np.ndarray]:  # 0-d entries too (the real one has them)
        return {"words": self.words, "idf": self.idf, "name": np.array(self.name), "k": np.array(10, np.int64)}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> "FakeVocabulary":
        assert arrays["k"].shape == () and int(arrays["k"]) == 10
        return cls(arrays["words"], arrays["idf"], str(arrays["name"][()]))


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> SimpleNamespace:
    """A SLAM run over a short synthetic drive, its map saved once."""
    root = tmp_path_factory.mktemp("mapio")
    seq_dir = generate(root / "synth", "static", frames=N_FRAMES, seed=0, size=SIZE)
    seq = open_sequence(seq_dir)
    sysm = System(SlamConfig(n_features=1000, local_ba="inline"), seq.calibration)
    try:
        for i in range(N_FRAMES):
            sysm.track(seq.frame(i))
    finally:
        sysm.shutdown()
    path = root / "map.dsmap"
    meta = {"sequence": seq_dir, "frames": N_FRAMES}
    mf = map_file_from_system(sysm, meta=meta)
    save_map(path, mf)
    assert meta == {"sequence": seq_dir, "frames": N_FRAMES}  # the caller's meta is not changed
    return SimpleNamespace(seq=seq, seq_dir=seq_dir, sysm=sysm, path=path, mf=mf, mp=sysm.map)


def _frame(sysm: System, sf, index: int = 0) -> Frame:
    """A Frame of a stereo pair, made as System.track makes it."""
    ex, c = sysm.extractor, sysm.calib
    left, right = sf.left_gray, sf.right_gray
    fl, fr = ex.extract(left, None), ex.extract(right, None)
    st = stereo_match(fl.uv, fl.octave, fl.desc, fr.uv, fr.octave, fr.desc, left, right, ex.scales, c.fx, c.bf)
    if sysm.disparity_offset:
        shift_disparity(fl.uv, st.u_right, st.depth, sysm.disparity_offset, c.bf)
    return Frame.from_features(index, fl, st.u_right, st.depth, c)


def _relocalize(tr: Tracker, mp: Map, f: Frame) -> tuple[bool, int]:
    """``Tracker.relocalize_against`` the bag-of-words candidates, from a keyframe
    database of ``mp`` made as ``System.load_map`` makes it."""
    db = KeyFrameDatabase(tr.vocab)
    for k, kf in mp.keyframes.items():
        db.add(k, tr.vocab.transform(kf.desc)[0])
    return tr.relocalize_against(mp, f, database_candidates(tr.vocab, db, mp, f, 3))


def _assert_same_map(a: Map, b: Map) -> None:
    assert (a.points.n, a.obs.n, a.next_kf_id) == (b.points.n, b.obs.n, b.next_kf_id)
    np.testing.assert_array_equal(a.scales, b.scales)
    for name in POINT_ARRAYS:
        x, y = getattr(a.points, name)[: a.points.n], getattr(b.points, name)[: b.points.n]
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    x, y = a.obs.head[: a.points.n], b.obs.head[: b.points.n]
    assert x.dtype == y.dtype
    np.testing.assert_array_equal(x, y, err_msg="head")
    for name in OBS_ARRAYS:
        x, y = getattr(a.obs, name)[: a.obs.n], getattr(b.obs, name)[: b.obs.n]
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    assert list(a.keyframes) == list(b.keyframes)
    for kid, ka in a.keyframes.items():
        kb = b.keyframes[kid]
        assert (ka.id, ka.frame_index, ka.bad) == (kb.id, kb.frame_index, kb.bad)
        np.testing.assert_array_equal(ka.T_cw, kb.T_cw)
        assert list(ka.covis.items()) == list(kb.covis.items())
        assert ka.calib.width == kb.calib.width and ka.calib.baseline == kb.calib.baseline
        np.testing.assert_array_equal(ka.calib.K, kb.calib.K)
        for name in KP_ARRAYS:
            x, y = getattr(ka, name), getattr(kb, name)
            assert x.dtype == y.dtype and x.shape == y.shape, (kid, name)
            np.testing.assert_array_equal(x, y, err_msg=f"keyframe {kid} {name}")
    assert list(a.culled) == list(b.culled)
    for kid, (p, T) in a.culled.items():
        assert b.culled[kid][0] == p
        np.testing.assert_array_equal(b.culled[kid][1], T)


# ------------------------------------------------------------------ round trip
def test_the_run_made_a_real_map(built):
    st = built.sysm.stats()
    assert st.lost == 0 and len(built.mp.keyframes) >= 3 and st.map_points > 500
    # fused / culled points and dead observation rows are part of what is stored
    assert built.mp.points.bad[: built.mp.points.n].any() and not built.mp.obs.alive[: built.mp.obs.n].all()
    assert any(kf.covis for kf in built.mp.keyframes.values())


def test_round_trip_is_exact(built):
    mf = load_map(built.path)
    _assert_same_map(built.mp, mf.map)
    c = built.seq.calibration
    np.testing.assert_array_equal(mf.calibration.K, c.K)
    assert (mf.calibration.baseline, mf.calibration.size) == (c.baseline, c.size)
    assert all(kf.calib is mf.calibration for kf in mf.map.keyframes.values())
    assert mf.disparity_offset == built.sysm.disparity_offset
    assert mf.orb == {"n_features": 1000, "scale_factor": 1.2, "n_levels": 8}
    assert mf.vocabulary is None and mf.bow is None
    assert mf.meta["frames"] == N_FRAMES and mf.meta["sequence"] == str(built.seq_dir)  # a Path, as text
    assert mf.meta["created"].startswith("20") and mf.meta["dynastereo_version"]
    # the keyframes own their arrays (no views into one shared buffer)
    kfs = list(mf.map.keyframes.values())
    assert not np.shares_memory(kfs[0].point_ids, kfs[1].point_ids)
    assert kfs[0].point_ids.base is None or kfs[0].point_ids.base.size == kfs[0].point_ids.size


def test_header_and_arrays_are_readable_without_dynastereo(built):
    h = read_header(built.path)
    assert h["format"] == FORMAT and h["version"] == VERSION == 1
    assert h["counts"]["points"] == built.mp.points.n and h["counts"]["keyframes"] == len(built.mp.keyframes)
    with zipfile.ZipFile(built.path) as zf:
        assert zf.namelist()[0] == "header.json"
        assert json.loads(zf.read("header.json"))["calibration"]["width"] == SIZE[0]
    with np.load(built.path, allow_pickle=False) as z:  # a plain .npz to numpy
        np.testing.assert_array_equal(z["points/pos"], built.mp.points.pos[: built.mp.points.n])
        assert z["keyframes/offsets"][-1] == sum(len(kf.uv) for kf in built.mp.keyframes.values())


def test_the_loaded_map_works(built):
    mp0, mp1 = built.mp, load_map(built.path).map
    c = built.seq.calibration
    good = np.flatnonzero(~mp0.points.bad[: mp0.points.n])
    for kf in list(mp0.keyframes.values())[:3]:
        fa = mp0.in_frustum(good, kf.T_cw, kf.center, c)
        fb = mp1.in_frustum(good, mp1.keyframes[kf.id].T_cw, mp1.keyframes[kf.id].center, c)
        assert len(fa.sel) > 100
        np.testing.assert_array_equal(fa.sel, fb.sel)
        np.testing.assert_array_equal(fa.u, fb.u)
        has = kf.point_ids[kf.point_ids >= 0]
        assert mp0.covisible_counts(has, exclude=kf.id) == mp1.covisible_counts(has, exclude=kf.id)
        np.testing.assert_array_equal(mp0.obs.rows_of(has), mp1.obs.rows_of(has))
    every = np.arange(mp0.points.n)
    np.testing.assert_array_equal(mp0.points.resolve(every), mp1.points.resolve(every))
    assert (mp0.points.resolve(every) != every).any()  # fused / bad points are followed
    np.testing.assert_array_equal(mp0.predict_level(good, np.full(len(good), 7.0)),
                                  mp1.predict_level(good, np.full(len(good), 7.0)))
    assert mp0.stats() == mp1.stats()
    # covisibility recomputed from the loaded observation table = from the original's
    # (the stored weights may be stale in a live map too: they are saved as they are)
    mp0c = copy.deepcopy(mp0)
    for kid in mp1.keyframes:
        mp0c.update_connections(mp0c.keyframes[kid])
        mp1.update_connections(mp1.keyframes[kid])
    assert [kf.covis for kf in mp1.keyframes.values()] == [kf.covis for kf in mp0c.keyframes.values()]
    # and it still grows: new points and observations beyond the loaded (trimmed) arrays
    kf = mp1.keyframes[max(mp1.keyframes)]
    free = np.flatnonzero((kf.point_ids < 0) & (kf.depth > 0))[:50]
    assert len(free) == 50
    ids = mp1.new_points(kf.unproject(free), kf.desc[free], kf.id)
    keep = mp1.add_observations(kf, free, ids)
    assert keep.all() and mp1.points.n == mp0.points.n + 50 and mp1.obs.n == mp0.obs.n + 50
    np.testing.assert_array_equal(mp1.obs.rows_of(ids), np.arange(mp0.obs.n, mp0.obs.n + 50))


def test_a_frame_relocalises_in_the_loaded_map_as_in_the_original(built):
    sysm, k = built.sysm, 7
    traj_T_cw = inv_T(np.vstack([built.sysm.trajectory()[k], [0, 0, 0, 1]]))
    poses = []
    for mp in (copy.deepcopy(built.mp), load_map(built.path).map):
        tr = sysm.tracker
        f = _frame(sysm, built.seq.frame(k))
        found, kid = _relocalize(tr, mp, f)
        assert found and kid in mp.keyframes and tr.n_inliers > 100
        poses.append((f.T_cw.copy(), kid, tr.n_inliers))
    (Ta, ka, na), (Tb, kb, nb) = poses
    assert (ka, na) == (kb, nb)
    np.testing.assert_allclose(Ta, Tb, atol=1e-9)
    # and the pose is the one the SLAM gave that frame
    assert np.linalg.norm(inv_T(Tb)[:3, 3] - inv_T(traj_T_cw)[:3, 3]) < 0.05
    dR = Tb[:3, :3] @ traj_T_cw[:3, :3].T
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.3


def test_culled_keyframes_bow_and_vocabulary_round_trip(built, tmp_path, monkeypatch):
    mf = load_map(built.path)
    mp = mf.map
    # cull a keyframe as local mapping does (in the loaded map: it is a working map)
    kf = list(mp.keyframes.values())[1]
    parent = mp.keyframes[kf.best_covisibles()[0]]
    T_cw = kf.T_cw.copy()
    mp.culled[kf.id] = (parent.id, kf.T_cw @ inv_T(parent.T_cw))
    mp.set_bad_keyframe(kf)
    rng = np.random.default_rng(3)
    mf.bow = {k: (rng.integers(0, 10**6, 40).astype(np.int32), rng.random(40)) for k in mp.keyframes}
    mf.vocabulary = FakeVocabulary(rng.integers(0, 256, (100, 32), dtype=np.uint8), rng.random(100))
    out = tmp_path / "culled.dsmap"
    save_map(out, mf)
    back = load_map(out, vocabulary_cls=FakeVocabulary)
    _assert_same_map(mp, back.map)
    assert kf.id not in back.map.keyframes and back.map.culled[kf.id][0] == parent.id
    np.testing.assert_allclose(back.map.keyframe_pose(kf.id), T_cw, atol=1e-9)
    assert list(back.bow) == list(mf.bow)
    for k, (w, g) in mf.bow.items():
        np.testing.assert_array_equal(back.bow[k][0], w)
        np.testing.assert_array_equal(back.bow[k][1], g)
        assert back.bow[k][0].dtype == np.int32
    assert isinstance(back.vocabulary, FakeVocabulary)
    np.testing.assert_array_equal(back.vocabulary.words, mf.vocabulary.words)
    np.testing.assert_array_equal(back.vocabulary.idf, mf.vocabulary.idf)
    assert back.vocabulary.name == "fake"  # a 0-d string array, still 0-d
    # the default class is dynastereo.slam.vocabulary.Vocabulary, imported only then
    fake_mod = types.ModuleType("dynastereo.slam.vocabulary")
    fake_mod.Vocabulary = FakeVocabulary
    monkeypatch.setitem(sys.modules, "dynastereo.slam.vocabulary", fake_mod)
    assert isinstance(load_map(out).vocabulary, FakeVocabulary)
    monkeypatch.setitem(sys.modules, "dynastereo.slam.vocabulary", None)  # import fails
    with pytest.raises(MapFileError, match="holds a vocabulary.*cannot be imported") as ei:
        load_map(out)
    assert str(out) in str(ei.value)
    assert load_map(built.path).vocabulary is None  # a file without one never imports it


def test_an_empty_map_round_trips(tmp_path):
    calib = StereoCalibration(np.array([[300.0, 0, 200], [0, 300, 100], [0, 0, 1]]), 0.5, 400, 200)
    mp = Map(1.2 ** np.arange(8))
    save_map(tmp_path / "e.dsmap", MapFile(mp, calib, 0.0, orb_settings(SlamConfig())))
    back = load_map(tmp_path / "e.dsmap")
    _assert_same_map(mp, back.map)
    assert back.map.stats() == {"keyframes": 0, "map_points": 0, "observations": 0}


def test_save_refuses_an_inconsistent_mapfile(built, tmp_path):
    mf = built.mf
    with pytest.raises(ValueError, match="n_levels"):
        save_map(tmp_path / "a", MapFile(mf.map, mf.calibration, 0.0, {**mf.orb, "n_levels": 4}))
    with pytest.raises(ValueError, match="orb lacks"):
        save_map(tmp_path / "a", MapFile(mf.map, mf.calibration, 0.0, {"n_features": 10}))
    other = StereoCalibration(mf.calibration.K, 0.3, mf.calibration.width, mf.calibration.height)
    with pytest.raises(ValueError, match="another calibration"):
        save_map(tmp_path / "a", MapFile(mf.map, other, 0.0, mf.orb))
    with pytest.raises(ValueError, match="not JSON"):
        save_map(tmp_path / "a", MapFile(mf.map, mf.calibration, 0.0, mf.orb, meta={"x": object()}))
    with pytest.raises(ValueError, match="bow given for keyframes not in the map"):
        save_map(tmp_path / "a", MapFile(mf.map, mf.calibration, 0.0, mf.orb, bow={10**6: (np.zeros(1, int),
                                                                                            np.zeros(1))}))
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ bad files
def _rewrite(src: Path, dst: Path, header=None, drop=(), replace=None) -> Path:
    """Copy a map file entry by entry, changing the header / dropping / replacing entries."""
    with zipfile.ZipFile(src) as zi, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as zo:
        for name in zi.namelist():
            if name in drop:
                continue
            data = zi.read(name)
            if name == "header.json" and header is not None:
                h = json.loads(data)
                header(h)
                data = json.dumps(h).encode()
            if replace and name in replace:
                buf = io.BytesIO()
                np.lib.format.write_array(buf, replace[name], allow_pickle=True)
                data = buf.getvalue()
            zo.writestr(name, data)
    return dst


def _flip_in_entry(src: Path, dst: Path, name: str) -> Path:
    data = bytearray(src.read_bytes())
    with zipfile.ZipFile(src) as zf:
        info = zf.getinfo(name)
    # local header: 30 bytes + name + extra field, then the entry's data
    start = info.header_offset + 30 + len(info.filename.encode()) + int.from_bytes(
        data[info.header_offset + 28: info.header_offset + 30], "little")
    mid = start + info.compress_size // 2
    data[mid: mid + 8] = bytes(b ^ 0xFF for b in data[mid: mid + 8])
    dst.write_bytes(bytes(data))
    return dst


def _write(p: Path, data: bytes) -> Path:
    p.write_bytes(data)
    return p


def _npz(p: Path) -> Path:
    with open(p, "wb") as fh:
        np.savez(fh, x=np.zeros(3))
    return p


def _bad_header(b, p: Path) -> Path:
    _rewrite(b.path, p, drop=("header.json",))
    with zipfile.ZipFile(p, "a") as zf:
        zf.writestr("header.json", "{oops")
    return p


def _set(key, value):
    def f(h):
        h[key] = value
    return f


def _counts(key, delta):
    def f(h):
        h["counts"][key] += delta
    return f


def _shifted(built, name, by):
    with np.load(built.path, allow_pickle=False) as z:
        return {name + ".npy": z[name] + by}


BAD_FILES = {
    "truncated": (lambda b, p: _write(p, b.path.read_bytes()[: b.path.stat().st_size // 2]),
                  "not a dynastereo-map file .*truncated"),
    "random bytes": (lambda b, p: _write(p, np.random.default_rng(0).bytes(5000)), "not a dynastereo-map file"),
    "empty": (lambda b, p: _write(p, b""), "not a dynastereo-map file"),
    "flipped deflated bytes": (lambda b, p: _flip_in_entry(b.path, p, "points/pos.npy"),
                               "corrupt map file: entry 'points/pos.npy' cannot be read"),
    "flipped stored bytes": (lambda b, p: _flip_in_entry(b.path, p, "keypoints/desc.npy"),
                             "corrupt map file: entry 'keypoints/desc.npy' cannot be read.*CRC"),
    "another zip": (lambda b, p: _npz(p), "not a dynastereo-map file: the archive has no 'header.json'"),
    "header not json": (_bad_header, "'header.json' is not valid JSON"),
    "wrong format": (lambda b, p: _rewrite(b.path, p, _set("format", "orbslam-atlas")),
                     "not a dynastereo-map file: the header's format is 'orbslam-atlas'"),
    "newer version": (lambda b, p: _rewrite(b.path, p, _set("version", 99)),
                      "written by a newer dynastereo: version 99, this one reads 1"),
    "bad version": (lambda b, p: _rewrite(b.path, p, _set("version", "1")), "unknown dynastereo-map version '1'"),
    "header lacks calibration": (lambda b, p: _rewrite(b.path, p, lambda h: h.pop("calibration")),
                                 "the header lacks 'calibration'"),
    "bad calibration": (lambda b, p: _rewrite(b.path, p, lambda h: h["calibration"].update(baseline=-1)),
                        "invalid calibration"),
    "missing entry": (lambda b, p: _rewrite(b.path, p, drop=("points/pos.npy",)),
                      "entry 'points/pos' is missing"),
    "wrong dtype": (lambda b, p: _rewrite(b.path, p, replace={"points/pos.npy": np.zeros((3, 3), np.float32)}),
                    "entry 'points/pos' has dtype float32, expected float64"),
    "counts disagree": (lambda b, p: _rewrite(b.path, p, _counts("points", 1)),
                        r"entry 'points/pos' has shape \(\d+, 3\), the header's counts say"),
    "pickled entry": (lambda b, p: _rewrite(b.path, p, replace={"obs/kf.npy": np.array([{"a": 1}], object)}),
                      "entry 'obs/kf' is not a valid array.*pickle"),
    "observations beyond points": (lambda b, p: _rewrite(b.path, p, replace=_shifted(b, "obs/pt", 10**6)),
                                   r"inconsistent map: \d+ values of obs/pt point beyond the \d+ map points"),
    "keypoint rows disagree": (lambda b, p: _rewrite(b.path, p, replace=_shifted(b, "obs/kp", 1)),
                               "inconsistent map: keyframe keypoints and the observation rows they name disagree"),
    "covis to unknown keyframe": (lambda b, p: _rewrite(b.path, p, replace=_shifted(b, "covis/dst", 1000)),
                                  "covis/dst names keyframes that are not in the map"),
    "offsets": (lambda b, p: _rewrite(b.path, p, replace=_shifted(b, "keyframes/offsets", 1)),
                "keyframes/offsets must rise from 0"),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_files_are_clear_errors(built, tmp_path, case):
    make, pattern = BAD_FILES[case]
    path = make(built, tmp_path / "bad.dsmap")
    with pytest.raises(MapFileError, match=pattern) as ei:
        load_map(path)
    assert isinstance(ei.value, InputError) and str(ei.value).startswith(f"{path}: ")
    assert ei.value.path == path


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(MapFileError, match="map file not found") as ei:
        load_map(tmp_path / "nope.dsmap")
    assert str(tmp_path / "nope.dsmap") in str(ei.value)
    with pytest.raises(MapFileError, match="is a folder"):
        load_map(tmp_path)
    with pytest.raises(MapFileError, match="map file not found"):
        read_header(tmp_path / "nope.dsmap")


# ------------------------------------------------------------------ compatibility
def test_check_compatible(built):
    mf, c, p = built.mf, built.seq.calibration, built.path
    orb = orb_settings(SlamConfig(n_features=1000))
    check_compatible(mf, c, orb, p)  # the same camera
    check_compatible(mf, c, orb_settings(SlamConfig(n_features=3000)), p)  # more features is fine
    check_compatible(mf, c, Config().with_overrides({"slam.n_features": 500}), p)  # a Config works too
    K = c.K.copy()
    K[0, 0] *= 1.0004  # 0.04 % off: within the tolerance
    check_compatible(mf, StereoCalibration(K, c.baseline, c.width, c.height), orb, p)

    def refused(calib, orb_, *patterns):
        with pytest.raises(MapFileError) as ei:
            check_compatible(mf, calib, orb_, p)
        msg = str(ei.value)
        assert msg.startswith(f"{p}: the map was built for another camera / ORB setting")
        for pat in patterns:
            assert pat in msg, (pat, msg)

    K = c.K.copy()
    K[0, 0] *= 1.0037  # KITTI 03 vs 06: 0.37 %
    refused(StereoCalibration(K, c.baseline, c.width, c.height), orb, "fx ", "0.37% > 0.10%")
    refused(StereoCalibration(c.K, c.baseline, c.width + 16, c.height), orb,
            f"image size {c.width}x{c.height} in the map, {c.width + 16}x{c.height} here")
    refused(StereoCalibration(c.K, c.baseline * 1.01, c.width, c.height), orb, "baseline")
    K = c.K.copy()
    K[0, 2] += 2.0
    refused(StereoCalibration(K, c.baseline, c.width, c.height), orb, "cx ")
    refused(c, {**orb, "n_levels": 4}, "ORB levels 8 in the map, 4 here")
    refused(c, {**orb, "scale_factor": 1.15}, "ORB scale factor 1.2 in the map, 1.15 here")
    # every mismatch at once
    refused(StereoCalibration(c.K * [[2], [1], [1]], 0.1, 100, 100), {**orb, "n_levels": 4},
            "image size", "fx ", "baseline", "ORB levels")


# ------------------------------------------------------------------ atomic save
def test_a_failing_save_leaves_no_partial_file(built, tmp_path, monkeypatch):
    target = tmp_path / "map.dsmap"
    target.write_bytes(b"previous map")
    calls = {"n": 0}
    real = zipfile.ZipFile.writestr

    def failing(self, *a, **kw):
        calls["n"] += 1
        if calls["n"] == 6:
            raise OSError(28, "No space left on device")
        return real(self, *a, **kw)

    monkeypatch.setattr(zipfile.ZipFile, "writestr", failing)
    with pytest.raises(MapFileError, match="cannot write the map file: No space left on device") as ei:
        save_map(target, built.mf)
    assert str(target) in str(ei.value)
    assert sorted(os.listdir(tmp_path)) == ["map.dsmap"] and target.read_bytes() == b"previous map"
    monkeypatch.setattr(zipfile.ZipFile, "writestr", real)

    def interrupted(self, *a, **kw):  # a Ctrl-C mid-write: re-raised, nothing left behind
        raise KeyboardInterrupt

    monkeypatch.setattr(zipfile.ZipFile, "writestr", interrupted)
    with pytest.raises(KeyboardInterrupt):
        save_map(target, built.mf)
    assert sorted(os.listdir(tmp_path)) == ["map.dsmap"] and target.read_bytes() == b"previous map"
    monkeypatch.setattr(zipfile.ZipFile, "writestr", real)

    def no_rename(src, dst):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(map_io.os, "replace", no_rename)
    with pytest.raises(MapFileError, match="Permission denied"):
        save_map(target, built.mf)
    assert sorted(os.listdir(tmp_path)) == ["map.dsmap"] and target.read_bytes() == b"previous map"
    monkeypatch.undo()
    save_map(target, built.mf)  # and a save that succeeds replaces the old file
    assert sorted(os.listdir(tmp_path)) == ["map.dsmap"] and load_map(target).map.points.n == built.mp.points.n


def test_save_into_a_missing_or_unwritable_place(built, tmp_path):
    with pytest.raises(MapFileError, match="cannot write the map file") as ei:
        save_map(tmp_path / "no" / "such" / "dir" / "map.dsmap", built.mf)
    assert "map.dsmap" in str(ei.value)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "folder").mkdir()
    with pytest.raises(MapFileError, match="is a folder"):
        save_map(tmp_path / "folder", built.mf)
    assert list(tmp_path.iterdir()) == [tmp_path / "folder"] and not any((tmp_path / "folder").iterdir())
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        with pytest.raises(MapFileError, match="cannot write the map file: Permission denied"):
            save_map(ro / "map.dsmap", built.mf)
        assert list(ro.iterdir()) == []


# ------------------------------------------------------------------ real data
@pytest.mark.realdata
def test_kitti06_map_round_trip_and_a_seq03_camera_is_refused(kitti06: Path, kitti03: Path, tmp_path: Path):
    seq = open_sequence(kitti06)
    cfg = Config()
    cfg.slam.local_ba = "inline"
    sysm = System(cfg, seq.calibration)
    try:
        for i in range(14):
            sysm.track(seq.frame(i))
    finally:
        sysm.shutdown()
    path = tmp_path / "kitti06.dsmap"
    save_map(path, map_file_from_system(sysm, meta={"sequence": str(kitti06)}))
    mf = load_map(path)
    _assert_same_map(sysm.map, mf.map)
    assert mf.disparity_offset == sysm.disparity_offset
    # image 10 found again in the loaded map, where the SLAM had put it
    tr = sysm.tracker
    f = _frame(sysm, seq.frame(10))
    found, _ = _relocalize(tr, mf.map, f)
    assert found and tr.n_inliers > 300
    T_wc = sysm.trajectory()[10]
    assert np.linalg.norm(inv_T(f.T_cw)[:3, 3] - T_wc[:, 3]) < 0.05
    check_compatible(mf, seq.calibration, cfg, path)
    # KITTI 03 was recorded with another calibration (fx 721.5 vs 718.9, 1242x375)
    with pytest.raises(MapFileError, match="another camera") as ei:
        check_compatible(mf, open_sequence(kitti03).calibration, cfg, path)
    assert "fx " in str(ei.value) and str(path) in str(ei.value)
