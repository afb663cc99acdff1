"""Per-frame, per-stage wall-clock timing (milliseconds) and its summary.

``timer = StageTimer(); timer.start_frame(i); with timer.stage("detect"): ...;
timer.end_frame()``; ``timer.summary()`` gives median / p90 / mean per stage, and
``timer.to_json()`` the ``timing.json`` contract: ``{"frames": [...], "summary": {...},
"derived": {stage: [parts]}}``.
Derived stages (``mask`` = everything in masking but the detector) are declared with
``add_derived``.
"""

from __future__ import annotations

import json
import time
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .io.outputs import atomic_write_text


class StageTimer:
    def __init__(self) -> None:
        self.frames: list[dict[str, Any]] = []
        self._current: dict[str, float] | None = None
        self._frame_index: int | None = None
        self._frame_t0 = 0.0
        self._derived: dict[str, tuple[str, ...]] = {}

    def add_derived(self, name: str, parts: tuple[str, ...]) -> None:
        """Stage ``name`` = sum of ``parts`` (those present in a frame)."""
        self._derived[name] = tuple(parts)

    def start_frame(self, index: int, elapsed_ms: float = 0.0) -> None:
        """A new frame; ``elapsed_ms``: its time spent before (counted in its ``total``)."""
        self._current = {}
        self._frame_index = index
        self._frame_t0 = time.perf_counter() - elapsed_ms / 1000.0

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, (time.perf_counter() - t0) * 1000.0)

    def add(self, name: str, ms: float) -> None:
        if self._current is None:
            raise RuntimeError("StageTimer.add called outside a frame")
        self._current[name] = self._current.get(name, 0.0) + ms

    def end_frame(self, **extra: Any) -> dict[str, Any]:
        if self._current is None:
            raise RuntimeError("StageTimer.end_frame without start_frame")
        stages = dict(self._current)
        for name, parts in self._derived.items():
            present = [stages[p] for p in parts if p in stages]
            if present:
                stages[name] = float(sum(present))
        stages["total"] = (time.perf_counter() - self._frame_t0) * 1000.0
        rec = {"frame": self._frame_index, "ms": {k: round(v, 3) for k, v in stages.items()}}
        rec.update(extra)
        self.frames.append(rec)
        self._current = None
        return rec

    def stage_names(self) -> list[str]:
        names: list[str] = []
        for f in self.frames:
            for k in f["ms"]:
                if k not in names:
                    names.append(k)
        return names

    def summary(self) -> dict[str, dict[str, float]]:
        out: dict[str, dict[str, float]] = {}
        for name in self.stage_names():
            v = np.array([f["ms"][name] for f in self.frames if name in f["ms"]], dtype=np.float64)
            if v.size == 0:
                continue
            out[name] = {
                "median": round(float(np.median(v)), 3),
                "p90": round(float(np.percentile(v, 90)), 3),
                "mean": round(float(v.mean()), 3),
                "n": int(v.size),
            }
        return out

    def to_json(self, summary_extra: dict[str, Any] | None = None, **extra: Any) -> dict[str, Any]:
        summary: dict[str, Any] = self.summary()
        summary.update(summary_extra or {})
        d: dict[str, Any] = {"unit": "ms", "frames": self.frames, "summary": summary,
                             "derived": {k: list(v) for k, v in self._derived.items()}}
        d.update(extra)
        return d

    def write(self, path: str | Path, summary_extra: dict[str, Any] | None = None, **extra: Any) -> None:
        """Write ``timing.json`` atomically (``summary_extra`` goes into ``summary``)."""
        atomic_write_text(path, json.dumps(self.to_json(summary_extra, **extra), indent=1), fsync=False, mkdir=False)


def timed(timer: "StageTimer | None", name: str):
    """``timer.stage(name)``, or a no-op context when there is no timer."""
    return timer.stage(name) if timer is not None else nullcontext()
