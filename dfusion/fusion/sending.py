r"""When a node sends: event-triggered sends, rate-limited per link, with a periodic heartbeat.

A node that sends only every send period ``P`` moves information one hop per period: a
measurement reaches a node ``d`` hops away after about ``d (P / 2 + latency)`` on average,
``d (P + latency)`` at worst, while the centralized EKF has it at once. Event-triggered
sends take the period out of that: a node sends to a tree neighbour ``j`` as soon as it
has information ``j`` does not have yet (:meth:`FusionNode.news`: a new own measurement,
or a received message that changed what it shares and must be relayed), so the lag of a
hop is its latency, and the lag of ``d`` hops ``d * latency``:

.. math::

    \text{lag}_\text{periodic}(d) \approx d \, (P/2 + \ell), \qquad
    \text{lag}_\text{event}(d) \approx d \, \ell \quad (\ell \ge \text{the minimum interval } m
    \text{ or no send on that link in the last } m).

Two rules keep it safe and cheap:

* **Minimum interval per link** ``m`` (``min_interval``, default :data:`MIN_SEND_INTERVAL`):
  a link never carries two messages of a node less than ``m`` apart (heartbeats and the
  messages after a change of the tree, :attr:`FusionNode.urgent`, included). News that
  comes sooner waits until ``m`` has passed (:meth:`SendSchedule.next_event`) and then
  goes in one message with whatever else came meanwhile: at most ``1 / m`` messages per
  second per link, whatever the rates of the sensors (no message storm).
* **Acknowledgements** travel in the neighbour's messages, which may now be fewer than a
  node's own on a link; the rule "acknowledgements more than ``ACK_LAG`` messages behind
  have stalled" (then partial messages carry everything since the newest acknowledged one,
  :mod:`dfusion.fusion.channel`) counts messages, and two periodic messages are two send
  periods. The schedule keeps that meaning with events: ``ack_lag = ACK_LAG * ceil(P / m)``
  messages (at most ``MAX_UNACKED / 2``; :attr:`FusionNode.ack_lag`). Without it a link
  whose far end has little to say would carry its recent blocks again in every message
  (measured in ``urus-mobile``: 2.6 times the bytes).
* **The periodic send stays** as the heartbeat: every send period every link gets a message
  (a beacon on links outside the tree), as without events. It carries the
  acknowledgements and the times of lost messages (:mod:`dfusion.fusion.channel`), so a
  lost event message is recovered as before, and the tree rule hears its neighbours.

Nothing about what a message holds changes: an event message is the same partial message
``V_j(t) = T(t) - M_j(t)`` at the times that changed (``docs/fusion.md``), so exactness on
a tree and the never-over-confident invariant of links that change hold whatever the send
times (the property tests draw arbitrary send times).

``mode="periodic"`` sends every send period only (and at once after a change of the tree),
the behaviour before event sends.
"""
from __future__ import annotations

import math
from collections.abc import Iterable
from typing import TYPE_CHECKING

from dfusion.errors import ValidationError
from dfusion.fusion.channel import ACK_LAG, MAX_UNACKED

if TYPE_CHECKING:
    from dfusion.fusion.node import FusionNode

__all__ = ["MIN_SEND_INTERVAL", "SEND_MODES", "SendSchedule"]

#: ``"event"``: send news at once (rate-limited) plus the periodic heartbeat; ``"periodic"``: every send period only.
SEND_MODES = ("event", "periodic")
#: Default minimum interval between two messages of a node on one link, in seconds: at most 20
#: messages per second per link, half a time step of the scenarios (``dt = 0.1``), so that
#: news can cross a wired hop (10 ms) and be relayed within one step.
MIN_SEND_INTERVAL = 0.05
_EPS = 1e-9


class SendSchedule:
    """One node's send times (see the module docstring).

    Parameters
    ----------
    period : float
        The send period (heartbeat), seconds, > 0.
    min_interval : float
        Least seconds between two messages on one link, >= 0 (0: no limit).
    mode : {"event", "periodic"}
    first : float, optional
        Time of the first periodic send (default ``period``).

    Attributes
    ----------
    last : dict[str, float]
        Per neighbour, the time of the node's last message to it.
    event_messages : int
        Messages sent because of news (not periodic, not urgent).
    """

    def __init__(self, period: float, min_interval: float = MIN_SEND_INTERVAL, mode: str = "event",
                 first: float | None = None) -> None:
        if not (isinstance(period, (int, float)) and math.isfinite(period) and period > 0):
            raise ValidationError(f"send period must be a positive number of seconds, got {period!r}")
        if not (isinstance(min_interval, (int, float)) and math.isfinite(min_interval) and min_interval >= 0):
            raise ValidationError(f"min_send_interval must be a non-negative number of seconds, got {min_interval!r}")
        if mode not in SEND_MODES:
            raise ValidationError(f"sends must be one of {SEND_MODES}, got {mode!r}")
        self.period = float(period)
        self.min_interval = float(min_interval)
        self.mode = mode
        self.next_periodic = self.period if first is None else float(first)
        self.last: dict[str, float] = {}
        self.event_messages = 0
        self._owed: set[str] = set()
        #: The links the last :meth:`due` skipped at the period (``skip``).
        self.skipped: list[str] = []
        #: Acknowledgement lag of the node's channels (:attr:`FusionNode.ack_lag`): ``ACK_LAG`` send
        #: periods' worth of messages, at most ``period / min_interval`` per period with events.
        self.ack_lag = ACK_LAG
        if self.interval > 0:
            self.ack_lag = min(ACK_LAG * max(1, math.ceil(self.period / self.interval - _EPS)), MAX_UNACKED // 2)

    @property
    def interval(self) -> float:
        """The minimum interval in force: ``min_interval`` with event sends, 0 when periodic (a
        change of the tree is sent at once, as before event sends)."""
        return self.min_interval if self.mode == "event" else 0.0

    def _allowed(self, j: str, t: float) -> bool:
        return t + _EPS >= self.last.get(j, -math.inf) + self.interval

    def due(self, node: FusionNode, t: float, skip: Iterable[str] = ()) -> list[tuple[str, bytes]]:
        """The messages ``node`` sends at time ``t``.

        * The period has come, or the tree changed (:attr:`FusionNode.urgent`): a message on
          every link (a beacon outside the tree) whose minimum interval has passed. At the
          period a link still inside its interval had a message less than ``min_interval``
          ago, which did the heartbeat's work; after a change of the tree such a link is owed
          its message and gets it at the end of its interval (:meth:`next_event`).
        * ``mode="event"``: a message to every tree neighbour with news
          (:meth:`FusionNode.news`) whose minimum interval has passed; the others wait.

        ``skip``: links not to send to now (a neighbour that is not alive); those the period
        would have sent to are listed in :attr:`skipped`.
        """
        skip = set(skip)
        self.skipped = []
        if node.ack_lag != self.ack_lag:
            node.ack_lag = self.ack_lag
        out: list[tuple[str, bytes]] = []
        links = set(node.neighbors)
        self._owed &= links
        periodic = t + _EPS >= self.next_periodic
        if periodic or node.urgent:
            if node.urgent:
                self._owed = set(links)
            ready = {j for j in links if self._allowed(j, t)}
            self.skipped = sorted(ready & skip)
            out = node.outgoing(sent_at=t, only=ready - skip)
            self._owed -= ready
            while self.next_periodic <= t + _EPS:
                self.next_periodic += self.period
        elif self._owed:
            ready = {j for j in self._owed - skip if self._allowed(j, t)}
            out = [(j, node.message_to(j, sent_at=t)) for j in sorted(ready)]
            self._owed -= ready
        if self.mode == "event":
            sent = {j for j, _ in out}
            for j in node.news():
                if j not in sent and j not in skip and self._allowed(j, t):
                    out.append((j, node.message_to(j, sent_at=t)))
                    self.event_messages += 1
        for j, _ in out:
            self.last[j] = t
        return out

    def next_event(self, node: FusionNode) -> float:
        """When ``node`` next has a send to make before its next period: the end of the minimum
        interval of a link with news or owed a message after a change of the tree (``-inf``:
        now, the tree changed; ``inf``: nothing waits)."""
        if node.urgent:
            return -math.inf
        waiting = set(self._owed) & set(node.neighbors)
        if self.mode == "event":
            waiting |= set(node.news())
        return min((self.last.get(j, -math.inf) + self.interval for j in waiting), default=math.inf)
