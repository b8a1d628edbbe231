"""Tests of dfusion.models against independent references.

Jacobians are checked against central finite differences; closed forms are
written out by hand here; ``filterpy`` and ``scipy`` provide external references.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.common import Q_continuous_white_noise
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp
from scipy.stats import linregress

from dfusion.errors import NonFiniteError, ShapeError, ValidationError
from dfusion.models import (
    ConstantVelocity,
    fit_path_loss,
    PinholeCamera,
    PositionSensor,
    RangeBearing,
    RSSISensor,
    Unicycle,
)
from dfusion.geometry import wrap_angle

FAST = settings(max_examples=60, deadline=None)


# --------------------------------------------------------------------------- helpers
def num_jac(fun, x, diff=None, step=1e-6):
    """Central finite-difference Jacobian of ``fun`` at ``x``.

    ``diff(a, b)`` computes ``a - b`` (pass a residual to wrap angle outputs).
    """
    diff = diff or (lambda a, b: np.asarray(a) - np.asarray(b))
    x = np.asarray(x, dtype=float)
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = step * max(1.0, abs(x[i]))
        cols.append(diff(fun(x + e), fun(x - e)) / (2.0 * e[i]))
    return np.column_stack(cols)


def angdiff(a, b):
    """Smallest signed difference between two angles (independent of wrap_angle)."""
    return math.atan2(math.sin(a - b), math.cos(a - b))


# --------------------------------------------------------------------------- ConstantVelocity
@pytest.mark.parametrize("axes", [1, 2, 3])
@pytest.mark.parametrize("dt", [0.01, 0.5, 3.0])
def test_cv_Q_matches_filterpy(axes, dt):
    q = 0.37
    model = ConstantVelocity(dim=axes, q=q)
    # filterpy orders per axis: [x, vx, y, vy, ...]; ours is [x, y, ..., vx, vy, ...].
    Qf = Q_continuous_white_noise(dim=2, dt=dt, spectral_density=q, block_size=axes)
    perm = [2 * k for k in range(axes)] + [2 * k + 1 for k in range(axes)]
    np.testing.assert_allclose(model.Q(dt), Qf[np.ix_(perm, perm)], rtol=1e-12, atol=0)
    # filterpy's own "order by derivative" layout is ours too.
    Qf2 = Q_continuous_white_noise(dim=2, dt=dt, spectral_density=q, block_size=axes, order_by_dim=False)
    np.testing.assert_allclose(model.Q(dt), Qf2, rtol=1e-12, atol=0)
    assert np.all(np.linalg.eigvalsh(model.Q(dt)) > 0)


@pytest.mark.parametrize("axes", [1, 2, 3])
def test_cv_F_and_f_closed_form(axes):
    rng = np.random.default_rng(1)
    model = ConstantVelocity(dim=axes, q=0.1)
    for _ in range(5):
        dt = rng.uniform(0.01, 5.0)
        x = rng.normal(size=2 * axes) * 10
        p, v = x[:axes], x[axes:]
        np.testing.assert_allclose(model.f(x, dt), np.concatenate([p + v * dt, v]), rtol=1e-13)
        I, Z = np.eye(axes), np.zeros((axes, axes))
        np.testing.assert_array_equal(model.F(dt), np.block([[I, dt * I], [Z, I]]))
        np.testing.assert_allclose(model.F(dt), num_jac(lambda s: model.f(s, dt), x), atol=1e-7)


def test_cv_bad_parameters():
    for q in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValidationError):
            ConstantVelocity(dim=2, q=q)
    with pytest.raises(ShapeError):
        ConstantVelocity(dim=4)


# --------------------------------------------------------------------------- Unicycle
def unicycle_ode(x0, u, dt):
    v, w = u
    sol = solve_ivp(
        lambda t, s: [v * np.cos(s[2]), v * np.sin(s[2]), w],
        (0.0, dt),
        np.asarray(x0, dtype=float),
        method="DOP853",
        rtol=1e-12,
        atol=1e-12,
    )
    assert sol.success
    return sol.y[:, -1]


OMEGAS = [0.0, 1e-12, -5e-10, 1e-9, 2e-9, -1e-7, 1e-5, 1e-3, 0.7, -2.5]


@pytest.mark.parametrize("w", OMEGAS)
def test_unicycle_f_matches_ode(w):
    rng = np.random.default_rng(abs(hash(w)) % 2**32)
    model = Unicycle(std_v=0.1, std_w=0.05)
    for _ in range(3):
        x0 = np.array([rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-np.pi, np.pi)])
        v, dt = rng.uniform(-3, 3), rng.uniform(0.05, 4.0)
        ref = unicycle_ode(x0, (v, w), dt)
        got = model.f(x0, dt, (v, w))
        np.testing.assert_allclose(got[:2], ref[:2], atol=1e-8)
        assert abs(angdiff(got[2], ref[2])) < 1e-10
        assert -np.pi <= got[2] < np.pi


def test_unicycle_full_circle_and_wrapping():
    model = Unicycle(std_v=0.1, std_w=0.05)
    # One full turn at 1 rad/s and 2 m/s: back at the start, circle radius 2 m.
    x = model.f([1.0, -2.0, 0.25], 2 * np.pi, [2.0, 1.0])
    np.testing.assert_allclose(x[:2], [1.0, -2.0], atol=1e-12)
    assert abs(angdiff(x[2], 0.25)) < 1e-12
    # Quarter turn from heading 0: the centre is at (0, r) so we end at (r, r).
    x = model.f([0.0, 0.0, 0.0], np.pi / 2, [2.0, 1.0])
    np.testing.assert_allclose(x, [2.0, 2.0, np.pi / 2], atol=1e-12)
    # Crossing +pi wraps to the negative side.
    x = model.f([0.0, 0.0, np.pi - 0.1], 1.0, [0.0, 0.3])
    assert x[2] == pytest.approx(-np.pi + 0.2, abs=1e-12)


def test_unicycle_no_control_means_zero_control():
    model = Unicycle(std_v=0.1, std_w=0.05)
    x0 = np.array([3.0, -1.0, 0.4])
    np.testing.assert_allclose(model.f(x0, 2.0), x0, atol=0)
    np.testing.assert_allclose(model.F(2.0, x0), np.eye(3), atol=0)
    np.testing.assert_allclose(model.Q(2.0, x0), model.Q(2.0, x0, [0.0, 0.0]), atol=0)


@given(
    x=st.floats(-100, 100),
    y=st.floats(-100, 100),
    th=st.floats(-np.pi, np.pi),
    v=st.floats(-5, 5),
    w=st.floats(0.01, 5).flatmap(lambda a: st.sampled_from([a, -a])),
    dt=st.floats(0.001, 10),
)
@FAST
def test_unicycle_f_matches_textbook_arc(x, y, th, v, w, dt):
    """Thrun et al. (2005) eq. for the exact arc, in the v/omega form."""
    got = Unicycle(0.1, 0.1).f([x, y, th], dt, [v, w])
    r = v / w
    ref = [x - r * np.sin(th) + r * np.sin(th + w * dt), y + r * np.cos(th) - r * np.cos(th + w * dt)]
    np.testing.assert_allclose(got[:2], ref, atol=1e-9 * (1 + abs(r)))
    assert abs(angdiff(got[2], th + w * dt)) < 1e-9


@pytest.mark.parametrize("w", OMEGAS + [2e-3 / 2.0 * (1 + 1e-9)])
def test_unicycle_F_and_V_finite_differences(w):
    rng = np.random.default_rng(7)
    model = Unicycle(std_v=0.2, std_w=0.1)
    for _ in range(4):
        x = np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(-np.pi, np.pi)])
        v, dt = rng.uniform(-3, 3), rng.choice([2.0, rng.uniform(0.01, 3.0)])
        u = np.array([v, w])
        F_num = num_jac(lambda s: model.f(s, dt, u), x, diff=model.residual)
        np.testing.assert_allclose(model.F(dt, x, u), F_num, atol=1e-7)
        V_num = num_jac(lambda c: model.f(x, dt, c), u, diff=model.residual)
        np.testing.assert_allclose(model.V(dt, x, u), V_num, atol=1e-7)


def test_unicycle_Q_control_noise_model():
    rng = np.random.default_rng(3)
    sv, sw, qf = 0.3, 0.07, 1e-5
    model = Unicycle(std_v=sv, std_w=sw, q_floor=qf)
    M = np.diag([sv**2, sw**2])
    for _ in range(6):
        x = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-np.pi, np.pi)])
        u = np.array([rng.uniform(-2, 2), rng.uniform(-1, 1)])
        dt = rng.uniform(0.01, 2.0)
        V_num = num_jac(lambda c: model.f(x, dt, c), u, diff=model.residual)
        Q = model.Q(dt, x, u)
        np.testing.assert_allclose(Q, V_num @ M @ V_num.T / dt + qf * dt * np.eye(3), atol=1e-8)
        np.testing.assert_array_equal(Q, Q.T)
        assert np.all(np.linalg.eigvalsh(Q) > 0)
        # Heading is a Wiener process: variance std_w^2 dt (plus the floor).
        assert Q[2, 2] == pytest.approx(sw**2 * dt + qf * dt, rel=1e-12)
    # Straight motion along +x: the along-track variance is std_v^2 dt, uncorrelated with heading.
    Q = model.Q(0.5, [0.0, 0.0, 0.0], [1.0, 0.0])
    assert Q[0, 0] == pytest.approx(sv**2 * 0.5 + qf * 0.5, rel=1e-12)
    assert Q[0, 2] == pytest.approx(0.0, abs=1e-15)
    assert Q[1, 1] == pytest.approx(1.0**2 * sw**2 * 0.5**3 / 4 + qf * 0.5, rel=1e-12)
    np.testing.assert_array_equal(model.Q(0.0, [0.0, 0.0, 0.0], [1.0, 0.5]), np.zeros((3, 3)))


@given(a=st.floats(-1e6, 1e6), b=st.floats(-1e6, 1e6))
@FAST
def test_motion_residual_wraps_angle(a, b):
    model = Unicycle(0.1, 0.1)
    d = model.residual([1.0, 2.0, a], [0.5, -1.0, b])
    assert d[0] == 0.5 and d[1] == 3.0
    assert -np.pi <= d[2] < np.pi
    # Same angle modulo 2 pi as the raw difference.
    assert abs(np.sin(d[2]) - np.sin(a - b)) < 1e-6 and abs(np.cos(d[2]) - np.cos(a - b)) < 1e-6


def test_unicycle_bad_parameters():
    for kwargs in (
        dict(std_v=0.0, std_w=0.1),
        dict(std_v=-1.0, std_w=0.1),
        dict(std_v=0.1, std_w=np.nan),
        dict(std_v=0.1, std_w=np.inf),
        dict(std_v="fast", std_w=0.1),
        dict(std_v=0.1, std_w=0.1, q_floor=0.0),
    ):
        with pytest.raises(ValidationError):
            Unicycle(**kwargs)
    model = Unicycle(0.1, 0.1)
    with pytest.raises(ValidationError, match="needs the state"):
        model.F(1.0)
    with pytest.raises(ShapeError):
        model.f([0.0, 0.0], 1.0, [1.0, 0.0])
    with pytest.raises(ShapeError):
        model.f([0.0, 0.0, 0.0], 1.0, [1.0, 0.0, 0.0])
    with pytest.raises(NonFiniteError):
        model.f([0.0, np.nan, 0.0], 1.0)
    with pytest.raises(ValidationError):
        model.Q(-0.1, [0.0, 0.0, 0.0])


# --------------------------------------------------------------------------- PositionSensor
@pytest.mark.parametrize("n", [2, 4, 6])
def test_position_sensor_H_finite_differences(n):
    rng = np.random.default_rng(n)
    sensor = PositionSensor(dim=2, std=[0.5, 1.0])
    for _ in range(3):
        x = rng.normal(size=n) * 10
        np.testing.assert_allclose(sensor.H(x), num_jac(sensor.h, x), atol=1e-8)
        np.testing.assert_allclose(sensor.h(x), x[:2], atol=0)
    np.testing.assert_array_equal(sensor.R, np.diag([0.25, 1.0]))


# --------------------------------------------------------------------------- RangeBearing
def test_range_bearing_closed_form():
    sensor = RangeBearing((1.0, 2.0, np.pi / 2), range_std=0.1, bearing_std=0.01)
    np.testing.assert_allclose(sensor.h([1.0, 5.0]), [3.0, 0.0], atol=1e-15)  # straight ahead
    np.testing.assert_allclose(sensor.h([0.0, 2.0, 9.0, 9.0]), [1.0, np.pi / 2], atol=1e-15)  # to the left
    np.testing.assert_allclose(sensor.h([4.0, -2.0]), [5.0, -np.pi / 2 - math.atan2(4, 3)], atol=1e-15)
    # Directly behind: bearing -pi (the wrapped representation of pi).
    np.testing.assert_allclose(sensor.h([1.0, 0.0]), [2.0, -np.pi], atol=1e-15)
    np.testing.assert_allclose(sensor.R, np.diag([0.01, 1e-4]), rtol=1e-14, atol=0)


@pytest.mark.parametrize("n", [2, 3, 5])
def test_range_bearing_H_finite_differences(n):
    rng = np.random.default_rng(10 + n)
    for _ in range(5):
        pose = (rng.uniform(-10, 10), rng.uniform(-10, 10), rng.uniform(-np.pi, np.pi))
        sensor = RangeBearing(pose, 0.5, 0.02)
        x = rng.uniform(-30, 30, size=n)
        np.testing.assert_allclose(sensor.H(x), num_jac(sensor.h, x, diff=sensor.residual), atol=1e-7)
        assert np.all(sensor.H(x)[:, 2:] == 0)
    # Target straight behind the sensor, where the bearing wraps at +-pi.
    sensor = RangeBearing((0.0, 0.0, 0.0), 0.5, 0.02)
    x = np.array([-4.0, 0.0, 1.0])
    np.testing.assert_allclose(sensor.H(x), num_jac(sensor.h, x, diff=sensor.residual), atol=1e-7)
    np.testing.assert_allclose(sensor.H(x)[:, :2], [[-1.0, 0.0], [0.0, -0.25]], atol=1e-15)


def test_range_bearing_residual_wraps_bearing():
    sensor = RangeBearing((0.0, 0.0, 0.0), 0.5, 0.02)
    d = sensor.residual([10.0, np.pi - 0.1], [9.0, -np.pi + 0.1])
    np.testing.assert_allclose(d, [1.0, -0.2], atol=1e-12)
    d = sensor.residual([10.0, -np.pi + 0.05], [10.0, np.pi - 0.05])
    np.testing.assert_allclose(d, [0.0, 0.1], atol=1e-12)


@given(z=st.floats(-50, 50), zhat=st.floats(-50, 50))
@FAST
def test_range_bearing_residual_property(z, zhat):
    sensor = RangeBearing((0.0, 0.0, 0.0), 0.5, 0.02)
    d = sensor.residual([1.0, z], [1.0, zhat])
    assert -np.pi <= d[1] < np.pi
    assert abs(d[1] - angdiff(z, zhat)) < 1e-9 or abs(abs(d[1]) - np.pi) < 1e-9


def test_range_bearing_errors():
    sensor = RangeBearing((1.0, 2.0, 0.3), 0.5, 0.02)
    with pytest.raises(ValidationError, match="sensor position"):
        sensor.H([1.0, 2.0, 5.0])
    with pytest.raises(ShapeError):
        sensor.h([1.0])
    with pytest.raises(ShapeError):
        RangeBearing((1.0, 2.0), 0.5, 0.02)
    for rs, bs in ((0.0, 0.1), (0.1, -0.1), (np.nan, 0.1), (0.1, np.inf)):
        with pytest.raises(ValidationError):
            RangeBearing((0.0, 0.0, 0.0), rs, bs)


# --------------------------------------------------------------------------- PinholeCamera
INTR = dict(fx=500.0, fy=400.0, cx=320.0, cy=240.0, width=640, height=480)


def down_camera(**kw):
    """Camera 10 m above the origin looking straight down, image 'up' = world +y."""
    return PinholeCamera.looking_at((0.0, 0.0, 10.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), **{**INTR, **kw})


def tilted_camera(**kw):
    """Camera 10 m up at the origin, looking 45 degrees down along +x."""
    return PinholeCamera.looking_at((0.0, 0.0, 10.0), (10.0, 0.0, 0.0), **{**INTR, **kw})


def test_camera_projection_by_hand():
    # Straight down: right = +x, down = -y, forward = -z; (2, 1, 0) -> p_c = (2, -1, 10).
    cam = down_camera()
    np.testing.assert_allclose(cam.h([2.0, 1.0]), [500 * 0.2 + 320, 400 * -0.1 + 240], atol=1e-12)
    # The same camera built from an explicit rotation (columns: right, down, forward).
    R_wc = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    cam2 = PinholeCamera((0.0, 0.0, 10.0), R_wc, **INTR)
    np.testing.assert_allclose(cam2.h([2.0, 1.0, 7.0]), [420.0, 200.0], atol=1e-12)
    np.testing.assert_allclose(cam.R_wc, R_wc, atol=1e-15)
    # Tilted 45 deg: right = -y, down = (-1, 0, -1)/sqrt2, forward = (1, 0, -1)/sqrt2.
    # (20, 5, 0) - C = (20, 5, -10) -> p_c = (-5, -10/sqrt2, 30/sqrt2).
    cam = tilted_camera()
    np.testing.assert_allclose(cam.h([20.0, 5.0]), [320 - 500 * math.sqrt(2) / 6, 240 - 400 / 3], atol=1e-9)
    np.testing.assert_allclose(cam.h([10.0, 0.0]), [320.0, 240.0], atol=1e-9)  # the look-at point
    # A raised plane: point (2, 1, 5) seen from 10 m straight above is 5 m deep.
    cam = down_camera(point_height=5.0)
    np.testing.assert_allclose(cam.h([2.0, 1.0]), [500 * 0.4 + 320, 400 * -0.2 + 240], atol=1e-12)
    np.testing.assert_array_equal(cam.R, np.eye(2))
    np.testing.assert_array_equal(cam.K, [[500, 0, 320], [0, 400, 240], [0, 0, 1]])


def _in_view_samples(cam, rng, count, n=2):
    pts = []
    while len(pts) < count:
        x = np.concatenate([rng.uniform(-5, 60, size=1), rng.uniform(-40, 40, size=1), rng.normal(size=n - 2)])
        if cam.in_view(x):
            pts.append(x)
    return pts


@pytest.mark.parametrize("n", [2, 4])
@pytest.mark.parametrize("point_height", [0.0, 1.5])
def test_camera_H_finite_differences(n, point_height):
    rng = np.random.default_rng(21 + n)
    cams = [
        tilted_camera(point_height=point_height),
        PinholeCamera.looking_at((3.0, -4.0, 6.0), (12.0, 2.0, 0.5), up=(0.1, 0.0, 1.0), **INTR,
                                 point_height=point_height),
    ]
    for cam in cams:
        for x in _in_view_samples(cam, rng, 5, n):
            np.testing.assert_allclose(cam.H(x), num_jac(cam.h, x), rtol=1e-6, atol=1e-6)
            assert np.all(cam.H(x)[:, 2:] == 0)


def test_camera_homography():
    # Straight down from 10 m: R_cw = diag(1, -1, -1), t = -R_cw C = (0, 0, 10).
    cam = down_camera()
    K = np.array([[500.0, 0, 320], [0, 400, 240], [0, 0, 1]])
    G_hand = K @ np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, 10]])
    G = cam.homography()
    np.testing.assert_allclose(G / G[2, 2], G_hand / G_hand[2, 2], atol=1e-12)
    rng = np.random.default_rng(5)
    for ph in (0.0, -0.7, 2.0):
        for cam in (tilted_camera(point_height=ph), down_camera(point_height=ph)):
            G = cam.homography()
            for x in _in_view_samples(cam, rng, 8):
                p = G @ np.array([x[0], x[1], 1.0])
                np.testing.assert_allclose(p[:2] / p[2], cam.h(x), atol=1e-8)


def test_camera_in_view_borders():
    cam = down_camera()
    eps = 1e-6

    # Straight down: pixel (u, v) sees ground point ((u - cx) 10 / fx, -(v - cy) 10 / fy).
    def ground(u, v):
        return np.array([(u - 320.0) * 10.0 / 500.0, -(v - 240.0) * 10.0 / 400.0])

    for u, v, inside in [
        (eps, 240, True), (-eps, 240, False),
        (640 - eps, 240, True), (640 + eps, 240, False),
        (320, eps, True), (320, -eps, False),
        (320, 480 - eps, True), (320, 480 + eps, False),
        (eps, eps, True), (640 - eps, 480 - eps, True),
    ]:
        assert cam.in_view(ground(u, v)) is inside, (u, v)


def test_camera_behind():
    # Horizontal camera at 10 m looking along +x. A ground point behind it, (-20, 0),
    # has p_c = (0, 10, -20): its mirrored projection (320, 40) is inside the image.
    cam = PinholeCamera.looking_at((0.0, 0.0, 10.0), (10.0, 0.0, 10.0), **INTR)
    x = np.array([-20.0, 0.0])
    np.testing.assert_allclose(cam.camera_point(x), [0.0, 10.0, -20.0], atol=1e-12)
    assert cam.in_view(x) is False
    with pytest.raises(ValidationError, match="behind"):
        cam.h(x)
    with pytest.raises(ValidationError, match="behind"):
        cam.H(x)
    # The same point in front, (20, 0), projects to (320, 240 + 400 * 10 / 20).
    assert cam.in_view([20.0, 0.0]) is True
    np.testing.assert_allclose(cam.h([20.0, 0.0]), [320.0, 440.0], atol=1e-12)
    assert cam.in_view([5.0, 0.0]) is False  # in front but below the image


@given(px=st.floats(0.01, 639.99), py=st.floats(170.0, 479.99), ph=st.sampled_from([0.0, 1.0, -2.0]))
@FAST
def test_camera_ground_point_inverts_h(px, py, ph):
    # Tilted camera: pixel rows v >= 170 look below the horizon at v = 240 - 400 = -160.
    cam = tilted_camera(point_height=ph)
    x = cam.ground_point((px, py))
    np.testing.assert_allclose(cam.h(x), [px, py], atol=1e-6)
    # And ground_point(h(x)) == x.
    np.testing.assert_allclose(cam.ground_point(cam.h(x)), x, rtol=1e-9, atol=1e-9)
    assert cam.in_view(np.append(x, 0.0))


def test_camera_ground_point_by_hand_and_errors():
    cam = down_camera()
    np.testing.assert_allclose(cam.ground_point((420.0, 200.0)), [2.0, 1.0], atol=1e-12)
    cam = tilted_camera()
    np.testing.assert_allclose(cam.ground_point((320.0, 240.0)), [10.0, 0.0], atol=1e-12)
    # 56 deg above the optical axis = 11 deg above the horizon: never hits the ground.
    with pytest.raises(ValidationError, match="does not hit"):
        cam.ground_point((320.0, 240.0 - 1.5 * 400.0))
    # Exactly at the horizon: parallel to the plane.
    with pytest.raises(ValidationError, match="does not hit"):
        cam.ground_point((320.0, 240.0 - 400.0))


def test_camera_bad_parameters():
    R_ok = np.diag([1.0, -1.0, -1.0])
    C = (0.0, 0.0, 10.0)
    with pytest.raises(ValidationError, match="rotation"):
        PinholeCamera(C, np.diag([1.0, 1.0, -1.0]), **INTR)  # a reflection
    with pytest.raises(ValidationError, match="rotation"):
        PinholeCamera(C, 2 * R_ok, **INTR)
    with pytest.raises(ShapeError):
        PinholeCamera(C, np.eye(2), **INTR)
    with pytest.raises(ShapeError):
        PinholeCamera((0.0, 10.0), R_ok, **INTR)
    for bad in (dict(fx=0.0), dict(fy=-1.0), dict(cx=np.nan), dict(width=0), dict(height=480.5),
                dict(pixel_std=0.0), dict(min_depth=-1.0)):
        with pytest.raises(ValidationError):
            PinholeCamera(C, R_ok, **{**INTR, **bad})
    with pytest.raises(ValidationError, match="coincides"):
        PinholeCamera.looking_at(C, C, **INTR)
    with pytest.raises(ValidationError, match="parallel"):
        PinholeCamera.looking_at(C, (0.0, 0.0, 0.0), **INTR)  # default up = +z
    with pytest.raises(ShapeError):
        down_camera().h([1.0])


# --------------------------------------------------------------------------- RSSISensor
def test_rssi_closed_form():
    p0, n = -40.0, 2.0
    s = RSSISensor([[3.0, 4.0], [0.0, 0.0], [-6.0, 8.0]], p0=p0, exponent=n, std=2.0)
    expected = [p0 - 20 * math.log10(5.0), p0 - 20 * math.log10(0.01), p0 - 20 * math.log10(10.0)]
    np.testing.assert_allclose(s.h([0.0, 0.0]), expected, atol=1e-12)  # middle one clamped at 1 cm
    assert s.dim_z == 3
    np.testing.assert_array_equal(s.R, 4.0 * np.eye(3))
    # 3-D receivers and a transmitter height; d0 = 2 m.
    s = RSSISensor([[0.0, 0.0, 2.0], [4.0, 0.0, -3.0]], p0=-30.0, exponent=3.0, std=[1.0, 2.0], d0=2.0,
                   height=1.0)
    d = [math.hypot(1.5, 1.0), math.sqrt(2.5**2 + 4.0**2)]
    np.testing.assert_allclose(s.h([1.5, 0.0, 9.0]), [-30.0 - 30 * math.log10(di / 2.0) for di in d], atol=1e-12)
    np.testing.assert_array_equal(s.R, np.diag([1.0, 4.0]))
    # 2-D receivers with a transmitter height: 3-4-5 triangle.
    s = RSSISensor([[0.0, 0.0]], p0=-50.0, exponent=2.5, std=1.0, height=3.0)
    np.testing.assert_allclose(s.h([4.0, 0.0]), [-50.0 - 25 * math.log10(5.0)], atol=1e-12)


@pytest.mark.parametrize("recv_dim,height,n", [(2, 0.0, 2), (2, 1.2, 4), (3, 0.0, 4), (3, -0.5, 3)])
def test_rssi_H_finite_differences(recv_dim, height, n):
    rng = np.random.default_rng(30 + recv_dim + n)
    receivers = rng.uniform(-20, 20, size=(5, recv_dim))
    s = RSSISensor(receivers, p0=-45.0, exponent=2.7, std=3.0, d0=1.5, height=height)
    for _ in range(6):
        x = rng.uniform(-25, 25, size=n)
        if np.min(np.linalg.norm(receivers[:, :2] - x[:2], axis=1)) < 0.5:
            continue
        H = s.H(x)
        assert H.shape == (5, n)
        np.testing.assert_allclose(H, num_jac(s.h, x), rtol=1e-6, atol=1e-6)
        assert np.all(H[:, 2:] == 0)


def test_rssi_clamp_keeps_h_and_H_finite():
    s = RSSISensor([[1.0, 2.0], [5.0, 5.0]], p0=-40.0, exponent=2.0, std=1.0, d_min=0.05)
    z = s.h([1.0, 2.0])
    H = s.H([1.0, 2.0])
    assert np.all(np.isfinite(z)) and np.all(np.isfinite(H))
    assert z[0] == pytest.approx(-40.0 - 20 * math.log10(0.05), abs=1e-12)
    np.testing.assert_array_equal(H[0], [0.0, 0.0])
    # Inside the clamp h is flat, so a finite difference there is zero too.
    np.testing.assert_allclose(num_jac(s.h, np.array([1.01, 2.0]))[0], [0.0, 0.0], atol=1e-9)


def test_fit_path_loss_recovers_parameters():
    rng = np.random.default_rng(2024)
    p0, n, std, d0 = -45.0, 2.7, 3.0, 1.0
    d = 10 ** rng.uniform(0.0, np.log10(50.0), size=2000)
    rssi = p0 - 10 * n * np.log10(d / d0) + rng.normal(0.0, std, size=d.size)
    p0_hat, n_hat, std_hat = fit_path_loss(d, rssi, d0=d0)
    # Sampling standard errors here are about 0.13 dB, 0.014 and 0.05 dB.
    assert p0_hat == pytest.approx(p0, abs=0.6)
    assert n_hat == pytest.approx(n, abs=0.06)
    assert std_hat == pytest.approx(std, abs=0.2)
    # Independent reference: ordinary regression of rssi on log10(d / d0).
    ref = linregress(np.log10(d / d0), rssi)
    assert p0_hat == pytest.approx(ref.intercept, abs=1e-9)
    assert n_hat == pytest.approx(-ref.slope / 10, abs=1e-11)
    resid = rssi - (ref.intercept + ref.slope * np.log10(d / d0))
    assert std_hat == pytest.approx(np.sqrt(resid @ resid / (d.size - 2)), rel=1e-9)


@given(p0=st.floats(-90, 0), n=st.floats(1.0, 6.0), d0=st.floats(0.1, 10.0))
@FAST
def test_fit_path_loss_noise_free_is_exact(p0, n, d0):
    d = np.array([0.5, 1.0, 2.0, 7.0, 30.0, 100.0])
    p0_hat, n_hat, std_hat = fit_path_loss(d, p0 - 10 * n * np.log10(d / d0), d0=d0)
    assert p0_hat == pytest.approx(p0, abs=1e-8)
    assert n_hat == pytest.approx(n, abs=1e-9)
    assert std_hat < 1e-8


def test_rssi_and_fit_bad_parameters():
    R = [[0.0, 0.0], [1.0, 1.0]]
    for kwargs in (
        dict(receivers=R, p0=-40, exponent=0.0, std=1.0),
        dict(receivers=R, p0=-40, exponent=2.0, std=-1.0),
        dict(receivers=R, p0=-40, exponent=2.0, std=[1.0, 0.0]),
        dict(receivers=R, p0=np.nan, exponent=2.0, std=1.0),
        dict(receivers=R, p0=-40, exponent=2.0, std=1.0, d0=0.0),
        dict(receivers=R, p0=-40, exponent=2.0, std=1.0, d_min=0.0),
        dict(receivers=R, p0=-40, exponent=2.0, std=1.0, height=np.inf),
        dict(receivers=[[0.0, np.nan]], p0=-40, exponent=2.0, std=1.0),
    ):
        with pytest.raises(ValidationError):
            RSSISensor(**kwargs)
    with pytest.raises(ShapeError):
        RSSISensor(np.zeros((2, 4)), p0=-40, exponent=2.0, std=1.0)
    with pytest.raises(ValidationError):
        RSSISensor(R, p0=-40, exponent=2.0, std=[1.0, 1.0, 1.0])
    with pytest.raises(ShapeError):
        RSSISensor(R, p0=-40, exponent=2.0, std=1.0).h([1.0])
    with pytest.raises(ValidationError, match="positive"):
        fit_path_loss([1.0, -2.0, 3.0], [0.0, 0.0, 0.0])
    with pytest.raises(ShapeError):
        fit_path_loss([1.0, 2.0, 3.0], [0.0, 0.0])
    with pytest.raises(ValidationError, match="at least 3"):
        fit_path_loss([1.0, 2.0], [0.0, 1.0])
    with pytest.raises(ValidationError, match="distinct"):
        fit_path_loss([2.0, 2.0, 2.0], [0.0, 1.0, 2.0])


def test_wrap_angle_range():
    a = np.array([-3 * np.pi, -np.pi, 0.0, np.pi, 3 * np.pi - 1e-9, 7.0])
    w = wrap_angle(a)
    assert np.all((w >= -np.pi) & (w < np.pi))
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-9)


def test_mean_reverting_velocity_against_van_loan():
    """F and Q of the Ornstein-Uhlenbeck velocity model against Van Loan's matrix exponential
    (C. F. Van Loan, "Computing integrals involving the matrix exponential", IEEE TAC 23(3), 1978)
    of the SDE dx = A x dt + B dW; the constant-velocity model in the limit tau -> inf."""
    from scipy.linalg import expm

    from dfusion.models import MeanRevertingVelocity

    m = MeanRevertingVelocity(2, sigma=0.05, tau=5.0)
    A = np.zeros((4, 4))
    A[0, 2] = A[1, 3] = 1.0
    A[2, 2] = A[3, 3] = -1.0 / m.tau
    BQB = np.diag([0.0, 0.0, m.q, m.q])
    for dt in (1e-4, 0.01, 0.049, 0.051, 1.0, 12.0, 30.0):      # (Van Loan loses accuracy for dt >> tau)
        M = expm(np.block([[-A, BQB], [np.zeros((4, 4)), A.T]]) * dt)
        F = M[4:, 4:].T
        Q = F @ M[:4, 4:]
        np.testing.assert_allclose(m.F(dt), F, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(m.Q(dt), Q, rtol=1e-8, atol=1e-20)
    # stationary velocity variance sigma^2; long-run position variance ~ 2 sigma^2 tau dt
    assert m.Q(1e4)[2, 2] == pytest.approx(0.05**2)
    assert m.Q(1e4)[0, 0] == pytest.approx(2 * 0.05**2 * 5.0 * 1e4, rel=1e-3)
    cv, slow = ConstantVelocity(2, 1e-3), MeanRevertingVelocity(2, sigma=math.sqrt(1e-3 * 1e6 / 2), tau=1e6)
    np.testing.assert_allclose(slow.Q(2.0), cv.Q(2.0), rtol=1e-5)
    np.testing.assert_allclose(slow.F(2.0), cv.F(2.0), atol=1e-5)
