"""Tests of dfusion.topology: loading, validation, tree checks, spanning trees, measures."""
from __future__ import annotations

import itertools
import logging
import random
import re
from collections import deque
from pathlib import Path

import networkx as nx
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dfusion.errors import TopologyError, ValidationError
from dfusion.topology import (
    Tree,
    check_tree,
    find_cycle,
    load_topology,
    load_tree,
    minimum_window,
    path,
    random_tree as random_recursive_tree,
    settling_rounds,
    spanning_tree,
    tree_diameter,
)

TOPOLOGIES = Path(__file__).parent.parent / "topologies"


# --------------------------------------------------------------------------- helpers


def links(*pairs: tuple[str, str], **quality: float) -> dict:
    """Topology mapping with the given links; ``quality`` maps "ab" to the quality of a-b."""
    tables = []
    for a, b in pairs:
        table = {"between": [a, b]}
        if a + b in quality:
            table["quality"] = quality[a + b]
        tables.append(table)
    return {"links": tables}


def toml_value(value: object) -> str:
    """TOML text of a string, number or bool (enough for the generated attributes)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(value)


def to_toml(graph: nx.Graph) -> str:
    """Write a graph as topology TOML text (the inverse of load_topology)."""
    lines = []
    for name, data in graph.nodes(data=True):
        lines.append("[[nodes]]")
        lines.append(f"name = {toml_value(name)}")
        lines.extend(f"{key} = {toml_value(value)}" for key, value in data.items())
    for a, b, data in graph.edges(data=True):
        lines.append("[[links]]")
        lines.append(f"between = [{toml_value(a)}, {toml_value(b)}]")
        lines.extend(f"{key} = {toml_value(value)}" for key, value in data.items())
    return "\n".join(lines) + "\n"


def bfs_distances(graph: nx.Graph, start: str) -> dict[str, int]:
    """Hop distances from ``start`` by a hand-written breadth-first search."""
    distances = {start: 0}
    queue = deque([start])
    while queue:
        node = queue.popleft()
        for neighbour in graph.adj[node]:
            if neighbour not in distances:
                distances[neighbour] = distances[node] + 1
                queue.append(neighbour)
    return distances


def brute_force_diameter(graph: nx.Graph) -> int:
    """Largest all-pairs hop distance."""
    return max(max(bfs_distances(graph, node).values()) for node in graph)


def is_spanning_tree(nodes: list[str], edges: tuple) -> bool:
    """True if ``edges`` (n-1 of them) connect all ``nodes`` without a cycle (union-find)."""
    parent = {node: node for node in nodes}

    def root(node: str) -> str:
        while parent[node] != node:
            node = parent[node]
        return node

    for a, b, _ in edges:
        ra, rb = root(a), root(b)
        if ra == rb:
            return False
        parent[ra] = rb
    return len(edges) == len(nodes) - 1


def brute_force_best_weight(graph: nx.Graph) -> float:
    """Largest total quality over all spanning trees, by enumerating edge subsets."""
    nodes = list(graph.nodes)
    edges = list(graph.edges(data="quality"))
    weights = [sum(q for *_, q in subset)
               for subset in itertools.combinations(edges, len(nodes) - 1)
               if is_spanning_tree(nodes, subset)]
    return max(weights)


def edge_set(graph: nx.Graph) -> set[frozenset]:
    return {frozenset(edge) for edge in graph.edges}


def cycle_in_message(message: str) -> list[str]:
    """Node names of the cycle named in a TopologyError message."""
    match = re.search(r"cycle (.+?);", message)
    assert match, message
    return match.group(1).split(" -> ")


def random_tree(n: int, seed: int, prefix: str = "n") -> nx.Graph:
    """Random labelled tree on nodes "n0".."n{n-1}" (uniform over labelled trees)."""
    if n == 1:
        tree = nx.Graph()
        tree.add_node(0)
    else:
        tree = nx.random_labeled_tree(n, seed=seed)
    return nx.relabel_nodes(tree, {i: f"{prefix}{i}" for i in tree.nodes})


# --------------------------------------------------------------------------- shipped files


@pytest.mark.parametrize(
    ("file", "nodes", "diameter"),
    [("chain5.toml", 5, 4), ("star5.toml", 5, 2), ("tree7.toml", 7, 4)],
)
def test_shipped_topologies_load(file: str, nodes: int, diameter: int) -> None:
    graph = load_topology(TOPOLOGIES / file)
    assert graph.number_of_nodes() == nodes
    assert graph.number_of_edges() == nodes - 1
    assert nx.is_tree(graph)
    assert tree_diameter(graph) == diameter == brute_force_diameter(graph)
    assert graph.graph["source"] == str(TOPOLOGIES / file)
    assert all(0.0 < q <= 1.0 for *_, q in graph.edges(data="quality"))


def test_shipped_chain_structure_and_attributes() -> None:
    chain = load_topology(TOPOLOGIES / "chain5.toml")
    assert path(chain, "n1", "n5") == ["n1", "n2", "n3", "n4", "n5"]
    assert all(q == 1.0 for *_, q in chain.edges(data="quality"))  # default quality
    star = load_topology(str(TOPOLOGIES / "star5.toml"))
    assert star.degree["hub"] == 4
    assert star.edges["hub", "leaf4"]["quality"] == 0.7


# --------------------------------------------------------------------------- parsing


def test_attributes_are_kept_and_link_only_nodes_added() -> None:
    data = {
        "duration": 10.0,  # scenario keys are ignored
        "nodes": [{"name": "a", "sensor": "camera", "std": 0.5}],
        "links": [{"between": ["a", "b"], "quality": 0.5, "latency": 0.1,
                   "outages": [[1.0, 2.0]]}],
    }
    graph = load_topology(data)
    assert list(graph.nodes) == ["a", "b"]
    assert graph.nodes["a"] == {"sensor": "camera", "std": 0.5}
    assert graph.nodes["b"] == {}
    assert graph.edges["a", "b"] == {"quality": 0.5, "latency": 0.1, "outages": [[1.0, 2.0]]}
    graph.edges["a", "b"]["outages"].append([3.0, 4.0])
    assert data["links"][0]["outages"] == [[1.0, 2.0]]  # no aliasing of the input


def test_single_node_is_a_tree() -> None:
    graph = load_topology({"nodes": [{"name": "solo"}]})
    assert list(graph.nodes) == ["solo"]
    assert tree_diameter(graph) == 0
    assert minimum_window(graph, max_latency=1.0, send_period=1.0,
                          max_measurement_delay=0.25) == 0.25


def test_integer_quality_is_a_float() -> None:
    graph = load_topology(links(("a", "b"), ab=1))
    assert graph.edges["a", "b"]["quality"] == 1.0
    assert isinstance(graph.edges["a", "b"]["quality"], float)


def test_source_keyword_names_a_mapping() -> None:
    with pytest.raises(TopologyError, match=r"^scenarios/x\.toml: links\[0\]"):
        load_topology(links(("a", "a")), source="scenarios/x.toml")
    with pytest.raises(TopologyError, match=r"^<dict>: links\[0\]"):
        load_topology(links(("a", "a")))


INVALID = [
    ({}, r"no nodes"),
    ({"nodes": []}, r"no nodes"),
    ({"nodes": "a"}, r"'nodes' must be an array of tables"),
    ({"links": {"between": ["a", "b"]}}, r"'links' must be an array of tables"),
    ({"nodes": ["a"]}, r"nodes\[0\] must be a table"),
    ({"nodes": [{"sensor": "camera"}]}, r"nodes\[0\]: missing 'name'"),
    ({"nodes": [{"name": ""}]}, r"nodes\[0\]: name must be a non-empty string"),
    ({"nodes": [{"name": "  "}]}, r"nodes\[0\]: name must be a non-empty string"),
    ({"nodes": [{"name": 3}]}, r"nodes\[0\]: name must be a non-empty string, got 3"),
    ({"nodes": [{"name": "a"}, {"name": "b"}, {"name": "a"}]},
     r"nodes\[2\]: duplicate node name 'a'"),
    ({"links": [{"quality": 0.5}]}, r"links\[0\]: missing 'between'"),
    ({"links": [{"between": ["a"]}]}, r"links\[0\]: 'between' must list exactly 2"),
    ({"links": [{"between": ["a", "b", "c"]}]}, r"links\[0\]: 'between' must list exactly 2"),
    ({"links": [{"between": "ab"}]}, r"links\[0\]: 'between' must list exactly 2"),
    ({"links": [{"between": ["a", ""]}]}, r"links\[0\]: node names must be non-empty strings"),
    ({"links": [{"between": ["a", 1]}]}, r"links\[0\]: node names must be non-empty strings"),
    (links(("a", "b"), ("b", "b")), r"links\[1\]: self-link b - b"),
    (links(("a", "b"), ("b", "c"), ("b", "a")),
     r"links\[2\]: duplicate link b - a \(same as links\[0\]\)"),
    (links(("a", "b"), ("a", "b")), r"links\[1\]: duplicate link a - b"),
    (links(("a", "b"), ab=0.0), r"links\[0\] \(a - b\): quality must be in \(0, 1\]"),
    (links(("a", "b"), ab=-0.5), r"links\[0\] \(a - b\): quality must be in \(0, 1\]"),
    (links(("a", "b"), ab=1.5), r"links\[0\] \(a - b\): quality must be in \(0, 1\]"),
    (links(("a", "b"), ab=float("nan")), r"links\[0\] \(a - b\): quality must be in"),
    (links(("a", "b"), ab="high"), r"links\[0\] \(a - b\): quality must be a number"),
    (links(("a", "b"), ab=True), r"links\[0\] \(a - b\): quality must be a number"),
]


@pytest.mark.parametrize(("data", "pattern"), INVALID)
def test_invalid_entries_are_rejected(data: dict, pattern: str) -> None:
    with pytest.raises(TopologyError, match=r"^<dict>: .*" + pattern) as info:
        load_topology(data)
    assert isinstance(info.value, ValueError)


def test_invalid_file_names_file_and_entry(tmp_path: Path) -> None:
    file = tmp_path / "bad.toml"
    file.write_text('[[nodes]]\nname = "a"\n[[links]]\nbetween = ["a", "b"]\nquality = 2.0\n')
    with pytest.raises(TopologyError, match=r"bad\.toml: links\[0\] \(a - b\): quality"):
        load_topology(file)


def test_toml_syntax_error_is_a_topology_error(tmp_path: Path) -> None:
    file = tmp_path / "broken.toml"
    file.write_text('[[nodes]]\nname = "a\n')
    with pytest.raises(TopologyError, match=r"broken\.toml: TOML syntax error") as info:
        load_topology(file)
    assert info.value.__cause__ is not None


def test_missing_file_and_wrong_argument_type(tmp_path: Path) -> None:
    with pytest.raises(TopologyError, match=r"absent\.toml: cannot read"):
        load_topology(tmp_path / "absent.toml")
    with pytest.raises(TopologyError, match=r"expected a path or a mapping"):
        load_topology(42)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- tree checks


def test_cycle_is_refused_and_named(tmp_path: Path) -> None:
    file = tmp_path / "ring.toml"
    file.write_text(to_toml(nx.relabel_nodes(nx.cycle_graph(4), str)) + "\n"
                    '[[links]]\nbetween = ["3", "tail"]\n')
    with pytest.raises(TopologyError, match=r"ring\.toml: not a tree: cycle ") as info:
        load_topology(file)
    cycle = cycle_in_message(str(info.value))
    assert cycle[0] == cycle[-1] and sorted(cycle[:-1]) == ["0", "1", "2", "3"]
    assert "tail" not in cycle


def test_find_cycle_returns_a_closed_walk_of_edges() -> None:
    graph = nx.Graph([("a", "b"), ("b", "c"), ("c", "d"), ("d", "b"), ("a", "e")])
    cycle = find_cycle(graph)
    assert cycle is not None and cycle[0] == cycle[-1]
    assert sorted(cycle[:-1]) == ["b", "c", "d"]
    assert all(graph.has_edge(u, v) for u, v in zip(cycle, cycle[1:]))
    assert find_cycle(nx.path_graph(4)) is None


def test_disconnected_graph_names_components() -> None:
    data = links(("a", "b"), ("c", "d"), ("d", "e"))
    data["nodes"] = [{"name": "lonely"}]
    with pytest.raises(TopologyError, match="not connected: 3 components") as info:
        load_topology(data)
    message = str(info.value)
    for part in ("{lonely}", "{a, b}", "{c, d, e}"):
        assert part in message
    with pytest.raises(TopologyError, match="not connected"):
        load_topology(data, spanning_tree=True)  # spanning tree does not help


def test_check_tree_on_graphs() -> None:
    check_tree(nx.path_graph(3))  # a tree: no error
    with pytest.raises(TopologyError, match="no nodes"):
        check_tree(nx.Graph())
    with pytest.raises(TopologyError, match="undirected simple graph"):
        check_tree(nx.DiGraph([(0, 1)]))
    with pytest.raises(TopologyError, match=r"not a tree: cycle 0 -> 1 -> 2 -> 0"):
        check_tree(nx.cycle_graph(3))
    with pytest.raises(TopologyError, match=re.escape("not connected: 2 components: {0, 1}; {2}")):
        graph = nx.path_graph(2)
        graph.add_node(2)
        check_tree(graph)


# --------------------------------------------------------------------------- spanning tree


def test_spanning_tree_option_removes_worst_link_and_warns(
        caplog: pytest.LogCaptureFixture) -> None:
    data = links(("a", "b"), ("b", "c"), ("c", "a"), ("c", "d"), ab=0.9, bc=0.3, ca=0.6)
    with pytest.raises(TopologyError, match="not a tree: cycle"):
        load_topology(data)
    with caplog.at_level(logging.WARNING, logger="dfusion.topology"):
        tree = load_topology(data, spanning_tree=True)
    assert edge_set(tree) == {frozenset("ab"), frozenset("ca"), frozenset("cd")}
    assert list(tree.nodes) == ["a", "b", "c", "d"]
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert "removed links: b - c (quality 0.3)" in warnings[0].getMessage()


def test_spanning_tree_option_on_a_tree_changes_nothing(
        caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="dfusion.topology"):
        tree = load_topology(TOPOLOGIES / "tree7.toml", spanning_tree=True)
    assert edge_set(tree) == edge_set(load_topology(TOPOLOGIES / "tree7.toml"))
    assert not caplog.records


def test_spanning_tree_keeps_attributes() -> None:
    graph = nx.Graph(source="x")
    graph.add_node("a", sensor="camera")
    graph.add_edge("a", "b", quality=0.5, latency=0.2)
    graph.add_edge("b", "c", quality=0.4)
    graph.add_edge("c", "a", quality=0.1)
    tree = spanning_tree(graph)
    assert tree.graph == {"source": "x"}
    assert tree.nodes["a"] == {"sensor": "camera"}
    assert tree.edges["a", "b"] == {"quality": 0.5, "latency": 0.2}
    assert graph.number_of_edges() == 3  # input untouched


@settings(max_examples=40, deadline=None)
@given(n=st.integers(3, 6), seed=st.integers(0, 10**6),
       qualities=st.lists(st.sampled_from([0.1, 0.25, 0.5, 0.75, 1.0]), min_size=15, max_size=15))
def test_spanning_tree_is_maximum_by_brute_force(n: int, seed: int, qualities: list[float]) -> None:
    rng = random.Random(seed)
    complete = list(itertools.combinations([f"v{i}" for i in range(n)], 2))
    tree_edges = list(random_tree(n, seed, prefix="v").edges)  # guarantees connectivity
    extra = [e for e in complete if frozenset(e) not in {frozenset(t) for t in tree_edges}]
    chosen = tree_edges + rng.sample(extra, rng.randint(0, len(extra)))
    graph = nx.Graph()
    graph.add_nodes_from(f"v{i}" for i in range(n))
    for (a, b), quality in zip(chosen, qualities):
        graph.add_edge(a, b, quality=quality)
    tree = spanning_tree(graph)
    assert nx.is_tree(tree) and set(tree.nodes) == set(graph.nodes)
    assert sum(q for *_, q in tree.edges(data="quality")) == pytest.approx(
        brute_force_best_weight(graph))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10**6))
def test_spanning_tree_ties_do_not_depend_on_order(seed: int) -> None:
    rng = random.Random(seed)
    edges = [(a, b, {"quality": rng.choice([0.5, 1.0])})
             for a, b in itertools.combinations("abcde", 2) if rng.random() < 0.7]
    edges += [("a", x, {"quality": 0.5}) for x in "bcde"]  # connected
    graph = nx.Graph(edges)
    shuffled_edges = list(graph.edges(data=True))
    rng.shuffle(shuffled_edges)
    shuffled_nodes = list(graph.nodes)
    rng.shuffle(shuffled_nodes)
    other = nx.Graph()
    other.add_nodes_from(shuffled_nodes)
    other.add_edges_from((b, a, d) if rng.random() < 0.5 else (a, b, d)
                         for a, b, d in shuffled_edges)
    assert edge_set(spanning_tree(graph)) == edge_set(spanning_tree(other))


def test_spanning_tree_tie_breaking_rule() -> None:
    # Equal qualities: the links whose sorted endpoint names compare smaller are kept.
    triangle = nx.Graph()
    triangle.add_edges_from([("c", "b"), ("b", "a"), ("c", "a")], quality=0.5)
    assert edge_set(spanning_tree(triangle)) == {frozenset("ab"), frozenset("ac")}
    # A generic graph without the weight attribute: every edge weighs 1.
    assert edge_set(spanning_tree(nx.Graph([("y", "z"), ("x", "z"), ("x", "y")]))) == {
        frozenset("xy"), frozenset("xz")}


def test_spanning_tree_rejects_non_numeric_weights() -> None:
    graph = nx.Graph([("a", "b", {"quality": "good"}), ("b", "c"), ("c", "a")])
    with pytest.raises(TopologyError, match="link a - b: quality must be a finite number"):
        spanning_tree(graph)


def test_spanning_tree_of_disconnected_graph_raises() -> None:
    graph = nx.Graph([("a", "b"), ("c", "d")])
    with pytest.raises(TopologyError, match="not connected"):
        spanning_tree(graph)


# --------------------------------------------------------------------------- measures


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 25), seed=st.integers(0, 10**6))
def test_diameter_and_paths_against_brute_force(n: int, seed: int) -> None:
    tree = random_tree(n, seed)
    assert tree_diameter(tree) == brute_force_diameter(tree)
    rng = random.Random(seed)
    a, b = rng.choice(list(tree)), rng.choice(list(tree))
    route = path(tree, a, b)
    assert route[0] == a and route[-1] == b
    assert len(route) == len(set(route)) == bfs_distances(tree, a)[b] + 1
    assert all(tree.has_edge(u, v) for u, v in zip(route, route[1:]))


def test_diameter_refuses_non_trees() -> None:
    with pytest.raises(TopologyError, match="not a tree"):
        tree_diameter(nx.cycle_graph(5))


def test_path_errors() -> None:
    chain = load_topology(TOPOLOGIES / "chain5.toml")
    assert path(chain, "n3", "n3") == ["n3"]
    with pytest.raises(TopologyError, match="unknown node 'zz'"):
        path(chain, "n1", "zz")
    with pytest.raises(TopologyError, match="no path between 'a' and 'c'"):
        path(nx.Graph([("a", "b"), ("c", "d")]), "a", "c")


def test_minimum_window_rule() -> None:
    chain = load_topology(TOPOLOGIES / "chain5.toml")
    star = load_topology(TOPOLOGIES / "star5.toml")
    assert minimum_window(chain, max_latency=0.1, send_period=0.2,
                          max_measurement_delay=0.05) == pytest.approx(4 * 0.3 + 0.05)
    assert minimum_window(star, max_latency=0.1, send_period=0.2) == pytest.approx(2 * 0.3)
    assert minimum_window(star, max_latency=0, send_period=0) == 0.0


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf"), "1", True])
def test_minimum_window_rejects_bad_times(bad: object) -> None:
    star = load_topology(TOPOLOGIES / "star5.toml")
    for kwargs in ({"max_latency": bad, "send_period": 0.1},
                   {"max_latency": 0.1, "send_period": bad},
                   {"max_latency": 0.1, "send_period": 0.1, "max_measurement_delay": bad}):
        with pytest.raises(ValidationError):
            minimum_window(star, **kwargs)  # type: ignore[arg-type]


def test_minimum_window_refuses_cycles() -> None:
    with pytest.raises(TopologyError, match="cycle"):
        minimum_window(nx.cycle_graph(3), max_latency=0.1, send_period=0.1)


# --------------------------------------------------------------------------- round trip


@pytest.fixture(scope="module")
def scratch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("roundtrip") / "tree.toml"


qualities = st.floats(min_value=0.0, max_value=1.0, exclude_min=True, allow_nan=False)
labels = st.text(alphabet="abcxyz_-0123456789 é", min_size=1, max_size=6).filter(str.strip)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(n=st.integers(1, 15), seed=st.integers(0, 10**6), data=st.data())
def test_random_trees_round_trip_and_any_extra_edge_closes_a_cycle(
        scratch: Path, n: int, seed: int, data: st.DataObject) -> None:
    tree = random_tree(n, seed)
    for node in tree:
        tree.nodes[node]["sensor"] = data.draw(labels)
        tree.nodes[node]["rate"] = data.draw(st.integers(1, 100))
    for a, b in tree.edges:
        tree.edges[a, b]["quality"] = data.draw(qualities)
        tree.edges[a, b]["latency"] = data.draw(st.floats(0, 1, allow_nan=False))
    scratch.write_text(to_toml(tree), encoding="utf-8")

    loaded = load_topology(scratch)
    assert list(loaded.nodes(data=True)) == list(tree.nodes(data=True))
    assert {frozenset((a, b)): d for a, b, d in loaded.edges(data=True)} == {
        frozenset((a, b)): d for a, b, d in tree.edges(data=True)}

    missing = [e for e in itertools.combinations(tree.nodes, 2) if not tree.has_edge(*e)]
    if not missing:  # n <= 2: every pair is already linked
        assert n <= 2
        return
    a, b = data.draw(st.sampled_from(missing))
    cyclic = tree.copy()
    cyclic.add_edge(a, b, quality=0.5)
    scratch.write_text(to_toml(cyclic), encoding="utf-8")
    with pytest.raises(TopologyError, match="not a tree: cycle") as info:
        load_topology(scratch)
    cycle = cycle_in_message(str(info.value))
    assert cycle[0] == cycle[-1]
    assert set(cycle[:-1]) == set(nx.shortest_path(tree, a, b))  # the unique cycle
    assert any({u, v} == {a, b} for u, v in zip(cycle, cycle[1:]))  # contains the new edge


# --------------------------------------------------------------------------- the lean Tree


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 40), seed=st.integers(0, 10**6))
def test_lean_tree_equals_the_networkx_graph(n: int, seed: int) -> None:
    """load_tree (no networkx) gives the nodes, links, attributes, neighbours and diameter of
    load_topology's graph; the diameter against brute force over every pair."""
    graph = random_tree(n, seed)
    for a, b in graph.edges:
        graph.edges[a, b]["latency"] = 0.01
    data = {"nodes": [{"name": v, "rate": 1.0} for v in graph],
            "links": [{"between": [a, b], "latency": 0.01} for a, b in graph.edges]}
    tree = load_tree(data, source="x")
    reference = load_topology(data, source="x")
    assert isinstance(tree, Tree) and tree.source == "x"
    assert tree.nodes == dict(reference.nodes(data=True))
    assert {frozenset(e): d for e, d in tree.edges.items()} == {
        frozenset((a, b)): d for a, b, d in reference.edges(data=True)}
    for v in graph:
        assert sorted(tree.neighbors(v)) == sorted(reference.neighbors(v))
    assert tree_diameter(tree) == brute_force_diameter(graph) == tree_diameter(reference)
    assert settling_rounds(tree) == settling_rounds(reference)
    back = tree.to_networkx()
    assert nx.utils.graphs_equal(back, reference)
    assert Tree.from_networkx(back).edges == tree.edges


@pytest.mark.parametrize("data", [
    links(("a", "b"), ("b", "c"), ("c", "a")),
    links(("a", "b"), ("c", "d")),
    {"nodes": [{"name": "a"}, {"name": "a"}]},
    {"links": [{"between": ["a"]}]},
])
def test_lean_tree_refuses_what_load_topology_refuses_with_the_same_message(data: dict) -> None:
    with pytest.raises(TopologyError) as lean:
        load_tree(data, source="s")
    with pytest.raises(TopologyError) as full:
        load_topology(data, source="s")
    assert str(lean.value) == str(full.value)


def test_lean_tree_with_spanning_tree_removes_the_worst_link() -> None:
    data = links(("a", "b"), ("b", "c"), ("c", "a"), ab=0.9, bc=0.8, ca=0.1)
    tree = load_tree(data, spanning_tree=True)
    assert {frozenset(e) for e in tree.edges} == {frozenset("ab"), frozenset("bc")}


def test_random_recursive_tree_is_a_reproducible_tree() -> None:
    edges = random_recursive_tree(128, seed=3)
    graph = nx.Graph(edges)
    assert nx.is_tree(graph) and graph.number_of_nodes() == 128
    assert all(int(a[1:]) < int(b[1:]) for a, b in edges)   # node k links to an earlier node
    assert random_recursive_tree(128, seed=3) == edges != random_recursive_tree(128, seed=4)
    assert 8 <= nx.diameter(graph) <= 30
    with pytest.raises(ValidationError):
        random_recursive_tree(0, seed=1)
