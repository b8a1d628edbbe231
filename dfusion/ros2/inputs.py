r"""ROS 2 input messages to a node's measurements: ``z``, the message's own covariance, its frame.

The message is first turned into a plain reading by the standard conversion of its type
(:mod:`dfusion.bags.convert`, the one ``dfusion replay`` uses), then into what the node's sensor
kind takes:

=====================================================  ============================  ===============
message type                                           ``z``                         covariance
=====================================================  ============================  ===============
``nav_msgs/Odometry``                                  ``(x, y)`` of the pose        its pose
                                                                                     covariance's
                                                                                     ``(x, y)`` block
``geometry_msgs/PoseWithCovarianceStamped``            ``(x, y)``                    same
``geometry_msgs/PoseStamped``, ``PointStamped``        ``(x, y)``                    none
``sensor_msgs/Range``                                  ``(range,)``                  none
``sensor_msgs/LaserScan``                              the ranges                    none
=====================================================  ============================  ===============

A covariance is used only when it is a finite, symmetric positive definite 2x2 block: ROS's
convention for "unknown" (all zeros, or ``-1`` in the first entry) leaves the node's own noise
(the ``std`` of its scenario table) in place. Poses and positions in another frame than the node's
are expressed in the node's frame with the static transforms (:mod:`dfusion.bags.tf`); a message
whose frame is not connected to the node's is refused (counted). Scans and ranges are taken as
they are (the sensor's mounting is the node's model's business).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from dfusion.bags.convert import POSITION_READINGS, convert, known_covariance, standard_z
from dfusion.bags.tf import StaticTransforms, rotate_covariance
from dfusion.errors import ValidationError
from dfusion.geometry import transform_points

__all__ = ["Reading", "SUPPORTED_INPUTS", "Z_SIZE", "reading_of"]


#: The size of ``z`` each input type gives (``None``: the message says, e.g. a scan's beams).
Z_SIZE: dict[str, int | None] = {
    "nav_msgs/msg/Odometry": 2,
    "geometry_msgs/msg/PoseWithCovarianceStamped": 2,
    "geometry_msgs/msg/PoseStamped": 2,
    "geometry_msgs/msg/PointStamped": 2,
    "sensor_msgs/msg/Range": 1,
    "sensor_msgs/msg/LaserScan": None,
}


#: The input message types a live node takes without a user converter.
SUPPORTED_INPUTS = tuple(Z_SIZE)


@dataclass(frozen=True)
class Reading:
    """One input message as a measurement: ``z`` in the node's frame, ``R`` its covariance from
    the message (``None``: the node's own), ``frame`` the message's frame."""

    z: np.ndarray
    R: np.ndarray | None
    frame: str


def reading_of(msgtype: str, msg: Any, frame: str, tf: StaticTransforms) -> Reading:
    """``msg`` of ``msgtype`` as a :class:`Reading` in ``frame`` (see the module docstring).

    Raises
    ------
    ValidationError
        For a message type that is not supported, or a frame not connected to ``frame``.
    """
    if msgtype not in SUPPORTED_INPUTS:
        raise ValidationError(f"input type {msgtype!r} is not supported (supported: {', '.join(SUPPORTED_INPUTS)})")
    r = convert(msgtype, msg, 0.0)
    z, C = standard_z(r)
    if not isinstance(r, POSITION_READINGS):   # ranges and scans: as they are
        return Reading(z, None, r.frame)
    src = r.frame.lstrip("/") or frame
    T = tf.lookup(frame, src)
    if T is None:
        raise ValidationError(f"frame {src!r} of a {msgtype} is not connected to {frame!r} by /tf_static")
    z = transform_points(np.asarray(z, dtype=float)[None], T)[0]
    R = known_covariance(C)
    return Reading(z, rotate_covariance(R, float(T[2])) if R is not None else None, src)
