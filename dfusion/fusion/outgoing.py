"""What a node sends: its messages (partial, full or naive), beacons, and which links have news.

:meth:`MessageSending.message_to` makes the message for one neighbour from the target's
values for that link (``V_j(t) = T(t) - M_j(t)``, :meth:`FusionNode._values_for`) at the
times the channel says changed or turned out lost (:mod:`dfusion.fusion.channel`), with the
acknowledgement of what the node applied from that neighbour and, with links that change,
the tree fields; a link that is not a tree link gets a beacon. :meth:`MessageSending.news`
and :attr:`FusionNode.urgent` tell an event-triggered sender (:class:`dfusion.fusion.sending.SendSchedule`)
when to send.
"""
from __future__ import annotations

from typing import Iterable

import numpy as np

from dfusion.errors import ValidationError
from dfusion.fusion.channel import all_of, nonzero_blocks, time_key
from dfusion.linalg import Array
from dfusion.wire import InfoMessage, encode

__all__ = ["MessageSending"]


class MessageSending:
    """The messages of a node (see the module docstring); a part of :class:`FusionNode`."""
    def message_to(self, neighbor: str, sent_at: float | None = None) -> bytes:
        """The message for ``neighbor`` (bytes, ready for any transport).

        Partial (what changed since the previous message, and what turned out lost) when
        the neighbour has been sent a full message, else the whole window
        (:mod:`dfusion.fusion.channel`).
        """
        self._settle()
        ch = self.channels.get(neighbor)
        if ch is None:
            if self.tree is not None and neighbor in self.tree.links:
                return self._beacon(neighbor, sent_at)
            raise ValidationError(f"{neighbor!r} is not a neighbour of {self.name!r}")
        f = self.filter
        oldest_key = time_key(f.oldest_time) - 1
        tot = self._total
        full = self.fusion == "naive" or self.messages == "full" or ch.next_is_full()
        if full:
            keys = record = tot.keys[tot.keys >= oldest_key]
            if self.fusion == "naive":
                infos, vecs = self._naive_increments(neighbor, keys, *tot.values_at(keys))
            else:
                infos, vecs = self._values_for(ch, keys)
        else:
            keys = record = ch.pending_keys(oldest_key)
            lag = ch.lag()
            # a busy neighbour: what would leave the window unconfirmed (the states that leave it within
            # lag + 1 more states; a window not full yet keeps them for its room)
            edge = lag + 1 - (f.window - len(f) if f.window is not None else 0)
            if ch.acked >= 0 and lag > ch.ack_lag and edge >= 0:
                times = f.times
                risk = ch.at_risk_keys(time_key(float(times[min(edge, times.size - 1)])))
                risk = risk[risk >= oldest_key]
                if risk.size:
                    keys = np.union1d(keys, risk)
            infos, vecs = self._values_for(ch, keys)
        times = keys / 1e9
        keep = nonzero_blocks(infos, vecs)
        if all_of(keep):
            cleared = np.zeros(0)
        else:
            cleared = times[~keep] if not full else np.zeros(0)
            times, infos, vecs = times[keep], infos[keep], vecs[keep]
        msg = InfoMessage(
            src=self.name,
            dst=neighbor,
            epoch=self.epoch,
            seq=ch.seq_out,
            start=f.oldest_time,
            sent_at=f.latest_time if sent_at is None else float(sent_at),
            times=times,
            info=infos,
            vec=vecs,
            dst_epoch=ch.epoch or self.incarnations.get(neighbor, 0),
            ack=ch.applied_seq,
            ack_mask=ch.received_mask(),
            cleared=cleared,
            full=full and self.fusion != "naive",
            naive=self.fusion == "naive",
            seq_start=ch.seq_start,
            **self._tree_fields(),
        )
        data = encode(msg, self.frame_key)
        if self.critical_path_first:   # recorded by settle() (the next call): the next message depends on it
            self._sent_pending.append((ch, msg.seq, record, msg.full))
            self._warm = self._deferred = True
        else:
            ch.record_sent(msg.seq, record, msg.full)
        self.stats.messages_sent += 1
        self.stats.bytes_sent += len(data)
        self.stats.full_messages_sent += int(msg.full)
        return data

    def _naive_increments(self, neighbor: str, keys: np.ndarray, infos: Array, vecs: Array) -> tuple[Array, Array]:
        """Rumour propagation: everything new since the last message to ``neighbor``, echo included."""
        sent = self._naive_sent.setdefault(neighbor, {})
        infos, vecs = infos.copy(), vecs.copy()
        for i, k in enumerate(keys.tolist()):
            prev = sent.get(k)
            sent[k] = (infos[i].copy(), vecs[i].copy())
            if prev is not None:
                infos[i] -= prev[0]
                vecs[i] -= prev[1]
        return infos, vecs

    def outgoing(self, sent_at: float | None = None, only: Iterable[str] | None = None) -> list[tuple[str, bytes]]:
        """``(neighbour, message)`` for every link: a fusion message on a tree link, a beacon on
        the others (links that change); every neighbour's message on a fixed tree. ``only``:
        those of the links only (the others are sent later: a minimum interval per link,
        :class:`dfusion.fusion.sending.SendSchedule`). Clears :attr:`FusionNode.urgent`."""
        self._settle()
        self._sent_tree_changes = self.stats.tree_changes
        pick = None if only is None else set(only)
        return [(j, self.message_to(j, sent_at)) for j in self.neighbors if pick is None or j in pick]

    def news(self) -> tuple[str, ...]:
        """The tree neighbours this node has information for that they do not have yet: a time of
        its window whose value ``V_j(t) = T(t) - M_j(t)`` changed since its last message to ``j``
        (a new own measurement, or a received message that changed ``T`` and must be relayed;
        the channel's ``dirty`` times). Losses are not news: they are resent with the next
        message, periodic or not (:mod:`dfusion.fusion.channel`). Event-triggered sends
        (:class:`dfusion.fusion.sending.SendSchedule`) send to these at once."""
        oldest = time_key(self.filter.oldest_time) - 1
        return tuple(j for j, ch in sorted(self.channels.items()) if ch.dirty and max(ch.dirty) >= oldest)

    def _beacon(self, neighbor: str, sent_at: float | None) -> bytes:
        """A beacon for ``neighbor``: the tree fields, no blocks."""
        f = self.filter
        seq = self._link_seq.get(neighbor, 0)
        self._link_seq[neighbor] = seq + 1
        msg = InfoMessage(src=self.name, dst=neighbor, epoch=self.epoch, seq=seq, seq_start=seq, start=f.oldest_time,
                          sent_at=f.latest_time if sent_at is None else float(sent_at), times=np.zeros(0),
                          info=np.zeros((0, f.n, f.n)), vec=np.zeros((0, f.n)),
                          dst_epoch=self.incarnations.get(neighbor, 0), full=False, beacon=True,
                          **self._tree_fields())
        data = encode(msg, self.frame_key)
        self.stats.messages_sent += 1
        self.stats.bytes_sent += len(data)
        return data

    def _tree_fields(self) -> dict:
        """The tree fields of this node's messages (empty on a fixed tree)."""
        if self.tree is None:
            return {}
        t = self.tree
        return {"tree_term": t.epoch.term, "tree_root": t.epoch.root, "parent": t.parent or ""}
