"""Simulation tools: a deterministic lossy network for testing fusion protocols."""
from .network import LinkSpec, SimulatedNetwork

__all__ = ["LinkSpec", "SimulatedNetwork"]
