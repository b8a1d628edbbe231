"""The scalar path of a small state (dfusion.estimation.scalar) against the numpy path and exact arithmetic.

The kernels compute on Python floats what the numpy path computes with LAPACK: the results may
differ by rounding only. References: the numpy path itself (TrajectoryInformation with the scalar
path off), and exact rational arithmetic (fractions.Fraction) of the same formulas. Bad input
(an information that makes the covariance indefinite, NaN, inf) is refused exactly as by the
numpy path: the same exception and message, and nothing changed.
"""
from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from dfusion.errors import NotPositiveDefiniteError
from dfusion.estimation import DelayedStateEIF, TrajectoryInformation, scalar
from dfusion.estimation import trajectory as trajectory_module
from dfusion.models import ConstantVelocity, PositionSensor


def spd(rng: np.random.Generator, n: int, cond: float, rank: int | None = None, spread: float = 0.0) -> np.ndarray:
    """A random symmetric PSD matrix with eigenvalues spread log-uniformly over ``cond`` (``rank`` of them)."""
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    ev = np.logspace(0.0, -np.log10(cond), n) * 10.0 ** rng.uniform(-spread, spread)
    if rank is not None:
        ev[rank:] = 0.0
    A = Q @ np.diag(ev) @ Q.T
    return 0.5 * (A + A.T)


def exact_fold(Pp: np.ndarray, L: np.ndarray, mp: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(I + P L)^-1 [P | m + P y]`` in exact rational arithmetic (Gauss-Jordan), then the
    covariance symmetrized: the fold of dfusion.estimation.scalar without rounding."""
    n = len(mp)
    F = [[Fraction(float(v)) for v in row] for row in Pp.tolist()]
    Lf = [[Fraction(float(v)) for v in row] for row in L.tolist()]
    M = [[sum(F[i][k] * Lf[k][j] for k in range(n)) + (1 if i == j else 0) for j in range(n)] for i in range(n)]
    rhs = [F[i] + [Fraction(float(mp[i])) + sum(F[i][k] * Fraction(float(y[k])) for k in range(n))] for i in range(n)]
    A = [M[i] + rhs[i] for i in range(n)]
    for c in range(n):
        p = next(i for i in range(c, n) if A[i][c] != 0)
        A[c], A[p] = A[p], A[c]
        A[c] = [v / A[c][c] for v in A[c]]
        for i in range(n):
            if i != c and A[i][c] != 0:
                A[i] = [a - A[i][c] * b for a, b in zip(A[i], A[c])]
    X = np.array([[float(v) for v in row[n:]] for row in A])
    return X[:, n], 0.5 * (X[:, :n] + X[:, :n].T)


def general_and_scalar(n: int, mp, Pp, L, y):
    """The fold of one state by the numpy path and by the scalar path."""
    out = []
    for scalar_on in (False, True):
        tr = TrajectoryInformation(np.zeros(n), np.eye(n))
        tr._scalar = scalar_on
        tr.L[0], tr.y[0] = L, y
        out.append(tr._filtered(0, mp, Pp))
    return out


def rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


EPS = np.finfo(float).eps


@pytest.mark.parametrize("n", range(1, scalar.MAX_N + 1))
@pytest.mark.parametrize("cond", [1.0, 1e4, 1e8])
@pytest.mark.parametrize("spread", [0.0, 1.0, 3.0])
def test_fold_agrees_with_the_numpy_path_and_exact_arithmetic(n, cond, spread):
    """Random P^- and L (full rank and rank n/2) with condition numbers up to ``cond``, their
    scales ``10^[-spread, spread]`` apart. Where ``I + P^- L`` is well conditioned (``spread``
    0 or 1: ``kappa`` below 100) both paths agree to 1e-12 (measured: a few 1e-15); where
    it is not (``spread`` 3: ``kappa`` up to 4e5) each path's own rounding error grows as
    ``kappa * eps`` (measured: LAPACK up to 9e-12 from the exact result, the scalar path up
    to 2e-11), and the scalar path must stay as close to the exact result as LAPACK."""
    rng = np.random.default_rng(1000 * n + 10 * int(np.log10(cond)) + int(spread))
    worst_gen = worst_sc = worst_pair = kappa = 0.0
    for trial in range(40):
        Pp = spd(rng, n, cond, spread=spread)
        L = spd(rng, n, cond, rank=None if trial % 2 else max(1, n // 2), spread=spread)
        mp, y = rng.normal(size=n) * 10, rng.normal(size=n) * 10
        gen, sc = general_and_scalar(n, mp, Pp, L, y)
        ex_mean, ex_cov = exact_fold(Pp, L, mp, y)
        np.testing.assert_array_equal(sc.cov, sc.cov.T)   # exactly symmetric, as the numpy path's
        assert sc.pred_mean is mp and sc.pred_cov is Pp
        kappa = max(kappa, float(np.linalg.cond(np.eye(n) + Pp @ L)))
        worst_pair = max(worst_pair, rel(sc.cov, gen.cov), rel(sc.mean, gen.mean))
        worst_gen = max(worst_gen, rel(gen.cov, ex_cov), rel(gen.mean, ex_mean))
        worst_sc = max(worst_sc, rel(sc.cov, ex_cov), rel(sc.mean, ex_mean))
    if kappa < 100:
        assert worst_pair < 1e-12
        assert worst_sc < 1e-12
    else:
        assert worst_pair < 16 * EPS * kappa
        assert worst_sc < 8 * EPS * kappa
    assert worst_sc <= 10 * worst_gen + 1e-14   # no further from the exact result than LAPACK


@pytest.mark.parametrize("n", range(1, scalar.MAX_N + 1))
def test_predict_kernel_agrees_with_numpy(n):
    rng = np.random.default_rng(n)
    predict = scalar.predict_kernel(n)
    for cond in (1.0, 1e4, 1e8):
        F = rng.normal(size=(n, n)) + np.eye(n)
        Q, P = spd(rng, n, cond), spd(rng, n, cond)
        c, m = rng.normal(size=n), rng.normal(size=n)
        mean, cov = predict(F.tolist(), Q.tolist(), c.tolist(), m.tolist(), P.tolist())
        # the reference in exact arithmetic
        Fe = [[Fraction(v) for v in r] for r in F.tolist()]
        Pe = [[Fraction(v) for v in r] for r in P.tolist()]
        FP = [[sum(Fe[i][k] * Pe[k][j] for k in range(n)) for j in range(n)] for i in range(n)]
        ref = np.array([[float(sum(FP[i][k] * Fe[j][k] for k in range(n)) + Fraction(Q[i, j])) for j in range(n)]
                        for i in range(n)])
        cov = np.array(cov)
        np.testing.assert_array_equal(cov, cov.T)
        assert rel(cov, ref) < 1e-13
        assert rel(np.array(mean), F @ m + c) < 1e-13


def run_filter(scalar_on: bool, seed: int, monkeypatch) -> list[tuple[np.ndarray, np.ndarray]]:
    monkeypatch.setattr(trajectory_module, "_SCALAR_MAX_N", scalar.MAX_N if scalar_on else 0)
    rng = np.random.default_rng(seed)
    f = DelayedStateEIF(ConstantVelocity(2, 0.1), window=10)
    f.initialize(0.0, np.zeros(4), np.eye(4))
    sensor = PositionSensor(2, 0.5)
    out = []
    t = 0.0
    for step in range(60):
        t = round(t + 0.1, 9)
        f.predict(t)
        f.update(t, rng.normal(size=2) + step * 0.1, sensor)
        if step % 7 == 3:   # a late measurement: the forward pass from an older state
            f.update(round(t - 0.3, 9), rng.normal(size=2), sensor)
        if step % 11 == 5:   # information between two states (inserted) and ill-conditioned
            f.add_information(round(t - 0.05, 9), spd(rng, 4, 1e8), rng.normal(size=4))
        out.append(f.estimate())
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_the_filter_gives_the_numpy_paths_estimates(seed, monkeypatch):
    general = run_filter(False, seed, monkeypatch)
    fast = run_filter(True, seed, monkeypatch)
    for (mg, Pg), (ms, Ps) in zip(general, fast):
        assert rel(ms, mg) < 1e-12 and rel(Ps, Pg) < 1e-12


def bad_inputs(n: int):
    L_neg = -10.0 * np.eye(n)   # with P = I: the covariance -I/9, not positive definite
    L_nan = np.eye(n)
    L_nan[0, 0] = np.nan
    L_inf = np.eye(n)
    L_inf[n - 1, n - 1] = np.inf
    y = np.ones(n)
    y_nan = y.copy()
    y_nan[0] = np.nan
    return [(L_neg, y), (-np.eye(n) * 0.5, y), (L_nan, y), (L_inf, y), (np.eye(n), y_nan)]


@pytest.mark.filterwarnings("ignore::RuntimeWarning")   # (the numpy path's matmul on NaN, as before)
@pytest.mark.parametrize("n", [1, 2, scalar.MAX_N])
def test_bad_information_is_refused_as_by_the_numpy_path(n):
    mp, Pp = np.ones(n), np.eye(n)
    for i, (L, y) in enumerate(bad_inputs(n)):
        errors = []
        for scalar_on in (False, True):
            tr = TrajectoryInformation(np.zeros(n), np.eye(n))
            tr._scalar = scalar_on
            tr.L[0], tr.y[0] = L, y
            try:
                got = tr._filtered(0, mp, Pp)
                errors.append(("ok", got.mean.tolist(), got.cov.tolist()))
            except NotPositiveDefiniteError as exc:
                errors.append(("error", str(exc)))
        if i == 1:   # -L/2 with P = I: the covariance 2 I is still proper, on both paths
            assert errors[0][0] == errors[1][0] == "ok"
            np.testing.assert_allclose(errors[1][2], errors[0][2], rtol=1e-12)
        else:   # refused, with the same error
            assert errors[0][0] == "error" and errors[0] == errors[1]
    # the kernel itself refuses (None): the numpy path decides
    fold = scalar.fold_kernel(n)
    for L, y in bad_inputs(n)[2:]:
        assert fold(Pp.tolist(), L.tolist(), mp.tolist(), y.tolist()) is None


def test_a_refused_update_changes_nothing(monkeypatch):
    """An indefinite difference (validate=False, as a fusion node's replacement) that leaves the
    newest covariance indefinite: the same error on both paths and the filter as before."""
    results = []
    for scalar_on in (False, True):
        monkeypatch.setattr(trajectory_module, "_SCALAR_MAX_N", scalar.MAX_N if scalar_on else 0)
        f = DelayedStateEIF(ConstantVelocity(2, 0.1), window=5)
        f.initialize(0.0, np.zeros(4), np.eye(4))
        for k in range(1, 8):
            f.predict(k * 0.1)
            f.update(k * 0.1, np.array([k * 0.01, 0.0]), PositionSensor(2, 0.5))
        before = f.estimate()
        with pytest.raises(NotPositiveDefiniteError) as err, f.transaction():
            f.add_information_batch([(0.7, -50.0 * np.eye(4), np.zeros(4))], validate=False)
            f.estimate()
        after = f.estimate()
        np.testing.assert_array_equal(after[0], before[0])
        np.testing.assert_array_equal(after[1], before[1])
        results.append((str(err.value), before))
    assert results[0][0] == results[1][0]
    assert rel(results[1][1][1], results[0][1][1]) < 1e-12


def test_kernels_refuse_other_dimensions():
    with pytest.raises(ValueError, match="scalar path takes 1 to"):
        scalar.fold_kernel(scalar.MAX_N + 1)
    with pytest.raises(ValueError, match="scalar path takes 1 to"):
        scalar.predict_kernel(0)


def test_a_guarded_hop_gives_the_numpy_paths_results(monkeypatch):
    """Two fusion nodes (the hop of benchmarks/transport.py: the receiver guarded, messages of one
    block, acknowledgements, settle): the receiver's estimates, guard counters and statistics
    with the scalar path against the numpy path."""
    from dfusion.fusion import FusionNode, GuardConfig

    motion, sensor = ConstantVelocity(2, 0.1), PositionSensor(2, 0.5)
    runs = []
    for scalar_on in (False, True):
        monkeypatch.setattr(trajectory_module, "_SCALAR_MAX_N", scalar.MAX_N if scalar_on else 0)
        rng = np.random.default_rng(5)
        a = FusionNode("a", ["b"], motion, window=10, prior=(0.0, np.zeros(4), np.eye(4)), guard=GuardConfig())
        b = FusionNode("b", ["a"], motion, window=10, prior=(0.0, np.zeros(4), np.eye(4)), guard=GuardConfig())
        out = []
        for i in range(1, 80):
            t = round(i * 0.1, 9)
            a.predict(t)
            a.update(t, np.array([0.3 * t, -0.2 * t]) + rng.normal(0.0, 0.5, 2), sensor)
            data = a.message_to("b", sent_at=t)
            b.predict(t)
            b.receive(data)
            out.append(b.estimate())
            a.receive(b.message_to("a", sent_at=t))
            a.settle()
            b.settle()
        runs.append((out, b.guard.summary(), b.stats.messages_received, b.stats.messages_rejected))
    (general, g_sum, g_rx, g_rej), (fast, f_sum, f_rx, f_rej) = runs
    assert (g_rx, g_rej) == (f_rx, f_rej)
    assert f_sum.pop("nis_mean") == pytest.approx(g_sum.pop("nis_mean"), rel=1e-12)   # (a statistic: rounding)
    assert f_sum == g_sum and g_sum["tests"] > 70   # the same tests, failures and quarantines
    for eg, ef in zip(general, fast):
        assert rel(ef[0], eg[0]) < 1e-12 and rel(ef[1], eg[1]) < 1e-12
    n = scalar.MAX_N + 1   # a larger state takes the numpy path
    assert not TrajectoryInformation(np.zeros(n), np.eye(n))._scalar
    assert TrajectoryInformation(np.zeros(n - 1), np.eye(n - 1))._scalar
