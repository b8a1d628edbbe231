r"""Front end of a robot localized by ICP scan matching against a map."""
from __future__ import annotations

import numpy as np

from dfusion.errors import ValidationError
from dfusion.estimation.estimate import Estimate
from dfusion.frontends.base import (
    FrontEnd,
    FrontEndStats,
    embed_source,
    position_information,
)
from dfusion.fusion.node import FusionNode
from dfusion.geometry import heading_of, se2_compose, se2_inverse
from dfusion.linalg import Array
from dfusion.localization.scan_matching import ScanMatcher, scan_to_points
from dfusion.models.laser import LaserConfig
from dfusion.reliability import covariance_reliability

__all__ = ["ICPFrontEnd"]

class ICPFrontEnd(FrontEnd):
    """ICP scan matching of the robot's scan against the map (the robot is the node's target).

    The initial guess is the node's fused position with the heading of the previous
    accepted match (or the direction of motion at the first scan, or when the last match
    is older than ``heading_timeout`` s); the match is accepted when ICP converged with at
    least ``min_inliers`` inliers and an inlier RMSE below ``max_rmse``. Its position
    ``(x, y)`` with covariance ``cov_scale * Sigma_xy + min_std^2 I`` (the Hessian
    covariance is optimistic: ``docs/localization.md``) is added as position information
    and reported as the source ``"<node>/icp"``.
    """

    def __init__(self, matcher: ScanMatcher, laser: LaserConfig, *, cov_scale: float = 4.0,
                 min_std: float = 0.02, min_inliers: int = 20, max_rmse: float = 0.1,
                 heading_timeout: float = 5.0) -> None:
        self.matcher = matcher
        self.laser = laser
        self.cov_scale = float(cov_scale)
        self.min_std = float(min_std)
        self.min_inliers = int(min_inliers)
        self.max_rmse = float(max_rmse)
        self.heading_timeout = float(heading_timeout)
        self.stats = FrontEndStats()
        self._heading: tuple[float, float] | None = None
        self.last: Estimate | None = None

    def process(self, node: FusionNode, t: float, z: Array) -> bool:
        self.stats.processed += 1
        mean, _ = node.estimate(t) if t >= node.filter.oldest_time else node.estimate()
        if self._heading is not None and t - self._heading[0] <= self.heading_timeout:
            th = self._heading[1]
        else:
            th = heading_of(mean)
        pts = scan_to_points(z, self.laser.angles, self.laser.max_range, self.laser.min_range)
        if pts.shape[0] < max(3, self.min_inliers):
            self.stats.rejected += 1
            return False
        init = np.array([mean[0], mean[1], th])
        try:
            res = self.matcher.match(pts, se2_compose(init, self.laser.offset))
        except ValidationError:
            self.stats.rejected += 1
            return False
        if not res.converged or res.n_inliers < self.min_inliers or res.rmse > self.max_rmse:
            self.stats.rejected += 1
            return False
        pose = se2_compose(res.pose, se2_inverse(self.laser.offset))
        self._heading = (float(t), float(pose[2]))
        C = self.cov_scale * res.covariance[:2, :2] + self.min_std**2 * np.eye(2)
        self.last = Estimate("icp", t, pose, res.covariance, covariance_reliability(C))
        Lam, y = position_information(pose[:2], C, node.filter.n)
        node.add_local_information(t, Lam, y)
        self.stats.contributed += 1
        m, P = node.estimate()
        node.report_source(embed_source(f"{node.name}/icp", t, m, P, pose[:2], C, self.last.reliability))
        return True
