"""The scenario's links emulated at the sender of a node process (``dfusion run``, on by default).

A scenario describes each link by a :class:`~dfusion.transport.simulated.LinkSpec`
(latency, jitter, drop, duplicate, reorder, outages). ``dfusion simulate`` applies
it in :class:`~dfusion.transport.simulated.SimulatedNetwork`; ``dfusion run``
applies it here, in the sending process, before the message reaches Zenoh.
:class:`EmulatedLinks` draws for every send exactly what ``SimulatedNetwork.send``
draws, from the generator of the same directed link
(:func:`~dfusion.transport.simulated.link_generator`), and applies the same rules:

1. a send at scenario time ``t`` inside an outage, or with ``u0 < drop``, is lost;
2. with ``u1 < duplicate`` a second copy goes too;
3. copy ``i`` is delayed by ``latency + jitter u`` (plus ``reorder_delay u'`` with
   probability ``reorder``) scenario seconds, and lost if its arrival falls in an
   outage.

So the ``k``-th message a node sends on a link is dropped, duplicated and delayed
as the ``k``-th message on that link is in ``simulate``. A delayed copy waits in a
delay queue (a heap ordered by due wall time, due = now + delay / speed) that the
node's loop drains while it waits for its next step (:meth:`EmulatedLinks.next_due`
bounds the wait): the loop never blocks on a delayed send. The real network adds
its own delay (about 1 ms on loopback) to the emulated one.
"""
from __future__ import annotations

import heapq
import itertools
import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from dfusion.transport.simulated import DRAWS_PER_MESSAGE, LinkSpec, link_generator

log = logging.getLogger(__name__)

#: ``send(src, dst, data, t)``: the real transport's send.
SendFn = Callable[[str, str, bytes, float], None]


@dataclass
class LinkCounters:
    """What the emulation did to one directed link's messages."""

    sent: int = 0
    dropped: int = 0
    duplicated: int = 0
    delayed: int = 0


class EmulatedLinks:
    """The outgoing links of node ``name``, emulated as ``SimulatedNetwork`` would (module docstring).

    Parameters
    ----------
    name : str
        The sending node.
    links : mapping
        ``{neighbour: LinkSpec}`` of this node's links (a link's spec holds for both directions).
    seed : int
        The scenario's seed (each directed link's generator derives from it).
    send : callable
        The real send, ``send(src, dst, data, t)``.
    speed : float
        Scenario seconds per wall second (delays are scenario seconds).
    clock : callable
        Wall clock (``time.time`` by default).
    """

    def __init__(self, name: str, links: Mapping[str, LinkSpec], seed: int, send: SendFn, *, speed: float = 1.0,
                 clock: Callable[[], float] = time.time) -> None:
        self.name, self.speed, self.clock, self._send = name, float(speed), clock, send
        self.specs = dict(links)
        self._rng = {nb: link_generator(seed, name, nb) for nb in self.specs}
        self.counters = {nb: LinkCounters() for nb in self.specs}
        self._heap: list[tuple[float, int, str, bytes, float]] = []
        self._seq = itertools.count()

    def send(self, dst: str, data: bytes, t: float, *, deliver: bool = True) -> int:
        """Emulate one send at scenario time ``t``; returns the copies that will go (0, 1 or 2).

        With ``deliver=False`` the draws are made (keeping the link's random stream
        aligned with ``simulate``'s, where every send draws) but nothing is sent:
        for a send the node skips because the neighbour is not alive.
        """
        spec = self.specs.get(dst)
        if spec is None:   # a link the scenario does not describe: no emulation
            if deliver:
                self._send(self.name, dst, data, t)
            return 1
        u = self._rng[dst].random(DRAWS_PER_MESSAGE).tolist()
        if not deliver:
            return 0
        c = self.counters[dst]
        c.sent += 1
        if spec.is_down(t) or u[0] < spec.drop:
            c.dropped += 1
            return 0
        copies = 2 if u[1] < spec.duplicate else 1
        c.duplicated += copies - 1
        went = 0
        for i in range(copies):
            u_jitter, u_reorder, u_extra = u[2 + 3 * i: 5 + 3 * i]
            delay = spec.latency + spec.jitter * u_jitter
            if u_reorder < spec.reorder:
                delay += spec.reorder_delay * u_extra
            if spec.is_down(t + delay):
                c.dropped += 1
                continue
            went += 1
            if delay <= 0:
                self._send(self.name, dst, data, t)
            else:
                c.delayed += 1
                heapq.heappush(self._heap, (self.clock() + delay / self.speed, next(self._seq), dst, data, t))
        return went

    def next_due(self) -> float:
        """Wall time of the next delayed copy (``inf`` if none waits)."""
        return self._heap[0][0] if self._heap else math.inf

    def pending(self) -> int:
        return len(self._heap)

    def release_due(self, now: float | None = None) -> int:
        """Send every delayed copy whose time has come; returns how many."""
        now = self.clock() if now is None else now
        n = 0
        while self._heap and self._heap[0][0] <= now:
            _, _, dst, data, t = heapq.heappop(self._heap)
            self._send(self.name, dst, data, t)
            n += 1
        return n

    def flush(self) -> int:
        """Send every delayed copy now, in due order (``SimulatedNetwork.flush`` before the final rounds)."""
        return self.release_due(math.inf)

    def discard(self) -> int:
        """Forget every delayed copy (the node stops); returns how many."""
        n = len(self._heap)
        self._heap.clear()
        return n

    def totals(self) -> dict[str, int]:
        """Counters summed over the links."""
        out = {"sent": 0, "dropped": 0, "duplicated": 0, "delayed": 0}
        for c in self.counters.values():
            for k in out:
                out[k] += getattr(c, k)
        return out


def node_links(links: Mapping[tuple[str, str], LinkSpec], name: str) -> dict[str, LinkSpec]:
    """``{neighbour: spec}`` of ``name`` from a scenario's ``{(a, b): spec}`` (undirected) links."""
    out = {}
    for (a, b), spec in links.items():
        if name in (a, b):
            out[b if a == name else a] = spec
    return out


def describe(enabled: bool, links: Mapping[tuple[str, str], LinkSpec]) -> str:
    """One line saying whether and what the run emulates (for the table and the plot)."""
    if not enabled:
        return "links not emulated (the real network only)"
    kinds = []
    specs = list(links.values())
    for label, present in (("latency", any(s.latency > 0 for s in specs)), ("jitter", any(s.jitter > 0 for s in specs)),
                           ("drops", any(s.drop > 0 for s in specs)), ("duplicates", any(s.duplicate > 0 for s in specs)),
                           ("reordering", any(s.reorder > 0 for s in specs)), ("outages", any(s.outages for s in specs))):
        if present:
            kinds.append(label)
    return "links emulated as in the scenario: " + (", ".join(kinds) if kinds else "ideal links")
