"""Running a scenario in one process: the simulated world and the runner.

* :mod:`dfusion.sim.world` -- ground truth and sensor measurements, deterministic by seed;
* :mod:`dfusion.sim.runner` -- every node on a :class:`~dfusion.transport.SimulatedNetwork`,
  the centralized EKF beside them, metrics (``dfusion simulate``);
* :mod:`dfusion.sim.replay` -- a scenario's nodes fed from a ROS bag (``dfusion replay SCENARIO BAG``);
* :mod:`dfusion.sim.bag_scans` -- a bag's detection arrays as the multi-target tracker's scans, and
  :mod:`dfusion.sim.track_replay` -- those scans tracked (``dfusion replay BAG --detections``).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from dfusion.lazy import lazy_exports

if TYPE_CHECKING:  # the names, for type checkers and IDEs; imported on first use at run time
    from dfusion.sim.runner import NodeOutput, SimulationResult, compute_metrics, run_scenario
    from dfusion.sim.world import Measurement, World, simulate_world

__all__ = [
    "run_scenario",
    "SimulationResult",
    "NodeOutput",
    "compute_metrics",
    "simulate_world",
    "World",
    "Measurement",
]

_WHERE = {
    "NodeOutput": ("dfusion.sim.runner", 'NodeOutput'),
    "SimulationResult": ("dfusion.sim.runner", 'SimulationResult'),
    "compute_metrics": ("dfusion.sim.runner", 'compute_metrics'),
    "run_scenario": ("dfusion.sim.runner", 'run_scenario'),
    "Measurement": ("dfusion.sim.world", 'Measurement'),
    "World": ("dfusion.sim.world", 'World'),
    "simulate_world": ("dfusion.sim.world", 'simulate_world'),
}


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)
