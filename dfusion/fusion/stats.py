"""A node's counters (:class:`NodeStats`) and its rate-limited log of rejected messages (:class:`RejectionLog`).

Every part of a fusion node logs to one logger, :data:`node_log` (``dfusion.fusion.node``),
whatever module its code is in: a user or a test filters the node's log by that one name.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

__all__ = ["LOG_INTERVAL", "NodeStats", "RejectionLog", "node_log"]

#: The logger of every part of a fusion node (:mod:`dfusion.fusion.node` and the modules of its parts).
node_log = logging.getLogger("dfusion.fusion.node")
log = node_log
#: Default seconds between two log lines about rejected messages.
LOG_INTERVAL = 10.0


@dataclass
class NodeStats:
    """Counters of a node's traffic.

    ``rejections`` counts rejected messages by reason: ``malformed``, ``corrupt``,
    ``unauthenticated``, ``version``, ``oversized`` (the frame), ``misaddressed``,
    ``not-a-neighbour``, ``dimension``, ``previous-incarnation``, ``implausible-incarnation`` (an
    incarnation number far ahead of this node's clock, :mod:`dfusion.fusion.incarnation`),
    ``sequence-jump``, ``numerical`` (the filter would not stay proper), ``internal``. ``duplicates`` counts
    copies of messages the node had applied already (network duplicates, replays inside the
    run, or messages older than the replay window, :meth:`ChannelFilter.was_applied`):
    discarded without an error, they change nothing.

    With links that change (``FusionNode(tree=...)``): ``not_fused`` counts messages used
    by the tree rule only (beacons, messages of another tree epoch or over a link that is
    not a tree link at this end), ``not_linked`` messages that arrived over a link that no
    longer exists (ignored), ``tree_changes`` the events that changed this node's tree
    links, ``new_epochs`` how often it entered a new tree epoch, ``withdrawn_blocks`` the
    blocks it withdrew.
    """

    messages_sent: int = 0
    bytes_sent: int = 0
    full_messages_sent: int = 0
    messages_received: int = 0
    messages_rejected: int = 0
    duplicates: int = 0
    blocks_outside_window: int = 0
    blocks_too_far_ahead: int = 0
    rejections: dict[str, int] = field(default_factory=dict)
    not_fused: int = 0
    not_linked: int = 0
    tree_changes: int = 0
    new_epochs: int = 0
    withdrawn_blocks: int = 0
    #: of ``messages_rejected``: copies rejected by the cheap checks as they arrived, before they
    #: were queued (:meth:`FusionNode.check_frame` run by the transport), so never delivered
    rejected_on_arrival: int = 0
    #: messages that showed a neighbour started a fresh channel for the link in the same
    #: incarnation (a new ``seq_start``): this node forgot its acknowledgements and sent it a full
    #: message (:mod:`dfusion.fusion.channel`, resynchronization)
    resyncs: int = 0
    #: messages that switched a link back to a neighbour's incarnation that a newer one had
    #: replaced, because it went on sending (without a key, :mod:`dfusion.fusion.incarnation`)
    incarnations_reverted: int = 0


class RejectionLog:
    """Counts rejected messages by reason and logs them at most once per ``interval`` seconds.

    The first rejection is logged at once; later ones are summed and reported in one
    line (``"a: 12,345 messages rejected in the last 10.0 s: corrupt 12,000, ..."``) when
    the next rejection comes after ``interval`` seconds, or at :meth:`flush`.
    """

    def __init__(self, name: str, interval: float = LOG_INTERVAL, logger: logging.Logger = log) -> None:
        self.name, self.interval, self.logger = name, float(interval), logger
        self._pending: dict[str, int] = {}
        self._last: float | None = None
        self._example = ""

    def add(self, reason: str, detail: str, count: int = 1) -> None:
        """Count ``count`` rejected messages of one ``reason`` (``detail``: the last one's)."""
        now = time.monotonic()
        if self._last is None:
            self._last = now
            self.logger.warning("%s: rejected a message (%s): %s", self.name, reason, detail)
            count -= 1
            if count <= 0:
                return
        self._pending[reason] = self._pending.get(reason, 0) + count
        self._example = f"{reason}: {detail}"
        if now - self._last >= self.interval:
            self.flush(now)

    def tick(self) -> None:
        """Write the pending summary if ``interval`` seconds have passed since the last line (call it
        now and then: after a flood ends no further rejection comes to trigger it)."""
        if self._pending and self._last is not None and time.monotonic() - self._last >= self.interval:
            self.flush()

    def flush(self, now: float | None = None) -> None:
        if self._pending:
            total = sum(self._pending.values())
            parts = ", ".join(f"{r} {c:,}" for r, c in sorted(self._pending.items(), key=lambda x: -x[1]))
            self.logger.warning("%s: %s messages rejected since the last report: %s (last: %s)", self.name,
                                f"{total:,}", parts, self._example)
            self._pending = {}
        self._last = time.monotonic() if now is None else now
