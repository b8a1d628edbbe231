"""Scenario files: the world, the sensors and the network, in TOML.

A scenario is also a valid topology file (``[[nodes]]`` and ``[[links]]``), so
the tree check of :mod:`dfusion.topology` applies to it. Every key is
documented in ``docs/scenarios.md``; anything invalid raises
:class:`~dfusion.errors.ScenarioError` naming the file and the key.

Sensor kinds are looked up in :data:`SENSOR_KINDS`; later node kinds register
themselves there with :func:`register_sensor`.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import networkx as nx
import numpy as np

from ..errors import DfusionError, ScenarioError, TopologyError
from ..models import ConstantVelocity, MeasurementModel, MotionModel, PositionSensor
from ..topology import load_topology
from .network import LinkSpec

#: Sensor factories: ``kind -> f(node_table, scenario) -> MeasurementModel``.
SENSOR_KINDS: dict[str, Callable[[Mapping[str, Any], "Scenario"], MeasurementModel]] = {}
#: Front-end factories: ``kind -> f(node_spec, scenario, seed) -> FrontEnd``. A front end turns
#: a node's raw measurements into what its FusionNode fuses; kinds without one use
#: :class:`dfusion.sim.frontends.EIFFrontEnd` (an EIF measurement update).
FRONT_ENDS: dict[str, Callable[..., Any]] = {}
#: Output policies: ``name -> f(params: dict) -> Policy`` (``policy = "name"`` or
#: ``policy = {kind = "name", ...}`` in a node table).
POLICY_KINDS: dict[str, Callable[[Mapping[str, Any]], Any]] = {}
#: Motion factories: ``name -> f(target_table) -> MotionModel``.
MOTION_KINDS: dict[str, Callable[[Mapping[str, Any]], MotionModel]] = {}

FUSION_MODES = ("channel", "naive")


def register_sensor(
    kind: str,
    factory: Callable[[Mapping[str, Any], "Scenario"], MeasurementModel],
    front_end: Callable[..., Any] | None = None,
) -> None:
    """Make ``sensor = "<kind>"`` available in scenario files.

    ``factory(node_table, scenario)`` returns the measurement model the simulated
    world measures with; ``front_end(node_spec, scenario, seed)``, if given, returns
    the object that fuses those measurements into the node (see
    :mod:`dfusion.sim.frontends`).
    """
    SENSOR_KINDS[kind] = factory
    if front_end is not None:
        FRONT_ENDS[kind] = front_end


def _position_sensor(table: Mapping[str, Any], sc: "Scenario") -> MeasurementModel:
    return PositionSensor(dim=sc.target.axes, std=table.get("std", 1.0))


def _constant_velocity(table: Mapping[str, Any]) -> MotionModel:
    mean = table.get("initial_mean")
    axes = len(mean) // 2 if isinstance(mean, list) and mean else 2
    return ConstantVelocity(dim=axes, q=table.get("q", 0.1))


register_sensor("position", _position_sensor)
MOTION_KINDS["constant_velocity"] = _constant_velocity


@dataclass
class TargetSpec:
    """The tracked target: its motion model and the common prior."""

    motion_kind: str
    motion: MotionModel
    initial_mean: np.ndarray
    initial_cov: np.ndarray

    @property
    def axes(self) -> int:
        return getattr(self.motion, "axes", 2)


@dataclass
class NodeSpec:
    """One fusion node: its sensor and its timing.

    Attributes
    ----------
    rate : float
        Measurements per second (0: the node measures nothing).
    send_period : float
        Seconds between two messages to each neighbour.
    delay : float
        Measurements reach the filter a uniform ``[0, delay]`` seconds late.
    phase : float
        Offset of the measurement times ``phase + k / rate``.
    active : list of (start, end)
        Intervals in which the sensor produces measurements (default: always).
    detection : float
        Probability that a measurement is produced when active.
    """

    name: str
    sensor_kind: str
    sensor: MeasurementModel | None
    rate: float
    send_period: float
    policy: Any = None
    delay: float = 0.0
    phase: float = 0.0
    active: list[tuple[float, float]] = field(default_factory=list)
    detection: float = 1.0
    params: dict[str, Any] = field(default_factory=dict)

    def is_active(self, t: float) -> bool:
        return not self.active or any(a <= t <= b for a, b in self.active)


@dataclass
class Scenario:
    """A parsed, validated scenario (see ``docs/scenarios.md``)."""

    path: str
    duration: float
    dt: float
    seed: int
    window: int | None
    horizon: float | None
    fusion: str
    target: TargetSpec
    nodes: dict[str, NodeSpec]
    links: dict[tuple[str, str], LinkSpec]
    graph: nx.Graph
    raw: dict[str, Any]

    @property
    def steps(self) -> int:
        return int(round(self.duration / self.dt))

    def outages(self) -> list[tuple[str, str, float, float]]:
        """Every outage interval as ``(a, b, start, end)``."""
        return [(a, b, s, e) for (a, b), spec in self.links.items() for s, e in spec.outages]


def _fail(src: str, where: str, msg: str) -> ScenarioError:
    return ScenarioError(f"{src}: {where}: {msg}")


def _num(src: str, where: str, v: Any, *, positive: bool = False, nonneg: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _fail(src, where, f"must be a finite number, got {v!r}")
    if positive and v <= 0:
        raise _fail(src, where, f"must be positive, got {v!r}")
    if nonneg and v < 0:
        raise _fail(src, where, f"must be non-negative, got {v!r}")
    return float(v)


def _intervals(src: str, where: str, v: Any) -> list[tuple[float, float]]:
    if not isinstance(v, list):
        raise _fail(src, where, "must be a list of [start, end] pairs")
    out = []
    for i, iv in enumerate(v):
        if not (isinstance(iv, list) and len(iv) == 2):
            raise _fail(src, f"{where}[{i}]", "must be a [start, end] pair")
        a, b = (_num(src, f"{where}[{i}]", x) for x in iv)
        if b < a:
            raise _fail(src, f"{where}[{i}]", f"end {b} before start {a}")
        out.append((a, b))
    return out


_NODE_KEYS = {"name", "sensor", "std", "rate", "send_period", "delay", "phase", "active", "detection", "policy"}


def register_policy(name: str, factory: Callable[[Mapping[str, Any]], Any]) -> None:
    """Make ``policy = "<name>"`` available in scenario files."""
    POLICY_KINDS[name] = factory


def _policy(src: str, where: str, value: Any) -> Any:
    if value is None:
        return None
    params: dict[str, Any]
    if isinstance(value, str):
        name, params = value, {}
    elif isinstance(value, dict) and isinstance(value.get("kind"), str):
        name, params = value["kind"], {k: v for k, v in value.items() if k != "kind"}
    else:
        raise _fail(src, where, 'must be a policy name or a table with kind = "name"')
    if name == "fusion":
        from ..fusion.policy import InformationFusionPolicy

        return InformationFusionPolicy()
    if name not in POLICY_KINDS:
        raise _fail(src, where, f"unknown policy {name!r}; known: {sorted(['fusion', *POLICY_KINDS])}")
    try:
        return POLICY_KINDS[name](params)
    except (DfusionError, TypeError) as exc:
        raise _fail(src, where, str(exc)) from None
def build_policy(value: Any, where: str = "policy", source: str = "<policy>") -> Any:
    """The policy object a ``policy`` value of a scenario or topology file describes.

    ``value`` is a registered name (``"fusion"``, ``"greedy"``, ``"hysteresis"``,
    ``"blend"``, ``"fusion_floor"``, or one added with :func:`register_policy`) or a table
    ``{kind = "name", ...parameters}``; ``None`` gives ``None`` (the node's default,
    information fusion). Raises :class:`ScenarioError` naming ``source`` and ``where`` otherwise.
    """
    from .. import switching  # noqa: F401  (registers the switching policies)

    return _policy(source, where, value)


def node_policies(graph: nx.Graph) -> dict[str, Any]:
    """The policy of every node of a topology whose node table names one (``policy = ...``).

    For topology files (:func:`dfusion.topology.load_topology`), which keep the value as
    a node attribute: ``FusionNode(name, ..., policy=node_policies(g).get(name))``.
    """
    source = graph.graph.get("source", "<topology>")
    return {name: build_policy(attrs["policy"], f"node {name!r}.policy", source)
            for name, attrs in graph.nodes(data=True) if attrs.get("policy") is not None}


_LINK_KEYS = {"between", "quality", "latency", "jitter", "drop", "duplicate", "reorder", "reorder_delay", "outages"}


def load_scenario(
    source: str | Path | Mapping[str, Any],
    *,
    seed: int | None = None,
    fusion: str | None = None,
    duration: float | None = None,
) -> Scenario:
    """Read and validate a scenario file (or an already parsed mapping).

    ``seed``, ``fusion`` and ``duration`` override the file's values.
    """
    from .. import sensors  # noqa: F401  (registers every sensor kind)
    from .. import switching  # noqa: F401  (registers the switching policies)

    if isinstance(source, Mapping):
        raw, src = dict(source), "<scenario>"
    else:
        src = str(source)
        try:
            raw = tomllib.loads(Path(source).read_text())
        except OSError as exc:
            raise ScenarioError(f"{src}: cannot read: {exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ScenarioError(f"{src}: invalid TOML: {exc}") from None
    spanning = raw.get("spanning_tree", False)
    if not isinstance(spanning, bool):
        raise _fail(src, "spanning_tree", f"must be true or false, got {spanning!r}")
    try:
        graph = load_topology(raw, source=src, spanning_tree=spanning)
    except TopologyError as exc:
        raise ScenarioError(str(exc)) from None

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

    t = raw.get("target", {})
    if not isinstance(t, dict):
        raise _fail(src, "target", "must be a table")
    kind = t.get("motion", "constant_velocity")
    if kind not in MOTION_KINDS:
        raise _fail(src, "target.motion", f"unknown motion {kind!r}; known: {sorted(MOTION_KINDS)}")
    try:
        motion = MOTION_KINDS[kind](t)
    except DfusionError as exc:
        raise _fail(src, "target", str(exc)) from None
    n = motion.dim
    mean = np.asarray(t.get("initial_mean", [0.0] * n), dtype=float)
    diag = np.asarray(t.get("initial_cov_diag", [1.0] * n), dtype=float)
    if mean.shape != (n,) or diag.shape != (n,):
        raise _fail(src, "target", f"initial_mean and initial_cov_diag must have {n} entries")
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(diag)) and np.all(diag > 0)):
        raise _fail(src, "target", "initial_mean must be finite and initial_cov_diag positive")
    target = TargetSpec(kind, motion, mean, np.diag(diag))

    sc = Scenario(src, duration, dt, int(s), window, horizon, fu, target, {}, {}, graph, raw)

    for i, tbl in enumerate(raw.get("nodes", [])):
        where = f"nodes[{i}] ({tbl.get('name', '?')})"
        kind = tbl.get("sensor", "none")
        if kind != "none" and kind not in SENSOR_KINDS:
            raise _fail(src, f"{where}.sensor", f"unknown sensor {kind!r}; known: {sorted(SENSOR_KINDS)} or 'none'")
        rate = _num(src, f"{where}.rate", tbl.get("rate", 1.0 if kind != "none" else 0.0), nonneg=True)
        spec = NodeSpec(
            name=tbl["name"],
            sensor_kind=kind,
            sensor=None,
            rate=rate,
            send_period=_num(src, f"{where}.send_period", tbl.get("send_period", 0.5), positive=True),
            delay=_num(src, f"{where}.delay", tbl.get("delay", 0.0), nonneg=True),
            phase=_num(src, f"{where}.phase", tbl.get("phase", 0.0), nonneg=True),
            active=_intervals(src, f"{where}.active", tbl.get("active", [])),
            detection=_num(src, f"{where}.detection", tbl.get("detection", 1.0), nonneg=True),
            policy=_policy(src, f"{where}.policy", tbl.get("policy")),
            params={k: v for k, v in tbl.items() if k not in _NODE_KEYS},
        )
        if spec.detection > 1:
            raise _fail(src, f"{where}.detection", "must be a probability in [0, 1]")
        if kind != "none":
            try:
                spec.sensor = SENSOR_KINDS[kind](tbl, sc)
            except DfusionError as exc:
                raise _fail(src, where, str(exc)) from None
        sc.nodes[spec.name] = spec
    for name in graph.nodes:   # nodes named only by links: relays without sensors
        sc.nodes.setdefault(name, NodeSpec(name, "none", None, 0.0, 0.5))

    for i, tbl in enumerate(raw.get("links", [])):
        a, b = tbl["between"]
        where = f"links[{i}] ({a} - {b})"
        unknown = set(tbl) - _LINK_KEYS
        if unknown:
            raise _fail(src, where, f"unknown keys {sorted(unknown)}")
        if not graph.has_edge(a, b):   # removed by spanning_tree = true
            continue
        try:
            spec = LinkSpec.from_dict({k: v for k, v in tbl.items() if k not in ("between", "quality")})
        except DfusionError as exc:
            raise _fail(src, where, str(exc)) from None
        sc.links[(a, b)] = spec
    return sc
