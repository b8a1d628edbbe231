"""Map-based localization of a robot with a planar laser.

* :mod:`.mcl` -- Monte Carlo localization (odometry motion model, URUS erfc beam model and
  likelihood field, KLD sampling, Augmented-MCL recovery, late scans).
* :mod:`.icp` -- 2-D ICP scan matching (point-to-point, point-to-line) with covariance.
* :mod:`.odometry_ekf` -- the EKF fusing odometry with scan-matching poses (survey eq. 5-8).
"""
from .icp import ICPResult, ScanMatcher, estimate_normals, icp, scan_to_points
from .mcl import (
    BeamErfcModel,
    LaserConfig,
    LikelihoodFieldModel,
    MonteCarloLocalization,
    OdometryMotionModel,
    PoseEstimate,
    gaussian_summary,
    kld_sample_size,
    reliability,
    se2_between,
    se2_compose,
    se2_inverse,
)
from .odometry_ekf import OdometryEKF, odometry_increment

__all__ = [
    "ICPResult",
    "ScanMatcher",
    "estimate_normals",
    "icp",
    "scan_to_points",
    "OdometryEKF",
    "odometry_increment",
    "BeamErfcModel",
    "LaserConfig",
    "LikelihoodFieldModel",
    "MonteCarloLocalization",
    "OdometryMotionModel",
    "PoseEstimate",
    "gaussian_summary",
    "kld_sample_size",
    "reliability",
    "se2_between",
    "se2_compose",
    "se2_inverse",
]
