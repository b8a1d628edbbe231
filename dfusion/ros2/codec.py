r"""ROS 2 messages as CDR bytes, with `rosbags <https://gitlab.com/ternaris/rosbags>`_'s type store.

No ROS installation is needed: rosbags carries the standard message definitions of each ROS 2
release (the Jazzy store here, the first release ``rmw_zenoh`` supports) and serializes them to
CDR and back. :func:`type_hash` is rosbags' RIHS01 hash of a type (REP-2016: SHA-256 of the type's
description; ``rmw_zenoh`` puts it in every key). The builders make the messages a live node
publishes: ``nav_msgs/Odometry`` and ``geometry_msgs/PoseWithCovarianceStamped`` of a planar
estimate (:func:`estimate_messages`) and ``diagnostic_msgs/DiagnosticArray`` (:func:`diagnostics`).
"""
from __future__ import annotations

import functools
import math
from typing import Any, Mapping

import numpy as np

from dfusion.bags.convert import quaternion_of_yaw
from dfusion.errors import ValidationError

__all__ = ["typestore", "encode", "decode", "type_hash", "register_definition", "make", "time_msg", "header",
           "estimate_messages",
           "diagnostics", "planar_pose_covariance", "DIAGNOSTIC_LEVELS"]

#: ``diagnostic_msgs/DiagnosticStatus`` levels.
DIAGNOSTIC_LEVELS = {"ok": 0, "warn": 1, "error": 2, "stale": 3}


@functools.lru_cache(maxsize=1)
def typestore() -> Any:
    """rosbags' ROS 2 Jazzy type store (built once)."""
    from rosbags.typesys import Stores, get_typestore   # noqa: PLC0415  (only a ROS 2 node needs it)

    return get_typestore(Stores.ROS2_JAZZY)


def _cls(msgtype: str) -> Any:
    try:
        return typestore().types[msgtype]
    except KeyError:
        raise ValidationError(f"unknown ROS 2 message type {msgtype!r} (rosbags' Jazzy store has the standard "
                              "ones: e.g. nav_msgs/msg/Odometry)") from None


@functools.lru_cache(maxsize=None)
def type_hash(msgtype: str) -> str:
    """``RIHS01_<sha256 hex>`` of ``msgtype`` (REP-2016), as rmw_zenoh puts it in keys."""
    _cls(msgtype)
    try:
        return typestore().hash_rihs01(msgtype)
    except KeyError as exc:   # a registered definition naming a type nobody defined
        raise ValidationError(f"the definition of {msgtype} uses the unknown type {exc.args[0]!r} (give its .msg "
                              "definition too)") from None


def register_definition(msgtype: str, text: str) -> None:
    """Add a message type from its ``.msg`` definition (a custom type: a vendor's detections, ...)."""
    from rosbags.typesys import get_types_from_msg   # noqa: PLC0415

    try:
        types = get_types_from_msg(text, msgtype)
    except Exception as exc:   # rosbags' parser errors: "Could not parse:", the text, the offset, the rest
        lines = str(exc).splitlines()
        where = (f"at {lines[3].strip()[:60]!r}" if len(lines) > 3 and lines[2].strip().isdigit()
                 else " ".join(" ".join(lines).split())[:200])
        raise ValidationError(f"the definition of {msgtype} does not parse: {where}") from None
    typestore().register(types)
    type_hash.cache_clear()


def encode(msg: Any) -> bytes:
    """CDR bytes (with the encapsulation header) of a rosbags message object."""
    return bytes(typestore().serialize_cdr(msg, msg.__msgtype__))


def decode(data: bytes, msgtype: str) -> Any:
    """The message ``msgtype`` in CDR ``data``; a clear error for bytes that are not one."""
    _cls(msgtype)
    try:
        return typestore().deserialize_cdr(bytes(data), msgtype)
    except Exception as exc:   # rosbags raises struct errors, IndexError, ... on bad bytes
        raise ValidationError(f"{len(data)} bytes are not a CDR {msgtype}: {type(exc).__name__}: {exc}") from None


def time_msg(ns: int) -> Any:
    """``builtin_interfaces/Time`` of ``ns`` nanoseconds since the epoch."""
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return _cls("builtin_interfaces/msg/Time")(sec=sec, nanosec=nsec)


def header(ns: int, frame: str) -> Any:
    return _cls("std_msgs/msg/Header")(stamp=time_msg(ns), frame_id=frame)


def planar_pose_covariance(mean: np.ndarray, cov: np.ndarray) -> tuple[float, np.ndarray, float, float, float]:
    r"""The planar pose of a state ``(x, y[, vx, vy, ...])`` and the ROS 6x6 pose covariance.

    The heading of a constant-velocity state is its direction of motion,
    :math:`\psi = \operatorname{atan2}(v_y, v_x)`, with variance :math:`J \Sigma_v J^T`,
    :math:`J = (-v_y, v_x) / |v|^2` (first order); without a velocity (or standing still,
    :math:`|v|` below 1 mm/s) the heading is 0 with variance :math:`\pi^2` (unknown).
    The 6x6 row-major covariance over ``(x, y, z, roll, pitch, yaw)`` has the ``(x, y)`` block,
    the yaw variance, and 0 for z, roll and pitch (a planar estimate).

    Returns ``(yaw, cov6, speed, speed_var, yaw_var)``.
    """
    C6 = np.zeros((6, 6))
    C6[:2, :2] = cov[:2, :2]
    yaw, yaw_var, speed, speed_var = 0.0, math.pi ** 2, 0.0, 0.0
    if mean.size >= 4:
        vx, vy = float(mean[2]), float(mean[3])
        speed = math.hypot(vx, vy)
        Sv = cov[2:4, 2:4]
        if speed > 1e-3:
            yaw = math.atan2(vy, vx)
            J = np.array([-vy, vx]) / speed ** 2
            yaw_var = float(J @ Sv @ J)
            u = np.array([vx, vy]) / speed
            speed_var = float(u @ Sv @ u)
        C6[:2, 5] = C6[5, :2] = 0.0
    C6[5, 5] = yaw_var
    return yaw, C6, speed, speed_var, yaw_var


def estimate_messages(mean: np.ndarray, cov: np.ndarray, stamp_ns: int, frame: str,
                      child_frame: str) -> tuple[Any, Any]:
    """``(nav_msgs/Odometry, geometry_msgs/PoseWithCovarianceStamped)`` of a planar estimate
    (:func:`planar_pose_covariance`); the odometry's twist is the speed along the heading
    (child frame), its variance in the twist covariance (other entries 0)."""
    mean, cov = np.asarray(mean, dtype=float), np.asarray(cov, dtype=float)
    yaw, C6, speed, speed_var, _ = planar_pose_covariance(mean, cov)
    Point, Quaternion = _cls("geometry_msgs/msg/Point"), _cls("geometry_msgs/msg/Quaternion")
    Pose, PoseCov = _cls("geometry_msgs/msg/Pose"), _cls("geometry_msgs/msg/PoseWithCovariance")
    pose = Pose(position=Point(x=float(mean[0]), y=float(mean[1]), z=0.0),
                orientation=Quaternion(**dict(zip("xyzw", quaternion_of_yaw(yaw)))))
    pwc = PoseCov(pose=pose, covariance=C6.reshape(-1).copy())
    Vector3, Twist = _cls("geometry_msgs/msg/Vector3"), _cls("geometry_msgs/msg/Twist")
    T6 = np.zeros(36)
    T6[0] = speed_var
    twist = _cls("geometry_msgs/msg/TwistWithCovariance")(
        twist=Twist(linear=Vector3(x=speed, y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=0.0)), covariance=T6)
    odom = _cls("nav_msgs/msg/Odometry")(header=header(stamp_ns, frame), child_frame_id=child_frame, pose=pwc,
                                         twist=twist)
    stamped = _cls("geometry_msgs/msg/PoseWithCovarianceStamped")(header=header(stamp_ns, frame), pose=pwc)
    return odom, stamped


def diagnostics(stamp_ns: int, name: str, hardware_id: str, level: str, message: str,
                values: Mapping[str, Any]) -> Any:
    """``diagnostic_msgs/DiagnosticArray`` with one status: ``level`` (ok, warn, error, stale), a
    one-line ``message`` and ``values`` as key/value strings."""
    if level not in DIAGNOSTIC_LEVELS:
        raise ValidationError(f"diagnostic level must be one of {sorted(DIAGNOSTIC_LEVELS)}, got {level!r}")
    KeyValue = _cls("diagnostic_msgs/msg/KeyValue")
    status = _cls("diagnostic_msgs/msg/DiagnosticStatus")(
        level=DIAGNOSTIC_LEVELS[level], name=name, message=message, hardware_id=hardware_id,
        values=[KeyValue(key=str(k), value=str(v)) for k, v in values.items()])
    return _cls("diagnostic_msgs/msg/DiagnosticArray")(header=header(stamp_ns, ""), status=[status])


def make(msgtype: str, **fields: Any) -> Any:
    """A message of ``msgtype`` from its fields (rosbags' dataclass)."""
    return _cls(msgtype)(**fields)
