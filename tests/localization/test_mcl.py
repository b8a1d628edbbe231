"""Monte Carlo localization: motion model statistics, sensor models against direct
computation, KLD, tracking, global localization, recovery and late scans."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import erfc
from scipy.stats import chi2

from dfusion.errors import NotInitializedError, OutsideWindowError, ShapeError, TimeError, ValidationError
from dfusion.models import BeamErfcModel, LaserConfig, LikelihoodFieldModel, OdometryMotionModel
from dfusion.localization import kld_sample_size, MonteCarloLocalization
from dfusion.localization.mcl import heaviest_cluster
from dfusion.estimation import gaussian_summary
from dfusion.reliability import covariance_reliability
from dfusion.geometry import se2_between, se2_compose, se2_inverse
from dfusion.maps import cast_rays
from dfusion.geometry import wrap_angle
from dfusion.maps.buildings import rooms
from tests.helpers.rooms_world import drifting_odometry, wander_path

LASER = LaserConfig.uniform(181, math.pi, 10.0)


@pytest.fixture(scope="module")
def world():
    """A seeded rooms map, a robot path through it, noisy scans and drifting odometry."""
    g = rooms(12.0, 8.0, 3, 2, seed=3)
    rng = np.random.default_rng(0)
    path = wander_path(g, 90, rng)
    assert g.is_free(path[:, :2]).all()
    scans = cast_rays(g, path, LASER.angles, LASER.max_range) + rng.normal(0, 0.02, (len(path), LASER.angles.size))
    odo = drifting_odometry(path, rng)  # odometry frame unrelated to the map frame
    return g, path, scans, odo


def _run(mcl, path, scans, odo, start=1, dt=0.1):
    err = []
    for k in range(start, len(path)):
        mcl.predict(k * dt, odo[k])
        mcl.update(k * dt, scans[k])
        e = mcl.estimate()
        err.append((math.hypot(*(e.mean[:2] - path[k, :2])), abs(float(wrap_angle(e.mean[2] - path[k, 2])))))
    return np.array(err)


# ----------------------------------------------------------------------------------------
# motion model
# ----------------------------------------------------------------------------------------
def test_odometry_motion_model_moments_match_first_order_prediction():
    """Sample mean and covariance of Table 5.6 against the linearized prediction.

    With ``u = (rot1, trans, rot2)`` perturbed by independent zero-mean noise of variances
    ``V = diag(v1, vt, v2)``, the first-order mean is the noise-free motion ``g(u)`` and
    the covariance is ``G V G^T`` with ``G = dg/du``. Noise is small, so second-order
    terms are far below the statistical tolerance.
    """
    a1, a2, a3, a4 = 0.002, 0.001, 0.003, 0.0015  # distinct: a swapped alpha would fail
    model = OdometryMotionModel(a1, a2, a3, a4)
    x0 = np.array([1.0, -2.0, 0.4])
    o0, o1 = np.array([0.3, 0.1, -0.2]), np.array([1.1, 0.6, 0.5])
    # independent reference: the decomposition of Table 5.6 written out here
    dx, dy = o1[0] - o0[0], o1[1] - o0[1]
    rot1 = math.atan2(dy, dx) - o0[2]
    trans = math.hypot(dx, dy)
    rot2 = o1[2] - o0[2] - rot1
    v1 = a1 * rot1**2 + a2 * trans**2
    vt = a3 * trans**2 + a4 * (rot1**2 + rot2**2)
    v2 = a1 * rot2**2 + a2 * trans**2
    h = x0[2] + rot1
    mean1 = np.array([x0[0] + trans * math.cos(h), x0[1] + trans * math.sin(h), x0[2] + rot1 + rot2])
    G = np.array(
        [
            [-trans * math.sin(h), math.cos(h), 0.0],
            [trans * math.cos(h), math.sin(h), 0.0],
            [1.0, 0.0, 1.0],
        ]
    )
    cov1 = G @ np.diag([v1, vt, v2]) @ G.T
    n = 200_000
    s = model.sample(np.tile(x0, (n, 1)), o0, o1, np.random.default_rng(11))
    mean_s, cov_s = gaussian_summary(s)
    # mean: each component within 5 standard errors (+ the second-order bias bound
    # trans * v1 / 2 of cos/sin, negligible here)
    se = np.sqrt(np.diag(cov1) / n)
    bias = trans * v1 / 2 + 1e-12
    d = mean_s - mean1
    d[2] = wrap_angle(d[2])
    assert np.all(np.abs(d) < 5 * se + bias), (d, se)
    # covariance: whitened sample covariance ~ I; entries of a Wishart(n) / n matrix have
    # standard deviation <= sqrt(2 / n)
    L = np.linalg.cholesky(cov1)
    W = np.linalg.solve(L, np.linalg.solve(L, cov_s).T)
    assert np.max(np.abs(W - np.eye(3))) < 5 * math.sqrt(2 / n) + 0.01  # 0.01: 2nd-order terms
    # no noise: exact SE(2) relative motion applied in the particle's frame
    exact = OdometryMotionModel(0, 0, 0, 0).sample(x0[None], o0, o1, np.random.default_rng(0))[0]
    np.testing.assert_allclose(exact, se2_compose(x0, se2_between(o0, o1)), atol=1e-12)


def test_odometry_motion_model_details():
    m = OdometryMotionModel()
    # below min_trans the heading of the displacement is ignored: rot1 = 0
    assert m.decompose([0, 0, 0.3], [0.005, 0.0, 0.8])[0] == 0.0
    rot1, trans, rot2 = m.decompose([0, 0, 0], [1.0, 1.0, math.pi / 2])
    assert rot1 == pytest.approx(math.pi / 4) and trans == pytest.approx(math.sqrt(2)) and rot2 == pytest.approx(math.pi / 4)
    # driving backwards: rot1 ~ pi, but the noise sees ~0 rotation (ROS AMCL rule)
    r1, tr, r2 = m.decompose([0, 0, 0], [-1.0, 0.0, 0.0])
    assert abs(abs(r1) - math.pi) < 1e-12
    v1, vt, v2 = m.variances(r1, tr, r2)
    assert v1 == pytest.approx(0.2 * tr**2, abs=1e-12) and vt == pytest.approx(0.2 * tr**2, abs=1e-12)


# ----------------------------------------------------------------------------------------
# helpers: summary, reliability, KLD, SE(2)
# ----------------------------------------------------------------------------------------
def test_gaussian_summary_circular_mean_and_reliability():
    p = np.array([[0.0, 0.0, math.pi - 0.1], [2.0, 0.0, -math.pi + 0.1]])
    mean, cov = gaussian_summary(p, [1.0, 1.0])
    assert abs(abs(mean[2]) - math.pi) < 1e-12
    np.testing.assert_allclose(cov, [[1.0, 0.0, 0.1], [0.0, 0.0, 0.0], [0.1, 0.0, 0.01]], atol=1e-12)
    assert covariance_reliability(np.diag([0.09, 0.16, 1.0])) == pytest.approx(1 / 1.5)
    a = np.array([1.0, 2.0, 0.5])
    np.testing.assert_allclose(se2_compose(a, se2_inverse(a)), np.zeros(3), atol=1e-12)


def test_kld_sample_size_matches_chi_square_quantile():
    eps, delta = 0.05, 0.01
    z = 2.3263478740408408  # standard-normal quantile 1 - delta
    for k in (2, 5, 20, 100, 1000):
        exact = chi2.ppf(1 - delta, k - 1) / (2 * eps)  # Fox 2003, eq. 11
        assert kld_sample_size(k, eps, z) == pytest.approx(exact, rel=0.03, abs=2)
    assert kld_sample_size(1, eps, z) == 1


# ----------------------------------------------------------------------------------------
# sensor models against direct computation
# ----------------------------------------------------------------------------------------
def test_erfc_beam_model_against_direct_formula(world):
    g = world[0]
    rng = np.random.default_rng(5)
    poses = g.sample_free_poses(30, rng)
    angles = LASER.angles[::6]
    z = cast_rays(g, poses[:1], angles, 10.0)[0] + rng.normal(0, 0.05, angles.size)
    for two_sided in (True, False):
        exact = BeamErfcModel(0.1, two_sided=two_sided, raycast="exact")
        exact.prepare(g, 10.0)
        ll_e, n = exact.log_likelihood(g.pose_to_grid(poses), z, angles)
        assert n == 1
        zhat = cast_rays(g, poses, angles, 10.0)
        d = z[None, :] - zhat
        direct = np.log(erfc((np.abs(d) if two_sided else d) / (0.1 * math.sqrt(2))).mean(axis=1))
        np.testing.assert_allclose(ll_e, np.maximum(direct, math.log(1e-300)), rtol=1e-12)
        if not two_sided:
            assert np.exp(ll_e).max() <= 2.0
    # the table version: the same up to the table's range errors
    tab = BeamErfcModel(0.1, theta_bins=720)
    tab.prepare(g, 10.0)
    ll_t, _ = tab.log_likelihood(g.pose_to_grid(poses), z, angles)
    exact = BeamErfcModel(0.1, raycast="exact")
    exact.prepare(g, 10.0)
    ll_e, _ = exact.log_likelihood(g.pose_to_grid(poses), z, angles)
    assert np.argmax(ll_t) == np.argmax(ll_e) == 0
    assert abs(ll_t[0] - ll_e[0]) < 0.2


def test_likelihood_field_against_direct_computation(world):
    g = world[0]
    rng = np.random.default_rng(6)
    poses = g.sample_free_poses(20, rng)
    poses[0] = [-5.0, 30.0, 0.3]  # off the map
    angles = LASER.angles[::4]
    z = rng.uniform(0.2, 12.0, angles.size)  # some beyond max range (skipped)
    m = LikelihoodFieldModel(0.2, 0.9, 0.1, max_distance=2.0)
    m.prepare(g, 10.0)
    ll, n = m.log_likelihood(g.pose_to_grid(poses), z, angles)
    use = z < 10.0
    assert n == use.sum()
    sd = g.surface_distance_field()
    for p in range(poses.shape[0]):
        total = 0.0
        for zz, a in zip(z[use], angles[use]):
            e = poses[p, :2] + zz * np.array([math.cos(poses[p, 2] + a), math.sin(poses[p, 2] + a)])
            i, j = g.world_to_cell(e[None])
            d = sd[i[0], j[0]] if g.in_bounds(i, j)[0] else 2.0
            d = min(d, 2.0)
            total += math.log(0.9 * math.exp(-0.5 * (d / 0.2) ** 2) / (math.sqrt(2 * math.pi) * 0.2) + 0.1 / 10.0)
        assert ll[p] == pytest.approx(total, rel=1e-5, abs=1e-4)


def test_likelihood_field_beam_skip_against_direct_computation(world):
    """AMCL's beam skipping, written out here: per beam, the share of particles whose end
    point lies within 0.5 m of the map's surface; beams at or below 0.3 are left out of
    every particle's product, unless 90 % of the beams would be."""
    g, path, _, _ = world
    rng = np.random.default_rng(7)
    true = path[30]
    angles = LASER.angles[::6]
    z = cast_rays(g, true[None], angles, 10.0)[0] + rng.normal(0, 0.01, angles.size)
    sd = g.surface_distance_field()

    def surface_distance(pose, ranges):
        e = pose[:2] + ranges[:, None] * np.column_stack([np.cos(pose[2] + angles), np.sin(pose[2] + angles)])
        i, j = g.world_to_cell(e)
        inside = g.in_bounds(i, j)
        return np.where(inside, sd[np.clip(i, 0, sd.shape[0] - 1), np.clip(j, 0, sd.shape[1] - 1)], 2.0)

    # unmapped obstacles: some beams end half-way, more than 1 m from any mapped surface
    occluded = np.flatnonzero(surface_distance(true, 0.5 * z) > 1.0)[:6]
    assert occluded.size >= 3
    z[occluded] *= 0.5
    poses = true + rng.normal(0, [0.05, 0.05, 0.02], (200, 3))
    plain = LikelihoodFieldModel()
    plain.prepare(g, 10.0)
    skip = LikelihoodFieldModel(beam_skip=True)
    skip.prepare(g, 10.0)
    lp = g.pose_to_grid(poses)
    use = z < 10.0
    near = np.array([surface_distance(p, z) <= 0.5 for p in poses])
    keep = use & (near.mean(axis=0) > 0.3)
    assert 0 < (use & ~keep).sum() < 0.9 * use.sum()
    assert not keep[occluded].any()  # the occluded beams are among the skipped ones
    ll, n = skip.log_likelihood(lp, z, angles)
    ref, n_ref = plain.log_likelihood(lp, z[keep], angles[keep])
    assert n == n_ref == keep.sum() and skip.skipped_beams == use.sum() - keep.sum()
    np.testing.assert_allclose(ll, ref, rtol=1e-6)
    # when at least beam_skip_error_threshold of the beams would be skipped, all are used
    strict = LikelihoodFieldModel(beam_skip=True, beam_skip_error_threshold=0.5 * (use & ~keep).sum() / use.sum())
    strict.prepare(g, 10.0)
    ll_all, n_all = strict.log_likelihood(lp, z, angles)
    assert n_all == use.sum() and strict.beam_skip_errors == 1 and skip.beam_skip_errors == 0
    np.testing.assert_allclose(ll_all, plain.log_likelihood(lp, z, angles)[0], rtol=1e-6)


def test_likelihood_field_random_distance_closed_form():
    """``r`` of ``short_skip`` is where the two mixture terms are equal:
    ``z_hit N(r; 0, sigma_hit^2) = z_rand / z_max`` (checked with scipy's normal density)."""
    from scipy.stats import norm

    for sigma, z_hit, z_rand, z_max in ((0.2, 0.95, 0.05, 30.0), (0.1, 0.5, 0.5, 10.0), (0.3, 0.9, 0.1, 5.0)):
        m = LikelihoodFieldModel(sigma, z_hit, z_rand, max_distance=5.0)
        r = m.random_distance(z_max)
        assert z_hit * norm.pdf(r, scale=sigma) == pytest.approx(z_rand / z_max, rel=1e-9)
    assert LikelihoodFieldModel().random_distance(30.0) == pytest.approx(0.7503, abs=1e-4)
    # the Gaussian never exceeds the uniform term: every end point is "random"
    assert LikelihoodFieldModel(1.0, 0.01, 0.99).random_distance(1.0) == 0.0
    # no uniform term: capped at max_distance
    assert LikelihoodFieldModel(0.2, 1.0, 0.0).random_distance(30.0) == 2.0


def test_likelihood_field_short_skip_against_brute_force(world):
    """``short_skip`` written out: at the particles' mean pose (unweighted, circular mean
    heading) a beam is short if its reading is shorter than the range to the first blocking
    cell along the ray (found here by stepping 1 mm along it) and its end point is more
    than ``r`` from the map's surface; short beams leave every particle's product."""
    g, path, _, _ = world
    rng = np.random.default_rng(11)
    true = path[30]
    angles = LASER.angles[::6]
    z = cast_rays(g, true[None], angles, 10.0)[0] + rng.normal(0, 0.01, angles.size)
    sd = g.surface_distance_field()

    def surface_distance(pose, ranges):
        e = pose[:2] + ranges[:, None] * np.column_stack([np.cos(pose[2] + angles), np.sin(pose[2] + angles)])
        i, j = g.world_to_cell(e)
        inside = g.in_bounds(i, j)
        return np.where(inside, sd[np.clip(i, 0, sd.shape[0] - 1), np.clip(j, 0, sd.shape[1] - 1)], 2.0)

    # unmapped obstacles: some beams end half-way, more than 1 m from any mapped surface
    occluded = np.flatnonzero(surface_distance(true, 0.5 * z) > 1.0)[:6]
    assert occluded.size >= 3
    z[occluded] *= 0.5
    # the cloud 0.3 m off the true pose: beams ending at walls must still be kept
    off = true + np.array([0.25, -0.15, 0.03])
    poses = off + rng.normal(0, [0.05, 0.05, 0.02], (200, 3))
    mean = np.array([poses[:, 0].mean(), poses[:, 1].mean(),
                     math.atan2(np.sin(poses[:, 2]).mean(), np.cos(poses[:, 2]).mean())])
    steps = np.arange(0.0, 10.0, 0.001)
    zhat = np.empty(angles.size)
    for b, a in enumerate(angles):
        pts = mean[:2] + steps[:, None] * np.array([math.cos(mean[2] + a), math.sin(mean[2] + a)])
        hit = np.flatnonzero(g.is_blocked(pts))
        zhat[b] = steps[hit[0]] if hit.size else 10.0
    plain = LikelihoodFieldModel()
    plain.prepare(g, 10.0)
    r = plain.random_distance(10.0)
    dist = surface_distance(mean, z)
    short = (z < zhat) & (dist > r)
    # no beam within the brute force's 1 mm (or a cell's rounding of the distance) of a boundary
    assert np.all((np.abs(z - zhat) > 0.002) | ~(dist > r)) and np.all(np.abs(dist - r) > 0.01)
    assert set(occluded) <= set(np.flatnonzero(short)) and short.sum() == occluded.size
    model = LikelihoodFieldModel(short_skip=True)
    model.prepare(g, 10.0)
    lp = g.pose_to_grid(poses)
    np.testing.assert_array_equal(model.short_beams_at(g.pose_to_grid(mean[None])[0], z, angles), short)
    ll, n = model.log_likelihood(lp, z, angles)
    ref, n_ref = plain.log_likelihood(lp, z[~short], angles[~short])
    assert n == n_ref == angles.size - short.sum() and model.short_beams == short.sum()
    np.testing.assert_allclose(ll, ref, rtol=1e-6)
    # when at least beam_skip_error_threshold of the beams would be left out, all are used
    strict = LikelihoodFieldModel(short_skip=True, beam_skip_error_threshold=0.5 * short.sum() / angles.size)
    strict.prepare(g, 10.0)
    ll_all, n_all = strict.log_likelihood(lp, z, angles)
    assert n_all == angles.size and strict.short_beams == 0
    np.testing.assert_allclose(ll_all, plain.log_likelihood(lp, z, angles)[0], rtol=1e-6)


def test_beam_selection_valid_spreads_the_budget_over_usable_beams(world):
    """``beam_selection="valid"``: ``max_beams`` evenly spaced indices among the beams with a
    reading below ``max_range`` (the others never reach the sensor model)."""
    g, path, scans, odo = world
    seen = {}
    for mode in ("all", "valid"):
        mcl = MonteCarloLocalization(g, LASER, max_particles=300, max_beams=20, beam_selection=mode, rng=0)
        calls = []
        orig = mcl.sensor.log_likelihood
        mcl.sensor.log_likelihood = lambda lp, z, a, _o=orig, _c=calls: (_c.append(a.copy()), _o(lp, z, a))[1]
        mcl.predict(0.0, odo[0])
        mcl.initialize_gaussian(path[0], np.diag([0.05, 0.05, 0.02]) ** 2)
        z = scans[1].copy()
        z[::2] = np.inf  # every other beam: no return
        z[100:] = LASER.max_range + 1.0  # and the left part beyond the range
        mcl.predict(0.1, odo[1])
        mcl.update(0.1, z)
        seen[mode] = calls[0]
    usable = np.flatnonzero(np.isfinite(z) & (z < LASER.max_range))
    expect = usable[np.round(np.linspace(0, usable.size - 1, 20)).astype(int)]
    np.testing.assert_array_equal(seen["valid"], LASER.angles[expect])
    # of the evenly spaced beams most have no reading within range
    assert np.isin(seen["all"], LASER.angles[usable]).sum() < 20 // 2
    with pytest.raises(ValidationError):
        MonteCarloLocalization(g, LASER, beam_selection="some")


def _clusters_brute_force(poses, w, bins):
    """Connected bins by pairwise comparison and union-find (the reference)."""
    n_th = math.ceil(2 * math.pi / bins[2])
    b = np.floor(poses / bins).astype(int)
    b[:, 2] %= n_th
    keys = sorted({tuple(x) for x in b})
    parent = list(range(len(keys)))

    def find(i):
        while parent[i] != i:
            i = parent[i]
        return i

    for i, u in enumerate(keys):
        for j, v in enumerate(keys[:i]):
            dth = abs(u[2] - v[2]) % n_th
            if abs(u[0] - v[0]) <= 1 and abs(u[1] - v[1]) <= 1 and min(dth, n_th - dth) <= 1:
                parent[find(i)] = find(j)
    root = {k: find(i) for i, k in enumerate(keys)}
    lab = np.array([root[tuple(x)] for x in b])
    tot = {r: w[lab == r].sum() for r in set(lab)}
    return lab == max(tot, key=tot.get)


def test_heaviest_cluster_against_brute_force():
    rng = np.random.default_rng(11)
    bins = np.array([0.5, 0.5, math.radians(10.0)])
    for trial in range(20):
        k = rng.integers(1, 5)
        centres = np.column_stack([rng.uniform(-3, 3, (k, 2)), rng.uniform(-math.pi, math.pi, k)])
        p = np.concatenate([c + rng.normal(0, [0.3, 0.3, 0.1], (rng.integers(20, 200), 3)) for c in centres])
        p[:, 2] = wrap_angle(p[:, 2])
        w = rng.uniform(0.1, 1.0, p.shape[0])
        np.testing.assert_array_equal(heaviest_cluster(p, w, bins), _clusters_brute_force(p, w, bins))


def test_estimate_cluster_reports_the_heavier_mode(world):
    g, path, _, odo = world
    mcl = MonteCarloLocalization(g, LASER, max_particles=2000, rng=0, estimate_cluster=True)
    plain = MonteCarloLocalization(g, LASER, max_particles=2000, rng=0)
    rng = np.random.default_rng(3)
    a = path[10] + rng.normal(0, [0.05, 0.05, 0.02], (600, 3))
    b = path[10] + [2.0, 0.0, 0.0] + rng.normal(0, [0.05, 0.05, 0.02], (400, 3))
    parts = np.vstack([a, b])
    for m in (mcl, plain):
        m.initialize_particles(parts, t=0.0)
    e, e_all = mcl.estimate(), plain.estimate()
    np.testing.assert_allclose(e.mean, gaussian_summary(a)[0], atol=1e-9)
    np.testing.assert_allclose(e_all.mean, gaussian_summary(parts)[0], atol=1e-9)
    # covariance: second moment of all particles about the reported mean
    r = parts - e.mean
    r[:, 2] = wrap_angle(r[:, 2])
    np.testing.assert_allclose(e.cov, r.T @ r / parts.shape[0], atol=1e-12)
    assert e.cov[0, 0] > e_all.cov[0, 0]  # the second mode still shows
    # one mode: the plain Gaussian summary
    for m in (mcl, plain):
        m.initialize_particles(a, t=0.0)
    np.testing.assert_allclose(mcl.estimate().mean, plain.estimate().mean, atol=1e-12)
    np.testing.assert_allclose(mcl.estimate().cov, plain.estimate().cov, atol=1e-12)


# ----------------------------------------------------------------------------------------
# the filter
# ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("sensor", ["likelihood_field", "erfc"])
def test_mcl_tracks_from_a_known_ish_start(world, sensor):
    g, path, scans, odo = world
    mcl = MonteCarloLocalization(g, LASER, sensor=sensor, max_particles=5000, rng=1)
    mcl.predict(0.0, odo[0])
    mcl.initialize_gaussian(path[0] + [0.3, -0.2, 0.1], np.diag([0.3, 0.3, 0.2]) ** 2)
    err = _run(mcl, path, scans, odo)
    assert err[15:, 0].mean() < 0.05 and err[15:, 0].max() < 0.2
    assert err[15:, 1].mean() < 0.05
    e = mcl.estimate()
    assert e.reliability > 0.8 and e.t == pytest.approx(8.9)
    # KLD: a converged filter keeps far fewer particles than the maximum
    assert e.n_particles < 5000


def test_mcl_global_localization_from_uniform_prior(world):
    g, path, scans, odo = world
    mcl = MonteCarloLocalization(g, LASER, sensor="likelihood_field", max_particles=20000, rng=2)
    mcl.predict(0.0, odo[0])
    mcl.initialize_global()
    assert mcl.estimate().n_particles == 20000 and mcl.estimate().reliability < 0.3
    err = _run(mcl, path, scans, odo)
    assert err[10:, 0].max() < 0.2 and err[10:, 0].mean() < 0.05


def test_adaptive_tempering_keeps_the_ess_floor(world):
    g, path, scans, odo = world
    mcl = MonteCarloLocalization(g, LASER, adaptive=False, n_particles=2000, resample_threshold=0.0, ess_floor=0.05, rng=3)
    mcl.initialize_global()
    assert mcl.update(0.0, scans[0])
    assert 0 < mcl.last_beta < 1
    assert mcl.n_eff == pytest.approx(0.05 * 2000, rel=1e-3)
    plain = MonteCarloLocalization(g, LASER, adaptive=False, n_particles=2000, resample_threshold=0.0, ess_floor=0.0, rng=3)
    plain.initialize_global()
    plain.update(0.0, scans[0])
    assert plain.last_beta == 1.0 and plain.n_eff < 2


def test_mcl_global_localization_erfc(world):
    g, path, scans, odo = world
    mcl = MonteCarloLocalization(g, LASER, sensor=BeamErfcModel(0.1, theta_bins=180), max_particles=20000, rng=3)
    mcl.predict(0.0, odo[0])
    mcl.initialize_global()
    err = _run(mcl, path, scans, odo)
    # the averaged erfc likelihood discriminates less per scan: allow 45 scans
    assert err[45:, 0].max() < 0.2 and err[45:, 0].mean() < 0.05


def test_mcl_recovers_from_kidnapping_only_with_augmented_mcl(world):
    g, path, scans, odo = world
    # the robot is carried from path[40] to another free place; odometry notices nothing
    k0 = 40
    shift = se2_compose(np.array([9.5, 6.5, -1.5]), se2_inverse(path[0]))  # another room, 8 m away
    path2 = path.copy()
    path2[k0:] = se2_compose(shift, path[: len(path) - k0])
    assert g.is_free(path2[:, :2]).all()
    rng = np.random.default_rng(9)
    scans2 = cast_rays(g, path2, LASER.angles, 10.0) + rng.normal(0, 0.02, scans.shape)
    odo2 = odo.copy()
    for k in range(k0, len(path)):  # odometry continues smoothly through the kidnapping
        step = np.zeros(3) if k == k0 else se2_between(path2[k - 1], path2[k])
        odo2[k] = se2_compose(odo2[k - 1], step)
    results = {}
    for a_s, a_f in ((0.001, 0.1), (0.0, 0.0)):
        mcl = MonteCarloLocalization(g, LASER, max_particles=10000, alpha_slow=a_s, alpha_fast=a_f, rng=4)
        mcl.predict(0.0, odo2[0])
        mcl.initialize_gaussian(path2[0], np.diag([0.1, 0.1, 0.05]) ** 2)
        results[a_f] = (_run(mcl, path2, scans2, odo2), mcl.stats["injected"])
    err, injected = results[0.1]
    assert err[: k0 - 1, 0].mean() < 0.05
    assert injected > 0
    assert err[-10:, 0].max() < 0.15  # recovered (measured over 6 seeds: 3-33 scans after)
    assert results[0.0][0][-10:, 0].min() > 1.0 and results[0.0][1] == 0  # lost for good


def test_late_scans_equal_in_order_processing_without_motion_noise(world):
    """With noise-free motion, a scan applied late (back-propagation) gives exactly the
    weights of processing it in time order."""
    g, path, scans, odo = world
    filters = []
    for order in ("in_order", "late"):
        mcl = MonteCarloLocalization(
            g,
            LASER,
            motion=OdometryMotionModel(0, 0, 0, 0),
            adaptive=False,
            n_particles=500,
            resample_threshold=0.0,
            alpha_slow=0.0,
            alpha_fast=0.0,
            ess_floor=0.0,  # tempering depends on the current weights, hence on the order
            rng=8,
        )
        mcl.predict(0.0, odo[0])
        mcl.initialize_gaussian(path[0], np.diag([0.2, 0.2, 0.1]) ** 2)
        for k in (1, 2, 3):
            mcl.predict(0.1 * k, odo[k])
        if order == "in_order":
            mcl.update(0.1, scans[1])
            mcl.update(0.2, scans[2])
            mcl.update(0.3, scans[3])
        else:
            mcl.update(0.3, scans[3])
            mcl.update(0.1, scans[1])  # late by 0.2 s
            mcl.update(0.2, scans[2])  # late by 0.1 s
            assert mcl.stats["late_scans"] == 2
        assert mcl.time == pytest.approx(0.3)
        filters.append(mcl)
    np.testing.assert_allclose(filters[0].particles, filters[1].particles, atol=1e-9)
    np.testing.assert_allclose(filters[0].weights, filters[1].weights, rtol=1e-6, atol=1e-12)


def test_delayed_and_out_of_order_scans_keep_tracking(world):
    g, path, scans, odo = world
    mcl = MonteCarloLocalization(g, LASER, max_particles=5000, rng=5)
    mcl.predict(0.0, odo[0])
    mcl.initialize_gaussian(path[0], np.diag([0.1, 0.1, 0.05]) ** 2)
    delay = 3  # scans arrive 0.3 s late, pairs swapped
    pending = []
    err = []
    for k in range(1, len(path)):
        mcl.predict(0.1 * k, odo[k])
        pending.append(k)
        if len(pending) > delay + 1:
            # the two oldest pending scans, newer one first: the older one is then late
            # (stamped before the filter time)
            for j in (pending[1], pending[0]):
                mcl.update(0.1 * j, scans[j])
            del pending[:2]
            e = mcl.estimate()  # refers to the filter time, 0.1 * (k - delay)
            err.append(math.hypot(*(e.mean[:2] - path[k - delay, :2])))
    assert mcl.stats["late_scans"] > 40
    assert np.mean(err[10:]) < 0.06


def test_time_errors_leave_the_filter_unchanged(world):
    g, path, scans, odo = world
    mcl = MonteCarloLocalization(g, LASER, max_particles=1000, odom_window=0.5, rng=6)
    with pytest.raises(NotInitializedError):
        mcl.update(0.0, scans[0])
    mcl.initialize_gaussian(path[0], np.diag([0.1, 0.1, 0.05]) ** 2)
    for k in range(12):
        mcl.predict(0.1 * k, odo[k])
    mcl.update(1.1, scans[11])
    before = (mcl.particles, mcl.weights, mcl.time)
    with pytest.raises(OutsideWindowError):
        mcl.update(0.2, scans[2])  # older than the 0.5 s odometry buffer
    with pytest.raises(OutsideWindowError):
        mcl.update(1.5, scans[11])  # 0.4 s ahead of the newest odometry
    with pytest.raises(TimeError):
        mcl.predict(0.5, odo[5])
    with pytest.raises(ShapeError):
        mcl.update(1.1, scans[11][:10])
    np.testing.assert_array_equal(mcl.particles, before[0])
    np.testing.assert_array_equal(mcl.weights, before[1])
    assert mcl.time == before[2]
    # a scan slightly ahead of the odometry is applied at the newest odometry time
    assert mcl.update(1.15, scans[11]) and mcl.time == pytest.approx(1.1)


def test_update_thresholds_skip_scans_while_standing_still(world):
    g, path, scans, odo = world
    mcl = MonteCarloLocalization(g, LASER, max_particles=1000, update_min_d=0.2, update_min_a=0.5, rng=7)
    mcl.predict(0.0, odo[0])
    mcl.initialize_gaussian(path[0], np.diag([0.1, 0.1, 0.05]) ** 2)
    assert mcl.update(0.0, scans[0])
    mcl.predict(0.1, odo[0])
    assert not mcl.update(0.1, scans[0])  # no motion: skipped
    mcl.predict(0.2, odo[2])  # 0.3 m
    assert mcl.update(0.2, scans[2])
    assert mcl.stats["skipped_scans"] == 1
