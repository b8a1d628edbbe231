r"""Front end of anonymous sightings of a team of known size, with lock-out re-acquisition.

A team of known size (robots, tagged people) is tracked by a
:class:`~dfusion.fusion.TrackingNode` whose tracks are given from the start
(:meth:`~dfusion.fusion.TrackingNode.add_track`), with no initiator: a detection that no
track's gate holds is clutter, or a team member whose track has lost it. A track that
coasted away in a gap of sightings with a covariance too small for where its target went
is then **locked out**: its target's detections keep falling outside its gate, and with no
initiator nothing ever takes them. :class:`TeamSightingsFrontEnd` feeds the node's scans
(:meth:`TrackingNode.process`) and recovers from that, as
:class:`~dfusion.frontends.TargetTrackingFrontEnd` does for a single target:

1. **Unexplained detections.** A detection ``z_j`` (noise ``R_j``) outside the gate of every
   track's fused estimate at the scan's time (``d^2 = (z_j - m_k)^T (P_k + R_j)^-1 (z_j - m_k)
   > gamma`` for every track ``k``, position block; in view or not) is kept for ``window``
   seconds.
2. **A lock-out** is declared when ``k`` unexplained detections of this node (``k`` =
   :meth:`MonitorSettings.run_length`, the single-target lock-out test's run length, 5 with
   its defaults) agree on one target: each earlier one within the gate of the newest,
   ``(z_i - z)^T (R_i + R + D(t - t_i))^-1 (z_i - z) <= gamma``, where ``D(dt) = dt^2
   sigma_v^2 I`` is the spread of a target moving with velocity standard deviation
   ``velocity_std`` (a run of clutter is unlikely to agree: the clutter density is low).
3. **The lost track.** With ``c``, ``R_c`` the information-weighted mean of the detections and
   its covariance, ``candidates = "stale"`` (default): the likeliest track ``argmax_k N(c;
   m_k, P_k + R_c)`` of those holding no information since the first of these detections (no
   sighting of it here, none from any neighbour: a track backed by someone's sightings over
   the span is following a target); none: nothing is done (``no_candidate``).
   ``candidates = "likeliest"``: the likeliest of the tracks that took no detection of this
   scan here (a target is detected once per scan), re-acquired only if it holds no
   information since the first detection; if it does, the detections are taken to be this
   node's own error (its pose), as the single-target recovery does not recover a belief its
   neighbours back (``backed``).
4. **Re-acquisition**: the track's belief of the position at the scan's time is widened to
   cover the jump, process noise ``delta delta^T + R_c`` on the position block
   (``delta = c - m_k``; :meth:`dfusion.fusion.FusionNode.add_process_noise`, as the single-target
   recovery), and the newest detection is fused into it (:meth:`TrackingNode.observe`).
   Process noise is not exchanged information: nothing is double counted; each node
   recovers its own belief, and the neighbours follow the fixes it then shares.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from dfusion.errors import ValidationError
from dfusion.estimation.innovation import MonitorSettings
from dfusion.fusion.tracking_node import TrackingNode
from dfusion.linalg import Array, cholesky, spd_inverse, symmetrize
from dfusion.models.measurement import PositionFix
from dfusion.tracking.track import Scan, TrackId

__all__ = ["TeamSightingsFrontEnd", "TeamStats"]


@dataclass
class TeamStats:
    """Counters of a :class:`TeamSightingsFrontEnd`."""

    scans: int = 0
    detections: int = 0
    unexplained: int = 0            # detections outside every track's gate
    lockouts: int = 0               # runs of agreeing unexplained detections
    reacquisitions: int = 0         # lock-outs recovered (a track widened and given the detection)
    no_candidate: int = 0           # lock-outs with every track backed by recent information ("stale")
    backed: int = 0                 # lock-outs whose likeliest track was backed by recent information ("likeliest")
    events: list[tuple[float, TrackId, float]] = field(default_factory=list)   # (t, track, jump in m)


class TeamSightingsFrontEnd:
    """A node's scans of a team of known size, with lock-out re-acquisition (module docstring).

    Parameters
    ----------
    node : the :class:`TrackingNode` (its tracks given by ``add_track``, no initiator).
    settings : the lock-out test's settings (its gate ``gamma`` and run length ``k``).
    velocity_std : m/s, the spread of a target's motion between agreeing detections.
    window : s, how long an unexplained detection is kept.
    candidates : ``"stale"`` or ``"likeliest"``: which track a lock-out re-acquires (module docstring).
    """

    def __init__(self, node: TrackingNode, settings: MonitorSettings = MonitorSettings(), *,
                 velocity_std: float = 0.1, window: float = 20.0, candidates: str = "stale") -> None:
        if not (math.isfinite(velocity_std) and velocity_std > 0 and math.isfinite(window) and window > 0):
            raise ValidationError(f"velocity_std and window must be finite and > 0, got {velocity_std!r}, {window!r}")
        if candidates not in ("likeliest", "stale"):
            raise ValidationError(f"candidates must be 'likeliest' or 'stale', got {candidates!r}")
        self.candidates = candidates
        self.node = node
        self.gamma = settings.gate(2)
        self.run_length = settings.run_length()
        self.velocity_std = float(velocity_std)
        self.window = float(window)
        self.pending: list[tuple[float, Array, Array]] = []      # unexplained (t, z, R), oldest first
        self.stats = TeamStats()

    def process(self, scan: Scan, *, exclude: Iterable[TrackId] = ()) -> None:
        """Associate ``scan`` with the node's fused tracks (:meth:`TrackingNode.process`; ``exclude``:
        tracks the scan cannot have seen, e.g. the observer itself), then re-acquire a locked-out
        track from the detections no track's gate holds."""
        node, t = self.node, float(scan.time)
        node.predict(t)
        Z = scan.detections
        self.stats.scans += 1
        self.stats.detections += Z.shape[0]
        skip = set(exclude)
        est = {tid: f.estimate(t) for tid, f in node.tracks.items() if t >= f.filter.oldest_time and tid not in skip}
        unexplained = []
        for j in range(Z.shape[0]):
            R = scan.detection_noise(j)
            if all(_d2(Z[j] - m[:2], P[:2, :2] + R) > self.gamma for m, P in est.values()):
                unexplained.append(j)
        node.process(scan, exclude=skip)
        took = {tid for tid, (_, P) in est.items()     # the tracks that took a detection of this scan
                if np.trace(node.tracks[tid].estimate(t)[1][:2, :2]) < (1.0 - 1e-6) * np.trace(P[:2, :2])}
        self.pending = [p for p in self.pending if t - p[0] <= self.window]
        for j in unexplained:   # (an excluded track is never re-acquired from this scan)
            self.stats.unexplained += 1
            z, R = Z[j], scan.detection_noise(j)
            agree = [i for i, (ti, zi, Ri) in enumerate(self.pending)
                     if _d2(zi - z, Ri + R + ((t - ti) * self.velocity_std) ** 2 * np.eye(2)) <= self.gamma]
            if len(agree) + 1 < self.run_length:
                self.pending.append((t, z, R))
                continue
            self.stats.lockouts += 1
            members = [self.pending[i] for i in agree] + [(t, z, R)]
            self.pending = [p for i, p in enumerate(self.pending) if i not in set(agree)]
            self._reacquire(t, z, R, members, skip | took)

    def _reacquire(self, t: float, z: Array, R: Array, members: list[tuple[float, Array, Array]],
                   skip: set[TrackId]) -> None:
        """Re-acquire the lost track of ``members`` (agreeing unexplained detections, the newest
        ``(z, R)`` at ``t``); ``skip``: tracks excluded from this scan or that took a detection of it."""
        node = self.node
        t_first = min(m[0] for m in members)
        Om = sum(spd_inverse(Ri, "detection noise") for _, _, Ri in members)
        R_c = spd_inverse(Om, "cluster information")
        c = R_c @ sum(spd_inverse(Ri, "detection noise") @ zi for _, zi, Ri in members)
        def stale(f) -> bool:
            newest = f.newest_information_time()
            return newest is None or newest < t_first - 1e-9

        best, best_ll = None, -math.inf
        for tid, f in sorted(node.tracks.items()):
            if tid in skip or t < f.filter.oldest_time or (self.candidates == "stale" and not stale(f)):
                continue
            m, P = f.estimate(t)
            S = symmetrize(P[:2, :2] + R_c)
            ll = -0.5 * _d2(c - m[:2], S) - 0.5 * math.log(np.linalg.det(S))
            if ll > best_ll:
                best, best_ll = tid, ll
        if best is None:
            self.stats.no_candidate += 1
            return
        if not stale(node.tracks[best]):
            self.stats.backed += 1
            return
        f = node.tracks[best]
        m, _ = f.estimate(t)
        delta = c - m[:2]
        Q = np.zeros((f.filter.n, f.filter.n))
        Q[:2, :2] = symmetrize(np.outer(delta, delta) + R_c)
        f.add_process_noise(t, Q)
        node.observe(best, t, z, PositionFix(z, R))
        self.stats.reacquisitions += 1
        self.stats.events.append((t, best, float(np.linalg.norm(delta))))


def _d2(nu: Array, S: Array) -> float:
    """``nu^T S^-1 nu`` by a Cholesky solve."""
    C = cholesky(symmetrize(S), "innovation covariance")
    w = np.linalg.solve(C, nu)
    return float(w @ w)
