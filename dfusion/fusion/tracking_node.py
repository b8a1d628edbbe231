r"""A fusion node for many targets: one delayed-state fusion per track, network-wide identities.

:class:`TrackingNode` is what a camera, a radio network or a robot runs when more than one
person or robot may be in view. It composes

* **one** :class:`~dfusion.fusion.node.FusionNode` **per track** (``tracks``): the track's
  delayed-state EIF and its channel filter per link, exactly the single-target machinery
  (transactional receive, drops, delays, reordering, restarts, links that change), so a
  track of a network is exact against a centralized filter of that track's measurements
  for the same reasons a single target is (``docs/fusion.md``);
* **the tracker** of Stone Soup's kinds (:mod:`dfusion.tracking`): a hypothesiser and a data
  associator (GNN or JPDA) that associate this node's detections with its **fused** tracks,
  an initiator that starts tracks from detections no track explains, a deleter;
* **the network's track book**: births, merges and deletions, announced to the neighbours in
  the track bundle (:mod:`dfusion.fusion.bundle`).

**The common prior of a track.** Every node gives a track the same prior at the track's
birth time ``t_b``: mean 0, covariance ``diag(s_p^2 I, s_v^2 I)`` (:class:`TrackPrior`;
broad). The node that starts a track from detections adds what the initiator learned as its
own information at ``t_b``: ``(Omega - Omega_0, eta - eta_0)``, so that its estimate is the
initiator's; a node that hears of the track first in a message creates it with the same
prior at the same ``t_b`` (carried in every bundle) and fuses what arrives. The prior is
common information, never exchanged: each track's network is a single-target network.

**Tracks every node knows from the start** (:meth:`TrackingNode.add_track`: a team of known
size, a registered tag): their common prior is a given ``(t_b, mean, cov)`` instead of
:class:`TrackPrior`. Every node must add such a track identically (same identity, time, mean
and covariance) before it takes or hears anything of it: it is then common information, as
:class:`TrackPrior` is, and the track is exact against a Kalman filter from that prior. A node
that hears of the track in a bundle without having added it creates it with
:class:`TrackPrior` at the same ``t_b`` (it lacks the given prior's information: conservative,
not exact).

**Association.** A scan at ``t`` (one sensor, one time; scans of a node in time order) is
associated with every track holding information at ``t`` (its fused estimate at ``t``, a
window state); a track's factor ``(Lambda, y)`` (:func:`dfusion.tracking.track_update_information`,
the PDA update in information form; for GNN the Kalman update of its detection) is this node's
own information at ``t`` in that track. With identities known (:meth:`TrackingNode.observe`)
the association is given and a measurement is an ordinary update of its track.

**Identities.** A track started here is ``TrackId(name, serial)``; ``first_serial`` lets a
restarted node go on past the serials it issued before.

**Merges** (track-to-track association, :class:`~dfusion.tracking.track_to_track.TrackToTrackAssociator`).
Two tracks found to be one target merge into the one born first (then: the smaller identity),
the rule every node applies the same way. A node decides a merge only of tracks its own scans hit
within the associator's ``distinct_for`` seconds: the evidence that two tracks are two targets
(both took a detection of one scan) is a node's own, so a node that does not see the pair (two
people passing each other in another camera's view) leaves the decision to the nodes that do,
and hears of it. A node that merges ``g`` into ``k`` (deciding itself,
or told by a neighbour) moves **its own** information of ``g`` into ``k`` (as own information at
the same state times, shared from then on over ``k``'s channels), drops what it received for
``g`` and records the end; every node does the same when it hears. Afterwards each
measurement's information is held as own information by exactly the node that took it, in
``k`` only, and reaches the others over ``k``'s channels: nothing counted twice, nothing lost
once the news has reached every node and the links have settled (own information of ``g``
older than ``k``'s window start cannot be moved: counted in ``stats.merge_outside_window``).
A node compares only tracks its own data bore on in the last ``merge_fresh`` seconds (in view
of one of its scans, or observed): only such a node can have seen the two tracks take
detections of one scan (distinct), and a merge is enforced on every node. A relay without
sensors, a node that does not see the place, or one cut off from the sensors by a link outage
(whose predictions of two people may drift together) decides no merge; it follows those of
the nodes that see (``tests/fusion/test_tracking_node.py``).

**Deletions.** A track a node's deleter ends is deleted at that node, recorded, and announced;
every node that hears deletes it too. The deleter sees the fused track (its estimate, and as
``last_hit`` the newest time anyone gave it information; as ``seen_here`` the newest time this
node's own scans hit or started it), so all nodes reach the same verdict, a node far from the
track's observers later by the links' latency: rules on the fused track whose verdict does not
come early there: :class:`~dfusion.tracking.deletion.ObserverDeleter` around the rules on the
age of the last hit (``StaleDeleter``, ``RegionDeleter``) leaves them to the nodes that see the
track; or a margin above the latency.

**Ends are reliable.** An end is sent to every neighbour in the next bundle, and again to a
neighbour whenever it sends a message for an ended track (it missed the news); messages for an
ended track are otherwise ignored (``stats.ended_track_messages``). Ends are remembered for
``ended_for`` seconds of the node's clock (a bundle sent longer ago than that starts no track: a
replayed or long-delayed message cannot bring back a track whose end is forgotten), at most ``16 max_tracks`` of them (the oldest
are forgotten first: ``stats.ends_forgotten``).

**Bounds.** At most ``max_tracks`` tracks (a message that would start more is not fused for
those tracks: ``stats.tracks_refused``); bundles of at most ``max_message_bytes`` (a send that
would be larger is split into several bundles); every message checked (:func:`decode_bundle`,
then each track's :meth:`FusionNode.receive`), rejections counted by reason and logged at
most once per ``log_interval``.
"""
from __future__ import annotations

import time as _time
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import MessageError, TimeError, ValidationError
from dfusion.fusion.bundle import (MAX_TRACKS_PER_BUNDLE, TrackBundle, TrackEnd, TrackMessage, decode_bundle,
                                   encode_bundle)
from dfusion.fusion.node import HOLD, MAX_AHEAD, FusionNode
from dfusion.fusion.stats import LOG_INTERVAL, RejectionLog
from dfusion.fusion.tree import SpanningTree
from dfusion.linalg import Array, as_spd, as_vector, symmetrize
from dfusion.models.base import MeasurementModel, MotionModel
from dfusion.tracking.association import GNN, DataAssociator
from dfusion.tracking.deletion import CovarianceDeleter, Deleter
from dfusion.tracking.gating import GaussianHypothesiser, Hypothesiser
from dfusion.tracking.initiation import Initiator, MofNInitiator
from dfusion.tracking.track import IdentityIssuer, Scan, Track, TrackId
from dfusion.tracking.track_to_track import TrackToTrackAssociator
from dfusion.tracking.tracker import track_update_information
from dfusion.wire import MAX_MESSAGE_BYTES, FrameKey

__all__ = ["TrackPrior", "TrackingNode", "TrackingStats"]

_BUNDLE_OVERHEAD = 64          # bytes of a bundle's envelope and header, at most (names of up to 256 bytes aside)
_TRACK_OVERHEAD = 40           # bytes per track entry besides its message and its origin's name, at most
_END_OVERHEAD = 60             # bytes per track end besides the names, at most


@dataclass(frozen=True)
class TrackPrior:
    """The common prior of every track at its birth time: mean 0, covariance
    ``diag(position_std^2, ..., velocity_std^2, ...)`` (the first half of the state is the
    position, the rest its derivatives). Broad: it is common information, and what a track
    knows comes from measurements."""

    position_std: float = 1.0e3
    velocity_std: float = 1.0e2

    def __post_init__(self) -> None:
        if not (0 < self.position_std < 1e8 and 0 < self.velocity_std < 1e8):
            raise ValidationError(f"track prior standard deviations must be in (0, 1e8), got {self}")

    def at(self, t: float, n: int) -> tuple[float, Array, Array]:
        """``(t, mean, cov)`` of a state of dimension ``n``."""
        axes = n // 2
        return float(t), np.zeros(n), np.diag([self.position_std**2] * axes + [self.velocity_std**2] * (n - axes))


@dataclass
class TrackingStats:
    """Counters of a :class:`TrackingNode` (the per-track counters are each track's ``FusionNode.stats``)."""

    births: int = 0
    tracks_heard: int = 0              # tracks created because a neighbour sent one
    merges: int = 0                    # tracks merged here (decided here or heard)
    merges_decided: int = 0
    deletions: int = 0                 # tracks deleted here (decided here or heard)
    deletions_decided: int = 0
    ended_track_messages: int = 0      # per-track messages for tracks that had ended (ignored)
    tracks_refused: int = 0            # tracks not started because of max_tracks
    merge_outside_window: int = 0      # own blocks of a merged track older than the survivor's window
    ends_forgotten: int = 0            # ends dropped before ended_for because more than max_ended were held
    bundles_sent: int = 0
    bytes_sent: int = 0
    bundles_received: int = 0
    bundles_rejected: int = 0
    track_messages_rejected: int = 0
    rejections: dict[str, int] = field(default_factory=dict)


@dataclass(eq=False)
class _TrackView:
    """What a :class:`~dfusion.tracking.deletion.Deleter` reads of a fused track."""

    id: TrackId
    node: FusionNode
    born: float
    time: float = 0.0
    last_hit: float | None = None
    hits: int = 0
    misses: int = 0
    consecutive_misses: int = 0
    recent: list[int] = field(default_factory=list)
    confirmed: bool = True
    seen: float | None = None          # newest time this node's own data bore on the track (in view, or observed)
    given_prior: bool = False          # added by add_track: its prior is informative from the start
    seen_here: float | None = None     # time of this node's newest own scan that hit the track

    def estimate(self) -> tuple[Array, Array]:
        return self.node.estimate()

    record = Track.record


class _Predicted:
    """A track's fused estimate at a scan's time, as the hypothesiser reads it."""

    __slots__ = ("mean", "cov")

    def __init__(self, mean: Array, cov: Array) -> None:
        self.mean, self.cov = mean, cov

    def estimate(self) -> tuple[Array, Array]:
        return self.mean, self.cov


class TrackingNode:
    """A fusion node for many targets (module docstring).

    Parameters
    ----------
    name, neighbors, motion : as :class:`FusionNode` (``neighbors``: the tree neighbours, or
        with ``links_change`` the links that exist at the start).
    associator, hypothesiser, initiator, deleter : the tracker's components (defaults: GNN, a
        0.99 gate, 3-of-5 initiation, a covariance deleter; ``deleter=False``: tracks end only
        when a neighbour's end is heard or :meth:`delete` is called).
    merger : the track-to-track associator (``None``: a default one; ``False``: no merges).
    merge_fresh : seconds: only tracks this node's own data (a scan that had them in view, an
        observation) bore on at most this long ago are compared for merges (module docstring, "Merges").
    prior : the common prior of every track.
    window, horizon, max_ahead, hold : each track's :class:`FusionNode` settings.
    links_change : links that change at run time (each track follows the tree rule).
    network_key, network, run : authentication of bundles (``docs/security.md``).
    epoch : this incarnation (default: the clock in nanoseconds); every track's ``FusionNode`` shares it.
    """

    def __init__(self, name: str, neighbors: Iterable[str], motion: MotionModel, *,
                 associator: DataAssociator | None = None, hypothesiser: Hypothesiser | None = None,
                 initiator: Initiator | None = None, deleter: Deleter | None | bool = None,
                 merger: TrackToTrackAssociator | None | bool = None, merge_fresh: float = 1.0,
                 prior: TrackPrior = TrackPrior(),
                 window: int | None = 100, horizon: float | None = None, max_ahead: float = MAX_AHEAD,
                 hold: float = HOLD, links_change: bool = False, peers: Iterable[str] | None = None,
                 network_key: bytes | None = None, network: str = "", run: str = "", epoch: int | None = None,
                 max_tracks: int = 1000, max_message_bytes: int = MAX_MESSAGE_BYTES, ended_for: float = 120.0,
                 first_serial: int = 0, log_interval: float = LOG_INTERVAL) -> None:
        nbrs = tuple(neighbors)
        if not isinstance(name, str) or not name or "#" in name:
            raise ValidationError(f"a tracking node's name must be a non-empty string without '#', got {name!r}")
        if name in nbrs or len(set(nbrs)) != len(nbrs):
            raise ValidationError(f"invalid neighbours of {name!r}: {nbrs}")
        if network_key is not None and (not isinstance(network_key, (bytes, bytearray)) or len(network_key) < 16):
            raise ValidationError("network_key must be at least 16 bytes (or None to turn authentication off)")
        if not (isinstance(max_tracks, int) and 1 <= max_tracks <= MAX_TRACKS_PER_BUNDLE):
            raise ValidationError(f"max_tracks must be an integer in [1, {MAX_TRACKS_PER_BUNDLE}], got {max_tracks!r}")
        if not (isinstance(first_serial, int) and first_serial >= 0):
            raise ValidationError(f"first_serial must be an integer >= 0, got {first_serial!r}")
        self.name = name
        self.neighbors = nbrs
        self.motion = motion
        self.associator = associator or GNN()
        self.hypothesiser = hypothesiser or GaussianHypothesiser()
        self.initiator = initiator or MofNInitiator(motion)
        self.deleter = None if deleter is False else (deleter or CovarianceDeleter())
        self.merger = None if merger is False else (merger or TrackToTrackAssociator())
        if not (isinstance(merge_fresh, (int, float)) and merge_fresh > 0 and np.isfinite(merge_fresh)):
            raise ValidationError(f"merge_fresh must be a positive number of seconds, got {merge_fresh!r}")
        self.merge_fresh = float(merge_fresh)
        self.prior = prior
        self.epoch = _time.time_ns() if epoch is None else int(epoch)
        if not 0 < self.epoch < 2**63:
            raise ValidationError(f"epoch must be in (0, 2^63), got {self.epoch}")
        self.links_change = bool(links_change)
        self.links: set[str] = set(nbrs)
        self.peers = None if peers is None else frozenset(peers)
        self.frame_key = None if network_key is None else FrameKey(bytes(network_key), network, run)
        self.max_tracks, self.max_message_bytes = max_tracks, int(max_message_bytes)
        self.ended_for = float(ended_for)
        #: Most ends remembered (the oldest are forgotten first).
        self.max_ended = 16 * max_tracks
        self._track_options = dict(window=window, horizon=horizon, max_ahead=max_ahead, hold=hold,
                                   max_message_bytes=self.max_message_bytes, log_interval=log_interval)
        self.issuer = IdentityIssuer(name)
        self.issuer.issued = first_serial
        #: The fusion of every live track: ``{track: FusionNode}``.
        self.tracks: dict[TrackId, FusionNode] = {}
        self._views: dict[TrackId, _TrackView] = {}
        #: Tracks that ended (deleted or merged), with the node time the end was recorded here.
        self.ended: dict[TrackId, tuple[TrackEnd, float]] = {}
        self._announce: dict[str, dict[TrackId, TrackEnd]] = {}
        self.time: float | None = None
        self._scan_time: float | None = None
        self.stats = TrackingStats()
        self.rejection_log = RejectionLog(name, log_interval)

    def __repr__(self) -> str:
        return f"TrackingNode({self.name!r}, neighbors={sorted(self.links)}, tracks={len(self.tracks)})"

    # ----------------------------------------------------------------------------------- tracks
    def born(self, track: TrackId) -> float:
        """Birth time of a live track (the time of its common prior)."""
        return self._views[track].born

    def _track(self, tid: TrackId, born: float,
               prior: tuple[float, Array, Array] | None = None) -> FusionNode | None:
        """The fusion of ``tid``, created with the common prior at ``born`` (or ``prior``) if new
        (``None``: over ``max_tracks``)."""
        node = self.tracks.get(tid)
        if node is not None:
            return node
        if len(self.tracks) >= self.max_tracks:
            self.stats.tracks_refused += 1
            return None
        links = sorted(self.links)
        tree = SpanningTree(self.name, links) if self.links_change else None
        node = FusionNode(self.name, links if self.links_change else self.neighbors, self.motion,
                          prior=prior or self.prior.at(born, self.motion.dim), epoch=self.epoch, tree=tree,
                          peers=self.peers, **self._track_options)
        if self.time is not None and self.time > node.latest_time:
            node.predict(self.time)
        self.tracks[tid] = node
        self._views[tid] = _TrackView(tid, node, float(born), given_prior=prior is not None)
        return node

    def add_track(self, track: TrackId, t: float, mean: ArrayLike, cov: ArrayLike) -> None:
        """A track every node knows from the start (a team of known size, a registered tag):
        its common prior is ``(t, mean, cov)`` instead of :class:`TrackPrior`, and it takes part
        in the association and :meth:`estimates` from the start. Every node must add it
        identically, before it takes or hears anything of it (module docstring)."""
        if not isinstance(track, TrackId):
            raise ValidationError(f"track must be a TrackId, got {track!r}")
        if track in self.tracks or track in self.ended:
            raise ValidationError(f"{self.name}: track {track} is already known here")
        n = self.motion.dim
        t = float(t)
        if not np.isfinite(t):
            raise TimeError(f"track {track}: prior time must be finite, got {t!r}")
        m = as_vector(mean, n, "track prior mean")
        P = as_spd(cov, n, "track prior covariance")
        if self._track(track, t, (t, m, P)) is None:
            raise ValidationError(f"{self.name}: at most {self.max_tracks} tracks")
        if track.origin == self.name:   # never issue this identity again
            self.issuer.issued = max(self.issuer.issued, track.serial + 1)

    def _informed(self, tid: TrackId) -> bool:
        """Whether a track holds information: measurements (own or received), or a given prior."""
        return self._views[tid].given_prior or self.tracks[tid].newest_information_time() is not None

    def _drop(self, tid: TrackId) -> FusionNode | None:
        self._views.pop(tid, None)
        if self.merger is not None:
            self.merger.forget(tid)
        return self.tracks.pop(tid, None)

    def estimates(self) -> list[tuple[TrackId, Array, Array]]:
        """``(track, mean, cov)`` of every track holding information (or a given prior), at the node's newest time."""
        return [(tid, *node.estimate()) for tid, node in sorted(self.tracks.items()) if self._informed(tid)]

    # ------------------------------------------------------------------------------ local data
    def predict(self, t: float) -> None:
        """Bring every track to ``t``; then the deleter and the track-to-track association run."""
        if self._advance(t):
            self._end_and_merge()

    def _advance(self, t: float) -> bool:
        """Bring every track to ``t`` (no deletion, no merge); whether the node's time moved."""
        t = float(t)
        if self.time is not None and t <= self.time:
            return False
        self.time = t
        for node in self.tracks.values():
            node.predict(t)
        self._expire_ends(t)
        return True

    def _end_and_merge(self) -> None:
        self._delete_ended()
        self._merge_duplicates()

    def observe(self, track: TrackId, t: float, z: ArrayLike, sensor: MeasurementModel, *,
                born: float | None = None) -> None:
        """A measurement of a known track (the association given: an oracle, or a tagged target);
        the track is created with the common prior at ``born`` (default ``t``) if new here."""
        if track in self.ended:
            raise ValidationError(f"track {track} has ended")
        node = self._track(track, t if born is None else born)
        if node is None:
            raise ValidationError(f"{self.name}: at most {self.max_tracks} tracks")
        if t > node.latest_time:
            self.predict(t)
        node.update(t, z, sensor)
        view = self._views[track]
        view.seen = t if view.seen is None else max(view.seen, t)
        view.seen_here = t if view.seen_here is None else max(view.seen_here, t)

    def process(self, scan: Scan, *, exclude: Iterable[TrackId] = ()) -> list[TrackId]:
        """Associate one scan of this node's sensors with the fused tracks, fuse it, start
        tracks from what no track explains; returns the tracks started. Scans in time order.
        ``exclude``: tracks the scan cannot have seen (a robot's camera never sees the robot
        itself): they take no part in the association.
        A scan newer than the node's time brings the tracks to it, and the deleter and the
        merger run after the scan (:meth:`predict` runs them at once)."""
        t = float(scan.time)
        if self._scan_time is not None and t < self._scan_time - 1e-9:
            raise TimeError(f"{self.name}: scan at t={t} is older than the previous scan ({self._scan_time})")
        self._scan_time = t
        # the tracks come to t, the scan is associated, and only then the deleter and the merger run
        # (as a centralized tracker's do): a track is not ended just before the detection that shows it is there
        advanced = self._advance(t)
        ids, views = [], []
        skip = set(exclude)
        for tid, node in sorted(self.tracks.items()):
            if tid in skip or not self._informed(tid) or t < node.filter.oldest_time:
                continue
            node.predict(t)   # a state at t (t is in the window)
            ids.append(tid)
            views.append(_Predicted(*node.estimate(t)))
        hyp = self.hypothesiser.hypothesise(views, scan)
        assoc = self.associator.associate(hyp)
        hit_ids = []
        for i, tid in enumerate(ids):
            if not assoc.active[i]:
                continue
            factor = track_update_information(hyp, assoc, i)
            if factor is not None:
                self.tracks[tid].add_local_information(t, *factor)
            hit = assoc.hit(i)
            if hit or hyp.visibility[i] >= 0.5:
                self._views[tid].record(hit, window=1)
                self._views[tid].seen = t
            if hit:
                hit_ids.append(tid)
                self._views[tid].seen_here = t
        if self.merger is not None and len(hit_ids) > 1:
            self.merger.distinct(hit_ids, t)
        if ids:
            claimed = (hyp.gated & assoc.active[:, None]).any(axis=0)
        else:
            claimed = np.zeros(len(scan.detections), dtype=bool)
        started = [self._birth(track) for track in self.initiator.initiate(scan, scan.detections[~claimed], self.issuer)]
        if advanced:
            self._end_and_merge()
        return [tid for tid in started if tid is not None]

    def _birth(self, track: Track) -> TrackId | None:
        """A track the initiator confirmed: its estimate becomes this node's own information at its time."""
        node = self._track(track.id, track.time)
        if node is None:
            return None
        _, mean0, cov0 = self.prior.at(track.time, self.motion.dim)
        Omega0 = np.linalg.inv(cov0)
        L = symmetrize(track.filter.Omega - Omega0)
        w, V = np.linalg.eigh(L)
        if w.min() < 0:   # a direction the initiator knows less about than the broad prior: keep the prior there
            L = symmetrize((V * np.maximum(w, 0.0)) @ V.T)
        node.add_local_information(track.time, L, track.filter.eta - Omega0 @ mean0)
        self._views[track.id].seen_here = track.time
        self.stats.births += 1
        return track.id

    # ------------------------------------------------------------------------- ends of tracks
    def _record_end(self, end: TrackEnd) -> None:
        self.ended[end.track] = (end, self.time if self.time is not None else end.at)
        while len(self.ended) > self.max_ended:   # the oldest ends go first (a flood of ends cannot grow a node)
            tid = next(iter(self.ended))
            del self.ended[tid]
            for pending in self._announce.values():
                pending.pop(tid, None)
            self.stats.ends_forgotten += 1
        for j in self.links:
            self._announce.setdefault(j, {})[end.track] = end

    def _expire_ends(self, now: float) -> None:
        old = [tid for tid, (_, at) in self.ended.items() if now - at > self.ended_for]
        for tid in old:
            del self.ended[tid]

    def _delete_ended(self) -> None:
        if self.deleter is None:
            return
        for tid in sorted(self.tracks):
            view = self._views[tid]
            newest = self.tracks[tid].newest_information_time()
            view.time = self.time if self.time is not None else view.born
            view.last_hit = newest
            if newest is not None and self.deleter.should_delete(view):
                self.delete(tid)

    def delete(self, tid: TrackId, *, decided: bool = True) -> None:
        """End track ``tid`` everywhere: here now, at the neighbours when they hear."""
        if self._drop(tid) is None:
            return
        self.stats.deletions += 1
        self.stats.deletions_decided += int(decided)
        self._record_end(TrackEnd(tid, None, 0.0, self.time or 0.0))

    def survivor(self, a: TrackId, b: TrackId) -> tuple[TrackId, TrackId]:
        """``(keep, gone)`` of two tracks found to be one target: keep the one born first, then the smaller id."""
        ka, kb = (self._views[a].born, a), (self._views[b].born, b)
        return (a, b) if ka <= kb else (b, a)

    def _merge_duplicates(self) -> None:
        if self.merger is None or self.time is None:
            return
        live = {tid: node.estimate() for tid, node in self.tracks.items()
                if self._views[tid].seen is not None and self.time - self._views[tid].seen <= self.merge_fresh
                and self._informed(tid)}
        for a, b in self.merger.check(live, self.time):
            if a in self.tracks and b in self.tracks:
                keep, gone = self.survivor(a, b)
                self.merge(gone, keep)

    def merge(self, gone: TrackId, keep: TrackId, *, keep_born: float | None = None, decided: bool = True) -> None:
        """Merge track ``gone`` into ``keep``: this node's own information of ``gone`` moves into
        ``keep`` (created with the common prior at ``keep_born`` if new here), what it received
        for ``gone`` is dropped, and the end is announced (module docstring)."""
        source = self.tracks.get(gone)
        if source is None or gone == keep:
            return
        born = self._views[keep].born if keep in self._views else keep_born
        if born is None:
            raise ValidationError(f"merge of {gone} into {keep}: the survivor's birth time is unknown here")
        own = source.own_information()
        seen_gone = self._views[gone].seen_here
        self._drop(gone)   # first: its place is the survivor's if the survivor is new here and the node is full
        target = self._track(keep, born)
        if target is None:   # (cannot happen: a place was just freed)
            raise ValidationError(f"merge of {gone} into {keep}: no place for the survivor")
        for t, L, y in own:
            if t < target.filter.oldest_time - target.filter.time_tol:
                self.stats.merge_outside_window += 1
                continue
            if t > target.latest_time:
                target.predict(t)
            target.add_local_information(t, L, y)
        seen = [v for v in (seen_gone, self._views[keep].seen_here) if v is not None]
        self._views[keep].seen_here = max(seen) if seen else None   # this node saw the target under either
        self.stats.merges += 1
        self.stats.merges_decided += int(decided)
        self._record_end(TrackEnd(gone, keep, born, self.time or 0.0))

    # ------------------------------------------------------------------------------- the links
    def link_up(self, neighbor: str) -> None:
        """A link to ``neighbor`` now exists (links that change): every track follows the tree rule."""
        self._links_required()
        if neighbor == self.name or (self.peers is not None and neighbor not in self.peers):
            raise ValidationError(f"{self.name!r} cannot link to {neighbor!r}")
        self.links.add(neighbor)
        for node in self.tracks.values():
            node.link_up(neighbor)
        # a neighbour that comes (back) hears every end this node remembers
        self._announce[neighbor] = {tid: end for tid, (end, _) in self.ended.items()}

    def link_down(self, neighbor: str) -> None:
        """The link to ``neighbor`` is gone (links that change)."""
        self._links_required()
        self.links.discard(neighbor)
        self._announce.pop(neighbor, None)
        for node in self.tracks.values():
            node.link_down(neighbor)

    def _links_required(self) -> None:
        if not self.links_change:
            raise ValidationError(f"{self.name!r} runs on a fixed tree: create it with links_change=True")

    # ------------------------------------------------------------------------------- messages
    def outgoing(self, sent_at: float | None = None) -> list[tuple[str, bytes]]:
        """``(neighbour, bundle)`` for every link: every track's message and the ends it has to
        hear (several bundles for a neighbour when one would exceed ``max_message_bytes``)."""
        per: dict[str, list[TrackMessage]] = {j: [] for j in sorted(self.links)}
        for tid, node in sorted(self.tracks.items()):
            born = self._views[tid].born
            for j, frame in node.outgoing(sent_at):
                if j in per:
                    per[j].append(TrackMessage(tid, born, frame))
        stamp = float(sent_at if sent_at is not None else (self.time or 0.0))
        out = []
        for j, messages in per.items():
            ends = tuple(self._announce.pop(j, {}).values())
            for chunk_msgs, chunk_ends in self._chunks(messages, ends):
                data = encode_bundle(TrackBundle(self.name, j, self.epoch, stamp, chunk_msgs, chunk_ends),
                                     self.frame_key)
                self.stats.bundles_sent += 1
                self.stats.bytes_sent += len(data)
                out.append((j, data))
        return out

    def _chunks(self, messages: list[TrackMessage], ends: tuple[TrackEnd, ...]):
        """Split into bundles of at most ``max_message_bytes`` and ``MAX_TRACKS_PER_BUNDLE`` tracks and ends
        each (the ends count in the byte budget as the track messages do)."""
        budget = self.max_message_bytes - _BUNDLE_OVERHEAD - len(self.name) - 256   # and the recipient's name
        msgs: list[TrackMessage] = []
        kept: list[TrackEnd] = []
        size = 0
        items = [(m, len(m.frame) + _TRACK_OVERHEAD + len(m.track.origin)) for m in messages]
        items += [(e, _END_OVERHEAD + len(e.track.origin) + (len(e.into.origin) if e.into else 0)) for e in ends]
        for item, cost in items:
            full = len(msgs) >= MAX_TRACKS_PER_BUNDLE or len(kept) >= MAX_TRACKS_PER_BUNDLE
            if (msgs or kept) and (size + cost > budget or full):
                yield tuple(msgs), tuple(kept)
                msgs, kept, size = [], [], 0
            (msgs if isinstance(item, TrackMessage) else kept).append(item)
            size += cost
        yield tuple(msgs), tuple(kept)

    def _rejected(self, reason: str, detail: str) -> MessageError:
        self.stats.bundles_rejected += 1
        self.stats.rejections[reason] = self.stats.rejections.get(reason, 0) + 1
        self.rejection_log.add(reason, detail)
        err = MessageError(detail)
        err.reason = reason
        return err

    def receive(self, data: bytes) -> int:
        """Fuse a neighbour's bundle; returns the number of state blocks that changed (all tracks).

        Raises :class:`MessageError` (with ``reason``), counted, when the bundle itself is
        refused (malformed, corrupt, unauthenticated, misaddressed, from a non-neighbour):
        nothing changes. A refused per-track message inside an accepted bundle changes
        nothing in its track and is counted (``stats.track_messages_rejected``, and by the
        track's ``FusionNode.stats``); the other tracks are fused.
        """
        try:
            bundle = decode_bundle(data, self.frame_key, self.max_message_bytes)
        except MessageError as exc:
            raise self._rejected(getattr(exc, "reason", "malformed"), str(exc)) from None
        if bundle.dst != self.name:
            raise self._rejected("misaddressed", f"bundle for {bundle.dst!r} delivered to {self.name!r}")
        allowed = self.peers if (self.links_change and self.peers is not None) else (
            None if self.links_change else set(self.neighbors))
        if allowed is not None and bundle.src not in allowed:
            raise self._rejected("not-a-neighbour", f"bundle from {bundle.src!r}, not a neighbour of {self.name!r}")
        if self.links_change and bundle.src not in self.links:
            self.stats.bundles_received += 1
            return 0     # over a link that no longer exists: ignored, as a FusionNode does
        self.stats.bundles_received += 1
        for end in bundle.ended:
            self._heard_end(end)
        changed = 0
        for m in bundle.tracks:
            if m.track in self.ended:
                self.stats.ended_track_messages += 1
                self._announce.setdefault(bundle.src, {})[m.track] = self.ended[m.track][0]
                continue
            known = m.track in self.tracks
            if not known and self.time is not None and bundle.sent_at < self.time - self.ended_for:
                # older than what the ends remember: a replayed or long-delayed message must not bring
                # back a track that ended (its end may be forgotten by now); counted
                self.stats.track_messages_rejected += 1
                self.rejection_log.add("stale", f"track {m.track} from {bundle.src!r} in a bundle sent at "
                                                f"{bundle.sent_at}, more than {self.ended_for:g} s ago")
                continue
            if known and abs(self._views[m.track].born - m.born) > 1e-9:
                self.stats.track_messages_rejected += 1
                self.rejection_log.add("born", f"track {m.track} from {bundle.src!r} born at {m.born}, here at "
                                               f"{self._views[m.track].born}")
                continue
            node = self._track(m.track, m.born)
            if node is None:
                continue
            try:
                changed += node.receive(m.frame)
            except MessageError as exc:
                self.stats.track_messages_rejected += 1
                self.rejection_log.add(getattr(exc, "reason", "malformed"), f"track {m.track}: {exc}")
                if not known:
                    self._drop(m.track)
                continue
            if not known:
                self.stats.tracks_heard += 1
        return changed

    def _heard_end(self, end: TrackEnd) -> None:
        if end.track in self.ended:
            return
        for _ in range(len(self.ended)):
            if end.into is None or end.into not in self.ended:
                break
            # the survivor itself ended meanwhile (a deletion or a later merge): follow it
            into_end = self.ended[end.into][0]
            end = TrackEnd(end.track, into_end.into, into_end.into_born if into_end.into else 0.0, end.at)
        if end.track in self.tracks:
            if end.into is None:
                self.delete(end.track, decided=False)
            else:
                self.merge(end.track, end.into, keep_born=end.into_born, decided=False)
            return
        self._record_end(end)

    def flush_log(self) -> None:
        """Write the pending summary of rejections now."""
        self.rejection_log.flush()
