"""The documentation: the generated pages are what their generators write now (a stale
page fails), the site builds with ``mkdocs build --strict`` (no broken link or anchor),
every configuration key has a meaning, README's links lead somewhere, results files are
named for what they measure, and no development history is left in the product."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

ROOT = Path(__file__).resolve().parents[1]
GEN = ROOT / "scripts" / "gen_docs.py"


def _gen():
    spec = importlib.util.spec_from_file_location("gen_docs", GEN)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def pages() -> dict:
    os.environ.setdefault("MPLBACKEND", "Agg")
    return _gen().generate()


def test_generated_pages_are_current(pages: dict) -> None:
    stale = _gen().stale(pages, ROOT / "docs")
    assert not stale, f"stale generated pages, run `python scripts/gen_docs.py`: {', '.join(stale)}"


def test_a_stale_page_is_found(pages: dict, tmp_path: Path) -> None:
    gen = _gen()
    docs = tmp_path / "docs"
    for p, content in pages.items():
        (docs / p).parent.mkdir(parents=True, exist_ok=True)
        (docs / p).write_bytes(content if isinstance(content, bytes) else content.encode())
    assert gen.stale(pages, docs) == []
    cfg = docs / "reference" / "configuration.md"
    cfg.write_text(cfg.read_text().replace("| `stereo.block_size` | int | `15` |", "| `stereo.block_size` | int | `17` |"))
    (docs / "benchmarks" / "gone.md").write_text("# a benchmark whose results file was removed\n")
    assert gen.stale(pages, docs) == ["benchmarks/gone.md", "reference/configuration.md"]


def test_every_configuration_key_has_a_type_default_and_meaning(pages: dict) -> None:
    from dynastereo.config import Config, to_dict

    def keys(d: dict, prefix: str = "") -> list[str]:
        return [k for name, v in d.items()
                for k in (keys(v, f"{prefix}{name}.") if isinstance(v, dict) else [f"{prefix}{name}"])]

    rows = {}
    for line in pages["reference/configuration.md"].splitlines():
        cells = [c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]]
        if len(cells) == 4 and re.fullmatch(r"`[\w.]+`", cells[0]):
            rows[cells[0].strip("`")] = cells[3]
    want = keys(to_dict(Config()))
    assert set(want) <= set(rows), f"keys missing from the reference: {sorted(set(want) - set(rows))}"
    blank = [k for k in want if not rows[k].strip()]
    assert not blank, f"configuration keys without a meaning (a comment beside the field in config.py): {blank}"


def test_every_command_and_option_is_in_the_cli_reference(pages: dict) -> None:
    sys.path.insert(0, str(ROOT / "tests"))
    from test_readme import help_options

    text = pages["reference/cli.md"]
    for path, opts in help_options().items():
        section = text.split(f"## `{path}`", 1)
        assert len(section) == 2, f"{path} has no section in the CLI reference"
        body = section[1].split("\n## ", 1)[0]
        assert all(f"`{o}`" in body for o in opts), f"{path}: options missing from the CLI reference"


def test_every_error_class_says_what_to_do(pages: dict) -> None:
    from dynastereo import errors

    text = pages["reference/errors.md"]
    classes = [c for c in vars(errors).values() if isinstance(c, type) and issubclass(c, (errors.DynastereoError, errors.Interrupted))]
    for c in classes:
        assert f"## {c.__name__}" in text
        assert "What to do:" in (c.__doc__ or ""), f"{c.__name__}'s docstring does not say what to do"
    assert "| `dynastereo.config` |" in text  # the messages themselves, with their module


def test_every_benchmark_has_a_page_with_a_table(pages: dict) -> None:
    results = sorted((ROOT / "benchmarks" / "results").glob("*.json"))
    assert results
    for r in results:
        page = pages.get(f"benchmarks/{r.stem}.md")
        assert page is not None, f"{r.name}: no benchmark script writes it (or names it in its docstring)"
        assert "## Reproduce" in page and f"benchmarks/results/{r.name}" in page
    # the page's table holds the results file's figures (whatever they are now)
    fps = json.loads((ROOT / "benchmarks" / "results" / "peers.json").read_text())["summary"]["06"]["default"]["fps"]
    assert f"| 06 / default | {fps:.1f} |" in pages["benchmarks/peers.md"] and "benchmarks/img/peers.png" in pages


def test_results_are_named_for_what_they_measure() -> None:
    names = [p.name for p in (ROOT / "benchmarks" / "results").iterdir()]
    history = [n for n in names if re.search(r"_s\d+|session|round|pass\d|_\d{8}", n)]
    assert not history, f"results named by when, not by what: {history}"


HISTORY = re.compile(r"\b[Ss]essions? \d+|\b[Rr]ound two\b|\b[Ii]ssues? #?\d+\b")


def test_no_development_history_in_the_product() -> None:
    files = [ROOT / "README.md", *sorted((ROOT / "src").rglob("*.py")), *sorted((ROOT / "docs").rglob("*.md")),
             *sorted((ROOT / "benchmarks").glob("*.py"))]
    found = [f"{p.relative_to(ROOT)}: {m.group(0)!r}" for p in files
             for m in [HISTORY.search(" ".join(p.read_text().replace("#", " ").split()))] if m]
    assert not found, "development history (session / round / issue numbers) in: " + ", ".join(found[:20])
    tests = [p for p in (ROOT / "tests").rglob("*") if p.is_file()]
    named = [p.name for p in tests if re.search(r"session|round|issue|_s\d+|\D\d\.py$", p.name)]
    named += [m.group(0) for p in tests if p.suffix == ".py"
              for m in re.finditer(r"def (test_\w*(?:session_?\d+|round_two|issue_?\d+|_s\d+)\w*)", p.read_text())]
    assert not named, f"test files or tests named by history: {named}"


def test_readme_links_lead_somewhere() -> None:
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 400
    missing = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"https?://", target):
            continue
        path, _, anchor = target.partition("#")
        if path and not (ROOT / path).exists():
            missing.append(target)
        elif anchor and path.endswith(".md"):
            heads = [re.sub(r"[^\w\s-]", "", h).strip().lower().replace(" ", "-")
                     for h in re.findall(r"^#+ (.*)$", (ROOT / path).read_text(), re.M)]
            if anchor not in heads:
                missing.append(target)
    assert not missing, f"README links that lead nowhere: {missing}"


def test_version() -> None:
    import dynastereo
    from dynastereo.cli.main import app

    r = CliRunner().invoke(app, ["--version"])
    assert r.exit_code == 0 and r.output.strip() == f"dynastereo {dynastereo.__version__}"
    assert re.fullmatch(r"\d+\.\d+\.\d+", dynastereo.__version__)
    assert f"## {dynastereo.__version__}" in (ROOT / "CHANGELOG.md").read_text()


def test_mkdocs_build_strict(tmp_path: Path) -> None:
    mkdocs = shutil.which("mkdocs", path=str(Path(sys.executable).parent)) or shutil.which("mkdocs")
    if mkdocs is None:
        if os.environ.get("DYNASTEREO_REQUIRE_DATA") == "1":
            pytest.fail("mkdocs is not installed (the extra `docs`: pip install -e '.[docs]')")
        pytest.skip("mkdocs is not installed (the extra `docs`: pip install -e '.[docs]')")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1", PYTHONPATH=str(ROOT / "src"))
    r = subprocess.run([mkdocs, "build", "--strict", "--site-dir", str(tmp_path / "site")], cwd=ROOT,
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, f"mkdocs build --strict failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    index = (tmp_path / "site" / "index.html").read_text()
    assert "dynastereo" in index and "fonts.googleapis.com" not in index  # builds and serves offline
    assert (tmp_path / "site" / "benchmarks" / "peers.html").is_file()
    assert "stereo.block_size" in (tmp_path / "site" / "reference" / "configuration.html").read_text()
