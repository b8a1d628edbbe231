"""Output policies beside fusion: the policy interface, switching policies, the component life cycle."""
from __future__ import annotations

from typing import TYPE_CHECKING

from dfusion.lazy import lazy_exports

if TYPE_CHECKING:  # the names, for type checkers and IDEs; imported on first use at run time
    from dfusion.policies.base import InformationFusionPolicy, Policy
    from dfusion.policies.lifecycle import TRANSITIONS, Component, InvalidTransition, LifecycleEvent, State, Supervisor
    from dfusion.policies.switching import BlendedTransitionPolicy, FusionFloorPolicy, GreedySwitchingPolicy, HysteresisSwitchingPolicy, Switch, SwitchingPolicy, effective_reliability, information_fusion, select_punishment

__all__ = [
    "Policy",
    "InformationFusionPolicy",
    "State",
    "TRANSITIONS",
    "InvalidTransition",
    "Component",
    "Supervisor",
    "LifecycleEvent",
    "Switch",
    "SwitchingPolicy",
    "GreedySwitchingPolicy",
    "HysteresisSwitchingPolicy",
    "BlendedTransitionPolicy",
    "FusionFloorPolicy",
    "effective_reliability",
    "select_punishment",
    "information_fusion",
]

_WHERE = {
    "InformationFusionPolicy": ("dfusion.policies.base", 'InformationFusionPolicy'),
    "Policy": ("dfusion.policies.base", 'Policy'),
    "TRANSITIONS": ("dfusion.policies.lifecycle", 'TRANSITIONS'),
    "Component": ("dfusion.policies.lifecycle", 'Component'),
    "InvalidTransition": ("dfusion.policies.lifecycle", 'InvalidTransition'),
    "LifecycleEvent": ("dfusion.policies.lifecycle", 'LifecycleEvent'),
    "State": ("dfusion.policies.lifecycle", 'State'),
    "Supervisor": ("dfusion.policies.lifecycle", 'Supervisor'),
    "BlendedTransitionPolicy": ("dfusion.policies.switching", 'BlendedTransitionPolicy'),
    "FusionFloorPolicy": ("dfusion.policies.switching", 'FusionFloorPolicy'),
    "GreedySwitchingPolicy": ("dfusion.policies.switching", 'GreedySwitchingPolicy'),
    "HysteresisSwitchingPolicy": ("dfusion.policies.switching", 'HysteresisSwitchingPolicy'),
    "Switch": ("dfusion.policies.switching", 'Switch'),
    "SwitchingPolicy": ("dfusion.policies.switching", 'SwitchingPolicy'),
    "effective_reliability": ("dfusion.policies.switching", 'effective_reliability'),
    "information_fusion": ("dfusion.policies.switching", 'information_fusion'),
    "select_punishment": ("dfusion.policies.switching", 'select_punishment'),
}


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)
