"""Tests of the radio map's noise laws, outlier floor and directional path loss (dfusion.localization.radio_map).

References are independent of the code under test: scipy.stats.norm and numerical
integration for the split normal, a general-purpose optimizer for its maximum-likelihood
fit, per-node loops for the bilinear look-up, numpy.linalg.lstsq on an augmented system for
the ridge fit, and dfusion.models.fit_path_loss for the plain log-distance case.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate, optimize, stats

from dfusion.errors import ValidationError
from dfusion.models import fit_path_loss, RSSISensor
from dfusion.localization import WSNTracker
from dfusion.localization import (
    fit_directional_path_loss,
    fit_split_normal,
    path_loss_design,
    RadioMap,
    split_normal_logpdf,
)


def _split_ref(u, m, sl, sr):
    """Split normal as two scaled normal halves: 2 sl / (sl + sr) N(u; m, sl^2) below m, likewise above."""
    u = np.asarray(u, dtype=float)
    lo = np.log(2 * sl / (sl + sr)) + stats.norm.logpdf(u, m, sl)
    hi = np.log(2 * sr / (sl + sr)) + stats.norm.logpdf(u, m, sr)
    return np.where(u < m, lo, hi)


def _split_sample(rng, n, m, sl, sr):
    left = rng.random(n) < sl / (sl + sr)
    h = np.abs(rng.standard_normal(n))
    return np.where(left, m - sl * h, m + sr * h)


def test_split_normal_logpdf_against_scipy_and_normalization():
    m, sl, sr = 0.6, 1.4, 0.6
    u = np.linspace(-8, 5, 501)
    np.testing.assert_allclose(split_normal_logpdf(u, m, sl, sr), _split_ref(u, m, sl, sr), rtol=1e-12, atol=1e-12)
    f = lambda x: np.exp(split_normal_logpdf(x, m, sl, sr))  # noqa: E731
    total = integrate.quad(f, -np.inf, m)[0] + integrate.quad(f, m, np.inf)[0]
    assert total == pytest.approx(1.0, abs=1e-9)
    mean = integrate.quad(lambda x: x * f(x), -np.inf, m)[0] + integrate.quad(lambda x: x * f(x), m, np.inf)[0]
    assert mean == pytest.approx(m + np.sqrt(2 / np.pi) * (sr - sl), abs=1e-8)
    # equal sides: the normal law
    np.testing.assert_allclose(split_normal_logpdf(u, 0.3, 2.0, 2.0), stats.norm.logpdf(u, 0.3, 2.0), rtol=1e-12)
    with pytest.raises(ValidationError):
        split_normal_logpdf(u, 0.0, 0.0, 1.0)


def test_fit_split_normal_is_the_maximum_likelihood():
    rng = np.random.default_rng(7)
    for true in ((0.57, 1.37, 0.62), (-2.0, 0.5, 3.0), (1.0, 1.0, 1.0)):
        u = _split_sample(rng, 4000, *true)
        got = fit_split_normal(u)
        nll = lambda p: -np.sum(_split_ref(u, p[0], np.exp(p[1]), np.exp(p[2])))  # noqa: E731
        best = None
        for start in ([np.median(u), 0.0, 0.0], [u.mean() - 1, 0.5, -0.5], [u.mean() + 1, -0.5, 0.5]):
            r = optimize.minimize(nll, start, method="Nelder-Mead",
                                  options=dict(xatol=1e-9, fatol=1e-10, maxiter=20000, maxfev=40000))
            best = r if best is None or r.fun < best.fun else best
        ref = (best.x[0], np.exp(best.x[1]), np.exp(best.x[2]))
        # the closed-form profile fit is at least as likely as the optimizer's and at the same point
        assert nll([got[0], np.log(got[1]), np.log(got[2])]) <= best.fun + 1e-6
        np.testing.assert_allclose(got, ref, rtol=2e-3, atol=2e-3)
        np.testing.assert_allclose(got, true, rtol=0.1, atol=0.1)  # and it recovers the law
    with pytest.raises(ValidationError):
        fit_split_normal([1.0, 1.0, 1.0, 1.0])
    with pytest.raises(ValidationError):
        fit_split_normal([0.0, 1.0])


def _small_map(rng, noise=None):
    mean = rng.normal(-72.0, 8.0, (3, 6, 5))
    std = rng.uniform(3.0, 7.0, (3, 6, 5))
    return RadioMap((1.0, -0.5), 0.4, mean, std, ["a"], noise)


def _node_total_ref(rm, z, j, s=1.0, eps=0.0, span=60.0):
    """Per-node total log-density of the readings, by loops over nodes and readings."""
    nx, ny = rm.shape
    T = np.zeros((nx, ny))
    for ix in range(nx):
        for iy in range(ny):
            for zk, jk in zip(z, j):
                M, S = rm.mean[jk, ix, iy], rm.std[jk, ix, iy]
                u = (zk - M) / (s * S)
                if rm.noise is None:
                    lf = stats.norm.logpdf(u) - np.log(s * S)
                else:
                    lf = _split_ref(u, *rm.noise) - np.log(s * S)
                if eps > 0:
                    lf = np.log((1 - eps) * np.exp(lf) + eps / span)
                T[ix, iy] += lf
    return T


def _bilinear_ref(rm, T, xy):
    """Bilinear interpolation of a node field, edge values off the grid, one point at a time."""
    nx, ny = rm.shape
    out = []
    for x, y in xy:
        u = min(max((x - rm.origin[0]) / rm.cell, 0.0), nx - 1.0)
        v = min(max((y - rm.origin[1]) / rm.cell, 0.0), ny - 1.0)
        i, k = min(int(u), nx - 2), min(int(v), ny - 2)
        a, b = u - i, v - k
        out.append((1 - a) * (1 - b) * T[i, k] + (1 - a) * b * T[i, k + 1] + a * (1 - b) * T[i + 1, k]
                   + a * b * T[i + 1, k + 1])
    return np.array(out)


@pytest.mark.parametrize("noise", [(0.6, 1.4, 0.6), None])
@pytest.mark.parametrize("eps", [0.0, 0.1])
def test_map_likelihood_with_split_noise_and_outlier_floor(noise, eps):
    rng = np.random.default_rng(11)
    rm = _small_map(rng, noise)
    z, j = np.array([-70.0, -81.0, -60.0, -75.0]), np.array([0, 2, 1, 0])
    nodes = np.column_stack([rm.origin[0] + rm.cell * rng.integers(0, 6, 40),
                             rm.origin[1] + rm.cell * rng.integers(0, 5, 40)])
    inside = rng.uniform(rm.origin + 0.05, rm.origin + rm.cell * np.array([5, 4]) - 0.05, (60, 2))
    outside = np.array([[-3.0, 0.1], [9.0, 9.0], [1.5, -4.0]])  # off the grid: edge values
    for s in (1.0, 1.6):
        T = _node_total_ref(rm, z, j, s, eps)
        if noise is None and eps == 0:
            # the Gaussian path interpolates coefficients; exact at nodes up to the dropped constant
            got = rm.log_likelihood(z, j, nodes, s)
            ref = _bilinear_ref(rm, T, nodes) + len(z) * (0.5 * np.log(2 * np.pi) + np.log(s))
            np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-9)
            continue
        for xy in (nodes, inside, outside):
            got = rm.log_likelihood(z, j, xy, s, outlier_prob=eps, rssi_span=60.0)
            np.testing.assert_allclose(got, _bilinear_ref(rm, T, xy), rtol=1e-10, atol=1e-9)
        # a particle's value does not depend on the others (the evaluated node box)
        np.testing.assert_allclose(rm.log_likelihood(z, j, inside[:3], s, eps),
                                   rm.log_likelihood(z, j, inside, s, eps)[:3], rtol=1e-12)
    if eps == 0:
        per = rm.reading_log_density(z, j, inside)
        assert per.shape == (len(inside), len(z))
        np.testing.assert_allclose(per.sum(axis=1), _bilinear_ref(rm, _node_total_ref(rm, z, j), inside),
                                   rtol=1e-10)


def test_tracker_combines_outlier_floor_and_radio_map():
    rng = np.random.default_rng(2)
    rm = RadioMap((0.0, 0.0), 0.5, rng.normal(-70, 6, (2, 21, 21)), rng.uniform(3, 6, (2, 21, 21)),
                  noise=(0.6, 1.4, 0.6))
    sensors = RSSISensor(np.array([[1.0, 1.0, 2.0], [9.0, 9.0, 2.0]]), -60.0, 2.0, 5.0)
    trk = WSNTracker(sensors, 500, bounds=(0, 0, 10, 10), radio_map=rm, outlier_prob=0.05, rssi_span=50.0,
                     seed=0)
    trk.initialize()
    z, j = np.array([-66.0, -90.0]), np.array([0, 1])
    np.testing.assert_allclose(trk.log_likelihood(z, j), rm.log_likelihood(z, j, trk.particles, 1.0, 0.05, 50.0))
    assert trk.update(trk.time, z, j) == 2
    with pytest.raises(ValidationError):
        rm.log_likelihood(z, j, trk.particles, outlier_prob=1.0)


def test_path_loss_design_and_directional_fit():
    rng = np.random.default_rng(5)
    d = rng.uniform(0.5, 15.0, 300)
    phi = rng.uniform(-np.pi, np.pi, 300)
    D = path_loss_design(d, phi, 2, d0=1.0)
    np.testing.assert_allclose(D[:, 1], -10 * np.log10(d))
    np.testing.assert_allclose(D[:, 2:], np.column_stack([np.cos(phi), np.sin(phi), np.cos(2 * phi), np.sin(2 * phi)]))
    beta = np.array([-58.0, 1.8, 3.0, -1.5, 0.7, 2.2])
    z = D @ beta
    p0, n, h, s = fit_directional_path_loss(d, phi, z, order=2, ridge=0.0)
    np.testing.assert_allclose([p0, n, *h], beta, atol=1e-9)
    assert s < 1e-9
    # ridge: against lstsq on the augmented system [D; sqrt(lam) P] beta = [z; 0]
    zn = z + rng.standard_normal(300) * 4.0
    lam = 250.0
    P = np.zeros((4, 6))
    P[:, 2:] = np.eye(4) * np.sqrt(lam)
    ref, *_ = np.linalg.lstsq(np.vstack([D, P]), np.concatenate([zn, np.zeros(4)]), rcond=None)
    p0, n, h, s = fit_directional_path_loss(d, phi, zn, order=2, ridge=lam)
    np.testing.assert_allclose([p0, n, *h], ref, rtol=1e-9, atol=1e-9)
    e = zn - D @ ref
    assert s == pytest.approx(np.sqrt(e @ e / (300 - 6)))
    # order 0: the plain log-distance fit
    p0, n, h, s = fit_directional_path_loss(d, phi, zn, order=0)
    np.testing.assert_allclose([p0, n, s], fit_path_loss(d, zn), rtol=1e-10)
    assert h.shape == (0,)
    with pytest.raises(ValidationError):
        fit_directional_path_loss(d[:5], phi[:5], zn[:5], order=2)
    with pytest.raises(ValidationError):
        path_loss_design(d, phi, -1)


def test_radio_map_npz_keeps_noise_and_settings(tmp_path):
    rng = np.random.default_rng(9)
    rm = _small_map(rng, (0.55, 1.38, 0.66))
    rm.settings = {"order": 3, "ridge": 100.0, "bandwidth": 0.5, "prior_weight": 0.2}
    rm.to_npz(tmp_path / "m.npz")
    back = RadioMap.from_npz(tmp_path / "m.npz")
    assert back.noise == pytest.approx(rm.noise) and back.settings == rm.settings
    plain = _small_map(rng)
    plain.to_npz(tmp_path / "p.npz")
    assert RadioMap.from_npz(tmp_path / "p.npz").noise is None
    with pytest.raises(ValidationError):
        RadioMap((0, 0), 0.4, rm.mean, rm.std, noise=(0.0, -1.0, 1.0))
