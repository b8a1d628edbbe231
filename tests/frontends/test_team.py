"""TeamSightingsFrontEnd: a team of known size tracked from anonymous detections; a track
locked out (its prior far from its target, with a small covariance: every detection of its
target outside every gate) is re-acquired after k agreeing unexplained detections, and ends
on its target; one stray detection re-acquires nothing; a track the scan cannot have seen
(exclude) takes no part."""
from __future__ import annotations

import numpy as np
import pytest

from dfusion.errors import ValidationError
from dfusion.estimation.innovation import MonitorSettings
from dfusion.frontends import TeamSightingsFrontEnd
from dfusion.fusion import TrackingNode
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.tracking import GNN, GaussianHypothesiser, NoInitiator, Scan, TrackId

A, B = TrackId("team", 0), TrackId("team", 1)
TRUTH = {A: np.array([0.0, 0.0]), B: np.array([6.0, 0.0])}


def _node(name: str = "n") -> TrackingNode:
    node = TrackingNode(name, [], ConstantVelocity(2, 1e-4), associator=GNN(), initiator=NoInitiator(),
                        hypothesiser=GaussianHypothesiser(0.999), deleter=False, merger=False, window=None,
                        horizon=30.0, epoch=1)
    node.add_track(A, 0.0, np.zeros(4), np.diag([0.05, 0.05, 1e-4, 1e-4]))
    node.add_track(B, 0.0, np.array([0.0, 5.0, 0.0, 0.0]), np.diag([0.1, 0.1, 1e-4, 1e-4]))   # 7.8 m off
    return node


def _scans(rng, n: int, stray_at: int | None = None):
    for k in range(1, n + 1):
        z = [TRUTH[A] + rng.normal(0, 0.1, 2), TRUTH[B] + rng.normal(0, 0.1, 2)]
        if k == stray_at:
            z.append(np.array([-8.0, 9.0]))
        yield Scan(0.5 * k, np.array(z), PositionSensor(2, 0.1), 1e-4, 0.9)


def test_a_locked_out_track_is_reacquired_and_ends_on_its_target():
    rng = np.random.default_rng(3)
    plain, robust = _node(), _node()
    front = TeamSightingsFrontEnd(robust, MonitorSettings(), velocity_std=0.1, window=20.0)
    assert front.run_length == 5
    for scan in _scans(rng, 12, stray_at=2):
        plain.predict(scan.time)
        plain.process(scan)
        front.process(scan)
    assert np.linalg.norm(plain.tracks[B].estimate()[0][:2] - TRUTH[B]) > 5.0       # locked out for good
    assert front.stats.reacquisitions == 1 and front.stats.events[0][1] == B
    assert front.stats.lockouts == 1 and front.stats.unexplained >= 5 + 1          # 5 of B's, the stray
    for tid in (A, B):
        mean, P = robust.tracks[tid].estimate()
        assert np.linalg.norm(mean[:2] - TRUTH[tid]) < 3 * np.sqrt(np.trace(P[:2, :2])) + 0.05, tid


def test_one_stray_detection_reacquires_nothing_and_bad_settings_are_refused():
    rng = np.random.default_rng(4)
    node = _node()
    node.tracks[B].update(0.0, TRUTH[B], PositionSensor(2, 0.01))   # B on its target now
    front = TeamSightingsFrontEnd(node)
    for scan in _scans(rng, 8, stray_at=3):
        front.process(scan)
    assert front.stats.unexplained == 1 and front.stats.lockouts == 0 and front.stats.reacquisitions == 0
    with pytest.raises(ValidationError, match="velocity_std"):
        TeamSightingsFrontEnd(node, velocity_std=0.0)


def test_an_excluded_track_takes_no_detection():
    node = _node()
    node.predict(0.5)
    node.process(Scan(0.5, np.array([[0.05, 0.0]]), PositionSensor(2, 0.1), 1e-4, 0.9), exclude=[A])
    assert node.tracks[A].newest_information_time() is None
    node.predict(1.0)
    node.process(Scan(1.0, np.array([[0.05, 0.0]]), PositionSensor(2, 0.1), 1e-4, 0.9))
    assert node.tracks[A].newest_information_time() == pytest.approx(1.0)


@pytest.mark.parametrize("candidates", ["likeliest", "stale"])
def test_detections_off_a_track_that_is_backed_reacquire_nothing(candidates):
    """This node's detections of B are 3 m off (its own pose error, say) while another sensor keeps
    B's track on its target: the lock-out is declared, but B is backed ('likeliest': its likeliest
    track is B, backed; 'stale': no track is without information), so nothing moves."""
    rng = np.random.default_rng(5)
    node = _node()
    front = TeamSightingsFrontEnd(node, candidates=candidates)
    for k in range(1, 11):
        t = 0.5 * k
        node.predict(t)
        node.observe(B, t, TRUTH[B] + rng.normal(0, 0.05, 2), PositionSensor(2, 0.05))   # the other sensor
        z = np.array([TRUTH[A] + rng.normal(0, 0.1, 2), TRUTH[B] + [0.0, 3.0] + rng.normal(0, 0.1, 2)])
        front.process(Scan(t, z, PositionSensor(2, 0.1), 1e-4, 0.9))
    assert front.stats.lockouts >= 1 and front.stats.reacquisitions == 0
    assert (front.stats.backed if candidates == "likeliest" else front.stats.no_candidate) == front.stats.lockouts
    assert np.linalg.norm(node.tracks[B].estimate()[0][:2] - TRUTH[B]) < 0.3
    with pytest.raises(ValidationError, match="candidates"):
        TeamSightingsFrontEnd(node, candidates="any")
