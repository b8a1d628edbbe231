"""Every localizer and tracker follows one protocol (predict / update / estimate) and reports one type."""
from __future__ import annotations

import inspect

import numpy as np
import pytest

from dfusion.estimation import Estimate, Estimator
from dfusion.localization import (
    EnvironmentCameraLocalizer,
    LandmarkEKF,
    MonteCarloLocalization,
    OdometryEKF,
    ScanMatcher,
    ScanMatchingEKF,
    WSNTracker,
)
from dfusion.maps.buildings import rooms
from dfusion.models import ConstantVelocity, LaserConfig, PinholeCamera, RSSISensor, Unicycle
from dfusion.models.odometry import VelocityOdometry

CLASSES = (MonteCarloLocalization, OdometryEKF, ScanMatchingEKF, LandmarkEKF, EnvironmentCameraLocalizer, WSNTracker)


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_signatures_start_with_time(cls):
    for method in ("predict", "update"):
        params = list(inspect.signature(getattr(cls, method)).parameters)
        assert params[:2] == ["self", "t"], (cls.__name__, method, params)
    assert list(inspect.signature(cls.update).parameters)[2] in ("z", "rssi")
    assert inspect.signature(cls.estimate).return_annotation in (Estimate, "Estimate")


def _instances():
    grid = rooms(seed=1)
    mcl = MonteCarloLocalization(grid, LaserConfig.uniform(31, 2 * np.pi, 8.0), rng=0, max_particles=300)
    mcl.initialize_gaussian([3.0, 3.0, 0.0], np.diag([0.01, 0.01, 0.01]), t=0.0)
    odo = OdometryEKF([0.0, 0.0, 0.0], np.eye(3) * 0.01)
    odo.predict(0.0, (0.0, 0.0))
    lm = LandmarkEKF(VelocityOdometry([0.0], [[0.0, 0.0]], Unicycle(0.1, 0.05)), 0.0, [0.0, 0.0, 0.0], np.eye(3) * 0.01)
    cam = EnvironmentCameraLocalizer(PinholeCamera.looking_at([0.0, 0.0, 3.0], [3.0, 0.0, 0.0], fx=500.0, fy=500.0,
                                                              cx=320.0, cy=240.0, width=640, height=480))
    cam.update(0.0, [320.0, 240.0])
    wsn = WSNTracker(RSSISensor([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]], -45.0, 2.0, 4.0), 200, seed=0,
                     motion="constant_velocity", q=ConstantVelocity(2, 0.1).q)
    wsn.initialize(mean=[1.0, 1.0], cov=np.eye(2), t=0.0)
    sm = ScanMatchingEKF(ScanMatcher.from_grid(grid), OdometryEKF([3.0, 3.0, 0.0], np.eye(3) * 0.01))
    sm.predict(0.1, ([0.0, 0.0, 0.0], [0.1, 0.0, 0.0]))
    return [mcl, odo, sm, lm, cam, wsn]


def test_instances_are_estimators_and_report_estimates():
    for obj in _instances():
        assert isinstance(obj, Estimator), type(obj).__name__
        est = obj.estimate()
        assert isinstance(est, Estimate) and est.name, type(obj).__name__
        mean, cov = est
        assert cov.shape == (mean.size, mean.size) and np.all(np.linalg.eigvalsh(cov) > -1e-12)
        assert 0.0 <= est.reliability <= 1.0
