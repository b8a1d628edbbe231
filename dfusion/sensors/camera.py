r"""Sensor kind ``camera``: a calibrated camera detecting the target in its image.

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

Scenario keys (``docs/scenarios.md``): ``position``, ``look_at`` or ``yaw`` and
``pitch``, ``fx``, ``fy``, ``cx``, ``cy``, ``width``, ``height``,
``pixel_std``, ``point_height``, ``false_detection_rate``, ``gate``,
``recognition_error``, and the common ``detection``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from ..errors import ValidationError
from ..fusion.node import FusionNode
from ..fusion.policy import SourceEstimate
from ..linalg import Array
from ..models.camera import PinholeCamera
from ..reliability import camera_reliability_at
from ..sim.scenario import _NODE_KEYS, register_sensor

__all__ = ["SceneCamera", "CameraFrontEnd", "CameraStats", "gate_threshold", "camera_from_table", "CAMERA_KEYS"]

#: Keys of a ``sensor = "camera"`` node table, besides the common node keys.
CAMERA_KEYS = {"position", "look_at", "yaw", "pitch", "fx", "fy", "cx", "cy", "width", "height", "pixel_std",
               "point_height", "false_detection_rate", "gate", "recognition_error"}


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
    from scipy.stats import chi2

    return float(chi2.ppf(gate, dof))


class SceneCamera(PinholeCamera):
    """A :class:`PinholeCamera` that also produces false detections in the simulated world.

    ``clutter_rate`` is the mean number of false detections per frame (Poisson);
    :meth:`sample_clutter` draws them uniformly in the image.
    """

    def __init__(self, *args: Any, clutter_rate: float = 0.0, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if not (math.isfinite(clutter_rate) and clutter_rate >= 0):
            raise ValidationError(f"false_detection_rate must be >= 0, got {clutter_rate!r}")
        self.clutter_rate = float(clutter_rate)

    def sample_clutter(self, rng: np.random.Generator, k: int) -> Array:
        """``k`` false detections ``(u, v)`` uniform in ``[0, width) x [0, height)``, shape ``(k, 2)``."""
        return rng.random((int(k), 2)) * np.array([self.width, self.height], dtype=float)


def _num(table: Mapping[str, Any], key: str, default: Any = None, *, positive: bool = False,
         nonneg: bool = False) -> float:
    v = table.get(key, default)
    if v is None:
        raise ValidationError(f"{key} is required")
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValidationError(f"{key} must be a finite number, got {v!r}")
    if positive and v <= 0:
        raise ValidationError(f"{key} must be positive, got {v!r}")
    if nonneg and v < 0:
        raise ValidationError(f"{key} must be non-negative, got {v!r}")
    return float(v)


def _vec(table: Mapping[str, Any], key: str, sizes: tuple[int, ...]) -> Array:
    v = table.get(key)
    if not (isinstance(v, list) and len(v) in sizes and all(
            isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in v)):
        raise ValidationError(f"{key} must be a list of {' or '.join(map(str, sizes))} finite numbers, got {v!r}")
    return np.asarray(v, dtype=float)


def camera_from_table(table: Mapping[str, Any]) -> SceneCamera:
    """Build the camera of a ``sensor = "camera"`` node table (keys: see ``docs/scenarios.md``)."""
    unknown = set(table) - _NODE_KEYS - CAMERA_KEYS
    if unknown:
        raise ValidationError(f"unknown keys {sorted(unknown)} for a camera (known: {sorted(CAMERA_KEYS)})")
    position = _vec(table, "position", (3,))
    width = table.get("width", 640)
    height = table.get("height", 480)
    for key, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise ValidationError(f"{key} must be a positive integer (pixels), got {v!r}")
    fx = _num(table, "fx", 500.0, positive=True)
    fy = _num(table, "fy", fx, positive=True)
    cx = _num(table, "cx", width / 2.0)
    cy = _num(table, "cy", height / 2.0)
    point_height = _num(table, "point_height", 0.0)
    kw = dict(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height,
              pixel_std=_num(table, "pixel_std", 2.0, positive=True), point_height=point_height)
    has_look = "look_at" in table
    has_angles = "yaw" in table or "pitch" in table
    if has_look == has_angles:
        raise ValidationError("give either look_at = [x, y(, z)] or yaw and pitch (degrees)")
    if has_look:
        target = _vec(table, "look_at", (2, 3))
        if target.shape[0] == 2:
            target = np.append(target, point_height)
        up = (0.0, 0.0, 1.0)
    else:
        yaw = math.radians(_num(table, "yaw"))
        pitch = math.radians(_num(table, "pitch"))
        if not -math.pi / 2 <= pitch <= math.pi / 2:
            raise ValidationError(f"pitch must be in [-90, 90] degrees, got {table['pitch']!r}")
        fwd = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), -math.sin(pitch)])
        target = position + fwd
        # looking straight down: the image's top faces the yaw direction
        up = (0.0, 0.0, 1.0) if abs(math.cos(pitch)) > 1e-6 else (math.cos(yaw), math.sin(yaw), 0.0)
    cam = PinholeCamera.looking_at(position, target, up, **kw)
    return SceneCamera(cam.position, cam.R_wc, fx, fy, cx, cy, width, height, kw["pixel_std"], point_height,
                       clutter_rate=_num(table, "false_detection_rate", 0.0, nonneg=True))


@dataclass
class CameraStats:
    """Counters of a camera front end."""

    detections: int = 0      # detections processed
    fused: int = 0           # passed the gate and fused
    gated: int = 0           # rejected by the gate
    unprojectable: int = 0   # rejected: the prediction is behind the camera


class CameraFrontEnd:
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
        self.stats.detections += 1
        d2 = self.distance(node, t, z)
        self.distances.append(d2)
        if not math.isfinite(d2):
            self.stats.unprojectable += 1
            return False
        if d2 > self.threshold:
            self.stats.gated += 1
            return False
        node.update(t, z, self.camera)
        self.stats.fused += 1
        mean, cov = node.estimate()
        node.report_source(SourceEstimate(self.source_name, node.latest_time, mean, cov,
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


def _camera_sensor(table: Mapping[str, Any], sc) -> SceneCamera:
    cam = camera_from_table(table)
    gate_threshold(table.get("gate", 0.99))   # validate at load time
    if "recognition_error" in table:
        _num(table, "recognition_error", nonneg=True)
    if cam.position[2] <= cam.point_height:
        raise ValidationError("position: the camera must be above point_height")
    return cam


def _camera_front_end(spec, sc, seed: int) -> CameraFrontEnd:
    return CameraFrontEnd(spec.sensor, gate=spec.params.get("gate", 0.99),
                          recognition_error=spec.params.get("recognition_error"))


register_sensor("camera", _camera_sensor, _camera_front_end)
