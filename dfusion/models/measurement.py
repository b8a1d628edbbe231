r"""Measurement models.

``PositionSensor``: ``z = [I 0] x + v``, ``v ~ N(0, std^2 I)``: observes the
first ``dim`` components (the position) of any state.

``RangeBearing``: range and bearing ``[r, wrap(atan2(dy, dx) - theta_s)]`` to a
target from a sensor with known pose.

``RSSISensor``: received signal strength at fixed receivers under the
log-distance path-loss model ``p0 - 10 n log10(d / d0)``; ``fit_path_loss``
calibrates ``(p0, n, std)`` from data.

Robots observing landmarks and other robots:

:class:`LandmarkRangeBearing`
    range and bearing of a known landmark ``l`` from the robot pose ``(x, y, theta)``
    (the state): ``h = [|l - p|, wrap(atan2(l_y - y, l_x - x) - theta)]``.
:class:`TargetRangeBearing`
    range and bearing of a target (state position ``q``) from an observer whose pose
    ``s = (x_s, y_s, theta_s)`` is an estimate with covariance ``P_s``. The pose error
    enters the measurement linearly, ``z ~ h(q, s) + J_s (s_true - s) + v``, so the
    target filter uses ``R_eff = R + J_s P_s J_s^T`` with
    ``J_s = dh/ds = [[-dx/r, -dy/r, 0], [dy/r^2, -dx/r^2, -1]]`` evaluated at the
    *measured* point ``(dx, dy) = r (cos(theta_s + b), sin(theta_s + b))`` (so ``R_eff``
    does not depend on the target's estimate). :meth:`TargetRangeBearing.position_fix`
    gives the same measurement as a linear :class:`PositionFix` of the target:
    ``p = s_xy + r (cos(theta_s + b), sin(theta_s + b))`` with
    ``R_eff = G R G^T + J_c P_s J_c^T`` (``G = dp/d(r, b)``, ``J_c = dp/ds``); a filter
    whose estimate is far from the target (after a long gap) cannot linearize the polar
    form well, the linear fix has no such problem. Both assume the observer's pose error
    is independent of the target's state and of the observer's other measurements of the
    same target; consecutive observations from one robot share its pose error, which this
    model ignores (see ``docs/robots.md``).
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import ShapeError, ValidationError
from dfusion.geometry import wrap_angle
from dfusion.linalg import Array, as_finite, as_positive, as_spd, as_vector, symmetrize
from dfusion.models.base import MeasurementModel


class PositionSensor(MeasurementModel):
    """Direct, noisy observation of the position part of the state.

    Parameters
    ----------
    dim : int
        Number of position components observed (the first ``dim`` of the state).
    std : float or sequence of float
        Standard deviation of the noise, one value or one per axis.
    """

    is_linear = True

    def __init__(self, dim: int = 2, std: float | list[float] = 1.0) -> None:
        self.dim_z = int(dim)
        s = np.broadcast_to(np.asarray(std, dtype=float), (self.dim_z,)).copy()
        if not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise ValidationError(f"PositionSensor std must be positive and finite, got {std}")
        self.std = s
        self._R = np.diag(s**2)

    def __repr__(self) -> str:
        return f"PositionSensor(dim={self.dim_z}, std={self.std.tolist()})"

    def h(self, x: Array) -> Array:
        return np.asarray(x, dtype=float)[: self.dim_z].copy()

    def H(self, x: Array) -> Array:
        n = np.shape(x)[0]
        if n < self.dim_z:
            raise ShapeError(f"state of length {n} has no {self.dim_z} position components")
        H = np.zeros((self.dim_z, n))
        H[:, : self.dim_z] = np.eye(self.dim_z)
        return H

    @property
    def R(self) -> Array:
        return self._R


def position_state(x: Array, who: str) -> Array:
    """``x`` as a finite float vector with at least two (position) components."""
    x = as_vector(x, name=f"{who} state x")
    if x.shape[0] < 2:
        raise ShapeError(f"{who}: state of length {x.shape[0]} has no (x, y) position components")
    return x


class RangeBearing(MeasurementModel):
    """Range and bearing to a target from a sensor with known pose.

    The target's ``(x, y)`` position is the first two state components (m); the
    sensor sits at ``(x_s, y_s)`` with heading ``theta_s`` (rad). With
    ``dx = x - x_s``, ``dy = y - y_s`` and ``r = sqrt(dx^2 + dy^2)``
    (Thrun, Burgard & Fox, *Probabilistic Robotics*, 2005, sec. 6.6)::

        h(x) = [r, wrap(atan2(dy, dx) - theta_s)]
        H(x) = [[ dx/r,    dy/r,    0 ...],
                [-dy/r^2,  dx/r^2,  0 ...]]

    ``R = diag(range_std^2, bearing_std^2)``. The bearing is wrapped to
    ``[-pi, pi)`` and ``angle_indices = (1,)`` so :meth:`residual` wraps it too.
    ``H`` raises :class:`ValidationError` when the target is at the sensor
    (``r < 1e-9`` m), where the bearing is undefined.

    Parameters
    ----------
    sensor_pose : (x_s, y_s, theta_s)
        Sensor position (m) and heading (rad) in the world frame.
    range_std : float
        Range noise standard deviation (m), ``> 0``.
    bearing_std : float
        Bearing noise standard deviation (rad), ``> 0``.
    """

    dim_z = 2
    is_linear = False
    angle_indices = (1,)
    #: Below this range (m) the bearing and the Jacobian are undefined.
    MIN_RANGE = 1e-9

    def __init__(self, sensor_pose: Array, range_std: float, bearing_std: float) -> None:
        self.sensor_pose = as_vector(sensor_pose, 3, "RangeBearing sensor_pose (x, y, theta)")
        self.range_std = as_positive(range_std, "RangeBearing range_std")
        self.bearing_std = as_positive(bearing_std, "RangeBearing bearing_std")
        self._R = np.diag([self.range_std**2, self.bearing_std**2])

    def __repr__(self) -> str:
        return (
            f"RangeBearing(sensor_pose={self.sensor_pose.tolist()}, "
            f"range_std={self.range_std}, bearing_std={self.bearing_std})"
        )

    def h(self, x: Array) -> Array:
        x = position_state(x, "RangeBearing")
        dx, dy = x[0] - self.sensor_pose[0], x[1] - self.sensor_pose[1]
        return np.array([np.hypot(dx, dy), wrap_angle(np.arctan2(dy, dx) - self.sensor_pose[2])])

    def H(self, x: Array) -> Array:
        x = position_state(x, "RangeBearing")
        dx, dy = x[0] - self.sensor_pose[0], x[1] - self.sensor_pose[1]
        r2 = dx * dx + dy * dy
        r = np.sqrt(r2)
        if r < self.MIN_RANGE:
            raise ValidationError(
                f"RangeBearing: target at the sensor position (range {r:.3g} m < {self.MIN_RANGE} m); "
                "the bearing and its Jacobian are undefined"
            )
        H = np.zeros((2, x.shape[0]))
        H[0, :2] = dx / r, dy / r
        H[1, :2] = -dy / r2, dx / r2
        return H

    @property
    def R(self) -> Array:
        return self._R


class RSSISensor(MeasurementModel):
    """Received signal strength at fixed receivers, log-distance path-loss model.

    The target (a transmitter) is at ``(x, y, height)``, ``(x, y)`` being the first
    two state components; receiver ``i`` is at ``(a_i, b_i)`` on the ground
    (``z = 0``) or at ``(a_i, b_i, c_i)`` when 3-D receivers are given. With
    ``d_i = max(||p - r_i||, d_min)`` (Rappaport, *Wireless Communications:
    Principles and Practice*, 2nd ed., 2002, sec. 4.9.1-4.9.2)::

        h_i(x) = p0 - 10 n log10(d_i / d0)                     (dBm)
        H_i(x) = -10 n / ln(10) * (p_xy - r_i,xy)^T / d_i^2    (0 where clamped)

    and ``R = diag(std^2)``: log-normal shadowing (Rappaport, sec. 4.9.2). The distance is
    clamped below at ``d_min`` (default 1 cm) so that ``h`` and ``H`` stay finite
    when the target is on top of a receiver; where the clamp is active ``h`` is
    constant and its Jacobian row is zero.

    Parameters
    ----------
    receivers : (m, 2) or (m, 3) array
        Receiver positions (m).
    p0 : float
        Received power at the reference distance ``d0`` (dBm).
    exponent : float
        Path-loss exponent ``n`` (dimensionless, ``> 0``; 2 in free space).
    std : float or sequence of m floats
        Shadowing standard deviation (dB), ``> 0``.
    d0 : float
        Reference distance (m), ``> 0``.
    height : float
        Height of the transmitter (m).
    d_min : float
        Lower clamp on the distance (m), ``> 0``.
    """

    is_linear = False

    def __init__(
        self,
        receivers: Array,
        p0: float,
        exponent: float,
        std: float | list[float],
        d0: float = 1.0,
        height: float = 0.0,
        d_min: float = 0.01,
    ) -> None:
        rec = np.array(receivers, dtype=float)
        if rec.ndim == 1:
            rec = rec.reshape(1, -1)
        if rec.ndim != 2 or rec.shape[0] < 1 or rec.shape[1] not in (2, 3):
            raise ShapeError(f"RSSISensor receivers must have shape (m, 2) or (m, 3), got {np.shape(receivers)}")
        if not np.all(np.isfinite(rec)):
            raise ValidationError("RSSISensor receivers contain NaN or inf")
        self.dim_z = rec.shape[0]
        self.receivers = rec
        self.p0 = as_finite(p0, "RSSISensor p0")
        self.exponent = as_positive(exponent, "RSSISensor exponent")
        self.d0 = as_positive(d0, "RSSISensor d0")
        self.height = as_finite(height, "RSSISensor height")
        self.d_min = as_positive(d_min, "RSSISensor d_min")
        try:
            s = np.broadcast_to(np.asarray(std, dtype=float), (self.dim_z,)).copy()
        except (TypeError, ValueError):
            raise ValidationError(f"RSSISensor std must be one value or one per receiver, got {std!r}") from None
        if not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise ValidationError(f"RSSISensor std must be positive and finite, got {std!r}")
        self.std = s
        self._R = np.diag(s**2)
        # Squared vertical offsets between transmitter and receivers (constant).
        rz = rec[:, 2] if rec.shape[1] == 3 else np.zeros(self.dim_z)
        self._dz2 = (self.height - rz) ** 2

    def __repr__(self) -> str:
        return (
            f"RSSISensor(receivers={self.receivers.tolist()}, p0={self.p0}, exponent={self.exponent}, "
            f"std={self.std.tolist()}, d0={self.d0}, height={self.height}, d_min={self.d_min})"
        )

    def _offsets(self, x: Array) -> tuple[int, Array, Array, Array]:
        """State length, horizontal offsets ``(m, 2)``, clamped distances ``(m,)``, clamp mask."""
        x = position_state(x, "RSSISensor")
        diff = x[:2] - self.receivers[:, :2]
        d = np.sqrt(np.einsum("ij,ij->i", diff, diff) + self._dz2)
        clamped = d < self.d_min
        return x.shape[0], diff, np.maximum(d, self.d_min), clamped

    def h(self, x: Array) -> Array:
        _, _, d, _ = self._offsets(x)
        return self.p0 - 10.0 * self.exponent * np.log10(d / self.d0)

    def H(self, x: Array) -> Array:
        n, diff, d, clamped = self._offsets(x)
        H = np.zeros((self.dim_z, n))
        H[:, :2] = (-10.0 * self.exponent / np.log(10.0)) * diff / (d * d)[:, None]
        H[clamped, :2] = 0.0
        return H

    @property
    def R(self) -> Array:
        return self._R


def fit_path_loss(distances: Array, rssi: Array, d0: float = 1.0) -> tuple[float, float, float]:
    """Fit the log-distance path-loss model to calibration data.

    Solves ``rssi_k = p0 - 10 n log10(d_k / d0) + e_k`` for ``(p0, n)`` by linear least
    squares (:func:`numpy.linalg.lstsq`) with design matrix
    ``[1, -10 log10(d_k / d0)]`` (the MMSE fit of Rappaport, 2002, sec. 4.9.2,
    Example 4.9, with ``p0`` estimated too), and
    estimates the shadowing standard deviation from the residuals with ``N - 2``
    degrees of freedom: ``std = sqrt(sum(e_k^2) / (N - 2))``.

    Parameters
    ----------
    distances : (N,) array
        Transmitter-receiver distances (m), ``> 0``.
    rssi : (N,) array
        Measured received power (dBm).
    d0 : float
        Reference distance (m) at which ``p0`` is defined.

    Returns
    -------
    p0, exponent, std : float
        Power at ``d0`` (dBm), path-loss exponent, residual standard deviation (dB).
    """
    d = as_vector(distances, name="fit_path_loss distances")
    z = as_vector(rssi, d.shape[0], "fit_path_loss rssi")
    d0 = as_positive(d0, "fit_path_loss d0")
    if np.any(d <= 0):
        raise ValidationError("fit_path_loss distances must be positive")
    if d.shape[0] < 3:
        raise ValidationError(f"fit_path_loss needs at least 3 samples, got {d.shape[0]}")
    L = np.log10(d / d0)
    if np.ptp(L) <= 1e-12:
        raise ValidationError("fit_path_loss needs at least two distinct distances")
    A = np.column_stack([np.ones_like(L), -10.0 * L])
    (p0, n), *_ = np.linalg.lstsq(A, z, rcond=None)
    e = z - A @ np.array([p0, n])
    std = float(np.sqrt(e @ e / (d.shape[0] - 2)))
    return float(p0), float(n), std


class LandmarkRangeBearing(MeasurementModel):
    """Range and bearing of a known landmark from the robot pose (the first 3 state entries).

    ``h(x) = [r, wrap(atan2(dy, dx) - theta)]`` with ``(dx, dy) = l - (x, y)``;
    ``H = [[-dx/r, -dy/r, 0], [dy/r^2, -dx/r^2, -1]]``; ``R = diag(range_std^2, bearing_std^2)``.
    """

    dim_z = 2
    is_linear = False
    angle_indices = (1,)

    def __init__(self, landmark: ArrayLike, range_std: float, bearing_std: float) -> None:
        self.landmark = as_vector(landmark, 2, "landmark position")
        self.range_std = as_positive(range_std, "range_std")
        self.bearing_std = as_positive(bearing_std, "bearing_std")
        self._R = np.diag([self.range_std**2, self.bearing_std**2])

    def __repr__(self) -> str:
        return f"LandmarkRangeBearing(landmark={self.landmark.tolist()}, range_std={self.range_std}, bearing_std={self.bearing_std})"

    def h(self, x: Array) -> Array:
        x = np.asarray(x, dtype=float)
        dx, dy = self.landmark[0] - x[0], self.landmark[1] - x[1]
        return np.array([math.hypot(dx, dy), float(wrap_angle(math.atan2(dy, dx) - x[2]))])

    def H(self, x: Array) -> Array:
        x = np.asarray(x, dtype=float)
        if x.shape[0] < 3:
            raise ShapeError("LandmarkRangeBearing needs a pose state (x, y, theta, ...)")
        dx, dy = self.landmark[0] - x[0], self.landmark[1] - x[1]
        r2 = dx * dx + dy * dy
        if r2 < 1e-18:
            raise ValidationError("LandmarkRangeBearing: robot at the landmark, bearing undefined")
        r = math.sqrt(r2)
        H = np.zeros((2, x.shape[0]))
        H[0, :3] = -dx / r, -dy / r, 0.0
        H[1, :3] = dy / r2, -dx / r2, -1.0
        return H

    @property
    def R(self) -> Array:
        return self._R


def _observer_jacobian(observer_pose: Array, z: Array) -> Array:
    """``dh/ds`` of range-bearing w.r.t. the observer pose, at the measured point."""
    r, b = float(z[0]), float(z[1])
    phi = observer_pose[2] + b
    dx, dy = r * math.cos(phi), r * math.sin(phi)
    r2 = max(r * r, 1e-18)
    r = math.sqrt(r2)
    return np.array([[-dx / r, -dy / r, 0.0], [dy / r2, -dx / r2, -1.0]])


class TargetRangeBearing(RangeBearing):
    """Range and bearing of a target (state position ``x[:2]``) from an uncertain observer.

    :class:`dfusion.models.RangeBearing` with the observer's estimated pose as the sensor
    pose (same ``h`` and ``H``), and the observer's pose uncertainty folded into the noise.

    Parameters
    ----------
    observer_pose : (3,)
        The observer's estimated pose ``(x_s, y_s, theta_s)``.
    observer_cov : (3, 3)
        Its covariance ``P_s`` (zeros: a known pose).
    z : (2,)
        The measurement ``(range, bearing)``; fixes the point where ``J_s`` is evaluated.
    range_std, bearing_std : float
        Sensor noise.

    ``R = diag(range_std^2, bearing_std^2) + J_s P_s J_s^T`` (module docstring).
    """

    def __init__(self, observer_pose: ArrayLike, observer_cov: ArrayLike, z: ArrayLike,
                 range_std: float, bearing_std: float) -> None:
        super().__init__(observer_pose, range_std, bearing_std)
        P = np.asarray(observer_cov, dtype=float)
        if P.shape != (3, 3) or not np.all(np.isfinite(P)):
            raise ShapeError("observer_cov must be a finite 3 x 3 matrix")
        self.observer_cov = symmetrize(P)
        self.z = as_vector(z, 2, "range-bearing measurement")
        J = _observer_jacobian(self.sensor_pose, self.z)
        self.J = J
        self._R = symmetrize(self._R + J @ self.observer_cov @ J.T)

    @property
    def observer_pose(self) -> Array:
        """The observer's estimated pose (the sensor pose of :class:`RangeBearing`)."""
        return self.sensor_pose

    def position_fix(self) -> "PositionFix":
        """The measurement converted to a position fix of the target (module docstring):
        ``p = s_xy + r (cos(theta_s + b), sin(theta_s + b))`` with covariance
        ``G R G^T + J_c P_s J_c^T``, ``G = dp/d(r, b)``, ``J_c = dp/ds``."""
        r, b = float(self.z[0]), float(self.z[1])
        s = self.observer_pose
        c, sn = math.cos(s[2] + b), math.sin(s[2] + b)
        p = s[:2] + r * np.array([c, sn])
        G = np.array([[c, -r * sn], [sn, r * c]])
        Jc = np.array([[1.0, 0.0, -r * sn], [0.0, 1.0, r * c]])
        R0 = np.diag([self.range_std**2, self.bearing_std**2])
        return PositionFix(p, symmetrize(G @ R0 @ G.T + Jc @ self.observer_cov @ Jc.T))


class PositionFix(MeasurementModel):
    """A linear position measurement ``z = x[:d] + v``, ``v ~ N(0, cov)`` with a full covariance.

    ``z`` (the fix itself) is kept in :attr:`z` for convenience.
    """

    is_linear = True

    def __init__(self, z: ArrayLike, cov: ArrayLike) -> None:
        self.z = np.asarray(z, dtype=float).reshape(-1)
        self.dim_z = self.z.size
        self._R = as_spd(cov, self.dim_z, "position fix covariance")

    def h(self, x: Array) -> Array:
        return np.asarray(x, dtype=float)[: self.dim_z].copy()

    def H(self, x: Array) -> Array:
        n = np.shape(x)[0]
        H = np.zeros((self.dim_z, n))
        H[:, : self.dim_z] = np.eye(self.dim_z)
        return H

    @property
    def R(self) -> Array:
        return self._R
