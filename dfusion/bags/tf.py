r"""Static transforms of a bag (``/tf_static``, ``tf2_msgs/TFMessage``), planar.

A robot's recording says where each sensor is mounted on the robot as static transforms
``parent -> child`` (``base_link -> laser``): translation ``(x, y)`` and the yaw of the
rotation (REP 103 frames; a mount tilted out of the plane is folded to its yaw, and
logged). :meth:`StaticTransforms.mount` chains them from a sensor's frame up to the
robot's frame; :func:`compose` puts the sensor's pose in the world:

.. math::

    x_s = x + \cos\theta\, m_x - \sin\theta\, m_y,\quad
    y_s = y + \sin\theta\, m_x + \cos\theta\, m_y,\quad
    \theta_s = \theta + m_\theta

for the robot's pose :math:`(x, y, \theta)` and the mount :math:`(m_x, m_y, m_\theta)`
(the composition of SE(2) poses, R. Smith, M. Self, P. Cheeseman, "Estimating uncertain
spatial relationships in robotics", 1990, the :math:`\oplus` operator).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from dfusion.bags.convert import yaw_of
from dfusion.bags.reader import Bag
from dfusion.errors import ValidationError
from dfusion.geometry import wrap_angle

log = logging.getLogger(__name__)

__all__ = ["StaticTransforms", "compose", "TF_STATIC"]

#: The topic of static transforms.
TF_STATIC = "/tf_static"


def compose(pose: np.ndarray, mount: np.ndarray) -> np.ndarray:
    """``pose`` :math:`\\oplus` ``mount`` (module docstring)."""
    x, y, th = (float(v) for v in pose)
    mx, my, mt = (float(v) for v in mount)
    c, s = math.cos(th), math.sin(th)
    return np.array([x + c * mx - s * my, y + s * mx + c * my, float(wrap_angle(th + mt))])


@dataclass
class StaticTransforms:
    """``child -> (parent, (x, y, yaw))`` of every static transform read."""

    parent: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)

    @classmethod
    def from_bag(cls, bag: Bag, topic: str = TF_STATIC) -> StaticTransforms:
        """The transforms of ``topic`` (none when the bag was read without it)."""
        out = cls()
        for m in bag.messages:
            if m.topic != topic:
                continue
            for tr in m.msg.transforms:
                q, v = tr.transform.rotation, tr.transform.translation
                if abs(float(q.x)) > 1e-6 or abs(float(q.y)) > 1e-6:
                    log.info("%s: %s -> %s is tilted out of the plane: only its yaw is used", topic,
                             tr.header.frame_id, tr.child_frame_id)
                out.parent[str(tr.child_frame_id).lstrip("/")] = (
                    str(tr.header.frame_id).lstrip("/"), np.array([float(v.x), float(v.y), yaw_of(q)]))
        return out

    def mount(self, frame: str, base: str) -> np.ndarray | None:
        """The pose of ``frame`` in ``base`` (chained up the tree), identity when they are
        the same frame, ``None`` when ``frame`` is not below ``base`` in the tree."""
        frame, base = frame.lstrip("/"), base.lstrip("/")
        acc = np.zeros(3)
        seen = set()
        while frame != base:
            if frame not in self.parent or frame in seen:
                return None
            seen.add(frame)
            parent, t = self.parent[frame]
            acc = compose(t, acc)
            frame = parent
        return acc

    def require(self, frame: str, base: str, what: str) -> np.ndarray:
        """:meth:`mount`, or a one-line error naming the frames."""
        m = self.mount(frame, base)
        if m is None:
            raise ValidationError(f"{what}: no static transform from frame {frame!r} to {base!r} in {TF_STATIC} "
                                  f"(frames: {sorted(self.parent)})")
        return m
