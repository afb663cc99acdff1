"""Every module of ``dynastereo`` imports on its own, as the first module of a fresh
interpreter: an import cycle (``a`` imports ``b`` which imports ``a``) fails only when one
of its modules is the first one imported, so each module gets its own process.

The processes are forked from a server that has already imported the heavy third-party
libraries (numpy, OpenCV, numba, ...; never a ``dynastereo`` module), so the ~130 imports
take seconds, not the minutes of as many cold interpreters.  Skipped, with the reason:
modules whose optional dependency (ROS 1's ``rospy``, ...) is not installed;
``ros/ros_package`` holds no Python modules (a catkin package's launch file and script).
"""

from __future__ import annotations

import importlib.util
import multiprocessing
import os
import re
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest

import dynastereo

PACKAGE = Path(dynastereo.__file__).resolve().parent
#: Third-party libraries the fork server imports once (none of them imports dynastereo).
PRELOAD = ["numpy", "yaml", "cv2", "scipy.optimize", "scipy.spatial", "scipy.ndimage", "scipy.sparse", "numba",
           "evo.core.metrics", "matplotlib.figure", "matplotlib.backends.backend_agg", "PIL.Image", "typer",
           "rich.console", "rich.table"]
#: Optional dependencies a module may need at import: missing, the module is skipped.
OPTIONAL = {"rospy", "rosbag", "genpy", "roslib", "std_msgs", "sensor_msgs", "cv_bridge"}


def all_modules() -> list[str]:
    """Dotted names of every module and package under ``src/dynastereo`` (files, not imports)."""
    names = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        if "ros_package" in rel.parts or "__pycache__" in rel.parts:
            continue
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
        names.append(".".join(parts))
    return names


def _first_import_code(module: str, path: Path | None) -> str:
    """What a worker runs (``exec``: nothing of this test module is imported there)."""
    top = module.split(".")[0]
    return (
        "import importlib, sys\n"
        + (f"sys.path.insert(0, {str(path)!r})\n" if path is not None else "")
        + f"loaded = [m for m in sys.modules if m.split('.')[0] == {top!r}]\n"
        + "assert not loaded, f'the worker had already imported {loaded}'\n"
        + f"importlib.import_module({module!r})\n"
    )


def first_import_failures(modules: list[str], path: Path | None = None) -> tuple[list[str], list[str]]:
    """Each module imported first in its own process (forked from a server with
    :data:`PRELOAD` imported; ``path``: put first on ``sys.path``): ``(failures with the
    worker's traceback, modules skipped for a missing optional dependency)``."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(PRELOAD)
    failures, skipped = [], []
    with ProcessPoolExecutor(max_workers=min(4, os.cpu_count() or 1), mp_context=ctx, max_tasks_per_child=1) as ex:
        futures = {m: ex.submit(exec, _first_import_code(m, path)) for m in modules}
        for m, fut in futures.items():
            err = fut.exception()
            if err is None:
                continue
            missing = _missing_optional(err)
            if missing is not None:
                skipped.append(f"{m} (needs {missing})")
                continue
            cause = getattr(err, "__cause__", None)  # the worker's traceback, as text
            failures.append(f"{m}: {type(err).__name__}: {err}\n{cause or ''}")
    return failures, skipped


def _missing_optional(err: BaseException) -> str | None:
    """The optional dependency whose absence ``err`` reports, if that is all it reports."""
    m = re.fullmatch(r"No module named '([\w.]+)'", str(err))
    if isinstance(err, ImportError) and m and m.group(1).split(".")[0] in OPTIONAL:
        if importlib.util.find_spec(m.group(1).split(".")[0]) is None:
            return m.group(1)
    return None


def test_the_module_walk_finds_the_package() -> None:
    mods = all_modules()
    assert len(mods) > 100 and "dynastereo" in mods and "dynastereo.slam.tracking" in mods
    assert "dynastereo.io.calib" in mods and "dynastereo.io.calib.kitti_txt" in mods  # packages and their modules
    assert not [m for m in mods if "ros_package" in m]


@pytest.mark.skipif(os.name != "posix", reason="the fork server needs POSIX")
def test_every_module_imports_alone_in_a_fresh_interpreter() -> None:
    failures, skipped = first_import_failures(all_modules())
    assert not failures, "modules that fail when imported first:\n" + "\n".join(failures)
    if skipped:
        print("skipped (optional dependency missing): " + ", ".join(skipped))


@pytest.mark.skipif(os.name != "posix", reason="the fork server needs POSIX")
def test_a_cycle_fails_when_one_of_its_modules_is_imported_first(tmp_path: Path) -> None:
    """The check itself: ``a`` and ``b`` import names from each other (each fails when
    imported first), ``c`` imports ``a`` (fails too), ``d`` is fine, ``e`` needs rospy."""
    pkg = tmp_path / "cyclepkg"
    pkg.mkdir()
    for name, text in {"__init__": "", "a": "from .b import B\nA = 1\n", "b": "from .a import A\nB = 2\n",
                       "c": "from . import a\n", "d": "import numpy\nD = 4\n", "e": "import rospy\n"}.items():
        (pkg / f"{name}.py").write_text(text)
    mods = [f"cyclepkg.{m}" for m in "abcde"]
    failures, skipped = first_import_failures(mods, tmp_path)
    assert [f.split(":")[0] for f in failures] == ["cyclepkg.a", "cyclepkg.b", "cyclepkg.c"], failures
    assert "partially initialized module" in failures[0] and "from .b import B" in failures[0]
    if importlib.util.find_spec("rospy") is None:
        assert skipped == ["cyclepkg.e (needs rospy)"]
