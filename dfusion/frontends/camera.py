r"""Front end of a calibrated camera detecting the target in its image.

A camera node fuses pixel detections ``z = (u, v)`` of the target's ground point
with the EIF (:class:`~dfusion.models.PinholeCamera`: ``h``, ``H``,
``R = pixel_std^2 I``). The simulated world produces a true detection only
when the target is in the camera's view (``in_view``), with probability
``detection``, plus ``false_detection_rate`` false detections per frame on
average, uniformly in the image (:mod:`dfusion.sim.world`).

**Gate** (:class:`CameraFrontEnd`). Before a detection is fused, its
Mahalanobis distance to the node's prediction at the detection's time is
tested (Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to
Tracking and Navigation*, 2001, sec. 2.4.3 and 5.4)::

    (mu, P) = node.estimate(t)                   t in the window (a state, or between two)
              newest state predicted to t        t newer than the newest state
    nu = z - h(mu),   S = H(mu) P H(mu)^T + R,   d^2 = nu^T S^-1 nu
    accept  iff  d^2 <= chi2_2^-1(gate) = -2 ln(1 - gate)

(the chi-square quantile with 2 degrees of freedom in closed form; ``gate =
0.99`` gives 9.21). Rejected detections are counted (``stats.gated``) and not
fused; a prediction behind the camera cannot be projected and rejects the
detection too (``stats.unprojectable``). ``gate = 1`` turns the gate off.

**Reliability.** After each fused detection the front end reports a source
``"camera"`` to the node (:meth:`FusionNode.report_source`): the node's newest
estimate with the camera reliability of the switching paper (eq. 1-9,
:func:`dfusion.reliability.camera_reliability_at`) at its position, for
switching policies; :meth:`CameraFrontEnd.reliability` gives it for the
current estimate at any time.

The scenario kind ``camera`` (:mod:`dfusion.scenario.camera_kind`) builds this front
end from a node table; ``robot_camera`` builds :class:`MountedCameraFrontEnd`, the same for
a camera on a robot that moves (:class:`~dfusion.models.camera.MountedCamera`: the camera
at the detection's time).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dfusion.errors import ValidationError
from dfusion.estimation.estimate import Estimate
from dfusion.frontends.base import FrontEnd, FrontEndStats
from dfusion.fusion.node import FusionNode
from dfusion.linalg import Array
from dfusion.models.camera import MountedCamera, PinholeCamera
from dfusion.reliability import camera_reliability_at

__all__ = ["CameraFrontEnd", "MountedCameraFrontEnd", "CameraStats", "gate_threshold"]


def gate_threshold(gate: float, dof: int = 2) -> float:
    """Chi-square quantile of probability ``gate``: ``-2 ln(1 - gate)`` for 2 degrees of freedom.

    ``gate = 1`` gives ``inf`` (no gate). Other ``dof`` use :func:`scipy.stats.chi2.ppf`.
    """
    if not (isinstance(gate, (int, float)) and 0.0 < gate <= 1.0):
        raise ValidationError(f"gate must be a probability in (0, 1], got {gate!r}")
    if gate == 1.0:
        return math.inf
    if dof == 2:
        return -2.0 * math.log1p(-gate)
    from scipy.stats import (
        chi2,  # here, not at the top: a camera node needs only the 2-dof case
    )

    return float(chi2.ppf(gate, dof))


@dataclass
class CameraStats(FrontEndStats):
    """Counters of a camera front end: ``processed`` detections, ``contributed`` (fused) and
    ``rejected`` ones, of which ``gated`` failed the gate and ``unprojectable`` had a
    prediction behind the camera."""

    gated: int = 0
    unprojectable: int = 0

    @property
    def detections(self) -> int:
        """Detections processed."""
        return self.processed

    @property
    def fused(self) -> int:
        """Detections that passed the gate and were fused."""
        return self.contributed


class CameraFrontEnd(FrontEnd):
    """Gate camera detections against the node's prediction, then fuse them (EIF update).

    Parameters
    ----------
    camera : PinholeCamera
    gate : float
        Chi-square gate probability in ``(0, 1]`` (1: no gate).
    recognition_error : float or None
        ``k`` of the reliability model (pixels); default the camera's ``pixel_std``.
    source_name : str
        Name of the source reported to the node.
    """

    def __init__(self, camera: PinholeCamera, gate: float = 0.99, recognition_error: float | None = None,
                 source_name: str = "camera") -> None:
        self.camera = camera
        self.gate = float(gate)
        self.threshold = gate_threshold(self.gate)
        self.recognition_error = camera.pixel_std if recognition_error is None else float(recognition_error)
        if not (math.isfinite(self.recognition_error) and self.recognition_error >= 0):
            raise ValidationError(f"recognition_error must be >= 0 pixels, got {recognition_error!r}")
        self.source_name = source_name
        self.stats = CameraStats()
        #: Mahalanobis distances of the detections, in processing order (for diagnostics).
        self.distances: list[float] = []

    def __repr__(self) -> str:
        return f"CameraFrontEnd(gate={self.gate}, {self.stats})"

    @staticmethod
    def prediction(node: FusionNode, t: float) -> tuple[Array, Array]:
        """The node's estimate of the state at ``t`` without the detection being gated.

        ``node.estimate(t)`` when ``t`` is inside the window (a window state, or
        between two: the marginal predicted from its neighbours); the newest state
        predicted forward with the motion model when ``t`` is newer than it. Raises
        :class:`~dfusion.errors.OutsideWindowError` when ``t`` is older than the window.
        """
        f = node.filter
        if t <= f.latest_time + f.time_tol:
            return node.estimate(t)
        mean, cov = node.estimate()
        dt = t - f.latest_time
        F = node.motion.F(dt, mean)
        return node.motion.f(mean, dt), F @ cov @ F.T + node.motion.Q(dt, mean)

    def distance(self, node: FusionNode, t: float, z: Array) -> float:
        """Squared Mahalanobis distance of detection ``z`` at ``t`` to the prediction (inf if unprojectable)."""
        mean, cov = self.prediction(node, t)
        cam = self.camera
        if cam.camera_point(mean)[2] <= max(cam.min_depth, cam.MIN_PROJECT_DEPTH):
            return math.inf
        H = cam.H(mean)
        nu = cam.residual(np.asarray(z, dtype=float), cam.h(mean))
        S = H @ cov @ H.T + cam.R
        return float(nu @ np.linalg.solve(S, nu))

    def process(self, node: FusionNode, t: float, z: Array) -> bool:
        """Gate and fuse detection ``z`` taken at ``t``; returns whether it was fused."""
        self.stats.processed += 1
        d2 = self.distance(node, t, z)
        self.distances.append(d2)
        if not math.isfinite(d2):
            self.stats.unprojectable += 1
            self.stats.rejected += 1
            return False
        if d2 > self.threshold:
            self.stats.gated += 1
            self.stats.rejected += 1
            return False
        node.update(t, z, self.camera)
        self.stats.contributed += 1
        mean, cov = node.estimate()
        node.report_source(Estimate(self.source_name, node.latest_time, mean, cov,
                                    reliability=self._reliability(mean)))
        return True

    def _reliability(self, mean: Array) -> float:
        try:
            return camera_reliability_at(self.camera, mean[:2], self.recognition_error)
        except ValidationError:   # camera not above the target's plane
            return 0.0

    def reliability(self, node: FusionNode) -> float:
        """Camera reliability (switching paper eq. 1-9) at the node's newest estimate; 0 out of view."""
        mean, _ = node.estimate()
        return self._reliability(mean)


class MountedCameraFrontEnd(CameraFrontEnd):
    """:class:`CameraFrontEnd` for a camera on a moving robot: each detection is gated and fused
    with the camera where it was at the detection's time (``mounted.at(t)``)."""

    def __init__(self, mounted: MountedCamera, gate: float = 0.99, recognition_error: float | None = None,
                 source_name: str = "camera") -> None:
        super().__init__(mounted.at(0.0), gate, recognition_error, source_name)
        self.mounted = mounted

    def process(self, node: FusionNode, t: float, z: Array) -> bool:
        self.camera = self.mounted.at(t)
        return super().process(node, t, z)
