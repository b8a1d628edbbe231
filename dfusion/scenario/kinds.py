"""The built-in sensor kinds, policies and motion models of scenario files, as explicit tables.

Nothing registers itself on import: :func:`builtin_kinds` lists every kind dfusion
ships, and a user's own kinds come from plug-in modules (:mod:`dfusion.scenario.plugins`).

========================  =====================================================
sensor kind               what
========================  =====================================================
``position``              a position sensor ``z = [I 0] x + v`` (``std``, metres)
``camera``                :mod:`dfusion.scenario.camera_kind`
``robot_camera``          :mod:`dfusion.scenario.camera_kind` (a camera on a robot that moves)
``wsn_rssi``              :mod:`dfusion.scenario.wsn_kind`
``robot_mcl``             :mod:`dfusion.scenario.robot_kinds`
``robot_icp``             :mod:`dfusion.scenario.robot_kinds`
``robot_env_camera``      :mod:`dfusion.scenario.robot_kinds`
``detections``            :mod:`dfusion.scenario.tracking_kinds` (multi-target: a camera's view)
``tags``                  :mod:`dfusion.scenario.tracking_kinds` (multi-target: identified targets)
========================  =====================================================

Policies: ``fusion`` (the default, :class:`~dfusion.policies.InformationFusionPolicy`),
``greedy``, ``hysteresis``, ``blend``, ``fusion_floor`` (:mod:`dfusion.policies.switching`).
Motion models: ``constant_velocity``.
"""
from __future__ import annotations

from typing import Any, Mapping

from dfusion.errors import ValidationError
from dfusion.models.base import MeasurementModel, MotionModel
from dfusion.models.measurement import PositionSensor
from dfusion.models.motion import ConstantVelocity
from dfusion.policies.base import InformationFusionPolicy
from dfusion.scenario.spec import Kinds, LazyTable, MotionKind, Scenario, SensorKind
from dfusion.scenario.values import check_keys, number

__all__ = ["POSITION", "CONSTANT_VELOCITY", "SENSOR_KINDS", "POLICY_KINDS", "MOTION_KINDS", "builtin_kinds"]


def _position_sensor(table: Mapping[str, Any], sc: Scenario) -> MeasurementModel:
    return PositionSensor(dim=sc.target.axes, std=number(table, "std", 1.0, positive=True))


#: The ``position`` sensor kind: ``z = [I 0] x + v``, ``v ~ N(0, std^2 I)``.
POSITION = SensorKind("position", frozenset({"std"}), _position_sensor, None,
                      "a position sensor z = [I 0] x + v (std, metres)")


def _constant_velocity(table: Mapping[str, Any]) -> MotionModel:
    """The number of axes is half the length of ``initial_mean`` (positions, then
    velocities); an odd length is refused, since no number of entries near it is right
    by itself (3 entries: 4 for a 2-D target, 6 for 3-D; 2 would be a 1-D target)."""
    mean = table.get("initial_mean")
    if isinstance(mean, list) and len(mean) % 2:
        n = len(mean)
        raise ValidationError(f"initial_mean of a constant_velocity target is the positions then the velocities, "
                              f"2 entries per axis: [x, y, vx, vy] in 2-D, [x, y, z, vx, vy, vz] in 3-D "
                              f"(got {n} entries; {n - 1} would be a {(n - 1) // 2}-D target)")
    axes = len(mean) // 2 if isinstance(mean, list) and mean else 2
    return ConstantVelocity(dim=axes, q=number(table, "q", 0.1, positive=True))


def _fusion_policy(params: Mapping[str, Any]) -> InformationFusionPolicy:
    check_keys(params, (), "policy 'fusion'")
    return InformationFusionPolicy()


#: Built-in sensor kinds by name (a kind's module is imported when a scenario names it).
SENSOR_KINDS: dict[str, SensorKind | str] = {
    "position": POSITION,
    "camera": "dfusion.scenario.camera_kind:CAMERA",
    "robot_camera": "dfusion.scenario.camera_kind:ROBOT_CAMERA",
    "wsn_rssi": "dfusion.scenario.wsn_kind:WSN_RSSI",
    "robot_mcl": "dfusion.scenario.robot_kinds:ROBOT_MCL",
    "robot_icp": "dfusion.scenario.robot_kinds:ROBOT_ICP",
    "robot_env_camera": "dfusion.scenario.robot_kinds:ROBOT_ENV_CAMERA",
    "detections": "dfusion.scenario.tracking_kinds:DETECTIONS",
    "tags": "dfusion.scenario.tracking_kinds:TAGS",
}
#: Built-in policies: ``name -> factory(params)`` (imported when a scenario names one).
POLICY_KINDS = {"fusion": _fusion_policy, "greedy": "dfusion.policies.switching:make_greedy",
                "hysteresis": "dfusion.policies.switching:make_hysteresis",
                "blend": "dfusion.policies.switching:make_blend",
                "fusion_floor": "dfusion.policies.switching:make_fusion_floor"}
#: The ``constant_velocity`` motion model (``q``: acceleration noise density, m^2 s^-3).
CONSTANT_VELOCITY = MotionKind("constant_velocity", frozenset({"q"}), _constant_velocity,
                               "constant velocity in 2-D or 3-D (q)")
#: Built-in motion models of ``[target]`` by name.
MOTION_KINDS: dict[str, MotionKind] = {CONSTANT_VELOCITY.name: CONSTANT_VELOCITY}


def builtin_kinds() -> Kinds:
    """dfusion's own sensor kinds, policies and motion models."""
    return Kinds(LazyTable(SENSOR_KINDS), LazyTable(POLICY_KINDS), LazyTable(MOTION_KINDS))

