r"""Links that change during a simulated run: which exist when, and how long the tree takes to follow.

A scenario's links change at run time (``Scenario.dynamic``, ``docs/dynamic-topology.md``)
through ``[[events]]`` (a link comes up or goes down, a node joins or leaves) and through
radio ranges: two nodes with a range are linked while their distance is at most the smaller
of their two ranges (:func:`dfusion.topology.radio_links`), positions taken from the
world's truth (fixed nodes where they stand, robots on their paths).

:class:`~dfusion.scenario.links.LinkSchedule` says which links exist at a time (the rule
``dfusion run``'s node processes evaluate too). :class:`DynamicLinks` applies them
step by step to the fusion nodes (:meth:`FusionNode.link_up`, :meth:`FusionNode.link_down`,
a joining node built with :func:`dfusion.scenario.build.build_joining_node`, a leaving node
removed after a link break at each of its neighbours) and to the simulated network, and
logs every change with the time the rule took to settle after it (:class:`LinkChange`):

* **tree settled**: every connected component of the links is in one tree epoch and its
  agreed tree links form a spanning tree of it (:func:`dfusion.fusion.tree.forest_settled`);
* **information settled**: additionally every node holds, for every state time up to the
  change, exactly the sum of the own information of the nodes of its component (relative
  tolerance 1e-6): what was measured before the change is everywhere in the component, once.
  Without any change this takes up to ``diameter`` send periods too (the measurements made
  just before are on their way); after a change of the tree the component re-synchronizes.

Times are reported in send periods (the largest ``send_period`` of the scenario's nodes).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from dfusion.fusion.channel import find_keys, time_key
from dfusion.fusion.node import FusionNode
from dfusion.fusion.tree import forest_settled, tree_components
from dfusion.scenario.build import build_joining_node, build_nodes
from dfusion.scenario.links import LinkSchedule
from dfusion.scenario.spec import Scenario
from dfusion.transport.simulated import SimulatedNetwork

__all__ = ["LinkSchedule", "DynamicLinks", "LinkChange", "agreed_edges", "information_settled", "INFO_RTOL"]

log = logging.getLogger(__name__)

#: Relative tolerance of the information check (rounding of sums and differences of blocks).
INFO_RTOL = 1e-6

Pair = tuple[str, str]


def _pair(a: str, b: str) -> Pair:
    return (a, b) if a < b else (b, a)


def agreed_edges(nodes: dict[str, FusionNode]) -> set[Pair]:
    """Tree links both ends agree on."""
    return {_pair(n, j) for n, x in nodes.items() for j in x.tree_links if j in nodes and n in nodes[j].tree_links}


@dataclass
class LinkChange:
    """One step's change of the links (what changed), and when the rule settled after it.

    ``tree_settled`` and ``info_settled`` are times (s) or None (not settled before the next
    change or the end); ``tree_changed``: the settled tree differs from the one before.
    """

    t: float
    what: list[str]
    tree_before: set[Pair]
    tree_after: set[Pair] | None = None
    tree_settled: float | None = None
    info_settled: float | None = None
    overlapped: bool = False
    components: list[set[str]] = field(default_factory=list)

    @property
    def tree_changed(self) -> bool:
        return self.tree_after is not None and self.tree_after != self.tree_before

    def as_dict(self, period: float) -> dict[str, Any]:
        def sp(t):
            return None if t is None else round((t - self.t) / period, 3)
        return {"t": self.t, "what": self.what, "tree_changed": self.tree_changed,
                "tree_settled_send_periods": sp(self.tree_settled), "info_settled_send_periods": sp(self.info_settled),
                "overlapped": self.overlapped,
                "tree_after": sorted(map(list, self.tree_after)) if self.tree_after is not None else None}


class DynamicLinks:
    """Drives the links of a scenario whose links change (module docstring).

    ``nodes`` (the present nodes, built by :meth:`start`) and ``network`` are updated in place
    by :meth:`step`; ``departed`` keeps the nodes that left.
    """

    def __init__(self, sc: Scenario) -> None:
        self.sc = sc
        self.schedule = LinkSchedule(sc)
        self.links: set[Pair] = set()
        self.nodes: dict[str, FusionNode] = {}
        self.departed: dict[str, FusionNode] = {}
        self.network: SimulatedNetwork | None = None
        self.changes: list[LinkChange] = []
        self.period = max(s.send_period for s in sc.nodes.values())
        self._settled_tree: set[Pair] = set()
        self._joined: set[str] = set()
        #: every step's agreed tree links (for figures): (t, edges)
        self.history: list[tuple[float, set[Pair]]] = []
        #: every step's roots of the tree epochs the present nodes are in (for figures): (t, names)
        self.roots: list[tuple[float, set[str]]] = []

    def start(self) -> tuple[dict[str, FusionNode], SimulatedNetwork]:
        """The nodes present at time 0 on the links that exist then, and the network."""
        self.links = self.schedule.links(0.0)
        self.nodes = build_nodes(self.sc, links=self.links)
        self.network = SimulatedNetwork(((a, b, self.sc.link_spec(a, b)) for a, b in sorted(self.links)),
                                        seed=self.sc.seed, nodes=sorted(self.sc.nodes))
        self._settled_tree = agreed_edges(self.nodes)
        self.history.append((0.0, set(self._settled_tree)))
        self.roots.append((0.0, self._roots()))
        return self.nodes, self.network

    def step(self, t: float, on_join: Callable[[str], None] | None = None) -> list[str]:
        """Apply the joins, leaves and link changes due at ``t``; returns what changed (words)."""
        present = self.schedule.present(t)
        what: list[str] = []
        for name in sorted(present - set(self.nodes)):
            if name in self.departed or name in self._joined:
                continue
            node = build_joining_node(self.sc, name)
            node.predict(t)
            self.nodes[name] = node
            self._joined.add(name)
            what.append(f"{name} joins")
            if on_join is not None:
                on_join(name)
        links = self.schedule.links(t)
        for a, b in sorted(self.links - links):
            self.network.disconnect(a, b)
            for x, y in ((a, b), (b, a)):
                if x in self.nodes:
                    self.nodes[x].link_down(y)
            what.append(f"{a} - {b} down")
        for name in sorted(set(self.nodes) - present):
            self.departed[name] = self.nodes.pop(name)
            what.append(f"{name} leaves")
        for a, b in sorted(links - self.links):
            self.network.connect(a, b, self.sc.link_spec(a, b))
            self.nodes[a].link_up(b)
            self.nodes[b].link_up(a)
            what.append(f"{a} - {b} up")
        self.links = links
        if what:
            for c in self.changes:
                if c.info_settled is None:
                    c.overlapped = True
            self.changes.append(LinkChange(t, what, set(self._settled_tree)))
            log.info("t=%.2f: %s", t, "; ".join(what))
        return what

    def observe(self, t: float) -> None:
        """After a step's messages: note when the tree and the information settled."""
        states = {n: x.tree.state() for n, x in self.nodes.items()}
        settled, _ = forest_settled(states, self.links)
        edges = agreed_edges(self.nodes)
        if settled:
            self._settled_tree = edges
        self.history.append((t, edges))
        self.roots.append((t, self._roots()))
        comps = None
        for c in self.changes:
            if c.info_settled is not None:
                continue
            if c.tree_settled is None and settled:
                c.tree_settled, c.tree_after = t, set(edges)
            if c.tree_settled is not None:
                comps = comps or tree_components(self.links, self.nodes)
                if information_settled(self.nodes, comps, c.t):
                    c.info_settled = t
                    c.components = comps

    def _roots(self) -> set[str]:
        return {x.tree.epoch.root for x in self.nodes.values()}

    def end(self, t: float) -> None:
        """After the final rounds: changes still open settle now if they do."""
        self.observe(t)

    def metrics(self) -> dict[str, Any]:
        rows = [c.as_dict(self.period) for c in self.changes]
        done = [r for r in rows if r["info_settled_send_periods"] is not None and not r["overlapped"]]
        trees = [r for r in done if r["tree_changed"]]

        def stats(key: str, rs: list) -> dict[str, float | None]:
            v = [r[key] for r in rs]
            return {"median": float(np.median(v)) if v else None, "max": float(np.max(v)) if v else None}

        return {
            "send_period": self.period,
            "link_changes": len(rows),
            "tree_changes": sum(r["tree_changed"] for r in rows),
            "changes": rows,
            "settling_tree_changes": {"tree": stats("tree_settled_send_periods", trees),
                                      "information": stats("info_settled_send_periods", trees), "count": len(trees)},
            "settling_other_changes": {"information": stats("info_settled_send_periods",
                                                            [r for r in done if not r["tree_changed"]])},
            "epochs_started": int(sum(x.tree.epochs_started for x in self.all_nodes().values())),
        }

    def all_nodes(self) -> dict[str, FusionNode]:
        return {**self.departed, **self.nodes}


def information_settled(nodes: dict[str, FusionNode], comps: list[set[str]], t: float) -> bool:
    """Whether every node holds, at every state time up to ``t`` in every window of its
    component, the sum of its component's own information (relative tolerance :data:`INFO_RTOL`)."""
    cutoff = time_key(t) + 1
    for comp in comps:
        members = [nodes[n] for n in sorted(comp)]
        lo = max(time_key(x.filter.oldest_time) for x in members) - 1
        keys = np.unique(np.concatenate([x.information_blocks(own=True)[0] for x in members]))
        keys = keys[(keys >= lo) & (keys <= cutoff)]
        if not keys.size:
            continue
        n = members[0].filter.n
        want_info = np.zeros((keys.size, n, n))
        want_vec = np.zeros((keys.size, n))
        for x in members:
            k, info, vec = x.information_blocks(own=True)
            found, pos = find_keys(keys, k)
            want_info[pos[found]] += info[found]
            want_vec[pos[found]] += vec[found]
        scale = max(float(np.abs(want_info).max()), 1e-300)
        vscale = max(float(np.abs(want_vec).max()), 1e-300)
        for x in members:
            k, info, vec = x.information_blocks()
            have_info = np.zeros_like(want_info)
            have_vec = np.zeros_like(want_vec)
            found, pos = find_keys(keys, k)
            have_info[pos[found]] = info[found]
            have_vec[pos[found]] = vec[found]
            if np.abs(have_info - want_info).max() > INFO_RTOL * scale:
                return False
            if np.abs(have_vec - want_vec).max() > INFO_RTOL * vscale:
                return False
    return True

