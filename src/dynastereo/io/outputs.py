"""Output paths checked before the first frame: writable, of the right kind, and not
holding an earlier run unless asked to replace it.

``prepare_output_dir(out, overwrite=...)`` creates ``out`` (parents too) and proves it
writable by writing a probe file; a folder that holds an earlier run's outputs (any of
``RUN_OUTPUTS``: masks, trajectories, timing.json, ...) is refused with an
:class:`OutputError` naming ``--overwrite``, or -- with ``overwrite`` -- those outputs
(and only those: in ``masks/``, ``disparity/`` and ``overlays/`` only the frame images
the program names ``NNNNNN.png``, a user's own files there are kept) are deleted, so that
no stale mask or plot of the earlier run is left beside the new ones.  Every input and
option is checked before that (``runtime.job``): a bad input never costs the earlier run.
``check_output_file(path)`` does the same for a single file (a plot, a map, a bag): not a
folder, its folder creatable and writable.  ``refuse_input_as_output`` refuses an output
path that is one of the command's inputs; :class:`OutputLock` keeps a second job from
writing into the same folder at the same time.
"""

from __future__ import annotations

import errno
import fnmatch
import os
import secrets
import shutil
import tempfile
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import IO, Iterable, Iterator

import numpy as np

from ..errors import OutputError

# Everything `dynastereo mask` / `run` (folder or bag) write into their output folder.
RUN_OUTPUTS = (
    "masks", "disparity", "overlays", "objects.jsonl", "objects_tracks.csv", "timing.json", "run.json", "bag.json",
    "trajectory.kitti.txt", "trajectory.tum.txt", "trajectory.frames.txt",
    "output.bag", "output.db3", "output.mcap",
)
# What `dynastereo synth` writes under its output root.
SYNTH_OUTPUTS = ("sequences/00", "poses/00.txt")
# The files the program writes inside its output folders (relative to the folder): with
# --overwrite only these are deleted, anything else a user put there stays.
OWN_FILES: dict[str, tuple[str, ...]] = {
    "masks": ("left/[0-9][0-9][0-9][0-9][0-9][0-9].png", "right/[0-9][0-9][0-9][0-9][0-9][0-9].png"),
    "disparity": ("[0-9][0-9][0-9][0-9][0-9][0-9].png",),
    "overlays": ("[0-9][0-9][0-9][0-9][0-9][0-9].png",),
}
#: The lock file that marks an output folder in use (``OutputLock``).
LOCK_NAME = ".dynastereo.lock"


@contextmanager
def atomic_open(path: str | Path, mode: str = "w", *, fsync: bool = True, mkdir: bool = True) -> Iterator[IO]:
    """``with atomic_open(path, "w" | "wb") as f:`` writes a temporary file beside ``path``
    (``.NAME.<random>.tmp``) and renames it over ``path`` when the block ends without an
    error; on an error the temporary file is removed and ``path`` stays as it was.  The
    file is created with mode 0666 minus the umask (0644 usually), as ``open(path, "w")``
    would make it -- not ``mkstemp``'s 0600.  ``fsync``: forced to disk before the rename;
    ``mkdir``: the parent folders are created."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open writes ('w' or 'wb'), not {mode!r}")
    path = Path(path)
    if mkdir:
        path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            if fsync:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with suppress(OSError):  # the error that stopped the write is the one to report
            tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | Path, text: str, *, fsync: bool = True, mkdir: bool = True) -> Path:
    """Write ``text`` to ``path`` atomically (:func:`atomic_open`)."""
    with atomic_open(path, "w", fsync=fsync, mkdir=mkdir) as f:
        f.write(text)
    return Path(path)


def atomic_write_bytes(path: str | Path, data: bytes, *, fsync: bool = True, mkdir: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically (:func:`atomic_open`)."""
    with atomic_open(path, "wb", fsync=fsync, mkdir=mkdir) as f:
        f.write(data)
    return Path(path)


def _reason(e: OSError) -> str:
    return e.strerror or type(e).__name__


def _probe_writable(folder: Path, target: Path, what: str = "output folder") -> None:
    try:
        fd, tmp = tempfile.mkstemp(prefix=".dynastereo-probe-", dir=folder)
    except OSError as e:
        raise OutputError(f"{what} is not writable ({_reason(e)})", target) from None
    os.close(fd)
    os.unlink(tmp)


def _make_dir(folder: Path, target: Path) -> None:
    for parent in (folder, *folder.parents):
        if parent.exists():
            if not parent.is_dir():
                what = "exists as a file" if parent == target else f"{parent} (on the path) is a file"
                raise OutputError(f"{what}, not a folder", target)
            break
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot create the output folder ({_reason(e)})", target) from None


def earlier_outputs(out: str | Path, names: Iterable[str] = RUN_OUTPUTS) -> list[Path]:
    """The outputs of an earlier run present in ``out``."""
    out = Path(out)
    return [out / n for n in names if (out / n).exists() or (out / n).is_symlink()]


def _own_files(folder: Path, patterns: tuple[str, ...]) -> list[Path]:
    """The files under ``folder`` whose relative path matches one of ``patterns``."""
    found = []
    for root, _dirs, files in os.walk(folder):
        for f in files:
            rel = (Path(root) / f).relative_to(folder).as_posix()
            if any(fnmatch.fnmatchcase(rel, pat) for pat in patterns):
                found.append(Path(root) / f)
    return found


def _remove_empty_dirs(folder: Path) -> None:
    """``folder`` and the folders below it that are empty (bottom up); others stay."""
    for root, _dirs, _files in sorted(os.walk(folder), key=lambda t: -len(t[0])):
        with suppress(OSError):
            os.rmdir(root)


def clear_outputs(paths: Iterable[Path]) -> None:
    """Delete ``paths``: files; folders of ``OWN_FILES`` only as far as the program wrote
    them (its frame images; a user's own files there stay); other folders whole."""
    for p in paths:
        try:
            own = OWN_FILES.get(p.name)
            if p.is_dir() and not p.is_symlink() and own is not None:
                for f in _own_files(p, own):
                    f.unlink()
                _remove_empty_dirs(p)
            elif p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
        except OSError as e:
            raise OutputError(f"cannot remove the earlier run's output ({_reason(e)})", p) from None


def _same_file(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return a.resolve() == b.resolve()


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except (OSError, ValueError):
        return False


def refuse_input_as_output(out: str | Path, inputs: Iterable[str | Path | None], *, what: str = "output file",
                           flag: str = "", folders: Iterable[str | Path | None] = (),
                           own: str | Path | None = None) -> None:
    """An :class:`OutputError` when ``out`` is one of ``inputs`` (the same file, by any
    path or link), or an existing file inside one of ``folders`` (a sequence folder: its
    images, calibration, stamps and poses are what the command reads) but not inside
    ``own`` (the command's output folder, which may lie in the sequence's): writing it
    would destroy the input."""
    out = Path(out)
    name = f"{flag} " if flag else ""
    for i in inputs:
        if i is None or str(i) == "":
            continue
        if _same_file(out, Path(i)):
            raise OutputError(f"{name}{what} is also an input of this command; writing it would destroy the input "
                              "-- choose another path", out)
    for f in folders:
        if f is None or str(f) == "" or not Path(f).is_dir():
            continue
        ours = own is not None and _inside(out, Path(own))
        if (out.is_file() or out.is_symlink()) and _inside(out, Path(f)) and not ours:
            raise OutputError(f"{name}{what} is a file of the input sequence {f}; writing it would destroy the "
                              "input -- choose a path outside it", out)


class OutputLock:
    """An exclusive lock on an output folder (``fcntl.flock`` on ``DIR/.dynastereo.lock``)
    for a job's whole life: a second job into the same folder at the same time is refused
    with an :class:`OutputError` (no mixed files, no torn rows).  The lock goes with the
    process (a killed job leaves no stale lock); the lock file itself stays."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self._fd: int | None = None

    def acquire(self) -> None:
        if self._fd is not None:
            return
        _make_dir(self.folder, self.folder)
        path = self.folder / LOCK_NAME
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as e:
            raise OutputError(f"output folder is not writable ({_reason(e)})", self.folder) from None
        try:
            import fcntl

            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except ImportError:  # not POSIX: no lock
            pass
        except OSError:
            other = ""
            with suppress(OSError, ValueError):
                other = os.pread(fd, 64, 0).decode().strip()
            os.close(fd)
            by = f" (pid {other})" if other.isdigit() else ""
            raise OutputError(f"output folder is in use by another dynastereo job{by}; wait for it to end, "
                              "or choose another folder", self.folder) from None
        with suppress(OSError):
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            with suppress(OSError):
                os.close(self._fd)  # closing the descriptor drops the lock
            self._fd = None

    def __enter__(self) -> "OutputLock":
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def prepare_output_dir(out: str | Path, *, overwrite: bool = False, names: Iterable[str] = RUN_OUTPUTS,
                       flag: str = "--overwrite") -> Path:
    """Create and check the output folder ``out`` (module doc); returns it as a Path."""
    out = Path(out)
    _make_dir(out, out)
    _probe_writable(out, out)
    earlier = earlier_outputs(out, names)
    if earlier:
        if not overwrite:
            shown = ", ".join(p.relative_to(out).as_posix() for p in earlier[:4]) + (", ..." if len(earlier) > 4 else "")
            raise OutputError(f"output folder holds an earlier run ({shown}); {flag} replaces it, "
                              "or choose another folder", out)
        clear_outputs(earlier)
    return out


def check_output_file(path: str | Path, *, what: str = "output file", overwrite: bool = True,
                      flag: str = "--overwrite") -> Path:
    """Check that ``path`` can be written as a file (module doc); with ``overwrite=False``
    an existing file is refused naming ``flag``."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{what} is a folder, not a file", path)
    if path.exists() and not path.is_file():  # a device, a FIFO, a socket: renaming into place would replace it
        raise OutputError(f"{what} is a special file (a device, pipe or socket), not a regular file", path)
    if path.exists() and not overwrite:
        raise OutputError(f"{what} exists already; {flag} replaces it", path)
    folder = path.parent if str(path.parent) else Path(".")
    try:
        _make_dir(folder, path)
    except OutputError as e:  # the folder is the file's: say which output it is for
        raise OutputError(f"{what}: {str(e).split(': ', 1)[-1]}", path) from None
    _probe_writable(folder, path, f"the {what}'s folder {folder}")
    if path.exists() and not os.access(path, os.W_OK):
        raise OutputError(f"{what} is not writable ({os.strerror(errno.EACCES)})", path)
    return path


# --------------------------------------------------------------------------- write errors


def write_failed(e: OSError, path: str | Path) -> OutputError:
    """The one-line error of a failed write (ENOSPC, EACCES, EIO, ...) naming ``path``."""
    return OutputError(f"cannot write ({_reason(e)})", path)


class RowFile:
    """An append-only text file of whole rows (lines): each :meth:`append` is one
    unbuffered ``write`` -- nothing waits in a buffer, so a crash keeps every row appended
    -- and a write that fails (disk full, EIO) is rolled back to the last whole row and
    raised as an :class:`OutputError` naming the file.  :meth:`truncate` drops rows from
    the end (it needs no free space), so that several files can be made to agree."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._f = open(self.path, "wb", buffering=0)
        except OSError as e:
            raise write_failed(e, self.path) from None
        self._ends: list[int] = [0]  # byte offset after each row (index = rows)

    @property
    def rows(self) -> int:
        return len(self._ends) - 1

    def append(self, text: str, fsync: bool = False) -> None:
        data = text.encode()
        try:
            n = self._f.write(data)
            if n is not None and n != len(data):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            if fsync:
                os.fsync(self._f.fileno())
        except OSError as e:
            self._cut(self._ends[-1])
            raise write_failed(e, self.path) from None
        self._ends.append(self._ends[-1] + len(data))

    def _cut(self, size: int) -> None:
        try:
            self._f.truncate(size)
            self._f.seek(size)
        except (OSError, ValueError):
            pass

    def truncate(self, rows: int) -> None:
        """Keep the first ``rows`` rows."""
        if 0 <= rows < self.rows:
            del self._ends[rows + 1:]
            self._cut(self._ends[-1])

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "RowFile":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path``; a failure (disk full, no permission) removes the
    partial file and raises an :class:`OutputError` naming it."""
    path = Path(path)
    try:
        with open(path, "wb") as f:
            f.write(data)
    except OSError as e:
        try:
            path.unlink(missing_ok=True)
        except OSError:
            pass
        raise write_failed(e, path) from None


#: ``run.json`` is written at the start with room for the final record (padding spaces,
#: which JSON ignores); when the disk is full at the end, the final record is written into
#: that room in place, so that the folder always says how the run ended.
RUN_JSON_ROOM = 64 * 1024


def write_json_reserved(path: str | Path, text: str, room: int = RUN_JSON_ROOM) -> None:
    """Write ``text`` (JSON) to ``path`` atomically; when that fails and ``path`` holds
    room reserved by an earlier call (its size), write it in place into that room.
    OutputError naming ``path`` when neither works."""
    path = Path(path)
    try:
        atomic_write_text(path, text, fsync=False)
        return
    except OSError as e:
        first = e
    data = text.encode()
    try:
        size = path.stat().st_size
        if len(data) > size:
            raise first
        with open(path, "r+b") as f:  # the blocks exist: overwriting them needs no free space
            f.write(data + b" " * (size - len(data)))
    except OSError as e:
        raise write_failed(e, path) from None


def reserve_json(path: str | Path, text: str, room: int = RUN_JSON_ROOM) -> None:
    """Write ``text`` padded with spaces to ``room`` bytes (see :func:`write_json_reserved`)."""
    data = text.encode()
    write_bytes(path, data + b" " * max(0, room - len(data)) + b"\n")


def write_ply(path: str | Path, points: np.ndarray) -> Path:
    """Write ``points`` (N, 3) as a binary little-endian PLY point cloud (float32 x, y, z),
    atomically; readable by any point-cloud tool (CloudCompare, MeshLab, Open3D)."""
    P = np.ascontiguousarray(np.asarray(points, dtype="<f4").reshape(-1, 3))
    head = ("ply\nformat binary_little_endian 1.0\ncomment dynastereo static map points\n"
            f"element vertex {len(P)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_open(path, "wb", fsync=False, mkdir=False) as fh:
            fh.write(head.encode("ascii"))
            fh.write(P.tobytes())
    except OSError as e:
        raise OutputError(f"cannot write the point cloud: {e.strerror}", path) from None
    return path
