"""Accuracy and consistency metrics.

* RMSE of the position: ``sqrt(mean_k ||p_k - p^true_k||^2)``.
* NEES: ``e_k^T P_k^-1 e_k`` with ``e_k = x_k - x^true_k`` (Bar-Shalom, Li &
  Kirubarajan 2001, sec. 5.4.2); a consistent filter has ``E[NEES] = n``.
* The chi-square interval of an average of ``M`` independent NEES values:
  ``[chi2.ppf(a/2, n M), chi2.ppf(1 - a/2, n M)] / M``.
"""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from dfusion.linalg import Array

__all__ = ["rmse", "nees", "chi2_interval", "error_stats"]


def rmse(est: Array, truth: Array, axes: int) -> float:
    """Position RMSE over time (first ``axes`` components)."""
    d = np.asarray(est)[:, :axes] - np.asarray(truth)[:, :axes]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def nees(est: Array, cov: Array, truth: Array, residual=None) -> Array:
    """NEES of every time step, through Cholesky solves."""
    e = np.asarray(est) - np.asarray(truth)
    if residual is not None:
        e = residual(np.asarray(est), np.asarray(truth))
    L = np.linalg.cholesky(cov)
    w = np.linalg.solve(L, e[..., None])[..., 0]
    return np.sum(w * w, axis=-1)


def chi2_interval(dof: int, samples: int, level: float = 0.95) -> tuple[float, float]:
    """Interval containing the average of ``samples`` chi-square(``dof``) values with probability ``level``."""
    a = 1.0 - level
    return (chi2.ppf(a / 2, dof * samples) / samples, chi2.ppf(1 - a / 2, dof * samples) / samples)


def error_stats(errors: Array) -> dict[str, float]:
    """RMSE, median, mean and 90th percentile of horizontal errors (m)."""
    e = np.asarray(errors, dtype=float)
    return {"rmse": float(np.sqrt(np.mean(e * e))), "median_error": float(np.median(e)),
            "mean_error": float(np.mean(e)), "p90_error": float(np.percentile(e, 90)), "n": int(e.size)}
