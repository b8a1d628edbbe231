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

from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace

#: A directed link ``(src, dst)``.
LinkKey = tuple[str, str]


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
    """

    t_arrival: float
    src: str
    dst: str
    data: bytes
    t_sent: float


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
