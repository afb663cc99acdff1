"""The benchmarks' harness: what every ``benchmarks/bench_*.py`` needs besides what it measures.

* **Data and models**: :func:`data_dir` / :func:`models_dir` (``$DYNASTEREO_DATA`` /
  ``$DYNASTEREO_MODELS``, else ``../shared/data`` / ``../shared/models`` beside the
  repository; missing, one line naming the variable and the script), :func:`data_path`
  (a file or folder under the data, one line naming it when it is not there) and
  :func:`clip_dirs` (the KITTI clips the benchmarks share).
* **The machine record**: :func:`machine` (host, cores, platform, Python and library
  versions, load average, date), kept under each results file's ``machine`` key;
  :func:`load` (the one-minute load average) and :func:`now` (the date as the files hold it).
* **Statistics**: :func:`median` / :func:`percentile` (``None`` left out; ``None`` when
  empty), :func:`stats` (median / p90 / mean / n), :func:`median_ms` (a call timed).
* **Writing**: :func:`results_path` (``benchmarks/results/NAME.json``, NAME = what it
  measures), :func:`write_json` (atomic: a temporary file beside it, then renamed) and
  :func:`markdown_table` / :func:`print_table`.

A script run as ``python benchmarks/bench_x.py`` has its own folder on the import path, so
``from _common import ...`` works as it is; nothing here imports ``dynastereo`` at import
time (the scripts also run against older source trees through ``PYTHONPATH``).
"""

from __future__ import annotations

import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
RESULTS = BENCH / "results"

ENV_DATA = "DYNASTEREO_DATA"
ENV_MODELS = "DYNASTEREO_MODELS"
#: where the data and models are when the variables are not set (``.ci/run``'s layout)
DEFAULT_DATA = ROOT.parent / "shared" / "data"
DEFAULT_MODELS = ROOT.parent / "shared" / "models"

#: the KITTI clips the benchmarks share, relative to the data folder
CLIPS = {
    "06": Path("kitti_odometry") / "dataset" / "sequences" / "06",
    "03": Path("kitti_odometry") / "dataset" / "sequences" / "03",
    "raw0001": Path("kitti_raw") / "2011_09_26" / "2011_09_26_drive_0001_sync",
}


class MissingData(SystemExit):
    """The data or models a benchmark needs are not there: exits with one line naming the
    script, the variable and the path."""

    def __init__(self, message: str) -> None:
        super().__init__(f"{_script()}: {message}")


def _script() -> str:
    return Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "benchmark"


# --------------------------------------------------------------------------------------
# data and models


def _env_dir(var: str, default: Path, what: str, required: bool) -> Path | None:
    value = os.environ.get(var)
    if value:
        path = Path(value).expanduser()
        if path.is_dir():
            return path
        if required:
            raise MissingData(f"${var}={value} is not a folder (it should hold {what})")
        return None
    if default.is_dir():
        return default
    if required:
        raise MissingData(f"{var} is not set and {default} is not there: set {var} to the folder of {what}")
    return None


def data_dir(required: bool = True) -> Path | None:
    """The shared data folder: ``$DYNASTEREO_DATA``, else ``../shared/data`` beside the
    repository.  Missing: :class:`MissingData` (``required``) or ``None``."""
    return _env_dir(ENV_DATA, DEFAULT_DATA, "the shared data (e.g. ../shared/data)", required)


def models_dir(required: bool = True) -> Path | None:
    """The detector models' folder: ``$DYNASTEREO_MODELS``, else ``../shared/models``
    beside the repository.  Missing: :class:`MissingData` (``required``) or ``None``."""
    return _env_dir(ENV_MODELS, DEFAULT_MODELS, "the detector models (e.g. ../shared/models)", required)


def data_path(*parts: str | Path, data: Path | None = None) -> Path:
    """``data_dir() / parts``; :class:`MissingData` naming it when it is not there."""
    root = data if data is not None else data_dir()
    path = root.joinpath(*parts)
    if not path.exists():
        raise MissingData(f"{Path(*parts)} not found under ${ENV_DATA}={root}")
    return path


def clip_dirs(data: Path | None = None) -> dict[str, Path]:
    """The shared KITTI clips (:data:`CLIPS`) under ``data`` (default :func:`data_dir`)."""
    root = data if data is not None else data_dir()
    return {name: root / rel for name, rel in CLIPS.items()}


# --------------------------------------------------------------------------------------
# the machine record


def now() -> str:
    """The date and time (UTC) as the results files hold it."""
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())


def load() -> float:
    """The one-minute load average (a shared machine's figures depend on it)."""
    return os.getloadavg()[0]


def _version(module: str, dist: str) -> str | None:
    mod = sys.modules.get(module)
    if mod is not None and getattr(mod, "__version__", None):
        return str(mod.__version__)
    from importlib import metadata

    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def _opencv_version() -> str | None:
    try:
        import cv2
    except ImportError:
        return None
    return str(cv2.__version__)


MACHINE_KEYS = ("host", "cpus", "platform", "python", "numpy", "opencv", "numba", "dynastereo", "load_avg", "date")


def machine(**extra: Any) -> dict[str, Any]:
    """The machine a benchmark ran on (:data:`MACHINE_KEYS`: host, CPU count, platform,
    Python, numpy / OpenCV / numba / dynastereo versions, the 1/5/15-minute load average
    now, the date), plus ``extra`` (a benchmark's own: a library's version, its thread
    count, the load before the runs...)."""
    record: dict[str, Any] = {
        "host": platform.node(),
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": _opencv_version(),
        "numba": _version("numba", "numba"),
        "dynastereo": _version("dynastereo", "dynastereo"),
        "load_avg": [round(x, 2) for x in os.getloadavg()],
        "date": now(),
    }
    record.update(extra)
    return record


# --------------------------------------------------------------------------------------
# statistics


def _values(values: Iterable[Any], finite: bool = False) -> np.ndarray:
    a = np.asarray([float(v) for v in values if v is not None], np.float64)
    return a[np.isfinite(a)] if finite else a


def median(values: Iterable[Any], digits: int | None = None, finite: bool = False) -> float | None:
    """The median of ``values`` (``None`` entries left out, and NaN / inf with ``finite``);
    ``None`` when none is left; rounded to ``digits`` when given."""
    a = _values(values, finite)
    if a.size == 0:
        return None
    m = float(np.median(a))
    return round(m, digits) if digits is not None else m


def percentile(values: Iterable[Any], q: float, digits: int | None = None) -> float | None:
    """The ``q``-th percentile of ``values`` (``None`` left out; ``None`` when empty)."""
    a = _values(values)
    if a.size == 0:
        return None
    p = float(np.percentile(a, q))
    return round(p, digits) if digits is not None else p


def stats(values: Iterable[Any], digits: int = 3) -> dict[str, float | int | None]:
    """``{"median", "p90", "mean", "n"}`` of ``values``, rounded to ``digits``."""
    a = _values(values)
    if a.size == 0:
        return {"median": None, "p90": None, "mean": None, "n": 0}
    return {"median": round(float(np.median(a)), digits), "p90": round(float(np.percentile(a, 90)), digits),
            "mean": round(float(a.mean()), digits), "n": int(a.size)}


def times_ms(fn: Callable[..., Any], repeats: int, items: Sequence[Any] | None = None) -> list[float]:
    """Wall milliseconds of ``fn()`` (or ``fn(item)`` for every item of ``items``),
    ``repeats`` times over."""
    out: list[float] = []
    for _ in range(repeats):
        for item in (items if items is not None else (None,)):
            t0 = time.perf_counter()
            fn() if items is None else fn(item)
            out.append((time.perf_counter() - t0) * 1e3)
    return out


def median_ms(fn: Callable[..., Any], repeats: int, items: Sequence[Any] | None = None) -> float:
    """The median of :func:`times_ms`."""
    return float(np.median(times_ms(fn, repeats, items)))


# --------------------------------------------------------------------------------------
# writing


def results_path(name: str) -> Path:
    """``benchmarks/results/NAME.json`` (NAME: what the file measures)."""
    return RESULTS / f"{name}.json"


def write_json(path: str | Path, obj: Any, *, indent: int | None = 1, default: Callable[[Any], Any] | None = None,
               **dumps: Any) -> Path:
    """Write ``obj`` as JSON (``json.dumps`` with ``indent``, ``default`` and ``dumps``) to
    ``path`` atomically (a temporary file beside it, flushed, then renamed over it: a reader
    never sees half a file); the folder is made."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(obj, indent=indent, default=default, **dumps) + "\n"
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def markdown_table(columns: Sequence[str], rows: Iterable[Sequence[Any]], align: str = "") -> str:
    """A Markdown table: ``columns`` as the header, one line per row (cells as given,
    ``|`` escaped); ``align`` one letter per column (``l``, ``r``, ``c``; default left)."""
    marks = {"l": "---", "r": "---:", "c": ":---:"}
    aligns = [marks.get(a, "---") for a in align.ljust(len(columns), "l")]
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join(aligns[: len(columns)]) + "|"]
    for row in rows:
        lines.append("| " + " | ".join(str(c).replace("|", "\\|") for c in row) + " |")
    return "\n".join(lines)


def print_table(columns: Sequence[str], rows: Iterable[Sequence[Any]], align: str = "") -> None:
    """Print :func:`markdown_table`."""
    print(markdown_table(columns, rows, align), flush=True)
