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

that is, everything it knows that did not come from ``j`` (DESIGN.md sec. 3,
"the equivalent view on trees"). When ``j`` receives it, the block of time ``t``
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

from dataclasses import dataclass, field

import numpy as np

from ..linalg import Array
from ..wire import InfoMessage


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


@dataclass
class ChannelFilter:
    """Information shared with neighbour ``remote`` over one link (held by ``local``).

    Attributes
    ----------
    local, remote : str
        The node holding the filter and its neighbour.
    received : dict[int, Entry]
        Per state time (nanosecond key), the latest information ``remote`` sent.
    epoch : int or None
        The incarnation of ``remote`` the entries come from.
    last_seq : int
        Newest sequence number received from ``remote`` (-1: none).
    seq_out : int
        Sequence number of the next message to ``remote``.
    """

    local: str
    remote: str
    received: dict[int, Entry] = field(default_factory=dict)
    epoch: int | None = None
    last_seq: int = -1
    seq_out: int = 0
    messages_in: int = 0
    messages_out: int = 0
    duplicates: int = 0

    def information(self, key: int) -> Entry | None:
        """The shared information at a state time, if any."""
        return self.received.get(key)

    def plan(self, msg: InfoMessage, oldest: float, time_tol: float) -> tuple[list[tuple[float, Array, Array]], dict[int, Entry | None], int]:
        """What receiving ``msg`` changes, without changing anything.

        Returns ``(deltas, updates, stale)``: the information to add to the
        receiver's filter per time (``new - old``), the entries to store
        (``None`` deletes), and how many blocks were too old for the window.
        """
        new_epoch = msg.epoch != self.epoch
        deltas: list[tuple[float, Array, Array]] = []
        updates: dict[int, Entry | None] = {}
        times = msg.times.tolist()
        keys = [time_key(t) for t in times]
        seen = set(keys)
        nonzero = msg.info.any(axis=(1, 2)) | msg.vec.any(axis=1)
        in_window = msg.times >= oldest - time_tol
        outside = int(np.count_nonzero(nonzero & ~in_window))
        fresh, replace, olds = [], [], []
        for i, key in enumerate(keys):
            if not in_window[i]:
                continue
            old = self.received.get(key)
            if old is None:
                if nonzero[i]:
                    fresh.append(i)
            elif new_epoch or old.seq < msg.seq:
                replace.append(i)
                olds.append(old)
        for i in fresh:
            deltas.append((times[i], msg.info[i], msg.vec[i]))
            updates[keys[i]] = Entry(times[i], msg.seq, msg.info[i], msg.vec[i])
        if replace:
            old_info = np.array([o.info for o in olds])
            old_vec = np.array([o.vec for o in olds])
            dL = msg.info[replace] - old_info
            dy = msg.vec[replace] - old_vec
            changed = dL.any(axis=(1, 2)) | dy.any(axis=1)
            for j, i in enumerate(replace):
                if changed[j]:
                    deltas.append((times[i], dL[j], dy[j]))
                updates[keys[i]] = Entry(times[i], msg.seq, msg.info[i], msg.vec[i])
        # times the sender still holds but sent nothing for: its information there is now zero
        for key, old in self.received.items():
            if key in seen or old.t < msg.start - time_tol:
                continue
            if new_epoch or old.seq < msg.seq:
                deltas.append((old.t, -old.info, -old.vec))
                updates[key] = None
        return deltas, updates, outside

    def commit(self, msg: InfoMessage, updates: dict[int, Entry | None]) -> None:
        """Store what :meth:`plan` decided."""
        if msg.epoch != self.epoch:
            # entries of the previous incarnation count as older than any new message
            self.received = {k: Entry(e.t, -1, e.info, e.vec) for k, e in self.received.items()}
            self.epoch = msg.epoch
            self.last_seq = -1
        for key, e in updates.items():
            if e is None:
                self.received.pop(key, None)
            else:
                self.received[key] = e
        self.last_seq = max(self.last_seq, msg.seq)
        self.messages_in += 1

    def prune(self, oldest_key: int) -> None:
        """Forget entries of states older than the window (already in the base)."""
        for key in [k for k in self.received if k < oldest_key]:
            del self.received[key]
