"""A fusion node: a delayed-state EIF, one channel filter per neighbour, a policy.

Every node of a tree runs the same motion model from the same prior. Its
belief is that common part plus single-state information: its own
measurements and what its neighbours sent (see :mod:`dfusion.fusion.channel`
for the protocol: full messages, partial ones with what changed, selective
acknowledgements, and why it neither double counts nor loses information).

**Receiving is transactional.** :meth:`FusionNode.receive` decodes and validates the
whole message (:func:`dfusion.wire.decode`), checks it against the node (recipient,
neighbour, dimension, incarnation, sequence number, base), plans every change without
making it (:meth:`ChannelFilter.plan`), and only then applies the plan to the filter, the
channel and the node's stores, undoing all of it if anything raises on the way: a
message is either fused completely or leaves the node exactly as it was. A rejected
message is counted by reason in ``stats.rejections``; rejections are logged at most once
per ``log_interval`` seconds, as one summary line with the counts by reason.

**Bounded resources.** Frames longer than ``max_message_bytes`` are rejected before they
are parsed; information for state times more than ``max_ahead`` seconds ahead of the
node's newest state, or beyond ``max_held`` held-back times, is not stored (counted in
``stats.blocks_too_far_ahead``; the message is then not acknowledged, so its sender
sends those times again).

Information for state times ahead of the node's newest state is held back and
added when :meth:`FusionNode.predict` reaches them, so a node never moves its
trajectory forward on a neighbour's clock. Information for times older than
the node's window cannot be added any more: it is dropped and counted in
``stats.blocks_outside_window`` (conservative, never over-confident; choose the window
with :func:`dfusion.topology.minimum_window` to avoid it).

**Links that change** (``tree=SpanningTree(...)``, :mod:`dfusion.fusion.tree`). The node
is told which links exist (:meth:`FusionNode.link_up`, :meth:`FusionNode.link_down`) and
keeps the fusion links a tree with its neighbours by the tree rule: every message carries
the node's tree epoch and parent, fusion messages go over tree links and beacons over the
others (:meth:`FusionNode.outgoing`). When the rule changes the tree the node withdraws
what came over the links that left it (everything, when it enters a new epoch) and starts
fresh channels on the links that joined it (``docs/dynamic-topology.md``). A fresh channel
numbers its messages on from the link's previous one and announces its start, so that a
neighbour that noticed nothing resynchronizes with it (:mod:`dfusion.fusion.channel`).

**Consistency test and quarantine** (``guard=``, off by default; on in scenarios through
``[protection]``): the blocks a message adds are tested jointly against the node's belief
inside the receive transaction, and a neighbour that keeps failing is quarantined: what
came over its link is withdrawn from the filter and from what the node shares, and the
withdrawn times are marked changed on the other links (:mod:`dfusion.fusion.guard`).

**Own information held back or withdrawn.** ``update(..., share=False)`` and
``add_local_information(..., share=False)`` fuse information here without sharing it (a
camera's tentative frame); :meth:`FusionNode.share_local_information` shares it later and
:meth:`FusionNode.withdraw_local_information` removes own information. Both mark the time
changed on every link, so the next partial messages carry the new value (or clear the
time), and the neighbours replace what they stored.

``fusion="naive"`` is fusion without channel filters, kept for comparison only:
each message carries everything the sender learned since its previous message
to that neighbour (including what came from the recipient) and the receiver
adds it. Information echoes back and forth and is counted again and again: the
rumour-propagation failure the channel filter prevents.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import DfusionError, MessageError, OutsideWindowError, ValidationError
from dfusion.estimation.delayed_state import DelayedStateEIF
from dfusion.estimation.estimate import Estimate
from dfusion.fusion.guard import (GuardConfig, LinkRecord, NeighbourGuard, block_eigen, information_statistic,
                                  split_blocks)
from dfusion.fusion.channel import (
    ACK_LAG,
    all_of,
    any_of,
    MAX_SEQ_JUMP,
    ChannelFilter,
    find_keys,
    nonzero_blocks,
    time_key,
    time_keys,
)
from dfusion.fusion.incarnation import Incarnations
from dfusion.fusion.tree import SpanningTree, TreeChange, TreeEpoch
from dfusion.linalg import Array, as_matrix, as_time, as_vector, check_psd, symmetrize
from dfusion.models.base import MeasurementModel, MotionModel
from dfusion.policies.base import InformationFusionPolicy, Policy
from dfusion.wire import MAX_MESSAGE_BYTES, FrameKey, InfoMessage, check_frame, decode, encode

log = logging.getLogger(__name__)

FUSION_MODES = ("channel", "naive")
#: ``"partial"``: what changed (the protocol); ``"full"``: the whole window in every message,
#: as the previous protocol did (for comparison: ``benchmarks/scale.py``).
MESSAGE_MODES = ("partial", "full")
#: Default bounds of a node (see the module docstring).
MAX_AHEAD = 10.0
LOG_INTERVAL = 10.0
#: Default ``hold`` (seconds): how long information a change of the tree took stays in a node's estimate.
HOLD = 10.0
#: Relative tolerance of "R(t) holds at least as much as L(t)" (rounding of sums of blocks).
HELD_RTOL = 1e-9


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


@dataclass
class _Info:
    t: float
    info: Array
    vec: Array


class _Blocks:
    """Single-state information per state time, as arrays sorted by time key.

    The node's own and total information (see the module docstring). Kept as
    arrays, like :class:`ChannelFilter`, so that a message is built with a few
    array operations instead of one Python step per state time. The entries live
    in ``[lo, hi)`` of buffers with spare room at the end: the usual changes
    (a new newest time, pruning the oldest) then copy nothing. The buffers are
    owned by the store and added to in place; what it hands out is a view to
    read at once (:attr:`keys` ...) or a copy.
    """

    def __init__(self, n: int) -> None:
        self._set(np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, n, n)), np.zeros((0, n)))

    def _set(self, keys: np.ndarray, times: Array, info: Array, vec: Array) -> None:
        """Hold these entries (sorted by key) in new buffers with room to grow."""
        size = keys.shape[0]
        cap = max(8, 2 * size)
        self._keys = np.zeros(cap, dtype=np.int64)
        self._times = np.zeros(cap)
        self._info = np.zeros((cap,) + info.shape[1:])
        self._vec = np.zeros((cap,) + vec.shape[1:])
        self._keys[:size], self._times[:size], self._info[:size], self._vec[:size] = keys, times, info, vec
        self._lo, self._hi = 0, size
        self._shared = False   # a mark() holds these buffers: copy them before writing into them

    def _writable(self) -> None:
        """Copy the buffers if a :meth:`mark` still refers to them (copy on write)."""
        if self._shared:
            self._keys, self._times = self._keys.copy(), self._times.copy()
            self._info, self._vec = self._info.copy(), self._vec.copy()
            self._shared = False

    @property
    def keys(self) -> np.ndarray:
        return self._keys[self._lo:self._hi]

    @property
    def times(self) -> Array:
        return self._times[self._lo:self._hi]

    @property
    def info(self) -> Array:
        return self._info[self._lo:self._hi]

    @property
    def vec(self) -> Array:
        return self._vec[self._lo:self._hi]

    def __len__(self) -> int:
        return self._hi - self._lo

    def items(self) -> list[tuple[int, _Info]]:
        """``(time key, _Info)`` pairs, oldest first (copies, for inspection)."""
        info, vec = self.info, self.vec
        return [(k, _Info(t, info[i].copy(), vec[i].copy()))
                for i, (k, t) in enumerate(zip(self.keys.tolist(), self.times.tolist()))]

    def add(self, t: float, info: Array, vec: Array) -> None:
        """Add ``(info, vec)`` at state time ``t`` (a new entry if there is none)."""
        key = time_key(t)
        keys = self.keys
        i = int(keys.searchsorted(key))
        j = self._lo + i
        if i < keys.size and keys[i] == key:
            self._writable()
            self._info[j] += info
            self._vec[j] += vec
        elif j == self._hi and j < self._keys.size:
            # a new newest entry goes into the spare room after the entries: a mark's entries
            # (up to its own end) are not written, so nothing needs copying
            self._keys[j], self._times[j], self._info[j], self._vec[j] = key, t, info, vec
            self._hi += 1
        else:
            self._set(*(np.concatenate((a[:i], np.asarray(row, dtype=a.dtype)[None], a[i:]))
                        for a, row in ((keys, key), (self.times, t), (self.info, info), (self.vec, vec))))

    def add_many(self, entries: Sequence[tuple[float, Array, Array]]) -> None:
        """Add every ``(t, info, vec)`` of ``entries`` (distinct times)."""
        if len(entries) < 4:
            for t, info, vec in entries:
                self.add(t, info, vec)
            return
        times = np.array([e[0] for e in entries], dtype=float)
        keys = time_keys(times)
        info = np.array([e[1] for e in entries], dtype=float)
        vec = np.array([e[2] for e in entries], dtype=float)
        found, pos = find_keys(self.keys, keys)
        if found.any():
            self._writable()
            self._info[self._lo + pos[found]] += info[found]
            self._vec[self._lo + pos[found]] += vec[found]
        new = ~found
        if new.any():
            keys = np.concatenate([self.keys, keys[new]])
            order = np.argsort(keys, kind="stable")
            self._set(keys[order], np.concatenate([self.times, times[new]])[order],
                      np.concatenate([self.info, info[new]])[order], np.concatenate([self.vec, vec[new]])[order])

    def subtract(self, entries: Sequence[tuple[float, Array, Array]]) -> np.ndarray:
        """Subtract ``(info, vec)`` at stored state times (information withdrawn or moved to
        another store), removing the rounding noise of the difference (:func:`_clean_difference`).
        Entries at times not stored are ignored. Returns the keys changed."""
        if not entries:
            return np.zeros(0, dtype=np.int64)
        keys = time_keys(np.array([e[0] for e in entries], dtype=float))
        found, pos = find_keys(self.keys, keys)
        if not found.any():
            return np.zeros(0, dtype=np.int64)
        self._writable()
        rows = self._lo + pos[found]
        info = np.array([e[1] for e in entries], dtype=float)[found]
        vec = np.array([e[2] for e in entries], dtype=float)[found]
        scale = np.abs(self._info[rows]).max(axis=(1, 2))
        vscale = np.abs(self._vec[rows]).max(axis=1)
        self._info[rows] = _clean_difference(self._info[rows] - info, scale)
        v = self._vec[rows] - vec
        v[np.abs(v) <= (ROUNDING_RTOL * vscale)[:, None]] = 0.0
        self._vec[rows] = v
        return keys[found]

    def prune(self, cutoff: int) -> None:
        """Forget the entries whose key is below ``cutoff``."""
        if self._lo < self._hi and self._keys[self._lo] < cutoff:
            self._lo += int(self.keys.searchsorted(cutoff))

    def values_at(self, keys: np.ndarray) -> tuple[Array, Array]:
        """The information at ``keys`` (zero where nothing is stored)."""
        n = self._info.shape[1]
        if len(self) and keys.size:
            found, pos = find_keys(self.keys, keys)
            if all_of(found):   # (the usual case: a message's times are stored times)
                return self.info[pos], self.vec[pos]
            info = np.zeros((keys.size, n, n))
            vec = np.zeros((keys.size, n))
            info[found] = self.info[pos[found]]
            vec[found] = self.vec[pos[found]]
            return info, vec
        return np.zeros((keys.size, n, n)), np.zeros((keys.size, n))

    def count_after(self, key: int) -> int:
        """Entries with a key above ``key``."""
        return int(len(self) - self.keys.searchsorted(key, side="right"))

    def checkpoint(self) -> tuple[np.ndarray, Array, Array, Array]:
        """Copies of the entries (to undo changes with :meth:`restore`)."""
        return self.keys.copy(), self.times.copy(), self.info.copy(), self.vec.copy()

    def restore(self, cp: tuple[np.ndarray, Array, Array, Array]) -> None:
        self._set(*cp)

    def mark(self) -> tuple:
        """A checkpoint without copies (for :meth:`rollback`): the buffers are copied when
        they are next written instead, which a receive that leaves the store alone never does."""
        self._shared = True
        return self._keys, self._times, self._info, self._vec, self._lo, self._hi

    def rollback(self, mark: tuple) -> None:
        """Go back to a :meth:`mark`."""
        self._keys, self._times, self._info, self._vec, self._lo, self._hi = mark
        self._shared = True

    def release(self) -> None:
        """The :meth:`mark` is no longer needed (the transaction succeeded): write in place again."""
        self._shared = False

    def between(self, lo: float, hi: float) -> list[tuple[float, Array, Array]]:
        """Entries with ``lo < t <= hi``, oldest first (copies)."""
        times = self.times
        if not times.size or times[-1] <= lo:
            return []
        a, b = np.searchsorted(times, (lo, hi), side="right").tolist()
        info, vec = self.info, self.vec
        return [(float(times[i]), info[i].copy(), vec[i].copy()) for i in range(a, b)]


#: Differences ``T(t) - M(t)`` smaller than this, relative to ``T(t)``, are rounding noise.
ROUNDING_RTOL = 1e-12


def _clean_difference(diff: Array, scale: Array) -> Array:
    """Remove rounding noise from information differences ``T(t) - M(t)``.

    The exact difference is positive semi-definite (it is a sum of measurement
    information). Computed in floating point it carries errors of order
    ``eps * |T(t)|``: entries below ``ROUNDING_RTOL * |T(t)|`` become exactly
    zero, and rounding-level negative eigenvalues are clipped to zero.

    Blocks that are then diagonally dominant with a non-negative diagonal are
    positive semi-definite (Gershgorin) and are kept without an eigenvalue
    decomposition (diagonal blocks, such as position measurements, are the usual case).
    """
    out = diff.copy()
    out[np.abs(out) <= (ROUNDING_RTOL * scale)[:, None, None]] = 0.0
    d = np.diagonal(out, axis1=1, axis2=2)
    dominant = ((2.0 * d - np.abs(out).sum(axis=2)) >= 0.0).all(axis=1)
    rest = ~dominant
    if rest.any():
        w, V = np.linalg.eigh(out[rest])
        neg = w.min(axis=1) < 0
        if neg.any():
            w = np.where(w < 0, 0.0, w)
            fixed = np.einsum("kij,kj,klj->kil", V, w, V)
            sub = out[rest]
            sub[neg] = 0.5 * (fixed[neg] + np.transpose(fixed[neg], (0, 2, 1)))
            out[rest] = sub
    return out


class FusionNode:
    """One fusion node of a tree.

    Parameters
    ----------
    name : str
        Unique node name.
    neighbors : iterable of str
        Names of the neighbours in the tree.
    motion : MotionModel
        Motion model shared by every node of the network.
    window : int, optional
        States kept by the delayed-state filter.
    prior : (t0, mean, cov)
        The common prior, identical at every node.
    horizon : float, optional
        Keep states newer than ``latest - horizon`` seconds (with or instead of ``window``).
    fusion : {"channel", "naive"}
        ``"channel"`` (default) removes shared information; ``"naive"`` does not.
    policy : Policy, optional
        Decides :meth:`output`; default :class:`InformationFusionPolicy`.
    network_key : bytes, optional
        The network's shared secret (at least 16 bytes): outgoing messages carry a MAC
        and incoming ones must (``docs/security.md``). ``None``: no authentication
        (every message still carries a checksum).
    network, run : str
        The network's name and the run's identifier: the MAC key is derived for them, so
        a message of another network or another run is rejected.
    epoch : int, optional
        Identifier of this incarnation; must grow when a node restarts (default: the
        current time in nanoseconds). Neighbours replace what the old incarnation sent and
        reject messages of earlier incarnations, and of a new incarnation more than 24 h
        ahead of their clocks (:mod:`dfusion.fusion.incarnation`).
    max_message_bytes, max_ahead, max_held : bounds
        Largest frame accepted; how far (seconds) and how many state times ahead of the
        newest state received information may be held back (default ``window`` times).
    log_interval : float
        Seconds between two log lines about rejected messages.
    messages : {"partial", "full"}
        ``"full"`` sends the whole window in every message (the previous protocol's
        behaviour, kept for comparison); the default sends what changed.
    tree : SpanningTree, optional
        Links that change at run time: the node's state of the tree rule
        (:mod:`dfusion.fusion.tree`; ``SpanningTree(name)`` for a node that joins a running
        network). ``neighbors`` are then the links that exist at the start (they must be
        ``tree.links``); the node keeps its fusion links a tree by the rule.
        ``None`` (default): a fixed tree, ``neighbors`` are the tree neighbours.
    peers : iterable of str, optional
        With ``tree``: the nodes that may link to this one (messages of others are rejected
        as ``not-a-neighbour``); ``None``: any node of the network.
    hold : float
        With ``tree``: seconds (of the node's clock) for which information that a change of
        the tree took from the channels stays in the node's own estimate, per state time,
        unless the new tree delivers as much earlier (never sent; ``docs/dynamic-topology.md``).
        0: it goes at once.
    guard : GuardConfig or NeighbourGuard, optional
        Test every neighbour's information for consistency with this node's belief and
        quarantine a neighbour that keeps failing (:mod:`dfusion.fusion.guard`; channel
        fusion only). Default: no test (every message is fused).

    Attributes
    ----------
    filter : DelayedStateEIF
        The local trajectory filter (prior, motion, own and received information).
    channels : dict[str, ChannelFilter]
    stats : NodeStats
    guard : NeighbourGuard or None
    """

    #: Steady-state messages take the critical path first (:meth:`settle`): ``False`` (on the
    #: class or a node) makes every message take the general path, with all its work done at
    #: once (the same results, bit for bit; for tests and comparisons).
    critical_path_first: bool = True

    def __init__(
        self,
        name: str,
        neighbors: Iterable[str],
        motion: MotionModel,
        window: int | None = 100,
        prior: tuple[float, ArrayLike, ArrayLike] | None = None,
        *,
        horizon: float | None = None,
        fusion: str = "channel",
        policy: Policy | None = None,
        network_key: bytes | None = None,
        network: str = "",
        run: str = "",
        epoch: int | None = None,
        time_tol: float = 1e-9,
        max_message_bytes: int = MAX_MESSAGE_BYTES,
        max_ahead: float = MAX_AHEAD,
        max_held: int | None = None,
        log_interval: float = LOG_INTERVAL,
        messages: str = "partial",
        tree: SpanningTree | None = None,
        peers: Iterable[str] | None = None,
        hold: float = HOLD,
        guard: GuardConfig | NeighbourGuard | None = None,
    ) -> None:
        if not isinstance(name, str) or not name:
            raise ValidationError("node name must be a non-empty string")
        nbrs = tuple(neighbors)
        if name in nbrs or len(set(nbrs)) != len(nbrs):
            raise ValidationError(f"invalid neighbours of {name!r}: {nbrs}")
        if fusion not in FUSION_MODES:
            raise ValidationError(f"fusion must be one of {FUSION_MODES}, got {fusion!r}")
        if prior is None:
            raise ValidationError("a prior (t0, mean, cov) common to all nodes is required")
        if messages not in MESSAGE_MODES:
            raise ValidationError(f"messages must be one of {MESSAGE_MODES}, got {messages!r}")
        if network_key is not None and (not isinstance(network_key, (bytes, bytearray)) or len(network_key) < 16):
            raise ValidationError("network_key must be at least 16 bytes (or None to turn authentication off)")
        if tree is not None and (tree.name != name or set(nbrs) != tree.links or fusion == "naive"):
            raise ValidationError(f"tree of {name!r}: its name and links must be the node's and its neighbours, "
                                  "and naive fusion has no tree rule")
        self.name = name
        self.neighbors = nbrs
        self.fusion = fusion
        self.messages = messages
        self.policy: Policy = policy or InformationFusionPolicy()
        self.frame_key = None if network_key is None else FrameKey(bytes(network_key), network, run)
        self.epoch = time.time_ns() if epoch is None else int(epoch)
        if not 0 < self.epoch < 2**63:
            raise ValidationError(f"epoch must be in (0, 2^63), got {self.epoch}")
        #: The bookkeeping of the last steady-state message, done by :meth:`settle` (:meth:`receive`).
        self._pending: tuple | None = None
        #: The records of messages sent, and whether the filter's estimate may be brought up to date,
        #: done by :meth:`settle` (:meth:`message_to`).
        self._sent_pending: list[tuple[ChannelFilter, int, np.ndarray, bool]] = []
        self._warm = False
        self._deferred = False   # any of the three
        self.filter = DelayedStateEIF(motion, window, horizon=horizon, time_tol=time_tol)
        t0, mean, cov = prior
        self.filter.initialize(t0, mean, cov)
        n = self.filter.n
        #: The tree rule's state (``None``: a fixed tree).
        self.tree = tree
        self.peers = None if peers is None else frozenset(peers)
        #: The newest incarnation heard from each node (links that change), and the newest sequence
        #: number heard from it (beacons included).
        self.incarnations: dict[str, int] = {}
        self._heard_seq: dict[str, int] = {}
        #: The judgement of neighbours' incarnation numbers (:mod:`dfusion.fusion.incarnation`).
        self._incarnation_judge = Incarnations(keyed=self.frame_key is not None)
        #: Per neighbour, the next sequence number of a channel made for the link or of a beacon
        #: over it: a fresh channel goes on from where the previous one stopped (links that change).
        self._link_seq: dict[str, int] = {}
        fusing = nbrs if tree is None else sorted(tree.tree_links())
        self._ack_lag = ACK_LAG
        self.channels: dict[str, ChannelFilter] = {j: self._channel(j) for j in fusing}
        self.stats = NodeStats()
        self.sources: dict[str, Estimate] = {}
        self.max_message_bytes = int(max_message_bytes)
        self.max_ahead = float(max_ahead)
        self.max_held = int(max_held if max_held is not None else (window or 100))
        self.rejection_log = RejectionLog(name, log_interval)
        self._tree_undo: tuple | None = None
        self._sent_tree_changes = 0
        #: Held information ``{time key: (t, L, y, until)}``: what a change of the tree took from
        #: the channels, kept for this node's own estimate (``_tree_hold``).
        self._tree_held: dict[int, tuple[float, Array, Array, float]] = {}
        self.hold = float(hold)
        self._own = _Blocks(n)
        self._total = _Blocks(n)   # entries newer than the newest state wait for predict
        self._held = _Blocks(n)    # own information fused here but not shared yet
        self._pruned_at = self.filter.oldest_time
        self._naive_sent: dict[str, dict[int, tuple[Array, Array]]] = {}
        self._heard: dict[str, float] = {}   # per neighbour: newest sent_at of a message applied completely
        if isinstance(guard, GuardConfig):
            guard = NeighbourGuard(nbrs, guard)
        if guard is not None:
            if fusion != "channel":
                raise ValidationError("a guard needs channel fusion (it withdraws what came over a link)")
            if set(guard.links) != set(nbrs):
                raise ValidationError(f"the guard's links {sorted(guard.links)} are not the neighbours {sorted(nbrs)}")
        self._guard: NeighbourGuard | None = guard

    def __repr__(self) -> str:
        return f"FusionNode({self.name!r}, neighbors={list(self.neighbors)}, {self.filter!r})"

    def __getstate__(self) -> dict:
        self._settle()
        return self.__dict__

    @property
    def channels(self) -> dict[str, ChannelFilter]:
        """The channel filter of every fusion link (``{neighbour: ChannelFilter}``), settled
        (:meth:`settle`)."""
        if self._deferred:
            self._settle()
        return self._channels

    @channels.setter
    def channels(self, value: dict[str, ChannelFilter]) -> None:
        self._channels = value

    @property
    def guard(self) -> NeighbourGuard | None:
        """The consistency test's records and quarantine decisions (``None``: no test), settled
        (:meth:`settle`: a steady-state message's verdict may be recorded there)."""
        if self._deferred:
            self._settle()
        return self._guard

    # ------------------------------------------------------------------ deferred bookkeeping
    def settle(self) -> None:
        """Do the work that the last message received or sent left for later now (a node may call
        it when idle; every method that reads or changes what is left does it first, and so does
        reading :attr:`channels`; :meth:`estimate`, :meth:`output`, :meth:`check_frame`,
        :meth:`is_quarantined`, :meth:`health` and :meth:`report_source` read none of it and
        leave it for later). What a caller waits for is done
        first, the rest after; no caller sees the node in between: every observable is the same,
        bit for bit, as if all of it had been done at once.

        * :meth:`receive` fuses a steady-state message into the filter at once (the estimate
          changes) and leaves what the estimate does not need (with a guard, its consistency
          test and verdict too when no verdict could complete a quarantine: the belief is then
          final whatever the verdict; else it is tested and judged at once): storing the blocks in the
          channel filter and the node's total information, marking them for the other links,
          the acknowledgement the message carries, pruning. A failure of this bookkeeping (a
          defect; nothing in it depends on the message's values) undoes the whole message, the
          filter's part too, and counts and logs it as an ``"internal"`` rejection.
        * :meth:`message_to` returns the message and leaves the record of what it carried
          (:meth:`ChannelFilter.record_sent`), and the filter's forward pass up to the newest
          state (its estimate: the next :meth:`predict` that marginalizes the oldest state
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

    # ------------------------------------------------------------------ one transaction's undo
    def _mark_stores(self, src: str, cp_filter: tuple | None = None, cp_guard: LinkRecord | None = None) -> tuple:
        """A mark of everything a received message may change, for :meth:`_rollback_stores`: the
        filter, the stores messages are made from (total, own, held back), the times held after
        a change of the tree, every channel filter, the prune mark and the guard's record of
        ``src``'s link. ``cp_filter``, ``cp_guard``: the filter's checkpoint and the record's
        copy taken earlier (the critical path changed them before the rest was marked).

        The one place that lists the stores: :meth:`_apply` and :meth:`_settle_receive` both undo
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

    # ------------------------------------------------------------------ local filter
    @property
    def motion(self) -> MotionModel:
        return self.filter.motion

    @property
    def latest_time(self) -> float:
        return self.filter.latest_time

    def predict(self, t: float, u: ArrayLike | None = None) -> None:
        """Advance the trajectory to ``t`` (or add a state at a past ``t`` in the window)."""
        self._settle()
        f = self.filter
        t = as_time(t)
        if t <= f.latest_time + f.time_tol:
            if t < f.oldest_time - f.time_tol:
                raise OutsideWindowError(f"time {t} is older than the window start {f.oldest_time}")
            f.ensure_state(t)
            self._prune()
            return
        pending = self._total.between(f.latest_time + f.time_tol, t + f.time_tol)
        if pending:
            with f.transaction():
                f.predict(t, u)
                f.add_information_batch(pending, validate=False)
        else:
            f.predict(t, u)
        self._prune()
        if self._tree_held:
            self._release_tree_held(t)

    def update(self, t: float, z: ArrayLike, sensor: MeasurementModel, *, share: bool = True) -> tuple[Array, Array]:
        """Fuse a local measurement taken at ``t`` (``t`` may be in the past, inside the window).

        Returns the single-state information ``(Lambda, y)`` it added. With ``share=False``
        it is fused here but held back from the neighbours until
        :meth:`share_local_information` (or removed by :meth:`withdraw_local_information`).
        """
        self._settle()
        f = self.filter
        t = as_time(t)
        if t < f.oldest_time - f.time_tol or t > f.latest_time + f.time_tol:
            raise OutsideWindowError(
                f"measurement time {t} is outside the window [{f.oldest_time}, {f.latest_time}]"
            )
        Lam, y = f.update(t, z, sensor)
        self._add_own(t, Lam, y, share)
        self._prune()
        return Lam, y

    def add_local_information(self, t: float, info_matrix: ArrayLike, info_vector: ArrayLike, *,
                              share: bool = True) -> None:
        """Fuse information produced by a local estimator at time ``t``.

        For sensors whose measurements are not fused by the EIF itself, such as a
        particle filter (:mod:`dfusion.frontends.base`: the Gaussian fit of its posterior
        minus that of its prediction, in information form). The information counts as
        this node's own, exactly like a measurement: it is shared with the
        neighbours and never double counted. ``info_matrix`` must be symmetric
        positive semi-definite, of the state's dimension. With ``share=False`` it is
        fused here but held back from the neighbours (a tentative data association, for
        instance) until :meth:`share_local_information`, or removed by
        :meth:`withdraw_local_information`.
        """
        self._settle()
        f = self.filter
        t = as_time(t)
        if t < f.oldest_time - f.time_tol or t > f.latest_time + f.time_tol:
            raise OutsideWindowError(
                f"information time {t} is outside the window [{f.oldest_time}, {f.latest_time}]"
            )
        Lam = as_matrix(info_matrix, (f.n, f.n), "information matrix")
        check_psd(Lam, "information matrix")
        Lam = symmetrize(Lam)
        y = as_vector(info_vector, f.n, "information vector")
        with f.transaction():
            f.add_information_batch([(t, Lam, y)], validate=False)
            f.estimate()
        self._add_own(t, Lam, y, share)
        self._prune()

    def share_local_information(self, t: float, info_matrix: ArrayLike, info_vector: ArrayLike) -> bool:
        """Start sharing own information fused earlier with ``share=False``: it moves from the
        held-back store to what the node shares, and its time is marked changed on every link,
        so the next (partial) messages carry it. Returns False (nothing to share) when ``t`` has
        left the window."""
        self._settle()
        f = self.filter
        t = as_time(t)
        if t < f.oldest_time - f.time_tol:
            return False
        Lam = np.asarray(info_matrix, dtype=float)
        y = np.asarray(info_vector, dtype=float)
        self._held.subtract([(t, Lam, y)])
        self._total.add(t, Lam, y)
        self._mark_dirty([time_key(t)])
        return True

    def withdraw_local_information(self, t: float, info_matrix: ArrayLike, info_vector: ArrayLike, *,
                                   shared: bool = True) -> bool:
        """Remove own information added earlier at ``t`` (a front end found it suspect).

        The filter and the node's own information lose ``(info_matrix, info_vector)``. If it
        was shared (``shared``), the time is marked changed on every link, so the next
        messages carry the smaller block (or clear the time): the neighbours replace what
        they stored and lose it too, and forward the change. Removing information is never
        over-confident. Returns False (and changes nothing) when ``t`` is outside the window:
        older information is marginalized into the window's base and stays.
        """
        self._settle()
        f = self.filter
        t = as_time(t)
        if t < f.oldest_time - f.time_tol or t > f.latest_time + f.time_tol:
            return False
        Lam = np.asarray(info_matrix, dtype=float)
        y = np.asarray(info_vector, dtype=float)
        with f.transaction():
            f.add_information_batch([(t, -Lam, -y)], validate=False)
            f.estimate()
        self._own.subtract([(t, Lam, y)])
        if shared:
            self._total.subtract([(t, Lam, y)])
            self._mark_dirty([time_key(t)])
        else:
            self._held.subtract([(t, Lam, y)])
        return True

    def add_process_noise(self, t: float, Q_extra: ArrayLike) -> None:
        """Add process noise ``Q_extra`` to this node's motion step ending at the window
        state ``t`` (:meth:`DelayedStateEIF.add_process_noise`): a local re-initialization
        of a diverged belief (a recovery, :mod:`dfusion.estimation.innovation`).

        Nothing exchanged changes: messages and channel filters carry single-state
        (measurement) information per state time, and this changes a motion factor, which
        is never sent; the own, held-back and received stores and the channels are
        untouched, so no information is counted twice or lost, whether messages are full or
        partial. The node's belief becomes the posterior of all the measurement
        information it holds under its motion model with the extra noise, wider than
        before; its neighbours keep the nominal model until they recover too. With a
        guard (:mod:`dfusion.fusion.guard`) the wider belief only makes the neighbours'
        information pass its test more easily (``docs/robots.md``).
        """
        self._settle()
        self.filter.add_process_noise(t, Q_extra)
        log.info("%s: process noise added at t=%.3f (trace %.3g)", self.name, float(t),
                 float(np.trace(np.asarray(Q_extra, dtype=float))))

    def reported_until(self) -> float:
        """The time up to which every neighbour whose information this node fuses has
        reported: the oldest of the newest ``sent_at`` of a message applied completely from
        each neighbour that is not quarantined (``-inf`` while one has not been heard from;
        ``inf`` without such neighbours). Over a link without losses the information a
        neighbour holds for states up to that ``sent_at`` has then reached this node; a
        message lost on the way is resent with the next messages once an acknowledgement
        shows the loss (:mod:`dfusion.fusion.channel`), so over a lossy link it may still be
        under way."""
        self._settle()
        live = [j for j in self.neighbors if not self.is_quarantined(j)]
        if not live:
            return float("inf")
        return min(self._heard.get(j, -np.inf) for j in live)

    def received_information(self, t0: float, t1: float) -> list[tuple[float, Array, Array]]:
        """The measurement information this node fuses from its neighbours at the window
        states with ``t0 <= t <= t1``, oldest first: the total (own shared plus received;
        what a quarantine withdrew is not in it) minus the own shared part
        (``own - held``)."""
        self._settle()
        tol = self.filter.time_tol
        own = {time_key(t): (L, y) for t, L, y in self._own.between(t0 - tol, t1 + tol)}
        held = {time_key(t): (L, y) for t, L, y in self._held.between(t0 - tol, t1 + tol)}
        out = []
        for t, L, y in self._total.between(t0 - tol, t1 + tol):
            k = time_key(t)
            L, y = np.array(L, dtype=float), np.array(y, dtype=float)
            if k in own:
                L, y = L - own[k][0], y - own[k][1]
            if k in held:
                L, y = L + held[k][0], y + held[k][1]
            out.append((t, L, y))
        return out

    def _add_own(self, t: float, Lam: Array, y: Array, share: bool = True) -> None:
        self._own.add(t, Lam, y)
        if share:
            self._total.add(t, Lam, y)
            self._mark_dirty([time_key(t)])
        else:
            self._held.add(t, Lam, y)

    def _mark_dirty(self, keys: Iterable[int], skip: str | None = None) -> None:
        """The value for every neighbour but ``skip`` changed at ``keys``: the next messages carry them."""
        keys = list(keys)
        if keys:
            for j, ch in self.channels.items():
                if j != skip:
                    ch.dirty.update(keys)

    def estimate(self, t: float | None = None) -> tuple[Array, Array]:
        """Fused ``(mean, cov)`` of the newest state, or of the window state at ``t``."""
        return self.filter.estimate(t)

    def output(self) -> Estimate:
        """The node's output: the policy's choice among the fused estimate and the sources."""
        mean, cov = self.filter.estimate()
        fused = Estimate("fused", self.filter.latest_time, mean, cov)
        return self.policy.decide(fused, list(self.sources.values()))

    def report_source(self, estimate: Estimate) -> None:
        """Record the latest estimate of a candidate source (for switching policies)."""
        self.sources[estimate.name] = estimate

    # ------------------------------------------------------------------ messages
    def _values_for(self, ch: ChannelFilter, keys: np.ndarray) -> tuple[Array, Array]:
        """``V(t) = T(t) - M(t)`` for ``ch``'s neighbour at ``keys`` (rounding noise removed);
        ``T(t)`` for a quarantined neighbour, whose information ``T`` does not hold."""
        infos, vecs = self._total.values_at(keys)
        if self.is_quarantined(ch.remote):
            return infos, vecs
        if not len(ch) or not keys.size:
            return infos, vecs
        found, pos = ch.lookup(keys)
        if not any_of(found):   # the neighbour sent nothing for these times (a new block)
            return infos, vecs
        held = np.zeros(keys.size, dtype=bool)
        held[found] = nonzero_blocks(ch.info[pos[found]], ch.vec[pos[found]])
        if any_of(held):
            m_info, m_vec = ch.info[pos[held]], ch.vec[pos[held]]
            scale = np.abs(infos[held]).max(axis=(1, 2))
            infos[held] = _clean_difference(infos[held] - m_info, scale)
            vecs[held] -= m_vec
        return infos, vecs

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

    def check_frame(self, data: bytes | bytearray | memoryview) -> None:
        """The cheap checks of a frame for this node (size, header, checksum, MAC: a few
        microseconds, :func:`dfusion.wire.check_frame`), without counting anything.

        Raises :class:`MessageError` with a ``reason``. It reads nothing the node changes, so a
        transport may run it in its own threads on every copy as it arrives and drop the
        failing ones before they take queue space
        (:meth:`dfusion.transport.zenoh.ZenohTransport.set_check`); count
        them with :meth:`count_rejections`. :meth:`receive` runs the same checks again.
        """
        check_frame(data, self.frame_key, self.max_message_bytes)

    def count_rejections(self, counts: dict[str, int], detail: str = "") -> None:
        """Count copies a transport rejected on arrival with :meth:`check_frame` (``{reason: count}``):
        in ``stats.messages_rejected``, ``stats.rejections``, ``stats.rejected_on_arrival`` and the
        rate-limited rejection log."""
        self._settle()
        for reason, count in counts.items():
            if count <= 0:
                continue
            self.stats.messages_rejected += count
            self.stats.rejected_on_arrival += count
            self.stats.rejections[reason] = self.stats.rejections.get(reason, 0) + count
            self.rejection_log.add(reason, detail or reason, count)

    def _reject(self, reason: str, detail: str) -> MessageError:
        if self._tree_undo is not None:   # the tree rule took the message in before it was refused: undo that
            undo, self._tree_undo = self._tree_undo, None
            self._tree_restore(undo)
        self.stats.messages_rejected += 1
        self.stats.rejections[reason] = self.stats.rejections.get(reason, 0) + 1
        self.rejection_log.add(reason, detail)
        err = MessageError(detail)
        err.reason = reason
        return err

    def _check(self, msg: InfoMessage) -> ChannelFilter:
        """Everything about ``msg`` that can be known without changing anything; its channel."""
        if msg.dst != self.name:
            raise self._reject("misaddressed", f"message for {msg.dst!r} delivered to {self.name!r}")
        ch = self.channels.get(msg.src)
        if ch is None:
            raise self._reject("not-a-neighbour", f"{msg.src!r} is not a neighbour of {self.name!r}")
        if msg.n != self.filter.n:
            raise self._reject("dimension", f"state dimension {msg.n} from {msg.src!r}, expected {self.filter.n}")
        if msg.naive != (self.fusion == "naive"):
            raise self._reject("malformed", f"{msg.src!r} uses another fusion mode")
        if bool(msg.tree_root) != (self.tree is not None):
            raise self._reject("malformed", f"{msg.src!r} uses another tree mode (a fixed tree or the tree rule)")
        if msg.epoch == ch.epoch:
            last = ch.last_seq
        elif self.tree is None:
            last = self._judge_incarnation(msg, ch.epoch, ch.last_seq)[1]
        else:   # (judged by the tree rule's part, _tree_heard)
            last = -1
        if msg.seq > last + MAX_SEQ_JUMP and self.frame_key is None:
            raise self._reject("sequence-jump", f"sequence number {msg.seq} from {msg.src!r} jumps past {last}")
        return ch

    def _judge_incarnation(self, msg: InfoMessage, current: int | None, newest: int) -> tuple[str, int]:
        """:meth:`Incarnations.judge` of ``msg``: the verdict and the reference of the sequence-jump
        bound; a rejection is counted and raised."""
        verdict, last = self._incarnation_judge.judge(msg.src, msg.epoch, msg.seq, msg.sent_at, current, newest)
        if verdict == "previous-incarnation":
            raise self._reject(verdict, f"message of an earlier incarnation of {msg.src!r} ({msg.epoch} < {current})")
        if verdict == "implausible-incarnation":
            raise self._reject(verdict, f"incarnation {msg.epoch} of {msg.src!r} is more than 24 h ahead of this "
                                        "node's clock")
        if verdict == "revert":
            self.stats.incarnations_reverted += 1
            log.warning("%s: %s's incarnation %d goes on after %d replaced it: the link switches back to it", self.name,
                        msg.src, msg.epoch, current)
        return verdict, last

    def receive(self, data: bytes) -> int:
        """Fuse a neighbour's message; returns the number of state blocks that changed.

        Raises :class:`MessageError` (with ``reason``), counts it and changes nothing else if
        the message is malformed, corrupt, unauthenticated while a key is set, from a
        non-neighbour, addressed to another node, of another state dimension, of an earlier
        incarnation, too far ahead in its sequence numbers, or not fusable.
        """
        self._settle()
        self._tree_undo = None
        try:
            msg = decode(data, self.frame_key, self.max_message_bytes)
        except MessageError as exc:
            raise self._reject(getattr(exc, "reason", "malformed"), str(exc)) from None
        except Exception as exc:   # a defect of the decoder: the message is still rejected, nothing changed
            raise self._reject("internal", f"message could not be decoded: {type(exc).__name__}: {exc}") from exc
        try:
            if self.tree is not None and not self._tree_heard(msg):
                return 0     # used by the tree rule only (a beacon, another epoch, not a tree link)
            ch = self._check(msg)
            if msg.epoch == ch.epoch and not msg.naive and ch.was_applied(msg.seq):
                # a network duplicate or a replay: discarded before any work, counted (not an error:
                # links may duplicate); it could change nothing anyway (every stored block is newer)
                self.stats.messages_received += 1   # as before: a duplicate is delivered, and fuses nothing
                self.stats.duplicates += 1
                return 0
            f = self.filter
            if msg.naive:
                plan = None
                if msg.epoch == ch.epoch and msg.seq <= ch.last_seq:
                    self.stats.duplicates += int(msg.seq == ch.last_seq)
                    return 0
                inside = msg.times >= f.oldest_time - f.time_tol
                deltas = [(t, L, y) for t, L, y, ok in zip(msg.times.tolist(), msg.info, msg.vec, inside) if ok]
                outside, changed = int(np.count_nonzero(~inside)), time_keys(msg.times[inside])
            else:
                plan = ch.plan(msg, f.oldest_time, f.time_tol)
                deltas, outside, changed = plan.deltas, plan.outside, plan.changed
            deltas, too_far = self._within_reach(deltas)
            if plan is not None:
                too_far = sorted(set(too_far) | set(self._entries_out_of_reach(ch, plan)))
            if too_far and plan is not None:
                plan = ch.plan(_without(msg, too_far), f.oldest_time, f.time_tol)
                deltas, changed = self._within_reach(plan.deltas)[0], plan.changed
        except MessageError:
            raise   # counted by _check (and the tree rule's changes undone by _reject)
        except Exception as exc:   # nothing changed yet (the tree rule's changes are undone by _reject)
            raise self._reject("internal", f"message from {msg.src!r} failed: {type(exc).__name__}: {exc}") from exc
        if plan is not None and plan.append and not too_far and self._steady(msg, ch, deltas):
            done = self._apply_steady(msg, ch, plan, deltas)
            if done is not None:
                return done
        self._apply(msg, ch, plan, deltas, changed, too_far, outside)
        self._tree_undo = None
        return len(deltas)

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
        """:meth:`_apply` of a steady-state message (:meth:`_steady`), the critical path first: the
        blocks go into the filter (and its estimate is brought up to date, which also tests
        that the belief stays proper) at once; with a guard they are tested as they are added
        and the verdict recorded (:meth:`_add_tested`, :meth:`NeighbourGuard.judge`); the rest
        is left to :meth:`settle`. Every result is the same, bit for bit, as :meth:`_apply`'s.

        The test itself is left to :meth:`settle` too when the message is one block at the
        newest state and a failing verdict would not quarantine the neighbour
        (:meth:`NeighbourGuard.may_quarantine`): no verdict can then change the filter, only
        the link's counters, so the estimate is final at once. The moments the statistic
        needs are saved as the block is added (the newest state's filtered moments before and
        after: what :meth:`DelayedStateEIF.add_information_moments` reads) and the verdict is
        recorded by :meth:`_settle_receive` (:meth:`_deferred_test`); reading :attr:`guard` or
        :meth:`health` settles first.

        A verdict that would quarantine the neighbour (its withdrawal needs the bookkeeping
        done) is not recorded: the filter is put back and ``None`` returned, and the caller
        takes :meth:`_apply`, which tests the message again (the same statistic) in its
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

    # ------------------------------------------------------------------ guard (dfusion.fusion.guard)
    def is_quarantined(self, neighbor: str) -> bool:
        """Whether the link to ``neighbor`` is quarantined (its information withdrawn)."""
        return self._guard is not None and self._guard.is_quarantined(neighbor)

    def health(self) -> str:
        """``"ok"``, ``"degraded"`` or ``"lost"`` (:meth:`NeighbourGuard.health`; always ok without a guard)."""
        if self._guard is None:
            return "ok"
        self._settle()   # (a verdict left for settle() counts)
        return self._guard.health()

    def _add_tested(self, entries: list[tuple[float, Array, Array]]) -> tuple[float, int, int]:
        """Add a message's blocks to the filter, testing the additions jointly (inside the
        caller's transaction). Returns ``(D^2, dof, blocks tested)``
        (:func:`dfusion.fusion.guard.information_statistic`)."""
        f = self.filter
        eigen = block_eigen(entries[0][1]) if len(entries) == 1 else None   # (one decomposition for both)
        add, other = split_blocks(entries, eigen)
        if other:
            f.add_information_batch(other, validate=False)
        if not add:
            return 0.0, 0, 0
        mu0, P0, mu1 = f.add_information_moments(add)
        stat, dof = information_statistic(add, mu0, P0, mu1, eigen)
        return stat, dof, len(add)

    def _deferred_test(self, block: tuple[float, Array, Array], mu0: Array, P0: Array, mu1: Array) -> tuple[float, int, int]:
        """:meth:`_add_tested`'s verdict of one block at the newest state, from the moments saved
        when it was added (the same values: :meth:`DelayedStateEIF.add_information_moments` reads
        the same filtered moments), for :meth:`settle`."""
        eigen = block_eigen(block[1])
        add, _ = split_blocks([block], eigen)
        if not add:
            return 0.0, 0, 0
        stat, dof = information_statistic(add, [mu0], [P0], [mu1], eigen)
        return stat, dof, 1

    def _record_verdict(self, src: str, n_blocks: int, verdict: tuple | None) -> bool:
        """Record a message of ``src`` with ``n_blocks`` blocks in its link's guard record: the
        blocks :meth:`_add_tested` did not test, and the test's verdict (``None``: nothing was
        tested). True when ``src`` is to be quarantined now (:meth:`NeighbourGuard.judge`)."""
        guard = self._guard
        guard.links[src].untested_blocks += n_blocks - (verdict[2] if verdict else 0)
        return verdict is not None and guard.judge(src, verdict[0], verdict[1])

    def _link_blocks(self, ch: ChannelFilter, sign: float = 1.0) -> tuple[list, list]:
        """The channel's stored blocks in the window as ``(t, info, vec)`` times ``sign``:
        ``(those the filter holds, all)``; the others are newer than the newest state and wait
        in the total store for :meth:`predict`."""
        if not len(ch):
            return [], []
        f = self.filter
        latest = f.latest_time + f.time_tol
        live = nonzero_blocks(ch.info, ch.vec) & (ch.times >= f.oldest_time - f.time_tol)
        every = [(float(ch.times[i]), sign * ch.info[i], sign * ch.vec[i]) for i in np.flatnonzero(live).tolist()]
        return [e for e in every if e[0] <= latest], every

    def _withdraw(self, neighbor: str) -> None:
        """Remove everything that came over the link to ``neighbor`` (quarantine): from the filter
        and from what the node shares; the other links are sent the changed times. Times held
        after a change of the tree are let go first (the filter then holds what its channels
        delivered, :meth:`_release_tree_held`): what it subtracts is in the filter once."""
        self._release_tree_held(math.inf)
        now, every = self._link_blocks(self.channels[neighbor], -1.0)
        if now:
            self.filter.add_information_batch(now, validate=False)
            self.filter.estimate()
        changed = self._total.subtract([(t, -L, -y) for t, L, y in every])
        self._mark_dirty(changed.tolist(), skip=neighbor)

    def _reinstate(self, neighbor: str) -> None:
        """Add the neighbour's current contribution back (the link leaves quarantine); held
        times are let go first, as in :meth:`_withdraw`."""
        self._release_tree_held(math.inf)
        now, every = self._link_blocks(self.channels[neighbor])
        if now:
            self.filter.add_information_batch(now, validate=False)
            self.filter.estimate()
        if every:
            self._total.add_many(every)
            self._mark_dirty(time_keys(np.array([e[0] for e in every])).tolist(), skip=neighbor)

    def _probation(self, neighbor: str, ch: ChannelFilter) -> str | None:
        """A message over a quarantined link: test the neighbour's whole current contribution
        against this node's belief (a trial: nothing is kept); after ``release`` passes in a
        row, take it back. Returns ``"released"`` then."""
        now, _ = self._link_blocks(ch)
        add, _ = split_blocks(now)
        if not add:
            return None
        f = self.filter
        try:
            with f.trial():
                mu0, P0, mu1 = f.add_information_moments(add)
                stat, dof = information_statistic(add, mu0, P0, mu1)
        except DfusionError:
            stat, dof = math.inf, 1
        if self._guard.probation(neighbor, stat, dof):
            self._reinstate(neighbor)
            return "released"
        return None

    def _prune(self) -> None:
        oldest = self.filter.oldest_time
        if oldest <= self._pruned_at:
            return
        self._pruned_at = oldest
        cutoff = time_key(oldest) - 1
        self._own.prune(cutoff)
        self._total.prune(cutoff)
        self._held.prune(cutoff)
        for k in [k for k in self._tree_held if k < cutoff]:
            del self._tree_held[k]
        for ch in self.channels.values():
            ch.prune(cutoff)

    # ------------------------------------------------------------------ links that change
    def _tree_fields(self) -> dict:
        """The tree fields of this node's messages (empty on a fixed tree)."""
        if self.tree is None:
            return {}
        t = self.tree
        return {"tree_term": t.epoch.term, "tree_root": t.epoch.root, "parent": t.parent or ""}

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

    def outgoing(self, sent_at: float | None = None, only: Iterable[str] | None = None) -> list[tuple[str, bytes]]:
        """``(neighbour, message)`` for every link: a fusion message on a tree link, a beacon on
        the others (links that change); every neighbour's message on a fixed tree. ``only``:
        those of the links only (the others are sent later: a minimum interval per link,
        :class:`dfusion.fusion.sending.SendSchedule`). Clears :attr:`urgent`."""
        self._settle()
        self._sent_tree_changes = self.stats.tree_changes
        pick = None if only is None else set(only)
        return [(j, self.message_to(j, sent_at)) for j in self.neighbors if pick is None or j in pick]

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

        A quarantined channel's information was withdrawn already (:meth:`_withdraw`): it is
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
        (a held time) or what its current channels delivered ``R(t)`` (:meth:`_received_at`); each is
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

    def _received_at(self, keys: np.ndarray) -> tuple[Array, Array]:
        """``R(t) = T(t) - own(t) + H(t)`` at ``keys``: what the current channels delivered and the
        filter holds (``T`` is what the node shares: its shared own information and what came
        over links that are not quarantined; ``H`` its own information not shared yet)."""
        tot, own, held = self._total.values_at(keys), self._own.values_at(keys), self._held.values_at(keys)
        return tot[0] - own[0] + held[0], tot[1] - own[1] + held[1]

    def _add_to_filter(self, entries: list) -> None:
        f = self.filter
        with f.transaction():
            f.add_information_batch(entries, validate=False)
            f.estimate()   # prior, motion and own information stay: the belief stays proper

    def _tree_heard(self, msg: InfoMessage) -> bool:
        """The tree rule's part of :meth:`receive` (links that change): whether to fuse ``msg``.

        Checks what the rule needs (recipient, sender, tree mode, dimension, incarnation),
        gives the tree fields to the rule and makes the channels follow its changes. A
        message is fused only when it is a fusion message of this node's tree epoch over a
        tree link; the others are counted in ``stats.not_fused`` (``stats.not_linked`` when
        the link no longer exists). If the message is then refused, :meth:`_reject` undoes
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

    def information_blocks(self, own: bool = False) -> tuple[np.ndarray, Array, Array]:
        """The single-state information this node shares per state time: ``(time keys, info, vec)``
        (copies), its own and what it received (also blocks held back for times ahead of its
        newest state), or with ``own`` its own only; both without the own information it fused
        but does not share yet (``share=False``)."""
        self._settle()
        if not own:
            return self._total.keys.copy(), self._total.info.copy(), self._total.vec.copy()
        keys = self._own.keys.copy()
        held = self._held.values_at(keys)
        return keys, self._own.info - held[0], self._own.vec - held[1]

    def _channel(self, j: str) -> ChannelFilter:
        """A fresh channel for the link to ``j``: its sequence numbers go on from the link's earlier
        channels and beacons, and the sequence-jump bound starts from the newest number heard from
        ``j``'s current incarnation (:mod:`dfusion.fusion.channel`, resynchronization)."""
        if self.tree is None:
            ch = ChannelFilter(self.name, j, self.filter.n)
        else:
            epoch = self.incarnations.get(j)
            ch = ChannelFilter(self.name, j, self.filter.n, self._link_seq.get(j, 0), epoch,
                               self._heard_seq.get(j, -1) if epoch is not None else -1)
        ch.ack_lag = self._ack_lag
        return ch

    @property
    def ack_lag(self) -> int:
        """Messages an acknowledgement may lag behind before partial messages to that neighbour
        carry everything since the newest acknowledged one (:data:`dfusion.fusion.channel.ACK_LAG`,
        2: two send periods when every message is periodic). Event-triggered sends
        (:class:`dfusion.fusion.sending.SendSchedule`) send up to ``period / min_interval``
        messages per period on a link while the neighbour acknowledges with its own (fewer)
        messages: they set it to two periods' worth, so that the rule still means "no
        acknowledgement for two send periods" (a link outage)."""
        return self._ack_lag

    @ack_lag.setter
    def ack_lag(self, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValidationError(f"ack_lag must be a non-negative integer, got {value!r}")
        self._ack_lag = value
        for ch in self.channels.values():
            ch.ack_lag = value

    def news(self) -> tuple[str, ...]:
        """The tree neighbours this node has information for that they do not have yet: a time of
        its window whose value ``V_j(t) = T(t) - M_j(t)`` changed since its last message to ``j``
        (a new own measurement, or a received message that changed ``T`` and must be relayed;
        the channel's ``dirty`` times). Losses are not news: they are resent with the next
        message, periodic or not (:mod:`dfusion.fusion.channel`). Event-triggered sends
        (:class:`dfusion.fusion.sending.SendSchedule`) send to these at once."""
        oldest = time_key(self.filter.oldest_time) - 1
        return tuple(j for j, ch in sorted(self.channels.items()) if ch.dirty and max(ch.dirty) >= oldest)

    @property
    def urgent(self) -> bool:
        """The tree links changed since :meth:`outgoing` was last called: send now rather than at
        the next send period (the new tree links start with full messages, beacons carry a new
        epoch on)."""
        return self.tree is not None and self.stats.tree_changes != self._sent_tree_changes

    def own_information(self) -> Sequence[tuple[float, Array, Array]]:
        """This node's own measurement information per state time, oldest first."""
        self._settle()
        return [(e.t, e.info, e.vec) for _, e in self._own.items()]

    def flush_log(self) -> None:
        """Write the pending summary of rejected messages now."""
        self.rejection_log.flush()


class _Numerical(Exception):
    """A message's information would make the filter improper."""


def _without(msg: InfoMessage, times: list[float]) -> InfoMessage:
    """``msg`` without the blocks and the cleared times at ``times``."""
    gone = time_keys(np.asarray(times))
    drop = np.isin(time_keys(msg.times), gone)
    cleared = msg.cleared[~np.isin(time_keys(msg.cleared), gone)] if msg.cleared.size else msg.cleared
    return dataclasses.replace(msg, times=msg.times[~drop], info=msg.info[~drop], vec=msg.vec[~drop],
                               cleared=cleared)
