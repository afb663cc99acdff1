"""CPU accounting the benchmarks share: the process tree's CPU over a run's frame loop
(:class:`LoopCpu`, an observer of ``run_sequence``) and the finished child processes' CPU
(:func:`children_cpu`).  Reads ``/proc`` and ``getrusage`` only: it imports nothing of
``dynastereo``, so a child process of an older source tree can use it too."""

from __future__ import annotations

import os
import resource
from pathlib import Path

TICK = os.sysconf("SC_CLK_TCK")


def children_cpu() -> float:
    """CPU seconds (user + system) of the finished child processes (``RUSAGE_CHILDREN``)."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def descendants(pid: int) -> list[int]:
    """The live descendants of process ``pid``."""
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            kids = [int(k) for k in (task / "children").read_text().split()]
        except OSError:
            continue
        for k in kids:
            out += [k, *descendants(k)]
    return out


def tree_cpu() -> float:
    """CPU seconds of this process and its live descendants (the BA workers)."""
    total = 0.0
    for pid in [os.getpid(), *descendants(os.getpid())]:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / TICK
    return total


class LoopCpu:
    """Observer: CPU of the process tree per frame over the frame loop only (first frame
    to last: start-up, model and vocabulary loading, and the final BA left out)."""

    def __init__(self) -> None:
        self.samples: list[float] = []

    def on_frame(self, event) -> None:
        self.samples.append(tree_cpu())

    @property
    def ms_per_frame(self) -> float:
        s = self.samples
        return (s[-1] - s[0]) / (len(s) - 1) * 1e3 if len(s) > 1 else float("nan")
