"""The policy seam: a node's output passes through its policy object."""
from __future__ import annotations

import numpy as np

from dfusion.fusion import FusionNode
from dfusion.policies import InformationFusionPolicy, Policy
from dfusion.estimation import Estimate
from dfusion.models import ConstantVelocity, PositionSensor


class MostReliable(Policy):
    """A minimal switching policy written against the public interface."""

    name = "most-reliable"

    def decide(self, fused, sources):
        healthy = [s for s in sources if s.healthy]
        return max(healthy, key=lambda s: s.reliability) if healthy else fused


def make(policy=None):
    node = FusionNode("a", [], ConstantVelocity(2, 0.1), window=10, prior=(0.0, np.zeros(4), np.eye(4)), policy=policy)
    node.predict(1.0)
    node.update(1.0, [1.0, 2.0], PositionSensor(2, 0.5))
    return node


def test_default_policy_outputs_the_fused_estimate():
    node = make()
    assert isinstance(node.policy, InformationFusionPolicy)
    out = node.output()
    mean, cov = node.estimate()
    assert out.name == "fused" and out.t == 1.0
    np.testing.assert_array_equal(out.mean, mean)
    np.testing.assert_array_equal(out.cov, cov)


def test_a_custom_policy_decides_the_output():
    node = make(MostReliable())
    lidar = Estimate("lidar", 1.0, np.ones(4), np.eye(4), reliability=0.9)
    camera = Estimate("camera", 1.0, np.zeros(4), np.eye(4), reliability=0.95, healthy=False)
    node.report_source(lidar)
    node.report_source(camera)
    assert node.output().name == "lidar"          # the camera is in error
    node.report_source(Estimate("camera", 1.1, np.zeros(4), np.eye(4), reliability=0.95))
    assert node.output().name == "camera"         # latest report replaces the previous one
    # the fused estimate is untouched by the policy
    assert node.estimate()[0][0] > 0.5


def test_local_information_counts_as_own_and_is_shared_once():
    """A local estimator's information is fused like a measurement (filterpy-free check:
    the same information entered as a PositionSensor measurement gives the same node)."""
    motion = ConstantVelocity(2, 0.1)
    prior = (0.0, np.zeros(4), np.eye(4))
    sensor = PositionSensor(2, 0.5)
    a = FusionNode("a", ["b"], motion, window=10, prior=prior)
    ref = FusionNode("a", ["b"], motion, window=10, prior=prior)
    for n in (a, ref):
        n.predict(1.0)
    z = np.array([1.0, -2.0])
    H = np.hstack([np.eye(2), np.zeros((2, 2))])
    Lam = H.T @ H / 0.25
    a.add_local_information(1.0, Lam, H.T @ z / 0.25)
    ref.update(1.0, z, sensor)
    np.testing.assert_allclose(a.estimate()[0], ref.estimate()[0], atol=1e-12)
    np.testing.assert_allclose(a.estimate()[1], ref.estimate()[1], atol=1e-12)
    b = FusionNode("b", ["a"], motion, window=10, prior=prior)
    b.predict(1.0)
    b.receive(a.message_to("b"))
    b.receive(a.message_to("b"))     # sent twice: counted once
    np.testing.assert_allclose(b.estimate()[1], ref.estimate()[1], atol=1e-12)
    import pytest
    from dfusion.errors import NotPositiveDefiniteError, OutsideWindowError
    before = a.estimate()
    with pytest.raises(NotPositiveDefiniteError):
        a.add_local_information(1.0, -Lam, np.zeros(4))
    with pytest.raises(OutsideWindowError):
        a.add_local_information(5.0, Lam, np.zeros(4))
    np.testing.assert_array_equal(a.estimate()[1], before[1])
