"""The consistency test of a neighbour's information and the quarantine (dfusion.fusion.guard),
in the transactional receive of the v2 protocol: the statistic against the joint innovation test
computed densely, its false-alarm rate on healthy networks by Monte Carlo, exactness with the test
on (partial messages, drops, duplicates), a lying neighbour quarantined (what came over the link
withdrawn, and forwarded as changed times) and released, own information held back, shared and
withdrawn through partial messages, and a failure during a message undoing the guard's records."""
from __future__ import annotations


import networkx as nx
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.stats import binom, chi2

from dfusion.errors import MessageError, ValidationError
from dfusion.estimation.delayed_state import DelayedStateEIF
from dfusion.fusion import FusionNode
from dfusion.fusion.guard import GuardConfig, NeighbourGuard, information_statistic, split_blocks
from dfusion.models import ConstantVelocity, PositionSensor
from dfusion.topology import settling_rounds
from tests.helpers.fusion_harness import P0, Q_PSD, CVTruth, Schedule, central_kalman, random_tree, run_network


# ----------------------------------------------------------------------------- the statistic
def _random_filter(rng, states=8):
    f = DelayedStateEIF(ConstantVelocity(2, q=0.2), window=100)
    f.initialize(0.0, rng.normal(size=4), np.diag([2.0, 2.0, 0.5, 0.5]))
    for k in range(1, states):
        f.predict(0.1 * k)
        if rng.random() < 0.7:
            f.update(0.1 * k, rng.normal(size=2) + [0.1 * k, 0.0], PositionSensor(2, 0.5))
    return f


def _dense_statistic(f: DelayedStateEIF, blocks) -> tuple[float, int]:
    """The stacked pseudo-measurements' innovation test with the joint covariance of the window
    (dense, numpy solves): the independent reference for information_statistic."""
    times = f.times
    Om, eta = f.dense_information()
    n = f.n
    N = Om.shape[0]
    Sigma = np.linalg.solve(Om, np.eye(N))
    mu = np.linalg.solve(Om, eta)
    rows, zs, rs = [], [], []
    for t, L, y in blocks:
        k = int(np.argmin(np.abs(times - t)))
        w, V = np.linalg.eigh(L)
        keep = w > 1e-9 * np.abs(w).max()
        for lam, v in zip(w[keep], V[:, keep].T):
            row = np.zeros(N)
            row[k * n:(k + 1) * n] = v
            rows.append(row)
            zs.append(v @ y / lam)
            rs.append(1.0 / lam)
    Hs = np.array(rows)
    S = Hs @ Sigma @ Hs.T + np.diag(rs)
    nu = np.array(zs) - Hs @ mu
    return float(nu @ np.linalg.solve(S, nu)), len(zs)


@pytest.mark.parametrize("seed", range(6))
def test_statistic_equals_the_joint_innovation_test_computed_densely(seed):
    rng = np.random.default_rng(seed)
    f = _random_filter(rng)
    # blocks at window states and one between two states (inserted), ranks 2 and 4
    blocks = []
    for t in (0.2, 0.45, 0.6):
        A = rng.normal(size=(4, 4)) if t == 0.45 else np.vstack([rng.normal(size=(2, 4)), np.zeros((2, 4))])
        L = A.T @ A
        x = rng.normal(size=4) * 2
        blocks.append((t, L, L @ x))
    mu0, P0_, mu1 = f.add_information_moments(blocks)
    stat, dof = information_statistic(blocks, mu0, P0_, mu1)
    # the reference on the same trajectory: the filter before the blocks, with the state at 0.45 inserted
    g = _random_filter(np.random.default_rng(seed))
    g.ensure_state(0.45)
    ref, ref_dof = _dense_statistic(g, blocks)
    assert dof == ref_dof == 2 + 4 + 2
    assert stat == pytest.approx(ref, rel=1e-7)


@pytest.mark.parametrize("seed", range(10, 22))
def test_statistic_equals_the_dense_test_on_random_blocks(seed):
    """Random messages: 1 to 6 blocks at random window states or between two, ranks 1 to 4, the
    pseudo-measurement drawn from the belief or far from it; against the dense joint test."""
    rng = np.random.default_rng(seed + 1000)
    states = int(rng.integers(3, 12))
    f = _random_filter(np.random.default_rng(seed), states=states)
    times = f.times
    blocks = []
    for s in rng.choice(len(times), size=min(int(rng.integers(1, 7)), len(times)), replace=False):
        t = float(times[s]) + (0.05 if rng.random() < 0.3 and s < len(times) - 1 else 0.0)
        A = rng.normal(size=(int(rng.integers(1, 5)), 4)) * rng.uniform(0.3, 3.0)
        L = A.T @ A
        x = rng.normal(size=4) * (1.0 if rng.random() < 0.5 else 10.0)
        blocks.append((round(t, 9), L, L @ x))
    g = _random_filter(np.random.default_rng(seed), states=states)
    for t, _, _ in blocks:
        g.ensure_state(t)
    ref, ref_dof = _dense_statistic(g, blocks)
    mu0, P0_, mu1 = f.add_information_moments(blocks)
    stat, dof = information_statistic(blocks, mu0, P0_, mu1)
    assert dof == ref_dof
    assert stat == pytest.approx(ref, rel=1e-7)


def test_stacked_block_computations_equal_one_block_at_a_time():
    """split_blocks and information_statistic work on all blocks at once; the same per block,
    one eigendecomposition each (negligible directions, zero blocks, y outside the range,
    removals), gives the same split, degrees of freedom and statistic."""
    rng = np.random.default_rng(5)
    for _ in range(200):
        b = int(rng.integers(1, 7))
        entries, mu0, P0_, mu1 = [], [], [], []
        for _ in range(b):
            kind = rng.integers(6)
            A = rng.normal(size=(int(rng.integers(1, 5)), 4))
            L = A.T @ A * (1e-12 if kind == 0 else 1.0)           # negligible for the receiver
            if kind == 1:
                L = -L                                               # a removal
            if kind == 2:
                L = np.zeros((4, 4))
            y = L @ rng.normal(size=4) + (rng.normal(size=4) * 1e-2 if kind == 3 else 0.0)   # 3: out of range
            entries.append((0.0, L, y))
            B = rng.normal(size=(4, 4))
            P0_.append(B @ B.T + 0.1 * np.eye(4))
            mu0.append(rng.normal(size=4))
            mu1.append(mu0[-1] + 0.1 * rng.normal(size=4))
        add, other = split_blocks(entries)
        ref_add = []
        for e in entries:
            w = np.linalg.eigvalsh(e[1])
            if (np.abs(w).max() > 0 and w[0] >= -1e-9 * np.abs(w).max()) or (not np.abs(w).max() and np.any(e[2])):
                ref_add.append(e)
        assert [id(e) for e in add] == [id(e) for e in ref_add]
        assert len(add) + len(other) == len(entries) - sum(1 for e in entries if not e[1].any() and not e[2].any())
        # the statistic per block, as the module docstring defines it
        ref, ref_dof = 0.0, 0
        for (t, L, y), m0, C0, m1 in zip(entries, mu0, P0_, mu1):
            w, V = np.linalg.eigh(L)
            pos = w > 1e-9 * np.abs(w).max() if np.abs(w).max() > 0 else np.zeros(4, bool)
            out = y - V[:, pos] @ (V[:, pos].T @ y)
            if out @ C0 @ out > 1e-6:
                ref, ref_dof = np.inf, ref_dof + int(pos.sum())
                break
            for lam, v in zip(w[pos], V[:, pos].T):
                if lam * v @ C0 @ v > 1e-9:
                    ref += (v @ y / lam - v @ m0) * lam * (v @ y / lam - v @ m1)
                    ref_dof += 1
        stat, dof = information_statistic(entries, mu0, P0_, mu1)
        assert dof == ref_dof
        assert stat == pytest.approx(ref, rel=1e-9, abs=1e-12)


def test_information_outside_the_range_of_its_matrix_fails_and_removals_are_not_tested():
    f = _random_filter(np.random.default_rng(1))
    L = np.diag([4.0, 4.0, 0.0, 0.0])
    bad = (0.3, L, np.array([1.0, 1.0, 5.0, 0.0]))          # a mean shift on the velocity without information
    mu0, P0_, mu1 = f.add_information_moments([bad])
    assert information_statistic([bad], mu0, P0_, mu1)[0] == np.inf
    add, other = split_blocks([(0.3, -L, np.zeros(4)), (0.4, L, np.zeros(4))])
    assert [e[0] for e in add] == [0.4] and [e[0] for e in other] == [0.3]


# ----------------------------------------------------------------------------- false alarms
class RecordingGuard(NeighbourGuard):
    """Records every tested message's statistic; never quarantines."""

    def __init__(self, neighbors, log):
        super().__init__(neighbors, GuardConfig(failures=1000, window=1000))
        self.log = log

    def judge(self, j, stat, dof):
        if dof > 0:
            self.log.append((stat, dof))
        return super().judge(j, stat, dof)


@pytest.fixture(scope="module")
def healthy_statistics() -> np.ndarray:
    """(statistic, dof) of every message tested in healthy networks: random trees of 6 nodes,
    data drawn from the filters' model, 20 % drops, duplicates, late and off-grid measurements,
    partial messages; windows of 50 states (the test's cost grows with the window; information
    that leaves a window before it is shared is lost, which leaves the statistic chi-square)."""
    log: list[tuple[float, int]] = []
    for seed in range(25):
        s = Schedule(seed=seed, steps=40, truth=True, drop=0.2, duplicate=0.1, window=50,
                     guard=lambda nbrs: RecordingGuard(nbrs, log))
        run_network(random_tree(6, seed), s, final_rounds=False)
    return np.array(log)


@pytest.mark.parametrize("alpha", [0.05, 0.01, 1e-3])
def test_false_alarm_rate_on_healthy_networks_is_the_chosen_one(healthy_statistics, alpha):
    """Monte Carlo: the share of healthy messages failing chi2^-1_dof(1 - alpha) is alpha, within its
    binomial 99.9 % range (1e-3 is the default, about 6 expected failures here)."""
    stat, dof = healthy_statistics[:, 0], healthy_statistics[:, 1]
    n = len(stat)
    assert n > 3000
    failures = int(np.count_nonzero(stat > chi2.isf(alpha, dof)))
    lo, hi = binom.ppf([0.0005, 0.9995], n, alpha)
    assert lo <= failures <= hi, (failures, n, alpha)


def test_healthy_statistics_average_one_per_degree_of_freedom(healthy_statistics):
    stat, dof = healthy_statistics[:, 0], healthy_statistics[:, 1]
    for alpha in (0.05, 0.01, 1e-3):   # the figures of docs/clutter.md
        print(f"alpha {alpha}: {int(np.count_nonzero(stat > chi2.isf(alpha, dof)))} of {len(stat)} messages fail, "
              f"expected {alpha * len(stat):.0f}; mean statistic per dof {stat.sum() / dof.sum():.3f}")
    # E[chi2_k] = k; the sum over n messages has standard deviation sqrt(2 sum k)
    assert abs(stat.sum() - dof.sum()) < 4 * np.sqrt(2 * dof.sum())


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(2, 12), seed=st.integers(0, 2**31 - 1), drop=st.floats(0.0, 0.4))
def test_property_healthy_networks_with_the_guard_equal_the_central_kalman(n, seed, drop):
    """With the default guard on every node, a healthy network quarantines nobody and every node
    still equals the centralized Kalman filter (filterpy) once the last messages are delivered."""
    graph = random_tree(n, seed)
    s = Schedule(seed=seed, steps=16, drop=drop, truth=True, guard=GuardConfig())
    nodes, meas, t_end = run_network(graph, s)
    mean, cov = central_kalman(meas, t_end)
    for node in nodes.values():
        assert not node.guard.quarantined
        m, P = node.estimate()
        assert np.max(np.abs(m - mean)) < 1e-8 * max(1.0, np.max(np.abs(mean)))
        assert np.max(np.abs(P - cov)) < 1e-8 * np.max(np.abs(cov))


# ----------------------------------------------------------------------------- a lying neighbour
def _chain(lie_until: float | None, steps: int = 60, restart_at: float | None = None, config=None,
           lie_from: float = 2.0):
    """a - b - c on the filters' model; c adds a false 'own measurement' 6 m off with 0.2 m noise
    every step while lie_from <= t <= lie_until (honest before). Lossless, every message delivered
    at once, sent every step."""
    rng = np.random.default_rng(5)
    motion = ConstantVelocity(2, Q_PSD)
    prior = (0.0, np.zeros(4), np.eye(4) * P0)
    config = config or GuardConfig()
    graph = nx.path_graph(["a", "b", "c"])
    make = lambda name, epoch=1: FusionNode(name, sorted(graph.neighbors(name)), motion, window=400,
                                            prior=prior, guard=config, epoch=epoch)
    nodes = {nm: make(nm) for nm in "abc"}
    sensors = {"a": PositionSensor(2, 0.8), "b": PositionSensor(2, 1.0), "c": PositionSensor(2, 0.6)}
    truth = CVTruth(rng)
    honest = []   # (t, z, std, node) of the honest measurements
    liar = PositionSensor(2, 0.2)
    history = {"b": [], "c": []}
    for k in range(1, steps + 1):
        t = round(0.1 * k, 9)
        if restart_at is not None and abs(t - restart_at) < 1e-9:
            nodes["c"] = make("c", epoch=99)   # a new incarnation: its neighbours replace the old one's blocks
        for nm in "abc":
            nodes[nm].predict(t)
        x = truth.at(t)
        for nm in "abc":
            z = x[:2] + sensors[nm].std * rng.standard_normal(2)
            if (nm == "c" and lie_until is not None and lie_from <= t <= lie_until
                    and (restart_at is None or t < restart_at)):
                nodes["c"].update(t, x[:2] + [6.0, 0.0] + 0.2 * rng.standard_normal(2), liar)
                continue
            nodes[nm].update(t, z, sensors[nm])
            honest.append((t, z, sensors[nm].std, nm))
        msgs = [(nb, nodes[nm].message_to(nb)) for nm in "abc" for nb in nodes[nm].neighbors]
        for nb, data in msgs:
            nodes[nb].receive(data)
        history["b"].append(nodes["b"].health())
        history["c"].append(nodes["c"].health())
    for _ in range(settling_rounds(graph)):   # the last measurements reach every node
        msgs = [(nb, nodes[nm].message_to(nb)) for nm in "abc" for nb in nodes[nm].neighbors]
        for nb, data in msgs:
            nodes[nb].receive(data)
    return nodes, honest, t, history


def test_a_lying_neighbour_is_quarantined_and_what_it_sent_is_withdrawn():
    nodes, honest, t_end, history = _chain(lie_until=10.0, steps=60)
    b, c = nodes["b"], nodes["c"]
    assert b.guard.quarantined == {"c"}
    assert b.guard.links["c"].quarantines == 1
    # the lie (from t = 2 s, step index 19) was caught within a few messages (k failures of the last m)
    assert "degraded" not in history["b"][:19]
    assert history["b"].index("degraded") - 19 <= GuardConfig().window
    # c, holding its own lie, finds b's information inconsistent too: it quarantines b, is cut off
    assert c.guard.quarantined == {"b"} and c.health() == "lost"
    assert b.health() == "degraded"
    # withdrawn for good (c's honest early measurements too): a and b equal the central Kalman
    # filter of a's and b's measurements alone. a learnt of the withdrawal from b's partial
    # messages (every message after the first to each neighbour is partial): the withdrawn
    # times were marked changed on the link to a
    assert b.stats.full_messages_sent == 2
    mean, cov = central_kalman([m[:3] for m in honest if m[3] != "c"], t_end)
    for name in ("a", "b"):
        m, P = nodes[name].estimate()
        assert np.max(np.abs(m - mean)) < 1e-8 * max(1.0, np.max(np.abs(mean))), name
        assert np.max(np.abs(P - cov)) < 1e-8 * np.max(np.abs(cov)), name
    assert nodes["a"].guard.quarantined == set()


def test_without_the_guard_the_lie_reaches_every_node():
    rng = np.random.default_rng(5)
    # the same chain without guards: the lie is fused everywhere (a is metres off)
    motion = ConstantVelocity(2, Q_PSD)
    prior = (0.0, np.zeros(4), np.eye(4) * P0)
    g = nx.path_graph(["a", "b", "c"])
    nodes = {nm: FusionNode(nm, sorted(g.neighbors(nm)), motion, window=400, prior=prior) for nm in "abc"}
    truth = CVTruth(rng)
    for k in range(1, 61):
        t = round(0.1 * k, 9)
        x = truth.at(t)
        for nm in "abc":
            nodes[nm].predict(t)
        nodes["a"].update(t, x[:2] + 0.8 * rng.standard_normal(2), PositionSensor(2, 0.8))
        nodes["c"].update(t, x[:2] + [6.0, 0.0] + 0.2 * rng.standard_normal(2), PositionSensor(2, 0.2))
        msgs = [(nb, nodes[nm].message_to(nb)) for nm in "abc" for nb in nodes[nm].neighbors]
        for nb, data in msgs:
            nodes[nb].receive(data)
    assert abs(nodes["a"].estimate()[0][0] - truth.x[0]) > 3.0


def test_a_quarantined_neighbour_leaves_quarantine_after_consistent_messages():
    """c lies, is quarantined by b, then restarts honest (a new incarnation): its probation
    messages pass, b takes it back after `release` of them, and a and b end equal to the central
    Kalman filter of every honest measurement."""
    cfg = GuardConfig(release=5)
    nodes, honest, t_end, history = _chain(lie_until=10.0, steps=60, restart_at=3.0, config=cfg)
    b = nodes["b"]
    assert b.guard.links["c"].quarantines == 1 and b.guard.links["c"].releases == 1
    assert not b.guard.quarantined
    assert "degraded" in history["b"] and history["b"][-1] == "ok"
    # the old incarnation's blocks were replaced: c's measurements count from its restart on
    mean, cov = central_kalman([m[:3] for m in honest if m[3] != "c" or m[0] >= 3.0], t_end)
    for name in ("a", "b", "c"):
        m, P = nodes[name].estimate()
        assert np.max(np.abs(m - mean)) < 1e-8 * max(1.0, np.max(np.abs(mean))), name
        assert np.max(np.abs(P - cov)) < 1e-8 * np.max(np.abs(cov)), name




# ----------------------------------------------------------------------------- own information held back
def _rounds(nodes: dict, graph: nx.Graph, k: int) -> None:
    for _ in range(k):
        msgs = [(nb, nodes[nm].message_to(nb)) for nm in sorted(nodes) for nb in nodes[nm].neighbors]
        for nb, data in msgs:
            nodes[nb].receive(data)


def _close(node: FusionNode, mean, cov, what="") -> None:
    m, P = node.estimate()
    assert np.max(np.abs(m - mean)) < 1e-8 * max(1.0, np.max(np.abs(mean))), (node.name, what)
    assert np.max(np.abs(P - cov)) < 1e-8 * np.max(np.abs(cov)), (node.name, what)


@pytest.mark.parametrize("guard", [None, GuardConfig()])
def test_held_own_information_is_shared_on_request_and_a_withdrawal_reaches_every_node(guard):
    """a - b - c, every message partial after the first. a fuses one measurement held back
    (share=False): b and c never get it until a shares it; then a withdraws another, shared,
    measurement: the next partial messages carry the smaller blocks and every node ends equal
    to the central Kalman filter without it."""
    rng = np.random.default_rng(2)
    motion = ConstantVelocity(2, Q_PSD)
    prior = (0.0, np.zeros(4), np.eye(4) * P0)
    graph = nx.path_graph(["a", "b", "c"])
    nodes = {nm: FusionNode(nm, sorted(graph.neighbors(nm)), motion, window=400, prior=prior, epoch=1, guard=guard)
             for nm in "abc"}
    truth = CVTruth(rng)
    sensor = PositionSensor(2, 0.5)
    meas = {}   # (node, t) -> z
    held = withdrawn = None
    for k in range(1, 21):
        t = round(0.1 * k, 9)
        for node in nodes.values():
            node.predict(t)
        x = truth.at(t)
        for nm in "abc":
            z = x[:2] + 0.5 * rng.standard_normal(2)
            meas[(nm, t)] = z
            if nm == "a" and k == 8:
                held = (t, *nodes["a"].update(t, z, sensor, share=False))
            elif nm == "a" and k == 12:
                withdrawn = (t, *nodes["a"].update(t, z, sensor))
            else:
                nodes[nm].update(t, z, sensor)
        _rounds(nodes, graph, 1)
    _rounds(nodes, graph, settling_rounds(graph))

    def central(skip):
        return central_kalman([(t, z, 0.5) for (nm, t), z in meas.items() if (nm, t) not in skip], 2.0)

    everything = central(set())
    _close(nodes["a"], *everything, "a holds its held measurement")
    for nm in "bc":
        _close(nodes[nm], *central({("a", held[0])}), "not shared yet")
    assert nodes["a"].share_local_information(*held)
    _rounds(nodes, graph, settling_rounds(graph))
    for node in nodes.values():
        _close(node, *everything, "shared")
    assert nodes["a"].withdraw_local_information(*withdrawn)
    _rounds(nodes, graph, settling_rounds(graph))
    for node in nodes.values():
        _close(node, *central({("a", withdrawn[0])}), "withdrawn")
        assert node.stats.full_messages_sent == len(node.neighbors)
    # a held frame withdrawn before anyone saw it; times outside the window are refused
    t_new = 2.1
    for node in nodes.values():
        node.predict(t_new)
    Lam, y = nodes["a"].update(t_new, meas[("a", 2.0)], sensor, share=False)
    assert nodes["a"].withdraw_local_information(t_new, Lam, y, shared=False)
    assert not nodes["a"].withdraw_local_information(5.0, Lam, y)
    _rounds(nodes, graph, settling_rounds(graph))
    after = central_kalman([(t, z, 0.5) for (nm, t), z in meas.items() if (nm, t) != ("a", withdrawn[0])], t_new)
    for node in nodes.values():
        _close(node, *after, "held then withdrawn")
        if node.guard is not None:
            assert not node.guard.quarantined and node.guard.summary()["failures"] == 0


# ----------------------------------------------------------------------------- transactions
def test_a_failure_while_quarantining_undoes_the_whole_message_and_the_guard_record(monkeypatch):
    """b quarantines c at the first failed message (k = m = 1). If the withdrawal fails half way,
    the message is rejected and b is exactly as before, guard record included; the same message
    delivered again then quarantines c and withdraws its information."""
    motion = ConstantVelocity(2, Q_PSD)
    prior = (0.0, np.zeros(4), np.eye(4) * P0)
    cfg = GuardConfig(failures=1, window=1)
    b = FusionNode("b", ["c"], motion, window=50, prior=prior, epoch=1, guard=cfg)
    c = FusionNode("c", ["b"], motion, window=50, prior=prior, epoch=2)
    alone = FusionNode("b", ["c"], motion, window=50, prior=prior, epoch=1)
    sensor = PositionSensor(2, 0.3)
    for k in range(1, 6):
        t = 0.1 * k
        for node in (b, c, alone):
            node.predict(t)
        b.update(t, [0.0, 0.0], sensor)
        alone.update(t, [0.0, 0.0], sensor)
        c.update(t, [0.05 * k, 0.0], sensor)   # consistent
        b.receive(c.message_to("b"))
    c.update(0.5, [40.0, 0.0], PositionSensor(2, 0.05))   # a lie
    data = c.message_to("b")
    before = (b.estimate(), b.guard.links["c"].tests, b.channels["c"].state(), {j: set(ch.dirty) for j, ch in b.channels.items()})

    def broken(self, neighbor):
        self.filter.add_information_batch([(0.5, -np.eye(4), np.zeros(4))], validate=False)
        raise RuntimeError("disk full")

    monkeypatch.setattr(FusionNode, "_withdraw", broken)
    with pytest.raises(MessageError) as err:
        b.receive(data)
    assert err.value.reason == "internal"
    assert not b.guard.quarantined and b.guard.links["c"].tests == before[1]
    for x, y in zip(b.estimate(), before[0]):
        assert np.array_equal(x, y)
    assert b.channels["c"].last_seq == before[2][6] and len(b.channels["c"]) == len(before[2][0])
    monkeypatch.undo()
    b.receive(data)
    assert b.guard.quarantined == {"c"} and b.health() == "lost"
    for x, y in zip(b.estimate(), alone.estimate()):
        np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12)
    # while quarantined, b sends c its whole belief (none of c's information is in it)
    c2 = FusionNode("c", ["b"], motion, window=50, prior=prior, epoch=3)
    c2.predict(0.5)
    c2.receive(b.message_to("c"))
    for x, y in zip(c2.estimate(), alone.estimate()):
        np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12)


def test_guard_requires_channel_fusion_and_matching_links():
    motion = ConstantVelocity(2, Q_PSD)
    prior = (0.0, np.zeros(4), np.eye(4))
    with pytest.raises(ValidationError):
        FusionNode("a", ["b"], motion, prior=prior, fusion="naive", guard=GuardConfig())
    with pytest.raises(ValidationError):
        FusionNode("a", ["b"], motion, prior=prior, guard=NeighbourGuard(["c"]))
    assert FusionNode("a", ["b"], motion, prior=prior).health() == "ok"   # off by default


# ----------------------------------------------------------------------------- configuration
def test_guard_config_and_health_rules():
    with pytest.raises(ValidationError):
        GuardConfig(false_alarm=0.0)
    with pytest.raises(ValidationError):
        GuardConfig(failures=4, window=3)
    g = NeighbourGuard(["x", "y"], GuardConfig(failures=3, window=10))
    assert g.threshold(4) == pytest.approx(chi2.ppf(1 - 1e-3, 4))
    assert g.health() == "ok"
    assert not g.judge("x", 100.0, 2)
    assert g.health() == "ok"                    # one failure: the expected false alarm
    assert not g.judge("x", 100.0, 2)
    assert g.health() == "degraded"              # two of the last ten
    assert g.judge("x", 100.0, 2)                # three: quarantine
    assert g.quarantined == {"x"} and g.health() == "degraded"
    for _ in range(2):
        g.judge("y", 100.0, 2)
    assert g.judge("y", 100.0, 2) and g.health() == "lost"
    assert [g.probation("x", 1.0, 2) for _ in range(10)] == [False] * 9 + [True]
    assert g.health() == "degraded"


def test_guard_thresholds_match_scipy_and_are_shared_by_the_guards_of_a_process():
    """The guard's thresholds (dfusion.linalg.chi2_isf, no scipy in a node program) equal scipy's
    chi2.isf, and a second guard of the same process reuses the first one's values."""
    from dfusion.fusion import guard as guard_module

    cfg = GuardConfig()
    for dof in (1, 2, 7, 40, 801):
        assert NeighbourGuard(["a"], cfg).threshold(dof) == pytest.approx(chi2.isf(cfg.false_alarm, dof), rel=1e-11)
    assert (cfg.false_alarm, 801) in guard_module._THRESHOLDS
    assert NeighbourGuard(["b"], cfg).threshold(801) == guard_module._THRESHOLDS[(cfg.false_alarm, 801)]
