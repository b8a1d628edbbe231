r"""Particle-filter tracking of a radio tag from the RSSI of fixed receivers (URUS sec. 8.3).

State: the tag's horizontal position ``(x, y)`` (``motion="random_walk"``) or
``(x, y, vx, vy)`` (``motion="constant_velocity"``).

**Motion.** Random walk: ``p' = p + w``, ``w ~ N(0, q dt I)`` (``q`` in m^2/s).
Constant velocity: the white-noise-acceleration model of
:class:`dfusion.models.ConstantVelocity` (``q`` in m^2/s^3), with the speed of
each particle optionally capped at ``max_speed``.

**Map constraint (URUS).** With an occupancy grid (a :class:`dfusion.maps.OccupancyGrid`,
or its node-lattice view :class:`dfusion.maps.NodeLattice`), a particle whose
move ends in an occupied cell or whose straight-line move passes through one is
discarded: its weight becomes zero and it keeps its previous (free) position, so
the particle set never contains a position inside an obstacle (occupied and unknown
cells block, and so does everything off the map:
:meth:`dfusion.maps.NodeLattice.segment_blocked`). Roughening
jitters that would cross a wall are vetoed the same way (the particle keeps its
resampled position). If every move of a step is refused the particles stay
where they were (counted in ``n_all_refused``).

**Likelihood ("annulus").** Receiver ``j`` at ``r_j = (a_j, b_j, c_j)`` sees the
tag at height ``h`` with the log-distance model of :class:`RSSISensor`,
``mu_j(p) = p0_j - 10 n_j log10(d_j(p) / d0_j)``, ``d_j = max(||(p, h) - r_j||, d_min)``.
A reading ``z_j`` weighs particle ``p`` by the Gaussian in RSSI

    log L_j(p) = -(z_j - mu_j(p))^2 / (2 sigma_j^2),

which, as a function of position, is a ring ("annulus") around the receiver,
centred on the distance ``d0_j 10^((p0_j - z_j) / (10 n_j))`` and wider the
farther out it lies. Readings of one update are independent; missing readings
(NaN) contribute nothing. ``std_scale`` multiplies every ``sigma_j``: values
above 1 temper the likelihood, which accounts for shadowing that is correlated
in time (successive packets are not independent measurements). With a
:class:`~dfusion.localization.radio_map.RadioMap` (``radio_map=``) the mean and standard
deviation of each reading are the map's at the particle instead (learnt
log-distance-plus-residual model; docs/wsn.md sec. 3), and the reading's law is the
map's noise law (Gaussian, or a left-skewed split normal,
:func:`~dfusion.localization.radio_map.split_normal_logpdf`). With ``outlier_prob = eps > 0``
each reading's density ``f`` (annulus or map) becomes ``(1 - eps) f + eps / rssi_span``.

**Information contribution**
(``docs/background.md#3-particle-filter-nodes-in-an-information-network``). The readings since
the last prediction as one linear-Gaussian measurement of the position ``(x, y)``: their
statistical linear regression over the weighted posterior particles, its error counted as
noise (or, with a radio map or outliers, the Gaussian fit of the posterior minus that of the
prediction, made positive semi-definite): see :meth:`WSNTracker.information_contribution`.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import NotInitializedError, ShapeError, ValidationError
from dfusion.estimation.estimate import Estimate
from dfusion.estimation.gaussian import InformationGaussian, project_psd_information
from dfusion.estimation.particle_filter import (
    ParticleDepletionError,
    ParticleFilter,
    weighted_mean_cov,
)
from dfusion.linalg import Array, as_spd, as_vector, cholesky, spd_inverse, symmetrize
from dfusion.localization.radio_map import RadioMap
from dfusion.maps.grid import OccupancyGrid as MapGrid
from dfusion.maps.lattice import NodeLattice, as_map_grid
from dfusion.models.measurement import RSSISensor
from dfusion.models.motion import ConstantVelocity
from dfusion.reliability import covariance_reliability

__all__ = [
    "WSNTracker",
    "MOTIONS",
]

MOTIONS = ("random_walk", "constant_velocity")

#: Largest ``rows x receivers x 4`` of one matrix product in :meth:`WSNTracker.log_likelihood`.
#: OpenBLAS runs a GEMM multithreaded above ``4 x 65536`` multiply-adds; on a machine whose cores
#: are busy (several node processes, other jobs) the threads wait for each other and one
#: ``(20000 x 4) @ (4 x 12)`` product took 15 ms instead of 0.08 ms (benchmarks/nodes.py).
#: Blocks below the threshold keep every product single-threaded.
_GEMM_BLOCK = 1 << 18


def _rows_matmul(a: Array, b: Array) -> Array:
    """``a @ b`` for a tall ``a`` (N x k) and a small ``b`` (k x m), in row blocks below ``_GEMM_BLOCK``."""
    n, k = a.shape
    m = b.shape[1]
    step = max(1, _GEMM_BLOCK // max(1, k * m))
    if n <= step:
        return a @ b
    out = np.empty((n, m))
    for s in range(0, n, step):
        np.matmul(a[s:s + step], b, out=out[s:s + step])
    return out




def _sensor_arrays(sensors: RSSISensor | Sequence[RSSISensor]) -> dict[str, Array]:
    """Per-receiver parameter arrays from one multi-receiver sensor or a list of sensors."""
    if isinstance(sensors, RSSISensor):
        sensors = [sensors]
    sensors = list(sensors)
    if not sensors or not all(isinstance(s, RSSISensor) for s in sensors):
        raise ValidationError("sensors must be an RSSISensor or a non-empty sequence of RSSISensor")
    cols: dict[str, list] = {k: [] for k in ("rxy", "rz", "height", "p0", "n", "std", "d0", "dmin")}
    for s in sensors:
        m = s.dim_z
        rec = s.receivers
        cols["rxy"].append(rec[:, :2])
        cols["rz"].append(rec[:, 2] if rec.shape[1] == 3 else np.zeros(m))
        for key, val in (("height", s.height), ("p0", s.p0), ("n", s.exponent), ("d0", s.d0), ("dmin", s.d_min)):
            cols[key].append(np.full(m, val))
        cols["std"].append(s.std)
    return {k: np.concatenate(v) if k != "rxy" else np.vstack(v) for k, v in cols.items()}


class WSNTracker:
    """Particle filter tracking a tag from received signal strengths (URUS sec. 8.3).

    Parameters
    ----------
    sensors : RSSISensor or sequence of RSSISensor
        The receivers and their path-loss parameters. One sensor with ``m``
        receivers shares ``p0`` and the exponent; a list (for example one
        single-receiver sensor per receiver, as
        :meth:`dfusion.localization.PathLossCalibration.sensors` builds them from
        :func:`~dfusion.models.fit_path_loss` fits) gives every receiver its own. Receiver ``j`` of :meth:`update` is the
        ``j``-th receiver in this order. The tag height is each sensor's ``height``.
    n_particles : int
        Number of particles.
    motion : {"random_walk", "constant_velocity"}
        Particle motion model.
    q : float
        Process noise: position diffusion (m^2/s) for the random walk, acceleration
        spectral density (m^2/s^3) for constant velocity. The default 0.5 m^2/s
        suits a walking person tracked packet by packet (docs/wsn.md).
    max_speed : float or None
        Constant velocity only: particle speeds are capped at this value (m/s).
    grid : dfusion.maps.OccupancyGrid, dfusion.maps.NodeLattice or None
        Map constraint (see the module docstring); also the initial support.
    bounds : (x_min, y_min, x_max, y_max) or None
        Initial support when there is no grid.
    std_scale : float
        Multiplies every receiver's noise standard deviation in the likelihood.
    outlier_prob, rssi_span : float
        With ``outlier_prob = eps > 0`` each reading's likelihood becomes
        ``(1 - eps) f(z) + eps / rssi_span`` (a uniform floor over a span of ``rssi_span`` dB),
        ``f`` the annulus Gaussian ``N(z; mu, sigma^2)`` or the radio map's density;
        0 (default) keeps the pure model.
    radio_map : RadioMap or None
        If given, the likelihood of a reading of receiver ``j`` is the map's density at the
        particle (its mean and standard deviation by bilinear look-up and its noise law,
        :meth:`RadioMap.log_likelihood`) instead of the log-distance annulus; the
        sensors then only give the receivers' positions. ``std_scale`` and ``outlier_prob``
        still apply.
    seed : int, Generator or None
        Seed of the filter's random generator.
    resampling, ess_threshold, roughening
        As in :class:`ParticleFilter` (roughening acts on the position only).
    """

    def __init__(
        self,
        sensors: RSSISensor | Sequence[RSSISensor],
        n_particles: int = 5000,
        *,
        motion: str = "random_walk",
        q: float = 0.5,
        max_speed: float | None = None,
        grid: MapGrid | NodeLattice | None = None,
        bounds: ArrayLike | None = None,
        std_scale: float = 1.0,
        outlier_prob: float = 0.0,
        rssi_span: float = 60.0,
        radio_map: RadioMap | None = None,
        seed: int | np.random.Generator | None = None,
        resampling: str = "systematic",
        ess_threshold: float = 0.5,
        roughening: float = 0.0,
    ) -> None:
        if motion not in MOTIONS:
            raise ValidationError(f"motion must be one of {MOTIONS}, got {motion!r}")
        if int(n_particles) < 2:
            raise ValidationError(f"n_particles must be >= 2, got {n_particles}")
        if not (np.isfinite(q) and q > 0):
            raise ValidationError(f"q must be positive, got {q}")
        if not (np.isfinite(std_scale) and std_scale > 0):
            raise ValidationError(f"std_scale must be positive, got {std_scale}")
        if not 0.0 <= float(outlier_prob) < 1.0:
            raise ValidationError(f"outlier_prob must be in [0, 1), got {outlier_prob}")
        if not (np.isfinite(rssi_span) and rssi_span > 0):
            raise ValidationError(f"rssi_span must be positive, got {rssi_span}")
        if max_speed is not None and not (np.isfinite(max_speed) and max_speed > 0):
            raise ValidationError(f"max_speed must be positive or None, got {max_speed}")
        if grid is not None and not isinstance(grid, (MapGrid, NodeLattice)):
            raise ValidationError("grid must be an NodeLattice or None")
        if bounds is not None:
            bounds = as_vector(bounds, 4, "bounds (x_min, y_min, x_max, y_max)")
            if not (bounds[2] > bounds[0] and bounds[3] > bounds[1]):
                raise ValidationError(f"bounds must have x_max > x_min and y_max > y_min, got {bounds}")
        p = _sensor_arrays(sensors)
        self.n_receivers = p["p0"].shape[0]
        if radio_map is not None:
            if not isinstance(radio_map, RadioMap) or radio_map.n_receivers != self.n_receivers:
                raise ValidationError(f"radio_map must be a RadioMap with {self.n_receivers} receivers")
        self.radio_map = radio_map
        self.receivers = np.column_stack([p["rxy"], p["rz"]])
        self._dz2 = (p["height"] - p["rz"]) ** 2
        self._dmin2 = p["dmin"] ** 2
        # Distances are expanded about the receivers' centroid (no cancellation for
        # large world coordinates): |p - r|^2 = |p'|^2 - 2 p'.r' + |r'|^2 with p' = p - c.
        self._centre = p["rxy"].mean(axis=0)
        rc = p["rxy"] - self._centre
        self._G = np.vstack([-2.0 * rc.T, np.ones(len(self._dz2)),
                             np.einsum("ij,ij->i", rc, rc) + self._dz2])  # (4, m)
        # Rounding can make the expanded d^2 slightly smaller than dz^2: clamp unless there is margin.
        self._clamp = bool(np.any(self._dz2 <= 1.01 * self._dmin2))
        self.p0, self.exponent, self.std, self.d0 = p["p0"], p["n"], p["std"], p["d0"]
        # log L = -0.5 * (A_j + B_j ln d^2)^2 with A_j = (z_j - p0_j - 10 n_j log10 d0_j) / s_j and
        # B_j = 5 n_j / (s_j ln 10): the residual z - mu in units of the (scaled) std.
        s = self.std * float(std_scale)
        self._inv_s = 1.0 / s
        self._B = 5.0 * self.exponent / (s * np.log(10.0))
        self._A0 = (-self.p0 - 10.0 * self.exponent * np.log10(self.d0)) / s
        self.std_scale = float(std_scale)
        self.outlier_prob = float(outlier_prob)
        self.rssi_span = float(rssi_span)
        # Outlier floor in the same units: log(eps / (1 - eps) * s_j sqrt(2 pi) / span).
        self._floor = (np.log(self.outlier_prob / (1.0 - self.outlier_prob)) + np.log(s * np.sqrt(2 * np.pi) / self.rssi_span)
                       if self.outlier_prob > 0 else None)
        self.motion = motion
        self.q = float(q)
        self.max_speed = None if max_speed is None else float(max_speed)
        self.grid = grid
        self._map: MapGrid | None = None if grid is None else as_map_grid(grid)
        self.bounds = bounds
        self.n_particles = int(n_particles)
        self.dim = 2 if motion == "random_walk" else 4
        self._seed = seed
        self._pf_args = dict(resampling=resampling, ess_threshold=ess_threshold, roughening=roughening)
        ParticleFilter(np.zeros((2, self.dim)), **self._pf_args)  # validate the arguments now
        self.pf: ParticleFilter | None = None
        # (particles, log-weights) after the last predict and after the last weighting.
        self._prior_snap: tuple[Array, Array] | None = None
        self._post_snap: tuple[Array, Array] | None = None
        # Readings (z, receiver indices) weighted in since the last prediction (for the contribution).
        self._pending: list[tuple[Array, np.ndarray]] = []
        #: Moves refused by the map (cumulative) and steps in which every move was refused.
        self.n_refused = 0
        self.n_all_refused = 0
        #: Time of the particles (set by :meth:`initialize`).
        self.time: float | None = None

    def __repr__(self) -> str:
        return (f"WSNTracker(receivers={self.n_receivers}, n_particles={self.n_particles}, motion={self.motion!r}, "
                f"q={self.q}, grid={self.grid!r})")

    # ------------------------------------------------------------ set-up
    def initialize(self, mean: ArrayLike | None = None, cov: ArrayLike | None = None,
                   speed_std: float = 0.5, t: float = 0.0) -> None:
        """Draw the initial particles, at time ``t``.

        Without ``mean``: uniform over the grid's free area (or ``bounds``). With
        ``mean`` and ``cov`` (2 x 2): Gaussian positions; with a grid, samples in
        obstacles are redrawn (up to 100 rounds). Velocities (constant-velocity
        model) are ``N(0, speed_std^2 I)``.
        """
        rng = np.random.default_rng(self._seed) if not isinstance(self._seed, np.random.Generator) else self._seed
        n = self.n_particles
        if mean is None:
            if self._map is not None:
                pos = self._map.sample_free(n, rng)
            elif self.bounds is not None:
                lo, hi = self.bounds[:2], self.bounds[2:]
                pos = lo + rng.random((n, 2)) * (hi - lo)
            else:
                raise ValidationError("initialize() needs a mean, a grid or bounds")
        else:
            m = as_vector(mean, 2, "initial mean")
            C = np.eye(2) if cov is None else as_spd(cov, 2, "initial covariance")
            L = np.linalg.cholesky(C)
            pos = m + rng.standard_normal((n, 2)) @ L.T
            if self.grid is not None:
                for _ in range(100):
                    bad = self._map.is_blocked(pos)
                    if not bad.any():
                        break
                    pos[bad] = m + rng.standard_normal((int(bad.sum()), 2)) @ L.T
                else:
                    raise ValidationError("could not draw initial particles in free space around the mean")
        x = pos if self.dim == 2 else np.column_stack([pos, rng.standard_normal((n, 2)) * speed_std])
        self.pf = ParticleFilter(x, rng=rng, **self._pf_args)
        self.pf.roughening_dims = (0, 1)  # jitter positions only
        self._prior_snap = self._snapshot()
        self._post_snap = self._prior_snap
        self._pending = []
        self.time = float(t)

    @property
    def rng(self) -> np.random.Generator:
        """The random generator of every draw of the tracker (after :meth:`initialize`)."""
        return self._require().rng

    def set_particles(self, particles: ArrayLike) -> None:
        """Replace the particles (equal weights), e.g. to draw velocities from a prior."""
        self._require().set_particles(particles)

    def _require(self) -> ParticleFilter:
        if self.pf is None:
            raise NotInitializedError("WSNTracker used before initialize()")
        return self.pf

    def _fit(self) -> tuple[Array, Array]:
        pf = self._require()
        return weighted_mean_cov(pf.particles[:, :2], pf.weights)

    def _snapshot(self) -> tuple[Array, Array]:
        # The filter replaces its arrays instead of writing into them, so references suffice.
        pf = self._require()
        return pf.particles, pf.log_weights

    # -------------------------------------------------------- prediction
    def _accept(self, old: Array, new: Array) -> np.ndarray:
        if self._map is None:
            return np.ones(old.shape[0], dtype=bool)
        return ~self._map.segment_blocked(old[:, :2], new[:, :2])

    def predict(self, t: float, u: None = None) -> int:
        """Move the particles to time ``t`` (not before their time); returns how many moves
        the map refused.

        The Gaussian fit of the prediction (after the map constraint, which is part
        of the motion model) is stored for :meth:`information_contribution`.
        """
        pf = self._require()
        t = float(t)
        dt = t - self.time
        if not (np.isfinite(dt) and dt >= 0):
            raise ValidationError(f"cannot predict the particles from t={self.time} back to t={t}")
        self.time = t
        refused = 0
        if dt > 0:
            x = pf.particles
            n = x.shape[0]
            if self.motion == "random_walk":
                new = x + pf.rng.standard_normal((n, 2)) * np.sqrt(self.q * dt)
            else:
                L = np.linalg.cholesky(ConstantVelocity(2, self.q).Q(dt))
                new = x.copy()
                new[:, :2] += dt * x[:, 2:]
                new += _rows_matmul(pf.rng.standard_normal((n, 4)), L.T)
                if self.max_speed is not None:
                    sp = np.hypot(new[:, 2], new[:, 3])
                    over = sp > self.max_speed
                    new[over, 2:] *= (self.max_speed / sp[over])[:, None]
            if self.grid is None:
                pf.move(new)
            else:
                ok = self._accept(x, new)
                try:
                    refused = pf.move(new, ok)
                except ParticleDepletionError:
                    refused = n
                    self.n_all_refused += 1
                self.n_refused += refused
        self._prior_snap = self._snapshot()
        self._post_snap = self._prior_snap
        self._pending = []
        return refused

    # ------------------------------------------------------------ update
    def log_likelihood(self, rssi: ArrayLike, receivers: ArrayLike | None = None,
                       particles: ArrayLike | None = None) -> Array:
        """Per-particle log-likelihood (up to a constant) of RSSI readings.

        ``rssi``: ``(m,)`` with one entry per receiver, NaN where missing; or, with
        ``receivers`` (integer indices, repeats allowed), ``(k,)`` readings of those
        receivers. ``particles`` defaults to the filter's own.
        """
        z, j = self._readings(rssi, receivers)
        x = self._require().particles if particles is None else np.asarray(particles, dtype=float)
        if x.ndim != 2 or x.shape[1] < 2:
            raise ShapeError(f"particles must have shape (N, >= 2), got {x.shape}")
        if j.size == 0:
            return np.zeros(x.shape[0])
        if self.radio_map is not None:
            return self.radio_map.log_likelihood(z, j, x[:, :2], self.std_scale, self.outlier_prob, self.rssi_span)
        # Squared 3-D distances by expansion, as one matmul:
        # [x, y, x^2 + y^2, 1] @ [-2 a_j, -2 b_j, 1, a_j^2 + b_j^2 + dz_j^2]
        # (built transposed: row-wise writes into an (N, 4) array are slow in numpy)
        PT = np.empty((4, x.shape[0]))
        np.subtract(x[:, 0], self._centre[0], out=PT[0])
        np.subtract(x[:, 1], self._centre[1], out=PT[1])
        np.multiply(PT[0], PT[0], out=PT[2])
        PT[2] += np.square(PT[1], out=PT[3])
        PT[3] = 1.0
        d2 = _rows_matmul(PT.T, self._G[:, j])   # row blocks: see _GEMM_BLOCK
        if self._clamp:  # some receiver can be closer than d_min (else d^2 >= dz^2 >= d_min^2)
            np.maximum(d2, self._dmin2[j], out=d2)
        L = np.log(d2, out=d2)
        a = z * self._inv_s[j] + self._A0[j]  # residual / std = a_j + B_j ln d^2
        b = self._B[j]
        if self._floor is None:
            # sum_j (a_j + b_j L_ij)^2 = sum a^2 + L (2 a b) + L^2 (b^2)
            out = L @ (2.0 * a * b)
            out += np.square(L, out=L) @ (b * b)
            out += a @ a
            out *= -0.5
            return out
        L *= b
        L += a
        np.square(L, out=L)
        L *= -0.5
        np.logaddexp(L, self._floor[j], out=L)
        return L.sum(axis=1)

    def _readings(self, rssi: ArrayLike, receivers: ArrayLike | None) -> tuple[Array, np.ndarray]:
        z = np.asarray(rssi, dtype=float).reshape(-1)
        if receivers is None:
            if z.shape[0] != self.n_receivers:
                raise ShapeError(f"rssi must have one entry per receiver ({self.n_receivers}), got {z.shape[0]}")
            j = np.flatnonzero(np.isfinite(z))
            return z[j], j
        j = np.asarray(receivers).reshape(-1)
        if j.shape != z.shape:
            raise ShapeError(f"receivers and rssi must have the same length, got {j.shape[0]} and {z.shape[0]}")
        if j.size and (not np.issubdtype(j.dtype, np.integer) or j.min() < 0 or j.max() >= self.n_receivers):
            raise ValidationError(f"receiver indices must be integers in [0, {self.n_receivers})")
        keep = np.isfinite(z)
        return z[keep], j[keep].astype(np.int64)

    def update(self, t: float, rssi: ArrayLike, receivers: ArrayLike | None = None) -> int:
        """Weight the particles by RSSI readings taken at ``t`` (see :meth:`log_likelihood`),
        then resample if needed.

        The particles are first predicted to ``t`` if they are older. Returns the number of
        readings used (0: none; missing ones are skipped). The Gaussian fit of the
        posterior (before resampling) is stored for :meth:`information_contribution`.
        """
        pf = self._require()
        if t > self.time:
            self.predict(t)
        z, j = self._readings(rssi, receivers)
        if j.size:
            pf.update(self.log_likelihood(z, j))
            self._post_snap = self._snapshot()
            self._pending.append((z, j))
            pf.resample_if_needed(accept=self._accept if self.grid is not None else None)
        return int(j.size)

    def reweight_information(self, info: InformationGaussian) -> None:
        """Re-weight the particles by information on ``(x, y)`` received from the network.

        Multiplies each weight by ``exp(eta^T p - p^T Omega p / 2)``, the likelihood that
        the information pair ``(eta, Omega)`` represents (pass the fused information minus this
        node's own share, or it is counted twice; ``docs/background.md`` sec. 3), then
        resamples if needed. The result becomes the new reference of
        :meth:`information_contribution` (like a prediction), so that the next
        contribution again holds only this node's own RSSI readings; readings
        processed since the last :meth:`predict` but not yet reported are therefore
        lost to the network: read the contribution first.
        """
        pf = self._require()
        if not isinstance(info, InformationGaussian) or info.dim != 2:
            raise ShapeError("reweight_information needs a 2-D InformationGaussian over (x, y)")
        p = pf.particles[:, :2]
        ll = p @ info.eta - 0.5 * np.einsum("ij,jk,ik->i", p, info.Omega, p)
        pf.update(ll)
        # Not a measurement of this node: fold it into the prediction side of the contribution.
        self._prior_snap = self._post_snap = self._snapshot()
        self._pending = []
        pf.resample_if_needed(accept=self._accept if self.grid is not None else None)

    # ----------------------------------------------------------- outputs
    @property
    def particles(self) -> Array:
        """The ``(N, dim)`` particles (read-only)."""
        return self._require().particles

    @property
    def weights(self) -> Array:
        """Normalized particle weights."""
        return self._require().weights

    def estimate(self) -> Estimate:
        """Weighted mean and covariance of the position ``(x, y)`` (the tracker's own readings only)."""
        pf = self._require()
        mean, cov = self._fit()
        return Estimate("wsn", self.time, mean, cov, covariance_reliability(cov), n_particles=pf.n, n_eff=pf.ess)

    def information_contribution(self, rtol: float = 1e-9, method: str = "quotient") -> InformationGaussian:
        r"""What this node's RSSI readings added, as information on ``(x, y)`` (``docs/background.md`` sec. 3).

        ``method = "regression"`` (the log-distance model without outliers, ``radio_map is
        None`` and ``outlier_prob == 0``; else ``"quotient"`` is used; scenario key
        ``pf_information``): the
        readings weighted in since the last :meth:`predict` are written as one linear-Gaussian
        measurement of the position by statistical linear regression over the weighted
        posterior particles (posterior linearization: Garcia-Fernandez, Svensson, Morelande
        and Sarkka, "Posterior linearization filter: principles and implementation using
        sigma points", IEEE TSP 63(20), 2015, eqs. 9-11). With ``p_i`` the particles, ``w_i``
        their weights, ``h(p)`` the mean RSSI of the log-distance model at each reading's
        receiver and ``R = diag(s_j^2)``::

            A = C_hp P^-1,  b = h_bar - A p_bar,  Omega_lin = C_hh - A P A^T
            z ~ N(A x + b, R + Omega_lin)
            Omega = A^T (R + Omega_lin)^-1 A,   eta = A^T (R + Omega_lin)^-1 (z - b)

        (``p_bar, P``: weighted mean and covariance of the positions; ``h_bar, C_hp, C_hh``:
        of ``h`` and its cross-covariance). ``Omega_lin`` is the error of the linearization
        over the posterior's spread, counted as measurement noise, so the pseudo-measurement
        ``Omega^+ eta`` is honest where the likelihood is far from Gaussian (a direction the
        readings hardly constrain gets little information, not a distant mean). ``Omega``
        is positive semi-definite by construction. With degenerate weights (effective sample
        size below 3, the parameters of an affine fit in 2-D, or no spread of the positions in
        some direction) the slope ``C_hp P^-1`` is rounding noise; the regression's limit for a
        narrow posterior is used instead, the first-order expansion at the weighted mean:
        ``A = dh/dp(p_bar)`` (:meth:`mean_rssi_jacobian`), ``b = h(p_bar) - A p_bar``,
        ``Omega_lin = 0``.

        ``method = "quotient"`` (the default): the Gaussian fit of the posterior divided by that of the
        prediction, ``Omega = P_post^-1 - P_pred^-1``, ``eta = P_post^-1 mu_post - P_pred^-1
        mu_pred`` (fits of the same particles before and after weighting), projected to
        positive semi-definite by :func:`project_psd_information` (negative eigenvalues appear
        when the posterior is wider than its prediction in some direction, e.g. a ring-shaped
        likelihood). Exact for a Gaussian prior and a linear measurement, but where the
        likelihood tilts the posterior in a direction it hardly narrows it, the quotient is
        a small ``lambda`` with a mean shift ``g``: a pseudo-measurement ``g / lambda`` far
        from the truth (on ``topologies/urus-mobile.scenario.toml`` seed 29, normalized
        errors against the truth up to 335 for 2 degrees of freedom; docs/dynamic-topology.md).

        Zero (and ``Omega = 0``) when there was no reading. Both tend to the EIF term
        ``H^T R^-1 H`` and ``H^T R^-1 (z - h(mu) + H mu)`` for a narrow posterior.
        Because the tag's measurement depends on the position only, the 2-D pair can be
        added to the position block of a larger state (velocities get zeros).
        Call it after the update(s) of a step and before the next :meth:`predict`.
        """
        self._require()
        if method not in ("regression", "quotient"):
            raise ValidationError(f"method must be 'regression' or 'quotient', got {method!r}")
        if self._post_snap is self._prior_snap:
            return InformationGaussian(np.zeros(2), np.zeros((2, 2)))
        if method == "regression" and self.radio_map is None and self.outlier_prob == 0.0 and self._pending:
            return self._regression_information()
        m0, P0 = weighted_mean_cov(self._prior_snap[0][:, :2], np.exp(self._prior_snap[1]))
        m1, P1 = weighted_mean_cov(self._post_snap[0][:, :2], np.exp(self._post_snap[1]))
        O0 = spd_inverse(P0, "covariance of the predicted particles")
        O1 = spd_inverse(P1, "covariance of the posterior particles")
        Om, eta, _ = project_psd_information(O1 - O0, O1 @ m1 - O0 @ m0, rtol)
        return InformationGaussian(eta, Om)

    def mean_rssi(self, positions: ArrayLike, receivers: ArrayLike) -> Array:
        """``(N, k)`` mean RSSI of the log-distance model at ``positions`` ``(N, >= 2)`` for the
        receiver indices ``receivers`` ``(k,)``: ``p0 - 10 n log10(d / d0)`` (``d``: 3-D distance,
        at least ``d_min``)."""
        x = np.asarray(positions, dtype=float)
        j = np.asarray(receivers, dtype=np.int64).reshape(-1)
        if x.ndim != 2 or x.shape[1] < 2:
            raise ShapeError(f"positions must have shape (N, >= 2), got {x.shape}")
        d2 = (x[:, None, 0] - self.receivers[j, 0]) ** 2 + (x[:, None, 1] - self.receivers[j, 1]) ** 2 + self._dz2[j]
        d2 = np.maximum(d2, self._dmin2[j])
        # residual / s = z / s + A0 + B ln d^2 (log_likelihood), so the mean is -s (A0 + B ln d^2)
        return -(self._A0[j] + self._B[j] * np.log(d2)) / self._inv_s[j]

    def mean_rssi_jacobian(self, position: ArrayLike, receivers: ArrayLike) -> Array:
        """``(k, 2)`` Jacobian of :meth:`mean_rssi` at one ``position`` ``(>= 2,)``:
        ``-10 n_j / ln 10 (p - r_j)^T / d_j^2`` (zero where the distance is clamped at ``d_min``)."""
        x = as_vector(np.asarray(position, dtype=float).reshape(-1)[:2], 2, "position")
        j = np.asarray(receivers, dtype=np.int64).reshape(-1)
        diff = x - self.receivers[j, :2]
        d2 = np.einsum("ij,ij->i", diff, diff) + self._dz2[j]
        # mean = -s (A0 + B ln d^2): d mean / dp = -s B 2 (p - r) / d^2, with s B = 5 n / ln 10
        g = (-2.0 * self._B[j] / self._inv_s[j]) / d2
        g[d2 < self._dmin2[j]] = 0.0
        return g[:, None] * diff

    def _regression_information(self) -> InformationGaussian:
        """The ``"regression"`` contribution of :meth:`information_contribution`."""
        x, lw = self._post_snap
        w = np.exp(lw - lw.max())
        w /= w.sum()
        p = x[:, :2]
        z = np.concatenate([zz for zz, _ in self._pending])
        j = np.concatenate([jj for _, jj in self._pending])
        R = np.diag(1.0 / self._inv_s[j] ** 2)
        pb = w @ p
        dp = p - pb
        P = (dp * w[:, None]).T @ dp
        if 1.0 / float(w @ w) < 3.0 or not np.all(np.linalg.eigvalsh(P) > 1e-12 * max(1.0, float(np.trace(P)))):
            # Degenerate weights: fewer effective particles than an affine fit in 2-D has
            # parameters (ESS < 3), or positions with no spread in some direction. The slope
            # C_hp P^-1 is then rounding noise (weights of 1e-60 next to 1), and it is undefined
            # for a point mass; its limit for a narrow posterior is the first-order Taylor
            # expansion at the weighted mean: A = dh/dp(p_bar), b = h(p_bar) - A p_bar, Omega_lin = 0.
            A = self.mean_rssi_jacobian(pb, j)
            hb = self.mean_rssi(pb[None], j)[0]
            S = R
        else:
            h = self.mean_rssi(p, j)                              # (N, k)
            hb = w @ h
            dh = h - hb
            Chp = (dh * w[:, None]).T @ dp                        # (k, 2)
            Chh = (dh * w[:, None]).T @ dh
            A = np.linalg.solve(P, Chp.T).T                       # C_hp P^-1 (P symmetric)
            S = R + Chh - A @ P @ A.T
        Lc = cholesky(symmetrize(S), "covariance of the RSSI regression's readings")
        G = np.linalg.solve(Lc, A)                                # L^-1 A
        r = np.linalg.solve(Lc, z - hb + A @ pb)                  # L^-1 (z - b)
        Om = G.T @ G
        return InformationGaussian(G.T @ r, symmetrize(Om))
