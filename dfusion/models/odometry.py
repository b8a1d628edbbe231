r"""Odometry: the sampled odometry motion model, velocity odometry, odometry increments.

* :class:`OdometryMotionModel` -- ``sample_motion_model_odometry`` of Thrun, Burgard &
  Fox, *Probabilistic Robotics*, 2005, table 5.6. The odometry displacement between two
  odometry poses is decomposed into ``rot1, trans, rot2``; each particle gets a perturbed
  copy with variances ``alpha1 rot1^2 + alpha2 trans^2`` (rotations),
  ``alpha3 trans^2 + alpha4 (rot1^2 + rot2^2)`` (translation). Two details follow ROS
  AMCL (``amcl_odom.cpp``): ``rot1 = 0`` when ``trans < 0.01 m`` (the heading of a tiny
  displacement is meaningless), and the rotation magnitudes entering the variances are
  ``min(|rot|, |pi - rot|)`` so that driving backwards does not count as a half turn.
* :class:`VelocityOdometry` -- piecewise-constant velocities ``(v, omega)`` integrated
  exactly with the :class:`~dfusion.models.Unicycle` model, with the accumulated
  Jacobian and process noise.
* :func:`odometry_increment` -- distance and heading change between two odometry poses.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import ShapeError, ValidationError
from dfusion.geometry import wrap_angle
from dfusion.linalg import Array, as_vector
from dfusion.models.motion import Unicycle

__all__ = ["OdometryMotionModel", "VelocityOdometry", "odometry_increment"]


class OdometryMotionModel:
    """``sample_motion_model_odometry`` (Thrun et al. 2005, table 5.6; see module docstring).

    Parameters
    ----------
    alpha1 : rotation noise from rotation (rad^2 / rad^2)
    alpha2 : rotation noise from translation (rad^2 / m^2)
    alpha3 : translation noise from translation (m^2 / m^2)
    alpha4 : translation noise from rotation (m^2 / rad^2)
    min_trans : below this translation (m) ``rot1`` is set to 0 (ROS AMCL uses 0.01).
    """

    def __init__(
        self,
        alpha1: float = 0.2,
        alpha2: float = 0.2,
        alpha3: float = 0.2,
        alpha4: float = 0.2,
        min_trans: float = 0.01,
    ) -> None:
        alphas = [float(a) for a in (alpha1, alpha2, alpha3, alpha4)]
        if not all(np.isfinite(a) and a >= 0 for a in alphas):
            raise ValidationError(f"alphas must be finite and >= 0, got {alphas}")
        self.alpha1, self.alpha2, self.alpha3, self.alpha4 = alphas
        self.min_trans = float(min_trans)

    def __repr__(self) -> str:
        return (
            f"OdometryMotionModel(alpha1={self.alpha1}, alpha2={self.alpha2}, "
            f"alpha3={self.alpha3}, alpha4={self.alpha4})"
        )

    def decompose(self, odom0: ArrayLike, odom1: ArrayLike) -> tuple[float, float, float]:
        """``(rot1, trans, rot2)`` of the odometry displacement from ``odom0`` to ``odom1``."""
        o0 = np.asarray(odom0, dtype=float)
        o1 = np.asarray(odom1, dtype=float)
        dx, dy = o1[0] - o0[0], o1[1] - o0[1]
        trans = math.hypot(dx, dy)
        rot1 = 0.0 if trans < self.min_trans else float(wrap_angle(math.atan2(dy, dx) - o0[2]))
        rot2 = float(wrap_angle(o1[2] - o0[2] - rot1))
        return rot1, trans, rot2

    def variances(self, rot1: float, trans: float, rot2: float) -> tuple[float, float, float]:
        """Variances of the noise added to ``rot1``, ``trans`` and ``rot2``."""
        r1 = min(abs(rot1), abs(float(wrap_angle(rot1 - math.pi))))
        r2 = min(abs(rot2), abs(float(wrap_angle(rot2 - math.pi))))
        v1 = self.alpha1 * r1 * r1 + self.alpha2 * trans * trans
        vt = self.alpha3 * trans * trans + self.alpha4 * (r1 * r1 + r2 * r2)
        v2 = self.alpha1 * r2 * r2 + self.alpha2 * trans * trans
        return v1, vt, v2

    def sample(
        self, particles: ArrayLike, odom0: ArrayLike, odom1: ArrayLike, rng: np.random.Generator
    ) -> Array:
        """Propagate every particle ``(N, 3)`` by one noisy copy of the odometry motion."""
        p = np.asarray(particles, dtype=float)
        rot1, trans, rot2 = self.decompose(odom0, odom1)
        v1, vt, v2 = self.variances(rot1, trans, rot2)
        n = p.shape[0]
        e = rng.standard_normal((n, 3))
        r1 = rot1 - math.sqrt(v1) * e[:, 0]
        tr = trans - math.sqrt(vt) * e[:, 1]
        r2 = rot2 - math.sqrt(v2) * e[:, 2]
        h = p[:, 2] + r1
        out = np.empty_like(p)
        out[:, 0] = p[:, 0] + tr * np.cos(h)
        out[:, 1] = p[:, 1] + tr * np.sin(h)
        out[:, 2] = wrap_angle(h + r2)
        return out


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
        xn = [x[0] + vds * c, x[1] + vds * sn, wrap_angle(x[2] + w * dt)]
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


def odometry_increment(odom0: ArrayLike, odom1: ArrayLike) -> tuple[float, float]:
    """``(Delta d, Delta theta)`` between two odometry poses.

    ``Delta d`` is the travelled distance, signed by the direction of travel relative to
    the heading at ``odom0`` (negative when driving backwards), and ``Delta theta`` the
    wrapped heading change.
    """
    o0 = as_vector(odom0, 3, "odom0")
    o1 = as_vector(odom1, 3, "odom1")
    dx, dy = o1[0] - o0[0], o1[1] - o0[1]
    d = math.hypot(dx, dy)
    if dx * math.cos(o0[2]) + dy * math.sin(o0[2]) < 0:
        d = -d
    return d, float(wrap_angle(o1[2] - o0[2]))
