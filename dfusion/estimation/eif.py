r"""Extended Information Filter on a single state.

Thrun, Burgard & Fox, *Probabilistic Robotics* (2005), Table 3.6::

    prediction:  mu = Omega^-1 eta,  Omega_bar = (F Omega^-1 F^T + Q)^-1,
                 eta_bar = Omega_bar f(mu, u)
    update:      Omega = Omega_bar + H^T R^-1 H
                 eta   = eta_bar + H^T R^-1 (z - h(mu_bar) + H mu_bar)

``F``, ``Q`` are evaluated at ``mu`` and ``H`` at the predicted mean
``mu_bar``. Every inverse is taken through a Cholesky factor.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import NotInitializedError, TimeError
from dfusion.estimation.delayed_state import measurement_information
from dfusion.estimation.gaussian import InformationGaussian
from dfusion.linalg import Array, as_matrix, as_spd, as_vector, spd_inverse, symmetrize
from dfusion.models.base import MeasurementModel, MotionModel


class ExtendedInformationFilter:
    """EIF over one state ``x`` with motion model ``motion``.

    Attributes
    ----------
    eta : ndarray (n,)
        Information vector.
    Omega : ndarray (n, n)
        Information matrix.
    """

    def __init__(self, motion: MotionModel) -> None:
        self.motion = motion
        self.eta: Array | None = None
        self.Omega: Array | None = None

    @property
    def n(self) -> int:
        return self.motion.dim

    def initialize(self, mean: ArrayLike, cov: ArrayLike) -> None:
        """Set the belief to ``N(mean, cov)``."""
        g = InformationGaussian.from_moments(as_vector(mean, self.n, "mean"), as_spd(cov, self.n, "covariance"))
        self.eta, self.Omega = g.eta, g.Omega

    def _require(self) -> None:
        if self.Omega is None:
            raise NotInitializedError("call initialize(mean, cov) first")

    def estimate(self) -> tuple[Array, Array]:
        """``(mean, cov)`` of the belief."""
        self._require()
        P = spd_inverse(self.Omega, "information matrix")
        return self.motion.normalize(P @ self.eta), P

    def predict(self, dt: float, u: ArrayLike | None = None) -> None:
        """Propagate the belief over ``dt > 0`` seconds with control ``u``."""
        self._require()
        if not (np.isfinite(dt) and dt > 0):
            raise TimeError(f"dt must be positive and finite, got {dt}")
        uu = None if u is None else as_vector(u, None, "control u")
        mu, P = self.estimate()
        F = as_matrix(self.motion.F(dt, mu, uu), (self.n, self.n), "motion Jacobian F")
        Q = as_spd(self.motion.Q(dt, mu, uu), self.n, "process noise Q")
        mu_bar = self.motion.normalize(as_vector(self.motion.f(mu, dt, uu), self.n, "f(x)"))
        Omega_bar = spd_inverse(symmetrize(F @ P @ F.T + Q), "predicted covariance")
        self.Omega, self.eta = Omega_bar, Omega_bar @ mu_bar

    def update(self, z: ArrayLike, sensor: MeasurementModel) -> None:
        """Fuse measurement ``z`` of ``sensor``."""
        self._require()
        x_lin = np.zeros(self.n) if sensor.is_linear else self.estimate()[0]
        Lam, y = measurement_information(sensor, z, x_lin)
        self.Omega = symmetrize(self.Omega + Lam)
        self.eta = self.eta + y
