"""The live inputs' drop policy: a bounded queue whose newest item wins (the live ROS node's
input, a camera's frames)."""

from __future__ import annotations

import threading
from collections import deque
from typing import Any

from ..errors import ConfigError


class DropOldestQueue:
    """A bounded FIFO: ``put`` on a full queue evicts (and counts) the oldest item."""

    def __init__(self, maxsize: int = 1) -> None:
        if int(maxsize) < 1:
            raise ConfigError(f"queue_size must be >= 1, got {maxsize}")
        self.maxsize = int(maxsize)
        self._dq: deque = deque()
        self._cv = threading.Condition()
        self._closed = False
        self.dropped = 0
        self.high_water = 0

    def put(self, item: Any) -> int:
        """Append ``item``; returns how many old items were dropped for it (0 or more)."""
        with self._cv:
            if self._closed:
                return 0
            n = 0
            while len(self._dq) >= self.maxsize:
                self._dq.popleft()
                n += 1
            self._dq.append(item)
            self.dropped += n
            self.high_water = max(self.high_water, len(self._dq))
            self._cv.notify()
            return n

    def get(self, timeout: float | None = None) -> Any:
        """The oldest item; None when closed (or on timeout)."""
        with self._cv:
            self._cv.wait_for(lambda: self._dq or self._closed, timeout)
            return self._dq.popleft() if self._dq else None

    def resize(self, maxsize: int) -> int:
        """New capacity; surplus oldest items are dropped (returned count)."""
        if int(maxsize) < 1:
            raise ConfigError(f"queue_size must be >= 1, got {maxsize}")
        with self._cv:
            self.maxsize = int(maxsize)
            n = 0
            while len(self._dq) > self.maxsize:
                self._dq.popleft()
                n += 1
            self.dropped += n
            return n

    def close(self) -> int:
        """Stop: waiting getters return None; returns the number of items discarded."""
        with self._cv:
            self._closed = True
            n = len(self._dq)
            self._dq.clear()
            self._cv.notify_all()
            return n

    def __len__(self) -> int:
        with self._cv:
            return len(self._dq)
