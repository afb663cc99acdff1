"""Transport-agnostic message <-> numpy conversions (no ROS installation needed).

Every function here works on *any* object with the fields of the ROS message: the
dataclasses of the ``rosbags`` library (bags, ROS 1 and ROS 2 field names alike) and the
genpy classes of ``rospy`` (live ROS 1 node) -- images are converted with numpy, never
with ``cv_bridge`` (Debian's cv_bridge is built against numpy 1).

Images
------
:class:`ImageDecoder` turns ``sensor_msgs/Image`` (``mono8``, ``8UC1``, ``mono16``,
``16UC1``, ``bgr8``, ``rgb8``, ``bgra8``, ``rgba8``, ``8UC3``) and
``sensor_msgs/CompressedImage`` (PNG, JPEG: whatever ``cv2.imdecode`` reads) into what the
pipeline eats: ``uint8`` gray ``(H, W)`` or BGR ``(H, W, 3)``.  Row padding (``step``)
and big-endian 16-bit data are honoured.  The message is checked here (encoding, sizes,
one-line :class:`InputError`) and its row padding dropped; ``rosbags-image``
(:func:`rosbags.image.image_to_cvimage`) then does dtype, byte order and the colour
conversion to BGR.  CompressedImage is decoded with ``cv2.imdecode(IMREAD_UNCHANGED)``
itself: rosbags-image's decoder (``IMREAD_ANYCOLOR``) would cut 16-bit PNGs to 8 bits
before the fixed shift below, and fails on bad data with a bare ``AssertionError``.  16-bit images become 8-bit by a right shift
that is fixed once per decoder (not per frame, which would change the brightness from
frame to frame): given, or chosen from the first 16-bit image so that its largest value
fits in 8 bits (a 12-bit camera -> shift 4, full 16-bit range -> shift 8).

:func:`image_fields` is the reverse: the field values of a ``sensor_msgs/Image`` for a
numpy image (``mono8`` / ``bgr8`` / ``32FC1`` / ``mono16``).

Calibration
-----------
:func:`calibration_from_camera_info` reads a left/right ``sensor_msgs/CameraInfo`` pair:
``P`` (3x4) is the projection of the *rectified* camera, ``R`` the rectification
rotation, ``K``/``D`` the raw camera.  When the pair says the images are already
rectified (``D`` zero, ``R`` identity, ``K == P[:, :3]``) -- or ``rectify="no"`` -- the
result is a rectified :class:`~dynastereo.datatypes.StereoCalibration` with ``K = P_left[:, :3]``
and ``baseline = (P_left[0,3] - P_right[0,3]) / fx`` (ROS: ``P_right[0,3] = -fx * B``; the
same arithmetic as KITTI's ``calib.txt``); otherwise a
:class:`~dynastereo.io.calib.RawStereoCalibration` that carries ``R``/``P`` as its
ready-made rectification (a :class:`~dynastereo.io.rectify.Rectifier` remaps with exactly
those, as ``image_proc`` does).  :func:`camera_info_fields` is the reverse.

Poses
-----
:func:`pose_quaternion` (3x4/4x4 -> position, quaternion ``x y z w`` with ``w >= 0``) and
:func:`twist_between` (finite-difference velocity, in the child frame).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
from rosbags.image import image_to_cvimage
from scipy.spatial.transform import Rotation

from ..errors import CalibrationError, InputError
from ..io.calib import RawStereoCalibration
from ..datatypes import StereoCalibration

# encoding -> (numpy dtype, channels)
IMAGE_ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    "mono8": (np.dtype(np.uint8), 1),
    "8UC1": (np.dtype(np.uint8), 1),
    "mono16": (np.dtype(np.uint16), 1),
    "16UC1": (np.dtype(np.uint16), 1),
    "bgr8": (np.dtype(np.uint8), 3),
    "rgb8": (np.dtype(np.uint8), 3),
    "8UC3": (np.dtype(np.uint8), 3),
    "bgra8": (np.dtype(np.uint8), 4),
    "rgba8": (np.dtype(np.uint8), 4),
    "32FC1": (np.dtype(np.float32), 1),
}

# encodings whose channel order is RGB(A)
_RGB = ("rgb8", "rgba8")


def field(msg: Any, *names: str, default: Any = None) -> Any:
    """The first attribute of ``msg`` among ``names`` (ROS 1 ``K`` vs ROS 2 ``k`` ...)."""
    for n in names:
        if hasattr(msg, n):
            return getattr(msg, n)
    if default is not None:
        return default
    raise AttributeError(f"{type(msg).__name__} has none of the fields {', '.join(names)}")


def _bytes_view(data: Any) -> np.ndarray:
    """``uint8`` view of a message's ``data`` (bytes from rospy, ndarray from rosbags, list)."""
    if isinstance(data, np.ndarray):
        return data.view(np.uint8).reshape(-1) if data.dtype != np.uint8 else data.reshape(-1)
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    return np.asarray(data, dtype=np.uint8).reshape(-1)


def _packed_image(msg: Any, where: str = "") -> SimpleNamespace:
    """The checked fields of a ``sensor_msgs/Image`` with the row padding dropped, as
    :func:`rosbags.image.image_to_cvimage` reads them (it takes rows as packed)."""
    enc = str(msg.encoding)
    if enc not in IMAGE_ENCODINGS:
        raise InputError(
            f"unsupported image encoding {enc!r}; supported: {', '.join(IMAGE_ENCODINGS)} "
            "(or sensor_msgs/CompressedImage)", where or None)
    dtype, ch = IMAGE_ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * ch * dtype.itemsize
    if h <= 0 or w <= 0:
        raise InputError(f"empty image ({w}x{h})", where or None)
    if step < row:
        raise InputError(f"image step {step} is smaller than width*channels*bytes = {row} ({enc}, {w}x{h})",
                         where or None)
    buf = _bytes_view(msg.data)
    if buf.size < h * step:
        raise InputError(f"image data holds {buf.size} bytes, expected height*step = {h}*{step} = {h * step}",
                         where or None)
    data = buf[: h * row] if step == row else np.ascontiguousarray(buf[: h * step].reshape(h, step)[:, :row])
    return SimpleNamespace(height=h, width=w, encoding=enc, is_bigendian=int(bool(getattr(msg, "is_bigendian", 0))),
                           step=row, data=data)


def image_to_array(msg: Any, where: str = "") -> np.ndarray:
    """A ``sensor_msgs/Image`` as a numpy array in its own encoding's dtype (native byte
    order; no conversion of depth or channel order): ``(H, W)`` or ``(H, W, C)``."""
    return image_to_cvimage(_packed_image(msg, where))


class ImageDecoder:
    """Image / CompressedImage messages -> ``uint8`` gray or BGR arrays (module doc).

    ``mono16_shift``: right shift for 16-bit images; ``None`` = choose from the first
    16-bit image and keep it.
    """

    def __init__(self, mono16_shift: int | None = None) -> None:
        if mono16_shift is not None and not 0 <= int(mono16_shift) <= 8:
            raise ValueError(f"mono16_shift must be in 0..8, got {mono16_shift}")
        self.mono16_shift = None if mono16_shift is None else int(mono16_shift)

    def to_uint8(self, img: np.ndarray) -> np.ndarray:
        if img.dtype == np.uint8:
            return img
        if img.dtype != np.uint16:
            raise InputError(f"cannot convert a {img.dtype} image to 8 bits")
        if self.mono16_shift is None:
            top = int(img.max()) if img.size else 0
            self.mono16_shift = max(0, top.bit_length() - 8)
        s = self.mono16_shift
        return (np.minimum(img >> s, 255) if s < 8 else img >> 8).astype(np.uint8)

    def decode(self, msg: Any, where: str = "") -> np.ndarray:
        """``uint8`` gray ``(H, W)`` or BGR ``(H, W, 3)`` from an Image or CompressedImage."""
        if hasattr(msg, "format") and not hasattr(msg, "encoding"):
            return self.decode_compressed(msg, where)
        packed = _packed_image(msg, where)
        if packed.encoding == "32FC1":
            raise InputError("a 32FC1 (float) image is not a camera image", where or None)
        if IMAGE_ENCODINGS[packed.encoding][1] > 1:  # colour: rosbags-image drops alpha, RGB -> BGR
            return image_to_cvimage(packed, "bgr8")
        return self.to_uint8(image_to_cvimage(packed))

    def decode_compressed(self, msg: Any, where: str = "") -> np.ndarray:
        buf = _bytes_view(msg.data)
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
        if img is None:
            raise InputError(f"cannot decode CompressedImage (format {str(msg.format)!r}, {buf.size} bytes)",
                             where or None)
        if img.ndim == 3:
            if img.shape[2] == 4:
                img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
            # OpenCV decodes to BGR; "rgb8; jpeg compressed bgr8" style formats describe the
            # raw image before compression, the compressed stream itself is BGR for OpenCV.
        return self.to_uint8(img) if img.dtype != np.uint8 else img


def image_fields(img: np.ndarray, encoding: str | None = None) -> dict[str, Any]:
    """Field values (``height width encoding is_bigendian step data``) of a
    ``sensor_msgs/Image`` holding ``img``; ``data`` is a flat ``uint8`` array (call
    ``.tobytes()`` for rospy).  Default encoding: ``mono8`` (2-D uint8), ``bgr8`` (3-channel
    uint8), ``mono16`` (uint16), ``32FC1`` (float32)."""
    img = np.asarray(img)
    if encoding is None:
        if img.dtype == np.uint8:
            encoding = "mono8" if img.ndim == 2 else "bgr8"
        elif img.dtype == np.uint16:
            encoding = "mono16"
        elif img.dtype == np.float32:
            encoding = "32FC1"
        else:
            raise ValueError(f"no image encoding for dtype {img.dtype}")
    if encoding not in IMAGE_ENCODINGS:
        raise ValueError(f"unsupported encoding {encoding!r}")
    dtype, ch = IMAGE_ENCODINGS[encoding]
    if encoding in _RGB and img.ndim == 3:
        img = img[:, :, ::-1]
    if ch == 3 and img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if ch == 1 and img.ndim == 3:
        raise ValueError(f"encoding {encoding} needs a single-channel image, got shape {img.shape}")
    img = np.ascontiguousarray(img, dtype=dtype.newbyteorder("<"))
    h, w = img.shape[:2]
    return {
        "height": int(h),
        "width": int(w),
        "encoding": encoding,
        "is_bigendian": 0,
        "step": int(w * ch * dtype.itemsize),
        "data": img.reshape(-1).view(np.uint8),
    }


def encode_compressed(img: np.ndarray, fmt: str = "png", jpeg_quality: int = 95) -> tuple[str, np.ndarray]:
    """``(format string, bytes as uint8 array)`` of a ``sensor_msgs/CompressedImage``."""
    fmt = fmt.lower()
    if fmt not in ("png", "jpeg"):
        raise ValueError(f"compressed format must be png or jpeg, got {fmt!r}")
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if fmt == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 1]
    ok, buf = cv2.imencode("." + ("jpg" if fmt == "jpeg" else "png"), img, params)
    if not ok:
        raise ValueError(f"cannot encode a {img.shape} {img.dtype} image as {fmt}")
    enc = "mono8" if img.ndim == 2 else "bgr8"
    return f"{enc}; {fmt} compressed {enc}", buf.reshape(-1)


# --------------------------------------------------------------------------- calibration


@dataclass(frozen=True)
class CameraInfoData:
    """The fields of one ``sensor_msgs/CameraInfo`` that matter here (numpy)."""

    width: int
    height: int
    distortion_model: str
    D: np.ndarray
    K: np.ndarray  # 3x3
    R: np.ndarray  # 3x3
    P: np.ndarray  # 3x4
    binning: tuple[int, int] = (0, 0)

    @classmethod
    def from_msg(cls, msg: Any) -> "CameraInfoData":
        D = np.asarray(field(msg, "D", "d"), dtype=np.float64).reshape(-1)
        K = np.asarray(field(msg, "K", "k"), dtype=np.float64).reshape(3, 3)
        R = np.asarray(field(msg, "R", "r"), dtype=np.float64).reshape(3, 3)
        P = np.asarray(field(msg, "P", "p"), dtype=np.float64).reshape(3, 4)
        return cls(int(msg.width), int(msg.height), str(msg.distortion_model or ""), D, K, R, P,
                   (int(getattr(msg, "binning_x", 0) or 0), int(getattr(msg, "binning_y", 0) or 0)))

    def same(self, other: "CameraInfoData") -> bool:
        return (self.width, self.height, self.distortion_model) == (other.width, other.height, other.distortion_model) \
            and all(np.array_equal(a, b) for a, b in ((self.D, other.D), (self.K, other.K), (self.R, other.R),
                                                       (self.P, other.P)))

    @property
    def is_rectified(self) -> bool:
        """True when rectification is the identity: no distortion, R = I, K = P[:, :3]."""
        return (not np.any(self.D)) and np.allclose(self.R, np.eye(3), atol=1e-9) \
            and np.allclose(self.K, self.P[:, :3], rtol=1e-9, atol=1e-9)


RECTIFY_MODES = ("auto", "yes", "no")


def calibration_from_camera_info(
    left: Any, right: Any, rectify: str = "auto", where: str = "CameraInfo"
) -> StereoCalibration | RawStereoCalibration:
    """Stereo calibration from a left/right CameraInfo pair (module doc).

    ``rectify``: ``"auto"`` (rectify unless the infos say the images are rectified
    already), ``"yes"`` (always remap with ``R``/``P``) or ``"no"`` (the images are
    rectified: use ``P`` only).  Raises :class:`CalibrationError` naming ``where``.
    """
    if rectify not in RECTIFY_MODES:
        raise CalibrationError(f"rectify must be one of {', '.join(RECTIFY_MODES)}, got {rectify!r}", where)
    L = left if isinstance(left, CameraInfoData) else CameraInfoData.from_msg(left)
    R = right if isinstance(right, CameraInfoData) else CameraInfoData.from_msg(right)
    if (L.width, L.height) != (R.width, R.height):
        raise CalibrationError(f"left camera is {L.width}x{L.height}, right camera {R.width}x{R.height}", where)
    if L.width <= 0 or L.height <= 0:
        raise CalibrationError(f"image size in CameraInfo is {L.width}x{L.height}", where)
    for side, c in (("left", L), ("right", R)):
        if not np.any(c.P):
            raise CalibrationError(f"{side} CameraInfo has no projection matrix P (camera not calibrated)", where)
        if max(c.binning) > 1:
            raise CalibrationError(f"{side} CameraInfo uses binning {c.binning}: not supported", where)
    Pl, Pr = L.P, R.P
    fx = float(Pl[0, 0])
    if not (fx > 0 and Pl[1, 1] > 0):
        raise CalibrationError(f"left P has focal lengths fx={Pl[0, 0]}, fy={Pl[1, 1]}", where)
    if not np.allclose(Pl[:, :3], Pr[:, :3], rtol=1e-6, atol=1e-6):
        raise CalibrationError("left and right P have different intrinsics: not a rectified stereo pair", where)
    baseline = (Pl[0, 3] - Pr[0, 3]) / fx
    if not baseline > 0:
        raise CalibrationError(
            f"baseline from P is {baseline:.4f} m: the right camera must be to the right "
            "(right P[0,3] = -fx * baseline; left and right swapped?)", where)
    raw_needed = rectify == "yes" or (rectify == "auto" and not (L.is_rectified and R.is_rectified))
    if not raw_needed:
        return StereoCalibration(K=Pl[:, :3].copy(), baseline=float(baseline), width=L.width, height=L.height)
    for side, c in (("left", L), ("right", R)):
        model = c.distortion_model.lower()
        if model not in ("", "plumb_bob", "rational_polynomial"):
            raise CalibrationError(f"{side} distortion model {c.distortion_model!r} not supported "
                                   "(plumb_bob, rational_polynomial)", where)
        if c.D.size not in (0, 4, 5, 8, 12, 14):
            raise CalibrationError(f"{side} D has {c.D.size} coefficients (4, 5, 8, 12 or 14 expected)", where)
        if not np.any(c.K):
            raise CalibrationError(f"{side} CameraInfo has no intrinsic matrix K", where)
    return RawStereoCalibration(K1=L.K, D1=L.D, K2=R.K, D2=R.D, width=L.width, height=L.height,
                                R1=L.R, R2=R.R, P1=Pl, P2=Pr)


def camera_info_fields(
    calib: StereoCalibration | None = None,
    side: str = "left",
    *,
    P: np.ndarray | None = None,
    K: np.ndarray | None = None,
    D: np.ndarray | None = None,
    R: np.ndarray | None = None,
    width: int | None = None,
    height: int | None = None,
) -> dict[str, Any]:
    """Field values of a CameraInfo (numpy, upper-case keys ``D K R P``).

    From a rectified ``calib``: ``K``, zero distortion, ``R = I``, ``P = [K | 0]`` (left) or
    ``[K | (-fx*B, 0, 0)]`` (right).  Explicit ``P`` (e.g. KITTI's ``P0``/``P1``, so the
    baseline round-trips bit-exactly), ``K``, ``D``, ``R`` override.
    """
    if side not in ("left", "right"):
        raise ValueError(f"side must be left or right, got {side!r}")
    if calib is not None:
        Kc = calib.K
        if P is None:
            P = np.hstack([Kc, np.zeros((3, 1))])
            if side == "right":
                P[0, 3] = -calib.bf
        K = Kc if K is None else K
        width = calib.width if width is None else width
        height = calib.height if height is None else height
    if P is None or width is None or height is None:
        raise ValueError("need a calibration or P, width and height")
    P = np.asarray(P, np.float64).reshape(3, 4)
    K = np.asarray(P[:, :3] if K is None else K, np.float64).reshape(3, 3)
    D = np.zeros(5) if D is None else np.asarray(D, np.float64).reshape(-1)
    R = np.eye(3) if R is None else np.asarray(R, np.float64).reshape(3, 3)
    return {"width": int(width), "height": int(height), "distortion_model": "plumb_bob",
            "D": D, "K": K.reshape(-1), "R": R.reshape(-1), "P": P.reshape(-1)}


# --------------------------------------------------------------------------- poses


def pose_quaternion(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(position (3,), quaternion x y z w (4,))`` of a 3x4 / 4x4 pose; ``w >= 0``."""
    T = np.asarray(T, dtype=np.float64)
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    if q[3] < 0:
        q = -q
    return T[:3, 3].copy(), q


def twist_between(T_prev: np.ndarray | None, T: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Linear and angular velocity (child frame) from two camera-to-world poses ``dt`` s apart;
    zeros without a previous pose or with ``dt <= 0``."""
    if T_prev is None or not dt > 0:
        return np.zeros(3), np.zeros(3)
    Rp, R = np.asarray(T_prev)[:3, :3], np.asarray(T)[:3, :3]
    v = R.T @ (np.asarray(T)[:3, 3] - np.asarray(T_prev)[:3, 3]) / dt
    w = Rotation.from_matrix(Rp.T @ R).as_rotvec() / dt
    return v, w


def stamp_split(stamp_ns: int) -> tuple[int, int]:
    """``(sec, nanosec)`` of a time in nanoseconds."""
    s = int(stamp_ns)
    return s // 1_000_000_000, s % 1_000_000_000


def masked_image(img: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``img`` with the dynamic pixels (mask > 0) set to 0: what the SLAM may use."""
    out = img.copy()
    out[mask > 0] = 0
    return out


def objects_view(image: np.ndarray, mask: np.ndarray, masks: Any) -> np.ndarray:
    """The left image with the objects coloured by the motion test's verdicts (``left/objects``)."""
    from ..viz.draw import draw_objects

    if masks is None:
        return draw_objects(image, mask, [])
    return draw_objects(image, mask, masks.objects, masks.labels_left)


def image_outputs(frame: Any, masks: Any) -> tuple[tuple[str, Any, str | None], ...]:
    """A live node's image topics for one frame: ``(topic under the namespace, a function that
    makes the image, encoding or None for the image's own)``. The images are made only for the
    topics someone listens to, so each comes as a function."""
    shape = frame.left.shape[:2]
    ml = masks.left if masks is not None else np.zeros(shape, np.uint8)
    mr = masks.right if masks is not None else np.zeros(shape, np.uint8)
    return (("left/masked", lambda: masked_image(frame.left, ml), None),
            ("right/masked", lambda: masked_image(frame.right, mr), None),
            ("left/mask", lambda: ml, "mono8"), ("right/mask", lambda: mr, "mono8"),
            ("left/objects", lambda: objects_view(frame.left, ml, masks), None))
