"""Finding the sequences of a dataset root and their ground truth.

``discover(root)`` walks ``root`` (at most :data:`MAX_DEPTH` folders deep, hidden folders
skipped) and recognizes, with the readers' own detection functions (``dynastereo.io``):

* **KITTI odometry** sets: a folder with ``sequences/NN`` (each a KITTI sequence folder,
  :func:`~dynastereo.io.detect_format` ``"kitti"``); ground truth ``poses/NN.txt`` beside
  ``sequences/``.  Named ``NN`` when the set is ``root`` itself, else ``REL/NN``
  (``REL`` the set's folder relative to ``root``).  A folder of ``dynastereo synth``
  outputs is a folder of such sets (``ROOT/convoy/sequences/00`` -> ``convoy/00``).
* **KITTI raw** drives (:func:`~dynastereo.io.kitti_raw.is_kitti_raw_drive`); ground
  truth: a KITTI or TUM trajectory ``groundtruth.txt`` / ``poses.txt`` in the drive folder,
  else the drive's ``oxts/`` (GPS/IMU, read as camera-0 poses by
  :func:`~dynastereo.eval.trajectory.read_trajectory`).
* **EuRoC** MAV sequences (:func:`~dynastereo.io.euroc.euroc_mav_dir`); ground truth:
  ``groundtruth.txt`` / ``poses.txt`` (KITTI or TUM) in the folder, else EuRoC's own
  ``mav0/state_groundtruth_estimate0/data.csv`` (body poses), converted on demand to TUM
  poses of the rectified left camera (``T_W_B @ T_BS(cam0) @ R1^T``).

A root that is itself one sequence folder gives that one sequence.  Raw drives and EuRoC
sequences are named by their folder relative to ``root``.

``select(sequences, spec)`` keeps those a ``--sequences`` spec names: comma-separated items,
each a range ``a-b`` of numbers (matched against a name's last ``/`` part, e.g. ``00-10``),
a number, or a name / shell pattern (``convoy/*``, ``*drive_0001*``).
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError, SequenceError
from ..eval.trajectory import find_ground_truth
from ..io import detect_format
from ..io.calib import read_euroc_T_BS
from ..io.euroc import euroc_mav_dir
from ..io.outputs import atomic_open
from ..io.kitti_raw import is_kitti_raw_drive

MAX_DEPTH = 4
GT_NAMES = ("groundtruth.txt", "poses.txt")
EUROC_GT_CSV = Path("state_groundtruth_estimate0") / "data.csv"


@dataclass(frozen=True)
class BenchSequence:
    name: str
    path: Path
    format: str  # kitti | kitti_raw | euroc | folder
    ground_truth: Path | None  # a KITTI/TUM trajectory file, or EuRoC's data.csv (converted by the job)

    def to_dict(self) -> dict:
        return {"name": self.name, "path": str(self.path), "format": self.format,
                "ground_truth": str(self.ground_truth) if self.ground_truth else None}


def _first_file(folder: Path, names: tuple[str, ...]) -> Path | None:
    return next((folder / n for n in names if (folder / n).is_file()), None)


def _format_or_none(path: Path) -> str | None:
    try:
        return detect_format(path)
    except SequenceError:
        return None


def _kitti_set(folder: Path, prefix: str) -> list[BenchSequence]:
    out = []
    for s in sorted(p for p in (folder / "sequences").iterdir() if p.is_dir()):
        if _format_or_none(s) == "kitti":
            out.append(BenchSequence(f"{prefix}{s.name}", s, "kitti", find_ground_truth(s)))
    return out


def _single(path: Path, name: str, fmt: str) -> BenchSequence:
    gt = _first_file(path, GT_NAMES)
    if fmt in ("kitti", "kitti_raw") and gt is None:  # ROOT/sequences/NN: ROOT/poses/NN.txt; a drive's oxts/
        gt = find_ground_truth(path)
    if fmt == "euroc" and gt is None:
        mav = euroc_mav_dir(path)
        cand = mav / EUROC_GT_CSV if mav is not None else None
        gt = cand if cand is not None and cand.is_file() else None
    return BenchSequence(name, path, fmt, gt)


def discover(root: str | Path, exclude: tuple[Path, ...] = ()) -> list[BenchSequence]:
    """Every sequence under ``root`` (see module doc), sorted by name; InputError when none."""
    root = Path(root)
    if not root.is_dir():
        raise InputError("dataset root not found (expected a folder)", root)
    excluded = {p.resolve() for p in exclude}
    own = _format_or_none(root)
    if own is not None and not (root / "sequences").is_dir():
        return [_single(root, root.name, own)]
    found: list[BenchSequence] = []

    def walk(d: Path, depth: int) -> None:
        if d.resolve() in excluded:
            return
        rel = d.relative_to(root).as_posix()
        if (d / "sequences").is_dir():
            found.extend(_kitti_set(d, "" if rel == "." else f"{rel}/"))
            return
        if d != root and (is_kitti_raw_drive(d) or euroc_mav_dir(d) is not None):
            fmt = _format_or_none(d)
            if fmt in ("kitti_raw", "euroc"):
                found.append(_single(d, rel, fmt))
            return
        if depth >= MAX_DEPTH:
            return
        try:
            subs = sorted(p for p in d.iterdir() if p.is_dir() and not p.name.startswith("."))
        except OSError:
            return
        for p in subs:
            walk(p, depth + 1)

    walk(root, 0)
    if not found:
        raise InputError("no sequences found (looked for KITTI odometry sequences/NN, KITTI raw drives, "
                         "EuRoC mav0/ folders and `dynastereo synth` outputs)", root)
    return sorted(found, key=lambda s: s.name)


def _in_range(name: str, lo: str, hi: str) -> bool:
    last = name.rsplit("/", 1)[-1]
    return last.isdigit() and int(lo) <= int(last) <= int(hi)


def select(sequences: list[BenchSequence], spec: str | None) -> list[BenchSequence]:
    """The sequences named by ``spec`` (see module doc), in discovery order; all for None.
    InputError naming an item that matches nothing."""
    if spec is None or not str(spec).strip():
        return list(sequences)
    keep: set[str] = set()
    for item in (t.strip() for t in str(spec).split(",")):
        if not item:
            continue
        lo, sep, hi = item.partition("-")
        if sep and lo.isdigit() and hi.isdigit():
            hits = {s.name for s in sequences if _in_range(s.name, lo, hi)}
        elif item.isdigit():
            hits = {s.name for s in sequences if _in_range(s.name, item, item)}
        else:
            hits = {s.name for s in sequences if fnmatch.fnmatchcase(s.name, item)}
        if not hits:
            names = ", ".join(s.name for s in sequences)
            raise InputError(f"--sequences: {item!r} matches none of the sequences found ({names})")
        keep |= hits
    return [s for s in sequences if s.name in keep]


def euroc_ground_truth_tum(csv_path: Path, sequence, out_path: Path) -> Path:
    """Write EuRoC's body ground truth (``data.csv``: ns, p xyz, q wxyz, ...) as TUM poses of
    the sequence's rectified left camera: ``T_W_C = T_W_B @ T_BS(cam0) @ R1^T``."""
    from scipy.spatial.transform import Rotation

    try:
        rows = np.loadtxt(csv_path, delimiter=",", comments="#", ndmin=2)
    except ValueError as e:
        raise InputError(f"cannot read EuRoC ground truth: {e}", csv_path) from None
    if rows.shape[1] < 8:
        raise InputError(f"EuRoC ground truth needs >= 8 columns (ns, p, q), found {rows.shape[1]}", csv_path)
    T_WB = np.broadcast_to(np.eye(4), (len(rows), 4, 4)).copy()
    T_WB[:, :3, 3] = rows[:, 1:4]
    T_WB[:, :3, :3] = Rotation.from_quat(rows[:, [5, 6, 7, 4]]).as_matrix()  # wxyz -> xyzw
    T_BS = read_euroc_T_BS(euroc_mav_dir(Path(sequence.path)) / "cam0" / "sensor.yaml")
    T_CR = np.eye(4)
    rect = getattr(sequence, "rectifier", None)
    if rect is not None:
        T_CR[:3, :3] = np.asarray(rect.R1).T
    T_WC = T_WB @ T_BS @ T_CR
    q = Rotation.from_matrix(T_WC[:, :3, :3]).as_quat()
    table = np.column_stack([rows[:, 0] * 1e-9, T_WC[:, :3, 3], q])
    with atomic_open(out_path, "w", fsync=False) as f:
        np.savetxt(f, table, fmt="%.9f")
    return out_path
