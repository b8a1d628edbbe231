r"""Front end of a robot localized by Monte Carlo localization against a map."""
from __future__ import annotations

import math

import numpy as np

from dfusion.estimation.estimate import Estimate
from dfusion.estimation.particle_filter import gaussian_summary
from dfusion.frontends.base import (
    FrontEnd,
    FrontEndStats,
    embed_source,
    fit_difference_information,
)
from dfusion.fusion.node import FusionNode
from dfusion.geometry import heading_of, wrap_angle
from dfusion.linalg import Array, symmetrize
from dfusion.localization.mcl import MonteCarloLocalization
from dfusion.reliability import covariance_reliability

__all__ = ["MCLFrontEnd"]

class MCLFrontEnd(FrontEnd):
    """Monte Carlo localization of the robot (the node's target, state ``(x, y, vx, vy)``).

    The particles ``(x, y, theta)`` live in a :class:`MonteCarloLocalization` (its sensor
    model, tempering and KLD resampling). Scenario robots have no wheel odometry, so the
    particles are *predicted from the node's own belief*: at a scan at ``t`` every particle
    moves by the displacement of the node's fused mean since the previous scan plus
    ``N(0, q_pos dt I)``, and its heading takes a random-walk step ``N(0, q_heading dt)``
    (the heading is not in the node's state; the scan constrains it). The first scan draws
    the particles from the node's position belief with headings spread
    ``heading_std`` around the direction of motion. Then:

    1. prediction fit ``(m0, P0)`` of the positions (weights before the scan);
    2. the scan weights the particles (``MonteCarloLocalization.update``, no resampling
       inside);
    3. posterior fit ``(m1, P1)``; the node receives ``fit_difference_information`` --
       the scan's information only, whatever the prior was (module docstring);
    4. resampling (KLD) when ``N_eff < resample_threshold N``.

    A scan whose contribution has no positive eigenvalue is counted in
    ``stats.rejected``.
    """

    def __init__(self, mcl: MonteCarloLocalization, *, q_pos: float = 0.05, q_heading: float = 0.05,
                 heading_std: float = 0.5, resample_threshold: float = 0.5, init_particles: int | None = None) -> None:
        self.mcl = mcl
        mcl.resample_threshold = 0.0  # resampling is done here, after the posterior fit
        self.q_pos = float(q_pos)
        self.q_heading = float(q_heading)
        self.heading_std = float(heading_std)
        self.resample_threshold = float(resample_threshold)
        self.init_particles = init_particles
        self.stats = FrontEndStats()
        self._t: float | None = None
        self._ref: Array | None = None  # fused mean position at the previous scan
        self.last: Estimate | None = None

    def process(self, node: FusionNode, t: float, z: Array) -> bool:
        self.stats.processed += 1
        mcl = self.mcl
        rng = mcl.rng
        mean, cov = node.estimate(t) if t >= node.filter.oldest_time else node.estimate()
        if self._t is None:
            n = self.init_particles or mcl.particle_count()
            L = np.linalg.cholesky(symmetrize(cov[:2, :2]) + 1e-12 * np.eye(2))
            p = np.empty((n, 3))
            p[:, :2] = mean[:2] + rng.standard_normal((n, 2)) @ L.T
            p[:, 2] = heading_of(mean) + self.heading_std * rng.standard_normal(n)
            mcl.initialize_particles(p)
        else:
            dt = max(float(t) - self._t, 0.0)
            p = mcl.particles
            w = mcl.weights
            p[:, :2] += (mean[:2] - self._ref) + math.sqrt(self.q_pos * dt) * rng.standard_normal((p.shape[0], 2))
            p[:, 2] = wrap_angle(p[:, 2] + math.sqrt(self.q_heading * dt) * rng.standard_normal(p.shape[0]))
            mcl.initialize_particles(p, w)
        self._t, self._ref = float(t), mean[:2].copy()
        w0 = mcl.weights
        parts = mcl.particles
        prior = gaussian_summary(parts, w0)
        if not mcl.update(t, z):
            self.stats.rejected += 1
            return False
        post_pose = gaussian_summary(parts, mcl.weights)
        self.last = Estimate("mcl", t, post_pose[0], post_pose[1], covariance_reliability(post_pose[1]),
                             n_particles=parts.shape[0], n_eff=mcl.n_eff)
        prior2 = (prior[0][:2], prior[1][:2, :2])
        post2 = (post_pose[0][:2], post_pose[1][:2, :2])
        try:
            Lam, y = fit_difference_information(prior2, post2, node.filter.n)
        except Exception:  # noqa: BLE001  (degenerate particle cloud: nothing to contribute)
            Lam = np.zeros((node.filter.n, node.filter.n))
            y = np.zeros(node.filter.n)
        contributed = bool(np.any(Lam))
        if not contributed:
            self.stats.rejected += 1
        else:
            node.add_local_information(t, Lam, y)
            self.stats.contributed += 1
            m, P = node.estimate()
            node.report_source(embed_source(f"{node.name}/mcl", t, m, P, post2[0], post2[1],
                                            self.last.reliability))
        if mcl.n_eff < self.resample_threshold * mcl.weights.size:
            mcl.resample()
        return contributed
