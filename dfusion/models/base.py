"""Abstract motion and measurement models.

A *motion model* describes ``x_k = f(x_{k-1}, dt, u) + w``, ``w ~ N(0, Q(dt))``;
a *measurement model* ``z = h(x) + v``, ``v ~ N(0, R)``. Filters only use the
methods below, so any model that implements them can be plugged in.
Jacobians are analytic; the test suite checks every one of them against central
finite differences.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from dfusion.geometry import wrap_angle
from dfusion.linalg import Array


class MotionModel(ABC):
    """State transition ``x' = f(x, dt, u) + w`` with ``w ~ N(0, Q(dt, x))``.

    Attributes
    ----------
    dim : int
        State dimension ``n``.
    is_linear : bool
        True when ``f`` is linear in ``x`` (then ``F`` and ``Q`` do not depend on ``x``
        and filters need no linearization point).
    angle_indices : tuple[int, ...]
        Components that are angles (wrapped to ``[-pi, pi)``).
    """

    dim: int
    is_linear: bool = False
    angle_indices: tuple[int, ...] = ()

    @abstractmethod
    def f(self, x: Array, dt: float, u: Array | None = None) -> Array:
        """Propagate the state ``x`` over ``dt`` seconds with control ``u``."""

    @abstractmethod
    def F(self, dt: float, x: Array | None = None, u: Array | None = None) -> Array:
        """Jacobian ``df/dx`` at ``x`` (``n x n``)."""

    @abstractmethod
    def Q(self, dt: float, x: Array | None = None, u: Array | None = None) -> Array:
        """Process-noise covariance over ``dt`` (``n x n``, positive definite for ``dt > 0``)."""

    def residual(self, a: Array, b: Array) -> Array:
        """``a - b`` with angle components wrapped to ``[-pi, pi)``."""
        d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
        for i in self.angle_indices:
            d[..., i] = wrap_angle(d[..., i])
        return d

    def normalize(self, x: Array) -> Array:
        """Return ``x`` with angle components wrapped to ``[-pi, pi)``."""
        x = np.array(x, dtype=float)
        for i in self.angle_indices:
            x[..., i] = wrap_angle(x[..., i])
        return x


class MeasurementModel(ABC):
    """Observation ``z = h(x) + v`` with ``v ~ N(0, R)``.

    Attributes
    ----------
    dim_z : int
        Measurement dimension.
    is_linear : bool
        True when ``h`` is linear in ``x`` (``H`` does not depend on ``x``).
    angle_indices : tuple[int, ...]
        Measurement components that are angles (innovation wrapped).
    """

    dim_z: int
    is_linear: bool = False
    angle_indices: tuple[int, ...] = ()

    @abstractmethod
    def h(self, x: Array) -> Array:
        """Predicted measurement for state ``x``."""

    @abstractmethod
    def H(self, x: Array) -> Array:
        """Jacobian ``dh/dx`` at ``x`` (``dim_z x n``)."""

    @property
    @abstractmethod
    def R(self) -> Array:
        """Measurement-noise covariance (``dim_z x dim_z``)."""

    def residual(self, z: Array, zhat: Array) -> Array:
        """Innovation ``z - zhat`` with angle components wrapped."""
        d = np.asarray(z, dtype=float) - np.asarray(zhat, dtype=float)
        for i in self.angle_indices:
            d[..., i] = wrap_angle(d[..., i])
        return d




def model_at(sensor: Any, t: float) -> Any:
    """The measurement model of ``sensor`` for a measurement taken at time ``t``: ``sensor.at(t)``
    for a model that moves (:class:`dfusion.models.camera.MountedCamera`), ``sensor`` itself otherwise."""
    at = getattr(sensor, "at", None)
    return sensor if at is None else at(t)
