r"""A pose EKF driven by velocity odometry and range-bearing sightings of known landmarks.

:class:`LandmarkEKF` propagates a robot pose ``(x, y, theta)`` with
:class:`~dfusion.models.odometry.VelocityOdometry` (the
:class:`~dfusion.models.Unicycle` model integrated exactly over piecewise-constant
velocities) and updates it with :class:`~dfusion.models.LandmarkRangeBearing`
measurements (EKF in Joseph form, Bar-Shalom, Li & Kirubarajan, *Estimation with
Applications to Tracking and Navigation*, 2001, eq. 5.2.3-18), rejecting innovations
beyond a chi-square gate, or, with an :class:`~dfusion.estimation.innovation.InnovationMonitor`,
with robust updates: the monitor's gate, Huber weights and lock-out recovery on the pose.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import cho_factor, cho_solve

from dfusion.estimation.estimate import Estimate
from dfusion.estimation.innovation import InnovationMonitor, monitored_update
from dfusion.geometry import wrap_angle
from dfusion.linalg import Array, as_spd, as_vector, symmetrize
from dfusion.models.base import MeasurementModel
from dfusion.models.odometry import VelocityOdometry
from dfusion.reliability import covariance_reliability

__all__ = ["LandmarkEKF"]

class LandmarkEKF:
    """Pose EKF: velocity odometry (:class:`VelocityOdometry`) + range-bearing to known landmarks.

    Parameters
    ----------
    odometry : VelocityOdometry
    t0 : float
        Time of the initial pose.
    x0, P0 : (3,), (3, 3)
        Initial pose and covariance.
    gate : float or None
        Chi-square threshold (2 degrees of freedom) on the normalized innovation; larger
        innovations are rejected and counted in :attr:`rejected` (default 13.8, 99.9 %).
        Not used with a ``monitor``.
    monitor : InnovationMonitor, optional
        Robust updates (:mod:`dfusion.estimation.innovation`): the monitor's gate, Huber
        weights (the landmark is fused with ``R / w``) and recovery: when the monitor
        detects a divergence (a lock-out or a drift of the pose), the jump's second moment
        ``delta delta^T + F^+`` estimated from the landmarks (the components they
        determine) is added to ``P`` as process noise and the rejected landmark is tested
        again. The landmark is the measurement's *source*: a lock-out is not declared on
        runs that one landmark alone could explain.
    """

    def __init__(self, odometry: VelocityOdometry, t0: float, x0: ArrayLike, P0: ArrayLike, *,
                 gate: float | None = 13.8, monitor: InnovationMonitor | None = None) -> None:
        self.odometry = odometry
        self.t = float(t0)
        self.x = as_vector(x0, 3, "x0").copy()
        self.x[2] = float(wrap_angle(self.x[2]))
        self.P = as_spd(P0, 3, "P0")
        self.gate = None if gate is None else float(gate)
        self.monitor = monitor
        self.accepted = 0
        self.rejected = 0

    def predict(self, t: float, u: None = None) -> None:
        """Propagate the pose to ``t`` with the odometry (nothing happens for ``t <= self.t``)."""
        if t <= self.t:
            return
        self.x, F, Q = self.odometry.propagate(self.x, self.t, float(t))
        self.P = symmetrize(F @ self.P @ F.T + Q)
        self.t = float(t)

    def _fuse(self, nu: Array, H: Array, R: Array) -> None:
        """Joseph-form EKF update with innovation ``nu`` (gain through a Cholesky solve)."""
        S = symmetrize(H @ self.P @ H.T + R)
        K = cho_solve(cho_factor(S), H @ self.P).T          # P H^T S^-1 (P and S symmetric)
        self.x = self.x + K @ nu
        self.x[2] = float(wrap_angle(self.x[2]))
        IKH = np.eye(3) - K @ H
        self.P = symmetrize(IKH @ self.P @ IKH.T + K @ R @ K.T)

    def update(self, t: float, z: ArrayLike, sensor: MeasurementModel) -> bool:
        """EKF update with a measurement ``z`` of the pose taken at ``t`` by ``sensor`` (the pose
        is first propagated to ``t``); ``False`` if gated out."""
        self.predict(t)
        zz = np.asarray(z, dtype=float).reshape(-1)
        if self.monitor is not None:
            return self._robust_update(zz, sensor)
        H = sensor.H(self.x)
        nu = sensor.residual(zz, sensor.h(self.x))
        S = symmetrize(H @ self.P @ H.T + sensor.R)
        if self.gate is not None and float(nu @ cho_solve(cho_factor(S), nu)) > self.gate:
            self.rejected += 1
            return False
        self._fuse(nu, H, sensor.R)
        self.accepted += 1
        return True

    def _robust_update(self, z: Array, sensor: MeasurementModel) -> bool:
        """:func:`~dfusion.estimation.innovation.monitored_update` with this EKF's steps."""
        R = sensor.R

        def innovation() -> tuple[Array, Array, Array, Array]:
            H = sensor.H(self.x)
            return sensor.residual(z, sensor.h(self.x)), symmetrize(H @ self.P @ H.T) + R, H, self.P

        def fuse(w: float) -> None:
            self._fuse(sensor.residual(z, sensor.h(self.x)), sensor.H(self.x), R / w)

        def inflate(Q: Array) -> None:
            self.P = symmetrize(self.P + Q)

        source = tuple(np.round(getattr(sensor, "landmark", ()), 6).tolist())  # the landmark
        a = monitored_update(self.monitor, self.t, innovation, fuse, inflate, source or None)
        self.accepted += int(a.accept)
        self.rejected += int(not a.accept)
        return a.accept

    @property
    def recoveries(self) -> int:
        """Recoveries carried out by the monitor (0 without one)."""
        return 0 if self.monitor is None else self.monitor.stats.recoveries

    def estimate(self) -> Estimate:
        return Estimate("landmark_ekf", self.t, self.x.copy(), self.P.copy(), covariance_reliability(self.P))
