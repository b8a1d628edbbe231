r"""The one estimate type and the estimator protocol.

Every estimator in dfusion reports its belief about a quantity as an
:class:`Estimate`: a Gaussian in moment form (mean, covariance) at a time, with the
reliability the switching policies use (Hu et al., "An automatic switching approach of
robotic components for improving robot localization reliability", eq. 11-12:
``R = 1 / (E + 1)``, see :mod:`dfusion.reliability`) and whether the source is healthy.
The information form of the same Gaussian is
:class:`dfusion.estimation.gaussian.InformationGaussian` (``Omega = cov^-1``,
``eta = Omega mean``).

:class:`Estimator` is the protocol every localizer and tracker follows
(:class:`~dfusion.localization.MonteCarloLocalization`,
:class:`~dfusion.localization.OdometryEKF`, :class:`~dfusion.localization.LandmarkEKF`,
:class:`~dfusion.localization.EnvironmentCameraLocalizer`,
:class:`~dfusion.localization.WSNTracker`): ``predict`` moves the belief to a time,
``update`` folds in one measurement and says whether it was used, ``estimate`` returns
the current :class:`Estimate`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterator, Protocol, runtime_checkable

from dfusion.linalg import Array

__all__ = ["Estimate", "Estimator"]


@dataclass(frozen=True)
class Estimate:
    """A Gaussian estimate of a quantity at time ``t``.

    Attributes
    ----------
    name : str
        The source (``"fused"`` for a fusion node's information filter, ``"mcl"``, ...).
    t : float or None
        Time of the estimate (None before the estimator has seen any data).
    mean, cov : ndarray
        Mean ``(n,)`` and covariance ``(n, n)``.
    reliability : float
        In ``[0, 1]``; 1 unless a reliability model says otherwise.
    healthy : bool
        False while the source is in an error state (a switching policy then counts
        it as reliability 0).
    n_particles : int
        Particles behind the estimate (particle filters; 0 otherwise).
    n_eff : float
        Their effective sample size (particle filters; 0 otherwise).

    An estimate behaves as the pair ``(mean, cov)`` where one is expected:
    ``mean, cov = estimate``, ``estimate[0]``, ``len(estimate) == 2``.
    """

    name: str
    t: float | None
    mean: Array
    cov: Array
    reliability: float = 1.0
    healthy: bool = True
    n_particles: int = 0
    n_eff: float = 0.0

    def __iter__(self) -> Iterator[Array]:
        yield self.mean
        yield self.cov

    def __getitem__(self, i: int) -> Array:
        return (self.mean, self.cov)[i]

    def __len__(self) -> int:
        return 2


@runtime_checkable
class Estimator(Protocol):
    """What every localizer and tracker implements."""

    def predict(self, t: float, u: Any = None) -> None:
        """Move the belief to time ``t`` (``u``: a control or odometry input, if the model takes one)."""

    def update(self, t: float, z: Any) -> bool:
        """Fold in measurement ``z`` taken at ``t``; returns whether it was used."""

    def estimate(self) -> Estimate:
        """The current belief."""
