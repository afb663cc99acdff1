"""The runtime's one assembly: every job and every live node builds its stages with
:func:`dynastereo.runtime.assembly.assemble_stages`, so ``System(...)``, the masker factory,
the motion test and the objects' world tracker are constructed in exactly one place in
``src/`` (calls found in the parsed source, not in docstrings or comments)."""

from __future__ import annotations

import ast
from pathlib import Path

import dynastereo

SRC = Path(dynastereo.__file__).resolve().parent
ASSEMBLY = "runtime/assembly.py"


def _calls(name: str) -> list[str]:
    """``file:line`` of every call of ``name`` (``name(...)``, ``x.name(...)``) under src/dynastereo."""
    out = []
    for path in sorted(SRC.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call):
                f = node.func
                called = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None
                if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name):
                    called = (called, f"{f.value.id}.{f.attr}")
                if name in (called if isinstance(called, tuple) else (called,)):
                    out.append(f"{path.relative_to(SRC).as_posix()}:{node.lineno}")
    return out


def test_system_constructed_in_one_place():
    calls = _calls("System")
    assert len(calls) == 1 and calls[0].startswith(ASSEMBLY + ":"), calls


def test_stages_built_only_by_the_assembly():
    for name in ("build_masker", "build_motion"):
        calls = _calls(name)
        assert calls and all(c.startswith(ASSEMBLY + ":") for c in calls), (name, calls)
    world = _calls("WorldObjects.from_config") + _calls("WorldObjects")
    assert world and all(c.startswith(ASSEMBLY + ":") for c in world), world


def test_jobs_and_nodes_call_the_assembly():
    for rel in ("runtime/job.py", "ros/core.py"):
        assert any(c.startswith(rel + ":") for c in _calls("assemble_stages")), rel


def test_the_check_sees_a_construction(tmp_path):
    """The scan itself finds a call (a test that cannot fail is a defect)."""
    tree = ast.parse("from x import System\ns = System(cfg, calib)\n'''System(in a docstring)'''\n")
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", None) == "System"]
    assert len(calls) == 1
