"""Indoor phone localization: reader, PDR, magnetic map, fingerprints, magnetic particle filter, network.

Checked against independent references: the raw file's lines, scipy's rotations and filter
response, brute-force sums and sorts, scipy's grid interpolator, and closed-form Gaussian products.
"""
from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator
from scipy.signal import freqz
from scipy.spatial.transform import Rotation

from dfusion.datasets.indoor import read_floor, read_trace
from dfusion.errors import ValidationError
from dfusion.frontends.base import position_information
from dfusion.frontends.indoor import FingerprintFrontEnd, MagneticFrontEnd
from dfusion.fusion.node import FusionNode
from dfusion.localization.fingerprint import FingerprintLocalizer
from dfusion.localization.magnetic_pf import MagneticLocalizer, MagneticPFSettings, build_bias_free_map
from dfusion.maps.magnetic import MagneticMap, bilinear, gaussian_kernel_1d, smooth_grid
from dfusion.models.motion import ConstantVelocity
from dfusion.models.pdr import (GRAVITY, PDRSteps, StepDetector, anchored_track, dead_reckon, detect_steps,
                                fit_heading_offset, fit_weinberg_gain, pdr_steps, quaternion_matrices)

DATA = Path(__file__).parent / "data" / "indoor" / "site1-F1"
WALK = DATA / "path_data_files" / "5dd9e7aac5b77e0006b1732b.txt.gz"


# ------------------------------------------------------------------ reader
def test_reader_matches_the_raw_lines():
    raw = [ln.rstrip("\n").split("\t") for ln in gzip.open(WALK, "rt") if not ln.startswith("#")]
    count = {k: sum(r[1] == k for r in raw) for k in ("TYPE_ACCELEROMETER", "TYPE_MAGNETIC_FIELD", "TYPE_WAYPOINT")}
    tr = read_trace(WALK, max_wifi_age=1e9)
    assert tr.acc.shape == (count["TYPE_ACCELEROMETER"], 4)
    assert tr.mag.shape == (count["TYPE_MAGNETIC_FIELD"], 4)
    assert tr.waypoints.shape == (count["TYPE_WAYPOINT"], 3)
    t0 = min(int(r[0]) for r in raw)
    first_wp = next(r for r in raw if r[1] == "TYPE_WAYPOINT")
    assert tr.waypoints[0, 1:] == pytest.approx([float(first_wp[2]), float(first_wp[3])])
    assert tr.waypoints[0, 0] == pytest.approx((int(first_wp[0]) - t0) / 1000)
    wifi = [r for r in raw if r[1] == "TYPE_WIFI"]
    assert sum(len(s.rssi) for s in tr.wifi) == len({(r[0], r[3]) for r in wifi})
    fresh = read_trace(WALK, max_wifi_age=2.0)
    stale = sum(int(r[0]) - int(r[6]) > 2000 for r in wifi)
    assert fresh.n_stale_wifi == stale
    assert len(tr.beacons) == sum(r[1] == "TYPE_BEACON" for r in raw)


def test_floor_outline_is_in_metres_and_spans_the_floor():
    fl = read_floor(DATA)
    assert len(fl.traces) == 2 and fl.width == pytest.approx(239.8175, abs=1e-3)
    pts = np.vstack(fl.outline)
    assert pts.min(axis=0) == pytest.approx([0, 0], abs=1e-9)
    assert pts.max(axis=0) == pytest.approx([fl.width, fl.height], rel=1e-9)
    from matplotlib.path import Path as Polygon  # an independent point-in-polygon test

    wp = np.vstack([t.waypoints[:, 1:] for t in fl.traces])
    assert any(Polygon(r).contains_points(wp).all() for r in fl.outline)  # the walks lie on the floor
    with pytest.raises(ValidationError, match="floor_info"):
        read_floor(DATA / "path_data_files")


def test_quaternion_matrices_match_scipy():
    rng = np.random.default_rng(3)
    q = Rotation.random(50, random_state=rng).as_quat()  # x, y, z, w
    q[q[:, 3] < 0] *= -1  # Android's w >= 0
    assert quaternion_matrices(q[:, :3]) == pytest.approx(Rotation.from_quat(q).as_matrix(), abs=1e-12)


# ------------------------------------------------------------- step detection
def synthetic_gait(f=1.8, A=2.0, T=20.0, rate=50.0):
    t = np.arange(0, T, 1 / rate)
    acc = np.zeros((t.size, 3))
    acc[:, 2] = GRAVITY + A * np.sin(2 * np.pi * f * t)
    return t, acc


def test_step_detection_on_a_closed_form_gait():
    f, A, rate = 1.8, 2.0, 50.0
    t, acc = synthetic_gait(f, A, rate=rate)
    det = StepDetector(rate=rate)
    st = detect_steps(t, acc, det)
    # the filtered gait is A |H| sin(2 pi f t + arg H): peaks at t_n = (1/4 + n - arg H / (2 pi)) / f
    b, a = det.coefficients()
    _, H = freqz(b, a, worN=[2 * np.pi * f / rate])
    phase = np.angle(H[0])
    peaks = (0.25 + np.arange(60) - phase / (2 * np.pi)) / f
    # after the filter's transient (1 s), each step is declared one sample after a closed-form peak
    late = st.t[st.t > 1.0]
    nearest = peaks[np.argmin(np.abs(peaks[:, None] - late[None]), axis=0)]
    assert np.all(late - nearest >= -1e-9) and np.all(late - nearest <= 2.0 / rate + 1e-9)
    assert np.diff(late) == pytest.approx(1 / f, abs=1.01 / rate)
    assert len(late) == np.sum((peaks > 1.0 - 2 / rate) & (peaks < t[-1] - 1 / rate))
    # Weinberg's swing a_max - a_min over a step: the filtered amplitude, peak to peak
    assert st.swing[st.t > 2.0] == pytest.approx(2 * A * abs(H[0]), rel=0.02)


def test_step_detection_is_causal_and_ignores_standing():
    t, acc = synthetic_gait()
    st = detect_steps(t, acc)
    cut = 10.0
    acc2 = acc.copy()
    acc2[t > cut, 2] = GRAVITY + 5.0 * np.sin(2 * np.pi * 2.5 * t[t > cut])  # a different future
    st2 = detect_steps(t, acc2)
    assert st2.t[st2.t <= cut] == pytest.approx(st.t[st.t <= cut])
    still = np.tile([0.0, 0.0, GRAVITY], (500, 1)) + np.random.default_rng(0).normal(0, 0.05, (500, 3))
    assert len(detect_steps(np.arange(500) / 50, still)) == 0


def test_dead_reckoning_and_fits_on_a_closed_form_walk():
    # a straight walk East at 0.7 m per step, floor rotated by 10 degrees from East
    n = 20
    st = PDRSteps(np.arange(1, n + 1) * 0.5, np.full(n, 2.0), np.zeros(n), np.zeros((n, 3)))
    rot = np.radians(10.0)
    p = dead_reckon(st, [1.0, 2.0], 0.35, rot)
    assert p[-1] == pytest.approx([1 + 0.7 * n * np.cos(rot), 2 + 0.7 * n * np.sin(rot)])
    wp = np.column_stack([[0.0, 5.0, 10.0], p[[0, 10, 20]]])
    assert fit_weinberg_gain([(wp, st)]) == pytest.approx(0.35)
    assert fit_heading_offset([(wp, st)]) == pytest.approx(rot)
    track = anchored_track(st, wp, 0.3, 0.0)  # wrong gain and heading: the anchors correct them
    assert track[9] == pytest.approx(wp[1, 1:]) and track[19] == pytest.approx(wp[2, 1:])


# --------------------------------------------------------------- magnetic map
def test_map_smoothing_and_interpolation_against_brute_force():
    rng = np.random.default_rng(5)
    g = rng.normal(size=(12, 9))
    sig = 1.3
    k = gaussian_kernel_1d(sig)
    r = (k.size - 1) // 2
    brute = np.zeros_like(g)
    for i in range(12):
        for j in range(9):
            for a in range(12):
                for b in range(9):
                    if abs(a - i) <= r and abs(b - j) <= r:
                        brute[i, j] += k[a - i + r] * k[b - j + r] * g[a, b]
    assert smooth_grid(g, sig) == pytest.approx(brute, abs=1e-12)
    vals = rng.normal(size=(12, 9, 2))
    origin, cell = np.array([3.0, -1.0]), 0.5
    cx = origin[0] + (np.arange(12) + 0.5) * cell
    cy = origin[1] + (np.arange(9) + 0.5) * cell
    pts = np.column_stack([rng.uniform(cx[0], cx[-1], 200), rng.uniform(cy[0], cy[-1], 200)])
    ref = RegularGridInterpolator((cx, cy), vals)(pts)
    assert bilinear(vals, origin, cell, pts) == pytest.approx(ref, abs=1e-12)


def test_map_recovers_a_field_and_its_noise():
    rng = np.random.default_rng(1)
    p = rng.uniform(0, 20, (20000, 2))
    field = lambda q: 40 + 5 * np.sin(q[:, 0] / 3) + 3 * np.cos(q[:, 1] / 4)  # noqa: E731
    z = field(p) + rng.normal(0, 1.0, p.shape[0])
    m = MagneticMap.build(p, z, bounds=(0, 0, 20, 20), cell=0.5, sigma=0.5, n0=0.01)
    q = rng.uniform(3, 17, (500, 2))
    mu, var = m.lookup(q)
    assert np.abs(mu[:, 0] - field(q)).max() < 0.5
    # the noise (1) plus the field's variation within the kernel and the cell: |grad|^2 (sigma^2 + h^2 / 12)
    # is at most (5/3)^2 + (3/4)^2 = 3.3 uT^2/m^2 times 0.27 m^2 = 0.9
    assert 1.0 < np.median(var) < 1.9
    far = MagneticMap.build(p[:10], z[:10], bounds=(0, 0, 100, 100), cell=1.0, sigma=1.0)
    assert far.lookup(np.array([[90.0, 90.0]]))[0][0, 0] == pytest.approx(z[:10].mean(), abs=1e-6)
    assert not far.on_support(np.array([[90.0, 90.0]]))[0]


# -------------------------------------------------------------- fingerprints
def test_fingerprint_knn_against_brute_force():
    rng = np.random.default_rng(2)
    aps = [f"ap{i}" for i in range(6)]
    pos = rng.uniform(0, 30, (40, 2))
    scans = [{a: float(rng.integers(-90, -40)) for a in aps if rng.random() < 0.7} for _ in pos]
    loc = FingerprintLocalizer(scans, pos, k=3, missing=-100.0, s0=1.0)
    q = {"ap1": -60.0, "ap3": -75.0, "ap9": -50.0}
    d = np.array([np.mean([abs(q[a] - s.get(a, -100.0)) for a in ("ap1", "ap3")]) for s in scans])
    nn = np.argsort(d)[:3]
    w = 1 / (d[nn] + 1e-3)
    w /= w.sum()
    fix = loc.locate(q)
    assert fix.mean == pytest.approx(w @ pos[nn])
    r = pos[nn] - fix.mean
    assert fix.cov == pytest.approx(sum(wi * np.outer(ri, ri) for wi, ri in zip(w, r)) + np.eye(2))
    assert loc.locate({"unknown": -50.0}) is None


def test_fingerprint_calibration_gives_mean_nees_two():
    rng = np.random.default_rng(4)
    aps = rng.uniform(0, 50, (8, 2))
    pos = rng.uniform(0, 50, (300, 2))
    rssi = -40 - 20 * np.log10(np.linalg.norm(pos[:, None] - aps[None], axis=2) + 1) + rng.normal(0, 4, (300, 8))
    scans = [{f"a{j}": float(v) for j, v in enumerate(row)} for row in rssi]
    loc = FingerprintLocalizer(scans, pos, groups=np.arange(300) // 10, k=4)
    loc.calibrate()
    nees = []
    for i in range(300):
        fix = loc._query(scans[i], exclude=loc.groups == loc.groups[i])
        e = pos[i] - fix.mean
        nees.append(e @ np.linalg.solve(fix.cov, e))
    assert np.mean(nees) == pytest.approx(2.0, rel=1e-9)


# ------------------------------------------------------ magnetic particle filter
def synthetic_map():
    rng = np.random.default_rng(7)
    p = rng.uniform(0, 40, (40000, 2))
    def truth(q):  # B_z, B_h and the magnitude
        bz, bh = 30 + 8 * np.sin(q[:, 0] / 2.5) * np.cos(q[:, 1] / 3.0), 20 + 6 * np.cos(q[:, 0] / 3.5)
        return np.column_stack([bz, bh, np.hypot(bz, bh)])

    f = truth(p)
    return MagneticMap.build(p, f + rng.normal(0, 0.5, f.shape), bounds=(0, 0, 40, 40), cell=0.5, sigma=0.5), truth


def test_magnetic_pf_with_a_bias_corrects_a_wrong_step_length():
    mp, truth = synthetic_map()
    rng = np.random.default_rng(8)
    n = 60
    psi = np.where(np.arange(n) < 30, 0.0, np.pi / 2)
    true = np.vstack([[5.0, 5.0], [5.0, 5.0] + np.cumsum(0.7 * np.column_stack([np.cos(psi), np.sin(psi)]), axis=0)])
    fld = truth(true[1:]) + [3.0, -2.0, 1.0] + rng.normal(0, 0.5, (n, 3))
    loc = MagneticLocalizer(mp, gain=0.7 / 1.25, theta_floor=0.0, settings=MagneticPFSettings(n_particles=1500), seed=1)
    loc.initialize(0.0, true[0], np.eye(2))
    for k in range(n):
        loc.step(k + 1.0, 1.0, psi[k], fld[k])
    pdr = dead_reckon(PDRSteps(np.arange(n) + 1.0, np.ones(n), psi, fld), true[0], 0.7 / 1.25, 0.0)
    assert np.hypot(*(pdr[-1] - true[-1])) > 5.0          # dead reckoning alone is 20 % short (5.9 m)
    assert np.hypot(*(loc.estimate()[0] - true[-1])) < 2.0
    with pytest.raises(Exception, match="before initialize"):
        MagneticLocalizer(mp, 0.5, 0.0).step(0, 1, 0, None)


def test_reweight_information_is_the_gaussian_product():
    mp, _ = synthetic_map()
    loc = MagneticLocalizer(mp, 0.5, 0.0, MagneticPFSettings(n_particles=200000, roughening=0.0), seed=2)
    m0, P0 = np.array([20.0, 20.0]), np.diag([9.0, 4.0])
    loc.initialize(0.0, m0, P0)
    Om = np.array([[0.5, 0.1], [0.1, 0.3]])
    z = np.array([22.0, 18.0])
    loc.pf.ess_threshold = 0.0  # keep the weights: compare the weighted fit with the closed form
    loc.reweight_information(Om @ z, Om)
    P1 = np.linalg.inv(np.linalg.inv(P0) + Om)
    m1 = P1 @ (np.linalg.solve(P0, m0) + Om @ z)
    mean, cov = loc.estimate()
    assert mean == pytest.approx(m1, abs=0.03)
    assert cov == pytest.approx(P1, abs=0.05)


def test_global_start_is_redrawn_from_the_first_fix_restricted_to_the_walkable_support():
    """init_from_radio: a set started without a prior becomes, at the first radio information, draws of
    N(z, C) restricted to the map's support, at equal weights (the fix is then not applied a second time).
    Reference: the truncated Gaussian's mean by brute-force summation over a fine grid of the support."""
    rng = np.random.default_rng(11)
    p = np.vstack([np.column_stack([rng.uniform(0, 40, 4000), rng.uniform(18, 22, 4000)]),   # an L of
                   np.column_stack([rng.uniform(18, 22, 4000), rng.uniform(0, 40, 4000)])])  # corridors
    mp = MagneticMap.build(p, np.full((p.shape[0], 3), 40.0), bounds=(0, 0, 40, 40), cell=0.5, sigma=0.5)
    loc = MagneticLocalizer(mp, 0.5, 0.0, MagneticPFSettings(n_particles=20000), seed=12)
    loc.initialize(0.0)
    assert loc.awaiting_radio
    z, C = np.array([27.0, 26.0]), np.array([[25.0, 5.0], [5.0, 16.0]])
    O = np.linalg.inv(C)
    loc.reweight_information(O @ z, O)
    assert not loc.awaiting_radio and loc.pf.ess == pytest.approx(loc.pf.n)
    assert loc.map.on_support(loc.pf.particles[:, :2]).all()
    g = np.arange(0.05, 40, 0.1)
    X, Y = np.meshgrid(g, g, indexing="ij")
    inside = mp.support[(X / 0.5).astype(int), (Y / 0.5).astype(int)]
    d = np.stack([X - z[0], Y - z[1]], axis=-1)
    dens = np.exp(-0.5 * np.einsum("...i,ij,...j->...", d, O, d)) * inside
    ref = np.array([(dens * X).sum(), (dens * Y).sum()]) / dens.sum()
    assert loc.estimate()[0] == pytest.approx(ref, abs=0.1)
    loc.reweight_information(O @ z, O)  # later information re-weights as before
    assert loc.pf.ess < 0.9 * loc.pf.n


def test_radio_fit_is_the_gaussian_integral():
    """For particles from N(m, P), sum_i w_i exp(-d_i^T Omega d_i / 2) tends to the closed form
    sqrt(det C / det(C + P)) exp(-(m - z)^T (C + P)^-1 (m - z) / 2), C = Omega^-1."""
    mp, _ = synthetic_map()
    loc = MagneticLocalizer(mp, 0.5, 0.0, MagneticPFSettings(n_particles=200000), seed=4)
    m, P = np.array([20.0, 20.0]), np.array([[4.0, 1.0], [1.0, 2.0]])
    loc.initialize(0.0, m, P)
    C = np.array([[9.0, -2.0], [-2.0, 16.0]])
    z = np.array([24.0, 15.0])
    d = m - z
    ref = np.sqrt(np.linalg.det(C) / np.linalg.det(C + P)) * np.exp(-0.5 * d @ np.linalg.solve(C + P, d))
    assert loc.radio_fit(z, np.linalg.inv(C)) == pytest.approx(ref, rel=0.01)


def test_augmented_mcl_redraws_a_lost_set_around_the_fix():
    """recovery_fraction follows Thrun's recurrences (a plain loop here); a set that stops agreeing with
    the fixes gets particles redrawn around them, a set that keeps agreeing gets none."""
    mp, _ = synthetic_map()
    cfg = MagneticPFSettings(n_particles=2000, recover_slow=0.1, recover_fast=0.5, redraw_from_track=False)
    fits = [0.4, 0.5, 0.45, 0.05, 0.02, 0.3]
    loc = MagneticLocalizer(mp, 0.5, 0.0, cfg, seed=5)
    loc.initialize(0.0, [20.0, 20.0], np.eye(2))
    ws = wf = None
    for f in fits:
        ws, wf = (f, f) if ws is None else (ws + 0.1 * (f - ws), wf + 0.5 * (f - wf))
        assert loc.recovery_fraction(f) == pytest.approx(max(0.0, 1.0 - wf / ws))
    C = 4.0 * np.eye(2)
    track = MagneticPFSettings(n_particles=2000, recover_slow=0.1, recover_fast=0.5, redraw_from_track=True)
    for truth, lost, c in (([20.0, 20.0], False, cfg), ([32.0, 20.0], True, cfg), ([20.0, 20.0], False, track),
                           ([32.0, 20.0], True, track)):
        loc = MagneticLocalizer(mp, 0.5, 0.0, c, seed=6)
        loc.initialize(0.0, [20.0, 20.0], 0.25 * np.eye(2))
        for k in range(8):  # the set stands at (20, 20); the fixes are at the truth
            z = np.asarray(truth) if k >= 3 else np.array([20.0, 20.0])
            loc.reweight_information(np.linalg.solve(C, z), np.linalg.inv(C))
        assert (loc.injected > 0) == lost
        if lost:  # redrawn around the latest fix, or around the radio track: here the mean of the 8 fixes
            target = np.asarray(truth) if c is cfg else np.array([(3 * 20.0 + 5 * truth[0]) / 8, 20.0])
            assert np.hypot(*(loc.estimate()[0] - target)) < 2.0
    # off: no redraws whatever the fit
    off = MagneticLocalizer(mp, 0.5, 0.0, MagneticPFSettings(n_particles=500, recover_slow=0.0, recover_fast=0.0),
                            seed=7)
    off.initialize(0.0, [20.0, 20.0], np.eye(2))
    assert off.recovery_fraction(0.01) == 0.0 and off.recovery_fraction(0.9) == 0.0


def test_radio_track_is_the_gaussian_product_and_its_test_the_chi_square_p_value():
    """The radio track is the information-form product of the fixes (moved by the particles' step), and
    the test's p-value is scipy's chi-square survival function of the set-to-track Mahalanobis distance."""
    from scipy.stats import chi2

    mp, _ = synthetic_map()
    loc = MagneticLocalizer(mp, 0.5, 0.0, MagneticPFSettings(n_particles=4000, roughening=0.0), seed=9)
    loc.initialize(0.0, [20.0, 20.0], np.eye(2))
    z1, C1 = np.array([22.0, 19.0]), np.diag([16.0, 9.0])
    loc.radio_track_test(z1, C1)
    assert loc.radio_track[0] == pytest.approx(z1) and loc.radio_track[1] == pytest.approx(C1)
    before = loc.pf.particles[:, :2].copy(), loc.pf.weights.copy()
    loc.step(1.0, 1.0, 0.0, None)                        # no magnetic update: the weights stay
    d = loc.pf.particles[:, :2] - before[0]
    dm = before[1] @ d
    dC = (d - dm).T @ ((d - dm) * before[1][:, None])
    r0, R0 = z1 + dm, C1 + dC
    assert loc.radio_track[0] == pytest.approx(r0) and loc.radio_track[1] == pytest.approx(R0)
    z2, C2 = np.array([18.0, 23.0]), np.array([[25.0, 4.0], [4.0, 10.0]])
    pval = loc.radio_track_test(z2, C2)
    R1 = np.linalg.inv(np.linalg.inv(R0) + np.linalg.inv(C2))
    r1 = R1 @ (np.linalg.solve(R0, r0) + np.linalg.solve(C2, z2))
    assert loc.radio_track[0] == pytest.approx(r1) and loc.radio_track[1] == pytest.approx(R1)
    m = np.average(loc.pf.particles[:, :2], axis=0, weights=loc.pf.weights)
    P = np.cov(loc.pf.particles[:, :2].T, aweights=loc.pf.weights, bias=True)
    assert pval == pytest.approx(chi2.sf((m - r1) @ np.linalg.solve(P + R1, m - r1), 2))


def test_bias_free_map_on_the_slice_tracks_the_other_walk():
    fl = read_floor(DATA)
    steps = [pdr_steps(t) for t in fl.traces]
    pairs = [(t.waypoints, s) for t, s in zip(fl.traces, steps)]
    K, off = fit_weinberg_gain(pairs), fit_heading_offset(pairs)
    tr = [anchored_track(s, t.waypoints, K, off) for t, s in zip(fl.traces, steps)]
    mp, bias = build_bias_free_map(tr[1:], [steps[1].field], bounds=(0, 0, fl.width, fl.height))
    assert bias[0] == pytest.approx(np.mean(steps[1].field - mp.lookup(tr[1])[0], axis=0), abs=1e-9)
    w0 = fl.traces[0].waypoints
    loc = MagneticLocalizer(mp, K, off, MagneticPFSettings(n_particles=500), seed=3)
    loc.initialize(w0[0, 0], w0[0, 1:], np.eye(2))
    est = []
    for k in range(len(steps[0])):
        loc.step(steps[0].t[k], steps[0].w[k], steps[0].psi[k], steps[0].field[k])
        est.append(loc.estimate()[0])
    est = np.array(est)
    err = [np.hypot(np.interp(w[0], steps[0].t, est[:, 0]) - w[1], np.interp(w[0], steps[0].t, est[:, 1]) - w[2])
           for w in w0[1:]]
    assert np.mean(err) < 4.0


# ------------------------------------------------------------------ network
def test_network_gives_the_phone_exactly_the_radio_information():
    """Over the tree wifi -- phone -- beacon, the information the phone's particles absorb equals the sum
    of the radio nodes' fixes (the centralized fusion of the same fixes), and none of its own comes back."""
    mp, _ = synthetic_map()
    motion = ConstantVelocity(2, 0.5)
    prior = (0.0, np.array([20.0, 20.0, 0, 0]), np.diag([1e4, 1e4, 4, 4]))
    nodes = {n: FusionNode(n, nb, motion, window=50, prior=prior)
             for n, nb in (("phone", ["wifi", "beacon"]), ("wifi", ["phone"]), ("beacon", ["phone"]))}
    rng = np.random.default_rng(0)
    pos = rng.uniform(0, 40, (30, 2))
    scans = [{"a": float(-40 - p[0]), "b": float(-40 - p[1])} for p in pos]
    radio = FingerprintFrontEnd(FingerprintLocalizer(scans, pos, k=2))
    beacon = FingerprintFrontEnd(FingerprintLocalizer(scans, pos, k=3))
    loc = MagneticLocalizer(mp, 0.5, 0.0, MagneticPFSettings(n_particles=500), seed=1)
    loc.initialize(0.0, [20.0, 20.0], 4 * np.eye(2))
    phone = MagneticFrontEnd(loc, radio_weight=1.0)
    seen = []
    phone.localizer.reweight_information = lambda eta, Om, inject, floor: seen.append((eta, Om))
    expected = []
    for t, q in ((1.0, {"a": -60.0, "b": -62.0}), (2.0, {"a": -61.0, "b": -60.0})):
        for nd in nodes.values():
            nd.predict(t)
        radio.process(nodes["wifi"], t, q)
        beacon.process(nodes["beacon"], t, q)
        phone.step(t, 1.0, 0.0, None)
        phone.process(nodes["phone"], t)
        for r in ("wifi", "beacon"):
            nodes["phone"].receive(nodes[r].message_to("phone"))
            nodes[r].receive(nodes["phone"].message_to(r))
        phone.absorb(nodes["phone"], t)
        L1, y1 = position_information(radio.last[1], radio.last[2], 4)
        L2, y2 = position_information(beacon.last[1], beacon.last[2], 4)
        expected.append(((y1 + y2)[:2], (L1 + L2)[:2, :2]))
    assert len(seen) == 2
    for (eta, Om), (e_eta, e_Om) in zip(seen, expected):
        assert eta == pytest.approx(e_eta, rel=1e-9) and Om == pytest.approx(e_Om, rel=1e-9)


def test_wifi_node_fed_by_the_magnetic_filter_is_not_over_confident():
    """The WiFi node fuses its own fixes (exact Gaussian noise) and the phone's magnetic contributions;
    its average NEES against the truth over a synthetic walk stays below the chi-square 95 % bound."""
    mp, truth = synthetic_map()
    rng = np.random.default_rng(11)
    motion = ConstantVelocity(2, 0.5)
    start = np.array([5.0, 5.0])
    prior = (0.0, np.array([*start, 0, 0]), np.diag([4.0, 4.0, 4, 4]))
    nodes = {"phone": FusionNode("phone", ["wifi"], motion, window=200, prior=prior),
             "wifi": FusionNode("wifi", ["phone"], motion, window=200, prior=prior)}
    loc = MagneticLocalizer(mp, 0.7, 0.0, MagneticPFSettings(n_particles=1000), seed=5)
    loc.initialize(0.0, start, 4 * np.eye(2))
    phone = MagneticFrontEnd(loc, radio_weight=1.0)
    C = np.diag([9.0, 4.0])
    p = start.copy()
    nees = []
    for k in range(1, 61):
        t = 0.5 * k
        psi = 0.0 if k <= 30 else np.pi / 2
        p = p + 0.7 * np.array([np.cos(psi), np.sin(psi)])
        f = truth(p[None])[0] + rng.normal(0, 0.5, 3)
        phone.step(t, 1.0, psi + rng.normal(0, 0.05), f)
        if k % 4 == 0:
            for nd in nodes.values():
                nd.predict(t)
            z = p + rng.multivariate_normal(np.zeros(2), C)
            Lam, y = position_information(z, C, 4)
            nodes["wifi"].add_local_information(t, Lam, y)
            phone.process(nodes["phone"], t)
            nodes["phone"].receive(nodes["wifi"].message_to("phone"))
            nodes["wifi"].receive(nodes["phone"].message_to("wifi"))
            phone.absorb(nodes["phone"], t)
            m, P = nodes["wifi"].estimate()
            e = m[:2] - p
            nees.append(float(e @ np.linalg.solve(P[:2, :2], e)))
    assert phone.stats.contributed > 0
    # chi-square with 2 * 15 degrees of freedom, 95 % upper bound 43.8, divided by 15
    assert np.mean(nees) < 43.8 / 15, nees


def test_a_contribution_older_than_the_window_is_refused_before_anything_moves():
    """``MagneticFrontEnd.process`` at a time older than the node's window raises
    ``OutsideWindowError`` before the localizer's reference moves: the magnetic information since
    the last contribution is still there for the next call (compared with an untouched twin)."""
    import copy

    from dfusion.errors import OutsideWindowError

    mp, truth = synthetic_map()
    motion = ConstantVelocity(2, 0.5)
    prior = (0.0, np.array([5.0, 5.0, 0, 0]), np.diag([4.0, 4.0, 4, 4]))
    node = FusionNode("phone", ["wifi"], motion, window=5, prior=prior)
    loc = MagneticLocalizer(mp, 0.7, 0.0, MagneticPFSettings(n_particles=300), seed=2)
    loc.initialize(0.0, [5.0, 5.0], 4 * np.eye(2))
    phone = MagneticFrontEnd(loc, radio_weight=1.0)
    p = np.array([5.0, 5.0])
    for k in range(1, 9):
        p = p + [0.7, 0.0]
        phone.step(0.5 * k, 1.0, 0.0, truth(p[None])[0])
        node.predict(0.5 * k)
    twin = copy.deepcopy(phone.localizer)
    with pytest.raises(OutsideWindowError):
        phone.process(node, 0.0)                       # older than the window of 5 states
    assert phone.stats.processed == 0 and phone.stats.contributed == 0
    got, want = phone.localizer.information_contribution(50.0), twin.information_contribution(50.0)
    assert np.array_equal(got.Omega, want.Omega) and np.array_equal(got.eta, want.eta)
    assert np.any(got.Omega)
