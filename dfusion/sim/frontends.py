"""Front ends: how a node fuses its raw measurements.

The simulated world produces raw measurements ``z`` of each node's sensor. A
front end turns them into what the node's :class:`~dfusion.fusion.FusionNode`
fuses. The default, :class:`EIFFrontEnd`, is an EIF measurement update
(``node.update``); a particle-filter sensor (WSN RSSI) or a robot localizer runs
its own estimator and contributes information with
``node.add_local_information`` (DESIGN.md sec. 4). Register a front end for a
sensor kind with :func:`dfusion.sim.scenario.register_sensor`.
"""
from __future__ import annotations

from typing import Protocol

from ..fusion.node import FusionNode
from ..linalg import Array
from ..models.base import MeasurementModel


class FrontEnd(Protocol):
    """Fuses one node's raw measurements into the node."""

    def process(self, node: FusionNode, t: float, z: Array) -> None:
        """Fuse the measurement ``z`` taken at ``t`` (``t`` may be in the past, inside the window)."""


class EIFFrontEnd:
    """The default: an EIF measurement update with the sensor's model."""

    def __init__(self, sensor: MeasurementModel) -> None:
        self.sensor = sensor

    def process(self, node: FusionNode, t: float, z: Array) -> None:
        node.update(t, z, self.sensor)
