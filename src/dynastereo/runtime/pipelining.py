"""Which thread runs what: the masking stage of frame k+1 beside the tracking of frame k.

:class:`StagePipeline` is the one hand-over between the two stages, for every job:

* **serial** (``pipelined=False``): :meth:`StagePipeline.next` takes the next item from the
  source and masks it on the calling thread;
* **pipelined**: one daemon thread takes an item, masks it and leaves it in a one-item
  slot; it takes the next item only once the tracker has taken the previous one.  So the
  item masked is always the newest one waiting (a live source drops the older ones by its
  own policy), and at most one masked item waits.  OpenCV, onnxruntime and the numba
  kernels release the GIL, so the two stages overlap on two cores.

The hand-over wait is bounded (``timeout_s``): when the masking thread gives nothing within
it (a stuck detector), the item it is stuck on is masked on the calling thread, the
pipeline goes on serially from there and the fallback is recorded (``fallbacks``, run.json).
An exception from the masking stage reaches the caller of :meth:`next` with its item
(:class:`StageFailed`), so a live source can count it and go on, and a job can stop.

An offline run pipelined and serial gives the same results bit for bit
(``tests/test_runtime.py``): each stage keeps its own state and the order of items is the
source's.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

log = logging.getLogger(__name__)

#: The longest wait for the masking thread's next item (the first frame's includes loading
#: the detector and compiling kernels): past it, serial from there on.
HAND_OVER_TIMEOUT_S = 120.0
#: How long :meth:`StagePipeline.close` waits for an item being masked (then left: a daemon).
JOIN_S = 10.0

_END = object()


class StageFailed(Exception):
    """The masking stage raised on ``item``: the original exception is ``__cause__``."""

    def __init__(self, item: Any, error: BaseException) -> None:
        super().__init__(f"{type(error).__name__}: {error}")
        self.item, self.error = item, error


@dataclass
class _Slot:
    item: Any = None
    result: Any = None
    error: BaseException | None = None


def block_sigint() -> None:
    """Block SIGINT in the calling (non-main) thread: the main thread gets it, always."""
    import signal

    if hasattr(signal, "pthread_sigmask") and threading.current_thread() is not threading.main_thread():
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})


class StagePipeline:
    """``take() -> item | None`` (None: the source ended), ``stage(item) -> result``;
    :meth:`next` gives ``(item, result)`` in the source's order, or None at the end (module doc)."""

    def __init__(self, take: Callable[[], Any], stage: Callable[[Any], Any], *, pipelined: bool,
                 timeout_s: float | None = None, idle_check: Callable[[], bool] | None = None) -> None:
        self._take, self._stage = take, stage
        self.timeout_s = HAND_OVER_TIMEOUT_S if timeout_s is None else float(timeout_s)
        self.fallbacks: list[dict[str, Any]] = []
        self._cv = threading.Condition()
        self._slot: _Slot | object | None = None  # a masked item, _END, or None (empty)
        self._current: Any = None  # the item the thread is masking
        self._abandoned = False
        self._thread: threading.Thread | None = None
        if pipelined:  # started by the first next()
            self._thread = threading.Thread(target=self._loop, name="dynastereo-mask", daemon=True)

    @property
    def pipelined(self) -> bool:
        return self._thread is not None and not self._abandoned

    def _run_stage(self, item: Any) -> _Slot:
        try:
            return _Slot(item, self._stage(item))
        except BaseException as e:  # noqa: BLE001 -- handed over with its item
            return _Slot(item, error=e)

    def _loop(self) -> None:
        block_sigint()
        while True:
            with self._cv:
                while self._slot is not None and not self._abandoned:
                    self._cv.wait()
                if self._abandoned:
                    return
            item = self._take()
            with self._cv:
                self._current = item
                self._cv.notify_all()  # the wait for it is bounded from now on
            slot = _END if item is None else self._run_stage(item)
            with self._cv:
                if self._abandoned:  # the caller went serial meanwhile: this result is not wanted
                    return
                self._slot, self._current = slot, None
                self._cv.notify_all()
            if slot is _END:
                return

    def next(self, position: int = 0) -> tuple[Any, Any] | None:
        """The next ``(item, result)``; None when the source ended.  Raises :class:`StageFailed`
        when the stage raised on an item (the pipeline stays usable).  ``position`` only
        names the item in a recorded fallback."""
        if not self.pipelined:
            item = self._take()
            return None if item is None else self._unwrap(self._run_stage(item))
        if not self._thread.is_alive() and self._thread.ident is None:
            self._thread.start()
        with self._cv:
            if not self._wait_for_slot():
                stuck, self._abandoned = self._current, True
                self._cv.notify_all()
                return self._go_serial(stuck, position)
            slot, self._slot = self._slot, None
            self._cv.notify_all()
        return None if slot is _END else self._unwrap(slot)

    def _wait_for_slot(self) -> bool:
        """Wait (holding the lock) for the slot; False when the thread spent over ``timeout_s``
        on one item.  A thread waiting on the source (no input yet) is waited for without end."""
        deadline = None
        while self._slot is None:
            if self._current is None:  # waiting on the source: a live input may be idle for long
                deadline = None
                self._cv.wait()
                continue
            now = time.monotonic()
            deadline = deadline if deadline is not None else now + self.timeout_s
            if now >= deadline:
                return False
            self._cv.wait(deadline - now)
        return True

    def _go_serial(self, stuck: Any, position: int) -> tuple[Any, Any] | None:
        frame = getattr(stuck, "index", None)
        self.fallbacks.append({"frame": int(frame if frame is not None else position), "position": int(position),
                               "what": "prefetch", "action": "masked inline from here on",
                               "reason": f"no masks from the prefetch thread within {self.timeout_s:g} s"})
        log.warning("frame %s: no masks from the prefetch thread within %g s; masking inline from here on",
                    frame if frame is not None else position, self.timeout_s)
        if stuck is None:  # the thread was waiting on the source itself
            stuck = self._take()
            if stuck is None:
                return None
        return self._unwrap(self._run_stage(stuck))

    @staticmethod
    def _unwrap(slot: _Slot) -> tuple[Any, Any]:
        if slot.error is not None:
            raise StageFailed(slot.item, slot.error) from slot.error
        return slot.item, slot.result

    def close(self, join_s: float = JOIN_S) -> bool:
        """Stop the masking thread (after the item it is masking; bounded): True if it ended.
        The source must already return None (or be closed) for a thread waiting on it."""
        with self._cv:
            self._abandoned = True
            self._cv.notify_all()
        if self._thread is None or self._thread.ident is None:
            return True
        self._thread.join(join_s)
        return not self._thread.is_alive()
