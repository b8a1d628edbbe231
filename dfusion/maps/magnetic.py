r"""Magnetic-field map of a floor: a kernel-smoothed grid with a per-cell mean and variance.

Training samples ``(p_k, f_k)`` (position [m], field features such as ``B_z, B_h, |B|`` [uT], each
with weight ``v_k``) are accumulated into a grid of cell size ``h``: per cell ``c`` the weight
``N_c = sum v_k``, the sums ``S_c = sum v_k f_k`` and ``Q_c = sum v_k f_k^2`` (``k`` in cell
``c``). The three grids are smoothed by the separable Gaussian kernel
``g(i, j) = k(i) k(j)``, ``k(i) = exp(-(i h)^2 / (2 sigma^2)) / sum_l exp(-(l h)^2 / (2 sigma^2))``
over ``|i| <= ceil(3 sigma / h)`` (Nadaraya-Watson regression on the grid), and shrunk to the
floor's global mean ``mu_g`` and variance ``s_g^2`` with ``n0`` pseudo-samples::

    mean_c = (g*S + n0 mu_g)_c / (g*N + n0)_c
    var_c  = (g*Q + n0 (s_g^2 + mu_g^2))_c / (g*N + n0)_c - mean_c^2

so a cell far from any training sample has the global mean and variance (an uninformative
likelihood), and a well-covered cell the local mean and the spread of the samples around it
(the field's variation within the kernel, phone-to-phone differences and the training positions'
errors). ``support`` marks the cells with ``g*N >= min_weight``: where people walked.

Look-ups (:meth:`MagneticMap.lookup`) interpolate the mean and variance bilinearly between cell
centres; outside the grid the nearest edge cell's values are used.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import ShapeError, ValidationError
from dfusion.linalg import Array

__all__ = ["MagneticMap", "gaussian_kernel_1d", "smooth_grid", "bilinear"]


def gaussian_kernel_1d(sigma_cells: float) -> Array:
    """Sampled, normalized Gaussian kernel of std ``sigma_cells`` cells, half-width ``ceil(3 sigma)``."""
    r = max(1, int(np.ceil(3.0 * sigma_cells)))
    i = np.arange(-r, r + 1, dtype=float)
    k = np.exp(-0.5 * (i / sigma_cells) ** 2)
    return k / k.sum()


def smooth_grid(grid: Array, sigma_cells: float) -> Array:
    """Separable convolution of ``grid`` ``(nx, ny, ...)`` with :func:`gaussian_kernel_1d` on both axes
    (zero outside the grid)."""
    k = gaussian_kernel_1d(sigma_cells)
    r = (k.size - 1) // 2
    g = np.asarray(grid, dtype=float)
    out = np.zeros_like(g)
    pad = np.pad(g, [(r, r), (0, 0)] + [(0, 0)] * (g.ndim - 2))
    for i, w in enumerate(k):
        out += w * pad[i:i + g.shape[0]]
    pad = np.pad(out, [(0, 0), (r, r)] + [(0, 0)] * (g.ndim - 2))
    out2 = np.zeros_like(g)
    for j, w in enumerate(k):
        out2 += w * pad[:, j:j + g.shape[1]]
    return out2


def bilinear(values: Array, origin: Array, cell: float, points: Array) -> Array:
    """Bilinear interpolation of ``values`` ``(nx, ny, m)`` given at cell centres
    ``origin + (i + 1/2, j + 1/2) h`` at ``points`` ``(N, 2)``; clamped to the edge cells outside."""
    nx, ny = values.shape[:2]
    u = (points[:, 0] - origin[0]) / cell - 0.5
    v = (points[:, 1] - origin[1]) / cell - 0.5
    u = np.clip(u, 0.0, nx - 1.0)
    v = np.clip(v, 0.0, ny - 1.0)
    i0 = np.minimum(np.floor(u).astype(np.int64), max(nx - 2, 0))
    j0 = np.minimum(np.floor(v).astype(np.int64), max(ny - 2, 0))
    i1 = np.minimum(i0 + 1, nx - 1)
    j1 = np.minimum(j0 + 1, ny - 1)
    a = (u - i0)[:, None]
    b = (v - j0)[:, None]
    return ((1 - a) * (1 - b) * values[i0, j0] + a * (1 - b) * values[i1, j0]
            + (1 - a) * b * values[i0, j1] + a * b * values[i1, j1])


@dataclass
class MagneticMap:
    """A smoothed magnetic grid (module docstring). ``mean``, ``var``: ``(nx, ny, m)``; ``weight``:
    ``(nx, ny)`` smoothed sample weight; ``origin`` the grid's lower-left corner [m]; ``cell`` [m]."""

    origin: Array
    cell: float
    mean: Array
    var: Array
    weight: Array
    min_weight: float

    @classmethod
    def build(cls, positions: ArrayLike, features: ArrayLike, *, bounds: ArrayLike, cell: float = 1.0,
              sigma: float = 1.0, n0: float = 2.0, sample_weight: float | ArrayLike = 1.0,
              min_weight: float = 0.5) -> "MagneticMap":
        """Build the map from training samples (module docstring). ``bounds`` = ``(x0, y0, x1, y1)``."""
        p = np.asarray(positions, dtype=float)
        f = np.asarray(features, dtype=float)
        if f.ndim == 1:
            f = f[:, None]
        if p.ndim != 2 or p.shape[1] != 2 or f.shape[0] != p.shape[0]:
            raise ShapeError(f"positions (N, 2) and features (N, m) must match, got {p.shape} and {f.shape}")
        if not (cell > 0 and sigma > 0 and n0 > 0):
            raise ValidationError("cell, sigma and n0 must be positive")
        ok = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(f), axis=1)
        p, f = p[ok], f[ok]
        if p.shape[0] == 0:
            raise ValidationError("no finite training samples")
        x0, y0, x1, y1 = (float(b) for b in bounds)
        nx, ny = int(np.ceil((x1 - x0) / cell)) + 1, int(np.ceil((y1 - y0) / cell)) + 1
        v = np.broadcast_to(np.asarray(sample_weight, dtype=float), (p.shape[0],))[ok[: p.shape[0]]] \
            if np.ndim(sample_weight) else np.full(p.shape[0], float(sample_weight))
        i = np.clip(((p[:, 0] - x0) / cell).astype(np.int64), 0, nx - 1)
        j = np.clip(((p[:, 1] - y0) / cell).astype(np.int64), 0, ny - 1)
        m = f.shape[1]
        N = np.zeros((nx, ny))
        S = np.zeros((nx, ny, m))
        Q = np.zeros((nx, ny, m))
        np.add.at(N, (i, j), v)
        np.add.at(S, (i, j), v[:, None] * f)
        np.add.at(Q, (i, j), v[:, None] * f * f)
        sc = sigma / cell
        N, S, Q = smooth_grid(N, sc), smooth_grid(S, sc), smooth_grid(Q, sc)
        mu = np.average(f, axis=0, weights=v)
        s2 = np.average((f - mu) ** 2, axis=0, weights=v)
        den = (N + n0)[..., None]
        mean = (S + n0 * mu) / den
        var = np.maximum((Q + n0 * (s2 + mu * mu)) / den - mean ** 2, 1e-6)
        return cls(np.array([x0, y0]), float(cell), mean, var, N, float(min_weight))

    @property
    def support(self) -> Array:
        """``(nx, ny)`` bool: cells with smoothed weight ``>= min_weight``."""
        return self.weight >= self.min_weight

    def lookup(self, points: ArrayLike) -> tuple[Array, Array]:
        """Bilinearly interpolated ``(mean, var)``, each ``(N, m)``, at ``points`` ``(N, 2)``."""
        q = np.asarray(points, dtype=float)
        if q.ndim != 2 or q.shape[1] < 2:
            raise ShapeError(f"points must have shape (N, 2), got {q.shape}")
        both = bilinear(np.concatenate([self.mean, self.var], axis=2), self.origin, self.cell, q[:, :2])
        m = self.mean.shape[2]
        return both[:, :m], both[:, m:]

    def on_support(self, points: ArrayLike) -> Array:
        """``(N,)`` bool: the point's cell is in :attr:`support` (False outside the grid)."""
        q = np.asarray(points, dtype=float)
        i = np.floor((q[:, 0] - self.origin[0]) / self.cell).astype(np.int64)
        j = np.floor((q[:, 1] - self.origin[1]) / self.cell).astype(np.int64)
        nx, ny = self.weight.shape
        ok = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
        out = np.zeros(q.shape[0], dtype=bool)
        out[ok] = self.support[i[ok], j[ok]]
        return out

    def sample_support(self, n: int, rng: np.random.Generator) -> Array:
        """``n`` positions uniform over the support cells."""
        cells = np.argwhere(self.support)
        if cells.shape[0] == 0:
            raise ValidationError("the map has no support cell")
        k = rng.integers(0, cells.shape[0], n)
        return self.origin + (cells[k] + rng.random((n, 2))) * self.cell
