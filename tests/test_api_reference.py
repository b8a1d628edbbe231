"""The API reference builds from the docstrings (``make docs``), and the docs stand alone.

* ``docs/build_api.py`` renders every module with pdoc into a temporary directory with
  every warning turned into an error and every docstring cross-reference checked; each
  public package gets a page that carries its own docstring.
* The reference checker is not vacuous: it rejects a stale module path and accepts the
  names a docstring may use (relative to its module, builtins, attributes set in methods).
* Every ``dfusion.``-qualified name and every repository file (and ``file::test``) quoted
  in the Markdown docs exists.
* No tracked text file points outside the repository (design notes, research-paper
  files by their storage name, absolute paths of one machine).
"""
from __future__ import annotations

import html
import importlib
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "docs"))
import build_api  # noqa: E402

PUBLIC_PACKAGES = [
    "dfusion.estimation", "dfusion.fusion", "dfusion.frontends", "dfusion.localization", "dfusion.models",
    "dfusion.maps", "dfusion.policies", "dfusion.scenario", "dfusion.sim", "dfusion.run", "dfusion.transport",
    "dfusion.datasets", "dfusion.geometry", "dfusion.reliability", "dfusion.metrics", "dfusion.wire",
    "dfusion.topology", "dfusion.bags", "dfusion.viz",
]


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """What ``make docs`` runs, in its own interpreter with ``-W error`` (any warning fails)."""
    out = tmp_path_factory.mktemp("api")
    r = subprocess.run([sys.executable, "-W", "error", str(ROOT / "docs" / "build_api.py"), str(out)],
                       capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "module pages" in r.stdout
    return out


@pytest.mark.parametrize("package", PUBLIC_PACKAGES)
def test_every_public_package_has_a_page_with_its_docstring(reference: Path, package: str) -> None:
    page = reference / (package.replace(".", "/") + ".html")
    assert page.is_file(), f"no page for {package}"
    text = html.unescape(re.sub(r"<[^>]+>", "", page.read_text(encoding="utf-8")))
    assert package in text
    first_line = importlib.import_module(package).__doc__.strip().splitlines()[0]
    words = re.findall(r"[A-Za-z]{4,}", first_line)[:4]   # markup aside, its first words are on the page
    assert words and all(w in text for w in words), (package, words)


def test_every_module_has_a_page_and_the_index_links_them(reference: Path) -> None:
    names = build_api.module_names()
    assert len(names) > 50
    index = (reference / "index.html").read_text(encoding="utf-8")
    packages = [n for n in names if hasattr(importlib.import_module(n), "__path__")]
    assert len(packages) >= 14
    for name in names:   # every package and module is on the index (it once listed 2 of the packages)
        assert (reference / (name.replace(".", "/") + ".html")).is_file(), name
        assert f'href="{name.replace(".", "/")}.html"' in index, name
    text = html.unescape(re.sub(r"<[^>]+>", "", index))
    for pkg in ("dfusion.bags", "dfusion.viz", "dfusion.fusion"):   # with the first words of its docstring
        words = re.findall(r"[A-Za-z]{4,}", importlib.import_module(pkg).__doc__.strip().splitlines()[0])[:3]
        assert all(w in text for w in words), (pkg, words)
    assert (reference / "search.js").stat().st_size > 10_000


def test_a_warning_fails_the_build(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Warnings are errors: one raised while a module is documented stops the build."""
    import pdoc.doc

    real = pdoc.doc.Module.from_name

    def warn_on_wire(name: str):
        if name == "dfusion.wire":
            warnings.warn("a docstring problem")
        return real(name)

    monkeypatch.setattr(pdoc.doc.Module, "from_name", staticmethod(warn_on_wire))
    with pytest.raises(UserWarning, match="a docstring problem"):
        build_api.build(tmp_path / "api")
    assert build_api.main([str(tmp_path / "api2")]) == 1


def test_reference_checker_rejects_stale_paths_and_accepts_valid_names() -> None:
    importlib.import_module("dfusion.localization.wsn_tracker")
    importlib.import_module("dfusion.transport.zenoh")
    assert not build_api.resolve("dfusion.pf.WSNTracker", "dfusion.localization")
    assert not build_api.resolve("~dfusion.fusion.policy.Policy", "dfusion.policies.switching")
    assert not build_api.resolve("close", "dfusion.transport.zenoh")   # a bare method name in a module docstring
    assert build_api.resolve("~dfusion.localization.WSNTracker", "dfusion.maps.grid")
    assert build_api.resolve("WSNTracker.information_contribution()", "dfusion.localization.wsn_tracker")
    assert build_api.resolve("ValueError", "dfusion.topology")
    assert build_api.resolve(".simulated", "dfusion.transport")
    from dfusion.maps.lattice import NodeLattice
    assert build_api.resolve("map", "dfusion.maps.lattice", NodeLattice)   # set by a method, not a class attribute
    bad = build_api.unresolved_references({"dfusion.transport.zenoh": _module_doc("dfusion.transport.zenoh")})
    assert bad == []


def _module_doc(name: str):
    import pdoc.doc

    return pdoc.doc.Module.from_name(name)


def _markdown_files() -> list[Path]:
    files = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    files += sorted(ROOT.glob("*/README.md")) + sorted((ROOT / "tests" / "data").glob("*/README.md"))
    return files


def test_names_quoted_in_the_markdown_docs_exist() -> None:
    files = _markdown_files()
    assert len(files) > 15
    assert build_api.unresolved_names_in_markdown(files) == []


def test_docs_index_lists_every_page_and_examples_readme_every_example() -> None:
    index = (ROOT / "docs" / "index.md").read_text(encoding="utf-8")
    pages = sorted(p.name for p in (ROOT / "docs").glob("*.md") if p.name != "index.md")
    assert len(pages) > 15
    assert [p for p in pages if f"]({p})" not in index] == []
    readme = (ROOT / "examples" / "README.md").read_text(encoding="utf-8")
    examples = sorted(p.name for p in (ROOT / "examples").glob("*.py"))
    assert len(examples) >= 8
    assert [e for e in examples if f"| `{e}` |" not in readme or f"examples/{e}" not in readme] == []


def test_repository_files_quoted_in_the_markdown_docs_exist() -> None:
    assert build_api.missing_paths_in_markdown(_markdown_files(), ROOT) == []


def test_checkers_catch_stale_names_and_paths_in_markdown(tmp_path: Path) -> None:
    md = tmp_path / "x.md"
    md.write_text("Use `dfusion.pf.WSNTracker` or `dfusion.localization.WSNTracker`.\n"
                  "Tested in `tests/test_wire.py::test_round_trip_is_bit_exact`, `tests/test_wire.py::test_gone`,\n"
                  "`nodes/gone.py` and `docs/background.md#2-fusion-on-a-tree`.\n", encoding="utf-8")
    assert build_api.unresolved_names_in_markdown([md]) == [f"{md}:1: dfusion.pf.WSNTracker"]
    assert build_api.missing_paths_in_markdown([md], ROOT) == [
        f"{md}:2: tests/test_wire.py::test_gone", f"{md}:3: nodes/gone.py"]


# Built by concatenation so that this file does not match itself.
_OUTSIDE = [
    re.compile("DES" + r"IGN\.md"),
    re.compile("ZENOH" + "_NOTES"),
    re.compile(r"\b\d{3}_[0-9a-f]{16}" + r"\.txt\b"),
    re.compile(r"\bseed" + r" 00[0-3]\b"),
    re.compile(r"(?<![\w.])/" + r"work/"),
    re.compile(r"\.\./" + r"shared/"),
    re.compile(r"(?<![\w.])/" + r"home/\w"),
]


def test_no_tracked_file_points_outside_the_repository() -> None:
    r = subprocess.run(["git", "ls-files"], capture_output=True, text=True, cwd=ROOT)
    if r.returncode == 0:
        files = r.stdout.splitlines()
    else:   # not a git checkout (an unpacked archive): every file but the generated ones
        skip = {".git", ".venv", "out", "__pycache__", ".hypothesis", ".pytest_cache"}
        files = [str(p.relative_to(ROOT)) for p in ROOT.rglob("*")
                 if not skip & set(p.relative_to(ROOT).parts) and ".egg-info" not in str(p)]
    assert len(files) > 100
    hits = []
    for rel in files:
        path = ROOT / rel
        if path.suffix not in {".py", ".md", ".toml", ".txt", ".cfg", ".yaml", ".yml", ""} or not path.is_file():
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for lineno, line in enumerate(text.splitlines(), 1):
            hits += [f"{rel}:{lineno}: {line.strip()[:100]}" for p in _OUTSIDE if p.search(line)]
    assert hits == [], "\n".join(hits)
