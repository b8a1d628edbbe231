r"""The channel filter of one link: the information both ends already share.

Fusion rule on a tree (Grime & Durrant-Whyte, "Data fusion in decentralized
sensor networks", Control Eng. Practice 1994; URUS paper, sec. 6)::

    Omega_i <- Omega_i + sum_j (Omega_j - Omega_ij),   eta likewise,

with ``(Omega_ij, eta_ij)`` the channel filter of link ``i-j``. dfusion keeps the
trajectory's information split by state time, and only single-state factors
(measurements) ever differ between nodes: prior and motion factors are common.
The channel filter of ``i`` for link ``i-j`` therefore stores, per state time
``t``, the latest single-state information ``M_ij(t)`` that ``j`` sent: the part
of ``j``'s belief that ``i`` now shares. Node ``i`` sends ``j``

    msg_{i->j}(t) = T_i(t) - M_ij(t),   T_i(t) = own_i(t) + sum_k M_ik(t),

that is, everything it knows that did not come from ``j`` (``docs/background.md#2-fusion-on-a-tree``,
"an equivalent view on trees"). When ``j`` receives it, the block of time ``t``
*replaces* the previous one from ``i``: ``j`` adds ``msg(t) - M_ji(t)`` to its
filter. Each entry records the sequence number of the message it came from; an
entry is only replaced by one from a newer message. Consequences:

* duplicates and reordered (older) messages change nothing;
* a lost message loses nothing for good: the next one carries the same times;
* crossing messages cannot double count: neither side's message contains what
  it received from the other;
* times older than the sender's window (``start``) are kept as they are: the
  sender dropped them, the receiver may still hold them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dfusion.linalg import Array
from dfusion.wire import InfoMessage


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


@dataclass(frozen=True)
class Plan:
    """What receiving one message changes (see :meth:`ChannelFilter.plan`).

    Attributes
    ----------
    deltas : list of (t, dL, dy)
        Information to add to the receiver's filter per state time (``new - old``).
    keys, times, info, vec : arrays
        The message blocks to store (with the message's sequence number), sorted by key.
    drop : (k,) int64
        Keys of stored entries the sender no longer holds information for.
    outside : int
        Blocks with information that were older than the receiver's window.
    """

    deltas: list[tuple[float, Array, Array]]
    keys: np.ndarray
    times: Array
    info: Array
    vec: Array
    drop: np.ndarray
    outside: int


def time_keys(times: Array) -> np.ndarray:
    """:func:`time_key` of an array of times (both round half to even)."""
    return np.rint(np.asarray(times, dtype=float) * 1e9).astype(np.int64)


def nonzero_blocks(info: Array, vec: Array) -> np.ndarray:
    """Per block: does ``(info[i], vec[i])`` carry any information (a non-zero entry)?"""
    return info.any(axis=(1, 2)) | vec.any(axis=1)


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
    """Information shared with neighbour ``remote`` over one link (held by ``local``).

    The entries are stored as arrays sorted by time key, so that planning a message
    of ``m`` blocks costs a few vectorized operations (a ``searchsorted`` join)
    instead of ``m`` Python steps.

    Attributes
    ----------
    local, remote : str
        The node holding the filter and its neighbour.
    keys : (k,) int64
        Time keys (:func:`time_key`) of the stored entries, increasing.
    times, seqs, info, vec : arrays
        Per entry: the state time, the sequence number of the message it came from
        (-1: from a previous incarnation of ``remote``), and the information
        ``(info[i], vec[i])`` that ``remote`` sent for that time.
    epoch : int or None
        The incarnation of ``remote`` the entries come from.
    last_seq : int
        Newest sequence number received from ``remote`` (-1: none).
    seq_out : int
        Sequence number of the next message to ``remote``.
    """

    def __init__(self, local: str, remote: str) -> None:
        self.local = local
        self.remote = remote
        self.keys = np.zeros(0, dtype=np.int64)
        self.times = np.zeros(0)
        self.seqs = np.zeros(0, dtype=np.int64)
        self.info: Array | None = None
        self.vec: Array | None = None
        self.epoch: int | None = None
        self.last_seq = -1
        self.seq_out = 0
        self.messages_in = 0
        self.messages_out = 0
        self.duplicates = 0

    def __repr__(self) -> str:
        return (f"ChannelFilter({self.local!r} <- {self.remote!r}, entries={len(self.keys)}, "
                f"epoch={self.epoch}, last_seq={self.last_seq}, seq_out={self.seq_out})")

    def __len__(self) -> int:
        return int(self.keys.size)

    @property
    def received(self) -> dict[int, Entry]:
        """The stored entries as a dict ``{time key: Entry}`` (a snapshot, for inspection)."""
        if not self.keys.size:
            return {}
        return {int(k): Entry(float(t), int(q), self.info[i].copy(), self.vec[i].copy())
                for i, (k, t, q) in enumerate(zip(self.keys, self.times, self.seqs))}

    def information(self, key: int) -> Entry | None:
        """The shared information at a state time, if any."""
        i = int(np.searchsorted(self.keys, key))
        if i < self.keys.size and self.keys[i] == key:
            return Entry(float(self.times[i]), int(self.seqs[i]), self.info[i].copy(), self.vec[i].copy())
        return None

    def lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`find_keys` of ``keys`` among the stored entries."""
        return find_keys(self.keys, keys)

    def plan(self, msg: InfoMessage, oldest: float, time_tol: float) -> Plan:
        """What receiving ``msg`` changes, without changing anything.

        A block of time ``t`` is new (stored, its information added), replaces a
        stored entry from an older message or an older incarnation (the difference
        is added), or is ignored (the stored entry is as new: a duplicate or a
        reordered message). Stored entries at times the sender still holds
        (``t >= msg.start``) but sent nothing for are removed (their information
        is subtracted). Blocks older than the receiver's window are counted in
        ``outside`` and ignored.
        """
        new_epoch = msg.epoch != self.epoch
        times, info, vec = msg.times, msg.info, msg.vec
        nonzero = nonzero_blocks(info, vec)
        mkeys = time_keys(times)
        found_all, pos_all = self.lookup(mkeys)
        found, pos = found_all, pos_all
        # times increase: the blocks inside the receiver's window are a suffix
        first = int(times.searchsorted(oldest - time_tol))
        outside = int(np.count_nonzero(nonzero[:first])) if first else 0
        if first:
            times, info, vec, nonzero = times[first:], info[first:], vec[first:], nonzero[first:]
            mkeys, found, pos = mkeys[first:], found[first:], pos[first:]
        fresh = nonzero & ~found
        if new_epoch or not self.keys.size:
            replace = found
        else:
            replace = found & (self.seqs.take(pos, mode="clip") < msg.seq)
        deltas: list[tuple[float, Array, Array]] = [
            (t, info[i], vec[i]) for i, t in zip(fresh.nonzero()[0].tolist(), times[fresh].tolist())
        ]
        ri = replace.nonzero()[0]
        if ri.size:
            oi = pos[ri]
            dL = info[ri] - self.info[oi]
            dy = vec[ri] - self.vec[oi]
            for j in nonzero_blocks(dL, dy).nonzero()[0].tolist():
                deltas.append((float(times[ri[j]]), dL[j], dy[j]))
        store = fresh | replace
        # times the sender still holds but sent nothing for: its information there is now zero
        drop = np.zeros(0, dtype=np.int64)
        if self.keys.size:
            gone = self.times >= msg.start - time_tol
            gone[pos_all[found_all]] = False
            if not new_epoch:
                gone &= self.seqs < msg.seq
            gi = gone.nonzero()[0]
            if gi.size:
                for i in gi.tolist():
                    deltas.append((float(self.times[i]), -self.info[i], -self.vec[i]))
                drop = self.keys[gi]
        if store.all():
            return Plan(deltas, mkeys, times, info, vec, drop, outside)
        return Plan(deltas, mkeys[store], times[store], info[store], vec[store], drop, outside)

    def commit(self, msg: InfoMessage, plan: Plan | None) -> None:
        """Store what :meth:`plan` decided (``None``: only note that ``msg`` arrived)."""
        if msg.epoch != self.epoch:
            # entries of the previous incarnation count as older than any new message
            self.seqs = np.full(self.keys.size, -1, dtype=np.int64)
            self.epoch = msg.epoch
            self.last_seq = -1
        self.last_seq = max(self.last_seq, msg.seq)
        self.messages_in += 1
        if plan is None:
            return
        n = msg.vec.shape[1]
        if self.info is None:
            self.info, self.vec = np.zeros((0, n, n)), np.zeros((0, n))
        seqs = np.full(plan.keys.size, msg.seq, dtype=np.int64)
        keep = self._kept(plan)
        if not keep.any():
            # the usual case: the message replaces every stored entry
            self.keys, self.times, self.seqs = plan.keys, plan.times, seqs
            self.info, self.vec = plan.info, plan.vec
            return
        keys = np.concatenate([self.keys[keep], plan.keys])
        order = np.argsort(keys, kind="stable")
        self.keys = keys[order]
        self.times = np.concatenate([self.times[keep], plan.times])[order]
        self.seqs = np.concatenate([self.seqs[keep], seqs])[order]
        self.info = np.concatenate([self.info[keep], plan.info])[order]
        self.vec = np.concatenate([self.vec[keep], plan.vec])[order]

    def _kept(self, plan: Plan) -> np.ndarray:
        """Mask of the stored entries that ``plan`` neither replaces nor drops."""
        keep = np.ones(self.keys.size, dtype=bool)
        for keys in (plan.drop, plan.keys):
            if keys.size and self.keys.size:
                found, pos = self.lookup(keys)
                keep[pos[found]] = False
        return keep

    def prune(self, oldest_key: int) -> None:
        """Forget entries of states older than the window (already in the base)."""
        if self.keys.size and self.keys[0] < oldest_key:
            keep = self.keys >= oldest_key
            self.keys, self.times, self.seqs = self.keys[keep], self.times[keep], self.seqs[keep]
            self.info, self.vec = self.info[keep], self.vec[keep]
