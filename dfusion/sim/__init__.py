"""Running a scenario in one process: the simulated world and the runner.

* :mod:`dfusion.sim.world` -- ground truth and sensor measurements, deterministic by seed;
* :mod:`dfusion.sim.runner` -- every node on a :class:`~dfusion.transport.SimulatedNetwork`,
  the centralized EKF beside them, metrics (``dfusion simulate``).
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

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
