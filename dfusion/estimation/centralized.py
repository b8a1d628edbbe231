"""Centralized extended Kalman filter: the reference every decentralized result is compared to.

:class:`CentralizedEKF` receives every measurement of every sensor, with its time stamp,
in any arrival order, and returns the estimate that a single EKF processing all of them
in time order would produce. Decentralized estimators are judged by how close they get
to it (``docs/centralized.md``).

Equations (standard EKF; Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to
Tracking and Navigation*, 2001, ch. 5 and sec. 10.3; Thrun, Burgard & Fox,
*Probabilistic Robotics*, 2005, table 3.3). Predict over ``dt`` with control ``u``::

    F   = df/dx (x, dt, u)                    at the current estimate x
    x-  = f(x, dt, u)
    P-  = F P F^T + Q(dt, x, u)

update with a measurement ``z`` of a sensor ``(h, H, R)``::

    H   = dh/dx (x-)
    nu  = z (-) h(x-)                         (-) = sensor.residual (angles wrapped)
    S   = H P- H^T + R
    K   = P- H^T S^-1
    x   = x- + K nu
    P   = (I - K H) P- (I - K H)^T + K R K^T  (Joseph form, as filterpy computes it)

After every predict and update the state is passed through ``motion.normalize`` (angles
wrapped) and ``P`` is symmetrized. The arithmetic itself is done by
:class:`filterpy.kalman.ExtendedKalmanFilter`.

Out-of-sequence measurements are handled exactly by re-processing (the "reprocessing"
solution discussed by Bar-Shalom, "Update with out-of-sequence measurements in tracking:
exact solution", IEEE Trans. AES 38(3), 2002): a checkpoint ``(x, P)`` is kept after every
processed measurement, and a late measurement restarts the filter from the checkpoint just
before it.
"""
from __future__ import annotations

import bisect
import logging
import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from numpy.typing import ArrayLike

from dfusion.errors import NonFiniteError, ShapeError, TimeError, ValidationError
from dfusion.linalg import Array, as_spd, as_time, as_vector, symmetrize
from dfusion.models.base import MeasurementModel, MotionModel

__all__ = ["CentralizedEKF", "History"]

logger = logging.getLogger(__name__)

#: Grid points of the ``dt_max`` grid closer than ``GRID_MERGE_RTOL * dt_max`` to another
#: break point (a measurement, control or query time) are dropped, so that rounding in
#: ``t0 + k * dt_max`` never creates steps of a few ulps.
GRID_MERGE_RTOL = 1e-9


class History(NamedTuple):
    """Filtered estimates at every distinct processed measurement time.

    Attributes
    ----------
    times : ndarray, shape (K,)
        Distinct measurement times, increasing.
    means : ndarray, shape (K, n)
        Posterior mean after all measurements at ``times[k]``.
    covs : ndarray, shape (K, n, n)
        Posterior covariance after all measurements at ``times[k]``.
    """

    times: Array
    means: Array
    covs: Array


@dataclass
class _Measurement:
    """One buffered measurement (validated copies)."""

    t: float
    z: Array
    sensor: Any  # MeasurementModel or anything with dim_z, h, H, residual
    R: Array  # snapshot of sensor.R at add time: re-processing uses the same R
    runs: int = 0  # how many times this measurement has been processed
    frame: bool = False  # sensor is a frame update (add_frame): sensor.update(x, P) -> (x, P)


class _MotionEKF(ExtendedKalmanFilter):
    """filterpy's EKF whose prediction uses a :class:`MotionModel`.

    filterpy's ``predict`` propagates ``x`` with ``predict_x`` and ``P`` with ``self.F`` and
    ``self.Q``; here ``predict_x`` applies the nonlinear ``f`` and ``F``, ``Q`` are set to
    the motion model's Jacobian and noise at the current estimate before each step.
    The state is kept as a 1-D vector of length ``n`` (filterpy's arithmetic works for 1-D
    ``x`` and ``z`` in the EKF; every step checks the result shapes).
    """

    def __init__(self, motion: MotionModel) -> None:
        super().__init__(dim_x=motion.dim, dim_z=1)
        self.motion = motion
        self._dt = 0.0

    def predict_x(self, u: Any = 0) -> None:  # filterpy hook
        self.x = np.asarray(self.motion.f(self.x, self._dt, u), dtype=float)

    def predict_motion(self, dt: float, u: Array | None) -> None:
        """One EKF prediction over ``dt`` with control ``u`` (see module docstring)."""
        n = self.dim_x
        x = self.x
        self.F = _checked(self.motion.F(dt, x, u), (n, n), "motion.F")
        self.Q = _checked(self.motion.Q(dt, x, u), (n, n), "motion.Q")
        self._dt = dt
        self.predict(u)
        self._finish("predict")

    def update_measurement(self, m: _Measurement) -> None:
        """One EKF update with the buffered measurement ``m`` (or its frame update)."""
        if m.frame:
            x, P = m.sensor.update(self.x.copy(), self.P.copy())
            self.x, self.P = np.asarray(x, dtype=float), np.asarray(P, dtype=float)
            self._finish(f"frame update (t={m.t!r}, {m.sensor!r})")
            return
        self.dim_z = m.sensor.dim_z
        self.update(m.z, HJacobian=m.sensor.H, Hx=m.sensor.h, R=m.R, residual=m.sensor.residual)
        self._finish(f"update (t={m.t!r}, sensor={m.sensor!r})")

    def _finish(self, what: str) -> None:
        n = self.dim_x
        x = np.asarray(self.motion.normalize(self.x), dtype=float)
        if x.shape != (n,) or self.P.shape != (n, n):
            raise ShapeError(
                f"{what} produced a state of shape {x.shape} and covariance of shape "
                f"{self.P.shape}, expected ({n},) and ({n}, {n}); check the model's output shapes"
            )
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(self.P))):
            raise NonFiniteError(f"{what} produced NaN or inf")
        self.x = x
        self.P = symmetrize(self.P)


def _checked(a: ArrayLike, shape: tuple[int, ...], name: str) -> Array:
    a = np.asarray(a, dtype=float)
    if a.shape != shape:
        raise ShapeError(f"{name} must have shape {shape}, got {a.shape}")
    return a


class CentralizedEKF:
    """EKF over all measurements of all sensors, processed in time order whatever the arrival order.

    Parameters
    ----------
    motion : MotionModel
        Motion model ``x' = f(x, dt, u) + w``, ``w ~ N(0, Q(dt, x, u))``.
    t0 : float
        Time of the prior.
    mean : array_like, shape (n,)
        Prior mean at ``t0``.
    cov : array_like, shape (n, n)
        Prior covariance at ``t0``, symmetric positive definite.
    dt_max : float, optional
        If given, predictions are made in steps of at most ``dt_max``, cut at the grid
        ``t0 + k dt_max`` (k = 1, 2, ...), as a filter running on that fixed grid would.
        Without it, one prediction step is made from one measurement time to the next
        (cut only at control changes).

    Semantics
    ---------
    The estimate is a pure function of the prior, the set of measurements and the set of
    controls: measurements are processed in the order of the key ``(t, seq, arrival)``,
    where ``seq`` is given to :meth:`add` (default: the arrival counter) and ``arrival`` is
    the arrival counter. Measurements at distinct times are therefore processed in time
    order whatever their arrival order; measurements at *equal* times are processed by
    ``seq``, so pass an explicit ``seq`` (e.g. the sensor index) to make the result
    independent of arrival order for equal times too (with the default they are processed
    in arrival order; for linear models the result differs only by rounding).

    Between measurement times ``t_a < t_b`` the filter predicts with the control valid on
    each sub-interval: controls are piecewise constant, a control added at ``t_c`` holds
    from ``t_c`` until the next control, and the prediction is cut at every control time in
    ``(t_a, t_b)`` (and at grid points if ``dt_max`` is given). Before the first control,
    ``u = None`` is passed to the motion model.

    Buffer and cost
    ---------------
    Every measurement is kept, with the checkpoint ``(x, P)`` after it was processed
    (memory ``O(N n^2)``). Processing is lazy: :meth:`add` and :meth:`add_control` only
    validate, insert and invalidate the checkpoints after the insertion point; the next
    :meth:`estimate`, :meth:`history` or :meth:`advance` restarts from the last valid
    checkpoint (the one just before the earliest late arrival, not the beginning). A late
    measurement inserted before ``k`` already processed ones costs ``k + 1`` updates and
    their predictions; an in-order one costs one. Several late arrivals between two queries
    cost one re-run from the earliest of them. :attr:`n_updates` and :attr:`n_reprocessed`
    count the updates run.

    Errors
    ------
    Every public method either succeeds or raises from :mod:`dfusion.errors` leaving the
    filter exactly as it was. If a model fails while the buffer is processed (e.g. returns
    NaN), the error names the measurement and the committed checkpoints are kept.

    Not thread-safe.
    """

    def __init__(
        self,
        motion: MotionModel,
        t0: float,
        mean: ArrayLike,
        cov: ArrayLike,
        *,
        dt_max: float | None = None,
    ) -> None:
        for attr in ("dim", "f", "F", "Q", "normalize"):
            if not hasattr(motion, attr):
                raise TypeError(f"motion model {motion!r} has no attribute {attr!r}")
        self.motion = motion
        self.dim = int(motion.dim)
        self.t0 = as_time(t0, "t0")
        self._mean0 = np.asarray(motion.normalize(as_vector(mean, self.dim, "mean")), dtype=float)
        self._cov0 = as_spd(cov, self.dim, "cov")
        if dt_max is not None:
            dt_max = float(dt_max)
            if not (math.isfinite(dt_max) and dt_max > 0):
                raise ValidationError(f"dt_max must be positive and finite, got {dt_max}")
        self.dt_max: float | None = dt_max

        self._ekf = _MotionEKF(motion)
        # Measurement buffer, sorted by key; parallel lists.
        self._keys: list[tuple[float, int, int]] = []
        self._times: list[float] = []
        self._meas: list[_Measurement] = []
        self._ckpt: list[tuple[Array, Array] | None] = []
        self._n_valid = 0  # checkpoints [0, _n_valid) are valid
        self._arrivals = 0
        # Piecewise-constant controls, sorted by time.
        self._ctrl_times: list[float] = []
        self._ctrl_values: list[Array] = []
        self._t_advanced = self.t0
        #: Total number of EKF updates run (including re-runs).
        self.n_updates = 0
        #: Number of updates that re-ran a measurement already processed before.
        self.n_reprocessed = 0

    def __repr__(self) -> str:
        return (
            f"CentralizedEKF(motion={self.motion!r}, t0={self.t0}, measurements={len(self)}, "
            f"controls={len(self._ctrl_times)}, dt_max={self.dt_max})"
        )

    def __len__(self) -> int:
        """Number of buffered measurements."""
        return len(self._meas)

    @property
    def t_latest(self) -> float:
        """Default time of :meth:`estimate`: latest of ``t0``, measurement times and :meth:`advance` times."""
        t = self._t_advanced
        if self._times:
            t = max(t, self._times[-1])
        return t

    # ------------------------------------------------------------------ inputs
    def add(self, t: float, z: ArrayLike, sensor: MeasurementModel, *, seq: int | None = None) -> None:
        """Buffer the measurement ``z`` of ``sensor`` taken at time ``t``.

        Parameters
        ----------
        t : float
            Measurement time, ``>= t0`` (any arrival order).
        z : array_like, shape (dim_z,)
            The measurement (``(dim_z, 1)`` and ``(1, dim_z)`` are accepted too).
        sensor : MeasurementModel
            Its model ``(h, H, R, residual)``; ``R`` is copied now and reused on re-processing.
        seq : int, optional
            Order among measurements with the same ``t`` (default: the arrival counter).

        Raises
        ------
        TimeError
            ``t`` is not finite or is before ``t0``.
        ShapeError, NonFiniteError
            ``z`` has the wrong length or contains NaN/inf; the sensor's ``R``, ``h`` or
            ``H`` (tried at the prior mean) have the wrong shape.
        NotPositiveDefiniteError
            ``sensor.R`` is not symmetric positive definite.
        """
        tf = as_time(t)
        if tf < self.t0:
            raise TimeError(f"measurement time {tf} is before t0 = {self.t0}")
        for attr in ("dim_z", "h", "H", "R", "residual"):
            if not hasattr(sensor, attr):
                raise TypeError(f"sensor {sensor!r} has no attribute {attr!r}")
        m = int(sensor.dim_z)
        zv = as_vector(z, m, "z")
        R = as_spd(sensor.R, m, "sensor.R")
        try:  # shape trial at the prior mean; a model singular there (e.g. a range at 0) is not rejected
            with np.errstate(all="ignore"):
                hx, Hx = sensor.h(self._mean0.copy()), sensor.H(self._mean0.copy())
        except ShapeError:
            raise
        except (ArithmeticError, ValidationError):
            pass
        else:
            _checked(hx, (m,), "sensor.h(x)")
            _checked(Hx, (m, self.dim), "sensor.H(x)")
        self._insert(_Measurement(tf, zv, sensor, R), seq)

    def add_frame(self, t: float, frame: Any, *, seq: int | None = None) -> None:
        """Buffer a frame update at time ``t``: ``frame.update(x, P) -> (x, P)`` replaces the
        EKF update there, for updates that are not one measurement (the probabilistic data
        association of a camera frame's detections,
        :meth:`dfusion.frontends.camera.CameraFrontEnd.reference_frame`).

        It is processed in time order like a measurement (re-run when a late measurement
        precedes it); ``seq`` orders it among entries with the same ``t``.
        """
        tf = as_time(t)
        if tf < self.t0:
            raise TimeError(f"frame time {tf} is before t0 = {self.t0}")
        if not callable(getattr(frame, "update", None)):
            raise TypeError(f"frame {frame!r} has no update(x, P) method")
        self._insert(_Measurement(tf, np.zeros(0), frame, np.zeros((0, 0)), frame=True), seq)

    def _insert(self, entry: _Measurement, seq: int | None) -> None:
        """Buffer ``entry`` under the key ``(t, seq, arrival)``; invalidate the checkpoints after it."""
        if seq is None:
            seq = self._arrivals
        elif isinstance(seq, bool) or not isinstance(seq, (int, np.integer)):
            raise TypeError(f"seq must be an int, got {seq!r}")
        tf = entry.t
        key = (tf, int(seq), self._arrivals)

        i = bisect.bisect_right(self._keys, key)
        self._keys.insert(i, key)
        self._times.insert(i, tf)
        self._meas.insert(i, entry)
        self._ckpt.insert(i, None)
        self._arrivals += 1
        if i < self._n_valid:
            logger.debug(
                "late measurement at t=%g: %d processed measurement(s) after it will be re-run",
                tf, self._n_valid - i,
            )
            self._n_valid = i

    def add_control(self, t: float, u: ArrayLike) -> None:
        """Record the control ``u``, valid from time ``t`` until the next control.

        Controls may arrive in any order; one that changes the past invalidates the
        checkpoints of the measurements after ``t``. All controls must have the same length.

        Raises
        ------
        TimeError
            ``t`` is not finite, is before ``t0``, or a *different* control is already
            recorded at ``t`` (re-sending the same one is a no-op).
        ShapeError, NonFiniteError
            ``u`` is not a vector of the length of the previous controls, or not finite.
        """
        tf = as_time(t)
        if tf < self.t0:
            raise TimeError(f"control time {tf} is before t0 = {self.t0}")
        n_u = self._ctrl_values[0].shape[0] if self._ctrl_values else None
        uv = as_vector(u, n_u, "u")
        j = bisect.bisect_left(self._ctrl_times, tf)
        if j < len(self._ctrl_times) and self._ctrl_times[j] == tf:
            if np.array_equal(self._ctrl_values[j], uv):
                return
            raise TimeError(f"a different control is already recorded at t={tf}")
        self._ctrl_times.insert(j, tf)
        self._ctrl_values.insert(j, uv)
        i = bisect.bisect_right(self._times, tf)
        if i < self._n_valid:
            logger.debug(
                "control at t=%g changes the past: %d measurement(s) will be re-run", tf, self._n_valid - i
            )
            self._n_valid = i

    # ----------------------------------------------------------------- queries
    def estimate(self, t: float | None = None) -> tuple[Array, Array]:
        """Filtered estimate ``(mean, cov)`` at time ``t`` (copies).

        The result of processing, in time order, every buffered measurement with time
        ``<= t``, then predicting to ``t``. ``t`` defaults to :attr:`t_latest`. For ``t``
        before later measurements this is the *filtered* estimate at ``t`` (the later
        measurements are not used), not a smoothed one.

        Raises
        ------
        TimeError
            ``t`` is not finite or is before ``t0``.
        """
        tq = self.t_latest if t is None else as_time(t)
        if tq < self.t0:
            raise TimeError(f"time {tq} is before t0 = {self.t0}")
        self._process()
        i = bisect.bisect_right(self._times, tq)
        if i == 0:
            x, P, ts = self._mean0, self._cov0, self.t0
        else:
            ck = self._ckpt[i - 1]
            assert ck is not None
            x, P = ck
            ts = self._times[i - 1]
        ekf = self._ekf
        ekf.x, ekf.P = x.copy(), P.copy()
        self._predict_to(ts, tq)
        return ekf.x.copy(), ekf.P.copy()

    def advance(self, t: float) -> tuple[Array, Array]:
        """Predict the latest estimate to ``t`` without a measurement and return it.

        Afterwards :meth:`estimate` without argument returns the estimate at ``t`` (or at
        a later measurement time). Measurements at times before ``t`` may still be added.

        Raises
        ------
        TimeError
            ``t`` is not finite or is before :attr:`t_latest`.
        """
        tf = as_time(t)
        if tf < self.t_latest:
            raise TimeError(f"cannot advance to {tf}: the filter is already at {self.t_latest}")
        result = self.estimate(tf)
        self._t_advanced = tf
        return result

    def history(self) -> History:
        """Posterior means and covariances at every distinct processed measurement time.

        One entry per distinct time, after all measurements at that time (see :class:`History`).
        """
        self._process()
        n = self.dim
        last = len(self._times) - 1
        idx = [k for k in range(last + 1) if k == last or self._times[k + 1] != self._times[k]]
        times = np.array([self._times[k] for k in idx], dtype=float)
        means = np.empty((len(idx), n))
        covs = np.empty((len(idx), n, n))
        for j, k in enumerate(idx):
            ck = self._ckpt[k]
            assert ck is not None
            means[j], covs[j] = ck
        return History(times, means, covs)

    # -------------------------------------------------------------- internals
    def _control_at(self, t: float) -> Array | None:
        """Control valid at ``t`` (the last one recorded at or before ``t``), or None."""
        j = bisect.bisect_right(self._ctrl_times, t)
        return self._ctrl_values[j - 1] if j > 0 else None

    def _breakpoints(self, ta: float, tb: float) -> list[float]:
        """Times ``ta = s_0 < s_1 < ... < s_m = tb`` at which the prediction ``ta -> tb`` is cut."""
        lo = bisect.bisect_right(self._ctrl_times, ta)
        hi = bisect.bisect_left(self._ctrl_times, tb)
        pts = [ta, *self._ctrl_times[lo:hi], tb]
        if self.dt_max is not None:
            h = self.dt_max
            tol = GRID_MERGE_RTOL * h
            fixed = pts
            k = max(1, math.floor((ta - self.t0) / h))
            grid = []
            while True:
                g = self.t0 + k * h
                if g >= tb - tol:
                    break
                if g > ta + tol:
                    # drop grid points that nearly coincide with a control time
                    j = bisect.bisect_left(fixed, g)
                    near = any(abs(fixed[c] - g) <= tol for c in (j - 1, j) if 0 <= c < len(fixed))
                    if not near:
                        grid.append(g)
                k += 1
            pts = sorted(fixed + grid)
        return pts

    def _predict_to(self, ta: float, tb: float) -> None:
        """Predict the working filter from ``ta`` to ``tb >= ta`` (no-op when equal)."""
        if tb <= ta:
            return
        pts = self._breakpoints(ta, tb)
        for s, e in zip(pts[:-1], pts[1:]):
            self._ekf.predict_motion(e - s, self._control_at(s))

    def _process(self) -> None:
        """Run the buffer from the last valid checkpoint; commit only if everything succeeds."""
        start = self._n_valid
        end = len(self._meas)
        if start == end:
            return
        if start == 0:
            x, P, t = self._mean0, self._cov0, self.t0
        else:
            ck = self._ckpt[start - 1]
            assert ck is not None
            x, P = ck
            t = self._times[start - 1]
        if start > 0:
            logger.debug("restarting from the checkpoint at t=%g: %d measurement(s) to process", t, end - start)
        ekf = self._ekf
        ekf.x, ekf.P = x.copy(), P.copy()
        new: list[tuple[Array, Array]] = []
        for k in range(start, end):
            m = self._meas[k]
            self._predict_to(t, m.t)
            ekf.update_measurement(m)
            new.append((ekf.x.copy(), ekf.P.copy()))
            t = m.t
        # commit
        re = 0
        for k, ck in zip(range(start, end), new):
            self._ckpt[k] = ck
            m = self._meas[k]
            re += m.runs > 0
            m.runs += 1
        self.n_updates += len(new)
        self.n_reprocessed += re
        self._n_valid = end
