"""Exceptions raised by dynastereo.

Every error that comes from bad user input names the file (or the option) and
the problem, so the CLI can print it as one line without a traceback.
"""

from __future__ import annotations

from pathlib import Path


class DynastereoError(Exception):
    """Base class of all errors dynastereo raises on purpose."""


class InputError(DynastereoError):
    """Bad input: a missing or malformed file, an unknown option value."""

    def __init__(self, message: str, path: str | Path | None = None):
        self.path = Path(path) if path is not None else None
        super().__init__(f"{path}: {message}" if path is not None else message)


class CalibrationError(InputError):
    """Missing or malformed calibration."""


class SequenceError(InputError):
    """A stereo sequence that cannot be read (layout, counts, image sizes)."""


class ImageReadError(InputError):
    """An image file that is missing or cannot be decoded."""


class ModelError(InputError):
    """A detector model that is unknown, missing, or fails its checksum."""


class ConfigError(InputError):
    """A configuration file or value that is invalid."""


class MapFileError(InputError):
    """A saved SLAM map that cannot be used: missing, corrupt, of another format or a
    newer version, inconsistent, or built for another camera / ORB setting."""


class RosUnavailable(DynastereoError):
    """ROS 1 (``rospy`` and the message packages) is not importable; the message names the
    Debian packages to install."""
