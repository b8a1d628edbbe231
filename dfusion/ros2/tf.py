r"""Static transforms (``/tf_static``, ``tf2_msgs/TFMessage``) in the plane.

Each ``geometry_msgs/TransformStamped`` gives the pose of ``child_frame_id`` in
``header.frame_id``; only its planar part is kept, ``(x, y, yaw)`` with the yaw of its rotation
(:func:`dfusion.bags.convert.yaw_of`). :meth:`StaticTransforms.lookup` chains transforms along the
path between two frames in the tree of frames (either direction), with SE(2) composition
:func:`dfusion.geometry.se2_compose` and :func:`~dfusion.geometry.se2_inverse`.

A measurement in frame ``s`` is expressed in the node's frame ``f`` by ``T = lookup(f, s)``: a pose
``p`` becomes ``T (+) p``, a position ``z`` becomes ``R(yaw_T) z + t_T``, and a covariance ``C``
becomes ``R C R^T`` (rotation only; the transform is exact, static tf carries no uncertainty).
"""
from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from dfusion.bags.convert import yaw_of
from dfusion.errors import ValidationError
from dfusion.geometry import se2_compose, se2_inverse

__all__ = ["StaticTransforms", "rotate_covariance"]


def rotate_covariance(C: np.ndarray, yaw: float) -> np.ndarray:
    """``R C R^T`` of a 2x2 (or larger, the first two axes) covariance, ``R`` the rotation by ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.eye(C.shape[0])
    R[:2, :2] = [[c, -s], [s, c]]
    out = R @ C @ R.T
    return 0.5 * (out + out.T)


class StaticTransforms:
    """The planar static transforms seen so far (a tree of frames)."""

    def __init__(self) -> None:
        #: child frame -> (parent frame, pose of the child in the parent)
        self.parents: dict[str, tuple[str, np.ndarray]] = {}

    def add(self, parent: str, child: str, pose: np.ndarray) -> None:
        """``child``'s pose ``(x, y, yaw)`` in ``parent`` (a newer one replaces the older)."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if not parent or not child or parent == child:
            raise ValidationError(f"a static transform needs two different frames, got {parent!r} -> {child!r}")
        self.parents[child] = (parent, np.asarray(pose, dtype=float).copy())

    def add_message(self, msg: Any) -> int:
        """Every transform of a ``tf2_msgs/TFMessage``; returns how many."""
        for tr in msg.transforms:
            t = tr.transform.translation
            self.add(tr.header.frame_id, tr.child_frame_id,
                     np.array([float(t.x), float(t.y), yaw_of(tr.transform.rotation)]))
        return len(msg.transforms)

    def _neighbours(self) -> dict[str, list[tuple[str, np.ndarray]]]:
        """Frame -> [(frame next to it, pose of that frame in this one)]."""
        out: dict[str, list[tuple[str, np.ndarray]]] = {}
        for child, (parent, pose) in self.parents.items():
            out.setdefault(parent, []).append((child, pose))
            out.setdefault(child, []).append((parent, se2_inverse(pose)))
        return out

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        """The pose of frame ``source`` in frame ``target`` (``None``: not connected)."""
        target, source = target.lstrip("/"), source.lstrip("/")
        if target == source:
            return np.zeros(3)
        nb = self._neighbours()
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
