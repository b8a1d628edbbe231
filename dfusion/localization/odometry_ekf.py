r"""EKF fusing wheel odometry with scan-matching poses (survey 001, sec. III.A, eq. 5-8).

State ``x = (x, y, theta)``, covariance ``Sigma``. Odometry gives ``u = (Delta d, Delta theta)``,
the distance travelled and the heading change since the previous step. Prediction
(eq. 5-6)::

    x'     = x + (Delta d cos theta, Delta d sin theta, Delta theta)
    Sigma' = Fx Sigma Fx^T + Fu Sigma_u Fu^T
    Fx = [[1, 0, -Delta d sin theta], [0, 1, Delta d cos theta], [0, 0, 1]]
    Fu = [[cos theta, 0], [sin theta, 0], [0, 1]]

A scan matcher (e.g. :class:`~dfusion.localization.scan_matching.ScanMatcher`) gives a pose ``x_s``
with covariance ``Sigma_s``; the update (eq. 7-8) is the information-weighted average::

    x     = (Sigma'^-1 + Sigma_s^-1)^-1 (Sigma'^-1 x' + Sigma_s^-1 x_s)
    Sigma = (Sigma'^-1 + Sigma_s^-1)^-1

which is the Kalman update with ``H = I`` and ``R = Sigma_s``. It is computed in that form
(gain ``K = Sigma' (Sigma' + Sigma_s)^-1``, Joseph-form covariance) by
:class:`filterpy.kalman.ExtendedKalmanFilter`, with the heading innovation
``theta_s - theta'`` wrapped to ``[-pi, pi)`` -- eq. 7 applied literally to angles would
average ``+179 deg`` and ``-179 deg`` to ``0``.

Odometry noise: by default ``Sigma_u = diag(k_d^2 Delta d^2 + s_d^2, k_theta^2 Delta theta^2 +
k_dtheta^2 Delta d^2 + s_theta^2)`` (error growing with the motion, plus a floor); pass
``Sigma_u`` to :meth:`OdometryEKF.predict` to override it. The filter follows the
:class:`~dfusion.estimation.Estimator` protocol: ``predict(t, u)``, ``update(t, z, R)``, ``estimate()``.

Optionally a scan-matching pose whose squared Mahalanobis distance to the prediction
exceeds ``gate`` (chi-square, 3 degrees of freedom) is rejected; the NIS of every pose is
kept (:meth:`OdometryEKF.innovation`, ``last_nis``) and the filter can be restarted
(:meth:`OdometryEKF.reinitialize`).

:class:`ScanMatchingEKF` runs a scan matcher and this EKF together, with lock-out
detection (:class:`~dfusion.estimation.innovation.LockoutDetector`) and recovery by a
widened, confirmed search; :func:`predict_odometry_step` predicts with one odometry step
split into a turn and a move.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from numpy.typing import ArrayLike
from scipy.stats import chi2

from dfusion.errors import ShapeError, ValidationError
from dfusion.estimation.estimate import Estimate
from dfusion.estimation.innovation import LockoutDetector
from dfusion.geometry import se2_between, wrap_angle
from dfusion.linalg import Array, as_spd, as_vector, cholesky, symmetrize
from dfusion.localization.correlative import enclosing_covariance
from dfusion.reliability import covariance_reliability

logger = logging.getLogger(__name__)

__all__ = ["OdometryEKF", "ScanMatchingEKF", "ScanMatchOutcome", "predict_odometry_step"]




class OdometryEKF:
    """The odometry + scan-matching EKF of the survey (eq. 5-8), on filterpy.

    Parameters
    ----------
    x0 : (3,) initial pose
    P0 : (3, 3) initial covariance
    k_d, k_theta, k_dtheta : float
        Odometry noise growth (m/m, rad/rad, rad/m); see the module docstring.
    s_d, s_theta : float
        Odometry noise floor per step (m, rad).
    gate : float or None
        Chi-square threshold for rejecting scan-matching poses (``None``: accept all).
    """

    def __init__(
        self,
        x0: ArrayLike,
        P0: ArrayLike,
        *,
        k_d: float = 0.05,
        k_theta: float = 0.05,
        k_dtheta: float = 0.02,
        s_d: float = 1e-3,
        s_theta: float = 1e-3,
        gate: float | None = None,
    ) -> None:
        self.k_d, self.k_theta, self.k_dtheta = float(k_d), float(k_theta), float(k_dtheta)
        self.s_d, self.s_theta = float(s_d), float(s_theta)
        self.gate = None if gate is None else float(gate)
        self.ekf = ExtendedKalmanFilter(dim_x=3, dim_z=3)
        self.ekf.x = as_vector(x0, 3, "x0").reshape(3, 1)
        self.ekf.x[2, 0] = wrap_angle(self.ekf.x[2, 0])
        self.ekf.P = as_spd(P0, 3, "P0")
        self._u = (0.0, 0.0)
        self.ekf.predict_x = self._predict_x  # eq. 5 instead of filterpy's linear F x
        self.t: float | None = None
        self.rejected = 0
        #: NIS of the latest scan-matching pose given to :meth:`update`
        self.last_nis: float | None = None

    # -- state -------------------------------------------------------------------------
    @property
    def x(self) -> Array:
        return self.ekf.x[:, 0].copy()

    @property
    def P(self) -> Array:
        return self.ekf.P.copy()

    def estimate(self) -> Estimate:
        P = self.P
        return Estimate("odometry_ekf", self.t, self.x, P, covariance_reliability(P))

    # -- prediction (eq. 5-6) ----------------------------------------------------------
    def odometry_covariance(self, delta_d: float, delta_theta: float) -> Array:
        """Default ``Sigma_u`` for an increment (see the module docstring)."""
        return np.diag(
            [
                (self.k_d * delta_d) ** 2 + self.s_d**2,
                (self.k_theta * delta_theta) ** 2 + (self.k_dtheta * delta_d) ** 2 + self.s_theta**2,
            ]
        )

    @staticmethod
    def jacobians(x: ArrayLike, delta_d: float) -> tuple[Array, Array]:
        """``(Fx, Fu)`` of eq. 6 at pose ``x``."""
        th = float(np.asarray(x, dtype=float).reshape(-1)[2])
        c, s = math.cos(th), math.sin(th)
        Fx = np.array([[1.0, 0.0, -delta_d * s], [0.0, 1.0, delta_d * c], [0.0, 0.0, 1.0]])
        Fu = np.array([[c, 0.0], [s, 0.0], [0.0, 1.0]])
        return Fx, Fu

    def _predict_x(self, u=0) -> None:
        d, dth = self._u
        x = self.ekf.x
        th = x[2, 0]
        self.ekf.x = np.array([[x[0, 0] + d * math.cos(th)], [x[1, 0] + d * math.sin(th)], [wrap_angle(th + dth)]])

    def predict(self, t: float | None, u: ArrayLike, Sigma_u: ArrayLike | None = None) -> None:
        """Eq. 5-6 with the odometry increment ``u = (delta_d, delta_theta)`` that ends at time ``t``
        (``None``: the filter's time does not change, for an increment split in parts).

        :func:`dfusion.models.odometry_increment` gives ``u`` from two odometry poses.
        """
        d, dth = (float(v) for v in np.asarray(u, dtype=float).reshape(2))
        if not (math.isfinite(d) and math.isfinite(dth)):
            raise ValidationError("odometry increment must be finite")
        Su = self.odometry_covariance(d, dth) if Sigma_u is None else np.asarray(Sigma_u, dtype=float)
        if Su.shape != (2, 2):
            raise ShapeError("Sigma_u must be 2 x 2")
        Fx, Fu = self.jacobians(self.ekf.x, d)
        self.ekf.F = Fx
        self.ekf.Q = Fu @ Su @ Fu.T
        self._u = (d, dth)
        self.ekf.predict()
        self.ekf.P = symmetrize(self.ekf.P)
        if t is not None:
            self.t = float(t)

    # -- update (eq. 7-8) --------------------------------------------------------------
    def innovation(self, z: ArrayLike, R: ArrayLike) -> tuple[Array, Array, float]:
        """Innovation ``nu = x_s - x`` of a scan-matching pose ``z = x_s`` with covariance
        ``R = Sigma_s`` (heading wrapped), its covariance ``S = Sigma + Sigma_s`` and the NIS
        ``nu^T S^-1 nu`` (Cholesky solve)."""
        z = as_vector(z, 3, "scan-matching pose")
        R = as_spd(R, 3, "scan-matching covariance")
        nu = z - self.x
        nu[2] = wrap_angle(nu[2])
        S = symmetrize(self.ekf.P + R)
        L = cholesky(S, "innovation covariance")
        w = np.linalg.solve(L, nu)
        return nu, S, float(w @ w)

    def update(self, t: float | None, z: ArrayLike, R: ArrayLike) -> bool:
        """Fuse a scan-matching pose ``z = x_s`` with covariance ``R = Sigma_s`` matched at time ``t``
        (the filter's time: odometry moves the pose, not the match); ``False`` if gated out.

        The NIS of the measurement is kept in ``last_nis`` (also when it is gated out).
        """
        z = as_vector(z, 3, "scan-matching pose")
        R = as_spd(R, 3, "scan-matching covariance")
        _, _, nis = self.innovation(z, R)
        self.last_nis = nis
        if self.gate is not None and nis > self.gate:
            self.rejected += 1
            return False

        def residual(a, b):
            d = np.asarray(a, dtype=float).reshape(3, 1) - np.asarray(b, dtype=float).reshape(3, 1)
            d[2, 0] = wrap_angle(d[2, 0])
            return d

        self.ekf.update(z.reshape(3, 1), HJacobian=lambda x: np.eye(3), Hx=lambda x: x, R=R, residual=residual)
        self.ekf.x[2, 0] = wrap_angle(self.ekf.x[2, 0])
        self.ekf.P = symmetrize(self.ekf.P)
        return True

    def reinitialize(self, x: ArrayLike, P: ArrayLike) -> None:
        """Restart the filter at ``x`` with covariance ``P`` (after a divergence; time and
        counters are kept)."""
        self.ekf.x = as_vector(x, 3, "x").reshape(3, 1)
        self.ekf.x[2, 0] = wrap_angle(self.ekf.x[2, 0])
        self.ekf.P = as_spd(P, 3, "P")


# ----------------------------------------------------------------------------------------
# Odometry step split into a turn and a move
# ----------------------------------------------------------------------------------------
def predict_odometry_step(ekf: OdometryEKF, odom0: ArrayLike, odom1: ArrayLike, t: float | None = None) -> None:
    """Predict ``ekf`` with the odometry step ``odom0 -> odom1`` as two eq. 5-6 steps.

    Eq. 5 moves the robot along its heading; a robot that turns in place moves its laser a
    few cm *sideways*, which one ``(Delta d, Delta theta)`` step would put along the
    heading. So the step is split exactly into a turn ``rot1`` towards the direction of
    travel and a ``(trans, rot2)`` step (``trans < 0`` for a step backwards); the composition
    of the two equals the SE(2) increment ``odom0^-1 odom1``. The noise of the whole step,
    ``(k_d trans)^2 + s_d^2`` and ``(k_theta Delta theta)^2 + (k_dtheta trans)^2 +
    s_theta^2``, goes into the second part (``rot1`` is an arbitrary angle when ``trans`` is
    tiny and must not scale the noise).
    """
    d = se2_between(as_vector(odom0, 3, "odom0"), as_vector(odom1, 3, "odom1"))
    trans = math.hypot(d[0], d[1])
    rot1 = math.atan2(d[1], d[0]) if trans > 1e-9 else 0.0
    if abs(rot1) > math.pi / 2:
        rot1 = float(wrap_angle(rot1 + math.pi))
        trans = -trans
    rot2 = float(wrap_angle(d[2] - rot1))
    ekf.predict(None, (0.0, rot1), Sigma_u=np.diag([1e-12, 1e-12]))
    ekf.predict(t, (trans, rot2), Sigma_u=ekf.odometry_covariance(abs(trans), float(d[2])))


# ----------------------------------------------------------------------------------------
# Scan matching + EKF with divergence monitoring and recovery
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ScanMatchOutcome:
    """What :meth:`ScanMatchingEKF.correct` did with one scan.

    ``status`` is ``"accepted"`` (fused), ``"gated"`` (rejected by the chi-square gate),
    ``"failed"`` (no usable match), ``"recovered"`` (a divergence alarm, and the filter was
    re-initialized from a confirmed alternative) or ``"recovery_failed"`` (an alarm, and no
    alternative confirmed yet). ``nis`` is the NIS of the match from the prediction
    (``None`` without a match) and ``alarm`` the reason of a divergence alarm.
    """

    status: str
    nis: float | None = None
    alarm: str | None = None


class ScanMatchingEKF:
    r"""The odometry EKF fed by a scan matcher, with lock-out detection and recovery.

    Each scan is matched from the EKF prediction; the match updates the EKF with the
    covariance ``Sigma_s = Sigma_ICP + Sigma_0``: ``Sigma_ICP`` from the matcher's residuals
    (:func:`~dfusion.localization.scan_matching.icp_covariance`) and ``Sigma_0`` (``cov_floor``) for
    the error the residuals of one scan cannot show (the map's registration error and its
    cell size). The EKF's chi-square gate rejects matches that disagree with the
    prediction; a :class:`~dfusion.estimation.innovation.LockoutDetector` watches the
    NIS of every match and the run of rejected (gated or failed) ones.

    **Correlative start and covariance** (``correlative``, a
    :class:`~dfusion.localization.correlative.CorrelativeScanMatcher`; optional). Before
    ICP, the scan is scored at every pose of a lattice over the box around the
    ``correlative_probability`` region of the prediction (at most ``correlative_cap``;
    :meth:`~dfusion.localization.correlative.CorrelativeScanMatcher.window`), and ICP
    starts from the lattice pose of highest posterior (scan likelihood times the
    predicted Gaussian) inside the prediction's ``correlative_probability`` ellipsoid
    instead of the prediction (Olson, ICRA 2009: ICP alone stops in
    the local minimum nearest to its start, e.g. a heading a turn's odometry error put
    off; the prior keeps the start from a far look-alike the window holds). The match is fused with ``enclosing_covariance(Sigma_ICP + Sigma_0, K_x)``,
    ``K_x`` the second moment of the normalized scan likelihood over the lattice about the
    ICP pose (:meth:`~dfusion.localization.correlative.CorrelativeResult.covariance_about`):
    in every direction the larger of the two, so a match that slid along a corridor, where
    the likelihood is flat, is fused with the spread of the likelihood along it, not with
    the curvature of ICP's cost at its end point.

    **Alternative hypotheses.** A rejection means that the filter or the match is wrong.
    Which one, a single scan cannot tell (a scan matcher sliding along a corridor is
    rejected exactly like a correct match against a drifted filter). So every rejected
    match starts an *alternative*: an :class:`OdometryEKF` with the same noise model at the
    match, covariance ``Sigma_s``, predicted with the same odometry. The alternatives of
    the current run of rejections are kept (at most ``max_alternatives``, the most
    recent).

    **Recovery** (on a divergence alarm). The scan is matched again from several starts:
    the prediction ``x^-``, the sigma points ``x^- +- sqrt(chi2.ppf(p, 3) lambda_i) v_i`` on
    the principal axes ``(lambda_i, v_i)`` of the predicted covariance (the boundary of
    its ``p = recovery_probability`` region), every alternative's prediction and any
    ``seeds`` given (e.g. another localizer's estimate); first with a correspondence
    distance widened by ``recovery_widen``, then refined with the normal one. The
    candidates are ranked by the robust (Cauchy) cost of the scan,
    :meth:`~dfusion.localization.scan_matching.ScanMatcher.robust_cost` (minus a log-likelihood up
    to a constant). The best one is used only if

    * it is *unambiguous*: no other candidate fits the scan about as well (cost within
      ``chi2.ppf(p, 3) / 2``, a likelihood-ratio test) while lying outside the gate of the
      best (a corridor, where matches slide along the walls), and
    * it is *confirmed*: it passes the chi-square gate of an alternative, i.e. two scans,
      matched independently, agree on where the robot is, up to the odometry between them
      (M-of-N confirmation, M = N = 2, of track initiation; Blackman & Popoli, *Design and
      Analysis of Modern Tracking Systems*, 1999, sec. 3.5).

    Then the confirming alternative is updated with it, and the EKF restarts with that
    alternative's mean and covariance (the covariance of two fused matches and the
    odometry between them: honest, not the drifted filter's). Otherwise the recovery waits
    (``recovery_failed``): the candidates become the alternatives and the next scan tries
    again, while the filter keeps predicting, its growing covariance widening the next
    search. Events are logged (``logging``, INFO) and counted in :attr:`stats`.
    """

    def __init__(
        self,
        matcher,
        ekf: OdometryEKF,
        *,
        cov_floor: ArrayLike | None = None,
        monitor: LockoutDetector | None = None,
        recovery: bool = True,
        recovery_probability: float = 0.99,
        recovery_widen: float = 2.0,
        max_alternatives: int = 16,
        correlative=None,
        correlative_probability: float = 0.99,
        correlative_cap: ArrayLike = (1.0, 1.0, 0.3),
    ) -> None:
        self.matcher = matcher
        #: optional :class:`~dfusion.localization.correlative.CorrelativeScanMatcher`: the
        #: start of ICP and a covariance from the whole score surface (class docstring)
        self.correlative = correlative
        if not 0.0 < correlative_probability < 1.0:
            raise ValidationError("correlative_probability must be in (0, 1)")
        self.correlative_probability = float(correlative_probability)
        self.correlative_cap = as_vector(correlative_cap, 3, "correlative_cap")
        self._corr_gate = float(chi2.ppf(self.correlative_probability, 3))
        self.last_correlative = None
        wide = None if matcher.max_correspondence_distance is None else recovery_widen * matcher.max_correspondence_distance
        self.wide_matcher = matcher.replace(max_correspondence_distance=wide)
        self.ekf = ekf
        self.cov_floor = np.zeros((3, 3)) if cov_floor is None else symmetrize(np.asarray(cov_floor, dtype=float))
        if self.cov_floor.shape != (3, 3) or np.any(np.linalg.eigvalsh(self.cov_floor) < 0):
            raise ValidationError("cov_floor must be a 3 x 3 positive semi-definite matrix")
        gate_p = 0.999 if ekf.gate is None else float(chi2.cdf(ekf.gate, 3))
        self.gate = float(chi2.ppf(gate_p, 3)) if ekf.gate is None else ekf.gate
        self.monitor = monitor if monitor is not None else LockoutDetector(3, gate_probability=gate_p)
        self.recovery = bool(recovery)
        if not 0.0 < recovery_probability < 1.0:
            raise ValidationError("recovery_probability must be in (0, 1)")
        self.recovery_probability = float(recovery_probability)
        self.max_alternatives = int(max_alternatives)
        self._chi2_p = float(chi2.ppf(self.recovery_probability, 3))
        self.alternatives: list[OdometryEKF] = []
        self.stats = {"accepted": 0, "gated": 0, "failed": 0, "alarms": 0, "recoveries": 0, "recovery_failures": 0}
        self.last_match = None

    @property
    def x(self) -> Array:
        return self.ekf.x

    @property
    def P(self) -> Array:
        return self.ekf.P

    def estimate(self) -> Estimate:
        """The EKF's current belief."""
        P = self.ekf.P
        return Estimate("scan_matching_ekf", self.ekf.t, self.ekf.x, P, covariance_reliability(P))

    def predict(self, t: float | None, u: tuple[ArrayLike, ArrayLike]) -> None:
        """Predict the filter and its alternatives to time ``t`` with one odometry step
        ``u = (odom0, odom1)`` (two odometry poses; :func:`predict_odometry_step`)."""
        odom0, odom1 = u
        predict_odometry_step(self.ekf, odom0, odom1, t)
        for alt in self.alternatives:
            predict_odometry_step(alt, odom0, odom1, t)

    def _match(self, points: Array, start: Array, matcher=None):
        try:
            return (matcher or self.matcher).match(points, start)
        except ValidationError:
            return None

    def _alternative(self, pose: Array, cov: Array) -> OdometryEKF:
        e = self.ekf
        alt = OdometryEKF(pose, cov, k_d=e.k_d, k_theta=e.k_theta, k_dtheta=e.k_dtheta, s_d=e.s_d,
                          s_theta=e.s_theta, gate=self.gate)
        alt.t = e.t
        return alt

    def _keep(self, alts: list[OdometryEKF]) -> None:
        self.alternatives = alts[-self.max_alternatives:]

    def update(self, t: float | None, z: ArrayLike, seeds: tuple = ()) -> bool:
        """Match the scan points ``z`` (``(K, 2)``, laser frame) taken at ``t`` and fuse them
        (:meth:`correct`); whether the filter used the scan (accepted, or recovered with it)."""
        return self.correct(t, z, seeds).status in ("accepted", "recovered")

    def correct(self, t: float | None, points: ArrayLike, seeds: tuple = ()) -> ScanMatchOutcome:
        """Match the scan points ``(K, 2)`` (laser frame) taken at ``t`` (the filter's time)
        from the prediction and fuse them; ``seeds``: extra starts for a recovery
        (:meth:`recovery_starts`)."""
        pts = np.asarray(points, dtype=float)
        corr = None
        start = self.ekf.x
        if self.correlative is not None and pts.shape[0] >= 3:
            w = self.correlative.window(self.ekf.P, self.correlative_probability, self.correlative_cap)
            corr = self.correlative.match(pts, self.ekf.x, w, prior_cov=self.ekf.P, prior_gate=self._corr_gate)
            start = corr.pose
        self.last_correlative = corr
        res = self._match(pts, start) if pts.shape[0] >= 3 else None
        self.last_match = res
        nis = None
        if res is None:
            status, accepted = "failed", False
        else:
            R = res.covariance + self.cov_floor
            if corr is not None:
                R = enclosing_covariance(R, corr.covariance_about(res.pose))
            accepted = self.ekf.update(t, res.pose, R)
            nis = self.ekf.last_nis
            status = "accepted" if accepted else "gated"
        self.stats[status] += 1
        alarm = self.monitor.record(nis, accepted)
        if alarm is None:
            if accepted:
                self.alternatives = []
            elif res is not None:
                self._keep(self.alternatives + [self._alternative(res.pose, R)])
            return ScanMatchOutcome(status, nis)
        self.stats["alarms"] += 1
        if not self.recovery:
            return ScanMatchOutcome(status, nis, alarm.reason)
        ok = self.recover(pts, seeds, reason=alarm.reason, t=t)
        return ScanMatchOutcome("recovered" if ok else "recovery_failed", nis, alarm.reason)

    def recovery_starts(self, seeds: tuple = ()) -> list[Array]:
        """The prediction, the sigma points of its ``recovery_probability`` region, the
        alternatives' predictions and ``seeds``."""
        x0, P0 = self.ekf.x, self.ekf.P
        lam, V = np.linalg.eigh(symmetrize(P0))
        r = np.sqrt(self._chi2_p * np.maximum(lam, 0.0))
        starts = [x0]
        for i in range(3):
            for sgn in (1.0, -1.0):
                s_ = x0 + sgn * r[i] * V[:, i]
                s_[2] = wrap_angle(s_[2])
                starts.append(s_)
        starts.extend(a.x for a in self.alternatives)
        starts.extend(as_vector(s_, 3, "seed") for s_ in seeds)
        return starts

    def recover(self, points: ArrayLike, seeds: tuple = (), reason: str = "", t: float | None = None) -> bool:
        """Widened search and confirmation against the alternatives (class docstring) for
        the scan points taken at ``t``; ``True`` if the filter was re-initialized."""
        pts = np.asarray(points, dtype=float)
        cands = []
        for st in self.recovery_starts(seeds):
            wide = self._match(pts, st, self.wide_matcher)
            if wide is None:
                continue
            res = self._match(pts, wide.pose)
            if res is not None and not any(np.allclose(res.pose, c.pose, atol=1e-3) for c in cands):
                cands.append(res)
        if not cands:
            self.stats["recovery_failures"] += 1
            logger.info("scan matching: recovery (%s) failed: no match from %s", reason, np.round(self.ekf.x, 3))
            return False
        scales = [c.scale for c in cands if math.isfinite(c.scale)]
        scale = float(np.median(scales)) if scales else max(float(np.median([c.rmse for c in cands])), 1e-3)
        costs = np.array([self.matcher.robust_cost(pts, c.pose, scale) for c in cands])
        b = int(np.argmin(costs))
        Rb = cands[b].covariance + self.cov_floor
        if logger.isEnabledFor(logging.DEBUG):
            for c, cost in zip(cands, costs):
                logger.debug("  candidate %s cost %.1f inliers %.2f sd %s", np.round(c.pose, 3), cost - costs[b],
                             c.inlier_fraction, np.round(np.sqrt(np.diag(c.covariance)), 3))
        # ambiguous: another candidate fits the scan about as well (log-likelihood ratio
        # below chi2.ppf(p, 3) / 2) but is a different pose (outside the gate of the best)
        ambiguous = False
        for i, c in enumerate(cands):
            if i == b or costs[i] - costs[b] > 0.5 * self._chi2_p:
                continue
            d = c.pose - cands[b].pose
            d[2] = wrap_angle(d[2])
            S = symmetrize(Rb + c.covariance + self.cov_floor)
            if float(d @ np.linalg.solve(S, d)) > self.gate:
                ambiguous = True
                break
        best = None
        if not ambiguous:
            for alt in self.alternatives:
                _, _, nis = alt.innovation(cands[b].pose, Rb)
                if nis <= self.gate and (best is None or nis < best[2]):
                    best = (b, alt, nis)
        if best is None:
            self.stats["recovery_failures"] += 1
            why = "the scan fits several poses" if ambiguous else f"no alternative of {len(self.alternatives)} confirms it"
            logger.info("scan matching: recovery (%s) waits: %s (%d candidates)", reason, why, len(cands))
            self._keep(self.alternatives + [self._alternative(cands[i].pose, cands[i].covariance + self.cov_floor)
                                            for i in np.argsort(-costs)])
            return False
        i, alt, _ = best
        alt.update(t, cands[i].pose, cands[i].covariance + self.cov_floor)
        x_old = self.ekf.x
        self.ekf.reinitialize(alt.x, alt.P)
        self.monitor.reset()
        self.alternatives = []
        self.stats["recoveries"] += 1
        logger.info("scan matching: recovery (%s) from %s to %s (best of %d candidates, confirmed by the previous scan)",
                    reason, np.round(x_old, 3), np.round(self.ekf.x, 3), len(cands))
        return True
