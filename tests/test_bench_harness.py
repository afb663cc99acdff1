"""The benchmarks' harness (``benchmarks/_common.py``): its medians, the machine record,
the atomic JSON writer and the data discovery's one-line errors; and a scan of every
``benchmarks/bench_*.py`` for boilerplate of its own (``sys.path`` edits, sibling
imports, a machine record or data discovery not from the harness, JSON written without
it), checked on fake scripts that break each rule."""

from __future__ import annotations

import ast
import importlib.util
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
SCRIPTS = sorted(BENCH.glob("bench_*.py"))


@pytest.fixture(scope="module")
def common():
    spec = importlib.util.spec_from_file_location("bench_harness_common", BENCH / "_common.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# ----------------------------------------------------------------------------- statistics


def test_median_leaves_out_none_and_is_none_when_empty(common) -> None:
    assert common.median([3, 1, None, 2]) == 2.0
    assert common.median([4.0, 1.0]) == 2.5
    assert common.median([]) is None and common.median([None]) is None
    assert common.median((x for x in [1.23456, 2.0, 9.0]), digits=2) == 2.0
    assert common.median([1.0, 2.0, 4.0, 8.0], digits=1) == 3.0
    assert math.isnan(common.median([1.0, float("nan"), 3.0]))  # NaN kept unless asked
    assert common.median([1.0, float("nan"), 3.0, float("inf")], finite=True) == 2.0


def test_percentile_and_stats(common) -> None:
    v = list(range(1, 101))
    assert common.percentile(v, 90) == pytest.approx(90.1)
    assert common.percentile([None], 90) is None
    s = common.stats([1.0, 2.0, 3.0, 10.0, None])
    assert s == {"median": 2.5, "p90": 7.9, "mean": 4.0, "n": 4}
    assert common.stats([]) == {"median": None, "p90": None, "mean": None, "n": 0}


def test_timing_calls_every_item_every_repeat(common) -> None:
    seen = []
    t = common.times_ms(seen.append, 3, items=["a", "b"])
    assert seen == ["a", "b"] * 3 and len(t) == 6 and all(x >= 0 for x in t)
    calls = []
    m = common.median_ms(lambda: calls.append(1), 5)
    assert len(calls) == 5 and m >= 0


# ----------------------------------------------------------------------------- machine record


def test_machine_record_keys(common) -> None:
    rec = common.machine()
    assert list(rec) == list(common.MACHINE_KEYS)
    assert rec["cpus"] == os.cpu_count() and rec["python"].count(".") == 2
    assert rec["numpy"] and len(rec["load_avg"]) == 3
    assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d UTC", rec["date"])
    json.dumps(rec)  # a results file can hold it
    extra = common.machine(onnxruntime="1.0", cpus=99)
    assert extra["onnxruntime"] == "1.0" and extra["cpus"] == 99  # a benchmark's own fields, added or set


# ----------------------------------------------------------------------------- writing


def test_write_json_is_atomic(common, tmp_path, monkeypatch) -> None:
    out = tmp_path / "results" / "x.json"
    assert common.write_json(out, {"a": [1, 2], "b": None}) == out
    text = out.read_text()
    assert text.endswith("}\n") and json.loads(text) == {"a": [1, 2], "b": None}
    common.write_json(out, {"p": Path("/x")}, indent=None, default=str)
    assert json.loads(out.read_text()) == {"p": "/x"}

    def fail(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(common.os, "replace", fail)
    with pytest.raises(OSError):
        common.write_json(out, {"new": 1})
    assert json.loads(out.read_text()) == {"p": "/x"}  # the old file whole
    assert [p.name for p in out.parent.iterdir()] == ["x.json"]  # no temporary file left
    with pytest.raises(TypeError):
        common.write_json(out, {"bad": object()})
    assert json.loads(out.read_text()) == {"p": "/x"}


def test_results_path_and_markdown_table(common) -> None:
    assert common.results_path("peers") == BENCH / "results" / "peers.json"
    assert common.markdown_table(("a", "b"), [(1, "x|y"), ("2", 3.5)], align="lr").splitlines() == [
        "| a | b |", "|---|---:|", "| 1 | x\\|y |", "| 2 | 3.5 |"]


# ----------------------------------------------------------------------------- data discovery


def test_data_discovery_names_the_variable(common, tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(common, "DEFAULT_DATA", tmp_path / "nowhere" / "data")
    monkeypatch.setattr(common, "DEFAULT_MODELS", tmp_path / "nowhere" / "models")
    monkeypatch.setattr(sys, "argv", ["bench_fake.py"])
    monkeypatch.delenv("DYNASTEREO_DATA", raising=False)
    monkeypatch.delenv("DYNASTEREO_MODELS", raising=False)
    with pytest.raises(SystemExit) as e:
        common.data_dir()
    msg = str(e.value.code)
    assert msg.startswith("bench_fake.py: DYNASTEREO_DATA is not set") and "\n" not in msg
    with pytest.raises(SystemExit, match="DYNASTEREO_MODELS is not set"):
        common.models_dir()
    assert common.data_dir(required=False) is None and common.models_dir(required=False) is None
    with pytest.raises(SystemExit, match="DYNASTEREO_DATA is not set"):
        common.clip_dirs()

    monkeypatch.setenv("DYNASTEREO_DATA", str(tmp_path / "typo"))
    with pytest.raises(SystemExit, match=r"\$DYNASTEREO_DATA=.*typo is not a folder"):
        common.data_dir()
    assert common.data_dir(required=False) is None

    data = tmp_path / "data"
    (data / "kitti_odometry").mkdir(parents=True)
    monkeypatch.setenv("DYNASTEREO_DATA", str(data))
    assert common.data_dir() == data
    assert common.data_path("kitti_odometry") == data / "kitti_odometry"
    with pytest.raises(SystemExit, match=r"kitti_raw/2011_09_26/2011_09_26_drive_0001_sync not found under "
                                         r"\$DYNASTEREO_DATA="):
        common.data_path(common.CLIPS["raw0001"])
    assert common.clip_dirs()["06"] == data / "kitti_odometry" / "dataset" / "sequences" / "06"

    monkeypatch.delenv("DYNASTEREO_DATA")
    monkeypatch.setattr(common, "DEFAULT_DATA", data)  # ../shared/data beside the repository
    assert common.data_dir() == data


# ----------------------------------------------------------------------------- the scripts


MACHINE_FIELDS = {"cpus", "cpu_count", "platform", "python", "host", "load_avg", "loadavg_at_end"}


def problems(source: str) -> list[str]:
    """What in a benchmark script's ``source`` belongs to the harness instead."""
    out = []
    tree = ast.parse(source)
    if "sys.path" in source:
        out.append("touches sys.path")
    if re.search(r"^\s*(from|import)\s+bench_\w+", source, re.M):
        out.append("imports a sibling benchmark")
    if not any(isinstance(n, ast.ImportFrom) and n.module == "_common" for n in ast.walk(tree)):
        out.append("does not use the harness (_common)")
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            if "platform" in names:
                out.append("a machine record of its own (imports platform)")
        elif isinstance(node, ast.Constant) and node.value in ("DYNASTEREO_DATA", "DYNASTEREO_MODELS"):
            out.append(f"finds the data itself (reads {node.value})")
        elif isinstance(node, ast.Dict):
            keys = {k.value for k in node.keys if isinstance(k, ast.Constant) and isinstance(k.value, str)}
            for k, v in zip(node.keys, node.values):
                if isinstance(k, ast.Constant) and k.value == "machine" and not (
                        isinstance(v, ast.Call) and isinstance(v.func, ast.Name) and v.func.id == "machine"):
                    out.append("a machine record of its own (machine: not machine())")
            if len(keys & MACHINE_FIELDS) >= 2:
                out.append(f"a machine record of its own ({', '.join(sorted(keys & MACHINE_FIELDS))})")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            if node.func.attr == "dump" and isinstance(node.func.value, ast.Name) and node.func.value.id == "json":
                out.append("writes JSON without write_json")
            if node.func.attr == "write_text" and node.args and isinstance(node.args[0], ast.Call) \
                    and isinstance(node.args[0].func, ast.Attribute) and node.args[0].func.attr == "dumps":
                out.append("writes JSON without write_json")
    return out


CLEAN = '''"""A benchmark."""
import json
from _common import data_dir, machine, write_json
data = data_dir()
print(json.dumps({"a": 1}))
write_json("x.json", {"machine": machine(), "rows": []})
'''

BROKEN = {
    "touches sys.path": CLEAN + "import sys\nsys.path.insert(0, 'benchmarks')\n",
    "imports a sibling benchmark": CLEAN + "from bench_peers import clip_dirs\n",
    "does not use the harness": CLEAN.replace("from _common import data_dir, machine, write_json", "import _common"),
    "imports platform": CLEAN + "import platform\n",
    "reads DYNASTEREO_DATA": CLEAN + "import os\nd = os.environ.get('DYNASTEREO_DATA')\n",
    "reads DYNASTEREO_MODELS": CLEAN + "import os\nd = os.environ['DYNASTEREO_MODELS']\n",
    "machine: not machine()": CLEAN + "r = {'machine': 'x86_64'}\n",
    "cpus, platform": CLEAN + "import os\nr = {'cpus': os.cpu_count(), 'platform': 'linux', 'rows': []}\n",
    "writes JSON without write_json": CLEAN + "from pathlib import Path\nPath('o.json').write_text(json.dumps({}))\n",
}


def test_the_scan_passes_a_clean_script() -> None:
    assert problems(CLEAN) == []


@pytest.mark.parametrize("what", sorted(BROKEN))
def test_the_scan_finds_boilerplate_of_its_own(what: str) -> None:
    found = problems(BROKEN[what])
    assert any(what in p for p in found), found


def test_no_benchmark_has_boilerplate_of_its_own() -> None:
    assert len(SCRIPTS) >= 30
    bad = {p.name: found for p in SCRIPTS if (found := problems(p.read_text()))}
    assert not bad, f"boilerplate that belongs to benchmarks/_common.py: {bad}"


def test_harness_modules_need_no_sys_path_and_no_dynastereo() -> None:
    """A script imports the harness from its own folder as it is, and the harness pulls in
    no ``dynastereo`` (scripts also run against older trees through PYTHONPATH)."""
    helpers = sorted(BENCH.glob("_*.py"))
    assert {p.name for p in helpers} >= {"_common.py", "_shared_cpu.py", "_shared_peer.py", "_shared_runs.py"}
    assert not [p.name for p in helpers if "sys.path" in p.read_text()]
    code = ("import sys, _common, _shared_cpu, _shared_runs, _shared_peer; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'dynastereo'))")
    r = subprocess.run([sys.executable, "-c", code], cwd=BENCH, capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": ""})
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


def test_a_script_runs_from_anywhere(tmp_path) -> None:
    """``python benchmarks/bench_x.py`` from another folder: its siblings' helpers import."""
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    r = subprocess.run([sys.executable, str(BENCH / "bench_gt_time.py"), "--help"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stderr
    assert "--peer-python" in r.stdout and "--variants" in r.stdout
