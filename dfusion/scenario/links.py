"""Which links a scenario allows at a time: the one rule ``dfusion simulate`` and ``dfusion run`` share.

A scenario whose links change at run time (``Scenario.dynamic``: ``[[events]]`` and radio
ranges; ``docs/dynamic-topology.md``) allows a link ``a - b`` at time ``t`` when both nodes
are present (joined and not left) and the link is either scripted (``[[links]]`` with the
``link_up`` / ``link_down`` events up to ``t`` applied) or in radio range: both nodes have a
range and their distance in the plane is at most the smaller one
(:func:`dfusion.topology.radio_links`). Positions are what the scenario knows of the nodes:
where a fixed node stands (``position``) and where a moving one is on its waypoint path at
``t`` (``path``, ``speed``, ``path_start``).

:class:`LinkSchedule` answers it for the whole network. ``dfusion simulate``
(:mod:`dfusion.sim.links`) applies its links to the simulated nodes and network;
every ``dfusion run`` node process (:mod:`dfusion.run.node_process`) evaluates the same
schedule on its own clock and keeps a link while it is allowed *and* the neighbour's Zenoh
liveliness token is seen (``docs/processes.md``). :func:`peers` lists the nodes a node may
ever link to (the Zenoh subscriptions and connections a node process needs).

No simulator, no networkx: the node program imports this module.
"""
from __future__ import annotations

import numpy as np

from dfusion.scenario.spec import Scenario
from dfusion.topology import radio_links

__all__ = ["LinkSchedule", "peers", "Pair"]

Pair = tuple[str, str]


def _pair(a: str, b: str) -> Pair:
    return (a, b) if a < b else (b, a)


class LinkSchedule:
    """Which nodes are present and which links exist at time ``t`` (module docstring)."""

    def __init__(self, sc: Scenario) -> None:
        self.sc = sc
        self.ranges = {n: s.radio_range for n, s in sc.nodes.items() if s.radio_range is not None}
        self._scripted0 = {_pair(a, b) for a, b in sc.links}
        self._link_events = [e for e in sc.events if e.kind in ("link_up", "link_down")]

    def present(self, t: float) -> set[str]:
        """The nodes in the network at ``t`` (joined and not left)."""
        return {n for n, s in self.sc.nodes.items() if s.is_present(t)}

    def positions(self, t: float) -> dict[str, np.ndarray]:
        """``(x, y)`` of every node that has one (fixed position or path)."""
        out = {}
        for n, s in self.sc.nodes.items():
            p = s.position_at(t)
            if p is not None:
                out[n] = p
        return out

    def scripted(self, t: float) -> set[Pair]:
        """``[[links]]`` with the link events up to ``t`` applied."""
        up = set(self._scripted0)
        for e in self._link_events:
            if e.t > t + 1e-9:
                break
            (up.add if e.kind == "link_up" else up.discard)(e.nodes)
        return up

    def links(self, t: float) -> set[Pair]:
        """The links that exist at ``t``: scripted or in radio range, between present nodes."""
        present = self.present(t)
        pos = {n: p for n, p in self.positions(t).items() if n in present}
        ranged = radio_links(pos, {n: r for n, r in self.ranges.items() if n in present})
        return {p for p in self.scripted(t) | ranged if p[0] in present and p[1] in present}

    def neighbours(self, name: str, t: float) -> set[str]:
        """The nodes ``name`` may link to at ``t``."""
        return {b if a == name else a for a, b in self.links(t) if name in (a, b)}


def peers(sc: Scenario, name: str) -> tuple[str, ...]:
    """The nodes ``name`` may ever link to, sorted: its tree neighbours on a fixed tree; with
    links that change, its ``[[links]]``, the other ends of its ``link_up`` events and, when it
    has a radio range, every other node with one."""
    if not sc.dynamic:
        return tuple(sc.neighbors(name))
    out = {b if a == name else a for a, b in sc.links if name in (a, b)}
    out |= {e.nodes[1] if e.nodes[0] == name else e.nodes[0] for e in sc.events
            if e.kind == "link_up" and name in e.nodes}
    if sc.nodes[name].radio_range is not None:
        out |= {n for n, s in sc.nodes.items() if s.radio_range is not None}
    out.discard(name)
    return tuple(sorted(out))
