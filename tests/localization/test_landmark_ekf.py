"""LandmarkEKF with an InnovationMonitor (dfusion.localization.landmark_ekf): it recovers from
an odometry heading slip that locks the plain EKF out, against the simulated truth."""
from __future__ import annotations

import math

import numpy as np

from dfusion.estimation.innovation import InnovationMonitor, MonitorSettings
from dfusion.localization import LandmarkEKF
from dfusion.models import LandmarkRangeBearing, Unicycle, VelocityOdometry


def test_landmark_ekf_recovers_from_a_heading_slip():
    """A robot drives a circle among 6 landmarks; at 30 s its odometry reports a 0.8 rad
    turn that did not happen (a slip). The plain EKF's landmarks are then gated out for
    good; the monitored one recovers."""
    rng = np.random.default_rng(8)
    lms = [np.array(p) for p in ([4, 0], [0, 4], [-4, 0], [0, -4], [3, 3], [-3, -3])]
    t = np.arange(0.0, 90.0, 0.1)
    v, w = 0.3, 0.1
    th = w * t
    truth = np.stack([3 * np.sin(th), 3 - 3 * np.cos(th), th], 1)   # radius v / w = 3
    odo_u = np.tile([v, w], (t.size, 1))
    odo_u[(t >= 30.0) & (t < 31.0), 1] += 0.8     # the slip: 0.8 rad over 1 s
    res = {}
    for name, mon in (("plain", None), ("robust", InnovationMonitor("pose", 2, MonitorSettings(drift_test=False, max_outlier_rate=0.5)))):
        odo = VelocityOdometry(t, odo_u, Unicycle(0.01, 0.02))
        ekf = LandmarkEKF(odo, 0.0, truth[0], np.diag([0.01, 0.01, 0.001]), monitor=mon)
        for k in range(1, t.size, 2):
            ekf.predict(t[k])
            for lm in lms:
                d = lm - truth[k, :2]
                b = math.atan2(d[1], d[0]) - truth[k, 2]
                if abs(math.remainder(b, 2 * math.pi)) > 0.6:
                    continue   # outside the camera's field of view
                z = [np.hypot(*d) + 0.05 * rng.standard_normal(), b + 0.01 * rng.standard_normal()]
                ekf.update(t[k], z, LandmarkRangeBearing(lm, 0.05, 0.01))
        ekf.predict(t[-1])
        e = ekf.x - truth[-1]
        res[name] = (np.hypot(e[0], e[1]), abs(math.remainder(e[2], 2 * math.pi)), ekf)
    assert res["plain"][1] > 0.5                  # heading still off by the slip
    assert res["robust"][0] < 0.2 and res["robust"][1] < 0.05
    assert res["robust"][2].recoveries >= 1
