"""YAML calibration files: OpenCV FileStorage (``%YAML:1.0``, ``!!opencv-matrix``) and plain
YAML, both read into a dict by :func:`read_yaml_file`."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from ...errors import CalibrationError
from ...yamlcheck import duplicate_key, yaml_error_line
from .common import _read_calib_text


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
    dup = duplicate_key(text)
    if dup is not None:
        raise CalibrationError(f"line {dup[1]}: key '{dup[0]}' is given twice (which one is meant?)", path)
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
            raise CalibrationError(f"invalid YAML: {yaml_error_line(e)}", path) from None
        except (KeyError, ValueError, TypeError) as e:
            raise CalibrationError(f"invalid !!opencv-matrix: {e}", path) from None
    if not isinstance(out, dict):
        raise CalibrationError("expected a YAML mapping of keys to values", path)
    return out
