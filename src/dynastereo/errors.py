"""Exceptions raised by dynastereo.

Every error that comes from bad user input names the file (or the option) and
the problem, so the CLI can print it as one line without a traceback.
"""

from __future__ import annotations

from pathlib import Path


class DynastereoError(Exception):
    """Base class of all errors dynastereo raises on purpose.

    What to do: read the one line; it names the file or option and the problem.  Messages
    of this class itself are about an option or a state the other classes do not cover."""


class InputError(DynastereoError):
    """Bad input: a missing or malformed file, an unknown option value.

    What to do: check the path the message starts with (does it exist, is it the kind of
    file the command wants) and the option values against ``dynastereo COMMAND --help``."""

    def __init__(self, message: str, path: str | Path | None = None):
        self.path = Path(path) if path is not None else None
        super().__init__(f"{path}: {message}" if path is not None else message)


class CalibrationError(InputError):
    """Missing or malformed calibration.

    What to do: write or fix the calibration YAML (docs/guide/inputs.md, "Write the
    calibration"), or pass it with ``--calib FILE``; its image size must match the images."""


class SequenceError(InputError):
    """A stereo sequence that cannot be read (layout, counts, image sizes).

    What to do: lay the images out as docs/guide/inputs.md says (``left/`` and ``right/``
    with the same number of images of one size), or point at the sequence folder itself."""


class ImageReadError(InputError):
    """An image file that is missing or cannot be decoded.

    What to do: replace or remove the file named (a truncated copy, a zero-byte file), keeping
    left and right paired."""


class ModelError(InputError):
    """A detector model that is unknown, missing, or fails its checksum.

    What to do: ``dynastereo models`` lists the names; ``dynastereo models download NAME``
    fetches one, ``--models-dir DIR`` or ``$DYNASTEREO_MODELS`` points at a folder holding it."""


class ConfigError(InputError):
    """A configuration file or value that is invalid.

    What to do: fix the key the message names (docs/reference/configuration.md lists every
    key with its type and default); ``dynastereo config -c FILE`` checks a file."""


class MapFileError(InputError):
    """A saved SLAM map that cannot be used: missing, corrupt, of another format or a
    newer version, inconsistent, or built for another camera / ORB setting.

    What to do: use a map saved with ``--save-map`` by this version, for the same camera
    calibration and ``slam`` ORB settings, or build a new one."""


class VocabularyError(InputError):
    """A vocabulary file that is missing, corrupt, of another format or version.

    What to do: leave ``--vocabulary`` out (the built-in one), or train one again with
    ``dynastereo vocab``."""


class RosUnavailable(DynastereoError):
    """ROS 1 (``rospy`` and the message packages) is not importable; the message names the
    Debian packages to install.

    What to do: install the packages the message names (docs/guide/ros.md), and make the
    venv with ``--system-site-packages`` (``scripts/venv.sh`` does)."""


class StereoCheckError(InputError):
    """A stereo pair that is not a rectified left/right pair: identical images, left and
    right swapped, or rows that do not line up (``--no-stereo-check`` overrides).

    What to do: check that left and right are not swapped or the same camera, and that the
    calibration fits (raw images need the raw form, rectified on read); see
    docs/guide/inputs.md, "Check the rectification"."""


class OutputError(InputError):
    """An output path that cannot be used: a file where a folder is wanted, not writable,
    or a folder holding an earlier run (``--overwrite``).

    What to do: choose another ``--out`` folder, or add ``--overwrite`` to replace the earlier
    run; check that the folder is writable and the disk not full."""


class Interrupted(BaseException):
    """SIGINT / SIGTERM received: the job stopped at a frame boundary, its results so far
    written.  A BaseException (like KeyboardInterrupt) so that ``except Exception`` blocks
    never swallow it.

    What to do: nothing; every output up to the last whole frame is written.  Exit status
    130 (SIGINT) or 143 (SIGTERM)."""

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
