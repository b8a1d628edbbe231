r"""Monte Carlo localization (MCL) of a robot with a 2-D laser against an occupancy grid.

A particle filter over the robot pose ``(x, y, theta)`` in the map frame (Thrun, Burgard &
Fox, *Probabilistic Robotics*, 2005, ch. 8; Dellaert, Fox, Burgard & Thrun, ICRA 1999),
as summarized by the URUS paper (Sanfeliu et al., sec. 8.1) and the repetitive-environment
survey (sec. III.A, "AMCL"). Pieces:

Motion: the sampled odometry model of :class:`dfusion.models.OdometryMotionModel`
    (Thrun et al. table 5.6).

Measurement: two laser models (``sensor=`` of :class:`MonteCarloLocalization`), the URUS
    erfc beam model :class:`dfusion.models.BeamErfcModel` and the likelihood field
    :class:`dfusion.models.LikelihoodFieldModel` (:mod:`dfusion.models.laser`).

Adaptive sample size: KLD sampling (Fox, "Adapting the sample size in particle filters
    through KLD-sampling", IJRR 22(12), 2003). At resampling, particles are drawn one by
    one (i.i.d. from the weights) and put into bins of size ``kld_bins`` (x, y, theta);
    with ``k`` non-empty bins the sampling stops once ``n`` reaches::

        n(k) = (k - 1) / (2 eps) (1 - 2 / (9 (k - 1)) + sqrt(2 / (9 (k - 1))) z_{1-delta})^3

    (Wilson-Hilferty approximation of the chi-square quantile), clipped to
    ``[min_particles, max_particles]``. As in ROS AMCL, bins are counted on the resampled
    poses (Fox bins the predicted ones).

Recovery: Augmented MCL (Thrun et al. table 8.3). ``w_slow`` and ``w_fast`` are
    exponential averages (rates ``alpha_slow << alpha_fast``) of the average measurement
    likelihood; at resampling each particle is replaced by a pose drawn uniformly over
    free space with probability ``max(0, 1 - w_fast / w_slow)``. Two choices, both
    documented in ``docs/localization.md``: the averaged quantity is the per-beam
    geometric mean ``L^(1 / n_terms)`` of each particle's likelihood (``n_terms`` = number
    of beams multiplied; 1 for the erfc model), weighted by the prior weights, so that
    scans with different numbers of valid beams are comparable; and both averages start
    at the first value. (ROS AMCL starts them at 0 and resets them to 0 after every
    injection, which disables injection for about ``1 / alpha_slow`` updates because
    ``w_fast / w_slow`` starts at ``alpha_fast / alpha_slow``; Thrun's table has no reset.)
    Recovery is off by default (``alpha_slow = alpha_fast = 0``, as in ROS AMCL); with the
    likelihood field, ``0.001, 0.1`` re-localizes a kidnapped robot within a few scans
    (tested). With the averaged erfc model it injects continuously (the scan-to-scan
    fluctuation of its weakly discriminative average exceeds the margin, and injected
    particles survive long enough to lower the next averages), degrading tracking from 2 to
    about 10 cm; see ``docs/localization.md``.

Lock-out detection and relocalization (``monitor=``; an addition): the predictive
    likelihood per beam of each scan (the quantity Augmented MCL averages) is tested against
    its running mean and variance over the accepted scans, one-sided at the monitor's gate
    probability; its squared deficit is the NIS fed to an
    :class:`~dfusion.estimation.innovation.LockoutDetector` (window and rejection-run
    tests). On an alarm particles are injected into the prior of the current scan (share
    ``max(1 - w_fast / w_slow, recovery_min_fraction)``), locally around the belief with an
    expanding region or uniformly, kept only if they explain the scan better than the belief
    (Bayes factor) and the next scan confirms it (:meth:`MonteCarloLocalization.relocalize`).

Global localization: :meth:`MonteCarloLocalization.initialize_global` draws poses uniformly
    over the free cells with uniform headings (the uniform prior of the survey, sec. III).

Adaptive tempering (``ess_floor``, default 0.02; an addition to the algorithms above): the
    product of 60 beam likelihoods is so peaked that, from a uniform prior, the first scan
    can put all the weight on one wrong particle that happens to fit better than the
    particles near the truth (none of which is very close), and resampling then loses the
    truth for good. If the effective sample size after weighting would fall below
    ``ess_floor * N``, the likelihood is raised to the largest exponent ``beta`` in
    ``(0, 1]`` that keeps it at ``ess_floor * N`` (bisection), the adaptive tempering of
    SMC samplers (e.g. Jasra, Stephens, Doucet & Tsagaris, Scand. J. Stat. 38, 2011).
    The rest of that scan's information is discarded, so the update is deliberately
    conservative. Measured on the test building (8 seeds, 20,000 particles): global
    localization with the likelihood field converged in 8 of 8 runs (2-4 scans) with
    ``ess_floor = 0.02`` against 4 of 8 without; tracking accuracy unchanged (2.1 cm).
    In tracking the floor is rarely reached.

Asynchronous and late scans (URUS sec. 8.1, "Integration of asynchronous data"):
    Odometry poses are buffered with their time stamps (``odom_window`` seconds). The
    particles live at the *filter time* ``T``; they are propagated only when a scan
    arrives (not for every odometry message). A scan stamped ``t``:

    * ``t >= T`` (in order): the odometry pose at ``t`` is interpolated from the buffer
      (linear in x, y, shortest arc in theta), the particles are moved with the sampled
      motion model from ``O(T)`` to ``O(t)``, and weighted at ``t``; ``T := t``. A scan up
      to ``max_scan_lead`` seconds newer than the newest odometry is applied at the newest
      odometry time (the robot is assumed not to have moved in between); a scan further
      ahead raises :class:`~dfusion.errors.OutsideWindowError` (feed the odometry first).
    * ``t < T`` (late): the odometry displacement ``D = O(t)^-1 O(T)`` over ``[t, T]`` is
      undone on every particle, ``x_i(t) = x_i(T) (+) D^-1`` ((+) the SE(2) composition):
      the particles *as they were at t* under the odometry. The scan is evaluated at
      ``x_i(t)``, the weights of the particles are updated, and (if needed) resampled;
      the particles then stay at ``x_i(T)``, i.e. they are re-propagated with the same
      displacement ``D`` (exactly the URUS back-propagation; no motion noise is drawn
      twice). The approximation is that the motion noise each particle received over
      ``[t, T]`` is not undone; it is small for delays of a few odometry steps. A scan
      older than the odometry buffer raises :class:`~dfusion.errors.OutsideWindowError`.

Output: :meth:`MonteCarloLocalization.estimate` -- the Gaussian summary of the weighted
    particles (mean with the circular mean for theta, covariance with theta residuals
    wrapped around it; particles injected by the recovery step are left out until a scan
    has weighted them) and the reliability ``R = 1 / (E + 1)``, ``E = sqrt(c_xx + c_yy)``
    (Hu et al., the switching paper, eq. 11-12; ``docs/background.md#references``).
"""
from __future__ import annotations

import logging
import math
from collections import deque
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike
from scipy.stats import chi2, norm

from dfusion.errors import (
    NonFiniteError,
    NotInitializedError,
    OutsideWindowError,
    ShapeError,
    TimeError,
    ValidationError,
)
from dfusion.estimation.estimate import Estimate
from dfusion.estimation.innovation import DivergenceAlarm
from dfusion.estimation.particle_filter import (
    effective_sample_size,
    gaussian_summary,
    multinomial_resample,
    systematic_resample,
)
from dfusion.geometry import se2_between, se2_compose, se2_inverse, wrap_angle
from dfusion.linalg import Array, as_vector
from dfusion.maps.grid import OccupancyGrid
from dfusion.maps.raycast import RayCastTable
from dfusion.models.laser import (
    BeamErfcModel,
    LaserConfig,
    LikelihoodFieldModel,
    laser_grid_poses,
)
from dfusion.models.odometry import OdometryMotionModel
from dfusion.reliability import covariance_reliability

logger = logging.getLogger(__name__)

__all__ = [
    "MonteCarloLocalization",
    "kld_sample_size",
    "heaviest_cluster",
]


# ----------------------------------------------------------------------------------------
# SE(2) helpers (poses as (..., 3) arrays)
# ----------------------------------------------------------------------------------------






# ----------------------------------------------------------------------------------------
# Gaussian summary and reliability
# ----------------------------------------------------------------------------------------






# ----------------------------------------------------------------------------------------
# Laser description
# ----------------------------------------------------------------------------------------


# ----------------------------------------------------------------------------------------
# Odometry motion model
# ----------------------------------------------------------------------------------------


# ----------------------------------------------------------------------------------------
# Laser measurement models
# ----------------------------------------------------------------------------------------






# ----------------------------------------------------------------------------------------
# KLD sample size
# ----------------------------------------------------------------------------------------
def kld_sample_size(k: ArrayLike, epsilon: float, z: float) -> Array:
    """Fox (2003) eq. 12: particles needed for ``k`` non-empty bins (``k <= 1`` gives 1)."""
    k = np.asarray(k, dtype=float)
    km1 = np.maximum(k - 1.0, 1.0)
    a = 2.0 / (9.0 * km1)
    n = km1 / (2.0 * epsilon) * (1.0 - a + np.sqrt(a) * z) ** 3
    return np.where(k <= 1, 1.0, np.ceil(n))


# ----------------------------------------------------------------------------------------
# The filter
# ----------------------------------------------------------------------------------------
class MonteCarloLocalization:
    """Adaptive (KLD) Monte Carlo localization with recovery and late-scan handling.

    Parameters
    ----------
    grid : OccupancyGrid
        The map.
    laser : LaserConfig
        The laser (beam angles, max range, mounting offset).
    motion : OdometryMotionModel, optional
        Default ``OdometryMotionModel()`` (all alphas 0.2, the ROS AMCL defaults).
    sensor : ``"likelihood_field"``, ``"erfc"`` or a model instance
        :class:`LikelihoodFieldModel` (default) or :class:`BeamErfcModel`.
    min_particles, max_particles : int
        KLD bounds (ROS AMCL defaults 100 and 5000).
    adaptive : bool
        KLD sampling; with ``False`` the set keeps ``n_particles`` (default ``max_particles``).
    kld_err, kld_z : float
        ``epsilon`` and the standard-normal quantile ``z_{1-delta}`` of KLD sampling
        (ROS AMCL: ``kld_err = 0.01``, ``kld_z = 0.99`` interpreted as ``1 - delta``).
    kld_bins : (dx, dy, dtheta)
        Bin size (m, m, rad), default (0.5, 0.5, 10 deg).
    alpha_slow, alpha_fast : float
        Augmented-MCL averaging rates; ``0, 0`` (default, as ROS AMCL) disables recovery.
        ``0.001, 0.1`` works with the likelihood field (``docs/localization.md``).
    resample_threshold : float
        Resample when ``N_eff < resample_threshold * N`` (1.0 = after every scan).
    max_beams : int
        Beams used per scan (evenly sub-sampled; ROS AMCL ``laser_max_beams``).
    estimate_cluster : bool
        :meth:`estimate` reports the mean of the heaviest cluster of connected KLD bins
        (:func:`heaviest_cluster`, as ROS AMCL) instead of the mean of all particles, with
        the second moment of *all* particles about it as covariance (the mean squared error
        of that point under the whole posterior, so a second mode still shows). Default
        ``False``: the mean of all particles.
    beam_selection : ``"all"`` or ``"valid"``
        ``"all"`` (default, as AMCL): the ``max_beams`` are evenly spaced over all beams and
        the ones without a usable reading (non-finite, below ``min_range``, at or beyond
        ``max_range``) are then dropped. ``"valid"``: evenly spaced over the beams with a
        usable reading, so that every scan contributes ``max_beams`` end points (or all it
        has): in open areas, where most beams return nothing within range, ``"all"`` leaves
        few end points exactly where the map is least complete.
    update_min_d, update_min_a : float
        Skip in-order scans until the odometry moved this far (m) or turned this much
        (rad) since the last integrated scan (ROS AMCL ``update_min_*``; 0 = never skip).
    ess_floor : float
        Adaptive likelihood tempering: if weighting with the full likelihood would leave
        an effective sample size below ``ess_floor * N``, the likelihood is raised to the
        largest power ``beta < 1`` that keeps it there (0 disables; see the module
        docstring). ``last_beta`` holds the value used for the latest scan.
    odom_window : float
        Seconds of odometry kept for late scans.
    max_scan_lead : float
        How far (s) a scan may be ahead of the newest odometry.
    rng : numpy Generator or seed
    monitor : :class:`~dfusion.estimation.innovation.LockoutDetector` (1 dof), optional
        Lock-out detection from the scan likelihood (:meth:`_likelihood_surprise`);
        ``None`` (default): off. Then continuous Augmented-MCL injection (``alpha_slow``,
        ``alpha_fast``) is replaced by injection on alarms only (:meth:`relocalize`).
    recovery_sampler : ``"local"``, ``"uniform"`` or ``"none"``
        Where relocalization draws particles on an alarm (``"none"``: detect and count only).
    recovery_probability, recovery_min_fraction, recovery_expansion : float
        Chi-square probability of the local search region, the smallest injected share,
        and the variance factor of the region per further alarm (see :meth:`relocalize`).
    """

    def __init__(
        self,
        grid: OccupancyGrid,
        laser: LaserConfig,
        *,
        motion: OdometryMotionModel | None = None,
        sensor: str | BeamErfcModel | LikelihoodFieldModel = "likelihood_field",
        min_particles: int = 100,
        max_particles: int = 5000,
        adaptive: bool = True,
        n_particles: int | None = None,
        kld_err: float = 0.01,
        kld_z: float = 0.99,
        kld_bins: tuple[float, float, float] = (0.5, 0.5, math.radians(10.0)),
        alpha_slow: float = 0.0,
        alpha_fast: float = 0.0,
        resample_threshold: float = 0.5,
        max_beams: int = 60,
        beam_selection: Literal["all", "valid"] = "all",
        estimate_cluster: bool = False,
        update_min_d: float = 0.0,
        update_min_a: float = 0.0,
        odom_window: float = 5.0,
        max_scan_lead: float = 0.1,
        rng: np.random.Generator | int | None = None,
        ray_table: RayCastTable | None = None,
        ess_floor: float = 0.02,
        monitor=None,
        recovery_sampler: Literal["local", "uniform", "none"] = "local",
        recovery_probability: float = 0.99,
        recovery_min_fraction: float = 0.1,
        recovery_expansion: float = 4.0,
    ) -> None:
        if not isinstance(grid, OccupancyGrid):
            raise ValidationError("grid must be an OccupancyGrid")
        if not isinstance(laser, LaserConfig):
            raise ValidationError("laser must be a LaserConfig")
        self.grid = grid
        self.laser = laser
        self.motion = motion or OdometryMotionModel()
        if isinstance(sensor, str):
            if sensor == "likelihood_field":
                sensor = LikelihoodFieldModel()
            elif sensor == "erfc":
                sensor = BeamErfcModel()
            else:
                raise ValidationError(f"unknown sensor model {sensor!r}")
        self.sensor = sensor
        self.sensor.prepare(grid, laser.max_range, ray_table)
        self.min_particles = int(min_particles)
        self.max_particles = int(max_particles)
        if not 1 <= self.min_particles <= self.max_particles:
            raise ValidationError("need 1 <= min_particles <= max_particles")
        self.adaptive = bool(adaptive)
        self.n_particles = int(n_particles or self.max_particles)
        if not (kld_err > 0 and 0.5 < kld_z < 1):
            raise ValidationError("need kld_err > 0 and 0.5 < kld_z < 1")
        self.kld_err = float(kld_err)
        self._kld_zq = float(norm.ppf(kld_z))
        self.kld_bins = np.asarray(kld_bins, dtype=float)
        if self.kld_bins.shape != (3,) or np.any(self.kld_bins <= 0):
            raise ValidationError("kld_bins must be three positive sizes")
        if not (0 <= alpha_slow <= 1 and 0 <= alpha_fast <= 1):
            raise ValidationError("alpha_slow and alpha_fast must be in [0, 1]")
        self.alpha_slow = float(alpha_slow)
        self.alpha_fast = float(alpha_fast)
        self.resample_threshold = float(resample_threshold)
        if not 0.0 <= ess_floor < 1.0:
            raise ValidationError("ess_floor must be in [0, 1)")
        self.ess_floor = float(ess_floor)
        self.last_beta = 1.0
        n = laser.angles.size
        self._beams = np.unique(np.round(np.linspace(0, n - 1, min(int(max_beams), n))).astype(int))
        if beam_selection not in ("all", "valid"):
            raise ValidationError(f"beam_selection must be 'all' or 'valid', got {beam_selection!r}")
        self.beam_selection = beam_selection
        self.estimate_cluster = bool(estimate_cluster)
        self.max_beams = int(max_beams)
        self.update_min_d = float(update_min_d)
        self.update_min_a = float(update_min_a)
        self.odom_window = float(odom_window)
        self.max_scan_lead = float(max_scan_lead)
        self.rng = np.random.default_rng(rng)
        # state
        self._particles: Array | None = None
        self._weights: Array | None = None
        self._time: float | None = None
        self._odom_at_time: Array | None = None
        self._odom: deque[tuple[float, Array]] = deque()
        self._last_update_odom: Array | None = None
        self._log_w_slow: float | None = None
        self._log_w_fast: float | None = None
        self._fresh: np.ndarray | None = None  # particles injected since the last scan
        # divergence monitoring and on-alarm relocalization (see relocalize)
        self.monitor = monitor
        if recovery_sampler not in ("local", "uniform", "none"):
            raise ValidationError(f"recovery_sampler must be 'local', 'uniform' or 'none', got {recovery_sampler!r}")
        if not (0.0 < recovery_probability < 1.0 and 0.0 <= recovery_min_fraction <= 1.0):
            raise ValidationError("need 0 < recovery_probability < 1 and 0 <= recovery_min_fraction <= 1")
        self.recovery_sampler = recovery_sampler
        self.recovery_probability = float(recovery_probability)
        self.recovery_min_fraction = float(recovery_min_fraction)
        if not recovery_expansion >= 1.0:
            raise ValidationError("recovery_expansion must be >= 1")
        self.recovery_expansion = float(recovery_expansion)
        self._chi2_recovery = float(chi2.ppf(self.recovery_probability, 3))
        self._surprise_z = None if monitor is None else float(norm.ppf(monitor.gate_probability))
        self._surprise_n = 0
        self._surprise_mean = 0.0
        self._surprise_var = 0.0
        self._alarms_since_consistent = 0
        self._anchor = None
        self._shadow: tuple[Array, Array] | None = None
        self._mean_range = 1.0
        #: NIS of the latest in-order scan (monitoring only)
        self.last_nis: float | None = None
        #: counters for diagnostics
        self.stats = {"scans": 0, "late_scans": 0, "skipped_scans": 0, "resamples": 0, "injected": 0,
                      "gated": 0, "alarms": 0, "recoveries": 0,
                      "recovery_failures": 0}

    # -- state access --------------------------------------------------------------------
    @property
    def particles(self) -> Array:
        self._require_init()
        return self._particles.copy()

    @property
    def weights(self) -> Array:
        self._require_init()
        return self._weights.copy()

    @property
    def time(self) -> float | None:
        """The time the particles refer to (``None`` before any odometry or stamped init)."""
        return self._time

    @property
    def n_eff(self) -> float:
        self._require_init()
        return effective_sample_size(self._weights)

    def _require_init(self) -> None:
        if self._particles is None:
            raise NotInitializedError("call initialize_gaussian, initialize_global or initialize_particles first")

    # -- initialization ------------------------------------------------------------------
    def particle_count(self, n: int | None = None) -> int:
        """``n`` checked, or the default number of particles of a new set (``max_particles``
        when adaptive, else ``n_particles``)."""
        if n is None:
            return self.max_particles if self.adaptive else self.n_particles
        n = int(n)
        if n < 1:
            raise ValidationError("the number of particles must be >= 1")
        return n

    def initialize_particles(self, particles: ArrayLike, weights: ArrayLike | None = None, t: float | None = None) -> None:
        """Start from given particles ``(N, 3)`` (world frame) and optional weights at time ``t``."""
        p = np.array(particles, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
            raise ShapeError(f"particles must have shape (N, 3), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise NonFiniteError("particles contain NaN or inf")
        if weights is None:
            w = np.full(p.shape[0], 1.0 / p.shape[0])
        else:
            w = np.array(weights, dtype=float).reshape(-1)
            if w.shape[0] != p.shape[0] or np.any(w < 0) or not np.isfinite(w).all() or w.sum() <= 0:
                raise ValidationError("weights must be finite, >= 0, not all 0, one per particle")
            w = w / w.sum()
        p[:, 2] = wrap_angle(p[:, 2])
        self._particles, self._weights = p, w
        self._fresh = None
        self._set_time(t)
        self._log_w_slow = self._log_w_fast = None
        self._last_update_odom = None

    def initialize_gaussian(self, mean: ArrayLike, cov: ArrayLike, n: int | None = None, t: float | None = None) -> None:
        """Particles drawn from ``N(mean, cov)`` (pose tracking from a known-ish start)."""
        mean = as_vector(mean, 3, "mean")
        cov = np.asarray(cov, dtype=float)
        if cov.shape != (3, 3):
            raise ShapeError("cov must be 3 x 3")
        p = self.rng.multivariate_normal(mean, cov, size=self.particle_count(n), method="cholesky")
        self.initialize_particles(p, t=t)

    def initialize_global(self, n: int | None = None, t: float | None = None) -> None:
        """Particles uniform over the free space of the map (global localization)."""
        self.initialize_particles(self.grid.sample_free_poses(self.particle_count(n), self.rng), t=t)

    def _set_time(self, t: float | None) -> None:
        """Particle time: ``t`` if inside the odometry buffer, else the newest odometry."""
        if self._odom:
            t_new = self._odom[-1][0]
            if t is not None and self._odom[0][0] <= t <= t_new:
                self._time, self._odom_at_time = float(t), self._odom_pose_at(float(t))
            else:
                self._time, self._odom_at_time = t_new, self._odom[-1][1].copy()
        else:
            self._time = None if t is None else float(t)
            self._odom_at_time = None

    # -- odometry ------------------------------------------------------------------------
    def predict(self, t: float, u: ArrayLike) -> None:
        """Buffer the odometry pose ``u = (x, y, theta)`` (odometry frame) stamped ``t``.

        Time stamps must not decrease (:class:`TimeError`); an equal stamp replaces the
        newest entry. Particles are not moved here (see the module docstring).
        """
        t = float(t)
        if not math.isfinite(t):
            raise TimeError(f"odometry time must be finite, got {t}")
        pose = as_vector(u, 3, "odometry pose")
        if self._odom and t < self._odom[-1][0]:
            raise TimeError(f"odometry time {t} is older than the newest one {self._odom[-1][0]}")
        if self._odom and t == self._odom[-1][0]:
            self._odom.pop()
        self._odom.append((t, pose))
        if self._particles is not None and self._odom_at_time is None:
            # particles initialized before any odometry: they refer to this first reading
            self._time, self._odom_at_time = t, pose.copy()
        cutoff = t - self.odom_window
        while len(self._odom) > 2 and self._odom[1][0] <= cutoff:
            self._odom.popleft()

    def _odom_pose_at(self, t: float) -> Array:
        """Odometry pose interpolated at ``t`` (linear in x, y; shortest arc in theta)."""
        times = [e[0] for e in self._odom]
        if t >= times[-1]:
            return self._odom[-1][1].copy()
        if t < times[0]:
            raise OutsideWindowError(f"time {t} is older than the odometry buffer (from {times[0]})")
        k = int(np.searchsorted(times, t, side="right"))  # times[k-1] <= t < times[k]
        t0, p0 = self._odom[k - 1]
        t1, p1 = self._odom[k]
        a = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
        out = p0 + a * (p1 - p0)
        out[2] = wrap_angle(p0[2] + a * wrap_angle(p1[2] - p0[2]))
        return out

    # -- scans ---------------------------------------------------------------------------
    def update(self, t: float, z: ArrayLike) -> bool:
        """Integrate a laser scan ``z`` stamped ``t`` (ranges for all ``laser.angles``).

        Returns ``False`` if the scan was skipped (``update_min_d`` / ``update_min_a``),
        ``True`` otherwise. Non-finite ranges and ranges below ``min_range`` are ignored.
        Raises :class:`OutsideWindowError` (filter unchanged) for scans older than the
        odometry buffer or more than ``max_scan_lead`` ahead of the newest odometry.
        """
        self._require_init()
        t = float(t)
        if not math.isfinite(t):
            raise TimeError(f"scan time must be finite, got {t}")
        z = np.asarray(z, dtype=float).reshape(-1)
        if z.size != self.laser.angles.size:
            raise ShapeError(f"scan must have {self.laser.angles.size} ranges, got {z.size}")
        late = False
        if self._odom and self._odom_at_time is not None:
            t_new = self._odom[-1][0]
            if t > t_new + self.max_scan_lead:
                raise OutsideWindowError(
                    f"scan at {t} is {t - t_new:.3f} s ahead of the newest odometry ({t_new})"
                )
            t_eff = min(t, t_new)
            if t_eff >= self._time:
                o_t = self._odom_pose_at(t_eff)
                if self._skip(o_t):
                    self.stats["skipped_scans"] += 1
                    return False
                self._particles = self.motion.sample(self._particles, self._odom_at_time, o_t, self.rng)
                if self._shadow is not None:
                    sp, sw = self._shadow
                    self._shadow = (self.motion.sample(sp, self._odom_at_time, o_t, self.rng), sw)
                self._time, self._odom_at_time = t_eff, o_t
                eval_poses = self._particles
            else:
                o_t = self._odom_pose_at(t_eff)  # raises OutsideWindowError if too old
                D = se2_between(o_t, self._odom_at_time)
                eval_poses = se2_compose(self._particles, se2_inverse(D))
                late = True
                logger.debug("late scan at %.3f s applied at its own time (filter time %.3f s)", t_eff, self._time)
        else:
            eval_poses = self._particles
        if self.beam_selection == "valid":
            usable = np.flatnonzero(np.isfinite(z) & (z >= self.laser.min_range) & (z < self.laser.max_range))
            b = usable[np.unique(np.round(np.linspace(0, usable.size - 1, min(self.max_beams, usable.size)))
                                 .astype(int))] if usable.size else usable
        else:
            b = self._beams
        zb = z[b]
        ab = self.laser.angles[b]
        ok = np.isfinite(zb) & (zb >= self.laser.min_range)
        zb, ab = zb[ok], ab[ok]
        if zb.size == 0:
            return False
        lp = laser_grid_poses(self.grid, eval_poses, self.laser.offset)
        ll, n_terms = self.sensor.log_likelihood(lp, zb, ab)
        if self.monitor is not None and not late:
            self._mean_range = float(np.mean(np.minimum(zb, self.laser.max_range)))
            if self._shadow is not None:
                ll = self._confirm_relocalization(ll, zb, ab)
            alarm = self._likelihood_surprise(ll, n_terms)
            if alarm is not None and self.recovery_sampler != "none":
                ll = self.relocalize(ll, zb, ab, alarm.reason)
        self._apply_likelihood(ll, n_terms)
        if not late:
            self._last_update_odom = self._odom_at_time
        self.stats["scans"] += 1
        self.stats["late_scans"] += int(late)
        return True

    # -- divergence monitoring and relocalization ----------------------------------------
    def _capture_range(self) -> float:
        """Distance (m) over which the sensor model tells poses apart: the likelihood field's
        ``max_distance`` (end points farther from any obstacle all score alike), ``3 sigma``
        for the erfc model."""
        d = getattr(self.sensor, "max_distance", None)
        return float(d) if d else 3.0 * float(getattr(self.sensor, "sigma", 0.1))

    def _likelihood_surprise(self, ll: Array, n_terms: int):
        r"""Test the scan's predictive likelihood against its usual level; the alarm or ``None``.

        ``l_k = log sum_i w_i L_i^(1 / n)`` is the log of the predictive likelihood of the
        scan per beam (the quantity Augmented MCL averages into ``w_slow`` and ``w_fast``;
        ``n`` beams, prior weights ``w_i``). Its long-run mean ``m`` and variance ``s^2`` are
        running averages over the *accepted* scans (rate ``max(alpha_slow, 1 / k)`` after
        ``k`` of them). A locked-out belief -- no particle near the robot -- explains the
        scan worse than usual, so the scan is *rejected* when

            u_k = (l_k - m) / s < -z,      z = Phi^-1(P_G)

        (one-sided test at level ``1 - P_G`` of the monitor's gate), and ``min(u_k, 0)^2``
        is recorded as its NIS (1 degree of freedom; the one-sided square is stochastically
        smaller than chi-square(1), so the window test stays conservative). The first
        ``10`` scans only initialize ``m`` and ``s``.
        """
        w0 = self._weights if self._fresh is None else np.where(self._fresh, 0.0, self._weights)
        ok = np.isfinite(ll)
        if w0.sum() <= 0 or not ok.any() or n_terms < 1:
            return None
        per_beam = np.where(ok, ll, -np.inf) / n_terms
        pm = float(np.max(per_beam))
        lk = pm + math.log(float(w0 @ np.exp(per_beam - pm)) / float(w0.sum()))
        n_seen = self._surprise_n
        accepted = True
        nis = 0.0
        if n_seen >= 10 and self._surprise_var > 0:
            u = (lk - self._surprise_mean) / math.sqrt(self._surprise_var)
            nis = min(u, 0.0) ** 2
            accepted = u >= -self._surprise_z
        self.last_nis = nis
        if accepted:
            a = max(self.alpha_slow, 1.0 / (n_seen + 1))
            d = lk - self._surprise_mean if n_seen else 0.0
            self._surprise_mean = lk if n_seen == 0 else self._surprise_mean + a * d
            self._surprise_var = (1.0 - a) * (self._surprise_var + a * d * d)
            self._surprise_n += 1
            self._alarms_since_consistent = 0
        self.stats["gated"] += int(not accepted)
        if n_seen < 10:
            return None
        alarm = self.monitor.record(nis, accepted)
        if alarm is None and not accepted and self._alarms_since_consistent > 0:
            # still rejected after a relocalization: widen the search at once
            alarm = DivergenceAlarm("rejection_run", float(self.monitor.run), float(self.monitor.max_run))
        if alarm is not None:
            self.stats["alarms"] += 1
        return alarm

    def _confirm_relocalization(self, ll: Array, z: Array, angles: Array) -> Array:
        """Keep the relocalized belief if it predicts this (next, independent) scan better
        than the belief without the injection, else undo it; the log-likelihoods of the kept
        particles."""
        sp, sw = self._shadow
        self._shadow = None
        ll_s, _ = self.sensor.log_likelihood(laser_grid_poses(self.grid, sp, self.laser.offset), z, angles)
        w0 = self._weights if self._fresh is None else np.where(self._fresh, 0.0, self._weights)
        log_bf = _log_mean_exp(ll, w0) - _log_mean_exp(ll_s, sw)
        if log_bf > 0.0:
            self.stats["recoveries"] += 1
            logger.info("MCL: relocalization confirmed by the next scan (log Bayes factor %.1f)", log_bf)
            return ll
        self.stats["recovery_failures"] += 1
        logger.info("MCL: relocalization undone: the next scan prefers the belief without it (log Bayes factor %.1f)",
                    log_bf)
        self._particles, self._weights, self._fresh = sp, sw, None
        return ll_s

    def relocalize(self, ll: Array, z: Array, angles: Array, reason: str = "") -> Array:
        r"""Inject particles into the prior of the current scan after a divergence alarm.

        The injected share ``f`` is Augmented MCL's ``max(0, 1 - w_fast / w_slow)`` (Thrun et
        al. 2005, table 8.3; the averages are tracked when ``alpha_slow, alpha_fast > 0``),
        at least ``recovery_min_fraction``: an alarm always relocalizes. ``f N`` new poses
        come from ``recovery_sampler``: ``local`` draws them from ``N(mu^-, chi2.ppf(p, 3)
        4^a Sigma^-)``, the belief before the scan widened to its ``p =
        recovery_probability`` region and its radius doubled for each of the ``a`` alarms
        since the last accepted scan (an expanding search for a drift-type
        lock-out; after a relocalization every further rejected scan raises the next
        alarm at once);
        ``uniform`` draws them uniformly over the free space (Thrun's choice; a kidnapped
        robot). All attempts of one run of alarms search around the belief at its first
        alarm (moved since by the odometry), so that repeated relocalizations cannot walk the
        belief away step by step. The prior becomes the mixture
        ``(1 - f) old + f new``: old particles keep their weights times ``1 - f``, the ``M``
        new ones get ``f / M`` each, and all are then weighted by the *current* scan (``ll``
        is extended with the new particles' log-likelihoods), so new particles that explain
        the scan take over at once. The ``local`` region is capped at the capture range of
        the sensor model (:meth:`_capture_range`: positions within it, headings within the
        turn that moves an end point at the mean beam range that far), and the injection is
        refused (counted in ``recovery_failures``) unless the new particles explain the scan
        better than the belief: their average likelihood must exceed the belief's predictive
        likelihood (a Bayes factor above 1 for "the robot is in the widened region" against
        "the robot is where the belief says"). An injection is tentative: the belief without
        it (weighted by this scan) is kept and moved with the odometry, and the next scan,
        independent evidence, decides: the relocalization is kept only if it predicts that
        scan better (Bayes factor; :meth:`_confirm_relocalization`; two scans must agree, as
        for the scan-matching recovery). ``stats["recoveries"]`` counts the confirmed
        relocalizations, ``stats["recovery_failures"]`` the refused and undone ones.

        On real maps that miss part of what the laser sees, the likelihood test also fires
        where the belief is right, and relocalizing then follows the map's errors (measured
        on the CARMEN logs, ``docs/localization.md``): use it where lock-outs are the
        bigger risk. Returns the extended ``ll`` (unchanged if refused).
        """
        N = self._particles.shape[0]
        p_inj = 0.0
        if self._log_w_slow is not None and (self.alpha_slow > 0 or self.alpha_fast > 0):
            p_inj = max(0.0, 1.0 - math.exp(self._log_w_fast - self._log_w_slow))
        f = min(max(p_inj, self.recovery_min_fraction), 1.0)
        w0 = self._weights if self._fresh is None else np.where(self._fresh, 0.0, self._weights)
        n_new = max(1, int(round(f * N)))
        if self.recovery_sampler == "local":
            if self._alarms_since_consistent == 0 or self._anchor is None:
                mu, C = gaussian_summary(self._particles, w0)
                self._anchor = (mu, 0.5 * (C + C.T), None if self._odom_at_time is None else self._odom_at_time.copy())
            mu, C, o_a = self._anchor
            if o_a is not None and self._odom_at_time is not None:
                mu = se2_compose(mu, se2_between(o_a, self._odom_at_time))
            C = self._chi2_recovery * self.recovery_expansion ** self._alarms_since_consistent * C
            # no farther than the capture range of the sensor model
            reach = self._capture_range()
            lam, V = np.linalg.eigh(C)
            cap = np.array([reach**2, reach**2, (reach / max(self._mean_range, 1e-3)) ** 2])
            lam = np.minimum(np.maximum(lam, 1e-12), (V * V).T @ cap)  # v^T diag(cap) v per axis v
            C = (V * lam) @ V.T
            new = self.rng.multivariate_normal(mu, C, size=n_new, method="eigh")
            new[:, 2] = wrap_angle(new[:, 2])
            free = self.grid.is_free(new[:, :2])
            new = new[free] if free.any() else new
        else:
            new = self.grid.sample_free_poses(n_new, self.rng)
        self._alarms_since_consistent += 1
        lp = laser_grid_poses(self.grid, new, self.laser.offset)
        ll_new, n_terms = self.sensor.log_likelihood(lp, z, angles)
        # Bayes factor of the injected component against the belief (log): the widened
        # region must explain the scan better than the belief does, else nothing changes
        log_bf = _log_mean_exp(ll_new) - _log_mean_exp(ll, w0)
        if not log_bf > 0.0:
            self.stats["recovery_failures"] += 1
            logger.info("MCL: relocalization (%s) refused: the %d %s particles explain the scan worse than "
                        "the belief (log Bayes factor %.1f)", reason, new.shape[0], self.recovery_sampler, log_bf)
            return ll
        M = new.shape[0]
        # the belief without the injection, weighted by this scan, waits for the next scan
        with np.errstate(divide="ignore"):
            a = np.log(w0) + np.where(np.isfinite(ll), ll, -np.inf)
        ws = np.exp(a - np.max(a))
        self._shadow = (self._particles.copy(), ws / ws.sum())
        self._particles = np.concatenate([self._particles, new])
        self._weights = np.concatenate([(1.0 - f) * w0 / w0.sum(), np.full(M, f / M)])
        self._fresh = None
        self.monitor.reset()
        self.stats["injected"] += M
        logger.info("MCL: relocalization (%s): %d %s particles added to %d (prior share %.2f, log Bayes factor "
                    "%.1f)", reason, M, self.recovery_sampler, N, f, log_bf)
        return np.concatenate([ll, ll_new])

    def _skip(self, o_t: Array) -> bool:
        if self._last_update_odom is None or (self.update_min_d <= 0 and self.update_min_a <= 0):
            return False
        d = se2_between(self._last_update_odom, o_t)
        return math.hypot(d[0], d[1]) < self.update_min_d and abs(d[2]) < self.update_min_a

    def _temper(self, logw0: Array, ll: Array) -> float:
        """Largest ``beta`` in ``(0, 1]`` with ``ESS(w L^beta) >= ess_floor N`` (bisection)."""
        N = logw0.size

        def ess(beta: float) -> float:
            a = logw0 + beta * ll
            a = a - np.max(a)
            e = np.exp(a)
            return float(e.sum() ** 2 / (e @ e))

        target = self.ess_floor * N
        if ess(1.0) >= target:
            return 1.0
        lo, hi = 0.0, 1.0
        for _ in range(20):
            mid = 0.5 * (lo + hi)
            if ess(mid) >= target:
                lo = mid
            else:
                hi = mid
        return max(lo, 1e-6)

    def _apply_likelihood(self, ll: Array, n_terms: int) -> None:
        w_prior = self._weights
        with np.errstate(divide="ignore"):
            logw0 = np.log(w_prior)
        ll_raw = ll
        self.last_beta = 1.0
        if self.ess_floor > 0:
            ok = np.isfinite(ll)
            if ok.any():
                beta = self._temper(logw0, np.where(ok, ll, np.min(ll[ok]) - 1e3))
                self.last_beta = beta
                ll = beta * ll
        logw = logw0 + ll
        m = np.max(logw)
        if not np.isfinite(m):  # every particle impossible: keep the prior weights
            return
        w = np.exp(logw - m)
        self._weights = w / w.sum()
        self._fresh = None
        # Augmented-MCL averages of the (per-beam geometric mean) likelihood
        recovering = self.alpha_slow > 0 or self.alpha_fast > 0
        if recovering:  # on the untempered likelihood
            per_beam = ll_raw / max(n_terms, 1)
            pm = np.max(per_beam)
            log_avg = pm + math.log(float(w_prior @ np.exp(per_beam - pm)))
            if self._log_w_slow is None:
                self._log_w_slow = self._log_w_fast = log_avg
            else:
                self._log_w_slow = _log_ema(self._log_w_slow, log_avg, self.alpha_slow)
                self._log_w_fast = _log_ema(self._log_w_fast, log_avg, self.alpha_fast)
        if self.n_eff < self.resample_threshold * self._weights.size:
            self.resample()

    def resample(self) -> None:
        """Resample now (KLD-adaptive or fixed size), with Augmented-MCL injection when enabled."""
        p_inject = 0.0
        if self._log_w_slow is not None and (self.alpha_slow > 0 or self.alpha_fast > 0) and self.monitor is None:
            # continuous Augmented MCL; with a monitor, particles are injected on alarms only
            p_inject = max(0.0, 1.0 - math.exp(self._log_w_fast - self._log_w_slow))
        rng = self.rng
        if self.adaptive:
            # i.i.d. draws (with injection) until the KLD bound is met; drawn in growing
            # chunks so that a converged filter does not draw max_particles candidates
            M = self.max_particles
            cands, injs = [], []
            total = 0
            chunk = min(M, max(self.min_particles, 2 * self._weights.size))
            while True:
                c = self._particles[multinomial_resample(self._weights, rng, chunk)]
                inj = rng.random(chunk) < p_inject if p_inject > 0 else np.zeros(chunk, dtype=bool)
                if inj.any():
                    c[inj] = self.grid.sample_free_poses(int(inj.sum()), rng)
                cands.append(c)
                injs.append(inj)
                total += chunk
                cand = np.concatenate(cands) if len(cands) > 1 else cands[0]
                n = self._kld_count(cand)
                if n < total or total >= M:
                    break
                chunk = min(M - total, total)
            new = cand[:n]
            fresh = (np.concatenate(injs) if len(injs) > 1 else injs[0])[:n]
            n_inj = int(fresh.sum())
        else:
            N = self.n_particles
            n_inj = int(rng.binomial(N, p_inject)) if p_inject > 0 else 0
            new = self._particles[systematic_resample(self._weights, rng, N - n_inj)]
            fresh = None
            if n_inj:
                new = np.concatenate([new, self.grid.sample_free_poses(n_inj, rng)])
                fresh = np.arange(N) >= N - n_inj
        self._particles = new
        self._weights = np.full(new.shape[0], 1.0 / new.shape[0])
        self._fresh = fresh if n_inj else None
        self.stats["resamples"] += 1
        self.stats["injected"] += n_inj
        if n_inj:
            logger.debug("recovery: %d of %d particles drawn uniformly over the free space", n_inj, new.shape[0])

    def _kld_count(self, cand: Array) -> int:
        """Number of leading candidates KLD sampling keeps."""
        M = cand.shape[0]
        b = np.floor(cand / self.kld_bins).astype(np.int64)
        b -= b.min(axis=0)
        span = b.max(axis=0) + 1
        key = (b[:, 0] * span[1] + b[:, 1]) * span[2] + b[:, 2]
        _, first = np.unique(key, return_index=True)
        new_bin = np.zeros(M, dtype=np.int64)
        new_bin[first] = 1
        k = np.cumsum(new_bin)  # non-empty bins after n = 1..M samples
        need = np.clip(kld_sample_size(k, self.kld_err, self._kld_zq), self.min_particles, self.max_particles)
        enough = np.arange(1, M + 1) >= need
        return int(np.argmax(enough)) + 1 if enough.any() else M

    # -- output --------------------------------------------------------------------------
    def estimate(self) -> Estimate:
        """Gaussian summary and reliability of the current particle set."""
        self._require_init()
        w = self._weights
        if self._fresh is not None and not self._fresh.all():
            # particles injected by the recovery step have not been weighted by any scan
            # yet: they are hypotheses, not evidence, and are left out of the summary
            w = np.where(self._fresh, 0.0, w)
        if self.estimate_cluster:
            keep = heaviest_cluster(self._particles, w, self.kld_bins)
            if not keep.all():
                mean, _ = gaussian_summary(self._particles[keep], w[keep])
                r = self._particles - mean
                r[:, 2] = wrap_angle(r[:, 2])
                wn = w / w.sum()
                cov = (r * wn[:, None]).T @ r
                cov = 0.5 * (cov + cov.T)
                return Estimate("mcl", self._time, mean, cov, covariance_reliability(cov),
                                n_particles=self._particles.shape[0], n_eff=self.n_eff)
        mean, cov = gaussian_summary(self._particles, w)
        return Estimate("mcl", self._time, mean, cov, covariance_reliability(cov),
                        n_particles=self._particles.shape[0], n_eff=self.n_eff)


def heaviest_cluster(poses: ArrayLike, weights: ArrayLike, bins: ArrayLike) -> np.ndarray:
    """Mask of the particles in the heaviest cluster of connected histogram bins.

    Poses ``(N, 3)`` are binned on the grid ``bins = (dx, dy, dtheta)`` (the KLD bins;
    headings wrap around); bins that touch (also diagonally: the 26 neighbours in
    ``(x, y, theta)``) form one cluster (connected components); the cluster with the
    largest total weight wins. This is how ROS AMCL chooses its pose estimate
    (``pf_cluster_stats``: clusters of connected kd-tree leaves, the pose of the heaviest
    one), so that a posterior with two modes (a corridor, a junction) is not summarized
    by a point between them where no particle is.
    """
    from scipy.sparse import coo_matrix  # noqa: PLC0415
    from scipy.sparse.csgraph import connected_components  # noqa: PLC0415

    p = np.asarray(poses, dtype=float)
    w = np.asarray(weights, dtype=float)
    bins = np.asarray(bins, dtype=float)
    n_th = max(1, int(math.ceil(2.0 * math.pi / bins[2])))
    b = np.floor(p / bins).astype(np.int64)
    b[:, 2] %= n_th
    uniq, inv = np.unique(b, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    k = uniq.shape[0]
    if k == 1:
        return np.ones(p.shape[0], dtype=bool)
    lo = uniq[:, :2].min(axis=0) - 1
    span = uniq[:, :2].max(axis=0) - lo + 2

    def code(u: np.ndarray) -> np.ndarray:
        return ((u[:, 0] - lo[0]) * span[1] + (u[:, 1] - lo[1])) * n_th + u[:, 2]

    codes = code(uniq)
    order = np.argsort(codes)
    sorted_codes = codes[order]
    rows, cols = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dt in (-1, 0, 1):
                if dx == dy == dt == 0:
                    continue
                nb = uniq + np.array([dx, dy, dt])
                nb[:, 2] %= n_th
                c = code(nb)
                pos = np.minimum(np.searchsorted(sorted_codes, c), k - 1)
                hit = sorted_codes[pos] == c
                rows.append(np.flatnonzero(hit))
                cols.append(order[pos[hit]])
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    graph = coo_matrix((np.ones(r.size), (r, c)), shape=(k, k))
    _, labels = connected_components(graph, directed=False)
    bin_w = np.bincount(inv, weights=w, minlength=k)
    best = int(np.argmax(np.bincount(labels, weights=bin_w)))
    return labels[inv] == best


def _log_mean_exp(a: Array, w: Array | None = None) -> float:
    """``log(sum_i w_i exp(a_i) / sum_i w_i)`` (``w`` = 1 by default), ignoring non-finite ``a``."""
    a = np.asarray(a, dtype=float)
    w = np.ones_like(a) if w is None else np.asarray(w, dtype=float)
    ok = np.isfinite(a) & (w > 0)
    if not ok.any():
        return -math.inf
    m = float(np.max(a[ok]))
    return m + math.log(float(w[ok] @ np.exp(a[ok] - m)) / float(w[ok].sum()))


def _log_ema(log_old: float, log_new: float, alpha: float) -> float:
    """``log((1 - alpha) exp(log_old) + alpha exp(log_new))`` without under/overflow."""
    if alpha <= 0:
        return log_old
    if alpha >= 1:
        return log_new
    a = math.log1p(-alpha) + log_old
    b = math.log(alpha) + log_new
    m = max(a, b)
    return m + math.log(math.exp(a - m) + math.exp(b - m))
