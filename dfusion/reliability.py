r"""Reliability models of localization sources, for the switching policies.

All three models of the switching paper (Hu et al., "An automatic switching approach of
robotic components for improving robot localization reliability", sec. 2) map a source's
own view of its accuracy to a reliability ``R`` in ``[0, 1]`` through the one rule
``R = 1 / (E + 1)`` (:func:`reliability_from_error`, eq. 8, 12 and 18) with ``E`` an
error in metres.

**Environmental camera** (sec. 2.1, eq. 1-9). A camera at height ``h`` above the plane of the target,
tilted by the installation angle ``alpha`` from the downward vertical, with a
vertical field angle ``theta`` over ``N`` pixel rows. A point seen at the
vertical angular coordinate ``phi`` in ``[-theta/2, theta/2]`` (measured from
the optical axis, positive towards the horizon) lies at the ground distance
``x = tan(phi + alpha) h`` and one pixel there covers ``D(phi)`` metres; the
farther the point, the larger ``D``, the fewer pixels a mark of width ``w``
covers and the larger the error of a detector that is off by ``k`` pixels::

    theta_0 = theta / N                                                   (1)
    x       = tan(phi + alpha) h                                          (2)
    D(phi)  = tan(phi + alpha + theta_0) h - tan(phi + alpha) h
            = sec^2(phi + alpha) h / (cot theta_0 - tan(phi + alpha))     (3)
    D(phi) ~= sec^2(phi + alpha) h / cot theta_0                          (4)
    n(phi)  = w / D                                                       (5)
    Phi     = n / n_max,   n_max = n(-theta/2)                            (6)
    E       = k D                                                         (7)
    S       = 1 / (E + 1)                                                 (8)
    R_c     = Phi S = n / (n(-theta/2) (k D + 1))                         (9)

The mark width ``w`` cancels in ``Phi = D(-theta/2) / D(phi)``, so it is not a
parameter here. ``D`` and ``E`` are in metres (``h`` in metres), ``k`` in pixels.

:func:`camera_geometry` and :func:`viewing_angle` read ``alpha, h, theta, N``
and ``phi`` off a :class:`~dfusion.models.PinholeCamera` and a target
position; :func:`camera_reliability_at` chains everything. The paper's model
is one-dimensional (the image row); for a camera without roll the row of a
ground point depends only on its distance along the camera's horizontal
heading, which is how ``phi`` is computed.

Every function is vectorized over ``phi`` where it takes one.

**Covariance model** (laser + AMCL), eq. (10)-(12). With ``C`` the covariance the
localizer reports (any size, ``x`` and ``y`` first)::

    E   = (c_xx + c_yy)^(1/2)                                             (11)
    R_l = 1 / (E + 1)                                                     (12)

``E`` is the root of the summed position variances (m); for a circular Gaussian it
is the RMS position error.

**Score model** (depth camera + NDT), eq. (17)-(18). The NDT matcher reports a score,
the summed Gaussian likelihood of the matched points in the normal distributions
of their map cells::

    score = sum_i exp(-(p_i - mu)^T Sigma^-1 (p_i - mu) / 2)              (17)

and "the correspondence between the score and localization error E" is established
"through a large number of experiments" as a lookup table; then::

    R_d = 1 / (E(score) + 1)                                              (18)

:class:`ScoreErrorTable` is that table: built from calibration pairs
``(score, error)``, binned, made monotone (a higher score never means a larger error:
isotonic regression by pool-adjacent-violators), and interpolated with a
shape-preserving monotone cubic (:class:`scipy.interpolate.PchipInterpolator`), clamped
to the calibrated range. :class:`NDTMap` computes eq. (17) for 2-D point sets (the
paper's matcher is 3-D; the score is the same sum in any dimension).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import ShapeError, ValidationError
from dfusion.linalg import Array

__all__ = [
    "pixel_angle",
    "ground_distance",
    "pixel_footprint",
    "mark_pixels",
    "recognition_accuracy",
    "localization_error",
    "camera_reliability",
    "CameraGeometry",
    "camera_geometry",
    "viewing_angle",
    "camera_reliability_at",
    "reliability_from_error",
    "error_from_reliability",
    "covariance_error",
    "covariance_reliability",
    "isotonic_decreasing",
    "ScoreErrorTable",
    "NDTMap",
]


def pixel_angle(theta: float, N: int) -> float:
    """Eq. (1): the field angle of one pixel row, ``theta_0 = theta / N`` (rad)."""
    if not (np.isfinite(theta) and 0 < theta < math.pi):
        raise ValidationError(f"vertical field angle theta must be in (0, pi), got {theta!r}")
    if N < 1:
        raise ValidationError(f"pixel rows N must be >= 1, got {N!r}")
    return float(theta) / float(N)


def ground_distance(phi: ArrayLike, alpha: float, h: float) -> Array:
    """Eq. (2): horizontal distance from the camera's foot, ``x = tan(phi + alpha) h`` (m)."""
    return np.tan(np.asarray(phi, dtype=float) + alpha) * h


def pixel_footprint(phi: ArrayLike, alpha: float, h: float, theta_0: float, *, approximate: bool = False) -> Array:
    """Eq. (3) (or its approximation eq. (4)): metres covered by one pixel row at ``phi``.

    ``D = sec^2(phi + alpha) h / (cot theta_0 - tan(phi + alpha))``; with
    ``approximate=True``, ``D = sec^2(phi + alpha) h tan(theta_0)`` (valid when
    ``cot theta_0 >> tan(phi + alpha)``). Where the pixel row reaches the horizon
    (``phi + alpha + theta_0 >= pi/2``) the footprint is infinite.
    """
    a = np.asarray(phi, dtype=float) + alpha
    sec2 = 1.0 / np.cos(a) ** 2
    if approximate:
        D = sec2 * h * math.tan(theta_0)
    else:
        with np.errstate(divide="ignore"):
            D = sec2 * h / (1.0 / math.tan(theta_0) - np.tan(a))
    return np.where((a + theta_0 < math.pi / 2) & (a > -math.pi / 2), D, np.inf)


def mark_pixels(w: float, D: ArrayLike) -> Array:
    """Eq. (5): pixels covered by a mark of width ``w`` (m), ``n = w / D``."""
    return w / np.asarray(D, dtype=float)


def _min_footprint_angle(alpha: float, theta: float, theta_0: float) -> float:
    # The paper's n_max = n(-theta/2) assumes alpha >= theta/2 (the image does not reach
    # past the camera's foot). Otherwise the smallest footprint (largest mark) is at the row
    # straddling the vertical, phi + alpha = -theta_0/2, clipped to the image.
    return float(np.clip(-alpha - theta_0 / 2, -theta / 2, theta / 2)) if alpha < theta / 2 else -theta / 2


def recognition_accuracy(phi: ArrayLike, alpha: float, h: float, theta: float, N: int, *,
                         approximate: bool = False) -> Array:
    """Eq. (6): ``Phi = n(phi) / n(-theta/2) = D(-theta/2) / D(phi)`` in ``[0, 1]``.

    (When ``alpha < theta/2`` the largest mark is not at the image edge; ``n_max``
    is then taken at the row straddling the vertical, so ``Phi`` stays in ``[0, 1]``.)
    """
    t0 = pixel_angle(theta, N)
    D = pixel_footprint(phi, alpha, h, t0, approximate=approximate)
    D_min = pixel_footprint(_min_footprint_angle(alpha, theta, t0), alpha, h, t0, approximate=approximate)
    return np.where(np.isfinite(D), D_min / D, 0.0)


def localization_error(k: float, D: ArrayLike) -> Array:
    """Eq. (7): ground error of a detector off by ``k`` pixels, ``E = k D`` (m)."""
    return k * np.asarray(D, dtype=float)




def camera_reliability(phi: ArrayLike, alpha: float, h: float, theta: float, N: int, k: float = 1.0, *,
                       approximate: bool = False) -> Array:
    """Eq. (9): ``R_c = Phi S = n / (n(-theta/2) (k D + 1))`` in ``[0, 1]``.

    Parameters
    ----------
    phi : float or array
        Vertical angular coordinate of the point in the image (rad), ``0`` on the
        optical axis, increasing towards the horizon.
    alpha : float
        Installation angle: the optical axis' angle from the downward vertical (rad).
    h : float
        Camera height above the target's plane (m), ``> 0``.
    theta : float
        Vertical field angle (rad); ``N`` the number of pixel rows.
    k : float
        Recognition error of the detector (pixels).

    Zero outside the image rows (``|phi| > theta/2``) and where the row reaches
    the horizon. With ``approximate=True`` the footprint uses eq. (4).
    """
    if not (np.isfinite(h) and h > 0):
        raise ValidationError(f"camera height above the target plane must be positive, got {h!r}")
    if not (np.isfinite(k) and k >= 0):
        raise ValidationError(f"recognition error k must be >= 0 pixels, got {k!r}")
    phi = np.asarray(phi, dtype=float)
    t0 = pixel_angle(theta, N)
    D = pixel_footprint(phi, alpha, h, t0, approximate=approximate)
    Phi = recognition_accuracy(phi, alpha, h, theta, N, approximate=approximate)
    finite = np.isfinite(D)
    R = np.where(finite, Phi * reliability_from_error(localization_error(k, np.where(finite, D, 0.0))), 0.0)
    inside = np.abs(phi) <= theta / 2 + 1e-12
    out = np.where(inside, R, 0.0)
    return float(out) if out.ndim == 0 else out


@dataclass(frozen=True)
class CameraGeometry:
    """The quantities of eq. (1)-(9) read off a camera: ``alpha``, ``h`` (m), ``theta`` (rad), ``N`` rows."""

    alpha: float
    h: float
    theta: float
    N: int


def _horizontal_heading(camera) -> Array:
    """Unit horizontal direction in which image rows move away from the camera."""
    f = camera.R_wc[:, 2]
    u = f[:2] if np.hypot(*f[:2]) > 1e-9 else -camera.R_wc[:2, 1]  # looking straight down: image "up"
    n = np.hypot(*u)
    if n < 1e-12:
        raise ValidationError("camera has no horizontal heading (optical axis and image rows vertical)")
    return u / n


def camera_geometry(camera) -> CameraGeometry:
    """``alpha, h, theta, N`` of a :class:`~dfusion.models.PinholeCamera`.

    ``h = C_z - point_height``; ``alpha = arccos(-f_z)`` with ``f`` the optical
    axis (0 looking straight down, ``pi/2`` horizontal); ``theta =
    atan(cy / fy) + atan((height - cy) / fy)`` (``2 atan(height / (2 fy))`` for a
    centred principal point); ``N = height``. Raises :class:`ValidationError`
    when the camera is not above the target's plane.
    """
    h = float(camera.position[2] - camera.point_height)
    if not h > 0:
        raise ValidationError(f"the camera is not above the target's plane (height {h:.3g} m)")
    fz = float(np.clip(camera.R_wc[2, 2], -1.0, 1.0))
    alpha = math.acos(-fz)
    theta = math.atan(camera.cy / camera.fy) + math.atan((camera.height - camera.cy) / camera.fy)
    return CameraGeometry(alpha, h, theta, int(camera.height))


def viewing_angle(camera, xy: ArrayLike, geometry: CameraGeometry | None = None) -> float:
    """Vertical angular coordinate ``phi`` of the ground point ``xy`` (eq. (2) inverted).

    ``phi = atan2(d, h) - alpha`` with ``d`` the point's horizontal distance from
    the camera's foot along the camera's heading. For a camera without roll this
    is the angle of the point's image row from the principal point,
    ``atan((cy - v) / fy)``.
    """
    g = geometry or camera_geometry(camera)
    p = np.asarray(xy, dtype=float).reshape(-1)[:2]
    d = float((p - camera.position[:2]) @ _horizontal_heading(camera))
    return math.atan2(d, g.h) - g.alpha


def camera_reliability_at(camera, xy: ArrayLike, k: float | None = None, *, approximate: bool = False) -> float:
    """Eq. (9) for a target at ground position ``xy`` seen by ``camera``.

    Zero when the target is not in the camera's view (``camera.in_view``): the
    camera cannot localize it there. ``k`` (recognition error, pixels) defaults to
    the camera's ``pixel_std``.
    """
    p = np.asarray(xy, dtype=float).reshape(-1)
    if not camera.in_view(p):
        return 0.0
    g = camera_geometry(camera)
    k = camera.pixel_std if k is None else k
    return float(camera_reliability(viewing_angle(camera, p, g), g.alpha, g.h, g.theta, g.N, k,
                                    approximate=approximate))


def reliability_from_error(E: ArrayLike) -> Array | float:
    """Eq. (8)/(12)/(18): ``R = 1 / (E + 1)`` for an error ``E >= 0`` (m)."""
    E = np.asarray(E, dtype=float)
    if np.any(E < 0) or np.any(np.isnan(E)):
        raise ValidationError("errors must be non-negative")
    R = 1.0 / (E + 1.0)
    return float(R) if R.ndim == 0 else R


def error_from_reliability(R: ArrayLike) -> Array | float:
    """Inverse of eq. (12): ``E = 1 / R - 1`` (``inf`` for ``R = 0``)."""
    R = np.asarray(R, dtype=float)
    if np.any((R < 0) | (R > 1)) or np.any(np.isnan(R)):
        raise ValidationError("reliabilities must be in [0, 1]")
    with np.errstate(divide="ignore"):
        E = 1.0 / R - 1.0
    return float(E) if E.ndim == 0 else E


def covariance_error(cov: ArrayLike) -> float:
    """Eq. (11): ``E = sqrt(c_xx + c_yy)`` from a covariance whose first two axes are x, y."""
    c = np.asarray(cov, dtype=float)
    if c.ndim != 2 or c.shape[0] != c.shape[1] or c.shape[0] < 2:
        raise ShapeError(f"covariance must be square with at least 2 rows, got {c.shape}")
    v = float(c[0, 0] + c[1, 1])
    if not math.isfinite(v):
        return math.inf
    return math.sqrt(max(v, 0.0))


def covariance_reliability(cov: ArrayLike) -> float:
    """Eq. (11)-(12): ``R_l = 1 / (sqrt(c_xx + c_yy) + 1)``.

    The reliability the covariance-based localizers report in their
    :class:`dfusion.estimation.Estimate` (MCL, ICP, the odometry and landmark EKFs).
    """
    E = covariance_error(cov)
    return 0.0 if math.isinf(E) else 1.0 / (E + 1.0)


def isotonic_decreasing(y: ArrayLike, w: ArrayLike | None = None) -> Array:
    """Least-squares non-increasing fit of ``y`` (pool-adjacent-violators), weights ``w``."""
    y = np.asarray(y, dtype=float).reshape(-1)
    w = np.ones_like(y) if w is None else np.asarray(w, dtype=float).reshape(-1)
    if w.shape != y.shape or np.any(w <= 0):
        raise ValidationError("weights must be positive, one per value")
    # blocks of (mean, weight, count); merge while a later block is larger (violation)
    means: list[float] = []
    weights: list[float] = []
    counts: list[int] = []
    for yi, wi in zip(y.tolist(), w.tolist()):
        means.append(yi)
        weights.append(wi)
        counts.append(1)
        while len(means) > 1 and means[-1] > means[-2]:
            m2, w2, c2 = means.pop(), weights.pop(), counts.pop()
            m1, w1, c1 = means.pop(), weights.pop(), counts.pop()
            means.append((m1 * w1 + m2 * w2) / (w1 + w2))
            weights.append(w1 + w2)
            counts.append(c1 + c2)
    return np.repeat(means, counts)


@dataclass
class ScoreErrorTable:
    """Monotone lookup table from a matcher's score to its localization error (eq. 17-18).

    Parameters
    ----------
    scores, errors : 1-D arrays
        The table's knots: strictly increasing scores and non-increasing errors (m).
        Use :meth:`from_samples` to build them from calibration runs.

    Scores below the first knot get the first knot's error, above the last the last
    one's (no extrapolation). Interpolation is monotone cubic (PCHIP), so the table
    never invents a minimum or maximum between knots.
    """

    scores: Array
    errors: Array

    def __post_init__(self) -> None:
        s = np.asarray(self.scores, dtype=float).reshape(-1)
        e = np.asarray(self.errors, dtype=float).reshape(-1)
        if s.shape != e.shape or s.size < 2:
            raise ShapeError("need at least two (score, error) knots of equal length")
        if not (np.all(np.isfinite(s)) and np.all(np.isfinite(e))):
            raise ValidationError("knots must be finite")
        if np.any(np.diff(s) <= 0):
            raise ValidationError("scores must be strictly increasing")
        if np.any(np.diff(e) > 1e-12) or np.any(e < 0):
            raise ValidationError("errors must be non-negative and non-increasing in the score")
        self.scores, self.errors = s, e
        from scipy.interpolate import (
            PchipInterpolator,  # here: node programs need not load scipy
        )

        self._f = PchipInterpolator(s, e, extrapolate=False)

    @classmethod
    def from_samples(cls, scores: ArrayLike, errors: ArrayLike, bins: int = 12) -> "ScoreErrorTable":
        """Build the table from calibration pairs (the paper's "large number of experiments").

        The samples are split into ``bins`` groups of equal count by score; each group
        gives one knot (median score, median error); the knot errors are then made
        non-increasing by isotonic regression (weighted by group size) and equal knot
        scores are merged.
        """
        s = np.asarray(scores, dtype=float).reshape(-1)
        e = np.asarray(errors, dtype=float).reshape(-1)
        if s.shape != e.shape:
            raise ShapeError("scores and errors must have the same length")
        ok = np.isfinite(s) & np.isfinite(e)
        s, e = s[ok], e[ok]
        bins = int(bins)
        if bins < 2 or s.size < 2 * bins:
            raise ValidationError(f"need at least {2 * max(bins, 2)} finite samples for {bins} bins")
        order = np.argsort(s, kind="stable")
        groups = np.array_split(order, bins)
        ks = np.array([np.median(s[g]) for g in groups])
        ke = np.array([np.median(e[g]) for g in groups])
        kw = np.array([g.size for g in groups], dtype=float)
        ke = isotonic_decreasing(ke, kw)
        us, inv = np.unique(ks, return_inverse=True)
        ue = np.array([np.average(ke[inv == i], weights=kw[inv == i]) for i in range(us.size)])
        if us.size < 2:
            raise ValidationError("calibration scores are all equal: no table can be built")
        return cls(us, np.maximum(ue, 0.0))

    def error(self, score: ArrayLike) -> Array | float:
        """Localization error (m) for ``score`` (clamped to the calibrated range)."""
        x = np.clip(np.asarray(score, dtype=float), self.scores[0], self.scores[-1])
        out = self._f(x)
        return float(out) if out.ndim == 0 else out

    def reliability(self, score: ArrayLike) -> Array | float:
        """Eq. (18): ``R_d = 1 / (E(score) + 1)``."""
        return reliability_from_error(np.maximum(self.error(score), 0.0))


class NDTMap:
    """Normal distributions of a reference point set on a grid, and the score of eq. (17).

    Parameters
    ----------
    points : (M, d) array
        Reference (map) points.
    cell : float
        Cell size (m).
    min_points : int
        Cells with fewer points get no distribution (points falling there score 0).
    regularization : float
        Added to every covariance's diagonal (m^2), so that cells on a straight wall
        (a degenerate, flat distribution) stay invertible (Magnusson 2009 inflates small
        eigenvalues for the same reason).
    """

    def __init__(self, points: ArrayLike, cell: float = 0.5, *, min_points: int = 3,
                 regularization: float = 1e-3) -> None:
        p = np.asarray(points, dtype=float)
        if p.ndim != 2 or p.shape[0] < min_points:
            raise ShapeError(f"points must be (M, d) with M >= {min_points}, got {p.shape}")
        if not cell > 0:
            raise ValidationError("cell must be positive")
        self.cell = float(cell)
        self.dim = p.shape[1]
        keys = np.floor(p / self.cell).astype(np.int64)
        uniq, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        inv = inv.reshape(-1)
        keep = counts >= min_points
        n = uniq.shape[0]
        sums = np.zeros((n, self.dim))
        np.add.at(sums, inv, p)
        mu = sums / counts[:, None]
        d = p - mu[inv]
        outer = np.zeros((n, self.dim, self.dim))
        np.add.at(outer, inv, d[:, :, None] * d[:, None, :])
        cov = outer / np.maximum(counts - 1, 1)[:, None, None] + regularization * np.eye(self.dim)
        self.keys = uniq[keep]
        self.means = mu[keep]
        self.inv_covs = np.linalg.inv(cov[keep])
        self._index = {tuple(k): i for i, k in enumerate(self.keys.tolist())}

    def score(self, points: ArrayLike, pose: ArrayLike | None = None) -> float:
        """Eq. (17) for ``points`` (sensor frame) moved by a 2-D ``pose = (x, y, theta)``."""
        q = np.asarray(points, dtype=float)
        if q.ndim != 2 or q.shape[1] != self.dim:
            raise ShapeError(f"points must be (K, {self.dim})")
        if pose is not None:
            if self.dim != 2:
                raise ValidationError("a pose (x, y, theta) applies to 2-D points only")
            x, y, th = np.asarray(pose, dtype=float).reshape(3)
            c, s = math.cos(th), math.sin(th)
            q = q @ np.array([[c, s], [-s, c]]) + np.array([x, y])
        keys = np.floor(q / self.cell).astype(np.int64)
        idx = np.array([self._index.get(tuple(k), -1) for k in keys.tolist()], dtype=np.int64)
        hit = idx >= 0
        if not hit.any():
            return 0.0
        d = q[hit] - self.means[idx[hit]]
        m = np.einsum("ki,kij,kj->k", d, self.inv_covs[idx[hit]], d)
        return float(np.exp(-0.5 * m).sum())
