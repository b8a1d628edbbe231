"""DelayedStateEIF against independent references: filterpy's KalmanFilter and
RTS smoother, and brute-force dense linear algebra."""
from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dfusion.estimation import DelayedStateEIF
from dfusion.errors import (
    DfusionError,
    NonFiniteError,
    NotInitializedError,
    NotPositiveDefiniteError,
    OutsideWindowError,
    ShapeError,
    TimeError,
)
from dfusion.models import ConstantVelocity, PositionSensor

Q_PSD = 0.3


def cv_F(dt: float, d: int) -> np.ndarray:
    """Closed-form constant-velocity transition, written independently of dfusion."""
    F = np.eye(2 * d)
    F[:d, d:] = dt * np.eye(d)
    return F


def cv_Q(dt: float, d: int, q: float = Q_PSD) -> np.ndarray:
    I = np.eye(d)
    return q * np.block([[dt**3 / 3 * I, dt**2 / 2 * I], [dt**2 / 2 * I, dt * I]])


def kalman_reference(t0, x0, P0, events, t_end, d, std, grid=()):
    """filterpy KalmanFilter over the union of event times, in time order.

    ``events`` is a list of ``(t, z)``; returns the filter at ``t_end`` and the
    per-step arrays needed by ``rts_smoother``.
    """
    n = 2 * d
    kf = KalmanFilter(dim_x=n, dim_z=d)
    kf.x = np.array(x0, float).reshape(n, 1)
    kf.P = np.array(P0, float)
    kf.H = np.hstack([np.eye(d), np.zeros((d, d))])
    kf.R = std**2 * np.eye(d)
    times = sorted({t for t, _ in events} | {t_end} | set(np.asarray(grid).tolist()))
    Xs, Ps, Fs, Qs, ts = [kf.x.ravel().copy()], [kf.P.copy()], [np.eye(n)], [np.zeros((n, n))], [t0]
    t_prev = t0
    by_time: dict[float, list] = {}
    for t, z in events:
        by_time.setdefault(t, []).append(z)
    for t in times:
        dt = t - t_prev
        if dt > 0:
            kf.F, kf.Q = cv_F(dt, d), cv_Q(dt, d)
            kf.predict()
        for z in by_time.get(t, []):
            kf.update(np.asarray(z, float).reshape(d, 1))
        if dt > 0:
            Xs.append(kf.x.ravel().copy())
            Ps.append(kf.P.copy())
            Fs.append(cv_F(dt, d))
            Qs.append(cv_Q(dt, d))
            ts.append(t)
        else:  # measurement at t0 itself
            Xs[-1], Ps[-1] = kf.x.ravel().copy(), kf.P.copy()
        t_prev = t
    return kf, np.array(ts), np.array(Xs), np.array(Ps), np.array(Fs), np.array(Qs)


def assert_close_rel(a, b, rtol):
    a, b = np.asarray(a), np.asarray(b)
    scale = max(np.max(np.abs(b)), 1e-12)
    assert np.max(np.abs(a - b)) <= rtol * scale, np.max(np.abs(a - b)) / scale


def make_filter(d=2, window=400, x0=None, P0=None):
    f = DelayedStateEIF(ConstantVelocity(dim=d, q=Q_PSD), window=window)
    n = 2 * d
    f.initialize(0.0, np.zeros(n) if x0 is None else x0, np.eye(n) * 4 if P0 is None else P0)
    return f


def scenario(seed, d=2, steps=60, dt=0.1, n_meas=80, max_delay=1.0):
    """Grid predictions plus measurements at irregular times, arriving late and shuffled."""
    rng = np.random.default_rng(seed)
    grid = np.round(dt * np.arange(1, steps + 1), 12)
    t_meas = np.sort(rng.uniform(0.0, grid[-1], n_meas))
    t_meas[::5] = grid[rng.integers(0, steps, size=len(t_meas[::5]))]  # some on grid points
    zs = rng.normal(0, 2.0, size=(n_meas, d))
    arrival = t_meas + rng.uniform(0, max_delay, n_meas)
    return grid, list(zip(t_meas.tolist(), zs)), arrival


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_latest_equals_kalman_filter_with_late_out_of_order_measurements(d, seed):
    grid, meas, arrival = scenario(seed, d=d)
    std = 0.7
    sensor = PositionSensor(dim=d, std=std)
    f = make_filter(d)
    pending = sorted(range(len(meas)), key=lambda i: arrival[i])
    j = 0
    for t in grid:
        f.predict(t)
        # deliver every measurement that has "arrived" by now, in arrival order
        while j < len(pending) and arrival[pending[j]] <= t:
            tm, z = meas[pending[j]]
            f.update(tm, z, sensor)
            j += 1
    for i in pending[j:]:
        f.update(meas[i][0], meas[i][1], sensor)
    kf, *_ = kalman_reference(0.0, np.zeros(2 * d), np.eye(2 * d) * 4, meas, grid[-1], d, std)
    m, P = f.estimate()
    assert_close_rel(m, kf.x.ravel(), 1e-9)
    assert_close_rel(P, kf.P, 1e-9)


@pytest.mark.parametrize("window", [400, 25])
def test_window_estimates_equal_rts_smoother(window):
    grid, meas, _ = scenario(3, n_meas=40)
    std = 0.5
    sensor = PositionSensor(dim=2, std=std)
    f = make_filter(2, window=window)
    events = sorted(meas, key=lambda e: e[0])
    j = 0
    for t in grid:
        f.predict(t)
        while j < len(events) and events[j][0] <= t:
            f.update(events[j][0], events[j][1], sensor)
            j += 1
    kf, ts, Xs, Ps, Fs, Qs = kalman_reference(0.0, np.zeros(4), np.eye(4) * 4, meas, grid[-1], 2, std, grid)
    xs, ps, _, _ = kf.rts_smoother(Xs.reshape(len(Xs), 4, 1), Ps, Fs, Qs)
    window_times = f.times
    assert len(window_times) == min(window, len(ts))
    for t in window_times:
        k = int(np.argmin(np.abs(ts - t)))
        assert abs(ts[k] - t) < 1e-9
        m, P = f.estimate(t)
        assert_close_rel(m, xs[k].ravel(), 1e-8)
        assert_close_rel(P, ps[k], 1e-8)
    # the whole trajectory at once agrees as well
    times, means, covs = f.trajectory()
    for t, m, P in zip(times, means, covs):
        k = int(np.argmin(np.abs(ts - t)))
        assert_close_rel(m, xs[k].ravel(), 1e-8)
        assert_close_rel(P, ps[k], 1e-8)


def test_estimate_between_states_is_prediction_from_smoothed_joint():
    f = make_filter(2)
    sensor = PositionSensor(2, 0.4)
    f.predict(1.0)
    f.update(1.0, [1.0, 2.0], sensor)
    f.predict(2.0)
    f.update(2.0, [2.5, 2.0], sensor)
    before = f.dense_information()
    m, P = f.estimate(1.37)
    # the filter itself is untouched
    after = f.dense_information()
    np.testing.assert_array_equal(before[0], after[0])
    assert len(f) == 3
    kf, *_ = kalman_reference(0.0, np.zeros(4), np.eye(4) * 4,
                              [(1.0, [1.0, 2.0]), (2.0, [2.5, 2.0])], 2.0, 2, 0.4)
    # reference: insert the state for real in a second filter (an update with no information)
    g = make_filter(2)
    g.predict(1.0)
    g.update(1.0, [1.0, 2.0], sensor)
    g.predict(2.0)
    g.update(2.0, [2.5, 2.0], sensor)
    g.add_information(1.37, np.zeros((4, 4)), np.zeros(4))
    m2, P2 = g.estimate(1.37)
    assert_close_rel(m, m2, 1e-10)
    assert_close_rel(P, P2, 1e-10)
    assert_close_rel(f.estimate()[0], kf.x.ravel(), 1e-10)


def dense_marginals(Omega, eta, n):
    """Brute force: invert the full information matrix."""
    P = np.linalg.inv(Omega)
    mu = P @ eta
    m = len(eta) // n
    return [mu[k * n:(k + 1) * n] for k in range(m)], [P[k * n:(k + 1) * n, k * n:(k + 1) * n] for k in range(m)]


def test_marginalization_leaves_remaining_marginals_unchanged():
    long = make_filter(2, window=1000)
    short = make_filter(2, window=12)
    sensor = PositionSensor(2, 0.3)
    rng = np.random.default_rng(5)
    for k in range(1, 40):
        t = 0.25 * k
        z = rng.normal(size=2)
        for f in (long, short):
            f.predict(t)
            f.update(t, z, sensor)
    assert len(short) == 12 and short.marginalized == 40 - 12
    Om, eta = long.dense_information()
    means, covs = dense_marginals(Om, eta, 4)
    long_times = long.times
    for t in short.times:
        k = int(np.argmin(np.abs(long_times - t)))
        m, P = short.estimate(t)
        assert_close_rel(m, means[k], 1e-9)
        assert_close_rel(P, covs[k], 1e-9)
    # the short window's joint equals the dense marginal of the long one's joint
    Om_s, _ = short.dense_information()
    P_long = np.linalg.inv(Om)
    tail = P_long[-12 * 4:, -12 * 4:]
    assert_close_rel(np.linalg.inv(Om_s), tail, 1e-9)


def test_horizon_in_seconds():
    f = DelayedStateEIF(ConstantVelocity(2, 0.1), window=None, horizon=1.0)
    f.initialize(0.0, np.zeros(4), np.eye(4))
    for k in range(1, 31):
        f.predict(0.1 * k)
    assert f.oldest_time >= f.latest_time - 1.0 - 1e-9
    assert len(f) == 11
    with pytest.raises(OutsideWindowError):
        f.update(1.5, [0.0, 0.0], PositionSensor(2, 1.0))


def test_block_tridiagonal_storage_matches_dense():
    f = make_filter(2, window=8)
    s = PositionSensor(2, 1.0)
    for k in range(1, 10):
        f.predict(0.3 * k)
        f.update(0.3 * k - 0.1, [k, -k], s)
    times, D, U, eta = f.information()
    Om, eta_dense = f.dense_information()
    m, n = len(times), 4
    assert D.shape == (m, n, n) and U.shape == (m - 1, n, n)
    # only the tridiagonal blocks are non-zero
    for i in range(m):
        for j in range(m):
            block = Om[i * n:(i + 1) * n, j * n:(j + 1) * n]
            if abs(i - j) > 1:
                assert np.all(block == 0)
    np.testing.assert_array_equal(Om, Om.T)
    assert np.all(np.linalg.eigvalsh(Om) > 0)


# ---------------------------------------------------------------- rejection
class BadSensor(PositionSensor):
    def __init__(self, R):
        super().__init__(2, 1.0)
        self._bad = np.asarray(R, float)

    @property
    def R(self):
        return self._bad


def snapshot(f):
    Om, eta = f.dense_information()
    return f.times.copy(), Om.copy(), eta.copy(), f.marginalized


def assert_unchanged(f, snap):
    times, Om, eta, marg = snapshot(f)
    np.testing.assert_array_equal(times, snap[0])
    np.testing.assert_array_equal(Om, snap[1])
    np.testing.assert_array_equal(eta, snap[2])
    assert marg == snap[3]


def filled_filter(window=5):
    f = make_filter(2, window=window)
    s = PositionSensor(2, 0.5)
    for k in range(1, 8):
        f.predict(0.5 * k)
        f.update(0.5 * k, [k, 1.0], s)
    return f


@pytest.mark.parametrize(
    "call, exc",
    [
        (lambda f: f.update(3.0, [np.nan, 1.0], PositionSensor(2, 0.5)), NonFiniteError),
        (lambda f: f.update(3.0, [np.inf, 1.0], PositionSensor(2, 0.5)), NonFiniteError),
        (lambda f: f.update(3.0, [1.0, 1.0, 1.0], PositionSensor(2, 0.5)), ShapeError),
        (lambda f: f.update(3.0, [[1.0, 1.0], [1.0, 1.0]], PositionSensor(2, 0.5)), ShapeError),
        (lambda f: f.update(3.0, "ab", PositionSensor(2, 0.5)), ShapeError),
        (lambda f: f.update(0.1, [1.0, 1.0], PositionSensor(2, 0.5)), OutsideWindowError),
        (lambda f: f.update(9.0, [1.0, 1.0], PositionSensor(2, 0.5)), OutsideWindowError),
        (lambda f: f.update(float("nan"), [1.0, 1.0], PositionSensor(2, 0.5)), TimeError),
        (lambda f: f.update(2.75, [1.0, 1.0], BadSensor([[1.0, 0.0], [0.0, -1.0]])), NotPositiveDefiniteError),
        (lambda f: f.update(2.75, [1.0, 1.0], BadSensor([[1.0, 0.5], [0.0, 1.0]])), NotPositiveDefiniteError),
        (lambda f: f.update(2.75, [1.0, 1.0], BadSensor([[np.nan, 0.0], [0.0, 1.0]])), NonFiniteError),
        (lambda f: f.predict(2.0), OutsideWindowError),
        (lambda f: f.predict(3.5), OutsideWindowError),
        (lambda f: f.predict(4.0, u=[np.nan]), NonFiniteError),
        (lambda f: f.add_information(3.0, -np.eye(4), np.zeros(4)), NotPositiveDefiniteError),
        (lambda f: f.add_information(3.0, np.eye(3), np.zeros(3)), ShapeError),
        (lambda f: f.add_information(2.9, np.eye(4), np.full(4, np.nan)), NonFiniteError),
        (lambda f: f.estimate(0.2), OutsideWindowError),
        (lambda f: f.ensure_state(100.0), OutsideWindowError),
        (lambda f: f.initialize(0.0, np.zeros(4), -np.eye(4)), NotPositiveDefiniteError),
        (lambda f: f.initialize(0.0, np.zeros(3), np.eye(4)), ShapeError),
    ],
)
def test_rejected_input_leaves_filter_unchanged(call, exc):
    f = filled_filter()
    snap = snapshot(f)
    est = f.estimate()
    with pytest.raises(exc) as info:
        call(f)
    assert isinstance(info.value, DfusionError) and isinstance(info.value, ValueError)
    assert_unchanged(f, snap)
    m, P = f.estimate()
    np.testing.assert_array_equal(m, est[0])
    np.testing.assert_array_equal(P, est[1])


def test_failure_midway_rolls_back_insertion():
    """A sensor whose R fails validation after the state was inserted: nothing changes."""
    f = filled_filter(window=50)
    snap = snapshot(f)
    with pytest.raises(NotPositiveDefiniteError):
        f.update(2.25, [1.0, 1.0], BadSensor([[1.0, 0.0], [0.0, 0.0]]))
    assert_unchanged(f, snap)


def test_uninitialized_filter_raises():
    f = DelayedStateEIF(ConstantVelocity(2, 0.1), window=3)
    with pytest.raises(NotInitializedError):
        f.predict(1.0)
    with pytest.raises(NotInitializedError):
        f.estimate()
    with pytest.raises(ValueError):
        DelayedStateEIF(ConstantVelocity(2, 0.1), window=0)


# ---------------------------------------------------------------- property test
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    n_meas=st.integers(1, 30),
    max_delay=st.floats(0.0, 2.0),
    window=st.integers(40, 80),
)
def test_property_any_arrival_order_equals_time_order(seed, n_meas, max_delay, window):
    rng = np.random.default_rng(seed)
    dt = 0.1
    grid = np.round(dt * np.arange(1, 31), 12)
    t_meas = np.round(rng.uniform(0.0, grid[-1], n_meas), 6)
    zs = rng.normal(0, 3.0, size=(n_meas, 2))
    arrival = t_meas + rng.uniform(0, max_delay, n_meas)
    sensor = PositionSensor(2, 0.8)
    f = make_filter(2, window=window)
    order = np.argsort(arrival, kind="stable")
    j = 0
    for t in grid:
        f.predict(t)
        while j < n_meas and arrival[order[j]] <= t:
            f.update(t_meas[order[j]], zs[order[j]], sensor)
            j += 1
    for i in order[j:]:
        f.update(t_meas[i], zs[i], sensor)
    kf, *_ = kalman_reference(0.0, np.zeros(4), np.eye(4) * 4, list(zip(t_meas.tolist(), zs)), grid[-1], 2, 0.8)
    m, P = f.estimate()
    assert_close_rel(m, kf.x.ravel(), 1e-9)
    assert_close_rel(P, kf.P, 1e-9)


@pytest.mark.parametrize("seed", [3, 4])
def test_window_estimates_equal_rts_smoother_with_late_out_of_order_measurements(seed):
    """estimate(t) for every window time, measurements arriving late, shuffled, at
    irregular times (states inserted between grid states), against filterpy's RTS."""
    grid, meas, arrival = scenario(seed, n_meas=40, max_delay=1.0)
    std = 0.5
    sensor = PositionSensor(dim=2, std=std)
    f = make_filter(2, window=400)
    pending = sorted(range(len(meas)), key=lambda i: arrival[i])
    assert any(arrival[a] > arrival[b] and meas[a][0] < meas[b][0] for a, b in zip(pending[1:], pending))
    j = 0
    for t in grid:
        f.predict(t)
        while j < len(pending) and arrival[pending[j]] <= t:
            f.update(meas[pending[j]][0], meas[pending[j]][1], sensor)
            j += 1
    for i in pending[j:]:
        f.update(meas[i][0], meas[i][1], sensor)
    kf, ts, Xs, Ps, Fs, Qs = kalman_reference(0.0, np.zeros(4), np.eye(4) * 4, meas, grid[-1], 2, std, grid)
    xs, ps, _, _ = kf.rts_smoother(Xs.reshape(len(Xs), 4, 1), Ps, Fs, Qs)
    assert len(f.times) == len(ts)
    np.testing.assert_allclose(f.times, ts, rtol=0, atol=1e-9)
    for k, t in enumerate(f.times):
        m, P = f.estimate(t)
        assert_close_rel(m, xs[k].ravel(), 1e-8)
        assert_close_rel(P, ps[k], 1e-8)


def test_rejected_input_on_a_window_that_still_holds_the_first_state():
    """A time before the first state, a predict that does not advance, an estimate
    ahead of the newest state: refused, nothing changes."""
    f = make_filter(2, window=50)
    s = PositionSensor(2, 0.5)
    for k in range(1, 4):
        f.predict(0.5 * k)
        f.update(0.5 * k, [k, 1.0], s)
    assert f.oldest_time == 0.0 and f.marginalized == 0
    snap = snapshot(f)
    est = f.estimate()
    calls = [
        (lambda: f.update(-0.25, [1.0, 1.0], s), TimeError),
        (lambda: f.add_information(-1.0, np.eye(4), np.zeros(4)), TimeError),
        (lambda: f.predict(1.5), TimeError),
        (lambda: f.predict(0.7), TimeError),
        (lambda: f.estimate(1.6), TimeError),
        (lambda: f.estimate(-0.1), TimeError),
        (lambda: f.update(1.0, [1.0, 1.0], BadSensor([[1.0, 0.0], [0.0, 0.0]])), NotPositiveDefiniteError),
    ]
    for call, exc in calls:
        with pytest.raises(exc):
            call()
        assert_unchanged(f, snap)
        m, P = f.estimate()
        np.testing.assert_array_equal(m, est[0])
        np.testing.assert_array_equal(P, est[1])


def test_add_information_moments_returns_the_smoothed_moments_before_and_after():
    """The moments at the entries' times (one between two states: inserted) are the window
    estimates (checked against the RTS smoother above) before and after the same batch;
    trial() undoes everything done inside it."""
    def filled():
        rng = np.random.default_rng(3)
        g = make_filter()
        for k in range(1, 12):
            g.predict(0.1 * k)
            g.update(0.1 * k, rng.normal(size=2), PositionSensor(2, 0.7))
        return g

    rng = np.random.default_rng(8)
    entries = []
    for t in (0.3, 0.45, 0.9):
        A = rng.normal(size=(2, 4))
        L = A.T @ A
        entries.append((t, L, L @ rng.normal(size=4)))
    f, before, after = filled(), filled(), filled()
    before.ensure_state(0.45)
    after.add_information_batch(entries, validate=False)
    times = f.times.tolist()
    with f.trial():
        f.add_information_moments(entries)
        assert len(f) == 13
    assert f.times.tolist() == times
    assert_close_rel(f.estimate()[0], filled().estimate()[0], 0.0)
    mu0, P0, mu1 = f.add_information_moments(entries)
    for (t, _, _), m0, C0, m1 in zip(entries, mu0, P0, mu1):
        assert_close_rel(m0, before.estimate(t)[0], 1e-10)
        assert_close_rel(C0, before.estimate(t)[1], 1e-10)
        assert_close_rel(m1, after.estimate(t)[0], 1e-10)
    for t in (0.0, 0.45, 1.1):
        assert_close_rel(f.estimate(t)[0], after.estimate(t)[0], 1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_smoothed_moments_with_cached_gains_equal_the_dense_solve_after_every_change(seed):
    """The smoother gains are cached with the forward terms (trajectory.py): after any sequence of
    changes (new states, updates at the newest and at older states, inserted states, a batch
    tested and kept, one tried and undone, marginalized states) every window marginal equals
    the dense solve of the window's information (``Omega^-1``, ``Omega^-1 eta``)."""
    rng = np.random.default_rng(seed)
    f = make_filter(window=15)
    sensor = PositionSensor(2, 0.6)
    t = 0.0

    def check():
        Om, eta = f.dense_information()
        Sigma = np.linalg.solve(Om, np.eye(Om.shape[0]))
        mu = Sigma @ eta
        _, means, covs = f.trajectory()
        for k, (m, P) in enumerate(zip(means, covs)):
            assert_close_rel(m, mu[4 * k:4 * k + 4], 1e-8)
            assert_close_rel(P, Sigma[4 * k:4 * k + 4, 4 * k:4 * k + 4], 1e-8)

    for step in range(40):
        t = round(t + 0.1, 9)
        f.predict(t)
        op = rng.integers(5)
        times = f.times
        if op == 0:
            f.update(t, rng.normal(size=2) + [t, 0.0], sensor)
        elif op == 1:   # a late measurement at an older state, or between two states
            tm = float(times[rng.integers(len(times))]) - (0.05 if rng.random() < 0.5 and len(times) > 1 else 0.0)
            if tm >= times[0]:
                f.update(round(tm, 9), rng.normal(size=2) + [tm, 0.0], sensor)
        elif op in (2, 3):   # a tested batch, kept (2) or tried and undone (3)
            A = rng.normal(size=(2, 4))
            L = A.T @ A
            entries = [(float(s), L, L @ rng.normal(size=4)) for s in rng.choice(times, size=min(3, len(times)),
                                                                                  replace=False)]
            if op == 2:
                f.add_information_moments(entries)
            else:
                with f.trial():
                    f.add_information_moments(entries)
        else:
            f.estimate(float(times[rng.integers(len(times))]))
        check()
