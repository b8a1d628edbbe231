"""The general receive path: a planned message applied to the node all or nothing, and the undo.

:meth:`dfusion.fusion.node.FusionNode.receive` decodes, checks and plans a message; this
part applies the plan (:meth:`ReceiveTransaction._apply`): the filter, the channel, the
stores, the guard's record of the link, the acknowledgement the message carries and the
pruning it causes change together, or, if anything raises on the way, not at all
(:meth:`ReceiveTransaction._mark_stores` / :meth:`ReceiveTransaction._rollback_stores`, the
one list of what a message may change; the steady path, :mod:`dfusion.fusion.steady`, undoes
with it too). It also bounds what a message may make the node store ahead of its newest
state (``max_ahead`` seconds, ``max_held`` times).
"""
from __future__ import annotations

import numpy as np

from dfusion.errors import DfusionError
from dfusion.fusion.channel import ChannelFilter, find_keys, time_key
from dfusion.fusion.guard import LinkRecord
from dfusion.fusion.stats import node_log as log
from dfusion.wire import InfoMessage

__all__ = ["ReceiveTransaction"]


class ReceiveTransaction:
    """The general path of a received message (see the module docstring); a part of :class:`FusionNode`."""
    def _within_reach(self, deltas: list) -> tuple[list, list]:
        """Split ``deltas`` into those within ``max_ahead`` seconds / ``max_held`` held times and the rest.

        A delta at a time already held back changes that entry and holds no new time: it is
        always within reach (else a full message would turn it into a zero entry of the
        channel while the store keeps the old value, which is double counted later).
        """
        f = self.filter
        latest = f.latest_time + f.time_tol
        if all(d[0] <= latest for d in deltas):   # (the usual case: nothing ahead of the newest state)
            return list(deltas), []
        horizon = f.latest_time + self.max_ahead + f.time_tol
        room = self.max_held - self._total.count_after(time_key(f.latest_time + f.time_tol))
        held = self._total.keys
        ok, far = [], []
        for d in deltas:
            if d[0] <= f.latest_time + f.time_tol:
                ok.append(d)
            elif find_keys(held, np.array([time_key(d[0])]))[0][0]:
                ok.append(d)
            elif d[0] <= horizon and room > 0:
                ok.append(d)
                room -= 1
            else:
                far.append(d[0])
        return ok, far

    def _entries_out_of_reach(self, ch: ChannelFilter, plan) -> list[float]:
        """Times of entries ``plan`` would newly store in ``ch`` beyond ``max_ahead`` seconds or
        ``max_held`` times ahead of the newest state.

        Zero entries (a cleared time, a zero block) change no information, so
        :meth:`_within_reach` never sees them; without this bound a message could make the
        channel store any number of them far in the future.
        """
        f = self.filter
        latest = time_key(f.latest_time + f.time_tol)
        if not plan.keys.size or plan.keys[-1] <= latest:   # (sorted keys: nothing ahead)
            return []
        keys = np.concatenate([ch.keys, plan.keys]) if plan.append else plan.keys   # (the entries after it)
        ahead = keys[keys > latest]
        if not ahead.size:
            return []
        new = ahead[~find_keys(ch.keys, ahead)[0]]
        if not new.size:
            return []
        horizon = time_key(f.latest_time + self.max_ahead + f.time_tol)
        room = self.max_held - (ahead.size - new.size)
        within = new[new <= horizon][:max(room, 0)]
        return (np.setdiff1d(new, within, assume_unique=True) / 1e9).tolist()

    def _apply(self, msg: InfoMessage, ch: ChannelFilter, plan, deltas: list, changed: np.ndarray,
               too_far: list, outside: int) -> None:
        """Apply a planned message to the filter, the channels, the stores and the statistics, with
        the acknowledgement it carries and the pruning it causes: all or nothing.

        ``too_far``: times held back (the message is then not acknowledged); ``outside``:
        blocks older than the window (ignored).

        With a guard (:mod:`dfusion.fusion.guard`) the blocks the message adds are tested as
        they are applied, inside the same transaction; a message that completes a quarantine
        also withdraws everything that came over the link. A message over a quarantined link
        is only stored in the channel, and is a probation test of the neighbour's whole
        contribution (which may end the quarantine). An exception anywhere undoes all of it,
        the guard's record of the link included.
        """
        f = self.filter
        latest = f.latest_time + f.time_tol
        now = [d for d in deltas if d[0] <= latest]
        mark = self._mark_stores(msg.src)
        guard = self._guard
        # the sender restarted (or, without a key, its replaced incarnation went on: a switch back), or
        # it started a fresh channel for the link in this incarnation (resynchronization)
        restarted = ch.epoch is not None and msg.epoch != ch.epoch
        reverted = restarted and msg.epoch < ch.epoch
        resync = not restarted and ch.remote_resynchronizes(msg)
        duplicate = msg.epoch == ch.epoch and msg.seq == ch.last_seq
        event = None
        try:
            if guard is not None and guard.is_quarantined(msg.src):
                ch.commit(msg, plan, complete=not too_far)
                ch.follow_remote(restarted or resync, reverted)
                event = self._probation(msg.src, ch)
            else:
                verdict = None
                if now:
                    try:
                        if guard is None:
                            f.add_information_batch(now, validate=False)
                        else:
                            verdict = self._add_tested(now)
                        f.estimate()   # the belief must still be proper
                    except DfusionError as exc:
                        raise _Numerical(str(exc)) from None
                ch.commit(msg, plan, complete=not too_far)
                ch.follow_remote(restarted or resync, reverted)
                if deltas:
                    self._total.add_many(deltas)
                self._mark_dirty(changed.tolist(), skip=msg.src)
                self._follow_tree_held(deltas)
                if guard is not None and self._record_verdict(msg.src, len(deltas), verdict):
                    self._withdraw(msg.src)
                    event = "quarantined"
            if msg.dst_epoch == self.epoch:
                ch.acknowledged(msg.ack, msg.ack_mask)
            self._prune()   # an inserted state may have pushed the oldest one out
        except BaseException as exc:
            self._rollback_stores(mark)
            if isinstance(exc, _Numerical):
                raise self._reject("numerical", f"message from {msg.src!r} cannot be fused: {exc}") from None
            if isinstance(exc, Exception):
                raise self._reject("internal", f"message from {msg.src!r} failed: {type(exc).__name__}: {exc}") from exc
            raise
        self._release_stores()
        self.stats.messages_received += 1
        if not too_far and not duplicate:
            self._heard[msg.src] = max(self._heard.get(msg.src, -np.inf), float(msg.sent_at))
        self.stats.duplicates += int(duplicate)
        self.stats.resyncs += int(resync)
        self.stats.blocks_outside_window += outside
        self.stats.blocks_too_far_ahead += len(too_far)
        if outside:
            log.debug("%s: %d blocks from %s older than the window were ignored", self.name, outside, msg.src)
        if event == "quarantined":
            cfg = guard.config
            log.warning("%s: neighbour %s quarantined (%d of its last %d tested messages failed the consistency "
                        "test); what came over the link is withdrawn", self.name, msg.src, cfg.failures, cfg.window)
        elif event == "released":
            log.warning("%s: neighbour %s leaves quarantine after %d consistent messages; its information is fused "
                        "again", self.name, msg.src, guard.config.release)

    def _mark_stores(self, src: str, cp_filter: tuple | None = None, cp_guard: LinkRecord | None = None) -> tuple:
        """A mark of everything a received message may change, for :meth:`_rollback_stores`: the
        filter, the stores messages are made from (total, own, held back), the times held after
        a change of the tree, every channel filter, the prune mark and the guard's record of
        ``src``'s link. ``cp_filter``, ``cp_guard``: the filter's checkpoint and the record's
        copy taken earlier (the critical path changed them before the rest was marked).

        The one place that lists the stores: :meth:`_apply` and :meth:`FusionNode._settle_receive` both undo
        with it (``tests/fusion/test_store_rollback.py`` compares every attribute of the node)."""
        guard = self._guard
        if cp_guard is None and guard is not None and src in guard.links:
            cp_guard = guard.state(src)
        return (self.filter.checkpoint() if cp_filter is None else cp_filter, self._total.mark(), self._own.mark(),
                self._held.mark(), dict(self._tree_held), {j: c.state() for j, c in self._channels.items()},
                self._pruned_at, src, cp_guard)

    def _rollback_stores(self, mark: tuple) -> None:
        """Go back to a :meth:`_mark_stores`."""
        cp_filter, total, own, held, tree_held, channels, pruned_at, src, cp_guard = mark
        self.filter.restore(cp_filter)
        self._total.rollback(total)
        self._own.rollback(own)
        self._held.rollback(held)
        self._tree_held = tree_held
        for j, c in self._channels.items():
            c.restore(channels[j])
        self._pruned_at = pruned_at
        if cp_guard is not None:
            self._guard.restore(src, cp_guard)

    def _release_stores(self) -> None:
        """The :meth:`_mark_stores` is no longer needed (the transaction succeeded): the stores
        write in place again."""
        self._total.release()
        self._own.release()
        self._held.release()


class _Numerical(Exception):
    """A message's information would make the filter improper."""
