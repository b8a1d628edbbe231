"""Motion models.

``ConstantVelocity``: the continuous white-noise-acceleration model
(Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and
Navigation*, 2001, sec. 6.2.2). State ``[p_1..p_d, v_1..v_d]``::

    F(dt) = [[I, dt I], [0, I]]
    Q(dt) = q [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]]

with ``q`` the power spectral density of the acceleration noise (m^2/s^3).
"""
from __future__ import annotations

import numpy as np

from ..errors import ShapeError, ValidationError
from .base import Array, MotionModel


class ConstantVelocity(MotionModel):
    """Nearly-constant-velocity model in ``dim`` (2 or 3) dimensions.

    Parameters
    ----------
    dim : int
        Number of position axes (2 or 3); the state has ``2 * dim`` components.
    q : float
        Acceleration noise spectral density (m^2 s^-3), ``> 0``.
    """

    is_linear = True

    def __init__(self, dim: int = 2, q: float = 0.1) -> None:
        if dim not in (1, 2, 3):
            raise ShapeError(f"ConstantVelocity dim must be 1, 2 or 3, got {dim}")
        if not (np.isfinite(q) and q > 0):
            raise ValidationError(f"ConstantVelocity q must be positive and finite, got {q}")
        self.axes = int(dim)
        self.dim = 2 * self.axes
        self.q = float(q)

    def __repr__(self) -> str:
        return f"ConstantVelocity(dim={self.axes}, q={self.q})"

    def F(self, dt: float, x: Array | None = None, u: Array | None = None) -> Array:
        d = self.axes
        F = np.eye(self.dim)
        F[:d, d:] = dt * np.eye(d)
        return F

    def f(self, x: Array, dt: float, u: Array | None = None) -> Array:
        return self.F(dt) @ np.asarray(x, dtype=float)

    def Q(self, dt: float, x: Array | None = None, u: Array | None = None) -> Array:
        d = self.axes
        I = np.eye(d)
        return self.q * np.block([[dt**3 / 3.0 * I, dt**2 / 2.0 * I], [dt**2 / 2.0 * I, dt * I]])
