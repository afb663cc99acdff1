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


class VocabularyError(InputError):
    """A vocabulary file that is missing, corrupt, of another format or version."""


class RosUnavailable(DynastereoError):
    """ROS 1 (``rospy`` and the message packages) is not importable; the message names the
    Debian packages to install."""


class StereoCheckError(InputError):
    """A stereo pair that is not a rectified left/right pair: identical images, left and
    right swapped, or rows that do not line up (``--no-stereo-check`` overrides)."""


class OutputError(InputError):
    """An output path that cannot be used: a file where a folder is wanted, not writable,
    or a folder holding an earlier run (``--overwrite``)."""


class Interrupted(BaseException):
    """SIGINT / SIGTERM received: the job stopped at a frame boundary, its results so far
    written.  A BaseException (like KeyboardInterrupt) so that ``except Exception`` blocks
    never swallow it."""

    def __init__(self, signum: int):
        import signal

        self.signum = int(signum)
        self.name = signal.Signals(self.signum).name
        super().__init__(f"{self.name} received")

    @property
    def exit_code(self) -> int:
        """128 + the signal number (130 SIGINT, 143 SIGTERM), as a shell reports it."""
        return 128 + self.signum


def as_interrupt(e: BaseException) -> BaseException:
    """``e``, or the :class:`Interrupted` it wraps: a signal handler that raises while a
    compiled function (a numba kernel's dispatcher) runs comes back as ``SystemError:
    ... returned a result with an exception set`` whose cause is the ``Interrupted``."""
    cause: BaseException | None = e
    while isinstance(cause, SystemError):  # possibly nested, one per native frame
        cause = cause.__cause__ or cause.__context__
    return cause if isinstance(cause, Interrupted) else e
