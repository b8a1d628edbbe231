"""Communication topologies: load, validate and measure the tree of fusion nodes.

Channel-filter fusion is exact only on trees (``docs/topology.md``): on a graph
with cycles the information two neighbours share cannot be tracked locally,
so the same measurement would be counted more than once. This module reads a
topology (or scenario) file, checks that its communication graph is a
connected tree and, on explicit request only, reduces a connected graph with
cycles to its maximum spanning tree weighted by link quality.

File format (TOML, read with :mod:`tomllib`)::

    [[nodes]]
    name = "camera1"          # required, a non-empty string; other keys become node attributes

    [[links]]
    between = ["camera1", "robot1"]   # required, exactly two node names
    quality = 0.9                     # optional, in (0, 1], default 1.0
    latency = 0.05                    # any other key becomes an edge attribute

Nodes that appear only in ``links`` are added without attributes. Other
top-level keys (``duration``, ``dt``, ``seed``, ``window``, ``[target]`` of a
scenario file) are ignored here, so every scenario file is a topology file.

Public API: :func:`load_topology`, :func:`check_tree`, :func:`find_cycle`,
:func:`spanning_tree`, :func:`tree_diameter`, :func:`path`,
:func:`minimum_window`, :func:`settling_rounds`, :func:`random_tree`, the lean
:class:`Tree` with :func:`load_tree`, and :func:`radio_links` (the links a radio range allows,
for topologies that change at run time: ``docs/dynamic-topology.md``). Every input this module rejects raises
:class:`~dfusion.errors.TopologyError` (a :class:`ValueError`), except bad
numbers given to :func:`minimum_window`, which raise
:class:`~dfusion.errors.ValidationError` (also a :class:`ValueError`).
"""
from __future__ import annotations

import copy
import logging
import math
import os
import tomllib
from collections import deque
from collections.abc import Hashable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dfusion.errors import TopologyError, ValidationError

if TYPE_CHECKING:   # networkx is imported where a graph algorithm needs it (a node program needs none)
    import networkx as nx

__all__ = [
    "DEFAULT_QUALITY",
    "Tree",
    "load_tree",
    "random_tree",
    "load_topology",
    "check_tree",
    "find_cycle",
    "spanning_tree",
    "tree_diameter",
    "path",
    "minimum_window",
    "settling_rounds",
    "radio_links",
]

logger = logging.getLogger(__name__)

#: Quality of a link that does not state one.
DEFAULT_QUALITY = 1.0

#: Name used in messages when :func:`load_topology` is given a mapping.
_DICT_SOURCE = "<dict>"


def _networkx():
    import networkx

    return networkx


class Tree:
    """A communication tree as plain data, without networkx: what a node program needs.

    ``nodes`` maps each name to its attributes (the other keys of its node table),
    ``edges`` each link ``(a, b)`` (in file order) to its attributes (``quality`` and
    any other link key), ``source`` names the file. :func:`load_tree` builds one and
    checks that it is a connected tree; :meth:`to_networkx` gives the
    :func:`load_topology` graph for graph algorithms.
    """

    def __init__(self, source: str = "") -> None:
        self.source = source
        self.nodes: dict[str, dict[str, Any]] = {}
        self.edges: dict[tuple[str, str], dict[str, Any]] = {}
        self._adj: dict[str, list[str]] = {}

    # the part of networkx's Graph API that loading uses
    def add_node(self, name: str, **attributes: Any) -> None:
        self.nodes.setdefault(name, {}).update(attributes)
        self._adj.setdefault(name, [])

    def add_edge(self, a: str, b: str, **attributes: Any) -> None:
        for end in (a, b):
            self.add_node(end)
        self.edges[(a, b)] = attributes
        self._adj[a].append(b)
        self._adj[b].append(a)

    def __contains__(self, name: object) -> bool:
        return name in self.nodes

    def __iter__(self) -> Iterator[str]:
        return iter(self.nodes)

    def __len__(self) -> int:
        return len(self.nodes)

    def number_of_nodes(self) -> int:
        return len(self.nodes)

    def number_of_edges(self) -> int:
        return len(self.edges)

    def has_edge(self, a: str, b: str) -> bool:
        return (a, b) in self.edges or (b, a) in self.edges

    def neighbors(self, name: str) -> tuple[str, ...]:
        """The nodes linked to ``name``, in file order."""
        return tuple(self._adj[name])

    def distances(self, start: str) -> dict[str, int]:
        """Hops from ``start`` to every node it reaches (breadth-first)."""
        dist = {start: 0}
        queue = deque([start])
        while queue:
            u = queue.popleft()
            for v in self._adj[u]:
                if v not in dist:
                    dist[v] = dist[u] + 1
                    queue.append(v)
        return dist

    def is_tree(self) -> bool:
        """Connected, with one link fewer than nodes."""
        return (len(self.nodes) > 0 and len(self.edges) == len(self.nodes) - 1
                and len(self.distances(next(iter(self.nodes)))) == len(self.nodes))

    def diameter(self) -> int:
        """Longest shortest path in hops: two breadth-first sweeps (a tree)."""
        first = self.distances(next(iter(self.nodes)))
        far = max(first, key=first.__getitem__)
        return max(self.distances(far).values())

    def to_networkx(self) -> nx.Graph:
        """The same tree as the graph :func:`load_topology` returns."""
        graph = _networkx().Graph(source=self.source)
        for name, attributes in self.nodes.items():
            graph.add_node(name, **attributes)
        for (a, b), attributes in self.edges.items():
            graph.add_edge(a, b, **attributes)
        return graph

    @classmethod
    def from_networkx(cls, graph: nx.Graph) -> Tree:
        """The tree of a graph of :func:`load_topology` (which checked it)."""
        tree = cls(graph.graph.get("source", ""))
        for name, attributes in graph.nodes(data=True):
            tree.add_node(name, **attributes)
        for a, b, attributes in graph.edges(data=True):
            tree.add_edge(a, b, **attributes)
        return tree

    def __repr__(self) -> str:
        return f"Tree({self.source!r}, {len(self.nodes)} nodes)"


def load_tree(
    path_or_dict: str | os.PathLike[str] | Mapping[str, Any],
    *,
    spanning_tree: bool = False,
    source: str | None = None,
    require_tree: bool = True,
) -> Tree:
    """:func:`load_topology` as a :class:`Tree`: the same checks and errors, networkx only
    for a spanning tree or to name what is wrong with a graph that is not a tree.
    ``require_tree=False``: any graph of valid entries (the links that exist at the start of
    a topology that changes at run time; cycles and several components allowed)."""
    data, source = _read(path_or_dict, source)
    if not require_tree:
        return _build_graph(data, source, Tree(source))
    if spanning_tree:
        return Tree.from_networkx(load_topology(data, spanning_tree=True, source=source))
    tree = _build_graph(data, source, Tree(source))
    if not tree.is_tree():
        check_tree(tree.to_networkx())   # raises, naming the components or a cycle
        raise TopologyError(f"{source}: not a tree")   # not reached
    return tree


def random_tree(n: int, seed: int, prefix: str = "n") -> list[tuple[str, str]]:
    """The links of a random recursive tree of ``n`` nodes ``{prefix}0 .. {prefix}{n-1}``.

    Node ``k`` links to a node drawn uniformly among ``0 .. k-1`` (``numpy.random.default_rng(seed)``),
    so the tree is reproducible from ``seed``; its expected depth grows as ``e ln n``
    (Devroye, "Branching processes in the analysis of the heights of trees", Acta
    Informatica 24, 1987): diameters of 13-17 hops at 128 nodes.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValidationError(f"a tree needs a positive number of nodes, got {n!r}")
    import numpy as np

    rng = np.random.default_rng(seed)
    return [(f"{prefix}{int(rng.integers(k))}", f"{prefix}{k}") for k in range(1, n)]


# --------------------------------------------------------------------------- loading


def load_topology(
    path_or_dict: str | os.PathLike[str] | Mapping[str, Any],
    *,
    spanning_tree: bool = False,
    source: str | None = None,
    require_tree: bool = True,
) -> nx.Graph:
    """Read, validate and return a communication tree.

    Parameters
    ----------
    path_or_dict
        Path of a TOML topology or scenario file, or the mapping such a file
        parses to (for example a scenario loaded elsewhere).
    spanning_tree
        If False (default) a graph with cycles is refused. If True a connected
        graph with cycles is reduced to its maximum spanning tree weighted by
        link quality and a warning lists the links removed. A disconnected
        graph is refused either way.
    source
        Name used in error messages; defaults to the path, or ``"<dict>"``.
    require_tree
        If False, any graph of valid entries is returned (cycles, several components):
        the links of a topology that changes at run time, where the tree rule of
        :mod:`dfusion.fusion.tree` keeps the fusion links a tree.

    Returns
    -------
    networkx.Graph
        Nodes are the node names (with the other keys of the node tables as
        attributes), edges the links (with ``quality`` and any other link keys
        as attributes). ``graph.graph["source"]`` holds the source name.

    Raises
    ------
    TopologyError
        Unreadable file, TOML syntax error, invalid entry, a cycle (unless
        ``spanning_tree``) or a disconnected graph. The message names the
        source and the offending entry, cycle or components.
    """
    data, source = _read(path_or_dict, source)
    graph = _build_graph(data, source)
    if not require_tree:
        return graph
    if spanning_tree:
        graph = _maximum_spanning_tree(graph)
    check_tree(graph)
    logger.debug(
        "%s: loaded a tree of %d nodes and %d links",
        source, graph.number_of_nodes(), graph.number_of_edges(),
    )
    return graph


def _read(path_or_dict: str | os.PathLike[str] | Mapping[str, Any],
          source: str | None) -> tuple[Mapping[str, Any], str]:
    """Return the parsed mapping and the source name used in messages."""
    if isinstance(path_or_dict, Mapping):
        return path_or_dict, source or _DICT_SOURCE
    if not isinstance(path_or_dict, (str, os.PathLike)):
        raise TopologyError(
            f"expected a path or a mapping, got {type(path_or_dict).__name__}")
    file = Path(path_or_dict)
    source = source or str(file)
    try:
        with file.open("rb") as handle:
            return tomllib.load(handle), source
    except tomllib.TOMLDecodeError as exc:
        raise TopologyError(f"{source}: TOML syntax error: {exc}") from exc
    except OSError as exc:
        raise TopologyError(f"{source}: cannot read: {exc}") from exc


def _build_graph(data: Mapping[str, Any], source: str, graph: Any = None) -> Any:
    """Validate the ``nodes`` and ``links`` entries and build the graph (a new networkx one, or ``graph``)."""
    if graph is None:
        graph = _networkx().Graph(source=source)
    for index, table in enumerate(_tables(data, "nodes", source)):
        _add_node(graph, table, index, source)
    seen: dict[frozenset[str], int] = {}
    for index, table in enumerate(_tables(data, "links", source)):
        _add_link(graph, table, index, seen, source)
    if graph.number_of_nodes() == 0:
        raise TopologyError(f"{source}: no nodes: expected [[nodes]] or [[links]] tables")
    return graph


def _tables(data: Mapping[str, Any], key: str, source: str) -> list[Mapping[str, Any]]:
    """Return ``data[key]`` checked to be an array of tables (empty if absent)."""
    if not isinstance(data, Mapping):
        raise TopologyError(f"{source}: expected a table at the top level")
    value = data.get(key, [])
    if not isinstance(value, list):
        raise TopologyError(
            f"{source}: '{key}' must be an array of tables ([[{key}]]), "
            f"got {type(value).__name__}")
    for index, table in enumerate(value):
        if not isinstance(table, Mapping):
            raise TopologyError(
                f"{source}: {key}[{index}] must be a table, got {table!r}")
    return value


def _is_name(value: object) -> bool:
    """True for a non-empty, non-blank string."""
    return isinstance(value, str) and value.strip() != ""


def _attributes(table: Mapping[str, Any], exclude: str) -> dict[str, Any]:
    """Copy of ``table`` without the key ``exclude``."""
    return {key: copy.deepcopy(value) for key, value in table.items() if key != exclude}


def _add_node(graph: nx.Graph, table: Mapping[str, Any], index: int, source: str) -> None:
    """Add the node of ``nodes[index]`` with its attributes."""
    where = f"{source}: nodes[{index}]"
    if "name" not in table:
        raise TopologyError(f"{where}: missing 'name' in {dict(table)!r}")
    name = table["name"]
    if not _is_name(name):
        raise TopologyError(f"{where}: name must be a non-empty string, got {name!r}")
    if name in graph:
        raise TopologyError(f"{where}: duplicate node name {name!r}")
    graph.add_node(name, **_attributes(table, "name"))


def _add_link(graph: nx.Graph, table: Mapping[str, Any], index: int,
              seen: dict[frozenset[str], int], source: str) -> None:
    """Add the edge of ``links[index]``; ``seen`` maps node pairs to link indices."""
    where = f"{source}: links[{index}]"
    a, b = _endpoints(table, where)
    pair = frozenset((a, b))
    if pair in seen:
        raise TopologyError(
            f"{where}: duplicate link {a} - {b} (same as links[{seen[pair]}])")
    seen[pair] = index
    attributes = _attributes(table, "between")
    attributes["quality"] = _quality(table, f"{where} ({a} - {b})")
    graph.add_edge(a, b, **attributes)


def _endpoints(table: Mapping[str, Any], where: str) -> tuple[str, str]:
    """Return the two node names of a link table."""
    if "between" not in table:
        raise TopologyError(f"{where}: missing 'between' in {dict(table)!r}")
    between = table["between"]
    if not isinstance(between, Sequence) or isinstance(between, str) or len(between) != 2:
        raise TopologyError(
            f"{where}: 'between' must list exactly 2 node names, got {between!r}")
    a, b = between
    for name in (a, b):
        if not _is_name(name):
            raise TopologyError(
                f"{where}: node names must be non-empty strings, got {between!r}")
    if a == b:
        raise TopologyError(f"{where}: self-link {a} - {b}")
    return a, b


def _quality(table: Mapping[str, Any], where: str) -> float:
    """Return the link quality as a float in (0, 1]."""
    quality = table.get("quality", DEFAULT_QUALITY)
    if isinstance(quality, bool) or not isinstance(quality, (int, float)):
        raise TopologyError(f"{where}: quality must be a number in (0, 1], got {quality!r}")
    if not 0.0 < quality <= 1.0:  # also rejects NaN
        raise TopologyError(f"{where}: quality must be in (0, 1], got {quality!r}")
    return float(quality)


# --------------------------------------------------------------------------- tree checks


def _source(graph: nx.Graph) -> str:
    """Prefix for messages about ``graph``."""
    source = graph.graph.get("source")
    return f"{source}: " if source else ""


def _check_simple(graph: nx.Graph) -> None:
    """Refuse directed graphs and multigraphs."""
    if graph.is_directed() or graph.is_multigraph():
        raise TopologyError(
            f"{_source(graph)}expected an undirected simple graph, got {type(graph).__name__}")


def _check_connected(graph: nx.Graph) -> None:
    """Raise TopologyError listing the connected components unless ``graph`` is connected."""
    prefix = _source(graph)
    if graph.number_of_nodes() == 0:
        raise TopologyError(f"{prefix}the graph has no nodes")
    components = list(_networkx().connected_components(graph))
    if len(components) > 1:
        listed = "; ".join(
            "{" + ", ".join(sorted(map(str, part))) + "}" for part in components)
        raise TopologyError(
            f"{prefix}not connected: {len(components)} components: {listed}")


def find_cycle(graph: nx.Graph) -> list[Hashable] | None:
    """Return one cycle of ``graph`` as a closed node list ``[a, b, c, a]``, or None."""
    nx = _networkx()
    try:
        edges = nx.find_cycle(graph)
    except nx.NetworkXNoCycle:
        return None
    return [edges[0][0]] + [v for _, v in edges]


def check_tree(graph: nx.Graph) -> None:
    """Raise :class:`TopologyError` unless ``graph`` is a connected tree.

    The message lists the connected components of a disconnected graph, or
    names one cycle (``"not a tree: cycle a -> b -> c -> a"``).
    """
    _check_simple(graph)
    _check_connected(graph)
    cycle = find_cycle(graph)
    if cycle is not None:
        raise TopologyError(
            f"{_source(graph)}not a tree: cycle {' -> '.join(map(str, cycle))}; "
            "channel-filter fusion is exact only on trees "
            "(to fuse over the maximum spanning tree, set spanning_tree = true at the top of the scenario file; "
            "from Python: load_topology(..., spanning_tree=True))")


def _canonical(u: Hashable, v: Hashable) -> tuple[str, str]:
    """Order-independent sort key of an edge, used to break weight ties."""
    a, b = sorted((str(u), str(v)))
    return a, b


def _edge_weight(graph: nx.Graph, u: Hashable, v: Hashable, weight: str) -> float:
    """Weight of edge u-v (1 if absent), checked to be a finite number."""
    value = graph.edges[u, v].get(weight, 1)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise TopologyError(
            f"{_source(graph)}link {u} - {v}: {weight} must be a finite number, got {value!r}")
    return float(value)


def _ranked(graph: nx.Graph, weight: str) -> nx.Graph:
    """Copy of the topology whose edges weigh their unique rank (higher is better).

    Edges are ordered by ``weight`` (larger first), ties by sorted endpoint
    names, so the maximum spanning tree of the ranked graph is unique and
    does not depend on the insertion order of nodes or edges.
    """
    order = sorted(graph.edges,
                   key=lambda e: (-_edge_weight(graph, *e, weight), _canonical(*e)))
    ranked = _networkx().Graph()
    ranked.add_nodes_from(graph.nodes)
    ranked.add_weighted_edges_from(
        ((u, v, len(order) - i) for i, (u, v) in enumerate(order)), weight="rank")
    return ranked


def spanning_tree(graph: nx.Graph, weight: str = "quality") -> nx.Graph:
    """Return the maximum spanning tree of a connected graph, weighted by ``weight``.

    Edges without the attribute weigh 1. Ties are broken deterministically,
    independent of the order of nodes and links: among equal weights the edge
    whose sorted endpoint names compare smaller is preferred. The result is a
    new graph with the same graph, node and edge attributes and the same node
    and edge order, minus the removed edges; if any are removed a warning
    lists them. A disconnected graph raises :class:`TopologyError`.
    """
    _check_simple(graph)
    _check_connected(graph)
    kept = _networkx().maximum_spanning_tree(_ranked(graph, weight), weight="rank")
    removed = [(u, v) for u, v in graph.edges if not kept.has_edge(u, v)]
    tree = graph.copy()
    tree.remove_edges_from(removed)
    if removed:
        logger.warning(
            "%sgraph has cycles: fusing over its maximum spanning tree by %s; removed links: %s",
            _source(graph), weight, ", ".join(
                f"{u} - {v} ({weight} {graph.edges[u, v].get(weight, 1)})" for u, v in removed))
    return tree


#: Alias used by :func:`load_topology`, whose ``spanning_tree`` keyword shadows the function.
_maximum_spanning_tree = spanning_tree


# --------------------------------------------------------------------------- measures


def tree_diameter(graph: nx.Graph) -> int:
    """Longest shortest path of a tree, in hops (0 for a single node).

    Computed exactly by two breadth-first sweeps (valid on trees only); the
    graph is checked with :func:`check_tree` first (a :class:`Tree` was checked when loaded).
    """
    if isinstance(graph, Tree):
        return graph.diameter()
    check_tree(graph)
    start = next(iter(graph.nodes))
    far = _farthest(graph, start)[0]
    return _farthest(graph, far)[1]


def _farthest(graph: nx.Graph, start: Hashable) -> tuple[Hashable, int]:
    """Node farthest from ``start`` and its distance in hops."""
    distances = _networkx().single_source_shortest_path_length(graph, start)
    node = max(distances, key=distances.__getitem__)
    return node, distances[node]


def path(graph: nx.Graph, a: Hashable, b: Hashable) -> list[Hashable]:
    """Nodes on the path from ``a`` to ``b``, both included (unique on a tree).

    On a graph that is not a tree a shortest path is returned. Raises
    :class:`TopologyError` if a node is unknown or ``b`` is unreachable.
    """
    for node in (a, b):
        if node not in graph:
            raise TopologyError(f"{_source(graph)}unknown node {node!r}")
    nx = _networkx()
    try:
        return nx.shortest_path(graph, a, b)
    except nx.NetworkXNoPath as exc:
        raise TopologyError(f"{_source(graph)}no path between {a!r} and {b!r}") from exc


def _non_negative(name: str, value: float) -> float:
    """Return ``value`` as a float, checked finite and >= 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValidationError(f"{name} must be a number, got {value!r}")
    if not math.isfinite(value) or value < 0:
        raise ValidationError(f"{name} must be finite and >= 0, got {value!r}")
    return float(value)


def settling_rounds(graph: nx.Graph) -> int:
    """Lossless message rounds after which every node holds every other node's information:
    ``diameter + 2``.

    In each round every node sends one message to every neighbour and every message is
    delivered. Information crosses one link per round, so ``diameter`` rounds carry it
    across the tree; what a lost message carried is sent again once an acknowledgement
    shows the loss, which takes one round for the acknowledgement and one for the resend
    (:mod:`dfusion.fusion.channel`).
    """
    return (tree_diameter(graph) if graph.number_of_nodes() > 1 else 0) + 2


def minimum_window(
    graph: nx.Graph,
    *,
    max_latency: float,
    send_period: float,
    max_measurement_delay: float = 0.0,
) -> float:
    """Shortest delayed-state window (seconds) for which fusion on ``graph`` is exact.

    ``window >= diameter * (max_latency + send_period) + max_measurement_delay``

    A measurement taken at time ``t`` reaches its node at most
    ``max_measurement_delay`` later; each hop then waits at most one
    ``send_period`` for the next message and ``max_latency`` for delivery, and
    the farthest node is ``diameter`` hops away. States must stay in every
    window until that information has reached every node, otherwise
    marginalization makes the fused estimate inexact (``docs/background.md#2-fusion-on-a-tree``).

    Raises :class:`TopologyError` if ``graph`` is not a tree and
    :class:`ValidationError` for negative or non-finite times.
    """
    latency = _non_negative("max_latency", max_latency)
    period = _non_negative("send_period", send_period)
    delay = _non_negative("max_measurement_delay", max_measurement_delay)
    return tree_diameter(graph) * (latency + period) + delay



def radio_links(positions: Mapping[str, Sequence[float]], ranges: Mapping[str, float]) -> set[tuple[str, str]]:
    """The links a radio range allows: pairs ``(a, b)`` (``a < b``) of nodes of ``ranges`` whose
    positions are at most ``min(range_a, range_b)`` apart (each end must hear the other).

    ``positions`` maps names to ``(x, y)`` (or ``(x, y, z)``: the distance is taken in the
    plane); a node without a position or a range takes no part. A simulator passes the true
    positions; a node process may pass its own estimates of where the nodes are.
    """
    names = sorted(n for n in ranges if n in positions)
    xy = {n: (float(positions[n][0]), float(positions[n][1])) for n in names}
    out = set()
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            if math.hypot(xy[a][0] - xy[b][0], xy[a][1] - xy[b][1]) <= min(ranges[a], ranges[b]):
                out.add((a, b))
    return out
