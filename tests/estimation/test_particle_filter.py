"""Tests of the generic particle filter (dfusion.estimation), the occupancy grid (dfusion.maps)
and the WSN tracker (dfusion.localization).

References are independent of the code under test: numpy's weighted covariance,
a binary-search implementation of systematic resampling, an exact Liang-Barsky
segment/square clipping for the map, ``RSSISensor.h`` and ``RSSISensor.H``
(dfusion.models) for the likelihood and the linearized information.
"""
from __future__ import annotations

import numpy as np
import pytest

from dfusion.errors import NotInitializedError, ShapeError, ValidationError
from dfusion.estimation import InformationGaussian
from dfusion.models import RSSISensor
from dfusion.maps import NodeLattice
from dfusion.estimation import (
    effective_sample_size,
    ParticleDepletionError,
    ParticleFilter,
    project_psd_information,
    roughening_std,
    stratified_resample,
    systematic_counts,
    systematic_resample,
    weighted_mean_cov,
)
from dfusion.localization import WSNTracker


# --------------------------------------------------------------------------- references
def ref_systematic(w, u):
    """Textbook systematic resampling: binary search of each pointer (u + k) / N in the CDF."""
    w = np.asarray(w, float) / np.sum(w)
    n = len(w)
    cdf = np.cumsum(w)
    out = []
    for k in range(n):
        p = (u + k) / n
        i = int(np.searchsorted(cdf, p, side="right"))
        out.append(min(i, n - 1))
    return np.array(out)


def segment_box_overlap(a, b, lo, hi):
    """Parameter length of segment a->b inside the boxes ``(lo[k], hi[k])`` (Liang-Barsky clipping).

    ``lo`` and ``hi`` are ``(K, 2)``; returns ``(K,)`` values in [0, 1].
    """
    lo = np.atleast_2d(lo)
    hi = np.atleast_2d(hi)
    t0 = np.zeros(lo.shape[0])
    t1 = np.ones(lo.shape[0])
    d = b - a
    for ax in range(2):
        if abs(d[ax]) < 1e-15:
            inside = (lo[:, ax] < a[ax]) & (a[ax] < hi[:, ax])
            t1 = np.where(inside, t1, 0.0)
            continue
        ta, tb = (lo[:, ax] - a[ax]) / d[ax], (hi[:, ax] - a[ax]) / d[ax]
        t0 = np.maximum(t0, np.minimum(ta, tb))
        t1 = np.minimum(t1, np.maximum(ta, tb))
    return np.maximum(0.0, t1 - t0)


def ref_blocked(grid: NodeLattice, a, b, eps=1e-9):
    """Exact: does a->b overlap an occupied square (or leave the grid) over a positive length?

    Returns None when the answer hinges on a tangency (overlap length below ``eps``).
    """
    c = grid.cell
    lo_w = grid.origin - c / 2
    hi_w = grid.origin + (np.array(grid.shape) - 0.5) * c
    inside = segment_box_overlap(a, b, lo_w, hi_w)[0]  # leaving the grid counts as blocked
    if inside < 1.0 - 1e-6:
        return True
    if inside < 1.0 - eps:
        return None
    centres = grid.origin + c * np.argwhere(grid.occupied)
    best = segment_box_overlap(a, b, centres - c / 2, centres + c / 2).max(initial=0.0)
    if 0 < best < eps:
        return None
    return bool(best > 0)


def point_occupied(grid: NodeLattice, p):
    """Occupancy of one point by direct arithmetic (no grid method)."""
    return bool(points_occupied(grid, np.asarray(p, float)[None])[0])


def points_occupied(grid: NodeLattice, p):
    """Occupancy of points ``(..., 2)`` by direct arithmetic: nearest node, outside = occupied."""
    i = np.floor((p[..., 0] - grid.origin[0]) / grid.cell + 0.5)
    j = np.floor((p[..., 1] - grid.origin[1]) / grid.cell + 0.5)
    inside = (i >= 0) & (i < grid.shape[0]) & (j >= 0) & (j < grid.shape[1])
    out = np.ones(i.shape, bool)
    out[inside] = grid.occupied[i[inside].astype(int), j[inside].astype(int)]
    return out


def dense_crossing(grid: NodeLattice, a, b, n=400):
    """Brute force: does any of ``n`` evenly spaced points of each segment a[k]->b[k] hit an obstacle?"""
    t = np.linspace(0.0, 1.0, n)[None, :, None]
    return points_occupied(grid, a[:, None, :] + t * (b - a)[:, None, :]).any(axis=1)


def walled_grid():
    """12 m x 10 m room (0.25 m cells) with an outer wall, an inner wall with a door, and a block."""
    nx, ny = 49, 41
    occ = np.zeros((nx, ny), bool)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    occ[24, :] = True
    occ[24, 18:23] = False  # door at y in [4.5, 5.5]
    occ[8:14, 26:32] = True  # block
    return NodeLattice(occ, 0.25)


# --------------------------------------------------------------------------- generic filter
def test_ess_formula():
    rng = np.random.default_rng(0)
    w = rng.random(500) ** 3
    expected = w.sum() ** 2 / np.sum(w**2)  # Kong-Liu-Wong on unnormalized weights
    assert effective_sample_size(w) == pytest.approx(expected, rel=1e-12)
    assert effective_sample_size(np.log(w), log=True) == pytest.approx(expected, rel=1e-12)
    assert effective_sample_size(np.ones(40)) == pytest.approx(40)
    assert effective_sample_size(np.eye(1, 40)[0]) == pytest.approx(1)
    pf = ParticleFilter(rng.random((500, 2)), np.log(w))
    assert pf.ess == pytest.approx(expected, rel=1e-12)


def test_systematic_counts_within_one_of_expected_and_match_binary_search():
    rng = np.random.default_rng(1)
    for trial in range(50):
        n = int(rng.integers(2, 300))
        w = rng.random(n) ** rng.uniform(0.5, 8)
        w[rng.random(n) < 0.2] = 0.0
        if w.sum() == 0:
            w[0] = 1.0
        u = rng.random()
        counts = systematic_counts(w, u)
        nw = n * w / w.sum()
        assert counts.sum() == n
        assert np.all(counts >= np.floor(nw) - 1e-9) and np.all(counts <= np.ceil(nw) + 1e-9)
        assert np.all(np.abs(counts - nw) < 1)
        assert np.all(counts[w == 0] == 0)
        ref = np.bincount(ref_systematic(w, u), minlength=n)
        np.testing.assert_array_equal(counts, ref)


def test_systematic_resample_uses_generator_and_is_deterministic():
    w = np.random.default_rng(2).random(1000)
    a = systematic_resample(w, np.random.default_rng(7))
    b = systematic_resample(w, np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, ref_systematic(w, np.random.default_rng(7).random()))


def test_stratified_resampling_is_unbiased_and_keeps_the_distribution():
    rng = np.random.default_rng(3)
    n = 200
    w = rng.random(n) ** 4
    w /= w.sum()
    reps = 2000
    counts = np.zeros(n)
    for _ in range(reps):
        idx = stratified_resample(w, rng)
        assert idx.shape == (n,) and np.all(np.diff(idx) >= 0)
        c = np.bincount(idx, minlength=n)
        # a stratum-partitioned interval of length n w_i holds between floor - 1 and ceil + 1 pointers
        assert np.all(c >= np.floor(n * w) - 1) and np.all(c <= np.ceil(n * w) + 1)
        counts += c
    mean = counts / reps
    # per-particle variance of a stratified count is at most 1/4 per partially covered stratum (<= 2)
    assert np.all(np.abs(mean - n * w) < 5 * np.sqrt(0.5 / reps) + 1e-12)


@pytest.mark.parametrize("method", ["systematic", "stratified"])
def test_resampling_keeps_the_weighted_moments(method):
    rng = np.random.default_rng(4)
    n = 20000
    x = rng.standard_normal((n, 2)) * [2.0, 0.5] + [1.0, -3.0]
    lw = -0.5 * ((x[:, 0] - 2.0) / 1.0) ** 2  # tilt: target mean shifts
    pf = ParticleFilter(x, lw, rng=5, resampling=method)
    m0, C0 = pf.gaussian_summary()
    pf.resample()
    m1, C1 = pf.gaussian_summary()
    assert np.allclose(pf.weights, 1.0 / n)
    assert np.all(np.abs(m1 - m0) < 4 * np.sqrt(np.diag(C0) / n) * 2)
    assert np.allclose(C1, C0, rtol=0.05, atol=0.01)


def test_gaussian_summary_matches_numpy_weighted_cov():
    rng = np.random.default_rng(6)
    x = rng.standard_normal((300, 3)) @ np.array([[1, 0.3, 0], [0, 2, 0.5], [0, 0, 0.7]])
    w = rng.random(300)
    pf = ParticleFilter(x, np.log(w))
    m, C = pf.gaussian_summary()
    np.testing.assert_allclose(m, np.average(x, axis=0, weights=w), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(C, np.cov(x.T, aweights=w, bias=True), rtol=1e-10, atol=1e-12)
    m2, C2 = pf.gaussian_summary(dims=[0, 2])
    np.testing.assert_allclose(C2, np.cov(x[:, [0, 2]].T, aweights=w, bias=True), rtol=1e-10, atol=1e-12)
    m3, C3 = weighted_mean_cov(x, w * 7.0)
    np.testing.assert_allclose(C3, C, rtol=1e-12, atol=1e-14)


def test_update_returns_log_predictive_likelihood_and_refuses_depletion():
    rng = np.random.default_rng(8)
    x = rng.standard_normal((50, 1))
    w = rng.random(50)
    pf = ParticleFilter(x, np.log(w), rng=1)
    ll = -0.5 * (x[:, 0] - 0.3) ** 2
    expected = np.log(np.sum(w / w.sum() * np.exp(ll)))
    assert pf.update(ll) == pytest.approx(expected, rel=1e-12)
    np.testing.assert_allclose(pf.weights, w * np.exp(ll) / np.sum(w * np.exp(ll)), rtol=1e-12)
    before = pf.log_weights.copy()
    with pytest.raises(ParticleDepletionError):
        pf.update(np.full(50, -np.inf))
    np.testing.assert_array_equal(pf.log_weights, before)
    with pytest.raises(ValidationError):
        pf.update(np.full(50, np.nan))
    with pytest.raises(ShapeError):
        pf.update(np.zeros(49))


def test_move_with_refusals_keeps_old_state_and_zero_weight():
    x = np.arange(10.0).reshape(5, 2)
    pf = ParticleFilter(x)
    ok = np.array([True, False, True, False, True])
    assert pf.move(x + 100, ok) == 2
    np.testing.assert_array_equal(pf.particles[ok], x[ok] + 100)
    np.testing.assert_array_equal(pf.particles[~ok], x[~ok])
    assert np.all(pf.weights[~ok] == 0) and pf.weights[ok] == pytest.approx(np.full(3, 1 / 3))
    with pytest.raises(ParticleDepletionError):
        pf.move(x, np.zeros(5, bool))


def test_roughening_std_follows_gordon():
    rng = np.random.default_rng(9)
    n, d = 4000, 2
    x = rng.random((n, d)) * [4.0, 1.0]
    K = 0.2
    expected = K * np.ptp(x, axis=0) * n ** (-1.0 / d)
    np.testing.assert_allclose(roughening_std(x, K), expected)
    pf = ParticleFilter(x, rng=10, roughening=K)
    std = pf.roughen()
    np.testing.assert_allclose(std, expected)
    jitter = pf.particles - x
    np.testing.assert_allclose(jitter.std(axis=0), expected, rtol=0.05)


def test_resample_if_needed_threshold_and_determinism():
    def run(seed):
        rng = np.random.default_rng(0)
        pf = ParticleFilter(rng.standard_normal((1000, 2)), rng=seed, ess_threshold=0.5, roughening=0.1)
        did = []
        for k in range(10):
            pf.move(pf.particles + 0.1)
            pf.update(-0.5 * np.sum((pf.particles - 0.2 * k) ** 2, axis=1) / 0.5)
            ess = pf.ess
            did.append(pf.resample_if_needed())
            assert did[-1] == (ess < 500)
        return pf.particles.copy(), did
    a, da = run(3)
    b, db = run(3)
    np.testing.assert_array_equal(a, b)
    assert da == db and any(da)


# --------------------------------------------------------------------------- occupancy grid
def test_occ_file_parsing_unsorted_lines(tmp_path):
    occ = np.zeros((4, 3), bool)
    occ[1, 2] = occ[3, 0] = True
    lines = [f"[{0.5 * i:.1f}, {0.5 * j:.1f}]::{int(occ[i, j])}" for i in range(4) for j in range(3)]
    rng = np.random.default_rng(0)
    rng.shuffle(lines)
    f = tmp_path / "x_0.5.occ"
    f.write_text("[[0.0, 0.0], [1.6, 1.1]]::0.5\n" + "\n".join(lines) + "\n")
    g = NodeLattice.from_occ_file(f)
    assert g.shape == (4, 3) and g.cell == 0.5
    np.testing.assert_array_equal(g.occupied, occ)
    g0 = NodeLattice.from_occ_file(f, occupied_value=0)
    np.testing.assert_array_equal(g0.occupied, ~occ)
    f.write_text("[[0.0, 0.0], [1.6, 1.1]]::0.5\n" + "\n".join(lines[:-1]) + "\n")
    with pytest.raises(ValidationError):
        NodeLattice.from_occ_file(f)


def test_world_cell_conversion_and_point_occupancy():
    g = walled_grid()
    rng = np.random.default_rng(1)
    p = rng.uniform(-1, 13, size=(2000, 2))
    ij = g.world_to_cell(p)
    np.testing.assert_array_equal(ij, np.floor(p / 0.25 + 0.5).astype(int))
    np.testing.assert_allclose(g.cell_to_world(ij), ij * 0.25)
    expected = np.array([point_occupied(g, q) for q in p])
    np.testing.assert_array_equal(g.is_occupied(p), expected)
    assert g.is_occupied(np.array([[np.nan, 1.0]]))[0]
    free = g.sample_free(3000, rng)
    assert not points_occupied(g, free).any()


def test_segment_test_is_exact_against_liang_barsky():
    rng = np.random.default_rng(2)
    occ = rng.random((30, 24)) < 0.25
    g = NodeLattice(occ, 0.2, origin=(1.0, -0.5))
    n = 1500
    a = g.origin + rng.uniform(-0.3, 6.2, size=(n, 2)) * [1, 0.8]
    b = a + rng.standard_normal((n, 2)) * rng.choice([0.03, 0.2, 1.0, 3.0], size=(n, 1))
    # include axis-parallel moves and moves within one cell
    b[:100, 1] = a[:100, 1]
    b[100:200, 0] = a[100:200, 0]
    b[200:300] = a[200:300] + 0.01
    got = g.segment_blocked(a, b)
    m = g.map

    def u1(v, ax):   # continuous cell coordinate along axis ax of the lattice's map
        return m._u1(v - m.origin[ax], ax)

    np.testing.assert_array_equal(got, m._blocked_exact(
        u1(a[:, 0], 0), u1(a[:, 1], 1), np.floor(u1(a[:, 0], 0)).astype(int),
        np.floor(u1(a[:, 1], 1)).astype(int), u1(b[:, 0], 0), u1(b[:, 1], 1)))
    checked = 0
    for k in range(n):
        ref = ref_blocked(g, a[k], b[k])
        if ref is None:
            continue
        checked += 1
        assert got[k] == ref, (k, a[k], b[k])
    assert checked > 0.99 * n
    assert 0.2 < got.mean() < 0.9


# --------------------------------------------------------------------------- WSN tracker
RECEIVERS = np.array([[x, y, 2.0] for x in (1.0, 6.0, 11.0) for y in (1.0, 4.5, 9.0)] +
                     [[3.5, 6.5, 2.0], [8.5, 2.5, 2.0], [8.5, 7.5, 2.0]])


def field(std=4.0):
    return RSSISensor(RECEIVERS, p0=-55.0, exponent=2.2, std=std, height=1.2)


def test_log_likelihood_matches_rssisensor_and_handles_missing():
    s = field()
    sensors = [RSSISensor(RECEIVERS[j], -55.0 - j, 2.0 + 0.05 * j, 3.0 + 0.1 * j, d0=1.5, height=1.2)
               for j in range(len(RECEIVERS))]
    for sens in (s, sensors):
        t = WSNTracker(sens, 50, bounds=[0, 0, 12, 10], seed=0)
        t.initialize()
        rng = np.random.default_rng(0)
        z = -70 + 8 * rng.standard_normal(12)
        z[[2, 7]] = np.nan
        ll = t.log_likelihood(z)
        single = [sens] if isinstance(sens, RSSISensor) else sens
        for i, x in enumerate(t.particles[:10]):
            mu = np.concatenate([q.h(x) for q in single])
            std = np.concatenate([q.std for q in single])
            ok = np.isfinite(z)
            expected = -0.5 * np.sum(((z[ok] - mu[ok]) / std[ok]) ** 2)
            assert ll[i] == pytest.approx(expected, rel=1e-9, abs=1e-9)
        # sparse form with repeated receivers equals the sum of single readings
        j = np.array([0, 0, 5])
        zz = np.array([-60.0, -65.0, -80.0])
        sparse = t.log_likelihood(zz, j)
        singles = sum(t.log_likelihood(zz[k:k + 1], j[k:k + 1]) for k in range(3))
        np.testing.assert_allclose(sparse, singles, rtol=1e-10)
    before = t.weights.copy()
    assert t.update(t.time, np.full(12, np.nan)) == 0
    np.testing.assert_array_equal(t.weights, before)


def test_log_likelihood_in_large_world_coordinates():
    off = np.array([4.5e5, 4.6e6, 0.0])  # UTM-like coordinates
    s = RSSISensor(RECEIVERS + off, p0=-55.0, exponent=2.2, std=4.0, height=1.2)
    t = WSNTracker(s, 20, bounds=[off[0], off[1], off[0] + 12, off[1] + 10], seed=0)
    t.initialize()
    z = s.h(t.particles[0]) + 1.0
    ll = t.log_likelihood(z)
    for i, x in enumerate(t.particles):
        assert ll[i] == pytest.approx(-0.5 * np.sum(((z - s.h(x)) / 4.0) ** 2), rel=1e-7, abs=1e-7)


def test_tracker_converges_on_synthetic_field():
    rng = np.random.default_rng(11)
    s = field(std=4.0)
    t = WSNTracker(s, 3000, q=0.3, bounds=[0, 0, 12, 10], seed=12)
    t.initialize()
    dt, steps = 0.5, 120
    truth = np.array([[2 + 8 * (0.5 - 0.5 * np.cos(np.pi * k / steps)), 5 + 3 * np.sin(2 * np.pi * k / steps)]
                      for k in range(steps)])
    err = []
    for k in range(steps):
        z = s.h(truth[k]) + rng.standard_normal(12) * 4.0
        t.predict(t.time + dt)
        t.update(t.time, z)
        err.append(np.linalg.norm(t.estimate().mean - truth[k]))
    err = np.array(err)
    assert np.sqrt(np.mean(err[20:] ** 2)) < 0.8
    m, C = t.estimate()
    assert np.linalg.norm(m - truth[-1]) < 4 * np.sqrt(np.trace(C)) + 0.3


def test_map_constraint_brute_force():
    g = walled_grid()
    s = RSSISensor(RECEIVERS, -55.0, 2.2, 4.0, height=1.2)
    t = WSNTracker(s, 600, q=1.0, grid=g, seed=3, roughening=0.3, ess_threshold=0.9)
    t.initialize()
    moves = []
    orig_move = t.pf.move

    def spy(new, valid=None):
        old = t.pf.particles.copy()
        alive = t.pf.weights > 0
        out = orig_move(new, valid)
        moves.append((old, np.asarray(new).copy(), None if valid is None else np.asarray(valid).copy(), alive))
        return out

    t.pf.move = spy
    orig_roughen = t.pf.roughen
    jitters = []

    def spy_r(*a, **kw):
        old = t.pf.particles.copy()
        out = orig_roughen(*a, **kw)
        jitters.append((old, t.pf.particles.copy()))
        return out

    t.pf.roughen = spy_r
    rng = np.random.default_rng(4)
    truth = np.array([3.0, 5.0])
    for k in range(20):
        truth = truth + [0.3, 0.0] if truth[0] < 9 else truth
        t.predict(t.time + 0.5)
        t.update(t.time, s.h(truth) + 4 * rng.standard_normal(12))
        assert not points_occupied(g, t.particles).any()
    assert moves and jitters
    refused = []
    for old, new, valid, alive in moves:
        assert valid is not None
        a, b, ok = old[alive], new[alive], valid[alive]
        assert not dense_crossing(g, a[ok], b[ok]).any()  # no accepted move crosses a wall
        refused += list(zip(a[~ok], b[~ok]))
    assert len(refused) > 50
    for a, b in refused[:: max(1, len(refused) // 200)]:  # refused moves do touch an obstacle
        assert ref_blocked(g, a, b) in (True, None)
    for old, new in jitters:
        assert not dense_crossing(g, old, new).any()


def test_map_keeps_particles_in_the_room_of_the_truth():
    g = walled_grid()
    s = field()
    t = WSNTracker(s, 2000, q=0.2, grid=g, seed=5)
    t.initialize(mean=[3.0, 8.0], cov=np.eye(2) * 0.3)
    for _ in range(20):
        t.predict(t.time + 0.5)
    # the wall at x = 6 m is only passable through the door; after 10 s of diffusion
    # without measurements nearly no particle has reached the other room
    assert np.mean(t.particles[:, 0] > 6.0) < 0.1


def test_information_contribution_is_psd_and_matches_linearized_update():
    s = field(std=3.0)
    mean = np.array([4.0, 6.0])
    P = np.diag([0.15, 0.1]) ** 2
    t = WSNTracker(s, 200_000, bounds=[0, 0, 12, 10], seed=21, ess_threshold=0.0)
    t.initialize(mean=mean, cov=P)
    t.predict(t.time + 0.0)
    z = s.h(mean)
    t.update(t.time, z)
    info = t.information_contribution()
    H = s.H(mean)
    Rinv = np.linalg.inv(s.R)
    Om = H.T @ Rinv @ H
    eta = H.T @ Rinv @ (z - s.h(mean) + H @ mean)
    assert np.linalg.eigvalsh(info.Omega).min() >= -1e-12
    assert np.linalg.norm(info.Omega - Om) / np.linalg.norm(Om) < 0.1
    assert np.linalg.norm(info.eta - eta) / np.linalg.norm(eta) < 0.1
    # no reading: no information
    t.predict(t.time + 0.1)
    t.update(t.time, np.full(12, np.nan))
    zero = t.information_contribution()
    assert np.all(zero.Omega == 0) and np.all(zero.eta == 0)


def test_information_contribution_psd_for_ring_posteriors():
    rng = np.random.default_rng(30)
    s = RSSISensor(RECEIVERS[:1], -55.0, 2.2, 2.0, height=1.2)
    for k in range(10):
        t = WSNTracker(s, 4000, bounds=[0, 0, 12, 10], seed=k, ess_threshold=0.0)
        t.initialize()  # uniform prior: one reading gives a ring, wider than the prior in some direction
        t.predict(t.time + 0.5)
        t.update(t.time, [-70 + 5 * rng.standard_normal()])
        info = t.information_contribution()
        lam = np.linalg.eigvalsh(info.Omega)
        assert lam.min() >= -1e-10 * max(1.0, lam.max())


def test_regression_information_matches_weighted_statistical_linearization():
    # Reference: the statistical linear regression written out with numpy's weighted covariance
    # and explicit inverses, and the sensor model's own h (not the tracker's mean_rssi).
    s = field(std=3.0)
    t = WSNTracker(s, 3000, bounds=[0, 0, 12, 10], seed=5, ess_threshold=0.0)
    t.initialize(mean=np.array([5.0, 5.0]), cov=np.diag([1.0, 0.5]))
    t.predict(t.time + 0.5)
    z = s.h(np.array([5.5, 4.8])) + 3.0 * np.random.default_rng(1).standard_normal(12)
    z[3] = np.nan  # a missing reading is left out
    t.update(t.time, z)
    info = t.information_contribution(method="regression")
    x, lw = t.particles[:, :2], t.pf.log_weights
    w = np.exp(lw - lw.max())
    keep = np.isfinite(z)
    h = np.array([s.h(p) for p in x])[:, keep]
    C = np.cov(np.hstack([x, h]).T, aweights=w, bias=True)
    P, Chp, Chh = C[:2, :2], C[2:, :2], C[2:, 2:]
    A = Chp @ np.linalg.inv(P)
    b = np.average(h, axis=0, weights=w) - A @ np.average(x, axis=0, weights=w)
    Si = np.linalg.inv(9.0 * np.eye(keep.sum()) + Chh - A @ P @ A.T)
    np.testing.assert_allclose(info.Omega, A.T @ Si @ A, rtol=1e-8)
    np.testing.assert_allclose(info.eta, A.T @ Si @ (z[keep] - b), rtol=1e-8)
    np.testing.assert_allclose(t.mean_rssi(x[:5], np.flatnonzero(keep)), h[:5], rtol=1e-10)
    with pytest.raises(ValidationError):
        t.information_contribution(method="exact")


def test_regression_information_is_an_honest_measurement():
    # A wide prior and two receivers in a line: the likelihood is a curved ridge. The
    # pseudo-measurement Omega^+ eta must be a measurement of the true position with
    # information Omega: its normalized error against the truth is chi-square with rank(Omega)
    # degrees of freedom, so the sum over independent trials is chi-square with the summed
    # degrees of freedom (scipy's quantiles as the reference).
    from scipy.stats import chi2
    s = RSSISensor(RECEIVERS[[0, 6]], p0=-55.0, exponent=2.2, std=3.0, height=1.2)
    rng = np.random.default_rng(7)
    mean, cov = np.array([6.0, 5.0]), np.diag([4.0, 4.0])
    total, dof, big = 0.0, 0, 0
    for k in range(150):
        truth = rng.multivariate_normal(mean, cov)
        z = s.h(truth) + 3.0 * rng.standard_normal(2)
        t = WSNTracker(s, 3000, bounds=[-10, -10, 22, 20], seed=k, ess_threshold=0.0)
        t.initialize(mean=mean, cov=cov)
        t.predict(t.time + 0.0)
        t.update(t.time, z)
        info = t.information_contribution(method="regression")
        lam, V = np.linalg.eigh(info.Omega)
        use = lam > 1e-9 * lam.max()
        e = (V[:, use].T @ info.eta) / lam[use] - V[:, use].T @ truth
        nis = float(e @ (lam[use] * e))
        total += nis
        dof += int(use.sum())
        big += nis > chi2.ppf(0.999, int(use.sum()))
    assert dof >= 150
    assert chi2.ppf(0.001, dof) < total < chi2.ppf(0.999, dof)
    assert big <= 2


class _LinearRSSI(WSNTracker):
    """A tracker whose readings are exactly linear in the position, ``z_j = H_j p + c_j + e_j``,
    ``e_j ~ N(0, sd_j^2)``: the case in which the regression must be the Kalman measurement
    information whatever the particles."""

    Hl = np.array([[2.0, -1.0], [0.5, 3.0], [-1.5, 0.7]])
    c = np.array([-60.0, -55.0, -70.0])
    sd = np.array([2.0, 3.0, 4.0])

    def __init__(self, n, seed):
        sensors = [RSSISensor(np.array([[0.0, 0.0, 2.0]]), -50.0, 2.0, sd, height=1.0) for sd in self.sd]
        super().__init__(sensors, n, bounds=[-5, -5, 5, 5], seed=seed, ess_threshold=0.0)

    def mean_rssi(self, positions, receivers):
        j = np.asarray(receivers)
        return np.asarray(positions)[:, :2] @ self.Hl[j].T + self.c[j]

    def mean_rssi_jacobian(self, position, receivers):
        return self.Hl[np.asarray(receivers)]

    def log_likelihood(self, rssi, receivers=None, particles=None):
        z = np.asarray(rssi, dtype=float)
        x = self.particles if particles is None else particles
        r = (z - self.mean_rssi(x, np.arange(3))) / self.sd
        return -0.5 * np.sum(r * r, axis=1)


def test_regression_information_is_the_kalman_information_for_a_linear_measurement():
    # Closed form: for z = H p + c + e, e ~ N(0, R), the information of the readings is
    # H^T R^-1 H and H^T R^-1 (z - c) (the EIF/Kalman measurement update), exactly, for any
    # particle set: the regression of an affine h has A = H and no linearization error. Checked
    # for well-spread weights and for weights so degenerate that the Taylor fallback is taken.
    z = np.array([-58.0, -52.0, -71.0])
    Ri = np.diag(1.0 / _LinearRSSI.sd ** 2)
    for scale, degenerate in ((1.0, False), (100.0, True)):
        t = _LinearRSSI(3000, seed=3)
        t.initialize()   # uniform over 10 m x 10 m: far from Gaussian
        t.predict(0.5)
        t.update(0.5, scale * (z - _LinearRSSI.c) + _LinearRSSI.c)
        assert (t.pf.ess < 3) == degenerate
        zz = scale * (z - _LinearRSSI.c) + _LinearRSSI.c
        info = t.information_contribution(method="regression")
        np.testing.assert_allclose(info.Omega, _LinearRSSI.Hl.T @ Ri @ _LinearRSSI.Hl, rtol=1e-9)
        np.testing.assert_allclose(info.eta, _LinearRSSI.Hl.T @ Ri @ (zz - _LinearRSSI.c), rtol=1e-9)


def test_regression_information_tends_to_the_linearized_update_for_a_narrow_posterior():
    # Reference: the EIF update linearized at the posterior mean with the sensor's own h and H
    # (posterior linearization). A noisy reading (the quotient follows the observed curvature
    # of the likelihood there, the regression does not). The difference left is the curvature of
    # h over the posterior's spread (0.1-0.15 m): 3-4 % measured, independent of N.
    s = field(std=3.0)
    mean = np.array([4.0, 6.0])
    t = WSNTracker(s, 20_000, bounds=[0, 0, 12, 10], seed=21, ess_threshold=0.0)
    t.initialize(mean=mean, cov=np.diag([0.15, 0.1]) ** 2)
    t.predict(t.time + 0.0)
    z = s.h(mean) + 3.0 * np.random.default_rng(21).standard_normal(12)
    t.update(t.time, z)
    info = t.information_contribution(method="regression")
    pm = t.weights @ t.particles[:, :2]
    H, Rinv = s.H(pm), np.linalg.inv(s.R)
    Om, eta = H.T @ Rinv @ H, H.T @ Rinv @ (z - s.h(pm) + H @ pm)
    assert np.linalg.norm(info.Omega - Om) / np.linalg.norm(Om) < 0.06
    assert np.linalg.norm(info.eta - eta) / np.linalg.norm(eta) < 0.03


def test_regression_information_with_degenerate_weights_is_the_linearized_update():
    # 50 particles and 0.3 dB readings: one particle carries the posterior (ESS 1; the next
    # weights are 1e-63 and smaller, or exactly 0). The weighted regression would divide rounding
    # noise by rounding noise (an eigenvalue of 2e5 m^-2 where the Fisher information is 300-440)
    # or a zero covariance by itself; the fallback is the first-order expansion at the weighted
    # mean, checked against the sensor's own h and H.
    for std in (0.3, 0.01):
        s = field(std=std)
        t = WSNTracker(s, 50, bounds=[0, 0, 12, 10], seed=0, ess_threshold=0.0)
        t.initialize()
        t.predict(0.1)
        z = s.h(np.array([5.0, 5.0]))
        t.update(0.1, z)
        assert t.pf.ess < 1.0 + 1e-9
        info = t.information_contribution(method="regression")
        pm = t.weights @ t.particles[:, :2]
        H, Rinv = s.H(pm), np.linalg.inv(s.R)
        np.testing.assert_allclose(info.Omega, H.T @ Rinv @ H, rtol=1e-8)
        np.testing.assert_allclose(info.eta, H.T @ Rinv @ (z - s.h(pm) + H @ pm), rtol=1e-8)
    # the Jacobian against the sensor's H and central differences (a point under a receiver: clamped)
    s = RSSISensor(RECEIVERS, p0=-55.0, exponent=2.2, std=3.0, height=2.0, d_min=0.5)
    t = WSNTracker(s, 10, bounds=[0, 0, 12, 10], seed=0)
    j = np.arange(12)
    for p in (np.array([4.2, 7.3]), RECEIVERS[4, :2] + 0.1):
        J = t.mean_rssi_jacobian(p, j)
        np.testing.assert_allclose(J, s.H(p), rtol=1e-10, atol=1e-12)
        e = 1e-6
        fd = np.column_stack([(t.mean_rssi((p + e * u)[None], j)[0] - t.mean_rssi((p - e * u)[None], j)[0]) / (2 * e)
                              for u in np.eye(2)])
        np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-6)
    assert np.all(t.mean_rssi_jacobian(RECEIVERS[4, :2] + 0.1, [4]) == 0.0)


def test_project_psd_information():
    V = np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    Om = V @ np.diag([2.0, -0.5]) @ V.T
    eta = np.array([1.0, -2.0])
    Op, ep, clipped = project_psd_information(Om, eta)
    assert clipped == 1
    np.testing.assert_allclose(Op, 2.0 * np.outer(V[:, 0], V[:, 0]), atol=1e-12)
    np.testing.assert_allclose(ep, V[:, 0] * (V[:, 0] @ eta), atol=1e-12)
    O2, e2, c2 = project_psd_information(np.eye(2), eta)
    assert c2 == 0
    np.testing.assert_allclose(O2, np.eye(2))
    np.testing.assert_allclose(e2, eta)


def test_reweight_information_is_a_kalman_update_for_a_gaussian_cloud():
    s = field()
    t = WSNTracker(s, 200_000, bounds=[0, 0, 12, 10], seed=2, ess_threshold=0.0)
    m0, P0 = np.array([5.0, 5.0]), np.diag([0.5, 0.3])
    t.initialize(mean=m0, cov=P0)
    Om = np.array([[4.0, 1.0], [1.0, 2.0]])
    z = np.array([5.4, 4.7])
    t.reweight_information(InformationGaussian(Om @ z, Om))
    Pk = np.linalg.inv(np.linalg.inv(P0) + Om)
    mk = Pk @ (np.linalg.inv(P0) @ m0 + Om @ z)
    m, C = t.estimate()
    np.testing.assert_allclose(m, mk, atol=0.01)
    np.testing.assert_allclose(C, Pk, atol=0.01)


def test_tracker_validation():
    s = field()
    with pytest.raises(NotInitializedError):
        WSNTracker(s, 10, bounds=[0, 0, 1, 1]).predict(1.0)
    with pytest.raises(ValidationError):
        WSNTracker(s, 10, motion="teleport")
    with pytest.raises(ValidationError):
        WSNTracker(s, 10, bounds=[0, 0, 1, 1], resampling="magic")
    t = WSNTracker(s, 10, bounds=[0, 0, 1, 1], seed=0)
    t.initialize()
    with pytest.raises(ShapeError):
        t.update(t.time, np.zeros(11))
    with pytest.raises(ValidationError):
        t.update(t.time, [-60.0], [12])
    with pytest.raises(ValidationError):
        t.predict(t.time - 1.0)


def test_constant_velocity_motion_runs_with_map_and_speed_cap():
    g = walled_grid()
    s = field()
    t = WSNTracker(s, 1000, motion="constant_velocity", q=0.5, max_speed=1.2, grid=g, seed=1)
    t.initialize(mean=[3.0, 3.0], cov=0.2 * np.eye(2))
    rng = np.random.default_rng(0)
    for k in range(20):
        t.update(t.time + 0.5, s.h([3 + 0.1 * k, 3.0]) + 4 * rng.standard_normal(12))
        assert t.particles.shape == (1000, 4)
        assert np.all(np.hypot(t.particles[:, 2], t.particles[:, 3]) <= 1.2 + 1e-9)
        assert not points_occupied(g, t.particles[:, :2]).any()


def test_resamplers_agree_with_filterpy_given_the_same_uniform_draws(monkeypatch):
    """The engine's resamplers against filterpy.monte_carlo's, which draw from numpy's global
    random state (why dfusion has its own, seeded per filter): fed the same uniforms, both
    select the same particles."""
    import filterpy.monte_carlo.resampling as fp

    from dfusion.estimation import multinomial_resample, stratified_resample, systematic_resample

    w = np.random.default_rng(3).gamma(0.5, size=700)
    w /= w.sum()
    for ours, theirs in ((systematic_resample, fp.systematic_resample),
                         (stratified_resample, fp.stratified_resample),
                         (multinomial_resample, fp.multinomial_resample)):
        for seed in range(5):
            monkeypatch.setattr(fp, "random", np.random.default_rng(seed).random)
            expected = np.sort(theirs(w))
            got = np.sort(ours(w, np.random.default_rng(seed)))
            np.testing.assert_array_equal(got, expected, err_msg=ours.__name__)
