"""Scenario files: the world, the sensors and the network, in TOML, checked strictly.

A scenario is also a valid topology file (``[[nodes]]`` and ``[[links]]``), so the tree
check of :mod:`dfusion.topology` applies to it. Every key is documented in
``docs/scenarios.md``. Anything invalid raises :class:`~dfusion.errors.ScenarioError`
with one line that names the file, the table and the key, and says what is expected:
unknown keys in any table (with the closest known key), a key that belongs to another
table (``window`` written after ``[target]`` lands in ``[target]``), ``[[link]]`` for
``[[links]]``, a link naming a node that has no ``[[nodes]]`` table, a file that is not
TOML, a scenario with fewer than two nodes. Degenerate but valid settings (a window
shorter than the tree needs, no node with a sensor) are logged as warnings and kept in
:attr:`Scenario.warnings`.

Sensor kinds, policies and motion models come from :func:`dfusion.scenario.builtin_kinds`
plus plug-ins (:mod:`dfusion.scenario.plugins`).
"""
from __future__ import annotations

import logging
import math
import tomllib
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from dfusion.errors import DfusionError, ScenarioError, TopologyError, ValidationError
from dfusion.policies.base import Policy
from dfusion.scenario.kinds import builtin_kinds
from dfusion.scenario.plugins import load_plugins
from dfusion.fusion.guard import GuardConfig
from dfusion.fusion.sending import MIN_SEND_INTERVAL, SEND_MODES
from dfusion.scenario.security import security_options
from dfusion.scenario.targets import check_multi_target, is_multi_target, load_targets, load_tracking, tracking_target
from dfusion.scenario.spec import (
    CLUTTER_MODELS,
    COMMON_NODE_KEYS,
    EVENT_KINDS,
    FUSION_MODES,
    Kinds,
    LinkEvent,
    NodeSpec,
    Protection,
    Scenario,
    TargetSpec,
)
from dfusion.scenario.values import intervals, number, suggest, vector, waypoint_path
from dfusion.topology import load_tree, minimum_window
from dfusion.transport.simulated import LinkSpec

__all__ = ["load_scenario", "build_policy", "node_policies", "TOP_LEVEL_KEYS", "TARGET_KEYS", "LINK_KEYS",
           "PROTECTION_KEYS", "RADIO_KEYS"]

log = logging.getLogger(__name__)

#: Keys of the top level of a scenario file.
TOP_LEVEL_KEYS = frozenset({"duration", "dt", "seed", "window", "horizon", "fusion", "sends", "min_send_interval",
                            "spanning_tree", "plugins",
                            "target", "nodes", "links", "security", "protection", "events", "radio",
                            "targets", "tracking"})
#: Keys of ``[target]`` every motion model takes (each motion adds its own, e.g. ``q``).
TARGET_KEYS = frozenset({"motion", "initial_mean", "initial_cov_diag"})
#: Keys of a ``[[links]]`` table.
LINK_KEYS = frozenset({"between", "quality", "latency", "jitter", "drop", "duplicate", "reorder", "reorder_delay",
                       "outages"})
#: Keys of the ``[radio]`` table: the behaviour of links that are not in ``[[links]]``, and ranges per kind.
RADIO_KEYS = frozenset({"latency", "jitter", "drop", "duplicate", "reorder", "reorder_delay", "ranges"})
#: Keys of ``[protection]`` (``docs/scenarios.md``, ``docs/clutter.md``).
PROTECTION_KEYS = frozenset({"enabled", "clutter_model", "network_check", "false_alarm", "quarantine", "release"})
_TABLES = {"target": "a table [target]", "nodes": "an array of tables [[nodes]]",
           "links": "an array of tables [[links]]", "security": "a table [security]",
           "protection": "a table [protection]", "events": "an array of tables [[events]]",
           "radio": "a table [radio]", "targets": "an array of tables [[targets]]",
           "tracking": "a table [tracking]"}
_TABLE_LIST = ("tables are [target], [[nodes]], [[links]], [[events]], [radio], [security] and [protection]; "
               "a multi-target scenario has [[targets]] and [tracking] instead of [target]")


def _fail(src: str, where: str, msg: str) -> ScenarioError:
    return ScenarioError(f"{src}: {where}: {msg}")


def _num(src: str, where: str, v: Any, *, positive: bool = False, nonneg: bool = False) -> float:
    """``v`` through :func:`dfusion.scenario.values.number` (finite, the sign asked for), the error naming the file."""
    try:
        return number({where: v}, where, positive=positive, nonneg=nonneg)
    except ValidationError as exc:
        raise ScenarioError(f"{src}: {exc}") from None


def _read(source: str | Path) -> dict[str, Any]:
    src = str(source)
    path = Path(source)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ScenarioError(f"{src}: cannot read: {exc.strerror or exc}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise ScenarioError(f"{src}: not a TOML scenario file (binary or not UTF-8 text)") from None
    if "\x00" in text:
        raise ScenarioError(f"{src}: not a TOML scenario file (binary data)")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{src}: invalid TOML: {exc}") from None


def _check_top_level(src: str, raw: Mapping[str, Any]) -> None:
    for key, value in raw.items():
        if key not in TOP_LEVEL_KEYS:
            hint = suggest(key, TOP_LEVEL_KEYS)
            if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
                raise _fail(src, f"[[{key}]]", f"unknown table{hint}; {_TABLE_LIST}")
            if isinstance(value, dict):
                raise _fail(src, f"[{key}]", f"unknown table{hint}; {_TABLE_LIST}")
            raise _fail(src, key, f"unknown top-level key{hint}; known: {', '.join(sorted(TOP_LEVEL_KEYS))}")
    if isinstance(raw.get("targets"), dict):   # [targets] written for [target]
        raise _fail(src, "[targets]", "unknown table (did you mean 'target'?); a multi-target scenario has an "
                                      "array of tables [[targets]], one per person or robot")
    for key, what in _TABLES.items():
        value = raw.get(key)
        if value is None:
            continue
        ok = isinstance(value, dict) if key in ("target", "security", "protection", "radio", "tracking") else (
            isinstance(value, list) and all(isinstance(v, dict) for v in value))
        if not ok:
            raise _fail(src, key, f"must be {what}, got {type(value).__name__}")


def _misplaced(key: str, table: str) -> str:
    """A hint when a key of another table landed in ``table``."""
    if key in TOP_LEVEL_KEYS - set(_TABLES):
        return f"; {key!r} is a top-level key: write it before the first table, not after [{table}]"
    return ""


def _check_table_keys(src: str, where: str, table: Mapping[str, Any], allowed: Iterable[str], table_name: str) -> None:
    allowed = set(allowed)
    for key in table:
        if key not in allowed:
            hint = _misplaced(key, table_name) or suggest(key, allowed)
            raise _fail(src, f"{where}.{key}", f"unknown key{hint}; {table_name} takes {', '.join(sorted(allowed))}")


def _policy(src: str, where: str, value: Any, kinds: Kinds) -> Policy | None:
    if value is None:
        return None
    params: dict[str, Any]
    if isinstance(value, str):
        name, params = value, {}
    elif isinstance(value, dict) and isinstance(value.get("kind"), str):
        name, params = value["kind"], {k: v for k, v in value.items() if k != "kind"}
    else:
        raise _fail(src, where, 'must be a policy name or a table with kind = "name"')
    if name not in kinds.policies:
        raise _fail(src, where, f"unknown policy {name!r}{suggest(name, kinds.policies)}; "
                                f"known: {', '.join(sorted(kinds.policies))}")
    try:
        return kinds.policies[name](params)
    except (DfusionError, TypeError) as exc:
        raise _fail(src, where, str(exc)) from None


def build_policy(value: Any, where: str = "policy", source: str = "<policy>", kinds: Kinds | None = None) -> Any:
    """The policy object a ``policy`` value of a scenario or topology file describes.

    ``value`` is a policy name (``"fusion"``, ``"greedy"``, ``"hysteresis"``, ``"blend"``,
    ``"fusion_floor"``, or one of a plug-in) or a table ``{kind = "name", ...parameters}``;
    ``None`` gives ``None`` (the node's default, information fusion). Raises
    :class:`ScenarioError` naming ``source`` and ``where`` otherwise.
    """
    return _policy(source, where, value, kinds or builtin_kinds())


def node_policies(graph: Any, kinds: Kinds | None = None) -> dict[str, Any]:
    """The policy of every node of a topology whose node table names one (``policy = ...``).

    For topology files (:func:`dfusion.topology.load_topology`), which keep the value as
    a node attribute: ``FusionNode(name, ..., policy=node_policies(g).get(name))``.
    """
    source = graph.graph.get("source", "<topology>")
    return {name: build_policy(attrs["policy"], f"node {name!r}.policy", source, kinds)
            for name, attrs in graph.nodes(data=True) if attrs.get("policy") is not None}


def _target(src: str, raw: Mapping[str, Any], kinds: Kinds) -> TargetSpec:
    t = raw.get("target", {})
    kind = t.get("motion", "constant_velocity")
    if kind not in kinds.motions:
        raise _fail(src, "target.motion", f"unknown motion {kind!r}{suggest(str(kind), kinds.motions)}; "
                                          f"known: {', '.join(sorted(kinds.motions))}")
    mk = kinds.motions[kind]
    _check_table_keys(src, "target", t, TARGET_KEYS | mk.keys, "[target]")
    try:
        motion = mk.model(t)
    except DfusionError as exc:
        raise _fail(src, "target", str(exc)) from None
    n = motion.dim
    try:
        mean = np.asarray(t.get("initial_mean", [0.0] * n), dtype=float)
        diag = np.asarray(t.get("initial_cov_diag", [1.0] * n), dtype=float)
    except (TypeError, ValueError):
        raise _fail(src, "target", "initial_mean and initial_cov_diag must be lists of numbers") from None
    if mean.shape != (n,) or diag.shape != (n,):
        raise _fail(src, "target", f"initial_mean and initial_cov_diag must have {n} entries")
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(diag)) and np.all(diag > 0)):
        raise _fail(src, "target", "initial_mean must be finite and initial_cov_diag positive")
    return TargetSpec(kind, motion, mean, np.diag(diag))


def _protection(src: str, raw: Mapping[str, Any], enabled: bool | None) -> Protection:
    """The ``[protection]`` table (every key optional); ``enabled`` overrides ``protection.enabled``."""
    table = raw.get("protection", {})
    _check_table_keys(src, "protection", table, PROTECTION_KEYS, "[protection]")
    for key in ("enabled", "network_check"):
        if not isinstance(table.get(key, True), bool):
            raise _fail(src, f"protection.{key}", f"must be true or false, got {table[key]!r}")
    model = table.get("clutter_model", "pda")
    if model not in CLUTTER_MODELS:
        raise _fail(src, "protection.clutter_model", f"must be one of {CLUTTER_MODELS}, got {model!r}")
    alarm = _num(src, "protection.false_alarm", table.get("false_alarm", 1e-3))
    q = table.get("quarantine", [3, 10])
    if not (isinstance(q, list) and len(q) == 2):
        raise _fail(src, "protection.quarantine", f"must be [failures, window], got {q!r}")
    release = table.get("release", 10)
    try:
        GuardConfig(false_alarm=alarm, failures=q[0], window=q[1], release=release)
    except DfusionError as exc:
        raise _fail(src, "protection", str(exc)) from None
    on = table.get("enabled", True) if enabled is None else bool(enabled)
    return Protection(on, model, table.get("network_check", True), alarm, q[0], q[1], release)


def _node(src: str, i: int, tbl: Mapping[str, Any], sc: Scenario, kinds: Kinds) -> NodeSpec:
    name = tbl.get("name", "?")
    where = f"nodes[{i}] ({name})"
    kind = tbl.get("sensor", "none")
    if kind != "none" and kind not in kinds.sensors:
        raise _fail(src, f"{where}.sensor", f"unknown sensor {kind!r}{suggest(str(kind), kinds.sensors)}; "
                                            f"known: {', '.join(sorted(kinds.sensors))} or 'none'")
    sk = kinds.sensors.get(kind)
    _check_table_keys(src, where, tbl, COMMON_NODE_KEYS | (sk.keys if sk else frozenset()),
                      f"a node with sensor = {kind!r}")
    rate = _num(src, f"{where}.rate", tbl.get("rate", 1.0 if kind != "none" else 0.0), nonneg=True)
    try:
        active = intervals(tbl.get("active", []), "active")
    except DfusionError as exc:
        raise _fail(src, where, str(exc)) from None
    spec = NodeSpec(
        name=name,
        sensor_kind=kind,
        sensor=None,
        rate=rate,
        send_period=_num(src, f"{where}.send_period", tbl.get("send_period", 0.5), positive=True),
        delay=_num(src, f"{where}.delay", tbl.get("delay", 0.0), nonneg=True),
        phase=_num(src, f"{where}.phase", tbl.get("phase", 0.0), nonneg=True),
        active=active,
        detection=_num(src, f"{where}.detection", tbl.get("detection", 1.0), nonneg=True),
        policy=_policy(src, f"{where}.policy", tbl.get("policy"), kinds),
        params={k: v for k, v in tbl.items() if k not in COMMON_NODE_KEYS},
    )
    if spec.detection > 1:
        raise _fail(src, f"{where}.detection", "must be a probability in [0, 1]")
    try:
        if "position" in tbl:
            spec.position = vector(tbl, "position", (2, 3))
        spec.path = waypoint_path(tbl)
    except DfusionError as exc:
        raise _fail(src, where, str(exc)) from None
    if spec.path is not None and "position" in tbl and kind != "camera":
        raise _fail(src, f"{where}.position", "a node with a path moves: give a position or a path, not both")
    ranges = sc.raw.get("radio", {}).get("ranges", {})
    if "radio_range" in tbl or kind in ranges:
        spec.radio_range = _num(src, f"{where}.radio_range" if "radio_range" in tbl else f"radio.ranges.{kind}",
                                tbl.get("radio_range", ranges.get(kind)), positive=True)
        if spec.position is None and spec.path is None:
            raise _fail(src, f"{where}.radio_range", "a node with a radio range needs a position or a path")
    if sk is not None:
        try:
            spec.sensor = sk.sensor(tbl, sc)
        except DfusionError as exc:
            raise _fail(src, where, str(exc)) from None
    return spec


def _undeclared_link_end(src: str, raw: Mapping[str, Any]) -> ScenarioError | None:
    """The error for the first link end that has no ``[[nodes]]`` table, if any."""
    named = {tbl.get("name") for tbl in raw.get("nodes", [])}
    for i, tbl in enumerate(raw.get("links", [])):
        between = tbl.get("between")
        if isinstance(between, list):
            for end in between:
                if isinstance(end, str) and end not in named:
                    return _fail(src, f"links[{i}].between", f"names node {end!r}, which has no [[nodes]] table"
                                                             f"{suggest(end, [n for n in named if isinstance(n, str)])}")
    return None


def _plugin_names(src: str, raw: Mapping[str, Any]) -> list[str]:
    names = raw.get("plugins", [])
    if not (isinstance(names, list) and all(isinstance(n, str) and n for n in names)):
        raise _fail(src, "plugins", "must be a list of module names or .py paths")
    return names


def load_scenario(
    source: str | Path | Mapping[str, Any],
    *,
    seed: int | None = None,
    fusion: str | None = None,
    duration: float | None = None,
    plugins: Iterable[str] = (),
    kinds: Kinds | None = None,
    protection: bool | None = None,
    sends: str | None = None,
    min_send_interval: float | None = None,
) -> Scenario:
    """Read and validate a scenario file (or an already parsed mapping).

    ``seed``, ``fusion``, ``duration``, ``sends`` and ``min_send_interval`` override the
    file's values; ``protection``
    overrides ``protection.enabled`` (``False``: no clutter model at the cameras, no
    consistency test of neighbours: ``dfusion simulate --no-protection``). ``plugins`` names
    plug-in modules beyond those the file names (``dfusion simulate --plugin``);
    ``kinds`` replaces the built-in kinds (plug-ins are added to it).
    """
    if isinstance(source, Mapping):
        raw, src = dict(source), "<scenario>"
        base_dir = None
    else:
        src = str(source)
        raw = _read(source)
        base_dir = str(Path(source).parent)
    _check_top_level(src, raw)
    kinds = load_plugins(kinds or builtin_kinds(), [*_plugin_names(src, raw), *plugins], base_dir)
    spanning = raw.get("spanning_tree", False)
    if not isinstance(spanning, bool):
        raise _fail(src, "spanning_tree", f"must be true or false, got {spanning!r}")
    dynamic = _links_change(src, raw)
    if dynamic and spanning:
        raise _fail(src, "spanning_tree", "has no meaning when links change at run time ([[events]], radio "
                                          "ranges): the tree rule picks the tree (docs/dynamic-topology.md)")
    for i, tbl in enumerate(raw.get("links", [])):
        _check_table_keys(src, f"links[{i}]", tbl, LINK_KEYS, "[[links]]")
    undeclared = _undeclared_link_end(src, raw)
    try:
        graph = load_tree(raw, source=src, spanning_tree=spanning, require_tree=not dynamic)
    except TopologyError as exc:
        # a misspelt node name in a link usually shows as a disconnected graph: name the cause
        if undeclared is not None and "cycle" not in str(exc):
            raise undeclared from None
        raise ScenarioError(str(exc)) from None
    if undeclared is not None:
        raise undeclared
    if graph.number_of_nodes() < 2:
        raise _fail(src, "nodes", f"a scenario needs at least two fusion nodes, got {graph.number_of_nodes()}")

    file_duration = raw.get("duration", 60.0)
    shortened = duration is not None and isinstance(file_duration, (int, float)) and duration < file_duration
    duration = _num(src, "duration", raw.get("duration", 60.0) if duration is None else duration, positive=True)
    dt = _num(src, "dt", raw.get("dt", 0.1), positive=True)
    if duration < dt:
        raise _fail(src, "duration", "shorter than one time step")
    s = raw.get("seed", 0) if seed is None else seed
    if isinstance(s, bool) or not isinstance(s, int) or s < 0:
        raise _fail(src, "seed", f"must be a non-negative integer, got {s!r}")
    window = raw.get("window", 100)
    if window is not None and (isinstance(window, bool) or not isinstance(window, int) or window < 1):
        raise _fail(src, "window", f"must be a positive integer (states), got {window!r}")
    horizon = raw.get("horizon")
    if horizon is not None:
        horizon = _num(src, "horizon", horizon, positive=True)
    fu = raw.get("fusion", "channel") if fusion is None else fusion
    if fu not in FUSION_MODES:
        raise _fail(src, "fusion", f"must be one of {FUSION_MODES}, got {fu!r}")

    se = raw.get("sends", "periodic") if sends is None else sends
    if se not in SEND_MODES:
        raise _fail(src, "sends", f"must be one of {SEND_MODES}, got {se!r}")
    msi = _num(src, "min_send_interval", raw.get("min_send_interval", MIN_SEND_INTERVAL)
               if min_send_interval is None else min_send_interval, nonneg=True)

    multi = is_multi_target(raw)
    tracking = load_tracking(src, raw) if multi else None
    target = tracking_target(tracking) if tracking is not None else _target(src, raw, kinds)
    sc = Scenario(src, duration, dt, int(s), window, horizon, fu, target, {}, {}, graph, raw, kinds=kinds,
                  protection=_protection(src, raw, protection), tracking=tracking)
    if multi:
        sc.targets, sc.rendezvous, warned = load_targets(src, raw, duration, dt, shortened=shortened)
        sc.warnings.extend(warned)
        sc.sends = se
        check_multi_target(src, raw, sc)
    try:
        sc.security = security_options(raw.get("security"), sc.base_dir)
    except DfusionError as exc:
        raise ScenarioError(f"{src}: {exc}") from None
    for i, tbl in enumerate(raw.get("nodes", [])):
        spec = _node(src, i, tbl, sc, kinds)
        sc.nodes[spec.name] = spec

    for i, tbl in enumerate(raw.get("links", [])):
        a, b = tbl["between"]
        if not graph.has_edge(a, b):   # removed by spanning_tree = true
            continue
        try:
            spec = LinkSpec.from_dict({k: v for k, v in tbl.items() if k not in ("between", "quality")})
        except DfusionError as exc:
            raise _fail(src, f"links[{i}] ({a} - {b})", str(exc)) from None
        sc.links[(a, b)] = spec
    sc.sends, sc.min_send_interval = se, msi
    sc.radio = _radio(src, raw.get("radio", {}), kinds)
    sc.events = _events(src, raw.get("events", []), sc)
    _warn_degenerate(sc)
    return sc


def _links_change(src: str, raw: Mapping[str, Any]) -> bool:
    """Whether the scenario's links change at run time: events or radio ranges."""
    radio = raw.get("radio", {})
    nodes = raw.get("nodes", [])
    return bool(raw.get("events")) or bool(isinstance(radio, dict) and radio.get("ranges")) or any(
        isinstance(t, dict) and "radio_range" in t for t in nodes)


def _radio(src: str, table: Mapping[str, Any], kinds: Kinds) -> LinkSpec:
    """The ``[radio]`` table: the spec of links that are not in ``[[links]]``; checks ``ranges``."""
    _check_table_keys(src, "radio", table, RADIO_KEYS, "[radio]")
    ranges = table.get("ranges", {})
    if not isinstance(ranges, dict):
        raise _fail(src, "radio.ranges", "must be a table of sensor kind = range in metres")
    for kind, value in ranges.items():
        if kind != "none" and kind not in kinds.sensors:
            raise _fail(src, f"radio.ranges.{kind}", f"unknown sensor kind{suggest(kind, kinds.sensors)}; known: "
                                                     f"{', '.join(sorted(kinds.sensors))} or 'none'")
        _num(src, f"radio.ranges.{kind}", value, positive=True)
    try:
        return LinkSpec.from_dict({k: v for k, v in table.items() if k != "ranges"})
    except DfusionError as exc:
        raise _fail(src, "radio", str(exc)) from None


def _events(src: str, tables: list[Mapping[str, Any]], sc: Scenario) -> list[LinkEvent]:
    """The ``[[events]]`` in time order, checked: each one action at a time within the run, on
    declared nodes; a link comes up only when it is down and goes down only when it is up; a
    node joins at most once (after the start) and leaves at most once (after it joined)."""
    events = []
    for i, tbl in enumerate(tables):
        where = f"events[{i}]"
        _check_table_keys(src, where, tbl, {"t", *EVENT_KINDS}, "[[events]]")
        if "t" not in tbl:
            raise _fail(src, f"{where}.t", "missing: the time of the event (s)")
        t = _num(src, f"{where}.t", tbl["t"], nonneg=True)
        if t > sc.duration:
            raise _fail(src, f"{where}.t", f"{t:g} s is after the end of the run ({sc.duration:g} s)")
        actions = [k for k in EVENT_KINDS if k in tbl]
        if len(actions) != 1:
            raise _fail(src, where, f"needs exactly one of {', '.join(EVENT_KINDS)}, got {len(actions)}")
        kind = actions[0]
        value = tbl[kind]
        if kind in ("link_up", "link_down"):
            if not (isinstance(value, list) and len(value) == 2 and all(isinstance(v, str) for v in value)
                    and value[0] != value[1]):
                raise _fail(src, f"{where}.{kind}", f"must name two different nodes, got {value!r}")
            names = tuple(sorted(value))
        else:
            if not isinstance(value, str):
                raise _fail(src, f"{where}.{kind}", f"must name a node, got {value!r}")
            names = (value,)
        for name in names:
            if name not in sc.nodes:
                raise _fail(src, f"{where}.{kind}", f"names node {name!r}, which has no [[nodes]] table"
                                                    f"{suggest(name, sc.nodes)}")
        events.append((t, i, LinkEvent(t, kind, names)))
    events.sort(key=lambda e: (e[0], e[1]))
    up = {tuple(sorted(pair)) for pair in sc.links}
    for t, i, ev in events:
        where = f"events[{i}].{ev.kind}"
        if ev.kind == "link_up":
            if ev.nodes in up:
                raise _fail(src, where, f"{ev.nodes[0]} - {ev.nodes[1]} is already up at t = {t:g} s")
            up.add(ev.nodes)
        elif ev.kind == "link_down":
            if ev.nodes not in up:
                raise _fail(src, where, f"{ev.nodes[0]} - {ev.nodes[1]} is not up at t = {t:g} s")
            up.discard(ev.nodes)
        else:
            spec = sc.nodes[ev.nodes[0]]
            if ev.kind == "join":
                if spec.joins is not None or spec.leaves is not None or t <= 0:
                    raise _fail(src, where, f"{spec.name} joins once, after the start and before it leaves")
                spec.joins = t
            else:
                if spec.leaves is not None:
                    raise _fail(src, where, f"{spec.name} leaves once")
                spec.leaves = t
    return [ev for _, _, ev in events]


def _warn_degenerate(sc: Scenario) -> None:
    """Log (and keep in ``sc.warnings``) settings that are valid but probably not meant."""
    if not any(spec.sensor is not None and spec.rate > 0 for spec in sc.nodes.values()):
        sc.warnings.append("no node has a sensor that measures: every estimate is the prior predicted forward")
    if sc.window is not None and sc.fusion == "channel" and not sc.dynamic:
        latency = max((spec.latency + spec.jitter + spec.reorder_delay for spec in sc.links.values()), default=0.0)
        period = max(spec.send_period for spec in sc.nodes.values())
        delay = max(spec.delay for spec in sc.nodes.values())
        seconds = minimum_window(sc.tree, max_latency=latency, send_period=period, max_measurement_delay=delay)
        need = math.ceil(seconds / sc.dt - 1e-9) + 1
        if sc.window < need:
            sc.warnings.append(f"window = {sc.window} states is shorter than the {need} this tree needs "
                               f"(topology.minimum_window): information may leave the window before it is "
                               f"shared, and nodes end conservative rather than equal to the centralized EKF")
    for w in sc.warnings:
        log.warning("%s: %s", sc.path, w)
