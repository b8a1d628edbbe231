r"""Front end of an environmental (ceiling) camera that localizes a robot."""
from __future__ import annotations

from typing import Any

from dfusion.estimation.estimate import Estimate
from dfusion.frontends.base import (
    FrontEnd,
    FrontEndStats,
    embed_source,
    position_information,
)
from dfusion.fusion.node import FusionNode
from dfusion.linalg import Array

__all__ = ["EnvCameraFrontEnd"]


class EnvCameraFrontEnd(FrontEnd):
    """An environmental (ceiling) camera localizing the robot (the node's target).

    ``z`` is the pixel of the robot's marker;
    :class:`~dfusion.localization.env_camera.EnvironmentCameraLocalizer` turns it into a
    ground position with covariance and the camera reliability of the switching paper
    (eq. 1-9, :func:`dfusion.reliability.camera_reliability`). Fixes with a reliability below
    ``min_reliability`` are dropped; the others are added as position information
    (:func:`position_information`) and reported to the node as a source named
    ``"<node>/env_camera"`` (for switching policies).
    """

    def __init__(self, localizer: Any, *, min_reliability: float = 0.0) -> None:
        self.localizer = localizer
        self.min_reliability = float(min_reliability)
        self.stats = FrontEndStats()
        self.last: Estimate | None = None

    def process(self, node: FusionNode, t: float, z: Array) -> bool:
        self.stats.processed += 1
        est = self.localizer.estimate() if self.localizer.update(t, z) else None
        self.last = est
        if est is None or est.reliability < self.min_reliability:
            self.stats.rejected += 1
            return False
        n = node.filter.n
        Lam, y = position_information(est.mean[:2], est.cov[:2, :2], n)
        node.add_local_information(t, Lam, y)
        self.stats.contributed += 1
        m, P = node.estimate()
        node.report_source(embed_source(f"{node.name}/env_camera", t, m, P, est.mean[:2],
                                        est.cov[:2, :2], est.reliability))
        return True
