r"""Plug-ins: sensor kinds, policies and motion models defined outside dfusion.

A plug-in is a Python module that defines any of three dictionaries::

    SENSOR_KINDS = {"range_beacon": SensorKind(...)}      # dfusion.scenario.SensorKind
    POLICY_KINDS = {"nearest": make_nearest_policy}       # name -> factory(params) -> Policy
    MOTION_KINDS = {"random_walk": MotionKind(...)}       # dfusion.scenario.MotionKind

Importing it has no other effect on dfusion: nothing is registered globally. A scenario
uses a plug-in in one of three ways, all honoured by ``dfusion simulate`` and
``dfusion run`` (whose node processes load the same plug-ins):

* the scenario file names it: ``plugins = ["my_package.my_sensor"]`` at the top level
  (a dotted module name, or a path to a ``.py`` file relative to the scenario file);
* the command line names it: ``dfusion simulate SCENARIO --plugin my_package.my_sensor``;
* an installed package declares an entry point in the group ``dfusion.plugins``
  (``[project.entry-points."dfusion.plugins"] my_sensor = "my_package.my_sensor"``),
  loaded for every scenario.

``docs/new-sensor-kind.md`` walks through a complete plug-in.
"""
from __future__ import annotations

import importlib
import importlib.util
import logging
import sys
from importlib.metadata import entry_points
from pathlib import Path
from types import ModuleType
from typing import Iterable

from dfusion.errors import ScenarioError
from dfusion.scenario.spec import Kinds, MotionKind, SensorKind

__all__ = ["ENTRY_POINT_GROUP", "load_plugin", "load_plugins", "plugin_kinds"]

log = logging.getLogger(__name__)

#: Entry-point group scanned for plug-ins of every scenario.
ENTRY_POINT_GROUP = "dfusion.plugins"


def _import(spec: str, base_dir: str | None) -> ModuleType:
    """Import a plug-in named by a dotted module name or a ``.py`` path."""
    if spec.endswith(".py"):
        path = Path(spec)
        if not path.is_absolute() and base_dir is not None:
            path = Path(base_dir) / path
        if not path.is_file():
            raise ScenarioError(f"plug-in file {path} not found")
        name = f"dfusion_plugin_{path.stem}_{abs(hash(str(path.resolve())))}"
        if name in sys.modules:
            return sys.modules[name]
        mod_spec = importlib.util.spec_from_file_location(name, path)
        if mod_spec is None or mod_spec.loader is None:
            raise ScenarioError(f"plug-in file {path} cannot be imported")
        module = importlib.util.module_from_spec(mod_spec)
        sys.modules[name] = module
        try:
            mod_spec.loader.exec_module(module)
        except Exception as exc:
            del sys.modules[name]
            raise ScenarioError(f"plug-in {path}: {type(exc).__name__}: {exc}") from exc
        return module
    try:
        return importlib.import_module(spec)
    except ImportError as exc:
        raise ScenarioError(f"plug-in {spec!r} cannot be imported: {exc}") from exc


def plugin_kinds(module: ModuleType, name: str) -> Kinds:
    """The kinds a plug-in module defines, checked."""
    sensors = getattr(module, "SENSOR_KINDS", {})
    policies = getattr(module, "POLICY_KINDS", {})
    motions = getattr(module, "MOTION_KINDS", {})
    if not (sensors or policies or motions):
        raise ScenarioError(f"plug-in {name!r} defines none of SENSOR_KINDS, POLICY_KINDS, MOTION_KINDS")
    for table, kind_type, what in ((sensors, SensorKind, "SENSOR_KINDS"), (motions, MotionKind, "MOTION_KINDS")):
        if not isinstance(table, dict):
            raise ScenarioError(f"plug-in {name!r}: {what} must be a dict")
        for key, value in table.items():
            if not isinstance(value, kind_type) or value.name != key:
                raise ScenarioError(f"plug-in {name!r}: {what}[{key!r}] must be a {kind_type.__name__} named {key!r}")
    if not isinstance(policies, dict) or not all(callable(f) for f in policies.values()):
        raise ScenarioError(f"plug-in {name!r}: POLICY_KINDS must map names to factories")
    return Kinds(dict(sensors), dict(policies), dict(motions), (name,))


def load_plugin(spec: str, base_dir: str | None = None) -> Kinds:
    """Import one plug-in (dotted module name or ``.py`` path) and return its kinds."""
    if not isinstance(spec, str) or not spec:
        raise ScenarioError(f"a plug-in must be a module name or a .py path, got {spec!r}")
    return plugin_kinds(_import(spec, base_dir), spec)


def load_plugins(base: Kinds, specs: Iterable[str], base_dir: str | None = None, *,
                 entry_point_plugins: bool = True) -> Kinds:
    """``base`` plus the kinds of every plug-in in ``specs`` and (by default) of the
    installed entry points of :data:`ENTRY_POINT_GROUP`."""
    kinds = base
    seen: set[str] = set()
    if entry_point_plugins:
        for ep in entry_points(group=ENTRY_POINT_GROUP):
            try:
                module = ep.load()
            except Exception as exc:  # noqa: BLE001  (a broken third-party package names itself)
                raise ScenarioError(f"entry point {ep.name!r} ({ep.value}) cannot be loaded: {exc}") from exc
            kinds = kinds.merged(plugin_kinds(module, ep.value), f"entry point {ep.name!r}")
            seen.add(ep.value)
    for spec in specs:
        if spec in seen:
            continue
        seen.add(spec)
        kinds = kinds.merged(load_plugin(spec, base_dir), f"plug-in {spec!r}")
        log.debug("loaded plug-in %s", spec)
    return kinds
