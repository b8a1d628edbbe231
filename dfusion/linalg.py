"""Small dense linear-algebra helpers shared by the estimators.

Everything here works on symmetric positive-definite (SPD) matrices through
their Cholesky factor: no explicit inverses are formed except where the
inverse itself is the result (a covariance from an information matrix).
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from dfusion.errors import (
    NonFiniteError,
    NotPositiveDefiniteError,
    ShapeError,
    TimeError,
    ValidationError,
)

Array = NDArray[np.float64]

#: Relative tolerance used to decide whether a matrix is symmetric.
SYMMETRY_RTOL = 1e-9


def _all_finite(a: np.ndarray) -> bool:
    """``np.isfinite(a).all()``; small arrays are tested on Python floats, which costs less than a
    numpy reduction (the same decision)."""
    if a.size <= 64:
        return all(map(math.isfinite, a.ravel().tolist()))
    return bool(np.isfinite(a).all())


def as_vector(x: ArrayLike, n: int | None = None, name: str = "vector") -> Array:
    """Return ``x`` as a finite float64 vector of length ``n`` (a copy).

    Accepts shapes ``(n,)``, ``(n, 1)`` and ``(1, n)``; raises :class:`ShapeError`
    or :class:`NonFiniteError` otherwise.
    """
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ShapeError(f"{name} is not numeric: {exc}") from None
    if a.ndim == 2 and 1 in a.shape:
        a = a.reshape(-1)
    if a.ndim == 0:
        a = a.reshape(1)
    if a.ndim != 1:
        raise ShapeError(f"{name} must be a vector, got shape {np.shape(x)}")
    if n is not None and a.shape[0] != n:
        raise ShapeError(f"{name} must have length {n}, got {a.shape[0]}")
    if not _all_finite(a):
        raise NonFiniteError(f"{name} contains NaN or inf")
    return a


def as_matrix(m: ArrayLike, shape: tuple[int, int] | None = None, name: str = "matrix") -> Array:
    """Return ``m`` as a finite float64 2-D array (a copy) of the given shape."""
    try:
        a = np.array(m, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ShapeError(f"{name} is not numeric: {exc}") from None
    if a.ndim == 0 and shape == (1, 1):
        a = a.reshape(1, 1)
    if a.ndim != 2:
        raise ShapeError(f"{name} must be a matrix, got shape {a.shape}")
    if shape is not None and a.shape != shape:
        raise ShapeError(f"{name} must have shape {shape}, got {a.shape}")
    if not _all_finite(a):
        raise NonFiniteError(f"{name} contains NaN or inf")
    return a


def symmetrize(a: Array) -> Array:
    """Return ``(a + a.T) / 2``."""
    return 0.5 * (a + a.T)


def check_symmetric(a: Array, name: str = "matrix", rtol: float = SYMMETRY_RTOL) -> None:
    """Raise :class:`NotPositiveDefiniteError` unless ``a`` is symmetric to ``rtol``."""
    scale = max(float(np.max(np.abs(a))), 1e-300)
    if float(np.max(np.abs(a - a.T))) > rtol * scale:
        raise NotPositiveDefiniteError(f"{name} is not symmetric")


def cholesky(a: Array, name: str = "matrix") -> Array:
    """Lower Cholesky factor of an SPD matrix; :class:`NotPositiveDefiniteError` otherwise."""
    try:
        return np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        raise NotPositiveDefiniteError(f"{name} is not positive definite") from None


def as_spd(m: ArrayLike, n: int | None = None, name: str = "matrix") -> Array:
    """Validate ``m`` as a finite, symmetric, positive-definite ``n x n`` matrix.

    Returns the exactly symmetrized copy.
    """
    a = as_matrix(m, None if n is None else (n, n), name)
    if a.shape[0] != a.shape[1]:
        raise ShapeError(f"{name} must be square, got {a.shape}")
    check_symmetric(a, name)
    a = symmetrize(a)
    cholesky(a, name)
    return a


def check_psd(a: Array, name: str = "matrix", atol: float = 1e-9) -> None:
    """Raise unless ``a`` is symmetric positive semi-definite within ``atol`` (relative to its scale)."""
    check_symmetric(a, name)
    if a.size == 0:
        return
    scale = max(float(np.max(np.abs(a))), 1.0)
    if float(np.linalg.eigvalsh(symmetrize(a))[0]) < -atol * scale:
        raise NotPositiveDefiniteError(f"{name} is not positive semi-definite")


def spd_inverse(a: Array, name: str = "matrix") -> Array:
    """Inverse of an SPD matrix through its Cholesky factor, exactly symmetric."""
    c = cholesky(a, name)
    ci = np.linalg.solve(c, np.eye(a.shape[0]))  # triangular in value, small n
    return ci.T @ ci


def spd_solve(a: Array, b: Array, name: str = "matrix") -> Array:
    """Solve ``a x = b`` for SPD ``a`` through its Cholesky factor ``a = L L^T``."""
    c = cholesky(a, name)
    return np.linalg.solve(c.T, np.linalg.solve(c, b))


def as_finite(value: object, name: str) -> float:
    """``value`` as a float; :class:`ValidationError` unless it is a finite number."""
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValidationError(f"{name} must be a finite number, got {value!r}") from None
    if not np.isfinite(v):
        raise ValidationError(f"{name} must be finite, got {value!r}")
    return v


def as_positive(value: object, name: str) -> float:
    """``value`` as a float; :class:`ValidationError` unless positive and finite."""
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValidationError(f"{name} must be a positive finite number, got {value!r}") from None
    if not (np.isfinite(v) and v > 0):
        raise ValidationError(f"{name} must be positive and finite, got {value!r}")
    return v


def as_time(t: object, name: str = "time") -> float:
    """A time stamp as a float; :class:`TimeError` unless it is a finite number."""
    try:
        tf = float(t)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise TimeError(f"{name} must be a number, got {t!r}") from None
    if not math.isfinite(tf):
        raise TimeError(f"{name} must be finite, got {t!r}")
    return tf


# ---------------------------------------------------------------------- chi-square tails without scipy
def chi2_sf(x: float, dof: int) -> float:
    r"""Upper tail ``Q(x; k) = P(X > x)`` of a chi-square variable with integer ``k = dof`` degrees of freedom.

    Closed forms for integer ``k`` (Abramowitz & Stegun, *Handbook of Mathematical
    Functions*, 1964, 26.4.4 and 26.4.5), with :math:`\chi = \sqrt{x}`:

    .. math::

        Q(x; k) = e^{-x/2} \sum_{r=0}^{k/2 - 1} \frac{(x/2)^r}{r!}
        \quad (k \text{ even}), \qquad
        Q(x; k) = \operatorname{erfc}(\chi / \sqrt{2})
        + \sqrt{2/\pi}\, e^{-x/2} \sum_{r=1}^{(k-1)/2} \frac{\chi^{2r-1}}{1 \cdot 3 \cdots (2r-1)}
        \quad (k \text{ odd}).

    Every term is positive (no cancellation in the tail); the sums are taken in
    log space (consecutive terms differ by the factor ``x / (2r)`` or ``x / (2r - 1)``),
    so large ``x`` and ``k`` do not underflow. Pure Python and numpy: the fusion node's
    consistency test uses it where importing :mod:`scipy.stats` would stall a real-time
    node for seconds.
    """
    k = _dof(dof)
    x = float(x)
    if not x > 0.0:
        return 1.0
    if k % 2 == 0:
        head, steps = -0.5 * x, np.log(x / (2.0 * np.arange(1, k // 2)))
        tail = 0.0
    else:
        chi = math.sqrt(x)
        head, steps = 0.5 * math.log(2.0 / math.pi) - 0.5 * x + math.log(chi), np.log(x / (2.0 * np.arange(2, (k + 1) // 2) - 1.0))
        tail = math.erfc(chi / math.sqrt(2.0))
        if k == 1:
            return tail
    logs = head + np.concatenate(([0.0], np.cumsum(steps)))
    top = float(np.max(logs))
    return tail + math.exp(top) * float(np.sum(np.exp(logs - top)))


def chi2_isf(alpha: float, dof: int) -> float:
    r"""The chi-square quantile :math:`\chi^{2\,-1}_k(1 - \alpha)`: the ``x`` with ``Q(x; k) = alpha`` (:func:`chi2_sf`).

    Solved by Newton's method on :math:`\ln Q(x; k) - \ln\alpha` (derivative
    :math:`-f(x; k) / Q(x; k)`, with the density
    :math:`f(x; k) = x^{k/2-1} e^{-x/2} / (2^{k/2}\,\Gamma(k/2))`), kept inside a bracket
    that is halved whenever a Newton step would leave it. Made for the tail (gates and
    tests: small ``alpha``): it agrees with ``scipy.stats.chi2.isf`` to ``1e-12`` relative
    for ``alpha <= 0.9`` and ``k`` up to 4000; as ``alpha`` nears 1 the lower tail
    ``1 - Q`` is resolved less finely (``1e-10`` relative at ``alpha = 0.999``).
    """
    k = _dof(dof)
    a = float(alpha)
    if not 0.0 < a < 1.0:
        raise ValidationError(f"alpha must be in (0, 1), got {alpha!r}")
    target = math.log(a)
    lo, hi = 0.0, float(k)
    while math.log(chi2_sf(hi, k)) > target:
        lo, hi = hi, 2.0 * hi
    log_norm = 0.5 * k * math.log(2.0) + math.lgamma(0.5 * k)
    x = 0.5 * (lo + hi)
    for _ in range(200):
        q = chi2_sf(x, k)
        g = math.log(q) - target
        if g > 0:
            lo = x
        else:
            hi = x
        log_f = (0.5 * k - 1.0) * math.log(x) - 0.5 * x - log_norm
        slope = math.exp(log_f) / q
        step = g / slope if slope > 0 else math.inf
        nxt = x + step
        if not lo < nxt < hi:
            nxt = 0.5 * (lo + hi)
        if abs(nxt - x) <= 1e-15 * max(x, 1e-300) or hi - lo <= 4e-16 * hi:
            return nxt
        x = nxt
    return x


def _dof(dof: object) -> int:
    if isinstance(dof, bool) or not isinstance(dof, (int, np.integer)) or dof < 1:
        raise ValidationError(f"degrees of freedom must be a positive integer, got {dof!r}")
    return int(dof)
