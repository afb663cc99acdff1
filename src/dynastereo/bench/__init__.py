"""``dynastereo bench``: whole-dataset sweeps of (sequence, masker, repeat) jobs, on a
local process pool or on Ray, resumable, with the thesis' tables.

Modules: ``discover`` (sequences and ground truth under a root), ``jobs`` (one job, run
in-process in a worker: run + eval, its record), ``engines`` (local pool, Ray), ``runner``
(the driver: retries, results.json), ``tables`` (tables.md, plots).
"""

from .discover import BenchSequence, discover, select
from .jobs import BenchJob, execute
from .runner import MASKERS, BenchResult, run_bench
from .tables import render_tables

__all__ = ["BenchJob", "BenchResult", "BenchSequence", "MASKERS", "discover", "execute", "render_tables",
           "run_bench", "select"]
