"""The architecture of docs/architecture.md, checked: layers, no import cycles, no private reach-ins.

* The layer contract lives in ``pyproject.toml`` (``[tool.importlinter]``) and is checked
  with import-linter: every package imports only the layers below it.
* No import cycle between modules (at import time), found with networkx on grimp's graph.
* No module uses another module's private names: no ``from x import _name`` across
  modules, and no ``obj._name`` where ``_name`` is not an attribute this module defines
  itself (its own classes' private state may be used inside the module).
"""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import grimp
import networkx as nx

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "dfusion"


def test_layer_contract_holds():
    lint = Path(sys.executable).with_name("lint-imports")
    proc = subprocess.run([str(lint), "--config", str(ROOT / "pyproject.toml")], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "0 broken" in proc.stdout


def test_no_import_cycles_between_modules():
    graph = grimp.build_graph("dfusion", cache_dir=None)
    g = nx.DiGraph()
    for module in graph.modules:
        for imported in graph.find_modules_directly_imported_by(module):
            # a package's __init__ re-exporting its own modules is not a cycle of the design
            if not imported.startswith(module + "."):
                g.add_edge(module, imported)
    cycles = list(nx.simple_cycles(g))
    assert not cycles, f"import cycles: {cycles[:5]}"


def _own_attributes(tree: ast.Module) -> set[str]:
    """Private names a module defines: its functions, classes, methods and ``self.x`` attributes."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            names.add(node.attr)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
    return {n for n in names if n.startswith("_")}


def private_reach_ins(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    own = _own_attributes(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("dfusion"):
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}: from {node.module} import {alias.name}")
        elif isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            base = node.value
            if isinstance(base, ast.Name) and base.id in ("self", "cls"):
                continue
            if node.attr not in own:
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}: .{node.attr}")
    return found


def test_no_private_state_of_another_module_is_used():
    found = [f for path in sorted(PACKAGE.rglob("*.py")) for f in private_reach_ins(path)]
    assert not found, "private names used across modules:\n" + "\n".join(found)


def test_the_private_access_check_finds_a_reach_in(tmp_path):
    bad = tmp_path / "dfusion_bad.py"
    bad.write_text("from dfusion.fusion.node import _Blocks\n\ndef f(mcl):\n    return mcl._resample()\n")
    global ROOT
    old, ROOT = ROOT, tmp_path
    try:
        assert len(private_reach_ins(bad)) == 2
    finally:
        ROOT = old
