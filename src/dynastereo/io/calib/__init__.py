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

One module per format: ``kitti_txt`` (KITTI), ``kitti_cam_to_cam`` (KITTI raw), ``euroc_sensor``
(EuRoC), ``stereo_yaml`` (generic YAML: dynastereo's own format), ``orbslam2`` (ORB-SLAM2
settings), ``middlebury``; beside them ``raw`` (:class:`RawStereoCalibration`), ``opencv_yaml``
(:func:`read_yaml_file`), ``common`` (numbers and sizes checked) and ``checks``
(:func:`check_intrinsics`, against the images).

All errors raise :class:`~dynastereo.errors.CalibrationError` naming the file and the key/row.
"""

from __future__ import annotations

from .checks import FOCAL_RATIO_MAX, PRINCIPAL_POINT_MARGIN, check_intrinsics
from .euroc_sensor import euroc_T_BS, load_euroc_calib, read_euroc_T_BS
from .kitti_cam_to_cam import (
    KITTI_RAW_COLOUR_PAIR,
    KITTI_RAW_GRAY_PAIR,
    kitti_raw_projections,
    load_kitti_raw_calib,
)
from .kitti_txt import kitti_projections, load_kitti_calib, read_kitti_calib_rows
from .middlebury import MiddleburyCalibration, load_middlebury_calib
from .opencv_yaml import read_yaml_file
from .orbslam2 import is_orbslam2_settings, load_orbslam2_settings, orbslam2_calibration
from .raw import RawStereoCalibration
from .stereo_yaml import load_stereo_yaml

__all__ = [
    "FOCAL_RATIO_MAX",
    "KITTI_RAW_COLOUR_PAIR",
    "KITTI_RAW_GRAY_PAIR",
    "MiddleburyCalibration",
    "PRINCIPAL_POINT_MARGIN",
    "RawStereoCalibration",
    "check_intrinsics",
    "euroc_T_BS",
    "is_orbslam2_settings",
    "kitti_projections",
    "kitti_raw_projections",
    "load_euroc_calib",
    "load_kitti_calib",
    "load_kitti_raw_calib",
    "load_middlebury_calib",
    "load_orbslam2_settings",
    "load_stereo_yaml",
    "orbslam2_calibration",
    "read_euroc_T_BS",
    "read_kitti_calib_rows",
    "read_yaml_file",
]
