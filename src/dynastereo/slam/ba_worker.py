"""Local-BA worker process: ``python -m dynastereo.slam.ba_worker``.

Reads pickled ``LocalBAProblem`` messages from stdin (8-byte little-endian length +
payload), writes pickled ``LocalBAResult`` messages to stdout the same way, exits at
end of input (or when the parent stops reading).  It runs in its own process group and
ignores SIGINT and SIGTERM: Ctrl-C is the parent's to handle, and the parent shuts it down
(closing the pipe) -- the worker never dies first or prints a traceback.  Started with
``subprocess`` rather than ``multiprocessing`` so that no user ``__main__`` module is
re-imported (scripts need no ``if __name__ == '__main__'`` guard) and the parent's
threads are never forked.
"""

from __future__ import annotations

import os
import signal
import sys

from .ipc import read_msg, write_msg


def _trim_heap():
    """glibc's ``malloc_trim``: the memory a big BA (the whole map) freed goes back to the
    system instead of staying in this process's heap; a no-op elsewhere."""
    try:
        import ctypes

        trim = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return lambda: None
    return lambda: trim(0)


def main() -> int:
    # a signal is the parent's to handle: it stops cleanly and closes the pipe, ending this loop
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import gtsam  # noqa: F401 -- import before the first job

    from .optimizer import run_ba

    trim = _trim_heap()
    inp = sys.stdin.buffer
    out = sys.stdout.buffer
    # nothing else may write to the result stream
    sys.stdout = sys.stderr
    while True:
        msg = read_msg(inp)
        if msg is None:
            return 0
        if msg == "ping":
            res = "pong"
        else:
            try:
                res = run_ba(msg)  # type: ignore[arg-type]
            except Exception as e:  # noqa: BLE001 -- report, keep serving
                res = e
        try:
            write_msg(out, res)
        except OSError:  # the parent is gone (killed, or stopped without reading): end quietly
            return 0
        del msg, res
        trim()


if __name__ == "__main__":
    sys.exit(main())
