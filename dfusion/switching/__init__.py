"""Switching as a policy beside fusion (DESIGN.md sec. 7).

* :mod:`.policies` -- greedy switching with the switching paper's punishment ``P``,
  hysteresis on a signal (the docking paper's similarity rate), blended transitions,
  information fusion of the sources above a reliability floor.
* :mod:`.lifecycle` -- the component life cycle (created, ready, active, error, reset)
  and a :class:`Supervisor` that restarts failed components.
* :mod:`.similarity` -- the correntropy similarity rate and the trimmed-ICP overlap ratio.

Importing this package registers the policies for scenario files
(``policy = "greedy"``, ``"hysteresis"``, ``"blend"``, ``"fusion_floor"``, or a table
``{kind = "greedy", punishment = 0.12}``); see ``docs/policies.md``.
"""
from ..sim.scenario import register_policy
from .lifecycle import Component, InvalidTransition, LifecycleEvent, State, Supervisor, TRANSITIONS
from .policies import (
    BlendedTransitionPolicy,
    FusionFloorPolicy,
    GreedySwitchingPolicy,
    HysteresisSwitchingPolicy,
    Switch,
    SwitchingPolicy,
    effective_reliability,
    information_fusion,
    make_blend,
    make_fusion_floor,
    make_greedy,
    make_hysteresis,
    select_punishment,
)
from .similarity import (
    SimilarityRate,
    SimilarityResult,
    correntropy_similarity,
    overlap_ratio,
    relative_pose,
    similarity_rate,
    transform_points,
    trimmed_overlap_ratio,
)

#: Scenario names of the policies defined here.
POLICIES = {
    "greedy": make_greedy,
    "hysteresis": make_hysteresis,
    "blend": make_blend,
    "fusion_floor": make_fusion_floor,
}
for _name, _factory in POLICIES.items():
    register_policy(_name, _factory)

__all__ = [
    "BlendedTransitionPolicy",
    "Component",
    "FusionFloorPolicy",
    "GreedySwitchingPolicy",
    "HysteresisSwitchingPolicy",
    "InvalidTransition",
    "LifecycleEvent",
    "POLICIES",
    "SimilarityRate",
    "SimilarityResult",
    "State",
    "Supervisor",
    "Switch",
    "SwitchingPolicy",
    "TRANSITIONS",
    "correntropy_similarity",
    "effective_reliability",
    "information_fusion",
    "overlap_ratio",
    "relative_pose",
    "select_punishment",
    "similarity_rate",
    "transform_points",
    "trimmed_overlap_ratio",
]
