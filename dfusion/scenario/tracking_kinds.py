"""The sensor kinds of multi-target scenarios: ``detections`` (a camera with a rectangular
view) and ``tags`` (identified targets: radio tags read by a sensor network, a robot's own
localization). Both measure positions, ``z = [I 0] x + v``, ``v ~ N(0, std^2 I)``;
``docs/scenarios.md`` ("Multi-target scenarios") documents their keys.

A kind's ``sensor(table, scenario)`` checks the table and returns the position sensor; what
the node does with it is :mod:`dfusion.sim.tracking_runner`'s (anonymous detections: the
node's tracker associates them; identified readings: an update of the target's track,
:meth:`~dfusion.fusion.tracking_node.TrackingNode.observe`). Named in a single-target
scenario they are refused: they need ``[[targets]]``.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

from dfusion.errors import ValidationError
from dfusion.models.base import MeasurementModel
from dfusion.models.measurement import PositionSensor
from dfusion.scenario.spec import Scenario, SensorKind
from dfusion.scenario.values import number, suggest

__all__ = ["DETECTIONS", "TAGS", "view_of"]


def view_of(table: Mapping[str, Any], required: bool) -> tuple[float, float, float, float] | None:
    """``view = [x0, x1, y0, y1]`` of a node table (metres), checked."""
    v = table.get("view")
    if v is None:
        if required:
            raise ValidationError("view is required: the rectangle [x0, x1, y0, y1] the camera sees (metres)")
        return None
    if not (isinstance(v, list) and len(v) == 4 and all(
            isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in v)):
        raise ValidationError(f"view must be [x0, x1, y0, y1] (metres), got {v!r}")
    x0, x1, y0, y1 = (float(c) for c in v)
    if not (x1 > x0 and y1 > y0):
        raise ValidationError(f"view must have x1 > x0 and y1 > y0, got {v!r}")
    return x0, x1, y0, y1


def _multi_target(sc: Scenario, kind: str) -> None:
    if not sc.multi_target:
        raise ValidationError(f"sensor {kind!r} belongs to a multi-target scenario ([[targets]] and [tracking])")


def _detections(table: Mapping[str, Any], sc: Scenario) -> MeasurementModel:
    _multi_target(sc, "detections")
    view_of(table, required=True)
    number(table, "clutter", 0.0, nonneg=True)
    return PositionSensor(2, number(table, "std", 0.3, positive=True))


def _tags(table: Mapping[str, Any], sc: Scenario) -> MeasurementModel:
    _multi_target(sc, "tags")
    view_of(table, required=False)
    names = table.get("targets")
    if not (isinstance(names, list) and names and all(isinstance(n, str) for n in names)):
        raise ValidationError(f"targets must be a non-empty list of target names (the tagged ones), got {names!r}")
    known = [t.name for t in sc.targets]
    for n in names:
        if n not in known:
            raise ValidationError(f"targets names {n!r}, which has no [[targets]] table{suggest(n, known)}")
    if len(set(names)) != len(names):
        raise ValidationError(f"targets names a target twice: {names!r}")
    return PositionSensor(2, number(table, "std", 1.0, positive=True))


#: ``sensor = "detections"``: a camera seeing the rectangle ``view``, anonymous detections with clutter.
DETECTIONS = SensorKind("detections", frozenset({"view", "std", "clutter"}), _detections, None,
                        "multi-target: a camera seeing the rectangle view = [x0, x1, y0, y1]; anonymous "
                        "position detections (std, m) and clutter false detections per frame")
#: ``sensor = "tags"``: positions of identified targets (``targets``), optionally only inside ``view``.
TAGS = SensorKind("tags", frozenset({"targets", "std", "view"}), _tags, None,
                  "multi-target: positions of identified targets (radio tags, a robot's own localization)")
