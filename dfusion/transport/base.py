"""The interface fusion nodes use to exchange byte messages with their neighbours.

Semantics every implementation follows (the simulated network in
:mod:`dfusion.transport.simulated` and the Zenoh transport alike):

* **Best effort.** A message may be lost, delayed, duplicated or reordered.
  There is no acknowledgement and no retransmission; protocols built on top
  must tolerate all four.
* **No buffering across outages.** A message sent while the link is down is
  lost; it is *not* queued and sent when the link comes back (this is how
  Zenoh behaves).
* **Point to point.** ``send`` addresses one neighbour; there is no broadcast.
* **Clocks.** ``t`` in :meth:`Transport.send` is the sender's clock and
  ``until`` in :meth:`Transport.receive` the receiver's clock. The simulated
  network assumes one shared clock.
* **Pull-based receive.** :meth:`Transport.receive` returns the messages that
  have arrived at a node by a given time and removes them, so each delivered
  copy is returned exactly once.
"""
from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace

#: A directed link ``(src, dst)``.
LinkKey = tuple[str, str]
#: Seconds between two log lines about one name's liveliness (:class:`LineBudget`).
LIVELINESS_LOG_INTERVAL = 1.0


class LineBudget:
    """At most one log line per key every ``interval`` seconds (a neighbour whose liveliness flaps,
    or a stranger flapping a token of its name, cannot flood the log).

    :meth:`allow` says whether a line may be written now and how many lines of that key were
    held back since the last one (say it in the line); :attr:`held_back` counts them all. Keys
    are the caller's bounded set (followed node names).
    """

    def __init__(self, interval: float = LIVELINESS_LOG_INTERVAL, clock=None) -> None:
        self.interval = float(interval)
        self.clock = clock or time.monotonic
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self.held_back = 0

    def allow(self, key: str) -> tuple[bool, int]:
        """``(write it now, lines of this key held back since the last written one)``."""
        now = self.clock()
        last = self._last.get(key)
        if last is not None and now - last < self.interval:
            self._held[key] = self._held.get(key, 0) + 1
            self.held_back += 1
            return False, 0
        self._last[key] = now
        return True, self._held.pop(key, 0)

    @staticmethod
    def suffix(held: int) -> str:
        """`` (N earlier changes not logged)`` or nothing."""
        return f" ({held} earlier change{'s' if held != 1 else ''} not logged)" if held else ""


@dataclass(frozen=True)
class Delivery:
    """One copy of a message arriving at ``dst``.

    Attributes
    ----------
    t_arrival : float
        Arrival time at ``dst``.
    src, dst : str
        Sender and receiver.
    data : bytes
        The payload, identical to the bytes that were sent.
    t_sent : float
        The ``t`` the sender passed to :meth:`Transport.send`.
    checked : bool
        Whether the transport ran the receiver's frame check (size, header, checksum, MAC:
        :meth:`dfusion.fusion.FusionNode.check_frame`) on exactly these bytes as they arrived and
        it passed; the receiver may then skip those checks (``FusionNode.receive(data,
        checked=True)``). False (the default) when no check ran.
    """

    t_arrival: float
    src: str
    dst: str
    data: bytes
    t_sent: float
    checked: bool = False


@dataclass
class TransportStats:
    """Message counters for one directed link, or summed over all of them.

    Attributes
    ----------
    sent : int
        Calls to :meth:`Transport.send`.
    delivered : int
        Copies returned by :meth:`Transport.receive` (or a flush).
    dropped : int
        Copies known to be lost (random drop, outage at send or at arrival).
    duplicated : int
        Extra copies created by the link (a message sent once and duplicated
        once counts ``sent=1, duplicated=1``).
    bytes_sent : int
        Payload bytes of the sent messages (duplicates not counted).
    bytes_delivered : int
        Payload bytes of the delivered copies (duplicates counted).
    """

    sent: int = 0
    delivered: int = 0
    dropped: int = 0
    duplicated: int = 0
    bytes_sent: int = 0
    bytes_delivered: int = 0

    @property
    def in_flight(self) -> int:
        """Copies neither delivered nor known to be lost: ``sent + duplicated - delivered - dropped``."""
        return self.sent + self.duplicated - self.delivered - self.dropped

    def __add__(self, other: TransportStats) -> TransportStats:
        if not isinstance(other, TransportStats):
            return NotImplemented
        return TransportStats(
            sent=self.sent + other.sent,
            delivered=self.delivered + other.delivered,
            dropped=self.dropped + other.dropped,
            duplicated=self.duplicated + other.duplicated,
            bytes_sent=self.bytes_sent + other.bytes_sent,
            bytes_delivered=self.bytes_delivered + other.bytes_delivered,
        )


@dataclass(frozen=True)
class StatsReport:
    """A snapshot of the counters: per directed link and their sum.

    Attributes
    ----------
    links : dict[tuple[str, str], TransportStats]
        Counters of each directed link ``(src, dst)`` (copies; changing them
        does not affect the transport).
    total : TransportStats
        The sum over all links.
    """

    links: dict[LinkKey, TransportStats] = field(default_factory=dict)
    total: TransportStats = field(default_factory=TransportStats)

    @classmethod
    def from_links(cls, links: dict[LinkKey, TransportStats]) -> StatsReport:
        """Build a report from per-link counters (copied), computing the total."""
        copies = {key: replace(stats) for key, stats in links.items()}
        return cls(links=copies, total=sum(copies.values(), TransportStats()))


class Transport(ABC):
    """Best-effort point-to-point byte transport between named nodes.

    See the module docstring for the delivery semantics.
    """

    @abstractmethod
    def send(self, src: str, dst: str, data: bytes, t: float) -> None:
        """Send ``data`` from ``src`` to its neighbour ``dst`` at sender time ``t``.

        Never blocks and never reports loss: a message that is dropped is
        only visible in :attr:`stats` (when the implementation can know it).
        """

    @abstractmethod
    def receive(self, node: str, until: float) -> list[Delivery]:
        """Remove and return the copies for ``node`` that arrived at or before ``until``.

        The list is in arrival order (ties in any order the implementation
        fixes; the simulated network uses send order).
        """

    @property
    @abstractmethod
    def stats(self) -> StatsReport:
        """Counters per directed link and in total (a snapshot)."""

    def close(self) -> None:
        """Release resources (sessions, sockets). The default does nothing."""
