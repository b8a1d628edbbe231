r"""Block-tridiagonal information of a trajectory, evaluated by a cached forward pass.

The delayed-state information over states ``x_0 .. x_{m-1}`` (oldest first) is
a product of factors:

* a *base* ``N(mu_b, P_b)`` on ``x_0`` (information ``B = P_b^-1``, ``b = B mu_b``): the
  prior, or what marginalizing older states left;
* *single-state* factors ``(L_k, y_k)`` on each ``x_k``: measurements and fused
  information, added up;
* *motion* factors ``x_{k+1} = F_k x_k + c_k + w``, ``w ~ N(0, Q_k)``.

Its information matrix is block-tridiagonal (URUS paper, sec. 6;
``docs/background.md#1-delayed-state-information-filter``)::

    Omega[k,k]   = [B]_{k=0} + L_k + Q_{k-1}^-1 + F_k^T Q_k^-1 F_k
    Omega[k,k+1] = -F_k^T Q_k^-1
    eta[k]       = [b]_{k=0} + y_k + Q_{k-1}^-1 c_{k-1} - F_k^T Q_k^-1 c_k

and :meth:`TrajectoryInformation.dense` / :meth:`TrajectoryInformation.blocks` assemble it.

**Evaluation.** Forward block elimination of this matrix,
``S_k = Omega[k,k] - Omega[k,k-1] S_{k-1}^-1 Omega[k-1,k]``, is algebraically the
information filter's predict/update recursion (Thrun et al. 2005, Table 3.6;
Eustice et al., ICRA 2005)::

    x_k filtered:    A_k = Pred_k + L_k,             a_k = pred_k + y_k
                     (evaluated as P_k = (I + P^-_k L_k)^-1 P^-_k, one LU solve)
    prediction:      P^-_{k+1} = F_k A_k^-1 F_k^T + Q_k,   mu^-_{k+1} = F_k A_k^-1 a_k + c_k
                     Pred_{k+1} = (P^-_{k+1})^-1,           pred_{k+1} = Pred_{k+1} mu^-_{k+1}

which we evaluate instead of the subtraction: when two states are close in
time ``Q_k^-1`` is huge and the subtraction loses digits (measured: 6e-8
relative error with states 0.6 ms apart), while this recursion only adds.
The filtered terms of ``x_k`` depend only on factors up to ``x_k``, so they
are cached: appending a state invalidates nothing, a change to ``x_s``
invalidates ``k >= s``. The usual cycle (append, update the newest, estimate)
costs O(1) in the window length; a late measurement ``j`` states back O(j).
Marginalizing ``x_0`` sets the new base to the prediction ``N(mu^-_1, P^-_1)``,
which the cache already holds (the base is kept in moment form for that).

**Smoothing** (any window state) is the Rauch-Tung-Striebel backward pass
(Rauch, Tung & Striebel, AIAA J. 1965)::

    G_k = P_k F_k^T (P^-_{k+1})^-1
    mu^s_k = mu_k + G_k (mu^s_{k+1} - mu^-_{k+1})
    P^s_k  = P_k + G_k (P^s_{k+1} - P^-_{k+1}) G_k^T

costing O(m - k). ``G_k`` depends on the factors up to ``x_{k+1}`` only, so it is cached with
the forward terms of ``x_{k+1}`` (:meth:`TrajectoryInformation.gains`): a pass after a change
at late states recomputes only their gains, and each step is then two small products.
Every inverse goes through a Cholesky factor.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dfusion.errors import NotPositiveDefiniteError
from dfusion.estimation.scalar import MAX_N as _SCALAR_MAX_N
from dfusion.estimation.scalar import fold_kernel, predict_kernel
from dfusion.linalg import Array, symmetrize

# numpy.linalg's compiled kernels called directly: the same LAPACK routines as
# numpy.linalg.solve / cholesky without their per-call Python checks, which cost more than
# the arithmetic on 4 x 4 blocks (3 against 16 us a call, measured). The module is numpy's
# own (numpy 1.x and 2.x); the public functions are the fall-back. A failed factorization
# gives NaN here instead of an exception: callers check finiteness.
try:
    from numpy.linalg import _umath_linalg as _kernels

    _cholesky = _kernels.cholesky_lo
    _solve = _kernels.solve
except (ImportError, AttributeError):   # pragma: no cover - other numpy builds
    _cholesky, _solve = np.linalg.cholesky, np.linalg.solve


@dataclass(frozen=True)
class MotionFactor:
    """A linearized motion factor ``x_b = F x_a + c + w``, ``w ~ N(0, Q)``.

    ``dt`` and ``u`` are kept so that the factor can be split when a state is
    inserted inside the interval. ``extra`` is process noise added to the motion
    model's on this interval after the fact (``Q`` includes it;
    :meth:`dfusion.estimation.DelayedStateEIF.add_process_noise`), kept so that a split
    keeps it too.
    """

    F: Array
    Q: Array
    c: Array
    dt: float
    u: Array | None = None
    extra: Array | None = None

    def information_blocks(self) -> tuple[Array, Array, Array, Array, Array]:
        """``(Omega_aa, Omega_ab, Omega_bb, eta_a, eta_b)`` contributed by the factor."""
        C = _chol(self.Q, "process noise Q")
        Ci = np.linalg.solve(C, np.eye(C.shape[0]))
        Qinv = Ci.T @ Ci
        FtQ = self.F.T @ Qinv
        Qc = Qinv @ self.c
        return symmetrize(FtQ @ self.F), -FtQ, Qinv, -self.F.T @ Qc, Qc


def _chol(S: Array, what: str) -> Array:
    """Lower Cholesky factor of ``S`` (LAPACK ``dpotrf``); :class:`NotPositiveDefiniteError` otherwise."""
    try:
        with np.errstate(invalid="ignore"):
            C = _cholesky(S)
    except np.linalg.LinAlgError:
        raise NotPositiveDefiniteError(f"{what} is not positive definite") from None
    if not np.isfinite(C).all():
        raise NotPositiveDefiniteError(f"{what} is not positive definite")
    return C


def _inv_from_chol(C: Array) -> Array:
    Ci = np.linalg.solve(C, np.eye(C.shape[0]))
    return Ci.T @ Ci


@dataclass
class _Filtered:
    """Cached forward-pass terms of one state."""

    mean: Array                      # filtered mean mu_k
    cov: Array                       # filtered covariance P_k
    pred_mean: Array | None = None   # mu^-_k (None for k = 0)
    pred_cov: Array | None = None    # P^-_k
    # the smoother gain G_{k-1} = P_{k-1} F_{k-1}^T (P^-_k)^-1 into this state: it depends on the
    # states before x_k only, like the prediction, so it is valid as long as this entry is
    _gain: Array | None = None


class TrajectoryInformation:
    """Factors of a delayed-state trajectory (oldest state first).

    All mutators replace arrays instead of writing into them, so a shallow copy
    (:meth:`snapshot`) is a complete, cheap checkpoint.

    When a single-state factor of ``x_k`` changes, the prediction ``N(mu^-_k, P^-_k)``
    stays valid (it depends on the states before ``x_k`` only): it is kept aside
    (``_kept``, always for state ``len(_cache)``) and reused by the next forward pass.
    """

    def __init__(self, mean: Array, cov: Array) -> None:
        self.n = cov.shape[0]
        # the base factor on x_0, kept as moments (mean, covariance): marginalizing
        # x_0 then just adopts the cached prediction of x_1, with no inversion
        self.base: tuple[Array, Array] = (np.array(mean, float), symmetrize(np.array(cov, float)))
        zero = np.zeros((self.n, self.n))
        self.L: list[Array] = [zero]
        self.y: list[Array] = [np.zeros(self.n)]
        self.factors: list[MotionFactor] = []  # factors[k] links x_k and x_{k+1}
        self._cache: list[_Filtered] = []
        self._kept: _Filtered | None = None   # prediction of state len(_cache), if still valid
        self._diag = np.diag_indices(self.n)
        # the scalar path of a small state (dfusion.estimation.scalar): the forward pass on floats
        # (the kernels are looked up, not kept: an instance stays picklable)
        self._scalar = self.n <= _SCALAR_MAX_N
        # the last smoothed means, (k_from, means of k_from .. m-1), while nothing changed since
        self._means: tuple[int, list[Array]] | None = None

    def __len__(self) -> int:
        return len(self.L)

    # ---------------------------------------------------------------- checkpoint
    def snapshot(self) -> tuple:
        """A checkpoint of the whole state (O(m) references, no array copies)."""
        return (self.base, list(self.L), list(self.y), list(self.factors), list(self._cache), self._kept)

    def restore(self, snap: tuple) -> None:
        """Return to a checkpoint taken by :meth:`snapshot`."""
        base, L, y, f, c, kept = snap
        self.base, self.L, self.y, self.factors, self._cache = base, list(L), list(y), list(f), list(c)
        self._kept = kept
        self._means = None

    # ---------------------------------------------------------------- mutation
    def _invalidate(self, k: int) -> None:
        """Forget the filtered terms of states ``k ..`` and their predictions."""
        self._means = None
        if k < len(self._cache):
            del self._cache[k:]
            self._kept = None
        elif k == len(self._cache):
            self._kept = None

    def add_information(self, k: int, Lam: Array, y: Array) -> None:
        """Add a single-state factor: ``Omega[k,k] += Lam``, ``eta[k] += y``."""
        self.L[k] = symmetrize(self.L[k] + Lam)
        self.y[k] = self.y[k] + y
        self._means = None
        cache = self._cache
        if k < len(cache):
            # x_k's prediction does not depend on its own single-state factor: keep it
            self._kept = cache[k] if k > 0 else None
            del cache[k:]

    def append(self, factor: MotionFactor) -> None:
        """Append a newest state linked to the current newest one by ``factor``."""
        self.L.append(np.zeros((self.n, self.n)))
        self.y.append(np.zeros(self.n))
        self.factors.append(factor)
        self._means = None
        # filtered terms of older states do not depend on later factors

    def split(self, a: int, first: MotionFactor, second: MotionFactor) -> None:
        """Insert a state between ``a`` and ``a+1``: factor ``a -> a+1`` becomes ``a -> s -> a+1``.

        For linear models the two steps compose to the original one
        (``F_2 F_1 = F``, ``F_2 Q_1 F_2^T + Q_2 = Q``), so the joint over the
        other states is unchanged.
        """
        self.L.insert(a + 1, np.zeros((self.n, self.n)))
        self.y.insert(a + 1, np.zeros(self.n))
        self.factors[a:a + 1] = [first, second]
        self._invalidate(a + 1)

    def replace_factor(self, k: int, factor: MotionFactor) -> None:
        """Replace the motion factor ``x_k -> x_{k+1}``; the filtered terms of the states
        after it become invalid."""
        self.factors[k] = factor
        self._invalidate(k + 1)

    def drop_oldest(self) -> None:
        """Marginalize ``x_0`` out: the new base is the prediction ``N(mu^-_1, P^-_1)``."""
        if len(self.L) < 2:
            raise ValueError("cannot marginalize the only state")
        self._forward(2)
        self._means = None
        f1 = self._cache[1]
        self.base = (f1.pred_mean, f1.pred_cov)
        del self.L[0], self.y[0], self.factors[0], self._cache[0]
        c0 = self._cache[0]
        self._cache[0] = _Filtered(c0.mean, c0.cov)
        # _kept (if any) is the prediction of state len(_cache), which moved down with it

    # ---------------------------------------------------------------- queries
    def _forward(self, upto: int) -> None:
        """Make the cached filtered terms valid for states ``0 .. upto-1``."""
        cache = self._cache
        k = len(cache)
        while k < upto:
            if k == 0:
                cache.append(self._filtered(0, self.base[0], self.base[1]))
            elif self._kept is not None:
                kept, self._kept = self._kept, None
                entry = self._filtered(k, kept.pred_mean, kept.pred_cov)
                entry._gain = kept._gain
                cache.append(entry)
            else:
                prev = cache[k - 1]
                f = self.factors[k - 1]
                if self._scalar:   # (the same prediction on floats; the filtered terms from it)
                    mp, Pp = predict_kernel(self.n)(f.F.tolist(), f.Q.tolist(), f.c.tolist(),
                                                    prev.mean.tolist(), prev.cov.tolist())
                    cache.append(self._filtered(k, np.array(mp), np.array(Pp), mp, Pp))
                else:
                    mp = f.F @ prev.mean + f.c
                    Pp = symmetrize(f.F @ prev.cov @ f.F.T + f.Q)
                    cache.append(self._filtered(k, mp, Pp))
            k += 1

    def _filtered(self, k: int, mp: Array, Pp: Array, mp_list: list | None = None,
                  Pp_list: list | None = None) -> _Filtered:
        """Fold the single-state information of ``x_k`` into its prediction ``N(mp, Pp)``.

        ``A = (P^-)^-1 + L``: ``P = A^-1 = (I + P^- L)^-1 P^-`` and
        ``mu = P ((P^-)^-1 mu^- + y) = (I + P^- L)^-1 (mu^- + P^- y)``, one LU solve
        with ``n + 1`` right-hand sides. ``I + P^- L`` is invertible: it is similar
        to ``I + (P^-)^1/2 L (P^-)^1/2``, which is positive definite.

        A small state takes the scalar path (:func:`dfusion.estimation.scalar.fold_kernel`: the
        same algorithm on floats; ``mp_list``, ``Pp_list``: the prediction as lists, if the
        caller has them); when it finds the result unusable the numpy path below decides.
        """
        Lk, yk = self.L[k], self.y[k]
        # (tests on Python lists: a numpy reduction costs more than the 4 x 4 arithmetic; the same
        # decisions, NaN counting as non-zero and non-finite)
        if self._scalar:
            Ll, yl = Lk.tolist(), yk.tolist()
            if not any(map(any, Ll)) and not any(yl):
                return _Filtered(mp, Pp, mp, Pp)
            done = fold_kernel(self.n)(Pp.tolist() if Pp_list is None else Pp_list, Ll,
                                       mp.tolist() if mp_list is None else mp_list, yl)
            if done is not None:
                return _Filtered(np.array(done[0]), np.array(done[1]), mp, Pp)
        elif not any(Lk.ravel().tolist()) and not any(yk.tolist()):
            return _Filtered(mp, Pp, mp, Pp)
        n = self.n
        M = Pp @ Lk
        M.reshape(-1)[::n + 1] += 1.0   # I + P^- L (the diagonal of the new, contiguous M)
        rhs = np.empty((n, n + 1))
        rhs[:, :n] = Pp
        rhs[:, n] = mp + Pp @ yk
        # one error-state context for the solve and the factorization (each costs a few us)
        with np.errstate(invalid="ignore", divide="ignore"):
            try:
                X = _solve(M, rhs)
            except np.linalg.LinAlgError:
                X = np.full_like(rhs, np.nan)
            if not all(map(math.isfinite, X.ravel().tolist())):
                raise NotPositiveDefiniteError(f"the information of window state {k} is singular")
            P = symmetrize(X[:, :n])
            # the information must stay positive definite
            try:
                C = _cholesky(P)
            except np.linalg.LinAlgError:
                C = None
        if C is None or not all(map(math.isfinite, C.ravel().tolist())):
            raise NotPositiveDefiniteError(f"the covariance of window state {k} is not positive definite")
        return _Filtered(X[:, n].copy(), P, mp, Pp)

    def latest(self) -> tuple[Array, Array]:
        """Mean and covariance of the newest state (the filtered estimate)."""
        m = len(self.L)
        self._forward(m)
        c = self._cache[m - 1]
        return c.mean, c.cov

    def gains(self, k_from: int) -> list[Array]:
        """The smoother gains ``G_k = P_k F_k^T (P^-_{k+1})^-1`` of states ``k_from .. m-2`` (the
        forward terms must be valid up to ``x_{m-1}``), through the Cholesky factor of
        ``P^-_{k+1}``. Each is cached with the forward terms of ``x_{k+1}``: it depends on the
        factors before ``x_{k+1}`` only, so a change at late states leaves the gains of earlier
        ones for the next smoothing; the missing ones are computed in one stacked call per step
        (factor, two triangular solves: the LAPACK kernels of :func:`numpy.linalg.solve` on a
        stack of 4 x 4 systems, without a Python call per state)."""
        cache, factors = self._cache, self.factors
        m = len(cache)
        missing = [k for k in range(k_from, m - 1) if cache[k + 1]._gain is None]
        if missing:
            Pp = np.array([cache[k + 1].pred_cov for k in missing])
            # F P_k = P^-_{k+1} G_k^T, as one stacked product (numpy's matmul loop: the same products
            # as one call per state, bit for bit)
            B = np.array([factors[k].F for k in missing]) @ np.array([cache[k].cov for k in missing])
            with np.errstate(invalid="ignore", divide="ignore"):
                try:
                    C = _cholesky(Pp)
                    Gt = _solve(C.transpose(0, 2, 1), _solve(C, B))
                except np.linalg.LinAlgError:
                    Gt = np.full_like(B, np.nan)
            ok = np.isfinite(Gt).all(axis=(1, 2))
            if not ok.all():
                bad = missing[int(np.argmin(ok))] + 1
                raise NotPositiveDefiniteError(f"the predicted covariance of window state {bad} is not positive definite")
            for i, k in enumerate(missing):   # a copy each: a view would keep the whole stack alive
                cache[k + 1]._gain = Gt[i].T.copy()
        return [cache[k + 1]._gain for k in range(k_from, m - 1)]

    def smoothed(self, k_from: int) -> tuple[list[Array], list[Array]]:
        """Smoothed means and covariances of states ``k_from .. m-1`` (RTS backward pass with the
        cached gains, :meth:`gains`)."""
        m = len(self.L)
        self._forward(m)
        mu, P = self.latest()
        means, covs = [mu], [P]
        cache = self._cache
        G = self.gains(k_from)
        for k in range(m - 2, k_from - 1, -1):
            ck, nxt, Gk = cache[k], cache[k + 1], G[k - k_from]
            mu = ck.mean + Gk @ (mu - nxt.pred_mean)
            P = symmetrize(ck.cov + Gk @ (P - nxt.pred_cov) @ Gk.T)
            means.append(mu)
            covs.append(P)
        means.reverse()
        covs.reverse()
        return means, covs

    def smoothed_means(self, k_from: int) -> list[Array]:
        """Smoothed means of states ``k_from .. m-1``: the mean recursion of :meth:`smoothed`
        without the covariances, ``mu_k = mu_k|k + G_k (mu_{k+1} - mu^-_{k+1})``.

        The result is kept until the trajectory changes: a later call reads it, and one from an
        older state continues the recursion where it stopped (the same operations on the same
        values as a pass from the newest state: the same bits). A node's consistency test
        (:meth:`dfusion.estimation.DelayedStateEIF.add_information_moments`) computes the means
        after one message and, when nothing happened in between, needs them before the next."""
        m = len(self.L)
        kept = self._means
        if kept is not None and kept[0] <= k_from:
            return kept[1][k_from - kept[0]:]
        self._forward(m)
        cache = self._cache
        G = self.gains(k_from)
        if kept is not None:
            top, means = kept[0], kept[1][::-1]   # (newest first, as the recursion builds it)
            mu = means[-1]
        else:
            top, mu = m - 1, self.latest()[0]
            means = [mu]
        for k in range(top - 1, k_from - 1, -1):
            mu = cache[k].mean + G[k - k_from] @ (mu - cache[k + 1].pred_mean)
            means.append(mu)
        means.reverse()
        self._means = (k_from, means)
        return means[:]

    def covariance_bounds(self, idx: list[int]) -> tuple[Array, Array]:
        r"""Bounds ``(lower, upper)`` (stacks, in the order of ``idx``) on the smoothed covariances of
        the states ``idx``, from the cached forward terms and gains (valid after :meth:`smoothed_means`
        from ``min(idx)`` or earlier, nothing changed since): in the Loewner order
        ``P_k - G_k P^-_{k+1} G_k^T  <=  P^s_k  <=  P_k``. The RTS recursion (module docstring)
        gives ``P^s_k = (P_k - G_k P^-_{k+1} G_k^T) + G_k P^s_{k+1} G_k^T``: the first term is the
        covariance of ``x_k`` given ``x_{k+1}`` and the information up to ``x_k``, the second is
        positive semi-definite, hence the lower bound; and ``P^s_k = P_k - G_k (P^-_{k+1} -
        P^s_{k+1}) G_k^T`` with ``P^s_{k+1} <= P^-_{k+1}`` (information only shrinks a
        covariance), hence the upper one (Rauch, Tung & Striebel 1965; Saerkkae, *Bayesian
        Filtering and Smoothing*, 2013, Theorem 8.2). Both are exact (``P^s``) at the newest
        state. O(len(idx)): for a test that needs a smoothed covariance only against thresholds
        (:mod:`dfusion.fusion.guard`), without the O(m) covariance pass of :meth:`smoothed`."""
        cache = self._cache
        m = len(cache)
        upper = np.array([cache[k].cov for k in idx])
        older = [i for i, k in enumerate(idx) if k < m - 1]
        lower = upper.copy()
        if older:
            G = np.array([cache[idx[i] + 1]._gain for i in older])
            Pp = np.array([cache[idx[i] + 1].pred_cov for i in older])
            lower[older] = upper[older] - G @ Pp @ G.transpose(0, 2, 1)
        return lower, upper

    def blocks(self) -> tuple[list[Array], list[Array], list[Array]]:
        """Assembled ``(D, U, eta)``: diagonal and super-diagonal blocks and vector."""
        m = len(self.L)
        D = [self.L[k].copy() for k in range(m)]
        eta = [self.y[k].copy() for k in range(m)]
        Binfo = _inv_from_chol(_chol(self.base[1], "the base covariance"))
        D[0] = D[0] + Binfo
        eta[0] = eta[0] + Binfo @ self.base[0]
        U = []
        for k, f in enumerate(self.factors):
            Daa, Dab, Dbb, ya, yb = f.information_blocks()
            D[k] = D[k] + Daa
            D[k + 1] = D[k + 1] + Dbb
            eta[k] = eta[k] + ya
            eta[k + 1] = eta[k + 1] + yb
            U.append(Dab)
        return [symmetrize(d) for d in D], U, eta

    def dense(self) -> tuple[Array, Array]:
        """The full information matrix and vector (for tests and small windows)."""
        D, U, eta = self.blocks()
        m, n = len(D), self.n
        Om = np.zeros((m * n, m * n))
        for k in range(m):
            Om[k * n:(k + 1) * n, k * n:(k + 1) * n] = D[k]
        for k in range(m - 1):
            Om[k * n:(k + 1) * n, (k + 1) * n:(k + 2) * n] = U[k]
            Om[(k + 1) * n:(k + 2) * n, k * n:(k + 1) * n] = U[k].T
        return Om, np.concatenate(eta)
