r"""Plane geometry shared by every layer: angles, SE(2) poses, point transforms.

Poses are arrays ``(..., 3)`` of ``(x, y, theta)`` (metres, radians), the usual
planar-robot convention (Thrun, Burgard & Fox, *Probabilistic Robotics*, 2005,
sec. 5.2). The composition ``a (+) b`` maps a pose ``b`` given in the frame of
``a`` into the frame ``a`` is given in::

    a (+) b = (x_a + cos(th_a) x_b - sin(th_a) y_b,
               y_a + sin(th_a) x_b + cos(th_a) y_b,
               wrap(th_a + th_b))
    a^-1    = (-cos(th_a) x_a - sin(th_a) y_a,  sin(th_a) x_a - cos(th_a) y_a,  wrap(-th_a))
    between(a, b) = a^-1 (+) b          (pose b seen from pose a)

Angles are wrapped to ``[-pi, pi)``.

:class:`WaypointPath` is a moving node's path: straight segments between waypoints at a
constant speed (a robot of a scenario, ``docs/scenarios.md``).
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import ValidationError
from dfusion.linalg import Array

__all__ = [
    "wrap_angle",
    "rotation",
    "se2_compose",
    "se2_inverse",
    "se2_between",
    "transform_points",
    "heading_of",
    "WaypointPath",
]


def wrap_angle(a):
    """Wrap angles to ``[-pi, pi)`` (a float for a float, an array otherwise)."""
    if type(a) is float:   # the scalar case of hot loops, without numpy's overhead
        return (a + math.pi) % (2.0 * math.pi) - math.pi
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def rotation(theta: float) -> Array:
    """The 2 x 2 rotation matrix ``R(theta) = [[cos, -sin], [sin, cos]]``."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


def transform_points(points: ArrayLike, pose: ArrayLike) -> Array:
    """``R(theta) p + (x, y)`` for every row ``p`` of ``points`` (``(N, 2)``)."""
    p = np.asarray(points, dtype=float)
    x, y, th = np.asarray(pose, dtype=float).reshape(3)
    c, s = math.cos(th), math.sin(th)
    out = p @ np.array([[c, s], [-s, c]])
    out += (x, y)
    return out


def se2_compose(a: ArrayLike, b: ArrayLike) -> Array:
    """``a (+) b``: pose ``b`` expressed in frame ``a``, mapped to the frame of ``a``."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack(
        [
            a[..., 0] + c * b[..., 0] - s * b[..., 1],
            a[..., 1] + s * b[..., 0] + c * b[..., 1],
            wrap_angle(a[..., 2] + b[..., 2]),
        ],
        axis=-1,
    )


def se2_inverse(a: ArrayLike) -> Array:
    """``a^-1`` such that ``a (+) a^-1 = 0``."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack(
        [-c * a[..., 0] - s * a[..., 1], s * a[..., 0] - c * a[..., 1], wrap_angle(-a[..., 2])],
        axis=-1,
    )


def se2_between(a: ArrayLike, b: ArrayLike) -> Array:
    """``a^-1 (+) b``: pose ``b`` in the frame of pose ``a``."""
    return se2_compose(se2_inverse(a), b)


def heading_of(x: Array, min_speed: float = 1e-9) -> float:
    """Direction of motion ``atan2(vy, vx)`` of a state ``(x, y, vx, vy)`` (0 when at rest)."""
    vx, vy = float(x[2]), float(x[3])
    return math.atan2(vy, vx) if vx * vx + vy * vy > min_speed * min_speed else 0.0




class WaypointPath:
    """Straight segments between waypoints, driven at a constant speed.

    Parameters
    ----------
    points : (k, 2) array
        Waypoints (m), ``k >= 2``, consecutive ones distinct.
    speed : float
        Metres per second, ``> 0``.
    start : float
        Time (s) the motion starts; before it the node waits at the first waypoint.
    loop : bool
        After the last waypoint go on to the first one and around again; otherwise stop at
        the last one.

    The position at ``t`` is at arc length ``s = speed (t - start)`` along the polyline
    (modulo its closed length when looping); the heading is that of the current segment.
    """

    def __init__(self, points: ArrayLike, speed: float, start: float = 0.0, loop: bool = False) -> None:
        pts = np.asarray(points, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 2 or not np.all(np.isfinite(pts)):
            raise ValidationError(f"path must be a list of at least two [x, y] waypoints, got {points!r}")
        if loop:
            pts = np.vstack([pts, pts[:1]])
        seg = np.diff(pts, axis=0)
        lengths = np.hypot(seg[:, 0], seg[:, 1])
        if np.any(lengths <= 0):
            raise ValidationError("path: two consecutive waypoints coincide")
        if not (isinstance(speed, (int, float)) and not isinstance(speed, bool) and math.isfinite(speed)
                and speed > 0):
            raise ValidationError(f"speed must be a positive number (m/s), got {speed!r}")
        if not (isinstance(start, (int, float)) and math.isfinite(start)):
            raise ValidationError(f"start must be a finite time, got {start!r}")
        self.points, self.speed, self.start, self.loop = pts, float(speed), float(start), bool(loop)
        self._seg, self._cum = seg, np.concatenate([[0.0], np.cumsum(lengths)])

    @property
    def length(self) -> float:
        """Length of the polyline (m), closed when looping."""
        return float(self._cum[-1])

    def _at(self, t: float) -> tuple[int, float]:
        s = max(0.0, self.speed * (float(t) - self.start))
        s = s % self.length if self.loop else min(s, self.length)
        i = min(int(np.searchsorted(self._cum, s, side="right")) - 1, len(self._seg) - 1)
        return i, (s - self._cum[i]) / (self._cum[i + 1] - self._cum[i])

    def position(self, t: float) -> Array:
        """``(x, y)`` at time ``t``."""
        i, u = self._at(t)
        return self.points[i] + u * self._seg[i]

    def heading(self, t: float) -> float:
        """Heading (rad) of the segment driven at ``t``."""
        i, _ = self._at(t)
        return math.atan2(self._seg[i, 1], self._seg[i, 0])

    def pose(self, t: float) -> Array:
        """``(x, y, theta)`` at time ``t``."""
        x, y = self.position(t)
        return np.array([x, y, self.heading(t)])
