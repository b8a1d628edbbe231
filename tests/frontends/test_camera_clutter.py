"""Camera frames under clutter (dfusion.frontends.camera): PDA in the node, the centralized
reference's frame updates, the track-loss test with the withdrawal of tentative frames (through
the v2 protocol's partial messages), and the loss evidence by hand."""
from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter

from dfusion.estimation import CentralizedEKF
from dfusion.estimation.pda import ClutterModel, pda_update
from dfusion.frontends.camera import CameraFrontEnd, loss_log_likelihood_ratio, miss_probability
from dfusion.fusion import FusionNode
from dfusion.models import ConstantVelocity, PositionSensor, SceneCamera

MOTION = ConstantVelocity(2, q=0.01)


def _camera(rate: float = 0.0) -> SceneCamera:
    cam = SceneCamera.looking_at([0.0, -6.0, 5.0], [0.0, 2.0, 0.0], fx=600, fy=600, cx=320, cy=240,
                                 width=640, height=480, pixel_std=2.0)
    cam.clutter_rate = rate
    return cam


def _node(name="cam", neighbors=(), var=0.04, mean=(0.0, 2.0, 1.0, 0.0)):
    return FusionNode(name, list(neighbors), MOTION, window=80, prior=(0.0, np.array(mean), var * np.eye(4)))


def test_a_frame_without_clutter_model_is_the_plain_eif_update():
    cam = _camera(0.0)
    a, b = _node(), _node()
    fe = CameraFrontEnd(cam, detection=0.9)
    truth = np.array([0.5, 2.0, 1.0, 0.0])
    for node in (a, b):
        node.predict(0.5)
    z = cam.h(truth) + [1.0, -0.5]
    assert fe.process_frame(a, 0.5, np.array([z, [30.0, 20.0]])) == 1   # the far one is gated out
    b.update(0.5, z, cam)
    for x, y in zip(a.estimate(), b.estimate()):
        assert np.array_equal(x, y)


def test_a_cluttered_frame_enters_the_node_as_the_pda_posterior():
    """Two detections in the gate: the node's estimate afterwards is the EKF-PDA posterior of its
    prediction (dfusion.estimation.pda, itself checked against brute force in test_pda.py)."""
    cam = _camera(0.5)
    node = _node(var=0.09)
    fe = CameraFrontEnd(cam, detection=0.9)
    node.predict(0.5)
    prior = node.estimate()
    truth = np.array([0.55, 2.05, 1.0, 0.0])
    Z = np.array([cam.h(truth), cam.h(truth) + [14.0, 9.0]])
    model = ClutterModel(0.5 / (640 * 480), 0.9, 0.99)
    ref = pda_update(*prior, Z, cam, model, detection=fe.detection_probability(*prior))
    assert ref.validated.all() and 0 < ref.beta0 < 0.2
    assert fe.process_frame(node, 0.5, Z) == 2
    mean, cov = node.estimate()
    np.testing.assert_allclose(mean, ref.mean, atol=1e-9)
    np.testing.assert_allclose(cov, ref.cov, atol=1e-9)
    assert fe.stats.nis_count == 1 and fe.stats.frames_fused == 1


def test_centralized_frames_are_rerun_in_time_order_after_a_late_measurement():
    """A frame update at t = 0.6 and a position measurement at 0.3 added after it: the filter
    re-runs from before 0.3 and equals filterpy's EKF doing the two in time order."""
    cam = _camera(0.3)
    fe = CameraFrontEnd(cam, detection=0.9)
    pos = PositionSensor(2, 0.5)
    x0, P0 = np.array([0.0, 2.0, 1.0, 0.0]), np.diag([0.2, 0.2, 0.05, 0.05])
    Z = np.array([cam.h(np.array([0.62, 2.0, 1.0, 0.0])), [600.0, 30.0]])
    ekf = CentralizedEKF(MOTION, 0.0, x0, P0)
    ekf.add_frame(0.6, fe.reference_frame(0.6, Z), seq=1)
    first = ekf.estimate(0.6)
    ekf.add(0.3, np.array([0.31, 2.02]), pos, seq=0)
    got = ekf.estimate(0.6)
    ref = ExtendedKalmanFilter(dim_x=4, dim_z=2)
    ref.x, ref.P = x0.copy(), P0.copy()
    ref.F, ref.Q = MOTION.F(0.3), MOTION.Q(0.3)
    ref.predict()
    ref.update(np.array([0.31, 2.02]), HJacobian=pos.H, Hx=pos.h, R=pos.R)
    ref.predict()
    res = pda_update(ref.x, ref.P, Z, cam, fe.model, detection=fe.detection_probability(ref.x, ref.P))
    np.testing.assert_allclose(got[0], res.mean, atol=1e-9)
    np.testing.assert_allclose(got[1], res.cov, atol=1e-9)
    assert not np.allclose(first[0], got[0])


def test_a_track_loss_withdraws_an_unconfirmed_clutter_association_nobody_else_saw():
    """cam - relay. The target re-enters the view with an uncertain prediction; a false detection
    near the prediction is associated (a tentative frame: fused by cam, not sent). Then the true
    target is detected frame after frame far outside the gate: the CUSUM declares a loss, the
    tentative frame is withdrawn and cam is back to its estimate without it; relay never had it."""
    cam = _camera(0.3)
    node, clean, relay = _node(neighbors=["relay"], var=0.5), _node(neighbors=["relay"], var=0.5), \
        _node("relay", ["cam"], var=0.5)
    fe = CameraFrontEnd(cam, detection=0.9, segment_gap=0.6)
    t = 0.2
    for n in (node, clean, relay):
        n.predict(t)
    mean, _ = node.estimate()
    assert fe.process_frame(node, t, np.array([cam.h(mean) + [3.0, -2.0]])) == 1     # the false one
    assert not np.allclose(node.estimate()[0], clean.estimate()[0])
    relay.receive(node.message_to("relay"))
    assert len(relay.channels["cam"]) == 0                    # held back: nothing was sent
    lost_truth = mean + np.array([1.5, 1.2, 0.0, 0.0])       # the real target, far from the gate
    k = 0
    while fe.status() == "ok":
        k += 1
        t = round(0.2 + 0.2 * k, 9)
        for n in (node, clean, relay):
            n.predict(t)
        fe.process_frame(node, t, np.array([cam.h(lost_truth + [0.2 * k, 0, 0, 0])]))
        assert k < 6
    assert fe.stats.losses == 1 and fe.stats.withdrawn == 1 and fe.status() == "lost"
    for x, y in zip(node.estimate(), clean.estimate()):
        np.testing.assert_allclose(x, y, atol=1e-9)
    relay.receive(node.message_to("relay"))
    for x, y in zip(relay.estimate(), clean.estimate()):
        np.testing.assert_allclose(x, y, atol=1e-9)      # the relay never fused the false detection


def test_tentative_frames_are_sent_once_a_second_frame_confirms_them():
    cam = _camera(0.3)
    node, relay = _node(neighbors=["relay"]), _node("relay", ["cam"])
    fe = CameraFrontEnd(cam, detection=0.9, segment_gap=0.6)
    truth = np.array([0.0, 2.0, 1.0, 0.0])
    for k, share in ((1, False), (2, True)):
        t = 0.2 * k
        node.predict(t)
        relay.predict(t)
        fe.process_frame(node, t, np.array([cam.h(truth + [t, 0, 0, 0])]))
        relay.receive(node.message_to("relay"))
        assert (len(relay.channels["cam"]) > 0) == share
    for x, y in zip(relay.estimate(), node.estimate()):
        np.testing.assert_allclose(x, y, atol=1e-9)


def test_a_withdrawn_shared_frame_is_cleared_at_the_neighbour_by_a_partial_message():
    """Two fused frames confirm a segment (both shared; the second not yet confirmed itself), then
    the target is seen far outside the gate until the camera declares a loss: it withdraws the
    second frame, already at the relay. The next (partial) message clears that time at the relay
    (a zero entry), and the relay ends with exactly the camera's belief."""
    cam = _camera(0.3)
    node, relay = _node(neighbors=["relay"], var=0.09), _node("relay", ["cam"], var=0.09)
    fe = CameraFrontEnd(cam, detection=0.9, segment_gap=0.6)
    truth = np.array([0.0, 2.0, 1.0, 0.0])

    def step(t, Z):
        node.predict(t)
        relay.predict(t)
        fe.process_frame(node, t, np.atleast_2d(Z))
        relay.receive(node.message_to("relay"))

    step(0.2, cam.h(truth + [0.2, 0, 0, 0]))
    step(0.4, cam.h(truth + [0.4, 0, 0, 0]))
    key = int(round(0.4 * 1e9))
    assert relay.channels["cam"].information(key).info.any()      # shared
    k = 0
    while fe.status() == "ok":
        k += 1
        step(round(0.4 + 0.2 * k, 9), cam.h(truth + [0.4 + 0.2 * k + 1.6, 1.3, 0, 0]))
        assert k < 6
    assert fe.stats.withdrawn == 1 and node.stats.full_messages_sent == 1
    entry = relay.channels["cam"].information(key)
    assert entry is not None and not entry.info.any() and not entry.vec.any()   # a tombstone
    for x, y in zip(relay.estimate(), node.estimate()):
        np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12)


def test_loss_evidence_is_a_likelihood_ratio_of_non_empty_frames():
    V, lam = 640 * 480, 0.3 / (640 * 480)
    # the estimate is out of view (P_D on track = 0): a frame without a validated detection is as
    # likely lost as on track, given that it is not empty
    assert loss_log_likelihood_ratio(0.0, 0.9, 0.99, lam, V, 0.0) == pytest.approx(0.0, abs=1e-12)
    # in view, gate a quarter of the image: by hand
    Vg = V / 4
    c = 1 - math.exp(-lam * (V - Vg))
    pn = lambda pd: 1 - (1 - pd) * math.exp(-lam * V)
    q0 = math.exp(-lam * Vg) * (0.9 * 0.01 + 0.1 * c) / pn(0.9)
    q1 = math.exp(-lam * Vg) * (0.9 + 0.1 * c) / pn(0.9)
    assert miss_probability(0.9, 0.99, lam, V, Vg) == pytest.approx(q0)
    assert loss_log_likelihood_ratio(0.9, 0.9, 0.99, lam, V, Vg) == pytest.approx(math.log(q1 / q0))
    # without clutter a frame with no validated detection means the target left the gate: 1 - P_G
    assert miss_probability(0.9, 0.99, 0.0, V, Vg) == pytest.approx(0.01)


def test_clutter_model_of_a_camera_node_follows_protection_and_its_own_key():
    from dfusion.scenario import load_scenario
    from dfusion.scenario.build import build_front_end

    from tests.frontends.test_camera import camera_scenario

    def model(protection=None, **cam):
        return build_front_end(load_scenario(camera_scenario(**cam), protection=protection), "cam").clutter_model

    assert model() == "pda"
    assert model(clutter_model="gate") == "gate"
    assert model(protection=False, clutter_model="pda") == "gate"      # off: the hard gate, whatever the key
    sc = camera_scenario()
    sc["protection"] = {"clutter_model": "gate"}
    assert build_front_end(load_scenario(sc), "cam").clutter_model == "gate"
