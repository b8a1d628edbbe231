"""Running a scenario in one process: the simulated world and the runner.

* :mod:`dfusion.sim.world` -- ground truth and sensor measurements, deterministic by seed;
* :mod:`dfusion.sim.runner` -- every node on a :class:`~dfusion.transport.SimulatedNetwork`,
  the centralized EKF beside them, metrics (``dfusion simulate``).
"""
from dfusion.sim.runner import (
           NodeOutput,
           SimulationResult,
           compute_metrics,
           run_scenario,
)
from dfusion.sim.world import Measurement, World, simulate_world

__all__ = ["run_scenario", "SimulationResult", "NodeOutput", "compute_metrics", "simulate_world", "World",
           "Measurement"]
