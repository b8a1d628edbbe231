"""Track initiation (dfusion.tracking.initiation): the two-point covariance against the linear
transform of the two detections' noise, M of N, identities."""
from __future__ import annotations

import numpy as np
import pytest

from dfusion.errors import ValidationError
from dfusion.models import ConstantVelocity, PositionSensor, RangeBearing
from dfusion.tracking import IdentityIssuer, MofNInitiator, Scan, TrackId, two_point_state


def test_two_point_state_is_the_linear_transform_of_two_detections():
    R = np.array([[0.09, 0.01], [0.01, 0.04]])
    dt = 0.1
    x, P = two_point_state([1.0, 2.0], [1.1, 2.05], dt, R)
    np.testing.assert_allclose(x, [1.1, 2.05, 1.0, 0.5])
    # x = A [z1; z2], A = [[0, I], [-I/dt, I/dt]]: the error covariance is A blkdiag(R, R) A^T
    I, O = np.eye(2), np.zeros((2, 2))
    A = np.block([[O, I], [-I / dt, I / dt]])
    np.testing.assert_allclose(P, A @ np.block([[R, O], [O, R]]) @ A.T, rtol=1e-12)


def test_two_point_state_covariance_matches_monte_carlo():
    rng = np.random.default_rng(1)
    R = np.diag([0.09, 0.09])
    p0, v, dt = np.array([3.0, 4.0]), np.array([1.2, -0.4]), 0.1
    errs = []
    for _ in range(20000):
        z1 = p0 + rng.normal(0, 0.3, 2)
        z2 = p0 + v * dt + rng.normal(0, 0.3, 2)
        x, P = two_point_state(z1, z2, dt, R)
        errs.append(x - np.concatenate([p0 + v * dt, v]))
    C = np.cov(np.array(errs).T)
    d = 1.0 / np.sqrt(np.diag(P))                       # compare in correlation units (sampling error ~ 1/sqrt(N))
    np.testing.assert_allclose(d[:, None] * C * d[None, :], d[:, None] * P * d[None, :], atol=0.03)


def scan_at(t, Z):
    return Scan(t, np.asarray(Z, float).reshape(-1, 2), PositionSensor(2, 0.3), 1e-3, 0.9)


def test_a_target_is_confirmed_at_its_mth_detection_with_the_next_identity():
    motion = ConstantVelocity(2, 0.05)
    init = MofNInitiator(motion, m=3, n=5)
    issuer = IdentityIssuer("cam1")
    issuer.next()                                       # one identity issued before
    p = lambda t: np.array([5.0 + t, 5.0])
    assert init.initiate(scan_at(0.1, [p(0.1)]), scan_at(0.1, [p(0.1)]).detections, issuer) == []
    assert init.initiate(scan_at(0.2, [p(0.2)]), np.array([p(0.2)]), issuer) == []
    assert len(init.tentative) == 1
    born = init.initiate(scan_at(0.3, [p(0.3)]), np.array([p(0.3)]), issuer)
    assert [tr.id for tr in born] == [TrackId("cam1", 1)]
    assert born[0].confirmed and not init.tentative
    mean, cov = born[0].estimate()
    assert np.linalg.norm(mean[:2] - p(0.3)) < 0.5


def test_scattered_detections_start_no_track_and_seeds_expire():
    motion = ConstantVelocity(2, 0.05)
    init = MofNInitiator(motion, m=3, n=5, max_seed_age=0.35)
    issuer = IdentityIssuer("n")
    for k in range(1, 30):                              # far apart every time: no pair within v_max dt + 3 sqrt(2) sigma
        z = np.array([[10.0 * k, 0.0]])
        assert init.initiate(scan_at(0.1 * k, z), z, issuer) == []
        assert all(0.1 * k - s.time <= 0.35 + 1e-9 for s in init.seeds)
    assert issuer.issued == 0 and not init.tentative


def test_a_tentative_track_that_stops_being_detected_is_dropped():
    motion = ConstantVelocity(2, 0.05)
    init = MofNInitiator(motion, m=4, n=5)
    issuer = IdentityIssuer("n")
    for k, Z in enumerate([[[1.0, 1.0]], [[1.1, 1.0]], [], [], [], []], start=1):
        init.initiate(scan_at(0.1 * k, Z), np.asarray(Z, float).reshape(-1, 2), issuer)
    assert not init.tentative and issuer.issued == 0


def test_bad_settings_and_sensors_are_refused():
    motion = ConstantVelocity(2, 0.05)
    with pytest.raises(ValidationError, match="M of N"):
        MofNInitiator(motion, m=4, n=3)
    with pytest.raises(ValidationError, match="max_speed"):
        MofNInitiator(motion, max_speed=0.0)
    with pytest.raises(ValidationError, match="dt > 0"):
        two_point_state([0, 0], [1, 1], 0.0, np.eye(2))
    init = MofNInitiator(motion)
    rb = RangeBearing(np.zeros(3), 0.1, 0.01)
    with pytest.raises(ValidationError, match="position"):
        init.initiate(Scan(0.1, [[1.0, 0.1]], rb, 0.0, 0.9), np.array([[1.0, 0.1]]), IdentityIssuer("n"))
    with pytest.raises(ValidationError, match="origin"):
        IdentityIssuer("a#b")
