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

**Where each part lives.** :class:`FusionNode` is composed of parts, one module each (a
class whose methods work on the node's state; the node inherits them all):

=====================================  ===================================================
``dfusion.fusion.node``                the node: construction, identity, neighbours,
                                       ``receive`` (decode, check, plan), rejections
``dfusion.fusion.target``              the fusion state of one target: filter, own and
                                       total information, per-link values, local updates
``dfusion.fusion.stores``              the information stores per state time
``dfusion.fusion.transaction``         the general receive path: apply all or nothing, undo
``dfusion.fusion.steady``              the steady-state path and :meth:`FusionNode.settle`
``dfusion.fusion.quarantine``          the guard in the node: tests, withdraw, probation
``dfusion.fusion.following``           the tree rule in the node: links, holds
``dfusion.fusion.outgoing``            messages, beacons, news
``dfusion.fusion.stats``               counters and the rejection log
=====================================  ===================================================
"""
from __future__ import annotations

import dataclasses
import time
from typing import Iterable

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import MessageError, ValidationError
from dfusion.estimation.delayed_state import DelayedStateEIF
from dfusion.estimation.estimate import Estimate
from dfusion.fusion.channel import ACK_LAG, MAX_SEQ_JUMP, ChannelFilter, time_keys
from dfusion.fusion.following import TreeFollowing
from dfusion.fusion.guard import GuardConfig, NeighbourGuard
from dfusion.fusion.incarnation import Incarnations
from dfusion.fusion.outgoing import MessageSending
from dfusion.fusion.quarantine import GuardedLinks
from dfusion.fusion.stats import LOG_INTERVAL, NodeStats, RejectionLog
from dfusion.fusion.stats import node_log as log
from dfusion.fusion.steady import SteadyPath
from dfusion.fusion.stores import InformationBlocks
from dfusion.fusion.target import TargetFusion
from dfusion.fusion.transaction import ReceiveTransaction
from dfusion.fusion.tree import SpanningTree
from dfusion.linalg import Array
from dfusion.models.base import MotionModel
from dfusion.policies.base import InformationFusionPolicy, Policy
from dfusion.wire import MAX_MESSAGE_BYTES, FrameKey, InfoMessage, check_frame, decode

__all__ = ["FUSION_MODES", "HOLD", "LOG_INTERVAL", "MAX_AHEAD", "MESSAGE_MODES", "FusionNode", "NodeStats",
           "RejectionLog"]

FUSION_MODES = ("channel", "naive")
#: ``"partial"``: what changed (the protocol); ``"full"``: the whole window in every message,
#: as the previous protocol did (for comparison: ``benchmarks/scale.py``).
MESSAGE_MODES = ("partial", "full")
#: Default bounds of a node (see the module docstring).
MAX_AHEAD = 10.0
#: Default ``hold`` (seconds): how long information a change of the tree took stays in a node's estimate.
HOLD = 10.0
#: The store class under its earlier name (:class:`dfusion.fusion.stores.InformationBlocks`),
#: for code that reaches it through this module.
_Blocks = InformationBlocks


class FusionNode(SteadyPath, ReceiveTransaction, GuardedLinks, TreeFollowing, MessageSending, TargetFusion):
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
        # (src, its incarnation record before this message's verdict, whether it reverted): what a
        # refusal of the message being received puts back (_reject); None outside receive
        self._incarnation_undo: tuple | None = None
        self._sent_tree_changes = 0
        #: Held information ``{time key: (t, L, y, until)}``: what a change of the tree took from
        #: the channels, kept for this node's own estimate (``_tree_hold``).
        self._tree_held: dict[int, tuple[float, Array, Array, float]] = {}
        self.hold = float(hold)
        self._own = InformationBlocks(n)
        self._total = InformationBlocks(n)   # entries newer than the newest state wait for predict
        self._held = InformationBlocks(n)    # own information fused here but not shared yet
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

    def receive(self, data: bytes, *, checked: bool = False) -> int:
        """Fuse a neighbour's message; returns the number of state blocks that changed.

        Raises :class:`MessageError` (with ``reason``), counts it and changes nothing else if
        the message is malformed, corrupt, unauthenticated while a key is set, from a
        non-neighbour, addressed to another node, of another state dimension, of an earlier
        incarnation, too far ahead in its sequence numbers, or not fusable.

        ``checked=True`` says that :meth:`check_frame` of this node passed on these very bytes
        (a transport's check on arrival: ``Delivery.checked``), so the checksum and the MAC are
        not computed a second time; the other checks run. Never pass it for bytes that
        :meth:`check_frame` has not accepted.
        """
        try:
            return self._receive(data, checked)
        except BaseException:   # (what did not go through _reject, an interrupt: its verdict undone too)
            self._undo_incarnation()
            raise
        finally:
            self._incarnation_undo = None

    def _receive(self, data: bytes, checked: bool = False) -> int:
        """:meth:`receive`, whose verdict on a neighbour's incarnation :meth:`_reject` undoes."""
        self._settle()
        self._tree_undo = None
        try:
            msg = decode(data, self.frame_key, self.max_message_bytes, checked=checked)
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
        before = self._incarnation_judge.replaced.get(msg.src)
        verdict, last = self._incarnation_judge.judge(msg.src, msg.epoch, msg.seq, msg.sent_at, current, newest)
        if verdict in ("new", "revert"):   # a refusal of this message later on puts the record back
            self._incarnation_undo = (msg.src, before, verdict == "revert")
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

    def _undo_incarnation(self) -> None:
        """Put back the incarnation judge's verdict on the message being received (a ``new`` or
        ``revert`` that the node did not take after all)."""
        if self._incarnation_undo is not None:
            (src, record, reverted), self._incarnation_undo = self._incarnation_undo, None
            self._incarnation_judge.restore(src, record)
            self.stats.incarnations_reverted -= int(reverted)

    def _reject(self, reason: str, detail: str) -> MessageError:
        if self._tree_undo is not None:   # the tree rule took the message in before it was refused: undo that
            undo, self._tree_undo = self._tree_undo, None
            self._tree_restore(undo)
        self._undo_incarnation()   # the verdict on its incarnation too
        self.stats.messages_rejected += 1
        self.stats.rejections[reason] = self.stats.rejections.get(reason, 0) + 1
        self.rejection_log.add(reason, detail)
        err = MessageError(detail)
        err.reason = reason
        return err

    def check_frame(self, data: bytes | bytearray | memoryview) -> None:
        """The cheap checks of a frame for this node (size, header, checksum, MAC: a few
        microseconds, :func:`dfusion.wire.check_frame`), without counting anything.

        Raises :class:`MessageError` with a ``reason``. It reads nothing the node changes, so a
        transport may run it in its own threads on every copy as it arrives and drop the
        failing ones before they take queue space
        (:meth:`dfusion.transport.zenoh.ZenohTransport.set_check`); count
        them with :meth:`count_rejections`; :meth:`receive` then need not compute the checksum and
        MAC again (``receive(data, checked=True)``).
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

    def flush_log(self) -> None:
        """Write the pending summary of rejected messages now."""
        self.rejection_log.flush()

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

    def output(self) -> Estimate:
        """The node's output: the policy's choice among the fused estimate and the sources."""
        mean, cov = self.filter.estimate()
        fused = Estimate("fused", self.filter.latest_time, mean, cov)
        return self.policy.decide(fused, list(self.sources.values()))

    def report_source(self, estimate: Estimate) -> None:
        """Record the latest estimate of a candidate source (for switching policies)."""
        self.sources[estimate.name] = estimate


def _without(msg: InfoMessage, times: list[float]) -> InfoMessage:
    """``msg`` without the blocks and the cleared times at ``times``."""
    gone = time_keys(np.asarray(times))
    drop = np.isin(time_keys(msg.times), gone)
    cleared = msg.cleared[~np.isin(time_keys(msg.cleared), gone)] if msg.cleared.size else msg.cleared
    return dataclasses.replace(msg, times=msg.times[~drop], info=msg.info[~drop], vec=msg.vec[~drop],
                               cleared=cleared)
