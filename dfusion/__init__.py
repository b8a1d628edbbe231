"""dfusion: decentralized sensor fusion for robotics.

Fusion nodes run Extended Information Filters over delayed-state trajectories
and exchange information with their neighbours in a tree; channel filters keep
anything from being counted twice.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from dfusion.lazy import lazy_exports

if TYPE_CHECKING:  # the names, for type checkers and IDEs; imported on first use at run time
    from dfusion import errors
    from dfusion import models
    from dfusion.estimation import DelayedStateEIF, Estimate, ExtendedInformationFilter, InformationGaussian
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

_WHERE = {
    "errors": ("dfusion.errors", None),
    "models": ("dfusion.models", None),
    "DelayedStateEIF": ("dfusion.estimation", 'DelayedStateEIF'),
    "Estimate": ("dfusion.estimation", 'Estimate'),
    "ExtendedInformationFilter": ("dfusion.estimation", 'ExtendedInformationFilter'),
    "InformationGaussian": ("dfusion.estimation", 'InformationGaussian'),
    "ChannelFilter": ("dfusion.fusion", 'ChannelFilter'),
    "FusionNode": ("dfusion.fusion", 'FusionNode'),
    "InformationFusionPolicy": ("dfusion.policies", 'InformationFusionPolicy'),
    "Policy": ("dfusion.policies", 'Policy'),
}


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)
