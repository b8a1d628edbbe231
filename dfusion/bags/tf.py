r"""Static transforms (``/tf_static``, ``tf2_msgs/TFMessage``) in the plane: the one home of tf
for bags (:mod:`dfusion.bags.datasets`) and live ROS 2 inputs (:mod:`dfusion.ros2.inputs`).

Each ``geometry_msgs/TransformStamped`` gives the pose of ``child_frame_id`` in
``header.frame_id`` (REP 103 frames); only its planar part is kept, ``(x, y, yaw)`` with the yaw
of its rotation (:func:`dfusion.bags.convert.yaw_of`; a transform tilted out of the plane is
folded to its yaw, and logged). :meth:`StaticTransforms.lookup` chains transforms along the path
between two frames of the tree of frames, in either direction, with the composition of SE(2)
poses (:func:`dfusion.geometry.se2_compose`, the :math:`\oplus` operator of R. Smith, M. Self,
P. Cheeseman, "Estimating uncertain spatial relationships in robotics", 1990):

.. math::

    x_s = x + \cos\theta\, m_x - \sin\theta\, m_y,\quad
    y_s = y + \sin\theta\, m_x + \cos\theta\, m_y,\quad
    \theta_s = \theta + m_\theta

for a robot's pose :math:`(x, y, \theta)` and a sensor's mount :math:`(m_x, m_y, m_\theta)`.

A measurement in frame ``s`` is expressed in frame ``f`` by ``T = lookup(f, s)``: a pose ``p``
becomes ``T (+) p``, a position ``z`` becomes ``R(yaw_T) z + t_T``, and a covariance ``C``
becomes ``R C R^T`` (:func:`rotate_covariance`; static tf carries no uncertainty).
"""
from __future__ import annotations

import logging
import math
from collections import deque
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np

from dfusion.bags.convert import yaw_of
from dfusion.bags.reader import Bag
from dfusion.errors import ValidationError
from dfusion.geometry import se2_compose, se2_inverse

log = logging.getLogger(__name__)

__all__ = ["StaticTransforms", "rotate_covariance", "TF_STATIC"]

#: The topic of static transforms.
TF_STATIC = "/tf_static"


def rotate_covariance(C: np.ndarray, yaw: float) -> np.ndarray:
    """``R C R^T`` of a 2x2 (or larger, the first two axes) covariance, ``R`` the rotation by ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.eye(C.shape[0])
    R[:2, :2] = [[c, -s], [s, c]]
    out = R @ C @ R.T
    return 0.5 * (out + out.T)


class StaticTransforms:
    """The planar static transforms seen so far (a tree of frames).

    The graph of frames :meth:`lookup` walks is built once and kept until :meth:`add` changes
    a transform (a live input looks up the same frames for every message).
    """

    def __init__(self) -> None:
        self._parents: dict[str, tuple[str, np.ndarray]] = {}
        self._graph: dict[str, list[tuple[str, np.ndarray]]] | None = None

    @property
    def parents(self) -> Mapping[str, tuple[str, np.ndarray]]:
        """Child frame -> (parent frame, pose of the child in the parent); read-only (:meth:`add`)."""
        return MappingProxyType(self._parents)

    @classmethod
    def from_bag(cls, bag: Bag, topic: str = TF_STATIC) -> StaticTransforms:
        """The transforms of ``topic`` in a bag (none when the bag was read without it)."""
        out = cls()
        for m in bag.messages:
            if m.topic == topic:
                out.add_message(m.msg, topic)
        return out

    def add(self, parent: str, child: str, pose: np.ndarray) -> None:
        """``child``'s pose ``(x, y, yaw)`` in ``parent`` (a newer one replaces the older)."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if not parent or not child or parent == child:
            raise ValidationError(f"a static transform needs two different frames, got {parent!r} -> {child!r}")
        self._parents[child] = (parent, np.asarray(pose, dtype=float).copy())
        self._graph = None

    def add_message(self, msg: Any, topic: str = TF_STATIC) -> int:
        """Every transform of a ``tf2_msgs/TFMessage``; returns how many."""
        for tr in msg.transforms:
            q, t = tr.transform.rotation, tr.transform.translation
            if abs(float(q.x)) > 1e-6 or abs(float(q.y)) > 1e-6:
                log.info("%s: %s -> %s is tilted out of the plane: only its yaw is used", topic,
                         tr.header.frame_id, tr.child_frame_id)
            self.add(tr.header.frame_id, tr.child_frame_id, np.array([float(t.x), float(t.y), yaw_of(q)]))
        return len(msg.transforms)

    def _neighbours(self) -> dict[str, list[tuple[str, np.ndarray]]]:
        """Frame -> [(frame next to it, pose of that frame in this one)]."""
        out: dict[str, list[tuple[str, np.ndarray]]] = {}
        for child, (parent, pose) in self._parents.items():
            out.setdefault(parent, []).append((child, pose))
            out.setdefault(child, []).append((parent, se2_inverse(pose)))
        return out

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        """The pose of frame ``source`` in frame ``target`` (``None``: not connected)."""
        target, source = target.lstrip("/"), source.lstrip("/")
        if target == source:
            return np.zeros(3)
        if self._graph is None:
            self._graph = self._neighbours()
        nb = self._graph
        seen = {target: np.zeros(3)}
        todo = deque([target])
        while todo:
            f = todo.popleft()
            for g, pose in nb.get(f, ()):
                if g not in seen:
                    seen[g] = se2_compose(seen[f], pose)
                    if g == source:
                        return seen[g]
                    todo.append(g)
        return None

    def require(self, frame: str, base: str, what: str) -> np.ndarray:
        """The pose of ``frame`` in ``base`` (:meth:`lookup`), or a one-line error naming the frames."""
        m = self.lookup(base, frame)
        if m is None:
            raise ValidationError(f"{what}: no static transform from frame {frame!r} to {base!r} in {TF_STATIC} "
                                  f"(frames: {sorted(self._parents)})")
        return m
