r"""Tracks, their network-unique identities, and the scans a tracker takes.

**Identity.** A track's identity is the pair ``(origin, serial)``: the name of the node
that started it and that node's count of tracks started so far (:class:`IdentityIssuer`).
Node names are unique in a network, so identities are unique without any message, and
deterministic: the same detections in the same order give the same identities. Identities
are totally ordered (``origin`` first, then ``serial``), so a rule such as "two tracks
found to be one target keep the smaller identity" gives the same answer on every node.

**State.** A track's filter is an :class:`~dfusion.estimation.ExtendedInformationFilter`
(a Kalman filter in information form, ``Omega = P^-1``, ``eta = Omega x``): what a track
learns from a scan is a factor ``(Lambda, y)`` added to ``(Omega, eta)``, the form the
fusion nodes exchange.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import ShapeError, TimeError, ValidationError
from dfusion.estimation.eif import ExtendedInformationFilter
from dfusion.linalg import Array, symmetrize
from dfusion.models.base import MeasurementModel

__all__ = ["TrackId", "IdentityIssuer", "Track", "Scan"]


@dataclass(frozen=True, order=True)
class TrackId:
    """A network-unique track identity: the starting node's name and its serial number there."""

    origin: str
    serial: int

    def __str__(self) -> str:
        return f"{self.origin}#{self.serial}"


class IdentityIssuer:
    """Issues ``TrackId(origin, 0), TrackId(origin, 1), ...`` for one node."""

    def __init__(self, origin: str) -> None:
        if not isinstance(origin, str) or not origin or "#" in origin:
            raise ValidationError(f"track origin must be a non-empty name without '#', got {origin!r}")
        self.origin = origin
        self.issued = 0

    def next(self) -> TrackId:
        tid = TrackId(self.origin, self.issued)
        self.issued += 1
        return tid


@dataclass(eq=False)
class Track:
    """One target's track.

    Attributes
    ----------
    id : its network-unique identity.
    filter : the per-track information filter (its ``Omega``, ``eta`` are the state at ``time``).
    time : time of the state (s).
    born : time the track was started.
    confirmed : ``False`` while tentative (initiation not finished).
    hits : scans (where it could be seen) in which a detection was associated with it.
    misses : scans (where it could be seen) in which none was; ``consecutive_misses`` since the last hit.
    last_hit : time of the last hit (``None`` before any).
    recent : 1 (hit) / 0 (miss) of the most recent scans where it could be seen, newest last
             (the M-of-N window of :class:`~dfusion.tracking.initiation.MofNInitiator`).
    """

    id: TrackId
    filter: ExtendedInformationFilter
    time: float
    born: float
    confirmed: bool = False
    hits: int = 0
    misses: int = 0
    consecutive_misses: int = 0
    recent: list[int] = field(default_factory=list)
    last_hit: float | None = None

    @property
    def seen_here(self) -> float | None:
        """Time of the newest hit by this tracker's own scans: every hit of a tracker's track is its own
        (a fusion node's tracks also hold its neighbours' information: ``TrackingNode``)."""
        return self.last_hit

    def predict(self, t: float) -> None:
        """Bring the state forward to ``t`` (no change when ``t`` equals the track's time)."""
        dt = t - self.time
        if dt < -1e-12:
            raise TimeError(f"track {self.id} is at t={self.time}, cannot predict back to t={t}")
        if dt > 1e-12:
            self.filter.predict(dt)
        self.time = max(self.time, t)

    def estimate(self) -> tuple[Array, Array]:
        """``(mean, cov)`` of the state at ``self.time``."""
        return self.filter.estimate()

    def add_information(self, info: Array, vec: Array) -> None:
        """Add a factor ``(Lambda, y)`` learned from a scan."""
        self.filter.Omega = symmetrize(self.filter.Omega + info)
        self.filter.eta = self.filter.eta + vec

    def record(self, hit: bool, window: int) -> None:
        """Count a scan in which the track could be seen: a hit or a miss."""
        if hit:
            self.hits += 1
            self.last_hit = self.time
            self.consecutive_misses = 0
        else:
            self.misses += 1
            self.consecutive_misses += 1
        self.recent.append(1 if hit else 0)
        del self.recent[:-window]


@dataclass(frozen=True)
class Scan:
    """The detections of one sensor at one time.

    Attributes
    ----------
    time : when the detections were taken (s).
    detections : (k, m) measurements, ``m = sensor.dim_z``; ``k`` may be 0.
    sensor : the measurement model (``h``, ``H``, ``R``, ``residual``, ``dim_z``).
    clutter_density : ``lambda``, false detections per unit measurement volume in this scan.
    detection_probability : ``P_D`` of a target in view.
    in_view : ``in_view(x) -> bool`` for a state ``x`` (``None``: every target is in view).
              A track out of view has ``P_D = 0`` in this scan: it is neither updated nor missed.
    source : name of the sensor (for logs and per-camera bookkeeping).
    view_probability : optional ``view_probability(mean, cov) -> float``, the probability that a
              target with this estimate is in the view; when given it replaces ``in_view``: the
              track's detection probability is ``P_D`` times it, and a scan without a detection
              counts as a miss only when it is at least 1/2 (a target near the edge of a view
              is not missed by a camera that probably does not see it).
    noise : optional (k, m, m) measurement noise covariance of each detection, replacing
              ``sensor.R`` for that detection (a sensor whose detections differ in accuracy, e.g.
              range-bearing sightings converted to world-frame positions, whose covariance grows
              with the range and the observer's pose uncertainty:
              :func:`dfusion.tracking.sightings.sightings_scan`). ``None``: ``sensor.R`` for all.
    """

    time: float
    detections: Array
    sensor: MeasurementModel
    clutter_density: float
    detection_probability: float
    in_view: Callable[[Array], bool] | None = None
    source: str = ""
    view_probability: Callable[[Array, Array], float] | None = None
    noise: Array | None = None

    def __post_init__(self) -> None:
        m = int(self.sensor.dim_z)
        z = np.asarray(self.detections, dtype=float)
        if z.size == 0:
            z = np.zeros((0, m))
        if z.ndim != 2 or z.shape[1] != m:
            raise ShapeError(f"scan detections must be (k, {m}), got shape {np.shape(self.detections)}")
        if not np.all(np.isfinite(z)):
            raise ValidationError("scan detections must be finite")
        if not math.isfinite(self.time):
            raise TimeError(f"scan time must be finite, got {self.time!r}")
        if not (math.isfinite(self.clutter_density) and self.clutter_density >= 0):
            raise ValidationError(f"clutter density must be >= 0, got {self.clutter_density!r}")
        if not (0.0 <= self.detection_probability <= 1.0):
            raise ValidationError(f"detection probability must be in [0, 1], got {self.detection_probability!r}")
        object.__setattr__(self, "detections", z)
        if self.noise is not None:
            R = np.asarray(self.noise, dtype=float)
            if R.size == 0 and z.shape[0] == 0:
                R = np.zeros((0, m, m))
            if R.shape != (z.shape[0], m, m):
                raise ShapeError(f"scan noise must be ({z.shape[0]}, {m}, {m}) (one covariance per detection), "
                                 f"got shape {R.shape}")
            if not np.all(np.isfinite(R)):
                raise ValidationError("scan noise covariances must be finite")
            if not np.allclose(R, np.swapaxes(R, 1, 2), rtol=1e-9, atol=1e-12):
                raise ValidationError("scan noise covariances must be symmetric")
            object.__setattr__(self, "noise", 0.5 * (R + np.swapaxes(R, 1, 2)))

    def detection_noise(self, j: int) -> Array:
        """The noise covariance of detection ``j``: ``noise[j]``, or ``sensor.R`` when the scan has no ``noise``."""
        if self.noise is None:
            return np.asarray(self.sensor.R, dtype=float)
        return self.noise[j]

    def sees(self, x: ArrayLike) -> bool:
        """Whether a target at state ``x`` is in this scan's view."""
        return True if self.in_view is None else bool(self.in_view(np.asarray(x)))

    def visibility(self, mean: Array, cov: Array) -> float:
        """Probability that a target with estimate ``(mean, cov)`` is in view (0 or 1 from ``in_view``)."""
        if self.view_probability is not None:
            p = float(self.view_probability(mean, cov))
            if not 0.0 <= p <= 1.0:
                raise ValidationError(f"view probability must be in [0, 1], got {p!r}")
            return p
        return 1.0 if self.sees(mean) else 0.0
