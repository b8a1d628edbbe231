"""TrackToTrackAssociator: the test statistic against scipy's Mahalanobis distance and chi-square
quantile, the confirmation count, and pairs seen distinct never merged."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import mahalanobis
from scipy.stats import chi2

from dfusion.errors import ValidationError
from dfusion.tracking import TrackId, TrackToTrackAssociator

A, B, C = TrackId("a", 0), TrackId("b", 0), TrackId("c", 0)


def est(x, y, var=0.1):
    return np.array([x, y, 0.0, 0.0]), np.diag([var, var, 1.0, 1.0])


def test_gate_is_the_mahalanobis_distance_of_the_difference_against_the_chi_square_quantile():
    rng = np.random.default_rng(1)
    tta = TrackToTrackAssociator(gate=0.99, confirm=1, max_distance=100.0)
    assert tta.threshold == pytest.approx(chi2.ppf(0.99, 2), rel=1e-6)
    for _ in range(200):
        Pa, Pb = (np.cov(rng.normal(size=(2, 5))) + 0.05 * np.eye(2) for _ in range(2))
        pa, pb = rng.normal(size=2), rng.normal(size=2) * 2
        ea = (np.r_[pa, 0, 0], np.block([[Pa, np.zeros((2, 2))], [np.zeros((2, 2)), np.eye(2)]]))
        eb = (np.r_[pb, 0, 0], np.block([[Pb, np.zeros((2, 2))], [np.zeros((2, 2)), np.eye(2)]]))
        d2 = mahalanobis(pa, pb, np.linalg.inv(Pa + Pb)) ** 2
        found = TrackToTrackAssociator(gate=0.99, confirm=1, max_distance=100.0).check({A: ea, B: eb}, 0.0)
        assert (found == [(A, B)]) == (d2 <= chi2.ppf(0.99, 2)), d2


def test_the_windowed_test_sums_the_statistics_of_consecutive_checks():
    """Over N checks: sum d_k^2 <= chi2_gate(2N) (scipy's quantile); one large d^2 among small
    ones passes where a test of each check alone would fail, a steady offset does not."""
    tta = TrackToTrackAssociator(gate=0.99, confirm=4, max_distance=10.0)
    assert tta.threshold == pytest.approx(chi2.ppf(0.99, 8), rel=1e-6)
    v = 0.1                                     # d^2 = dx^2 / (2 v)
    spike = [0.1, 0.1, np.sqrt(2 * v * 12.0), 0.1]   # d^2 of 12 > chi2_0.99(2) = 9.2 at one check
    assert [tta.check({A: est(0, 0, v), B: est(dx, 0, v)}, k) for k, dx in enumerate(spike)][-1] == [(A, B)]
    steady = TrackToTrackAssociator(gate=0.99, confirm=4, max_distance=10.0)
    dx = np.sqrt(2 * v * 6.0)                   # d^2 = 6 each time: 24 > chi2_0.99(8) = 20.1
    assert all(steady.check({A: est(0, 0, v), B: est(dx, 0, v)}, k) == [] for k in range(10))


def test_confirmed_after_consecutive_close_checks_and_never_when_seen_distinct():
    tta = TrackToTrackAssociator(confirm=3, max_distance=1.0, distinct_for=2.0)
    close = {A: est(0, 0), B: est(0.1, 0), C: est(10, 0)}
    assert tta.check(close, 0.0) == [] and tta.check(close, 0.1) == []
    assert tta.check({A: est(0, 0), B: est(5, 0)}, 0.2) == []          # apart: the count starts again
    assert [tta.check(close, t) for t in (0.3, 0.4, 0.5)] == [[], [], [(A, B)]]
    tta.distinct([A, B], 1.0)                                          # both detected in one scan
    assert all(tta.check(close, t) == [] for t in np.arange(1.0, 2.9, 0.1))
    assert [tta.check(close, t) for t in (3.1, 3.2, 3.3)] == [[], [], [(A, B)]]


def test_max_distance_and_bad_settings():
    tta = TrackToTrackAssociator(confirm=1, max_distance=0.5)
    assert tta.check({A: est(0, 0, var=100.0), B: est(2, 0, var=100.0)}, 0.0) == []
    for bad in (dict(gate=1.0), dict(confirm=0), dict(max_distance=float("nan"))):
        with pytest.raises(ValidationError):
            TrackToTrackAssociator(**bad)
