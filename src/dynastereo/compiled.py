"""The one numba decorator of the compiled kernels (the SLAM's, ``slam/kernels``, and the
masking's): ``jit`` = ``njit(nogil=True, cache=True)``.

Compiled kernels are cached on disk beside their source (``__pycache__``).  numba itself
falls back to the user cache (``~/.cache/numba``) when the package directory is read-only;
where neither is writable (a read-only install under a read-only home) the cache goes to
``$TMPDIR/dynastereo-numba-<uid>`` so that importing never fails and later runs still load
compiled code.  ``NUMBA_CACHE_DIR`` set by the user always wins.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numba
from numba import types
from numba.core import config as _config
from numba.extending import intrinsic


def _writable(d: Path) -> bool:
    """Whether numba could write its cache in ``d`` (created if missing)."""
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(d, os.W_OK | os.X_OK)


def cache_dir_fallback() -> str | None:
    """Point numba at a temporary cache directory when neither the package's
    ``__pycache__`` nor the user cache is writable; returns the directory used (None:
    numba's own choice)."""
    if os.environ.get("NUMBA_CACHE_DIR") or _config.CACHE_DIR:
        return _config.CACHE_DIR or None
    if _writable(Path(__file__).resolve().parent / "__pycache__"):
        return None
    from numba.misc.appdirs import AppDirs

    if _writable(Path(AppDirs("numba", appauthor=False).user_cache_dir)):
        return None
    d = Path(tempfile.gettempdir()) / f"dynastereo-numba-{os.getuid() if hasattr(os, 'getuid') else 'user'}"
    d.mkdir(parents=True, exist_ok=True)
    _config.CACHE_DIR = str(d)
    return str(d)


CACHE_DIR = cache_dir_fallback()


def jit(fn=None, **kw):
    """``numba.njit(nogil=True, cache=True)`` (other options may be added by keyword).

    No ``fastmath``: the kernels must give the same floats on every run and as close as
    possible to the numpy code they replace."""
    opts = dict(nogil=True, cache=True)
    opts.update(kw)
    if fn is None:
        return lambda f: numba.njit(**opts)(f)
    return numba.njit(**opts)(fn)


if _config.DISABLE_JIT:  # NUMBA_DISABLE_JIT=1 (debugging): the kernels run as plain Python

    def popcount64(x):
        return int(x).bit_count()

    def cttz64(x):
        x = int(x)
        return (x & -x).bit_length() - 1 if x else 64

else:

    def _u64_op(emit, doc: str):
        """An intrinsic ``uint64 -> uint64`` whose body is ``emit(builder, value)`` (one LLVM
        instruction), for any integer argument."""

        def typer(typingctx, x):
            if not isinstance(x, types.Integer):
                return None
            sig = types.uint64(types.uint64)

            def codegen(context, builder, signature, args):
                return emit(context, builder, context.cast(builder, args[0], signature.args[0], types.uint64))

            return sig, codegen

        typer.__doc__ = doc
        return intrinsic(typer)

    popcount64 = _u64_op(lambda ctx, b, v: b.ctpop(v),
                         "Number of set bits of a uint64 (LLVM ``ctpop``: one POPCNT instruction where the CPU has it).")
    cttz64 = _u64_op(lambda ctx, b, v: b.cttz(v, ctx.get_constant(types.boolean, False)),
                     "Trailing zero bits of a uint64 (LLVM ``cttz``: one TZCNT where the CPU has it; 64 for 0).")
