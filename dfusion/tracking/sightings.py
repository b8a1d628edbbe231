r"""Scans from a robot's anonymous range-bearing sightings of other targets.

A robot at estimated pose ``s^ = (x_s, y_s, theta_s)`` with covariance ``P_s`` (its
localizer's) sees targets at range ``r`` and bearing ``b`` (relative to its heading), with
noise ``N(0, diag(sigma_r^2, sigma_b^2))`` and *without* their identities. Each sighting
becomes a world-frame position detection (``docs/robots.md``, "pose uncertainty in the
measurement"; :meth:`dfusion.models.TargetRangeBearing.position_fix`)::

    p = s^_xy + r (cos(theta_s + b), sin(theta_s + b))
    R_p = G diag(sigma_r^2, sigma_b^2) G^T + J P_s J^T
    G = dp/d(r, b) = [[c, -r s], [s, r c]],  J = dp/ds = [[1, 0, -r s], [0, 1, r c]],
    c = cos(theta_s + b), s = sin(theta_s + b)

the first-order (linearization) propagation of the sighting noise and of the observer's
pose error ``s - s^`` through ``p(r, b, s)`` (Bar-Shalom, Li & Kirubarajan, *Estimation
with Applications to Tracking and Navigation*, 2001, sec. 1.4.15 for the polar-to-
Cartesian conversion; the pose term is the same first-order propagation, assuming the
pose error independent of the sighting noise and of the target). ``R_p`` differs per
sighting (it grows with ``r``), so the scan carries it per detection
(:attr:`dfusion.tracking.Scan.noise`). Sightings of one camera frame share the observer's
pose error, which this treats as independent between detections (as the single-target
MRCLAM nodes do).

The camera's view (:class:`CameraView`): targets within ``half_angle`` of the heading and
between ``min_range`` and ``max_range``. A track's probability of being in view
(:meth:`CameraView.probability`) is the share of a fixed set of samples of its position
estimate ``N(x^, P^)`` that fall in the view seen from ``s^``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import ShapeError, ValidationError
from dfusion.geometry import wrap_angle
from dfusion.linalg import Array, as_spd, as_vector
from dfusion.models import PositionSensor, TargetRangeBearing
from dfusion.tracking.track import Scan

__all__ = ["CameraView", "sightings_scan", "VIEW_SAMPLES"]

#: Number of samples of a track's position estimate used by :meth:`CameraView.probability`
#: (a fixed, seeded set: the probability is deterministic, resolution 1/256).
VIEW_SAMPLES = 256
_UNIT = np.random.default_rng(20090724).standard_normal((VIEW_SAMPLES, 2))


@dataclass(frozen=True)
class CameraView:
    """A robot camera's field of view: bearing within ``+-half_angle`` (rad), range in ``[min_range, max_range]`` (m)."""

    half_angle: float
    min_range: float
    max_range: float

    def __post_init__(self) -> None:
        if not (0.0 < self.half_angle <= math.pi):
            raise ValidationError(f"half_angle must be in (0, pi], got {self.half_angle!r}")
        if not (math.isfinite(self.max_range) and 0.0 <= self.min_range < self.max_range):
            raise ValidationError(f"need 0 <= min_range < max_range (finite), got {self.min_range!r}, {self.max_range!r}")

    def contains(self, pose: ArrayLike, xy: ArrayLike) -> Array:
        """Whether points ``xy`` ((2,) or (n, 2)) are in view from ``pose`` ``(x, y, theta)``."""
        s = as_vector(pose, 3, "pose")
        p = np.asarray(xy, dtype=float)
        d = p.reshape(-1, 2) - s[:2]
        r = np.hypot(d[:, 0], d[:, 1])
        b = wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - s[2])
        inside = (np.abs(b) <= self.half_angle) & (r >= self.min_range) & (r <= self.max_range)
        return inside if p.ndim == 2 else inside[0]

    def probability(self, pose: ArrayLike, mean: ArrayLike, cov: ArrayLike) -> float:
        """Probability that a target with position estimate ``N(mean[:2], cov[:2, :2])`` is in view
        from ``pose``: the share of :data:`VIEW_SAMPLES` fixed samples in view."""
        m = np.asarray(mean, dtype=float)[:2]
        P = np.asarray(cov, dtype=float)[:2, :2]
        lam, V = np.linalg.eigh(0.5 * (P + P.T))
        L = V * np.sqrt(np.maximum(lam, 0.0))
        return float(np.mean(self.contains(pose, m + _UNIT @ L.T)))


def sightings_scan(t: float, ranges: ArrayLike, bearings: ArrayLike, pose: ArrayLike, pose_cov: ArrayLike,
                   range_std: float, bearing_std: float, *, view: CameraView | None, detection_probability: float,
                   clutter_density: float, source: str = "") -> Scan:
    """One camera frame's anonymous sightings as a :class:`~dfusion.tracking.Scan` of world-frame positions.

    Each sighting ``(ranges[j], bearings[j])`` becomes the position ``p_j`` with its own
    covariance ``R_p,j`` (module docstring), for a constant-velocity state ``[x, y, vx, vy]``
    (the scan's sensor measures the position, ``H = [I 0]``; its nominal ``R`` is unused).
    ``view``: the camera's view from the estimated ``pose`` (``None``: every track in view);
    ``clutter_density``: false sightings per m^2 per frame.
    """
    r = np.atleast_1d(np.asarray(ranges, dtype=float))
    b = np.atleast_1d(np.asarray(bearings, dtype=float))
    if r.ndim != 1 or r.shape != b.shape:
        raise ShapeError(f"ranges and bearings must be two (k,) arrays, got shapes {r.shape} and {b.shape}")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(b))) or np.any(r < 0):
        raise ValidationError("sighting ranges must be finite and >= 0, bearings finite")
    s = as_vector(pose, 3, "observer pose")
    Ps = as_spd(pose_cov, 3, "observer pose covariance")
    fixes = [TargetRangeBearing(s, Ps, (ri, bi), range_std, bearing_std).position_fix() for ri, bi in zip(r, b)]
    Z = np.array([f.z for f in fixes]).reshape(-1, 2)
    noise = np.array([f.R for f in fixes]).reshape(-1, 2, 2)
    vp = None if view is None else (lambda mean, cov: view.probability(s, mean, cov))
    return Scan(float(t), Z, PositionSensor(2, range_std), clutter_density, detection_probability,
                source=source, view_probability=vp, noise=noise)
