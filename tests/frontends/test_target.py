"""TargetTrackingFrontEnd (dfusion.frontends.target): a node locked out by a confident wrong
prior recovers from its observer's fixes, stays locked out without recovery, and waits while
a neighbour backs its belief or has not reported; checked against the simulated truth."""
from __future__ import annotations

import numpy as np

from dfusion import FusionNode
from dfusion.estimation.innovation import InnovationMonitor, MonitorSettings
from dfusion.frontends import TargetTrackingFrontEnd
from dfusion.models import ConstantVelocity, PositionFix


def test_target_front_end_recovers_a_locked_out_node_unless_neighbours_back_it():
    rng = np.random.default_rng(7)

    def scenario(neighbour_fixes: bool, recover: bool = True, silent: bool = False):
        prior = (0.0, np.zeros(4), np.diag([0.01, 0.01, 1e-6, 1e-6]))   # confident, and wrong
        node = FusionNode("n", ["m"], ConstantVelocity(2, 1e-8), window=400, horizon=60.0, prior=prior)
        nb = FusionNode("m", ["n"], ConstantVelocity(2, 1e-8), window=400, horizon=60.0, prior=prior)
        fe = TargetTrackingFrontEnd(InnovationMonitor("n/target", 2, MonitorSettings(drift_test=False, recover=recover)))
        truth = np.array([2.0, 1.0])   # the target is not where the prior says
        for k in range(1, 60):
            t = 0.5 * k
            node.predict(t)
            nb.predict(t)
            if neighbour_fixes:   # the neighbour's observer sees the target where the prior says
                nb.update(t, np.zeros(2), PositionFix(np.zeros(2), 0.01 * np.eye(2)))
            if not silent:
                node.receive(nb.message_to("n", sent_at=t))
            z = truth + 0.1 * rng.standard_normal(2)
            fe.process(node, t, PositionFix(z, 0.01 * np.eye(2)))
        return np.linalg.norm(node.estimate()[0][:2] - truth), fe.monitor.stats

    err, st = scenario(False)
    assert st.recoveries >= 1 and err < 0.2
    err_off, st_off = scenario(False, recover=False)
    assert st_off.recoveries == 0 and st_off.lockouts >= 1 and err_off > 2.0
    # a neighbour backs the wrong belief with its own fixes: the node's fixes could be the
    # ones that are wrong (its observer's pose), no recovery
    _, st_backed = scenario(True)
    assert st_backed.recoveries == 0 and st_backed.rejected > 5
    # a neighbour that has not reported on the span yet: the decision waits
    _, st_silent = scenario(False, silent=True)
    assert st_silent.recoveries == 0 and st_silent.rejected > 5


def test_a_locked_out_node_with_a_guard_recovers_and_takes_its_neighbour_back():
    """Both nodes start from the same confident, wrong prior; the neighbour's fixes pull it
    to the target, so the locked-out node's guard quarantines the neighbour (its information
    contradicts the wrong belief). What a quarantine withdrew is no support: the node
    recovers from its own fixes at once, and takes the neighbour back once the states from
    before the recovery (where its belief is still the wrong prior) have left its 60 s
    window and ten probation tests passed."""
    from dfusion.fusion.guard import GuardConfig

    rng = np.random.default_rng(7)
    wrong = (0.0, np.zeros(4), np.diag([0.01, 0.01, 1e-6, 1e-6]))
    truth = np.array([2.0, 1.0])
    node = FusionNode("n", ["m"], ConstantVelocity(2, 1e-8), window=400, horizon=60.0, prior=wrong,
                      guard=GuardConfig(), epoch=1)
    nb = FusionNode("m", ["n"], ConstantVelocity(2, 1e-8), window=400, horizon=60.0, prior=wrong, epoch=2)
    fe = TargetTrackingFrontEnd(InnovationMonitor("n/target", 2, MonitorSettings(drift_test=False)))
    quarantined, error = {}, {}
    for k in range(1, 200):
        t = 0.5 * k
        node.predict(t)
        nb.predict(t)
        fix = PositionFix(truth + 0.1 * rng.standard_normal(2), 0.01 * np.eye(2))
        nb.update(t, fix.z, fix)
        node.receive(nb.message_to("n", sent_at=t))
        nb.receive(node.message_to("m", sent_at=t))
        fe.process(node, t, PositionFix(truth + 0.1 * rng.standard_normal(2), 0.01 * np.eye(2)))
        quarantined[t] = node.is_quarantined("m")
        error[t] = float(np.linalg.norm(node.estimate()[0][:2] - truth))
    assert fe.monitor.stats.recoveries == 1 and quarantined[5.0]
    assert max(e for t, e in error.items() if 10.0 <= t) < 0.1       # recovered, and stays on the target
    released = min(t for t, q in quarantined.items() if t > 5.0 and not q)
    assert 60.0 < released < 80.0 and not any(q for t, q in quarantined.items() if t >= released)
    assert fe.health()["recoveries"] == 1 and fe.status() == "ok"
