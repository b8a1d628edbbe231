"""The benchmarks and examples import only names that exist and are public.

They are run by hand (benchmarks print tables, examples need full datasets), so nothing
else would notice a name that moved or became private. Every ``from dfusion... import
name`` and ``import dfusion...`` in them is resolved here, without running the scripts.
"""
from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted([*ROOT.glob("benchmarks/*.py"), *ROOT.glob("examples/*.py"), *ROOT.glob("nodes/*.py")])


def _imports(path: Path) -> list[tuple[str, str | None, int]]:
    """``(module, name or None, line)`` of every dfusion import in ``path``."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and node.module.split(".")[0] == "dfusion":
            out += [(node.module, a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.Import):
            out += [(a.name, None, node.lineno) for a in node.names if a.name.split(".")[0] == "dfusion"]
    return out


def test_there_are_scripts():
    assert len(SCRIPTS) >= 10, [p.name for p in SCRIPTS]


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_dfusion_name_a_script_imports_exists_and_is_public(path):
    problems = []
    for module, name, line in _imports(path):
        try:
            mod = importlib.import_module(module)
        except ImportError as exc:
            problems.append(f"line {line}: import {module}: {exc}")
            continue
        if name is None:
            continue
        if name.startswith("_"):
            problems.append(f"line {line}: {module}.{name} is private")
        elif not hasattr(mod, name):
            try:   # a submodule imported by name
                importlib.import_module(f"{module}.{name}")
            except ImportError:
                problems.append(f"line {line}: {module} has no {name}")
    assert not problems, f"{path.relative_to(ROOT)}: " + "; ".join(problems)
