"""What a scenario file describes, as plain data: the target, the nodes, the links, the kinds.

:func:`dfusion.scenario.load_scenario` builds a :class:`Scenario` from a TOML file;
``docs/scenarios.md`` documents every key.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator, Mapping

import numpy as np

from dfusion.errors import ScenarioError
from dfusion.models.base import MeasurementModel, MotionModel
from dfusion.scenario.security import SecurityOptions
from dfusion.topology import Tree
from dfusion.transport.simulated import LinkSpec

if TYPE_CHECKING:   # type names only: no import at run time
    import networkx as nx

    from dfusion.frontends.base import FrontEnd
    from dfusion.geometry import WaypointPath
    from dfusion.policies.base import Policy

__all__ = ["TargetSpec", "NodeSpec", "Scenario", "SensorKind", "MotionKind", "Kinds", "LazyTable", "Protection",
           "FUSION_MODES", "COMMON_NODE_KEYS", "CLUTTER_MODELS", "LinkEvent", "EVENT_KINDS", "TargetPath",
           "Rendezvous", "TrackingSpec", "TARGET_KINDS", "ASSOCIATORS"]

#: Values of the top-level key ``fusion``.
FUSION_MODES = ("channel", "naive")

#: Values of ``protection.clutter_model`` and of a camera node's ``clutter_model``.
CLUTTER_MODELS = ("pda", "gate")

#: Keys every ``[[nodes]]`` table may have, whatever its sensor kind.
COMMON_NODE_KEYS = frozenset({"name", "sensor", "rate", "send_period", "delay", "phase", "active", "detection",
                              "policy", "position", "path", "speed", "loop", "path_start", "radio_range"})
#: What an ``[[events]]`` table can do (its one key besides ``t``).
EVENT_KINDS = ("link_up", "link_down", "join", "leave")


@dataclass(frozen=True)
class SensorKind:
    """A sensor kind a scenario file can name (``sensor = "<name>"`` in a node table).

    Attributes
    ----------
    name : str
        The name scenario files use.
    keys : frozenset of str
        The node-table keys this kind accepts besides :data:`COMMON_NODE_KEYS`; any
        other key is an error.
    sensor : callable
        ``sensor(table, scenario) -> MeasurementModel``: the model the simulated world
        measures with (``h``, ``R``; and ``in_view``, ``clutter_rate`` when it has them).
        It validates the table and raises :class:`~dfusion.errors.ValidationError` with a
        one-line message naming the key.
    front_end : callable or None
        ``front_end(spec, scenario, seed) -> FrontEnd``: what fuses the sensor's
        measurements into the node (``None``: an EIF update with the sensor's model,
        :class:`~dfusion.frontends.EIFFrontEnd`).
    doc : str
        One line for error messages and listings.
    """

    name: str
    keys: frozenset[str]
    sensor: Callable[[Mapping[str, Any], "Scenario"], MeasurementModel]
    front_end: Callable[["NodeSpec", "Scenario", int], "FrontEnd"] | None = None
    doc: str = ""


@dataclass(frozen=True)
class MotionKind:
    """A motion model a scenario's ``[target]`` table can name (``motion = "<name>"``).

    ``model(target_table) -> MotionModel``; ``keys`` are the ``[target]`` keys it reads
    besides ``motion``, ``initial_mean`` and ``initial_cov_diag``.
    """

    name: str
    keys: frozenset[str]
    model: Callable[[Mapping[str, Any]], MotionModel]
    doc: str = ""


class LazyTable(Mapping[str, Any]):
    """A table of kinds whose entries may be given as ``"module:attribute"``, imported on first use.

    A node program then loads only the sensor kind it runs (a position sensor needs no
    camera model, no particle filter, no scipy). Iterating over the names imports nothing.
    """

    def __init__(self, entries: Mapping[str, Any]) -> None:
        self._entries = dict(entries)

    def __getitem__(self, name: str) -> Any:
        value = self._entries[name]
        if isinstance(value, str):
            module, _, attribute = value.partition(":")
            value = getattr(importlib.import_module(module), attribute)
            self._entries[name] = value
        return value

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def entries(self) -> dict[str, Any]:
        """The entries as given (names to objects or ``"module:attribute"`` strings), nothing imported."""
        return dict(self._entries)


def _entries(table: Mapping[str, Any]) -> dict[str, Any]:
    return table.entries() if isinstance(table, LazyTable) else dict(table)


@dataclass(frozen=True)
class Kinds:
    """The sensor kinds, policies and motion models a scenario may name.

    :func:`dfusion.scenario.builtin_kinds` holds dfusion's own; plug-ins add theirs
    (:func:`dfusion.scenario.load_plugins`). Nothing is registered globally: each
    scenario carries the kinds it was loaded with.
    """

    sensors: Mapping[str, SensorKind]
    policies: Mapping[str, Callable[[Mapping[str, Any]], "Policy"]]
    motions: Mapping[str, MotionKind]
    plugins: tuple[str, ...] = ()

    def merged(self, other: "Kinds", source: str) -> "Kinds":
        """These kinds plus ``other``'s; a name defined twice is an error."""
        for mine, theirs, what in ((self.sensors, other.sensors, "sensor kind"),
                                   (self.policies, other.policies, "policy"),
                                   (self.motions, other.motions, "motion model")):
            clash = sorted(set(mine) & set(theirs))
            if clash:
                raise ScenarioError(f"{source}: {what} {clash[0]!r} is already defined")
        return Kinds(LazyTable({**_entries(self.sensors), **_entries(other.sensors)}),
                     LazyTable({**_entries(self.policies), **_entries(other.policies)}),
                     LazyTable({**_entries(self.motions), **_entries(other.motions)}), self.plugins + other.plugins)


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


#: Values of a ``[[targets]]`` table's ``kind``.
TARGET_KINDS = ("person", "robot")
#: Values of ``tracking.associator``.
ASSOCIATORS = ("jpda", "gnn")


@dataclass(frozen=True)
class Rendezvous:
    """A robot's path meets a person's: ``robot`` and ``person`` come within ``within`` metres
    (closest at ``t``, ``distance`` apart), checked when the file is loaded."""

    robot: str
    person: str
    within: float
    t: float
    distance: float


@dataclass
class TargetPath:
    """One target of a multi-target scenario (``[[targets]]``): a person or a robot that
    appears at ``appear`` on the first waypoint of ``path``, walks it at ``path.speed``, and
    leaves at ``leave`` (by default when it reaches the last waypoint: a path that ends on the
    border of the area is a border crossing)."""

    name: str
    kind: str
    path: "WaypointPath"
    appear: float
    leave: float

    def present(self, t: float) -> bool:
        """Whether the target exists at ``t``."""
        return self.appear - 1e-9 <= t <= self.leave + 1e-9

    def position(self, t: float) -> np.ndarray:
        """``(x, y)`` at ``t`` (on its path; meaningful while :meth:`present`)."""
        return self.path.position(t)


@dataclass(frozen=True)
class TrackingSpec:
    """The ``[tracking]`` table of a multi-target scenario: every node's tracker and the metrics
    (``docs/scenarios.md``, "Multi-target scenarios"). The tracks' motion is constant
    velocity in 2-D with acceleration noise ``q``.

    Attributes
    ----------
    associator : ``"jpda"`` (exact, EHM) or ``"gnn"``.
    gate : gate probability of the association and of the initiator.
    q : acceleration noise spectral density of every track (m^2 s^-3).
    confirm : ``(m, n)``: M-of-N confirmation of the initiator.
    velocity_std, max_speed, max_seed_age : the initiator's velocity prior (None: none), pairing
        speed (m/s) and seed age (s) (:class:`~dfusion.tracking.MofNInitiator`).
    max_age : a track with no information newer than ``max_age`` seconds ends
        (:class:`~dfusion.tracking.StaleDeleter`; a node hears of others' detections late, so
        more than the network's delay).
    max_misses : ``K`` consecutive misses in this node's own scans (in view) end a track (None: off).
    region : ``(x0, x1, y0, y1)`` where targets can be (None: anywhere); a track whose estimate
        left it ends once its newest information is ``region_grace`` seconds old.
    merge : whether nodes merge tracks found to be one target (track-to-track association).
    merge_gate, merge_confirm, merge_distance, merge_distinct_for : the
        :class:`~dfusion.tracking.track_to_track.TrackToTrackAssociator`'s settings.
    prior_position_std, prior_velocity_std : the common prior of every track (broad).
    gospa_c, match : the metrics' GOSPA cut-off (m) and CLEAR MOT / IDF1 match distance (m).
    """

    associator: str = "jpda"
    gate: float = 0.99
    q: float = 0.05
    confirm: tuple[int, int] = (3, 5)
    velocity_std: float | None = 1.5
    max_speed: float = 3.0
    max_seed_age: float = 0.35
    max_age: float = 2.0
    max_misses: int | None = 5
    region: tuple[float, float, float, float] | None = None
    region_grace: float = 1.0
    merge: bool = True
    merge_gate: float = 0.99
    merge_confirm: int = 5
    merge_distance: float = 1.5
    merge_distinct_for: float = 3.0
    prior_position_std: float = 1.0e3
    prior_velocity_std: float = 1.0e2
    gospa_c: float = 2.0
    match: float = 1.0

    def inside(self, x: np.ndarray) -> bool:
        """Whether state ``x`` is in :attr:`region` (always true without a region)."""
        if self.region is None:
            return True
        x0, x1, y0, y1 = self.region
        return bool(x0 <= x[0] <= x1 and y0 <= x[1] <= y1)


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
    params : dict
        The node table's kind-specific keys.
    position : array or None
        Where a fixed node is (``(x, y)`` or ``(x, y, z)``, m): the key ``position``.
    path : WaypointPath or None
        The path of a moving node (keys ``path``, ``speed``, ``loop``, ``path_start``).
    radio_range : float or None
        Metres within which it links to other nodes with a range (``docs/dynamic-topology.md``).
    joins, leaves : float or None
        When the node joins the running network and leaves it for good (``[[events]]``).
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
    position: np.ndarray | None = None
    path: "WaypointPath | None" = None
    radio_range: float | None = None
    joins: float | None = None
    leaves: float | None = None

    def is_present(self, t: float) -> bool:
        """Whether the node is in the network at ``t`` (joined and not left)."""
        return (self.joins is None or t >= self.joins) and (self.leaves is None or t < self.leaves)

    def is_active(self, t: float) -> bool:
        return self.is_present(t) and (not self.active or any(a <= t <= b for a, b in self.active))

    def position_at(self, t: float) -> np.ndarray | None:
        """``(x, y)`` at ``t``: on its path when it moves, its ``position`` otherwise (None: unknown)."""
        if self.path is not None:
            return self.path.position(t)
        return None if self.position is None else self.position[:2]


@dataclass(frozen=True)
class LinkEvent:
    """One ``[[events]]`` entry: at ``t`` a link comes up or goes down (``nodes`` the pair), or a
    node joins or leaves (``nodes`` the node)."""

    t: float
    kind: str
    nodes: tuple[str, ...]

    def __str__(self) -> str:
        if self.kind in ("join", "leave"):
            return f"{self.nodes[0]} {self.kind}s"
        return f"{self.nodes[0]} - {self.nodes[1]} {'up' if self.kind == 'link_up' else 'down'}"


@dataclass(frozen=True)
class Protection:
    """The ``[protection]`` table: the cameras' clutter model and the network's consistency test
    (``docs/clutter.md``).

    Attributes
    ----------
    enabled : bool
        ``False`` turns every protection off (cameras: the hard gate alone, whatever their
        ``clutter_model``; no consistency test): the behaviour before the protections existed.
    clutter_model : {"pda", "gate"}
        ``clutter_model`` of the camera nodes that do not set their own.
    network_check : bool
        Every node tests its neighbours' information and quarantines one that keeps failing
        (:mod:`dfusion.fusion.guard`).
    false_alarm, failures, window, release
        The test's false-alarm probability per message, quarantine after ``failures`` failed
        messages among the last ``window`` tested, release after ``release`` passes in a row
        (:class:`dfusion.fusion.guard.GuardConfig`).
    """

    enabled: bool = True
    clutter_model: str = "pda"
    network_check: bool = True
    false_alarm: float = 1e-3
    failures: int = 3
    window: int = 10
    release: int = 10

    def camera_model(self, own: str | None = None) -> str:
        """The clutter model of a camera node whose table sets ``own`` (None: not set)."""
        if not self.enabled:
            return "gate"
        return own or self.clutter_model

    def node_guard(self) -> Any:
        """The :class:`~dfusion.fusion.guard.GuardConfig` of every node (None: no test)."""
        if not (self.enabled and self.network_check):
            return None
        from dfusion.fusion.guard import GuardConfig

        return GuardConfig(self.false_alarm, self.failures, self.window, self.release)

    def describe(self) -> str:
        """One line for tables and JSON: what is on."""
        if not self.enabled:
            return "off"
        return f"cameras {self.clutter_model}, network check {'on' if self.network_check else 'off'}"


@dataclass
class Scenario:
    """A parsed, validated scenario (see ``docs/scenarios.md``).

    Attributes
    ----------
    kinds : Kinds
        The sensor kinds, policies and motion models it was loaded with (built-in and
        plug-ins).
    warnings : list of str
        Degenerate settings found while loading (also logged).
    security : SecurityOptions
        The ``[security]`` table: the network key file and mutual TLS of ``dfusion run``.
    protection : Protection
        The ``[protection]`` table (default: every protection on).
    tree : Tree
        The ``[[links]]`` as plain data (:class:`dfusion.topology.Tree`): the communication
        tree, unless the scenario's links change (:attr:`dynamic`), when they are only the
        links that exist at the start (cycles allowed); :attr:`graph` is the same as a
        networkx graph, built on first use.
    events : list of LinkEvent
        The ``[[events]]``, in time order.
    radio : LinkSpec
        The ``[radio]`` table: how links that are not in ``[[links]]`` behave (made by a
        radio range or by an event).
    """

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
    tree: Tree
    raw: dict[str, Any]
    kinds: Kinds | None = None
    warnings: list[str] = field(default_factory=list)
    security: SecurityOptions = field(default_factory=SecurityOptions)
    protection: Protection = field(default_factory=Protection)
    events: list[LinkEvent] = field(default_factory=list)
    radio: LinkSpec = field(default_factory=LinkSpec)
    #: When nodes send (``docs/dynamic-topology.md``, :mod:`dfusion.fusion.sending`): ``"event"``
    #: (news at once, rate-limited per link, plus the periodic heartbeat) or ``"periodic"``.
    sends: str = "periodic"
    #: Least seconds between two messages of a node on one link (event sends).
    min_send_interval: float = 0.05
    #: A multi-target scenario's ``[[targets]]`` (empty for a single-target scenario).
    targets: list[TargetPath] = field(default_factory=list)
    #: A multi-target scenario's ``[tracking]`` (None for a single-target scenario).
    tracking: TrackingSpec | None = None
    #: The rendezvous of a robot with a person (``meets`` of a robot's ``[[targets]]`` table).
    rendezvous: list[Rendezvous] = field(default_factory=list)

    @property
    def multi_target(self) -> bool:
        """Whether this is a multi-target scenario (``[[targets]]`` and ``[tracking]``)."""
        return self.tracking is not None

    @property
    def dynamic(self) -> bool:
        """Whether the links change at run time: events, or radio ranges (``docs/dynamic-topology.md``)."""
        return bool(self.events) or any(n.radio_range is not None for n in self.nodes.values())

    @property
    def graph(self) -> nx.Graph:
        """The tree as a networkx graph (as :func:`dfusion.topology.load_topology` returns it)."""
        graph = self.__dict__.get("_graph")
        if graph is None:
            graph = self.__dict__["_graph"] = self.tree.to_networkx()
        return graph

    def neighbors(self, name: str) -> tuple[str, ...]:
        """The tree neighbours of node ``name``, sorted (the links at the start when links change)."""
        return tuple(sorted(self.tree.neighbors(name)))

    @property
    def steps(self) -> int:
        return int(round(self.duration / self.dt))

    @property
    def base_dir(self) -> str | None:
        """Directory of the scenario file (relative paths in it start there); None for a mapping."""
        return None if self.path.startswith("<") else str(Path(self.path).parent)

    def link_spec(self, a: str, b: str) -> LinkSpec:
        """How the link ``a - b`` behaves: its ``[[links]]`` entry, else ``[radio]``."""
        return self.links.get((a, b)) or self.links.get((b, a)) or self.radio

    def outages(self) -> list[tuple[str, str, float, float]]:
        """Every outage interval as ``(a, b, start, end)``."""
        return [(a, b, s, e) for (a, b), spec in self.links.items() for s, e in spec.outages]
