"""InnovationMonitor (dfusion.estimation.innovation): thresholds, robust weights, the jump
estimate, the lock-out and drift tests and the recovery of a kidnapped tracker.

References are independent of the code under test: scipy's chi-square quantiles and
binomial tails, numpy least squares on the stacked whitened system, Monte Carlo rates,
and the ground truth of simulated targets. (LockoutDetector: test_lockout_detector.py.)
"""
from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from scipy.stats import binom, chi2

from dfusion.errors import ValidationError
from dfusion.estimation.innovation import (
    InnovationMonitor,
    MonitorSettings,
    estimate_jump,
    monitored_update,
)


# --------------------------------------------------------------------------- settings
def test_thresholds_are_the_stated_chi_square_quantiles_and_run_length():
    s = MonitorSettings()
    assert s.gate(2) == pytest.approx(13.8155, abs=1e-3)           # chi2_2(0.999), tables
    assert s.huber(2) == pytest.approx(5.9915, abs=1e-3)           # chi2_2(0.95)
    assert s.quantile(3) == pytest.approx(chi2.isf(1e-3, 3))
    assert s.quantile(2, 10) == pytest.approx(chi2.isf(1e-4, 2))
    # run length: the smallest k with (0.25 + 0.001)^k <= 1e-3, by brute force
    for rate, fa in [(0.25, 1e-3), (0.5, 1e-3), (0.1, 1e-4), (0.3, 1e-2)]:
        st = MonitorSettings(max_outlier_rate=rate, false_alarm=fa)
        p = rate + 1 - st.gate_probability
        k = next(k for k in range(1, 100) if p**k <= fa)
        assert st.run_length() == k
    assert MonitorSettings().run_length() == 5 and MonitorSettings(max_outlier_rate=0.5).run_length() == 10
    with pytest.raises(ValidationError):
        MonitorSettings(gate_probability=1.0)
    with pytest.raises(ValidationError):
        MonitorSettings(huber_probability=0.9995)
    with pytest.raises(ValidationError):
        MonitorSettings(window=0)


def test_gate_and_huber_rates_on_consistent_innovations_match_chi_square():
    rng = np.random.default_rng(1)
    mon = InnovationMonitor("mc", 2, MonitorSettings(drift_test=False))
    S = np.array([[0.3, 0.1], [0.1, 0.2]])
    L = np.linalg.cholesky(S)
    n = 20000
    weights = []
    for _ in range(n):
        a = mon.test(0.0, L @ rng.standard_normal(2), S)
        if a.accept:
            weights.append(a.weight)
            # Huber weight: min(1, c / d) with c^2 = chi2_2(0.95), d^2 = NIS
            assert a.weight == pytest.approx(min(1.0, math.sqrt(chi2.ppf(0.95, 2) / a.nis)))
    st = mon.stats
    assert st.tested == n and st.accepted + st.rejected == n
    # binomial 99.99 % bounds around 1e-3 and 0.05 - 1e-3
    lo, hi = binom.interval(0.9999, n, 1e-3)
    assert lo <= st.rejected <= hi
    lo, hi = binom.interval(0.9999, n, 0.049)
    assert lo <= st.downweighted <= hi
    assert st.lockouts == 0  # scattered rejections: no run of 5


# --------------------------------------------------------------------------- jump estimate
def test_estimate_jump_matches_least_squares_and_keeps_only_determined_components():
    rng = np.random.default_rng(2)
    entries = []
    for _ in range(6):
        G = rng.standard_normal((2, 3))
        entries.append((rng.standard_normal(2), G))
    P_b = np.diag([0.04, 0.09, 0.01])
    jump = estimate_jump(entries, P_b)
    A = np.vstack([G for _, G in entries])
    b = np.concatenate([u for u, _ in entries])
    ref, res, rank, _ = np.linalg.lstsq(A, b, rcond=None)
    np.testing.assert_allclose(jump.delta, ref, atol=1e-10)
    np.testing.assert_allclose(jump.cov, np.linalg.inv(A.T @ A), atol=1e-10)
    assert jump.residual == pytest.approx(float(res[0]))
    assert jump.rank == 3 and jump.dof == 12 - 3
    assert jump.glr == pytest.approx(float(b @ A @ ref))
    # kept components, recomputed in the P_b-normalized basis by hand
    C = np.linalg.cholesky(P_b)
    Ft = C.T @ A.T @ A @ C
    mu, W = np.linalg.eigh(Ft)
    c = W.T @ np.linalg.solve(C, ref)
    keep = mu * c**2 > 1
    noise = C @ (W[:, keep] * (c[keep] ** 2 + 1 / mu[keep])) @ W[:, keep].T @ C.T
    np.testing.assert_allclose(jump.noise, noise, atol=1e-10)
    assert jump.kept == int(keep.sum())


def test_jump_along_an_undetermined_direction_gets_no_noise():
    # measurements of x only (y unobserved): a large apparent jump in x is kept,
    # nothing is added along y
    entries = [(np.array([3.0]), np.array([[1.0, 0.0]])) for _ in range(5)]
    jump = estimate_jump(entries, np.eye(2) * 0.01)
    assert jump.rank == 1 and jump.kept == 1
    assert jump.noise[1, 1] == pytest.approx(0.0, abs=1e-12)
    assert jump.noise[0, 0] == pytest.approx(3.0**2 + 1 / 5)
    # a component smaller than its own standard deviation is not kept
    weak = estimate_jump([(np.array([0.1]), np.array([[1.0, 0.0]]))], np.eye(2))
    assert weak.kept == 0 and not weak.noise.any()


# --------------------------------------------------------------------------- lock-out test
def _run(mon, innovations, S, sources=None, t0=0.0):
    out = []
    for i, nu in enumerate(innovations):
        out.append(mon.test(t0 + i, nu, S, source=None if sources is None else sources[i]))
    return out


def test_lockout_needs_a_run_of_consistent_rejections():
    S = np.eye(2) * 0.01      # belief + noise: 0.1 m
    P_b = np.eye(2) * 0.001
    mon = InnovationMonitor("lock", 2, MonitorSettings(drift_test=False))
    # four consistent rejections: not yet
    _run(mon, [np.array([1.0, 0.5])] * 4, S)
    assert mon.run == 4 and mon.divergence(P_b) is None
    _run(mon, [np.array([1.02, 0.49])], S, t0=4.0)
    kind, jump = mon.divergence(P_b)
    assert kind == "lockout"
    np.testing.assert_allclose(jump.delta, [1.004, 0.498], atol=1e-9)
    # scattered rejections (outliers) are not explained by one jump
    mon2 = InnovationMonitor("outliers", 2, MonitorSettings(drift_test=False))
    _run(mon2, [np.array(v) for v in ([2, 0], [-2, 1], [0, -3], [1.5, 1.5], [-1, -2])], S)
    assert mon2.run == 5 and mon2.divergence(P_b) is None
    # an accepted measurement breaks the run
    mon3 = InnovationMonitor("broken", 2, MonitorSettings(drift_test=False))
    _run(mon3, [np.array([1.0, 0.5])] * 4 + [np.zeros(2)] + [np.array([1.0, 0.5])] * 4, S)
    assert mon3.run == 4 and mon3.divergence(P_b) is None


def test_a_burst_of_rejections_in_few_looks_is_no_lockout_until_it_lasts_k_looks():
    """MRCLAM's pattern (dataset 6, robot 5 at 110.6-111.1 s): 10 landmarks rejected in 3
    scans during a fast turn, all consistent with one pose jump, which a plain EKF got
    over by itself. The measurements of one scan share the belief error and none of them
    is fused: one look, not 4 independent rejections. Only k = 10 looks make a lock-out."""
    S = np.eye(2) * 0.01
    P_b = np.eye(3) * 0.001
    H = {"A": np.array([[1.0, 0.0, 0.3], [0.0, 1.0, -0.2]]), "B": np.array([[0.2, 1.0, 1.0], [1.0, 0.0, -1.0]]),
         "C": np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), "D": np.array([[0.0, 1.0, 0.5], [1.0, 0.3, 0.0]])}
    d = np.array([0.6, 0.5, 0.4])
    mon = InnovationMonitor("burst", 2, MonitorSettings(drift_test=False, max_outlier_rate=0.5))
    assert mon.run_length == 10
    scans = [(110.6, "ABCD"), (110.8, "ABC"), (111.1, "ABC")]   # 10 measurements, 3 looks
    for t, srcs in scans:
        for src in srcs:
            assert not mon.test(t, H[src] @ d, S, H[src], source=src).accept
    assert mon.run == 10 and mon.looks == 3
    assert mon.divergence(P_b) is None
    # the belief stays wrong for 10 looks: a lock-out, the jump from all their measurements
    for i in range(7):
        for src in "AB" if i % 2 else "CD":
            mon.test(111.3 + 0.2 * i, H[src] @ d, S, H[src], source=src)
    assert mon.looks == 10
    kind, jump = mon.divergence(P_b)
    assert kind == "lockout"
    np.testing.assert_allclose(jump.delta, d, atol=1e-9)


def test_lockout_judges_only_measurements_up_to_the_horizon():
    S = np.eye(2) * 0.01
    mon = InnovationMonitor("h", 2, MonitorSettings(drift_test=False))
    _run(mon, [np.array([1.0, 0.5])] * 7, S)          # rejected at t = 0 .. 6
    assert mon.divergence(np.eye(2) * 0.001, horizon=3.5) is None   # only 4 judged
    spans = []
    found = mon.divergence(np.eye(2) * 0.001, supported=lambda a, b: spans.append((a, b)) or False, horizon=4.0)
    assert found[0] == "lockout" and spans == [(0.0, 4.0)]


def test_lockout_is_not_declared_on_a_single_source_or_when_supported():
    S = np.eye(2) * 0.01
    H = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])   # sees x, y of a 3-state block
    P_b = np.eye(3) * 0.001
    one = InnovationMonitor("one", 2, MonitorSettings(drift_test=False))
    for i in range(5):
        one.test(float(i), np.array([1.0, 0.5]), S, H, source="landmark A")
    assert one.divergence(P_b) is None  # one landmark could be wrong
    # two sources, but without A the rest cannot determine a 3-state jump either
    two = InnovationMonitor("two", 2, MonitorSettings(drift_test=False))
    H2 = np.array([[1.0, 0.0, 0.3], [0.0, 1.0, -0.2]])
    for i, (src, Hi) in enumerate([("A", H), ("A", H), ("B", H2), ("B", H2), ("A", H)]):
        two.test(float(i), Hi @ np.array([1.0, 0.5, 0.0]), S, Hi, source=src)
    assert two.divergence(P_b) is None
    three = InnovationMonitor("three", 2, MonitorSettings(drift_test=False))
    H3 = np.array([[0.2, 1.0, 1.0], [1.0, 0.0, -1.0]])
    rows = [("A", H), ("B", H2), ("C", H3), ("A", H), ("B", H2), ("C", H3)]
    d = np.array([1.0, 0.5, 0.2])
    for i, (src, Hi) in enumerate(rows):
        three.test(float(i), Hi @ d, S, Hi, source=src)
    kind, jump = three.divergence(P_b)
    assert kind == "lockout"
    np.testing.assert_allclose(jump.delta, d, atol=1e-9)
    # the same run, but the belief was backed by other evidence over its span
    assert three.divergence(P_b, supported=lambda t0, t1: True) is None
    spans = []
    three.divergence(P_b, supported=lambda t0, t1: spans.append((t0, t1)) or False)
    assert spans == [(1.0, 5.0)]   # the measurements of the last k = 5 looks


def test_drift_test_flags_a_persistent_bias_but_not_zero_mean_heavy_tails():
    rng = np.random.default_rng(3)
    st = MonitorSettings(window=10)
    S = np.eye(2)
    # Student-t (3 dof) innovations scaled to unit variance: heavy tails, zero mean
    fired = 0
    mon = InnovationMonitor("t", 2, st)
    n = 5000
    for i in range(n):
        nu = rng.standard_t(3, size=2) / math.sqrt(3.0)
        mon.test(float(i), nu, S)
        if mon.check(float(i), np.eye(2), lambda Q: None) is not None:
            fired += 1
    # at most the Bonferroni-corrected rate: 1e-3 per window of 10 measurements
    assert fired <= 2 * n * 1e-3 / 10 + 2
    # a bias of 1.6 standard deviations in x, inside the gate, is found within 3 windows
    mon = InnovationMonitor("bias", 2, st)
    found = None
    for i in range(30):
        mon.test(float(i), np.array([1.6, 0.0]) + 0.3 * rng.standard_normal(2), S)
        found = mon.divergence(np.eye(2))
        if found:
            break
    assert found is not None and found[0] == "drift"
    assert found[1].delta[0] == pytest.approx(1.6, abs=0.3)


# --------------------------------------------------------------------------- a 2-D tracker
def _track(recover: bool, jump_at: int = 40, n: int = 120, seed: int = 4):
    """A constant-position belief with tiny process noise; at ``jump_at`` the target
    jumps by 3 m (a kidnapping); fixes with 0.2 m noise, 10 % outliers uniform in a
    20 m square. Returns the final error and the monitor."""
    rng = np.random.default_rng(seed)
    truth = np.zeros(2)
    x, P = np.zeros(2), np.eye(2) * 0.01
    Q, R = np.eye(2) * 1e-6, np.eye(2) * 0.04
    mon = InnovationMonitor("trk", 2, MonitorSettings(drift_test=False, recover=recover))
    for k in range(n):
        if k == jump_at:
            truth = truth + np.array([3.0, -1.0])
        P = P + Q
        z = truth + 0.2 * rng.standard_normal(2)
        if rng.random() < 0.1:
            z = rng.uniform(-10, 10, 2)
        state = {"x": x, "P": P}

        def innovation():
            return z - state["x"], state["P"] + R, np.eye(2), state["P"]

        def fuse(w):
            Rw = R / w
            K = np.linalg.solve(state["P"] + Rw, state["P"]).T
            state["x"] = state["x"] + K @ (z - state["x"])
            state["P"] = (np.eye(2) - K) @ state["P"]

        def inflate(Qb):
            state["P"] = state["P"] + Qb

        monitored_update(mon, float(k), innovation, fuse, inflate)
        x, P = state["x"], state["P"]
    return float(np.linalg.norm(x - truth)), mon


def test_tracker_recovers_from_a_kidnapping_and_is_locked_out_without_recovery(caplog):
    with caplog.at_level(logging.WARNING, logger="dfusion.estimation.innovation"):
        err, mon = _track(recover=True)
    assert err < 0.3                       # back on the target (0.2 m fixes)
    assert mon.stats.lockouts >= 1 and mon.stats.recoveries == mon.stats.lockouts
    assert any("lockout" in r.message for r in caplog.records)
    ev = mon.stats.events[0]
    assert ev["kind"] == "lockout" and np.hypot(*ev["jump"]) == pytest.approx(math.hypot(3, 1), abs=0.3)
    err0, mon0 = _track(recover=False)
    assert err0 > 3.0                      # never comes back
    assert mon0.stats.lockouts >= 1 and mon0.stats.recoveries == 0
    # outliers alone never trigger a recovery
    _, quiet = _track(recover=True, jump_at=10**6)
    assert quiet.stats.recoveries == 0 and quiet.stats.rejected > 0
