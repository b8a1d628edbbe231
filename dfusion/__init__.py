"""dfusion: decentralized sensor fusion for robotics.

Fusion nodes run Extended Information Filters over delayed-state trajectories
and exchange information with their neighbours in a tree; channel filters keep
anything from being counted twice.
"""
from dfusion import errors, models
from dfusion.estimation import (
    DelayedStateEIF,
    Estimate,
    ExtendedInformationFilter,
    InformationGaussian,
)
from dfusion.fusion import ChannelFilter, FusionNode
from dfusion.policies import InformationFusionPolicy, Policy

__version__ = "0.1.0"

__all__ = [
    "errors",
    "models",
    "DelayedStateEIF",
    "ExtendedInformationFilter",
    "InformationGaussian",
    "ChannelFilter",
    "FusionNode",
    "Policy",
    "InformationFusionPolicy",
    "Estimate",
]
