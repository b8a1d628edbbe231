"""Motion and measurement models (``f, F, Q`` and ``h, H, R``)."""
from .base import MeasurementModel, MotionModel, wrap_angle
from .camera import PinholeCamera
from .measurement import PositionSensor, RangeBearing, RSSISensor, fit_path_loss
from .motion import ConstantVelocity, Unicycle

__all__ = [
    "MotionModel",
    "MeasurementModel",
    "wrap_angle",
    "ConstantVelocity",
    "PositionSensor",
    "Unicycle",
    "RangeBearing",
    "RSSISensor",
    "fit_path_loss",
    "PinholeCamera",
]
