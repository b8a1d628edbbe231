r"""Robot localizers as fusion-node front ends (``docs/robots.md``).

A robot takes part in a fusion network in two ways:

* **its own pose** -- a localizer (Monte Carlo localization, ICP scan matching, an
  environmental camera, a landmark EKF) estimates where the robot is, and the node whose
  state is the robot's position receives that estimate;
* **a target it observes** -- the robot measures another object (range and bearing) from
  a pose it only knows up to its localizer's covariance; the node whose state is the
  target receives the measurement with that pose uncertainty folded into its noise.

Contributions (DESIGN.md sec. 4). What a front end adds to its :class:`FusionNode` with
``add_local_information(t, Lambda, y)`` is information the rest of the network does not
have yet, on the node's state ``x`` (dimension ``n``, position = the first ``d`` entries):

* a *Gaussian* localizer result (ICP pose, camera fix), independent of the node's prior:
  the pseudo-measurement ``z = p`` of the position with covariance ``S``,
  ``Lambda = E^T S^-1 E``, ``y = E^T S^-1 p`` (``E = [I_d 0]``; :func:`position_information`);
* a *particle* localizer whose particles were predicted from the node's own belief
  (:class:`MCLFrontEnd`): the Gaussian fit of its posterior minus the Gaussian fit of its
  prediction, in information form, over the position, projected to positive
  semi-definite (:func:`fit_difference_information`). For a linear-Gaussian model this is
  exactly ``H^T R^-1 H`` and ``H^T R^-1 z``; the prior, whatever it was, cancels, so the
  node's own belief is not counted twice.

Measurement models defined here (``h``, ``H``, ``R`` as in :mod:`dfusion.models`):

:class:`LandmarkRangeBearing`
    range and bearing of a known landmark ``l`` from the robot pose ``(x, y, theta)``
    (the state): ``h = [|l - p|, wrap(atan2(l_y - y, l_x - x) - theta)]``.
:class:`TargetRangeBearing`
    range and bearing of a target (state position ``q``) from an observer whose pose
    ``s = (x_s, y_s, theta_s)`` is an estimate with covariance ``P_s``. The pose error
    enters the measurement linearly, ``z ~ h(q, s) + J_s (s_true - s) + v``, so the
    target filter uses ``R_eff = R + J_s P_s J_s^T`` with
    ``J_s = dh/ds = [[-dx/r, -dy/r, 0], [dy/r^2, -dx/r^2, -1]]`` evaluated at the
    *measured* point ``(dx, dy) = r (cos(theta_s + b), sin(theta_s + b))`` (so ``R_eff``
    does not depend on the target's estimate). :meth:`TargetRangeBearing.position_fix`
    gives the same measurement as a linear :class:`PositionFix` of the target:
    ``p = s_xy + r (cos(theta_s + b), sin(theta_s + b))`` with
    ``R_eff = G R G^T + J_c P_s J_c^T`` (``G = dp/d(r, b)``, ``J_c = dp/ds``); a filter
    whose estimate is far from the target (after a long gap) cannot linearize the polar
    form well, the linear fix has no such problem. Both assume the observer's pose error
    is independent of the target's state and of the observer's other measurements of the
    same target; consecutive observations from one robot share its pose error, which this
    model ignores (see ``docs/robots.md``).
:class:`LaserScanSensor`
    the ranges a planar laser on the robot would measure in an occupancy grid, for a
    state ``(x, y, vx, vy)`` with the heading taken as the direction of motion; used to
    *simulate* scans in scenario files. Its Jacobian (central differences, with beams
    that cross a range discontinuity zeroed) serves only the centralized reference EKF.

Localizer:

:class:`LandmarkEKF`
    pose EKF driven by velocity odometry (:class:`VelocityOdometry`, the
    :class:`~dfusion.models.Unicycle` model integrated exactly over piecewise-constant
    velocities) and updated with :class:`LandmarkRangeBearing` (chi-square gate).

Front ends (``process(node, t, z)``, see :mod:`dfusion.sim.frontends`): :class:`EnvCameraFrontEnd`,
:class:`MCLFrontEnd`, :class:`ICPFrontEnd`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..errors import ShapeError, ValidationError
from ..fusion.node import FusionNode
from ..fusion.policy import SourceEstimate
from ..linalg import as_positive, as_spd, as_vector, symmetrize
from ..maps.grid import OccupancyGrid
from ..maps.raycast import cast_rays
from ..models.base import Array, MeasurementModel, wrap_angle
from ..models.measurement import RangeBearing
from ..models.motion import Unicycle
from ..pf.wsn import project_psd_information
from .icp import ScanMatcher, scan_to_points
from .mcl import (
    LaserConfig,
    MonteCarloLocalization,
    PoseEstimate,
    gaussian_summary,
    reliability,
)

__all__ = [
    "LandmarkRangeBearing",
    "TargetRangeBearing",
    "PositionFix",
    "LaserScanSensor",
    "VelocityOdometry",
    "LandmarkEKF",
    "position_information",
    "fit_difference_information",
    "embed_source",
    "EnvCameraFrontEnd",
    "MCLFrontEnd",
    "ICPFrontEnd",
]


# ----------------------------------------------------------------------------------------
# Measurement models
# ----------------------------------------------------------------------------------------
class LandmarkRangeBearing(MeasurementModel):
    """Range and bearing of a known landmark from the robot pose (the first 3 state entries).

    ``h(x) = [r, wrap(atan2(dy, dx) - theta)]`` with ``(dx, dy) = l - (x, y)``;
    ``H = [[-dx/r, -dy/r, 0], [dy/r^2, -dx/r^2, -1]]``; ``R = diag(range_std^2, bearing_std^2)``.
    """

    dim_z = 2
    is_linear = False
    angle_indices = (1,)

    def __init__(self, landmark: ArrayLike, range_std: float, bearing_std: float) -> None:
        self.landmark = as_vector(landmark, 2, "landmark position")
        self.range_std = as_positive(range_std, "range_std")
        self.bearing_std = as_positive(bearing_std, "bearing_std")
        self._R = np.diag([self.range_std**2, self.bearing_std**2])

    def __repr__(self) -> str:
        return f"LandmarkRangeBearing(landmark={self.landmark.tolist()}, range_std={self.range_std}, bearing_std={self.bearing_std})"

    def h(self, x: Array) -> Array:
        x = np.asarray(x, dtype=float)
        dx, dy = self.landmark[0] - x[0], self.landmark[1] - x[1]
        return np.array([math.hypot(dx, dy), float(wrap_angle(math.atan2(dy, dx) - x[2]))])

    def H(self, x: Array) -> Array:
        x = np.asarray(x, dtype=float)
        if x.shape[0] < 3:
            raise ShapeError("LandmarkRangeBearing needs a pose state (x, y, theta, ...)")
        dx, dy = self.landmark[0] - x[0], self.landmark[1] - x[1]
        r2 = dx * dx + dy * dy
        if r2 < 1e-18:
            raise ValidationError("LandmarkRangeBearing: robot at the landmark, bearing undefined")
        r = math.sqrt(r2)
        H = np.zeros((2, x.shape[0]))
        H[0, :3] = -dx / r, -dy / r, 0.0
        H[1, :3] = dy / r2, -dx / r2, -1.0
        return H

    @property
    def R(self) -> Array:
        return self._R


def _observer_jacobian(observer_pose: Array, z: Array) -> Array:
    """``dh/ds`` of range-bearing w.r.t. the observer pose, at the measured point."""
    r, b = float(z[0]), float(z[1])
    phi = observer_pose[2] + b
    dx, dy = r * math.cos(phi), r * math.sin(phi)
    r2 = max(r * r, 1e-18)
    r = math.sqrt(r2)
    return np.array([[-dx / r, -dy / r, 0.0], [dy / r2, -dx / r2, -1.0]])


class TargetRangeBearing(RangeBearing):
    """Range and bearing of a target (state position ``x[:2]``) from an uncertain observer.

    :class:`dfusion.models.RangeBearing` with the observer's estimated pose as the sensor
    pose (same ``h`` and ``H``), and the observer's pose uncertainty folded into the noise.

    Parameters
    ----------
    observer_pose : (3,)
        The observer's estimated pose ``(x_s, y_s, theta_s)``.
    observer_cov : (3, 3)
        Its covariance ``P_s`` (zeros: a known pose).
    z : (2,)
        The measurement ``(range, bearing)``; fixes the point where ``J_s`` is evaluated.
    range_std, bearing_std : float
        Sensor noise.

    ``R = diag(range_std^2, bearing_std^2) + J_s P_s J_s^T`` (module docstring).
    """

    def __init__(self, observer_pose: ArrayLike, observer_cov: ArrayLike, z: ArrayLike,
                 range_std: float, bearing_std: float) -> None:
        super().__init__(observer_pose, range_std, bearing_std)
        P = np.asarray(observer_cov, dtype=float)
        if P.shape != (3, 3) or not np.all(np.isfinite(P)):
            raise ShapeError("observer_cov must be a finite 3 x 3 matrix")
        self.observer_cov = symmetrize(P)
        self.z = as_vector(z, 2, "range-bearing measurement")
        J = _observer_jacobian(self.sensor_pose, self.z)
        self.J = J
        self._R = symmetrize(self._R + J @ self.observer_cov @ J.T)

    @property
    def observer_pose(self) -> Array:
        """The observer's estimated pose (the sensor pose of :class:`RangeBearing`)."""
        return self.sensor_pose

    def position_fix(self) -> "PositionFix":
        """The measurement converted to a position fix of the target (module docstring):
        ``p = s_xy + r (cos(theta_s + b), sin(theta_s + b))`` with covariance
        ``G R G^T + J_c P_s J_c^T``, ``G = dp/d(r, b)``, ``J_c = dp/ds``."""
        r, b = float(self.z[0]), float(self.z[1])
        s = self.observer_pose
        c, sn = math.cos(s[2] + b), math.sin(s[2] + b)
        p = s[:2] + r * np.array([c, sn])
        G = np.array([[c, -r * sn], [sn, r * c]])
        Jc = np.array([[1.0, 0.0, -r * sn], [0.0, 1.0, r * c]])
        R0 = np.diag([self.range_std**2, self.bearing_std**2])
        return PositionFix(p, symmetrize(G @ R0 @ G.T + Jc @ self.observer_cov @ Jc.T))


class PositionFix(MeasurementModel):
    """A linear position measurement ``z = x[:d] + v``, ``v ~ N(0, cov)`` with a full covariance.

    ``z`` (the fix itself) is kept in :attr:`z` for convenience.
    """

    is_linear = True

    def __init__(self, z: ArrayLike, cov: ArrayLike) -> None:
        self.z = np.asarray(z, dtype=float).reshape(-1)
        self.dim_z = self.z.size
        self._R = as_spd(cov, self.dim_z, "position fix covariance")

    def h(self, x: Array) -> Array:
        return np.asarray(x, dtype=float)[: self.dim_z].copy()

    def H(self, x: Array) -> Array:
        n = np.shape(x)[0]
        H = np.zeros((self.dim_z, n))
        H[:, : self.dim_z] = np.eye(self.dim_z)
        return H

    @property
    def R(self) -> Array:
        return self._R


def heading_of(x: Array, min_speed: float = 1e-9) -> float:
    """Direction of motion ``atan2(vy, vx)`` of a state ``(x, y, vx, vy)`` (0 when at rest)."""
    vx, vy = float(x[2]), float(x[3])
    return math.atan2(vy, vx) if vx * vx + vy * vy > min_speed * min_speed else 0.0


class LaserScanSensor(MeasurementModel):
    """Simulated planar laser on a robot with state ``(x, y, vx, vy)`` (heading = direction of motion).

    ``h(x)`` = exact ray-cast ranges (:func:`~dfusion.maps.cast_rays`) from the pose
    ``(x, y, atan2(vy, vx))`` for the beams of ``laser``; ``R = range_std^2 I``. A
    simulated reading above ``max_range`` means "no return".

    ``H`` (only for the centralized reference EKF, which fuses raw ranges): central
    differences with a step of half a cell in ``x, y`` and ``0.01 rad`` in the heading
    (chained through ``d heading / d v = (-vy, vx) / |v|^2``); a beam whose two
    one-sided differences disagree by more than ``jump`` (it crosses a range
    discontinuity, e.g. a door frame) gets a zero row. It is a crude linearization:
    docs/robots.md.
    """

    is_linear = False

    def __init__(self, grid: OccupancyGrid, laser: LaserConfig, range_std: float = 0.05, *,
                 jump: float = 0.2) -> None:
        if not isinstance(grid, OccupancyGrid):
            raise ValidationError("LaserScanSensor needs a dfusion.maps.OccupancyGrid")
        self.grid = grid
        self.laser = laser
        self.range_std = as_positive(range_std, "range_std")
        self.jump = float(jump)
        self.dim_z = int(laser.angles.size)
        self._R = self.range_std**2 * np.eye(self.dim_z)

    def __repr__(self) -> str:
        return f"LaserScanSensor(beams={self.dim_z}, max_range={self.laser.max_range}, range_std={self.range_std})"

    def pose(self, x: Array) -> Array:
        x = np.asarray(x, dtype=float)
        return np.array([x[0], x[1], heading_of(x)])

    def ranges(self, poses: Array) -> Array:
        from .mcl import se2_compose  # noqa: PLC0415

        lp = se2_compose(np.atleast_2d(poses), self.laser.offset)
        return cast_rays(self.grid, lp, self.laser.angles, self.laser.max_range)

    def h(self, x: Array) -> Array:
        return self.ranges(self.pose(x))[0]

    def H(self, x: Array) -> Array:
        x = np.asarray(x, dtype=float)
        p = self.pose(x)
        d = 0.5 * self.grid.resolution
        da = 0.01
        steps = np.array([[d, 0, 0], [-d, 0, 0], [0, d, 0], [0, -d, 0], [0, 0, da], [0, 0, -da]])
        r0 = self.ranges(p)[0]
        r = self.ranges(p + steps)
        H = np.zeros((self.dim_z, x.shape[0]))
        for k, (h_step) in enumerate((d, d, da)):
            fwd, bwd = r[2 * k] - r0, r0 - r[2 * k + 1]
            g = (fwd + bwd) / (2.0 * h_step)
            bad = np.abs(fwd - bwd) > self.jump
            g[bad] = 0.0
            if k < 2:
                H[:, k] = g
            else:
                sp2 = float(x[2] ** 2 + x[3] ** 2)
                if sp2 > 1e-6:
                    H[:, 2] = g * (-x[3] / sp2)
                    H[:, 3] = g * (x[2] / sp2)
        return H

    @property
    def R(self) -> Array:
        return self._R


# ----------------------------------------------------------------------------------------
# Odometry and the landmark EKF
# ----------------------------------------------------------------------------------------
class VelocityOdometry:
    """Piecewise-constant velocity odometry ``(v, omega)``, each row valid until the next.

    Consecutive identical rows are merged (the exact arc of a merged piece equals the
    composition of its parts). :meth:`propagate` integrates a pose from ``ta`` to ``tb``
    with the :class:`~dfusion.models.Unicycle` model and accumulates its Jacobian and
    process noise, ``F = F_m ... F_1`` and ``Q = F_m (... (F_2 Q_1 F_2^T + Q_2) ...) F_m^T
    + Q_m``, so that ``P(tb) = F P(ta) F^T + Q`` equals the EKF run piece by piece. Before
    the first row the robot stands still (no noise is added either).
    """

    def __init__(self, times: ArrayLike, velocities: ArrayLike, motion: Unicycle) -> None:
        t = np.asarray(times, dtype=float).reshape(-1)
        u = np.asarray(velocities, dtype=float).reshape(-1, 2)
        if t.shape[0] != u.shape[0]:
            raise ShapeError("times and velocities must have the same number of rows")
        if t.size and np.any(np.diff(t) < 0):
            raise ValidationError("odometry times must be sorted")
        keep = np.ones(t.size, dtype=bool)
        if t.size > 1:
            keep[1:] = np.any(u[1:] != u[:-1], axis=1)
        self.times = t[keep]
        self.u = u[keep]
        self.motion = motion
        self._sv2, self._sw2 = motion.std_v**2, motion.std_w**2
        self._qf = motion.q_floor

    def _piece(self, x: list[float], v: float, w: float, dt: float) -> tuple[list[float], Array, Array]:
        """Exact arc, its Jacobian ``F`` and noise ``Q`` (same formulas as :class:`Unicycle`)."""
        a = 0.5 * w * dt if abs(w) > Unicycle.OMEGA_EPS else 0.0
        if abs(a) < 1e-3:
            s = 1.0 - a * a / 6.0 + a**4 / 120.0
            ds = -a / 3.0 + a**3 / 30.0 - a**5 / 840.0
        else:
            s = math.sin(a) / a
            ds = (a * math.cos(a) - math.sin(a)) / (a * a)
        phi = x[2] + a
        c, sn = math.cos(phi), math.sin(phi)
        vds = v * dt * s
        xn = [x[0] + vds * c, x[1] + vds * sn, (x[2] + w * dt + math.pi) % (2 * math.pi) - math.pi]
        F = np.array([[1.0, 0.0, -vds * sn], [0.0, 1.0, vds * c], [0.0, 0.0, 1.0]])
        half = 0.5 * v * dt * dt
        V = np.array([[dt * s * c, half * (ds * c - s * sn)], [dt * s * sn, half * (ds * sn + s * c)], [0.0, dt]])
        Q = (V * np.array([self._sv2, self._sw2])) @ V.T / dt + self._qf * dt * np.eye(3)
        return xn, F, Q

    def propagate(self, x: ArrayLike, ta: float, tb: float) -> tuple[Array, Array, Array]:
        """Pose at ``tb`` from pose ``x`` at ``ta <= tb``, with the accumulated ``F`` and ``Q``."""
        xs = [float(v) for v in np.asarray(x, dtype=float).reshape(3)]
        F = np.eye(3)
        Q = np.zeros((3, 3))
        if tb < ta:
            raise ValidationError(f"cannot propagate backwards ({ta} -> {tb})")
        t = float(ta)
        k = int(np.searchsorted(self.times, t, side="right")) - 1
        while t < tb:
            t_next = float(self.times[k + 1]) if k + 1 < self.times.size else math.inf
            t_end = min(t_next, tb)
            dt = t_end - t
            if k >= 0 and dt > 0:
                xs, Fi, Qi = self._piece(xs, float(self.u[k, 0]), float(self.u[k, 1]), dt)
                F = Fi @ F
                Q = Fi @ Q @ Fi.T + Qi
            t = t_end
            if t == t_next:
                k += 1
        return np.array(xs), F, Q


class LandmarkEKF:
    """Pose EKF: velocity odometry (:class:`VelocityOdometry`) + range-bearing to known landmarks.

    Parameters
    ----------
    odometry : VelocityOdometry
    t0 : float
        Time of the initial pose.
    x0, P0 : (3,), (3, 3)
        Initial pose and covariance.
    gate : float or None
        Chi-square threshold (2 degrees of freedom) on the normalized innovation; larger
        innovations are rejected and counted in :attr:`rejected` (default 13.8, 99.9 %).
    """

    def __init__(self, odometry: VelocityOdometry, t0: float, x0: ArrayLike, P0: ArrayLike, *,
                 gate: float | None = 13.8) -> None:
        self.odometry = odometry
        self.t = float(t0)
        self.x = as_vector(x0, 3, "x0").copy()
        self.x[2] = float(wrap_angle(self.x[2]))
        self.P = as_spd(P0, 3, "P0")
        self.gate = None if gate is None else float(gate)
        self.accepted = 0
        self.rejected = 0

    def predict_to(self, t: float) -> None:
        """Propagate the pose to ``t >= self.t`` with the odometry."""
        if t <= self.t:
            return
        self.x, F, Q = self.odometry.propagate(self.x, self.t, float(t))
        self.P = symmetrize(F @ self.P @ F.T + Q)
        self.t = float(t)

    def update(self, z: ArrayLike, sensor: MeasurementModel) -> bool:
        """EKF update with a measurement of the pose (``False`` if gated out)."""
        zz = np.asarray(z, dtype=float).reshape(-1)
        H = sensor.H(self.x)
        nu = sensor.residual(zz, sensor.h(self.x))
        S = H @ self.P @ H.T + sensor.R
        Sinv = np.linalg.inv(S)
        if self.gate is not None and float(nu @ Sinv @ nu) > self.gate:
            self.rejected += 1
            return False
        K = self.P @ H.T @ Sinv
        self.x = self.x + K @ nu
        self.x[2] = float(wrap_angle(self.x[2]))
        IKH = np.eye(3) - K @ H
        self.P = symmetrize(IKH @ self.P @ IKH.T + K @ sensor.R @ K.T)
        self.accepted += 1
        return True

    def estimate(self) -> PoseEstimate:
        return PoseEstimate(self.t, self.x.copy(), self.P.copy(), reliability(self.P))


# ----------------------------------------------------------------------------------------
# Information contributions
# ----------------------------------------------------------------------------------------
def position_information(mean: ArrayLike, cov: ArrayLike, n: int) -> tuple[Array, Array]:
    """Information ``(Lambda, y)`` on an ``n``-state of the pseudo-measurement ``z = mean``
    of its first ``d = len(mean)`` entries with covariance ``cov``."""
    m = np.asarray(mean, dtype=float).reshape(-1)
    d = m.size
    S = as_spd(cov, d, "position covariance")
    W = np.linalg.inv(S)
    Lam = np.zeros((n, n))
    y = np.zeros(n)
    Lam[:d, :d] = symmetrize(W)
    y[:d] = W @ m
    return Lam, y


def fit_difference_information(prior: tuple[Array, Array], post: tuple[Array, Array], n: int,
                               rtol: float = 1e-9) -> tuple[Array, Array]:
    """``(P_post^-1 - P_prior^-1, P_post^-1 m_post - P_prior^-1 m_prior)`` on the first
    ``d`` entries of an ``n``-state, projected to positive semi-definite
    (:func:`dfusion.pf.project_psd_information`)."""
    m0, P0 = (np.asarray(a, dtype=float) for a in prior)
    m1, P1 = (np.asarray(a, dtype=float) for a in post)
    d = m0.size
    O0 = np.linalg.inv(as_spd(P0, d, "prior covariance"))
    O1 = np.linalg.inv(as_spd(P1, d, "posterior covariance"))
    Om, eta, _ = project_psd_information(O1 - O0, O1 @ m1 - O0 @ m0, rtol)
    Lam = np.zeros((n, n))
    y = np.zeros(n)
    Lam[:d, :d] = Om
    y[:d] = eta
    return Lam, y


def embed_source(name: str, t: float, node_mean: Array, node_cov: Array, mean: Array, cov: Array,
                 rel: float, healthy: bool = True) -> SourceEstimate:
    """A localizer's position estimate as a :class:`SourceEstimate` in the node's state space:
    the node's fused mean and covariance with the position part replaced (cross terms 0)."""
    d = np.asarray(mean).size
    m = np.array(node_mean, dtype=float)
    P = np.array(node_cov, dtype=float)
    m[:d] = mean
    P[:d, :] = 0.0
    P[:, :d] = 0.0
    P[:d, :d] = cov
    return SourceEstimate(name, float(t), m, P, float(rel), healthy)


# ----------------------------------------------------------------------------------------
# Front ends
# ----------------------------------------------------------------------------------------
@dataclass
class FrontEndStats:
    """Counters of a robot front end."""

    processed: int = 0
    contributed: int = 0
    rejected: int = 0


class EnvCameraFrontEnd:
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
        self.last: PoseEstimate | None = None

    def process(self, node: FusionNode, t: float, z: Array) -> None:
        self.stats.processed += 1
        est = self.localizer.update(t, z)
        self.last = est
        if est is None or est.reliability < self.min_reliability:
            self.stats.rejected += 1
            return
        n = node.filter.n
        Lam, y = position_information(est.mean[:2], est.covariance[:2, :2], n)
        node.add_local_information(t, Lam, y)
        self.stats.contributed += 1
        m, P = node.estimate()
        node.report_source(embed_source(f"{node.name}/env_camera", t, m, P, est.mean[:2],
                                        est.covariance[:2, :2], est.reliability))


class MCLFrontEnd:
    """Monte Carlo localization of the robot (the node's target, state ``(x, y, vx, vy)``).

    The particles ``(x, y, theta)`` live in a :class:`MonteCarloLocalization` (its sensor
    model, tempering and KLD resampling). Scenario robots have no wheel odometry, so the
    particles are *predicted from the node's own belief*: at a scan at ``t`` every particle
    moves by the displacement of the node's fused mean since the previous scan plus
    ``N(0, q_pos dt I)``, and its heading takes a random-walk step ``N(0, q_heading dt)``
    (the heading is not in the node's state; the scan constrains it). The first scan draws
    the particles from the node's position belief with headings spread
    ``heading_std`` around the direction of motion. Then:

    1. prediction fit ``(m0, P0)`` of the positions (weights before the scan);
    2. the scan weights the particles (``MonteCarloLocalization.add_scan``, no resampling
       inside);
    3. posterior fit ``(m1, P1)``; the node receives ``fit_difference_information`` --
       the scan's information only, whatever the prior was (module docstring);
    4. resampling (KLD) when ``N_eff < resample_threshold N``.

    A scan whose contribution has no positive eigenvalue is counted in
    ``stats.rejected``.
    """

    def __init__(self, mcl: MonteCarloLocalization, *, q_pos: float = 0.05, q_heading: float = 0.05,
                 heading_std: float = 0.5, resample_threshold: float = 0.5, init_particles: int | None = None) -> None:
        self.mcl = mcl
        mcl.resample_threshold = 0.0  # resampling is done here, after the posterior fit
        self.q_pos = float(q_pos)
        self.q_heading = float(q_heading)
        self.heading_std = float(heading_std)
        self.resample_threshold = float(resample_threshold)
        self.init_particles = init_particles
        self.stats = FrontEndStats()
        self._t: float | None = None
        self._ref: Array | None = None  # fused mean position at the previous scan
        self.last: PoseEstimate | None = None

    def process(self, node: FusionNode, t: float, z: Array) -> None:
        self.stats.processed += 1
        mcl = self.mcl
        rng = mcl.rng
        mean, cov = node.estimate(t) if t >= node.filter.oldest_time else node.estimate()
        if self._t is None:
            n = self.init_particles or mcl._default_n(None)  # noqa: SLF001
            L = np.linalg.cholesky(symmetrize(cov[:2, :2]) + 1e-12 * np.eye(2))
            p = np.empty((n, 3))
            p[:, :2] = mean[:2] + rng.standard_normal((n, 2)) @ L.T
            p[:, 2] = heading_of(mean) + self.heading_std * rng.standard_normal(n)
            mcl.initialize_particles(p)
        else:
            dt = max(float(t) - self._t, 0.0)
            p = mcl.particles
            w = mcl.weights
            p[:, :2] += (mean[:2] - self._ref) + math.sqrt(self.q_pos * dt) * rng.standard_normal((p.shape[0], 2))
            p[:, 2] = wrap_angle(p[:, 2] + math.sqrt(self.q_heading * dt) * rng.standard_normal(p.shape[0]))
            mcl.initialize_particles(p, w)
        self._t, self._ref = float(t), mean[:2].copy()
        w0 = mcl.weights
        parts = mcl.particles
        prior = gaussian_summary(parts, w0)
        if not mcl.add_scan(t, z):
            self.stats.rejected += 1
            return
        post_pose = gaussian_summary(parts, mcl.weights)
        self.last = PoseEstimate(t, post_pose[0], post_pose[1], reliability(post_pose[1]),
                                 parts.shape[0], mcl.n_eff)
        prior2 = (prior[0][:2], prior[1][:2, :2])
        post2 = (post_pose[0][:2], post_pose[1][:2, :2])
        try:
            Lam, y = fit_difference_information(prior2, post2, node.filter.n)
        except Exception:  # noqa: BLE001  (degenerate particle cloud: nothing to contribute)
            Lam = np.zeros((node.filter.n, node.filter.n))
            y = np.zeros(node.filter.n)
        if not np.any(Lam):
            self.stats.rejected += 1
        else:
            node.add_local_information(t, Lam, y)
            self.stats.contributed += 1
            m, P = node.estimate()
            node.report_source(embed_source(f"{node.name}/mcl", t, m, P, post2[0], post2[1],
                                            self.last.reliability))
        if mcl.n_eff < self.resample_threshold * mcl.weights.size:
            mcl._resample()  # noqa: SLF001


class ICPFrontEnd:
    """ICP scan matching of the robot's scan against the map (the robot is the node's target).

    The initial guess is the node's fused position with the heading of the previous
    accepted match (or the direction of motion at the first scan, or when the last match
    is older than ``heading_timeout`` s); the match is accepted when ICP converged with at
    least ``min_inliers`` inliers and an inlier RMSE below ``max_rmse``. Its position
    ``(x, y)`` with covariance ``cov_scale * Sigma_xy + min_std^2 I`` (the Hessian
    covariance is optimistic: ``docs/localization.md``) is added as position information
    and reported as the source ``"<node>/icp"``.
    """

    def __init__(self, matcher: ScanMatcher, laser: LaserConfig, *, cov_scale: float = 4.0,
                 min_std: float = 0.02, min_inliers: int = 20, max_rmse: float = 0.1,
                 heading_timeout: float = 5.0) -> None:
        self.matcher = matcher
        self.laser = laser
        self.cov_scale = float(cov_scale)
        self.min_std = float(min_std)
        self.min_inliers = int(min_inliers)
        self.max_rmse = float(max_rmse)
        self.heading_timeout = float(heading_timeout)
        self.stats = FrontEndStats()
        self._heading: tuple[float, float] | None = None
        self.last: PoseEstimate | None = None

    def process(self, node: FusionNode, t: float, z: Array) -> None:
        self.stats.processed += 1
        mean, _ = node.estimate(t) if t >= node.filter.oldest_time else node.estimate()
        if self._heading is not None and t - self._heading[0] <= self.heading_timeout:
            th = self._heading[1]
        else:
            th = heading_of(mean)
        pts = scan_to_points(z, self.laser.angles, self.laser.max_range, self.laser.min_range)
        if pts.shape[0] < max(3, self.min_inliers):
            self.stats.rejected += 1
            return
        from .mcl import se2_compose, se2_inverse  # noqa: PLC0415

        init = np.array([mean[0], mean[1], th])
        try:
            res = self.matcher.match(pts, se2_compose(init, self.laser.offset))
        except ValidationError:
            self.stats.rejected += 1
            return
        if not res.converged or res.n_inliers < self.min_inliers or res.rmse > self.max_rmse:
            self.stats.rejected += 1
            return
        pose = se2_compose(res.pose, se2_inverse(self.laser.offset))
        self._heading = (float(t), float(pose[2]))
        C = self.cov_scale * res.covariance[:2, :2] + self.min_std**2 * np.eye(2)
        self.last = PoseEstimate(t, pose, res.covariance, reliability(C))
        Lam, y = position_information(pose[:2], C, node.filter.n)
        node.add_local_information(t, Lam, y)
        self.stats.contributed += 1
        m, P = node.estimate()
        node.report_source(embed_source(f"{node.name}/icp", t, m, P, pose[:2], C, self.last.reliability))
