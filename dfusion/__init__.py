"""dfusion: decentralized sensor fusion for robotics.

Fusion nodes run Extended Information Filters over delayed-state trajectories
and exchange information with their neighbours in a tree; channel filters keep
anything from being counted twice.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

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


def __getattr__(name: str) -> Any:
    """Import a public name on first use, so that importing the package loads nothing else."""
    where = _WHERE.get(name)
    if where is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module, attribute = where
    obj = importlib.import_module(module)
    if attribute is not None:
        obj = getattr(obj, attribute)
    globals()[name] = obj
    return obj


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
