"""Measurement models.

``PositionSensor``: ``z = [I 0] x + v``, ``v ~ N(0, std^2 I)``: observes the
first ``dim`` components (the position) of any state.
"""
from __future__ import annotations

import numpy as np

from ..errors import ShapeError, ValidationError
from .base import Array, MeasurementModel


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
