"""Anonymous robot sightings as tracker scans (dfusion.tracking.sightings) and per-detection noise in the
tracker: the world-frame covariance against Monte Carlo, the view probability against brute-force
sampling, the per-detection updates against filterpy's Kalman filter and a brute-force JPDA mixture."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from scipy.stats import multivariate_normal

from dfusion.errors import ShapeError, ValidationError
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.tracking import (GNN, JPDA, CameraView, GaussianHypothesiser, MofNInitiator, MultiTargetTracker,
                              NoDeleter, NoInitiator, Scan, TrackId, sightings_scan)


def test_sighting_covariance_matches_monte_carlo():
    """Sighting noise and the observer's pose error, propagated to the world-frame position: the
    empirical covariance of fixes computed from the estimated pose (MRCLAM-like values)."""
    rng = np.random.default_rng(1)
    pose = np.array([2.0, -1.0, 0.7])
    Ps = np.array([[0.03, 0.008, 0.001], [0.008, 0.02, -0.002], [0.001, -0.002, 0.004]])
    targets = np.array([[4.5, 1.5], [1.0, 3.0]])
    rs, bs = 0.15, 0.02
    n = 200_000
    true_pose = pose + rng.standard_normal((n, 3)) @ np.linalg.cholesky(Ps).T
    nominal = []
    fixes = []
    for q in targets:
        d = q - true_pose[:, :2]
        r = np.hypot(d[:, 0], d[:, 1]) + rs * rng.standard_normal(n)
        b = np.arctan2(d[:, 1], d[:, 0]) - true_pose[:, 2] + bs * rng.standard_normal(n)
        fixes.append(pose[:2] + r[:, None] * np.column_stack([np.cos(pose[2] + b), np.sin(pose[2] + b)]))
        dn = q - pose[:2]
        nominal.append((math.hypot(*dn), math.atan2(dn[1], dn[0]) - pose[2]))
    scan = sightings_scan(3.0, [z[0] for z in nominal], [z[1] for z in nominal], pose, Ps, rs, bs,
                          view=None, detection_probability=0.5, clutter_density=1e-4)
    assert scan.detections.shape == (2, 2) and scan.noise.shape == (2, 2, 2)
    np.testing.assert_allclose(scan.detections, targets, atol=1e-9)
    for j in range(2):
        L = np.linalg.cholesky(scan.noise[j])             # whitened: L^-1 C_mc L^-T = I within 5 %
        W = np.linalg.solve(L, np.linalg.solve(L, np.cov(fixes[j].T)).T)
        np.testing.assert_allclose(W, np.eye(2), atol=0.05)
    # the two sightings differ in accuracy: the farther one is wider
    assert np.trace(scan.noise[0]) != pytest.approx(np.trace(scan.noise[1]), rel=0.05)


def test_camera_view_contains_and_probability_against_brute_force():
    view = CameraView(0.6, 0.9, 8.7)
    pose = np.array([1.0, 1.0, math.pi / 2])
    assert view.contains(pose, [1.0, 4.0]) and not view.contains(pose, [1.0, 1.5])      # ahead; too close
    assert not view.contains(pose, [4.0, 1.0]) and not view.contains(pose, [1.0, 10.0])  # to the side; too far
    assert list(view.contains(pose, [[1.0, 4.0], [1.0, -3.0]])) == [True, False]         # behind
    rng = np.random.default_rng(5)
    for mean, cov in (([1.0, 4.0], np.diag([0.01, 0.01])), ([3.0, 4.0], np.diag([2.0, 1.0])),
                      ([1.0, 1.0], np.array([[9.0, 2.0], [2.0, 4.0]])), ([6.0, 1.0], np.diag([0.1, 0.1]))):
        pts = rng.multivariate_normal(mean, cov, 200_000)
        ref = float(np.mean(view.contains(pose, pts)))
        got = view.probability(pose, np.r_[mean, 0.0, 0.0], np.pad(cov, (0, 2)))
        assert got == pytest.approx(ref, abs=0.06)      # 256 fixed samples: standard error <= 0.031
    with pytest.raises(ValidationError):
        CameraView(0.6, 5.0, 1.0)


def _kf(x, P, z, R):
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.x, kf.P, kf.R = x.copy(), P.copy(), R
    kf.H = np.hstack([np.eye(2), np.zeros((2, 2))])
    kf.update(z)
    return kf.x, kf.P


def test_gnn_with_per_detection_noise_is_filterpys_update_with_each_detections_noise():
    """Two tracks, two detections with their own R (listed in either order): each track takes its
    detection and its state is filterpy's Kalman update with that detection's R, to 1e-9."""
    P0 = np.diag([0.2, 0.3, 0.01, 0.01])
    xa, xb = np.array([0.0, 0.0, 0.0, 0.0]), np.array([3.0, 1.0, 0.0, 0.0])
    za, zb = np.array([0.2, -0.1]), np.array([2.7, 1.3])
    Ra, Rb = np.array([[0.05, 0.01], [0.01, 0.02]]), np.array([[0.4, -0.1], [-0.1, 0.3]])
    for order in ((0, 1), (1, 0)):
        Z, R = np.array([za, zb])[list(order)], np.array([Ra, Rb])[list(order)]
        trk = MultiTargetTracker(ConstantVelocity(2, 0.01), GNN(), NoInitiator(), NoDeleter(),
                                 hypothesiser=GaussianHypothesiser(0.999, detections_in_view=True))
        trk.add_track(xa, P0, 0.0, TrackId("start", 1))
        trk.add_track(xb, P0, 0.0, TrackId("start", 2))
        trk.step(Scan(0.0, Z, PositionSensor(2, 1.0), 1e-4, 0.9, noise=R))
        (_, ma, Pa), (_, mb, Pb) = trk.estimates()
        for (m, P), (x, z, Rj) in zip(((ma, Pa), (mb, Pb)), ((xa, za, Ra), (xb, zb, Rb))):
            ref_x, ref_P = _kf(x, P0, z, Rj)
            np.testing.assert_allclose(m, ref_x, atol=1e-9)
            np.testing.assert_allclose(P, ref_P, atol=1e-12)


def test_jpda_with_per_detection_noise_is_the_brute_force_mixture():
    """Two close tracks, two detections with their own R: each track's posterior is the moment-matched
    mixture over every joint hypothesis (weights P_D N(nu; S_tj) and lambda (1 - P_D P_G); per-hypothesis
    posteriors by filterpy), to 1e-9."""
    P0 = np.diag([0.3, 0.3, 0.05, 0.05])
    X = [np.array([0.0, 0.0, 0.0, 0.0]), np.array([0.6, 0.2, 0.0, 0.0])]
    Z = np.array([[0.1, 0.1], [0.5, 0.0]])
    R = np.array([[[0.04, 0.0], [0.0, 0.06]], [[0.09, 0.02], [0.02, 0.05]]])
    pd, lam, pg = 0.8, 0.05, 0.999
    trk = MultiTargetTracker(ConstantVelocity(2, 0.01), JPDA(), NoInitiator(), NoDeleter(),
                             hypothesiser=GaussianHypothesiser(pg))
    for i, x in enumerate(X):
        trk.add_track(x, P0, 0.0, TrackId("s", i))
    trk.step(Scan(0.0, Z, PositionSensor(2, 1.0), lam, pd, noise=R))
    H = np.hstack([np.eye(2), np.zeros((2, 2))])

    def g(t, j):
        return 1.0 if j is None else pd * multivariate_normal(H @ X[t], H @ P0 @ H.T + R[j]).pdf(Z[j]) / (
            lam * (1 - pd * pg))

    hyps = [h for h in itertools.product([None, 0, 1], repeat=2) if h[0] is None or h[0] != h[1]]
    w = np.array([g(0, h[0]) * g(1, h[1]) for h in hyps])
    w /= w.sum()
    for t, (_, m, P) in enumerate(trk.estimates()):
        comps = [(X[t], P0) if h[t] is None else _kf(X[t], P0, Z[h[t]], R[h[t]]) for h in hyps]
        mean = sum(wi * c[0] for wi, c in zip(w, comps))
        cov = sum(wi * (c[1] + np.outer(c[0] - mean, c[0] - mean)) for wi, c in zip(w, comps))
        np.testing.assert_allclose(m, mean, atol=1e-9)
        np.testing.assert_allclose(P, cov, atol=1e-9)


def test_detection_weight_in_view_keeps_a_wide_track_above_clutter():
    """A track not seen for long (wide, mostly outside the camera's view) and one sighting in view:
    with the view probability in the detection weight the sighting is clutter; with detections_in_view
    the weight is P_D N(nu; 0, S) (scipy), and the track takes it."""
    pose = np.array([0.0, 0.0, 0.0])
    view = CameraView(0.6, 0.9, 8.7)
    x, P = np.array([2.0, 0.0, 0.0, 0.0]), np.diag([100.0, 100.0, 0.01, 0.01])
    scan = sightings_scan(1.0, [3.0], [0.1], pose, np.diag([1e-4, 1e-4, 1e-5]), 0.15, 0.02, view=view,
                          detection_probability=0.4, clutter_density=2e-4)
    v = view.probability(pose, x, P)
    assert 0.0 < v < 0.2
    taken = {}
    for flag in (False, True):
        hyp_ = GaussianHypothesiser(0.999, detections_in_view=flag)
        trk = MultiTargetTracker(ConstantVelocity(2, 1e-4), GNN(), NoInitiator(), NoDeleter(), hypothesiser=hyp_)
        trk.add_track(x, P, 1.0)
        hyp = hyp_.hypothesise(trk.tracks, scan)
        S = P[:2, :2] + scan.noise[0]
        pdet = 0.4 if flag else 0.4 * v
        assert hyp.log_weight[0, 0] == pytest.approx(math.log(pdet * multivariate_normal(x[:2], S).pdf(
            scan.detections[0])), rel=1e-9)
        assert hyp.log_miss[0] == pytest.approx(math.log(2e-4 * (1 - 0.4 * v * 0.999)), rel=1e-12)
        trk.step(scan)
        taken[flag] = trk.tracks[0].hits == 1
    assert taken == {False: False, True: True}


def test_scan_noise_is_validated_and_mofn_refuses_it():
    with pytest.raises(ShapeError):
        Scan(0.0, np.zeros((2, 2)), PositionSensor(2, 1.0), 0.0, 0.9, noise=np.zeros((1, 2, 2)))
    with pytest.raises(ValidationError):
        Scan(0.0, np.zeros((1, 2)), PositionSensor(2, 1.0), 0.0, 0.9, noise=np.array([[[1.0, 0.5], [0.0, 1.0]]]))
    scan = Scan(0.0, np.zeros((1, 2)), PositionSensor(2, 1.0), 0.0, 0.9, noise=np.eye(2)[None])
    np.testing.assert_array_equal(scan.detection_noise(0), np.eye(2))
    cv = ConstantVelocity(2, 0.1)
    trk = MultiTargetTracker(cv, GNN(), MofNInitiator(cv), NoDeleter())
    with pytest.raises(ValidationError, match="per-detection noise"):
        trk.step(scan)
