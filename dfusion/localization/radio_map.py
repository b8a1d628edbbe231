r"""Radio map: a per-receiver RSSI mean and spread that vary over the floor, looked up bilinearly.

The log-distance model (:class:`dfusion.models.RSSISensor`) predicts the same RSSI on
every circle around a receiver; walls, furniture and the body make the real mean
depart from it by several dB, smoothly over the floor (spatially correlated
shadowing). A *radio map* learns that departure from packets with known tag
positions (fingerprinting; Bahl & Padmanabhan, "RADAR", INFOCOM 2000; Daniş et
al. build one for the BLE RSSI dataset):

    z_j = mu_j(p) + m_j(p) + s_j(p) u,     u ~ N(0, 1)  (or the split normal below)

with ``mu_j`` the log-distance mean of receiver ``j`` and ``m_j`` a kernel
(Nadaraya-Watson) regression of the training residuals ``r_i = z_i - mu_j(x_i)``
over the floor, shrunk towards 0 where there is little data:

    m_j(p)   = sum_i K(p - x_i) r_i / (sum_i K(p - x_i) + w0)
    s_j(p)^2 = (sum_i K(p - x_i) (r_i - m_j(p))^2 + w0 (s0_j^2 + m_j(p)^2)) / (sum_i K(p - x_i) + w0)

``K(u) = c^2 / (2 pi b^2) exp(-|u|^2 / (2 b^2))`` (bandwidth ``b``, ``c`` the map's
cell, so that ``sum K`` counts training points per cell), ``w0`` a prior weight of
pseudo-points at residual 0 with the global spread ``s0_j`` (the log-distance fit's
residual standard deviation). Far from the training data ``m_j -> 0`` and
``s_j -> s0_j``: the model falls back to plain path loss. It is the posterior
mean and spread of a local Gaussian with a conjugate-style prior of weight ``w0``.

:func:`fit_radio_map` bins the residuals on the map's nodes (nearest node) and
convolves the binned sums with a sampled Gaussian (:func:`scipy.ndimage.gaussian_filter`,
zero outside the map), which equals the formula above up to the binning (at most
half a cell per point); :func:`kernel_residual_map` evaluates the formula directly
(the reference of the tests). The stored grids are the full mean ``mu_j + m_j`` and
the spread ``s_j``; a particle filter needs one bilinear look-up per reading
(:meth:`RadioMap.log_likelihood`: of the Gaussian log-likelihood's coefficients, or,
for the split normal, of the readings' summed log-density evaluated at the nodes
around the particles).

**Directional path loss.** The base mean ``mu_j`` may carry a gain that depends on the
azimuth ``phi`` of the tag seen from the receiver (antenna pattern, a receiver mounted
against a wall or inside furniture), a truncated Fourier series of order ``K``:

    mu_j(p) = p0_j - 10 n_j log10(d_j / d0) + sum_{k=1..K} (a_jk cos k phi + b_jk sin k phi)

fitted by least squares with a ridge penalty ``lambda sum_k (a_jk^2 + b_jk^2)`` on the
harmonics only (:func:`fit_directional_path_loss`; ``K = 0`` is the plain log-distance fit).
Unlike the kernel map, which falls back to ``mu_j`` beyond about two bandwidths from the
training paths, the harmonics extrapolate along rays from the receiver into unvisited aisles.

**Noise shape.** The standardized residual ``u = (z - M_j(p)) / S_j(p)`` is skewed to the
left (deep fades from bodies and furniture are more common than readings far above the
mean). A map may therefore carry a split-normal (two-piece normal) noise law
(:func:`split_normal_logpdf`, fitted by :func:`fit_split_normal`)

    f(u) = sqrt(2 / pi) / (sl + sr) exp(-(u - m)^2 / (2 sl^2))   for u < m
         = sqrt(2 / pi) / (sl + sr) exp(-(u - m)^2 / (2 sr^2))   for u >= m

and the density of a reading is ``f(u) / S_j(p)``; without it the reading is Gaussian,
``N(z; M_j(p), S_j(p)^2)``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import ShapeError, ValidationError
from dfusion.linalg import Array

__all__ = ["RadioMap", "fit_radio_map", "fit_radio_maps", "kernel_residual_map", "binned_residual_stats",
           "split_normal_logpdf", "fit_split_normal", "path_loss_design", "fit_directional_path_loss"]

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)


def split_normal_logpdf(u: ArrayLike, mode: float, sigma_left: float, sigma_right: float) -> Array:
    """Log-density of the split-normal (two-piece normal) law of the module docstring.

    ``log f(u) = log(sqrt(2/pi) / (sl + sr)) - (u - m)^2 / (2 s^2)`` with ``s = sl`` below the
    mode ``m`` and ``s = sr`` above it. Its mean is ``m + sqrt(2/pi) (sr - sl)``.
    """
    u = np.asarray(u, dtype=float)
    if not (sigma_left > 0 and sigma_right > 0):
        raise ValidationError("split-normal standard deviations must be positive")
    v = u - mode
    prec = np.where(v < 0, 1.0 / sigma_left ** 2, 1.0 / sigma_right ** 2)
    return np.log(2.0 / (sigma_left + sigma_right)) - _LOG_SQRT_2PI - 0.5 * v * v * prec


def fit_split_normal(u: ArrayLike) -> tuple[float, float, float]:
    """Maximum-likelihood split-normal ``(mode, sigma_left, sigma_right)`` of the samples ``u``.

    For a fixed mode ``m`` with ``A = sum_{u < m} (u - m)^2`` and ``B = sum_{u >= m} (u - m)^2``
    the likelihood is maximal at ``sl = A^(1/3) k``, ``sr = B^(1/3) k``,
    ``k = sqrt((A^(1/3) + B^(1/3)) / n)``, and the profile log-likelihood is
    ``-3/2 n log(A^(1/3) + B^(1/3)) + const`` (John, "The three-parameter two-piece normal
    family of distributions", Commun. Statist. A 11, 1982): the mode minimizes
    ``A^(1/3) + B^(1/3)``. It is searched over 257 quantiles of the sample, then refined by a
    bounded scalar minimization between the neighbours of the best one.
    """
    x = np.sort(np.asarray(u, dtype=float).reshape(-1))
    n = x.size
    if n < 3 or not np.all(np.isfinite(x)) or np.ptp(x) <= 0:
        raise ValidationError("fit_split_normal needs at least 3 finite, not all equal samples")
    c1 = np.concatenate([[0.0], np.cumsum(x)])
    c2 = np.concatenate([[0.0], np.cumsum(x * x)])

    def ab(m: float | Array) -> tuple[Array, Array]:
        i = np.searchsorted(x, m, side="left")  # samples below m: x[:i]
        a = c2[i] - 2.0 * m * c1[i] + m * m * i
        b = (c2[n] - c2[i]) - 2.0 * m * (c1[n] - c1[i]) + m * m * (n - i)
        return np.maximum(a, 0.0), np.maximum(b, 0.0)

    def crit(m: float | Array) -> Array:
        a, b = ab(m)
        return np.cbrt(a) + np.cbrt(b)

    cand = np.quantile(x, np.linspace(0.0, 1.0, 257))
    k = int(np.argmin(crit(cand)))
    lo, hi = cand[max(k - 1, 0)], cand[min(k + 1, cand.size - 1)]
    m = float(cand[k])
    if hi > lo:
        from scipy.optimize import minimize_scalar  # here: fitting only, a tracker needs no scipy
        r = minimize_scalar(lambda v: float(crit(v)), bounds=(lo, hi), method="bounded",
                            options=dict(xatol=1e-10 * max(1.0, float(np.ptp(x)))))
        if r.fun <= crit(m):
            m = float(r.x)
    a, b = ab(m)
    scale = np.sqrt((np.cbrt(a) + np.cbrt(b)) / n)
    return m, float(np.cbrt(a) * scale), float(np.cbrt(b) * scale)


def path_loss_design(distance: ArrayLike, azimuth: ArrayLike, order: int = 0, d0: float = 1.0) -> Array:
    """Design matrix ``[1, -10 log10(d / d0), cos phi, sin phi, ..., cos K phi, sin K phi]`` (N x (2 + 2K)).

    The coefficients are ``[p0, n, a_1, b_1, ..., a_K, b_K]`` of the directional path loss of the
    module docstring; ``azimuth`` (rad) is the direction of the tag seen from the receiver.
    """
    d = np.asarray(distance, dtype=float).reshape(-1)
    phi = np.asarray(azimuth, dtype=float).reshape(-1)
    if d.shape != phi.shape:
        raise ShapeError("distance and azimuth must have the same length")
    if int(order) != order or order < 0:
        raise ValidationError(f"order must be a non-negative integer, got {order}")
    cols = [np.ones_like(d), -10.0 * np.log10(np.maximum(d, 1e-9) / d0)]
    for k in range(1, int(order) + 1):
        cols += [np.cos(k * phi), np.sin(k * phi)]
    return np.column_stack(cols)


def fit_directional_path_loss(distance: ArrayLike, azimuth: ArrayLike, rssi: ArrayLike, order: int = 0,
                              ridge: float = 100.0, d0: float = 1.0) -> tuple[float, float, Array, float]:
    """Least-squares directional path loss (module docstring) of one receiver.

    Minimizes ``sum_i (z_i - D_i beta)^2 + ridge * sum_k (a_k^2 + b_k^2)`` over
    ``beta = [p0, n, a_1, b_1, ...]`` (:func:`path_loss_design`; ``p0`` and ``n`` are not
    penalized): ``beta = (D^T D + ridge P)^-1 D^T z`` with ``P`` the identity on the harmonics.
    ``ridge`` is a Gaussian prior on each harmonic coefficient with variance ``sigma^2 / ridge``
    (``sigma`` the shadowing spread). Returns ``(p0, n, harmonics (2K,), std)``, ``std`` the
    residual standard deviation with ``N - 2 - 2K`` degrees of freedom. ``order = 0`` is the
    log-distance fit of :func:`dfusion.models.fit_path_loss`.
    """
    z = np.asarray(rssi, dtype=float).reshape(-1)
    D = path_loss_design(distance, azimuth, order, d0)
    if D.shape[0] != z.size:
        raise ShapeError("distance, azimuth and rssi must have the same length")
    if ridge < 0 or not np.isfinite(ridge):
        raise ValidationError(f"ridge must be >= 0, got {ridge}")
    dof = z.size - D.shape[1]
    if dof < 1:
        raise ValidationError(f"fit_directional_path_loss needs more than {D.shape[1]} samples, got {z.size}")
    P = np.full(D.shape[1], float(ridge))
    P[:2] = 0.0
    beta = np.linalg.solve(D.T @ D + np.diag(P), D.T @ z)
    e = z - D @ beta
    return float(beta[0]), float(beta[1]), beta[2:].copy(), float(np.sqrt(e @ e / dof))


@dataclass
class RadioMap:
    """Per-receiver RSSI mean and standard deviation on a regular grid of nodes.

    Parameters
    ----------
    origin : (2,) float
        World position of node ``(0, 0)`` (m).
    cell : float
        Node spacing (m).
    mean : (m, nx, ny) float
        Mean RSSI of receiver ``j`` for a tag at node ``(ix, iy)`` (dBm), x first.
    std : (m, nx, ny) float
        Standard deviation of the RSSI there (dB), positive.
    tracks : list of str
        Names of the data the map was learnt from (provenance, for leave-one-out checks).
    noise : (mode, sigma_left, sigma_right) or None
        Law of the standardized residual ``u = (z - mean) / std``: a split normal
        (:func:`split_normal_logpdf`), or ``None`` for the standard normal.
    settings : dict
        How the map was made (provenance only, e.g. bandwidth, prior weight, path-loss order).

    Values between nodes are bilinear; positions off the grid take the value of
    the nearest edge.
    """

    origin: Array
    cell: float
    mean: Array
    std: Array
    tracks: list[str] = field(default_factory=list)
    noise: tuple[float, float, float] | None = None
    settings: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, dtype=float).reshape(2)
        self.cell = float(self.cell)
        self.mean = np.asarray(self.mean, dtype=float)
        self.std = np.asarray(self.std, dtype=float)
        if self.mean.ndim != 3 or self.mean.shape != self.std.shape or min(self.mean.shape[1:]) < 2:
            raise ShapeError(f"mean and std must be equal (m, nx >= 2, ny >= 2) arrays, got {self.mean.shape} "
                             f"and {self.std.shape}")
        if not (self.cell > 0 and np.all(np.isfinite(self.mean)) and np.all(self.std > 0)):
            raise ValidationError("radio map needs cell > 0, finite means and positive standard deviations")
        if self.noise is not None:
            m, sl, sr = (float(v) for v in self.noise)
            if not (np.isfinite(m) and sl > 0 and sr > 0 and np.isfinite(sl) and np.isfinite(sr)):
                raise ValidationError(f"noise must be (mode, sigma_left > 0, sigma_right > 0), got {self.noise}")
            self.noise = (m, sl, sr)
        self._coef_cache: dict[float, Array] = {}
        self._inv_log_std: tuple[Array, Array] | None = None

    def _coef(self, std_scale: float = 1.0) -> Array:
        """``(m * nx * ny, 3)`` log-likelihood coefficients per node (see :meth:`log_likelihood`)."""
        c = self._coef_cache.get(std_scale)
        if c is None:
            m, nx, ny = self.mean.shape
            P = 1.0 / (self.std ** 2 * std_scale ** 2)
            c = np.stack([-0.5 * P, self.mean * P, -0.5 * self.mean ** 2 * P - np.log(self.std)], axis=-1)
            c = self._coef_cache[std_scale] = np.ascontiguousarray(c.reshape(m * nx * ny, 3))
        return c

    @property
    def n_receivers(self) -> int:
        return self.mean.shape[0]

    @property
    def shape(self) -> tuple[int, int]:
        """``(nx, ny)`` nodes."""
        return self.mean.shape[1], self.mean.shape[2]

    def node_positions(self) -> tuple[Array, Array]:
        """World x of the node columns and y of the node rows (m)."""
        nx, ny = self.shape
        return self.origin[0] + self.cell * np.arange(nx), self.origin[1] + self.cell * np.arange(ny)

    def _corners(self, xy: Array) -> tuple[np.ndarray, Array, Array]:
        """Flat index of the lower-left node and the bilinear fractions of each position."""
        nx, ny = self.shape
        u = (xy[:, 0] - self.origin[0]) / self.cell
        v = (xy[:, 1] - self.origin[1]) / self.cell
        np.clip(u, 0.0, nx - 1.0, out=u)
        np.clip(v, 0.0, ny - 1.0, out=v)
        i = np.minimum(u.astype(np.int64), nx - 2)
        k = np.minimum(v.astype(np.int64), ny - 2)
        fu = u - i
        fv = v - k
        return i * ny + k, fu, fv

    def lookup(self, xy: ArrayLike, receivers: ArrayLike) -> tuple[Array, Array]:
        """Bilinear mean and standard deviation, ``(N, k)`` each, of receivers ``receivers`` at ``xy`` (N, 2)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        j = np.asarray(receivers, dtype=np.int64).reshape(-1)
        flat, fu, fv = self._corners(xy)
        ny = self.shape[1]
        out = []
        for grid in (self.mean, self.std):
            g = grid.reshape(self.n_receivers, -1)[j]  # (k, nx * ny)
            v00, v01 = g[:, flat], g[:, flat + 1]
            v10, v11 = g[:, flat + ny], g[:, flat + ny + 1]
            val = (v00 * (1 - fv) + v01 * fv) * (1 - fu) + (v10 * (1 - fv) + v11 * fv) * fu
            out.append(val.T)
        return out[0], out[1]

    def log_likelihood(self, z: ArrayLike, receivers: ArrayLike, xy: ArrayLike, std_scale: float = 1.0,
                       outlier_prob: float = 0.0, rssi_span: float = 60.0) -> Array:
        """Log-likelihood of the readings ``z`` (of receivers ``receivers``) per position ``p`` of ``xy``.

        Gaussian map (``noise is None``) without outliers: ``sum_k log N(z_k; M_jk(p), (s S_jk(p))^2)``
        up to a constant, with the coefficients ``-1/(2 S^2)``, ``M / S^2`` and ``-M^2/(2 S^2) - ln S``
        interpolated bilinearly (not ``M`` and ``S`` themselves): between nodes this
        differs from the Gaussian with interpolated ``M``, ``S`` by the interpolation
        error only. ``std_scale = s`` multiplies every standard deviation in the quadratic
        part (tempering; the ``ln S`` normalization is kept).

        Otherwise (a split-normal :attr:`noise`, or ``outlier_prob = eps > 0``): the exact
        log-density of the readings at the nodes, summed over the readings, interpolated
        bilinearly between nodes (:meth:`node_log_density`); with ``eps > 0`` each reading's
        density ``f`` is mixed with a uniform floor first, ``log((1 - eps) f + eps / rssi_span)``
        (``rssi_span`` in dB). Only the nodes of the bounding box of the particles' cells are
        evaluated, so the cost is ``O(box x readings + N)`` instead of ``O(N x readings)``.
        """
        z = np.asarray(z, dtype=float).reshape(-1)
        j = np.asarray(receivers, dtype=np.int64).reshape(-1)
        xy = np.asarray(xy, dtype=float)
        n = xy.shape[0]
        if z.size == 0:
            return np.zeros(n)
        if not 0.0 <= outlier_prob < 1.0:
            raise ValidationError(f"outlier_prob must be in [0, 1), got {outlier_prob}")
        if outlier_prob > 0 and not (np.isfinite(rssi_span) and rssi_span > 0):
            raise ValidationError(f"rssi_span must be positive, got {rssi_span}")
        if self.noise is not None or outlier_prob > 0:
            return self._box_interpolate(xy, z, j, std_scale, outlier_prob, rssi_span, per_reading=False)
        coef = self._coef(float(std_scale))
        flat, fu, fv = self._corners(xy)
        ny = self.shape[1]
        gu = 1.0 - fu
        gv = 1.0 - fv
        zz = np.stack([z * z, z, np.ones_like(z)], axis=1)  # (k, 3)
        base = (j * (self.mean.shape[1] * ny))[None, :]  # (1, k)
        out = np.zeros(n)
        for off, w in ((0, gu * gv), (1, gu * fv), (ny, fu * gv), (ny + 1, fu * fv)):
            c = np.take(coef, (flat + off)[:, None] + base, axis=0)  # (N, k, 3)
            out += w * np.einsum("nkc,kc->n", c, zz)
        return out

    def node_log_density(self, z: ArrayLike, receivers: ArrayLike, std_scale: float = 1.0,
                         index: tuple | None = None) -> Array:
        """Exact log-density of each reading at the nodes, ``(k,) + node shape``.

        ``log f(u) - ln S - ln s`` with ``u = (z - M) / (s S)`` (``s = std_scale``) and ``f`` the
        standard normal or the split normal :attr:`noise`. ``index``: a tuple of slices
        selecting nodes (default: all nodes, ``(k, nx, ny)``).
        """
        z = np.asarray(z, dtype=float).reshape(-1)
        j = np.asarray(receivers, dtype=np.int64).reshape(-1)
        if not (np.isfinite(std_scale) and std_scale > 0):
            raise ValidationError(f"std_scale must be positive, got {std_scale}")
        if self._inv_log_std is None:
            self._inv_log_std = (1.0 / self.std, np.log(self.std))
        sl = (j,) + (index if index is not None else (slice(None), slice(None)))
        inv_s, log_s = (a[sl] for a in self._inv_log_std)
        u = np.subtract(z.reshape((-1,) + (1,) * (inv_s.ndim - 1)), self.mean[sl])
        u *= inv_s
        if std_scale != 1.0:
            u /= std_scale
        if self.noise is None:
            out = np.square(u, out=u)
            out *= -0.5
            out -= _LOG_SQRT_2PI + np.log(std_scale)
        else:
            m, sl_, sr = self.noise
            u -= m
            prec = np.where(u < 0, -0.5 / sl_ ** 2, -0.5 / sr ** 2)
            out = np.square(u, out=u)
            out *= prec
            out += np.log(2.0 / (sl_ + sr)) - _LOG_SQRT_2PI - np.log(std_scale)
        out -= log_s
        return out

    def reading_log_density(self, z: ArrayLike, receivers: ArrayLike, xy: ArrayLike,
                            std_scale: float = 1.0) -> Array:
        """``(N, k)`` log-density of each reading at each position of ``xy``: :meth:`node_log_density`
        interpolated bilinearly (exact at the nodes)."""
        z = np.asarray(z, dtype=float).reshape(-1)
        j = np.asarray(receivers, dtype=np.int64).reshape(-1)
        return self._box_interpolate(np.asarray(xy, dtype=float), z, j, std_scale, 0.0, 1.0, per_reading=True)

    def _box_interpolate(self, xy: Array, z: Array, j: np.ndarray, std_scale: float, outlier_prob: float,
                         rssi_span: float, per_reading: bool) -> Array:
        flat, fu, fv = self._corners(xy)
        ny = self.shape[1]
        ix = flat // ny
        iy = flat - ix * ny
        i0, i1 = int(ix.min()), int(ix.max()) + 1  # lower-left corners and their upper neighbours
        k0, k1 = int(iy.min()), int(iy.max()) + 1
        by = k1 - k0 + 1
        ll = self.node_log_density(z, j, std_scale, (slice(i0, i1 + 1), slice(k0, k1 + 1)))  # (k, bx, by)
        if outlier_prob > 0:
            ll += np.log1p(-outlier_prob)
            np.logaddexp(ll, np.log(outlier_prob / rssi_span), out=ll)
        b = (ix - i0) * by + (iy - k0)
        gu = 1.0 - fu
        gv = 1.0 - fv
        if per_reading:
            T = ll.reshape(ll.shape[0], -1).T  # (box nodes, k)
            return ((gu * gv)[:, None] * np.take(T, b, axis=0) + (gu * fv)[:, None] * np.take(T, b + 1, axis=0)
                    + (fu * gv)[:, None] * np.take(T, b + by, axis=0)
                    + (fu * fv)[:, None] * np.take(T, b + by + 1, axis=0))
        T = ll.sum(axis=0).reshape(-1)  # total over the readings per node
        out = gu * gv * np.take(T, b)
        out += gu * fv * np.take(T, b + 1)
        out += fu * gv * np.take(T, b + by)
        out += fu * fv * np.take(T, b + by + 1)
        return out

    # ------------------------------------------------------------ storage
    def to_npz(self, path: str | Path) -> None:
        """Save to a compressed ``.npz``; mean and std are stored in units of 0.01 dB as int16.

        The rounding (at most 0.005 dB) is three orders of magnitude below the spread of the
        model; it keeps a 12-receiver map of the 0.2 m BLE grid near 200 kB.
        """
        q = [np.round(a * 100.0) for a in (self.mean, self.std)]
        if max(np.abs(a).max() for a in q) > np.iinfo(np.int16).max:
            raise ValidationError("radio map values beyond +-327 dB cannot be stored")
        extra = {} if self.noise is None else {"noise": np.array(self.noise, dtype=float)}
        if self.settings:
            extra["settings_json"] = np.array(json.dumps(self.settings, sort_keys=True))
        np.savez_compressed(path, origin=self.origin, cell=np.float64(self.cell), mean_cdb=q[0].astype(np.int16),
                            std_cdb=np.maximum(q[1], 1).astype(np.int16), tracks=np.array(self.tracks, dtype=str),
                            **extra)

    @classmethod
    def from_npz(cls, path: str | Path) -> "RadioMap":
        """Read :meth:`to_npz` output (files without ``noise`` give a Gaussian map)."""
        try:
            with np.load(path, allow_pickle=False) as f:
                noise = tuple(float(v) for v in f["noise"]) if "noise" in f.files else None
                settings = json.loads(str(f["settings_json"])) if "settings_json" in f.files else {}
                return cls(f["origin"], float(f["cell"]), f["mean_cdb"] / 100.0, f["std_cdb"] / 100.0,
                           [str(t) for t in f["tracks"]], noise, settings)
        except (KeyError, ValueError) as exc:
            raise ValidationError(f"{path}: not a radio map ({exc})") from None


def binned_residual_stats(positions: ArrayLike, receiver: ArrayLike, residual: ArrayLike, n_receivers: int,
                          origin: ArrayLike, cell: float, shape: tuple[int, int]) -> tuple[Array, Array, Array]:
    """Count, sum and sum of squares of the residuals per receiver and nearest node, ``(m, nx, ny)`` each.

    Points off the grid go to the nearest edge node.
    """
    p = np.asarray(positions, dtype=float).reshape(-1, 2)
    j = np.asarray(receiver, dtype=np.int64).reshape(-1)
    r = np.asarray(residual, dtype=float).reshape(-1)
    if not (p.shape[0] == j.size == r.size):
        raise ShapeError("positions, receiver and residual must have the same length")
    nx, ny = shape
    o = np.asarray(origin, dtype=float).reshape(2)
    ix = np.clip(np.rint((p[:, 0] - o[0]) / cell).astype(np.int64), 0, nx - 1)
    iy = np.clip(np.rint((p[:, 1] - o[1]) / cell).astype(np.int64), 0, ny - 1)
    flat = (j * nx + ix) * ny + iy
    size = n_receivers * nx * ny
    C = np.bincount(flat, minlength=size).astype(float).reshape(n_receivers, nx, ny)
    S = np.bincount(flat, weights=r, minlength=size).reshape(n_receivers, nx, ny)
    Q = np.bincount(flat, weights=r * r, minlength=size).reshape(n_receivers, nx, ny)
    return C, S, Q


def _shrunk_moments(C: Array, S: Array, Q: Array, s0: Array, w0: float) -> tuple[Array, Array]:
    """Mean and std of the module docstring from kernel-weighted count, sum and sum of squares."""
    s0 = np.asarray(s0, dtype=float).reshape((-1,) + (1,) * (C.ndim - 1))
    den = C + w0
    m = S / den
    var = (Q - 2.0 * m * S + m * m * C + w0 * (s0 * s0 + m * m)) / den
    return m, np.sqrt(np.maximum(var, 1e-6))


def fit_radio_map(positions: ArrayLike, receiver: ArrayLike, rssi: ArrayLike,
                  base_mean: Callable[[np.ndarray, Array], Array], base_std: ArrayLike, *,
                  origin: ArrayLike, cell: float, shape: tuple[int, int], bandwidth: float = 1.0,
                  prior_weight: float = 1.0, spatial_std: bool = True,
                  tracks: list[str] | None = None, noise: tuple[float, float, float] | None = None,
                  settings: dict | None = None) -> RadioMap:
    """Learn a :class:`RadioMap` from labelled packets (module docstring).

    Parameters
    ----------
    positions : (K, 2)
        Tag positions of the training packets (m).
    receiver, rssi : (K,)
        Receiving receiver index and RSSI (dBm) of each packet.
    base_mean : callable ``(j, xy) -> (len(xy),)``
        Mean RSSI of receiver ``j`` at positions ``xy`` under the base model (log-distance,
        possibly directional).
    base_std : (m,)
        Residual standard deviation ``s0_j`` of the base model (the fallback spread).
    origin, cell, shape
        The node grid of the map (world position of node (0, 0), spacing, ``(nx, ny)``).
    bandwidth : float
        Kernel bandwidth ``b`` (m); 0 gives the plain base model.
    prior_weight : float
        ``w0``, in training points per cell.
    spatial_std : bool
        ``True``: the spread ``s_j(p)`` of the module docstring; ``False``: ``s0_j`` everywhere.
    tracks : list of str
        Provenance recorded in the map.
    noise, settings
        Stored in the map (:class:`RadioMap`).
    """
    return next(iter(fit_radio_maps(positions, receiver, rssi, base_mean, base_std, origin=origin, cell=cell,
                                    shape=shape, bandwidths=[bandwidth], prior_weights=[prior_weight],
                                    spatial_std=spatial_std, tracks=tracks, noise=noise,
                                    settings=settings).values()))


def fit_radio_maps(positions: ArrayLike, receiver: ArrayLike, rssi: ArrayLike,
                   base_mean: Callable[[np.ndarray, Array], Array], base_std: ArrayLike, *,
                   origin: ArrayLike, cell: float, shape: tuple[int, int], bandwidths: list[float],
                   prior_weights: list[float], spatial_std: bool = True, tracks: list[str] | None = None,
                   noise: tuple[float, float, float] | None = None,
                   settings: dict | None = None) -> dict[tuple[float, float], RadioMap]:
    """:func:`fit_radio_map` for every ``(bandwidth, prior_weight)`` pair, sharing the binning and smoothing.

    Returns ``{(bandwidth, prior_weight): RadioMap}``; each map's :attr:`RadioMap.settings` holds
    ``settings`` plus its bandwidth and prior weight.
    """
    p = np.asarray(positions, dtype=float).reshape(-1, 2)
    j = np.asarray(receiver, dtype=np.int64).reshape(-1)
    z = np.asarray(rssi, dtype=float).reshape(-1)
    s0 = np.asarray(base_std, dtype=float).reshape(-1)
    m = s0.size
    bws, pws = [float(v) for v in bandwidths], [float(v) for v in prior_weights]
    if not bws or not pws or min(bws) < 0 or min(pws) <= 0 or cell <= 0:
        raise ValidationError("fit_radio_map needs bandwidth >= 0, prior_weight > 0 and cell > 0")
    if j.size and (j.min() < 0 or j.max() >= m):
        raise ValidationError(f"receiver indices must be in [0, {m})")
    o = np.asarray(origin, dtype=float).reshape(2)
    nx, ny = shape
    gx, gy = o[0] + cell * np.arange(nx), o[1] + cell * np.arange(ny)
    nodes = np.column_stack([np.repeat(gx, ny), np.tile(gy, nx)])
    mu = np.stack([np.asarray(base_mean(r, nodes), dtype=float).reshape(nx, ny) for r in range(m)])
    res = np.empty_like(z)
    for r in range(m):
        sel = j == r
        res[sel] = z[sel] - np.asarray(base_mean(r, p[sel]), dtype=float)
    const_std = np.broadcast_to(s0[:, None, None], mu.shape)
    C, S, Q = binned_residual_stats(p, j, res, m, o, cell, (nx, ny))
    out: dict[tuple[float, float], RadioMap] = {}
    for bw in bws:
        if bw > 0:
            sig = bw / cell
            # gaussian_filter's kernel sums to 1 over the nodes: kernel-weighted counts per cell, like K above.
            from scipy.ndimage import gaussian_filter  # here: fitting only, a tracker needs no scipy
            Cs, Ss, Qs = (gaussian_filter(a, sigma=(0, sig, sig), mode="constant", cval=0.0, truncate=4.0)
                          for a in (C, S, Q))
        for w0 in pws:
            if bw == 0:
                mean, std = mu, const_std.copy()
            else:
                mres, std = _shrunk_moments(Cs, Ss, Qs, s0, w0)
                mean = mu + mres
                if not spatial_std:
                    std = const_std.copy()
            st = dict(settings or {}, bandwidth=bw, prior_weight=w0)
            out[(bw, w0)] = RadioMap(o, cell, mean, std, list(tracks or []), noise, st)
    return out


def kernel_residual_map(xy: ArrayLike, positions: ArrayLike, residual: ArrayLike, s0: float, *,
                        cell: float, bandwidth: float, prior_weight: float) -> tuple[Array, Array]:
    """Direct evaluation of ``m(p)`` and ``s(p)`` of the module docstring for one receiver (O(N K))."""
    q = np.asarray(xy, dtype=float).reshape(-1, 2)
    p = np.asarray(positions, dtype=float).reshape(-1, 2)
    r = np.asarray(residual, dtype=float).reshape(-1)
    d2 = ((q[:, None, :] - p[None, :, :]) ** 2).sum(axis=2)
    K = cell * cell / (2 * np.pi * bandwidth ** 2) * np.exp(-0.5 * d2 / bandwidth ** 2)
    m, s = _shrunk_moments(K.sum(axis=1)[None], (K @ r)[None], (K @ (r * r))[None], np.array([s0]), prior_weight)
    return m[0], s[0]
