"""Motion and measurement models (``f, F, Q`` and ``h, H, R``)."""
from .base import MeasurementModel, MotionModel, wrap_angle
from .measurement import PositionSensor
from .motion import ConstantVelocity

__all__ = ["MotionModel", "MeasurementModel", "wrap_angle", "ConstantVelocity", "PositionSensor"]
