"""Gating and association (dfusion.tracking.gating, .association) against brute-force enumeration
of every joint hypothesis, and the JPDA track update against a mixture of filterpy Kalman updates."""
from __future__ import annotations

import itertools

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from scipy.stats import chi2, multivariate_normal

from dfusion.estimation import ExtendedInformationFilter
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.tracking import GNN, JPDA, GaussianHypothesiser, Scan, Track, TrackId, ehm_marginals, gated_clusters
from dfusion.tracking.tracker import track_update_information


def joint_hypotheses(gated):
    """Every feasible joint hypothesis: a tuple a with a[t] = -1 (missed) or a gated detection, all distinct."""
    T, k = gated.shape
    options = [[-1] + list(np.flatnonzero(gated[t])) for t in range(T)]
    for a in itertools.product(*options):
        used = [j for j in a if j >= 0]
        if len(used) == len(set(used)):
            yield a


def brute_marginals(g, g0, gated):
    T, k = gated.shape
    beta, beta0, Z = np.zeros((T, k)), np.zeros(T), 0.0
    for a in joint_hypotheses(gated):
        p = np.prod([g0[t] if j < 0 else g[t, j] for t, j in enumerate(a)])
        Z += p
        for t, j in enumerate(a):
            if j < 0:
                beta0[t] += p
            else:
                beta[t, j] += p
    return beta / Z, beta0 / Z


def make_tracks(means, cov):
    tracks = []
    for i, m in enumerate(means):
        f = ExtendedInformationFilter(ConstantVelocity(2, 0.1))
        f.initialize(m, cov)
        tracks.append(Track(TrackId("n", i), f, 0.0, 0.0, confirmed=True))
    return tracks


@pytest.mark.parametrize("seed", range(12))
def test_ehm_marginals_equal_brute_force_enumeration(seed):
    rng = np.random.default_rng(seed)
    T, k = int(rng.integers(1, 6)), int(rng.integers(0, 7))
    gated = rng.uniform(size=(T, k)) < 0.6
    g = np.where(gated, rng.uniform(0.01, 5.0, (T, k)), 0.0)
    g0 = rng.uniform(0.01, 2.0, T)
    beta, beta0 = ehm_marginals(g, g0)
    ref, ref0 = brute_marginals(g, g0, gated)
    np.testing.assert_allclose(beta, ref, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(beta0, ref0, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(beta.sum(axis=1) + beta0, 1.0, rtol=1e-12)


def test_clusters_are_the_connected_components_of_the_gate():
    gated = np.array([[1, 0, 0, 0], [1, 1, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1], [0, 0, 0, 0]], bool)
    groups = sorted((tuple(t), tuple(d)) for t, d in gated_clusters(gated))
    assert groups == [((0, 1, 2), (0, 1)), ((3,), (3,))]


def scene(seed, T=4, k=6, spread=3.0):
    rng = np.random.default_rng(seed)
    means = [np.array([*rng.uniform(0, spread, 2), *rng.normal(0, 1, 2)]) for _ in range(T)]
    cov = np.diag([0.4, 0.4, 1.0, 1.0])
    tracks = make_tracks(means, cov)
    Z = rng.uniform(-0.5, spread + 0.5, (k, 2))
    scan = Scan(0.0, Z, PositionSensor(2, 0.3), clutter_density=0.05, detection_probability=0.9)
    return tracks, scan


@pytest.mark.parametrize("seed", range(5))
def test_jpda_weights_are_the_brute_force_marginals_of_the_gaussian_likelihoods(seed):
    tracks, scan = scene(seed)
    hyp = GaussianHypothesiser(0.99).hypothesise(tracks, scan)
    R = scan.sensor.R
    gamma = chi2.ppf(0.99, 2)
    g = np.zeros(hyp.shape)
    gated = np.zeros(hyp.shape, bool)
    for t, tr in enumerate(tracks):
        x, P = tr.estimate()
        S = P[:2, :2] + R
        for j, z in enumerate(scan.detections):
            d = z - x[:2]
            if d @ np.linalg.solve(S, d) <= gamma:
                gated[t, j] = True
                g[t, j] = 0.9 * multivariate_normal(x[:2], S).pdf(z)
    g0 = np.full(len(tracks), 0.05 * (1 - 0.9 * 0.99))
    np.testing.assert_array_equal(hyp.gated, gated)
    assoc = JPDA().associate(hyp)
    ref, ref0 = brute_marginals(g, g0, gated)
    np.testing.assert_allclose(assoc.weights, ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(assoc.miss, ref0, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_gnn_takes_the_most_probable_joint_hypothesis(seed):
    tracks, scan = scene(seed)
    hyp = GaussianHypothesiser(0.99).hypothesise(tracks, scan)
    g = np.exp(hyp.log_weight)
    g0 = np.exp(hyp.log_miss)
    best = max(joint_hypotheses(hyp.gated),
               key=lambda a: np.prod([g0[t] if j < 0 else g[t, j] for t, j in enumerate(a)]))
    assoc = GNN().associate(hyp)
    got = tuple(int(np.flatnonzero(assoc.weights[t])[0]) if assoc.miss[t] == 0 else -1 for t in range(len(tracks)))
    assert got == best


def test_jpda_track_update_is_the_mixture_of_kalman_updates_over_joint_hypotheses():
    """Two tracks, three detections, well inside every gate: each track's posterior is the moment match of
    beta_t0 N(prior) + sum_j beta_tj KF(prior, z_j), each KF a filterpy update; the information form
    reproduces it when every direction is kept."""
    means = [np.array([0.0, 0.0, 1.0, 0.0]), np.array([0.6, 0.2, 0.0, 1.0])]
    cov = np.diag([0.5, 0.5, 1.0, 1.0])
    tracks = make_tracks(means, cov)
    Z = np.array([[0.1, 0.05], [0.5, 0.3], [0.3, -0.1]])
    scan = Scan(0.0, Z, PositionSensor(2, 0.3), clutter_density=0.5, detection_probability=0.9)
    hyp = GaussianHypothesiser(0.999).hypothesise(tracks, scan)
    assert hyp.gated.all()
    assoc = JPDA().associate(hyp)
    for t, tr in enumerate(tracks):
        comps = [(assoc.miss[t], means[t], cov)]
        for j, z in enumerate(Z):
            kf = KalmanFilter(dim_x=4, dim_z=2)
            kf.x, kf.P, kf.R = means[t].copy(), cov.copy(), np.eye(2) * 0.09
            kf.H = np.hstack([np.eye(2), np.zeros((2, 2))])
            kf.update(z)
            comps.append((assoc.weights[t, j], kf.x.copy(), kf.P.copy()))
        mean = sum(w * x for w, x, _ in comps)
        post = sum(w * (P + np.outer(x - mean, x - mean)) for w, x, P in comps)
        Lam, y = track_update_information(hyp, assoc, t)
        Omega = np.linalg.inv(cov) + Lam
        eta = np.linalg.solve(cov, means[t]) + y
        np.testing.assert_allclose(np.linalg.inv(Omega), post, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(np.linalg.solve(Omega, eta), mean, rtol=1e-9, atol=1e-12)


def test_a_track_out_of_view_takes_no_part():
    tracks, _ = scene(0, T=2, k=0)
    Z = np.array([tracks[0].estimate()[0][:2], tracks[1].estimate()[0][:2]])
    x0 = tracks[0].estimate()[0]
    scan = Scan(0.0, Z, PositionSensor(2, 0.3), 0.05, 0.9, in_view=lambda x: np.allclose(x, x0))
    hyp = GaussianHypothesiser().hypothesise(tracks, scan)
    for assoc in (JPDA().associate(hyp), GNN().associate(hyp)):
        assert assoc.active.tolist() == [True, False]
        assert assoc.miss[1] == 1.0 and not assoc.weights[1].any()
