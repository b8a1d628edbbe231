"""Process noise added after the fact (DelayedStateEIF.add_process_noise): the recovery of a
diverged belief. Reference: filterpy's KalmanFilter with the extra noise written into its Q."""
from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from dfusion import DelayedStateEIF
from dfusion.errors import OutsideWindowError
from dfusion.models import ConstantVelocity, PositionSensor
from tests.helpers.fusion_harness import Q_PSD, cv_F, cv_Q


def kalman(P0: np.ndarray) -> KalmanFilter:
    """filterpy's Kalman filter of the 2-D constant-velocity state observed in position (std 0.5)."""
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.x = np.zeros((4, 1))
    kf.P = np.array(P0, float)
    kf.H = np.hstack([np.eye(2), np.zeros((2, 2))])
    kf.R = 0.25 * np.eye(2)
    return kf


def test_added_process_noise_equals_a_kalman_filter_with_that_noise_including_splits():
    rng = np.random.default_rng(5)
    P0 = np.eye(4) * 2.0
    f = DelayedStateEIF(ConstantVelocity(2, Q_PSD), window=50)
    f.initialize(0.0, np.zeros(4), P0)
    sensor = PositionSensor(2, 0.5)
    zs = {t: rng.standard_normal(2) for t in (1.0, 2.0, 3.0, 4.0)}
    extra = np.diag([0.7, 0.4, 0.05, 0.02])
    extra[0, 1] = extra[1, 0] = 0.1
    for t in (1.0, 2.0, 3.0, 4.0):
        f.predict(t)
        f.update(t, zs[t], sensor)
    f.add_process_noise(3.0, extra)            # on the step 2 -> 3
    z_late = rng.standard_normal(2)
    f.update(2.5, z_late, sensor)             # splits the step: 2 -> 2.5 -> 3
    kf = kalman(P0)
    t_prev = 0.0
    for t, z in [(1.0, zs[1.0]), (2.0, zs[2.0]), (2.5, z_late), (3.0, zs[3.0]), (4.0, zs[4.0])]:
        kf.F, kf.Q = cv_F(t - t_prev), cv_Q(t - t_prev) + (extra if t == 3.0 else 0.0)
        kf.predict()
        kf.update(z.reshape(2, 1))
        t_prev = t
    m, P = f.estimate()
    np.testing.assert_allclose(m, kf.x.ravel(), atol=1e-9)
    np.testing.assert_allclose(P, kf.P, atol=1e-9)
    with pytest.raises(OutsideWindowError):
        f.add_process_noise(0.0, extra)       # no motion step ends at the oldest state
    with pytest.raises(OutsideWindowError):
        f.add_process_noise(3.3, extra)       # not a window state
