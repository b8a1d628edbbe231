r"""ROS messages to dfusion's plain measurement types.

One function per supported message type (ROS 1 and ROS 2 share the field names); each
takes the message and its time ``t`` (seconds, from :class:`~dfusion.bags.Bag`) and
returns a plain dataclass:

===============================================  =========================================
message type                                     result
===============================================  =========================================
``nav_msgs/Odometry``                            :class:`PoseReading` (pose, yaw, twist,
                                                 covariance of ``(x, y, yaw)``)
``geometry_msgs/PoseStamped``, ``Pose``          :class:`PoseReading`
``geometry_msgs/Twist``, ``TwistStamped``        :class:`Velocity` (``v``: linear x,
                                                 ``w``: angular z)
``sensor_msgs/LaserScan``                        :class:`ScanReading`
``geometry_msgs/PoseWithCovarianceStamped``      :class:`PositionFix` (``x, y`` and their
                                                 2x2 covariance)
``geometry_msgs/PointStamped``                   :class:`PositionFix` (no covariance)
``sensor_msgs/Range``                            :class:`RangeReading`
``geometry_msgs/PoseArray``                      :class:`Detections` (positions, no
                                                 covariance)
``vision_msgs/Detection3DArray``                 :class:`Detections` (positions; the
                                                 covariance of the best hypothesis's pose)
``vision_msgs/Detection2DArray``                 :class:`Detections` of pixels (the
                                                 bottom centre of each box)
===============================================  =========================================

**Detection arrays.** A ``PoseArray`` gives the ``(x, y)`` of each pose. A ``Detection3D``
gives the position of its best hypothesis (largest ``score``) with that pose's ``(x, y)``
covariance when the hypothesis states one (:func:`known_covariance`), else the centre of its
``bbox`` without a covariance. A ``Detection2D`` gives the pixel ``(u, v)`` of the middle of
its box's lower edge, ``center + R(theta) (0, size_y / 2)`` (image ``v`` points down: where a
standing person touches the ground); pixels become ground positions only through a camera
model (``docs/ros.md``). Heights (``z``) are dropped: dfusion tracks in the plane.

Where a **pose** is read (a scan's pose, ground truth), :func:`read_pose` takes
``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``, ``Pose`` and
``PoseWithCovarianceStamped`` (with its ``(x, y, yaw)`` covariance) alike.

Any other type (a vendor's detection array, ...) is mapped by a **user function**
``convert(msg, t) -> measurement`` passed where a replay asks for converters
(``docs/ros.md`` has an example). The yaw of a quaternion is
``atan2(2 (w z + x y), 1 - 2 (y^2 + z^2))`` (the ZYX Euler angle; REP 103 frames).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from dfusion.errors import ValidationError

__all__ = [
    "PoseReading",
    "Velocity",
    "ScanReading",
    "PositionFix",
    "RangeReading",
    "Detections",
    "DETECTION_TYPES",
    "known_covariance",
    "Converter",
    "CONVERTERS",
    "convert",
    "standard_z",
    "POSITION_READINGS",
    "read_pose",
    "POSE_TYPES",
    "yaw_of",
    "quaternion_of_yaw",
]

#: A user function: the message and its time (s) -> a measurement.
Converter = Callable[[Any, float], Any]


@dataclass(frozen=True)
class PoseReading:
    """A planar pose ``(x, y, yaw)``; ``cov`` its 3x3 covariance when the message has one,
    ``twist`` the body-frame ``(v, w)`` of an odometry message."""

    t: float
    pose: np.ndarray
    cov: np.ndarray | None = None
    twist: np.ndarray | None = None
    frame: str = ""


@dataclass(frozen=True)
class Velocity:
    """Body-frame forward speed ``v`` (m/s) and turn rate ``w`` (rad/s)."""

    t: float
    v: float
    w: float


@dataclass(frozen=True)
class ScanReading:
    """A laser scan: ranges (m, float64), beam angles (rad, from ``angle_min`` in steps of
    ``angle_increment``) and the valid beams (finite, inside ``[range_min, range_max)``)."""

    t: float
    ranges: np.ndarray
    angles: np.ndarray
    range_min: float
    range_max: float
    valid: np.ndarray
    frame: str = ""


@dataclass(frozen=True)
class PositionFix:
    """A position ``z = (x, y)`` with covariance ``R`` (``None``: the node's own)."""

    t: float
    z: np.ndarray
    R: np.ndarray | None = None
    frame: str = ""


@dataclass(frozen=True)
class RangeReading:
    """One range (m) of a ``sensor_msgs/Range`` sensor, with its valid interval."""

    t: float
    r: float
    min_range: float
    max_range: float
    frame: str = ""

    @property
    def valid(self) -> bool:
        return math.isfinite(self.r) and self.min_range <= self.r <= self.max_range


@dataclass(frozen=True)
class Detections:
    """What one detection array holds: ``points`` (k, 2), positions in ``frame`` (or image
    pixels ``(u, v)`` when ``pixels``); ``covs`` (k, 2, 2) the covariance each detection states
    (NaN where it states none; ``None``: none does); ``ids`` the detections' ids (may be empty)."""

    t: float
    points: np.ndarray
    covs: np.ndarray | None = None
    frame: str = ""
    pixels: bool = False
    ids: tuple[str, ...] = ()


def known_covariance(C: Any) -> np.ndarray | None:
    """The ``(x, y)`` block of a covariance when it states one (finite, symmetric, positive
    definite), else ``None``: ROS's "unknown" (all zeros, or ``-1`` first) states none."""
    if C is None:
        return None
    C = np.asarray(C, dtype=float)
    if C.ndim == 1:
        n = int(round(math.sqrt(C.size)))
        if n * n != C.size or n < 2:
            return None
        C = C.reshape(n, n)
    C = C[:2, :2]
    if not np.all(np.isfinite(C)) or C[0, 0] <= 0 or not np.allclose(C, C.T, rtol=1e-9, atol=1e-12):
        return None
    try:
        np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return None
    return 0.5 * (C + C.T)


def yaw_of(q: Any) -> float:
    """Yaw (rad) of a quaternion with fields ``x, y, z, w``."""
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quaternion_of_yaw(yaw: float) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a rotation by ``yaw`` about z."""
    return 0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)


def _frame(msg: Any) -> str:
    h = getattr(msg, "header", None)
    return str(getattr(h, "frame_id", "")) if h is not None else ""


def _pose(p: Any) -> np.ndarray:
    return np.array([float(p.position.x), float(p.position.y), yaw_of(p.orientation)])


def _cov3(c: Any) -> np.ndarray:
    """``(x, y, yaw)`` block of a row-major 6x6 covariance (x, y, z, roll, pitch, yaw)."""
    C = np.asarray(c, dtype=float).reshape(6, 6)
    k = [0, 1, 5]
    return C[np.ix_(k, k)]


def odometry(msg: Any, t: float) -> PoseReading:
    """``nav_msgs/Odometry``: pose, ``(x, y, yaw)`` covariance, twist ``(v, w)``."""
    tw = msg.twist.twist
    return PoseReading(t, _pose(msg.pose.pose), _cov3(msg.pose.covariance),
                       np.array([float(tw.linear.x), float(tw.angular.z)]), _frame(msg))


def pose_stamped(msg: Any, t: float) -> PoseReading:
    """``geometry_msgs/PoseStamped`` (or a bare ``Pose``)."""
    return PoseReading(t, _pose(getattr(msg, "pose", msg)), frame=_frame(msg))


def twist(msg: Any, t: float) -> Velocity:
    """``geometry_msgs/Twist`` or ``TwistStamped``."""
    tw = getattr(msg, "twist", msg)
    return Velocity(t, float(tw.linear.x), float(tw.angular.z))


def laser_scan(msg: Any, t: float) -> ScanReading:
    """``sensor_msgs/LaserScan``. ROS stores ranges as float32: they are widened to float64
    unchanged. Beam ``i`` has the angle ``angle_min + i * angle_increment``."""
    r = np.asarray(msg.ranges, dtype=np.float64)
    ang = float(msg.angle_min) + np.arange(r.size) * float(msg.angle_increment)
    rmin, rmax = float(msg.range_min), float(msg.range_max)
    valid = np.isfinite(r) & (r > 0) & (r >= rmin) & (r < rmax - 1e-6)
    return ScanReading(t, r, ang, rmin, rmax, valid, _frame(msg))


def pose_with_covariance(msg: Any, t: float) -> PositionFix:
    """``geometry_msgs/PoseWithCovarianceStamped``: ``(x, y)`` and its 2x2 covariance."""
    p = msg.pose.pose.position
    R = _cov3(msg.pose.covariance)[:2, :2]
    return PositionFix(t, np.array([float(p.x), float(p.y)]), R, _frame(msg))


def pose_with_covariance_pose(msg: Any, t: float) -> PoseReading:
    """``geometry_msgs/PoseWithCovarianceStamped`` as a pose: ``(x, y, yaw)`` and its 3x3
    covariance."""
    return PoseReading(t, _pose(msg.pose.pose), _cov3(msg.pose.covariance), frame=_frame(msg))


#: Message types that hold a planar pose, and their converters (:func:`read_pose`).
POSE_TYPES: dict[str, Converter] = {
    "nav_msgs/msg/Odometry": odometry,
    "geometry_msgs/msg/PoseStamped": pose_stamped,
    "geometry_msgs/msg/Pose": pose_stamped,
    "geometry_msgs/msg/PoseWithCovarianceStamped": pose_with_covariance_pose,
}


def read_pose(msgtype: str, msg: Any, t: float, topic: str = "") -> PoseReading:
    """The pose of a message of one of :data:`POSE_TYPES`; any other type is refused in one
    line (a ``PointStamped`` has no heading)."""
    fn = POSE_TYPES.get(msgtype)
    if fn is None:
        raise ValidationError(f"{topic or 'pose topic'}: a {msgtype} holds no pose (pose types: {sorted(POSE_TYPES)})")
    return fn(msg, t)


def point_stamped(msg: Any, t: float) -> PositionFix:
    """``geometry_msgs/PointStamped``: ``(x, y)``, no covariance."""
    return PositionFix(t, np.array([float(msg.point.x), float(msg.point.y)]), None, _frame(msg))


def range_msg(msg: Any, t: float) -> RangeReading:
    """``sensor_msgs/Range``."""
    return RangeReading(t, float(msg.range), float(msg.min_range), float(msg.max_range), _frame(msg))


def pose_array(msg: Any, t: float) -> Detections:
    """``geometry_msgs/PoseArray``: the ``(x, y)`` of every pose, no covariance."""
    pts = np.array([[float(p.position.x), float(p.position.y)] for p in msg.poses], dtype=float).reshape(-1, 2)
    return Detections(t, pts, None, _frame(msg))


def _best_hypothesis(results: Any) -> Any | None:
    """The hypothesis of largest score (ROS 2 ``hypothesis.score``, ROS 1 ``score``), or ``None``."""
    best, score = None, -math.inf
    for r in results:
        s = float(getattr(getattr(r, "hypothesis", r), "score", 0.0))
        if best is None or s > score:
            best, score = r, s
    return best


def detection3d_array(msg: Any, t: float) -> Detections:
    """``vision_msgs/Detection3DArray`` (module docstring)."""
    k = len(msg.detections)
    pts = np.zeros((k, 2))
    covs = np.full((k, 2, 2), np.nan)
    ids = []
    for i, d in enumerate(msg.detections):
        best = _best_hypothesis(d.results)
        C = known_covariance(best.pose.covariance) if best is not None else None
        p = best.pose.pose.position if C is not None else d.bbox.center.position
        pts[i] = float(p.x), float(p.y)
        if C is not None:
            covs[i] = C
        ids.append(str(getattr(d, "id", "") or getattr(d, "tracking_id", "") or ""))
    return Detections(t, pts, covs if np.isfinite(covs).any() else None, _frame(msg), False, tuple(ids))


def detection2d_array(msg: Any, t: float) -> Detections:
    """``vision_msgs/Detection2DArray``: the bottom centre of every box, in pixels (module docstring)."""
    pts = np.zeros((len(msg.detections), 2))
    ids = []
    for i, d in enumerate(msg.detections):
        c = d.bbox.center
        pos = getattr(c, "position", c)            # vision_msgs 4.x: center.position; before: center.x
        th = float(c.theta)
        half = 0.5 * float(d.bbox.size_y)
        pts[i] = float(pos.x) - math.sin(th) * half, float(pos.y) + math.cos(th) * half
        ids.append(str(getattr(d, "id", "") or ""))
    return Detections(t, pts, None, _frame(msg), True, tuple(ids))


#: Detection array types and their converters (each gives :class:`Detections`).
DETECTION_TYPES: dict[str, Converter] = {
    "geometry_msgs/msg/PoseArray": pose_array,
    "vision_msgs/msg/Detection3DArray": detection3d_array,
    "vision_msgs/msg/Detection2DArray": detection2d_array,
}


#: Message type -> converter, for the standard types (ROS 2 names; ROS 1 bags read by
#: rosbags use the same names).
CONVERTERS: dict[str, Converter] = {
    "nav_msgs/msg/Odometry": odometry,
    "geometry_msgs/msg/PoseStamped": pose_stamped,
    "geometry_msgs/msg/Pose": pose_stamped,
    "geometry_msgs/msg/Twist": twist,
    "geometry_msgs/msg/TwistStamped": twist,
    "sensor_msgs/msg/LaserScan": laser_scan,
    "geometry_msgs/msg/PoseWithCovarianceStamped": pose_with_covariance,
    "geometry_msgs/msg/PointStamped": point_stamped,
    "sensor_msgs/msg/Range": range_msg,
    **DETECTION_TYPES,
}


def convert(msgtype: str, msg: Any, t: float, converters: dict[str, Converter] | None = None) -> Any:
    """Convert one message by its type: ``converters`` (user functions) first, then
    :data:`CONVERTERS`."""
    fn = (converters or {}).get(msgtype) or CONVERTERS.get(msgtype)
    if fn is None:
        raise ValidationError(f"no converter for message type {msgtype!r}: pass a function msg, t -> measurement "
                              f"(standard types: {sorted(CONVERTERS)})")
    return fn(msg, t)


#: Converted readings whose ``z`` is a position in the message's frame (:func:`standard_z`): a node in
#: another frame expresses it in its own through the static transforms (:mod:`dfusion.bags.tf`).
POSITION_READINGS = (PoseReading, PositionFix)


def standard_z(reading: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """The measurement ``z`` of a converted standard message and the covariance of ``z`` the message
    states (``None``: none): the one mapping ``dfusion replay`` and a live node's inputs share.

    =========================  ===================  ==================================
    reading                    ``z``                covariance
    =========================  ===================  ==================================
    :class:`PositionFix`       ``(x, y)``           its ``R``
    :class:`PoseReading`       ``(x, y)`` of pose   the ``(x, y)`` block of its ``cov``
    :class:`RangeReading`      ``(r,)``             none
    :class:`ScanReading`       the ranges           none
    =========================  ===================  ==================================

    Raises
    ------
    ValidationError
        For any other reading (a :class:`Velocity`, a user type): no measurement of a node.
    """
    if isinstance(reading, PositionFix):
        return np.asarray(reading.z, float), reading.R
    if isinstance(reading, PoseReading):
        return np.asarray(reading.pose[:2], float), (reading.cov[:2, :2] if reading.cov is not None else None)
    if isinstance(reading, RangeReading):
        return np.array([float(reading.r)]), None
    if isinstance(reading, ScanReading):
        return np.asarray(reading.ranges, float), None
    if isinstance(reading, Detections):
        raise ValidationError("a detection array is many targets' detections: track it with dfusion replay BAG "
                              "--detections TOPIC=SENSOR (docs/ros.md), or map the topic to a node with a function "
                              "msg, t -> z")
    raise ValidationError(f"a {type(reading).__name__} is no measurement of a scenario node: map the topic with a "
                          f"function msg, t -> z")
