r"""A pose EKF driven by velocity odometry and range-bearing sightings of known landmarks.

:class:`LandmarkEKF` propagates a robot pose ``(x, y, theta)`` with
:class:`~dfusion.models.odometry.VelocityOdometry` (the
:class:`~dfusion.models.Unicycle` model integrated exactly over piecewise-constant
velocities) and updates it with :class:`~dfusion.models.LandmarkRangeBearing`
measurements (EKF in Joseph form, Bar-Shalom, Li & Kirubarajan, *Estimation with
Applications to Tracking and Navigation*, 2001, eq. 5.2.3-18), rejecting innovations
beyond a chi-square gate.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import cho_factor, cho_solve

from dfusion.estimation.estimate import Estimate
from dfusion.geometry import wrap_angle
from dfusion.linalg import as_spd, as_vector, symmetrize
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
    """

    def __init__(self, odometry: VelocityOdometry, t0: float, x0: ArrayLike, P0: ArrayLike, *,
                 gate: float | None = 13.8) -> None:
        self.odometry = odometry
        self.t = float(t0)
        self.x = as_vector(x0, 3, "x0").copy()
        self.x[2] = float(wrap_angle(self.x[2]))
        self.P = as_spd(P0, 3, "P0")
        self.gate = None if gate is None else float(gate)
        self.accepted = 0
        self.rejected = 0

    def predict(self, t: float, u: None = None) -> None:
        """Propagate the pose to ``t`` with the odometry (nothing happens for ``t <= self.t``)."""
        if t <= self.t:
            return
        self.x, F, Q = self.odometry.propagate(self.x, self.t, float(t))
        self.P = symmetrize(F @ self.P @ F.T + Q)
        self.t = float(t)

    def update(self, t: float, z: ArrayLike, sensor: MeasurementModel) -> bool:
        """EKF update with a measurement ``z`` of the pose taken at ``t`` by ``sensor`` (the pose
        is first propagated to ``t``); ``False`` if gated out."""
        self.predict(t)
        zz = np.asarray(z, dtype=float).reshape(-1)
        H = sensor.H(self.x)
        nu = sensor.residual(zz, sensor.h(self.x))
        S = symmetrize(H @ self.P @ H.T + sensor.R)
        c = cho_factor(S)
        if self.gate is not None and float(nu @ cho_solve(c, nu)) > self.gate:
            self.rejected += 1
            return False
        K = cho_solve(c, H @ self.P).T          # P H^T S^-1 (P and S symmetric)
        self.x = self.x + K @ nu
        self.x[2] = float(wrap_angle(self.x[2]))
        IKH = np.eye(3) - K @ H
        self.P = symmetrize(IKH @ self.P @ IKH.T + K @ sensor.R @ K.T)
        self.accepted += 1
        return True

    def estimate(self) -> Estimate:
        return Estimate("landmark_ekf", self.t, self.x.copy(), self.P.copy(), covariance_reliability(self.P))
