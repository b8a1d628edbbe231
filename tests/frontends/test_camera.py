"""Camera nodes: field of view through the world, clutter, the Mahalanobis gate, scenario keys,
and the camera reliability model of the switching paper (eq. 1-9) against hand computations."""
from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from dfusion.errors import OutsideWindowError, ScenarioError
from dfusion.fusion import FusionNode
from dfusion.models import ConstantVelocity, PinholeCamera
from dfusion.reliability import (
    camera_geometry,
    camera_reliability,
    camera_reliability_at,
    pixel_footprint,
    recognition_accuracy,
    viewing_angle,
)
from dfusion.frontends import CameraFrontEnd, gate_threshold
from dfusion.models import SceneCamera
from dfusion.scenario import load_scenario
from dfusion.sim import simulate_world


def camera_scenario(**cam) -> dict:
    node = {"name": "cam", "sensor": "camera", "position": [0.0, -6.0, 5.0], "look_at": [0.0, 2.0],
            "fx": 600.0, "width": 640, "height": 480, "pixel_std": 2.0, "rate": 5.0, "send_period": 0.5}
    node.update(cam)
    return {
        "duration": 20.0, "dt": 0.1, "seed": 4, "window": 60,
        # the target crosses the view from left to right
        "target": {"motion": "constant_velocity", "q": 0.001, "initial_mean": [-12.0, 2.0, 1.2, 0.0],
                   "initial_cov_diag": [0.01, 0.01, 0.001, 0.001]},
        "nodes": [node, {"name": "relay", "send_period": 0.5}],
        "links": [{"between": ["cam", "relay"], "latency": 0.05}],
    }


# ----------------------------------------------------------------------------- world
def test_world_detects_only_in_view_and_every_frame_in_view():
    sc = load_scenario(camera_scenario())
    cam = sc.nodes["cam"].sensor
    w = simulate_world(sc)
    frames = np.round(0.2 * np.arange(1, 101), 9)
    seen = {t: cam.in_view(w.truth(t)) for t in frames}
    det = [m for m in w.measurements if m.node == "cam"]
    assert 0 < sum(seen.values()) < len(frames)          # in and out of view
    assert sorted(m.t for m in det) == [t for t in frames if seen[t]]
    for m in det:
        assert not m.clutter
        assert np.all(np.abs(m.z - cam.h(w.truth(m.t))) < 6 * cam.pixel_std)


def test_detection_probability_misses_frames():
    sc = load_scenario(camera_scenario(detection=0.5))
    w = simulate_world(sc)
    full = simulate_world(load_scenario(camera_scenario()))
    n, n_full = len(w.measurements), len(full.measurements)
    assert 0.3 * n_full < n < 0.7 * n_full


def test_clutter_is_uniform_in_the_image_flagged_and_leaves_the_rest_unchanged():
    clean = simulate_world(load_scenario(camera_scenario()))
    sc = load_scenario(camera_scenario(false_detection_rate=1.5))
    w = simulate_world(sc)
    clutter = [m for m in w.measurements if m.clutter]
    true = [m for m in w.measurements if not m.clutter]
    # Poisson(1.5) per frame over 100 frames: 150 +- 12
    assert 110 < len(clutter) < 190 and w.n_clutter == len(clutter)
    z = np.array([m.z for m in clutter])
    assert np.all((z >= 0) & (z < [640, 480]))
    assert abs(z[:, 0].mean() - 320) < 40 and abs(z[:, 1].mean() - 240) < 30
    # a separate generator: the truth and the true detections are bit-identical to the clutter-free world
    assert np.array_equal(w.states, clean.states)
    assert [(m.t, m.arrival) for m in true] == [(m.t, m.arrival) for m in clean.measurements]
    assert all(np.array_equal(a.z, b.z) for a, b in zip(true, clean.measurements))
    assert simulate_world(sc).n_clutter == len(clutter)   # deterministic


def _digest(world) -> str:
    h = hashlib.sha256()
    h.update(np.round(world.times, 9).tobytes())
    h.update(np.round(world.states, 9).tobytes())
    for m in world.measurements:
        h.update(repr((m.t, m.node, m.arrival)).encode())
        h.update(np.round(np.asarray(m.z, float), 9).tobytes())
    return h.hexdigest()


#: Digests of worlds produced before the clutter extension (dfusion/sim/world.py at e3518a2).
WORLD_DIGESTS = {
    "tests/data/mc4.scenario.toml": "172d655c49620093610b51e1696f44743f122094ff43db2d96d266a89ee42e7d",
    "topologies/tree7-outage.scenario.toml": "d67bc4b1a3239d0ffd561153ece113309bcbcad79bc8e52778209d66bb5913fb",
}


@pytest.mark.parametrize("path", sorted(WORLD_DIGESTS))
def test_existing_scenarios_produce_the_same_worlds_as_before_clutter(path):
    from pathlib import Path

    w = simulate_world(load_scenario(Path(__file__).resolve().parents[2] / path))
    assert not any(m.clutter for m in w.measurements)
    assert _digest(w) == WORLD_DIGESTS[path]


# ----------------------------------------------------------------------------- gate
def _node_and_camera(t_prior: float = 0.0, mean=(0.0, 2.0, 1.0, 0.0), var=0.04):
    motion = ConstantVelocity(2, q=0.01)
    node = FusionNode("cam", [], motion, window=50, prior=(t_prior, np.array(mean), var * np.eye(4)))
    cam = SceneCamera.looking_at([0.0, -6.0, 5.0], [0.0, 2.0, 0.0], fx=600, fy=600, cx=320, cy=240,
                                 width=640, height=480, pixel_std=2.0)
    return node, cam


def test_gate_accepts_a_true_detection_and_rejects_far_clutter():
    node, cam = _node_and_camera()
    fe = CameraFrontEnd(cam, gate=0.99)
    node.predict(0.5)
    truth = np.array([0.5, 2.0, 1.0, 0.0])
    z_true = cam.h(truth) + np.array([1.5, -1.0])
    assert fe.process(node, 0.5, z_true)
    mean, _ = node.estimate()
    assert np.hypot(*(mean[:2] - truth[:2])) < 0.1
    # a false detection in the image corner, metres away from the track
    z_false = np.array([20.0, 30.0])
    assert np.hypot(*(cam.ground_point(z_false) - truth[:2])) > 3
    before = node.estimate()[0].copy()
    assert not fe.process(node, 0.5, z_false)
    assert np.array_equal(node.estimate()[0], before)   # nothing fused
    assert (fe.stats.detections, fe.stats.fused, fe.stats.gated) == (2, 1, 1)
    assert fe.distances[0] < gate_threshold(0.99) < fe.distances[1]
    # the gate is the chi-square quantile with 2 dof
    assert gate_threshold(0.99) == pytest.approx(9.2103404, rel=1e-7)
    assert gate_threshold(1.0) == math.inf
    # the node reports the camera source with its reliability (eq. 1-9 at the estimate)
    src = node.sources["camera"]
    assert 0 < src.reliability <= 1
    assert src.reliability == pytest.approx(camera_reliability_at(cam, src.mean[:2]))
    assert fe.reliability(node) == pytest.approx(src.reliability)


def test_gate_uses_the_prediction_at_the_detection_time():
    node, cam = _node_and_camera()
    fe = CameraFrontEnd(cam)
    for t in (0.1, 0.2, 0.3, 0.4):
        node.predict(t)
    # between two window states: node.estimate(t) (a throw-away insertion), here x = 0.25
    mean, _ = fe.prediction(node, 0.25)
    assert mean[0] == pytest.approx(0.25)
    # newer than the newest state: the newest state predicted forward
    mean, cov = fe.prediction(node, 0.9)
    assert mean[0] == pytest.approx(0.9)
    assert cov[0, 0] > node.estimate()[1][0, 0]
    # a late true detection is gated (and accepted) at its own time; older than the window: refused
    truth_then = np.array([0.25, 2.0, 1.0, 0.0])
    assert fe.process(node, 0.25, cam.h(truth_then))
    with pytest.raises(OutsideWindowError):
        fe.process(node, -5.0, cam.h(truth_then))


def test_a_prediction_behind_the_camera_rejects_the_detection():
    node, cam = _node_and_camera(mean=(0.0, -12.0, 0.0, 0.0), var=0.01)
    fe = CameraFrontEnd(cam)
    assert not fe.process(node, 0.0, np.array([320.0, 240.0]))
    assert fe.stats.unprojectable == 1


def test_gated_clutter_in_a_simulated_run():
    """The front end fed every detection of a cluttered world: most clutter gated, true ones fused."""
    sc = load_scenario(camera_scenario(false_detection_rate=0.5, pixel_std=2.0))
    w = simulate_world(sc)
    cam = sc.nodes["cam"].sensor
    node = FusionNode("cam", [], sc.target.motion, window=60,
                      prior=(0.0, sc.target.initial_mean, sc.target.initial_cov))
    fe = CameraFrontEnd(cam, gate=0.99)
    fused = {True: 0, False: 0}
    total = {True: 0, False: 0}
    for m in sorted(w.measurements, key=lambda m: (m.arrival, m.t)):
        node.predict(m.t)
        total[m.clutter] += 1
        fused[m.clutter] += fe.process(node, m.t, m.z)
    assert total[True] > 30 and total[False] > 20
    assert fused[False] >= 0.95 * total[False]
    assert fused[True] <= 0.05 * total[True]
    T = w.times[-1]
    node.predict(T)
    assert np.hypot(*(node.estimate()[0][:2] - w.truth(T)[:2])) < 0.5


# ----------------------------------------------------------------------------- scenario keys
def test_yaw_pitch_equals_look_at():
    a = load_scenario(camera_scenario()).nodes["cam"].sensor
    pitch = math.degrees(math.atan2(5.0, 8.0))
    b = load_scenario(_without(camera_scenario(yaw=90.0, pitch=pitch), "look_at")).nodes["cam"].sensor
    assert np.allclose(a.R_wc, b.R_wc, atol=1e-12)
    assert isinstance(a, SceneCamera) and a.clutter_rate == 0.0
    down = load_scenario(_without(camera_scenario(yaw=0.0, pitch=90.0), "look_at")).nodes["cam"].sensor
    assert down.R_wc[2, 2] == pytest.approx(-1.0)
    assert camera_geometry(down).alpha == pytest.approx(0.0, abs=1e-9)


def _without(d: dict, key: str) -> dict:
    d["nodes"][0].pop(key)
    return d


@pytest.mark.parametrize("change, words", [
    ({"position": [0, 0]}, "position"),
    ({"yaw": 10.0}, "look_at"),
    ({"fx": -1.0}, "fx"),
    ({"width": 64.5}, "width"),
    ({"false_detection_rate": -0.1}, "false_detection_rate"),
    ({"gate": 1.5}, "gate"),
    ({"clutter_model": "mht"}, "clutter_model"),
    ({"zoom": 2}, "zoom"),
    ({"position": [0.0, -6.0, -1.0]}, "above"),
])
def test_bad_camera_keys_raise_scenario_errors(change, words):
    with pytest.raises(ScenarioError) as info:
        load_scenario(camera_scenario(**change))
    assert words in str(info.value) and "cam" in str(info.value)


# ----------------------------------------------------------------------------- reliability (eq. 1-9)
def hand_reliability(phi_deg, alpha_deg, h, theta_deg, N, k):
    """Eq. (1)-(9) of the switching paper, step by step with math (no numpy)."""
    phi, alpha, theta = (math.radians(v) for v in (phi_deg, alpha_deg, theta_deg))
    theta0 = theta / N                                                        # (1)
    def D(p):                                                                 # (3)
        return (1 / math.cos(p + alpha) ** 2) * h / (1 / math.tan(theta0) - math.tan(p + alpha))
    w = 0.3                                                                   # any mark width
    n, n_max = w / D(phi), w / D(-theta / 2)                                  # (5)
    Phi = n / n_max                                                           # (6)
    E = k * D(phi)                                                            # (7)
    S = 1 / (E + 1)                                                           # (8)
    return Phi * S                                                            # (9)


@pytest.mark.parametrize("phi", [-29.0, 0.0, 20.0, 28.0])
def test_reliability_matches_the_hand_computation_for_the_papers_indoor_camera(phi):
    # alpha = 40 deg, h = 2 m, N = 900, theta = 58 deg (the paper's Figure 4), k = 5 pixels
    got = camera_reliability(math.radians(phi), math.radians(40), 2.0, math.radians(58), 900, 5.0)
    assert got == pytest.approx(hand_reliability(phi, 40, 2.0, 58, 900, 5.0), rel=1e-12)


def test_reliability_properties():
    a, h, th, N = math.radians(40), 2.0, math.radians(58), 900
    phis = np.radians(np.linspace(-29, 29, 59))
    R = camera_reliability(phis, a, h, th, N, 5.0)
    assert R[0] == pytest.approx(1 / (1 + 5.0 * pixel_footprint(-th / 2, a, h, th / N)))  # Phi = 1 at the edge
    assert np.all(np.diff(R) < 0)                    # decreases with the distance
    assert camera_reliability(math.radians(30), a, h, th, N) == 0.0   # outside the image rows
    # eq. (4) is close to eq. (3) for small theta_0
    approx = camera_reliability(phis, a, h, th, N, 5.0, approximate=True)
    assert np.allclose(approx, R, rtol=0.02)
    assert np.all((0 <= R) & (R <= 1))
    assert np.all(recognition_accuracy(phis, a, h, th, N) <= 1.0)


@pytest.mark.parametrize("height, look, target", [
    (5.0, (0.0, 8.0), (1.0, 8.0)),     # on the optical axis region
    (4.0, (3.0, 5.0), (1.0, 3.0)),     # off the principal column
    (6.0, (0.0, 12.0), (0.0, 18.0)),   # far: low reliability
])
def test_reliability_of_a_pinhole_camera_matches_the_hand_computation(height, look, target):
    cam = PinholeCamera.looking_at([0.0, 0.0, height], [look[0], look[1], 0.0], fx=500, fy=500, cx=320, cy=240,
                                   width=640, height=480, pixel_std=2.0)
    assert cam.in_view(np.array(target))
    # hand: alpha from the look-at geometry, theta = 2 atan(240 / 500), phi from the image row
    alpha = math.degrees(math.atan2(math.hypot(*look), height))
    theta = math.degrees(2 * math.atan(240 / 500))
    u, v = cam.h(np.array(target))
    phi = math.degrees(math.atan((240 - v) / 500))
    g = camera_geometry(cam)
    assert math.degrees(g.alpha) == pytest.approx(alpha, rel=1e-12)
    assert math.degrees(g.theta) == pytest.approx(theta, rel=1e-12)
    assert g.h == height and g.N == 480
    assert math.degrees(viewing_angle(cam, target)) == pytest.approx(phi, abs=1e-9)
    want = hand_reliability(phi, alpha, height, theta, 480, 2.0)
    assert camera_reliability_at(cam, target) == pytest.approx(want, rel=1e-9)
    assert camera_reliability_at(cam, (40.0, 40.0)) == 0.0       # out of view
