"""Motion and measurement models (``f, F, Q`` and ``h, H, R``), laser and odometry models."""
from __future__ import annotations

from typing import TYPE_CHECKING

from dfusion.lazy import lazy_exports

if TYPE_CHECKING:  # the names, for type checkers and IDEs; imported on first use at run time
    from dfusion.models.pdr import StepDetector, PDRSteps, detect_steps, pdr_steps, fit_weinberg_gain, fit_heading_offset, dead_reckon, anchored_track, world_field, quaternion_matrices
    from dfusion.models.base import MeasurementModel, MotionModel, model_at
    from dfusion.models.camera import MountedCamera, PinholeCamera, SceneCamera
    from dfusion.models.laser import BeamErfcModel, LaserConfig, LaserScanSensor, LikelihoodFieldModel
    from dfusion.models.measurement import LandmarkRangeBearing, PositionFix, PositionSensor, RangeBearing, RSSISensor, TargetRangeBearing, fit_path_loss
    from dfusion.models.motion import ConstantVelocity, MeanRevertingVelocity, Unicycle
    from dfusion.models.odometry import OdometryMotionModel, VelocityOdometry, odometry_increment

__all__ = [
    "StepDetector",
    "PDRSteps",
    "detect_steps",
    "pdr_steps",
    "fit_weinberg_gain",
    "fit_heading_offset",
    "dead_reckon",
    "anchored_track",
    "world_field",
    "quaternion_matrices",
    "MotionModel",
    "MeasurementModel",
    "PinholeCamera",
    "SceneCamera",
    "MountedCamera",
    "model_at",
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
    "MeanRevertingVelocity",
    "Unicycle",
    "OdometryMotionModel",
    "VelocityOdometry",
    "odometry_increment",
]

_WHERE = {
    "StepDetector": ("dfusion.models.pdr", "StepDetector"),
    "PDRSteps": ("dfusion.models.pdr", "PDRSteps"),
    "detect_steps": ("dfusion.models.pdr", "detect_steps"),
    "pdr_steps": ("dfusion.models.pdr", "pdr_steps"),
    "fit_weinberg_gain": ("dfusion.models.pdr", "fit_weinberg_gain"),
    "fit_heading_offset": ("dfusion.models.pdr", "fit_heading_offset"),
    "dead_reckon": ("dfusion.models.pdr", "dead_reckon"),
    "anchored_track": ("dfusion.models.pdr", "anchored_track"),
    "world_field": ("dfusion.models.pdr", "world_field"),
    "quaternion_matrices": ("dfusion.models.pdr", "quaternion_matrices"),
    "MeasurementModel": ("dfusion.models.base", 'MeasurementModel'),
    "MotionModel": ("dfusion.models.base", 'MotionModel'),
    "PinholeCamera": ("dfusion.models.camera", 'PinholeCamera'),
    "SceneCamera": ("dfusion.models.camera", 'SceneCamera'),
    "MountedCamera": ("dfusion.models.camera", 'MountedCamera'),
    "model_at": ("dfusion.models.base", 'model_at'),
    "BeamErfcModel": ("dfusion.models.laser", 'BeamErfcModel'),
    "LaserConfig": ("dfusion.models.laser", 'LaserConfig'),
    "LaserScanSensor": ("dfusion.models.laser", 'LaserScanSensor'),
    "LikelihoodFieldModel": ("dfusion.models.laser", 'LikelihoodFieldModel'),
    "LandmarkRangeBearing": ("dfusion.models.measurement", 'LandmarkRangeBearing'),
    "PositionFix": ("dfusion.models.measurement", 'PositionFix'),
    "PositionSensor": ("dfusion.models.measurement", 'PositionSensor'),
    "RangeBearing": ("dfusion.models.measurement", 'RangeBearing'),
    "RSSISensor": ("dfusion.models.measurement", 'RSSISensor'),
    "TargetRangeBearing": ("dfusion.models.measurement", 'TargetRangeBearing'),
    "fit_path_loss": ("dfusion.models.measurement", 'fit_path_loss'),
    "ConstantVelocity": ("dfusion.models.motion", 'ConstantVelocity'),
    "MeanRevertingVelocity": ("dfusion.models.motion", 'MeanRevertingVelocity'),
    "Unicycle": ("dfusion.models.motion", 'Unicycle'),
    "OdometryMotionModel": ("dfusion.models.odometry", 'OdometryMotionModel'),
    "VelocityOdometry": ("dfusion.models.odometry", 'VelocityOdometry'),
    "odometry_increment": ("dfusion.models.odometry", 'odometry_increment'),
}


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)
