"""Multi-target scenarios: the ``[[targets]]`` and ``[tracking]`` tables, checked strictly.

A scenario with ``[[targets]]`` (and an optional ``[tracking]``) describes several people and
robots, each on a waypoint path between the time it appears and the time it leaves, seen by
camera nodes with rectangular views (``sensor = "detections"``) and, when they carry a radio
tag, by a tag reader (``sensor = "tags"``: an identified target). Every node runs a
:class:`~dfusion.fusion.tracking_node.TrackingNode` (``dfusion simulate``,
:mod:`dfusion.sim.tracking_runner`). ``docs/scenarios.md`` ("Multi-target scenarios") documents
every key; a single-target scenario (``[target]``) is untouched by this module.

As in :mod:`dfusion.scenario.loader`, anything invalid raises
:class:`~dfusion.errors.ScenarioError` with one line naming the file, the table and the key.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from dfusion.errors import DfusionError, ScenarioError, ValidationError
from dfusion.geometry import WaypointPath
from dfusion.models.motion import ConstantVelocity
from dfusion.scenario.spec import (ASSOCIATORS, TARGET_KINDS, Rendezvous, Scenario, TargetPath, TargetSpec,
                                   TrackingSpec)
from dfusion.tracking.track import TrackId
from dfusion.scenario.values import integer, number, suggest, waypoint_path

__all__ = ["TARGETS_KEYS", "TRACKING_KEYS", "INITIATOR_KEYS", "DELETER_KEYS", "MERGE_KEYS", "PRIOR_KEYS",
           "MULTI_TARGET_SENSORS", "NOT_MULTI_TARGET_NODE_KEYS", "is_multi_target", "load_tracking", "load_targets",
           "check_multi_target", "tracking_target", "tag_track_id"]

#: Keys of a ``[[targets]]`` table.
TARGETS_KEYS = frozenset({"name", "kind", "path", "speed", "appear", "leave", "loop", "meets", "meet_within"})
#: Keys of ``[tracking]`` (its sub-tables have their own).
TRACKING_KEYS = frozenset({"associator", "gate", "q", "region", "gospa_c", "match", "prior", "initiator", "deleter",
                           "merge"})
INITIATOR_KEYS = frozenset({"confirm", "velocity_std", "max_speed", "max_seed_age"})
DELETER_KEYS = frozenset({"max_age", "max_misses", "region_grace"})
MERGE_KEYS = frozenset({"enabled", "gate", "confirm", "max_distance", "distinct_for"})
PRIOR_KEYS = frozenset({"position_std", "velocity_std"})
#: Sensor kinds a node of a multi-target scenario may have (and ``"none"``).
MULTI_TARGET_SENSORS = ("detections", "tags")
#: Node keys of single-target scenarios that mean nothing in a multi-target one (refused).
NOT_MULTI_TARGET_NODE_KEYS = ("delay", "policy", "path", "speed", "loop", "path_start", "radio_range")


def _fail(src: str, where: str, msg: str) -> ScenarioError:
    return ScenarioError(f"{src}: {where}: {msg}")


def is_multi_target(raw: Mapping[str, Any]) -> bool:
    """Whether a parsed file is a multi-target scenario (it has ``[[targets]]`` or ``[tracking]``)."""
    return "targets" in raw or "tracking" in raw


def _keys(src: str, where: str, table: Any, allowed: frozenset[str], name: str) -> Mapping[str, Any]:
    if not isinstance(table, dict):
        raise _fail(src, where, f"must be a table {name}, got {type(table).__name__}")
    for key in table:
        if key not in allowed:
            raise _fail(src, f"{where}.{key}", f"unknown key{suggest(key, allowed)}; {name} takes "
                                               f"{', '.join(sorted(allowed))}")
    return table


def _checked(src: str, where: str, fn, *args, **kw):
    try:
        return fn(*args, **kw)
    except ValidationError as exc:
        raise ScenarioError(f"{src}: {where}.{exc}") from None


def _probability(src: str, where: str, table: Mapping[str, Any], key: str, default: float) -> float:
    v = _checked(src, where, number, table, key, default)
    if not 0.0 < v < 1.0:
        raise _fail(src, f"{where}.{key}", f"must be a probability in (0, 1), got {v!r}")
    return v


def _rect(src: str, where: str, value: Any) -> tuple[float, float, float, float]:
    if not (isinstance(value, list) and len(value) == 4 and all(
            isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in value)):
        raise _fail(src, where, f"must be [x0, x1, y0, y1] (metres), got {value!r}")
    x0, x1, y0, y1 = (float(c) for c in value)
    if not (x1 > x0 and y1 > y0):
        raise _fail(src, where, f"must have x1 > x0 and y1 > y0, got {value!r}")
    return x0, x1, y0, y1


def load_tracking(src: str, raw: Mapping[str, Any]) -> TrackingSpec:
    """The ``[tracking]`` table (every key optional) of a multi-target scenario."""
    if "target" in raw:
        raise _fail(src, "[target]", "a multi-target scenario has [[targets]] (the people and robots) and "
                                     "[tracking] (the tracks' motion and the tracker), not [target]")
    t = _keys(src, "tracking", raw.get("tracking", {}), TRACKING_KEYS, "[tracking]")
    assoc = t.get("associator", "jpda")
    if assoc not in ASSOCIATORS:
        raise _fail(src, "tracking.associator", f"must be one of {', '.join(ASSOCIATORS)}, got {assoc!r}"
                                                f"{suggest(str(assoc), ASSOCIATORS)}")
    w = "tracking"
    ini = _keys(src, "tracking.initiator", t.get("initiator", {}), INITIATOR_KEYS, "[tracking.initiator]")
    dele = _keys(src, "tracking.deleter", t.get("deleter", {}), DELETER_KEYS, "[tracking.deleter]")
    mer = _keys(src, "tracking.merge", t.get("merge", {}), MERGE_KEYS, "[tracking.merge]")
    pri = _keys(src, "tracking.prior", t.get("prior", {}), PRIOR_KEYS, "[tracking.prior]")
    confirm = ini.get("confirm", [3, 5])
    if not (isinstance(confirm, list) and len(confirm) == 2 and all(
            isinstance(c, int) and not isinstance(c, bool) for c in confirm) and 2 <= confirm[0] <= confirm[1]):
        raise _fail(src, "tracking.initiator.confirm", f"must be [m, n], integers with 2 <= m <= n, got {confirm!r}")
    vstd = ini.get("velocity_std", 1.5)
    if vstd is not False:
        vstd = _checked(src, "tracking.initiator", number, ini, "velocity_std", 1.5, positive=True)
    misses = _checked(src, "tracking.deleter", integer, dele, "max_misses", 5, minimum=0)
    enabled = mer.get("enabled", True)
    if not isinstance(enabled, bool):
        raise _fail(src, "tracking.merge.enabled", f"must be true or false, got {enabled!r}")
    spec = TrackingSpec(
        associator=assoc,
        gate=_probability(src, w, t, "gate", 0.99),
        q=_checked(src, w, number, t, "q", 0.05, positive=True),
        confirm=(confirm[0], confirm[1]),
        velocity_std=None if vstd is False else vstd,
        max_speed=_checked(src, "tracking.initiator", number, ini, "max_speed", 3.0, positive=True),
        max_seed_age=_checked(src, "tracking.initiator", number, ini, "max_seed_age", 0.35, positive=True),
        max_age=_checked(src, "tracking.deleter", number, dele, "max_age", 2.0, positive=True),
        max_misses=misses or None,
        region=_rect(src, "tracking.region", t["region"]) if "region" in t else None,
        region_grace=_checked(src, "tracking.deleter", number, dele, "region_grace", 1.0, nonneg=True),
        merge=enabled,
        merge_gate=_probability(src, "tracking.merge", mer, "gate", 0.99),
        merge_confirm=_checked(src, "tracking.merge", integer, mer, "confirm", 5, minimum=1),
        merge_distance=_checked(src, "tracking.merge", number, mer, "max_distance", 1.5, nonneg=True),
        merge_distinct_for=_checked(src, "tracking.merge", number, mer, "distinct_for", 3.0, nonneg=True),
        prior_position_std=_checked(src, "tracking.prior", number, pri, "position_std", 1.0e3, positive=True),
        prior_velocity_std=_checked(src, "tracking.prior", number, pri, "velocity_std", 1.0e2, positive=True),
        gospa_c=_checked(src, w, number, t, "gospa_c", 2.0, positive=True),
        match=_checked(src, w, number, t, "match", 1.0, positive=True),
    )
    if spec.max_seed_age < 0.05:
        raise _fail(src, "tracking.initiator.max_seed_age", f"must be at least 0.05 s, got {spec.max_seed_age!r}")
    return spec


def tracking_target(spec: TrackingSpec) -> TargetSpec:
    """The :class:`TargetSpec` of every track of a multi-target scenario: constant velocity in
    2-D with ``q``, the common broad prior (``Scenario.target`` of such a scenario)."""
    motion = ConstantVelocity(2, spec.q)
    diag = [spec.prior_position_std**2] * 2 + [spec.prior_velocity_std**2] * 2
    return TargetSpec("constant_velocity", motion, np.zeros(4), np.diag(diag))


def load_targets(src: str, raw: Mapping[str, Any], duration: float, dt: float, *,
                 shortened: bool = False) -> tuple[list[TargetPath], list[Rendezvous], list[str]]:
    """The ``[[targets]]`` of a multi-target scenario, the rendezvous their ``meets`` keys ask
    for, and warnings. A rendezvous that does not happen is an error, unless the run was
    ``shortened`` (``--duration``) to before it: then it is left out with a warning."""
    tables = raw.get("targets")
    if not tables:
        raise _fail(src, "targets", "a multi-target scenario needs at least one [[targets]] table")
    out: list[TargetPath] = []
    meets: list[tuple[int, TargetPath, Any, float]] = []
    for i, tbl in enumerate(tables):
        name = tbl.get("name", "?")
        where = f"targets[{i}] ({name})"
        _keys(src, where, tbl, TARGETS_KEYS, "[[targets]]")
        if not (isinstance(name, str) and name and "#" not in name):
            raise _fail(src, f"{where}.name", f"must be a non-empty name without '#', got {name!r}")
        if any(t.name == name for t in out):
            raise _fail(src, f"{where}.name", f"target {name!r} is defined twice")
        kind = tbl.get("kind", "person")
        if kind not in TARGET_KINDS:
            raise _fail(src, f"{where}.kind", f"must be one of {', '.join(TARGET_KINDS)}, got {kind!r}"
                                              f"{suggest(str(kind), TARGET_KINDS)}")
        if "path" not in tbl:
            raise _fail(src, f"{where}.path", "missing: the target's waypoints [[x, y], ...]")
        appear = _checked(src, where, number, tbl, "appear", 0.0, nonneg=True)
        if appear >= duration:
            raise _fail(src, f"{where}.appear", f"{appear:g} s is not before the end of the run ({duration:g} s)")
        path_table = {k: tbl[k] for k in ("path", "speed", "loop") if k in tbl}
        path_table["path_start"] = appear
        try:
            path = waypoint_path(path_table)
        except DfusionError as exc:
            raise _fail(src, where, str(exc)) from None
        assert path is not None
        end = duration if path.loop else appear + path.length / path.speed
        leave = _checked(src, where, number, tbl, "leave", min(end, duration), nonneg=True)
        if leave <= appear:
            raise _fail(src, f"{where}.leave", f"{leave:g} s must be after appear ({appear:g} s)")
        target = TargetPath(name, kind, path, appear, min(leave, duration))
        out.append(target)
        if "meets" in tbl:
            meets.append((i, target, tbl["meets"], _checked(src, where, number, tbl, "meet_within", 1.0,
                                                             positive=True)))
        elif "meet_within" in tbl:
            raise _fail(src, f"{where}.meet_within", "needs meets = \"<person>\"")
    names = {t.name: t for t in out}
    rendezvous, warnings = [], []
    for i, robot, other, within in meets:
        where = f"targets[{i}] ({robot.name}).meets"
        if robot.kind != "robot":
            raise _fail(src, where, "a rendezvous is a robot meeting a person: give meets on a robot's table")
        if not isinstance(other, str) or other not in names or names[other].kind != "person":
            people = [t.name for t in out if t.kind == "person"]
            raise _fail(src, where, f"must name a person of [[targets]], got {other!r}{suggest(str(other), people)}")
        try:
            rendezvous.append(_rendezvous(src, where, robot, names[other], within, dt))
        except ScenarioError as exc:
            if not shortened:
                raise
            warnings.append(f"{exc} in the shortened run: left out")
    return out, rendezvous, warnings


def _rendezvous(src: str, where: str, robot: TargetPath, person: TargetPath, within: float,
                dt: float) -> Rendezvous:
    """Where ``robot`` and ``person`` are closest while both exist (on the ``dt`` grid); refused
    when they never come within ``within`` metres."""
    lo, hi = max(robot.appear, person.appear), min(robot.leave, person.leave)
    if hi < lo:
        raise _fail(src, where, f"{robot.name} and {person.name} never exist at the same time")
    ts = np.arange(lo, hi + 1e-9, min(dt, 0.05))
    d = np.array([np.linalg.norm(robot.position(t) - person.position(t)) for t in ts])
    k = int(np.argmin(d))
    if d[k] > within:
        raise _fail(src, where, f"{robot.name} comes no closer than {d[k]:.2f} m to {person.name} (at t = "
                                f"{ts[k]:.1f} s); meet_within = {within:g} m")
    return Rendezvous(robot.name, person.name, within, float(ts[k]), float(d[k]))


def check_multi_target(src: str, raw: Mapping[str, Any], sc: Scenario) -> None:
    """What a multi-target scenario may not have: node keys and kinds of single-target
    scenarios, links that change, naive fusion, event sends, a target named like a node."""
    for key, why in (("events", "[[events]] (links that change)"), ("radio", "[radio]")):
        if key in raw:
            raise _fail(src, key, f"{why} is not supported in a multi-target scenario yet; a link outage is "
                                  f"[[links]] outages = [[start, end]]")
    if sc.fusion != "channel":
        raise _fail(src, "fusion", "a multi-target scenario fuses with channel filters (fusion = \"channel\")")
    if sc.sends != "periodic":
        raise _fail(src, "sends", "a multi-target scenario's nodes send periodically (sends = \"periodic\")")
    for i, tbl in enumerate(raw.get("nodes", [])):
        where = f"nodes[{i}] ({tbl.get('name', '?')})"
        kind = tbl.get("sensor", "none")
        if kind != "none" and kind not in MULTI_TARGET_SENSORS:
            raise _fail(src, f"{where}.sensor", f"a multi-target scenario's nodes have sensor = "
                                                f"{' or '.join(repr(k) for k in MULTI_TARGET_SENSORS)} or 'none', "
                                                f"got {kind!r}{suggest(str(kind), MULTI_TARGET_SENSORS)}")
        for key in NOT_MULTI_TARGET_NODE_KEYS:
            if key in tbl:
                raise _fail(src, f"{where}.{key}", "not used by a multi-target scenario's nodes")
    node_names = {tbl.get("name") for tbl in raw.get("nodes", [])}
    for t in sc.targets:
        if t.name in node_names:
            raise _fail(src, "targets", f"target {t.name!r} has the name of a node: a tagged target's track is "
                                        f"named after it, so target and node names must differ")


def tag_track_id(target: str) -> TrackId:
    """The network-wide identity of an identified target's track (a tag, a robot's own
    localization): ``TrackId(target, 0)``; every node that reads it uses the same one."""
    return TrackId(target, 0)
