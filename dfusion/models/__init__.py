"""Motion and measurement models (``f, F, Q`` and ``h, H, R``), laser and odometry models."""
from dfusion.models.base import MeasurementModel, MotionModel
from dfusion.models.camera import PinholeCamera, SceneCamera
from dfusion.models.laser import (
    BeamErfcModel,
    LaserConfig,
    LaserScanSensor,
    LikelihoodFieldModel,
)
from dfusion.models.measurement import (
    LandmarkRangeBearing,
    PositionFix,
    PositionSensor,
    RangeBearing,
    RSSISensor,
    TargetRangeBearing,
    fit_path_loss,
)
from dfusion.models.motion import ConstantVelocity, Unicycle
from dfusion.models.odometry import (
    OdometryMotionModel,
    VelocityOdometry,
    odometry_increment,
)

__all__ = [
    "MotionModel",
    "MeasurementModel",
    "PinholeCamera",
    "SceneCamera",
    "LaserConfig",
    "BeamErfcModel",
    "LikelihoodFieldModel",
    "LaserScanSensor",
    "PositionSensor",
    "RangeBearing",
    "RSSISensor",
    "fit_path_loss",
    "LandmarkRangeBearing",
    "TargetRangeBearing",
    "PositionFix",
    "ConstantVelocity",
    "Unicycle",
    "OdometryMotionModel",
    "VelocityOdometry",
    "odometry_increment",
]
