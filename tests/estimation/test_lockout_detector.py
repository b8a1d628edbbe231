"""LockoutDetector: thresholds against scipy's chi-square quantiles, the per-step
false-alarm rate of the window test against the exact chi-square tail (Monte Carlo,
consistent NIS), the rejection-run length against its closed form."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from dfusion.estimation.innovation import LockoutDetector


# ----------------------------------------------------------------------------------------
# LockoutDetector
# ----------------------------------------------------------------------------------------
def test_monitor_thresholds_and_run_length():
    m = LockoutDetector(3, window=10, alpha=1e-4, gate_probability=0.999)
    assert m.threshold() == pytest.approx(chi2.ppf(1 - 1e-4, 30))
    assert m.threshold(4) == pytest.approx(chi2.ppf(1 - 1e-4, 12))
    assert m.nis_cap == pytest.approx(chi2.ppf(0.999, 3))
    # smallest r with 0.001^r <= 1e-4
    assert m.max_run == 2
    assert LockoutDetector(3, alpha=1e-7, gate_probability=0.99).max_run == 4
    assert m.record(1.0, True) is None
    assert m.record(50.0, False) is None  # one rejection: the gate's business
    a = m.record(None, False)  # a failed match is a rejection without NIS
    assert a is not None and a.reason == "rejection_run" and m.alarms["rejection_run"] == 1
    m.reset()
    assert m.run == 0 and m.window_sum == 0.0


def test_monitor_false_alarm_rate_matches_the_chi_square_tail():
    """Consistent NIS (chi-square 3): the window alarm rate per step is alpha (the window
    sum of n values is chi-square 3n); capping at the gate can only lower it."""
    rng = np.random.default_rng(1)
    alpha, n = 0.01, 5
    m = LockoutDetector(3, window=n, alpha=alpha, gate_probability=0.999999)
    nis = rng.chisquare(3, 200_000)
    alarms = 0
    for k, e in enumerate(nis):
        a = m.record(float(e), True)
        if a is not None and k >= n - 1:
            alarms += 1
    steps = nis.size - n + 1
    # exact per-step probability (independent reference: the chi-square tail)
    p = chi2.sf(chi2.ppf(1 - alpha, 3 * n), 3 * n)
    sd = math.sqrt(p * (1 - p) / steps)  # overlapping windows: the mean is still p
    assert abs(alarms / steps - p) < 6 * sd * math.sqrt(n)
