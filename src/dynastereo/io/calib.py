"""Stereo calibration files.

Two kinds of result:

* :class:`~dynastereo.datatypes.StereoCalibration` -- the images are already rectified
  (KITTI, pre-rectified folders): ``K``, baseline in metres, image size.
* :class:`RawStereoCalibration` -- the images are raw (EuRoC, calibrated but not
  rectified cameras): per-camera ``K``/``D`` and either the pose between the cameras
  (``R``, ``T``) or a ready-made rectification (``R1, R2, P1, P2``, as ORB-SLAM2's
  ``LEFT.R/LEFT.P/RIGHT.R/RIGHT.P``).  :class:`~dynastereo.io.rectify.Rectifier` turns it
  into rectification maps and a rectified ``StereoCalibration``.

Supported files
---------------

**KITTI** ``calib.txt`` (odometry and object benchmarks): labelled rows
``P0: <12 numbers>`` ... ``P3: ...`` (3x4 row-major projection matrices of the rectified
cameras).  Other rows (``Tr``, ``R0_rect``, ``Tr_velo_to_cam`` ...) are ignored.  The gray
pair ``image_0``/``image_1`` uses P0/P1, the colour pair ``image_2``/``image_3`` P2/P3;
``baseline = (Pl[0,3] - Pr[0,3]) / fx``.  See :func:`load_kitti_calib`.

**KITTI raw** ``calib_cam_to_cam.txt`` (in a drive's date folder): labelled rows
``P_rect_00: <12 numbers>`` ... ``P_rect_03`` (rectified projections, all from rectified
camera 0's frame) and ``S_rect_00: <width> <height>`` ... (rectified image sizes), beside
the raw ``K_0x``/``D_0x``/``R_0x``/``T_0x`` (unused).  Gray pair 00/01, colour pair 02/03.
See :func:`load_kitti_raw_calib`.

**EuRoC** ``mav0/cam0/sensor.yaml`` + ``mav0/cam1/sensor.yaml``: ``T_BS`` (camera to
body, 4x4), ``intrinsics: [fu, fv, cu, cv]``, ``distortion_model: radial-tangential``,
``distortion_coefficients: [k1, k2, p1, p2]``, ``resolution: [w, h]``.  The camera-to-camera
pose is ``T_21 = inv(T_BS_cam1) @ T_BS_cam0``.  See :func:`load_euroc_calib`.

**Generic YAML** for a pair of image folders (:func:`load_stereo_yaml`), in either form:

(a) dynastereo's own format (plain YAML; lengths in metres), either *rectified*::

        fx: 718.856          # pixels
        fy: 718.856          # optional, defaults to fx
        cx: 607.1928
        cy: 185.2157
        baseline: 0.5372     # metres; or  bf: 386.1448  (baseline * fx, ORB-SLAM2 style)
        width: 1241          # optional when the images are at hand
        height: 376

    or *raw* (rectified on read)::

        width: 752
        height: 480
        left:
          K: [458.654, 457.296, 367.215, 248.375]   # fx, fy, cx, cy -- or 9 numbers / 3x3
          D: [-0.2834, 0.0740, 0.0002, 0.00002]     # OpenCV order k1 k2 p1 p2 [k3 ...]; optional
        right:
          K: [457.587, 456.134, 379.999, 255.238]
          D: [-0.2837, 0.0745, -0.0001, -0.00004]
        R: [[...], [...], [...]]   # rotation left -> right camera (X_r = R X_l + T): 3x3, 9 numbers
                                   # or a 3-vector (Rodrigues)
        T: [-0.1101, 0.0004, -0.0009]              # metres
        alpha: 0.0                 # optional: cv2.stereoRectify free scaling (0 = no black borders)

    Unknown keys are an error.

(b) an ORB-SLAM2 stereo settings file (OpenCV FileStorage YAML, first line
    ``%YAML:1.0``): ``Camera.fx, Camera.fy, Camera.cx, Camera.cy, Camera.bf`` and
    ``Camera.width/height`` for rectified images; if ``LEFT.K, LEFT.D, LEFT.R, LEFT.P``
    and ``RIGHT.*`` (``!!opencv-matrix``) are present, as in ORB-SLAM2's ``EuRoC.yaml``, the
    images are raw and are rectified with exactly those R/P (like ORB-SLAM2 does).
    ORB-SLAM2 itself ignores ``Camera.width/height`` for stereo and uses the images' size;
    so do we when the images are at hand.  :func:`load_orbslam2_settings` returns every key of
    such a file (``ThDepth``, ``ORBextractor.*``...) as a flat dict.

**Middlebury 2014** ``calib.txt`` (``cam0=[...]``, ``baseline`` in mm, ``doffs``...):
:func:`load_middlebury_calib`.

All errors raise :class:`~dynastereo.errors.CalibrationError` naming the file and the key/row.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from ..errors import CalibrationError
from ..datatypes import StereoCalibration

# --------------------------------------------------------------------------- raw calibration


@dataclass(frozen=True)
class RawStereoCalibration:
    """Calibration of a raw (unrectified) stereo pair.

    ``K1, D1`` / ``K2, D2``: intrinsics and OpenCV distortion of the left / right camera.
    Either ``R, T`` (pose of the left camera in the right camera's frame: ``X_r = R X_l + T``,
    metres -- OpenCV's ``stereoRectify`` convention) or a ready-made rectification
    ``R1, R2, P1, P2`` (then ``R, T`` may be absent).  ``width, height``: raw image size.
    """

    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    width: int
    height: int
    R: np.ndarray | None = None
    T: np.ndarray | None = None
    R1: np.ndarray | None = None
    R2: np.ndarray | None = None
    P1: np.ndarray | None = None
    P2: np.ndarray | None = None
    alpha: float = 0.0  # free scaling for cv2.stereoRectify (ignored with a ready-made R1..P2)
    source: Path | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        def arr(v: Any, shape: tuple[int, ...] | None) -> np.ndarray | None:
            if v is None:
                return None
            a = np.asarray(v, dtype=np.float64)
            return a.reshape(shape) if shape is not None else a.reshape(-1)

        for name, shape in (("K1", (3, 3)), ("K2", (3, 3)), ("R", (3, 3)), ("T", (3,)), ("R1", (3, 3)),
                            ("R2", (3, 3)), ("P1", (3, 4)), ("P2", (3, 4)), ("D1", None), ("D2", None)):
            object.__setattr__(self, name, arr(getattr(self, name), shape))
        for name in ("D1", "D2"):
            if getattr(self, name).size not in (0, 4, 5, 8, 12, 14):
                raise ValueError(f"{name} must have 4, 5, 8, 12 or 14 coefficients, got {getattr(self, name).size}")
        if self.has_rectification:
            pass
        elif self.R is None or self.T is None:
            raise ValueError("need either R and T, or all of R1, R2, P1, P2")
        if not (self.width > 0 and self.height > 0):
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")

    @property
    def has_rectification(self) -> bool:
        return all(getattr(self, k) is not None for k in ("R1", "R2", "P1", "P2"))

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    @property
    def baseline(self) -> float:
        """Distance between the optical centres in metres."""
        if self.T is not None:
            return float(np.linalg.norm(self.T))
        return float(-self.P2[0, 3] / self.P2[0, 0])  # type: ignore[index]


# --------------------------------------------------------------------------- KITTI


def _read_calib_text(path: Path) -> str:
    """The text of a calibration file; CalibrationError naming it when missing or unreadable."""
    if not path.is_file():
        raise CalibrationError("calibration file not found" if not path.exists() else "not a file", path)
    try:
        return path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise CalibrationError(f"cannot read: {e.strerror}", path) from None


def read_kitti_calib_rows(path: str | Path) -> dict[str, list[str]]:
    """The labelled rows of a KITTI ``calib.txt`` as raw tokens: ``{"P0": ["7.07e+02", ...], ...}``.

    Blank lines and ``#`` comments are skipped; a non-empty line without ``NAME:`` is an error.
    """
    path = Path(path)
    text = _read_calib_text(path)
    rows: dict[str, list[str]] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        key, sep, rest = s.partition(":")
        if not sep or not key.strip() or " " in key.strip():
            raise CalibrationError(f"line {lineno} is not a labelled row 'NAME: numbers': {s[:60]!r}", path)
        rows[key.strip()] = rest.split()
    return rows


def _kitti_matrix(rows: dict[str, list[str]], key: str, path: Path, needed_for: str) -> np.ndarray:
    if key not in rows:
        found = ", ".join(rows) or "none"
        raise CalibrationError(f"no row '{key}:' (needed for {needed_for}); rows found: {found}", path)
    toks = rows[key]
    if len(toks) != 12:
        raise CalibrationError(f"row '{key}' has {len(toks)} numbers, expected 12 (a 3x4 projection matrix)", path)
    try:
        vals = [float(t) for t in toks]
    except ValueError:
        bad = next(t for t in toks if not _is_float(t))
        raise CalibrationError(f"row '{key}': {bad!r} is not a number", path) from None
    P = np.array(vals, dtype=np.float64).reshape(3, 4)
    if not np.all(np.isfinite(P)):
        raise CalibrationError(f"row '{key}' contains non-finite values", path)
    return P


def _is_float(t: str) -> bool:
    try:
        float(t)
        return True
    except ValueError:
        return False


def kitti_projections(path: str | Path, color: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(P_left, P_right)`` 3x4 for the gray (P0, P1) or colour (P2, P3) pair."""
    path = Path(path)
    rows = read_kitti_calib_rows(path)
    kl, kr = ("P2", "P3") if color else ("P0", "P1")
    pair = "the colour pair image_2/image_3" if color else "the gray pair image_0/image_1"
    return _kitti_matrix(rows, kl, path, pair), _kitti_matrix(rows, kr, path, pair)


def load_kitti_calib(path: str | Path, image_size: tuple[int, int], color: bool = False) -> StereoCalibration:
    """Rectified calibration from a KITTI ``calib.txt``.

    ``image_size`` is ``(width, height)`` of the images (the file does not hold it);
    ``color`` selects P2/P3 (image_2/image_3) instead of P0/P1 (image_0/image_1).
    """
    path = Path(path)
    Pl, Pr = kitti_projections(path, color)
    kl, kr = ("P2", "P3") if color else ("P0", "P1")
    return _rectified_pair(Pl, Pr, kl, kr, path, image_size)


def _rectified_pair(Pl: np.ndarray, Pr: np.ndarray, kl: str, kr: str, path: Path,
                    image_size: tuple[int, int]) -> StereoCalibration:
    """``StereoCalibration`` of a rectified pair from its two 3x4 projections (rows ``kl``, ``kr``)."""
    K, Kr = Pl[:, :3], Pr[:, :3]
    fx = K[0, 0]
    if not (fx > 0 and K[1, 1] > 0):
        raise CalibrationError(f"row '{kl}': focal lengths must be positive (fx={fx}, fy={K[1, 1]})", path)
    if not np.allclose(K, Kr, rtol=1e-6, atol=1e-6):
        raise CalibrationError(f"rows '{kl}' and '{kr}' have different intrinsics: not a rectified pair", path)
    baseline = (Pl[0, 3] - Pr[0, 3]) / fx
    if not baseline > 0:
        raise CalibrationError(
            f"baseline from rows '{kl}'/'{kr}' is {baseline:.4f} m; the right camera must be to the right "
            f"({kr}[0,3] < {kl}[0,3])",
            path,
        )
    w, h = image_size
    return StereoCalibration(K=K.copy(), baseline=float(baseline), width=int(w), height=int(h))


# --------------------------------------------------------------------------- KITTI raw

#: The two stereo pairs of a KITTI raw drive: camera numbers (left, right).
KITTI_RAW_GRAY_PAIR: tuple[str, str] = ("00", "01")
KITTI_RAW_COLOUR_PAIR: tuple[str, str] = ("02", "03")


def kitti_raw_projections(path: str | Path, color: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(P_rect_left, P_rect_right)`` 3x4 of a KITTI raw ``calib_cam_to_cam.txt``: the gray
    pair (``P_rect_00``/``P_rect_01``) or the colour pair (``P_rect_02``/``P_rect_03``)."""
    path = Path(path)
    rows = read_kitti_calib_rows(path)
    cl, cr = KITTI_RAW_COLOUR_PAIR if color else KITTI_RAW_GRAY_PAIR
    pair = f"the {'colour' if color else 'gray'} pair image_{cl}/image_{cr}"
    prows = {k: v for k, v in rows.items() if k.startswith("P_rect")}  # "rows found" lists these only
    return _kitti_matrix(prows, f"P_rect_{cl}", path, pair), _kitti_matrix(prows, f"P_rect_{cr}", path, pair)


def _kitti_raw_size(rows: dict[str, list[str]], key: str, path: Path) -> tuple[int, int] | None:
    """``(width, height)`` from a ``S_..`` row (two numbers, e.g. ``1.242000e+03 3.750000e+02``); None if absent."""
    if key not in rows:
        return None
    toks = rows[key]
    try:
        vals = [float(t) for t in toks]
    except ValueError:
        bad = next(t for t in toks if not _is_float(t))
        raise CalibrationError(f"row '{key}': {bad!r} is not a number", path) from None
    if len(vals) != 2 or not all(np.isfinite(vals)) or min(vals) <= 0 or any(v != round(v) for v in vals):
        raise CalibrationError(f"row '{key}' must hold two positive whole numbers (width height), got {toks}", path)
    return int(vals[0]), int(vals[1])


def load_kitti_raw_calib(path: str | Path, image_size: tuple[int, int], color: bool = False,
                         image_path: str | Path | None = None) -> StereoCalibration:
    """Rectified calibration of a KITTI raw drive from its date folder's ``calib_cam_to_cam.txt``.

    ``color=False``: the gray pair ``image_00``/``image_01`` (``P_rect_00``/``P_rect_01``);
    ``color=True``: the colour pair ``image_02``/``image_03`` (``P_rect_02``/``P_rect_03``).
    The P_rect matrices all project from the rectified camera 0's frame, so the baseline is
    ``(P_rect_l[0,3] - P_rect_r[0,3]) / fx`` (for the gray pair ``-P_rect_01[0,3] / fx``).
    ``image_size`` (``(width, height)`` of the images, ``image_path`` one of them, named in
    errors) must match the rows ``S_rect_0x`` (rectified size) when the file holds them.
    """
    path = Path(path)
    rows = read_kitti_calib_rows(path)
    cl, cr = KITTI_RAW_COLOUR_PAIR if color else KITTI_RAW_GRAY_PAIR
    Pl, Pr = kitti_raw_projections(path, color)
    iw, ih = int(image_size[0]), int(image_size[1])
    what = f"the images ({image_path})" if image_path is not None else "the images"
    for cam in (cl, cr):
        s = _kitti_raw_size(rows, f"S_rect_{cam}", path)
        if s is not None and s != (iw, ih):
            raw = _kitti_raw_size(rows, f"S_{cam}", path)
            hint = ("; they have the unrectified size S_" + cam + ": only rectified drives (*_sync) can be read"
                    if raw == (iw, ih) else "")
            raise CalibrationError(
                f"row 'S_rect_{cam}' gives the rectified size {s[0]}x{s[1]}, {what} are {iw}x{ih}{hint}", path
            )
    return _rectified_pair(Pl, Pr, f"P_rect_{cl}", f"P_rect_{cr}", path, (iw, ih))


# --------------------------------------------------------------------------- YAML reading


class _YamlLoader(yaml.SafeLoader):
    """SafeLoader that reads ``1e-5`` as a float (YAML 1.1 wants a dot) and ``!!opencv-matrix``."""


_YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def _opencv_matrix(loader: yaml.SafeLoader, node: yaml.Node) -> np.ndarray:
    m = loader.construct_mapping(node, deep=True)
    return np.asarray(m["data"], dtype=np.float64).reshape(int(m["rows"]), int(m["cols"]))


_YamlLoader.add_constructor("tag:yaml.org,2002:opencv-matrix", _opencv_matrix)


def _filenode_to_py(node: "cv2.FileNode") -> Any:
    if node.isNone():
        return None
    if node.isMap():
        keys = node.keys()
        if {"rows", "cols", "data"} <= set(keys) and "dt" in keys:
            return np.asarray(node.mat(), dtype=np.float64)
        return {k: _filenode_to_py(node.getNode(k)) for k in keys}
    if node.isSeq():
        return [_filenode_to_py(node.at(i)) for i in range(node.size())]
    if node.isInt():
        return int(node.real())
    if node.isReal():
        return float(node.real())
    if node.isString():
        return node.string()
    return None


def _cv_parse_message(e: BaseException) -> str:
    err = e.__cause__ if isinstance(e.__cause__, cv2.error) else e
    m = re.search(r"\((\d+)\): (.*)$", str(getattr(err, "func", "") or ""))
    if m:  # OpenCV puts "<file>(<line>): <problem>" in the function-name field
        return f"line {m.group(1)}: {m.group(2)}"
    return str(getattr(err, "err", "") or "") or "parse error"


def read_yaml_file(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping: OpenCV FileStorage files (``%YAML:1.0``) through ``cv2.FileStorage``
    (which accepts their quirks, e.g. ``data:[...]``), anything else through PyYAML.
    ``!!opencv-matrix`` nodes become ``np.ndarray``."""
    path = Path(path)
    text = _read_calib_text(path)
    if text.lstrip().startswith("%YAML:"):
        try:
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError) as e:  # cv2 may wrap its parse error in a SystemError
            raise CalibrationError(f"cannot parse OpenCV YAML: {_cv_parse_message(e)}", path) from None
        try:
            if not fs.isOpened():
                raise CalibrationError("cannot parse OpenCV YAML", path)
            out = _filenode_to_py(fs.root())
        finally:
            fs.release()
    else:
        try:
            out = yaml.load(text, Loader=_YamlLoader)
        except yaml.YAMLError as e:
            raise CalibrationError(f"invalid YAML: {e}", path) from None
        except (KeyError, ValueError, TypeError) as e:
            raise CalibrationError(f"invalid !!opencv-matrix: {e}", path) from None
    if not isinstance(out, dict):
        raise CalibrationError("expected a YAML mapping of keys to values", path)
    return out


def _number(value: Any, key: str, path: Path) -> float:
    if isinstance(value, bool) or value is None:
        raise CalibrationError(f"key '{key}': expected a number, got {value!r}", path)
    if isinstance(value, np.ndarray) and value.size == 1:
        value = value.reshape(-1)[0]
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise CalibrationError(f"key '{key}': expected a number, got {value!r}", path) from None
    if not np.isfinite(v):
        raise CalibrationError(f"key '{key}': expected a finite number, got {value!r}", path)
    return v


def _numbers(value: Any, key: str, path: Path, sizes: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise CalibrationError(f"key '{key}': expected a list of numbers, got {value!r}", path) from None
    if a.size not in sizes:
        want = " or ".join(str(s) for s in sizes)
        raise CalibrationError(f"key '{key}': expected {want} numbers, got {a.size}", path)
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"key '{key}': contains non-finite values", path)
    return a


def _intrinsics(value: Any, key: str, path: Path) -> np.ndarray:
    a = _numbers(value, key, path, (4, 9))
    if a.size == 4:
        fx, fy, cx, cy = a
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
    else:
        K = a.reshape(3, 3)
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError(f"key '{key}': focal lengths must be positive", path)
    return K


def _size_from(d: dict[str, Any], wkey: str, hkey: str, path: Path,
               image_size: tuple[int, int] | None) -> tuple[int, int]:
    if wkey in d and hkey in d:
        w, h = int(_number(d[wkey], wkey, path)), int(_number(d[hkey], hkey, path))
        if w <= 0 or h <= 0:
            raise CalibrationError(f"image size must be positive, got {wkey}={w}, {hkey}={h}", path)
        return w, h
    if image_size is not None:
        return int(image_size[0]), int(image_size[1])
    raise CalibrationError(f"keys '{wkey}' and '{hkey}' (image size) are missing", path)


# --------------------------------------------------------------------------- EuRoC


def _euroc_camera(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    d = read_yaml_file(path)
    for key in ("T_BS", "intrinsics", "resolution"):
        if key not in d:
            raise CalibrationError(f"key '{key}' is missing (EuRoC sensor.yaml)", path)
    model = d.get("camera_model", "pinhole")
    if model != "pinhole":
        raise CalibrationError(f"camera_model {model!r} is not supported (only 'pinhole')", path)
    dist_model = d.get("distortion_model", "radial-tangential")
    if dist_model not in ("radial-tangential", "radtan", "plumb_bob"):
        raise CalibrationError(
            f"distortion_model {dist_model!r} is not supported (only 'radial-tangential')", path
        )
    T = d["T_BS"]
    T_data = T.get("data") if isinstance(T, dict) else T
    T_BS = _numbers(T_data, "T_BS.data", path, (16,)).reshape(4, 4)
    K = _intrinsics(d["intrinsics"], "intrinsics", path)
    D = _numbers(d.get("distortion_coefficients", [0, 0, 0, 0]), "distortion_coefficients", path, (4, 5, 8))
    res = _numbers(d["resolution"], "resolution", path, (2,))
    return T_BS, K, D, (int(res[0]), int(res[1]))


def load_euroc_calib(cam0_yaml: str | Path, cam1_yaml: str | Path) -> RawStereoCalibration:
    """Raw stereo calibration from EuRoC's ``cam0/sensor.yaml`` (left) and ``cam1/sensor.yaml`` (right)."""
    p0, p1 = Path(cam0_yaml), Path(cam1_yaml)
    T0, K1, D1, size0 = _euroc_camera(p0)
    T1, K2, D2, size1 = _euroc_camera(p1)
    if size0 != size1:
        raise CalibrationError(f"resolution {size1} differs from {p0}'s {size0}", p1)
    T_21 = np.linalg.inv(T1) @ T0  # left camera -> right camera
    R, t = T_21[:3, :3], T_21[:3, 3]
    if not t[0] < 0:
        raise CalibrationError(
            f"cam1 is not to the right of cam0 (translation cam0->cam1 = {np.round(t, 4).tolist()})", p1
        )
    return RawStereoCalibration(K1=K1, D1=D1, K2=K2, D2=D2, width=size0[0], height=size0[1], R=R, T=t,
                                source=p0.parent.parent)


# --------------------------------------------------------------------------- ORB-SLAM2 + generic YAML


def load_orbslam2_settings(path: str | Path) -> dict[str, Any]:
    """Every key of an ORB-SLAM2 settings file, flat as written (``"Camera.fx"``, ``"ThDepth"``,
    ``"ORBextractor.nFeatures"``, ``"LEFT.K"`` -> 3x3 ``np.ndarray`` ...)."""
    path = Path(path)
    d = read_yaml_file(path)
    flat: dict[str, Any] = {}

    def walk(prefix: str, v: Any) -> None:  # files written as nested maps are flattened with dots
        if isinstance(v, dict):
            for k, vv in v.items():
                walk(f"{prefix}.{k}" if prefix else str(k), vv)
        else:
            flat[prefix] = v

    walk("", d)
    if "Camera.fx" not in flat:
        raise CalibrationError("not an ORB-SLAM2 settings file: key 'Camera.fx' is missing", path)
    return flat


def is_orbslam2_settings(d: dict[str, Any]) -> bool:
    return "Camera.fx" in d or ("Camera" in d and isinstance(d["Camera"], dict) and "fx" in d["Camera"])


def orbslam2_calibration(settings: dict[str, Any], path: str | Path,
                         image_size: tuple[int, int] | None = None) -> StereoCalibration | RawStereoCalibration:
    """Calibration from ORB-SLAM2 settings (see :func:`load_orbslam2_settings`).

    Without ``LEFT.*``/``RIGHT.*``: rectified ``StereoCalibration`` (size = ``image_size`` if given,
    as ORB-SLAM2 reads it from the images, else ``Camera.width/height``).  With them: a
    ``RawStereoCalibration`` carrying ``LEFT.R/P`` and ``RIGHT.R/P`` as the rectification.
    """
    path = Path(path)
    s = settings
    for key in ("Camera.fx", "Camera.fy", "Camera.cx", "Camera.cy", "Camera.bf"):
        if key not in s:
            raise CalibrationError(f"key '{key}' is missing (ORB-SLAM2 stereo settings)", path)
    fx, fy, cx, cy, bf = (_number(s[k], k, path) for k in
                          ("Camera.fx", "Camera.fy", "Camera.cx", "Camera.cy", "Camera.bf"))
    if not (fx > 0 and fy > 0):
        raise CalibrationError(f"focal lengths must be positive (Camera.fx={fx}, Camera.fy={fy})", path)
    if not bf > 0:
        raise CalibrationError(f"key 'Camera.bf' must be positive (baseline * fx), got {bf}", path)
    rect_keys = [f"{side}.{m}" for side in ("LEFT", "RIGHT") for m in ("K", "D", "R", "P")]
    present = [k for k in rect_keys if k in s]
    if not present:
        if image_size is not None:
            w, h = int(image_size[0]), int(image_size[1])
        else:
            w, h = _size_from(s, "Camera.width", "Camera.height", path, None)
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
        return StereoCalibration(K=K, baseline=bf / fx, width=w, height=h)
    missing = [k for k in rect_keys if k not in s]
    if missing:
        raise CalibrationError(f"rectification keys {', '.join(missing)} are missing (found {', '.join(present)})",
                               path)
    mats: dict[str, np.ndarray] = {}
    for k, sizes in (("K", (9,)), ("D", (4, 5, 8)), ("R", (9,)), ("P", (12,))):
        for side in ("LEFT", "RIGHT"):
            mats[f"{side}.{k}"] = _numbers(s[f"{side}.{k}"], f"{side}.{k}", path, sizes)
    if "LEFT.width" in s and "LEFT.height" in s:
        w, h = _size_from(s, "LEFT.width", "LEFT.height", path, None)
    else:  # the raw size: ORB-SLAM2 rectifies to LEFT.width/height; fall back to Camera.* or the images
        w, h = _size_from(s, "Camera.width", "Camera.height", path, image_size)
    if "RIGHT.width" in s and "RIGHT.height" in s:
        if _size_from(s, "RIGHT.width", "RIGHT.height", path, None) != (w, h):
            raise CalibrationError("LEFT.width/height and RIGHT.width/height differ", path)
    P1 = mats["LEFT.P"].reshape(3, 4)
    P2 = mats["RIGHT.P"].reshape(3, 4)
    if not np.allclose([P1[0, 0], P1[1, 1], P1[0, 2], P1[1, 2]], [fx, fy, cx, cy], rtol=1e-4, atol=1e-3):
        raise CalibrationError(
            "Camera.fx/fy/cx/cy must equal LEFT.P's intrinsics (the rectified camera): "
            f"{[fx, fy, cx, cy]} vs {[P1[0, 0], P1[1, 1], P1[0, 2], P1[1, 2]]}",
            path,
        )
    if not (P2[0, 3] < 0):
        raise CalibrationError(f"RIGHT.P[0,3] must be -bf (negative), got {P2[0, 3]}", path)
    return RawStereoCalibration(
        K1=mats["LEFT.K"].reshape(3, 3), D1=mats["LEFT.D"], K2=mats["RIGHT.K"].reshape(3, 3), D2=mats["RIGHT.D"],
        width=w, height=h, R1=mats["LEFT.R"].reshape(3, 3), R2=mats["RIGHT.R"].reshape(3, 3), P1=P1, P2=P2,
        source=path,
    )


_OWN_RECTIFIED_KEYS = {"fx", "fy", "cx", "cy", "baseline", "bf", "width", "height"}
_OWN_RAW_KEYS = {"left", "right", "R", "T", "width", "height", "alpha"}


def load_stereo_yaml(path: str | Path,
                     image_size: tuple[int, int] | None = None) -> StereoCalibration | RawStereoCalibration:
    """Calibration from a generic YAML file: dynastereo's format or ORB-SLAM2 settings (module doc).

    ``image_size`` (``(width, height)`` of the images, if known) fills in a missing size.
    """
    path = Path(path)
    d = read_yaml_file(path)
    if is_orbslam2_settings(d):
        return orbslam2_calibration(load_orbslam2_settings(path), path, image_size)
    if "left" in d or "right" in d:
        return _own_raw(d, path, image_size)
    if "fx" in d:
        return _own_rectified(d, path, image_size)
    raise CalibrationError(
        "unrecognized calibration YAML: expected 'fx, cx, cy, baseline' (rectified), "
        "'left: {K, D}, right: {K, D}, R, T' (raw) or an ORB-SLAM2 settings file with 'Camera.fx'; "
        f"found keys {', '.join(map(str, d)) or 'none'}",
        path,
    )


def _check_keys(d: dict[str, Any], allowed: set[str], path: Path, form: str) -> None:
    unknown = [str(k) for k in d if k not in allowed]
    if unknown:
        raise CalibrationError(
            f"unknown key(s) {', '.join(unknown)} in the {form} form (allowed: {', '.join(sorted(allowed))})", path
        )


def _own_rectified(d: dict[str, Any], path: Path, image_size: tuple[int, int] | None) -> StereoCalibration:
    _check_keys(d, _OWN_RECTIFIED_KEYS, path, "rectified")
    for key in ("cx", "cy"):
        if key not in d:
            raise CalibrationError(f"key '{key}' is missing (rectified form)", path)
    fx = _number(d["fx"], "fx", path)
    fy = _number(d.get("fy", fx), "fy", path)
    cx, cy = _number(d["cx"], "cx", path), _number(d["cy"], "cy", path)
    if not (fx > 0 and fy > 0):
        raise CalibrationError(f"focal lengths must be positive (fx={fx}, fy={fy})", path)
    if "baseline" in d:
        baseline = _number(d["baseline"], "baseline", path)
    elif "bf" in d:
        baseline = _number(d["bf"], "bf", path) / fx
    else:
        raise CalibrationError("key 'baseline' (metres) or 'bf' (baseline * fx) is missing", path)
    if not baseline > 0:
        raise CalibrationError(f"baseline must be positive, got {baseline}", path)
    w, h = _size_from(d, "width", "height", path, image_size)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
    return StereoCalibration(K=K, baseline=baseline, width=w, height=h)


def _own_raw(d: dict[str, Any], path: Path, image_size: tuple[int, int] | None) -> RawStereoCalibration:
    _check_keys(d, _OWN_RAW_KEYS, path, "raw")
    cams = []
    for side in ("left", "right"):
        c = d.get(side)
        if not isinstance(c, dict):
            raise CalibrationError(f"key '{side}' must be a mapping with K (and D), got {c!r}", path)
        unknown = [str(k) for k in c if k not in ("K", "D")]
        if unknown:
            raise CalibrationError(f"unknown key(s) {', '.join(unknown)} under '{side}' (allowed: K, D)", path)
        if "K" not in c:
            raise CalibrationError(f"key '{side}.K' is missing", path)
        K = _intrinsics(c["K"], f"{side}.K", path)
        D = _numbers(c.get("D", [0.0] * 5), f"{side}.D", path, (0, 4, 5, 8, 12, 14))
        cams.append((K, D))
    for key in ("R", "T"):
        if key not in d:
            raise CalibrationError(f"key '{key}' is missing (raw form: rotation and translation left -> right)", path)
    r = _numbers(d["R"], "R", path, (3, 9))
    R = cv2.Rodrigues(r.reshape(3, 1))[0] if r.size == 3 else r.reshape(3, 3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
        raise CalibrationError("key 'R' is not a rotation matrix (R R^T != I or det < 0)", path)
    T = _numbers(d["T"], "T", path, (3,))
    if not T[0] < 0:
        raise CalibrationError(
            f"key 'T': the right camera must be to the right of the left one (T[0] < 0, metres), got {T.tolist()}",
            path,
        )
    w, h = _size_from(d, "width", "height", path, image_size)
    alpha = _number(d.get("alpha", 0.0), "alpha", path)
    return RawStereoCalibration(K1=cams[0][0], D1=cams[0][1], K2=cams[1][0], D2=cams[1][1], width=w, height=h,
                                R=R, T=T, alpha=alpha, source=path)


# --------------------------------------------------------------------------- Middlebury


@dataclass(frozen=True)
class MiddleburyCalibration:
    """Middlebury 2014 ``calib.txt``: rectified pair with a principal-point offset ``doffs``.

    ``depth = baseline * fx / (disparity + doffs)``; ``calibration`` is cam0's ``K`` with the
    baseline in metres (the file gives millimetres).
    """

    calibration: StereoCalibration
    K1: np.ndarray
    doffs: float
    ndisp: int
    vmin: float | None = None
    vmax: float | None = None


def load_middlebury_calib(path: str | Path) -> MiddleburyCalibration:
    path = Path(path)
    if not path.is_file():
        raise CalibrationError("calibration file not found" if not path.exists() else "not a file", path)
    vals: dict[str, str] = {}
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        key, sep, rest = s.partition("=")
        if not sep:
            raise CalibrationError(f"line {lineno} is not 'key=value': {s[:60]!r}", path)
        vals[key.strip()] = rest.strip()

    def mat(key: str) -> np.ndarray:
        if key not in vals:
            raise CalibrationError(f"key '{key}' is missing", path)
        toks = vals[key].strip("[]").replace(";", " ").split()
        try:
            a = np.array([float(t) for t in toks], dtype=np.float64)
        except ValueError:
            raise CalibrationError(f"key '{key}': not a 3x3 matrix of numbers: {vals[key]!r}", path) from None
        if a.size != 9:
            raise CalibrationError(f"key '{key}': expected 9 numbers, got {a.size}", path)
        return a.reshape(3, 3)

    def num(key: str, required: bool = True) -> float | None:
        if key not in vals:
            if required:
                raise CalibrationError(f"key '{key}' is missing", path)
            return None
        return _number(vals[key], key, path)

    K0, K1 = mat("cam0"), mat("cam1")
    baseline_mm = num("baseline")
    calib = StereoCalibration(K=K0, baseline=float(baseline_mm) / 1000.0, width=int(num("width")),
                              height=int(num("height")))
    return MiddleburyCalibration(calibration=calib, K1=K1, doffs=float(num("doffs")), ndisp=int(num("ndisp")),
                                 vmin=num("vmin", False), vmax=num("vmax", False))


# --------------------------------------------------------------------------- sanity against the images

#: The principal point may lie this share of the image size outside the image (a
#: rectification with a free scaling moves it a little); farther out is a typo.
PRINCIPAL_POINT_MARGIN = 0.1
#: fx / fy outside [1/FOCAL_RATIO_MAX, FOCAL_RATIO_MAX] is no camera of this project.
FOCAL_RATIO_MAX = 1.5


def check_intrinsics(calibration: "StereoCalibration | RawStereoCalibration", size: tuple[int, int],
                     source: str | Path | None) -> None:
    """CalibrationError naming ``source`` and the value when a camera's principal point
    lies outside the ``size`` = ``(width, height)`` image by more than
    :data:`PRINCIPAL_POINT_MARGIN` of its size, or its fx/fy ratio is beyond
    :data:`FOCAL_RATIO_MAX` -- a calibration that would track, drifting, without a word."""
    w, h = size
    if isinstance(calibration, RawStereoCalibration):
        cams = (("left K", calibration.K1), ("right K", calibration.K2))
    else:
        cams = (("", calibration.K),)
    mx, my = PRINCIPAL_POINT_MARGIN * w, PRINCIPAL_POINT_MARGIN * h
    for label, K in cams:
        fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        where = f"{label}: " if label else ""
        if not (-mx <= cx <= w + mx and -my <= cy <= h + my):
            raise CalibrationError(
                f"{where}principal point cx={cx:g}, cy={cy:g} lies outside the {w}x{h} image (allowed "
                f"cx {-mx:g}..{w + mx:g}, cy {-my:g}..{h + my:g}: a margin of {PRINCIPAL_POINT_MARGIN:.0%})", source)
        if not 1 / FOCAL_RATIO_MAX <= fx / fy <= FOCAL_RATIO_MAX:
            raise CalibrationError(
                f"{where}fx={fx:g}, fy={fy:g}: the ratio fx/fy={fx / fy:.3g} is outside "
                f"{1 / FOCAL_RATIO_MAX:.3g}..{FOCAL_RATIO_MAX:g} (pixels that far from square are a typo)", source)
