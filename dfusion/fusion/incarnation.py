r"""Which incarnation of a neighbour to believe: the bounds on a forged incarnation number.

Every message carries its sender's incarnation ``epoch``: the time in nanoseconds when
the sender started (:class:`~dfusion.fusion.FusionNode`'s default, ``time.time_ns()``;
``dfusion run`` claims ``max(clock, last + 1)`` from the run's state directory so that a
restart is newer even after the clock went back, ``dfusion.run.measurements.claim_epoch``;
simulations and tests number incarnations 1, 2, ...). A receiver takes a message of a
newer incarnation for a restart of its sender (it forgets what the old incarnation said
and sends it a full message) and rejects messages of older ones (``previous-incarnation``).

With a network key incarnations are authenticated: only key holders can send them. Without
one a single forged frame with a valid checksum and a huge ``epoch`` used to lock the
sender out for good: every genuine message was then of an "earlier incarnation". Two
bounds limit that damage (``docs/security.md``):

* **An incarnation far beyond any clock is refused** (``implausible-incarnation``): a new
  incarnation more than :data:`MAX_EPOCH_AHEAD_NS` (24 h) ahead of the receiver's wall
  clock cannot be a start time (the tolerance covers clocks of different hosts and a
  restart after the clock was set back, which ``claim_epoch`` numbers ``last + 1``).
* **A replaced incarnation that goes on is taken back** (without a key only). The receiver
  remembers the incarnation a newer one replaced (:class:`Replaced`) and the newest
  sequence number it had from it. A later message of it that *continues* its stream (a
  larger sequence number: not a replay, not a duplicate) switches the link back to it, as
  if it had restarted, when

  - it was made after the message that replaced it (its ``sent_at`` is later): a restarted
    node's first message is made after everything its previous incarnation sent, so a
    message of the previous incarnation still under way is refused, while a neighbour
    whose incarnation a stranger forged (copying one of its frames) is taken back with its
    next message: within one send period after the forgery stops; or
  - it is the :data:`REVERT_STREAK`-th such message in a row without a message of the
    current incarnation in between (a forger that also claims a late ``sent_at``): a
    restarted node keeps sending, a dead incarnation does not.

  Each switch is handled like a restart (the link resynchronizes: full messages both ways)
  and counted in ``NodeStats.incarnations_reverted``. A forger that keeps sending keeps the
  link switching back and forth: without a key it can send any information anyway; only a
  key (or TLS) keeps it out.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

from dfusion.fusion.channel import MAX_SEQ_JUMP

__all__ = ["MAX_EPOCH_AHEAD_NS", "REVERT_STREAK", "Replaced", "Incarnations"]

#: A new incarnation more than this far (ns) ahead of the receiver's wall clock is refused.
MAX_EPOCH_AHEAD_NS = 24 * 3600 * 10**9
#: Continuing messages of a replaced incarnation, in a row, that switch the link back to it
#: whatever their ``sent_at`` (without a key).
REVERT_STREAK = 3


@dataclass(frozen=True, slots=True)
class Replaced:
    """The incarnation ``epoch`` of a neighbour that a newer one replaced: the newest sequence
    number heard from it, the ``sent_at`` of the message that replaced it, and its continuing
    messages counted since (``streak``) while the current incarnation's newest sequence
    number stayed ``mark``."""

    epoch: int
    newest_seq: int
    sent_at: float
    streak: int = 0
    mark: int = -1


class Incarnations:
    """A node's judgement of its neighbours' incarnation numbers (module docstring).

    ``keyed``: the node authenticates messages (no switching back then); ``clock``: the wall
    clock in nanoseconds (for tests).
    """

    def __init__(self, keyed: bool, clock: Callable[[], int] = time.time_ns) -> None:
        self.keyed = keyed
        self.clock = clock
        #: per neighbour, the incarnation its current one replaced
        self.replaced: dict[str, Replaced] = {}

    def restore(self, src: str, record: Replaced | None) -> None:
        """Put back ``src``'s record as it was before a :meth:`judge` whose message was then refused."""
        if record is None:
            self.replaced.pop(src, None)
        else:
            self.replaced[src] = record

    def judge(self, src: str, epoch: int, seq: int, sent_at: float, current: int | None, newest: int) -> tuple[str, int]:
        """The verdict on a message of incarnation ``epoch`` (sequence number ``seq``) from ``src``,
        whose current incarnation is ``current`` (``None``: none yet) with newest sequence number
        ``newest``, and the newest sequence number of the incarnation it belongs to (the reference
        of the sequence-jump bound, -1: none).

        Verdicts: ``"same"``, ``"new"`` (a newer incarnation; ``"first"`` when none was known),
        ``"revert"`` (back to the incarnation the current one replaced), or a rejection reason:
        ``"implausible-incarnation"``, ``"previous-incarnation"``. A ``"new"`` or ``"revert"``
        records the incarnation it replaces (the caller puts the record back with :meth:`restore`
        when the message is refused later on); a message of the replaced incarnation that
        continues its stream advances its record, even when it is refused.
        """
        if epoch == current:
            return "same", newest
        if current is None or epoch > current:
            if epoch - self.clock() > MAX_EPOCH_AHEAD_NS:
                return "implausible-incarnation", -1
            if current is None:
                return "first", -1
            self.replaced[src] = Replaced(current, newest, sent_at)
            return "new", -1
        rec = self.replaced.get(src)
        if self.keyed or rec is None or rec.epoch != epoch or seq <= rec.newest_seq:
            return "previous-incarnation", -1
        if seq > rec.newest_seq + MAX_SEQ_JUMP:   # no continuation: a forged number must not move the record
            return "previous-incarnation", -1
        streak = rec.streak + 1 if rec.mark == newest else 1
        if sent_at > rec.sent_at or streak >= REVERT_STREAK:
            self.replaced[src] = Replaced(current, newest, sent_at)
            return "revert", rec.newest_seq
        self.replaced[src] = Replaced(rec.epoch, seq, rec.sent_at, streak, newest)
        return "previous-incarnation", -1
