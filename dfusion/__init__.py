"""dfusion: decentralized sensor fusion for robotics.

Fusion nodes run Extended Information Filters over delayed-state trajectories
and exchange information with their neighbours in a tree; channel filters keep
anything from being counted twice.
"""
from . import errors, models
from .estimation import DelayedStateEIF, ExtendedInformationFilter
from .fusion import ChannelFilter, FusionNode, InformationFusionPolicy, Policy, SourceEstimate
from .gaussian import InformationGaussian

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
    "SourceEstimate",
]
