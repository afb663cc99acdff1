"""Timestamps of image sequences.

``times.txt``: one timestamp (seconds) per line, strictly increasing.  A malformed line or
a stamp that does not increase is a :class:`SequenceError` naming the file and the line (an
out-of-order ``times.txt`` would otherwise be written into ``trajectory.tum.txt`` out of
order and break every evaluation tool).

:func:`sequence_timestamps` decides where a generic folder's stamps come from, in this
order: a ``times.txt``; else the image file names when they are Unix times
(:func:`stamps_from_names`: seconds, ms, µs or ns, told apart by magnitude); else frame
``i`` at ``i / rate`` (10 Hz unless a rate is given, with a warning that names the
assumption).  The result says which (:attr:`Timestamps.source`, recorded in ``run.json``).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError, SequenceError

log = logging.getLogger(__name__)

DEFAULT_RATE_HZ = 10.0  # KITTI's cameras run at about 10 Hz

# A file name (without suffix) that is a Unix time: digits, optionally a decimal fraction (seconds).
_NUMERIC_NAME = re.compile(r"^\d+(\.\d+)?$")
UNIX_DATE_MIN_S = 100_000_000  # 1e8 s (March 1973): smaller stamps are not dates (KITTI's times.txt starts at 0)
# Unit of an integer name by its magnitude (first stamp >= the bound): a Unix time of any date
# from 1973 to 5138 falls in exactly one band.
_UNIT_BANDS: tuple[tuple[float, str, int], ...] = (
    (UNIX_DATE_MIN_S * 1e9, "ns", 1), (UNIX_DATE_MIN_S * 1e6, "µs", 1_000),
    (UNIX_DATE_MIN_S * 1e3, "ms", 1_000_000), (UNIX_DATE_MIN_S, "s", 1_000_000_000),
)
# Median interval between frames (s) that file-name stamps must show to be taken as stamps.
_PLAUSIBLE_INTERVAL_S = (1e-4, 10.0)


@dataclass(frozen=True)
class Timestamps:
    """A sequence's stamps (float64 seconds), where they came from (``"times.txt"``,
    ``"file names (ns)"``, ``"rate 10 Hz (assumed)"``, ...), and the exact nanoseconds when
    the source has them (file names in integer units)."""

    seconds: np.ndarray
    source: str
    ns: np.ndarray | None = None


def read_times(path: str | Path) -> np.ndarray:
    """The stamps of a ``times.txt`` (float64 seconds); blank lines are skipped."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise SequenceError(f"cannot read timestamps: {e.strerror or e}", path) from None
    numbered = [(i, ln.strip()) for i, ln in enumerate(text.splitlines(), 1) if ln.strip()]
    try:
        t = np.array([float(s) for _, s in numbered], dtype=np.float64)
    except ValueError:
        lineno, s = next((i, s) for i, s in numbered if not _is_float(s))
        raise SequenceError(f"line {lineno}: {s[:40]!r} is not a timestamp (one number in seconds per line)",
                            path) from None
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise SequenceError(f"line {numbered[int(bad[0])][0]}: non-finite timestamp", path)
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        k = int(back[0]) + 1
        rel = "equals" if t[k] == t[k - 1] else "is before"
        raise SequenceError(f"line {numbered[k][0]}: timestamp {numbered[k][1]} {rel} line {numbered[k - 1][0]}'s "
                            f"{numbered[k - 1][1]} (timestamps must increase strictly)", path)
    return t


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


#: Frame rates (Hz) ``--rate`` takes: one frame in 1000 s up to 100 kHz.
RATE_BOUNDS = (1e-3, 1e5)


def check_rate(rate: float | None) -> float | None:
    """``rate`` (Hz) if it is a finite frame rate within :data:`RATE_BOUNDS` (or None);
    InputError naming ``--rate`` else."""
    if rate is None:
        return None
    if not (np.isfinite(rate) and RATE_BOUNDS[0] <= rate <= RATE_BOUNDS[1]):
        raise InputError(f"--rate must be a frame rate in Hz within {RATE_BOUNDS[0]:g}..{RATE_BOUNDS[1]:g}, "
                         f"got {rate:g}")
    return float(rate)


def stamps_from_names(paths: list[Path]) -> Timestamps | None:
    """The stamps the file names of ``paths`` (in pairing order) spell, or None when they are
    not Unix times.

    Names (without suffix) must all be numbers; one with a decimal point is seconds, integer
    names are seconds, ms, µs or ns by the magnitude of the first one (a date after 1973:
    >= 1e8 s, 1e11 ms, 1e14 µs, 1e17 ns); and the median interval must be 0.1 ms .. 10 s.
    Frame counters (``000000.png``) and relative times are therefore not stamps.  Names that
    are stamps but do not increase in name order (``999.png`` sorted after ``1000.png``) are a
    SequenceError naming the two files.
    """
    stems = [p.stem for p in paths]
    if len(stems) < 2 or not all(_NUMERIC_NAME.match(s) for s in stems):
        return None
    if any("." in s for s in stems):
        unit, ns = "s", None
        seconds = np.array([float(s) for s in stems], dtype=np.float64)
        if seconds[0] < UNIX_DATE_MIN_S:
            return None
    else:
        values = [int(s) for s in stems]
        band = next(((u, f) for lo, u, f in _UNIT_BANDS if values[0] >= lo), None)
        if band is None or max(values) * band[1] >= 2**63:  # beyond int64 nanoseconds (year 2262)
            return None
        unit, factor = band
        ns = np.array([v * factor for v in values], dtype=np.int64)
        seconds = (ns // 1_000_000_000).astype(np.float64) + (ns % 1_000_000_000).astype(np.float64) * 1e-9
    back = np.flatnonzero(np.diff(seconds) <= 0)
    if back.size:
        k = int(back[0]) + 1
        raise SequenceError(
            f"the image names are timestamps ({unit}) but do not increase in name order: {paths[k].name} comes "
            f"after {paths[k - 1].name} (give the names equal length, e.g. zero-padded, or add a times.txt)",
            paths[k].parent)
    interval = float(np.median(np.diff(seconds)))
    if not _PLAUSIBLE_INTERVAL_S[0] <= interval <= _PLAUSIBLE_INTERVAL_S[1]:
        return None
    return Timestamps(seconds, f"file names ({unit})", ns)


def sequence_timestamps(n: int, times_txt: Path | None, names: list[Path], rate: float | None = None,
                        where: Path | None = None, required: bool = False) -> Timestamps:
    """The stamps of a sequence of ``n`` frames: ``times_txt`` when it exists (or is
    ``required``: then a missing file is a SequenceError), else the
    file names ``names`` when they are Unix times (:func:`stamps_from_names`), else frame
    ``i`` at ``i / rate`` (``rate`` None: 10 Hz, with a warning naming the assumption).
    A ``rate`` given while stamps exist is ignored with a warning."""
    rate = check_rate(rate)
    stamps: Timestamps | None = None
    if times_txt is not None and (required or times_txt.is_file()):
        t = read_times(times_txt)
        if len(t) != n:
            raise SequenceError(f"{len(t)} timestamps for {n} image pairs", times_txt)
        stamps = Timestamps(t, times_txt.name)
    else:
        stamps = stamps_from_names(names)
    if stamps is not None:
        if rate is not None:
            log.warning("%s: --rate %g ignored: the timestamps come from %s", where or "", rate, stamps.source)
        return stamps
    if rate is not None:
        return Timestamps(np.arange(n, dtype=np.float64) / rate, f"rate {rate:g} Hz (given)")
    log.warning("%s: no times.txt and the image names are not timestamps: assuming %g Hz (frame i at i/%g s); "
                "pass --rate HZ or add a times.txt", where or "", DEFAULT_RATE_HZ, DEFAULT_RATE_HZ)
    return Timestamps(np.arange(n, dtype=np.float64) / DEFAULT_RATE_HZ, f"rate {DEFAULT_RATE_HZ:g} Hz (assumed)")
