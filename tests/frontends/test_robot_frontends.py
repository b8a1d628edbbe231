"""Robot localizers as fusion-node front ends (dfusion.frontends, dfusion.localization.env_camera,
dfusion.scenario.robot_kinds) and the map constraint shared by dfusion.maps and the WSN tracker.

References are independent of the code under test where possible: finite differences for
Jacobians, Monte Carlo sampling for propagated covariances, the switching paper's eq. 1-9
written out by hand, the dfusion.models.Unicycle steps one by one, a dense sampling of
segments for the map test.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from dfusion.errors import ShapeError, ValidationError
from dfusion.fusion import FusionNode
from dfusion.models import LaserConfig, LikelihoodFieldModel
from dfusion.localization import MonteCarloLocalization, ScanMatcher
from dfusion.localization import EnvironmentCameraLocalizer
from dfusion.reliability import camera_reliability
from dfusion.frontends import (
    EnvCameraFrontEnd,
    fit_difference_information,
    ICPFrontEnd,
    MCLFrontEnd,
    position_information,
)
from dfusion.localization import LandmarkEKF
from dfusion.models import LandmarkRangeBearing, LaserScanSensor, PositionFix, TargetRangeBearing, VelocityOdometry
from dfusion.maps import OccupancyGrid
from dfusion.models import ConstantVelocity, PinholeCamera, Unicycle
from dfusion.maps.io import read_occ
from dfusion.maps.buildings import rooms


def fd_jacobian(f, x, eps=1e-6):
    x = np.asarray(x, float)
    cols = []
    for i in range(x.size):
        d = np.zeros_like(x)
        d[i] = eps
        cols.append((f(x + d) - f(x - d)) / (2 * eps))
    return np.column_stack(cols)


# --------------------------------------------------------------------------- measurement models
def test_landmark_range_bearing_jacobian_and_values():
    s = LandmarkRangeBearing([3.0, 1.0], 0.1, 0.01)
    x = np.array([1.0, -0.5, 0.3])
    z = s.h(x)
    assert z[0] == pytest.approx(math.hypot(2.0, 1.5))
    assert z[1] == pytest.approx(math.atan2(1.5, 2.0) - 0.3)
    np.testing.assert_allclose(s.H(x), fd_jacobian(s.h, x), atol=1e-7)
    np.testing.assert_allclose(s.R, np.diag([0.01, 1e-4]))


def test_target_range_bearing_effective_noise_matches_monte_carlo():
    rng = np.random.default_rng(0)
    pose = np.array([1.0, 2.0, 0.4])
    Ps = np.array([[0.04, 0.01, 0.002], [0.01, 0.09, -0.003], [0.002, -0.003, 0.0025]])
    target = np.array([4.0, 3.5])
    rs, bs = 0.1, 0.02
    # true observer poses around the estimate; measurements from the true pose
    n = 200_000
    L = np.linalg.cholesky(Ps)
    true_pose = pose + rng.standard_normal((n, 3)) @ L.T
    d = target - true_pose[:, :2]
    z = np.column_stack([np.hypot(d[:, 0], d[:, 1]) + rs * rng.standard_normal(n),
                         np.arctan2(d[:, 1], d[:, 0]) - true_pose[:, 2] + bs * rng.standard_normal(n)])
    z_nom = np.array([np.hypot(*(target - pose[:2])), math.atan2(*(target - pose[:2])[::-1]) - pose[2]])
    m = TargetRangeBearing(pose, Ps, z_nom, rs, bs)
    np.testing.assert_allclose(m.H(np.r_[target, 0, 0]), fd_jacobian(lambda q: m.h(q), np.r_[target, 0.0, 0.0]), atol=1e-7)
    # polar R_eff: the spread of z - h(target) seen from the estimated pose
    resid = z - m.h(target)
    emp = np.cov(resid.T)
    np.testing.assert_allclose(m.R, emp, rtol=0.05, atol=1e-6)
    # Cartesian fix: the spread of the fixes computed from the *estimated* pose
    fixes = pose[:2] + z[:, :1] * np.column_stack([np.cos(pose[2] + z[:, 1]), np.sin(pose[2] + z[:, 1])])
    fix = m.position_fix()
    assert isinstance(fix, PositionFix) and fix.is_linear
    np.testing.assert_allclose(fix.z, target, atol=1e-9)
    np.testing.assert_allclose(fix.R, np.cov(fixes.T), rtol=0.05, atol=1e-6)
    np.testing.assert_allclose(fixes.mean(axis=0), target, atol=0.01)


def test_position_fix_and_information_helpers():
    f = PositionFix([1.0, 2.0], [[0.5, 0.1], [0.1, 0.3]])
    np.testing.assert_array_equal(f.H(np.zeros(4)), np.eye(2, 4))
    Lam, y = position_information([1.0, 2.0], [[0.5, 0.1], [0.1, 0.3]], 4)
    W = np.linalg.inv([[0.5, 0.1], [0.1, 0.3]])
    np.testing.assert_allclose(Lam[:2, :2], W)
    np.testing.assert_allclose(y[:2], W @ [1.0, 2.0])
    assert not Lam[2:].any() and not y[2:].any()
    # posterior fit minus prior fit = measurement information (linear Gaussian case)
    P0, m0 = np.diag([1.0, 2.0]), np.array([0.0, 1.0])
    Pz, mz = np.diag([0.2, 0.5]), np.array([0.3, 0.2])
    P1 = np.linalg.inv(np.linalg.inv(P0) + np.linalg.inv(Pz))
    m1 = P1 @ (np.linalg.inv(P0) @ m0 + np.linalg.inv(Pz) @ mz)
    Lam2, y2 = fit_difference_information((m0, P0), (m1, P1), 4)
    np.testing.assert_allclose(Lam2[:2, :2], np.linalg.inv(Pz), atol=1e-12)
    np.testing.assert_allclose(y2[:2], np.linalg.inv(Pz) @ mz, atol=1e-12)
    # a posterior wider than the prior in one direction: that direction is dropped
    Lam3, _ = fit_difference_information((m0, P0), (m0, np.diag([0.5, 4.0])), 4)
    assert np.all(np.linalg.eigvalsh(Lam3) >= -1e-12) and Lam3[1, 1] == pytest.approx(0.0, abs=1e-12)


# --------------------------------------------------------------------------- odometry, landmark EKF
def test_velocity_odometry_equals_unicycle_steps():
    motion = Unicycle(0.02, 0.05)
    t = np.array([0.5, 0.7, 0.7 + 1e-3, 1.0, 1.0 + 0.4, 2.0])
    u = np.array([[0.3, 0.2], [0.3, 0.2], [0.5, -0.4], [0.0, 0.0], [0.2, 0.0], [0.1, 0.5]])
    odo = VelocityOdometry(t, u, motion)
    assert odo.times.size == 5  # the repeated row is merged
    x0 = np.array([1.0, 2.0, 3.0])
    x, F, Q = odo.propagate(x0, 0.0, 2.3)
    # reference: dfusion.models.Unicycle piece by piece (unmerged rows)
    edges = [0.0, *t, 2.3]
    xr, Fr, Qr = x0.copy(), np.eye(3), np.zeros((3, 3))
    for k in range(len(edges) - 1):
        a, b = edges[k], edges[k + 1]
        if k == 0 or b <= a:
            continue  # standing still before the first row
        uk = u[k - 1]
        Fi, Qi = motion.F(b - a, xr, uk), motion.Q(b - a, xr, uk)
        xr = motion.f(xr, b - a, uk)
        Fr, Qr = Fi @ Fr, Fi @ Qr @ Fi.T + Qi
    np.testing.assert_allclose(x, xr, atol=1e-12)
    np.testing.assert_allclose(F, Fr, atol=1e-12)
    # merging the two identical pieces changes Q by the linearization only
    np.testing.assert_allclose(Q, Qr, rtol=1e-3, atol=1e-9)
    with pytest.raises(ValidationError):
        odo.propagate(x0, 1.0, 0.5)


def test_landmark_ekf_localizes_and_gates_outliers():
    rng = np.random.default_rng(3)
    motion = Unicycle(0.01, 0.02)
    t = np.arange(0.0, 60.0, 0.1)
    u = np.column_stack([np.full(t.size, 0.2), 0.1 * np.sin(0.1 * t)])
    true_odo = VelocityOdometry(t, u, motion)
    noisy = VelocityOdometry(t, u * (1 + 0.05 * rng.standard_normal((t.size, 2))), motion)
    lms = np.array([[0.0, 5.0], [6.0, 0.0], [6.0, 6.0], [-3.0, 3.0]])
    ekf = LandmarkEKF(noisy, 0.0, [0.0, 0.0, 0.0], np.diag([0.01, 0.01, 0.01]))
    x_true = np.zeros(3)
    errs = []
    for k in range(1, 60):
        x_true, _, _ = true_odo.propagate(x_true, k - 1.0, float(k))
        ekf.predict(float(k))
        for j, lm in enumerate(lms):
            s = LandmarkRangeBearing(lm, 0.1, 0.02)
            z = s.h(x_true) + [0.1 * rng.standard_normal(), 0.02 * rng.standard_normal()]
            if k == 30 and j == 0:
                z[0] += 5.0  # an outlier
            ekf.update(float(k), z, s)
        errs.append(np.hypot(*(ekf.x[:2] - x_true[:2])))
    assert ekf.rejected >= 1 and ekf.accepted > 200
    assert np.sqrt(np.mean(np.square(errs))) < 0.15
    est = ekf.estimate()
    assert est.cov.shape == (3, 3) and 0 < est.reliability <= 1


# --------------------------------------------------------------------------- environmental camera
def test_camera_reliability_is_eq_1_to_9():
    """The shared model (dfusion.reliability) used by the localizer, against eq. 1-9 by hand."""
    alpha, h, N, theta, k = math.radians(40), 2.0, 900, math.radians(58), 3.0
    th0 = theta / N

    def D(phi):
        return math.tan(phi + alpha + th0) * h - math.tan(phi + alpha) * h  # eq. 3, first form

    for phi in np.linspace(-theta / 2, theta / 2, 7):
        phi_ = float(phi)
        n, n_max = 1.0 / D(phi_), 1.0 / D(-theta / 2)  # eq. 5 with w = 1
        Phi = n / n_max  # eq. 6
        E = k * D(phi_)  # eq. 7
        S = 1.0 / (E + 1.0)  # eq. 8
        assert camera_reliability(phi_, alpha, h, theta, N, k) == pytest.approx(Phi * S, rel=1e-12)  # eq. 9
    # eq. 3 second form (sec^2 / (cot theta0 - tan)) is the same D
    phi = 0.1
    D2 = h / math.cos(phi + alpha) ** 2 / (1 / math.tan(th0) - math.tan(phi + alpha))
    assert D(phi) == pytest.approx(D2, rel=1e-9)
    r = camera_reliability(np.linspace(-theta / 2, theta / 2, 50), alpha, h, theta, N, k)
    assert np.all(np.diff(r) < 0) and r[0] == pytest.approx(1 / (k * D(-theta / 2) + 1))
    assert camera_reliability(math.pi / 2 - alpha, alpha, h, theta, N, k) == 0.0  # beyond the horizon


def ceiling_camera(pixel_std=1.0):
    return PinholeCamera.looking_at([0.0, 0.0, 3.0], [4.0, 0.0, 0.0], fx=600, fy=600, cx=320, cy=240,
                                    width=640, height=480, pixel_std=pixel_std)


def test_env_camera_localizer_position_covariance_heading():
    cam = ceiling_camera(pixel_std=2.0)
    loc = EnvironmentCameraLocalizer(cam, min_baseline=0.3)
    geo = loc.geometry
    assert geo.alpha == pytest.approx(math.atan2(4.0, 3.0))
    assert geo.h == pytest.approx(3.0) and geo.N == 480
    # the pixel row's angle is the shared model's viewing angle of the ground point
    from dfusion.reliability import camera_reliability_at

    assert loc.reliability(cam.h([3.0, 0.5])) == pytest.approx(camera_reliability_at(cam, [3.0, 0.5]), rel=1e-9)
    p_true = np.array([3.0, 0.5])
    px = cam.h(p_true)
    assert loc.update(0.0, px)
    est = loc.estimate()
    np.testing.assert_allclose(est.mean[:2], p_true, atol=1e-9)
    assert est.cov[2, 2] == pytest.approx(math.pi**2 / 3)  # no heading yet
    # covariance: Monte Carlo of the pixel noise through the back-projection
    rng = np.random.default_rng(1)
    pts = np.array([cam.ground_point(px + 2.0 * rng.standard_normal(2)) for _ in range(20000)])
    emp = np.cov(pts.T)
    np.testing.assert_allclose(est.cov[:2, :2], emp, rtol=0.06, atol=0.03 * emp.max())
    # farther from the camera: larger covariance, lower reliability
    assert loc.update(10.0, cam.h([6.0, 0.5]))
    far = loc.estimate()
    assert far.reliability < est.reliability and np.trace(far.cov[:2, :2]) > np.trace(est.cov[:2, :2])
    # heading from the displacement of two fixes less than max_gap apart
    assert loc.update(11.0, cam.h([6.0, 1.5]))
    e2 = loc.estimate()
    assert e2.mean[2] == pytest.approx(math.pi / 2, abs=0.01) and e2.cov[2, 2] < 0.01
    assert not loc.update(12.0, [-5.0, 10.0])  # outside the image


# --------------------------------------------------------------------------- front ends and fusion
PRIOR = (0.0, np.array([3.0, 4.0, 0.3, 0.0]), np.diag([0.04, 0.04, 0.01, 0.01]))


def pair(window=50):
    cv = ConstantVelocity(2, 0.01)
    a = FusionNode("a", ["b"], cv, window=window, prior=PRIOR, epoch=1)
    b = FusionNode("b", ["a"], cv, window=window, prior=PRIOR, epoch=2)
    return a, b


@pytest.fixture(scope="module")
def room():
    return rooms(12.0, 8.0, 1, 1, obstacles=6, seed=4)


def scans_along(grid, laser, n, rng, dt=0.5):
    sensor = LaserScanSensor(grid, laser, 0.02)
    out = []
    for k in range(1, n + 1):
        x = np.array([3.0 + 0.3 * k * dt, 4.0 + 0.02 * k, 0.3, 0.04])
        out.append((k * dt, x, sensor.h(x) + 0.02 * rng.standard_normal(laser.angles.size)))
    return out


@pytest.mark.parametrize("kind", ["icp", "mcl", "camera"])
def test_front_end_contribution_reaches_the_neighbour_without_double_counting(kind, room):
    rng = np.random.default_rng(5)
    laser = LaserConfig.uniform(61, 2 * math.pi, 10.0)
    a, b = pair()
    if kind == "icp":
        fe = ICPFrontEnd(ScanMatcher.from_grid(room, "point_to_line", trim_fraction=0.1, tolerance=1e-4), laser)
        data = [(t, x, z) for t, x, z in scans_along(room, laser, 6, rng)]
    elif kind == "mcl":
        mcl = MonteCarloLocalization(room, laser, sensor=LikelihoodFieldModel(), max_particles=3000, rng=2)
        fe = MCLFrontEnd(mcl)
        data = [(t, x, z) for t, x, z in scans_along(room, laser, 6, rng)]
    else:
        cam = ceiling_camera()
        fe = EnvCameraFrontEnd(EnvironmentCameraLocalizer(cam))
        data = []
        for k in range(1, 7):
            x = np.array([3.0 + 0.15 * k, 0.2, 0.3, 0.0])
            data.append((0.5 * k, x, cam.h(x) + rng.standard_normal(2)))
    for t, _, z in data:
        a.predict(t)
        b.predict(t)
        fe.process(a, t, z)
    assert fe.stats.contributed == len(data), fe.stats
    t_end = data[-1][0]
    ma, Pa = a.estimate()
    # the node learned something: its position error is small and its covariance shrank
    assert np.hypot(*(ma[:2] - data[-1][1][:2])) < 0.1
    assert np.trace(Pa[:2, :2]) < 0.2 * np.trace(PRIOR[2][:2, :2])
    # exchange: the receiver's estimate equals the sender's
    b.receive(a.message_to("b"))
    mb, Pb = b.estimate()
    np.testing.assert_allclose(mb, ma, atol=1e-9)
    np.testing.assert_allclose(Pb, Pa, atol=1e-10)
    # and the echo changes nothing at the sender (no double counting)
    a.receive(b.message_to("a"))
    ma2, Pa2 = a.estimate()
    np.testing.assert_allclose(ma2, ma, atol=1e-9)
    np.testing.assert_allclose(Pa2, Pa, atol=1e-10)
    # a switching policy can see the localizer as a source in the node's state space
    src = a.sources[next(iter(a.sources))]
    assert src.mean.shape == (4,) and src.cov.shape == (4, 4) and 0 < src.reliability <= 1 and src.t == t_end


def test_mcl_contribution_is_the_scan_information(room):
    """Node posterior after the contribution = the particles' posterior fit (Gaussian identity)."""
    rng = np.random.default_rng(7)
    laser = LaserConfig.uniform(61, 2 * math.pi, 10.0)
    cv = ConstantVelocity(2, 0.01)
    node = FusionNode("a", [], cv, window=20, prior=PRIOR)
    mcl = MonteCarloLocalization(room, laser, sensor=LikelihoodFieldModel(), adaptive=False, n_particles=20000,
                                 ess_floor=0.0, rng=3)
    fe = MCLFrontEnd(mcl)
    t, x, z = scans_along(room, laser, 1, rng)[0]
    node.predict(t)
    m_prior, P_prior = node.estimate()
    fe.process(node, t, z)
    m, P = node.estimate()
    post = fe.last
    np.testing.assert_allclose(m[:2], post.mean[:2], atol=0.01)
    np.testing.assert_allclose(P[:2, :2], post.cov[:2, :2], rtol=0.15, atol=1e-5)
    assert np.trace(P[:2, :2]) < 0.1 * np.trace(P_prior[:2, :2])


def test_laser_scan_sensor_shapes_and_jacobian(room):
    laser = LaserConfig.uniform(31, 2 * math.pi, 10.0)
    s = LaserScanSensor(room, laser, 0.05)
    x = np.array([3.0, 4.0, 0.3, 0.1])
    assert s.h(x).shape == (31,) and s.R.shape == (31, 31)
    H = s.H(x)
    assert H.shape == (31, 4) and np.isfinite(H).all()
    ok = np.any(H != 0, axis=1)
    assert ok.mean() > 0.7
    # the kept rows predict the ranges after a small move (the walls are cell staircases,
    # so the linearization is only good on average)
    rng = np.random.default_rng(0)
    errs = []
    for _ in range(20):
        dx = np.r_[rng.normal(0, 0.03, 2), 0.0, 0.0]
        errs.append(np.abs(s.h(x + dx) - s.h(x) - H @ dx)[ok])
    assert np.median(np.concatenate(errs)) < 0.01


# --------------------------------------------------------------------------- scenario kinds
MAP = {"map": "rooms", "map_args": {"width": 12.0, "height": 8.0, "rooms_x": 1, "rooms_y": 1, "obstacles": 6, "seed": 4}}


def robot_scenario():
    return {
        "duration": 10.0, "dt": 0.1, "seed": 1, "window": 200,
        "target": {"motion": "constant_velocity", "q": 0.005, "initial_mean": [3.0, 4.0, 0.4, 0.1],
                   "initial_cov_diag": [0.01, 0.01, 0.0025, 0.0025]},
        "nodes": [
            {"name": "cam", "sensor": "robot_env_camera", "rate": 2.0, "send_period": 0.5,
             "camera_position": [0.0, 4.0, 3.0], "camera_target": [5.0, 4.0, 0.0]},
            {"name": "mcl", "sensor": "robot_mcl", "rate": 2.0, "send_period": 0.5, "particles": 1000, **MAP},
            {"name": "icp", "sensor": "robot_icp", "rate": 2.0, "send_period": 0.5, **MAP},
        ],
        "links": [{"between": ["cam", "mcl"], "latency": 0.05}, {"between": ["mcl", "icp"], "latency": 0.05}],
    }


def test_robot_scenario_kinds_run_and_agree():
    from dfusion.scenario import build_front_ends
    from dfusion.sim import run_scenario
    from dfusion.scenario import load_scenario

    sc = load_scenario(robot_scenario())
    fronts = build_front_ends(sc)
    assert isinstance(fronts["cam"], EnvCameraFrontEnd) and isinstance(fronts["mcl"], MCLFrontEnd)
    assert isinstance(fronts["icp"], ICPFrontEnd)
    res = run_scenario(sc)
    for name in ("cam", "mcl", "icp"):
        assert res.metrics["nodes"][name]["rmse"] < 0.08, res.table()
    # after the final lossless rounds every node holds the same information: the same
    # final estimate, hence the same distance to the (laser-range) centralized EKF
    gaps = [res.metrics["nodes"][n]["final_gap"] for n in ("cam", "mcl", "icp")]
    assert max(gaps) - min(gaps) < 1e-6


def test_robot_scenario_errors():
    from dfusion.errors import ScenarioError
    from dfusion.scenario import load_scenario

    raw = robot_scenario()
    raw["nodes"][0] = {"name": "cam", "sensor": "robot_env_camera"}  # no camera pose
    with pytest.raises(ScenarioError, match="camera_position"):
        load_scenario(raw)
    raw = robot_scenario()
    raw["nodes"][1]["map"] = "no/such/map.yaml"
    with pytest.raises(ScenarioError, match="not found"):
        load_scenario(raw)


# --------------------------------------------------------------------------- map constraint (dfusion.maps, used by the WSN tracker)
def test_segment_blocked_on_a_rotated_map_with_unknown_cells():
    rng = np.random.default_rng(4)
    data = np.where(rng.random((30, 40)) < 0.15, 100, 0)
    data[:3, :3] = -1  # unknown cells block (unknown_blocks=True)
    g = OccupancyGrid(data, 0.2, origin=(1.0, -2.0, 0.6))
    a = g.sample_free(600, rng)
    b = a + rng.standard_normal((600, 2)) * 0.8
    got = g.segment_blocked(a, b)
    dense = np.linspace(0, 1, 800)[None, :, None]
    pts = a[:, None, :] + dense * (b - a)[:, None, :]
    ref = g.is_blocked(pts.reshape(-1, 2)).reshape(600, -1).any(axis=1)
    assert np.mean(got == ref) > 0.99  # the dense test misses corner clips only
    assert np.all(got[ref])  # never misses what the dense test sees
    assert not g.is_blocked(a).any() and g.is_blocked(np.array([[np.nan, 0.0], [-50.0, 0.0]])).all()
    unk = g.cell_to_world(1, 1)
    assert g.is_blocked(unk[None])[0] and not g.is_blocked(unk[None], unknown_blocks=False)[0]
    with pytest.raises(ShapeError):
        g.segment_blocked(a, b[:5])


def test_node_grid_view_is_the_map_grid(tmp_path):
    from dfusion.maps import NodeLattice as NodeGrid
    from dfusion.localization import WSNTracker
    from dfusion.models import RSSISensor

    occ = np.zeros((5, 4), bool)
    occ[0, :] = occ[:, 0] = occ[3, 2] = True
    v = NodeGrid(occ, 0.5, origin=(1.0, 2.0))
    m = v.map
    assert isinstance(m, OccupancyGrid) and m.shape == (4, 5) and v.shape == (5, 4)
    np.testing.assert_array_equal(m.occupied, occ.T)
    np.testing.assert_allclose(m.origin, [0.75, 1.75, 0.0])
    np.testing.assert_allclose(v.cell_to_world([3, 2]), m.cell_to_world(2, 3))
    lines = [f"[{1.0 + 0.5 * i}, {2.0 + 0.5 * j}]::{int(occ[i, j])}" for i in range(5) for j in range(4)]
    f = tmp_path / "g_0.5.occ"
    f.write_text("[[1.0, 2.0], [3.0, 3.5]]::0.5\n" + "\n".join(lines) + "\n")
    np.testing.assert_array_equal(read_occ(f).data, m.data)
    # WSNTracker takes either; the same seed gives the same particles
    s = RSSISensor(np.array([[1.0, 2.0, 2.0], [3.0, 3.0, 2.0]]), -40.0, 2.0, 4.0)
    t1 = WSNTracker(s, 200, grid=v, seed=3)
    t2 = WSNTracker(s, 200, grid=m, seed=3)
    t1.initialize()
    t2.initialize()
    np.testing.assert_array_equal(t1.particles, t2.particles)
    assert not m.is_blocked(t1.particles).any()
