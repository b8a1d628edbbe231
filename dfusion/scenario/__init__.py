"""Scenario files: loading and checking them, the sensor kinds they name, building their nodes.

* :func:`load_scenario` -- read and strictly validate a TOML scenario (``docs/scenarios.md``);
* :class:`Scenario`, :class:`NodeSpec`, :class:`TargetSpec` -- what it describes;
* :class:`SensorKind`, :class:`MotionKind`, :class:`Kinds`, :func:`builtin_kinds` -- the
  kinds a file may name, as explicit tables; plug-ins add more (:mod:`.plugins`);
* :func:`build_node`, :func:`build_nodes`, :func:`build_front_end`, :func:`build_front_ends`
  -- the one place that builds fusion nodes and front ends for ``simulate`` and ``run``.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from dfusion.lazy import lazy_exports

if TYPE_CHECKING:  # the names, for type checkers and IDEs; imported on first use at run time
    from dfusion.scenario.security import SecurityOptions
    from dfusion.scenario.build import build_front_end, build_front_ends, build_node, build_nodes
    from dfusion.scenario.kinds import builtin_kinds
    from dfusion.scenario.loader import build_policy, load_scenario, node_policies
    from dfusion.scenario.plugins import ENTRY_POINT_GROUP, load_plugin, load_plugins
    from dfusion.scenario.spec import COMMON_NODE_KEYS, Kinds, MotionKind, NodeSpec, Scenario, SensorKind, TargetSpec

__all__ = [
    "SecurityOptions",
    "load_scenario",
    "Scenario",
    "NodeSpec",
    "TargetSpec",
    "SensorKind",
    "MotionKind",
    "Kinds",
    "COMMON_NODE_KEYS",
    "builtin_kinds",
    "load_plugin",
    "load_plugins",
    "ENTRY_POINT_GROUP",
    "build_policy",
    "node_policies",
    "build_node",
    "build_nodes",
    "build_front_end",
    "build_front_ends",
]

_WHERE = {
    "SecurityOptions": ("dfusion.scenario.security", "SecurityOptions"),
    "build_front_end": ("dfusion.scenario.build", 'build_front_end'),
    "build_front_ends": ("dfusion.scenario.build", 'build_front_ends'),
    "build_node": ("dfusion.scenario.build", 'build_node'),
    "build_nodes": ("dfusion.scenario.build", 'build_nodes'),
    "builtin_kinds": ("dfusion.scenario.kinds", 'builtin_kinds'),
    "build_policy": ("dfusion.scenario.loader", 'build_policy'),
    "load_scenario": ("dfusion.scenario.loader", 'load_scenario'),
    "node_policies": ("dfusion.scenario.loader", 'node_policies'),
    "ENTRY_POINT_GROUP": ("dfusion.scenario.plugins", 'ENTRY_POINT_GROUP'),
    "load_plugin": ("dfusion.scenario.plugins", 'load_plugin'),
    "load_plugins": ("dfusion.scenario.plugins", 'load_plugins'),
    "COMMON_NODE_KEYS": ("dfusion.scenario.spec", 'COMMON_NODE_KEYS'),
    "Kinds": ("dfusion.scenario.spec", 'Kinds'),
    "MotionKind": ("dfusion.scenario.spec", 'MotionKind'),
    "NodeSpec": ("dfusion.scenario.spec", 'NodeSpec'),
    "Scenario": ("dfusion.scenario.spec", 'Scenario'),
    "SensorKind": ("dfusion.scenario.spec", 'SensorKind'),
    "TargetSpec": ("dfusion.scenario.spec", 'TargetSpec'),
}


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)
