"""Output policies beside fusion: the policy interface, switching policies, the component life cycle."""
from dfusion.policies.base import InformationFusionPolicy, Policy
from dfusion.policies.lifecycle import (
    TRANSITIONS,
    Component,
    InvalidTransition,
    LifecycleEvent,
    State,
    Supervisor,
)
from dfusion.policies.switching import (
    BlendedTransitionPolicy,
    FusionFloorPolicy,
    GreedySwitchingPolicy,
    HysteresisSwitchingPolicy,
    Switch,
    SwitchingPolicy,
    effective_reliability,
    information_fusion,
    select_punishment,
)

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
