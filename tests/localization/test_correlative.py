"""Correlative scan matching (Olson 2009): the vectorized search against a brute-force
loop over the same lattice, the score-surface covariance against closed forms (a flat
corridor: a uniform distribution over the window), the enclosing covariance against its
definition, and the scan-matching EKF using it."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from dfusion.errors import ShapeError, ValidationError
from dfusion.localization import (
    OdometryEKF,
    ScanMatcher,
    ScanMatchingEKF,
    scan_to_points,
)
from dfusion.localization.correlative import (
    CorrelativeScanMatcher,
    enclosing_covariance,
)
from dfusion.maps import OccupancyGrid, cast_rays
from dfusion.maps.buildings import rooms

ANGLES = np.linspace(-math.pi, math.pi, 180, endpoint=False)


@pytest.fixture(scope="module")
def room_map():
    return rooms(12.0, 8.0, 3, 2, seed=3)


def _scan(grid, pose, max_range=10.0, noise=0.01, seed=0):
    """Scan points from a ray cast with Gaussian range noise (noise-free end points on
    axis-aligned walls lie exactly on cell boundaries, where rounding decides the cell)."""
    z = cast_rays(grid, np.asarray(pose, dtype=float), ANGLES, max_range)[0]
    z = z + np.random.default_rng(seed).normal(0.0, noise, z.shape)
    return scan_to_points(z, ANGLES, max_range)


def _brute_force_scores(grid, pts, center, ox, oy, oth, sigma, z_hit, z_rand, max_distance, max_range):
    """Score of every lattice pose, one pose at a time: end points -> cell -> distance to
    the surface -> the likelihood-field formula written out here."""
    dist = np.asarray(grid.surface_distance_field())
    H, W = dist.shape
    out = np.empty((oth.size, oy.size, ox.size))
    for h, dth in enumerate(oth):
        th = center[2] + dth
        c, s = math.cos(th), math.sin(th)
        for i, dy in enumerate(oy):
            for j, dx in enumerate(ox):
                ex = c * pts[:, 0] - s * pts[:, 1] + center[0] + dx - grid.origin[0]
                ey = s * pts[:, 0] + c * pts[:, 1] + center[1] + dy - grid.origin[1]
                cj = np.floor(ex / grid.resolution).astype(int)
                ci = np.floor(ey / grid.resolution).astype(int)
                inside = (ci >= 0) & (ci < H) & (cj >= 0) & (cj < W)
                d = np.full(pts.shape[0], max_distance)
                d[inside] = np.minimum(dist[ci[inside], cj[inside]], max_distance)
                p = z_hit * np.exp(-0.5 * (d / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi)) + z_rand / max_range
                out[h, i, j] = np.log(p).sum()
    return out


def test_search_equals_brute_force_and_finds_the_true_pose(room_map):
    truth = np.array([5.02, 3.51, 0.3])
    assert room_map.is_free(truth[None, :2]).all()
    pts = _scan(room_map, truth)
    m = CorrelativeScanMatcher(room_map, sigma_hit=0.1, max_range=10.0, angular_step=0.01)
    center = truth + np.array([0.2, -0.15, 0.04])
    S, (ox, oy, oth), _ = m.scores(pts, center, (0.3, 0.3, 0.08))
    ref = _brute_force_scores(room_map, pts, center, ox, oy, oth, 0.1, 0.95, 0.05, 1.0, 10.0)
    assert S.shape == ref.shape == (17, 13, 13)
    # float32 table against float64: agreement to 1e-4 per point
    np.testing.assert_allclose(S, ref, atol=1e-4 * pts.shape[0])
    assert np.unravel_index(np.argmax(S), S.shape) == np.unravel_index(np.argmax(ref), ref.shape)
    res = m.match(pts, center, (0.3, 0.3, 0.08))
    # the lattice holds a pose within half a cell / half a step of the truth; the best one is it
    assert abs(res.pose[0] - truth[0]) <= 0.5 * 0.05 + 1e-9
    assert abs(res.pose[1] - truth[1]) <= 0.5 * 0.05 + 1e-9
    assert abs(res.pose[2] - truth[2]) <= 0.5 * 0.01 + 1e-9
    assert res.n_candidates == S.size and res.n_points == pts.shape[0]


def test_mean_and_covariance_are_the_weighted_moments_of_the_lattice(room_map):
    truth = np.array([5.02, 3.51, 0.3])
    pts = _scan(room_map, truth)[::3]
    # a wide likelihood so that many lattice poses carry weight
    m = CorrelativeScanMatcher(room_map, sigma_hit=0.5, max_range=10.0, angular_step=0.02)
    center = truth + np.array([0.05, 0.0, 0.0])
    hw = (0.2, 0.15, 0.06)
    S, (ox, oy, oth), _ = m.scores(pts, center, hw)
    w = np.exp(S - S.max()).reshape(-1)
    w /= w.sum()
    X = np.array([[center[0] + dx, center[1] + dy, center[2] + dt] for dt in oth for dy in oy for dx in ox])
    mean = w @ X
    cov = (X - mean).T @ ((X - mean) * w[:, None]) + np.diag([0.05**2, 0.05**2, 0.02**2]) / 12
    res = m.match(pts, center, hw)
    np.testing.assert_allclose(res.mean, mean, atol=1e-9)
    np.testing.assert_allclose(res.covariance, cov, atol=1e-12)
    other = truth + np.array([0.1, -0.1, 0.05])
    d = mean - other
    np.testing.assert_allclose(res.covariance_about(other), cov + np.outer(d, d), atol=1e-12)


def test_a_prior_moves_the_best_pose_but_not_the_likelihood_moments(room_map):
    """With a Gaussian prior at the center, the best pose is the lattice pose of highest
    log-likelihood + log-prior (computed pose by pose here), within the gate if one is
    given; the mean and covariance stay those of the likelihood alone."""
    truth = np.array([5.02, 3.51, 0.3])
    pts = _scan(room_map, truth)[::2]
    m = CorrelativeScanMatcher(room_map, sigma_hit=0.2, max_range=10.0, angular_step=0.01)
    center = truth + np.array([0.25, -0.2, 0.06])
    hw = (0.4, 0.4, 0.1)
    S, (ox, oy, oth), _ = m.scores(pts, center, hw)
    P = np.array([[0.004, 0.001, 0.0], [0.001, 0.003, 0.0002], [0.0, 0.0002, 0.0004]])
    Pi = np.linalg.inv(P)
    gate = chi2.ppf(0.99, 3)
    best, best_val, best_g, best_g_val = None, -np.inf, None, -np.inf
    for h, dt in enumerate(oth):
        for i, dy in enumerate(oy):
            for j, dx in enumerate(ox):
                d = np.array([dx, dy, dt])
                q = d @ Pi @ d
                v = S[h, i, j] - 0.5 * q
                if v > best_val:
                    best, best_val = center + d, v
                if q <= gate and v > best_g_val:
                    best_g, best_g_val = center + d, v
    plain = m.match(pts, center, hw)
    with_prior = m.match(pts, center, hw, prior_cov=P)
    gated = m.match(pts, center, hw, prior_cov=P, prior_gate=gate)
    np.testing.assert_allclose(with_prior.pose, best, atol=1e-12)
    np.testing.assert_allclose(gated.pose, best_g, atol=1e-12)
    # here the prior (centred 32 cm / 0.06 rad off) pulls the best pose away from the truth
    assert math.hypot(*(with_prior.pose[:2] - plain.pose[:2])) > 0.02
    for r in (with_prior, gated):
        np.testing.assert_allclose(r.mean, plain.mean, atol=1e-12)
        np.testing.assert_allclose(r.covariance, plain.covariance, atol=1e-15)
        assert r.score == plain.score == S.max()


def test_flat_corridor_gives_the_uniform_variance_along_it():
    # a 60 m x 2 m corridor along x (walls one cell thick), laser range 8 m: no end point
    # sees an end, so the score does not change along x
    res_m = 0.05
    data = np.full((44, 1200), -1, dtype=int)
    data[1, :] = 100
    data[42, :] = 100
    data[2:42, :] = 0
    g = OccupancyGrid(data, res_m)
    truth = np.array([30.0, 1.1, 0.02])
    pts = _scan(g, truth, max_range=8.0, noise=0.0)
    m = CorrelativeScanMatcher(g, sigma_hit=0.1, max_range=8.0, angular_step=0.005)
    hw = (0.5, 0.3, 0.03)
    r = m.match(pts, truth + np.array([0.12, 0.0, 0.0]), hw)
    n = 2 * round(0.5 / res_m) + 1
    # closed form: the variance of a uniform distribution over n cells of width r
    assert r.covariance[0, 0] == pytest.approx((n * res_m) ** 2 / 12, rel=1e-9)
    assert r.covariance[0, 1] == pytest.approx(0.0, abs=1e-12)
    assert r.covariance[0, 2] == pytest.approx(0.0, abs=1e-12)
    # across the corridor and in heading the walls fix it: within the quantization
    assert math.sqrt(r.covariance[1, 1]) < 0.03
    assert math.sqrt(r.covariance[2, 2]) < 0.01
    assert abs(r.pose[1] - truth[1]) <= 0.025 + 1e-9 and abs(r.pose[2] - truth[2]) <= 0.005 + 1e-9


def test_window_is_the_box_of_the_probability_region(room_map):
    m = CorrelativeScanMatcher(room_map)
    P = np.diag([0.1, 0.05, 0.05]) ** 2
    k = chi2.ppf(0.99, 3)
    np.testing.assert_allclose(m.window(P, 0.99, cap=(1.0, 1.0, 0.3)), np.sqrt(k) * np.array([0.1, 0.05, 0.05]))
    np.testing.assert_allclose(m.window(P, 0.99, cap=(0.2, 1.0, 0.1)), [0.2, 0.05 * math.sqrt(k), 0.1])
    np.testing.assert_allclose(m.window(np.diag([1e-8, 1e-8, 1e-8])), [0.1, 0.1, 0.002])


def test_enclosing_covariance():
    np.testing.assert_allclose(enclosing_covariance(np.diag([1.0, 4.0]), np.diag([2.0, 3.0])), np.diag([2.0, 4.0]))
    rng = np.random.default_rng(1)
    for _ in range(20):
        a = rng.normal(size=(3, 3))
        b = rng.normal(size=(3, 3))
        A, B = a @ a.T + 0.1 * np.eye(3), b @ b.T + 0.1 * np.eye(3)
        C = enclosing_covariance(A, B)
        assert np.linalg.eigvalsh(C - A).min() > -1e-9
        assert np.linalg.eigvalsh(C - B).min() > -1e-9
        np.testing.assert_allclose(C, C.T)
        # where one dominates, it is the answer
        np.testing.assert_allclose(enclosing_covariance(A + B, B), A + B, atol=1e-9)
        np.testing.assert_allclose(enclosing_covariance(A, A + B), A + B, atol=1e-9)


def test_bad_input(room_map):
    m = CorrelativeScanMatcher(room_map, max_candidates=1000)
    pts = _scan(room_map, (5.0, 3.5, 0.0))
    with pytest.raises(ValidationError, match="max_candidates"):
        m.match(pts, (5.0, 3.5, 0.0), (1.0, 1.0, 0.3))
    with pytest.raises(ValidationError, match="at least 3"):
        m.match(pts[:2], (5.0, 3.5, 0.0), (0.1, 0.1, 0.01))
    with pytest.raises(ShapeError):
        m.match(pts[:, :1], (5.0, 3.5, 0.0), (0.1, 0.1, 0.01))
    with pytest.raises(ValidationError, match="OccupancyGrid"):
        CorrelativeScanMatcher(np.zeros((3, 3)))


def test_scan_matching_ekf_recovers_the_heading_icp_misses(room_map):
    """The prediction is 0.4 rad off in heading (with a covariance that admits it): ICP
    from the prediction stops in a wrong local minimum (12 cm, 0.027 rad off); from the
    correlative optimum over the window it finds the true pose, and the EKF takes it."""
    truth = np.array([5.02, 3.51, 0.3])
    pts = _scan(room_map, truth)
    matcher = ScanMatcher.from_grid(room_map, "point_to_line", max_correspondence_distance=0.5,
                                    robust="cauchy", tolerance=1e-4, max_iterations=40)
    pred = truth + np.array([0.0, 0.0, -0.4])
    P = np.diag([0.1, 0.1, 0.15]) ** 2
    plain = matcher.match(pts, pred)
    assert math.hypot(*(plain.pose[:2] - truth[:2])) > 0.1  # ICP alone: a wrong local minimum
    corr = CorrelativeScanMatcher(room_map, max_range=10.0)
    ekf = OdometryEKF(pred, P, gate=float(chi2.ppf(0.999, 3)))
    loc = ScanMatchingEKF(matcher, ekf, cov_floor=np.diag([0.02, 0.02, 0.01]) ** 2, correlative=corr,
                          correlative_cap=(1.0, 1.0, 0.6))
    out = loc.correct(0.0, pts)
    assert out.status == "accepted"
    assert abs(loc.last_match.pose[2] - truth[2]) < 1e-3
    assert abs(ekf.x[2] - truth[2]) < 0.02 and math.hypot(*(ekf.x[:2] - truth[:2])) < 0.02
