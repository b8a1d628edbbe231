r"""Extended Information Filter over a delayed-state trajectory.

The filter estimates the joint Gaussian of the states ``x(t_0) .. x(t_{m-1})``
at the times of a bounded window, in information form (URUS paper, sec. 6;
Eustice, Singh & Leonard, "Exactly Sparse Delayed-State Filters", ICRA 2005).

* **predict(t)** appends ``x(t)`` with the motion factor from the newest state
  (:class:`~dfusion.estimation.trajectory.MotionFactor`), linearized at the newest
  state's current mean. Only the blocks of the two states change.
* **update(t, z, sensor)** adds ``H^T R^-1 H`` and ``H^T R^-1 (z - h(mu) + H mu)``
  to the block of the state at ``t`` (linearized at that state's current smoothed
  mean), for any ``t`` inside the window: late and out-of-order measurements need
  no re-filtering. A ``t`` between two window states inserts a state there
  (exact for linear models).
* States beyond the window are marginalized (Schur complement onto the next one).

**Linearization.** Each factor is linearized once, when it is created: a motion
factor at the mean of the state it starts from, a measurement factor at the
smoothed mean of the state it observes. Factors are never relinearized later;
this is what makes information that was already sent to other nodes consistent
with what stays here. For linear models no linearization point is needed and
the filter equals the Kalman filter/RTS smoother exactly.

**Cost.** Storage is block-tridiagonal (``O(m n^2)``). The newest estimate is
kept current by cached forward elimination, so a cycle of predict, update at
the newest state and estimate costs O(1) in the window length; an update ``j``
states in the past costs O(j); ``estimate(t)`` for an older time and
``trajectory()`` cost O(m).
"""
from __future__ import annotations

import logging
from bisect import bisect_left
from dataclasses import replace
from typing import Iterator

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import (
    NonFiniteError,
    NotInitializedError,
    OutsideWindowError,
    ShapeError,
    TimeError,
    ValidationError,
)
from dfusion.estimation.trajectory import MotionFactor, TrajectoryInformation
from dfusion.linalg import (
    Array,
    as_matrix,
    as_spd,
    as_time,
    as_vector,
    check_psd,
    cholesky,
    symmetrize,
)
from dfusion.models.base import MeasurementModel, MotionModel

log = logging.getLogger(__name__)

#: Two time stamps closer than this (seconds) name the same state.
DEFAULT_TIME_TOL = 1e-9


_WHITENERS: dict[bytes, Array] = {}


def _whitener(R: ArrayLike, dim_z: int) -> Array:
    """``C^-1`` for the Cholesky factor ``R = C C^T`` of a validated ``R``.

    Whitening with it (``C^-1 H``, ``C^-1 r``) is the triangular solve done
    once; cached by the exact bytes of ``R``, so a changed ``R`` is validated anew.
    """
    a = np.asarray(R, dtype=np.float64)
    key = a.tobytes() + bytes(str(a.shape), "ascii")
    W = _WHITENERS.get(key)
    if W is None:
        C = cholesky(as_spd(a, dim_z, "measurement covariance R"), "measurement covariance R")
        W = np.linalg.solve(C, np.eye(dim_z))
        if len(_WHITENERS) > 1024:
            _WHITENERS.clear()
        _WHITENERS[key] = W
    return W


def measurement_information(
    sensor: MeasurementModel, z: ArrayLike, x_lin: Array
) -> tuple[Array, Array]:
    r"""Information added by measurement ``z`` linearized at ``x_lin``.

    ``Lam = H^T R^-1 H`` and ``y = H^T R^-1 (z - h(x_lin) + H x_lin)``
    (EIF measurement update; Thrun et al. 2005, Table 3.6, lines 6-7), computed
    with the Cholesky factor of ``R``. Raises :class:`ShapeError`,
    :class:`~dfusion.errors.NonFiniteError` or :class:`~dfusion.errors.NotPositiveDefiniteError` on bad input.
    """
    zv = as_vector(z, sensor.dim_z, "measurement z")
    if sensor.is_linear and not any(x_lin.tolist()):   # (a list test: cheaper than a numpy reduction)
        return _linear_information(sensor, zv, x_lin)
    W = _whitener(sensor.R, sensor.dim_z)
    H = as_matrix(sensor.H(x_lin), (sensor.dim_z, x_lin.shape[0]), "measurement Jacobian H")
    innov = sensor.residual(zv, sensor.h(x_lin)) + H @ x_lin
    innov = as_vector(innov, sensor.dim_z, "innovation")
    AH, Ar = W @ H, W @ innov  # C^-1 H, C^-1 r
    return symmetrize(AH.T @ AH), AH.T @ Ar


_LINEAR: dict[tuple, tuple[Array, Array, Array]] = {}


def _linear_information(sensor: MeasurementModel, zv: Array, x0: Array) -> tuple[Array, Array]:
    """:func:`measurement_information` of a linear sensor at ``x_lin = 0``.

    ``W = C^-1``, ``C^-1 H`` and ``Lam = H^T R^-1 H`` do not depend on ``z``: they are
    computed (and validated) once per exact ``(R, H)`` and cached; ``y`` is computed
    as in the general case, ``(C^-1 H)^T (C^-1 (z - h(0)))``. The returned ``Lam`` is
    read-only (shared by every measurement of that sensor).
    """
    R = np.asarray(sensor.R, dtype=np.float64)
    H = np.asarray(sensor.H(x0), dtype=np.float64)
    key = (R.tobytes(), R.shape, H.tobytes(), H.shape)
    cached = _LINEAR.get(key)
    if cached is None:
        W = _whitener(R, sensor.dim_z)
        H = as_matrix(H, (sensor.dim_z, x0.shape[0]), "measurement Jacobian H")
        AH = W @ H
        Lam = symmetrize(AH.T @ AH)
        Lam.flags.writeable = False
        if len(_LINEAR) > 1024:
            _LINEAR.clear()
        cached = _LINEAR[key] = (W, AH, Lam)
    W, AH, Lam = cached
    innov = sensor.residual(zv, sensor.h(x0))
    innov = as_vector(innov, sensor.dim_z, "innovation")
    return Lam, AH.T @ (W @ innov)


def _checked_square(a: ArrayLike, n: int, name: str, spd: bool = False) -> Array:
    """Fast validation of a model's ``n x n`` output (finite; symmetric PD if ``spd``)."""
    a = np.asarray(a, dtype=np.float64)
    if a.shape != (n, n):
        raise ShapeError(f"{name} must have shape {(n, n)}, got {a.shape}")
    if not np.isfinite(a).all():
        raise NonFiniteError(f"{name} contains NaN or inf")
    if spd:
        a = symmetrize(a)
        cholesky(a, name)
    return a


class CovarianceBounds:
    """Bounds on the smoothed covariances of some window states before a change, and the exact
    values on demand (:meth:`DelayedStateEIF.add_information_moments` with
    ``exact_covariances=False``).

    ``lower`` and ``upper`` (stacks ``(len, n, n)``, in the order of the entries) satisfy
    ``lower <= P^s <= upper`` in the Loewner order
    (:meth:`~dfusion.estimation.trajectory.TrajectoryInformation.covariance_bounds`).
    :meth:`exact` runs the covariance pass of the smoother on the trajectory as it was before
    the change (a snapshot: references, no copies) and gives the same values, bit for bit, as
    ``add_information_moments`` with exact covariances; it leaves the filter as it is.
    """

    __slots__ = ("lower", "upper", "_traj", "_before", "_rows", "_k0", "_exact")

    def __init__(self, lower: Array, upper: Array, traj: TrajectoryInformation, before: tuple,
                 rows: list[int], k0: int) -> None:
        self.lower, self.upper = lower, upper
        self._traj, self._before, self._rows, self._k0 = traj, before, rows, k0
        self._exact: list[Array] | None = None

    def exact(self) -> list[Array]:
        """The smoothed covariances before the change (computed once)."""
        if self._exact is None:
            tr = self._traj
            now = tr.snapshot()
            tr.restore(self._before)
            try:
                covs = tr.smoothed(self._k0)[1]
            finally:
                tr.restore(now)
            self._exact = [covs[r] for r in self._rows]
        return self._exact


class DelayedStateEIF:
    """Extended Information Filter over a bounded window of past states.

    Parameters
    ----------
    motion : MotionModel
        The motion model (``f, F, Q``).
    window : int, optional
        Number of states kept (``>= 1``). Older states are marginalized.
    horizon : float, optional
        Keep only states newer than ``latest_time - horizon`` seconds (the newest
        state is always kept). Either or both of ``window`` and ``horizon``.
    time_tol : float
        Time stamps closer than this are the same state.

    Attributes
    ----------
    motion : MotionModel
    window : int or None
    horizon : float or None
    marginalized : int
        Number of states marginalized out so far.

    Examples
    --------
    >>> import numpy as np
    >>> from dfusion import DelayedStateEIF
    >>> from dfusion.models import ConstantVelocity, PositionSensor
    >>> f = DelayedStateEIF(ConstantVelocity(dim=2, q=0.1), window=50)
    >>> f.initialize(0.0, np.zeros(4), np.eye(4))
    >>> f.predict(1.0)
    >>> f.update(0.5, [0.1, -0.2], PositionSensor(dim=2, std=0.5))  # late: inserts a state
    >>> mean, cov = f.estimate()
    """

    def __init__(
        self,
        motion: MotionModel,
        window: int | None = 100,
        *,
        horizon: float | None = None,
        time_tol: float = DEFAULT_TIME_TOL,
    ) -> None:
        if window is None and horizon is None:
            raise ValidationError("give a window (number of states) or a horizon (seconds)")
        if window is not None and (int(window) != window or window < 1):
            raise ValidationError(f"window must be a positive integer, got {window!r}")
        if horizon is not None and not (np.isfinite(horizon) and horizon > 0):
            raise ValidationError(f"horizon must be positive seconds, got {horizon!r}")
        self.motion = motion
        self.window = None if window is None else int(window)
        self.horizon = None if horizon is None else float(horizon)
        self.time_tol = float(time_tol)
        self.marginalized = 0
        self._times: list[float] = []
        self._traj: TrajectoryInformation | None = None
        self._linear_cache: dict[float, tuple[Array, Array]] = {}

    # ------------------------------------------------------------------ state
    @property
    def n(self) -> int:
        """State dimension."""
        return self.motion.dim

    @property
    def initialized(self) -> bool:
        return self._traj is not None

    @property
    def times(self) -> Array:
        """Times of the window states, oldest first (a copy)."""
        return np.array(self._times)

    @property
    def latest_time(self) -> float:
        self._require_init()
        return self._times[-1]

    @property
    def oldest_time(self) -> float:
        self._require_init()
        return self._times[0]

    def __len__(self) -> int:
        return len(self._times)

    def __repr__(self) -> str:
        span = f"[{self._times[0]:.3f}, {self._times[-1]:.3f}]" if self._times else "uninitialized"
        return f"DelayedStateEIF({self.motion!r}, window={self.window}, horizon={self.horizon}, states={len(self)} {span})"

    def _require_init(self) -> None:
        if self._traj is None:
            raise NotInitializedError("call initialize(t, mean, cov) first")

    def index_of(self, t: float) -> int | None:
        """Index of the window state at time ``t`` (within ``time_tol``), or None."""
        i = bisect_left(self._times, t - self.time_tol)
        if i < len(self._times) and abs(self._times[i] - t) <= self.time_tol:
            return i
        return None

    # ------------------------------------------------------------------ transaction
    def checkpoint(self) -> tuple:
        """The filter's state, to go back to with :meth:`restore` (cheap: no copy of unchanged blocks)."""
        self._require_init()
        return (self._traj.snapshot(), list(self._times), self.marginalized)

    def restore(self, checkpoint: tuple) -> None:
        """Go back to a :meth:`checkpoint` of this filter."""
        traj, times, marg = checkpoint
        self._traj.restore(traj)
        self._times, self.marginalized = list(times), marg

    class _Transaction:
        """Checkpoint on entry; restore on an exception (or always, with ``always=True``)."""

        def __init__(self, f: "DelayedStateEIF", always: bool = False) -> None:
            self.f = f
            self.always = always

        def __enter__(self) -> None:
            self.snap = self.f.checkpoint()

        def __exit__(self, exc_type, exc, tb) -> bool:
            if exc_type is not None or self.always:
                self.f.restore(self.snap)
            return False

    def transaction(self) -> "_Transaction":
        """Context manager: every change made inside is undone if an exception escapes."""
        self._require_init()
        return DelayedStateEIF._Transaction(self)

    def trial(self) -> "_Transaction":
        """Context manager: every change made inside is undone on leaving it (what-if evaluations)."""
        self._require_init()
        return DelayedStateEIF._Transaction(self, always=True)

    _transaction = transaction

    # ------------------------------------------------------------------ API
    def initialize(self, t: float, mean: ArrayLike, cov: ArrayLike) -> None:
        """Start the trajectory with one state ``x(t) ~ N(mean, cov)``."""
        tf = as_time(t)
        P = as_spd(cov, self.n, "initial covariance")
        m = as_vector(mean, self.n, "initial mean")
        self._traj = TrajectoryInformation(m, P)
        self._times = [tf]
        self.marginalized = 0

    def _motion_factor(self, x_from: Array | None, dt: float, u: Array | None) -> MotionFactor:
        """Linearize the motion model over ``dt`` at ``x_from`` (ignored if linear)."""
        mo = self.motion
        if dt <= 0:
            raise TimeError(f"motion step must be positive, got dt={dt}")
        if mo.is_linear and u is None:
            key = round(dt, 12)
            cached = self._linear_cache.get(key)
            if cached is None:
                F = _checked_square(mo.F(dt), self.n, "motion Jacobian F")
                Q = _checked_square(mo.Q(dt), self.n, "process noise Q", spd=True)
                if len(self._linear_cache) > 256:
                    self._linear_cache.clear()
                cached = self._linear_cache[key] = (F, Q)
            F, Q = cached
            return MotionFactor(F, Q, np.zeros(self.n), dt, None)
        x = np.zeros(self.n) if x_from is None else x_from
        F = _checked_square(mo.F(dt, x, u), self.n, "motion Jacobian F")
        Q = _checked_square(mo.Q(dt, x, u), self.n, "process noise Q", spd=True)
        fx = as_vector(mo.f(x, dt, u), self.n, "predicted state f(x)")
        # c = f(mu) - F mu, with angles of f(mu) kept continuous with F mu
        c = mo.residual(fx, F @ x) if mo.angle_indices else fx - F @ x
        return MotionFactor(F, Q, c, dt, None if u is None else np.array(u, float))

    def predict(self, t: float, u: ArrayLike | None = None) -> None:
        """Append the state ``x(t)``, ``t`` after the newest state, with control ``u``."""
        self._require_init()
        tf = as_time(t)
        last = self._times[-1]
        if tf <= last + self.time_tol:
            raise OutsideWindowError(
                f"predict({tf}) must be later than the newest state ({last}); "
                "use update() for past times"
            )
        uu = None if u is None else as_vector(u, None, "control u")
        with self._transaction():
            x = None if self.motion.is_linear else self._traj.latest()[0]
            factor = self._motion_factor(x, tf - last, uu)
            self._traj.append(factor)
            self._times.append(tf)
            self._enforce_window()

    def ensure_state(self, t: float) -> int:
        """Index of the window state at ``t``, inserting one between two states if needed.

        Raises :class:`OutsideWindowError` if ``t`` is older than the oldest state
        or newer than the newest (use :meth:`predict` to go forward).
        """
        self._require_init()
        tf = as_time(t)
        i = self.index_of(tf)
        if i is not None:
            return i
        if tf < self._times[0] or tf > self._times[-1]:
            raise OutsideWindowError(
                f"time {tf} is outside the window [{self._times[0]}, {self._times[-1]}]"
            )
        with self._transaction():
            self._insert(tf)
            self._enforce_window()
        return self.index_of(tf)

    def _insert(self, tf: float) -> int:
        a = bisect_left(self._times, tf) - 1
        ta, tb = self._times[a], self._times[a + 1]
        old = self._traj.factors[a]
        u = old.u
        if self.motion.is_linear and u is None:
            first = self._motion_factor(None, tf - ta, None)
            second = self._motion_factor(None, tb - tf, None)
        else:
            means, _ = self._traj.smoothed(a)
            xa = means[0]
            first = self._motion_factor(xa, tf - ta, u)
            xs = self.motion.f(xa, tf - ta, u)
            second = self._motion_factor(xs, tb - tf, u)
        if old.extra is not None:  # added process noise stays on the interval ending at tb
            second = replace(second, Q=symmetrize(second.Q + old.extra), extra=old.extra)
        self._traj.split(a, first, second)
        self._times.insert(a + 1, tf)
        return a + 1

    def add_process_noise(self, t: float, Q_extra: ArrayLike) -> None:
        """Add ``Q_extra`` to the process noise of the motion step that ends at the window
        state ``t`` (not the oldest): ``x(t) = F x(t_prev) + c + w``,
        ``w ~ N(0, Q + Q_extra)``. The marginal covariance of ``x(t)`` (before the
        information on ``x(t)`` itself) grows by ``Q_extra``; the states before are
        unchanged. Used to re-initialize a diverged belief (a recovery,
        :mod:`dfusion.estimation.innovation`): process noise is part of the motion model,
        not measurement information, so nothing that a fusion node exchanges changes.
        ``Q_extra`` must be symmetric positive semi-definite.
        """
        self._require_init()
        tf = as_time(t)
        Qx = as_matrix(Q_extra, (self.n, self.n), "extra process noise")
        check_psd(Qx, "extra process noise")
        Qx = symmetrize(Qx)
        k = self.index_of(tf)
        if k is None or k == 0:
            raise OutsideWindowError(f"time {tf} is not a window state after the oldest ({self._times[0]})")
        with self._transaction():
            old = self._traj.factors[k - 1]
            extra = Qx if old.extra is None else symmetrize(old.extra + Qx)
            self._traj.replace_factor(k - 1, replace(old, Q=symmetrize(old.Q + Qx), extra=extra))
            self._traj.latest()  # the belief must stay proper; otherwise roll back

    def update(self, t: float, z: ArrayLike, sensor: MeasurementModel) -> tuple[Array, Array]:
        """Fuse measurement ``z`` of ``sensor`` taken at time ``t`` (any time in the window).

        Returns the single-state information ``(H^T R^-1 H, H^T R^-1 (z - h + H mu))``
        added to the state at ``t`` (see :func:`measurement_information`).
        """
        self._require_init()
        tf = as_time(t)
        if tf < self._times[0] - self.time_tol or tf > self._times[-1] + self.time_tol:
            raise OutsideWindowError(
                f"measurement time {tf} is outside the window [{self._times[0]}, {self._times[-1]}]"
            )
        if getattr(sensor, "dim_z", None) is None:
            raise ShapeError(f"{sensor!r} is not a measurement model")
        with self._transaction():
            k = self.ensure_state(tf)
            if k is None:   # inserted, then marginalized at once by the horizon
                raise OutsideWindowError(f"time {tf} is outside the window [{self._times[0]}, {self._times[-1]}]")
            x_lin = np.zeros(self.n) if sensor.is_linear else self._mean_at(k)
            Lam, y = measurement_information(sensor, z, x_lin)
            self._traj.add_information(k, Lam, y)
            self._enforce_window()
        return Lam, y

    def add_information(self, t: float, info_matrix: ArrayLike, info_vector: ArrayLike) -> None:
        """Add a factor on the single state at ``t``: ``Omega[t,t] += info_matrix``.

        ``info_matrix`` must be symmetric positive semi-definite; ``t`` must be in
        the window (a state is inserted if needed).
        """
        self._require_init()
        tf = as_time(t)
        Lam = as_matrix(info_matrix, (self.n, self.n), "information matrix")
        check_psd(Lam, "information matrix")
        y = as_vector(info_vector, self.n, "information vector")
        with self._transaction():
            k = self.ensure_state(tf)
            self._traj.add_information(k, symmetrize(Lam), y)

    def add_information_batch(
        self, entries: list[tuple[float, Array, Array]], *, validate: bool = True
    ) -> None:
        """Add single-state factors ``(t, info_matrix, info_vector)`` in one transaction.

        With ``validate=False`` the matrices are taken as they are (symmetric,
        finite, right shape) and may be indefinite: a fusion node uses that to
        *replace* information it received earlier by the difference new - old.
        Either all entries are added or, on an error, none.
        """
        self._require_init()
        checked = []
        for t, Lam, y in entries:
            tf = as_time(t)
            if validate:
                Lam = as_matrix(Lam, (self.n, self.n), "information matrix")
                check_psd(Lam, "information matrix")
                Lam = symmetrize(Lam)
                y = as_vector(y, self.n, "information vector")
            checked.append((tf, Lam, y))
        with self._transaction():
            for tf, Lam, y in checked:
                k = self.index_of(tf)
                if k is None:
                    if tf < self._times[0] or tf > self._times[-1]:
                        raise OutsideWindowError(
                            f"time {tf} is outside the window [{self._times[0]}, {self._times[-1]}]"
                        )
                    k = self._insert(tf)
                # validated matrices are symmetrized above; the others are symmetric by contract
                self._traj.add_information(k, Lam, y)
            self._enforce_window()

    def add_information_moments(
        self, entries: list[tuple[float, Array, Array]], *, exact_covariances: bool = True
    ) -> tuple[list[Array], "list[Array] | CovarianceBounds", list[Array]]:
        """:meth:`add_information_batch` (``validate=False``) that also returns the smoothed
        moments at the entries' times: ``(means before, covariances before, means after)``,
        in the order of ``entries`` (raw means, angles not wrapped).

        With ``exact_covariances=False`` the covariances before are a :class:`CovarianceBounds`
        when the smoothing passes run: bounds from the cached forward terms
        (:meth:`TrajectoryInformation.covariance_bounds`), the exact values computed only if
        asked for (:meth:`CovarianceBounds.exact`), which saves the covariance pass.

        States are inserted for every entry time first (exact for linear models), so the
        moments before and after refer to the same trajectory; the window is enforced after
        the information is added, as in :meth:`add_information_batch`. Two smoothing passes
        from the oldest entry: O(window), each step two small products with the cached smoother
        gains (the pass after computes the gains of the states the entries changed, which the
        next pass before reuses). For consistency tests (:mod:`dfusion.fusion.guard`).
        """
        self._require_init()
        if not entries:
            return [], [], []
        if len(entries) == 1:   # (a steady-state message: one block at the newest state, whose smoothed
            t, Lam, y = entries[0]   # moments are the filtered ones: the same values without the passes)
            k = self.index_of(as_time(t))
            if k is not None and k == len(self._times) - 1:
                with self._transaction():
                    mean0, cov0 = self._traj.latest()
                    self._traj.add_information(k, Lam, y)
                    mean1 = self._traj.latest()[0]
                    self._enforce_window()
                return [mean0], [cov0], [mean1]
        with self._transaction():
            for t, _, _ in entries:
                tf = as_time(t)
                if self.index_of(tf) is None:
                    if tf < self._times[0] or tf > self._times[-1]:
                        raise OutsideWindowError(
                            f"time {tf} is outside the window [{self._times[0]}, {self._times[-1]}]"
                        )
                    self._insert(tf)
            idx = [self.index_of(as_time(t)) for t, _, _ in entries]
            k0 = min(idx)
            tr = self._traj
            if exact_covariances:
                means0, covs0 = tr.smoothed(k0)
                cov_out = [covs0[k - k0] for k in idx]
            else:
                means0 = tr.smoothed_means(k0)
                lower, upper = tr.covariance_bounds(idx)
                cov_out = CovarianceBounds(lower, upper, tr, tr.snapshot(), [k - k0 for k in idx], k0)
            for k, (_, Lam, y) in zip(idx, entries):
                tr.add_information(k, Lam, y)
            means1 = tr.smoothed_means(k0)
            out = ([means0[k - k0] for k in idx], cov_out, [means1[k - k0] for k in idx])
            self._enforce_window()
        return out

    def newest_moments(self) -> tuple[Array, Array]:
        """Filtered ``(mean, cov)`` of the newest state, the mean raw (angles not wrapped): what
        :meth:`add_information_moments` returns as the moments before a block at the newest
        state, bit for bit (the same cached forward pass). The arrays are the filter's own
        cache: read them, do not write into them (the filter replaces, never writes, its arrays)."""
        self._require_init()
        return self._traj.latest()

    def linearization_point(self, t: float) -> Array:
        """Current mean of the window state at ``t``, angles *not* wrapped.

        This is the point a new factor on that state must be linearized at:
        the stored factors keep angles continuous, so a wrapped mean could be
        ``2 pi`` away from them.
        """
        self._require_init()
        k = self.index_of(as_time(t))
        if k is None:
            raise OutsideWindowError(f"no window state at t={t}")
        return self._mean_at(k)

    def _mean_at(self, k: int) -> Array:
        if k == len(self._times) - 1:
            return self._traj.latest()[0]
        means, _ = self._traj.smoothed(k)
        return means[0]

    def estimate(self, t: float | None = None) -> tuple[Array, Array]:
        """``(mean, cov)`` of the newest state, or of the window state at ``t``.

        For ``t`` between two window states the marginal is predicted from the
        joint of its neighbours without changing the filter (exact for linear
        models).
        """
        self._require_init()
        if t is None:
            mean, cov = self._traj.latest()
            return self.motion.normalize(mean), cov
        tf = as_time(t)
        k = self.index_of(tf)
        if k is None:
            if tf < self._times[0] or tf > self._times[-1]:
                raise OutsideWindowError(
                    f"time {tf} is outside the window [{self._times[0]}, {self._times[-1]}]"
                )
            # evaluate on a throw-away insertion, then roll back
            snap = (self._traj.snapshot(), list(self._times))
            try:
                k = self._insert(tf)
                means, covs = self._traj.smoothed(k)
                return self.motion.normalize(means[0]), covs[0]
            finally:
                self._traj.restore(snap[0])
                self._times = snap[1]
        if k == len(self._times) - 1:
            mean, cov = self._traj.latest()
        else:
            means, covs = self._traj.smoothed(k)
            mean, cov = means[0], covs[0]
        return self.motion.normalize(mean), cov

    def trajectory(self) -> tuple[Array, Array, Array]:
        """``(times, means, covs)`` of every window state, oldest first (smoothed marginals)."""
        self._require_init()
        means, covs = self._traj.smoothed(0)
        return self.times, np.array([self.motion.normalize(m) for m in means]), np.array(covs)

    def information(self) -> tuple[Array, Array, Array, Array]:
        """``(times, D, U, eta)``: diagonal and super-diagonal blocks and vector (copies)."""
        self._require_init()
        D, U, eta = self._traj.blocks()
        return self.times, np.array(D), np.array(U).reshape(-1, self.n, self.n), np.array(eta)

    def dense_information(self) -> tuple[Array, Array]:
        """Full ``(Omega, eta)`` of the window (``m n`` square; for tests and inspection)."""
        self._require_init()
        return self._traj.dense()

    def _enforce_window(self) -> None:
        tr = self._traj
        while len(self._times) > 1 and (
            (self.window is not None and len(self._times) > self.window)
            or (self.horizon is not None and self._times[0] < self._times[-1] - self.horizon - self.time_tol)
        ):
            tr.drop_oldest()
            dropped = self._times.pop(0)
            self.marginalized += 1
            log.debug("marginalized state at t=%.6f", dropped)

    def __iter__(self) -> Iterator[float]:
        return iter(list(self._times))
