"""The packages' layers: the data flow io -> masking -> objects -> slam -> eval under one
runtime, read from the source (every import: module level, inside functions and under
``TYPE_CHECKING``).

* ``slam`` imports nothing above it (no masking, objects, viz, runtime, ros, eval, ...);
* no package imports another that imports it back (the package graph has no cycle).
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import dynastereo

SRC = Path(dynastereo.__file__).resolve().parent

#: What ``slam`` may import: itself and the packages and modules below it.
SLAM_MAY_IMPORT = {"slam", "<root>", "compiled", "config", "datatypes", "errors", "io", "timing", "dotted"}


def _module(path: Path, root: Path) -> tuple[str, bool]:
    rel = path.relative_to(root.parent).with_suffix("")
    is_pkg = rel.name == "__init__"
    return ".".join(rel.parts[:-1] if is_pkg else rel.parts), is_pkg


def _targets(node: ast.AST, module: str, is_pkg: bool) -> list[str]:
    """The dotted modules an import statement in ``module`` names (none for other nodes)."""
    if isinstance(node, ast.ImportFrom):
        if not node.level:
            return [node.module or ""]
        base = module.split(".") if is_pkg else module.split(".")[:-1]
        base = base[: len(base) - (node.level - 1)]
        return [".".join(base + ([node.module] if node.module else []))]
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    return []


def imports_of(source: str, module: str, is_pkg: bool) -> set[str]:
    """Every ``dynastereo`` module or name that ``source`` (the module ``module``) imports,
    anywhere in the file, as dotted names."""
    out = set()
    for node in ast.walk(ast.parse(source)):
        for target in _targets(node, module, is_pkg):
            out.add(target)
            if isinstance(node, ast.ImportFrom):
                out.update(f"{target}.{a.name}" for a in node.names)
    return {m for m in out if m.split(".")[0] == "dynastereo"}


def package_graph(root: Path = SRC) -> dict[str, set[str]]:
    """``{package: packages it imports}`` over the top-level packages and modules of
    ``root`` (``<root>``: the package's own ``__init__``)."""
    files = [p for p in root.rglob("*.py") if "ros_package" not in p.parts]
    modules = {_module(p, root)[0] for p in files}

    def top(name: str) -> str:
        parts = name.split(".")
        return parts[1] if len(parts) > 1 else "<root>"

    graph: dict[str, set[str]] = defaultdict(set)
    for p in files:
        name, is_pkg = _module(p, root)
        for target in imports_of(p.read_text(encoding="utf-8"), name, is_pkg):
            if target in modules and top(target) != top(name):
                graph[top(name)].add(top(target))
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The graph's cycles, one path per strongly connected component of two or more."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_slam_imports_nothing_above_it():
    above = sorted(package_graph()["slam"] - SLAM_MAY_IMPORT)
    assert not above, f"slam imports {above}"


def test_no_package_imports_back():
    assert cycles(package_graph()) == []


def test_the_checks_see_an_upward_import_and_a_cycle(tmp_path):
    """The scans themselves find what they look for (a test that cannot fail is a defect)."""
    pkg = tmp_path / "dynastereo"
    for rel, text in {
        "__init__.py": "",
        "slam/__init__.py": "",
        "slam/system.py": "def f():\n    from ..masking import x\n",
        "masking/__init__.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ..slam import system\n",
    }.items():
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        (pkg / rel).write_text(text)
    graph = package_graph(pkg)
    assert graph["slam"] == {"masking"}
    assert cycles(graph) == [["masking", "slam"]]


def _constructions(name: str) -> list[str]:
    """``file`` (relative to the package) of every call of ``name(...)`` in the source."""
    out = []
    for path in sorted(SRC.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call):
                f = node.func
                called = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None
                if called == name:
                    out.append(path.relative_to(SRC).as_posix())
    return out


def test_both_ros_nodes_run_the_one_runtime():
    """The ROS 1 and the ROS 2 node are adapters over ``ros/core.py``'s StereoNodeCore, whose
    FrameLoop and FrameProcessor are the runtime's: no other place builds a frame loop."""
    cores = _constructions("StereoNodeCore")
    assert "ros/ros1.py" in cores and "ros/ros2.py" in cores, cores
    for name in ("FrameLoop", "FrameProcessor"):
        where = set(_constructions(name))
        assert where and where <= {"runtime/job.py", "ros/core.py"}, (name, where)


def long_functions(root: Path = SRC, limit: int = 80) -> list[str]:
    """``file:function (lines)`` of every function outside a compiled kernel (``@jit``)
    longer than ``limit`` lines."""
    out = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if any("jit" in ast.unparse(d) for d in node.decorator_list):
                    continue
                n = node.end_lineno - node.lineno + 1
                if n > limit:
                    out.append(f"{path.relative_to(root).as_posix()}:{node.name} ({n})")
    return out


def test_no_function_is_over_80_lines():
    assert long_functions() == []


def test_the_length_check_sees_a_long_function(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(90))
    (tmp_path / "m.py").write_text(f"def long():\n{body}\n\n@jit\ndef kernel():\n{body}\n")
    assert long_functions(tmp_path) == ["m.py:long (91)"]


def unresolved_imports(root: Path = SRC) -> list[str]:
    """``file:line module`` of every ``dynastereo`` import (lazy ones inside functions too)
    whose module does not exist: a moved module leaves no import behind that fails only when
    its branch runs."""
    files = [p for p in root.rglob("*.py") if "ros_package" not in p.parts]
    modules = {_module(p, root)[0] for p in files}
    out = []
    for p in files:
        name, is_pkg = _module(p, root)
        for node in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
            for t in _targets(node, name, is_pkg):
                if t.split(".")[0] == root.name and t not in modules:
                    out.append(f"{p.relative_to(root).as_posix()}:{node.lineno} {t}")
    return out


def test_every_import_of_the_package_resolves():
    assert unresolved_imports() == []


def test_the_import_check_sees_a_moved_module(tmp_path):
    pkg = tmp_path / "dynastereo"
    for rel, text in {"__init__.py": "", "a/__init__.py": "", "a/b.py": "def f():\n    from ..a.gone import x\n",
                      "a/c.py": "from .b import f\n"}.items():
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        (pkg / rel).write_text(text)
    assert unresolved_imports(pkg) == ["a/b.py:2 dynastereo.a.gone"]
