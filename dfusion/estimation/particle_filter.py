r"""A generic, vectorized particle filter (sequential importance resampling).

The belief is a set of ``N`` particles ``x_i`` (an ``(N, d)`` array) with
log-weights ``l_i``; the normalized weights are ``w_i = exp(l_i) / sum_j exp(l_j)``.
Log-weights are kept normalized (``logsumexp(l) = 0``) so that likelihoods far
in the tails never underflow. A particle with weight zero has ``l_i = -inf``.

Building blocks (Gordon, Salmond & Smith, "Novel approach to nonlinear/
non-Gaussian Bayesian state estimation", IEE Proc. F 140(2), 1993; Douc, Cappé &
Moulines, "Comparison of resampling schemes for particle filtering", ISPA 2005;
Kong, Liu & Wong, JASA 89(425), 1994, for the effective sample size):

* **effective sample size** ``ESS = 1 / sum_i w_i^2`` (between 1 and ``N``);
* **resampling** when ``ESS < threshold * N``: *systematic* (one uniform
  ``u ~ U[0, 1/N)``, pointers ``u + k/N``; every particle is copied
  ``floor(N w_i)`` or ``ceil(N w_i)`` times; computed in O(N) from the
  cumulative weights, no search) or *stratified* (one uniform per stratum
  ``[k/N, (k+1)/N)``, one ``searchsorted``); both are unbiased;
* **roughening** (Gordon et al. 1993, sec. 4): after resampling, every component
  ``j`` is jittered by ``N(0, sigma_j^2)`` with ``sigma_j = K E_j N^(-1/d)``,
  ``E_j`` the range (max - min) of component ``j`` over the particles and ``K``
  a tuning constant (Gordon et al. use 0.2);
* **Gaussian summary**: weighted mean ``m = sum_i w_i x_i`` and covariance
  ``C = sum_i w_i (x_i - m)(x_i - m)^T`` (the weighted maximum-likelihood fit;
  equal to ``numpy.cov(x.T, aweights=w, bias=True)``).

All randomness comes from one seeded :class:`numpy.random.Generator`, so a run
is reproducible from its seed.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import DfusionError, ShapeError, ValidationError
from dfusion.geometry import wrap_angle
from dfusion.linalg import Array

__all__ = [
    "ParticleFilter",
    "ParticleDepletionError",
    "effective_sample_size",
    "normalize_log_weights",
    "systematic_counts",
    "systematic_resample",
    "stratified_resample",
    "multinomial_resample",
    "roughening_std",
    "weighted_mean_cov",
    "RESAMPLERS",
    "gaussian_summary",
]


class ParticleDepletionError(DfusionError, RuntimeError):
    """Every particle would get weight zero: the update is refused and the filter left unchanged."""


def _as_rng(rng: int | np.random.Generator | None) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    return np.random.default_rng(rng)


def normalize_log_weights(log_weights: ArrayLike) -> tuple[Array, float]:
    """Return ``(l - logsumexp(l), logsumexp(l))``.

    Raises :class:`ParticleDepletionError` when every entry is ``-inf`` (no
    particle has positive weight) and :class:`ValidationError` on NaN or ``+inf``.
    """
    lw = np.asarray(log_weights, dtype=float)
    if np.any(np.isnan(lw)) or np.any(lw == np.inf):
        raise ValidationError("log-weights contain NaN or +inf")
    top = float(np.max(lw)) if lw.size else -np.inf
    if top == -np.inf:
        raise ParticleDepletionError("every particle has weight zero")
    lse = top + float(np.log(np.sum(np.exp(lw - top))))
    return lw - lse, lse


def effective_sample_size(weights: ArrayLike, log: bool = False) -> float:
    """``1 / sum_i w_i^2`` of the normalized weights (``log=True``: ``weights`` are log-weights)."""
    w = np.asarray(weights, dtype=float)
    if log:
        w = np.exp(normalize_log_weights(w)[0])
    else:
        if np.any(w < 0) or not np.all(np.isfinite(w)):
            raise ValidationError("weights must be finite and non-negative")
        s = w.sum()
        if s <= 0:
            raise ParticleDepletionError("every particle has weight zero")
        w = w / s
    return float(1.0 / _sum_sq(w))


def _sum_sq(w: Array) -> float:
    """``sum w_i^2`` without BLAS: OpenBLAS runs ``dot`` multithreaded above 10,000 entries, which on
    a machine with busy cores took 8 ms instead of 0.01 ms at 20,000 particles (benchmarks/nodes.py)."""
    return float(np.einsum("i,i->", w, w))


def _cumulative(weights: Array) -> Array:
    c = np.cumsum(weights)
    c /= c[-1]  # exact 1 at the end: no pointer can fall past the last particle
    c[-1] = 1.0
    return c


def systematic_counts(weights: ArrayLike, u: float, n: int | None = None) -> np.ndarray:
    """How often systematic resampling with offset ``u`` in ``[0, 1)`` copies each particle.

    The pointers ``(u + k) / n``, ``k = 0 .. n-1``, below the cumulative weight
    ``C_i`` number ``ceil(n C_i - u)``, so particle ``i`` gets
    ``ceil(n C_i - u) - ceil(n C_{i-1} - u)`` copies: ``floor(n w_i)`` or
    ``ceil(n w_i)``. O(N), no search.
    """
    w = np.asarray(weights, dtype=float)
    n = w.shape[0] if n is None else int(n)
    c = np.cumsum(w)
    c *= n / c[-1]
    k = np.ceil(c - u).astype(np.int64)
    np.clip(k, 0, n, out=k)
    k[-1] = n  # C_N = 1 exactly: every pointer lies below it
    return np.diff(k, prepend=0)


def systematic_resample(weights: ArrayLike, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """Indices drawn by systematic resampling: pointers ``(u + k) / n``, one ``u ~ U[0, 1)``.

    Particle ``i`` is selected ``floor(n w_i)`` or ``ceil(n w_i)`` times (see
    :func:`systematic_counts`); the indices come out sorted.
    """
    w = np.asarray(weights, dtype=float)
    counts = systematic_counts(w, rng.random(), n)
    return np.repeat(np.arange(w.shape[0]), counts)


def stratified_resample(weights: ArrayLike, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """Indices drawn by stratified resampling: pointers ``(u_k + k) / n``, ``u_k ~ U[0, 1)`` independent."""
    w = np.asarray(weights, dtype=float)
    n = w.shape[0] if n is None else int(n)
    pointers = (rng.random(n) + np.arange(n)) / n
    return np.searchsorted(_cumulative(w), pointers, side="right").clip(max=w.shape[0] - 1)


def multinomial_resample(weights: ArrayLike, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """Indices of ``n`` i.i.d. draws from the weights (``weights`` need not be normalized).

    The draws are ``u_k ~ U[0, 1)`` scaled to the total weight and located in the
    cumulative weights, so a prefix of the result is itself a multinomial sample: KLD
    sampling (:class:`dfusion.localization.MonteCarloLocalization`) stops drawing once
    enough bins are filled.
    """
    w = np.asarray(weights, dtype=float)
    n = w.shape[0] if n is None else int(n)
    cdf = np.cumsum(w)
    return np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), cdf.size - 1)


RESAMPLERS: dict[str, Callable[..., np.ndarray]] = {
    "systematic": systematic_resample,
    "stratified": stratified_resample,
    "multinomial": multinomial_resample,
}


def roughening_std(particles: ArrayLike, K: float) -> Array:
    """Gordon et al. (1993) roughening standard deviations ``K * (max - min) * N^(-1/d)`` per component."""
    x = np.asarray(particles, dtype=float)
    n, d = x.shape
    return float(K) * np.ptp(x, axis=0) * n ** (-1.0 / d)


def weighted_mean_cov(particles: ArrayLike, weights: ArrayLike) -> tuple[Array, Array]:
    """Weighted mean and (maximum-likelihood, ``bias=True``) covariance of the rows of ``particles``.

    ``weights`` need not be normalized; zero weights are allowed.
    """
    x = np.asarray(particles, dtype=float)
    w = np.asarray(weights, dtype=float)
    s = w.sum()
    if s <= 0:
        raise ParticleDepletionError("every particle has weight zero")
    w = w / s
    m = w @ x
    dx = x - m
    C = (dx * w[:, None]).T @ dx
    return m, 0.5 * (C + C.T)


def _validated(particles: ArrayLike, log_weights: ArrayLike | None) -> tuple[Array, Array]:
    """Copies of ``particles`` as a finite ``(N, d)`` array and of the normalized log-weights."""
    x = np.array(particles, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or x.shape[0] < 1:
        raise ShapeError(f"particles must have shape (N, d), got {np.shape(particles)}")
    if not np.all(np.isfinite(x)):
        raise ValidationError("particles contain NaN or inf")
    if log_weights is None:
        return x, np.full(x.shape[0], -np.log(x.shape[0]))
    lw = np.array(log_weights, dtype=float)
    if lw.shape != (x.shape[0],):
        raise ShapeError(f"log_weights must have shape ({x.shape[0]},), got {lw.shape}")
    return x, normalize_log_weights(lw)[0]


class ParticleFilter:
    """Weighted particle set with resampling, roughening and a Gaussian summary.

    Parameters
    ----------
    particles : (N, d) array
        Initial particles (copied).
    log_weights : (N,) array, optional
        Initial log-weights (normalized on entry); equal weights by default.
    rng : int, Generator or None
        Seed or generator; every random draw of the filter uses it.
    resampling : {"systematic", "stratified"}
        Resampling scheme.
    ess_threshold : float in [0, 1]
        :meth:`resample_if_needed` resamples when ``ESS < ess_threshold * N``
        (1 resamples at every step unless all weights are equal; 0 never).
    roughening : float
        Gordon's ``K``; 0 disables roughening. Applied after every resampling.

    The filter is model-agnostic: the caller moves the particles
    (:meth:`move`) and supplies per-particle log-likelihoods (:meth:`update`).
    """

    def __init__(
        self,
        particles: ArrayLike,
        log_weights: ArrayLike | None = None,
        *,
        rng: int | np.random.Generator | None = None,
        resampling: str = "systematic",
        ess_threshold: float = 0.5,
        roughening: float = 0.0,
    ) -> None:
        if resampling not in RESAMPLERS:
            raise ValidationError(f"resampling must be one of {sorted(RESAMPLERS)}, got {resampling!r}")
        if not 0.0 <= float(ess_threshold) <= 1.0:
            raise ValidationError(f"ess_threshold must be in [0, 1], got {ess_threshold}")
        if not (np.isfinite(roughening) and roughening >= 0):
            raise ValidationError(f"roughening must be >= 0, got {roughening}")
        x, lw = _validated(particles, log_weights)
        self._x = x
        self._lw = lw
        self.rng = _as_rng(rng)
        self.resampling = resampling
        self.ess_threshold = float(ess_threshold)
        self.roughening = float(roughening)
        #: Number of resamplings performed so far.
        self.n_resamples = 0
        #: Components jittered by roughening (None: all).
        self.roughening_dims: tuple[int, ...] | None = None

    # ------------------------------------------------------------------ state
    @property
    def n(self) -> int:
        """Number of particles ``N``."""
        return self._x.shape[0]

    @property
    def dim(self) -> int:
        """State dimension ``d``."""
        return self._x.shape[1]

    @property
    def particles(self) -> Array:
        """The ``(N, d)`` particles (a read-only view)."""
        v = self._x.view()
        v.flags.writeable = False
        return v

    @property
    def log_weights(self) -> Array:
        """Normalized log-weights (``logsumexp = 0``; ``-inf`` = weight zero), read-only view."""
        v = self._lw.view()
        v.flags.writeable = False
        return v

    @property
    def weights(self) -> Array:
        """Normalized weights (sum to 1)."""
        return np.exp(self._lw)

    @property
    def ess(self) -> float:
        """Effective sample size ``1 / sum w_i^2``."""
        w = np.exp(self._lw)
        return float(1.0 / _sum_sq(w))

    def set_particles(self, particles: ArrayLike, log_weights: ArrayLike | None = None) -> None:
        """Replace the particle set (the number of particles may change; equal weights by default)."""
        self._x, self._lw = _validated(particles, log_weights)

    # ------------------------------------------------------------- prediction
    def move(self, new_particles: ArrayLike, valid: ArrayLike | None = None) -> int:
        """Replace the particles by ``new_particles`` (the prediction step).

        ``valid`` (boolean ``(N,)``) marks the moves that are allowed. A refused
        move is discarded: that particle keeps its previous state and gets weight
        zero. If every move is refused the particles keep their previous states and
        weights and :class:`ParticleDepletionError` is raised. Returns the number of
        refused moves.
        """
        y = np.asarray(new_particles, dtype=float)
        if y.shape != self._x.shape:
            raise ShapeError(f"new particles must have shape {self._x.shape}, got {y.shape}")
        if valid is None:
            self._x = y.copy()
            return 0
        ok = np.asarray(valid, dtype=bool)
        if ok.shape != (self.n,):
            raise ShapeError(f"valid must have shape ({self.n},), got {ok.shape}")
        alive = ok & (self._lw > -np.inf)
        if not np.any(alive):
            raise ParticleDepletionError("every move was refused")
        bad = np.flatnonzero(~ok)
        lw = self._lw.copy()
        lw[bad] = -np.inf
        lw, _ = normalize_log_weights(lw)
        x = y.copy()
        x[bad] = np.take(self._x, bad, axis=0)
        self._x = x
        self._lw = lw
        return int(self.n - np.count_nonzero(ok))

    def predict(self, transition: Callable[[Array, np.random.Generator], Array]) -> None:
        """Move every particle with ``transition(particles, rng) -> new particles``."""
        self.move(transition(self._x.copy(), self.rng))

    # ----------------------------------------------------------------- update
    def update(self, log_likelihood: ArrayLike) -> float:
        """Multiply the weights by ``exp(log_likelihood)`` (``(N,)``, ``-inf`` allowed).

        Returns the log of the predictive likelihood ``log sum_i w_i p(z | x_i)``.
        Raises :class:`ParticleDepletionError` (filter unchanged) if no particle
        keeps a positive weight, :class:`ValidationError` on NaN or ``+inf``.
        """
        ll = np.asarray(log_likelihood, dtype=float)
        if ll.shape != (self.n,):
            raise ShapeError(f"log-likelihood must have shape ({self.n},), got {ll.shape}")
        lw = self._lw + ll
        top = float(lw.max())  # NaN propagates through max
        if not np.isfinite(top):  # NaN, +inf, or every weight zero
            normalize_log_weights(lw)  # raises the matching error
        e = np.exp(lw - top)
        lse = top + float(np.log(e.sum()))
        lw -= lse
        self._lw = lw
        return lse

    # ------------------------------------------------------------- resampling
    def resample(self, method: str | None = None) -> np.ndarray:
        """Resample now (equal weights afterwards), then roughen if enabled; returns the indices."""
        method = method or self.resampling
        if method not in RESAMPLERS:
            raise ValidationError(f"resampling must be one of {sorted(RESAMPLERS)}, got {method!r}")
        idx = RESAMPLERS[method](np.exp(self._lw), self.rng)
        self._x = np.take(self._x, idx, axis=0)  # much faster than fancy row indexing
        self._lw = np.full(self.n, -np.log(self.n))
        self.n_resamples += 1
        return idx

    def resample_if_needed(self, accept: Callable[[Array, Array], np.ndarray] | None = None) -> bool:
        """Resample (and roughen, see :meth:`roughen`) when ``ESS < ess_threshold * N``."""
        if self.ess < self.ess_threshold * self.n:
            self.resample()
            if self.roughening > 0:
                self.roughen(accept=accept)
            return True
        return False

    def roughen(self, K: float | None = None, accept: Callable[[Array, Array], np.ndarray] | None = None,
                dims: ArrayLike | None = None) -> Array:
        """Jitter the particles with std ``K * range_j * N^(-1/d)`` (Gordon et al. 1993).

        ``accept(old, new) -> (N,) bool`` may veto individual jitters (those
        particles keep their state, weights are unchanged). ``dims`` restricts the
        jitter to some components (``d`` in the formula is then ``len(dims)``); default
        :attr:`roughening_dims`.
        Returns the standard deviations used.
        """
        K = self.roughening if K is None else float(K)
        dims = self.roughening_dims if dims is None else dims
        cols = np.arange(self.dim) if dims is None else np.asarray(dims, dtype=int)
        sub = self._x[:, cols]
        std = roughening_std(sub, K)
        new = self._x.copy()
        new[:, cols] = sub + self.rng.standard_normal(sub.shape) * std
        if accept is not None:
            ok = np.asarray(accept(self._x, new), dtype=bool)
            new = np.where(ok[:, None], new, self._x)
        self._x = new
        return std

    # ---------------------------------------------------------------- summary
    def gaussian_summary(self, dims: ArrayLike | None = None) -> tuple[Array, Array]:
        """Weighted mean and covariance of the particles (of components ``dims`` if given)."""
        x = self._x if dims is None else self._x[:, np.asarray(dims, dtype=int)]
        return weighted_mean_cov(x, np.exp(self._lw))


def gaussian_summary(poses: ArrayLike, weights: ArrayLike | None = None) -> tuple[Array, Array]:
    """Weighted mean (circular mean for theta) and covariance of poses ``(N, 3)``.

    ``theta`` residuals are wrapped around the circular mean
    ``atan2(sum w sin theta, sum w cos theta)``; the covariance is the weighted second
    moment ``sum w_i r_i r_i^T`` (weights normalized to sum 1, no small-sample correction).
    """
    p = np.asarray(poses, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
        raise ShapeError(f"poses must have shape (N, 3), N >= 1, got {p.shape}")
    if weights is None:
        w = np.full(p.shape[0], 1.0 / p.shape[0])
    else:
        w = np.asarray(weights, dtype=float).reshape(-1)
        if w.shape[0] != p.shape[0]:
            raise ShapeError("weights must have one entry per pose")
        w = w / w.sum()
    mean = np.empty(3)
    mean[:2] = w @ p[:, :2]
    mean[2] = math.atan2(float(w @ np.sin(p[:, 2])), float(w @ np.cos(p[:, 2])))
    r = p - mean
    r[:, 2] = wrap_angle(r[:, 2])
    cov = (r * w[:, None]).T @ r
    return mean, 0.5 * (cov + cov.T)
