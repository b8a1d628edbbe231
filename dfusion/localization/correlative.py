r"""Correlative scan matching against an occupancy grid (Olson, ICRA 2009).

E. Olson, "Real-time correlative scan matching", ICRA 2009: instead of descending from
one start (ICP, which stops in the nearest local minimum), evaluate the scan's
log-likelihood at *every* pose of a lattice over a search window and keep the whole score
surface. The score of a pose ``x = (x, y, theta)`` is the likelihood-field log-likelihood
of the scan's end points (Thrun et al. 2005, table 6.3)::

    s(x) = sum_k log( z_hit N(d(R(theta) p_k + t); 0, sigma_hit^2) + z_rand / z_max )

with ``d`` the distance of an end point to the nearest obstacle surface
(:meth:`~dfusion.maps.OccupancyGrid.surface_distance_field`), looked up in a table built
once (:meth:`~dfusion.models.LikelihoodFieldModel.point_log_likelihood`). The lattice: the
grid's cells in translation (step ``r``, the cell size) and headings ``theta_c + j
delta`` with ``delta = r / max_k |p_k|`` by default, so that the farthest end point moves
by at most one cell between neighbouring headings (Olson, sec. III). Vectorized: each
heading rotates the points once; translations by whole cells are index shifts into the
table, so one heading costs one gather of ``K x (2 n_x + 1)(2 n_y + 1)`` table values.

**Covariance** (Olson, sec. IV, eq. 15-17). Each lattice pose ``x_i`` has the
(unnormalized) likelihood ``p_i = exp(s_i - max s)``; with ``P = sum p_i``::

    u = sum p_i x_i / P,        K = sum p_i x_i x_i^T / P - u u^T

plus the variance of a uniform spread within one lattice cell (``r^2 / 12``,
``delta^2 / 12``). Unlike a curvature at the optimum it stays honest where the score
surface is flat or has several peaks: along a featureless corridor it is as large as the
window allows (for an exactly flat score over ``n`` cells: ``(n r)^2 / 12``, the variance
of a uniform distribution over the window). :meth:`CorrelativeResult.covariance_about`
gives the second moment about another pose (e.g. an ICP refinement of the optimum): ``K +
(u - x)(u - x)^T``, which also counts how far that pose is from the score's mass.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import solve_triangular
from scipy.stats import chi2

from dfusion.errors import ShapeError, ValidationError
from dfusion.geometry import wrap_angle
from dfusion.linalg import Array, as_vector, cholesky, spd_inverse
from dfusion.maps import OccupancyGrid
from dfusion.models import LikelihoodFieldModel

__all__ = ["CorrelativeResult", "CorrelativeScanMatcher", "enclosing_covariance"]


@dataclass(frozen=True)
class CorrelativeResult:
    """Outcome of :meth:`CorrelativeScanMatcher.match` (world frame).

    Attributes
    ----------
    pose : (3,) array
        The lattice pose with the highest score (with a prior: the highest posterior).
    score : float
        The highest log-likelihood of the lattice (sum over the points used).
    mean, covariance : (3,) and (3, 3) arrays
        Mean and covariance of the normalized likelihood over the lattice (module
        docstring), the covariance including the within-cell spread.
    n_points, n_candidates : int
        Scan points scored and lattice poses evaluated.
    half_width : (3,) array
        The search window actually used (m, m, rad; grid frame), ``step``: ``(r, r, delta)``.
    """

    pose: Array
    score: float
    mean: Array
    covariance: Array
    n_points: int
    n_candidates: int
    half_width: Array
    step: Array

    def covariance_about(self, pose: ArrayLike) -> Array:
        """Second moment of the likelihood about ``pose``: ``K + (u - x)(u - x)^T`` (heading wrapped)."""
        d = self.mean - as_vector(pose, 3, "pose")
        d[2] = wrap_angle(d[2])
        c = self.covariance + np.outer(d, d)
        return 0.5 * (c + c.T)


def enclosing_covariance(A: ArrayLike, B: ArrayLike) -> Array:
    r"""The smallest covariance (in the ordering of its ellipsoids) that is at least ``A`` and ``B``.

    With ``A = L L^T`` (Cholesky) and ``L^-1 B L^-T = V diag(lambda) V^T``:
    ``C = L V diag(max(1, lambda)) V^T L^T``. ``C - A`` and ``C - B`` are positive
    semi-definite, and ``C`` equals ``A`` (``B``) when ``A >= B`` (``B >= A``): in every
    direction the larger of the two variances, measured in the metric of ``A``
    (simultaneous diagonalization; e.g. Kalman-filter covariance union, Uhlmann 2003,
    "Covariance consistency methods for fault-tolerant distributed data fusion").
    """
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    if A.shape != B.shape or A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ShapeError("A and B must be square matrices of one shape")
    L = cholesky(0.5 * (A + A.T), "A")
    Li_B = solve_triangular(L, 0.5 * (B + B.T), lower=True)
    M = solve_triangular(L, Li_B.T, lower=True)  # L^-1 B L^-T (symmetric)
    lam, V = np.linalg.eigh(0.5 * (M + M.T))
    LV = L @ V
    C = (LV * np.maximum(lam, 1.0)) @ LV.T
    return 0.5 * (C + C.T)


class CorrelativeScanMatcher:
    """Exhaustive search of a scan's pose over a window, scored by a likelihood field.

    Parameters
    ----------
    grid : OccupancyGrid
        The map; translations are searched in steps of its cell size.
    sigma_hit, z_hit, z_rand, max_distance :
        The likelihood field (:class:`~dfusion.models.LikelihoodFieldModel`); end points
        off the map score as ``max_distance`` from every surface.
    max_range : float
        ``z_max`` of the random term (m).
    max_points : int or None
        Score at most this many scan points, evenly spread in beam order (``None``: all).
    angular_step : float or None
        Heading step (rad); default ``r / max_k |p_k|`` per scan (the farthest point moves
        by at most one cell), at least ``min_angular_step``.
    min_angular_step : float
        Lower bound of the default heading step (rad).
    max_candidates : int
        Refuse windows with more lattice poses than this (``ValidationError``).
    """

    def __init__(
        self,
        grid: OccupancyGrid,
        *,
        sigma_hit: float = 0.1,
        z_hit: float = 0.95,
        z_rand: float = 0.05,
        max_distance: float = 1.0,
        max_range: float = 30.0,
        max_points: int | None = None,
        angular_step: float | None = None,
        min_angular_step: float = 0.002,
        max_candidates: int = 2_000_000,
    ) -> None:
        if not isinstance(grid, OccupancyGrid):
            raise ValidationError("grid must be an OccupancyGrid")
        if not max_range > 0:
            raise ValidationError("max_range must be positive")
        if max_points is not None and max_points < 3:
            raise ValidationError("max_points must be at least 3")
        if angular_step is not None and not angular_step > 0:
            raise ValidationError("angular_step must be positive")
        if not min_angular_step > 0:
            raise ValidationError("min_angular_step must be positive")
        self.grid = grid
        self.resolution = float(grid.resolution)
        self.field = LikelihoodFieldModel(sigma_hit, z_hit, z_rand, max_distance=max_distance)
        self.max_range = float(max_range)
        self.max_points = None if max_points is None else int(max_points)
        self.angular_step = None if angular_step is None else float(angular_step)
        self.min_angular_step = float(min_angular_step)
        self.max_candidates = int(max_candidates)
        self.table = self.field.point_log_likelihood(grid.surface_distance_field(), self.max_range).astype(np.float32)
        self.off_map = float(self.field.point_log_likelihood(max_distance, self.max_range))

    # -- windows --------------------------------------------------------------------------
    def window(self, cov: ArrayLike, probability: float = 0.99, cap: ArrayLike = (1.0, 1.0, 0.3),
               floor: ArrayLike | None = None) -> Array:
        r"""Half-widths ``(w_x, w_y, w_theta)`` (grid frame) of the box around the
        ``probability`` region of a Gaussian with covariance ``cov`` (world frame):
        ``w_a = sqrt(chi2.ppf(probability, 3) Sigma_aa)``, at most ``cap`` and at least
        ``floor`` (default: two cells, two heading steps of 1 mrad)."""
        P = np.asarray(cov, dtype=float)
        if P.shape != (3, 3):
            raise ShapeError("cov must be 3 x 3")
        if not 0.0 < probability < 1.0:
            raise ValidationError("probability must be in (0, 1)")
        c, s = math.cos(self.grid.origin[2]), math.sin(self.grid.origin[2])
        Rg = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> grid axes
        d = np.maximum(np.diag(Rg @ P @ Rg.T), 0.0)
        w = np.sqrt(float(chi2.ppf(probability, 3)) * d)
        lo = np.array([2 * self.resolution, 2 * self.resolution, 0.002]) if floor is None else as_vector(floor, 3, "floor")
        return np.clip(w, lo, as_vector(cap, 3, "cap"))

    # -- matching -------------------------------------------------------------------------
    def _select(self, points: Array) -> Array:
        if self.max_points is None or points.shape[0] <= self.max_points:
            return points
        idx = np.round(np.linspace(0, points.shape[0] - 1, self.max_points)).astype(np.int64)
        return points[idx]

    def heading_step(self, points: ArrayLike) -> float:
        """The heading step for these points (class docstring)."""
        if self.angular_step is not None:
            return self.angular_step
        p = np.asarray(points, dtype=float)
        far = float(np.max(np.hypot(p[:, 0], p[:, 1]))) if p.size else 0.0
        return max(self.resolution / far, self.min_angular_step) if far > 0 else self.min_angular_step

    def scores(self, points: ArrayLike, center: ArrayLike, half_width: ArrayLike) -> tuple[Array, Array, Array]:
        """Score of every lattice pose: ``(S, (offsets_x, offsets_y, offsets_theta))``.

        ``S[h, i, j]`` is the log-likelihood of the points (laser frame, ``(K, 2)``; all of
        them, no selection) at the grid-frame pose ``center + (ox[j], oy[i], oth[h])``;
        ``center`` is a world pose, offsets along the grid axes. Also returns the center in
        the grid frame.
        """
        p = np.asarray(points, dtype=float)
        if p.ndim != 2 or p.shape[1] != 2:
            raise ShapeError(f"points must be (K, 2), got {p.shape}")
        if p.shape[0] < 3:
            raise ValidationError("correlative matching needs at least 3 scan points")
        w = as_vector(half_width, 3, "half_width")
        if np.any(w < 0) or not np.all(np.isfinite(w)):
            raise ValidationError("half_width must be finite and non-negative")
        r = self.resolution
        step = self.heading_step(p)
        nx, ny, nh = round(float(w[0]) / r), round(float(w[1]) / r), math.ceil(float(w[2]) / step - 1e-9)
        n_cand = (2 * nx + 1) * (2 * ny + 1) * (2 * nh + 1)
        if n_cand > self.max_candidates:
            raise ValidationError(f"search window of {n_cand} poses exceeds max_candidates={self.max_candidates}")
        cg = self.grid.pose_to_grid(as_vector(center, 3, "center"))
        oth = step * np.arange(-nh, nh + 1)
        ox = r * np.arange(-nx, nx + 1)
        oy = r * np.arange(-ny, ny + 1)
        th = cg[2] + oth
        cth, sth = np.cos(th)[:, None], np.sin(th)[:, None]
        ex = (cth * p[:, 0] - sth * p[:, 1] + cg[0]) / r  # (Nh, K) in cells
        ey = (sth * p[:, 0] + cth * p[:, 1] + cg[1]) / r
        bj = np.floor(ex).astype(np.int64)
        bi = np.floor(ey).astype(np.int64)
        # a crop of the table covering every end point of every candidate, off-map cells
        # at the off-map score
        i0, i1 = int(bi.min()) - ny, int(bi.max()) + ny + 1
        j0, j1 = int(bj.min()) - nx, int(bj.max()) + nx + 1
        H, W = self.table.shape
        crop = np.full((i1 - i0, j1 - j0), self.off_map, dtype=np.float32)
        a0, a1, b0, b1 = max(i0, 0), min(i1, H), max(j0, 0), min(j1, W)
        if a0 < a1 and b0 < b1:
            crop[a0 - i0:a1 - i0, b0 - j0:b1 - j0] = self.table[a0:a1, b0:b1]
        flat = crop.reshape(-1)
        Wc = crop.shape[1]
        base = (bi - i0) * Wc + (bj - j0)  # (Nh, K)
        shifts = (np.arange(-ny, ny + 1)[:, None] * Wc + np.arange(-nx, nx + 1)[None, :]).reshape(-1)
        S = np.empty((oth.size, shifts.size))
        chunk = max(1, int(4_000_000 // max(p.shape[0] * shifts.size, 1)))
        for h0 in range(0, oth.size, chunk):
            b = base[h0:h0 + chunk]
            S[h0:h0 + chunk] = flat.take(b[:, :, None] + shifts[None, None, :]).sum(axis=1, dtype=np.float64)
        return S.reshape(oth.size, oy.size, ox.size), (ox, oy, oth), cg

    def match(self, points: ArrayLike, center: ArrayLike, half_width: ArrayLike,
              prior_cov: ArrayLike | None = None, prior_gate: float | None = None) -> CorrelativeResult:
        """Best lattice pose of the scan points (laser frame) within ``center +- half_width``
        (world pose; m, m, rad along the grid axes), with the score surface's mean and
        covariance (module docstring).

        ``prior_cov`` (world frame, ``3 x 3``): a Gaussian prior ``N(center, prior_cov)``
        (e.g. the prediction of a filter); ``pose`` is then the lattice pose of highest
        posterior, ``s_i - (x_i - c)^T prior_cov^-1 (x_i - c) / 2`` (Olson 2009, sec. III:
        the prior and the scan likelihood combined), while ``mean``, ``covariance`` and
        ``score`` stay those of the scan likelihood alone (a measurement to fuse with that
        prior must not contain it). ``prior_gate``: only lattice poses with ``(x_i - c)^T
        prior_cov^-1 (x_i - c) <= prior_gate`` can be ``pose`` (e.g. ``chi2.ppf(0.99, 3)``:
        the prior's 99 % ellipsoid rather than its bounding box).
        """
        p = self._select(np.asarray(points, dtype=float))
        S, (ox, oy, oth), cg = self.scores(p, center, half_width)
        if prior_cov is None:
            k = int(np.argmax(S))
        else:
            P = np.asarray(prior_cov, dtype=float)
            if P.shape != (3, 3):
                raise ShapeError("prior_cov must be 3 x 3")
            c0, s0 = math.cos(self.grid.origin[2]), math.sin(self.grid.origin[2])
            Rg = np.array([[c0, s0, 0.0], [-s0, c0, 0.0], [0.0, 0.0, 1.0]])  # world -> grid axes
            A = spd_inverse(0.5 * (Rg @ P @ Rg.T + (Rg @ P @ Rg.T).T), "prior_cov")
            X, Y, T = ox[None, None, :], oy[None, :, None], oth[:, None, None]
            quad = (A[0, 0] * X * X + A[1, 1] * Y * Y + A[2, 2] * T * T
                    + 2.0 * (A[0, 1] * X * Y + A[0, 2] * X * T + A[1, 2] * Y * T))
            post = S - 0.5 * quad
            if prior_gate is not None:
                post = np.where(quad <= float(prior_gate), post, -np.inf)
            k = int(np.argmax(post))
        h, i, j = np.unravel_index(k, S.shape)
        k_max = int(np.argmax(S))
        wts = np.exp(S - S.flat[k_max])
        tot = float(wts.sum())
        wh = wts.sum(axis=(1, 2)) / tot
        wy = wts.sum(axis=(0, 2)) / tot
        wx = wts.sum(axis=(0, 1)) / tot
        m = np.array([wx @ ox, wy @ oy, wh @ oth])
        # second moments of the offsets (grid axes)
        C = np.empty((3, 3))
        C[0, 0] = wx @ ox**2 - m[0] ** 2
        C[1, 1] = wy @ oy**2 - m[1] ** 2
        C[2, 2] = wh @ oth**2 - m[2] ** 2
        wxy = wts.sum(axis=0) / tot  # (Ny, Nx)
        C[0, 1] = C[1, 0] = float(oy @ wxy @ ox) - m[0] * m[1]
        wxh = wts.sum(axis=1) / tot  # (Nh, Nx)
        C[0, 2] = C[2, 0] = float(oth @ wxh @ ox) - m[0] * m[2]
        wyh = wts.sum(axis=2) / tot  # (Nh, Ny)
        C[1, 2] = C[2, 1] = float(oth @ wyh @ oy) - m[1] * m[2]
        step = np.array([self.resolution, self.resolution, oth[1] - oth[0] if oth.size > 1 else self.heading_step(p)])
        C += np.diag(step**2 / 12.0)
        # grid frame -> world frame
        g = self.grid.origin
        c, s = math.cos(g[2]), math.sin(g[2])
        Rw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        best_g = cg + np.array([ox[j], oy[i], oth[h]])
        mean_g = cg + m

        def to_world(x: Array) -> Array:
            xy = self.grid.grid_to_world(x[:2])
            return np.array([xy[0], xy[1], float(wrap_angle(x[2] + g[2]))])

        cov = Rw @ C @ Rw.T
        w = as_vector(half_width, 3, "half_width")
        return CorrelativeResult(to_world(best_g), float(S.flat[k_max]), to_world(mean_g), 0.5 * (cov + cov.T),
                                 int(p.shape[0]), int(S.size), np.array([ox[-1], oy[-1], oth[-1]]) if w.size else w,
                                 step)

    def score(self, points: ArrayLike, pose: ArrayLike) -> float:
        """Log-likelihood of the (selected) scan points at one world pose."""
        p = self._select(np.asarray(points, dtype=float))
        S, _, _ = self.scores(p, pose, (0.0, 0.0, 0.0))
        return float(S[0, 0, 0])
