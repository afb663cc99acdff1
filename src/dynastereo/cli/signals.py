"""SIGINT / SIGTERM for the CLI: stop at the next frame boundary, results written.

While :class:`StopOnSignal` is installed, the first SIGINT or SIGTERM only records the
signal: the job's progress callback calls :meth:`StopOnSignal.check` after every frame,
which raises :class:`~dynastereo.errors.Interrupted` there -- between two frames, so the
job's clean-up writes a consistent ``run.json`` / ``timing.json`` / trajectory (rows =
frames done).  A second signal raises at once (for a job stuck in one long step).
Outside a job (``deferred`` not set) the first signal raises at once.

Interrupts are idempotent: once :class:`Interrupted` has been raised (the job is
stopping and writing its files), further signals are only counted, never raised -- any
number of Ctrl-C during the shutdown still leaves run.json and timing.json written.  The
job's waits are bounded (the BA worker, the prefetch hand-over), so the shutdown ends; as a
last resort a signal :data:`FORCE_AFTER_S` or more into the shutdown raises again, to
break a wait that would not end (the job's clean-up catches it around the SLAM's
shutdown and still writes its files).
"""

from __future__ import annotations

import signal
import time
from contextlib import contextmanager
from typing import Any, Iterator

from ..errors import Interrupted

SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: Seconds into a shutdown after which a signal breaks the wait in progress (see above).
FORCE_AFTER_S = 10.0


class StopOnSignal:
    def __init__(self) -> None:
        self.received: int | None = None
        self.deferred = False
        self.stopping = False  # Interrupted was raised: the job is writing its files
        self._since = 0.0  # when it was raised (time.monotonic)
        self.count = 0  # signals received
        self._old: dict[int, Any] = {}

    def install(self) -> "StopOnSignal":
        for s in SIGNALS:
            self._old[s] = signal.signal(s, self._handle)
        return self

    def uninstall(self) -> None:
        """Restore the earlier handlers -- or, once a signal came, ignore further ones: the
        process is on its way out, and Python's default handler would print a traceback
        from the interpreter's own shutdown (joining threads) for the next Ctrl-C."""
        for s, h in self._old.items():
            signal.signal(s, signal.SIG_IGN if self.count else h)
        self._old.clear()

    def _handle(self, signum: int, _frame: Any) -> None:
        first = self.received is None
        self.count += 1
        if self.stopping:  # already stopping: the clean-up must run to its end ...
            if not self.deferred or time.monotonic() - self._since < FORCE_AFTER_S:
                return
            self._since = time.monotonic()  # ... unless it has been stuck for a while
            raise Interrupted(signum)
        self.received = signum
        if not (first and self.deferred):
            self._stop()
            raise Interrupted(signum)

    def _stop(self) -> None:
        self.stopping = True
        self._since = time.monotonic()

    def check(self) -> None:
        """Raise :class:`Interrupted` if a signal came (call between frames)."""
        if self.received is not None and not self.stopping:
            self._stop()
            raise Interrupted(self.received)

    @contextmanager
    def job(self) -> Iterator["StopOnSignal"]:
        """Signals wait for the next :meth:`check` inside the block; any signal still
        unchecked at the end of the block is raised there."""
        self.deferred = True
        self.stopping = False
        try:
            yield self
        finally:
            self.deferred = False
        self.check()


STOP = StopOnSignal()
