"""Frame selection: which frame indices of a sequence to process.

``parse_frame_spec(spec, n)``:

* ``None`` (or ``"all"``) -> every frame ``0 .. n-1``;
* an ``int`` or a lone number ``"N"`` -> the first ``N`` frames ``0 .. N-1``;
* a comma-separated list of inclusive index ranges and single indices, e.g.
  ``"0-98,40-60,7"``, kept **in the given order with repeats** (so ``"0-98,40-60"``
  replays frames 40..60 after 98: a revisit).  ``"a-"`` means ``a`` to the last frame.
  A lone number always means "the first N"; to select the single frame 5 write ``"5-5"``.

Anything out of range or malformed raises :class:`~dynastereo.errors.InputError`
quoting the spec and the sequence length.
"""

from __future__ import annotations

import logging
import re
from typing import Any

from ..errors import InputError

log = logging.getLogger(__name__)

_RANGE = re.compile(r"^\s*(\d+)\s*(?:-\s*(\d*)\s*)?$")


def parse_frame_spec(spec: str | int | None, n: int) -> list[int]:
    """Frame indices selected by ``spec`` in a sequence of ``n`` frames (see module doc)."""
    if n < 0:
        raise ValueError(f"sequence length must be >= 0, got {n}")
    if spec is None:
        return list(range(n))
    if isinstance(spec, bool):  # bool is an int subclass: refuse it explicitly
        raise InputError(f"frame spec must be a number or a range list, got {spec!r}")
    if isinstance(spec, int):
        return _first(spec, n, repr(spec))
    if not isinstance(spec, str):
        raise InputError(f"frame spec must be a string, an int or None, got {type(spec).__name__}")
    text = spec.strip()
    if text.lower() in ("all", "*"):
        return list(range(n))
    if not text:
        raise InputError("empty frame spec (use e.g. '100' for the first 100 frames or '0-98,40-60')")
    if text.isdigit():
        return _first(int(text), n, repr(spec))

    out: list[int] = []
    for part in text.split(","):
        m = _RANGE.match(part)
        if not m:
            raise InputError(
                f"malformed frame spec {spec!r}: part {part.strip()!r} is not 'a', 'a-b' or 'a-' "
                "(non-negative frame indices, inclusive ranges)"
            )
        a = int(m.group(1))
        if m.group(2) is None:  # single index
            b = a
        elif m.group(2) == "":  # open range "a-"
            b = n - 1
        else:
            b = int(m.group(2))
        if a >= n or b >= n:
            raise InputError(
                f"frame spec {spec!r}: part {part.strip()!r} is out of range, the sequence has {n} frames (0-{n - 1})"
            )
        if b < a:
            raise InputError(f"frame spec {spec!r}: range {part.strip()!r} is reversed (start > end)")
        out.extend(range(a, b + 1))
    return out


def _first(count: int, n: int, shown: str) -> list[int]:
    if count <= 0:
        raise InputError(f"frame spec {shown}: the number of frames must be positive")
    if count > n:
        raise InputError(f"frame spec {shown}: asks for the first {count} frames, the sequence has only {n}")
    return list(range(count))


def select_frames(spec: str | int | None, sequence: Any) -> list[int]:
    """:func:`parse_frame_spec` over a sequence whose frame indices may have gaps (KITTI
    images keep their own numbers, ``available_frames``): a count ``N`` (or all) takes
    the first ``N`` images there are; ranges name frame numbers, the missing ones left
    out with a warning (an InputError when none is left).  A live source (``sequence.live``,
    a camera: no end) takes all (a lazy ``range``) or a count N, no ranges."""
    if getattr(sequence, "live", False):  # a camera: no end, frames in the order they come
        if spec is None or (isinstance(spec, str) and spec.strip().lower() in ("all", "*")):
            return range(len(sequence))  # type: ignore[return-value]  -- a lazy range, no list
        if (isinstance(spec, int) and not isinstance(spec, bool)) or (isinstance(spec, str) and spec.strip().isdigit()):
            return parse_frame_spec(spec, len(sequence))
        raise InputError(f"frame spec {spec!r}: a live source takes a count N (stop after N frames), not ranges")
    available = getattr(sequence, "available_frames", None)
    n = len(sequence)
    if available is None:
        return parse_frame_spec(spec, n)
    have = available()
    if len(have) == n:
        return parse_frame_spec(spec, n)
    text = spec.strip().lower() if isinstance(spec, str) else None
    if spec is None or (isinstance(spec, int) and not isinstance(spec, bool)) or (
            text is not None and (text.isdigit() or text in ("all", "*"))):
        return [have[k] for k in parse_frame_spec(spec, len(have))]
    wanted = parse_frame_spec(spec, n)
    present = set(have)
    keep = [i for i in wanted if i in present]
    dropped = sorted(set(wanted) - present)
    if not keep:
        raise InputError(f"frame spec {spec!r}: no image has any of these numbers (the numbering has gaps)")
    if dropped:
        log.warning("frame spec %r: %d frame number(s) have no image and are left out (%s)", spec, len(dropped),
                    ", ".join(map(str, dropped[:8])) + (", ..." if len(dropped) > 8 else ""))
    return keep
