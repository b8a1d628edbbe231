r"""Initiators: new tracks from detections that no confirmed track explains.

:class:`MofNInitiator` starts tracks from the detections alone, in three stages:

1. **Seed.** A detection no track takes becomes a seed ``(t_1, z_1)``.
2. **Two-point differencing** (Bar-Shalom, Li & Kirubarajan, *Estimation with
   Applications to Tracking and Navigation*, 2001, sec. 5.5.3). A later detection ``z_2``
   at ``t_2`` (``dt = t_2 - t_1 >= min_dt``) within ``v_max dt + k_sigma sqrt(2) sigma``
   of the seed (assigned to seeds by :func:`dfusion.assignment.gated_assignment` on the distances) starts a
   tentative track at ``t_2`` with, for a sensor measuring the position with noise ``R``::

       x = [z_2, (z_2 - z_1) / dt],   P = [[R, R / dt], [R / dt, 2 R / dt^2]]

   the exact covariance of the estimation error of this estimate when the target moves at
   constant velocity between the two detections (``z_2 - p_2 = v_2``,
   ``(z_2 - z_1)/dt - v = (v_2 - v_1)/dt`` with independent ``v_1, v_2 ~ N(0, R)``): no
   prior on the velocity, so the covariance is honest whatever the target's speed (the
   motion model's process noise over ``dt`` is added, a slight overstatement).
3. **M of N.** Tentative tracks are predicted and updated like confirmed ones, with GNN on
   the detections left over. The two starting detections count as two hits; a tentative
   track is confirmed, and gets its network identity, as soon as ``m`` of its last ``n``
   scans in view were hits, and dropped when it has ``n`` scans and fewer than ``m`` hits
   among the last ``n``. Seeds older than ``max_seed_age`` are dropped.

The sensor must measure the position directly (``H = [I 0]``, linear), e.g.
:class:`~dfusion.models.PositionSensor`.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from dfusion.assignment import gated_assignment

from dfusion.errors import ValidationError
from dfusion.estimation.delayed_state import measurement_information
from dfusion.estimation.eif import ExtendedInformationFilter
from dfusion.linalg import Array, symmetrize
from dfusion.models.base import MeasurementModel, MotionModel
from dfusion.tracking.association import GNN
from dfusion.tracking.gating import GaussianHypothesiser
from dfusion.tracking.track import IdentityIssuer, Scan, Track

__all__ = ["Initiator", "MofNInitiator", "NoInitiator", "two_point_state"]


class Initiator(ABC):
    """Component kind: turns detections no confirmed track takes into confirmed tracks."""

    @abstractmethod
    def initiate(self, scan: Scan, detections: Array, issuer: IdentityIssuer) -> list[Track]:
        """Process ``detections`` (rows of ``scan.detections`` no confirmed track took); return the tracks
        confirmed by this scan, with identities from ``issuer``."""

    @property
    @abstractmethod
    def tentative(self) -> list[Track]:
        """Tracks being initiated (not confirmed yet)."""


class NoInitiator(Initiator):
    """Starts no track: the tracks are given (:meth:`~dfusion.tracking.MultiTargetTracker.add_track`),
    e.g. a team of known size started from known positions; a detection no track takes is
    treated as clutter."""

    def initiate(self, scan: Scan, detections: Array, issuer: IdentityIssuer) -> list[Track]:
        return []

    @property
    def tentative(self) -> list[Track]:
        return []


def _position_axes(sensor: MeasurementModel, n: int) -> int:
    m = int(sensor.dim_z)
    expect = np.zeros((m, n))
    expect[:, :m] = np.eye(m)
    if (not getattr(sensor, "is_linear", False) or 2 * m != n
            or not np.array_equal(np.asarray(sensor.H(np.zeros(n)), dtype=float), expect)):
        raise ValidationError("two-point initiation needs a linear sensor measuring the position (H = [I 0]) "
                              "of a constant-velocity state [position, velocity]")
    return m


def two_point_state(z1: Array, z2: Array, dt: float, R: Array) -> tuple[Array, Array]:
    """State ``[z2, (z2 - z1)/dt]`` and its error covariance ``[[R, R/dt], [R/dt, 2R/dt^2]]`` (module docstring)."""
    if not (math.isfinite(dt) and dt > 0):
        raise ValidationError(f"two-point differencing needs dt > 0, got {dt!r}")
    z1 = np.asarray(z1, dtype=float)
    z2 = np.asarray(z2, dtype=float)
    x = np.concatenate([z2, (z2 - z1) / dt])
    P = np.block([[R, R / dt], [R / dt, 2.0 * R / dt**2]])
    return x, symmetrize(P)


@dataclass(eq=False)
class _Seed:
    time: float
    z: Array


class MofNInitiator(Initiator):
    """Seed, two-point differencing, then M of N (module docstring).

    Parameters
    ----------
    motion : the tracks' motion model (constant velocity).
    m, n : confirm with ``m`` hits among the last ``n`` scans in view (the two starting detections count).
    max_speed : ``v_max`` (m/s) for pairing a detection with a seed.
    k_sigma : pairing radius in standard deviations of the difference of two detections.
    min_dt, max_seed_age : a seed pairs only with detections ``min_dt`` to ``max_seed_age`` seconds later.
    gate : gate probability of the tentative tracks' association.
    velocity_std : optional prior standard deviation of a target's velocity (m/s) per axis.
    """

    def __init__(self, motion: MotionModel, *, m: int = 3, n: int = 5, max_speed: float = 3.0, k_sigma: float = 3.0,
                 min_dt: float = 0.05, max_seed_age: float = 0.35, gate: float = 0.99,
                 velocity_std: float | None = None) -> None:
        if not (isinstance(m, int) and isinstance(n, int) and 2 <= m <= n):
            raise ValidationError(f"M of N needs integers 2 <= m <= n, got m={m!r}, n={n!r}")
        for name, v in (("max_speed", max_speed), ("k_sigma", k_sigma), ("min_dt", min_dt),
                        ("max_seed_age", max_seed_age)):
            if not (math.isfinite(v) and v > 0):
                raise ValidationError(f"{name} must be positive and finite, got {v!r}")
        if velocity_std is not None and not (math.isfinite(velocity_std) and velocity_std > 0):
            raise ValidationError(f"velocity_std must be positive and finite, got {velocity_std!r}")
        self.velocity_std = velocity_std
        if max_seed_age < min_dt:
            raise ValidationError(f"max_seed_age ({max_seed_age}) must be >= min_dt ({min_dt})")
        self.motion = motion
        self.m, self.n = m, n
        self.max_speed, self.k_sigma = float(max_speed), float(k_sigma)
        self.min_dt, self.max_seed_age = float(min_dt), float(max_seed_age)
        self.hypothesiser = GaussianHypothesiser(gate)
        self.associator = GNN()
        self.seeds: list[_Seed] = []
        self.candidates: list[Track] = []
        self.candidate_ids: IdentityIssuer | None = None

    @property
    def tentative(self) -> list[Track]:
        return list(self.candidates)

    def initiate(self, scan: Scan, detections: Array, issuer: IdentityIssuer) -> list[Track]:
        _position_axes(scan.sensor, self.motion.dim)
        if scan.noise is not None:
            raise ValidationError("MofNInitiator needs one noise covariance for all detections of a scan "
                                  "(a scan with per-detection noise is not supported yet)")
        Z = np.asarray(detections, dtype=float).reshape(-1, int(scan.sensor.dim_z))
        if self.candidate_ids is None:
            self.candidate_ids = IdentityIssuer(issuer.origin + "~tentative")
        left = self._update_candidates(scan, Z)
        left = self._pair_seeds(scan, Z, left, self.candidate_ids)
        self.seeds = [s for s in self.seeds if scan.time - s.time <= self.max_seed_age + 1e-9]
        self.seeds.extend(_Seed(scan.time, Z[j].copy()) for j in left)
        confirmed = []
        for track in list(self.candidates):
            if len(track.recent) >= 1 and sum(track.recent[-self.n:]) >= self.m:
                track.confirmed = True
                track.id = issuer.next()
                confirmed.append(track)
                self.candidates.remove(track)
            elif len(track.recent) >= self.n:
                self.candidates.remove(track)
        return confirmed

    def _update_candidates(self, scan: Scan, Z: Array) -> list[int]:
        """Tentative tracks take detections by GNN; returns the detections left."""
        if not self.candidates:
            return list(range(len(Z)))
        for track in self.candidates:
            track.predict(scan.time)
        sub = Scan(scan.time, Z, scan.sensor, scan.clutter_density, scan.detection_probability, scan.in_view,
                   scan.source, scan.view_probability)
        hyp = self.hypothesiser.hypothesise(self.candidates, sub)
        assoc = self.associator.associate(hyp)
        taken = set()
        for t, track in enumerate(self.candidates):
            if not assoc.active[t]:
                continue
            j = np.flatnonzero(assoc.weights[t] > 0.5)
            if not j.size and hyp.visibility[t] < 0.5:
                continue
            if j.size:
                track.add_information(*measurement_information(scan.sensor, Z[j[0]], np.zeros_like(hyp.means[t])))
                taken.add(int(j[0]))
            track.record(bool(j.size), self.n)
        return [j for j in range(len(Z)) if j not in taken]

    def _pair_seeds(self, scan: Scan, Z: Array, left: list[int], tentative_ids: IdentityIssuer) -> list[int]:
        """Pair seeds with detections into tentative tracks; returns the detections left."""
        n = self.motion.dim
        seeds = [s for s in self.seeds if scan.time - s.time >= self.min_dt - 1e-9]
        if not seeds or not left:
            return left
        R = np.asarray(scan.sensor.R, dtype=float)
        sigma = math.sqrt(float(np.max(np.linalg.eigvalsh(R))))
        D = np.full((len(seeds), len(left)), np.inf)
        for a, s in enumerate(seeds):
            radius = self.max_speed * (scan.time - s.time) + self.k_sigma * math.sqrt(2.0) * sigma
            d = np.linalg.norm(Z[left] - s.z, axis=1)
            D[a] = np.where(d <= radius, d, np.inf)
        used: set[int] = set()
        paired: set[int] = set()
        for a, b in zip(*gated_assignment(D)):   # pairs within their radius only
            s, j = seeds[a], left[b]
            dt = scan.time - s.time
            x, P = two_point_state(s.z, Z[j], dt, R)
            P = symmetrize(P + self.motion.Q(dt, x))
            filt = ExtendedInformationFilter(self.motion)
            filt.initialize(x, P)
            if self.velocity_std is not None:
                axes = n // 2
                filt.Omega = symmetrize(filt.Omega + np.diag([0.0] * axes + [self.velocity_std**-2] * axes))
            track = Track(tentative_ids.next(), filt, scan.time, s.time, confirmed=False)
            track.record(True, self.n)
            track.record(True, self.n)
            self.candidates.append(track)
            used.add(j)
            paired.add(id(s))
        self.seeds = [s for s in self.seeds if id(s) not in paired]
        return [j for j in left if j not in used]
