"""The parts of a fusion node (docs/architecture.md, "Inside a fusion node"): one module each,
independent of each other and of the node, and no name defined by two of them (the node
inherits them all, so a name defined twice would silently take one of the two)."""
from __future__ import annotations

import ast
import importlib
from pathlib import Path

from dfusion.fusion import FusionNode

PARTS = {
    "dfusion.fusion.target": "TargetFusion",
    "dfusion.fusion.transaction": "ReceiveTransaction",
    "dfusion.fusion.steady": "SteadyPath",
    "dfusion.fusion.quarantine": "GuardedLinks",
    "dfusion.fusion.following": "TreeFollowing",
    "dfusion.fusion.outgoing": "MessageSending",
}


def part_classes() -> list[type]:
    return [getattr(importlib.import_module(m), c) for m, c in PARTS.items()]


def test_the_node_is_composed_of_every_part():
    mro = FusionNode.__mro__
    for cls in part_classes():
        assert cls in mro, cls.__name__
    assert set(FusionNode.__bases__) == set(part_classes())


def test_no_name_is_defined_by_two_parts_or_by_a_part_and_the_node():
    owners: dict[str, str] = {}
    for cls in [FusionNode, *part_classes()]:
        for name in vars(cls):
            if name.startswith("__") and name.endswith("__"):
                continue
            assert name not in owners, f"{name!r} is defined by {owners[name]} and {cls.__name__}"
            owners[name] = cls.__name__


def test_no_part_imports_the_node_or_another_part():
    modules = set(PARTS) | {"dfusion.fusion.node"}
    for module in PARTS:
        path = Path(importlib.import_module(module).__file__)
        imported = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                imported.add(node.module)
            elif isinstance(node, ast.Import):
                imported.update(a.name for a in node.names)
        assert not imported & (modules - {module}), f"{module} imports {sorted(imported & modules)}"
