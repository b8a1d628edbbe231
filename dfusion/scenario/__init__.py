"""Scenario files: loading and checking them, the sensor kinds they name, building their nodes.

* :func:`load_scenario` -- read and strictly validate a TOML scenario (``docs/scenarios.md``);
* :class:`Scenario`, :class:`NodeSpec`, :class:`TargetSpec` -- what it describes;
* :class:`SensorKind`, :class:`MotionKind`, :class:`Kinds`, :func:`builtin_kinds` -- the
  kinds a file may name, as explicit tables; plug-ins add more (:mod:`.plugins`);
* :func:`build_node`, :func:`build_nodes`, :func:`build_front_end`, :func:`build_front_ends`
  -- the one place that builds fusion nodes and front ends for ``simulate`` and ``run``.
"""
from dfusion.scenario.build import (
    build_front_end,
    build_front_ends,
    build_node,
    build_nodes,
)
from dfusion.scenario.kinds import builtin_kinds
from dfusion.scenario.loader import build_policy, load_scenario, node_policies
from dfusion.scenario.plugins import ENTRY_POINT_GROUP, load_plugin, load_plugins
from dfusion.scenario.spec import (
    COMMON_NODE_KEYS,
    Kinds,
    MotionKind,
    NodeSpec,
    Scenario,
    SensorKind,
    TargetSpec,
)

__all__ = [
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
