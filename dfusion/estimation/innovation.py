r"""Innovation monitoring for EKF-type estimators: robust weights, lock-out detection, recovery.

An estimator tests each measurement's innovation ``nu`` (dimension ``m``) against its
predicted covariance ``S`` with the normalized innovation squared
``NIS = nu^T S^-1 nu``, which is ``chi2(m)`` distributed while the estimator is
consistent, and the innovations of a consistent filter are white (Bar-Shalom, Li &
Kirubarajan, *Estimation with Applications to Tracking and Navigation*, 2001, sec. 5.4).
:class:`InnovationMonitor` turns these facts into decisions, every threshold a
chi-square quantile with a stated probability (:class:`MonitorSettings`):

1. **Gate.** ``NIS > chi2_m^-1(gate_probability)`` (default 0.999, 13.8 for ``m = 2``):
   the measurement is rejected (an inlier is rejected with probability 1e-3).
2. **Huber weight** for accepted measurements (Huber, *Robust Statistics*, 1981; the
   Huber-weighted Kalman update of Karlgaard & Schaub, JGCD 30(3), 2007): with the
   Mahalanobis distance ``d = sqrt(NIS)`` and ``c^2 = chi2_m^-1(huber_probability)``
   (default 0.95, 5.99 for ``m = 2``), the measurement is fused with the noise
   ``R / w``, ``w = min(1, c / d)``. 95 % of inliers keep ``w = 1``. In information form
   this is ``w H^T R^-1 H``: additive information, so a fusion node can exchange it
   like any other measurement.
3. **Divergence**, modelled as a *jump* ``delta`` of the monitored state block ``b``
   that the estimator does not know about: the innovations then carry
   ``nu_i = H_i delta + (white, covariance S_i)``, ``H_i = dh/dx_b`` (Willsky & Jones,
   "A generalized likelihood ratio approach to the detection and estimation of jumps in
   linear systems", IEEE TAC 21(1), 1976). With the whitened ``u_i = L_i^-1 nu_i``,
   ``G_i = L_i^-1 H_i`` (``S_i = L_i L_i^T``), the jump's estimate from a set of
   innovations is ``delta = F^+ g``, ``F = sum G_i^T G_i``, ``g = sum G_i^T u_i``, with
   covariance ``F^+``. Two tests, each with false-alarm probability ``false_alarm``
   (default 1e-3):

   * **lock-out**: every measurement of the last ``k`` *looks* was rejected (a look: the
     measurements with one time stamp, e.g. one scan's landmarks), with
     ``k = ceil(log(false_alarm) / log(max_outlier_rate + 1 - gate_probability))``
     (default ``max_outlier_rate = 0.25``: ``k = 5``; a consistent estimator rejects a
     measurement with probability ``1 - gate_probability`` plus the outlier rate, so
     ``k`` independent rejections in a row have probability at most ``false_alarm``).
     The independent trials are looks, not measurements: the measurements of one look
     share the belief's error at that time, and since none of them is fused, nothing
     removes it between them; their innovations are correlated, and a belief error of
     3-4 standard deviations (a fast turn) gets all of them rejected at once. Counting
     them as ``k`` independent rejections made bursts of 10 landmarks in 2-4 scans
     (0.5-0.8 s, MRCLAM dataset 6) pass as lock-outs that a plain EKF got over by itself
     within seconds (``docs/robots.md``);
     **and** they are explained by one jump: the residual
     ``sum |u_i - G_i delta|^2 <= chi2_{mk - rank F}^-1(1 - false_alarm)``. Scattered
     outliers fail this test and stay rejected; a belief that drifted away from what
     the sensors agree on passes it. Two more conditions separate a wrong belief from a
     wrong sensor: the jump must be identifiable without the measurements of any single
     *source* (measurements carry an optional source label, e.g. the landmark), and an
     optional ``supported(t0, t1)`` callback must say that nothing else backed the belief
     over the run's span; measurements newer than an optional ``horizon`` are not
     judged yet (a fusion node: its neighbours have not reported on them);
   * **drift** (over-confidence without lock-out; ``drift_test``), over the NIS window of
     the last ``window`` tested measurements (default 10): the generalized-likelihood-
     ratio statistic ``g^T F^+ g > chi2_{rank F}^-1(1 - false_alarm / window)`` (the
     Bonferroni bound over the overlapping windows that share a measurement), with the
     Huber-clipped ``psi(u_i) = u_i min(1, c / |u_i|)`` in ``g`` so that heavy-tailed
     but zero-mean innovations (and outliers) do not set it off: it detects a
     *persistent bias* of the innovations. Under the model ``Var(g) = F`` (the
     innovations are white), so the statistic is ``chi2_{rank F}``; the clipping only
     lowers it. The windowed mean NIS is tracked as a statistic
     (:meth:`InnovationMonitor.nis_window`, :class:`MonitorStats`); it is no divergence
     test here: one heavy-tailed measurement sets it off (measured on the MRCLAM
     landmarks, whose NIS has a median of 0.4-0.9 and a mean of up to 10).

**Recovery** (:meth:`InnovationMonitor.check`). The estimator adds the process noise
``Q_b = delta delta^T + F^+`` to the monitored block: the second moment of the jump
estimated from the measurements, so the belief keeps its mean and its covariance
becomes ``P_b + delta delta^T + F^+``, honest about the jump (a re-initialization of the
block from the measurements). Only the components of the jump that exceed their own
standard deviation are kept (:func:`estimate_jump`): a direction the measurements do
not determine gets no noise, and a divergence needs at least one such component. The
rejected measurement is then tested again and the next measurements move the estimate
(:func:`monitored_update`). How a fusion node adds such noise without double counting
is in ``docs/robots.md``.

Events are logged (``logging``, warning level) and counted in :class:`MonitorStats`.

Lock-out detection from scalar NIS values (:class:`LockoutDetector`)
-------------------------------------------------------------------

For estimators that give one NIS value per measurement and no innovation vector to
attribute (MCL's predictive likelihood, a scan matcher's fix): :class:`LockoutDetector`
runs the two tests below on that sequence.

A tracking filter whose estimate has drifted away from the truth can lock itself out: its
gate rejects the measurements that would correct it, because they disagree with the
(wrong, over-confident) prediction. :class:`LockoutDetector` watches two statistics
that a consistent filter keeps small, each tested at a stated false-alarm rate ``alpha``:

Windowed NIS
    The normalized innovation squared of measurement ``k``,
    ``eps_k = nu_k^T S_k^-1 nu_k`` (``nu`` the innovation, ``S`` its predicted covariance),
    is chi-square with ``d`` degrees of freedom for a consistent linear-Gaussian filter,
    and innovations are white, so the sum over the last ``n`` measurements is chi-square
    with ``n d`` degrees of freedom (Bar-Shalom, Li & Kirubarajan, *Estimation with
    Applications to Tracking and Navigation*, 2001, sec. 5.4.2, the time-average NIS
    test). Divergence is declared when

        sum_{j = k - n + 1}^{k} eps_j > chi2.ppf(1 - alpha, n d)

    (with fewer than ``n`` values so far, the sum over those against their own quantile).
    Rejected measurements enter too (they are the evidence), each capped at the gate
    ``chi2.ppf(P_G, d)``: one gross outlier is the gate's business, not a divergence,
    and capping only lowers the sum, so the false-alarm rate stays below ``alpha``.

Run of rejections
    A measurement is rejected by a gate ``eps > chi2.ppf(P_G, d)`` with probability
    ``1 - P_G`` when the filter is consistent; ``r`` consecutive rejections then have
    probability ``(1 - P_G)^r``. Divergence is declared when the run reaches the
    smallest ``r`` with ``(1 - P_G)^r <= alpha``, i.e.
    ``r = ceil(log(alpha) / log(1 - P_G))`` (2 for ``P_G = 0.999``, ``alpha = 1e-4``).
    Measurements that could not be used at all (a failed scan match) count as
    rejections with no NIS.

After an alarm the detector is :meth:`LockoutDetector.reset` by the caller once it has recovered (its
window must not carry the NIS of the diverged filter into the new one).

Why two classes
---------------

Both watch a windowed NIS and a run of rejections, but they answer different questions
and :class:`InnovationMonitor` cannot delegate to :class:`LockoutDetector` without
changing its decisions (and so the MRCLAM results):

* the run: :class:`LockoutDetector` counts rejections and alarms after
  ``r = ceil(log(alpha) / log(1 - P_G))`` of them (every rejection is evidence, no
  outliers are expected); :class:`InnovationMonitor` allows for outliers, so its run is
  longer (``k`` from ``max_outlier_rate + 1 - P_G``), and it needs the *innovation
  vectors* of the run (a lock-out must be explained by one jump of the state block, not
  by one source, and be judged only up to a horizon), from which it also computes the
  recovery noise. A counter cannot give either;
* the window: :class:`LockoutDetector` *tests* the sum of capped NIS values against
  ``chi2(n d)``; :class:`InnovationMonitor` only *reports* the uncapped windowed mean
  (:meth:`InnovationMonitor.nis_window`), and its divergence test over the window is the
  GLR drift test on the whitened innovations (a persistent bias), because the NIS sum is
  set off by heavy-tailed but unbiased sensors (the MRCLAM landmarks above).

:class:`LockoutDetector` is the one for estimators with a scalar NIS only (MCL, scan
matching); :class:`InnovationMonitor` for EKF-type estimators with an innovation vector
and a state block to inflate.
"""
from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike
from scipy.stats import chi2

from dfusion.errors import ValidationError
from dfusion.linalg import Array, symmetrize

log = logging.getLogger(__name__)

__all__ = [
    "MonitorSettings",
    "MonitorStats",
    "Assessment",
    "JumpEstimate",
    "InnovationMonitor",
    "estimate_jump",
    "monitored_update",
    "LockoutDetector",
    "DivergenceAlarm",
]


@dataclass(frozen=True)
class MonitorSettings:
    """Probabilities behind the thresholds of :class:`InnovationMonitor` (module docstring).

    Attributes
    ----------
    gate_probability : float
        Chi-square gate quantile (an inlier is rejected with ``1 - gate_probability``).
    huber_probability : float or None
        Quantile of the Huber threshold ``c^2``; ``None``: no Huber weights.
    false_alarm : float
        False-alarm probability of each divergence test.
    max_outlier_rate : float
        The largest rate of independent outliers the lock-out test must not mistake for a
        lock-out (sets the run length ``k``).
    window : int
        Number of tested measurements in the sliding window: its NIS statistics are
        tracked (:meth:`InnovationMonitor.nis_window`, :class:`MonitorStats`) and the drift
        test runs over it.
    drift_test : bool
        Whether the drift test is on.
    recover : bool
        Whether a detected divergence triggers the recovery (``False``: detection and
        counting only).
    """

    gate_probability: float = 0.999
    huber_probability: float | None = 0.95
    false_alarm: float = 1e-3
    max_outlier_rate: float = 0.25
    window: int = 10
    drift_test: bool = True
    recover: bool = True

    def __post_init__(self) -> None:
        for name in ("gate_probability", "false_alarm", "max_outlier_rate"):
            v = getattr(self, name)
            if not 0.0 < v < 1.0:
                raise ValidationError(f"{name} must be in (0, 1), got {v!r}")
        if self.huber_probability is not None and not 0.0 < self.huber_probability < self.gate_probability:
            raise ValidationError("huber_probability must be in (0, gate_probability)")
        if self.max_outlier_rate + 1.0 - self.gate_probability >= 1.0:
            raise ValidationError("max_outlier_rate + 1 - gate_probability must be below 1")
        if int(self.window) != self.window or self.window < 1:
            raise ValidationError(f"window must be a positive integer, got {self.window!r}")

    def gate(self, m: int) -> float:
        """``chi2_m^-1(gate_probability)``."""
        return float(chi2.ppf(self.gate_probability, m))

    def huber(self, m: int) -> float:
        """``c^2 = chi2_m^-1(huber_probability)`` (``inf`` without Huber weights)."""
        return math.inf if self.huber_probability is None else float(chi2.ppf(self.huber_probability, m))

    def run_length(self) -> int:
        """``k = ceil(log(false_alarm) / log(max_outlier_rate + 1 - gate_probability))``."""
        p = self.max_outlier_rate + 1.0 - self.gate_probability
        return max(1, math.ceil(math.log(self.false_alarm) / math.log(p) - 1e-9))

    def quantile(self, dof: int, tests: int = 1) -> float:
        """``chi2_dof^-1(1 - false_alarm / tests)`` (``inf`` for ``dof <= 0``)."""
        return float(chi2.ppf(1.0 - self.false_alarm / tests, dof)) if dof > 0 else math.inf


@dataclass
class MonitorStats:
    """Counters of one :class:`InnovationMonitor`."""

    tested: int = 0
    accepted: int = 0
    downweighted: int = 0
    rejected: int = 0
    lockouts: int = 0           # divergences detected by the lock-out test
    drifts: int = 0             # divergences detected by the drift test
    recoveries: int = 0         # recoveries carried out (both kinds; none with recover=False)
    nis_sum: float = 0.0        # NIS of every tested measurement, summed (mean: / tested)
    window_nis_max: float = 0.0  # the largest mean NIS over a full window
    events: list[dict] = field(default_factory=list)


@dataclass(frozen=True)
class Assessment:
    """The decision on one measurement: its NIS, whether it is fused, and its weight ``w``
    (fuse with the noise ``R / w``)."""

    nis: float
    accept: bool
    weight: float


@dataclass(frozen=True)
class JumpEstimate:
    """A jump ``delta`` of the monitored block estimated from whitened innovations
    (:func:`estimate_jump`).

    Attributes
    ----------
    delta, cov : the least-squares jump ``F^+ g`` and its covariance ``F^+``
    glr : ``g^T F^+ g``, the generalized likelihood ratio statistic
    residual : ``sum |u_i - G_i delta|^2`` (unclipped innovations), with ``dof = m k - rank F``
    rank : rank of ``F``
    noise : the recovery's process noise: ``delta delta^T + F^+`` restricted to the
        components of the jump that exceed their own standard deviation (see
        :func:`estimate_jump`); zero if there is none.
    kept : number of such components
    """

    delta: Array
    cov: Array
    glr: float
    residual: float
    rank: int
    dof: int
    noise: Array
    kept: int


def estimate_jump(entries: list[tuple[Array, Array]], P_b: Array, clip: float = math.inf) -> JumpEstimate:
    """Least-squares jump from whitened innovations ``entries = [(u_i, G_i)]``
    (module docstring): ``F = sum G_i^T G_i``, ``g = sum G_i^T psi(u_i)`` with the Huber
    clip ``psi(u) = u min(1, clip / |u|)``, ``delta = F^+ g``, covariance ``F^+``; the
    residual uses the unclipped ``u_i``.

    The recovery noise keeps only the components of the jump that the measurements
    determine: in the coordinates ``xi = C^-1 delta`` normalized by the block's current
    covariance ``P_b = C C^T`` (so that the result does not depend on the units of the
    block's entries), with ``C^T F C = sum_i mu_i w_i w_i^T``, the component
    ``c_i = w_i^T xi`` has variance ``1 / mu_i``; it is kept if ``mu_i c_i^2 > 1`` (its
    size exceeds its standard deviation: including it then lowers the mean squared
    error, the rule of truncated principal-component regression, e.g. Hansen, *Rank-
    Deficient and Discrete Ill-Posed Problems*, SIAM 1998, sec. 3.2). Then
    ``noise = C (sum_kept (c_i^2 + 1 / mu_i) w_i w_i^T) C^T``: the second moment of the
    kept part of the jump. A direction in which the measurements hardly constrain the
    block (two landmarks seen along nearly the same line) is thus left alone instead of
    being inflated by metres.
    """
    n = entries[0][1].shape[1]
    F = np.zeros((n, n))
    g = np.zeros(n)
    for u, G in entries:
        nu = float(np.linalg.norm(u))
        psi = u if nu <= clip else u * (clip / nu)
        F += G.T @ G
        g += G.T @ psi
    F = symmetrize(F)
    w, V = np.linalg.eigh(F)
    tol = max(w.max(initial=0.0), 0.0) * n * 1e-10
    keep = w > tol
    rank = int(np.count_nonzero(keep))
    Fp = (V[:, keep] / w[keep]) @ V[:, keep].T
    delta = Fp @ g
    res = float(sum(np.sum((u - G @ delta) ** 2) for u, G in entries))
    m = sum(u.size for u, _ in entries)
    # components in the coordinates normalized by P_b
    C = np.linalg.cholesky(symmetrize(np.asarray(P_b, dtype=float)))
    mu, W = np.linalg.eigh(symmetrize(C.T @ F @ C))
    Cg = C.T @ g
    noise = np.zeros((n, n))
    kept = 0
    for i in range(n):
        if mu[i] <= tol * float(np.trace(C.T @ C)) or mu[i] <= 0.0:
            continue
        c = float(W[:, i] @ Cg) / mu[i]
        if mu[i] * c * c > 1.0:
            v = C @ W[:, i]
            noise += (c * c + 1.0 / mu[i]) * np.outer(v, v)
            kept += 1
    return JumpEstimate(delta, symmetrize(Fp), float(g @ delta), res, rank, m - rank, symmetrize(noise), kept)


@dataclass(frozen=True)
class _Tested:
    """One tested measurement: time, NIS, decision, whitened innovation ``u = L^-1 nu``,
    whitened block Jacobian ``G = L^-1 H_b`` and source label."""

    t: float
    nis: float
    accept: bool
    u: Array
    G: Array
    source: object


def _last_looks(run: list[_Tested], k: int) -> list[_Tested]:
    """The measurements of the last ``k`` looks (distinct measurement times) of ``run``, or
    ``[]`` if it has fewer: the measurements of one look (one scan's landmarks, the fixes
    of one filter step) see the same belief error and none of them was fused, so they are
    one piece of evidence that the belief is wrong, not ``n`` independent ones."""
    times = sorted({e.t for e in run})
    if len(times) < k:
        return []
    return [e for e in run if e.t >= times[-k]]


def _no_single_source(run: list[_Tested]) -> bool:
    """Whether a run of measurements determines a jump of the block even without the
    measurements of any one source: ``F`` of the others has full rank for every labelled
    source (unlabelled measurements, source ``None``, each count as their own source).
    Otherwise one faulty source (a misread landmark, a range failure on two neighbouring
    landmarks) could explain the run as well as a jump of the estimator's state."""
    sources = {e.source for e in run if e.source is not None}
    n = run[0].G.shape[1]
    for src in sources:
        rest = [e.G for e in run if e.source != src]
        if not rest:
            return False
        F = sum(G.T @ G for G in rest)
        w = np.linalg.eigvalsh(symmetrize(F))
        if int(np.count_nonzero(w > max(w.max(), 0.0) * n * 1e-10)) < n:
            return False
    return True


class InnovationMonitor:
    """Gate, Huber weights, divergence tests and recovery noise of one estimator's
    measurement stream (module docstring).

    Parameters
    ----------
    name : str
        For the log (e.g. ``"robot3/target"``).
    dim : int
        Measurement dimension ``m``.
    settings : MonitorSettings

    Each measurement goes through :meth:`test` with its innovation ``nu``, covariance
    ``S`` and ``H_b`` (the Jacobian of the measurement with respect to the monitored
    block); then :meth:`check` detects a divergence and calls the estimator's
    ``inflate(Q_b)``. :func:`monitored_update` does both.
    """

    def __init__(self, name: str, dim: int = 2, settings: MonitorSettings | None = None) -> None:
        self.name = name
        self.dim = int(dim)
        self.settings = settings or MonitorSettings()
        s = self.settings
        self.gate = s.gate(self.dim)
        self.huber = s.huber(self.dim)
        self.clip = math.sqrt(self.huber)
        self.run_length = s.run_length()
        self.stats = MonitorStats()
        self._recent: deque[_Tested] = deque(maxlen=s.window)   # the last tested measurements
        self._run: list[_Tested] = []   # the current run of consecutive rejected measurements
        self._run_cap = 8 * self.run_length

    @property
    def run(self) -> int:
        """Current number of consecutive rejected measurements."""
        return len(self._run)

    @property
    def looks(self) -> int:
        """Current number of looks (distinct measurement times) in the run of rejections:
        what the lock-out test compares with :attr:`run_length`."""
        return len({e.t for e in self._run})

    def nis_window(self) -> float:
        """Mean NIS of the last ``window`` tested measurements (``chi2_m / m`` on average
        times ``m``, i.e. ``m`` for a consistent estimator)."""
        return float(np.mean([e.nis for e in self._recent])) if self._recent else 0.0

    def test(self, t: float, nu: ArrayLike, S: ArrayLike, H_b: ArrayLike | None = None, *,
             source: object = None, retest: bool = False) -> Assessment:
        """Assess one innovation ``nu`` with covariance ``S``; ``H_b``: the measurement's
        Jacobian with respect to the monitored block (default the identity: the block is
        the measured quantity itself). ``retest``: the same measurement again after a
        recovery (it was counted as rejected; it is counted as accepted if it passes)."""
        nu = np.asarray(nu, dtype=float).reshape(-1)
        S = symmetrize(np.asarray(S, dtype=float))
        H = np.eye(nu.size) if H_b is None else np.asarray(H_b, dtype=float)
        L = np.linalg.cholesky(S)
        u = np.linalg.solve(L, nu)
        nis = float(u @ u)
        st = self.stats
        accept = bool(nis <= self.gate)   # NaN is rejected
        if retest:
            if accept:
                st.accepted += 1
                st.rejected -= 1
                self._run.clear()
        else:
            st.tested += 1
            st.nis_sum += nis
            entry = _Tested(float(t), nis, accept, u, np.linalg.solve(L, H), source)
            self._recent.append(entry)
            if len(self._recent) == self.settings.window:
                st.window_nis_max = max(st.window_nis_max, self.nis_window())
            if accept:
                st.accepted += 1
                self._run.clear()
            else:
                st.rejected += 1
                self._run.append(entry)
                del self._run[:-self._run_cap]
        if not accept:
            return Assessment(nis, False, 0.0)
        w = 1.0 if nis <= self.huber else math.sqrt(self.huber / nis)
        st.downweighted += int(w < 1.0)
        return Assessment(nis, True, w)

    def divergence(self, P_b: Array, supported: Callable[[float, float], bool] | None = None,
                   horizon: float = math.inf) -> tuple[str, JumpEstimate] | None:
        """``("lockout", jump)``, ``("drift", jump)`` or ``None`` (module docstring);
        ``P_b``: the block's current covariance. A divergence needs at least one kept
        component of the jump (:func:`estimate_jump`), and ``supported(t0, t1)`` (if
        given) must be false for the span ``[t0, t1]`` of the measurements that show it:
        the estimator's belief was not backed by other evidence over that span (for a
        fusion node: no neighbour's measurement information; ``docs/robots.md``).
        Measurements newer than ``horizon`` are not judged yet (for a fusion node: its
        neighbours have not reported on them): the tests use the rejected measurements of
        the last ``k`` looks (or the last ``window`` tested measurements) up to ``horizon``."""
        s = self.settings
        k = self.run_length   # looks
        run = _last_looks([e for e in self._run if e.t <= horizon], k)
        if run and _no_single_source(run) and not (supported and supported(run[0].t, run[-1].t)):
            jump = estimate_jump([(e.u, e.G) for e in run], P_b)
            if jump.rank == jump.delta.size and jump.residual <= s.quantile(jump.dof) and jump.kept:
                return "lockout", jump
        if s.drift_test:
            win = [e for e in self._recent if e.t <= horizon]
            if len(win) == s.window:
                jump = estimate_jump([(e.u, e.G) for e in win], P_b, self.clip)
                if (jump.rank and jump.glr > s.quantile(jump.rank, s.window) and jump.kept
                        and not (supported and supported(win[0].t, win[-1].t))):
                    return "drift", jump
        return None

    def check(self, t: float, P_b: Array, inflate: Callable[[Array], None],
              supported: Callable[[float, float], bool] | None = None,
              horizon: float = math.inf) -> JumpEstimate | None:
        """Detect a divergence (``P_b``: the block's current covariance; ``supported``,
        ``horizon``: see :meth:`divergence`); if there is one, call ``inflate(Q_b)`` with
        the jump's recovery noise (:attr:`JumpEstimate.noise`) unless ``settings.recover``
        is off, log and count the event, and forget the measurements that showed it.
        Returns the jump if the estimator was inflated."""
        found = self.divergence(P_b, supported, horizon)
        if found is None:
            return None
        kind, jump = found
        applied = self.settings.recover
        if applied:
            inflate(jump.noise)
        st = self.stats
        if kind == "lockout":
            st.lockouts += 1
        else:
            st.drifts += 1
        st.recoveries += int(applied)
        ev = {"t": float(t), "kind": kind, "applied": bool(applied), "run": len(self._run),
              "jump": jump.delta.tolist(), "jump_std": np.sqrt(np.diag(jump.cov)).tolist(),
              "added_std": np.sqrt(np.diag(jump.noise)).tolist(), "glr": jump.glr,
              "residual": jump.residual, "nis_window": self.nis_window()}
        st.events.append(ev)
        log.warning("%s: %s at t=%.2f (run %d, GLR %.1f, residual %.1f/%d dof): jump %s, %s", self.name, kind,
                    t, len(self._run), jump.glr, jump.residual, jump.dof, np.round(jump.delta, 3).tolist(),
                    f"std {np.round(ev['added_std'], 3).tolist()} added" if applied else "no recovery")
        self._run.clear()
        self._recent.clear()
        return jump if applied else None


def monitored_update(
    monitor: InnovationMonitor,
    t: float,
    innovation: Callable[[], tuple[Array, Array, Array, Array]],
    fuse: Callable[[float], None],
    inflate: Callable[[Array], None],
    source: object = None,
    supported: Callable[[float, float], bool] | None = None,
    horizon: Callable[[], float] | None = None,
) -> Assessment:
    """One measurement through ``monitor``: the steps every estimator here shares.

    ``innovation()`` returns ``(nu, S, H_b, P_b)`` at the estimator's current belief
    (``P_b`` the monitored block's covariance),
    ``fuse(w)`` fuses the measurement with the noise ``R / w``, ``inflate(Q_b)`` adds
    the process noise ``Q_b`` to the monitored block; ``source``, ``supported`` and
    ``horizon()``: see :meth:`InnovationMonitor.test` and
    :meth:`InnovationMonitor.divergence`. After a recovery a measurement
    that was rejected is tested again against the inflated belief and fused if it now
    passes the gate. Returns the final assessment.
    """
    nu, S, H, _ = innovation()
    a = monitor.test(t, nu, S, H, source=source)
    if a.accept:
        fuse(a.weight)
    jump = monitor.check(t, innovation()[3], inflate, supported, math.inf if horizon is None else horizon())
    if jump is not None and not a.accept:
        nu, S, H, _ = innovation()
        a = monitor.test(t, nu, S, H, source=source, retest=True)
        if a.accept:
            fuse(a.weight)
    return a


@dataclass(frozen=True)
class DivergenceAlarm:
    """Why :meth:`LockoutDetector.record` declared divergence.

    Attributes
    ----------
    reason : ``"nis_window"`` or ``"rejection_run"``
    value : float
        The windowed NIS sum, or the length of the run of rejections.
    threshold : float
        The chi-square quantile, or the run length that raised the alarm.
    """

    reason: str
    value: float
    threshold: float


class LockoutDetector:
    """Sliding-window NIS test and run-of-rejections test (see the module docstring).

    Parameters
    ----------
    dof : int
        Dimension ``d`` of the innovation.
    window : int
        Number ``n`` of recent measurements in the NIS sum.
    alpha : float
        False-alarm probability of each test for a consistent filter.
    gate_probability : float
        ``P_G`` of the gate the filter applies (used for the run-length test).
    """

    def __init__(self, dof: int = 3, *, window: int = 10, alpha: float = 1e-4, gate_probability: float = 0.999) -> None:
        if dof < 1 or window < 1:
            raise ValidationError("dof and window must be >= 1")
        if not (0.0 < alpha < 1.0 and 0.0 < gate_probability < 1.0):
            raise ValidationError("alpha and gate_probability must be in (0, 1)")
        self.dof = int(dof)
        self.window = int(window)
        self.alpha = float(alpha)
        self.gate_probability = float(gate_probability)
        #: rejections in a row that raise the alarm
        self.max_run = max(1, int(math.ceil(math.log(self.alpha) / math.log(1.0 - self.gate_probability))))
        #: cap of one NIS value in the window sum (the gate)
        self.nis_cap = float(chi2.ppf(self.gate_probability, self.dof))
        self._thresholds = [float(chi2.ppf(1.0 - self.alpha, n * self.dof)) for n in range(1, self.window + 1)]
        self._nis: deque[float] = deque(maxlen=self.window)
        self.run = 0
        #: alarms raised so far, by reason
        self.alarms = {"nis_window": 0, "rejection_run": 0}

    @property
    def window_sum(self) -> float:
        return float(sum(self._nis))

    def threshold(self, n: int | None = None) -> float:
        """``chi2.ppf(1 - alpha, n d)`` for ``n`` values (default: a full window)."""
        return self._thresholds[(self.window if n is None else int(n)) - 1]

    def record(self, nis: float | None, accepted: bool) -> DivergenceAlarm | None:
        """Add one measurement (its NIS, ``None`` if there is none) and test; the alarm or ``None``."""
        if nis is not None:
            nis = float(nis)
            if not math.isfinite(nis) or nis < 0:
                nis = math.inf
            self._nis.append(min(nis, self.nis_cap))
        self.run = 0 if accepted else self.run + 1
        if self.run >= self.max_run:
            return self._alarm(DivergenceAlarm("rejection_run", float(self.run), float(self.max_run)))
        if self._nis:
            s, thr = self.window_sum, self.threshold(len(self._nis))
            if s > thr:
                return self._alarm(DivergenceAlarm("nis_window", s, thr))
        return None

    def _alarm(self, alarm: DivergenceAlarm) -> DivergenceAlarm:
        self.alarms[alarm.reason] += 1
        log.debug("divergence: %s %.3g > %.3g", alarm.reason, alarm.value, alarm.threshold)
        return alarm

    def reset(self) -> None:
        """Forget the window and the run (after a recovery)."""
        self._nis.clear()
        self.run = 0
