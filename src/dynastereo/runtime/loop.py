"""The frame loop: every job's frames go through :class:`FrameLoop`.

For each frame the source gives: the masking stage (:meth:`FrameProcessor.mask`, on the
masking thread when pipelined), then on the loop's thread the tracking stage
(:meth:`FrameProcessor.track`), the sinks' files (all or none of the frame's:
:func:`~dynastereo.runtime.sinks.write_frame`), the observers, the progress callback.

Offline jobs run the loop on the main thread and stop at the first error
(``on_error=None``); the live node runs it on its own thread, counts a failed frame and
goes on (``on_error``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

from ..timing import StageTimer
from .pipelining import StageFailed, StagePipeline
from .processor import FrameItem, FrameProcessor, Masked, Processed
from .sinks import ObserverSink, Sink, write_frame

Progress = Callable[[int, int, dict], None]


@dataclass
class LoopState:
    n_done: int = 0  # frames whose outputs are all written
    stamps: list[float] = field(default_factory=list)  # of the frames done
    failed: int = 0  # frames that raised (a live loop goes on)
    t0: float = field(default_factory=time.perf_counter)

    @property
    def fps(self) -> float:
        wall = time.perf_counter() - self.t0
        return self.n_done / wall if wall > 0 else 0.0


class FrameLoop:
    """The frames of ``processor.source`` through ``processor`` into ``sinks`` and
    ``observers`` (module doc).  ``total``: frames expected (the progress bar's end)."""

    def __init__(self, processor: FrameProcessor, timer: StageTimer, *, sinks: list[Sink] | None = None,
                 observers: ObserverSink | None = None, pipelined: bool = True, timeout_s: float | None = None,
                 progress: Progress | None = None, total: int = 0,
                 on_error: Callable[[BaseException], None] | None = None,
                 after: Callable[[Processed], None] | None = None) -> None:
        self.processor, self.timer, self.sinks, self.observers = processor, timer, list(sinks or []), observers
        self.progress, self.total, self.on_error, self.after = progress, total, on_error, after
        self.state = LoopState()
        self.pipeline = StagePipeline(processor.source.take, processor.mask, pipelined=pipelined,
                                      timeout_s=timeout_s)

    def run(self) -> LoopState:
        """Until the source ends (offline: the first error propagates)."""
        while self.step():
            pass
        return self.state

    def step(self) -> bool:
        """One frame; False when the source ended."""
        st, source = self.state, self.processor.source
        try:
            got = self.pipeline.next(st.n_done)
        except StageFailed as f:
            source.done(f.item)
            self._failed(f.error)
            return True
        if got is None:
            return False
        item, masked = got
        try:
            self._frame(masked)
        except BaseException as e:  # noqa: BLE001 -- offline: re-raised; live: counted
            self._failed(e)
        finally:
            source.done(item)
        return True

    def process(self, item: FrameItem) -> Processed:
        """An item the source did not give (the live node's synchronous ``process``) through
        both stages on the calling thread; errors propagate."""
        return self._frame(self.processor.mask(item))

    def _failed(self, e: BaseException) -> None:
        if self.on_error is None or not isinstance(e, Exception):
            raise e
        self.state.failed += 1
        self.on_error(e)

    def _frame(self, m: Masked) -> Processed:
        st, timer = self.state, self.timer
        serial_ms = 0.0 if self.pipeline.pipelined else m.ms.get("total", 0.0)  # its masking was on this thread
        timer.start_frame(m.item.index if m.item.index is not None else st.n_done, serial_ms)
        p = self.processor.track(m, timer, st.n_done)
        rec = timer.end_frame(status=p.status) if self.processor.system is not None else timer.end_frame()
        p.ms = rec["ms"]
        try:
            write_frame(self.sinks, p, st.n_done)
        except BaseException:
            del timer.frames[st.n_done:]  # not done
            raise
        st.n_done += 1  # its outputs are written: what follows (an observer too) may fail, they stay
        st.stamps.append(p.stamp)
        if self.after is not None:
            self.after(p)
        if self.observers is not None:
            self.observers.notify(p)
        if self.progress is not None:
            self.progress(st.n_done, self.total, dict(rec, fps=st.fps))
        return p

    @property
    def fallbacks(self) -> list[dict[str, Any]]:
        return self.pipeline.fallbacks

    def close(self) -> bool:
        """Stop the masking thread (bounded); True if it ended."""
        return self.pipeline.close()
