"""Compiled SLAM kernels (numba): one call per stage and frame over whole arrays.

Each module holds one concept; ``dynastereo.compiled.jit`` is the shared decorator
(``njit(nogil=True, cache=True)``, with an on-disk cache that also works from a
read-only install).
"""
