"""Estimators: information-form filters over one state or a delayed-state window."""
from .delayed_state import DelayedStateEIF, measurement_information
from .eif import ExtendedInformationFilter
from .trajectory import MotionFactor, TrajectoryInformation

__all__ = [
    "DelayedStateEIF",
    "ExtendedInformationFilter",
    "MotionFactor",
    "TrajectoryInformation",
    "measurement_information",
]
