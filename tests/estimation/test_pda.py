"""Probabilistic data association (dfusion.estimation.pda) against independent references: a
numerical integration of the mixture posterior, the closed-form mixture of per-hypothesis Kalman
updates (filterpy), and the information form's exactness and conservativeness."""
from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from scipy.stats import chi2, multivariate_normal

from dfusion.estimation.pda import (
    ClutterModel,
    frame_innovations,
    gate_threshold,
    pda_information,
    pda_update,
    pda_weights,
)
from dfusion.models import PositionSensor


def _grid_posterior(mean, cov, Z, R, density, pd, gate):
    """Posterior moments of x (2-D) under prior N(mean, cov) and the clutter likelihood of the
    validated detections, by summing on a fine grid. With Poisson clutter of density lambda and a
    target detected with P_D (inside the gate with P_G), the likelihood of the validated set,
    divided by lambda^(m-1), is (Bar-Shalom & Li 1995, sec. 3.4)

        l(x) = (1 - P_D P_G) lambda + P_D sum_i N(z_i; x, R).
    """
    g = np.linspace(-20.0, 20.0, 1201)   # the prior has standard deviations up to 3: +-20 holds all its mass
    X, Y = np.meshgrid(g, g, indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel()])

    def gauss(center, C):
        d = pts - center
        Ci = np.linalg.solve(C, np.eye(2))
        return np.exp(-0.5 * np.einsum("ij,jk,ik->i", d, Ci, d)) / (2 * np.pi * np.sqrt(np.linalg.det(C)))

    prior = gauss(mean, cov)
    S = cov + R
    valid = [z for z in Z if (z - mean) @ np.linalg.solve(S, z - mean) <= chi2.ppf(gate, 2)]
    lik = np.full(len(pts), (1.0 - pd * gate) * density)
    for z in valid:
        lik += pd * gauss(z, R)
    w = prior * lik
    w /= w.sum()
    m = w @ pts
    d = pts - m
    return m, (d * w[:, None]).T @ d, len(valid)


@pytest.mark.parametrize("seed", range(4))
def test_pda_update_equals_the_numerically_integrated_mixture_posterior(seed):
    rng = np.random.default_rng(seed)
    mean = rng.normal(size=2)
    A = rng.normal(size=(2, 2))
    cov = A @ A.T + 0.4 * np.eye(2)
    sensor = PositionSensor(2, 0.6)
    Z = mean + 1.3 * rng.normal(size=(4, 2))
    model = ClutterModel(density=0.04, detection=0.8, gate=0.99)
    res = pda_update(mean, cov, Z, sensor, model)
    m, P, nv = _grid_posterior(mean, cov, Z, sensor.R, 0.04, 0.8, 0.99)
    assert nv == int(res.validated.sum()) >= 1
    np.testing.assert_allclose(res.mean, m, atol=1e-6)
    np.testing.assert_allclose(res.cov, P, atol=1e-6)


def test_pda_update_equals_the_mixture_of_kalman_updates_on_a_4d_state():
    """Constant-velocity state, position detections: the PDA moments are those of the mixture
    beta_0 N(prior) + sum_i beta_i N(KF update with z_i), each update by filterpy, the weights
    from the predicted likelihoods N(z_i; H x, S) (scipy)."""
    rng = np.random.default_rng(3)
    mean = np.array([1.0, -2.0, 0.5, 0.2])
    B = rng.normal(size=(4, 4))
    cov = B @ B.T + np.diag([0.5, 0.5, 0.1, 0.1])
    sensor = PositionSensor(2, 0.5)
    H = np.hstack([np.eye(2), np.zeros((2, 2))])
    S = H @ cov @ H.T + sensor.R
    Z = mean[:2] + rng.multivariate_normal(np.zeros(2), S, size=3)
    lam, pd, pg = 0.02, 0.9, 0.999
    res = pda_update(mean, cov, Z, sensor, ClutterModel(lam, pd, pg))
    assert res.validated.all()
    comps, weights = [(mean, cov)], [(1.0 - pd * pg) * lam]
    for z in Z:
        kf = KalmanFilter(dim_x=4, dim_z=2)
        kf.x, kf.P, kf.H, kf.R = mean.copy(), cov.copy(), H, sensor.R
        kf.update(z)
        comps.append((kf.x.copy(), kf.P.copy()))
        weights.append(pd * multivariate_normal(H @ mean, S).pdf(z))
    w = np.array(weights) / sum(weights)
    m = sum(wi * c[0] for wi, c in zip(w, comps))
    P = sum(wi * (c[1] + np.outer(c[0] - m, c[0] - m)) for wi, c in zip(w, comps))
    assert res.beta0 == pytest.approx(w[0], rel=1e-9)
    np.testing.assert_allclose(res.beta, w[1:], rtol=1e-9)
    np.testing.assert_allclose(res.mean, m, atol=1e-10)
    np.testing.assert_allclose(res.cov, P, atol=1e-10)


def _posterior_from_information(mean, cov, info):
    Om = np.linalg.solve(cov, np.eye(len(mean))) + info.info
    P = np.linalg.solve(Om, np.eye(len(mean)))
    return P @ (np.linalg.solve(cov, mean) + info.vec), P


@pytest.mark.parametrize("seed", range(6))
def test_equivalent_information_reproduces_the_pda_moments_when_nothing_is_dropped(seed):
    rng = np.random.default_rng(seed)
    mean = np.array([0.5, 1.0, 0.3, -0.1])
    B = rng.normal(size=(4, 4))
    cov = B @ B.T + 0.3 * np.eye(4)
    sensor = PositionSensor(2, 0.7)
    H = np.hstack([np.eye(2), np.zeros((2, 2))])
    S = H @ cov @ H.T + sensor.R
    Z = mean[:2] + 0.5 * rng.multivariate_normal(np.zeros(2), S, size=2)   # close together
    res = pda_update(mean, cov, Z, sensor, ClutterModel(0.05, 0.9, 0.99))
    info = pda_information(res)
    assert info.exact and info.kept == 2
    m, P = _posterior_from_information(mean, cov, info)
    np.testing.assert_allclose(m, res.mean, atol=1e-9)
    np.testing.assert_allclose(P, res.cov, atol=1e-9)


def test_equivalent_information_is_psd_and_never_more_than_one_detection():
    rng = np.random.default_rng(11)
    sensor = PositionSensor(2, 0.7)
    H = np.hstack([np.eye(2), np.zeros((2, 2))])
    one = H.T @ np.linalg.solve(sensor.R, H)
    seen_dropped = 0
    for _ in range(200):
        mean = rng.normal(size=4)
        B = rng.normal(size=(4, 4))
        cov = B @ B.T + 0.2 * np.eye(4)
        S = H @ cov @ H.T + sensor.R
        Z = mean[:2] + 2.0 * rng.multivariate_normal(np.zeros(2), S, size=rng.integers(1, 5))
        res = pda_update(mean, cov, Z, sensor, ClutterModel(rng.uniform(0.001, 0.2), rng.uniform(0.3, 1.0), 0.99))
        info = pda_information(res)
        seen_dropped += info.dropped > 0
        assert np.linalg.eigvalsh(info.info).min() > -1e-9
        assert np.linalg.eigvalsh(one - info.info).min() > -1e-9      # R_eq >= R
        if info.kept:
            m, P = _posterior_from_information(mean, cov, info)
            assert np.linalg.eigvalsh(cov - P).min() > -1e-9          # information only adds
    assert seen_dropped > 10


def test_a_direction_where_pda_is_wider_than_the_prior_carries_no_information():
    """Two equally likely detections 2.6 sigma either side along x: the PDA posterior is bimodal
    and wider than the prior along x; the equivalent information drops x (no shift, no
    information) and keeps y exactly."""
    mean = np.zeros(2)
    cov = np.eye(2)
    sensor = PositionSensor(2, 0.5)
    s = math.sqrt(1.25)
    Z = np.array([[2.6 * s, 0.3], [-2.6 * s, 0.3]])
    res = pda_update(mean, cov, Z, sensor, ClutterModel(0.01, 0.9, 0.99))
    assert res.cov[0, 0] > cov[0, 0]
    info = pda_information(res)
    assert info.dropped == 1 and info.kept == 1
    assert abs(info.info[0, 0]) < 1e-12 and abs(info.vec[0]) < 1e-12
    m, P = _posterior_from_information(mean, cov, info)
    assert m[0] == pytest.approx(0.0, abs=1e-12) and P[0, 0] == pytest.approx(1.0)
    assert m[1] == pytest.approx(res.mean[1], abs=1e-12) and P[1, 1] == pytest.approx(res.cov[1, 1])


def test_weights_limits():
    S = np.diag([4.0, 9.0])
    assert pda_weights(np.zeros(0), S, 0.1, 0.9, 0.99) == (1.0, pytest.approx(np.zeros(0)))
    b0, b = pda_weights(np.array([1.0, 4.0]), S, 0.0, 0.9, 0.99)       # no clutter: one is the target
    assert b0 == 0.0 and b.sum() == pytest.approx(1.0) and b[0] / b[1] == pytest.approx(math.exp(1.5))
    assert pda_weights(np.array([1.0]), S, 0.1, 0.0, 0.99)[0] == 1.0     # never detected
    b0, b = pda_weights(np.array([5000.0]), S, 1e-3, 0.9, 1.0)          # no gate: no underflow
    assert b0 == pytest.approx(1.0) and np.isfinite(b).all()
    # Bar-Shalom's b = lambda |2 pi S|^1/2 (1 - P_D P_G) / P_D by hand
    lam, pd, pg, d2 = 0.01, 0.8, 0.99, np.array([2.0])
    bb = lam * math.sqrt(np.linalg.det(2 * math.pi * S)) * (1 - pd * pg) / pd
    e = math.exp(-1.0)
    assert pda_weights(d2, S, lam, pd, pg)[0] == pytest.approx(bb / (bb + e), rel=1e-12)


@pytest.mark.parametrize("dof", [1, 2, 3, 4, 6])
@pytest.mark.parametrize("gate", [0.5, 0.9, 0.99, 0.999, 1 - 1e-6])
def test_gate_threshold_is_scipys_chi_square_quantile(gate, dof):
    """The gate against scipy.stats.chi2.ppf (independent), for every dof, without scipy on the node's path."""
    assert gate_threshold(gate, dof) == pytest.approx(chi2.ppf(gate, dof), rel=1e-9)


def test_frame_innovations_are_scipys_gaussian_log_likelihoods():
    """nu_i, S and log N(nu_i; 0, S) = log_norm - d2 / 2 of a frame (what PDA and the multi-target
    hypothesiser share) against scipy's multivariate normal; no detections: empty, S still given."""
    rng = np.random.default_rng(5)
    sensor = PositionSensor(dim=2, std=0.7)
    A = rng.normal(size=(4, 4))
    mean, cov = rng.normal(size=4), A @ A.T + 0.1 * np.eye(4)
    Z = rng.normal(size=(3, 2)) * 2.0
    fi = frame_innovations(mean, cov, Z, sensor)
    S = cov[:2, :2] + 0.49 * np.eye(2)
    np.testing.assert_allclose(fi.S, S, rtol=1e-12)
    np.testing.assert_allclose(fi.innovations, Z - mean[:2], rtol=1e-12)
    np.testing.assert_allclose(fi.log_norm - 0.5 * fi.d2, multivariate_normal(mean[:2], S).logpdf(Z), rtol=1e-10)
    none = frame_innovations(mean, cov, np.zeros((0, 2)), sensor)
    assert none.innovations.shape == (0, 2) and none.d2.shape == (0,)
    np.testing.assert_allclose(none.S, S, rtol=1e-12)
