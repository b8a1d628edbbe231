r"""Front ends: how a fusion node turns its sensor's raw measurements into information.

A *front end* sits between one sensor and one :class:`~dfusion.fusion.FusionNode`. It
consumes the sensor's raw measurements ``z`` (a pixel detection, the RSSI readings of a
radio network, a laser scan, ...) with their time stamps, runs whatever local estimator
the sensor needs, and contributes *information the rest of the network does not have
yet* to the node, in one of two ways:

* ``node.update(t, z, sensor)`` -- an EIF measurement update with a
  :class:`~dfusion.models.MeasurementModel` (``h``, ``H``, ``R``), linearized at the
  node's fused estimate: :class:`EIFFrontEnd` (the default for a sensor kind without a
  front end of its own) and the camera's :class:`~dfusion.frontends.camera.CameraFrontEnd`;
* ``node.add_local_information(t, Lambda, y)`` -- single-state information computed by
  a local estimator, on the node's state ``x`` (dimension ``n``, position = the first
  ``d`` entries):

  - a *Gaussian* localizer result (ICP pose, camera fix), independent of the node's
    prior: the pseudo-measurement ``z = p`` of the position with covariance ``S``,
    ``Lambda = E^T S^-1 E``, ``y = E^T S^-1 p`` (``E = [I_d 0]``;
    :func:`position_information`);
  - a *particle* filter (the WSN tracker, MCL) contributes the information its own
    measurements added: the Gaussian fit of its posterior minus the Gaussian fit of its
    prediction, in information form, projected to positive semi-definite
    (:func:`fit_difference_information`; URUS, Sanfeliu et al., sec. 8.3). For a
    linear-Gaussian model this is exactly ``H^T R^-1 H`` and ``H^T R^-1 z``; the prior,
    whatever it was, cancels, so the node's own belief is not counted twice.

The node shares that information with its neighbours through its channel filters, so
it is counted exactly once in the network, like any measurement.

Every front end derives from :class:`FrontEnd` and implements :meth:`FrontEnd.process`;
it reports its health figures (counters of what it processed, contributed and rejected)
through :meth:`FrontEnd.health`, and may report candidate estimates to the node's policy
with :meth:`FusionNode.report_source` (for switching policies). A front end touches the
node only through its public methods. ``docs/new-sensor-kind.md`` shows how to write one.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike

from dfusion.estimation.estimate import Estimate
from dfusion.estimation.gaussian import project_psd_information
from dfusion.fusion.node import FusionNode
from dfusion.linalg import Array, as_spd, spd_inverse
from dfusion.models.base import MeasurementModel

__all__ = ["FrontEnd", "FrontEndStats", "EIFFrontEnd", "position_information", "fit_difference_information",
           "embed_position_information", "embed_source"]


@dataclass
class FrontEndStats:
    """Counters of a front end (each sensor kind adds its own fields).

    Attributes
    ----------
    processed : int
        Measurements handed to the front end.
    contributed : int
        Measurements that added information to the node.
    rejected : int
        Measurements that added nothing (gated out, unusable, ...).
    """

    processed: int = 0
    contributed: int = 0
    rejected: int = 0

    def as_dict(self) -> dict[str, int]:
        """The counters by name."""
        return asdict(self)


class FrontEnd(ABC):
    """Turns one sensor's raw measurements into information for a :class:`FusionNode`.

    Attributes
    ----------
    stats : FrontEndStats
        The counters behind :meth:`health`.
    """

    stats: FrontEndStats

    @abstractmethod
    def process(self, node: FusionNode, t: float, z: Array) -> bool:
        """Fuse the measurement ``z`` taken at ``t`` into ``node``; returns whether it contributed.

        ``t`` may be in the past, inside the node's window (a late measurement). A
        measurement older than the window raises
        :class:`~dfusion.errors.OutsideWindowError` before anything is changed.
        """

    def process_frame(self, node: FusionNode, t: float, measurements: Array) -> int:
        """Fuse the measurements of one frame (one sensor, one time ``t``: rows of
        ``measurements``) into ``node``; returns how many contributed.

        A front end that associates a frame's measurements together (a camera's
        detections under clutter) overrides it; the default processes them one by one.
        """
        return sum(bool(self.process(node, t, z)) for z in np.atleast_2d(np.asarray(measurements, dtype=float)))

    def reference_frame(self, t: float, measurements: Array) -> object | None:
        """The frame as the centralized reference must apply it: an object with
        ``update(x, P) -> (x, P)`` (:meth:`dfusion.estimation.CentralizedEKF.add_frame`), or
        ``None`` (the default): each measurement is an EKF update with the sensor's model."""
        return None

    def status(self) -> str:
        """``"ok"``, or ``"lost"`` while the front end's sensor contradicts the node's estimate
        (a camera's track loss, :mod:`dfusion.frontends.camera`)."""
        return "ok"

    def finish(self, node: FusionNode) -> None:
        """End of a run: hand the node anything still held back (default: nothing)."""

    def health(self) -> dict[str, float]:
        """Health figures of the front end (its counters), for tables and JSON."""
        return dict(self.stats.as_dict())


class EIFFrontEnd(FrontEnd):
    """The default front end: an EIF measurement update with the sensor's model."""

    def __init__(self, sensor: MeasurementModel) -> None:
        self.sensor = sensor
        self.stats = FrontEndStats()

    def process(self, node: FusionNode, t: float, z: Array) -> bool:
        self.stats.processed += 1
        node.update(t, z, self.sensor)
        self.stats.contributed += 1
        return True


def position_information(mean: ArrayLike, cov: ArrayLike, n: int) -> tuple[Array, Array]:
    """Information ``(Lambda, y)`` on an ``n``-state of the pseudo-measurement ``z = mean``
    of its first ``d = len(mean)`` entries with covariance ``cov``."""
    m = np.asarray(mean, dtype=float).reshape(-1)
    d = m.size
    W = spd_inverse(as_spd(cov, d, "position covariance"), "position covariance")
    Lam = np.zeros((n, n))
    y = np.zeros(n)
    Lam[:d, :d] = W
    y[:d] = W @ m
    return Lam, y


def embed_position_information(Omega: ArrayLike, eta: ArrayLike, n: int) -> tuple[Array, Array]:
    """Information ``(Omega, eta)`` on the position (the first ``d`` entries) as ``(Lambda, y)`` on an
    ``n``-state: ``Omega`` in the position block, zeros elsewhere."""
    O = np.asarray(Omega, dtype=float)
    d = O.shape[0]
    Lam = np.zeros((n, n))
    y = np.zeros(n)
    Lam[:d, :d] = O
    y[:d] = np.asarray(eta, dtype=float)
    return Lam, y


def fit_difference_information(prior: tuple[Array, Array], post: tuple[Array, Array], n: int,
                               rtol: float = 1e-9) -> tuple[Array, Array]:
    """``(P_post^-1 - P_prior^-1, P_post^-1 m_post - P_prior^-1 m_prior)`` on the first
    ``d`` entries of an ``n``-state, projected to positive semi-definite
    (:func:`dfusion.estimation.gaussian.project_psd_information`)."""
    m0, P0 = (np.asarray(a, dtype=float) for a in prior)
    m1, P1 = (np.asarray(a, dtype=float) for a in post)
    d = m0.size
    O0 = spd_inverse(as_spd(P0, d, "prior covariance"), "prior covariance")
    O1 = spd_inverse(as_spd(P1, d, "posterior covariance"), "posterior covariance")
    Om, eta, _ = project_psd_information(O1 - O0, O1 @ m1 - O0 @ m0, rtol)
    Lam = np.zeros((n, n))
    y = np.zeros(n)
    Lam[:d, :d] = Om
    y[:d] = eta
    return Lam, y


def embed_source(name: str, t: float, node_mean: Array, node_cov: Array, mean: Array, cov: Array,
                 rel: float, healthy: bool = True) -> Estimate:
    """A localizer's position estimate as an :class:`Estimate` in the node's state space:
    the node's fused mean and covariance with the position part replaced (cross terms 0)."""
    d = np.asarray(mean).size
    m = np.array(node_mean, dtype=float)
    P = np.array(node_cov, dtype=float)
    m[:d] = mean
    P[:d, :] = 0.0
    P[:, :d] = 0.0
    P[:d, :d] = cov
    return Estimate(name, float(t), m, P, float(rel), healthy)
