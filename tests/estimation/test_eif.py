"""ExtendedInformationFilter, DelayedStateEIF (nonlinear models) and InformationGaussian
against independent references: filterpy's ExtendedKalmanFilter driven directly, and
the covariance-form Gaussian formulas written out here."""
from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter

from dfusion.estimation import DelayedStateEIF, ExtendedInformationFilter, InformationGaussian
from dfusion.models import ConstantVelocity, PinholeCamera, RangeBearing, Unicycle

SEEDS = [0, 1, 2, 3, 4]


# ---------------------------------------------------------------- helpers
def assert_close_rel(a, b, rtol, what=""):
    """``max|a - b| <= rtol * max|b|``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape, (what, a.shape, b.shape)
    scale = max(float(np.max(np.abs(b))), 1e-300)
    err = float(np.max(np.abs(a - b))) / scale
    assert err <= rtol, f"{what}: relative error {err:.3g} > {rtol:.1g}"


def random_spd(rng, n, scale=1.0, cond=20.0):
    """Random SPD matrix with eigenvalues in ``scale * [1/cond, 1]``."""
    Qm, _ = np.linalg.qr(rng.normal(size=(n, n)))
    w = scale * np.exp(rng.uniform(-np.log(cond), 0.0, n))
    return (Qm * w) @ Qm.T


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def ekf_step(x, P, F, Q, z, sensor, angle_meas=()):
    """One filterpy EKF predict (linear motion ``F``) + update, driven directly.

    Column vectors throughout; ``angle_meas`` lists the measurement components whose
    residual is wrapped.
    """
    n, m = len(x), sensor.dim_z
    ekf = ExtendedKalmanFilter(dim_x=n, dim_z=m)
    ekf.x = np.asarray(x, float).reshape(n, 1)
    ekf.P = np.array(P, float)
    ekf.F = np.array(F, float)
    ekf.Q = np.array(Q, float)
    ekf.predict()
    ekf_update(ekf, z, sensor, angle_meas)
    return ekf.x.ravel(), ekf.P


def ekf_update(ekf, z, sensor, angle_meas=()):
    m = sensor.dim_z

    def residual(a, b):
        d = np.asarray(a, float).reshape(m, 1) - np.asarray(b, float).reshape(m, 1)
        for i in angle_meas:
            d[i] = wrap(d[i])
        return d

    ekf.update(
        np.asarray(z, float).reshape(m, 1),
        HJacobian=lambda xc: sensor.H(xc.ravel()),
        Hx=lambda xc: np.asarray(sensor.h(xc.ravel())).reshape(m, 1),
        R=sensor.R,
        residual=residual,
    )


def cv_F(dt, d):
    """Constant-velocity transition, written independently of dfusion."""
    F = np.eye(2 * d)
    F[:d, d:] = dt * np.eye(d)
    return F


def cv_Q(dt, d, q):
    I = np.eye(d)
    return q * np.block([[dt**3 / 3 * I, dt**2 / 2 * I], [dt**2 / 2 * I, dt * I]])


def camera():
    return PinholeCamera.looking_at(
        [0.0, -4.0, 6.0], [4.0, 4.0, 0.0], fx=500.0, fy=480.0, cx=320.0, cy=240.0,
        width=640, height=480, pixel_std=1.5,
    )


def camera_case(rng):
    """CV target on the ground in front of the camera, a pixel measurement."""
    x = np.concatenate([[4.0, 4.0] + rng.uniform(-1.5, 1.5, 2), rng.normal(0, 1.0, 2)])
    P = random_spd(rng, 4, scale=0.5)
    cam = camera()
    dt = float(rng.uniform(0.05, 0.5))
    truth = cv_F(dt, 2) @ x + rng.multivariate_normal(np.zeros(4), 0.5 * P)
    z = cam.h(truth) + rng.normal(0, cam.pixel_std, 2)
    assert cam.in_view(truth)
    return x, P, dt, z, cam


def range_bearing_case(rng):
    """CV target seen from a sensor with a known pose, random geometry (the +-pi cut: see below)."""
    pose = np.array([rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(-np.pi, np.pi)])
    sensor = RangeBearing(pose, range_std=0.2, bearing_std=0.03)
    bearing, dist = rng.uniform(-np.pi, np.pi), rng.uniform(3, 8)
    x = np.concatenate([pose[:2] + dist * np.array([np.cos(bearing), np.sin(bearing)]), rng.normal(0, 1.0, 2)])
    P = random_spd(rng, 4, scale=0.8)
    dt = float(rng.uniform(0.05, 0.5))
    truth = cv_F(dt, 2) @ x + rng.multivariate_normal(np.zeros(4), 0.3 * P)
    zc = sensor.h(truth) + rng.normal(0, [0.2, 0.03])
    z = np.array([zc[0], wrap(zc[1])])
    return x, P, dt, z, sensor


CASES = {"camera": camera_case, "range_bearing": range_bearing_case}


# ---------------------------------------------------------------- single-state EIF
@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("seed", SEEDS)
def test_eif_step_equals_filterpy_ekf_step(case, seed):
    rng = np.random.default_rng(seed)
    x, P, dt, z, sensor = CASES[case](rng)
    q = 0.4
    eif = ExtendedInformationFilter(ConstantVelocity(dim=2, q=q))
    eif.initialize(x, P)
    eif.predict(dt)
    eif.update(z, sensor)
    m, C = eif.estimate()
    x_ref, P_ref = ekf_step(x, P, cv_F(dt, 2), cv_Q(dt, 2, q), z, sensor, angle_meas=sensor.angle_indices)
    assert_close_rel(m, x_ref, 1e-10, "mean")
    assert_close_rel(C, P_ref, 1e-10, "covariance")
    # the measurement moved the estimate: the comparison is not vacuous
    assert np.max(np.abs(x_ref - cv_F(dt, 2) @ x)) > 1e-3


def test_eif_bearing_residual_is_wrapped():
    """A bearing just across +-pi from the prediction is a small innovation, not ~2 pi."""
    sensor = RangeBearing([0.0, 0.0, 0.0], range_std=0.1, bearing_std=0.05)
    x = np.array([-5.0, 0.05, 0.0, 0.0])        # bearing ~ +pi - 0.01
    P = np.diag([0.2, 0.2, 0.1, 0.1])
    z = np.array([5.0, -np.pi + 0.02])          # measured just across the cut
    eif = ExtendedInformationFilter(ConstantVelocity(dim=2, q=0.1))
    eif.initialize(x, P)
    eif.predict(0.1)
    eif.update(z, sensor)
    m, C = eif.estimate()
    x_ref, P_ref = ekf_step(x, P, cv_F(0.1, 2), cv_Q(0.1, 2, 0.1), z, sensor, angle_meas=(1,))
    assert_close_rel(m, x_ref, 1e-10, "mean")
    assert_close_rel(C, P_ref, 1e-10, "covariance")
    assert abs(m[1] - x[1]) < 0.2  # a 2 pi innovation would have thrown y by metres


# ---------------------------------------------------------------- delayed-state EIF, one step
@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("seed", SEEDS)
def test_delayed_state_latest_equals_filterpy_ekf_step(case, seed):
    rng = np.random.default_rng(100 + seed)
    x, P, dt, z, sensor = CASES[case](rng)
    q = 0.4
    f = DelayedStateEIF(ConstantVelocity(dim=2, q=q), window=10)
    t0 = float(rng.uniform(0, 100))
    f.initialize(t0, x, P)
    f.predict(t0 + dt)
    f.update(t0 + dt, z, sensor)
    m, C = f.estimate()
    x_ref, P_ref = ekf_step(x, P, cv_F(dt, 2), cv_Q(dt, 2, q), z, sensor, angle_meas=sensor.angle_indices)
    assert_close_rel(m, x_ref, 1e-10, "mean")
    assert_close_rel(C, P_ref, 1e-10, "covariance")
    # the same, asked for by time
    m2, C2 = f.estimate(t0 + dt)
    assert_close_rel(m2, x_ref, 1e-10, "mean by time")
    assert_close_rel(C2, P_ref, 1e-10, "covariance by time")


# ---------------------------------------------------------------- multi-step nonlinear
def unicycle_run(seed, steps=10):
    """Controls, times and range-bearing measurements of a unicycle seen from a fixed sensor."""
    rng = np.random.default_rng(seed)
    mo = Unicycle(std_v=0.2, std_w=0.1, q_floor=1e-3)
    sensor = RangeBearing([10.0, -3.0, 2.5], range_std=0.15, bearing_std=0.02)
    x = np.array([0.0, 0.0, 3.0])  # heading near pi: wrapping is exercised
    times = np.cumsum(rng.uniform(0.1, 0.4, steps))
    us, zs = [], []
    t_prev = 0.0
    for t in times:
        u = np.array([rng.uniform(0.5, 1.5), rng.uniform(-0.6, 0.6)])
        x = mo.f(x, t - t_prev, u) + rng.multivariate_normal(np.zeros(3), mo.Q(t - t_prev, x, u))
        zc = sensor.h(x) + rng.normal(0, [0.15, 0.02])
        us.append(u)
        zs.append(np.array([zc[0], wrap(zc[1])]))
        t_prev = t
    return mo, sensor, np.array([0.1, -0.2, 2.9]), np.diag([0.3, 0.3, 0.05]), times, us, zs


def unicycle_ekf_reference(mo, sensor, x0, P0, times, us, zs):
    """filterpy EKF: F, Q at the current mean, x <- f(x), then the wrapped-bearing update."""
    ekf = ExtendedKalmanFilter(dim_x=3, dim_z=2)
    ekf.x = np.asarray(x0, float).reshape(3, 1)
    ekf.P = np.array(P0, float)
    out = []
    t_prev = 0.0
    for t, u, z in zip(times, us, zs):
        dt = t - t_prev
        xm = ekf.x.ravel().copy()
        ekf.F = mo.F(dt, xm, u)
        ekf.Q = mo.Q(dt, xm, u)
        ekf.predict_x = lambda _u=0, xm=xm, dt=dt, u=u: setattr(ekf, "x", mo.f(xm, dt, u).reshape(3, 1))
        ekf.predict()
        ekf_update(ekf, z, sensor, angle_meas=(1,))
        xx = ekf.x.ravel().copy()
        xx[2] = wrap(xx[2])
        ekf.x = xx.reshape(3, 1)
        out.append((xx, ekf.P.copy()))
        t_prev = t
    return out


@pytest.mark.parametrize("window", [100, 3])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_delayed_state_multistep_unicycle_equals_filterpy_ekf(seed, window):
    """In-order measurements: every factor is linearized where the EKF linearizes.

    Motion factor x_{k-1} -> x_k at the filtered mean of x_{k-1} (= EKF posterior);
    measurement factor on x_k at its mean when it arrives (= EKF prediction). So the
    newest estimate equals the EKF's at every step, to rounding. A short window
    (marginalization every step) must not change that.
    """
    mo, sensor, x0, P0, times, us, zs = unicycle_run(seed)
    ref = unicycle_ekf_reference(mo, sensor, x0, P0, times, us, zs)
    f = DelayedStateEIF(mo, window=window)
    f.initialize(0.0, x0, P0)
    for (t, u, z), (x_ref, P_ref) in zip(zip(times, us, zs), ref):
        f.predict(t, u)
        f.update(t, z, sensor)
        m, C = f.estimate()
        assert abs(wrap(m[2] - x_ref[2])) <= 1e-9 * np.max(np.abs(x_ref))
        m[2] = x_ref[2]
        assert_close_rel(m, x_ref, 1e-9, f"mean at t={t:.3f}")
        assert_close_rel(C, P_ref, 1e-9, f"covariance at t={t:.3f}")
    assert len(f) == min(window, len(times) + 1)


def test_single_state_eif_multistep_unicycle_equals_filterpy_ekf():
    mo, sensor, x0, P0, times, us, zs = unicycle_run(7)
    ref = unicycle_ekf_reference(mo, sensor, x0, P0, times, us, zs)
    eif = ExtendedInformationFilter(mo)
    eif.initialize(x0, P0)
    t_prev = 0.0
    for (t, u, z), (x_ref, P_ref) in zip(zip(times, us, zs), ref):
        eif.predict(t - t_prev, u)
        eif.update(z, sensor)
        m, C = eif.estimate()
        assert abs(wrap(m[2] - x_ref[2])) <= 1e-9
        m[2] = x_ref[2]
        assert_close_rel(m, x_ref, 1e-9, "mean")
        assert_close_rel(C, P_ref, 1e-9, "covariance")
        t_prev = t


# ---------------------------------------------------------------- InformationGaussian
@pytest.mark.parametrize("seed", SEEDS)
def test_information_gaussian_moments_round_trip(seed):
    rng = np.random.default_rng(200 + seed)
    n = int(rng.integers(1, 8))
    mean = rng.normal(0, 5, n)
    cov = random_spd(rng, n, scale=float(rng.uniform(0.1, 10)), cond=1e3)
    g = InformationGaussian.from_moments(mean, cov)
    # reference: the definition, with numpy's general inverse
    Omega_ref = np.linalg.inv(cov)
    assert_close_rel(g.Omega, Omega_ref, 1e-10, "Omega")
    assert_close_rel(g.eta, Omega_ref @ mean, 1e-10, "eta")
    m2, P2 = g.to_moments()
    assert_close_rel(m2, mean, 1e-10, "mean")
    assert_close_rel(P2, cov, 1e-10, "cov")


@pytest.mark.parametrize("seed", SEEDS)
def test_information_gaussian_marginal_is_covariance_sub_block(seed):
    rng = np.random.default_rng(300 + seed)
    n = int(rng.integers(2, 9))
    mean = rng.normal(0, 3, n)
    cov = random_spd(rng, n, scale=2.0, cond=100.0)
    keep = np.sort(rng.choice(n, size=int(rng.integers(1, n)), replace=False))
    g = InformationGaussian.from_moments(mean, cov).marginalize(keep)
    m, P = g.to_moments()
    assert_close_rel(m, mean[keep], 1e-10, "marginal mean")
    assert_close_rel(P, cov[np.ix_(keep, keep)], 1e-10, "marginal covariance")
    # keep in a non-sorted order: the result follows that order
    perm = keep[::-1]
    m, P = InformationGaussian.from_moments(mean, cov).marginalize(perm).to_moments()
    assert_close_rel(m, mean[perm], 1e-10, "permuted marginal mean")
    assert_close_rel(P, cov[np.ix_(perm, perm)], 1e-10, "permuted marginal covariance")


@pytest.mark.parametrize("seed", SEEDS)
def test_information_gaussian_condition_is_closed_form_conditional(seed):
    rng = np.random.default_rng(400 + seed)
    n = int(rng.integers(2, 9))
    mean = rng.normal(0, 3, n)
    cov = random_spd(rng, n, scale=2.0, cond=100.0)
    given = np.sort(rng.choice(n, size=int(rng.integers(1, n)), replace=False))
    keep = np.setdiff1d(np.arange(n), given)
    v = mean[given] + rng.normal(0, 1, given.size)
    m, P = InformationGaussian.from_moments(mean, cov).condition(given, v).to_moments()
    # Gaussian conditional in covariance form (e.g. Bishop 2006, eq. 2.81-2.82)
    Saa, Sag, Sgg = cov[np.ix_(keep, keep)], cov[np.ix_(keep, given)], cov[np.ix_(given, given)]
    K = Sag @ np.linalg.inv(Sgg)
    assert_close_rel(m, mean[keep] + K @ (v - mean[given]), 1e-10, "conditional mean")
    assert_close_rel(P, Saa - K @ Sag.T, 1e-10, "conditional covariance")
