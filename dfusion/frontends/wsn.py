r"""Front end of a wireless sensor network tracking a radio tag with a particle filter.

The world measures the RSSI of the tag's packets at every receiver with the
log-distance model of :class:`~dfusion.models.RSSISensor` (one reading per
receiver per measurement time). The node does not fuse them with the EIF:
its front end (:class:`WSNFrontEnd`) runs a :class:`~dfusion.localization.WSNTracker`
(URUS sec. 8.3) and joins the information network as :mod:`dfusion.frontends.base`
explains for particle filters.
On each RSSI measurement taken at ``t``:

1. the particles are predicted from the tracker's time to ``t``;
2. they are weighted by the readings (the "annulus" likelihood);
3. :meth:`WSNTracker.information_contribution` gives what these readings
   added on the position: by default the quotient of the posterior and prior Gaussian fits of
   the particles; with ``information="regression"`` one linear-Gaussian measurement, ``Omega = A^T (R +
   Omega_lin)^-1 A``, ``eta = A^T (R + Omega_lin)^-1 (z - b)``: the statistical linear
   regression ``z ~ A x + b`` of the readings over the weighted posterior particles, its
   error ``Omega_lin`` counted as noise (posterior linearization, Garcia-Fernandez et al.,
   IEEE TSP 2015; ``docs/wsn.md``);
4. the 2 x 2 pair is embedded in the node's state (position block; zeros for
   the velocities) and fused with ``node.add_local_information(t, Lam, y)``.

Only the information of the node's own readings enters the network, exactly
like a measurement: it is sent once to the neighbours through the channel
filters and never double counted. The particle filter is an independent
filter of the WSN's own readings, started from the network's common prior:
fused information is *not* fed back into the particles (a particle set
sharpened by the cameras would make ``P_post^-1 - P_pred^-1`` a small
difference of two large, noisy matrices).

**Late measurements.** Measurements are processed in arrival order. The
particles cannot be predicted backwards: a measurement older than the
tracker's time is skipped and counted (``stats.late``); one older than the
node's window raises :class:`~dfusion.errors.OutsideWindowError` before the
particles are touched (the runner counts it as refused).

The scenario kind ``wsn_rssi`` (:mod:`dfusion.scenario.wsn_kind`) builds this front end
from a node table.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dfusion.errors import OutsideWindowError, ValidationError
from dfusion.frontends.base import FrontEnd, FrontEndStats, embed_position_information
from dfusion.fusion.node import FusionNode
from dfusion.linalg import Array
from dfusion.localization.wsn_tracker import WSNTracker
from dfusion.estimation.estimate import Estimate

__all__ = ["WSNFrontEnd", "WSNStats"]


@dataclass
class WSNStats(FrontEndStats):
    """Counters of a WSN front end.

    ``processed`` RSSI measurements (one reading per receiver each), ``contributed``
    information contributions fused into the node, ``rejected`` measurements that added
    nothing; of these, ``empty`` had no usable reading and ``late`` were older than the
    particles' time. ``readings`` counts the individual receiver readings used;
    ``refused`` the measurements older than the node's window (not processed).
    """

    readings: int = 0
    empty: int = 0
    late: int = 0
    refused: int = 0

    @property
    def measurements(self) -> int:
        """RSSI measurements processed."""
        return self.processed

    @property
    def contributions(self) -> int:
        """Information contributions fused into the node."""
        return self.contributed


class WSNFrontEnd(FrontEnd):
    """Runs a :class:`WSNTracker` on a node's RSSI measurements and fuses its information contributions.

    Parameters
    ----------
    tracker : WSNTracker
        Not yet initialized; it is initialized from ``prior`` at the first measurement.
    prior : (t0, mean, cov)
        The network's common prior (state ``[x, y, (z,) vx, vy, (vz)]``): particle
        positions (and velocities for a constant-velocity tracker) are drawn from it.
    axes : int
        Position axes of the state (2 or 3); the contribution goes to ``x, y``.
    information : {"quotient", "regression"}
        ``method`` of :meth:`WSNTracker.information_contribution`.
    """

    def __init__(self, tracker: WSNTracker, prior: tuple[float, Array, Array], axes: int = 2,
                 information: str = "quotient") -> None:
        if information not in ("quotient", "regression"):
            raise ValidationError(f"information must be 'quotient' or 'regression', got {information!r}")
        self.information = information
        self.tracker = tracker
        self.t0 = float(prior[0])
        self.prior_mean = np.asarray(prior[1], dtype=float)
        self.prior_cov = np.asarray(prior[2], dtype=float)
        self.axes = int(axes)
        self.stats = WSNStats()

    def __repr__(self) -> str:
        return f"WSNFrontEnd({self.tracker!r}, time={self.time}, {self.stats})"

    @property
    def time(self) -> float | None:
        """Time of the particles (None before the first measurement)."""
        return self.tracker.time

    def _initialize(self) -> None:
        trk = self.tracker
        m, C = self.prior_mean, self.prior_cov
        trk.initialize(mean=m[:2], cov=C[:2, :2], t=self.t0)
        if trk.dim == 4:
            # velocities drawn from the prior conditioned on the drawn positions
            iv = [self.axes, self.axes + 1]
            ip = [0, 1]
            Cpp, Cvp, Cvv = C[np.ix_(ip, ip)], C[np.ix_(iv, ip)], C[np.ix_(iv, iv)]
            K = np.linalg.solve(Cpp, Cvp.T).T
            Cc = Cvv - K @ Cvp.T
            x = np.array(trk.particles)
            L = np.linalg.cholesky(0.5 * (Cc + Cc.T) + 1e-12 * np.eye(2))
            x[:, 2:] = m[iv] + (x[:, :2] - m[ip]) @ K.T + trk.rng.standard_normal((x.shape[0], 2)) @ L.T
            trk.set_particles(x)

    def process(self, node: FusionNode, t: float, z: Array) -> bool:
        """Predict the particles to ``t``, weight them by the readings ``z``, fuse the contribution.

        Returns whether information was fused. See the module docstring for late measurements.
        """
        f = node.filter
        if t < f.oldest_time - f.time_tol:
            self.stats.refused += 1
            raise OutsideWindowError(f"RSSI measurement at t={t} is older than the window start {f.oldest_time}")
        trk = self.tracker
        if trk.time is None:
            self._initialize()
        if t < trk.time - f.time_tol:
            self.stats.late += 1
            self.stats.rejected += 1
            return False
        self.stats.processed += 1
        trk.predict(max(float(t), trk.time))
        used = trk.update(trk.time, z)
        self.stats.readings += used
        info = trk.information_contribution(method=self.information)
        if used == 0 or not np.any(info.Omega):
            self.stats.empty += 1
            self.stats.rejected += 1
            return False
        Lam, y = embed_position_information(info.Omega, info.eta, f.n)
        node.add_local_information(t, Lam, y)
        self.stats.contributed += 1
        return True

    def estimate(self) -> Estimate:
        """The particle filter's own Gaussian fit of ``(x, y)`` (its readings only)."""
        return self.tracker.estimate()
