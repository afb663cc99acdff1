"""Trajectory files: KITTI and TUM, read (format auto-detected) and written.

Formats
-------
* **KITTI** odometry: one pose per row, 12 numbers = the first three rows of the 4x4
  camera-to-world matrix, row-major.  No timestamps; row ``i`` is frame ``i``.
* **TUM**: 8 numbers per row, ``t tx ty tz qx qy qz qw`` (camera-to-world, quaternion
  scalar last).

* **KITTI raw OXTS**: a KITTI raw drive folder or its ``oxts/`` folder is read as the
  drive's ground truth, converted from GPS/IMU to rectified camera-0 poses
  (:func:`dynastereo.io.kitti_raw.kitti_raw_ground_truth`), with the frames' timestamps.

:func:`find_ground_truth` is the one rule that finds a sequence's ground truth (used by
``run``, ``report``, ``bench``): the KITTI odometry layout's ``poses/NN.txt`` beside
``sequences/NN``, else a KITTI raw drive's ``oxts/``.

Blank lines and lines starting with ``#`` are ignored; numbers may be separated by
spaces, tabs or commas.  A malformed row raises :class:`InputError` naming the file
and the line.

Writing
-------
:func:`write_kitti` / :func:`write_tum` write a whole trajectory atomically (temporary
file + rename).  :class:`TrajectoryWriter` appends one row per frame to
``trajectory.kitti.txt``, ``trajectory.tum.txt`` and ``trajectory.frames.txt`` (the
sequence frame index of each row, so that frames lost by tracking or revisited frames
still match the ground truth) and flushes after every row, so a crash mid-sequence
keeps every row already written.

Why not ``evo.tools.file_interface`` (checked): its writers use
``np.savetxt``'s ``%.18e`` (ours: ``%.9e`` KITTI, ``%.9f`` TUM, so the files would change)
and write whole files only; its readers split on single spaces only (tabs, commas,
repeated or trailing spaces, blank and indented-comment lines are refused), give one
message without file or line, read KITTI 8x slower, and make TUM rotations differ from
scipy's in the last bits (1e-15).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ..io.outputs import RowFile, atomic_write_text

KITTI_COLUMNS = 12
TUM_COLUMNS = 8

KITTI_NAME = "trajectory.kitti.txt"
TUM_NAME = "trajectory.tum.txt"
FRAMES_NAME = "trajectory.frames.txt"


@dataclass
class Trajectory:
    """A sequence of camera-to-world poses.

    ``poses``: ``(N, 4, 4)`` float64 camera-to-world matrices; ``timestamps``: ``(N,)``
    seconds or ``None`` (KITTI files); ``name``: a label for tables and plots;
    ``path``: the file it was read from, if any (used in error messages).
    """

    poses: np.ndarray
    timestamps: np.ndarray | None = None
    name: str = "trajectory"
    path: Path | None = None

    def __post_init__(self) -> None:
        poses = np.asarray(self.poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise ValueError(f"poses must be (N, 4, 4), got {poses.shape}")
        self.poses = poses
        if self.timestamps is not None:
            ts = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
            if ts.shape[0] != poses.shape[0]:
                raise ValueError(f"{ts.shape[0]} timestamps for {poses.shape[0]} poses")
            self.timestamps = ts

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    @property
    def positions(self) -> np.ndarray:
        """``(N, 3)`` camera centres in world coordinates."""
        return self.poses[:, :3, 3]

    @property
    def path_length(self) -> float:
        """Length of the polyline through the positions, metres."""
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())

    def subset(self, rows: np.ndarray | list[int], name: str | None = None) -> "Trajectory":
        """The rows ``rows`` (indices; repeats allowed) as a new trajectory."""
        rows = np.asarray(rows, dtype=np.intp)
        ts = None if self.timestamps is None else self.timestamps[rows]
        return Trajectory(self.poses[rows], ts, name or self.name, self.path)


# --------------------------------------------------------------------------- reading


def _data_lines(text: str) -> tuple[list[int], list[list[str]]]:
    """Line numbers (1-based) and tokens of the non-blank, non-comment lines."""
    numbered = [
        (i, ln) for i, ln in enumerate(text.splitlines(), start=1) if ln.strip() and not ln.lstrip().startswith("#")
    ]
    return [i for i, _ in numbered], [ln.replace(",", " ").split() for _, ln in numbered]


def _parse_rows(path: Path, line_numbers: list[int], tokens: list[list[str]], ncol: int) -> np.ndarray:
    counts = np.fromiter(map(len, tokens), dtype=np.intp, count=len(tokens))
    bad = np.flatnonzero(counts != ncol)
    fmt = "KITTI" if ncol == KITTI_COLUMNS else "TUM"
    if bad.size:
        k = int(bad[0])
        raise InputError(
            f"line {line_numbers[k]}: expected {ncol} numbers ({fmt} format, as on line {line_numbers[0]}), "
            f"found {counts[k]}",
            path,
        )
    flat = list(itertools.chain.from_iterable(tokens))
    try:
        values = np.array(flat, dtype=np.float64)
    except ValueError:
        # error path only: find the offending token
        for ln, row in zip(line_numbers, tokens):
            for tok in row:
                try:
                    float(tok)
                except ValueError:
                    raise InputError(f"line {ln}: {tok!r} is not a number", path) from None
        raise  # pragma: no cover - unreachable: some token failed above
    rows = values.reshape(-1, ncol)
    nonfinite = np.flatnonzero(~np.isfinite(rows).all(axis=1))
    if nonfinite.size:
        raise InputError(f"line {line_numbers[int(nonfinite[0])]}: non-finite value (nan/inf)", path)
    return rows


def find_ground_truth(sequence: str | Path) -> Path | None:
    """The ground truth of the sequence folder ``sequence``, if it has one: the KITTI
    odometry layout's ``poses/NN.txt`` beside ``sequences/NN`` (also what ``dynastereo
    synth`` writes), else a KITTI raw drive's ``oxts/`` folder (read by
    :func:`read_trajectory`)."""
    from ..io.kitti_raw import oxts_dir

    seq = Path(sequence)
    gt = seq.parent.parent / "poses" / f"{seq.name}.txt"
    if seq.name and gt.is_file():
        return gt
    return oxts_dir(seq) if seq.is_dir() else None


def recorded_ground_truth(run: dict, run_json: Path) -> Path | None:
    """The ground truth of the run whose ``run.json`` (at ``run_json``) holds ``run``: the
    one it recorded (``ground_truth``), else the one beside its ``sequence`` -- which must
    be an absolute path: a relative one (an older run.json) was relative to a folder that
    is not known, and resolving it here could score against another sequence's poses
    (:class:`InputError` naming run.json)."""
    gt = run.get("ground_truth")
    if isinstance(gt, str) and gt:
        if not Path(gt).is_absolute():
            raise InputError(f"its ground_truth {gt!r} is a relative path; give the ground truth explicitly", run_json)
        return Path(gt)
    seq = run.get("sequence")
    if not isinstance(seq, str) or not seq:
        return None
    if not Path(seq).is_absolute():
        raise InputError(f"its sequence {seq!r} is a relative path (relative to where the run was started, not "
                         "known here); give the ground truth explicitly", run_json)
    return find_ground_truth(seq)


def read_trajectory(path: str | Path, name: str | None = None, at: str = "images") -> Trajectory:
    """Read a KITTI (12 numbers a row) or TUM (8 numbers a row) trajectory file, or the
    OXTS ground truth of a KITTI raw drive (its folder or ``oxts/`` folder; ``at``: the
    times its poses are for, :func:`~dynastereo.io.kitti_raw.kitti_raw_ground_truth`'s).

    The format is detected from the first data row; every row must have the same
    count.  Raises :class:`InputError` (file and line named) for a missing, empty or
    malformed file.
    """
    path = Path(path)
    if path.is_dir():
        from ..io.kitti_raw import kitti_raw_ground_truth, oxts_dir

        if oxts_dir(path) is None:
            raise InputError("a folder, but not a KITTI raw drive with oxts/ (expected a KITTI or TUM trajectory file)",
                             path)
        g = kitti_raw_ground_truth(path, at=at)
        return Trajectory(g.poses, g.timestamps, name or g.drive.name, path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise InputError("trajectory file not found", path) from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read trajectory file: {e}", path) from None
    line_numbers, tokens = _data_lines(text)
    if not tokens:
        raise InputError("no poses in trajectory file (empty or only comments)", path)
    ncol = len(tokens[0])
    if ncol not in (KITTI_COLUMNS, TUM_COLUMNS):
        raise InputError(
            f"line {line_numbers[0]}: expected {KITTI_COLUMNS} numbers (KITTI: 3x4 pose, row-major) or "
            f"{TUM_COLUMNS} (TUM: t tx ty tz qx qy qz qw), found {ncol}",
            path,
        )
    rows = _parse_rows(path, line_numbers, tokens, ncol)
    n = rows.shape[0]
    poses = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    if ncol == KITTI_COLUMNS:
        poses[:, :3, :] = rows.reshape(n, 3, 4)
        timestamps = None
    else:
        quat = rows[:, 4:8]
        norms = np.linalg.norm(quat, axis=1)
        zero = np.flatnonzero(norms < 1e-12)
        if zero.size:
            raise InputError(f"line {line_numbers[int(zero[0])]}: zero quaternion", path)
        poses[:, :3, :3] = Rotation.from_quat(quat / norms[:, None]).as_matrix()
        poses[:, :3, 3] = rows[:, 1:4]
        timestamps = rows[:, 0]
    # Rows are named after the file: "trajectory.kitti.txt" -> "trajectory", "06.txt" -> "06".
    return Trajectory(poses, timestamps, name or path.name.split(".")[0] or path.name, path)


def read_frame_indices(path: str | Path) -> np.ndarray:
    """Read a ``trajectory.frames.txt`` (one non-negative integer a line)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise InputError(f"cannot read frame-index file: {e}", path) from None
    line_numbers, tokens = _data_lines(text)
    out = np.empty(len(tokens), dtype=np.int64)
    for k, (ln, row) in enumerate(zip(line_numbers, tokens)):
        if len(row) != 1 or not row[0].isdigit():
            raise InputError(f"line {ln}: expected one non-negative integer frame index, found {' '.join(row)!r}", path)
        out[k] = int(row[0])
    return out


def frame_indices_beside(estimate_path: str | Path) -> Path | None:
    """The ``<stem>.frames.txt`` written beside ``<stem>.kitti.txt``/``<stem>.tum.txt``, if present."""
    p = Path(estimate_path)
    candidate = p.with_name(p.name.split(".")[0] + ".frames.txt")
    return candidate if candidate.is_file() and candidate != p else None


# --------------------------------------------------------------------------- writing


def _as_poses(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim == 2:
        poses = poses[None]
    if poses.ndim != 3 or poses.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"poses must be (N, 4, 4) or (N, 3, 4), got {poses.shape}")
    return poses


def kitti_rows(poses: np.ndarray) -> str:
    """KITTI text rows for ``(N, 4, 4)`` poses (one line each, newline-terminated)."""
    p = _as_poses(poses)[:, :3, :].reshape(-1, KITTI_COLUMNS)
    return "".join(" ".join(f"{v:.9e}" for v in row) + "\n" for row in p)


def tum_rows(poses: np.ndarray, timestamps: np.ndarray) -> str:
    """TUM text rows ``t tx ty tz qx qy qz qw`` for ``(N, 4, 4)`` poses."""
    p = _as_poses(poses)
    ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if ts.shape[0] != p.shape[0]:
        raise ValueError(f"{ts.shape[0]} timestamps for {p.shape[0]} poses")
    q = Rotation.from_matrix(p[:, :3, :3]).as_quat()  # x y z w (scalar last), as TUM
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)  # canonical sign: qw >= 0
    rows = np.column_stack([p[:, :3, 3], q])
    return "".join(f"{t:.9f} " + " ".join(f"{v:.9f}" for v in row) + "\n" for t, row in zip(ts, rows))




def write_kitti(path: str | Path, poses: np.ndarray) -> Path:
    """Write ``(N, 4, 4)`` camera-to-world poses as a KITTI file (atomically)."""
    return atomic_write_text(path, kitti_rows(poses))


def write_tum(path: str | Path, poses: np.ndarray, timestamps: np.ndarray) -> Path:
    """Write poses and timestamps (seconds) as a TUM file (atomically)."""
    return atomic_write_text(path, tum_rows(poses, timestamps))


def write_trajectory(path: str | Path, traj: Trajectory, fmt: str | None = None) -> Path:
    """Write ``traj`` as ``fmt`` ('kitti' / 'tum'; default: TUM if it has timestamps)."""
    fmt = fmt or ("tum" if traj.timestamps is not None else "kitti")
    if fmt == "kitti":
        return write_kitti(path, traj.poses)
    if fmt == "tum":
        ts = traj.timestamps if traj.timestamps is not None else np.arange(len(traj), dtype=np.float64)
        return write_tum(path, traj.poses, ts)
    raise ValueError(f"unknown trajectory format {fmt!r} (kitti, tum)")


class TrajectoryWriter:
    """Append one pose per frame to ``<stem>.kitti.txt``, ``<stem>.tum.txt`` and
    ``<stem>.frames.txt`` in ``out_dir``, flushing after every row.

    ``append(pose, frame_index=None, timestamp=None)``: ``frame_index`` defaults to the
    number of rows written so far; the TUM timestamp defaults to ``float(frame_index)``.
    With ``fsync=True`` every row is also forced to disk (survives a power cut, slower).
    The files are truncated when the writer opens them.  Use as a context manager.
    """

    def __init__(self, out_dir: str | Path, *, stem: str = "trajectory", fsync: bool = False):
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.kitti_path = self.out_dir / f"{stem}.kitti.txt"
        self.tum_path = self.out_dir / f"{stem}.tum.txt"
        self.frames_path = self.out_dir / f"{stem}.frames.txt"
        self.fsync = fsync
        self.n_written = 0
        self._files: list[RowFile] = []
        try:
            for p in (self.kitti_path, self.tum_path, self.frames_path):
                self._files.append(RowFile(p))
        except InputError:
            self.close()
            raise

    def append(self, pose: np.ndarray, frame_index: int | None = None, timestamp: float | None = None) -> None:
        """One row in each file; a write that fails (disk full, EIO) takes the row back out
        of the files already written, so they keep agreeing, and raises an OutputError
        naming the file."""
        if not self._files:
            raise ValueError("TrajectoryWriter is closed")
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape not in ((4, 4), (3, 4)) or not np.isfinite(pose).all():
            raise ValueError(f"pose must be a finite 4x4 or 3x4 matrix, got shape {pose.shape}")
        idx = self.n_written if frame_index is None else int(frame_index)
        ts = float(idx) if timestamp is None else float(timestamp)
        # Format every row first, then write: a formatting error leaves the files consistent.
        rows = (kitti_rows(pose), tum_rows(pose, [ts]), f"{idx}\n")
        try:
            for f, row in zip(self._files, rows):
                f.append(row, self.fsync)
        except InputError:
            self.truncate(self.n_written)
            raise
        self.n_written += 1

    def truncate(self, rows: int) -> None:
        """Keep the first ``rows`` rows of every file (another output of the frame failed)."""
        for f in self._files:
            f.truncate(rows)
        self.n_written = min(self.n_written, rows)

    def close(self) -> None:
        for f in self._files:
            f.close()
        self._files = []

    def __enter__(self) -> "TrajectoryWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
