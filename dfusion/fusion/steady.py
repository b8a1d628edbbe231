"""The steady-state receive path: the critical path first, the bookkeeping left for :meth:`FusionNode.settle`.

A message planned as an append of new blocks (the usual message of a running network) is
fused into the filter at once and the rest of its work, which the estimate does not need
(the channel's commit, the total store, the marks for the other links, the acknowledgement,
pruning; with a guard, the consistency test when no verdict could change the belief), is
left for :meth:`SteadyPath.settle`, which every method that reads or changes that state
runs first. Every observable is the same, bit for bit, as on the general path
(:mod:`dfusion.fusion.transaction`); ``FusionNode.critical_path_first = False`` sends every
message there. :meth:`FusionNode.settle` also records the messages :meth:`FusionNode.message_to` sent.
"""
from __future__ import annotations

import numpy as np

from dfusion.errors import DfusionError
from dfusion.fusion.channel import ChannelFilter
from dfusion.fusion.stats import node_log as log
from dfusion.wire import InfoMessage

__all__ = ["SteadyPath"]


class SteadyPath:
    """The steady-state path of a received message and the deferred bookkeeping (see the module
    docstring); a part of :class:`FusionNode`."""
    def _steady(self, msg: InfoMessage, ch: ChannelFilter, deltas: list) -> bool:
        """Whether a message planned as an append (:meth:`ChannelFilter.plan`: new blocks after every
        stored one, nothing cleared, nothing older than the window) may take
        :meth:`_apply_steady`: a newer message of the link's incarnation, every block at or before
        the newest state, a fixed tree (the tree rule's holds stay on the general path) and a link
        that is not quarantined (its messages are probation tests)."""
        if (not self.critical_path_first or self.tree is not None or self._tree_held or msg.seq <= ch.last_seq
                or msg.seq_start != ch.remote_start or (self._guard is not None and self._guard.is_quarantined(msg.src))):
            return False
        latest = self.filter.latest_time + self.filter.time_tol
        return all(d[0] <= latest for d in deltas)

    def _apply_steady(self, msg: InfoMessage, ch: ChannelFilter, plan, deltas: list) -> int | None:
        """:meth:`FusionNode._apply` of a steady-state message (:meth:`_steady`), the critical path first: the
        blocks go into the filter (and its estimate is brought up to date, which also tests
        that the belief stays proper) at once; with a guard they are tested as they are added
        and the verdict recorded (:meth:`FusionNode._add_tested`, :meth:`NeighbourGuard.judge`); the rest
        is left to :meth:`FusionNode.settle`. Every result is the same, bit for bit, as :meth:`FusionNode._apply`'s.

        The test itself is left to :meth:`FusionNode.settle` too when the message is one block at the
        newest state and a failing verdict would not quarantine the neighbour
        (:meth:`NeighbourGuard.may_quarantine`): no verdict can then change the filter, only
        the link's counters, so the estimate is final at once. The moments the statistic
        needs are saved as the block is added (the newest state's filtered moments before and
        after: what :meth:`DelayedStateEIF.add_information_moments` reads) and the verdict is
        recorded by :meth:`_settle_receive` (:meth:`FusionNode._deferred_test`); reading :attr:`guard` or
        :meth:`FusionNode.health` settles first.

        A verdict that would quarantine the neighbour (its withdrawal needs the bookkeeping
        done) is not recorded: the filter is put back and ``None`` returned, and the caller
        takes :meth:`FusionNode._apply`, which tests the message again (the same statistic) in its
        transaction."""
        f = self.filter
        guard = self._guard
        cp_filter = f.checkpoint()
        verdict = None
        test = None   # the test left for settle(): (block, means and covariance before, mean after)
        if guard is not None and len(deltas) == 1 and not guard.may_quarantine(msg.src) \
                and f.index_of(deltas[0][0]) == len(f) - 1:
            test = deltas[0]
        if deltas:
            try:
                if test is not None:   # (no verdict can change the belief: tested in settle())
                    mu0, P0 = f.newest_moments()
                    f.add_information_batch(deltas, validate=False)
                    f.estimate()   # the belief must still be proper
                    test = (test, mu0, P0, f.newest_moments()[0])
                elif guard is None:
                    f.add_information_batch(deltas, validate=False)
                    f.estimate()
                else:
                    verdict = self._add_tested(deltas)
                    f.estimate()
            except BaseException as exc:
                f.restore(cp_filter)
                if isinstance(exc, DfusionError):
                    raise self._reject("numerical", f"message from {msg.src!r} cannot be fused: {exc}") from None
                if isinstance(exc, Exception):
                    raise self._reject("internal",
                                       f"message from {msg.src!r} failed: {type(exc).__name__}: {exc}") from exc
                raise
        cp_guard = None
        if guard is not None and test is None:
            src = msg.src
            try:
                if verdict is not None and guard.would_quarantine(src, verdict[0], verdict[1]):
                    f.restore(cp_filter)
                    return None
                cp_guard = guard.state(src)
                self._record_verdict(src, len(deltas), verdict)   # (False: would_quarantine)
            except BaseException as exc:   # (a defect) the message is undone, the link's record too
                f.restore(cp_filter)
                if cp_guard is not None:
                    guard.restore(src, cp_guard)
                if isinstance(exc, Exception):
                    raise self._reject("internal",
                                       f"message from {src!r} failed: {type(exc).__name__}: {exc}") from exc
                raise
        heard = self._heard.get(msg.src)
        self._heard[msg.src] = max(self._heard.get(msg.src, -np.inf), float(msg.sent_at))
        self.stats.messages_received += 1
        self._pending = (msg, ch, plan, deltas, cp_filter, cp_guard, heard, test)
        self._deferred = True
        self._tree_undo = None
        return len(deltas)

    def settle(self) -> None:
        """Do the work that the last message received or sent left for later now (a node may call
        it when idle; every method that reads or changes what is left does it first, and so does
        reading :attr:`FusionNode.channels`; :meth:`FusionNode.estimate`, :meth:`FusionNode.output`, :meth:`FusionNode.check_frame`,
        :meth:`FusionNode.is_quarantined`, :meth:`FusionNode.health` and :meth:`FusionNode.report_source` read none of it and
        leave it for later). What a caller waits for is done
        first, the rest after; no caller sees the node in between: every observable is the same,
        bit for bit, as if all of it had been done at once.

        * :meth:`FusionNode.receive` fuses a steady-state message into the filter at once (the estimate
          changes) and leaves what the estimate does not need (with a guard, its consistency
          test and verdict too when no verdict could complete a quarantine: the belief is then
          final whatever the verdict; else it is tested and judged at once): storing the blocks in the
          channel filter and the node's total information, marking them for the other links,
          the acknowledgement the message carries, pruning. A failure of this bookkeeping (a
          defect; nothing in it depends on the message's values) undoes the whole message, the
          filter's part too, and counts and logs it as an ``"internal"`` rejection.
        * :meth:`FusionNode.message_to` returns the message and leaves the record of what it carried
          (:meth:`ChannelFilter.record_sent`), and the filter's forward pass up to the newest
          state (its estimate: the next :meth:`FusionNode.predict` that marginalizes the oldest state
          needs part of it; nothing else changes).
        """
        if self._deferred:
            self._settle()

    def _settle(self) -> None:
        if not self._deferred:
            return
        self._deferred = False
        if self._sent_pending:
            sent, self._sent_pending = self._sent_pending, []
            for ch, seq, keys, full in sent:
                ch.record_sent(seq, keys, full)
        if self._pending is not None:
            self._settle_receive()
        if self._warm:
            self._warm = False
            try:
                self.filter.estimate()
            except DfusionError:   # an improper belief: the operation that needs it reports it
                pass

    def _settle_receive(self) -> None:
        p = self._pending
        self._pending = None
        msg, ch, plan, deltas, cp_filter, cp_guard, heard, test = p
        mark = self._mark_stores(msg.src, cp_filter, cp_guard)
        try:
            ch.commit(msg, plan)
            if deltas:
                self._total.add_many(deltas)
            self._mark_dirty(plan.changed.tolist(), skip=msg.src)
            if test is not None and self._record_verdict(msg.src, 1, self._deferred_test(*test)):
                self._withdraw(msg.src)   # (not reached: the message was deferred because no verdict quarantines)
                log.warning("%s: neighbour %s quarantined after a deferred test; what came over the link is "
                            "withdrawn", self.name, msg.src)
            if msg.dst_epoch == self.epoch:
                ch.acknowledged(msg.ack, msg.ack_mask)
            self._prune()
        except BaseException as exc:
            self._rollback_stores(mark)
            self.stats.messages_received -= 1
            if heard is None:
                self._heard.pop(msg.src, None)
            else:
                self._heard[msg.src] = heard
            if not isinstance(exc, Exception):   # an interrupt: undone, not a rejected message
                raise
            detail = f"message from {msg.src!r} failed: {type(exc).__name__}: {exc}"
            self._reject("internal", detail)
            log.error("%s: the bookkeeping of a fused message failed; the message is undone: %s", self.name, detail)
            return
        self._release_stores()
