"""A deterministic simulated network with lossy, delaying, reordering links.

Each directed link ``(src, dst)`` has a :class:`LinkSpec`. Sending a message
on it draws, from the link's own random generator:

1. whether it is **dropped** (probability ``drop``);
2. whether it is **duplicated** (probability ``duplicate``: one extra copy);
3. for each copy, a delay ``latency + U(0, jitter)``, plus ``U(0, reorder_delay)``
   with probability ``reorder`` (this lets later messages overtake it).

A message sent while the link is in an **outage** is lost, and so is a copy
whose arrival time falls in one. Outage intervals are half-open
``[start, end)``. A copy sent before an outage and arriving after it survives.

Determinism: every send consumes exactly :data:`DRAWS_PER_MESSAGE` uniform
numbers from the link's generator, whatever the outcome, and each directed
link's generator is seeded from ``(seed, link name)`` only. So for a given
seed, the ``k``-th message on a link always sees the same random numbers,
whatever happens on other links, whether links are added, and whatever the
link's parameters are (changing ``drop`` changes which messages are dropped
but not the delays of the others).

**Links that come and go.** :meth:`SimulatedNetwork.connect` adds a link (or brings one
back) and :meth:`SimulatedNetwork.disconnect` takes it away: the copies in flight on it are
lost (counted as dropped), and so is anything sent over it until it is connected again
(a simulator of robots moving in and out of radio range, ``docs/dynamic-topology.md``).

See ``docs/simulated-network.md``.
"""
from __future__ import annotations

import hashlib
import heapq
import itertools
import json
import logging
import math
import numbers
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dfusion.errors import ValidationError
from dfusion.transport.base import (
    Delivery,
    LinkKey,
    StatsReport,
    Transport,
    TransportStats,
)

_log = logging.getLogger(__name__)

#: Uniform numbers drawn per send: drop, duplicate, then (jitter, reorder?,
#: reorder delay) for each of the at most two copies.
DRAWS_PER_MESSAGE = 8

_SPEC_KEYS = ("latency", "jitter", "drop", "duplicate", "reorder", "reorder_delay", "outages")


def _real(name: str, value: Any) -> float:
    """``value`` as a finite float, or a ValidationError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValidationError(f"{name} must be a number, got {value!r}")
    x = float(value)
    if not math.isfinite(x):
        raise ValidationError(f"{name} must be finite, got {value!r}")
    return x


@dataclass(frozen=True)
class LinkSpec:
    """Behaviour of one link (all times in seconds).

    Attributes
    ----------
    latency : float
        Fixed delay, ``>= 0``.
    jitter : float
        Extra delay uniform in ``[0, jitter]``, ``>= 0``.
    drop : float
        Probability that a message is lost, in ``[0, 1)``.
    duplicate : float
        Probability that a delivered message arrives twice, in ``[0, 1]``.
        The two copies have independent delays.
    reorder : float
        Probability, in ``[0, 1]``, that a copy gets an extra delay uniform in
        ``[0, reorder_delay]``.
    reorder_delay : float
        Maximum extra delay of a reordered copy, ``>= 0``; must be ``> 0`` when
        ``reorder > 0``.
    outages : tuple[tuple[float, float], ...]
        Intervals ``[start, end)`` during which the link is down (``start < end``).
        Any sequence of pairs is accepted and stored sorted as a tuple.
    """

    latency: float = 0.0
    jitter: float = 0.0
    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    reorder_delay: float = 0.0
    outages: tuple[tuple[float, float], ...] = field(default=())

    def __post_init__(self) -> None:
        values = {name: _real(name, getattr(self, name)) for name in _SPEC_KEYS[:-1]}
        for name in ("latency", "jitter", "reorder_delay"):
            if values[name] < 0:
                raise ValidationError(f"{name} must be >= 0, got {values[name]!r}")
        if not 0.0 <= values["drop"] < 1.0:
            raise ValidationError(f"drop must be in [0, 1), got {values['drop']!r}")
        for name in ("duplicate", "reorder"):
            if not 0.0 <= values[name] <= 1.0:
                raise ValidationError(f"{name} must be in [0, 1], got {values[name]!r}")
        if values["reorder"] > 0 and values["reorder_delay"] == 0:
            raise ValidationError("reorder_delay must be > 0 when reorder > 0")
        for name, x in values.items():
            object.__setattr__(self, name, x)
        object.__setattr__(self, "outages", _outages(self.outages))

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> LinkSpec:
        """Build a spec from a mapping (e.g. a scenario file); missing keys take the defaults.

        Accepted keys: ``latency, jitter, drop, duplicate, reorder, reorder_delay,
        outages``. Raises :class:`ValidationError` naming the offending key.
        """
        if not isinstance(d, Mapping):
            raise ValidationError(f"a link spec must be a mapping, got {type(d).__name__}")
        for key in d:
            if key not in _SPEC_KEYS:
                raise ValidationError(f"unknown link spec key {key!r} (allowed: {', '.join(_SPEC_KEYS)})")
        return cls(**d)

    def is_down(self, t: float) -> bool:
        """True when ``t`` lies in one of the outage intervals ``[start, end)``."""
        return any(start <= t < end for start, end in self.outages)


def _outages(value: Any) -> tuple[tuple[float, float], ...]:
    """Validate and normalize the ``outages`` field."""
    if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, Iterable):
        raise ValidationError(f"outages must be a list of (start, end) pairs, got {value!r}")
    out = []
    for i, interval in enumerate(value):
        try:
            start, end = interval
        except (TypeError, ValueError):
            raise ValidationError(f"outages[{i}] must be a (start, end) pair, got {interval!r}") from None
        start, end = _real(f"outages[{i}] start", start), _real(f"outages[{i}] end", end)
        if not start < end:
            raise ValidationError(f"outages[{i}] must have start < end, got ({start!r}, {end!r})")
        out.append((start, end))
    return tuple(sorted(out))


def link_generator(seed: int, src: str, dst: str) -> np.random.Generator:
    """The random generator of directed link ``src -> dst``, a function of ``(seed, src, dst)`` only.

    The link name is hashed (SHA-256 of ``json.dumps([src, dst])``, stable
    across processes, unlike :func:`hash`) into the ``spawn_key`` of a
    :class:`numpy.random.SeedSequence`.
    """
    digest = hashlib.sha256(json.dumps([src, dst]).encode("utf-8")).digest()
    key = tuple(int(w) for w in np.frombuffer(digest, dtype="<u4"))
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=key)))


@dataclass
class _Link:
    """Internal state of one directed link."""

    spec: LinkSpec
    rng: np.random.Generator
    stats: TransportStats = field(default_factory=TransportStats)


#: Heap entry: (arrival time, send sequence number, delivery).
_Entry = tuple[float, int, Delivery]


class SimulatedNetwork(Transport):
    """In-process :class:`Transport` over links with given :class:`LinkSpec`.

    Parameters
    ----------
    links :
        Either a mapping ``{(src, dst): LinkSpec}`` of **directed** links, or an
        iterable of ``(a, b, LinkSpec)`` **undirected** links (both directions
        get the spec, each direction its own random generator).
    seed :
        Non-negative integer; the same seed and the same calls give the same
        deliveries.
    nodes :
        Nodes that have no link yet (links may be connected later).

    Raises
    ------
    ValidationError
        Bad seed, node names, specs, self-loops or a link given twice.
    """

    def __init__(self, links: Mapping[LinkKey, LinkSpec] | Iterable[tuple[str, str, LinkSpec]], seed: int,
                 nodes: Iterable[str] = ()) -> None:
        if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
            raise ValidationError(f"seed must be a non-negative integer, got {seed!r}")
        self._seed = int(seed)
        directed: list[tuple[str, str, LinkSpec]] = []
        if isinstance(links, Mapping):
            for key, spec in links.items():
                if not (isinstance(key, tuple) and len(key) == 2):
                    raise ValidationError(f"directed link keys must be (src, dst) pairs, got {key!r}")
                directed.append((key[0], key[1], spec))
        else:
            for entry in links:
                if not (isinstance(entry, tuple) and len(entry) == 3):
                    raise ValidationError(f"undirected links must be (a, b, LinkSpec) triples, got {entry!r}")
                a, b, spec = entry
                directed += [(a, b, spec), (b, a, spec)]
        self._links: dict[LinkKey, _Link] = {}
        for src, dst, spec in directed:
            for name in (src, dst):
                if not isinstance(name, str) or not name:
                    raise ValidationError(f"node names must be non-empty strings, got {name!r}")
            if src == dst:
                raise ValidationError(f"a link needs two different nodes, got ({src!r}, {dst!r})")
            if not isinstance(spec, LinkSpec):
                raise ValidationError(f"link ({src!r}, {dst!r}) needs a LinkSpec, got {type(spec).__name__}")
            if (src, dst) in self._links:
                raise ValidationError(f"link ({src!r}, {dst!r}) is given twice")
            self._links[(src, dst)] = _Link(spec, link_generator(self._seed, src, dst))
        nodes = {n for key in self._links for n in key} | set(nodes)
        self._queues: dict[str, list[_Entry]] = {n: [] for n in sorted(nodes)}
        self._down: set[LinkKey] = set()
        self._seq = itertools.count()
        _log.debug("simulated network: %d nodes, %d directed links, seed %d", len(nodes), len(self._links), seed)

    # ------------------------------------------------------------------ topology

    @property
    def nodes(self) -> tuple[str, ...]:
        """All node names, sorted."""
        return tuple(self._queues)

    @property
    def links(self) -> dict[LinkKey, LinkSpec]:
        """The spec of every directed link (a new dict)."""
        return {key: link.spec for key, link in self._links.items()}

    def neighbors(self, node: str) -> tuple[str, ...]:
        """The nodes ``node`` can send to (sorted)."""
        self._check_node(node)
        return tuple(sorted(dst for src, dst in self._links if src == node))

    def link_up(self, a: str, b: str, t: float) -> bool:
        """Whether the directed link ``a -> b`` is connected and outside its outages at time ``t``."""
        return (a, b) not in self._down and not self._link(a, b).spec.is_down(_real("t", t))

    def connect(self, a: str, b: str, spec: LinkSpec) -> None:
        """Connect ``a - b`` (both directions): a new link with ``spec``, or one that was
        disconnected (it keeps its spec and its random generator)."""
        if a == b or not all(isinstance(n, str) and n for n in (a, b)):
            raise ValidationError(f"a link needs two different node names, got ({a!r}, {b!r})")
        for src, dst in ((a, b), (b, a)):
            if (src, dst) not in self._links:
                if not isinstance(spec, LinkSpec):
                    raise ValidationError(f"link ({src!r}, {dst!r}) needs a LinkSpec, got {type(spec).__name__}")
                self._links[(src, dst)] = _Link(spec, link_generator(self._seed, src, dst))
            self._down.discard((src, dst))
            self._queues.setdefault(dst, [])
            self._queues.setdefault(src, [])

    def disconnect(self, a: str, b: str) -> int:
        """Take the link ``a - b`` away (both directions); returns the copies in flight it lost."""
        lost = 0
        for src, dst in ((a, b), (b, a)):
            link = self._link(src, dst)
            self._down.add((src, dst))
            queue = self._queues[dst]
            keep = [e for e in queue if e[2].src != src]
            if len(keep) != len(queue):
                link.stats.dropped += len(queue) - len(keep)
                lost += len(queue) - len(keep)
                heapq.heapify(keep)
                self._queues[dst] = keep
        return lost

    # ------------------------------------------------------------------ transport

    def send(self, src: str, dst: str, data: bytes, t: float) -> None:
        """Send ``data`` on link ``src -> dst`` at time ``t`` (see the module docstring).

        Raises :class:`ValidationError` when the link does not exist, ``data``
        is not bytes-like or ``t`` is not finite.
        """
        link = self._link(src, dst)
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise ValidationError(f"data must be bytes, got {type(data).__name__}")
        payload = bytes(data)
        t = _real("t", t)
        u = link.rng.random(DRAWS_PER_MESSAGE).tolist()
        spec, stats = link.spec, link.stats
        stats.sent += 1
        stats.bytes_sent += len(payload)
        if (src, dst) in self._down or spec.is_down(t) or u[0] < spec.drop:
            stats.dropped += 1
            return
        copies = 1
        if u[1] < spec.duplicate:
            copies = 2
            stats.duplicated += 1
        for i in range(copies):
            u_jitter, u_reorder, u_extra = u[2 + 3 * i : 5 + 3 * i]
            delay = spec.latency + spec.jitter * u_jitter
            if u_reorder < spec.reorder:
                delay += spec.reorder_delay * u_extra
            t_arrival = t + delay
            seq = next(self._seq)
            if spec.is_down(t_arrival):
                stats.dropped += 1
                continue
            heapq.heappush(self._queues[dst], (t_arrival, seq, Delivery(t_arrival, src, dst, payload, t)))

    def receive(self, node: str, until: float) -> list[Delivery]:
        """Remove and return the copies for ``node`` with ``t_arrival <= until``.

        Ordered by arrival time, ties by send order. ``until`` may be ``inf``.
        A message sent later with an earlier sender time can still arrive
        before an ``until`` already used in a previous call.
        """
        self._check_node(node)
        until = float(until)
        if math.isnan(until):
            raise ValidationError("until must not be NaN")
        queue = self._queues[node]
        out = []
        while queue and queue[0][0] <= until:
            out.append(self._deliver(heapq.heappop(queue)))
        return out

    def next_arrival(self, nodes: Iterable[str] | None = None) -> float:
        """The earliest arrival time of a copy in flight (to one of ``nodes``, or to any node);
        ``inf`` if none."""
        queues = self._queues.values() if nodes is None else [self._queues[n] for n in nodes if n in self._queues]
        return min((q[0][0] for q in queues if q), default=math.inf)

    def flush(self) -> list[Delivery]:
        """Deliver everything in flight, for all nodes, in arrival order (ties by send order)."""
        entries = sorted(e for queue in self._queues.values() for e in queue)
        for queue in self._queues.values():
            queue.clear()
        return [self._deliver(e) for e in entries]

    def pending(self, node: str | None = None) -> int:
        """Number of copies in flight (to ``node``, or to any node)."""
        if node is None:
            return sum(len(q) for q in self._queues.values())
        self._check_node(node)
        return len(self._queues[node])

    @property
    def stats(self) -> StatsReport:
        """Counters per directed link and in total (a snapshot).

        For every link and the total,
        ``sent + duplicated == delivered + dropped + in_flight``, where
        ``in_flight`` is the number of copies :meth:`pending` counts.
        """
        return StatsReport.from_links({key: link.stats for key, link in self._links.items()})

    # ------------------------------------------------------------------ helpers

    def _deliver(self, entry: _Entry) -> Delivery:
        delivery = entry[2]
        stats = self._links[(delivery.src, delivery.dst)].stats
        stats.delivered += 1
        stats.bytes_delivered += len(delivery.data)
        return delivery

    def _check_node(self, node: str) -> None:
        if node not in self._queues:
            raise ValidationError(f"unknown node {node!r}")

    def _link(self, src: str, dst: str) -> _Link:
        try:
            return self._links[(src, dst)]
        except (KeyError, TypeError):
            raise ValidationError(f"there is no link {src!r} -> {dst!r}") from None
