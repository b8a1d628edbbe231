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
    if not np.isfinite(a).all():
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
    if not np.isfinite(a).all():
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
