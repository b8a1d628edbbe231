r"""EKF fusing wheel odometry with scan-matching poses (survey 001, sec. III.A, eq. 5-8).

State ``x = (x, y, theta)``, covariance ``Sigma``. Odometry gives ``u = (Delta d, Delta theta)``,
the distance travelled and the heading change since the previous step. Prediction
(eq. 5-6)::

    x'     = x + (Delta d cos theta, Delta d sin theta, Delta theta)
    Sigma' = Fx Sigma Fx^T + Fu Sigma_u Fu^T
    Fx = [[1, 0, -Delta d sin theta], [0, 1, Delta d cos theta], [0, 0, 1]]
    Fu = [[cos theta, 0], [sin theta, 0], [0, 1]]

A scan matcher (e.g. :class:`~dfusion.localization.scan_matching.ScanMatcher`) gives a pose ``x_s``
with covariance ``Sigma_s``; the update (eq. 7-8) is the information-weighted average::

    x     = (Sigma'^-1 + Sigma_s^-1)^-1 (Sigma'^-1 x' + Sigma_s^-1 x_s)
    Sigma = (Sigma'^-1 + Sigma_s^-1)^-1

which is the Kalman update with ``H = I`` and ``R = Sigma_s``. It is computed in that form
(gain ``K = Sigma' (Sigma' + Sigma_s)^-1``, Joseph-form covariance) by
:class:`filterpy.kalman.ExtendedKalmanFilter`, with the heading innovation
``theta_s - theta'`` wrapped to ``[-pi, pi)`` -- eq. 7 applied literally to angles would
average ``+179 deg`` and ``-179 deg`` to ``0``.

Odometry noise: by default ``Sigma_u = diag(k_d^2 Delta d^2 + s_d^2, k_theta^2 Delta theta^2 +
k_dtheta^2 Delta d^2 + s_theta^2)`` (error growing with the motion, plus a floor); pass
``Sigma_u`` to :meth:`OdometryEKF.predict` to override it. The filter follows the
:class:`~dfusion.estimation.Estimator` protocol: ``predict(t, u)``, ``update(t, z, R)``, ``estimate()``.

Optionally a scan-matching pose whose squared Mahalanobis distance to the prediction
exceeds ``gate`` (chi-square, 3 degrees of freedom) is rejected.
"""
from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from numpy.typing import ArrayLike

from dfusion.errors import ShapeError, ValidationError
from dfusion.estimation.estimate import Estimate
from dfusion.geometry import wrap_angle
from dfusion.linalg import Array, as_spd, as_vector, symmetrize
from dfusion.reliability import covariance_reliability

__all__ = [
    "OdometryEKF",
]




class OdometryEKF:
    """The odometry + scan-matching EKF of the survey (eq. 5-8), on filterpy.

    Parameters
    ----------
    x0 : (3,) initial pose
    P0 : (3, 3) initial covariance
    k_d, k_theta, k_dtheta : float
        Odometry noise growth (m/m, rad/rad, rad/m); see the module docstring.
    s_d, s_theta : float
        Odometry noise floor per step (m, rad).
    gate : float or None
        Chi-square threshold for rejecting scan-matching poses (``None``: accept all).
    """

    def __init__(
        self,
        x0: ArrayLike,
        P0: ArrayLike,
        *,
        k_d: float = 0.05,
        k_theta: float = 0.05,
        k_dtheta: float = 0.02,
        s_d: float = 1e-3,
        s_theta: float = 1e-3,
        gate: float | None = None,
    ) -> None:
        self.k_d, self.k_theta, self.k_dtheta = float(k_d), float(k_theta), float(k_dtheta)
        self.s_d, self.s_theta = float(s_d), float(s_theta)
        self.gate = None if gate is None else float(gate)
        self.ekf = ExtendedKalmanFilter(dim_x=3, dim_z=3)
        self.ekf.x = as_vector(x0, 3, "x0").reshape(3, 1)
        self.ekf.x[2, 0] = wrap_angle(self.ekf.x[2, 0])
        self.ekf.P = as_spd(P0, 3, "P0")
        self._u = (0.0, 0.0)
        self.ekf.predict_x = self._predict_x  # eq. 5 instead of filterpy's linear F x
        self.t: float | None = None
        self.rejected = 0

    # -- state -------------------------------------------------------------------------
    @property
    def x(self) -> Array:
        return self.ekf.x[:, 0].copy()

    @property
    def P(self) -> Array:
        return self.ekf.P.copy()

    def estimate(self) -> Estimate:
        P = self.P
        return Estimate("odometry_ekf", self.t, self.x, P, covariance_reliability(P))

    # -- prediction (eq. 5-6) ----------------------------------------------------------
    def odometry_covariance(self, delta_d: float, delta_theta: float) -> Array:
        """Default ``Sigma_u`` for an increment (see the module docstring)."""
        return np.diag(
            [
                (self.k_d * delta_d) ** 2 + self.s_d**2,
                (self.k_theta * delta_theta) ** 2 + (self.k_dtheta * delta_d) ** 2 + self.s_theta**2,
            ]
        )

    @staticmethod
    def jacobians(x: ArrayLike, delta_d: float) -> tuple[Array, Array]:
        """``(Fx, Fu)`` of eq. 6 at pose ``x``."""
        th = float(np.asarray(x, dtype=float).reshape(-1)[2])
        c, s = math.cos(th), math.sin(th)
        Fx = np.array([[1.0, 0.0, -delta_d * s], [0.0, 1.0, delta_d * c], [0.0, 0.0, 1.0]])
        Fu = np.array([[c, 0.0], [s, 0.0], [0.0, 1.0]])
        return Fx, Fu

    def _predict_x(self, u=0) -> None:
        d, dth = self._u
        x = self.ekf.x
        th = x[2, 0]
        self.ekf.x = np.array([[x[0, 0] + d * math.cos(th)], [x[1, 0] + d * math.sin(th)], [wrap_angle(th + dth)]])

    def predict(self, t: float | None, u: ArrayLike, Sigma_u: ArrayLike | None = None) -> None:
        """Eq. 5-6 with the odometry increment ``u = (delta_d, delta_theta)`` that ends at time ``t``
        (``None``: the filter's time does not change, for an increment split in parts).

        :func:`dfusion.models.odometry_increment` gives ``u`` from two odometry poses.
        """
        d, dth = (float(v) for v in np.asarray(u, dtype=float).reshape(2))
        if not (math.isfinite(d) and math.isfinite(dth)):
            raise ValidationError("odometry increment must be finite")
        Su = self.odometry_covariance(d, dth) if Sigma_u is None else np.asarray(Sigma_u, dtype=float)
        if Su.shape != (2, 2):
            raise ShapeError("Sigma_u must be 2 x 2")
        Fx, Fu = self.jacobians(self.ekf.x, d)
        self.ekf.F = Fx
        self.ekf.Q = Fu @ Su @ Fu.T
        self._u = (d, dth)
        self.ekf.predict()
        self.ekf.P = symmetrize(self.ekf.P)
        if t is not None:
            self.t = float(t)

    # -- update (eq. 7-8) --------------------------------------------------------------
    def update(self, t: float | None, z: ArrayLike, R: ArrayLike) -> bool:
        """Fuse a scan-matching pose ``z = x_s`` with covariance ``R = Sigma_s`` matched at time ``t``
        (the filter's time: odometry moves the pose, not the match); ``False`` if gated out."""
        z = as_vector(z, 3, "scan-matching pose")
        R = as_spd(R, 3, "scan-matching covariance")
        if self.gate is not None:
            nu = z - self.x
            nu[2] = wrap_angle(nu[2])
            S = self.ekf.P + R
            if float(nu @ np.linalg.solve(S, nu)) > self.gate:
                self.rejected += 1
                return False

        def residual(a, b):
            d = np.asarray(a, dtype=float).reshape(3, 1) - np.asarray(b, dtype=float).reshape(3, 1)
            d[2, 0] = wrap_angle(d[2, 0])
            return d

        self.ekf.update(z.reshape(3, 1), HJacobian=lambda x: np.eye(3), Hx=lambda x: x, R=R, residual=residual)
        self.ekf.x[2, 0] = wrap_angle(self.ekf.x[2, 0])
        self.ekf.P = symmetrize(self.ekf.P)
        return True
