"""Following the tree rule in the node: links that appear and vanish, and information held over a change.

:class:`dfusion.fusion.tree.SpanningTree` is the tree rule itself (a pure state machine:
which links carry fusion, the tree epoch, the parent). This part makes the node follow it
(``docs/dynamic-topology.md``): the tree fields of received messages go to the rule
(:meth:`TreeFollowing._tree_heard`, with an undo if the message is then refused), the
transport's link events too (:meth:`TreeFollowing.link_up`, :meth:`TreeFollowing.link_down`);
when the rule changes the tree, what came over the links that left it is withdrawn from
what the node shares (everything, in a new epoch) and fresh channels start on the links
that joined it (:meth:`TreeFollowing._follow`). The node's own estimate keeps the withdrawn
information per state time (``hold`` seconds, or until the new tree delivers as much:
:meth:`TreeFollowing._tree_hold`, :meth:`TreeFollowing._release_tree_held`).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from dfusion.errors import ValidationError
from dfusion.fusion.channel import MAX_SEQ_JUMP, ChannelFilter, nonzero_blocks, time_key
from dfusion.fusion.guard import LinkRecord
from dfusion.fusion.tree import TreeChange, TreeEpoch
from dfusion.wire import InfoMessage

__all__ = ["HELD_RTOL", "TreeFollowing"]

#: Relative tolerance of "R(t) holds at least as much as L(t)" (rounding of sums of blocks).
HELD_RTOL = 1e-9


class TreeFollowing:
    """The node's side of the tree rule (see the module docstring); a part of :class:`FusionNode`."""
    @property
    def tree_links(self) -> tuple[str, ...]:
        """The links that carry fusion (on a fixed tree: every neighbour)."""
        return tuple(sorted(self.channels))

    def link_up(self, neighbor: str) -> None:
        """A link to ``neighbor`` now exists (links that change; the transport saw it appear)."""
        self._settle()
        self._tree_required()
        if neighbor == self.name or (self.peers is not None and neighbor not in self.peers):
            raise ValidationError(f"{self.name!r} cannot link to {neighbor!r}")
        self._follow(self.tree.link_up(neighbor))

    def link_down(self, neighbor: str) -> None:
        """The link to ``neighbor`` is gone (it broke, or ``neighbor`` left): see the tree rule."""
        self._settle()
        self._tree_required()
        self._follow(self.tree.link_down(neighbor))

    def _tree_required(self) -> None:
        if self.tree is None:
            raise ValidationError(f"{self.name!r} runs on a fixed tree (FusionNode(tree=...) for links that change)")

    def _follow(self, change: TreeChange) -> None:
        """Make the channels follow a change of the tree: withdraw what came over the links that
        left it (everything in a new epoch), fresh channels for the links that joined it."""
        self.neighbors = tuple(sorted(self.tree.links))
        if change:
            self.stats.tree_changes += 1
            if change.new_epoch:
                self.stats.new_epochs += 1
                self._tree_withdraw(list(self.channels.values()), everything=True)
                for ch in self.channels.values():
                    self._link_seq[ch.remote] = ch.seq_out
                self.channels = {j: self._channel(j) for j in sorted(self.tree.tree_links())}
            else:
                lost = [self.channels.pop(j) for j in sorted(change.lost) if j in self.channels]
                for ch in lost:
                    self._link_seq[ch.remote] = ch.seq_out
                if lost:
                    self._tree_withdraw(lost)
                for j in sorted(change.gained):
                    self.channels[j] = self._channel(j)
        if self._guard is not None:
            # a record per link that exists (after the withdrawal, which asks whether a link was
            # quarantined); a quarantine outlives changes of the tree while the link exists
            links = self._guard.links
            for j in [j for j in links if j not in self.tree.links]:
                del links[j]
            for j in self.neighbors:
                if j not in links:
                    links[j] = LinkRecord(self._guard.config.window)

    def _tree_withdraw(self, channels: list[ChannelFilter], everything: bool = False) -> None:
        """Take what ``channels`` delivered out of the stores messages are made from (the other
        channels send those times again: per-time replacement carries the withdrawal on); the
        node's own estimate keeps it per state time until the tree delivers as much
        (:meth:`_tree_hold`). ``everything``: these are all the channels, what the node sends from
        becomes its own information alone (what it fused but does not share yet stays out).

        A quarantined channel's information was withdrawn already (:meth:`FusionNode._withdraw`): it is
        not subtracted again."""
        entries: dict[int, list] = {}
        for ch in channels:
            if self.is_quarantined(ch.remote):
                continue
            for i in np.flatnonzero(nonzero_blocks(ch.info, ch.vec)).tolist():
                key = int(ch.keys[i])
                e = entries.get(key)
                if e is None:
                    entries[key] = [float(ch.times[i]), -ch.info[i], -ch.vec[i]]
                else:
                    e[1] = e[1] - ch.info[i]
                    e[2] = e[2] - ch.vec[i]
        self.stats.withdrawn_blocks += len(entries)
        self._tree_hold(sorted(entries))
        if everything:
            self._total.restore(self._own.checkpoint())
            self._total.subtract([(e.t, e.info, e.vec) for _, e in self._held.items()])
        elif entries:
            self._total.add_many([tuple(entries[k]) for k in sorted(entries)])
            keys = list(entries)
            for ch in self.channels.values():
                ch.dirty.update(keys)
        if self.hold <= 0:
            self._release_tree_held(self.filter.latest_time + 1.0)

    def _tree_hold(self, keys: list[int]) -> None:
        """Before the received information at ``keys`` changes with the tree: keep, per state time
        in the filter, what the filter holds of it (``L(t)``), so the estimate does not lose it
        until the new tree delivers as much (``docs/dynamic-topology.md``).

        The filter holds, per state time, the node's own information plus either ``L(t)``
        (a held time) or what its current channels delivered ``R(t)`` (:meth:`FusionNode._received_at`); each is
        information of other nodes counted once, so either choice never double counts.
        Messages are made from ``T(t)`` alone: held information is never sent.
        """
        f = self.filter
        lo, hi = time_key(f.oldest_time) - 1, time_key(f.latest_time + f.time_tol)
        new = np.array([k for k in keys if lo <= k <= hi and k not in self._tree_held], dtype=np.int64)
        if not new.size:
            return
        received = self._received_at(new)
        until = f.latest_time + self.hold
        for i, k in enumerate(new.tolist()):
            L, y = received[0][i], received[1][i]
            if L.any() or y.any():
                self._tree_held[k] = (k / 1e9, L, y, until)

    def _follow_tree_held(self, deltas: list) -> None:
        """After a message was fused: at held times the filter keeps ``L(t)`` (the message's change
        of ``R(t)`` is taken out again), unless ``R(t)`` now holds at least as much information
        (``R(t) - L(t)`` positive semi-definite): then the time is no longer held."""
        if not self._tree_held or not deltas:
            return
        keys = [time_key(d[0]) for d in deltas]
        undo = [(d[0], -d[1], -d[2]) for d, k in zip(deltas, keys) if k in self._tree_held
                and d[0] <= self.filter.latest_time + self.filter.time_tol]
        if not undo:
            return
        self._add_to_filter(undo)
        self._release_tree_held(None, [time_key(d[0]) for d in undo])

    def _release_tree_held(self, now: float | None, keys: list[int] | None = None) -> None:
        """Let held times go: those that expired by ``now`` (``hold`` seconds after they were held)
        and, among ``keys``, those whose ``R(t)`` dominates ``L(t)``: the filter takes
        ``R(t) - L(t)`` at them."""
        if not self._tree_held:
            return
        go = [k for k, e in self._tree_held.items() if now is not None and e[3] <= now]
        if keys:
            cand = np.array([k for k in keys if k in self._tree_held and k not in go], dtype=np.int64)
            if cand.size:
                R = self._received_at(cand)[0]
                L = np.array([self._tree_held[k][1] for k in cand.tolist()])
                scale = np.maximum(np.abs(R).max(axis=(1, 2)), np.abs(L).max(axis=(1, 2)))
                ok = np.linalg.eigvalsh(R - L)[:, 0] >= -HELD_RTOL * scale
                go += cand[ok].tolist()
        if not go:
            return
        keys_go = np.array(sorted(set(go)), dtype=np.int64)
        R, r = self._received_at(keys_go)
        change = []
        for i, k in enumerate(keys_go.tolist()):
            t, L, y, _ = self._tree_held.pop(k)
            change.append((t, R[i] - L, r[i] - y))
        self._add_to_filter(change)

    def _tree_heard(self, msg: InfoMessage) -> bool:
        """The tree rule's part of :meth:`FusionNode.receive` (links that change): whether to fuse ``msg``.

        Checks what the rule needs (recipient, sender, tree mode, dimension, incarnation),
        gives the tree fields to the rule and makes the channels follow its changes. A
        message is fused only when it is a fusion message of this node's tree epoch over a
        tree link; the others are counted in ``stats.not_fused`` (``stats.not_linked`` when
        the link no longer exists). If the message is then refused, :meth:`FusionNode._reject` undoes
        what this did (``self._tree_undo``): a rejection changes nothing.
        """
        src = msg.src
        if msg.dst != self.name:
            raise self._reject("misaddressed", f"message for {msg.dst!r} delivered to {self.name!r}")
        if src == self.name or (self.peers is not None and src not in self.peers):
            raise self._reject("not-a-neighbour", f"{src!r} may not link to {self.name!r}")
        if not msg.tree_root:
            raise self._reject("malformed", f"{src!r} uses another tree mode (a fixed tree)")
        if msg.n != self.filter.n:
            raise self._reject("dimension", f"state dimension {msg.n} from {src!r}, expected {self.filter.n}")
        known = self.incarnations.get(src)
        newest = self._heard_seq.get(src, -1)
        verdict, last = ("same", newest) if msg.epoch == known else self._judge_incarnation(msg, known, newest)
        if msg.beacon and msg.seq > last + MAX_SEQ_JUMP and self.frame_key is None:
            # (a fusion message's jump is checked against its channel, :meth:`_check`)
            raise self._reject("sequence-jump", f"sequence number {msg.seq} from {src!r} jumps past {last}")
        if src not in self.tree.links:
            self.stats.not_linked += 1
            self._undo_incarnation()   # the rule did not take src's incarnation (incarnations[src] unchanged)
            return False
        undo = None if msg.beacon else self._tree_checkpoint()
        self._tree_undo = undo     # a failure from here on undoes the rule's changes (_reject)
        if verdict in ("new", "revert"):   # src restarted (or went back): what it said before no longer holds
            self._follow(self.tree.forget(src))
        self.incarnations[src] = msg.epoch
        self._heard_seq[src] = last   # (a channel the rule makes now starts its jump bound there)
        parent = msg.parent or None
        if parent == self.name and msg.dst_epoch not in (0, self.epoch):
            parent = None     # it names an earlier incarnation of this node
        self._follow(self.tree.heard_from(src, TreeEpoch(msg.tree_term, msg.tree_root), parent))
        self._heard_seq[src] = max(msg.seq, last)
        if msg.beacon or src not in self.channels or TreeEpoch(msg.tree_term, msg.tree_root) != self.tree.epoch:
            self.stats.not_fused += 1
            self._tree_undo = None
            return False
        return True

    def _tree_checkpoint(self) -> tuple:
        return (self.tree.snapshot(), dict(self.incarnations), dict(self.channels),
                {j: ch.state() for j, ch in self.channels.items()}, self.filter.checkpoint(),
                self._total.checkpoint(), self.neighbors, dataclasses.replace(self.stats), dict(self._tree_held),
                None if self._guard is None else dict(self._guard.links), dict(self._heard_seq), dict(self._link_seq))

    def _tree_restore(self, cp: tuple) -> None:
        tree, inc, channels, states, filt, total, nbrs, stats, held, guard_links, heard_seq, link_seq = cp
        self._heard_seq, self._link_seq = heard_seq, link_seq
        self._tree_held = held
        if guard_links is not None:
            self._guard.links = guard_links
        self.tree.restore(tree)
        self.incarnations, self.channels, self.neighbors = inc, channels, nbrs
        for j, st in states.items():
            channels[j].restore(st)
        self.filter.restore(filt)
        self._total.restore(total)
        self.stats = stats

    @property
    def urgent(self) -> bool:
        """The tree links changed since :meth:`outgoing` was last called: send now rather than at
        the next send period (the new tree links start with full messages, beacons carry a new
        epoch on)."""
        return self.tree is not None and self.stats.tree_changes != self._sent_tree_changes
