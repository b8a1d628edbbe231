"""The consistency test without the smoother's covariance pass (2026-11-28): the covariances
before a message enter only two threshold tests, which bounds on them decide
(TrajectoryInformation.covariance_bounds, guard._thresholds_from_bounds), the exact covariances
computed only when they do not; the smoothed means after a message kept for the next one.

Checked against independent references: the bounds against the window's joint covariance from a
dense solve (numpy.linalg), the verdicts and statistics against the test with the exact smoothed
covariances (the code path of before, still in the library: add_information_moments with
exact_covariances=True and split_blocks), on random messages that include the boundary cases
(negligible directions near the threshold, values out of the range of their information,
removals, blocks between two states)."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from dfusion.estimation.delayed_state import CovarianceBounds, DelayedStateEIF
from dfusion.fusion.guard import NEGLIGIBLE, block_eigen, information_statistic, split_blocks
from dfusion.fusion.quarantine import GuardedLinks
from dfusion.models import ConstantVelocity, PositionSensor


def _filter(seed: int, states: int = 12) -> DelayedStateEIF:
    """A filter with measurements at most states and a few late ones (the same for a seed)."""
    rng = np.random.default_rng(seed)
    f = DelayedStateEIF(ConstantVelocity(2, q=0.3), window=100)
    f.initialize(0.0, rng.normal(size=4), np.diag([2.0, 2.0, 0.5, 0.5]))
    sensor = PositionSensor(2, 0.6)
    for k in range(1, states):
        t = round(0.1 * k, 9)
        f.predict(t)
        if rng.random() < 0.7:
            f.update(t, rng.normal(size=2) + [t, 0.0], sensor)
        if k > 3 and rng.random() < 0.3:
            s = round(0.1 * int(rng.integers(1, k)), 9)
            f.update(s, rng.normal(size=2) + [s, 0.0], sensor)
    return f


def _dense_covariance(f: DelayedStateEIF) -> np.ndarray:
    Om, _ = f.dense_information()
    return np.linalg.solve(Om, np.eye(Om.shape[0]))


def _psd(A: np.ndarray, scale: float) -> bool:
    return bool(np.linalg.eigvalsh(0.5 * (A + A.T)).min() >= -1e-10 * scale)


@pytest.mark.parametrize("seed", range(6))
def test_covariance_bounds_enclose_the_joint_marginals_of_a_dense_solve(seed):
    """lower <= Sigma_kk <= upper in the Loewner order for every window state, Sigma the inverse
    of the window's dense information matrix; both bounds exact at the newest state."""
    f = _filter(seed)
    tr = f._traj
    m = len(f)
    idx = list(range(m))
    tr.smoothed_means(0)
    lower, upper = tr.covariance_bounds(idx)
    S = _dense_covariance(f)
    n = f.n
    for k in idx:
        Skk = S[k * n:(k + 1) * n, k * n:(k + 1) * n]
        scale = float(np.abs(Skk).max())
        assert _psd(Skk - lower[k], scale) and _psd(upper[k] - Skk, scale)
        assert not np.allclose(lower[k], upper[k]) or k == m - 1
    np.testing.assert_allclose(lower[-1], S[-n:, -n:], rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(lower[-1], upper[-1])


def _message(rng, f: DelayedStateEIF, P_exact: list[np.ndarray] | None = None) -> list:
    """A random message: 1 to 6 blocks at window states or between two, of rank 0 to 4; some with
    a value out of the range of their information, some removing information, some with one
    direction of information right at the negligible threshold (given the exact covariances)."""
    times = f.times
    blocks = []
    for s in rng.choice(len(times), size=min(int(rng.integers(1, 7)), len(times)), replace=False):
        t = float(times[s]) + (0.05 if rng.random() < 0.2 and s < len(times) - 1 else 0.0)
        kind = rng.random()
        r = int(rng.integers(1, 5))
        A = rng.normal(size=(r, 4)) * rng.uniform(0.3, 3.0)
        L = A.T @ A
        x = rng.normal(size=4) * (1.0 if rng.random() < 0.5 else 10.0)
        y = L @ x
        if kind < 0.1:                       # removal: an indefinite difference new - old
            L = L - 1.05 * np.outer(A[0], A[0])
            y = L @ x
        elif kind < 0.2:                     # y outside the range of L
            v = np.linalg.svd(A)[2][-1] if r < 4 else None
            if v is not None:
                y = y + rng.choice([1e-9, 1e-3, 1.0]) * v
        elif kind < 0.3:                     # no information, a value anyway
            L = np.zeros((4, 4))
            y = rng.choice([0.0, 1e-12, 1.0]) * rng.normal(size=4)
        blocks.append((round(t, 9), L, y))
    return blocks


def _near_threshold(rng, f: DelayedStateEIF) -> list:
    """Blocks of rank 1 whose signal l v^T P0 v is NEGLIGIBLE times (1 +- 1e-6), P0 the exact
    smoothed covariance, at a state away from the newest (where the bounds differ): the bounds
    cannot decide them."""
    k = int(rng.integers(0, len(f) - 2))
    t = float(f.times[k])
    _, P = f.estimate(t)
    v = rng.normal(size=4)
    v /= np.linalg.norm(v)
    lam = NEGLIGIBLE / float(v @ P @ v) * (1.0 + rng.choice([-1e-6, 1e-6]))
    L = lam * np.outer(v, v)
    return [(t, L, L @ rng.normal(size=4)), (float(f.times[-1]), np.eye(4), rng.normal(size=4))]


def _exact_test(f: DelayedStateEIF, entries: list) -> tuple[float, int]:
    """The test with the exact smoothed covariances and a decomposition per call (before)."""
    eigen = block_eigen(entries[0][1]) if len(entries) == 1 else None
    add, other = split_blocks(entries, eigen)
    if other:
        f.add_information_batch(other, validate=False)
    if not add:
        return 0.0, 0
    mu0, P0, mu1 = f.add_information_moments(add, exact_covariances=True)
    return information_statistic(add, mu0, P0, mu1, eigen)


def _bounded_test(f: DelayedStateEIF, entries: list) -> tuple[float, int]:
    """The test as a node does it now (FusionNode._add_tested, on this filter)."""
    stat, dof, _ = GuardedLinks._add_tested(SimpleNamespace(filter=f), entries)
    return stat, dof


@pytest.mark.parametrize("seed", range(8))
def test_bounded_test_gives_the_verdicts_and_statistics_of_the_exact_one(seed, monkeypatch):
    """Two copies of a filter receive the same 12 random messages (boundary cases included), one
    tested with the exact smoothed covariances, one with bounds: the same degrees of freedom,
    statistics equal to rounding (bit for bit when more than one block is tested), the same
    verdicts, and the same filter afterwards, bit for bit. Messages whose blocks sit at the
    negligible threshold are decided by the exact covariances (the fallback runs) unless the
    bounds are tight enough there."""
    fallbacks = []
    exact = CovarianceBounds.exact
    monkeypatch.setattr(CovarianceBounds, "exact", lambda self: fallbacks.append(1) or exact(self))
    rng = np.random.default_rng(seed + 500)
    a, b = _filter(seed), _filter(seed)
    near = 0   # messages at the threshold decided by the exact covariances (where the bounds are not tight)
    for i in range(12):
        t = round(float(a.times[-1]) + 0.1, 9)
        a.predict(t)
        b.predict(t)
        msg = _near_threshold(rng, a) if i % 4 == 3 else _message(rng, a)
        before = len(fallbacks)
        try:
            ref = _exact_test(a, msg)
        except Exception as e:   # (an indefinite belief: both must refuse it alike)
            with pytest.raises(type(e)):
                _bounded_test(b, msg)
            continue
        got = _bounded_test(b, msg)
        assert got[1] == ref[1]
        if math.isinf(ref[0]):
            assert math.isinf(got[0])
        else:
            assert got[0] == pytest.approx(ref[0], rel=1e-12, abs=1e-12)
        near += (i % 4 == 3) and len(fallbacks) > before
        Oa, ea = a.dense_information()
        Ob, eb = b.dense_information()
        np.testing.assert_array_equal(Oa, Ob)
        np.testing.assert_array_equal(ea, eb)
        np.testing.assert_array_equal(a.estimate()[0], b.estimate()[0])
    assert near >= 1, "blocks at the threshold must be decided by the exact covariances"


def test_out_of_range_values_fail_with_bounds_as_with_the_exact_covariances():
    """A value outside the range of its information by more than rounding: infinite statistic, the
    same degrees of freedom both ways; by a rounding error: a finite one."""
    for scale, inf in ((1.0, True), (1e-13, False)):
        a, b = _filter(3), _filter(3)
        e1 = np.array([1.0, 0.0, 0.0, 0.0])
        L = np.outer(e1, e1)
        y = L @ np.ones(4) + scale * np.array([0.0, 1.0, 0.0, 0.0])
        msg = [(0.3, L, y), (0.5, 2.0 * L, 2.0 * L @ np.ones(4))]
        ref, got = _exact_test(a, msg), _bounded_test(b, msg)
        assert math.isinf(ref[0]) == math.isinf(got[0]) == inf
        assert ref[1] == got[1]


@pytest.mark.parametrize("seed", range(3))
def test_kept_smoothed_means_equal_a_fresh_pass_bit_for_bit(seed):
    """smoothed_means reads the means it kept, or continues their recursion to older states: the
    same bits as a pass from the newest state on an identical filter; a change drops them."""
    a, b = _filter(seed), _filter(seed)
    m = len(a)
    tr = a._traj
    for k in (m - 3, 2, 5, 0):
        fresh = _filter(seed)._traj.smoothed_means(k)
        got = tr.smoothed_means(k)
        assert len(got) == len(fresh) == m - k
        for x, y in zip(got, fresh):
            np.testing.assert_array_equal(x, y)
    L = np.eye(4)
    a.add_information_batch([(0.4, L, np.ones(4))], validate=False)
    b.add_information_batch([(0.4, L, np.ones(4))], validate=False)
    for x, y in zip(a._traj.smoothed_means(1), b._traj.smoothed(1)[0]):
        np.testing.assert_array_equal(x, y)
    # the smoothed moments of the whole window agree with the means kept
    means, _ = b._traj.smoothed(0)
    for x, y in zip(a._traj.smoothed_means(0), means):
        np.testing.assert_array_equal(x, y)
