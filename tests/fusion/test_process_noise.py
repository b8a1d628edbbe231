"""A fusion node's recovery (FusionNode.add_process_noise) in a network, with the v2 protocol
(partial and full messages, own information held back, the consistency guard on
measurements drawn from the model):
every measurement must be counted exactly once at every node. References: filterpy's
KalmanFilter given all measurements, with the extra noise in its Q at the recovering node
only; the information a node receives against H^T R^-1 H in closed form."""
from __future__ import annotations

import numpy as np
import pytest

from dfusion import FusionNode
from dfusion.fusion.guard import GuardConfig
from dfusion.models import ConstantVelocity, PositionSensor
from tests.estimation.test_process_noise import kalman
from tests.helpers.fusion_harness import Q_PSD, cv_F, cv_Q

SENSOR = PositionSensor(2, 0.5)
#: H^T R^-1 H of one position fix with std 0.5 (closed form)
FIX_INFO = np.diag([4.0, 4.0, 0.0, 0.0])


def exchange(nodes: dict) -> None:
    """Crossing messages a -> b and b -> a."""
    ma, mb = nodes["a"].message_to("b"), nodes["b"].message_to("a")
    nodes["b"].receive(ma)
    nodes["a"].receive(mb)


@pytest.mark.parametrize("messages", ["partial", "full"])
@pytest.mark.parametrize("guarded", [False, True])
def test_a_node_recovering_double_counts_nothing(messages, guarded):
    """Node a adds process noise to its own motion step (at a state its measurements and
    b's are on, and again after a late measurement split that step); after the exchanges node
    b equals the centralized Kalman filter with the nominal model given all measurements
    and node a the one with the extra noise: every measurement counted exactly once at
    both, with partial (per-time replacement) or full messages, with or without the guard.
    Node a also holds one fix back (share=False) and shares it later."""
    rng = np.random.default_rng(6)
    P0 = np.eye(4) * 4.0
    nodes = {n: FusionNode(n, [m], ConstantVelocity(2, Q_PSD), window=100, prior=(0.0, np.zeros(4), P0),
                           messages=messages, guard=GuardConfig() if guarded else None, epoch=k + 1)
             for k, (n, m) in enumerate((("a", "b"), ("b", "a")))}
    meas = []
    extra = np.diag([2.0, 2.0, 0.1, 0.1])
    held = None
    x0 = rng.standard_normal(4) * 2.0   # a truth drawn from the prior (constant velocity)

    def fix(t: float) -> np.ndarray:
        return x0[:2] + t * x0[2:] + 0.5 * rng.standard_normal(2)

    for k in range(1, 9):
        t = float(k)
        for n in nodes.values():
            n.predict(t)
        for name in ("a", "b"):
            z = fix(t)
            share = not (name == "a" and k == 3)
            L, y = nodes[name].update(t, z, SENSOR, share=share)
            if not share:
                held = (t, L, y)
            meas.append((t, z))
        if k == 4:
            nodes["a"].add_process_noise(t, extra)
        if k == 6:   # a late fix at 3.5 splits a's step 3 -> 4 that carries the extra noise
            z = fix(3.5)
            nodes["a"].update(3.5, z, SENSOR)
            meas.append((3.5, z))
            nodes["a"].share_local_information(*held)
        if k % 2 == 0:
            exchange(nodes)
    exchange(nodes)
    exchange(nodes)   # acknowledgements settle
    for name, add in (("b", None), ("a", 4.0)):
        kf = kalman(P0)
        t_prev = 0.0
        for t in sorted({t for t, _ in meas}):
            kf.F, kf.Q = cv_F(t - t_prev), cv_Q(t - t_prev) + (extra if t == add else 0.0)
            kf.predict()
            for tt, z in meas:
                if tt == t:
                    kf.update(z.reshape(2, 1))
            t_prev = t
        m, P = nodes[name].estimate()
        np.testing.assert_allclose(m, kf.x.ravel(), atol=1e-8)
        np.testing.assert_allclose(P, kf.P, atol=1e-8)
    # what b holds from a: one fix per time 1..8 and the late one at 3.5, in closed form
    got = nodes["b"].received_information(0.0, 8.0)
    assert [t for t, _, _ in got] == [1.0, 2.0, 3.0, 3.5, 4.0, 5.0, 6.0, 7.0, 8.0]
    for _, L, _ in got:
        np.testing.assert_allclose(L, FIX_INFO, atol=1e-9)
    assert nodes["b"].reported_until() == 8.0 and nodes["a"].reported_until() == 8.0
    assert not any(n.is_quarantined(m) for n, m in ((nodes["a"], "b"), (nodes["b"], "a")))


def test_received_information_leaves_out_held_back_own_information():
    """Own information held back (share=False) is neither own shared information nor
    received: received_information is what came from the neighbours only."""
    P0 = np.eye(4) * 4.0
    a = FusionNode("a", ["b"], ConstantVelocity(2, Q_PSD), prior=(0.0, np.zeros(4), P0), epoch=1)
    b = FusionNode("b", ["a"], ConstantVelocity(2, Q_PSD), prior=(0.0, np.zeros(4), P0), epoch=2)
    for n in (a, b):
        n.predict(1.0)
    assert a.reported_until() == -np.inf
    a.update(1.0, [0.3, 0.1], SENSOR, share=False)
    a.update(1.0, [0.2, 0.0], SENSOR)
    b.update(1.0, [0.1, 0.4], SENSOR)
    a.receive(b.message_to("a"))
    (t, L, _), = a.received_information(0.0, 1.0)
    assert t == 1.0
    np.testing.assert_allclose(L, FIX_INFO, atol=1e-9)
    assert a.reported_until() == 1.0
    alone = FusionNode("x", [], ConstantVelocity(2, 1.0), prior=(0.0, np.zeros(4), P0))
    assert alone.reported_until() == np.inf and alone.received_information(0.0, 1.0) == []
