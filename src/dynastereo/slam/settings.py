"""ORB-SLAM2 stereo settings files (``Camera.fx`` ... ``Camera.bf``, ``ThDepth``,
``ORBextractor.*``) -> ``SlamConfig`` + ``StereoCalibration``.

They are OpenCV FileStorage YAML (``%YAML:1.0`` header); read with
``cv2.FileStorage``, falling back to plain YAML.  Keys used::

    Camera.fx, Camera.fy, Camera.cx, Camera.cy, Camera.bf, Camera.width, Camera.height
    Camera.fps -> max_frames
    ThDepth -> th_depth
    ORBextractor.nFeatures / scaleFactor / nLevels / iniThFAST / minThFAST

Rectification matrices (``LEFT.*`` / ``RIGHT.*``) are not read here: dynastereo's io
rectifies raw input itself.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from ..config import SlamConfig
from ..errors import ConfigError
from ..types import StereoCalibration

_MAP = {
    "ORBextractor.nFeatures": ("n_features", int),
    "ORBextractor.scaleFactor": ("scale_factor", float),
    "ORBextractor.nLevels": ("n_levels", int),
    "ORBextractor.iniThFAST": ("ini_th_fast", int),
    "ORBextractor.minThFAST": ("min_th_fast", int),
    "ThDepth": ("th_depth", float),
}


def read_orbslam_settings(path: str | Path) -> dict[str, Any]:
    """All scalar keys of an ORB-SLAM2 settings file."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError("ORB-SLAM2 settings file not found", p)
    out: dict[str, Any] = {}
    try:
        import cv2

        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
        if fs.isOpened():
            root = fs.root()
            for key in root.keys():
                node = root.getNode(key)
                if node.isReal() or node.isInt():
                    out[key] = node.real()
                elif node.isString():
                    out[key] = node.string()
            fs.release()
    except Exception:  # noqa: BLE001 -- fall back to plain YAML below
        out = {}
    if not out:
        import yaml

        try:
            text = "\n".join(ln for ln in p.read_text().splitlines() if not ln.startswith("%YAML"))
            data = yaml.safe_load(text) or {}
        except (OSError, yaml.YAMLError) as e:
            raise ConfigError(f"cannot parse ORB-SLAM2 settings: {e}", p) from None
        if not isinstance(data, dict):
            raise ConfigError("top level must be a mapping", p)
        out = {k: v for k, v in data.items() if isinstance(v, (int, float, str))}
    return out


def is_orbslam_settings(data: dict[str, Any]) -> bool:
    return any(k.startswith(("Camera.", "ORBextractor.")) or k == "ThDepth" for k in data)


def slam_config_from_orbslam(data: dict[str, Any], base: SlamConfig | None = None, path: Path | None = None) -> SlamConfig:
    cfg = dataclasses.replace(base or SlamConfig())
    for key, (field_name, tp) in _MAP.items():
        if key in data:
            try:
                setattr(cfg, field_name, tp(data[key]))
            except (TypeError, ValueError):
                raise ConfigError(f"'{key}' must be a number, got {data[key]!r}", path) from None
    if "Camera.fps" in data:
        try:
            fps = float(data["Camera.fps"])
        except (TypeError, ValueError):
            raise ConfigError(f"'Camera.fps' must be a number, got {data['Camera.fps']!r}", path) from None
        if fps > 0:
            cfg.max_frames = int(round(fps))
    return cfg


def calibration_from_orbslam(data: dict[str, Any], path: Path | None = None) -> StereoCalibration | None:
    """Rectified stereo calibration from ``Camera.*`` keys (None if absent)."""
    need = ("Camera.fx", "Camera.fy", "Camera.cx", "Camera.cy", "Camera.bf")
    if not all(k in data for k in need):
        missing = [k for k in need if k not in data]
        if len(missing) < len(need):
            raise ConfigError(f"ORB-SLAM2 settings lack {', '.join(missing)}", path)
        return None
    try:
        fx, fy, cx, cy, bf = (float(data[k]) for k in need)
        w = int(float(data.get("Camera.width", 2 * cx)))
        h = int(float(data.get("Camera.height", 2 * cy)))
    except (TypeError, ValueError) as e:
        raise ConfigError(f"invalid camera value: {e}", path) from None
    if fx <= 0 or bf <= 0:
        raise ConfigError(f"Camera.fx and Camera.bf must be positive (fx={fx}, bf={bf})", path)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return StereoCalibration(K=K, baseline=bf / fx, width=w, height=h)


def load_orbslam_settings(path: str | Path, base: SlamConfig | None = None) -> tuple[SlamConfig, StereoCalibration | None]:
    """``(SlamConfig, StereoCalibration or None)`` from an ORB-SLAM2 stereo settings file."""
    p = Path(path)
    data = read_orbslam_settings(p)
    if not is_orbslam_settings(data):
        raise ConfigError("not an ORB-SLAM2 settings file (no Camera.* / ORBextractor.* / ThDepth keys)", p)
    return slam_config_from_orbslam(data, base, p), calibration_from_orbslam(data, p)
