r"""The channel filter of one link: what both ends already share, and what the other end has acknowledged.

Fusion rule on a tree (Grime & Durrant-Whyte, "Data fusion in decentralized
sensor networks", Control Eng. Practice 1994; URUS paper, sec. 6)::

    Omega_i <- Omega_i + sum_j (Omega_j - Omega_ij),   eta likewise,

with ``(Omega_ij, eta_ij)`` the channel filter of link ``i-j``. dfusion keeps the
trajectory's information split by state time, and only single-state factors
(measurements) ever differ between nodes: prior and motion factors are common.
The channel filter of ``i`` for link ``i-j`` therefore stores, per state time
``t``, the latest single-state information ``M_ij(t)`` that ``j`` sent: the part
of ``j``'s belief that ``i`` now shares. What ``i`` has for ``j`` is

    V_ij(t) = T_i(t) - M_ij(t),   T_i(t) = own_i(t) + sum_k M_ik(t),

everything ``i`` knows that did not come from ``j`` ("the equivalent view on
trees", see ``docs/fusion.md``). At ``j`` a block of time ``t`` from ``i``
*replaces* the previous one: ``j`` adds ``V(t) - M_ji(t)`` to its filter.

**Sending what the neighbour does not have yet.** Each message carries the
sender's incarnation ``epoch`` and a per-link sequence number ``seq``, and
acknowledges what the sender has applied from the recipient: the newest sequence
number ``ack`` and, as a bit mask, which of the 64 before it (a selective
acknowledgement). A message is either

* *full*: ``V(t)`` for every time of the sender's window from ``start`` on; a time it
  does not carry is zero there. The first message to a neighbour (or to a new
  incarnation of it) is full, and so is the one after an unacknowledged full message
  that turned out lost;
* *partial*: ``V(t)`` only for the times whose value changed since the previous message
  (:attr:`ChannelFilter.dirty`), plus the times of every earlier message the recipient
  turned out not to have received (:meth:`ChannelFilter.acknowledged` collects them); a
  time among those whose value is now zero is listed in ``cleared``.

Blocks are absolute values, not increments: a block (or a clearing) replaces what the
recipient stores for that time, and only from a newer message (every stored entry
remembers the sequence number it came from; a cleared time is kept as a zero entry, a
tombstone, so that an older message arriving late cannot bring it back). A partial
message is therefore safe to apply on its own, whatever else arrived. Consequences,
whatever the transport does:

* duplicates and reordered (older) messages change nothing;
* crossing messages cannot double count: neither side's message contains what it
  received from the other;
* a lost message loses nothing for good: once an acknowledgement shows a later message
  arrived without it, its times are sent again with their current values; until then
  the recipient holds older values for them, which is less information, never more
  (never over-confident). A lost acknowledgement only delays that;
* in the steady state without losses a message carries only what changed since the
  previous one: the information minimum, plus a header;
* while nothing is acknowledged (a link used one way only, or the first messages) and
  when acknowledgements stall (more than :data:`ACK_LAG` messages behind and none advanced
  during the last ``ACK_LAG + 1`` messages: the link is down, or the recipient is), partial
  messages carry everything sent since the newest acknowledged message: a lost message is
  then recovered by the next one, and the first message through after an outage brings the
  recipient up to date at once. Acknowledgements that lag but keep advancing (a busy
  recipient working through a queue) do not count as stalled: such a recipient is sent what
  changed only, and a loss shows in its acknowledgements (the resend backoff; resending
  everything then kept a CPU-starved recipient behind), except that the unacknowledged times
  about to leave the window are carried in every message (:meth:`ChannelFilter.at_risk_keys`);
* a restarted node has a new, larger ``epoch``: its neighbours forget what it had
  acknowledged and send it a full message, and treat the blocks its previous incarnation
  sent as older than any new message; a message of an earlier incarnation is rejected;
* **resynchronization**: a node may drop a channel and start a fresh one for the same link
  in the same incarnation (the tree rule withdrew the link and took it back, perhaps while
  the other end noticed nothing). The fresh channel forgot what the neighbour sent, and
  its sequence numbers go on from where the previous channel's stopped (``start``), so the
  neighbour never takes its messages for duplicates of old ones, and an acknowledgement
  the neighbour sent for a message of the previous channel (a number below ``start``) is
  ignored. Every message carries ``seq_start``, the number its channel started at: a
  recipient that sees a new ``seq_start`` on a message newer than any it received from
  that incarnation knows the sender forgot what it had sent it, and does what it does for a
  restarted sender (:meth:`ChannelFilter.remote_restarted`: forget the acknowledgements,
  send a full message); the sender's fresh channel sends a full message first, which
  replaces everything the recipient holds from it. Both directions are then resynchronized
  without double counting anything: per-time replacement keeps at most one value per time
  from each neighbour, whichever channel it came from;
* times older than the sender's window (``start``) are kept as they are: the
  sender dropped them, the recipient may still hold them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dfusion.linalg import Array
from dfusion.wire import InfoMessage, time_keys

__all__ = ["ChannelFilter", "Plan", "Entry", "time_key", "time_keys", "nonzero_blocks", "find_keys",
           "MAX_SEQ_JUMP", "MAX_UNACKED", "REPLAY_WINDOW"]

_MASK64 = (1 << 64) - 1
#: Messages an acknowledgement may lag behind before partial messages also carry everything
#: sent since the newest acknowledged one (so that a link coming back from an outage
#: catches up with its first message).
ACK_LAG = 2

#: Largest forward jump of the sequence number within one incarnation, for nodes without a
#: network key (a stranger cannot then lock a sender out with one message numbered near
#: 2^63). With a key the bound is not applied: only key holders can send an authenticated
#: message, they can forge any message anyway, and a link that lost more than this many
#: messages in a row (28 h at 10 Hz) must still come back.
MAX_SEQ_JUMP = 1_000_000
#: Messages remembered while unacknowledged: beyond this many the sender sends a full
#: message instead (and forgets the records).
MAX_UNACKED = 64
#: Messages before the newest applied one that the receiver remembers (the selective
#: acknowledgement's 64 bits): an applied one, or an older one, is discarded as a duplicate.
REPLAY_WINDOW = 64


def time_key(t: float) -> int:
    """Integer nanoseconds: the key under which a state time is stored.

    Messages carry times below ``dfusion.wire.MAX_ABS_TIME`` at least 1 ns apart, so
    every block of a message has its own key.
    """
    return int(round(t * 1e9))


@dataclass(frozen=True)
class Entry:
    """Single-state information ``(info, vec)`` at time ``t`` from message ``seq``."""

    t: float
    seq: int
    info: Array
    vec: Array


@dataclass(slots=True)   # (not frozen: a frozen dataclass's __init__ costs a few us per message)
class Plan:
    """What receiving one message changes (see :meth:`ChannelFilter.plan`); nothing is changed yet.

    Attributes
    ----------
    deltas : list of (t, dL, dy)
        Information to add to the receiver's filter per state time (``new - old``).
    keys, times, seqs, info, vec : arrays
        The channel's entries after the message (sorted by key): replaces the stored arrays.
    changed : (k,) int64
        Keys whose stored value changed (the receiver's other links must send them).
    outside : int
        Blocks with information that were older than the receiver's window (ignored).
    append : bool
        The steady-state message (:meth:`ChannelFilter.plan`): ``keys .. vec`` are only the
        message's entries, which go after every stored one; the stored entries stay as they
        are (:meth:`ChannelFilter.commit` appends them in place, without copying the channel).
    """

    deltas: list[tuple[float, Array, Array]]
    keys: np.ndarray
    times: Array
    seqs: np.ndarray
    info: Array
    vec: Array
    changed: np.ndarray
    outside: int
    append: bool = False


def nonzero_blocks(info: Array, vec: Array) -> np.ndarray:
    """Per block: does ``(info[i], vec[i])`` carry any information (a non-zero entry)?

    One block (a steady-state message) is tested on Python lists, which costs less than a
    numpy reduction; the result is then a shared read-only array.
    """
    if info.shape[0] == 1:
        return _ONE_TRUE if any(info.ravel().tolist()) or any(vec.ravel().tolist()) else _ONE_FALSE
    return info.any(axis=(1, 2)) | vec.any(axis=1)


_ONE_TRUE = np.ones(1, dtype=bool)
_ONE_FALSE = np.zeros(1, dtype=bool)
_ONE_TRUE.flags.writeable = _ONE_FALSE.flags.writeable = False


def all_of(flags: np.ndarray) -> bool:
    """``flags.all()`` for a boolean array, without a numpy reduction for one element."""
    return bool(flags[0]) if flags.shape[0] == 1 else bool(flags.all())


def any_of(flags: np.ndarray) -> bool:
    """``flags.any()`` for a boolean array, without a numpy reduction for one element."""
    return bool(flags[0]) if flags.shape[0] == 1 else bool(flags.any())


_NO_KEYS = np.zeros(0, dtype=np.int64)
_NO_KEYS.flags.writeable = False


def _unique(keys: np.ndarray) -> np.ndarray:
    """The sorted distinct values of an int64 array (``np.unique`` without its Python-level
    overhead, which costs more than the work on a few dozen keys)."""
    keys = np.sort(keys)
    if keys.size > 1:
        keys = keys[np.concatenate(([True], keys[1:] != keys[:-1]))]
    return keys


def find_keys(stored: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Join ``keys`` (any order) against the increasing array ``stored``.

    Returns ``(found, pos)``: ``found[i]`` whether ``keys[i]`` is stored, and then
    ``stored[pos[i]] == keys[i]`` (elsewhere ``pos[i]`` is where it would be inserted).
    """
    pos = np.searchsorted(stored, keys)
    if not stored.size:
        return np.zeros(pos.shape, dtype=bool), pos
    return stored.take(pos, mode="clip") == keys, pos


class ChannelFilter:
    """The link to neighbour ``remote``, held by ``local``.

    Inbound: the information ``remote`` sent, per state time, as arrays sorted by time key
    (zero entries are cleared times). Outbound: what ``remote`` has acknowledged of this
    node's messages, and which times changed since.

    Attributes
    ----------
    keys, times, seqs, info, vec : arrays
        Per stored entry: time key (:func:`time_key`), time, sequence number of the
        message it came from (-1: from a previous incarnation of ``remote``) and the
        information ``(info[i], vec[i])``.
    epoch : int or None
        The incarnation of ``remote`` the entries come from.
    last_seq : int
        Newest sequence number received from ``remote`` in that incarnation (-1: none).
    applied_seq : int
        Newest sequence number from ``remote`` applied completely (what is acknowledged,
        with :meth:`received_mask`).
    seq_out : int
        Sequence number of the next message to ``remote``.
    seq_start : int
        The sequence number this channel started at (sent in every message): a channel made
        for a link that had one before in this incarnation goes on from its ``seq_out``.
    remote_start : int or None
        The ``seq_start`` of ``remote``'s newest message (``None``: nothing received yet).
    ack_floor : int
        Acknowledgements of messages below this number refer to an earlier channel, or were
        made before ``remote`` restarted or resynchronized: they are ignored.
    need_full : bool
        The next message to ``remote`` must be full.
    acked : int
        Newest of this node's messages ``remote`` acknowledged (-1: none).
    acked_at : int
        ``seq_out`` when ``acked`` last advanced (:meth:`stalled`).
    dirty : set of int
        Keys whose value for ``remote`` changed since the last message to it.
    ack_lag : int
        Acknowledgements more than this many messages behind count as stalled (:data:`ACK_LAG`).
    """

    #: Steady-state messages are planned as appends (:meth:`plan`); ``False`` (on the class or a
    #: channel): the general plan for every message (the same results; for tests and comparisons).
    append_plans: bool = True

    def __init__(self, local: str, remote: str, n: int, start: int = 0, epoch: int | None = None,
                 last_seq: int = -1) -> None:
        """``start``: the first sequence number (a channel replacing an earlier one for the link
        goes on from that one's ``seq_out``); ``epoch``, ``last_seq``: the incarnation of ``remote``
        and the newest sequence number received from it over the earlier channel (the reference of
        the sequence-jump bound; nothing it sent is kept)."""
        self.local = local
        self.remote = remote
        self.n = n
        self.keys = np.zeros(0, dtype=np.int64)
        self.times = np.zeros(0)
        self.seqs = np.zeros(0, dtype=np.int64)
        self.info = np.zeros((0, n, n))
        self.vec = np.zeros((0, n))
        self.epoch: int | None = epoch
        self.last_seq = last_seq
        self.applied_seq = -1
        self._applied_mask = 0
        self.seq_out = self.seq_start = self.ack_floor = start
        self.remote_start: int | None = None
        self.need_full = True
        self.acked = -1
        #: ``seq_out`` when :attr:`acked` last advanced: the messages sent since are those the
        #: recipient has not answered yet (:meth:`pending_keys`).
        self.acked_at = start
        self.dirty: set[int] = set()
        #: Messages the acknowledgement may lag behind before partial messages carry everything
        #: since the newest acknowledged one (:data:`ACK_LAG`; more with event-triggered sends,
        #: :class:`dfusion.fusion.sending.SendSchedule`).
        self.ack_lag = ACK_LAG
        self._resend = np.zeros(0, dtype=np.int64)
        self._sent: dict[int, tuple[np.ndarray, bool]] = {}   # seq -> (keys it may have changed, full?)
        self.messages_in = 0
        self.messages_out = 0
        self.duplicates = 0
        # the buffers the stored arrays are views of after an append (:meth:`_append`): the
        # five buffers, the views handed out and where they are, and how far the buffers are written
        self._buf: tuple | None = None
        self._views: tuple | None = None
        self._lo = self._hi = self._fill = 0

    def __repr__(self) -> str:
        return (f"ChannelFilter({self.local!r} <- {self.remote!r}, entries={len(self.keys)}, "
                f"epoch={self.epoch}, last_seq={self.last_seq}, seq_out={self.seq_out})")

    def __len__(self) -> int:
        return int(self.keys.size)

    # ------------------------------------------------------------------ inbound
    @property
    def received(self) -> dict[int, Entry]:
        """The stored non-zero entries as a dict ``{time key: Entry}`` (a snapshot, for inspection)."""
        live = nonzero_blocks(self.info, self.vec)
        return {int(self.keys[i]): Entry(float(self.times[i]), int(self.seqs[i]), self.info[i].copy(),
                                          self.vec[i].copy()) for i in np.flatnonzero(live)}

    def information(self, key: int) -> Entry | None:
        """The shared information at a state time, if any."""
        i = int(np.searchsorted(self.keys, key))
        if i < self.keys.size and self.keys[i] == key:
            return Entry(float(self.times[i]), int(self.seqs[i]), self.info[i].copy(), self.vec[i].copy())
        return None

    def lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`find_keys` of ``keys`` among the stored entries."""
        return find_keys(self.keys, keys)

    def values_at(self, keys: np.ndarray) -> tuple[Array, Array]:
        """The stored information at ``keys`` (zero where nothing is stored)."""
        info = np.zeros((keys.size, self.n, self.n))
        vec = np.zeros((keys.size, self.n))
        if self.keys.size and keys.size:
            found, pos = self.lookup(keys)
            info[found] = self.info[pos[found]]
            vec[found] = self.vec[pos[found]]
        return info, vec

    def state(self) -> tuple:
        """Everything :meth:`commit`, :meth:`acknowledged` and :meth:`record_sent` change (to undo them)."""
        return (self.keys, self.times, self.seqs, self.info, self.vec, self.epoch, self.last_seq, self.applied_seq,
                self._applied_mask, self.need_full, self.acked, set(self.dirty), self._resend, dict(self._sent), self.seq_out,
                self.messages_in, self.messages_out, self.duplicates, self.acked_at, self.seq_start, self.remote_start,
                self.ack_floor)

    def restore(self, state: tuple) -> None:
        (self.keys, self.times, self.seqs, self.info, self.vec, self.epoch, self.last_seq, self.applied_seq,
         self._applied_mask, self.need_full, self.acked, self.dirty, self._resend, self._sent, self.seq_out,
         self.messages_in, self.messages_out, self.duplicates, self.acked_at, self.seq_start, self.remote_start,
         self.ack_floor) = state

    def plan(self, msg: InfoMessage, oldest: float, time_tol: float) -> Plan:
        """What receiving ``msg`` changes, without changing anything.

        A block of time ``t`` is new (stored, its information added), replaces a stored
        entry from an older message or an older incarnation (the difference is added),
        or is ignored (the stored entry is as new: a duplicate or a reordered message).
        A cleared time, and for a full message every stored time from ``msg.start`` on
        that the message does not carry, becomes a zero entry when the stored one is
        older (its information is subtracted). Blocks older than the receiver's window
        are counted in ``outside`` and ignored.
        """
        new_epoch = msg.epoch != self.epoch
        times, info, vec = msg.times, msg.info, msg.vec
        mkeys = time_keys(times)
        if (self.append_plans and not new_epoch and not msg.full and not msg.cleared.size and mkeys.size
                and (not self.keys.size or mkeys[0] > self.keys[-1]) and times[0] >= oldest - time_tol):
            # the steady state: new blocks after every stored one, nothing cleared, nothing older
            # than the window. Every block is new, so the differences are the blocks themselves
            # and nothing stored moves: what the general plan below decides, without its joins
            # and copies (the same deltas, bit for bit: the same array rows)
            moved = nonzero_blocks(info, vec)
            deltas = [(float(times[j]), info[j], vec[j]) for j in np.flatnonzero(moved).tolist()]
            return Plan(deltas, mkeys, times, np.full(mkeys.size, msg.seq, dtype=np.int64), info, vec,
                        mkeys[moved], 0, append=True)
        seqs_now = np.full(self.keys.size, -1, dtype=np.int64) if new_epoch else self.seqs
        first = int(times.searchsorted(oldest - time_tol))
        outside = int(np.count_nonzero(nonzero_blocks(info[:first], vec[:first]))) if first else 0
        if first:
            times, info, vec, mkeys = times[first:], info[first:], vec[first:], mkeys[first:]
        if msg.full:
            held = self.keys >= time_key(msg.start) - 1
            held &= self.keys >= time_key(oldest) - 1
            absent = np.setdiff1d(self.keys[held], mkeys, assume_unique=True)
            ckeys = absent
        elif msg.cleared.size:
            ckeys = time_keys(msg.cleared)
            ckeys = ckeys[ckeys >= time_key(oldest) - 1]
        else:
            ckeys = _NO_KEYS
        # candidates: the message's blocks, then the times it clears (value zero)
        if ckeys.size:
            all_keys = np.concatenate([mkeys, ckeys])
            all_info = np.concatenate([info, np.zeros((ckeys.size, self.n, self.n))])
            all_vec = np.concatenate([vec, np.zeros((ckeys.size, self.n))])
            all_times = np.concatenate([times, ckeys / 1e9])
        else:   # the usual partial message: no concatenation (the candidates are sorted then)
            all_keys, all_info, all_vec, all_times = mkeys, info, vec, times
        found, pos = self.lookup(all_keys)
        newer = ~found
        if self.keys.size:
            newer |= seqs_now.take(pos, mode="clip") < msg.seq
        if not newer.any():
            return Plan([], self.keys, self.times, seqs_now, self.info, self.vec, np.zeros(0, dtype=np.int64),
                        outside)
        # the candidates that are newer than what is stored (usually all of them: a slice, no copies)
        idx = slice(None) if newer.all() else np.flatnonzero(newer)
        f = found[idx]
        replaced = pos[idx][f] if f.any() else _NO_KEYS
        new_info, new_vec, new_keys = all_info[idx], all_vec[idx], all_keys[idx]
        if replaced.size:
            old_info = np.zeros((new_keys.size, self.n, self.n))
            old_vec = np.zeros((new_keys.size, self.n))
            old_info[f] = self.info[replaced]
            old_vec[f] = self.vec[replaced]
            d_info = new_info - old_info
            d_vec = new_vec - old_vec
        else:   # nothing stored is replaced: the differences are the blocks (x - 0 is x, bit for bit)
            d_info, d_vec = new_info, new_vec   # the plan's arrays below are concatenated copies
        moved = nonzero_blocks(d_info, d_vec)
        new_times = all_times[idx]
        deltas = [(float(new_times[j]), d_info[j], d_vec[j]) for j in np.flatnonzero(moved).tolist()]
        # the new arrays: stored entries not touched, plus the message's newer ones
        seq_col = np.full(new_keys.size, msg.seq, dtype=np.int64)
        if replaced.size:
            keep = np.ones(self.keys.size, dtype=bool)
            keep[replaced] = False
            old = (self.keys[keep], self.times[keep], seqs_now[keep], self.info[keep], self.vec[keep])
        else:
            old = (self.keys, self.times, seqs_now, self.info, self.vec)
        cols = [np.concatenate([o, n]) for o, n in zip(old, (new_keys, new_times, seq_col, new_info, new_vec))]
        # new entries after every stored one (the newest state's block) are in order already
        # (candidates are sorted when nothing is cleared; keys are distinct)
        if ckeys.size or (old[0].size and new_keys[0] <= old[0][-1]):
            order = np.argsort(cols[0], kind="stable")
            cols = [c[order] for c in cols]
        return Plan(deltas, *cols, new_keys[moved], outside)

    def commit(self, msg: InfoMessage, plan: Plan | None, complete: bool = True) -> None:
        """Store what :meth:`plan` decided (``None``: only note that ``msg`` arrived).

        ``complete``: every block of the message was applied (none was held back for
        being too far ahead), so the message may be acknowledged.
        """
        if msg.epoch != self.epoch:
            self.epoch = msg.epoch
            self.last_seq = self.applied_seq = -1
            self._applied_mask = 0
        if msg.seq > self.last_seq:
            self.remote_start = msg.seq_start
            self.last_seq = msg.seq
        if complete:
            self.note_applied(msg.seq)
        self.messages_in += 1
        if plan is not None:
            if plan.append:
                self._append(plan.keys, plan.times, plan.seqs, plan.info, plan.vec)
            else:
                self.keys, self.times, self.seqs, self.info, self.vec = plan.keys, plan.times, plan.seqs, plan.info, plan.vec

    def _is_tail(self) -> bool:
        """Whether the stored arrays are the views :meth:`_append` or :meth:`prune` made of the buffers."""
        v = self._views
        return (v is not None and self.keys is v[0] and self.times is v[1] and self.seqs is v[2]
                and self.info is v[3] and self.vec is v[4])

    def _append(self, keys: np.ndarray, times: Array, seqs: np.ndarray, info: Array, vec: Array) -> None:
        """Store entries that come after every stored one.

        The stored arrays are then views ``[lo, hi)`` of buffers with room to grow: when they
        still are the views the last append or prune made and nothing was written after
        them, the entries go into the spare room and the views grow, copying nothing. A
        snapshot (:meth:`state`) holds views that end at or before ``hi``, which are never
        written again, so it stays valid; after anything else replaced the arrays (a general
        plan, :meth:`restore`), they are copied into new buffers first.
        """
        m = keys.size
        old = (self.keys, self.times, self.seqs, self.info, self.vec)
        buf = self._buf
        if not self._is_tail() or self._hi != self._fill or self._hi + m > buf[0].shape[0]:
            size = old[0].shape[0]
            cap = max(8, 2 * (size + m))
            buf = tuple(np.empty((cap,) + a.shape[1:], dtype=a.dtype) for a in old)
            for b, a in zip(buf, old):
                b[:size] = a
            self._buf, self._lo, self._hi = buf, 0, size
        lo, hi = self._lo, self._hi
        for b, a in zip(buf, (keys, times, seqs, info, vec)):
            b[hi:hi + m] = a
        hi += m
        self._hi = self._fill = hi
        views = tuple(b[lo:hi] for b in buf)
        self.keys, self.times, self.seqs, self.info, self.vec = views
        self._views = views

    def prune(self, oldest_key: int) -> None:
        """Forget entries of states older than the window (already in the base)."""
        if self.keys.size and self.keys[0] < oldest_key:
            # the keys are sorted: the entries kept are a tail (views; the arrays are only ever replaced)
            i = int(self.keys.searchsorted(oldest_key))
            tail = self._is_tail()
            self.keys, self.times, self.seqs = self.keys[i:], self.times[i:], self.seqs[i:]
            self.info, self.vec = self.info[i:], self.vec[i:]
            if tail:   # still the buffers' views (a shorter tail of them): appends may go on in place
                self._lo += i
                self._views = (self.keys, self.times, self.seqs, self.info, self.vec)
        if self.dirty and min(self.dirty) < oldest_key:
            self.dirty = {k for k in self.dirty if k >= oldest_key}

    # ------------------------------------------------------------------ outbound
    def received_mask(self) -> int:
        """The selective acknowledgement to send: bit ``k`` set when message ``applied_seq - 1 - k``
        was applied completely."""
        return self._applied_mask

    def was_applied(self, seq: int) -> bool:
        """Whether message ``seq`` of the current incarnation cannot be new: it was applied
        completely already (``applied_seq``, or a set bit of the mask of the
        :data:`REPLAY_WINDOW` before it), or it is older than that window. The receiver discards
        it before any work (counted in ``NodeStats.duplicates``): a replay, or a network
        duplicate, would change nothing anyway (every block stored is newer). The sender
        takes a message of the current incarnation that falls out of the window unacknowledged as
        lost and sends its times again (:meth:`acknowledged`), so rejecting it loses nothing.
        (The sliding window of IPsec, RFC 4303 section 3.4.3, and DTLS, RFC 6347 section 4.1.2.6.)
        """
        top = self.applied_seq
        if top < 0 or seq > top:
            return False
        if seq == top or top - seq > REPLAY_WINDOW:
            return True
        return bool((self._applied_mask >> (top - seq - 1)) & 1)

    def note_applied(self, seq: int) -> None:
        """Message ``seq`` of the current incarnation was applied completely."""
        top = self.applied_seq
        if seq > top:
            shift = seq - top
            # a jump of more than the window leaves nothing of the old mask in it: never shift a
            # Python integer by an unbounded (peer-chosen) number of bits
            if top < 0 or shift > REPLAY_WINDOW:
                self._applied_mask = 0
            else:
                self._applied_mask = ((self._applied_mask << shift) | (1 << (shift - 1))) & _MASK64
            self.applied_seq = seq
        elif seq < top and top - seq <= 64:
            self._applied_mask |= 1 << (top - seq - 1)

    def acknowledged(self, ack: int, mask: int) -> None:
        """``remote`` acknowledged this node's messages: ``ack`` and, by ``mask``, some of the 64
        before it. Messages up to ``ack`` it did not acknowledge are taken as lost: the times
        they carried are sent again (:meth:`pending_keys`); a lost full message makes the next
        one full."""
        if ack < self.ack_floor or ack >= self.seq_out:
            return
        if ack > self.acked:
            self.acked_at = self.seq_out
        self.acked = max(self.acked, ack)
        for s in [s for s in self._sent if s <= ack]:
            keys, full = self._sent.pop(s)
            got = s == ack or (ack - s <= 64 and (mask >> (ack - s - 1)) & 1)
            if not got:
                if full:
                    self.need_full = True
                self._resend = np.union1d(self._resend, keys)

    def remote_restarted(self) -> None:
        """``remote`` holds nothing of this node's (a new incarnation, or it started a fresh channel
        for the link): forget its acknowledgements, including those still under way (below
        :attr:`ack_floor`); the next message is full."""
        self.need_full = True
        self.acked = -1
        self.acked_at = self.ack_floor = self.seq_out
        self._sent.clear()
        self._resend = np.zeros(0, dtype=np.int64)

    def follow_remote(self, forgot: bool, reverted: bool = False) -> None:
        """After a message was committed: ``forgot``, the sender holds nothing of this node's (it
        restarted, or started a fresh channel: :meth:`remote_restarted`); ``reverted``, the link
        went back to an incarnation of the sender that a newer one had replaced (without a key,
        :mod:`dfusion.fusion.incarnation`): what this node holds from it may have been replaced by
        the other one's messages, so this end starts afresh too (a new :attr:`seq_start`), and
        the sender, seeing it, sends a full message."""
        if forgot:
            self.remote_restarted()
        if reverted:
            self.seq_start = self.seq_out

    def remote_resynchronizes(self, msg: InfoMessage) -> bool:
        """Whether ``msg`` (of ``remote``'s current incarnation) shows that ``remote`` started a
        fresh channel for the link since its previous message: a new ``seq_start`` on a message
        newer than any received (a reordered message of the earlier channel does not count)."""
        return (self.remote_start is not None and msg.seq_start != self.remote_start and msg.epoch == self.epoch
                and msg.seq > self.last_seq)

    def next_is_full(self) -> bool:
        """Whether the next message must be full (first one, after a restart or a lost full one,
        or too many unacknowledged messages)."""
        return self.need_full or len(self._sent) > MAX_UNACKED

    def stalled(self) -> bool:
        """Whether the next partial message carries everything sent since the newest acknowledged
        message (the catch-up): nothing was acknowledged yet, or the acknowledgements have
        *stalled*: the newest acknowledged message is more than ``ack_lag`` messages old **and**
        no acknowledgement advanced during the last ``ack_lag + 1`` messages (a link outage, say).
        A recipient whose acknowledgements keep advancing but lag behind (alive, busy: a CPU-starved
        process working through a queue) is sent what changed only; a loss among the messages it
        has not answered yet shows in its next acknowledgements, whose times are then sent again
        (the resend backoff: ``docs/fusion.md``)."""
        if self.acked < 0:
            return True
        return self.lag() > self.ack_lag and self.seq_out - self.acked_at > self.ack_lag

    def lag(self) -> int:
        """Messages sent since the newest acknowledged one (all of them while none was
        acknowledged)."""
        return self.seq_out - 1 - self.acked

    def pending_keys(self, oldest_key: int) -> np.ndarray:
        """Times a partial message must carry: changed since the last message, or carried by a
        message that turned out lost; and, while the acknowledgements are stalled
        (:meth:`stalled`: nothing acknowledged yet, or no acknowledgement for more than
        ``ack_lag`` messages: a link outage, say), every time carried since the
        newest acknowledged message (sorted keys from ``oldest_key`` on)."""
        parts = [self._resend]
        if self.stalled():
            parts += [keys for keys, _ in self._sent.values()]
        parts = [p for p in parts if p.size]
        if not parts:   # the steady state: what changed since the last message only
            keys = sorted(k for k in self.dirty if k >= oldest_key)
            return np.array(keys, dtype=np.int64) if keys else np.zeros(0, dtype=np.int64)
        keys = _unique(np.concatenate(parts + [np.fromiter(self.dirty, dtype=np.int64, count=len(self.dirty))]))
        return keys[keys >= oldest_key]

    def at_risk_keys(self, edge_key: int) -> np.ndarray:
        """While the acknowledgements lag more than ``ack_lag`` messages behind without stalling
        (a busy recipient, :meth:`stalled`), the times up to ``edge_key`` of the messages not
        acknowledged yet (sorted): those that would leave the window before an acknowledgement
        could show them lost. :meth:`FusionNode.message_to
        <dfusion.fusion.node.FusionNode.message_to>` carries them again in every message (the
        window state ``lag + 1`` from the oldest is the edge) and leaves them out of that
        message's record (:meth:`record_sent`): they are the values already sent, tracked by
        the record of the message that first carried them, so they stop once it is acknowledged
        (or are sent again as lost)."""
        if self.acked < 0 or self.lag() <= self.ack_lag or self.stalled():
            return _NO_KEYS
        parts = [k[k <= edge_key] for k, _ in self._sent.values()]
        parts = [p for p in parts if p.size]
        return _unique(np.concatenate(parts)) if parts else _NO_KEYS

    def record_sent(self, seq: int, keys: np.ndarray, full: bool) -> None:
        """Remember the times message ``seq`` may have changed at ``remote`` (what it carried or
        cleared, and the times that changed since the previous message); reset the dirty and
        resend sets."""
        if self.dirty and not self.dirty.issubset(keys.tolist()):
            keys = _unique(np.concatenate([keys, np.fromiter(self.dirty, dtype=np.int64, count=len(self.dirty))]))
        if full:
            self._sent.clear()
            self.need_full = False
        self._sent[seq] = (keys, full)
        self.dirty = set()
        self._resend = np.zeros(0, dtype=np.int64)
        self.seq_out = seq + 1
        self.messages_out += 1
