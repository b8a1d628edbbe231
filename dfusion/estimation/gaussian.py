r"""Gaussians in information (canonical) form.

A Gaussian :math:`N(\mu, P)` in information form is the pair
:math:`(\eta, \Omega)` with :math:`\Omega = P^{-1}` and :math:`\eta = \Omega \mu`
(Thrun, Burgard & Fox, *Probabilistic Robotics*, 2005, sec. 3.5.1).
Independent information adds; marginalizing the block ``o`` out, keeping ``a``,
is the Schur complement (ibid., Table 11.6; URUS paper, sec. 6)::

    Omega_a' = Omega_aa - Omega_ao Omega_oo^-1 Omega_oa
    eta_a'   = eta_a    - Omega_ao Omega_oo^-1 eta_o

Conditioning on ``x_o = v`` just drops rows: ``Omega_a' = Omega_aa``,
``eta_a' = eta_a - Omega_ao v``. All solves go through Cholesky factors.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from dfusion.errors import ShapeError
from dfusion.linalg import (
    Array,
    as_matrix,
    as_spd,
    as_vector,
    check_psd,
    cholesky,
    spd_inverse,
    symmetrize,
)


@dataclass(frozen=True)
class InformationGaussian:
    """A Gaussian as information vector ``eta`` and information matrix ``Omega``.

    Attributes
    ----------
    eta : ndarray, shape (n,)
        Information vector ``Omega @ mean``.
    Omega : ndarray, shape (n, n)
        Information matrix (inverse covariance), symmetric positive semi-definite
        (positive definite when the Gaussian is proper).
    """

    eta: Array
    Omega: Array

    def __post_init__(self) -> None:
        Omega = as_matrix(self.Omega, name="information matrix")
        n = Omega.shape[0]
        if Omega.shape != (n, n):
            raise ShapeError(f"information matrix must be square, got {Omega.shape}")
        eta = as_vector(self.eta, n, "information vector")
        check_psd(Omega, "information matrix")
        object.__setattr__(self, "Omega", symmetrize(Omega))
        object.__setattr__(self, "eta", eta)

    @property
    def dim(self) -> int:
        """State dimension."""
        return self.eta.shape[0]

    @classmethod
    def from_moments(cls, mean: ArrayLike, cov: ArrayLike) -> "InformationGaussian":
        """Build from mean and (SPD) covariance: ``Omega = P^-1``, ``eta = P^-1 mean``."""
        P = as_spd(cov, name="covariance")
        m = as_vector(mean, P.shape[0], "mean")
        Omega = spd_inverse(P, "covariance")
        return cls(Omega @ m, Omega)

    def to_moments(self) -> tuple[Array, Array]:
        """Return ``(mean, cov)``; raises NotPositiveDefiniteError if ``Omega`` is singular."""
        P = spd_inverse(self.Omega, "information matrix")
        return P @ self.eta, P

    def __add__(self, other: "InformationGaussian") -> "InformationGaussian":
        """Fuse independent information: ``(eta_1 + eta_2, Omega_1 + Omega_2)``."""
        if other.dim != self.dim:
            raise ShapeError(f"cannot add information of dimensions {self.dim} and {other.dim}")
        return InformationGaussian(self.eta + other.eta, self.Omega + other.Omega)

    def __sub__(self, other: "InformationGaussian") -> "InformationGaussian":
        """Remove information (the result must remain positive semi-definite)."""
        if other.dim != self.dim:
            raise ShapeError(f"cannot subtract information of dimensions {self.dim} and {other.dim}")
        return InformationGaussian(self.eta - other.eta, self.Omega - other.Omega)

    def marginalize(self, keep: ArrayLike) -> "InformationGaussian":
        """Marginal over the components ``keep`` (Schur complement of the others)."""
        keep = np.asarray(keep, dtype=int).reshape(-1)
        if keep.size and (keep.min() < 0 or keep.max() >= self.dim or len(set(keep.tolist())) != keep.size):
            raise ShapeError(f"invalid indices to keep: {keep.tolist()}")
        drop = np.setdiff1d(np.arange(self.dim), keep)
        if drop.size == 0:
            return InformationGaussian(self.eta[keep], self.Omega[np.ix_(keep, keep)])
        Ooo = self.Omega[np.ix_(drop, drop)]
        Oao = self.Omega[np.ix_(keep, drop)]
        C = cholesky(Ooo, "information block being marginalized")
        W = np.linalg.solve(C, Oao.T)            # C^-1 Omega_oa
        w = np.linalg.solve(C, self.eta[drop])   # C^-1 eta_o
        Omega = self.Omega[np.ix_(keep, keep)] - W.T @ W
        eta = self.eta[keep] - W.T @ w
        return InformationGaussian(eta, symmetrize(Omega))

    def condition(self, given: ArrayLike, value: ArrayLike) -> "InformationGaussian":
        """Conditional over the other components given ``x[given] = value``."""
        given = np.asarray(given, dtype=int).reshape(-1)
        keep = np.setdiff1d(np.arange(self.dim), given)
        v = as_vector(value, given.size, "conditioning value")
        eta = self.eta[keep] - self.Omega[np.ix_(keep, given)] @ v
        return InformationGaussian(eta, self.Omega[np.ix_(keep, keep)])


def project_psd_information(Omega: ArrayLike, eta: ArrayLike, rtol: float = 1e-9) -> tuple[Array, Array, int]:
    """Project an information pair onto the positive semi-definite cone.

    With ``Omega = V diag(lam) V^T``: eigenvalues below ``rtol * max|lam|`` are set
    to 0 (``Omega_+ = V diag(max(lam, 0)) V^T``, the nearest PSD matrix in the
    Frobenius norm), and ``eta`` is projected onto the range of ``Omega_+``
    (``eta_+ = V_+ V_+^T eta``): information a measurement can carry has
    ``eta = H^T R^-1 z'`` in that range, and directions whose information was
    dropped must not shift the mean either. Returns ``(Omega_+, eta_+, n_clipped)``.
    """
    Om = symmetrize(np.asarray(Omega, dtype=float))
    e = np.asarray(eta, dtype=float)
    lam, V = np.linalg.eigh(Om)
    scale = float(np.max(np.abs(lam))) if lam.size else 0.0
    keep = lam > rtol * scale if scale > 0 else np.zeros_like(lam, dtype=bool)
    Vk = V[:, keep]
    Om_p = symmetrize((Vk * lam[keep]) @ Vk.T)
    eta_p = Vk @ (Vk.T @ e)
    return Om_p, eta_p, int(np.count_nonzero(~keep & (lam < 0)))
