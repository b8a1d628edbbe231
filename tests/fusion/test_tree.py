"""The tree rule (dfusion.fusion.tree) on its own: epochs, adoption, link breaks, restarts,
and, over random graphs and random message orders, parent pointers that never form a
cycle and a rule that settles on a spanning tree of every component."""
from __future__ import annotations

import itertools

import networkx as nx
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dfusion.fusion.tree import (
    JOIN_TERM,
    START_TERM,
    SpanningTree,
    TreeEpoch,
    forest_settled,
    initial_parents,
    tree_components,
)


def test_epochs_are_ordered_by_term_then_smaller_root():
    assert TreeEpoch(2, "z") > TreeEpoch(1, "a")
    assert TreeEpoch(1, "a") > TreeEpoch(1, "b")
    assert TreeEpoch(1, "a") == TreeEpoch(1, "a")
    assert sorted([TreeEpoch(1, "b"), TreeEpoch(3, "c"), TreeEpoch(1, "a")])[-1] == TreeEpoch(3, "c")
    assert max(TreeEpoch(JOIN_TERM, "a"), TreeEpoch(START_TERM, "z")) == TreeEpoch(START_TERM, "z")
    for bad in ((-1, "a"), (1, ""), (True, "a"), (1.0, "a")):
        with pytest.raises(ValueError):
            TreeEpoch(*bad)


def test_a_node_adopts_a_newer_epoch_from_the_first_neighbour_it_hears_it_from():
    t = SpanningTree("b", ["a", "c"])
    assert t.epoch == TreeEpoch(JOIN_TERM, "b") and t.parent is None
    e = TreeEpoch(1, "a")
    change = t.heard_from("c", e, "a")
    assert change.new_epoch and t.epoch == e and t.parent == "c"
    assert t.tree_links() == {"c"} and change.gained == {"c"}
    # the same epoch from another neighbour: no change of parent
    assert not t.heard_from("a", e, None)
    assert t.parent == "c"
    # a neighbour that names b as its parent in b's epoch is a child
    t.link_up("d")
    change = t.heard_from("d", e, "b")
    assert change.gained == {"d"} and t.children() == {"d"}
    # an older epoch changes nothing
    assert not t.heard_from("a", TreeEpoch(0, "a"), None)


def test_losing_the_parent_starts_a_newer_epoch_losing_a_child_ends_that_link():
    e = TreeEpoch(3, "a")
    t = SpanningTree("b", ["a", "c", "d"], epoch=e, parent="a",
                     known={"a": (e, None), "c": (e, "b"), "d": (TreeEpoch(5, "x"), "y")})
    assert t.tree_links() == {"a", "c"} and t.max_term == 5
    change = t.link_down("c")
    assert change.lost == {"c"} and not change.new_epoch and t.epoch == e
    assert not t.link_down("zz")      # a link that did not exist
    change = t.link_down("a")
    assert change.new_epoch and t.epoch == TreeEpoch(6, "b") and t.parent is None
    assert change.lost == {"a"} and t.tree_links() == set()
    assert t.epochs_started == 1


def test_a_non_tree_link_breaking_changes_nothing():
    e = TreeEpoch(1, "a")
    t = SpanningTree("c", ["a", "b"], epoch=e, parent="a", known={"a": (e, None), "b": (e, "a")})
    assert t.tree_links() == {"a"}
    assert not t.link_down("b")
    assert t.epoch == e and t.parent == "a"


def test_stale_messages_are_ignored_and_a_restart_is_forgotten():
    e1, e2 = TreeEpoch(1, "a"), TreeEpoch(2, "c")
    t = SpanningTree("b", ["a", "c"], epoch=e1, parent="a", known={"a": (e1, None), "c": (e1, "b")})
    assert t.heard_from("c", e2, None).new_epoch and t.parent == "c"
    # c's older message, overtaken on the way: ignored, c is not a child of b
    assert not t.heard_from("c", e1, "b")
    assert t.heard["c"] == (e2, None)
    # c restarts: b's parent is gone, b starts a newer epoch; c is still linked
    change = t.forget("c")
    assert change.new_epoch and t.epoch == TreeEpoch(3, "b") and "c" in t.links
    # the restarted c joins: it may now say anything newer than nothing
    assert not t.heard_from("c", TreeEpoch(0, "c"), None)


def test_a_configured_start_is_checked():
    e = TreeEpoch(1, "a")
    with pytest.raises(ValueError):
        SpanningTree("b", ["a"], epoch=e)              # not the root and no parent
    with pytest.raises(ValueError):
        SpanningTree("b", ["a"], epoch=e, parent="c")  # the parent is not a link
    with pytest.raises(ValueError):
        SpanningTree("a", ["a"])


def test_initial_parents_of_a_tree_is_the_tree_and_of_a_graph_a_spanning_tree_per_component():
    g = nx.random_labeled_tree(12, seed=3)
    g = nx.relabel_nodes(g, {i: f"n{i:02d}" for i in g})
    start = initial_parents(g.nodes, g.edges)
    edges = {frozenset((n, p)) for n, (_, p) in start.items() if p is not None}
    assert edges == {frozenset(e) for e in g.edges}
    assert {e for e, _ in start.values()} == {TreeEpoch(START_TERM, "n00")}
    # two components with cycles
    links = [("a", "b"), ("b", "c"), ("c", "a"), ("x", "y"), ("y", "z"), ("z", "x")]
    start = initial_parents("abcxyz", links)
    assert start["a"] == (TreeEpoch(1, "a"), None) and start["x"] == (TreeEpoch(1, "x"), None)
    assert start["c"][1] == "a" and start["z"][1] == "x"
    assert tree_components(links, "abcxyz") == [{"a", "b", "c"}, {"x", "y", "z"}]


def run_rule(names, events, rng_order):
    """Run the pure rule: ``events`` is a list of ('up'|'down'|'round', a, b); a round delivers every
    node's state to every linked neighbour in the order ``rng_order`` picks. Checks, after every
    delivery, that the parent pointers of every epoch form no cycle."""
    trees = {n: SpanningTree(n) for n in names}
    links: set[tuple[str, str]] = set()

    def check_acyclic():
        for n, t in trees.items():
            seen, cur = set(), n
            while cur is not None:
                assert cur not in seen, f"cycle of parents through {cur}"
                seen.add(cur)
                p = trees[cur].parent
                # a parent pointer only counts within the same epoch (a stale pointer ends the chain)
                if p is None or trees[p].epoch != trees[cur].epoch:
                    break
                cur = p

    for kind, a, b in events:
        if kind == "up" and (a, b) not in links:
            links.add((a, b))
            trees[a].link_up(b)
            trees[b].link_up(a)
        elif kind == "down" and (a, b) in links:
            links.discard((a, b))
            trees[a].link_down(b)
            trees[b].link_down(a)
        elif kind == "round":
            msgs = [(n, j, trees[n].epoch, trees[n].parent) for n in names for j in sorted(trees[n].links)]
            for i in rng_order(len(msgs)):
                n, j, e, p = msgs[i]
                if j in trees[n].links and n in trees[j].links:
                    trees[j].heard_from(n, e, p)
                    check_acyclic()
    return trees, links


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), n=st.integers(2, 8))
def test_parents_never_form_a_cycle_and_the_rule_settles_on_a_spanning_tree(data, n):
    names = [f"n{i}" for i in range(n)]
    pairs = list(itertools.combinations(names, 2))
    change = st.tuples(st.sampled_from(["up", "down"]), st.sampled_from(pairs)).map(lambda e: (e[0], *e[1]))
    events = data.draw(st.lists(st.one_of(change, st.just(("round", "", ""))), min_size=1, max_size=40))

    def order(k):
        return data.draw(st.permutations(range(k))) if k else []

    trees, links = run_rule(names, events, order)
    # then lossless rounds in a fixed order: the rule settles within a few rounds per node
    for r in range(3 * n + 3):
        if forest_settled({x: t.state() for x, t in trees.items()}, links)[0]:
            break
        run_rule_round(trees, names)
    ok, why = forest_settled({x: t.state() for x, t in trees.items()}, links)
    assert ok, why
    # the agreed tree links span every component without a cycle
    edges = {frozenset((x, t.parent)) for x, t in trees.items() if t.parent is not None}
    g = nx.Graph(list(map(tuple, edges)))
    g.add_nodes_from(names)
    assert nx.is_forest(g)
    assert nx.number_connected_components(g) == len(tree_components(links, names))


def run_rule_round(trees, names):
    msgs = [(n, j, trees[n].epoch, trees[n].parent) for n in names for j in sorted(trees[n].links)]
    for n, j, e, p in msgs:
        trees[j].heard_from(n, e, p)


def test_forest_settled_says_why_not():
    e = TreeEpoch(1, "a")
    a = SpanningTree("a", ["b"], epoch=e)
    b = SpanningTree("b", ["a"])            # has not heard of e yet
    states = {"a": a.state(), "b": b.state()}
    ok, why = forest_settled(states, [("a", "b")])
    assert not ok and "epochs" in why
    b.heard_from("a", e, None)
    ok, why = forest_settled({"a": a.state(), "b": b.state()}, [("a", "b")])
    assert not ok and "agree" in why       # a does not know b is its child yet
    a.heard_from("b", e, "a")
    assert forest_settled({"a": a.state(), "b": b.state()}, [("a", "b")]) == (True, "")
