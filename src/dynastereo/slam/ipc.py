"""Length-prefixed pickle messages over pipes (System <-> local-BA worker process)."""

from __future__ import annotations

import pickle
import struct
from typing import IO


def read_msg(stream: IO[bytes]) -> object | None:
    """Next message, or None at end of stream."""
    head = stream.read(8)
    if len(head) < 8:
        return None
    (n,) = struct.unpack("<Q", head)
    data = stream.read(n)
    if len(data) < n:
        return None
    return pickle.loads(data)


def write_msg(stream: IO[bytes], obj: object) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(struct.pack("<Q", len(data)))
    stream.write(data)
    stream.flush()
