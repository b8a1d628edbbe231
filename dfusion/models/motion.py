"""Motion models.

``ConstantVelocity``: the continuous white-noise-acceleration model
(Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and
Navigation*, 2001, sec. 6.2.2). State ``[p_1..p_d, v_1..v_d]``::

    F(dt) = [[I, dt I], [0, I]]
    Q(dt) = q [[dt^3/3 I, dt^2/2 I], [dt^2/2 I, dt I]]

with ``q`` the power spectral density of the acceleration noise (m^2/s^3).

``MeanRevertingVelocity``: the velocity is an Ornstein-Uhlenbeck process, ``dv = -v/tau dt
+ sqrt(q) dW`` per axis, with stationary standard deviation ``sigma`` (``q = 2 sigma^2 /
tau``): Singer's model (R. A. Singer, "Estimating optimal tracking filter performance for
manned maneuvering targets", IEEE Trans. AES 6(4), 1970; Bar-Shalom, Li & Kirubarajan 2001,
sec. 8.2.3) one derivative lower. A target whose direction of motion decorrelates within
``tau`` seconds (a robot that keeps turning) and that is not seen for a long time: the
predicted mean stops after about ``tau`` instead of drifting on with the last velocity,
and the position variance grows like a random walk's, ``2 sigma^2 tau dt``, not like
``sigma_v^2 dt^2``. With ``a = exp(-dt/tau)``, per axis::

    F(dt) = [[1, tau (1 - a)], [0, a]]
    Q(dt) = q [[tau^3/2 (2 dt/tau - 3 + 4a - a^2), tau^2/2 (1 - a)^2],
               [tau^2/2 (1 - a)^2,                  tau/2 (1 - a^2)]]

(the integrals ``int_0^dt e^{A s} B q B^T e^{A^T s} ds`` of the linear SDE with ``A = [[0, 1],
[0, -1/tau]]``; for ``dt/tau < 1e-2`` the position term is its series ``q (dt^3/3 - dt^4/(4
tau) + 7 dt^5/(60 tau^2) - dt^6/(24 tau^3))``, which avoids the cancellation; ``tau -> inf`` is the
constant-velocity model).

``Unicycle``: planar unicycle ``(x, y, theta)`` driven by velocity odometry
``u = (v, omega)``, integrated exactly along circular arcs, with control-noise
process covariance (Thrun, Burgard & Fox, *Probabilistic Robotics*, 2005,
sec. 5.3 and 7.4).
"""
from __future__ import annotations

import numpy as np

from dfusion.errors import ShapeError, ValidationError
from dfusion.geometry import wrap_angle
from dfusion.linalg import Array, as_vector
from dfusion.linalg import as_positive as _positive
from dfusion.models.base import MotionModel


class ConstantVelocity(MotionModel):
    """Nearly-constant-velocity model in ``dim`` (2 or 3) dimensions.

    Parameters
    ----------
    dim : int
        Number of position axes (2 or 3); the state has ``2 * dim`` components.
    q : float
        Acceleration noise spectral density (m^2 s^-3), ``> 0``.
    """

    is_linear = True

    def __init__(self, dim: int = 2, q: float = 0.1) -> None:
        if dim not in (1, 2, 3):
            raise ShapeError(f"ConstantVelocity dim must be 1, 2 or 3, got {dim}")
        if not (np.isfinite(q) and q > 0):
            raise ValidationError(f"ConstantVelocity q must be positive and finite, got {q}")
        self.axes = int(dim)
        self.dim = 2 * self.axes
        self.q = float(q)

    def __repr__(self) -> str:
        return f"ConstantVelocity(dim={self.axes}, q={self.q})"

    def F(self, dt: float, x: Array | None = None, u: Array | None = None) -> Array:
        d = self.axes
        F = np.eye(self.dim)
        F[:d, d:] = dt * np.eye(d)
        return F

    def f(self, x: Array, dt: float, u: Array | None = None) -> Array:
        return self.F(dt) @ np.asarray(x, dtype=float)

    def Q(self, dt: float, x: Array | None = None, u: Array | None = None) -> Array:
        d = self.axes
        Q = np.zeros((self.dim, self.dim))
        i = np.arange(d)
        Q[i, i] = self.q * dt**3 / 3.0
        Q[i, i + d] = Q[i + d, i] = self.q * dt**2 / 2.0
        Q[i + d, i + d] = self.q * dt
        return Q


class MeanRevertingVelocity(MotionModel):
    """Position and an Ornstein-Uhlenbeck velocity in ``dim`` (1-3) dimensions (module docstring).

    Parameters
    ----------
    dim : number of position axes; the state is ``[p_1..p_d, v_1..v_d]`` (as :class:`ConstantVelocity`).
    sigma : stationary standard deviation of each velocity component (m/s), ``> 0``.
    tau : velocity correlation time (s), ``> 0``.
    """

    is_linear = True

    def __init__(self, dim: int = 2, sigma: float = 0.05, tau: float = 5.0) -> None:
        if dim not in (1, 2, 3):
            raise ShapeError(f"MeanRevertingVelocity dim must be 1, 2 or 3, got {dim}")
        self.axes = int(dim)
        self.dim = 2 * self.axes
        self.sigma = _positive(sigma, "MeanRevertingVelocity sigma")
        self.tau = _positive(tau, "MeanRevertingVelocity tau")
        self.q = 2.0 * self.sigma**2 / self.tau

    def __repr__(self) -> str:
        return f"MeanRevertingVelocity(dim={self.axes}, sigma={self.sigma}, tau={self.tau})"

    def F(self, dt: float, x: Array | None = None, u: Array | None = None) -> Array:
        d = self.axes
        a = float(np.exp(-dt / self.tau))
        F = np.eye(self.dim)
        F[:d, d:] = -self.tau * float(np.expm1(-dt / self.tau)) * np.eye(d)
        F[d:, d:] = a * np.eye(d)
        return F

    def f(self, x: Array, dt: float, u: Array | None = None) -> Array:
        return self.F(dt) @ np.asarray(x, dtype=float)

    def Q(self, dt: float, x: Array | None = None, u: Array | None = None) -> Array:
        d, q, tau = self.axes, self.q, self.tau
        r = dt / tau
        b = -float(np.expm1(-r))                     # 1 - a, accurate for small r
        if r < 1e-2:
            pp = q * (dt**3 / 3.0 - dt**4 / (4.0 * tau) + 7.0 * dt**5 / (60.0 * tau**2) - dt**6 / (24.0 * tau**3))
        else:
            pp = q * tau**3 / 2.0 * (2.0 * r - 2.0 * b - b * b)    # 2r - 3 + 4a - a^2 with a = 1 - b
        pv = q * tau**2 / 2.0 * b * b
        vv = q * tau / 2.0 * b * (2.0 - b)           # 1 - a^2 = b (2 - b)
        Q = np.zeros((self.dim, self.dim))
        i = np.arange(d)
        Q[i, i] = pp
        Q[i, i + d] = Q[i + d, i] = pv
        Q[i + d, i + d] = vv
        return Q


def _sinc_and_derivative(a: float) -> tuple[float, float]:
    """``s(a) = sin(a)/a`` (``s(0) = 1``) and ``s'(a)``, both accurate for small ``a``."""
    s = float(np.sinc(a / np.pi))
    if abs(a) < 1e-3:  # Taylor series: the closed form below cancels catastrophically
        ds = -a / 3.0 + a**3 / 30.0 - a**5 / 840.0
    else:
        ds = (a * np.cos(a) - np.sin(a)) / a**2
    return s, ds


class Unicycle(MotionModel):
    """Planar unicycle (differential-drive) driven by velocity odometry.

    State ``x = (x, y, theta)`` (m, m, rad), control ``u = (v, omega)`` (forward speed
    in m/s and turn rate in rad/s, held constant over ``dt``). The exact
    integration of ``x' = v cos(theta), y' = v sin(theta), theta' = omega``
    (Thrun, Burgard & Fox, *Probabilistic Robotics*, 2005, sec. 5.3) is,
    for ``|omega| > 1e-9``, the circular arc::

        x_k     = x + v/omega (sin(theta + omega dt) - sin(theta))
        y_k     = y + v/omega (cos(theta) - cos(theta + omega dt))
        theta_k = wrap(theta + omega dt)

    evaluated in the algebraically identical, cancellation-free half-angle form
    ``x_k = x + v dt s(a) cos(theta + a)``, ``y_k = y + v dt s(a) sin(theta + a)``
    with ``a = omega dt / 2`` and ``s(a) = sin(a)/a``. For ``|omega| <= 1e-9`` the
    position moves on a straight line (``a = 0``, ``s = 1``). ``theta`` is wrapped
    to ``[-pi, pi)``.

    Process noise: the control is perturbed by white noise with power spectral
    densities ``std_v^2`` (m^2/s) and ``std_w^2`` (rad^2/s). Its mean over ``dt``
    has covariance ``M / dt`` with ``M = diag(std_v^2, std_w^2)``, and propagating
    it to first order through ``f`` (the control-noise model of *Probabilistic
    Robotics*, sec. 5.3 and 7.4, ``R_t = V_t M_t V_t^T``, here with ``M_t = M / dt``)
    gives::

        Q(dt, x, u) = V M V^T / dt + q_floor dt I,    V = df/du (3 x 2)

    ``Q`` therefore scales consistently with the step: the heading variance is
    exactly ``std_w^2 dt`` (a Wiener process), as is the along-track variance when
    ``omega = 0``. The ``q_floor dt I`` term keeps ``Q`` invertible (``V M V^T`` has
    rank 2). ``Q(0) = 0``.

    Parameters
    ----------
    std_v : float
        Forward-speed noise density (m / sqrt(s)), ``> 0``.
    std_w : float
        Turn-rate noise density (rad / sqrt(s)), ``> 0``.
    q_floor : float
        Spectral density of an extra isotropic noise term (units^2 / s), ``> 0``.
    """

    dim = 3
    is_linear = False
    angle_indices = (2,)
    #: Below this turn rate (rad/s) the position moves on a straight line.
    OMEGA_EPS = 1e-9

    def __init__(self, std_v: float, std_w: float, q_floor: float = 1e-6) -> None:
        self.std_v = _positive(std_v, "Unicycle std_v")
        self.std_w = _positive(std_w, "Unicycle std_w")
        self.q_floor = _positive(q_floor, "Unicycle q_floor")

    def __repr__(self) -> str:
        return f"Unicycle(std_v={self.std_v}, std_w={self.std_w}, q_floor={self.q_floor})"

    # -- helpers -----------------------------------------------------------------------
    def _terms(self, x: Array | None, dt: float, u: Array | None, who: str):
        if x is None:
            raise ValidationError(f"Unicycle is nonlinear: {who} needs the state x")
        x = as_vector(x, 3, "Unicycle state x")
        if u is None:
            v, w = 0.0, 0.0
        else:
            v, w = (float(c) for c in as_vector(u, 2, "Unicycle control u (v, omega)"))
        dt = float(dt)
        if not np.isfinite(dt):
            raise ValidationError(f"dt must be finite, got {dt}")
        a = 0.0 if abs(w) <= self.OMEGA_EPS else 0.5 * w * dt
        s, ds = _sinc_and_derivative(a)
        phi = x[2] + a
        return x, v, w, dt, s, ds, phi

    # -- MotionModel -------------------------------------------------------------------
    def f(self, x: Array, dt: float, u: Array | None = None) -> Array:
        x, v, w, dt, s, _, phi = self._terms(x, dt, u, "f")
        return np.array(
            [
                x[0] + v * dt * s * np.cos(phi),
                x[1] + v * dt * s * np.sin(phi),
                wrap_angle(x[2] + w * dt),
            ]
        )

    def F(self, dt: float, x: Array | None = None, u: Array | None = None) -> Array:
        """``df/dx = [[1, 0, -v dt s sin(theta+a)], [0, 1, v dt s cos(theta+a)], [0, 0, 1]]``."""
        x, v, w, dt, s, _, phi = self._terms(x, dt, u, "F")
        F = np.eye(3)
        F[0, 2] = -v * dt * s * np.sin(phi)
        F[1, 2] = v * dt * s * np.cos(phi)
        return F

    def V(self, dt: float, x: Array | None = None, u: Array | None = None) -> Array:
        """Jacobian ``df/du`` (3 x 2) of the exact motion, with ``a = omega dt / 2``::

            [[dt s cos(theta+a), v dt^2/2 (s'(a) cos(theta+a) - s sin(theta+a))],
             [dt s sin(theta+a), v dt^2/2 (s'(a) sin(theta+a) + s cos(theta+a))],
             [0,                 dt]]

        On the straight-line branch this is the limit ``omega -> 0`` (``s = 1``, ``s' = 0``).
        """
        x, v, w, dt, s, ds, phi = self._terms(x, dt, u, "V")
        c, sn = np.cos(phi), np.sin(phi)
        half = 0.5 * v * dt * dt
        return np.array(
            [
                [dt * s * c, half * (ds * c - s * sn)],
                [dt * s * sn, half * (ds * sn + s * c)],
                [0.0, dt],
            ]
        )

    def Q(self, dt: float, x: Array | None = None, u: Array | None = None) -> Array:
        """``V diag(std_v^2, std_w^2) V^T / dt + q_floor dt I`` (zero for ``dt = 0``)."""
        dt = float(dt)
        if not (np.isfinite(dt) and dt >= 0):
            raise ValidationError(f"Unicycle Q needs a finite dt >= 0, got {dt}")
        if dt == 0.0:
            return np.zeros((3, 3))
        V = self.V(dt, x, u)
        Vs = V * np.array([self.std_v, self.std_w])
        return (Vs @ Vs.T) / dt + self.q_floor * dt * np.eye(3)
